"""The ``torchhand`` command line, run in-process through ``torchhand.app.cli.main``."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest

from torchhand.app.cli import build_parser, main

REPO = Path(__file__).resolve().parents[1]
SUBCOMMANDS = ("demo", "synth", "eval", "track")


# ------------------------------------------------------------------ help
def test_help_lists_subcommands(capsys):
    with pytest.raises(SystemExit) as ex:
        main(["--help"])
    assert ex.value.code == 0
    out = capsys.readouterr().out
    for cmd in SUBCOMMANDS:
        assert cmd in out


def test_no_subcommand_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as ex:
        main([])
    assert ex.value.code == 2
    assert "usage" in capsys.readouterr().err


@pytest.mark.skipif(shutil.which("torchhand") is None, reason="the torchhand console script is not installed")
def test_console_script_help():
    res = subprocess.run([shutil.which("torchhand"), "--help"], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    for cmd in SUBCOMMANDS:
        assert cmd in res.stdout


def test_pyproject_packages_every_subpackage():
    tomllib = pytest.importorskip("tomllib")
    cfg = tomllib.loads((REPO / "pyproject.toml").read_text())
    packages = set(cfg["tool"]["setuptools"]["packages"])
    subpackages = {"torchhand." + str(p.parent.relative_to(REPO / "torchhand")).replace("/", ".")
                   for p in (REPO / "torchhand").rglob("__init__.py") if p.parent != REPO / "torchhand"}
    assert {"torchhand.data", "torchhand.tracking.energies", "torchhand.io"} <= subpackages  # the layout this test assumes
    missing = sorted(subpackages - packages)
    assert not missing, f"not packaged: {missing}"


# ------------------------------------------------------------------ demo
# --track-frames 0: the demo's synthesise-track-evaluate stage takes tens of seconds per
# frame on a busy 2-core machine; its parts are covered by the synth/eval/track tests.
DEMO = ["--frames", "2", "--track-frames", "0"]


@pytest.fixture(scope="module")
def demo_out(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "demo"
    assert main(["demo", "--out", str(out), *DEMO]) == 0
    return out


def test_demo_writes_outputs(demo_out):
    out = demo_out
    assert (out / "overlays" / "000000.png").is_file() and (out / "overlays" / "000001.png").is_file()
    assert not (out / "overlays" / "000002.png").exists()
    img = cv2.imread(str(out / "overlays" / "000000.png"))
    assert img is not None and img.shape == (480, 640, 3)
    assert (out / "demo.mp4").is_file() and (out / "demo.mp4").stat().st_size > 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 2
    assert summary["models"] == ["hand_right", "hand_left", "ball"] and summary["dofs"] == 80
    assert summary["tracking"] is None
    kp = json.loads((out / "keypoints_2d.json").read_text())
    assert len(kp) == 2 and set(kp[0]) == {"hand_right", "hand_left"} and len(kp[0]["hand_right"]) == 21


def test_demo_refuses_to_overwrite(demo_out, capsys):
    out = demo_out
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert main(["demo", "--out", str(out), *DEMO]) == 2
    err = capsys.readouterr().err
    assert "torchhand demo: error" in err and str(out) in err and "--force" in err
    after = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert after == before


def test_demo_summary_lists_only_written_outputs(demo_out):
    summary = json.loads((demo_out / "summary.json").read_text())
    missing = [o for o in summary["outputs"] if not (demo_out / o).exists()]
    assert not missing, f"listed but not written: {missing}"


# ------------------------------------------------------------------ synth + eval
@pytest.fixture(scope="module")
def synth_out(tmp_path_factory):
    out = tmp_path_factory.mktemp("cli") / "random"
    code = main(["synth", "--random", "--models", "hand_right", "--frames", ":2", "--out", str(out), "--noise", "none"])
    assert code == 0
    return out


def test_synth_random(synth_out):
    seq = json.loads((synth_out / "sequence.json").read_text())
    assert seq["frames"] == 2 and seq["models"] == ["hand_right"] and seq["has_rgb"] is True
    assert seq["source"]["noise"] == "none"
    assert sorted(p.name for p in (synth_out / "depth").iterdir()) == ["000000.png", "000001.png"]
    assert sorted(p.name for p in (synth_out / "rgb").iterdir()) == ["000000.png", "000001.png"]
    assert np.load(synth_out / "gt" / "theta.npy").shape == (2, 37)


def test_eval_ground_truth_against_itself(synth_out, tmp_path, capsys):
    j, plot = tmp_path / "res" / "scores.json", tmp_path / "pck.png"
    assert main(["eval", str(synth_out / "gt"), "--gt", str(synth_out), "--json", str(j), "--plot", str(plot)]) == 0
    r = json.loads(j.read_text())
    assert {"thesis_mean_px", "median_px", "mean_mm", "auc_0_50mm", "frames"} <= set(r)
    assert r["frames"] == 2
    assert r["thesis_mean_px"] == 0 and r["median_px"] == 0 and r["mean_mm"] == 0 and r["median_mm"] == 0
    for key in ("mpjpe_mm", "pa_mpjpe_mm", "rr_mpjpe_mm", "mean_px"):  # the 21 joints' figures at the top level
        assert r[key] == pytest.approx(0.0, abs=1e-6) and r[key] == r["joints21"][key], key
    assert r["auc_0_50"] == 1.0
    assert r["auc_0_50mm"] == 1.0
    joints = r["joints21"]  # synthesis writes the standard 21 joints too
    assert {k: joints[k] for k in ("mpjpe_mm", "pa_mpjpe_mm", "rr_mpjpe_mm", "mean_px")} == pytest.approx(
        {"mpjpe_mm": 0.0, "pa_mpjpe_mm": 0.0, "rr_mpjpe_mm": 0.0, "mean_px": 0.0}, abs=1e-6)
    assert joints["auc_0_50"] == 1.0
    img = cv2.imread(str(plot))
    assert img is not None and img.ndim == 3
    out = capsys.readouterr().out
    assert "2 frames" in out and str(j) in out and "standard 21 joints: MPJPE 0.00 mm" in out


def test_eval_needs_one_gt_per_prediction(synth_out, capsys):
    assert main(["eval", str(synth_out), str(synth_out), "--gt", str(synth_out)]) == 2
    assert "--gt" in capsys.readouterr().err


def test_eval_missing_prediction(synth_out, tmp_path, capsys):
    assert main(["eval", str(tmp_path / "none"), "--gt", str(synth_out)]) == 2
    assert "none" in capsys.readouterr().err


def test_synth_unknown_sequence(tmp_path, capsys):
    root = tmp_path / "hia"
    (root / "Configs").mkdir(parents=True)
    (root / "Models").mkdir()
    out = tmp_path / "out"
    assert main(["synth", "--hia-root", str(root), "--sequence", "99", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "torchhand synth: error" in err and "99" in err
    assert not out.exists()


def test_synth_unknown_sequence_in_thesis_data(hia_root, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["synth", "--hia-root", str(hia_root), "--sequence", "99", "--out", str(out)]) == 2
    assert "99" in capsys.readouterr().err
    assert not out.exists()


def test_synth_without_hia_root(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["synth", "--sequence", "16", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "--hia-root" in err
    assert not out.exists()


def test_synth_random_with_sequence_is_refused(tmp_path, capsys):
    assert main(["synth", "--random", "--sequence", "16", "--out", str(tmp_path / "o")]) == 2
    assert "--random" in capsys.readouterr().err


def test_synth_bad_frames_and_noise_are_usage_errors(tmp_path, capsys):
    with pytest.raises(SystemExit) as ex:
        main(["synth", "--random", "--frames", "abc", "--out", str(tmp_path / "o")])
    assert ex.value.code == 2
    assert "--frames" in capsys.readouterr().err
    with pytest.raises(SystemExit) as ex:
        main(["synth", "--random", "--noise", "gauss", "--out", str(tmp_path / "o")])
    assert ex.value.code == 2
    assert "argument --noise: invalid choice: 'gauss'" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("value", ["0", "-1", "abc", "nan"])
def test_track_bad_min_motion_is_a_usage_error(tmp_path, capsys, value):
    with pytest.raises(SystemExit) as ex:
        main(["track", str(tmp_path), "--out", str(tmp_path / "o"), "--min-motion", value])
    assert ex.value.code == 2 and "--min-motion" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_track_nails_choices_are_the_runners():
    from torchhand.app.cli import build_parser
    from torchhand.app.runner import NAIL_SOURCES

    track = build_parser()._subparsers._group_actions[0].choices["track"]
    assert tuple(next(a for a in track._actions if a.dest == "nails").choices) == NAIL_SOURCES


def test_track_unknown_energy(synth_out, tmp_path, capsys):
    out = tmp_path / "track"
    assert main(["track", str(synth_out), "--out", str(out), "--energy", "XY"]) == 2
    assert "XY" in capsys.readouterr().err
    assert not out.exists()



def test_track_negative_prediction(synth_out, tmp_path, capsys):
    out = tmp_path / "track"
    assert main(["track", str(synth_out), "--out", str(out), "--prediction", "-1"]) == 2
    assert "prediction" in capsys.readouterr().err
    assert not out.exists()

def test_track_limit_slack_is_an_angle_or_none(capsys):
    from torchhand.tracking.tracker import TrackerConfig

    parse = build_parser().parse_args
    assert parse(["track", "d", "--out", "o"]).limit_slack == TrackerConfig().limit_slack == 0.0
    assert parse(["track", "d", "--out", "o", "--limit-slack", "none"]).limit_slack is None
    assert parse(["track", "d", "--out", "o", "--limit-slack", "0.2"]).limit_slack == 0.2
    for bad in ("-0.1", "inf", "wide"):
        with pytest.raises(SystemExit) as ex:
            parse(["track", "d", "--out", "o", "--limit-slack", bad])
        assert ex.value.code == 2
        assert "argument --limit-slack: expected none or a" in capsys.readouterr().err


def test_parser_defaults():
    args = build_parser().parse_args(["synth", "--random", "--out", "x", "--frames", "3:7"])
    assert args.frames == slice(3, 7) and args.noise == "kinect" and args.seed == 0 and args.models == "hand_right"
    args = build_parser().parse_args(["eval", "p", "--gt", "g"])
    assert args.workers == 1 and not args.no_penetration


def _actions(parser):
    import argparse

    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from ((f"{name} {a}", x) for a, x in _actions(sub))
        elif not isinstance(action, argparse._HelpAction):
            yield "/".join(action.option_strings) or action.dest, action


def test_every_option_has_help_and_shows_its_default():
    parser = build_parser()
    missing = [name for name, a in _actions(parser) if not a.help]
    assert missing == [], f"options without help: {missing}"
    for cmd in SUBCOMMANDS:
        text = " ".join(parser._subparsers._group_actions[0].choices[cmd].format_help().split())
        for name, a in _actions(parser._subparsers._group_actions[0].choices[cmd]):
            if a.option_strings and a.default is not None and a.required is False:
                assert f"{a.help} (default: {a.default})" in text, (cmd, name)


@pytest.fixture()
def sample_seq(tmp_path):
    seq = tmp_path / "seq"
    shutil.copytree(REPO / "datasets" / "sample", seq)
    shutil.rmtree(seq / "gt")
    return seq


@pytest.mark.parametrize("kind", ["metres", "8-bit"])
def test_track_refuses_unusable_depth_with_a_clear_error(sample_seq, tmp_path, capsys, kind):
    """Depth stored in metres or as 8-bit images: no frame can be tracked. track exits
    non-zero naming the file and writes nothing for the sequence."""
    for png in sorted((sample_seq / "depth").iterdir()):
        d = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
        bad = np.round(d / 1000.0).astype(np.uint16) if kind == "metres" else np.clip(d // 8, 0, 255).astype(np.uint8)
        cv2.imwrite(str(png), bad)
    out = tmp_path / "out"
    assert main(["track", str(sample_seq), "--out", str(out), "--iterations", "1", "--first-iterations", "1"]) == 1
    err = capsys.readouterr().err
    assert "torchhand track: error" in err and "000000.png" in err and "nothing written" in err
    assert ("metres" in err) if kind == "metres" else ("16-bit" in err)
    assert not any(out.glob("*/theta.npy"))


def test_track_fails_a_sequence_of_which_no_frame_is_tracked(sample_seq, tmp_path, capsys):
    """Readable depth that holds nothing in the working range (every frame flagged)."""
    for png in sorted((sample_seq / "depth").iterdir()):
        cv2.imwrite(str(png), np.full((480, 640), 3000, np.uint16))  # beyond the 1.5 m far plane
    out = tmp_path / "out"
    assert main(["track", str(sample_seq), "--out", str(out), "--iterations", "1", "--first-iterations", "1"]) == 1
    err = capsys.readouterr().err
    assert "no frame of the 4 could be tracked" in err and "no valid depth" in err
    assert not any(out.glob("*/theta.npy"))


@pytest.mark.slow
def test_track_writes_labelled_overlays_and_eval_counts_flagged_frames(tmp_path, capsys):
    seq = tmp_path / "seq"
    shutil.copytree(REPO / "datasets" / "sample", seq)
    (seq / "depth" / "000002.png").unlink()  # a missing frame: flagged, previous pose kept
    out = tmp_path / "out"
    args = ["track", str(seq), "--out", str(out), "--iterations", "2", "--first-iterations", "2", "--viz",
            "--min-motion", "0.1"]
    assert main(args) == 0
    name = json.loads((seq / "sequence.json").read_text())["name"]
    log = json.loads((out / name / "track_log.json").read_text())
    assert log["settings"]["tracker"]["min_joint_motion"] == 0.1 and log["settings"]["nails"] == "auto"
    assert [f["valid"] for f in log["frames"]] == [True, True, False, True]
    assert "depth frame not found" in log["frames"][2]["notes"]
    img = cv2.imread(str(out / name / "overlays" / "000001.png"))
    assert img is not None and (out / name / "overlays.mp4").stat().st_size > 0
    # the labels: a dark legend box at the top left, the colour bar at the right
    assert (img[6:12, 6:60] == 40).all(-1).mean() > 0.3
    assert img[24:456, 640 - 62 : 640 - 48].std() > 20
    capsys.readouterr()
    assert main(["eval", str(out / name), "--gt", str(seq / "gt"), "--no-penetration"]) == 0
    assert "(1 flagged by the tracker)" in capsys.readouterr().out


# ------------------------------------------------------------------ error policy
def _error_lines(capsys) -> list:
    return capsys.readouterr().err.strip().splitlines()


def test_a_bad_argument_is_one_line_naming_it(synth_out, tmp_path, capsys):
    assert main(["track", str(synth_out), "--out", str(tmp_path / "o"), "--batch", "0"]) == 2
    err = _error_lines(capsys)
    assert len(err) == 1 and err[0].startswith("torchhand track: error: --batch"), err


def test_a_missing_optional_dependency_names_its_extra(synth_out, tmp_path, capsys, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "ray", None)  # import ray fails as where it is not installed
    assert main(["track", str(synth_out), "--out", str(tmp_path / "o"), "--ray"]) == 2
    err = [line for line in _error_lines(capsys) if not line.startswith("track ")]  # the progress bar's
    assert len(err) == 1, err
    assert err[0].startswith("torchhand track: error: --ray needs ray: pip install 'torchhand[ray]'"), err


def test_an_import_of_an_extra_module_names_the_extra():
    from torchhand.core.errors import user_error

    assert "torchhand[physics]" in user_error(ModuleNotFoundError("No module named 'pybullet'", name="pybullet"))
    assert user_error(ImportError("cannot import name 'x' from 'torchhand.app.runner'", name="torchhand.app.runner")) \
        is None


@pytest.mark.parametrize("bug", [TypeError("f() got an unexpected keyword argument 'x'"), KeyError("x"),
                                 AttributeError("'NoneType' object has no attribute 'x'"), "numpy"])
def test_a_library_bug_is_not_reported_as_a_usage_error(bug, synth_out, tmp_path, capsys, monkeypatch):
    import torchhand.app.scaleout as scaleout

    def broken(*args, **kwargs):
        if bug == "numpy":
            np.stack([])  # a ValueError from inside numpy: torchhand passed it something wrong
        raise bug

    monkeypatch.setattr(scaleout, "track_many", broken)
    code = main(["track", str(synth_out), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 1, err
    assert "Traceback" in err and "in broken" in err and "bug in torchhand, please report it" in err


@pytest.mark.parametrize("bug", [False, True], ids=["no_depth", "key_error"])
def test_a_failed_sequence_says_why_in_one_line_unless_it_is_a_bug(bug, synth_out, tmp_path, capsys, monkeypatch):
    """A sequence that fails on its data (no hand in view) is one line naming the frame; a
    bug inside the task keeps its traceback and asks to be reported. Either way the
    sequence fails alone (exit status 1) and nothing is written for it."""
    import torchhand.app.runner as runner
    from torchhand.geometry.camera import kinect_camera
    from torchhand.tracking.segmentation import segment_hands

    def tracks(*args, **kwargs):
        if bug:
            {}["frames"]  # a library bug inside the task
        segment_hands(np.zeros((480, 640), np.float32), kinect_camera(), frame="depth/000000.png")  # no depth

    monkeypatch.setattr(runner, "track_sequences", tracks)  # the task imports it when it runs
    code = main(["track", str(synth_out), "--out", str(tmp_path / "o")])
    err = [line for line in _error_lines(capsys) if not line.startswith("track ")]  # the progress bar's
    name = json.loads((synth_out / "sequence.json").read_text())["name"]
    assert code == 1, err
    assert err[0] == (f"torchhand track: error: {name}: KeyError: 'frames' (a bug in torchhand: please "
                      "report it with this traceback); nothing written" if bug else
                      f"torchhand track: error: {name}: depth/000000.png: no depth between 200 and 1500 mm; "
                      "nothing written"), err
    assert ("Traceback (most recent call last):" in err) == bug and any("in tracks" in line for line in err) == bug
    assert err[-1] == "torchhand track: 1 of 1 sequences failed"
    assert not (tmp_path / "o" / name).exists()
