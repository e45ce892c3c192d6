"""Salient point detector: a tiny fully-convolutional network with Hough voting, on
depth (the thesis' fingertips) or on colour (Ballan et al.'s finger nails).

The thesis (Ch. 4.2, Eq. 4.14-4.15; Sec. 4.3.1.5) and Ballan et al. (ECCV 2012, Sec. 4)
detect fingertips with a Hough forest: every image patch casts a weighted vote for the
position of the fingertip centre, and detections are the maxima of the accumulated
votes. :class:`SalientNet` keeps the voting and replaces the forest by a small network:

1. the input is normalised inside the network: a depth map (mm, 0 = invalid) by
   :func:`normalise_depth`, a colour image (RGB, 0..255) by :func:`normalise_colour`
   (``SalientConfig.modality``);
2. a stride-4 encoder predicts, per output cell, a fingertip score (logit) and a 2D
   offset (px) from the cell centre to the fingertip centre;
3. each cell votes at ``cell centre + offset`` with weight ``sigmoid(score)``; votes
   are splatted bilinearly (scatter-add) into a Hough map at stride 2 and smoothed by
   a fixed Gaussian. All of this is part of ``forward`` and of the exported ONNX graph.

The voting and the peak picking live in :mod:`torchhand.salient.hough`. Peak picking
(:func:`~torchhand.salient.hough.detect_peaks`: max-pool non-maximum suppression,
threshold, top-k, sub-cell refinement, and the confidence of each peak: its Hough value
times the squared score probability of the cell under it) is post-processing outside
``forward``.
:class:`SalientDetector` (torch) and :class:`OnnxSalientDetector` (ONNX Runtime) wrap
network, padding, input checks and peak picking behind one ``detect(image)`` call.

Two networks ship: ``models/salient_fingertips.pt`` (depth, fingertips, thesis Ch. 4)
and ``models/salient_nails_rgb.pt`` (colour, nail centres, Ballan et al. Sec. 4.1),
each with its ONNX export; ``SalientDetector.load(modality="colour")`` picks the second.

Pixel coordinates follow :mod:`torchhand.geometry.camera`: pixel centres at integer
coordinates, ``u`` = column (x), ``v`` = row (y).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, NamedTuple, Optional, Union

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from torchhand.io.assets import model_dirs
from torchhand.salient.weights import load_weights, save_weights
from torchhand.salient.hough import (DEFAULT_MAX_DETECTIONS, DEFAULT_NMS_RADIUS, DEFAULT_THRESHOLD, HOUGH_STRIDE,
                                     STRIDE, Detections, detect_peaks, hough_votes)

__all__ = [
    "SalientConfig",
    "SalientOutput",
    "SalientNet",
    "normalise_depth",
    "normalise_colour",
    "SalientDetector",
    "OnnxSalientDetector",
    "export_onnx",
    "DEFAULT_WEIGHTS",
    "DEFAULT_ONNX",
    "DEFAULT_NAIL_WEIGHTS",
    "DEFAULT_NAIL_ONNX",
    "MODALITIES",
    "shipped_weights",
    "WEIGHTS_FORMAT",
]


def _shipped(name: str) -> Path:
    """A shipped file of the model folders (installed package or source checkout)."""
    dirs = model_dirs()
    for d in dirs:
        if (d / name).is_file():
            return d / name
    return (dirs[0] if dirs else Path(__file__).resolve().parents[2] / "models") / name


#: Shipped weights (state dict + network config), see ``models/README.md``.
DEFAULT_WEIGHTS = _shipped("salient_fingertips.pt")
#: The same network exported to ONNX (dynamic batch, height and width).
DEFAULT_ONNX = _shipped("salient_fingertips.onnx")
#: The colour network of Ballan et al.'s nails (``train/salient_detector.py --config
#: train/configs/nails_rgb.json``) and its ONNX export.
DEFAULT_NAIL_WEIGHTS = _shipped("salient_nails_rgb.pt")
DEFAULT_NAIL_ONNX = _shipped("salient_nails_rgb.onnx")
#: Input kinds of :class:`SalientNet`: channels of the image it takes, ONNX input name.
MODALITIES = {"depth": (1, "depth"), "colour": (3, "rgb")}
#: Tag stored in weight files written by :meth:`SalientNet.save`.
WEIGHTS_FORMAT = "torchhand.salient.SalientNet/1"

@dataclass(frozen=True)
class SalientConfig:
    """Architecture of :class:`SalientNet` (stored in the weights file).

    Attributes:
        channels: width of the stride-2 and stride-4 feature maps.
        dilations: dilation of each 3x3 conv at stride 4 (their number sets the depth;
            receptive field 7 + 8 * sum(dilations) px).
        depth_scale_mm: depth range (mm) that maps to 1 in the normalised input.
        depth_clip: normalised depths are clipped to [0, depth_clip].
        offset_scale_px: the head's raw offset output is multiplied by this (px).
        hough_sigma: std of the Gaussian smoothing the Hough map, in Hough cells.
        modality: ``"depth"`` ((B, 1, H, W) mm, 0 = invalid) or ``"colour"``
            ((B, 3, H, W) RGB in 0..255); weight files without it are depth networks.
    """

    channels: tuple = (12, 20)
    dilations: tuple = (1, 2, 4, 1)
    depth_scale_mm: float = 150.0
    depth_clip: float = 3.0
    offset_scale_px: float = 8.0
    hough_sigma: float = 1.0
    modality: str = "depth"

    def __post_init__(self) -> None:
        if self.modality not in MODALITIES:
            raise ValueError(f"SalientConfig.modality must be one of {sorted(MODALITIES)}, got {self.modality!r}")
        object.__setattr__(self, "channels", tuple(int(c) for c in self.channels))
        object.__setattr__(self, "dilations", tuple(int(d) for d in self.dilations))
        if len(self.channels) != 2 or min(self.channels) < 1:
            raise ValueError(f"SalientConfig.channels must be two positive ints, got {self.channels}")
        if not self.dilations or min(self.dilations) < 1:
            raise ValueError(f"SalientConfig.dilations must be positive ints, got {self.dilations}")
        for name in ("depth_scale_mm", "depth_clip", "offset_scale_px", "hough_sigma"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"SalientConfig.{name} must be a positive number, got {value!r}")


class SalientOutput(NamedTuple):
    """Raw outputs of :class:`SalientNet` for a (B, C, H, W) input.

    Attributes:
        logits: (B, 1, H/4, W/4) fingertip score logits per cell.
        offsets: (B, 2, H/4, W/4) offset (du, dv) in input pixels from the cell centre
            ``(4 j + 1.5, 4 i + 1.5)`` (column j, row i) to the voted fingertip centre.
        hough: (B, 1, H/2, W/2) smoothed Hough map; cell (i, j) is centred on pixel
            ``(2 j + 0.5, 2 i + 0.5)``. Its values are sums of sigmoid scores.
    """

    logits: torch.Tensor
    offsets: torch.Tensor
    hough: torch.Tensor


# ------------------------------------------------------------------------- pure functions


def normalise_depth(depth: torch.Tensor, scale_mm: float, clip: float) -> torch.Tensor:
    """Network input from depth: a validity channel and depth relative to the nearest point.

    ``rel = clamp((d - d_near) / scale_mm, 0, clip)`` with ``d_near`` the smallest valid
    depth of the frame (hands are usually the nearest surfaces); invalid pixels (0)
    get ``rel = clip``, like far background. Translation invariant in depth, so the
    net does not learn absolute distances. An empty frame gives valid = 0, rel = clip.

    Args:
        depth: (B, 1, H, W) depth in mm, 0 where invalid.

    Returns:
        (B, 2, H, W): [valid (0/1), rel].
    """
    valid = depth > 0
    far = depth.new_full((1,), 1e6)
    near = torch.where(valid, depth, far).amin(dim=(2, 3), keepdim=True)
    rel = ((depth - near) / scale_mm).clamp(0.0, clip)
    rel = torch.where(valid, rel, depth.new_full((1,), clip))
    return torch.cat([valid.to(depth.dtype), rel], 1)


def normalise_colour(rgb: torch.Tensor) -> torch.Tensor:
    """Network input from colour: ``rgb / 127.5 - 1`` per channel, (B, 3, H, W) RGB in
    0..255 -> [-1, 1]. A fixed map (no per-image statistics), so that a crop and the
    whole frame see the same values; brightness changes are left to the training's
    augmentation."""
    return rgb / 127.5 - 1.0


def _gaussian_kernel(sigma: float) -> torch.Tensor:
    r = max(1, int(math.ceil(2 * sigma)))
    x = torch.arange(-r, r + 1, dtype=torch.float64)
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    k = g[:, None] * g[None, :]
    # Normalised to sum 1, so the smoothed map keeps the total vote mass.
    return (k / k.sum()).float()[None, None]


# --------------------------------------------------------------------------------- network


def _conv(cin: int, cout: int, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, padding=dilation, dilation=dilation, bias=False),
                         nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class SalientNet(nn.Module):
    """Salient point score, offset and Hough-vote network on depth or colour.

    Args:
        config: the architecture (default :class:`SalientConfig`: depth).

    ``forward(image)`` takes (B, 1, H, W) depth in mm (0 = invalid), or (B, 3, H, W)
    RGB in 0..255 for a colour network, with H and W multiples of 4 and returns a
    :class:`SalientOutput`. The same code runs on any
    device and dtype; it is traced as-is into ONNX by :func:`export_onnx`.
    """

    def __init__(self, config: Optional[SalientConfig] = None):
        super().__init__()
        self.config = config if config is not None else SalientConfig()
        c1, c2 = self.config.channels
        cin = 2 if self.config.modality == "depth" else 3  # depth: [valid, rel]
        layers = [_conv(cin, c1, stride=2), _conv(c1, c2, stride=2)]
        layers += [_conv(c2, c2, dilation=d) for d in self.config.dilations]
        self.encoder = nn.Sequential(*layers)
        self.head = nn.Conv2d(c2, 3, 1)
        nn.init.zeros_(self.head.weight)
        with torch.no_grad():
            self.head.bias.copy_(torch.tensor([-4.0, 0.0, 0.0]))  # start with few, weak votes
        self.register_buffer("smooth", _gaussian_kernel(self.config.hough_sigma), persistent=False)

    @property
    def modality(self) -> str:
        return self.config.modality

    def forward(self, image: torch.Tensor) -> SalientOutput:
        if not (torch.jit.is_tracing() or torch.onnx.is_in_onnx_export()):
            _check_net_input(image, self.config.modality)
        cfg = self.config
        if cfg.modality == "depth":
            x = normalise_depth(image, cfg.depth_scale_mm, cfg.depth_clip)
        else:
            x = normalise_colour(image)
        out = self.head(self.encoder(x))
        logits = out[:, :1]
        offsets = out[:, 1:] * cfg.offset_scale_px
        H, W = image.shape[2], image.shape[3]
        hough = hough_votes(torch.sigmoid(logits), offsets, H // HOUGH_STRIDE, W // HOUGH_STRIDE)
        pad = self.smooth.shape[-1] // 2
        hough = F.conv2d(hough, self.smooth.to(hough.dtype), padding=pad)
        return SalientOutput(logits, offsets, hough)

    # ------------------------------------------------------------------ weights files
    def save(self, path) -> Path:
        """Write ``{"format", "config", "state_dict"}`` (:func:`~torchhand.salient.weights.save_weights`)."""
        return save_weights(self, path, WEIGHTS_FORMAT)

    @classmethod
    def load(cls, path, map_location="cpu") -> "SalientNet":
        """Read a file written by :meth:`save`; errors name the file and what is wrong."""
        return load_weights(cls, SalientConfig, path, WEIGHTS_FORMAT, "salient detector", map_location)


def _check_net_input(image, modality: str = "depth") -> None:
    channels, name = MODALITIES[modality]
    what = "one depth channel, mm" if modality == "depth" else "RGB in 0..255"
    if not isinstance(image, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor of shape (B, {channels}, H, W), got {type(image).__name__}")
    if image.ndim != 4 or image.shape[1] != channels:
        raise ValueError(f"{name} must have shape (B, {channels}, H, W) ({what}) for a {modality} network, "
                         f"got {tuple(image.shape)}")
    if not image.is_floating_point():
        raise TypeError(f"{name} must be a floating point tensor ({what}), got {image.dtype}")
    if image.shape[2] % STRIDE or image.shape[3] % STRIDE:
        raise ValueError(f"{name} height and width must be multiples of {STRIDE}, got {tuple(image.shape[2:])}; "
                         "SalientDetector.detect pads any size")


# ---------------------------------------------------------------------- frame-level API

ArrayLike = Union[np.ndarray, torch.Tensor]


def _check_frame(depth) -> np.ndarray | torch.Tensor:
    """Validate one (H, W) depth frame; returns it (unchanged type)."""
    if not isinstance(depth, (np.ndarray, torch.Tensor)):
        raise TypeError(f"depth must be a numpy array or torch tensor of shape (H, W) in mm, got {type(depth).__name__}")
    if depth.ndim != 2:
        raise ValueError(f"depth must have shape (H, W) (one depth frame, mm), got {tuple(depth.shape)}")
    if isinstance(depth, np.ndarray):
        if not (np.issubdtype(depth.dtype, np.floating) or np.issubdtype(depth.dtype, np.integer)) \
                or depth.dtype == np.bool_:
            raise TypeError(f"depth must be a float or integer array (mm), got dtype {depth.dtype}")
        bad = np.isnan(depth).any() if np.issubdtype(depth.dtype, np.floating) else False
        neg = (depth < 0).any()
    else:
        if depth.dtype in (torch.bool, torch.complex64, torch.complex128):
            raise TypeError(f"depth must be a float or integer tensor (mm), got dtype {depth.dtype}")
        bad = bool(torch.isnan(depth).any()) if depth.is_floating_point() else False
        neg = bool((depth < 0).any())
    if bad:
        raise ValueError("depth contains NaN; mark invalid pixels with 0")
    if neg:
        raise ValueError("depth contains negative values; depth is in mm with 0 marking invalid pixels")
    if min(depth.shape) < 1:
        raise ValueError(f"depth must not be empty, got shape {tuple(depth.shape)}")
    return depth


def _check_colour_frame(rgb) -> np.ndarray:
    """Validate one (H, W, 3) RGB frame (uint8, or float in 0..255); returns float32 numpy."""
    if not isinstance(rgb, (np.ndarray, torch.Tensor)):
        raise TypeError(f"rgb must be a numpy array or torch tensor of shape (H, W, 3), got {type(rgb).__name__}")
    arr = rgb.detach().cpu().numpy() if isinstance(rgb, torch.Tensor) else rgb
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(f"rgb must have shape (H, W, 3) (one RGB frame) for a colour detector, got {tuple(arr.shape)}")
    if min(arr.shape[:2]) < 1:
        raise ValueError(f"rgb must not be empty, got shape {tuple(arr.shape)}")
    if arr.dtype == np.uint8:
        return arr.astype(np.float32)
    if not np.issubdtype(arr.dtype, np.floating):
        raise TypeError(f"rgb must be uint8 or float in 0..255, got dtype {arr.dtype}")
    if not np.isfinite(arr).all() or arr.min() < 0 or arr.max() > 255:
        raise ValueError(f"rgb values must be finite and in 0..255, got "
                         f"{float(np.nanmin(arr))}..{float(np.nanmax(arr))}")
    return arr.astype(np.float32, copy=False)


def _padded(image: np.ndarray) -> np.ndarray:
    """(H, W) depth or (H, W, 3) RGB -> (1, C, H', W') float32, zero-padded at the
    bottom/right to multiples of 4 (invalid depth; black)."""
    H, W = image.shape[:2]
    Hp, Wp = -(-H // STRIDE) * STRIDE, -(-W // STRIDE) * STRIDE
    if image.ndim == 3:
        out = np.zeros((1, 3, Hp, Wp), np.float32)
        out[0, :, :H, :W] = image.transpose(2, 0, 1)
        return out
    out = np.zeros((1, 1, Hp, Wp), np.float32)
    out[0, 0, :H, :W] = np.where(np.isfinite(image), image, 0)  # +inf counts as invalid
    return out


def _finish(dets: Detections, depth_np: np.ndarray) -> Detections:
    H, W = depth_np.shape
    if len(dets.score) == 0:
        return dets
    cols = dets.uv[:, 0].round().long().clamp(0, W - 1).cpu().numpy()
    rows = dets.uv[:, 1].round().long().clamp(0, H - 1).cpu().numpy()
    d = torch.as_tensor(depth_np[rows, cols].astype(np.float32), device=dets.uv.device).to(dets.uv.dtype)
    return Detections(dets.uv, dets.score, d)


def _empty(device="cpu") -> Detections:
    z = torch.zeros(0, dtype=torch.float32, device=device)
    return Detections(z.reshape(0, 2), z, z)


def _detect_frame(detector, depth: ArrayLike, forward: Callable[[np.ndarray], SalientOutput], device="cpu") -> Detections:
    """The ``detect`` of both detectors: input checks, padding, ``forward`` (a padded
    (1, C, H', W') float32 array -> :class:`SalientOutput`), peak picking with the
    detector's settings and confidence, and the depth at each detection (0 for colour)."""
    if detector.modality == "colour":
        rgb = _check_colour_frame(depth)
        out = forward(_padded(rgb))
        dets = detect_peaks(out.hough, detector.threshold, detector.max_detections, detector.nms_radius,
                            rgb.shape[:2], logits=out.logits)[0]
        return Detections(*(x.to(device) for x in dets))
    depth = _check_frame(depth)
    depth_np = depth.detach().cpu().numpy() if isinstance(depth, torch.Tensor) else depth
    depth_np = depth_np.astype(np.float32, copy=False)
    if not (depth_np > 0).any():
        return _empty(device)
    out = forward(_padded(depth_np))
    dets = detect_peaks(out.hough, detector.threshold, detector.max_detections, detector.nms_radius, depth_np.shape,
                        logits=out.logits)[0]
    return _finish(dets, depth_np)


class SalientDetector:
    """Salient point detection on single frames with a :class:`SalientNet`: fingertips
    on depth, or nails on colour (the network's ``modality``).

    Args:
        net: the network (moved to ``device`` and set to eval mode).
        device: where the network runs ("cpu", "cuda", ...).
        threshold, max_detections, nms_radius: see :func:`detect_peaks`.

    ``detect`` pads any frame to multiples of 4 (invalid depth, black colour).
    """

    def __init__(self, net: SalientNet, device="cpu", threshold: float = DEFAULT_THRESHOLD,
                 max_detections: int = DEFAULT_MAX_DETECTIONS, nms_radius: int = DEFAULT_NMS_RADIUS):
        self.device = torch.device(device)
        self.net = net.to(self.device).eval()
        self.threshold = float(threshold)
        self.max_detections = int(max_detections)
        self.nms_radius = int(nms_radius)
        self.modality = self.net.config.modality

    @classmethod
    def load(cls, path=None, device="cpu", modality: str = "depth", **kwargs) -> "SalientDetector":
        """Detector from a weights file (default: the shipped network of ``modality``,
        ``models/salient_fingertips.pt`` for depth, ``models/salient_nails_rgb.pt`` for
        colour)."""
        path = shipped_weights(modality, onnx=False) if path is None else path
        return cls(SalientNet.load(path), device=device, **kwargs)

    @classmethod
    def load_onnx(cls, path=None, threads: int = 2, modality: str = "depth", **kwargs) -> "OnnxSalientDetector":
        """ONNX Runtime detector (default: the shipped export of ``modality``)."""
        path = shipped_weights(modality, onnx=True) if path is None else path
        return OnnxSalientDetector(path, threads=threads, **kwargs)

    def detect(self, image: ArrayLike) -> Detections:
        """Salient points in one frame.

        Args:
            image: a depth network's (H, W) depth in mm (float or integer, numpy or
                torch), 0 = invalid; a colour network's (H, W, 3) RGB (uint8, or float
                in 0..255).

        Returns:
            :class:`Detections` on ``self.device`` (float32), pixel coordinates of the
            input frame. A depth frame without valid pixels gives zero detections.

        Raises:
            TypeError / ValueError: an array of the wrong shape or type for the
            network's modality, NaN or negative values.
        """
        return _detect_frame(self, image, self._forward, self.device)

    def _forward(self, x: np.ndarray) -> SalientOutput:
        with torch.no_grad():
            return self.net(torch.from_numpy(x).to(self.device))


class OnnxSalientDetector:
    """:class:`SalientDetector` running the exported graph with ONNX Runtime (CPU).

    Args:
        path: ``.onnx`` file written by :func:`export_onnx`.
        threads: ``intra_op_num_threads`` of the session.
        threshold, max_detections, nms_radius: see :func:`detect_peaks`.
    """

    def __init__(self, path, threads: int = 2, threshold: float = DEFAULT_THRESHOLD,
                 max_detections: int = DEFAULT_MAX_DETECTIONS, nms_radius: int = DEFAULT_NMS_RADIUS):
        import onnxruntime as ort

        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"{self.path}: ONNX salient detector not found")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = int(threads)
        opts.inter_op_num_threads = 1
        try:
            self.session = ort.InferenceSession(str(self.path), opts, providers=["CPUExecutionProvider"])
        except Exception as e:
            raise ValueError(f"{self.path}: not a loadable ONNX model ({type(e).__name__}: {e})") from None
        inputs = [i.name for i in self.session.get_inputs()]
        outputs = [o.name for o in self.session.get_outputs()]
        names = {name: m for m, (_, name) in MODALITIES.items()}
        if len(inputs) != 1 or inputs[0] not in names or outputs != list(SalientOutput._fields):
            raise ValueError(f"{self.path}: not a salient detector graph (inputs {inputs}, outputs {outputs}; "
                             f"expected one of {[[n] for n in names]} and {list(SalientOutput._fields)})")
        self.input_name = inputs[0]
        self.modality = names[inputs[0]]
        self.threshold = float(threshold)
        self.max_detections = int(max_detections)
        self.nms_radius = int(nms_radius)

    def run(self, image: np.ndarray) -> SalientOutput:
        """Raw outputs for a (B, C, H, W) float32 array (H, W multiples of 4)."""
        outs = self.session.run(None, {self.input_name: np.ascontiguousarray(image, np.float32)})
        return SalientOutput(*(torch.from_numpy(o) for o in outs))

    def detect(self, image: ArrayLike) -> Detections:
        """Same contract as :meth:`SalientDetector.detect`; tensors on the CPU."""
        return _detect_frame(self, image, self.run)


def shipped_weights(modality: str = "depth", onnx: bool = False) -> Path:
    """The shipped network of ``modality`` (``"depth"``: fingertips, ``"colour"``:
    nails): its weights file, or its ONNX export with ``onnx``."""
    if modality not in MODALITIES:
        raise ValueError(f"modality must be one of {sorted(MODALITIES)}, got {modality!r}")
    if modality == "depth":
        return DEFAULT_ONNX if onnx else DEFAULT_WEIGHTS
    return DEFAULT_NAIL_ONNX if onnx else DEFAULT_NAIL_WEIGHTS


def export_onnx(net: SalientNet, path, height: int = 240, width: int = 320, opset: int = 17) -> Path:
    """Export ``net`` (legacy TorchScript-based exporter) with dynamic batch, height, width.

    Inputs: ``depth`` (B, 1, H, W) float32 mm, or ``rgb`` (B, 3, H, W) float32 0..255 for
    a colour network; outputs ``logits``, ``offsets``, ``hough`` as in
    :class:`SalientOutput`. The Hough voting exports as ScatterElements with
    ``reduction="add"`` (opset >= 16).
    """
    if opset < 16:
        raise ValueError(f"opset must be >= 16 (ScatterElements with reduction='add'), got {opset}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    net = net.to("cpu", torch.float32).eval()
    channels, name = MODALITIES[net.config.modality]
    example = torch.zeros(1, channels, height, width)
    example[0, :, height // 4: 3 * height // 4, width // 4: 3 * width // 4] = 600.0 if channels == 1 else 128.0
    cells = {0: "batch", 2: "height_4", 3: "width_4"}
    axes = {name: {0: "batch", 2: "height", 3: "width"}, "logits": cells, "offsets": cells,
            "hough": {0: "batch", 2: "height_2", 3: "width_2"}}
    # the legacy (TorchScript) exporter on purpose: the dynamo exporter needs onnxscript
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(net, (example,), str(path), dynamo=False, opset_version=opset, input_names=[name],
                          output_names=list(SalientOutput._fields), dynamic_axes=axes)
    return path
