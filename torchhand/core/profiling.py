"""Stage timers for profiling the tracker against its floor (docs/benchmarks.md).

The library marks its stages with :func:`stage`; nothing is timed unless a
:func:`recording` is open, and then each stage is also a ``torch.profiler``
``record_function`` range, so the same names show in a torch profiler trace::

    with stage("render", work=lambda: (flops, bytes)):   # free when not recording
        ...

    with recording() as rec:                             # eval/bench_track.py --profile
        tracker.track(...)
    rec.totals()     # {path: StageTotal(calls, seconds, flops, bytes)}

Stages nest: a stage's path is the names of the stages open around it joined by
``/`` (``frame/iteration/lm/solve``), and its time includes its children's. ``work``
gives the arithmetic (flops) and the memory traffic (bytes) the stage cannot avoid,
the basis of its floor; it is called only while recording, so estimating it costs
nothing otherwise. On CUDA, ``recording(synchronize=True)`` synchronises at each
stage's ends, so that the times are the device's (and the stages no longer overlap).
"""

from __future__ import annotations

import contextlib
import time
from typing import Callable, Dict, Iterator, List, NamedTuple, Optional, Tuple

import torch

__all__ = ["stage", "recording", "Recorder", "StageTotal", "active"]

_NULL = contextlib.nullcontext()
_recorder: Optional["Recorder"] = None


class StageTotal(NamedTuple):
    """A stage's totals: calls, seconds (wall, children included), flops and bytes (the
    sums of its ``work`` estimates; 0 where none was given)."""

    calls: int
    seconds: float
    flops: float
    bytes: float


class Recorder:
    """The stages timed during one :func:`recording`: ``events`` is a list of (path,
    seconds, flops, bytes), in the order the stages ended."""

    def __init__(self, synchronize: bool = False):
        self.synchronize = bool(synchronize)
        self.events: List[Tuple[str, float, float, float]] = []
        self._open: List[str] = []

    @contextlib.contextmanager
    def _stage(self, name: str, work: Optional[Callable[[], Tuple[float, float]]]) -> Iterator[None]:
        self._open.append(name)
        path = "/".join(self._open)
        try:
            with torch.profiler.record_function(name):
                self._sync()
                t0 = time.perf_counter()
                yield
                self._sync()
                seconds = time.perf_counter() - t0
            flops, nbytes = work() if work is not None else (0.0, 0.0)
            self.events.append((path, seconds, float(flops), float(nbytes)))
        finally:
            self._open.pop()

    def _sync(self) -> None:
        if self.synchronize and torch.cuda.is_available():
            torch.cuda.synchronize()

    def totals(self) -> Dict[str, StageTotal]:
        """Per stage path, its totals over the recording (paths in first-seen order)."""
        out: Dict[str, list] = {}
        for path, s, f, b in self.events:
            t = out.setdefault(path, [0, 0.0, 0.0, 0.0])
            t[0] += 1
            t[1] += s
            t[2] += f
            t[3] += b
        return {p: StageTotal(*t) for p, t in out.items()}


def active() -> bool:
    """Whether a :func:`recording` is open."""
    return _recorder is not None


def stage(name: str, work: Optional[Callable[[], Tuple[float, float]]] = None):
    """A context manager timing the enclosed work as stage ``name`` while a
    :func:`recording` is open (a shared no-op context otherwise). ``work``: a callable
    giving (flops, bytes) of the stage's unavoidable work, called only while recording."""
    rec = _recorder
    if rec is None:
        return _NULL
    return rec._stage(name, work)


@contextlib.contextmanager
def recording(synchronize: bool = False) -> Iterator[Recorder]:
    """Record the stages run inside the block (not re-entrant: one recording at a
    time, in the thread that opened it)."""
    global _recorder
    if _recorder is not None:
        raise RuntimeError("a stage recording is open already")
    _recorder = Recorder(synchronize)
    try:
        yield _recorder
    finally:
        _recorder = None
