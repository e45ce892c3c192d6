"""The work of each ``torchhand`` subcommand: its parsed arguments in, the library
called, a summary printed; the exit status out. The parser is :mod:`torchhand.app.cli`."""

from __future__ import annotations

import dataclasses
import json
import math
import sys
from pathlib import Path

__all__ = ["demo", "synth", "scan", "rig", "evaluate", "track", "import_folder", "init", "calibrate",
           "segment_config"]


def demo(args) -> int:
    from torchhand.app.demo import run_demo

    summary = run_demo(args.out, frames=args.frames, force=args.force, device=args.device,
                       track_frames=args.track_frames)
    print(f"rendered {summary['frames']} frames of {', '.join(summary['models'])} "
          f"({summary['dofs']} DoF, {summary['render_ms_per_frame']:.1f} ms/frame to render)")
    t = summary["tracking"]
    if t:
        print(f"tracked {t['frames']} synthetic Kinect frames from the first-frame pose: "
              f"mean error {t['mean_px']:.2f} px, {t['mean_mm']:.2f} mm ({t['seconds_per_frame']:.1f} s/frame)")
    print("wrote " + ", ".join(f"{args.out}/{o}" for o in summary["outputs"]))
    return 0


def synth(args) -> int:
    from torchhand.data.synth import demo_motion, random_poses, thesis_motion, with_camera_ring, write_synthetic_sequence

    if args.scan_object is not None:
        from torchhand.data.scanning import write_scan_sequence

        if args.frames is not None and (args.frames.start not in (None, 0) or args.frames.stop is None):
            raise ValueError("with --scan-object, --frames is N (or :N), the number of frames")
        out = write_scan_sequence(args.scan_object, args.out, hand=args.hand,
                                  frames=None if args.frames is None else args.frames.stop, noise=args.noise,
                                  seed=args.seed, force=args.force, backend=args.backend)
        print(f"wrote an in-hand scan of {args.scan_object} held by {args.hand} to {out} (noise: {args.noise}; the "
              f"object's poses and mesh in {out / 'gt'})")
        return 0
    if args.demo:
        frames = demo_motion(args.frames)
    elif args.random:
        if args.sequence or args.hia_root:
            raise ValueError("--random renders random poses; do not combine it with --hia-root/--sequence")
        n = args.frames.stop if args.frames is not None and args.frames.stop else 100
        frames = random_poses(args.models.split(","), n, seed=args.seed)
    else:
        if not (args.hia_root and args.sequence):
            raise ValueError("give --hia-root and --sequence (or --random, or --demo)")
        frames = thesis_motion(args.hia_root, args.sequence, args.frames)
    if args.views is None:
        if args.depth or args.protocol != "none" or args.image_scale != 1:
            raise ValueError("--depth, --protocol and --image-scale go with --views N (colour cameras)")
        out = write_synthetic_sequence(frames, args.out, noise=args.noise, seed=args.seed, force=args.force,
                                       rgb=not args.no_rgb, backend=args.backend)
        print(f"wrote {len(frames.theta)} frames of {', '.join(frames.scene.names)} to {out} "
              f"(noise: {args.noise}; ground truth in {out / 'gt'})")
        return 0
    if args.no_rgb:
        raise ValueError("--views renders colour cameras: --no-rgb does not apply")
    frames = with_camera_ring(frames, args.views, args.image_scale)
    out = write_synthetic_sequence(frames, args.out, noise=args.noise, seed=args.seed, force=args.force,
                                   backend=args.backend, colour="shaded", depth=args.depth,
                                   protocol=args.protocol)
    what = "colour and depth" if args.depth else "colour"
    print(f"wrote {len(frames.theta)} frames of {', '.join(frames.scene.names)} in {args.views} {what} views to "
          f"{out} (protocol: {args.protocol}; ground truth in {out / 'gt'})")
    return 0


def scan(args) -> int:
    from torchhand.app.scan import scan_folder
    from torchhand.reconstruction.in_hand import ScanConfig

    config = ScanConfig()
    if args.gamma_t is not None:
        if not args.gamma_t >= 0:
            raise ValueError(f"--gamma-t must be >= 0, got {args.gamma_t}")
        config = dataclasses.replace(config, registration=dataclasses.replace(config.registration,
                                                                              gamma_t=args.gamma_t))
    log = scan_folder(args.seq, args.out, hand=args.hand, force=args.force, config=config, baseline=args.baseline,
                      near=args.near, far=args.far)
    print(f"scanned {log['frames']} frames ({log['fused_frames']} fused) in {log['seconds']['per_frame']:.2f} s/frame: "
          f"{log['faces']} faces, {'watertight' if log['watertight'] else 'NOT watertight'} -> "
          f"{args.out / 'model.npz'}, {args.out / 'mesh.ply'}")
    return 0


def rig(args) -> int:
    from torchhand.app.rig import rig_folder
    from torchhand.reconstruction.deformable import DeformConfig
    from torchhand.reconstruction.rigging import RigConfig

    pose = None
    if args.template_pose is not None:
        try:
            pose = json.loads(Path(args.template_pose).read_text())
        except (OSError, json.JSONDecodeError) as err:
            raise ValueError(f"--template-pose {args.template_pose}: not a readable JSON 4x4 matrix ({err})") from None
    deform = DeformConfig(gamma_def=args.gamma_def)
    if args.rigidity is not None:
        deform = dataclasses.replace(deform, rigidity=args.rigidity)
    if args.stretch is not None:
        deform = dataclasses.replace(deform, stretch=args.stretch)
    log = rig_folder(args.seq, args.template, args.out, hands=[h for h in args.hands.split(",") if h],
                     name=args.name, template_pose=pose, deform=deform, lambda_thr=args.lambda_thr,
                     use_normals=not args.no_normals, config=RigConfig(skin_width=args.skin_width),
                     merge_ratio=args.merge_ratio, interval=args.interval, refine=not args.no_refine,
                     near=args.near, far=args.far, frames=args.frames, force=args.force, track=not args.no_track)
    joints = ", ".join(f"{d} DoF" for d in log["joint_dofs"]) or "none"
    print(f"rigged {log['frames']} frames: {log['parts']} parts, joints: {joints}; {log['seconds']['total']:.0f} s -> "
          f"{args.out / 'model.npz'}, {args.out / 'skeleton.png'}"
          + (f", {args.out / 'track'}" if "track" in log else ""))
    return 0


def evaluate(args) -> int:
    from torchhand.app.scaleout import evaluate_pairs, read_list
    from torchhand.scoring.sequences import fit_report

    if args.gt is None and not args.list:  # no ground truth: how well the fitted models explain the data
        if not args.pred:
            raise ValueError("no predictions given (PRED... or --list FILE)")
        result = fit_report(args.pred)
        for r in result["sequences"]:
            print(f"{r['sequence']}: {r['frames']} frames, silhouette IoU mean {r['mean_iou']:.2f} (min "
                  f"{r['min_iou']:.2f} at frame {r['worst_frame']}), median depth residual "
                  f"{r['median_depth_residual_mm']:.1f} mm, {r['frames_below_iou']} frames below IoU "
                  f"{result['iou_threshold']}, {r['reinitialized_frames']} re-initialised, "
                  f"{r['fit_flagged_frames']} failing the fit check")
        print(f"fit quality (no ground truth) over {result['frames']} frames: silhouette IoU mean "
              f"{result['mean_iou']:.2f} (min {result['min_iou']:.2f}), median depth residual "
              f"{result['median_depth_residual_mm']:.1f} mm, {result['frames_below_iou']} frames below IoU "
              f"{result['iou_threshold']}, {result['fit_flagged_frames']} failing the fit check")
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(result, indent=2))
            print(f"wrote {args.json}")
        return 0
    gts = args.gt or []
    if len(args.pred) != len(gts):
        raise ValueError(f"give one --gt folder per prediction: {len(args.pred)} predictions, {len(gts)} --gt")
    pairs = list(zip(args.pred, gts)) + (read_list(args.list, 2) if args.list else [])
    if not pairs:
        raise ValueError("no predictions given (PRED... --gt GT... or --list FILE)")
    missing = [str(p) for pair in pairs for p in pair if not Path(p).is_dir()]
    if missing:
        raise FileNotFoundError(f"{len(missing)} folders not found, nothing was scored: {', '.join(missing)}")
    result = evaluate_pairs(pairs, workers=args.workers, ray=args.ray, with_penetration=not args.no_penetration)
    for f in result["failed"]:
        print(f"torchhand eval: error: {f['prediction']}: {f['error']}", file=sys.stderr)
    flagged = sum(r["flagged_frames"] for r in result.get("sequences", [result]))
    print(f"{result['frames']} frames ({flagged} flagged by the tracker)" + (
        f": thesis keypoints 2D error mean {result['thesis_mean_px']:.2f} px (median {result['median_px']:.2f}), "
        f"3D error mean {result['mean_mm']:.2f} mm (median {result['median_mm']:.2f}), "
        f"AUC 0-50 mm {result['auc_0_50mm']:.3f}" if "thesis_mean_px" in result else
        f", ground truth of the standard 21 joints only; {result['lost_frames']} lost frames (above 20 mm)"))
    models = result.get("models", {})
    if models:
        name, worst = max(models.items(), key=lambda kv: kv[1]["mean_mm"])
        print("models: " + ", ".join(f"{n} {m['mean_mm']:.1f} mm" for n, m in models.items())
              + f"; worst model {name} ({worst['metric']}, {worst['mean_mm']:.1f} mm mean, worst frame "
              f"{worst['worst_frame_mm']:.1f} mm); {result['lost_frames']} lost frames (a model above 20 mm)")
    if "joints21" in result:
        j = result["joints21"]
        print(f"standard 21 joints: MPJPE {j['mpjpe_mm']:.2f} mm, PA-MPJPE {j['pa_mpjpe_mm']:.2f} mm, root-relative "
              f"{j['rr_mpjpe_mm']:.2f} mm, AUC 0-50 mm {j['auc_0_50']:.3f}, 2D {j['mean_px']:.2f} px")
    if "penetration" in result:
        p = result["penetration"]
        print(f"penetration: {p['pairs_per_frame']:.1f} intersecting triangle pairs per frame, "
              f"max depth {p['max_depth_mm']:.1f} mm")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2))
        print(f"wrote {args.json}")
    if args.plot:
        from torchhand.app.drawing import plot_curves

        seqs = result.get("sequences", [result])
        pck = lambda r: r["pck"] if "pck" in r else r["joints21"]["pck"]  # noqa: E731  thesis keypoints, else 21 joints
        curves = {r["sequence"]: (pck(r)["thresholds_mm"], pck(r)["fraction"]) for r in seqs if "pck" in r or "joints21" in r}
        plot_curves(curves, args.plot, "3D error threshold (mm)", "fraction of keypoints")
        print(f"wrote {args.plot}")
    return 1 if result["failed"] else 0


def eval_dataset(args) -> int:
    from torchhand.app.dataset_eval import RESULTS_NAME, evaluate_dataset
    from torchhand.app.options import TrackOptions
    from torchhand.tracking.energies import parse_energy
    from torchhand.tracking.tracker import TrackerConfig

    parse_energy(args.energy)
    seg = segment_config(args, "auto")
    table = evaluate_dataset(args.name, args.root, args.split, args.out,
                             TrackOptions(TrackerConfig(energy=args.energy), device=args.device),
                             workers=args.workers, ray=args.ray, retries=args.retries, threads=args.threads,
                             segmentation=None if seg.mode == "none" else seg.to_dict(),
                             cameras=None if args.cameras is None else [c for c in args.cameras.split(",") if c.strip()])
    for r in table["sequences"]:
        if r["status"] == "ok":
            print(f"{r['sequence']}: {r['frames']} frames, MPJPE {r['mpjpe_mm']:.2f} mm, PA-MPJPE "
                  f"{r['pa_mpjpe_mm']:.2f} mm, 2D {r['mean_px']:.2f} px, {r['lost_frames']} lost")
        else:
            print(f"torchhand eval-dataset: error: {r['sequence']}: {r['error']}", file=sys.stderr)
    o = table["overall"]
    if o["sequences"]:
        print(f"{args.name} {args.split}: {o['sequences']} sequences, {o['frames']} frames: MPJPE {o['mpjpe_mm']:.2f} "
              f"mm, PA-MPJPE {o['pa_mpjpe_mm']:.2f} mm, AUC 0-50 mm {o['auc_0_50']:.3f}, 2D {o['mean_px']:.2f} px")
    print(f"wrote {Path(args.out) / RESULTS_NAME}")
    return 1 if table["failed"] else 0


def view(args) -> int:
    from torchhand.app.viewer import view_sequence

    res = view_sequence(args.out, rrd=args.rrd, gt=args.gt, spawn=args.spawn, stride=args.stride, force=args.force)
    print(f"recorded {res['frames']} frames of {res['cameras']} camera(s)"
          + (" with the ground truth" if res["ground_truth"] else "") + (f" -> {res['rrd']}" if res["rrd"] else ""))
    return 0


def track(args) -> int:
    from torchhand.app.options import TrackOptions
    from torchhand.app.scaleout import CHUNK_OVERLAP, SUMMARY_NAME, TrackJob, read_list, track_many
    from torchhand.tracking.energies import parse_energy
    from torchhand.tracking.tracker import TrackerConfig

    parse_energy(args.energy)  # reject unknown energies before reading any data
    cfg = TrackerConfig(energy=args.energy, metric=args.metric, max_iterations=args.iterations,
                        min_joint_motion=args.min_motion, first_frame_iterations=args.first_iterations,
                        prediction=args.prediction, prediction_limiter=args.prediction_limiter, seed=args.seed,
                        backend=args.backend, labels=args.labels, solver=args.solver, particles=args.particles,
                        generations=args.generations, limit_slack=args.limit_slack)
    segment = segment_config(args, "none") if _segment_given(args) else None
    dirs = list(args.dirs) + ([r[0] for r in read_list(args.list)] if args.list else [])
    options = TrackOptions(cfg, device=args.device, viz=args.viz, segment=segment, write_render=args.write_render,
                           write_vertices=args.write_vertices, reinit_iou=args.reinit_iou,
                           models=tuple(args.models.split(",")) if args.models else None, nails=args.nails)
    job = TrackJob(options, threads=args.threads)
    if args.chunk_overlap is not None and args.chunk is None:
        raise ValueError("--chunk-overlap is the overlap of --chunk: give --chunk N too")
    run = track_many(dirs, args.out, job, workers=args.workers, ray=args.ray, batch=args.batch, resume=args.resume,
                     force=args.force, retries=args.retries, chunk=args.chunk,
                     chunk_overlap=CHUNK_OVERLAP if args.chunk_overlap is None else args.chunk_overlap)
    summaries = run["sequences"]
    failed = [s for s in summaries if s["status"] != "ok"]
    for s in summaries:
        if s.get("resumed"):
            print(f"{s['sequence']}: complete, kept (--resume) -> {s['out']}")
        elif s["status"] == "ok":
            fit = (f"silhouette IoU {s['mean_iou']:.2f}, median depth residual {s['median_depth_residual_mm']:.1f} mm"
                   if math.isfinite(s["mean_iou"]) else "not measured (no depth views)")
            print(f"{s['sequence']}: {s['frames']} frames, {s['seconds_per_frame']:.2f} s/frame, "
                  f"{s['flagged_frames']} flagged, {s['reinitialized_frames']} re-initialised, fit: {fit} -> {s['out']}")
        else:
            text, tb, frames = s["error"].rstrip().partition("\nTraceback")  # a traceback goes last
            print(f"torchhand track: error: {s['sequence']}: {text}; nothing written" + (f"{tb}{frames}" if tb else ""),
                  file=sys.stderr)
    if len(summaries) > 1:
        print(f"{len(summaries) - len(failed)} of {len(summaries)} sequences tracked ({run['resumed']} kept), "
              f"{run['frames']} frames in {run['seconds']:.1f} s; summary: {Path(args.out) / SUMMARY_NAME}")
    if failed:
        print(f"torchhand track: {len(failed)} of {len(summaries)} sequences failed", file=sys.stderr)
        return 1
    return 0


def segment_config(args, default_mode: str):
    from torchhand.tracking.segmentation import SegmentConfig

    mode = args.segment or default_mode
    localiser = ""
    if (args.localiser is not None or args.localiser_flip) and mode != "auto":
        raise ValueError(f"--localiser and --localiser-flip are settings of --segment auto, not of --segment {mode}")
    if args.localiser is not None:
        localiser = str(Path(args.localiser).expanduser().resolve())  # the sequence folder keeps it for later runs
        _check_localiser(args.localiser, localiser, args.localiser_flip)
    return SegmentConfig(mode=mode, hands=args.hands, near=args.near, far=args.far,
                         remove_plane=args.remove_plane, localiser=localiser, localiser_flip=args.localiser_flip)


def _check_localiser(given, path: str, flip: bool) -> None:
    """Load the localiser of ``--localiser`` (which runs it once), so that a file that is
    not one fails now, naming the option, not frames later."""
    from torchhand.tracking.segmentation import shared_localiser

    if Path(path).suffix != ".onnx":
        raise ValueError(f"--localiser {given}: expected the .onnx file of a localiser (its .pt beside it), "
                         f"as python -m train.hand_localiser writes them")
    try:
        shared_localiser(path, flip)
    except (ValueError, FileNotFoundError) as err:
        raise ValueError(f"--localiser {given}: {err}") from None


def _segment_given(args) -> bool:
    """Whether the command line sets the segmentation (else the sequence folder's is
    used); a localiser alone cannot be set on top of the folder's."""
    if not args.segment and (args.localiser is not None or args.localiser_flip):
        raise ValueError("--localiser and --localiser-flip set the segmentation of --segment auto: give "
                         "--segment auto too (without --segment the sequence folder's own is used)")
    return bool(args.segment)


def import_dataset(args) -> int:
    """``torchhand import --format NAME``: a published dataset's sequence, with its own
    camera, units and ground truth (:mod:`torchhand.data.datasets`)."""
    from torchhand.data.datasets import FORMATS

    unused = [flag for flag, v in (("--fx", args.fx), ("--fy", args.fy), ("--cx", args.cx), ("--cy", args.cy),
                                   ("--intrinsics", args.intrinsics), ("--depth-unit-mm", args.depth_unit_mm),
                                   ("--rgb", args.rgb)) if v is not None]
    if args.models != "hand_right":
        unused.append("--models")
    if args.camera is not None and args.format != "nyu":
        unused.append("--camera")
    if args.cameras is not None and args.format != "dexycb":
        unused.append("--cameras")
    if unused:
        raise ValueError(f"--format {args.format} reads the dataset's own camera, units and hand; "
                         f"{', '.join(unused)} cannot be given with it")
    seg = segment_config(args, "auto")
    options = {"camera": args.camera or 1} if args.format == "nyu" else {}
    if args.format == "dexycb" and args.cameras is not None:
        options = {"cameras": [c for c in args.cameras.split(",") if c.strip()]}
    info = FORMATS[args.format](args.src, args.out, force=args.force,
                                segmentation=None if seg.mode == "none" else seg.to_dict(), **options)
    missing = len(info.source.get("frames_without_pose", []))
    print(f"imported {info.frames} frames of {args.format} sequence {args.src} to {args.out} "
          f"({info.frames - missing} with a hand pose; segmentation: {seg.mode})")
    return 0


def import_folder(args) -> int:
    from torchhand.data.importing import import_depth_folder, read_intrinsics

    if args.format is not None:
        return import_dataset(args)
    if args.cameras is not None:
        raise ValueError("--cameras selects the cameras of a dataset with several (--format dexycb)")
    given = [args.fx, args.fy, args.cx, args.cy]
    if args.intrinsics is not None:
        if any(v is not None for v in given):
            raise ValueError("give either --intrinsics FILE or --fx/--fy/--cx/--cy, not both")
        intr = read_intrinsics(args.intrinsics)
    else:
        if any(v is None for v in given):
            raise ValueError("the camera intrinsics are needed: --fx, --fy, --cx, --cy (pixels) or --intrinsics FILE")
        intr = dict(zip(("fx", "fy", "cx", "cy"), given))
    unit = args.depth_unit_mm if args.depth_unit_mm is not None else intr.get("depth_unit_mm")
    if unit is None:
        raise ValueError("--depth-unit-mm is needed (millimetres per depth unit: 1 for Kinect, 0.125 for the "
                         "RealSense SR305)")
    seg = segment_config(args, "auto")
    models = args.models.split(",")
    info = import_depth_folder(args.src, args.out, intr, float(unit), models, rgb=args.rgb, fps=args.fps,
                               segmentation=None if seg.mode == "none" else seg.to_dict(), force=args.force)
    print(f"imported {info.frames} frames ({info.cameras[0].width}x{info.cameras[0].height}, "
          f"{info.depth_unit_mm:g} mm per unit) of {', '.join(info.models)} to {args.out} "
          f"(segmentation: {seg.mode})")
    return 0


def init(args) -> int:
    from torchhand.app.initialize import initialize_sequence

    segment = segment_config(args, "auto") if _segment_given(args) else None
    res = initialize_sequence(args.seq, force=args.force, segment=segment)
    print(f"wrote {res['init_pose']} and {res['overlay']}: silhouette IoU {res['iou']:.2f}, median depth residual "
          f"{res['depth_residual_mm']:.1f} mm ({res['seconds']:.1f} s)")
    return 0


def calibrate(args) -> int:
    from torchhand.app.calibrate import calibrate_sequence

    segment = segment_config(args, "auto") if _segment_given(args) else None
    rep = calibrate_sequence(args.seq, args.model, args.out, frames=args.frames, force=args.force, segment=segment)
    fingers = ", ".join(f"{f} {v:.3f}" for f, v in rep["fingers"].items())
    print(f"wrote {rep['model']} and {rep['report']}: scale {rep['scale']:.3f}; finger lengths {fingers}; "
          f"silhouette IoU {rep['mean_iou_before']:.2f} -> {rep['mean_iou_after']:.2f} over "
          f"{len(rep['frames'])} frames")
    return 0
