"""A whole split of a public dataset imported, tracked and scored:
``torchhand eval-dataset NAME ROOT --split S --out DIR [--workers N | --ray]``.

Each sequence of the split is one task of the scale-out (:func:`torchhand.app.scaleout.run_tasks`:
in this process, over local processes or on Ray, with retries): it is imported
(``DIR/sequences/<name>``, :data:`torchhand.data.datasets.FORMATS`), tracked with the
run's options (``DIR/track/<name>``, :func:`torchhand.app.runner.track_sequences`) and
scored against its 21 joints (``DIR/scores/<name>.json``,
:func:`torchhand.scoring.sequences.evaluate_sequence`). Every step writes its result
under a hidden name renamed when complete, so the run is resumable: run it again and
each task keeps what is complete (a tracked folder only when it was tracked with the
same settings; one tracked otherwise is refused, naming it) and does the rest. One
progress bar counts the sequences. ``DIR/results.json`` holds the table: per sequence
its status, frames and the five figures (``mpjpe_mm``, ``pa_mpjpe_mm``, ``rr_mpjpe_mm``,
``auc_0_50``, ``mean_px``) and lost frames, and ``overall`` pooled over the sequences
scored (:func:`torchhand.scoring.sequences.summarize`).

Splits (``--split``): a file listing sequence folders, one per line, relative to ROOT
(``#`` starts a comment line);
or a name: DexYCB's ``s0_train`` ... ``s3_test`` (:data:`DEXYCB_SPLITS`: the protocol of
Chao et al., subjects, cameras and sequences; each sequence is tracked with the split's
cameras as one rig); HO-3D's split folders (``train``, ``evaluation``: every sequence
folder in ``ROOT/<split>``); FPHA's ``all`` (every ``Video_files/<subject>/<action>/<seq>``);
NYU's ``train`` or ``test`` (its camera 1).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Dict, List, NamedTuple, Optional

from tqdm import tqdm

from torchhand.app.options import TrackOptions
from torchhand.app.scaleout import TaskFailure, run_tasks
from torchhand.core.errors import UnknownName, UsageError
from torchhand.data.layout import OutputLayout, SequenceLayout, read_sequence_info
from torchhand.scoring.sequences import JOINT_KEYS, summarize

__all__ = ["evaluate_dataset", "split_sequences", "DatasetSequence", "DEXYCB_SPLITS", "RESULTS_NAME"]

#: the table of a run, in ``DIR``
RESULTS_NAME = "results.json"

_DEXYCB_SUBJECTS = ["20200709-weiy", "20200813-ceppner", "20200820-amousavian", "20200903-ynarang", "20200908-yux",
                    "20200918-ftozetoramos", "20200928-ahanda", "20201002-dieterf", "20201015-ychao",
                    "20201022-lmanuelli"]
_DEXYCB_SERIALS = ["836212060125", "839512060362", "840412060917", "841412060263", "932122060857", "932122060861",
                   "932122061900", "932122062010"]
_ALL, _EVERY5TH = list(range(10)), [i for i in range(100) if i % 5 == 4]
#: DexYCB's evaluation protocol: split -> (subject indices, camera indices, sequence indices of
#: each subject's 100 sorted sequences); s0 seen subjects, s1 unseen subjects, s2 unseen
#: cameras, s3 unseen grasped objects (Chao et al., CVPR 2021)
DEXYCB_SPLITS = {
    "s0_train": (_ALL, list(range(8)), [i for i in range(100) if i % 5 != 4]),
    "s0_val": ([0, 1], list(range(8)), _EVERY5TH),
    "s0_test": (list(range(2, 10)), list(range(8)), _EVERY5TH),
    "s1_train": ([0, 1, 2, 3, 4, 5, 9], list(range(8)), list(range(100))),
    "s1_val": ([6], list(range(8)), list(range(100))),
    "s1_test": ([7, 8], list(range(8)), list(range(100))),
    "s2_train": (_ALL, list(range(6)), list(range(100))),
    "s2_val": (_ALL, [6], list(range(100))),
    "s2_test": (_ALL, [7], list(range(100))),
    "s3_train": (_ALL, list(range(8)), [i for i in range(100) if i // 5 not in (3, 7, 11, 15, 19)]),
    "s3_val": (_ALL, list(range(8)), [i for i in range(100) if i // 5 in (3, 19)]),
    "s3_test": (_ALL, list(range(8)), [i for i in range(100) if i // 5 in (7, 11, 15)]),
}


class DatasetSequence(NamedTuple):
    """One sequence of a split: its source folder, output name and the reader's options."""

    src: Path
    name: str
    options: Dict


def _dexycb_split(root: Path, split: str) -> List[DatasetSequence]:
    subjects, cameras, indices = DEXYCB_SPLITS[split]
    out = []
    for s in subjects:
        folder = root / _DEXYCB_SUBJECTS[s]
        seqs = sorted(p for p in folder.iterdir() if p.is_dir()) if folder.is_dir() else []
        if len(seqs) != 100:
            raise UsageError(f"{folder}: {len(seqs)} sequence folders, DexYCB's protocol ({split}) expects 100")
        opts = {} if len(cameras) == 8 else {"cameras": [_DEXYCB_SERIALS[c] for c in cameras]}
        out += [DatasetSequence(seqs[i], f"{folder.name}_{seqs[i].name}", opts) for i in indices]
    return out


def split_sequences(name: str, root, split: str) -> List[DatasetSequence]:
    """The sequences of ``split`` of the dataset ``name`` at ``root`` (module docstring)."""
    from torchhand.data.datasets import FORMATS

    root = Path(root)
    if name not in FORMATS:
        raise UnknownName(f"dataset {name!r}: known are {', '.join(sorted(FORMATS))}")
    if not root.is_dir():
        raise UsageError(f"{root}: not a folder (give the dataset's root)")
    if Path(split).is_file():
        lines = [ln.strip() for ln in Path(split).read_text().splitlines()]
        srcs = [Path(ln) if Path(ln).is_absolute() else root / ln for ln in lines if ln and not ln.startswith("#")]
        return [DatasetSequence(s, "_".join(s.relative_to(root).parts) if s.is_relative_to(root) else s.name,
                                {}) for s in srcs]
    if name == "dexycb" and split in DEXYCB_SPLITS:
        return _dexycb_split(root, split)
    if name == "ho3d" and (root / split).is_dir():
        return [DatasetSequence(p, p.name, {}) for p in sorted((root / split).iterdir()) if (p / "depth").is_dir()]
    if name == "fpha" and split == "all":
        return [DatasetSequence(p, "_".join(p.parts[-3:]), {})
                for p in sorted((root / "Video_files").glob("*/*/*")) if p.is_dir()]
    if name == "nyu" and split in ("train", "test"):
        return [DatasetSequence(root / split, f"nyu_{split}", {"camera": 1})]
    known = {"dexycb": ", ".join(DEXYCB_SPLITS), "ho3d": "a folder of ROOT (train, evaluation)", "fpha": "all",
             "nyu": "train, test"}[name]
    raise UsageError(f"--split {split}: not a list file nor a split of {name} ({known})")


def _write_atomic(path: Path, text: str) -> None:
    partial = path.parent / f".{path.name}.partial"
    partial.write_text(text)
    os.replace(partial, path)


def _tracked(target: Path, settings: dict) -> bool:
    """``target`` is a complete tracked folder of these settings (a folder of others is refused)."""
    log = OutputLayout(target).track_log
    if not target.exists():
        return False
    try:
        same = json.loads(log.read_text()).get("settings") == settings
    except (OSError, ValueError):
        same = False
    if not same:
        raise UsageError(f"{target}: tracked with other settings or not by torchhand track; choose another --out "
                         "(eval-dataset resumes only a run of the same settings)")
    return True


def _segmentation(d: Optional[Dict]) -> Optional[Dict]:
    """A segmentation as a sequence folder stores it, with every setting (one written
    before a setting existed has its default)."""
    from torchhand.tracking.segmentation import SegmentConfig

    return SegmentConfig.from_dict(d).to_dict() if d else None


def _sequence_task(spec: dict, report) -> dict:
    """Import, track and score one sequence (module docstring); what is complete is kept."""
    from torchhand.app.runner import track_sequences
    from torchhand.data.datasets import FORMATS
    from torchhand.scoring.sequences import evaluate_sequence

    out, seq = spec["out"], spec["seq"]
    name, options = seq.name, spec["options"]
    seq_dir, scores = out / "sequences" / name, out / "scores" / f"{name}.json"
    imported = SequenceLayout(seq_dir).info.is_file()
    if imported and _segmentation(read_sequence_info(seq_dir).segmentation) != _segmentation(spec["segmentation"]):
        raise UsageError(f"{seq_dir}: imported with another segmentation; choose another --out (eval-dataset "
                         "resumes only a run of the same settings)")
    if scores.is_file() and _tracked(out / "track" / name, options.settings()):
        return json.loads(scores.read_text())
    if not imported:
        FORMATS[spec["format"]](seq.src, seq_dir, force=True, segmentation=spec["segmentation"], **seq.options)
    if not _tracked(out / "track" / name, options.settings()):
        res = track_sequences([seq_dir], out / "track", options, names=[name], force=True, progress=False,
                              on_frames=lambda n: report("frames", n))[0]
        if res["status"] != "ok":
            raise UsageError(f"tracking failed: {res.get('error')}")  # the data's, as the runner found it
    result = evaluate_sequence(out / "track" / name, seq_dir, with_penetration=False)
    scores.parent.mkdir(parents=True, exist_ok=True)
    _write_atomic(scores, json.dumps(result))
    return result


def _row(seq: DatasetSequence, result) -> dict:
    if isinstance(result, TaskFailure):
        return {"sequence": seq.name, "source": str(seq.src), "status": "failed", "error": result.error}
    return {"sequence": seq.name, "source": str(seq.src), "status": "ok", "frames": result["frames"],
            **{k: result.get(k) for k in JOINT_KEYS}, "lost_frames": result.get("lost_frames")}


def evaluate_dataset(name: str, root, split: str, out, options: Optional[TrackOptions] = None, workers: int = 1,
                     ray: Optional[str] = None, retries: int = 2, threads: int = 1, segmentation: Optional[Dict] = None,
                     cameras: Optional[List[str]] = None, progress: bool = True) -> dict:
    """Import, track and score every sequence of a split (module docstring); ``cameras``
    (DexYCB): the serials of every sequence instead of the split's. Returns and writes
    ``DIR/results.json``: ``{"dataset", "split", "sequences": [rows], "overall", "failed"}``."""
    options = options or TrackOptions()
    seqs = split_sequences(name, root, split)
    if cameras is not None:
        if name != "dexycb":
            raise UsageError(f"--cameras selects DexYCB's cameras; {name} has none to select")
        seqs = [s._replace(options={**s.options, "cameras": list(cameras)}) for s in seqs]
    if not seqs:
        raise UsageError(f"--split {split}: no sequences of {name} in {root}")
    names = [s.name for s in seqs]
    if len(set(names)) != len(names):
        raise UsageError(f"--split {split}: two sequences have the same name ({names})")
    out = Path(out).resolve()
    (out / "sequences").mkdir(parents=True, exist_ok=True)
    specs = [{"out": out, "seq": s, "format": name, "options": options, "segmentation": segmentation} for s in seqs]
    bar = tqdm(total=len(seqs), desc=f"eval-dataset {name} {Path(split).name}", unit="seq", disable=not progress)
    try:
        results = run_tasks(_sequence_task, specs, workers, ray, retries, threads,
                            lambda e: bar.update(1) if e[1] == "done" else None)
    finally:
        bar.close()
    good = [r for r in results if not isinstance(r, TaskFailure)]
    pooled = summarize(good) if good else {}
    table = {"dataset": name, "split": split, "root": str(Path(root).resolve()),
             "sequences": [_row(s, r) for s, r in zip(seqs, results)],
             "overall": {"sequences": len(good), "frames": pooled.get("frames", 0),
                         **{k: pooled.get(k) for k in JOINT_KEYS}, "lost_frames": pooled.get("lost_frames")},
             "failed": len(results) - len(good)}
    _write_atomic(out / RESULTS_NAME, json.dumps(table, indent=2))
    return table
