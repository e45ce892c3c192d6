"""What the energy terms see of a frame: camera rigs, the solve's render box, the
rendered scene and the data labels as :class:`~torchhand.tracking.energies.TrackState`
objects, and the colour views' previous frames (for the optical flow).

One camera is a rig of one view: every problem has V >= 1 views, and the terms that
read images are prepared on the B x V *view problems* (problem-major: view v of problem
b at row b V + v), the others on the B problems.
"""

from __future__ import annotations

import dataclasses
from typing import Dict, List, NamedTuple, Optional, Sequence

import torch

from torchhand.core.check import skip_checks
from torchhand.core.profiling import stage
from torchhand.geometry.camera import Camera
from torchhand.geometry.render import Renderer, RenderResult, window_map
from torchhand.model.scene import Scene, SceneOutput
from torchhand.tracking.energies import TrackState
from torchhand.tracking.labels import label_by_proximity, label_data
from torchhand.tracking.preprocess import ColourConfig, ColourFrame, ColourView, preprocess_colour

__all__ = ["FrameStates", "StateBuilder", "ColourHistory", "same_camera", "rigs_of", "per_view", "crop_views",
           "CROP_MARGIN"]


def same_camera(a: Camera, b: Camera) -> bool:
    """Whether two cameras are the same (the same object, or equal size and matrices)."""
    return a is b or (a.width == b.width and a.height == b.height and torch.equal(a.K, b.K)
                      and torch.equal(a.T_cw, b.T_cw))


class FrameStates(NamedTuple):
    """The states of one outer iteration: ``view`` of the B x V view problems (for the
    terms that read images), ``pose`` of the B problems, each seen by its first view
    (for the terms of the pose alone)."""

    view: TrackState
    pose: TrackState


class StateBuilder:
    """Renders the scene and labels the data for the terms.

    Args:
        scene: the scene; renderer: its :class:`~torchhand.geometry.render.Renderer`.
        labels: ``"proximity"`` or ``"rendered"`` (:mod:`torchhand.tracking.labels`);
        label_distance: mm, label_radius: px, of those labellings.
        neighbor_backend: of the proximity labelling.
        render_margin: px around the projections of a solve's start poses that its
            renders cover.
        rig_budget: views' worth of correspondences a camera rig's image terms take,
            spread evenly over its views (``TrackState.share``); None: each view all.
    """

    def __init__(self, scene: Scene, renderer: Renderer, labels: str, label_distance: float, label_radius: float,
                 neighbor_backend: str, render_margin: int, rig_budget: Optional[float] = None):
        self.scene, self.renderer = scene, renderer
        self.labels, self.label_distance, self.label_radius = labels, label_distance, label_radius
        self.neighbor_backend, self.render_margin = neighbor_backend, int(render_margin)
        self.rig_budget = rig_budget

    def share(self, views: int) -> float:
        """``TrackState.share`` of the view problems of a rig of ``views`` views."""
        return 1.0 if self.rig_budget is None else min(1.0, self.rig_budget / views)

    def box(self, vertices: torch.Tensor, cameras: Sequence[Camera], shared: bool) -> tuple:
        """The pixel box (r0, r1, c0, c1) a solve renders in: the projections of its start
        poses' ``vertices`` (B x V view problems), widened by ``render_margin`` px for the
        motion within the frame (one host sync per solve)."""
        b = self.renderer.pixel_boxes(vertices.detach(), [cameras[0]] if shared else list(cameras),
                                      per_problem=not shared)
        m = self.render_margin
        H, W = cameras[0].height, cameras[0].width
        lo, hi = b.amin(0).tolist(), b.amax(0).tolist()
        return (max(lo[0] - m, 0), min(hi[1] + m, H), max(lo[2] - m, 0), min(hi[3] + m, W))

    def render(self, vertices: torch.Tensor, cameras: Sequence[Camera], slots: torch.Tensor, shared: bool,
               box: Optional[tuple]) -> RenderResult:
        """One render call for the view problems: one camera for all (``shared``), or
        one per view problem; maps of the box only (``RenderResult.origin``)."""
        with skip_checks():  # the library's own posed vertices
            if shared:
                return self.renderer(vertices, cameras[0], normals=False, slots=slots, box=box, crop=True)
            r = self.renderer(vertices, list(cameras), normals=False, per_problem=True, slots=slots, box=box,
                              crop=True)
        return r.maps(lambda x: x[:, 0])

    def label(self, frames: list, cameras: Sequence[Camera], posed: SceneOutput, rend: RenderResult) -> torch.Tensor:
        """(P, H, W) int64 the model id of each data pixel of the P view problems (-1
        none; (P, 1, 1) where the problems have colour images only)."""
        if all(f is None for f in frames):  # colour views: no data pixels to label (a 1 x 1 map each)
            return torch.full((len(frames), 1, 1), -1, dtype=torch.int64, device=rend.model_id.device)
        if self.labels == "proximity":
            return label_by_proximity(frames, cameras, posed.vertices, self.scene.vertex_model_id,
                                      self.label_distance, self.neighbor_backend)
        H, W = cameras[0].height, cameras[0].width  # OpenCV on the CPU, on whole images
        ids = window_map(rend.model_id, rend.origin, (0, H, 0, W), -1)
        return torch.stack([label_data(f, ids[b], self.label_radius) for b, f in enumerate(frames)])

    def states(self, theta: torch.Tensor, previous: torch.Tensor, frames: list, cameras: Sequence[Camera], *,
               views: int = 1, colours: Optional[list] = None, problems: Optional[torch.Tensor] = None,
               frame_data: Optional[Dict] = None, posed: Optional[SceneOutput] = None,
               labels: Optional[torch.Tensor] = None, shared: Optional[bool] = None,
               box: Optional[tuple] = None) -> FrameStates:
        """The states of one outer iteration.

        Args:
            theta, previous: (B, D) the current and the previous frame's poses.
            frames, cameras, colours: per view problem (B x V, problem-major); a frame is
                None for colour views.
            views: V.
            problems: (B x V,) int64 each view problem's index in its solve (default
                ``arange``); frame_data: the terms' data side of the solve (default:
                a new one).
            posed: the scene at theta (default: posed here).
            labels: the data labels of the frame, (B x V, H, W) (default: labelled
                here, at theta: once per frame).
            shared: every view problem has the same camera (default: compared here).
            box: the solve's render box (None: the whole image).
        """
        V, nb = int(views), theta.shape[0]
        problems = torch.arange(nb * V, device=theta.device) if problems is None else problems
        frame_data = {} if frame_data is None else frame_data
        shared = all(same_camera(c, cameras[0]) for c in cameras) if shared is None else shared
        posed = posed if posed is not None else self.scene(theta, validate=False)
        rep = torch.arange(nb, device=theta.device).repeat_interleave(V)
        th_v, prev_v, posed_v = theta[rep], previous[rep], posed.select(rep)
        with stage("render", work=lambda: _render_work(self.scene, posed_v.vertices.shape[0], rend)):
            rend = self.render(posed_v.vertices.detach(), cameras, problems, shared, box)
        if labels is None:  # once per frame, at its start pose
            with stage("labels", work=lambda: _label_work(frames, posed_v.vertices)):
                labels = self.label(frames, cameras, posed_v, rend)
        view = TrackState(self.scene, th_v, prev_v, posed_v, frames, cameras, rend, labels, problems=problems,
                          frame_data=frame_data, box=box, colours=colours, share=self.share(V))
        first = slice(0, None, V)  # each problem seen by its first view
        pose = TrackState(self.scene, theta, previous, posed, frames[first], cameras[first],
                          rend.maps(lambda x: x[first]), labels[first],
                          problems=problems[first] // V, frame_data=frame_data, box=box,
                          colours=None if colours is None else colours[first])
        return FrameStates(view, pose)


def _render_work(scene: Scene, views: int, rend: RenderResult) -> tuple:
    """(flops, bytes) floor of a render: every vertex projected (20 flops, 12 bytes read),
    every face set up (40 flops, 12 bytes of indices), every pixel of the box resolved
    (20 flops; an 8-byte z-buffer entry and the 16 bytes of face, depth and ids)."""
    pixels = rend.model_id.numel()
    nv, nf = views * scene.num_vertices, views * scene.faces.shape[0]
    return 20.0 * nv + 40.0 * nf + 20.0 * pixels, 12.0 * nv + 12.0 * nf + 24.0 * pixels


def _label_work(frames: list, vertices: torch.Tensor) -> tuple:
    """(flops, bytes) floor of the proximity labels: a grid of the vertices (10 flops,
    24 bytes each), every valid data pixel moved to the world and compared with the
    ~27 vertices of its neighbourhood (230 flops, 20 bytes)."""
    n = sum(int(f.mask.sum()) for f in frames if f is not None)
    nv = vertices.shape[0] * vertices.shape[1]
    return 10.0 * nv + 230.0 * n, 24.0 * nv + 20.0 * n


class ColourHistory:
    """The previous colour frame of each view problem, for the optical flow: a colour
    view is preprocessed with the grey image and ignored pixels this history last saw
    of it. :meth:`clear` forgets them (a new set of sequences)."""

    def __init__(self, config: ColourConfig):
        self.config = config
        self._last: dict = {}  # view problem -> (grey image, ignored pixels) of its previous frame

    def clear(self) -> None:
        self._last.clear()

    def frame(self, item, camera: Camera, key: int, like: torch.Tensor) -> ColourFrame:
        """``item`` (an image, a :class:`ColourView` or an ``(image, ignore, salient)``
        tuple) of view problem ``key`` preprocessed, with its previous frame."""
        view = ColourView(*item) if isinstance(item, tuple) else ColourView(item)
        prev, prev_ignore = self._last.get(key, (None, None))
        if prev is not None and prev.shape != (camera.height, camera.width):
            prev, prev_ignore = None, None
        frame = preprocess_colour(view.image, camera, self.config, prev, view.ignore, device=like.device,
                                  dtype=like.dtype, salient=view.salient, previous_ignore=prev_ignore)
        self._last[key] = (frame.gray, view.ignore)
        return frame


#: px that a cropped view keeps beyond a solve's render box (``render_margin``): the
#: reach of the data the terms pair with the models' pixels (free space's 40 px radius;
#: the labels' 30 mm, about 40 px at 400 mm).
CROP_MARGIN = 48


def crop_views(depth_views: List[Optional[list]], rigs: List[tuple], vertices: torch.Tensor, renderer,
               margin: int) -> tuple:
    """Each view of each rig cut to its hands: the box of the projected start pose's
    ``vertices`` (B, N, 3) widened by ``margin`` px, one size for every view (the
    largest box) and kept inside the image; its camera's principal point moved with it,
    so the geometry is the same. Returns (depth views, rigs) as given when no view would
    be smaller than 80 % of its image (a model out of view or before a camera)."""
    B, V = len(rigs), len(rigs[0])
    cams = [c for rig in rigs for c in rig]
    H, W = cams[0].height, cams[0].width
    b = renderer.pixel_boxes(vertices.detach().repeat_interleave(V, 0), cams, per_problem=True).cpu().long()
    r0, r1 = (b[:, 0] - margin).clamp(0, H), (b[:, 1] + margin).clamp(0, H)
    c0, c1 = (b[:, 2] - margin).clamp(0, W), (b[:, 3] + margin).clamp(0, W)
    h, w = int((r1 - r0).max()), int((c1 - c0).max())
    if h * w >= 0.8 * H * W:
        return depth_views, rigs
    r0, c0 = torch.minimum(r0, torch.tensor(H - h)).tolist(), torch.minimum(c0, torch.tensor(W - w)).tolist()
    out_views, out_rigs = [], []
    for p, rig in enumerate(rigs):
        crops = []
        for v, cam in enumerate(rig):
            i = p * V + v
            K = cam.K.clone()
            K[0, 2] -= c0[i]
            K[1, 2] -= r0[i]
            crops.append(dataclasses.replace(cam, K=K, width=w, height=h))
        out_rigs.append(tuple(crops))
        views = depth_views[p]
        at = [(r0[p * V + v], c0[p * V + v]) for v in range(V)]
        out_views.append(None if views is None else [d[r:r + h, c:c + w] for (r, c), d in zip(at, views)])
    return out_views, out_rigs


def rigs_of(cameras: Sequence, B: int) -> tuple:
    """(B rigs as tuples of V cameras, V, nested) of ``track_frame``'s cameras: one camera
    per problem, or (``nested``) one rig per problem with the same number of views and
    one image size."""
    if len(cameras) != B:
        raise ValueError(f"give one camera (or camera rig) per problem: previous has {B} rows, got {len(cameras)}")
    nested = bool(cameras) and not isinstance(cameras[0], Camera)
    if any(isinstance(c, Camera) == nested for c in cameras):
        raise ValueError("give a Camera for every problem, or a camera rig (a sequence of Cameras) for every problem")
    rigs = [tuple(c) if nested else (c,) for c in cameras]
    V = len(rigs[0]) if rigs else 1
    for b, rig in enumerate(rigs):
        if len(rig) != V or V == 0:
            raise ValueError(f"problem {b} has {len(rig)} views, problem 0 has {V}: a batch tracks rigs of one size")
        for v, c in enumerate(rig):
            if not isinstance(c, Camera):
                raise TypeError(f"problem {b}, view {v}: expected a Camera, got {type(c).__name__}")
            if (c.width, c.height) != (rig[0].width, rig[0].height):
                raise ValueError(f"problem {b}: view {v} is {c.width}x{c.height} px, view 0 is {rig[0].width}x"
                                 f"{rig[0].height}: every view of a rig needs the same image size")
    return rigs, V, nested


def per_view(items: Sequence, B: int, V: int, what: str, nested: bool) -> List[Optional[list]]:
    """B entries of V items each (None: the problem's frame is missing); with one camera
    per problem (not ``nested`` in rigs) an entry is the item itself. A frame missing in
    some views of a problem only is an error."""
    if len(items) != B:
        raise ValueError(f"give one {what} entry per problem ({B}), got {len(items)}")
    out: List[Optional[list]] = []
    for b, item in enumerate(items):
        if item is None:
            out.append(None)
            continue
        views = list(item) if nested else [item]
        if len(views) != V:
            raise ValueError(f"problem {b}: {len(views)} {what}s for a rig of {V} views")
        missing = [v for v, x in enumerate(views) if x is None]
        if missing and len(missing) < V:
            raise ValueError(f"problem {b}: views {missing} have no {what} while the other views have one: "
                             "every view of a rig needs each frame")
        out.append(None if missing else views)
    return out
