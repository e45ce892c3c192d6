"""The tasks of a tracking run (:func:`~torchhand.app.scaleout.track_many`): same-scene
sequences in batches, and sequences longer than ``--chunk`` frames split into chunks
that are tracked as tasks of their own and written once all are in
(docs/scaleout.md)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Dict, List, Optional, Sequence

from torchhand.app.options import TrackOptions
from torchhand.core.errors import failure_text

__all__ = ["CHUNK_OVERLAP", "chunk_windows", "plan_tasks", "task_length", "write_chunked"]

#: Frames each chunk after the first tracks before its own (``--chunk-overlap``): the
#: automatic initialisation's pose settles within a few frames on the thesis sequences.
CHUNK_OVERLAP = 10


def chunk_windows(frames: int, chunk: int, overlap: int) -> List[tuple]:
    """(start, keep, stop) of each chunk of a sequence of ``frames`` frames: a chunk keeps
    frames [keep, stop) and tracks from ``start`` = ``keep - overlap`` (0 for the first),
    re-tracking the previous chunk's last ``overlap`` frames from its own automatic
    initialisation to reach ``keep`` with a settled pose. ``ceil(frames / chunk)``
    chunks (fewer where the overlap would leave a chunk no frame of its own), each
    tracking nearly the same number of frames (balanced work: the first keeps
    ``overlap`` more than the others)."""
    n = max(1, math.ceil(frames / chunk))
    while n > 1 and (frames - overlap) / n < 1:
        n -= 1
    tracked = (frames + (n - 1) * overlap) / n
    stops = [round(tracked + j * (tracked - overlap)) for j in range(n - 1)] + [frames]
    keeps = [0] + stops[:-1]
    return [(max(0, k - overlap), k, e) for k, e in zip(keeps, stops)]


def task_length(task: tuple, infos: Sequence) -> int:
    """Frames a task tracks: its chunk's, or its longest sequence's."""
    members, window = task
    return window[2] - window[0] if window else max(infos[k].frames for k in members)


def plan_tasks(infos: Sequence, skip, batch: int, chunk: Optional[int], overlap: int) -> tuple:
    """(tasks, chunked): the tasks, each (its sequences, its chunk's window or None), the
    longest first; and each chunked sequence's windows. Sequences in ``skip`` are left
    out; same-scene ones are batched by ``batch``; those longer than ``chunk`` frames
    are split (:func:`chunk_windows`)."""
    groups: Dict[tuple, List[int]] = {}
    chunked: Dict[int, List[tuple]] = {}
    for k, info in enumerate(infos):
        if k in skip:
            continue
        if chunk is not None and info.frames > chunk:
            chunked[k] = chunk_windows(info.frames, chunk, overlap)
        else:
            groups.setdefault(tuple(info.models), []).append(k)
    tasks = [(members[j : j + batch], None) for members in groups.values() for j in range(0, len(members), batch)]
    tasks += [([k], w) for k, windows in chunked.items() for w in windows]
    # the longest tasks first (stable: equal ones keep their order), so that no worker
    # starts a long sequence while the others finish: the run ends sooner, whatever
    # the number of workers, and each task still computes the same
    tasks.sort(key=lambda t: -task_length(t, infos))
    return tasks, chunked


def write_chunked(root: Path, target: Path, options: TrackOptions, parts: list, settings: dict, force: bool,
                  name: str) -> dict:
    """Write a sequence from its tracked chunks
    (:func:`~torchhand.app.runner.write_chunks`); its summary. The write fails the
    sequence alone, as a task's error fails its task (its
    :func:`~torchhand.core.errors.failure_text` in the summary); the others are written."""
    from torchhand.app.runner import write_chunks

    try:
        return write_chunks(root, target, options, parts, settings, force, name)
    except Exception as err:  # noqa: BLE001 - as a task's own error (scaleout._call)
        error = failure_text(err)
        return {"sequence": name, "status": "failed", "error": error, "frames": 0, "out": None}
