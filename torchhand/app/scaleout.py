"""Many sequences at once: tracking and scoring as tasks over local processes or a Ray
cluster, with one progress bar, a summary, retries and resumable output.

The unit of work is a *task*: up to ``batch`` same-scene sequences tracked as one
batch by :func:`~torchhand.app.runner.track_sequences` (or one prediction scored),
submitted longest first to workers started once per run. The
tasks depend only on the sequence list and ``batch``, never on the number of workers,
so a run with any worker count, local or on Ray, computes exactly what the sequential
run computes (the same θ to the last bit on CPU with the same ``--threads``).

- ``workers > 1``: a pool of local processes (forked from a server process that has
  imported torchhand once, or spawned where there is no fork); a worker that dies (killed, out
  of memory) takes its task down with it, and the pool is rebuilt and the unfinished
  tasks resubmitted, up to ``retries`` times each.
- ``ray``: the tasks are Ray tasks (``max_retries=retries``: Ray reruns the task of a
  dead worker). ``"local"`` starts a local Ray instance with ``workers`` CPUs;
  ``"auto"`` joins the running cluster (``ray start``; ``RAY_ADDRESS``); ``HOST:PORT``
  joins that cluster's head, checked first with a socket so that an unreachable
  address fails in seconds with the address named. The workers must see the same
  file system paths (sequence folders and ``--out``) and have torchhand installed.

Every sequence is written to a hidden partial folder and renamed when complete
(:mod:`torchhand.io.output_dir`), so a killed worker or an interrupted run (Ctrl-C)
never leaves a folder that looks finished; the partial folders of a run are removed
when it ends, however it ends. A retried task keeps the folders its killed attempt
finished. ``resume`` skips the sequences whose folders are
complete and were tracked with the same settings (``track_log.json``), and refuses a
folder written by another command or with other settings, naming the difference.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import queue as queue_lib
import socket
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence

import torch
from tqdm import tqdm

from torchhand.core.check import check_int
from torchhand.app.chunks import CHUNK_OVERLAP, chunk_windows, plan_tasks, task_length, write_chunked
from torchhand.app.options import TrackOptions
from torchhand.app.workers import worker_context
from torchhand.core.errors import MissingExtra, failure_text, is_bug
from torchhand.data.layout import TRACK_SUMMARY, OutputLayout, SequenceError, read_sequence_info
from torchhand.io.output_dir import remove_partials
from torchhand.scoring.sequences import EvaluationError, evaluate_sequence, summarize

__all__ = ["TrackJob", "track_many", "chunk_windows", "CHUNK_OVERLAP", "evaluate_pairs", "run_tasks", "read_list",
           "connect_ray", "default_batch", "TaskFailure", "SUMMARY_NAME"]

#: The run summary written into ``--out``: every sequence's status, time and frames.
SUMMARY_NAME = TRACK_SUMMARY


@dataclass(frozen=True)
class TrackJob:
    """What every task of a run is asked: the options that
    :func:`~torchhand.app.runner.track_sequences` takes, and the torch threads of each
    worker (which change no result)."""

    options: TrackOptions = field(default_factory=TrackOptions)
    threads: int = 1

    def __post_init__(self) -> None:
        if not isinstance(self.options, TrackOptions):
            raise TypeError(f"options must be a TrackOptions, got {type(self.options).__name__}")
        check_int(self.threads, "threads", low=1)


@dataclass(frozen=True)
class TaskFailure:
    """A task that raised, or whose worker died more often than it was retried: ``error``
    its :func:`~torchhand.core.errors.failure_text`; ``bug`` True when the task raised a
    bug in torchhand (:func:`~torchhand.core.errors.is_bug`; not a worker that died)."""

    error: str
    bug: bool = False


def default_batch(device: str) -> int:
    """Same-scene sequences per task: 1 on CPU (processes gain ~1.9x on two cores where
    batching gains 1.2x, docs/benchmarks.md), 16 on a GPU (where batching is the gain)."""
    return 1 if str(device) == "cpu" else 16


# ----------------------------------------------------------------------------- tasks


class _Report:
    """Sends a task's events (``start`` with its pid, ``frames`` with a count) to the
    process that runs the tasks; picklable (it holds a queue)."""

    def __init__(self, sink, index: int):
        self.sink, self.index = sink, index

    def __call__(self, kind: str, value, last: bool = False) -> None:
        event = (self.index, kind, value)
        if callable(self.sink):
            self.sink(event)
        elif hasattr(self.sink, "put") and hasattr(self.sink.put, "remote"):  # a Ray event log
            sent = self.sink.put.remote(event)  # fire and forget while the task runs (a task blocked in
            if last:  # ray.get lends its CPU to another task); its last event waits, so that every event
                import ray  # of a finished task has reached the log

                ray.get(sent)
        else:
            self.sink.put(event)


def _call(fn: Callable, arg, report: _Report, threads: int):
    """Run one task in a worker: its threads, its start event, its errors as a value."""
    torch.set_num_threads(max(1, threads))
    report("start", os.getpid())
    try:
        result = fn(arg, report)
    except Exception as err:  # a task's own error is its result; the others go on
        result = TaskFailure(failure_text(err), is_bug(err))
    report("done", None, last=True)
    return result


def run_tasks(fn: Callable, args: Sequence, workers: int = 1, ray: Optional[str] = None, retries: int = 2,
              threads: int = 1, on_event: Optional[Callable[[tuple], None]] = None) -> List:
    """``[fn(a, report) for a in args]``, sequentially, over ``workers`` local processes
    or as Ray tasks (``ray``: ``"local"``, ``"auto"`` or an address; see the module).

    ``fn`` must be importable by the workers (a module-level function); it reports
    progress through ``report(kind, value)``, which reaches ``on_event((index, kind,
    value))`` in this process. A task that raises returns a :class:`TaskFailure`, as
    does one whose worker died more than ``retries`` times. Results are in the order
    of ``args``."""
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"--workers must be an integer >= 1, got {workers!r}")
    if retries < 0:
        raise ValueError(f"--retries must be >= 0, got {retries}")
    handle = on_event or (lambda event: None)
    if ray is not None:
        return _run_ray(fn, args, workers, ray, retries, threads, handle)
    if workers == 1 or len(args) <= 1:
        old = torch.get_num_threads()
        try:
            return [_call(fn, a, _Report(handle, i), threads) for i, a in enumerate(args)]
        finally:
            torch.set_num_threads(old)
    return _run_processes(fn, args, workers, retries, threads, handle)


def _drain(q, handle) -> None:
    while True:
        try:
            handle(q.get_nowait())
        except queue_lib.Empty:
            return
        except (EOFError, OSError, BrokenPipeError):  # the manager went away (interrupted)
            return


def _run_processes(fn, args, workers, retries, threads, handle) -> List:
    # workers fork from a server process that imported torch and the task's module once
    # (no fork of this process, which may hold torch threads; no import per worker); the
    # command line starts it when it parses --workers (torchhand.app.workers)
    ctx = worker_context(fn.__module__)
    results: Dict[int, object] = {}
    attempts = {i: 0 for i in range(len(args))}
    with ctx.Manager() as manager:
        q = manager.Queue()
        pool = ProcessPoolExecutor(max_workers=min(workers, len(args)), mp_context=ctx)
        running: dict = {}
        try:
            running = {pool.submit(_call, fn, args[i], _Report(q, i), threads): i for i in range(len(args))}
            while running:
                done, _ = wait(list(running), timeout=0.1, return_when=FIRST_COMPLETED)
                _drain(q, handle)
                broken = False
                for fut in done:
                    i = running.pop(fut)
                    try:
                        results[i] = fut.result()
                    except BrokenProcessPool:
                        broken = True
                        attempts[i] += 1
                if broken:  # a worker died: every task it shared the pool with is resubmitted
                    lost = sorted(set(running.values()) | {i for i in attempts if i not in results})
                    for fut in running:
                        fut.cancel()
                    pool.shutdown(wait=True, cancel_futures=True)
                    pool = ProcessPoolExecutor(max_workers=min(workers, len(args)), mp_context=ctx)
                    running = {}
                    for i in lost:
                        if attempts[i] > retries:
                            results[i] = TaskFailure(f"its worker process died {attempts[i]} times")
                        else:
                            running[pool.submit(_call, fn, args[i], _Report(q, i), threads)] = i
            _drain(q, handle)
            pool.shutdown(wait=True)
        finally:
            if running:  # Ctrl-C or an error here: stop the workers now
                for p in list((getattr(pool, "_processes", None) or {}).values()):
                    if p.is_alive():
                        p.terminate()
                pool.shutdown(wait=False, cancel_futures=True)
    return [results[i] for i in range(len(args))]


def connect_ray(address: str, num_cpus: int, timeout_s: float = 5.0) -> bool:
    """Connect to (or start, ``"local"``) a Ray cluster; True when this call started it.
    An address that does not answer within ``timeout_s`` is an error naming it."""
    try:
        import ray
    except ImportError:
        raise MissingExtra("--ray", "ray") from None
    if ray.is_initialized():
        return False
    if address == "local":
        ray.init(num_cpus=num_cpus, include_dashboard=False, log_to_driver=False, configure_logging=False)
        return True
    if address != "auto":
        hostport = address.split("://", 1)[-1]
        host, _, port = hostport.rpartition(":")
        if not host or not port.isdigit():
            raise ValueError(f"--ray {address}: expected auto, or HOST:PORT of a Ray head (e.g. 10.0.0.1:6379)")
        try:
            socket.create_connection((host, int(port)), timeout=timeout_s).close()
        except OSError as err:
            raise ConnectionError(f"--ray {address}: no Ray cluster answers at {hostport} within {timeout_s:g} s "
                                  f"({err})") from None
    try:
        ray.init(address=address, log_to_driver=False, configure_logging=False)
    except ConnectionError as err:
        raise ConnectionError(f"--ray {address}: cannot connect to a Ray cluster ({err})") from None
    return False


def _run_ray(fn, args, workers, address, retries, threads, handle) -> List:
    started = connect_ray(address, workers)
    import ray

    refs: Dict[object, int] = {}
    try:
        log = ray.remote(num_cpus=0)(_EventLog).remote()
        task = ray.remote(num_cpus=threads, max_retries=retries)(_call)
        refs = {task.remote(fn, a, _Report(log, i), threads): i for i, a in enumerate(args)}
        results: Dict[int, object] = {}
        pending = list(refs)
        while pending:
            done, pending = ray.wait(pending, num_returns=1, timeout=0.1)
            _drain_ray(log, handle)
            for ref in done:
                try:
                    results[refs[ref]] = ray.get(ref)
                except ray.exceptions.RayError as err:  # retries exhausted, or the task could not run
                    results[refs[ref]] = TaskFailure(f"{type(err).__name__}: {err}")
        _drain_ray(log, handle)
        return [results[i] for i in range(len(args))]
    finally:
        for ref in refs:  # Ctrl-C or an error here: stop what still runs
            try:
                ray.cancel(ref, force=True)
            except Exception:  # already finished
                pass
        if started:
            ray.shutdown()


class _EventLog:
    """The events of Ray tasks, as a synchronous single-threaded actor: it runs the calls
    of one submitter in their order, so a task's ``start`` comes before its ``frames``
    (Ray's own queue is an async actor, which does not keep that order)."""

    def __init__(self):
        self.events: List[tuple] = []

    def put(self, event: tuple) -> None:
        self.events.append(event)

    def take(self) -> List[tuple]:
        events, self.events = self.events, []
        return events


def _drain_ray(log, handle) -> None:
    import ray

    for event in ray.get(log.take.remote()):
        handle(event)


# -------------------------------------------------------------------------- tracking


def read_list(path, columns: int = 1) -> List[tuple]:
    """The rows of a list file (``--list``): one sequence (or ``columns`` paths) per
    line, blank lines and ``#`` comments skipped; relative paths are relative to the
    list file's folder."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"--list {path}: no such file")
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        if len(parts) != columns:
            raise ValueError(f"--list {path} line {n}: expected {columns} path(s), got {len(parts)}: {line!r}")
        rows.append(tuple(p if Path(p).is_absolute() else path.parent / p for p in parts))
    if not rows:
        raise ValueError(f"--list {path}: no paths in it")
    return [tuple(Path(p) for p in r) for r in rows]


def _signature(target: Path) -> Optional[tuple]:
    """Which write of ``target``'s track log is there (inode, mtime), or None."""
    try:
        st = OutputLayout(target).track_log.stat()
    except OSError:
        return None
    return st.st_ino, st.st_mtime_ns


def _track_task(spec: dict, report: _Report):
    from torchhand.app.runner import track_chunk, track_sequences

    job: TrackJob = spec["job"]
    if "window" in spec:  # one chunk of a sequence: its frames, written by track_many
        start, keep, stop = spec["window"]
        return track_chunk(spec["roots"][0], job.options, start, stop, keep, on_frames=lambda n: report("frames", n))
    # A worker that dies after a sequence's folder was renamed complete, before the task
    # returned, leaves that folder to the task's retry: it is kept, not tracked again. A
    # folder that was there before the run (--force replaces it) is never kept.
    finished = {}
    for j, name in enumerate(spec["names"]):
        if _signature(spec["out"] / name) not in (None, spec["before"][j]):
            try:
                finished[j] = dict(_complete(spec["out"] / name, spec["settings"]), resumed=False)
            except ValueError:  # not this run's: track_sequences refuses it, naming it
                pass
    todo = [j for j in range(len(spec["names"])) if j not in finished]
    if todo:
        tracked = track_sequences([spec["roots"][j] for j in todo], spec["out"], job.options,
                                  names=[spec["names"][j] for j in todo], force=spec["force"], progress=False,
                                  on_frames=lambda n: report("frames", n))
        finished.update(zip(todo, tracked))
    return [finished[j] for j in range(len(spec["names"]))]


def _differences(old: dict, new: dict, prefix: str = "") -> List[str]:
    out = []
    for k in sorted(set(old) | set(new)):
        a, b = old.get(k), new.get(k)
        if isinstance(a, dict) and isinstance(b, dict):
            out += _differences(a, b, f"{prefix}{k}.")
        elif a != b:
            out.append(f"{prefix}{k}: {a!r} there, {b!r} now")
    return out


def _complete(target: Path, settings: dict) -> Optional[dict]:
    """The summary of a finished sequence folder tracked with ``settings``; errors for a
    folder of another command or other settings."""
    log = OutputLayout(target).track_log
    if not log.is_file():
        raise ValueError(f"--resume: {target} was not written by torchhand track (no track_log.json); "
                         "choose another --out")
    try:
        d = json.loads(log.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"--resume: {log} is not valid JSON ({err})") from None
    old = d.get("settings")
    if old is None or old.get("command") != "track":
        raise ValueError(f"--resume: {target} was written by another command or an older torchhand (its "
                         "track_log.json records no track settings); choose another --out")
    diff = _differences(old, settings)
    if diff:
        raise ValueError(f"--resume: {target} was tracked with other settings: " + "; ".join(diff))
    frames = d.get("frames", [])
    return {"sequence": d.get("sequence", target.name), "status": "ok", "resumed": True, "frames": len(frames),
            "out": str(target), "seconds_per_frame": sum(f.get("seconds", 0.0) for f in frames) / max(len(frames), 1),
            "flagged_frames": sum(not f.get("valid", True) for f in frames),
            "reinitialized_frames": sum(bool(f.get("reinitialized")) for f in frames)}


def _read_infos(roots: List[Path], options: TrackOptions) -> list:
    """Every sequence's ``sequence.json`` (the scene of ``options.models`` where given);
    all unreadable folders are named in one error."""
    if not roots:
        raise ValueError("no sequence folders given (DIR... or --list FILE)")
    infos, bad = [], []
    for r in roots:
        try:
            infos.append(read_sequence_info(r))
        except SequenceError as err:
            bad.append(str(err))
    if bad:
        raise ValueError(f"{len(bad)} of {len(roots)} sequence folders cannot be read, nothing was tracked:\n  "
                         + "\n  ".join(bad))
    if options.models is not None:
        infos = [dataclasses.replace(i, models=list(options.models)) for i in infos]
    return infos


def _finished(out: Path, names: List[str], settings: dict, resume: bool, force: bool) -> Dict[int, dict]:
    """The summaries of the sequences whose output folders are complete with these
    settings (``resume``); errors for a non-empty folder that is neither kept
    (``resume``) nor replaced (``force``)."""
    done: Dict[int, dict] = {}
    taken = []
    for k, n in enumerate(names):
        target = out / n
        if target.exists() and (not target.is_dir() or any(target.iterdir())):
            if resume:
                done[k] = _complete(target, settings)
            elif not force:
                taken.append(str(target))
    if taken:
        raise FileExistsError(f"{len(taken)} output folders are not empty: {', '.join(taken)}; choose another --out, "
                              "pass --resume to keep the finished ones, or --force to replace them")
    return done


def track_many(roots: Sequence, out, job: Optional[TrackJob] = None, workers: int = 1, ray: Optional[str] = None,
               batch: Optional[int] = None, resume: bool = False, force: bool = False, retries: int = 2,
               progress: bool = True, on_event: Optional[Callable[[tuple], None]] = None,
               chunk: Optional[int] = None, chunk_overlap: int = CHUNK_OVERLAP) -> dict:
    """``torchhand track DIR... [--workers N | --ray [ADDRESS]] [--resume] [--chunk N]``:
    track sequence folders as tasks (see the module), with one progress bar over all
    their frames, and write ``<out>/track_summary.json``.

    ``chunk``: a sequence longer than ``chunk`` frames is split into chunks of about
    ``chunk`` frames (:func:`~torchhand.app.chunks.chunk_windows`), each a task of its
    own, so that the workers share one long recording; each chunk after the first starts ``chunk_overlap`` frames early from the
    automatic initialisation (hands-only scenes with depth), and the sequence is
    written once all its chunks are tracked. This is not identical to one pass: each
    chunk forgets the previous pose, a chunk whose start cannot be initialised fails the
    sequence, and frames near a chunk's start are tracked from a fresh search (the
    overlap lets it settle before its frames are kept). The chunking is part of the
    run's settings (``track_log.json``, ``--resume``).

    Every folder is checked before any work starts (all unreadable ones are named in
    one error), as is every existing output folder (refused unless ``force`` or, with
    ``resume``, complete with the same settings). Returns the summary: ``sequences``
    (each one's status, error, frames, time, output), ``failed``, ``frames``,
    ``seconds``, and the run's ``settings``."""
    from torchhand.app.runner import output_names

    t0 = time.perf_counter()
    job = job or TrackJob()
    if resume and force:
        raise ValueError("--resume keeps finished sequences and --force replaces them: give one")
    if batch is not None and (isinstance(batch, bool) or not isinstance(batch, int) or batch < 1):
        raise ValueError(f"--batch must be an integer >= 1, got {batch!r}")
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"--workers must be an integer >= 1, got {workers!r}")
    if chunk is not None:
        check_int(chunk, "--chunk", low=1)
        check_int(chunk_overlap, "--chunk-overlap", low=0)
    roots = [Path(r).resolve() for r in roots]
    options = job.options
    infos = _read_infos(roots, options)
    out = Path(out).resolve()
    names = output_names(infos)
    settings = options.settings()
    if chunk is not None:
        settings = {**settings, "chunk": chunk, "chunk_overlap": chunk_overlap}
    done = _finished(out, names, settings, resume, force)
    remove_partials(out, set(names))  # what killed runs left: never results
    batch = batch or default_batch(options.device)
    tasks, chunked = plan_tasks(infos, done, batch, chunk, chunk_overlap)
    specs = [{"roots": [roots[k] for k in t], "names": [names[k] for k in t], "out": out, "force": force, "job": job,
              "settings": settings, "before": [_signature(out / names[k]) for k in t], **({"window": w} if w else {})}
             for t, w in tasks]
    total = sum(task_length(t, infos) * len(t[0]) for t in tasks)
    n_seq = sum(len(t) for t, w in tasks if w is None) + len(chunked)
    bar = tqdm(total=total, desc=f"track {n_seq} sequence{'s' if n_seq != 1 else ''}", unit="frame",
               disable=not progress)

    def handle(event: tuple) -> None:
        if event[1] == "frames":
            bar.update(event[2])
        if on_event is not None:
            on_event(event)

    try:
        results = run_tasks(_track_task, specs, workers, ray, retries, job.threads, handle)
        summaries = _collect(tasks, results, chunked, dict(done), roots, out, names, job.options, settings, force)
    finally:
        bar.close()
        remove_partials(out, set(names))
    for k in summaries:
        summaries[k]["source"] = str(roots[k])
    seqs = [summaries[k] for k in range(len(roots))]
    summary = {"command": "track", "settings": settings, "workers": workers, "ray": ray, "batch": batch,
               "tasks": len(tasks), "sequences": seqs, "failed": sum(s["status"] != "ok" for s in seqs),
               "resumed": len(done), "frames": sum(infos[k].frames for k in range(len(roots)) if k not in done),
               "chunked": len(chunked), "seconds": time.perf_counter() - t0}
    out.mkdir(parents=True, exist_ok=True)
    (out / SUMMARY_NAME).write_text(json.dumps(_jsonable(summary), indent=2))
    return summary


def _collect(tasks: list, results: list, chunked: dict, summaries: Dict[int, dict], roots: list, out: Path,
             names: list, options: TrackOptions, settings: dict, force: bool) -> Dict[int, dict]:
    """Every sequence's summary from its task's result; a chunked sequence written once
    all its chunks are in (failed with the first failing chunk's error)."""
    pieces: Dict[int, list] = {k: [] for k in chunked}
    for (t, w), res in zip(tasks, results):
        if w is not None:
            pieces[t[0]].append(res)
            continue
        for j, k in enumerate(t):
            summaries[k] = _failed_task(names[k], res) if isinstance(res, TaskFailure) else res[j]
    for k, parts in pieces.items():
        bad = [p for p in parts if isinstance(p, TaskFailure)]
        summaries[k] = (_failed_task(names[k], bad[0]) if bad else
                        write_chunked(roots[k], out / names[k], options, parts, settings, force, names[k]))
    return summaries


def _failed_task(name: str, failure: TaskFailure) -> dict:
    return {"sequence": name, "status": "failed", "error": failure.error, "frames": 0, "out": None}


def _jsonable(x):
    """JSON without NaN (null instead) and with paths as strings."""
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, Path):
        return str(x)
    return x


# --------------------------------------------------------------------------- scoring


def _evaluate_task(pair: tuple, report: _Report) -> dict:
    pred, gt, with_penetration = pair
    return evaluate_sequence(pred, gt, with_penetration=with_penetration)


def evaluate_pairs(pairs: Sequence[tuple], workers: int = 1, ray: Optional[str] = None,
                   with_penetration: bool = True, progress: bool = True, retries: int = 2) -> dict:
    """Score (prediction, ground truth) folder pairs as tasks (sequentially, over local
    processes or on Ray) and pool them (:func:`~torchhand.scoring.sequences.summarize`).
    Pairs that cannot be scored are listed in ``failed`` (prediction, error: a bug's with
    its traceback); the others are scored. When none can be: ``RuntimeError`` when some
    task hit a bug in torchhand (its traceback in the message), else
    :class:`EvaluationError`."""
    pairs = [(Path(p).resolve(), Path(g).resolve(), with_penetration) for p, g in pairs]
    bar = tqdm(total=len(pairs), desc="eval", unit="seq", disable=not progress)
    try:
        results = run_tasks(_evaluate_task, pairs, workers, ray, retries, 1,
                            lambda e: bar.update(1) if e[1] == "done" else None)
    finally:
        bar.close()
    failures = [(str(p[0]), r) for p, r in zip(pairs, results) if isinstance(r, TaskFailure)]
    failed = [{"prediction": p, "error": r.error} for p, r in failures]  # a bug's traceback kept
    good = [r for r in results if not isinstance(r, TaskFailure)]
    if not good:
        text = "no prediction could be scored: " + "; ".join(f"{p}: {r.error}" for p, r in failures)
        if any(r.bug for _, r in failures):
            raise RuntimeError(text)  # not the user's to fix: the command line reports it as a bug
        raise EvaluationError(text)
    result = summarize(good)
    result["failed"] = failed
    return result
