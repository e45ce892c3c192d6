"""``torchhand view`` (torchhand.app.viewer): a recording of a two-camera synthetic depth
sequence and an output folder made from its ground truth (the joints moved 5 mm) is
written to an .rrd file and read back with rerun's chunk reader: its entities, the
frames each has, and the error curve."""

from __future__ import annotations

import json
import shutil
import sys
from collections import defaultdict

import numpy as np
import pytest

from torchhand.app.cli import main
from torchhand.core.errors import MissingExtra
from torchhand.data.layout import OutputLayout, SequenceLayout, read_joints21, write_joints21

FRAMES = 3


@pytest.fixture(scope="module")
def tracked(tmp_path_factory):
    """(sequence folder, output folder): the output holds the ground truth's poses, its
    21 joints moved by (3, 4, 0) mm, and a track log naming the sequence."""
    root = tmp_path_factory.mktemp("view")
    seq = root / "seq"
    assert main(["synth", "--random", "--models", "hand_right", "--frames", f":{FRAMES}", "--views", "2", "--depth",
                 "--out", str(seq), "--noise", "none"]) == 0
    out = OutputLayout(root / "out" / "seq")
    shutil.copytree(SequenceLayout(seq).gt.root, out.root, ignore=shutil.ignore_patterns("ids", "salient*"))
    j3, j2 = read_joints21(out.root)
    write_joints21(out.root, j3 + np.array([3.0, 4.0, 0.0]), j2)
    out.track_log.write_text(json.dumps({"sequence": "seq", "source": str(seq), "frames": [
        {"frame": f, "iou": 0.9 - 0.1 * f, "depth_residual_mm": 2.0 + f, "surrounded": 0.2 * f, "keypoint_mm": None,
         "fit_flagged": f == 2} for f in range(FRAMES)]}))
    return seq, out.root


def _read(rrd):
    """entity path -> sorted frame indices logged (static entities: [])."""
    from rerun.chunk import RrdReader

    frames, values = defaultdict(set), defaultdict(list)
    for chunk in RrdReader(str(rrd)).stream().to_chunks():
        batch = chunk.to_record_batch()
        frames[chunk.entity_path]
        if "frame" in batch.schema.names:
            frames[chunk.entity_path] |= set(batch.column("frame").to_pylist())
        if "Scalars:scalars" in batch.schema.names:
            values[chunk.entity_path] += [v[0] for v in batch.column("Scalars:scalars").to_pylist()]
        if "Points3D:positions" in batch.schema.names:
            values[chunk.entity_path] += [len(v) for v in batch.column("Points3D:positions").to_pylist()]
    return {e: sorted(f) for e, f in frames.items()}, values


@pytest.mark.slow
def test_recording_has_every_entity_and_frame(tracked, tmp_path, capsys):
    pytest.importorskip("rerun")
    seq, out = tracked
    rrd = tmp_path / "rec" / "seq.rrd"
    assert main(["view", str(out), "--gt", str(seq), "--rrd", str(rrd), "--stride", "8"]) == 0
    assert f"recorded {FRAMES} frames of 2 camera(s) with the ground truth -> {rrd}" in capsys.readouterr().out
    assert [p.name for p in rrd.parent.iterdir()] == ["seq.rrd"]  # no partial file left
    frames, scalars = _read(rrd)
    every = list(range(FRAMES))
    for entity in ("/world/cam0/depth", "/world/cam1/depth", "/world/models/hand_right", "/world/joints21/tracked",
                   "/world/joints21/tracked/bones", "/world/joints21/ground_truth",
                   "/world/joints21/ground_truth/bones", "/metrics/mpjpe_mm", "/metrics/iou",
                   "/metrics/depth_residual_mm"):
        assert frames.get(entity) == every, (entity, frames.get(entity))
    for entity in ("/world", "/world/cam0", "/world/cam1"):  # the view coordinates and the rig: static
        assert frames.get(entity) == [], entity
    assert scalars["/metrics/mpjpe_mm"] == pytest.approx([5.0] * FRAMES)
    assert scalars["/metrics/iou"] == pytest.approx([0.9, 0.8, 0.7])
    assert scalars["/metrics/surrounded"] == pytest.approx([0.0, 0.2, 0.4])
    assert scalars["/metrics/fit_flagged"] == [0.0, 0.0, 1.0]
    assert "/metrics/keypoint_mm" not in frames and "/metrics/off_hand" not in frames  # no frame has them
    assert min(scalars["/world/cam1/depth"]) > 10 and scalars["/world/joints21/tracked"] == [21] * FRAMES  # points


@pytest.mark.slow
def test_without_gt_the_log_names_the_sequence(tracked, tmp_path):
    pytest.importorskip("rerun")
    from torchhand.app.viewer import view_sequence

    _, out = tracked
    res = view_sequence(out, rrd=tmp_path / "a.rrd", progress=False)
    assert res == {"frames": FRAMES, "cameras": 2, "rrd": str(tmp_path / "a.rrd"), "ground_truth": False}
    frames, _ = _read(tmp_path / "a.rrd")
    assert "/world/joints21/ground_truth" not in frames and "/metrics/mpjpe_mm" not in frames
    assert frames["/world/cam1/depth"] == list(range(FRAMES))


@pytest.mark.slow
def test_bad_input_is_one_line(tracked, tmp_path, capsys):
    seq, out = tracked
    (tmp_path / "taken.rrd").write_text("mine")
    for argv, message in ((["--rrd", str(tmp_path / "taken.rrd")], "taken.rrd exists"),
                          ([], "give --rrd FILE")):
        assert main(["view", str(out), *argv]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("torchhand view: error: ") and message in err and "\n" not in err
    assert (tmp_path / "taken.rrd").read_text() == "mine"
    assert main(["view", str(seq), "--rrd", str(tmp_path / "b.rrd")]) == 2  # a sequence, not an output folder
    assert "is not a tracked sequence's output folder" in capsys.readouterr().err


@pytest.mark.slow
def test_missing_extra(tracked, tmp_path, monkeypatch, capsys):
    from torchhand.app.viewer import view_sequence

    _, out = tracked
    monkeypatch.setitem(sys.modules, "rerun", None)  # as if rerun-sdk were not installed
    with pytest.raises(MissingExtra, match=r"pip install 'torchhand\[viz\]'"):
        view_sequence(out, rrd=tmp_path / "c.rrd")
    assert main(["view", str(out), "--rrd", str(tmp_path / "c.rrd")]) == 2
    assert "torchhand[viz]" in capsys.readouterr().err and not (tmp_path / "c.rrd").exists()
