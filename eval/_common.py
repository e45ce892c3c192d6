"""Small helpers shared by the benchmark scripts (timing, JSON output)."""

from __future__ import annotations

import json
import platform
import time
from pathlib import Path
from typing import Callable, List

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
