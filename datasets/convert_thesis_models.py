"""Convert the thesis' personalised models into torchhand model files.

    python datasets/convert_thesis_models.py --hia-root ../shared/data/hands_in_action --out models

Writes ``hand_right``, ``hand_left``, ``ball``, ``cube``, ``pipe`` and ``rope`` as
``<out>/<name>.npz`` (format: ``torchhand/io/assets.py``). The hand meshes are the
same in every sequence; the joint limits of sequences 01-18 are used (19-21 carry a
variant). The rope's rigging pose comes from its skeleton, since sequence 18 has no
MOTION file.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from torchhand.io import THESIS_MODEL_NAMES, assets_from_thesis, read_thesis_model, read_voi, save_assets

SOURCES = {  # thesis model -> sequence to take it from
    "Model_Hand_R": "01",
    "Model_Hand_L": "01",
    "Model_Object_Ball": "15",
    "Model_Object_Cube": "20",
    "Model_Object_Pipe_Gray": "17",
    "Model_Object_Pipe_Green_Long": "18",
}
# full fingertip vertex sets of the two hand meshes (checked by their vertex counts)
VOI_SETS = {"Model_Hand_R": "VOIs_Model_0.txt", "Model_Hand_L": "VOIs_Model_1.txt"}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--hia-root", required=True, type=Path)
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--force", action="store_true", help="replace existing model files")
    ap.add_argument("--demo-sequence", default="16", help="sequence whose motion the demo plays")
    ap.add_argument("--demo-frames", type=int, default=60)
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    for thesis_name, seq in SOURCES.items():
        files = read_thesis_model(args.hia_root / "Models" / seq, thesis_name)
        tips = VOI_SETS.get(thesis_name)
        tips = read_voi(args.hia_root / "VOIs" / tips) if tips else None
        assets = assets_from_thesis(files, source=f"Hands in Action (MIT), Models/{seq}/{thesis_name}",
                                    fingertips=tips)
        path = save_assets(assets, args.out / f"{THESIS_MODEL_NAMES[thesis_name]}.npz", overwrite=args.force)
        print(f"{path}: {assets.num_bones} bones, {len(assets.dof_names)} DoF, {len(assets.vertices)} vertices")
    write_demo_motion(args.hia_root, args.demo_sequence, args.demo_frames, args.out / "demo_motion.npz", args.force)


def write_demo_motion(hia_root: Path, seq: str, frames: int, path: Path, force: bool) -> None:
    """A short excerpt of a thesis motion as theta of the shipped models, for the demo."""
    import json

    import numpy as np
    import torch

    from torchhand import load_model
    from torchhand.io import sequence_models
    from torchhand.model.motion import motion_to_theta

    if path.exists() and not force:
        raise FileExistsError(f"{path} exists; pass --force to replace it")
    names, bounds = sequence_models(hia_root, seq)
    thetas, models = [], []
    rows = np.arange(frames) + bounds.motion_offset
    for thesis_name in names:
        model = load_model(THESIS_MODEL_NAMES[thesis_name], dtype=torch.float64)
        motion = read_thesis_model(hia_root / "Models" / seq, thesis_name).motion
        thetas.append(motion_to_theta(model, {b: m[rows] for b, m in motion.items()}))
        models.append(model.name)
    meta = {"models": models, "source": f"Hands in Action (MIT), sequence {seq}, frames 0-{frames - 1}"}
    np.savez_compressed(path, theta=torch.cat(thetas, 1).numpy().astype(np.float32),
                        meta=np.frombuffer(json.dumps(meta).encode(), np.uint8))
    print(f"{path}: {frames} frames of {models}")


if __name__ == "__main__":
    main()
