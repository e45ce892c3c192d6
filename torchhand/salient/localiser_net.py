"""The hand localiser's network (:class:`LocaliserNet`): a small U-Net from depth to
per-pixel classes, the 21 joints' heat maps, their sub-cell offsets and depths, at stride
2 of its input; its config (stored with its weights) and its ONNX export. It is run on
frames by :class:`~torchhand.salient.localiser.HandLocaliser` and trained by
``python -m train.hand_localiser`` (docs/localiser.md)."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import NamedTuple, Optional

import torch
import torch.nn.functional as F
from torch import nn

from torchhand.salient.localiser_data import CLASSES
from torchhand.salient.weights import load_weights, save_weights

__all__ = ["LocaliserConfig", "LocaliserOutput", "LocaliserNet", "export_localiser_onnx", "LOCALISER_FORMAT",
           "ONNX_OUTPUTS", "STRIDE", "normalise_input"]

#: Tag stored in weight files written by :meth:`LocaliserNet.save`.
LOCALISER_FORMAT = "torchhand.salient.LocaliserNet/1"
#: Output names of the ONNX graph (the fields of :class:`LocaliserOutput`; the joints'
#: depth is ``joint_depth``, as ``depth`` names the input).
ONNX_OUTPUTS = ["classes", "heat", "offset", "joint_depth"]
#: Output stride of the network (input px per output cell).
STRIDE = 2


@dataclass(frozen=True)
class LocaliserConfig:
    """Architecture and input scaling of :class:`LocaliserNet` (stored with the weights).

    Attributes:
        channels: encoder widths at strides 2, 4 and 8.
        decoder: decoder widths at strides 4 and 2.
        dilations: the dilated 3x3 convolutions at stride 8 (the receptive field that
            sees a whole hand in a crop).
        input_size: side of the crop pass's input (px).
        frame_size: long side of the frame pass's input (px).
        depth_scale_mm, relative_scale_mm, relative_clip: the two input channels.
    """

    channels: tuple = (16, 32, 64)
    decoder: tuple = (32, 24)
    dilations: tuple = (1, 2, 4)
    input_size: int = 128
    frame_size: int = 160
    depth_scale_mm: float = 1000.0
    relative_scale_mm: float = 200.0
    relative_clip: float = 4.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "channels", tuple(int(c) for c in self.channels))
        object.__setattr__(self, "decoder", tuple(int(c) for c in self.decoder))
        object.__setattr__(self, "dilations", tuple(int(d) for d in self.dilations))
        if len(self.channels) != 3 or len(self.decoder) != 2:
            raise ValueError(f"LocaliserConfig needs 3 encoder and 2 decoder widths, got {self.channels}, {self.decoder}")
        if self.input_size % 8 or self.frame_size % 8:  # stride 8, and a mirror must keep the cells
            raise ValueError(f"LocaliserConfig sizes must be multiples of 8, got input_size {self.input_size}, "
                             f"frame_size {self.frame_size}")


class LocaliserOutput(NamedTuple):
    """Network outputs at stride 2: classes (B, 4, h, w) logits; heat (B, 21, h, w)
    logits of the joints of any hand (which hand a peak belongs to is read from the
    classes); offset (B, 42, h, w) sub-cell (du, dv) per joint in cells; depth (B, 21,
    h, w) joint depth minus the reference, in units of ``relative_scale_mm``."""

    classes: torch.Tensor
    heat: torch.Tensor
    offset: torch.Tensor
    depth: torch.Tensor


def normalise_input(depth: torch.Tensor, reference: torch.Tensor, config: LocaliserConfig) -> torch.Tensor:
    """(B, 1, H, W) depth mm and (B,) reference mm -> the network's (B, 2, H, W) input."""
    valid = (depth > 0).to(depth.dtype)
    absolute = depth / config.depth_scale_mm
    rel = ((depth - reference.reshape(-1, 1, 1, 1)) / config.relative_scale_mm).clamp(-config.relative_clip,
                                                                                      config.relative_clip)
    return torch.cat([absolute, rel * valid], 1)


def _conv(cin: int, cout: int, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, dilation, dilation, bias=False), nn.BatchNorm2d(cout),
                         nn.ReLU(inplace=True))


class LocaliserNet(nn.Module):
    """A small U-Net: encoder to stride 8 with dilated convolutions, decoder back to
    stride 2 with skips, four 1x1 heads (:class:`LocaliserOutput`)."""

    JOINTS = 21

    def __init__(self, config: Optional[LocaliserConfig] = None):
        super().__init__()
        self.config = config or LocaliserConfig()
        c1, c2, c3 = self.config.channels
        d2, d1 = self.config.decoder
        self.enc1 = nn.Sequential(_conv(2, c1, 2), _conv(c1, c1))
        self.enc2 = nn.Sequential(_conv(c1, c2, 2), _conv(c2, c2))
        self.enc3 = nn.Sequential(_conv(c2, c3, 2), *[_conv(c3, c3, dilation=d) for d in self.config.dilations])
        self.dec2 = _conv(c3 + c2, d2)
        self.dec1 = _conv(d2 + c1, d1)
        J = self.JOINTS
        self.head = nn.Conv2d(d1, len(CLASSES) + J + 2 * J + J, 1)
        with torch.no_grad():  # heat starts rare (focal-loss prior)
            self.head.bias[len(CLASSES):len(CLASSES) + J] = -4.0

    def forward(self, depth: torch.Tensor, reference: torch.Tensor) -> LocaliserOutput:
        x = normalise_input(depth, reference, self.config)
        e1 = self.enc1(x)
        e2 = self.enc2(e1)
        e3 = self.enc3(e2)
        u2 = self.dec2(torch.cat([F.interpolate(e3, size=e2.shape[-2:], mode="nearest"), e2], 1))
        u1 = self.dec1(torch.cat([F.interpolate(u2, size=e1.shape[-2:], mode="nearest"), e1], 1))
        out = self.head(u1)
        C, J = len(CLASSES), self.JOINTS
        return LocaliserOutput(out[:, :C], out[:, C:C + J], out[:, C + J:C + 3 * J], out[:, C + 3 * J:])

    def widen_from(self, narrower: "LocaliserNet") -> "LocaliserNet":
        """Take the weights of a network of the same design with fewer channels, so that
        this one computes the same outputs (its extra channels start with random weights
        of their own and zero weights into the channels the narrower network has, the
        head's too): training goes on from the narrower network's state with more
        capacity. Returns self."""
        a, b = narrower.config, self.config
        widths = list(zip(a.channels + a.decoder, b.channels + b.decoder))
        if replace(a, channels=b.channels, decoder=b.decoder) != b or any(n < o for o, n in widths):
            raise ValueError(f"cannot widen a localiser of {a} to {b}: only the widths may differ, and only grow")
        (o1, o2, o3), (od2, od1) = a.channels, a.decoder
        n3, nd2 = b.channels[2], b.decoder[0]
        r = lambda n: list(range(n))  # noqa: E731
        plan = [(self.enc1[0], narrower.enc1[0], r(2)), (self.enc1[1], narrower.enc1[1], r(o1)),
                (self.enc2[0], narrower.enc2[0], r(o1)), (self.enc2[1], narrower.enc2[1], r(o2)),
                (self.enc3[0], narrower.enc3[0], r(o2)),
                *[(x, y, r(o3)) for x, y in zip(self.enc3[1:], narrower.enc3[1:])],
                # the decoders' inputs are concatenations: (upsampled deeper level, skip)
                (self.dec2, narrower.dec2, r(o3) + [n3 + i for i in range(o2)]),
                (self.dec1, narrower.dec1, r(od2) + [nd2 + i for i in range(o1)])]
        with torch.no_grad():
            for new, old, cols in plan:
                k = old[0].out_channels
                new[0].weight[:k] = 0.0
                new[0].weight[:k, cols] = old[0].weight
                for name in ("weight", "bias", "running_mean", "running_var"):
                    getattr(new[1], name)[:k] = getattr(old[1], name)
                new[1].num_batches_tracked.copy_(old[1].num_batches_tracked)
            self.head.weight.zero_()
            self.head.weight[:, :od1] = narrower.head.weight
            self.head.bias.copy_(narrower.head.bias)
        return self

    def save(self, path) -> Path:
        """Write ``{"format", "config", "state_dict"}`` (:func:`~torchhand.salient.weights.save_weights`)."""
        return save_weights(self, path, LOCALISER_FORMAT)

    @classmethod
    def load(cls, path, map_location="cpu") -> "LocaliserNet":
        """Read a file written by :meth:`save` (``python -m train.hand_localiser``)."""
        return load_weights(cls, LocaliserConfig, path, LOCALISER_FORMAT, "hand localiser", map_location)


def export_localiser_onnx(net: LocaliserNet, path, size: int = 128, opset: int = 17) -> Path:
    """ONNX export with dynamic batch, height and width (inputs ``depth``, ``reference``)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    net = net.eval()
    x = torch.zeros(1, 1, size, size)
    ref = torch.full((1,), 500.0)
    names = ONNX_OUTPUTS
    with warnings.catch_warnings():  # the legacy exporter announces its deprecation
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(net, (x, ref), str(path), input_names=["depth", "reference"], output_names=names,
                          dynamic_axes={"depth": {0: "b", 2: "h", 3: "w"}, "reference": {0: "b"},
                                        **{n: {0: "b", 2: "oh", 3: "ow"} for n in names}},
                          opset_version=opset, dynamo=False)
    return path
