"""Small helpers shared by the benchmark scripts (timing, JSON output)."""

from __future__ import annotations

import contextlib
import json
import platform
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Callable, List, Sequence

import torch


def median_seconds(fn: Callable[[], object], repeats: int, warmup: int = 1) -> float:
    """Median wall time of ``fn()`` over ``repeats`` runs after ``warmup`` runs."""
    for _ in range(warmup):
        fn()
    times: List[float] = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    times.sort()
    return times[len(times) // 2]


def run_together(commands: Sequence[Sequence[str]]) -> float:
    """Start every command at once as its own process and wait for all: the wall
    seconds until the last one ends. A command that fails raises with its stderr's end.

    Two independent commands, each on half the work, side by side with one command on
    all of it, measure what two cores give a workload when the processes share nothing
    but the machine (its memory and caches, a neighbour's load): the reference for a
    scale-out's speed-up, apart from how the scale-out distributes the work."""
    with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as stack:
        logs = [stack.enter_context(open(Path(tmp) / f"stderr{k}", "w+")) for k in range(len(commands))]
        procs = []  # stderr to files: pipes could fill and block
        try:
            t0 = time.perf_counter()
            for cmd, log in zip(commands, logs):
                procs.append(subprocess.Popen([str(c) for c in cmd], stdout=subprocess.DEVNULL, stderr=log))
            codes = [p.wait() for p in procs]
            wall = time.perf_counter() - t0
        finally:  # an error or Ctrl-C leaves no process running
            for p in procs:
                if p.poll() is None:
                    p.kill()
                    p.wait()
        for cmd, log, code in zip(commands, logs, codes):
            if code != 0:
                log.seek(0)
                raise RuntimeError(f"{' '.join(map(str, cmd))} exited {code}:\n{log.read()[-2000:]}")
    return wall


def set_threads(n: int) -> None:
    """torch CPU threads for a benchmark (recorded by machine())."""
    torch.set_num_threads(max(1, n))


def machine() -> dict:
    return {"cpu_threads": torch.get_num_threads(), "torch": torch.__version__, "python": platform.python_version()}


def write_json(path: Path, result: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))


def demo_scene():
    """The shipped demo motion: (model names, theta (N, D), Scene, thesis camera)."""
    from torchhand.geometry.camera import kinect_camera
    from torchhand.io.assets import load_demo_motion
    from torchhand.model.scene import Scene

    names, theta = load_demo_motion()
    return names, theta, Scene.from_names(names), kinect_camera()
