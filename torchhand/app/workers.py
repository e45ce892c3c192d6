"""The local worker processes' server, started as early as a command knows it will need it.

Local workers (``--workers N``) are forked from a server process that imports torch and
torchhand once (:mod:`multiprocessing`'s forkserver, so no worker forks a process that
may hold torch threads). Its imports take seconds (torch, open3d, the runner), as the
command's own do; started when the command line is parsed, before the command imports
anything heavy, the server imports on the other core while the command does, and the
workers start at once when the tasks are submitted. This module imports nothing heavy.
"""

from __future__ import annotations

import multiprocessing
from typing import List, Optional

__all__ = ["worker_context", "start_server", "PRELOAD"]

#: what the server imports once for every worker (the task's own module is added)
PRELOAD = ["torch", "torchhand.app.runner", "torchhand.app.scaleout"]


def worker_context(module: Optional[str] = None):
    """The multiprocessing context of the local workers: the forkserver preloading
    :data:`PRELOAD` (and ``module``, the tasks' module) where there is one, else spawn."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    ctx = multiprocessing.get_context("forkserver")
    preload: List[str] = PRELOAD + ([module] if module and module not in PRELOAD else [])
    ctx.set_forkserver_preload(preload)
    return ctx


def start_server(workers: int, ray: Optional[str] = None) -> bool:
    """Start the workers' server now when a run will use local workers (``workers`` > 1
    without ``ray``); True when it was started (or runs already). A run that needs no
    workers starts nothing."""
    if workers <= 1 or ray is not None or "forkserver" not in multiprocessing.get_all_start_methods():
        return False
    worker_context()
    from multiprocessing import forkserver

    forkserver.ensure_running()
    return True
