"""Tracking many sequences as tasks: local processes and Ray give the sequential run's
θ to the last bit, a killed worker is retried, --resume, Ctrl-C and failing sequences
leave every finished sequence intact, and bad input is named."""

from __future__ import annotations

import json
import math
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from torchhand.app.cli import main
from torchhand.app.options import TrackOptions
from torchhand.app.scaleout import SUMMARY_NAME, TrackJob, connect_ray, evaluate_pairs, read_list, track_many
from torchhand.data.layout import OutputLayout, camera_dir, frame_name
from torchhand.data.synth import SyntheticFrames, demo_motion, write_synthetic_sequence
from torchhand.model.scene import Scene
from torchhand.tracking.tracker import TrackerConfig

FRAMES = 3
JOB = TrackJob(TrackOptions(TrackerConfig(max_iterations=8, first_frame_iterations=8)))


@pytest.fixture(scope="module")
def sequences(tmp_path_factory):
    """Four 3-frame one-hand sequences (windows of the demo motion), kinect noise."""
    root = tmp_path_factory.mktemp("seqs")
    demo = demo_motion()
    scene = Scene.from_names(["hand_right"], dtype=demo.theta.dtype)
    right = demo.scene.slices["hand_right"]
    out = []
    for k in range(4):
        th = demo.theta[10 * k : 10 * k + FRAMES, right]
        fr = SyntheticFrames(scene, th, demo.cameras, f"s{k}", {"format": "test"})
        out.append(write_synthetic_sequence(fr, root / f"s{k}", noise="kinect", seed=k, rgb=False))
    return out


@pytest.fixture(scope="module")
def sequential(sequences, tmp_path_factory):
    out = tmp_path_factory.mktemp("sequential")
    run = track_many(sequences, out, JOB, progress=False)
    assert run["failed"] == 0 and run["tasks"] == 4
    return out


def _theta(out: Path, names=("s0", "s1", "s2", "s3")) -> dict:
    return {n: np.load(out / n / "theta.npy") for n in names}


def _assert_equal(a: Path, b: Path, names=("s0", "s1", "s2", "s3")) -> None:
    ta, tb = _theta(a, names), _theta(b, names)
    for n in names:
        assert np.array_equal(ta[n], tb[n]), n  # to the last bit
        assert len(json.loads((a / n / "track_log.json").read_text())["frames"]) == FRAMES, n
        assert [p.name for p in (a / n / "motion").iterdir()] == ["Model_Hand_R.MOTION"], n
    assert not [p for p in a.iterdir() if ".partial-" in p.name]


@pytest.mark.slow
def test_processes_equal_the_sequential_run(sequences, sequential, tmp_path):
    events = []
    run = track_many(sequences, tmp_path / "out", JOB, workers=2, progress=False, on_event=events.append)
    _assert_equal(tmp_path / "out", sequential)
    pids = {e[2] for e in events if e[1] == "start"}
    assert len(pids) == 2 and os.getpid() not in pids  # two worker processes did the work
    assert sum(e[2] for e in events if e[1] == "frames") == 4 * FRAMES  # the progress of every frame
    summary = json.loads((tmp_path / "out" / SUMMARY_NAME).read_text())
    assert [s["status"] for s in summary["sequences"]] == ["ok"] * 4 and summary["frames"] == 4 * FRAMES
    assert run["workers"] == 2


def _kill_once(state: dict):
    """An event handler that kills the worker of task 1 at its first tracked frame."""

    def handle(event):
        i, kind, value = event
        if kind == "start":
            state.setdefault("pids", {})[i] = value
        if kind == "frames" and i == 1 and not state.get("killed"):
            state["killed"] = state["pids"][1]
            os.kill(state["pids"][1], signal.SIGKILL)

    return handle


@pytest.mark.slow
def test_a_killed_worker_is_retried_and_the_outputs_equal(sequences, sequential, tmp_path):
    state = {}
    run = track_many(sequences, tmp_path / "out", JOB, workers=2, progress=False, on_event=_kill_once(state))
    assert state.get("killed")
    assert run["failed"] == 0
    _assert_equal(tmp_path / "out", sequential)


@pytest.mark.slow
def test_a_retry_keeps_what_its_killed_attempt_finished_and_force_replaces_older_folders(
        sequences, sequential, tmp_path):
    import shutil

    out = tmp_path / "out"
    shutil.copytree(sequential / "s2", out / "s2")  # an older run's folder: --force replaces it
    np.save(out / "s2" / "theta.npy", np.zeros(3))
    events = []

    def handle(event):  # as task 1 starts, its folder appears complete: what an attempt killed
        events.append(event)  # after renaming it, before returning, leaves to the retry
        if event[:2] == (1, "start"):
            shutil.copytree(sequential / "s1", out / "s1")

    run = track_many(sequences, out, JOB, force=True, progress=False, on_event=handle)
    assert run["failed"] == 0
    assert [e[1] for e in events if e[0] == 1] == ["start", "done"]  # kept, not tracked again
    assert sum(e[2] for e in events if e[0] == 2 and e[1] == "frames") == FRAMES
    _assert_equal(out, sequential)


@pytest.mark.slow
def test_resume_after_an_interrupted_run(sequences, sequential, tmp_path):
    out = tmp_path / "out"

    def interrupt(event):  # Ctrl-C as the third task starts
        if event[1] == "start" and event[0] == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        track_many(sequences, out, JOB, progress=False, on_event=interrupt)
    assert sorted(p.name for p in out.iterdir()) == ["s0", "s1"]  # the finished ones, no partial folder
    _assert_equal(out, sequential, ("s0", "s1"))
    kept = (out / "s0" / "theta.npy").stat().st_mtime_ns
    (out / ".s2.partial-deadbeef").mkdir()  # what a killed writer leaves
    with pytest.raises(FileExistsError, match="--resume"):
        track_many(sequences, out, JOB, progress=False)
    run = track_many(sequences, out, JOB, resume=True, progress=False)
    assert run["resumed"] == 2 and run["tasks"] == 2 and run["failed"] == 0
    assert (out / "s0" / "theta.npy").stat().st_mtime_ns == kept
    _assert_equal(out, sequential)
    other = TrackJob(TrackOptions(TrackerConfig(energy="LO", max_iterations=8, first_frame_iterations=8)))
    with pytest.raises(ValueError, match="tracker.energy: 'LO\\+F' there, 'LO' now"):
        track_many(sequences, out, other, resume=True, progress=False)


@pytest.mark.slow
def test_one_sequence_in_this_process_writes_it_and_the_summary(sequences, tmp_path):
    """The default tier's run of track_many: one sequence, no worker processes."""
    job = TrackJob(TrackOptions(TrackerConfig(max_iterations=2, first_frame_iterations=2)))
    events = []
    run = track_many(sequences[:1], tmp_path / "out", job, progress=False, on_event=events.append)
    assert run["failed"] == 0 and run["tasks"] == 1 and run["frames"] == FRAMES
    assert [e[1] for e in events][0] == "start" and [e[1] for e in events][-1] == "done"
    theta = np.load(tmp_path / "out" / "s0" / "theta.npy")
    assert theta.shape == (FRAMES, 37) and np.isfinite(theta).all()
    summary = json.loads((tmp_path / "out" / SUMMARY_NAME).read_text())
    assert [(s["sequence"], s["status"]) for s in summary["sequences"]] == [("s0", "ok")]
    assert not [p for p in (tmp_path / "out").iterdir() if ".partial-" in p.name]


def test_resume_refuses_a_folder_of_another_command(sequences, tmp_path):
    assert main(["demo", "--out", str(tmp_path / "s0"), "--frames", "2", "--track-frames", "0"]) == 0
    with pytest.raises(ValueError, match="not written by torchhand track"):
        track_many(sequences[:1], tmp_path, JOB, resume=True, progress=False)


@pytest.mark.slow
def test_a_failing_sequence_among_good_ones(sequences, sequential, tmp_path, capsys):
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(sequences[0], bad)
    (camera_dir(bad, 0) / "depth" / frame_name(0)).write_bytes(b"not a png")
    listing = tmp_path / "list.txt"
    listing.write_text(f"# a dataset\n{sequences[1]}\n\nbad\n{sequences[2]}\n")
    code = main(["track", "--list", str(listing), "--out", str(tmp_path / "out"), "--workers", "2",
                 "--iterations", "8", "--first-iterations", "8"])
    assert code == 1
    err = capsys.readouterr().err
    assert "s0" in err and frame_name(0) in err and "1 of 3 sequences failed" in err
    summary = json.loads((tmp_path / "out" / SUMMARY_NAME).read_text())
    assert [s["status"] for s in summary["sequences"]] == ["ok", "failed", "ok"]
    assert np.array_equal(np.load(tmp_path / "out" / "s1" / "theta.npy"), np.load(sequential / "s1" / "theta.npy"))
    assert not (tmp_path / "out" / "s0").exists()


def test_bad_input_is_named(sequences, tmp_path, capsys):
    listing = tmp_path / "list.txt"
    listing.write_text(f"{sequences[0]}\nmissing_a\nmissing_b\n")
    assert main(["track", "--list", str(listing), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "missing_a" in err and "missing_b" in err and "nothing was tracked" in err
    assert not (tmp_path / "out").exists()
    with pytest.raises(SystemExit) as ex:
        main(["track", str(sequences[0]), "--out", str(tmp_path / "out"), "--workers", "0"])
    assert ex.value.code == 2
    assert "--workers: expected an integer >= 1, got 0" in capsys.readouterr().err
    with pytest.raises(ValueError, match="2 path"):
        listing.write_text("only_one\n")
        read_list(listing, 2)
    with pytest.raises(ValueError, match="--workers must be an integer >= 1"):
        track_many(sequences, tmp_path / "out", JOB, workers=-1, progress=False)


ray = pytest.importorskip("ray") if os.environ.get("TORCHHAND_TEST_RAY", "1") != "0" else None


@pytest.fixture(scope="module")
def ray_cluster():
    if ray is None:
        pytest.skip("Ray tests disabled")
    connect_ray("local", 2)
    yield
    ray.shutdown()


def test_an_unreachable_ray_address_fails_fast():
    pytest.importorskip("ray")
    t0 = time.perf_counter()
    with pytest.raises(ConnectionError, match="127.0.0.1:9"):
        connect_ray("127.0.0.1:9", 1, timeout_s=2.0)
    assert time.perf_counter() - t0 < 10


@pytest.mark.slow
def test_ray_equals_the_sequential_run_and_retries_a_killed_worker(ray_cluster, sequences, sequential, tmp_path):
    events = []
    run = track_many(sequences, tmp_path / "ray", JOB, ray="local", progress=False, on_event=events.append)
    assert run["failed"] == 0
    for i in range(4):  # each task's events arrive, in the order it sent them
        kinds = [e[1] for e in events if e[0] == i]
        assert kinds[0] == "start" and kinds[-1] == "done" and kinds.count("frames") == FRAMES, (i, kinds)
    _assert_equal(tmp_path / "ray", sequential)
    state = {}
    run = track_many(sequences, tmp_path / "killed", JOB, ray="local", progress=False, on_event=_kill_once(state))
    assert state.get("killed") and run["failed"] == 0, [s.get("error") for s in run["sequences"]]
    _assert_equal(tmp_path / "killed", sequential)
    pairs = [(tmp_path / "ray" / s.name, s / "gt") for s in sequences] + [(tmp_path / "nothing", sequences[0] / "gt")]
    scored = evaluate_pairs(pairs, ray="local", with_penetration=False, progress=False)
    here = evaluate_pairs(pairs[:4], with_penetration=False, progress=False)
    assert scored["mean_mm"] == here["mean_mm"] and scored["frames"] == 4 * FRAMES
    assert [f["prediction"] for f in scored["failed"]] == [str((tmp_path / "nothing").resolve())]


def test_tasks_are_submitted_longest_first(tmp_path, monkeypatch):
    """Workers start the longest sequences first (equal lengths keep their order); the
    summary keeps the order of the given folders."""
    import torchhand.app.scaleout as scaleout

    demo = demo_motion()
    scene = Scene.from_names(["hand_right"], dtype=demo.theta.dtype)
    right = demo.scene.slices["hand_right"]
    roots = [write_synthetic_sequence(SyntheticFrames(scene, demo.theta[:n, right], demo.cameras, f"n{k}",
                                                      {"format": "test"}), tmp_path / f"n{k}", rgb=False)
             for k, n in enumerate((1, 3, 2, 3))]
    seen = []

    def fake_run(fn, specs, *args, **kwargs):
        seen.extend(name for spec in specs for name in spec["names"])
        return [[{"sequence": n, "status": "ok", "frames": 0, "out": None} for n in spec["names"]] for spec in specs]

    monkeypatch.setattr(scaleout, "run_tasks", fake_run)
    run = track_many(roots, tmp_path / "out", JOB, batch=1, progress=False)
    assert seen == ["n1", "n3", "n2", "n0"]
    assert [s["sequence"] for s in run["sequences"]] == ["n0", "n1", "n2", "n3"]


def test_the_workers_server_starts_only_for_local_workers():
    from torchhand.app.workers import PRELOAD, start_server, worker_context

    assert not start_server(1) and not start_server(4, ray="local")
    ctx = worker_context("torchhand.app.dataset_eval")
    if ctx.get_start_method() == "forkserver":
        assert start_server(2)  # started now, or running already: the workers fork from it
    assert "torch" in PRELOAD


def test_chunk_windows_cover_every_frame_once_in_balanced_chunks():
    from torchhand.app.scaleout import chunk_windows

    assert chunk_windows(12, 6, 2) == [(0, 0, 7), (5, 7, 12)]
    assert chunk_windows(7, 7, 3) == [(0, 0, 7)]
    assert chunk_windows(5, 2, 9) == [(0, 0, 5)]  # an overlap longer than the chunks: one pass
    for frames, chunk, overlap in ((12, 6, 2), (100, 30, 10), (101, 50, 0), (1000, 300, 10), (40, 3, 2)):
        w = chunk_windows(frames, chunk, overlap)
        assert len(w) == math.ceil(frames / chunk)
        kept = [f for _, keep, stop in w for f in range(keep, stop)]
        assert kept == list(range(frames))
        tracked = [stop - start for start, _, stop in w]
        assert max(tracked) - min(tracked) <= 1  # balanced work
        assert all(start == max(0, keep - overlap) and stop > keep for start, keep, stop in w)


def test_chunk_overlap_without_chunk_is_refused(sequences, tmp_path, capsys):
    assert main(["track", str(sequences[0]), "--out", str(tmp_path / "o"), "--chunk-overlap", "3"]) == 2
    assert "--chunk N" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_a_sequence_in_chunks_over_two_workers(tmp_path):
    """A 12-frame sequence in two chunks (``--chunk 6``, overlap 2: frames 0-6 and, from
    frame 5, 7-11) on two workers: written as one sequence; the first chunk's frames
    equal the one-pass run's to the last bit, the second's, tracked from the automatic
    initialisation at frame 5, land on the hand."""
    demo = demo_motion()
    scene = Scene.from_names(["hand_right"], dtype=demo.theta.dtype)
    th = demo.theta[:12, demo.scene.slices["hand_right"]]
    fr = SyntheticFrames(scene, th, demo.cameras, "long", {"format": "test"})
    root = write_synthetic_sequence(fr, tmp_path / "long", noise="kinect", seed=3, rgb=False)
    one = track_many([root], tmp_path / "one", JOB, progress=False)
    events = []
    run = track_many([root], tmp_path / "two", JOB, workers=2, progress=False, chunk=6, chunk_overlap=2,
                     on_event=events.append)
    assert one["failed"] == 0 and run["failed"] == 0 and run["tasks"] == 2 and run["chunked"] == 1
    assert sum(e[2] for e in events if e[1] == "frames") == 7 + 7  # the overlap is tracked twice
    assert len({e[2] for e in events if e[1] == "start"}) == 2
    one_out, two_out = OutputLayout(tmp_path / "one" / "long"), OutputLayout(tmp_path / "two" / "long")
    a, b = np.load(one_out.theta), np.load(two_out.theta)
    assert a.shape == b.shape == (12, th.shape[1])
    assert np.array_equal(a[:7], b[:7])
    ka, kb = np.load(one_out.keypoints_3d), np.load(two_out.keypoints_3d)
    assert np.linalg.norm(ka[7:] - kb[7:], axis=-1).mean() < 10.0  # mm: the same hand, tracked from a new start
    log = json.loads(two_out.track_log.read_text())
    assert len(log["frames"]) == 12 and log["settings"]["chunk"] == 6 and log["settings"]["chunk_overlap"] == 2
    assert "first frame of a chunk tracked from frame 5" in log["frames"][7]["notes"]
    assert [p.name for p in (tmp_path / "two" / "long" / "motion").iterdir()] == ["Model_Hand_R.MOTION"]
    with pytest.raises(ValueError, match="other settings"):  # the chunking is part of the settings
        track_many([root], tmp_path / "two", JOB, resume=True, progress=False)


@pytest.mark.parametrize("kind", ["data", "check", "bug"])
def test_pairs_that_cannot_be_scored_are_the_datas_unless_a_task_hit_a_bug(kind, tmp_path, monkeypatch):
    """No pair scored: an EvaluationError (a usage error) unless a task hit a bug, which is
    not the user's to fix and stays a RuntimeError. The data's own error (empty folders)
    is one line; a ValueError of torchhand's checks keeps its traceback without being
    called a bug; a bug keeps its traceback and asks to be reported."""
    import torchhand.app.scaleout as scaleout
    from torchhand.core.check import check_int
    from torchhand.scoring.sequences import EvaluationError

    if kind == "check":
        monkeypatch.setattr(scaleout, "evaluate_sequence", lambda *a, **k: check_int(-1, "frames", low=0))
    elif kind == "bug":
        monkeypatch.setattr(scaleout, "evaluate_sequence", lambda *a, **k: {}["frames"])
    (tmp_path / "pred").mkdir()
    (tmp_path / "gt").mkdir()
    with pytest.raises(RuntimeError if kind == "bug" else EvaluationError) as err:
        evaluate_pairs([(tmp_path / "pred", tmp_path / "gt")], progress=False)
    text = str(err.value)
    assert isinstance(err.value, EvaluationError) == (kind != "bug")
    assert ("Traceback (most recent call last)" in text) == (kind != "data"), text
    assert ("a bug in torchhand" in text) == (kind == "bug"), text
    assert ("frames must be an int >= 0, got -1" in text) == (kind == "check"), text
