"""The ``torchhand`` command line: argument parsing and the error policy; each command's work
is in :mod:`torchhand.app.commands`, which calls the library.

Exit status: 0 when everything worked, 1 when some sequence failed (its error is
printed; the others are written), 2 for bad arguments or unusable input (one line
naming it, :func:`torchhand.core.errors.user_error`), also for an optional dependency that is not installed
(the line names the extra to install). Any other exception is a bug in torchhand: its
traceback is printed with a line asking to report it, and the status is 1.
"""

from __future__ import annotations

import argparse
import sys
import traceback
from pathlib import Path

from torchhand.app import commands
from torchhand.core.errors import UsageError, user_error

__all__ = ["main", "build_parser"]


_Formatter = argparse.ArgumentDefaultsHelpFormatter

#: ``torchhand import --format`` choices: the names of ``torchhand.data.datasets.FORMATS``,
#: spelled out so that parsing does not load the readers (tests/test_fpha.py compares them).
DATASET_FORMATS = ("fpha", "nyu", "ho3d", "dexycb")


def _frames_slice(text: str | None) -> slice | None:
    if not text:
        return None
    try:
        if ":" not in text:  # N: the first N frames
            return slice(None, int(text))
        a, b = (int(x) if x else None for x in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--frames must look like A:B (e.g. 0:100) or N, got {text!r}") from None
    return slice(a, b)


def _segment_options(p: argparse.ArgumentParser, default: str | None) -> None:
    from torchhand.tracking.segmentation import SEGMENT_MODES

    p.add_argument("--segment", default=default, choices=SEGMENT_MODES,
                   help="hand segmentation: auto (the learned hand localiser: hands, arm and body told apart, "
                        "joints and handedness; the blob rules when it finds no hand), blobs (the nearest "
                        "hand-sized depth blobs, cut at the wrist), range (the depth range only), skin (colour), "
                        "none (all valid depth is hands and objects)"
                   + ("" if default else "; default: what the sequence folder says (set by import), else none"))
    p.add_argument("--near", type=float, default=200.0, help="nearest depth kept, mm")
    p.add_argument("--far", type=float, default=1500.0, help="farthest depth kept, mm")
    p.add_argument("--remove-plane", action="store_true", help="remove the dominant plane (a table), RANSAC")
    p.add_argument("--hands", type=int, default=1, choices=[1, 2], help="hands in the scene (auto segmentation)")
    p.add_argument("--localiser", type=Path, metavar="ONNX",
                   help="auto segmentation with this hand localiser (an .onnx file of python -m "
                        "train.hand_localiser, its .pt beside it) instead of the shipped one")
    p.add_argument("--localiser-flip", action="store_true",
                   help="auto segmentation: run the localiser also on each frame mirrored and average "
                        "(about 10 ms more per frame; docs/localiser.md)")


def _positive_int(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {n}")
    return n


def _positive_float(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}") from None
    if not x > 0 or x == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, got {text}")
    return x


def limit_slack_arg(text: str):
    """``--limit-slack``: ``none`` or a finite number >= 0 (radians); also the eval
    scripts' parser."""
    if text.strip().lower() == "none":
        return None
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected none or a number >= 0 (radians), got {text!r}") from None
    if not 0 <= x < float("inf"):
        raise argparse.ArgumentTypeError(f"expected none or a finite number >= 0 (radians), got {text}")
    return x


def _scale_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--workers", type=_positive_int, default=1,
                   help="local processes, one task at a time each (with --ray: the CPUs of a local Ray instance)")
    p.add_argument("--ray", nargs="?", const="local", default=None, metavar="ADDRESS",
                   help="run the tasks on Ray: without ADDRESS a local instance, 'auto' the running cluster, or "
                        "HOST:PORT of its head (pip install 'torchhand[ray]')")
    p.add_argument("--retries", type=int, default=2, help="times a task whose worker died is run again")


def _backend_option(p: argparse.ArgumentParser) -> None:
    from torchhand.geometry.raycast import BACKENDS

    p.add_argument("--backend", default=None, choices=BACKENDS,
                   help="renderer: Warp rasterisation, Warp BVH ray casting, or open3d (the CPU reference); "
                        "default: warp where it loads")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="torchhand", description="Capture the 3D motion of hands in action.",
                                 formatter_class=_Formatter)
    ap.add_argument("--threads", type=_positive_int, default=1,
                    help="torch CPU threads per process (1: the per-frame work is many small operations, which "
                         "lose far more to thread contention than they gain; see docs/benchmarks.md)")
    sub = ap.add_subparsers(dest="command", required=True)
    p = sub.add_parser("demo", help="pose, render and draw the default scene, then track a few synthetic frames",
                       formatter_class=_Formatter)
    p.add_argument("--out", type=Path, required=True, help="output folder (created; must be new or empty)")
    p.add_argument("--frames", type=int, default=None, help="number of frames to render (None: all 60)")
    p.add_argument("--track-frames", type=int, default=8, help="frames to synthesise and track (0: skip)")
    p.add_argument("--force", action="store_true", help="replace the content of a non-empty --out")
    p.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda")
    p.set_defaults(func=commands.demo)

    p = sub.add_parser("synth", help="render a thesis motion or random poses into a sequence folder",
                       formatter_class=_Formatter)
    p.add_argument("--hia-root", type=Path, help="Hands-in-Action data root (Configs/, Models/, Calibration/)")
    p.add_argument("--sequence", help="thesis sequence id, e.g. 16")
    p.add_argument("--random", action="store_true", help="random poses within the limits, random viewpoints")
    p.add_argument("--demo", action="store_true", help="the shipped demo motion (no thesis data needed)")
    p.add_argument("--models", default="hand_right", help="with --random: comma-separated model names")
    p.add_argument("--out", type=Path, required=True, help="sequence folder to write (must be new or empty)")
    p.add_argument("--frames", type=_frames_slice, default=None,
                   help="A:B frame range, or N for the first N (with --random and --scan-object: the number of "
                        "frames; None: the whole motion, 100 random, or two turns of a scan)")
    p.add_argument("--noise", default="kinect", choices=["none", "kinect"], help="depth noise model (docs/noise.md)")
    p.add_argument("--seed", type=int, default=0, help="seed of the noise and of the random poses")
    p.add_argument("--no-rgb", action="store_true", help="write depth only")
    p.add_argument("--views", type=int, default=None,
                   help="N colour cameras around the scene (camera 0 the thesis' view; docs/multicam.md): shaded "
                        "colour with nails and a textured background in cam<k>/rgb, no depth unless --depth")
    p.add_argument("--depth", action="store_true", help="with --views: also write each view's depth (RGB-D rig)")
    p.add_argument("--image-scale", type=float, default=1.0,
                   help="with --views: each camera's image this many times 640x480 in each direction, the same field "
                        "of view (2: 1280x960, f = 1050 px)")
    p.add_argument("--protocol", default="none", choices=["none", "ballan"],
                   help="with --views: Ballan et al.'s noise (100 circles per image, salient detections deleted, "
                        "outliers within 200 px, 5 px jitter) and simulated nail detections in salient.json")
    p.add_argument("--scan-object", type=Path, default=None,
                   help="an in-hand scan: the hand holds this closed mesh (.ply/.obj/.off, mm) and turns it twice "
                        "in front of the camera (docs/scanning.md); --frames N sets the length")
    p.add_argument("--hand", default="hand_right", help="with --scan-object: the hand that holds it")
    _backend_option(p)
    p.add_argument("--force", action="store_true", help="replace the content of a non-empty --out")
    p.set_defaults(func=commands.synth)

    p = sub.add_parser("scan", help="in-hand scanning: track the hand, remove it, reconstruct the held object as a "
                       "closed mesh and a rigid model for --models (thesis Ch. 5)", formatter_class=_Formatter)
    p.add_argument("seq", type=Path, help="sequence folder with depth and rgb/ (the hand is found by skin colour)")
    p.add_argument("--hand", default="hand_right", help="the hand model that holds the object")
    p.add_argument("--out", type=Path, required=True, help="output folder (must be new or empty)")
    p.add_argument("--baseline", action="store_true",
                   help="the KinectFusion-style baseline: raw depth, ICP alone, no hand tracking")
    p.add_argument("--gamma-t", type=float, default=None, help="weight of the contact term against ICP (Eq. 5.2)")
    p.add_argument("--near", type=float, default=200.0, help="mm, nearer depth is ignored")
    p.add_argument("--far", type=float, default=1500.0, help="mm, farther depth is ignored")
    p.add_argument("--force", action="store_true", help="replace the content of a non-empty --out")
    p.set_defaults(func=commands.scan)

    p = sub.add_parser("rig", help="a rigged model (mesh, skeleton, skinning weights) of an articulated object from a "
                       "depth sequence of it being bent, then the sequence tracked with it (thesis Ch. 6)",
                       formatter_class=_Formatter)
    p.add_argument("seq", type=Path, help="sequence folder with the object being bent (depth; several cameras: "
                   "multi-view depth)")
    p.add_argument("--template", required=True, help="the object's closed mesh in mm (PLY, OFF, OBJ, STL) or a model "
                   "(name or .npz, e.g. the model.npz of torchhand scan)")
    p.add_argument("--out", type=Path, required=True, help="output folder (must be new or empty)")
    p.add_argument("--hands", default="", help="comma-separated hands of the sequence to track first and remove "
                   "(their first pose from init_pose.json)")
    p.add_argument("--template-pose", help="JSON file with the 4x4 template-to-world transform on frame 0 (default: "
                   "from init_pose.json when the sequence lists a model with the template's mesh)")
    p.add_argument("--name", help="the rigged model's name (default rig_<sequence>)")
    p.add_argument("--gamma-def", type=float, default=0.005, help="weight of the data terms in the deformable "
                   "tracking (Eq. 6.1; thesis: 0.005 for small triangles, 0.05 for large)")
    p.add_argument("--lambda-thr", type=float, default=0.7, help="eigenvalue threshold of the spectral clustering: "
                   "higher finds more, smaller parts (thesis: 0.7, 0.98 for small parts)")
    p.add_argument("--rigidity", type=float, default=None, help="weight of the as-rigid-as-possible term added "
                   "to the deformable tracking (default 0.005; 0: the thesis' Laplacian alone, docs/rigging.md)")
    p.add_argument("--stretch", type=float, default=None, help="weight of the edge-length term added to the "
                   "deformable tracking (default 0.05; 0: off, docs/rigging.md)")
    p.add_argument("--interval", choices=("sequence", "thesis"), default="sequence", help="frames the motion "
                   "segmentation compares: any two, or the thesis' Eq. 6.7 interval (docs/rigging.md)")
    p.add_argument("--no-refine", action="store_true", help="take the count of eigenvalues below --lambda-thr as "
                   "the number of clusters (the thesis); by default one more cluster is tried while it survives the "
                   "merge of redundant parts (docs/rigging.md)")
    p.add_argument("--no-normals", action="store_true", help="segment by distance changes alone (no d^n, Eq. 6.10)")
    p.add_argument("--merge-ratio", type=float, default=1.5, help="join neighbouring parts that one rigid motion "
                   "fits within this factor of their own residual (redundant bones; 0: keep every cluster)")
    p.add_argument("--skin-width", type=float, default=5.0, help="mm, width of the skinning blend across joints")
    p.add_argument("--frames", type=int, help="rig from the first N frames only")
    p.add_argument("--no-track", action="store_true", help="build the model, do not track the sequence with it")
    p.add_argument("--near", type=float, default=200.0, help="mm, nearer depth is ignored")
    p.add_argument("--far", type=float, default=1500.0, help="mm, farther depth is ignored")
    p.add_argument("--force", action="store_true", help="replace the content of a non-empty --out")
    p.set_defaults(func=commands.rig)

    p = sub.add_parser("eval", help="score predictions against ground truth (px, mm, PCK/AUC, penetration)",
                       formatter_class=_Formatter)
    p.add_argument("pred", nargs="*", type=Path, help="prediction folder(s) in the gt/ layout")
    p.add_argument("--gt", nargs="+", type=Path, default=None,
                   help="ground truth folder(s), one per prediction; without --gt, the fit quality each prediction's "
                        "track_log.json records (silhouette IoU, depth residual), as for a real recording")
    p.add_argument("--json", type=Path, help="write all scores to this JSON file")
    p.add_argument("--plot", type=Path, help="write the PCK curves (0-50 mm) to this PNG")
    p.add_argument("--list", type=Path, help="a file of 'PRED GT' folder pairs, one per line (relative to the file)")
    _scale_options(p)
    p.add_argument("--no-penetration", action="store_true", help="skip the mesh interpenetration measures")
    p.set_defaults(func=commands.evaluate)

    p = sub.add_parser("eval-dataset", help="import, track and score a whole split of a public dataset (one task per "
                       "sequence, resumable; DIR/results.json: per sequence and overall MPJPE, PA-MPJPE, AUC, 2D px)",
                       formatter_class=_Formatter)
    p.add_argument("name", choices=DATASET_FORMATS, help="the dataset")
    p.add_argument("root", type=Path, help="the dataset's root folder, as published")
    p.add_argument("--split", required=True,
                   help="a split name (dexycb: s0_train ... s3_test; ho3d: a folder of ROOT such as train; fpha: all; "
                        "nyu: train or test) or a file of sequence folders relative to ROOT, one per line")
    p.add_argument("--out", type=Path, required=True,
                   help="run folder: sequences/, track/, scores/ and results.json; run again to resume")
    p.add_argument("--cameras", default=None, metavar="SERIAL,...",
                   help="dexycb: the cameras of every sequence (default: the split's; camera 0 the master when selected)")
    _scale_options(p)
    p.add_argument("--energy", default="LO+F", help="energy terms of the tracking (as torchhand track --energy)")
    p.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda")
    _segment_options(p, "auto")
    p.set_defaults(func=commands.eval_dataset)

    p = sub.add_parser("view", help="a 3D recording of a tracked sequence for rerun: each camera's depth as points, "
                       "the posed models, the 21 joints and the ground truth, per-frame error and fit-check curves, the "
                       "camera rig (pip install 'torchhand[viz]')", formatter_class=_Formatter)
    p.add_argument("out", type=Path, help="a tracked sequence's output folder, OUT/<sequence> of torchhand track")
    p.add_argument("--gt", type=Path, default=None,
                   help="the sequence folder: its depth, cameras and gt/ joints (default: the folder track_log.json "
                        "names, drawn without ground truth)")
    p.add_argument("--rrd", type=Path, default=None, help="write the recording to this .rrd file (rerun FILE opens it)")
    p.add_argument("--spawn", action="store_true", help="send the recording to a rerun viewer it starts (a display)")
    p.add_argument("--stride", type=_positive_int, default=4,
                   help="every Nth pixel of each depth map, in each direction, becomes a point")
    p.add_argument("--force", action="store_true", help="replace an existing --rrd file")
    p.set_defaults(func=commands.view)

    p = sub.add_parser("track", help="track sequences from their first-frame pose (the tracking never reads gt/)",
                       formatter_class=_Formatter)
    p.add_argument("dirs", nargs="*", type=Path, help="sequence folders")
    p.add_argument("--list", type=Path, help="a file of sequence folders, one per line (relative to the file)")
    _scale_options(p)
    p.add_argument("--batch", type=int, default=None,
                   help="same-scene sequences tracked as one batch per task (default: 1 on CPU, 16 on CUDA); the "
                        "results depend on it, never on --workers")
    p.add_argument("--resume", action="store_true",
                   help="keep the sequences of --out that are complete and were tracked with these settings; track "
                        "the rest")
    p.add_argument("--chunk", type=_positive_int, default=None, metavar="N",
                   help="split sequences longer than N frames into chunks of about N frames, tracked as separate "
                        "tasks (so that --workers share one long recording); each chunk after the first starts from "
                        "the automatic initialisation (hands only): not identical to one pass")
    p.add_argument("--chunk-overlap", type=int, default=None, metavar="K",
                   help="frames each chunk after the first tracks before its own, to settle (default: "
                        "torchhand.app.scaleout.CHUNK_OVERLAP, 10)")
    p.add_argument("--out", type=Path, required=True, help="output folder; each sequence gets OUT/<name>/")
    p.add_argument("--energy", default="LO+F",
                   help="energy terms: LO (model-to-data + data-to-model, depth) and any of C (collisions), S "
                        "(salient points), F (free space), P (physics, needs pybullet), E (edges of colour images), "
                        "O (optical flow of colour images), e.g. LO+CS or LO+CSP; colour views (synth --views): "
                        "E+C+O; every camera of sequence.json is used")
    p.add_argument("--metric", default="point-to-plane", choices=["point-to-point", "point-to-plane"],
                   help="model-to-data distance (thesis Eq. 4.6 / 4.7)")
    p.add_argument("--solver", default="lm", choices=["lm", "pso"],
                   help="per frame: Levenberg-Marquardt (Algorithm 1), or a particle swarm over the same energy (the "
                        "HOPE baseline of Ballan et al.; slow: particles x generations energy evaluations a frame)")
    p.add_argument("--particles", type=int, default=64, help="with --solver pso (HOPE64, HOPE128)")
    p.add_argument("--generations", type=int, default=40, help="with --solver pso")
    from torchhand.tracking.labels import LABELINGS

    p.add_argument("--labels", default="proximity", choices=LABELINGS,
                   help="which model a data pixel belongs to: the model nearest in 3D, or the nearest rendered "
                        "model in the image (docs/results.md)")
    p.add_argument("--iterations", type=int, default=50, help="max iterations per frame")
    p.add_argument("--min-motion", type=_positive_float, default=0.2,
                   help="a frame has converged when the joints move less than this (mm) in an iteration (the "
                        "thesis' 0.2; 0.1 tracks colour rigs closer at about 1.8x the time, docs/results.md)")
    p.add_argument("--first-iterations", type=int, default=50, help="iterations on the first frame")
    p.add_argument("--prediction", type=float, default=None,
                   help="start each frame from the previous pose + P x its last step (minmod-limited, see "
                        "--no-prediction-limiter): 0 = the previous pose (the thesis), 1 = constant velocity; "
                        "default: 1, except 0 for a scene with a rope tracked with depth terms (LO)")
    p.add_argument("--no-prediction-limiter", dest="prediction_limiter", action="store_false",
                   help="with --prediction, extrapolate the last step as it is (default: per DoF the smaller of the "
                        "last two steps, 0 where they disagree in sign)")
    p.add_argument("--limit-slack", type=limit_slack_arg, default=0.0, metavar="RAD|none",
                   help="the solver keeps each sequence in a box: the joint limits widened by RAD radians and "
                        "grown to hold its first-frame pose (the thesis' own motions leave the limits); none: no "
                        "box, the soft limits of E_anatomy (thesis Eq. 4.17) alone (docs/results.md)")
    p.add_argument("--seed", type=int, default=0, help="seed of the recovery perturbations (runs are repeatable)")
    p.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda")
    _backend_option(p)
    p.add_argument("--viz", action="store_true",
                   help="write labelled overlay PNGs and an MP4 per sequence (with the ground-truth skeletons "
                        "where the sequence has gt/)")
    p.add_argument("--force", action="store_true", help="replace existing output folders")
    p.add_argument("--models", help="the scene instead of each sequence.json's: shipped names or .npz paths (e.g. "
                   "a hand from torchhand calibrate)")
    p.add_argument("--reinit-iou", type=float, default=0.5,
                   help="re-initialise a frame whose fitted hands overlap their data with a silhouette IoU below this "
                        "(particle swarm seeded from the frame's blobs and the pose tracked; 0: never)")
    # options.NAIL_SOURCES, spelled out: importing it (and the tracker) would slow every command's parsing by seconds
    p.add_argument("--nails", choices=("auto", "detector"), default="auto",
                   help="nail detections of colour views (S): auto = each camera's salient.json where it has one, "
                        "else the shipped colour nail detector; detector = the shipped detector everywhere")
    p.add_argument("--write-render", action="store_true",
                   help="also write each frame's rendered model depth (OUT/<sequence>/render/NNNNNN.png, 16-bit mm)")
    p.add_argument("--write-vertices", action="store_true",
                   help="also write each model's posed vertices per frame (OUT/<sequence>/vertices/<model>.npy, "
                        "(N, V, 3) float32 mm in camera 0's coordinates), to score any model against ground-truth "
                        "vertices")
    _segment_options(p, None)
    p.set_defaults(func=commands.track)

    p = sub.add_parser("init", help="find the first-frame pose of the hands (particle swarm + LM) and write "
                       "init_pose.json and init_overlay.png into the sequence folder", formatter_class=_Formatter)
    p.add_argument("seq", type=Path, help="sequence folder")
    p.add_argument("--force", action="store_true", help="replace an existing init_pose.json")
    _segment_options(p, None)
    p.set_defaults(func=commands.init)

    p = sub.add_parser("calibrate", help="fit a hand's size (global scale, finger lengths) to a few frames of a "
                       "sequence and write the resized model (.npz, for --models) and a report", formatter_class=_Formatter)
    p.add_argument("seq", type=Path, help="sequence folder")
    p.add_argument("--model", default="hand_right", help="the hand to resize: a shipped name or a .npz path")
    p.add_argument("--out", type=Path, required=True, help="the resized model, e.g. my_hand.npz (report: my_hand.json)")
    p.add_argument("--frames", type=int, default=5, help="frames to fit, evenly spread over the sequence")
    p.add_argument("--force", action="store_true", help="replace an existing --out and its report")
    _segment_options(p, None)
    p.set_defaults(func=commands.calibrate)

    p = sub.add_parser("import", help="turn a folder of 16-bit depth PNGs (a user's recording) into a sequence folder",
                       formatter_class=_Formatter)
    p.add_argument("src", type=Path, help="folder of single-channel 16-bit depth PNGs (natural file-name order); "
                                          "with --format, one sequence folder of that dataset")
    p.add_argument("--out", type=Path, required=True, help="sequence folder to write (must be new or empty)")
    p.add_argument("--format", choices=DATASET_FORMATS,
                   help="read SRC as a published dataset's sequence (fpha: <root>/Video_files/<subject>/<action>/"
                        "<seq>, its skeleton.txt as ground truth; nyu: a split folder, train/ or test/, with its "
                        "joint_data.mat; ho3d: one sequence folder <root>/<split>/<SEQ> with depth/, meta/ and rgb/; "
                        "dexycb: one sequence folder <root>/<subject>/<YYYYMMDD_HHMMSS>, all its cameras as one rig), "
                        "with the dataset's own intrinsics and units; default: a folder of depth "
                        "PNGs")
    p.add_argument("--camera", type=_positive_int, default=None,
                   help="with --format nyu: which of the split's three Kinects (1-3; default 1)")
    p.add_argument("--cameras", default=None, metavar="SERIAL,...",
                   help="with --format dexycb: the camera serials to import (default: all of meta.yml; camera 0 is "
                        "the master when selected)")
    p.add_argument("--fx", type=float, help="focal length x, px")
    p.add_argument("--fy", type=float, help="focal length y, px")
    p.add_argument("--cx", type=float, help="principal point x, px (pixel centres at integers)")
    p.add_argument("--cy", type=float, help="principal point y, px")
    p.add_argument("--intrinsics", type=Path, help="JSON with fx, fy, cx, cy (and optionally depth_unit_mm)")
    p.add_argument("--depth-unit-mm", type=float, help="millimetres per depth unit (SR305: 0.125, Kinect: 1)")
    p.add_argument("--models", default="hand_right", help="the scene: shipped model names or .npz paths")
    p.add_argument("--rgb", help="glob of colour images, one per depth frame (natural order)")
    p.add_argument("--fps", type=float, default=30.0, help="frame rate of the recording")
    p.add_argument("--force", action="store_true", help="replace the content of a non-empty --out")
    _segment_options(p, "auto")
    p.set_defaults(func=commands.import_folder)
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if getattr(args, "workers", 1) > 1:  # the workers' server imports while this process does
        from torchhand.app.workers import start_server

        start_server(args.workers, getattr(args, "ray", None))
    import torch

    torch.set_num_threads(args.threads)
    try:
        device = getattr(args, "device", "cpu")
        if str(device).startswith("cuda") and not torch.cuda.is_available():
            raise UsageError(f"--device {device}: no CUDA device is available (use --device cpu)")
        return args.func(args)
    except KeyboardInterrupt:
        print(f"torchhand {args.command}: interrupted; every sequence already written is complete (rerun with "
              "--resume to finish the others)", file=sys.stderr)
        return 130
    except Exception as err:
        message = user_error(err)
        if message is None:  # a bug: never reported as a usage error
            traceback.print_exc()
            print(f"torchhand {args.command}: internal error ({type(err).__name__}); this is a bug in torchhand, "
                  "please report it with the traceback above", file=sys.stderr)
            return 1
        print(f"torchhand {args.command}: error: {message}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
