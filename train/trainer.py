"""The one training loop of every detector in ``train/``.

A detector is a :class:`Task`: its config (a :class:`RunConfig` subclass), its network,
its rendered datasets, one step's batch, its loss, its validation and its results. The
loop, the same for all of them, is :func:`train`; the command line around it (run
folder, ``--config``, ``--resume``, ``--force``, ``--stop-at``, ``done.json``) is
:func:`main`. A detector's module is then a task and a two-line ``main``::

    def main(argv=None) -> int:
        return trainer.main(SalientTask, argv, __doc__)

The loop trains with AdamW and a one-cycle schedule, shows a tqdm bar, appends a
record to ``RUN/log.jsonl`` and writes an atomic checkpoint every ``checkpoint_every``
steps. ``--resume`` continues exactly where the last checkpoint stopped (model,
optimizer, scheduler, RNG states, step) and refuses a config that differs from the
run's ``config.json``. A finished or started run is never overwritten without ``--force``.

Distributed data-parallel training runs one process per rank under torchrun (gloo on
CPU, nccl with SyncBatchNorm on CUDA, one GPU per rank). Every rank draws the same
batch from one generator seeded alike and keeps only its share of it
(:meth:`Task.batch` ``part``); :meth:`Task.loss` normalises by the whole batch, so the
sum of the ranks' losses is the single-process loss. Rank 0 builds the datasets first
(the others then read its cache), writes the log, the checkpoints and the results; a
resume is exact for the same world size.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import torch
import torch.distributed as dist
from tqdm import tqdm

REPO = Path(__file__).resolve().parents[1]
DEFAULT_HIA_ROOT = REPO.parent / "shared" / "data" / "hands_in_action"


@dataclass
class RunConfig:
    """The fields of every training run (``--config`` JSON overrides fields); a task's
    config subclasses it with its own."""

    seed: int = 0
    steps: int = 2500
    batch_size: int = 16
    lr: float = 4e-3
    weight_decay: float = 1e-4
    checkpoint_every: int = 250
    threads: int = 2
    # --- fine-tuning: start from these weights (a ``net.save`` file) instead of random
    init_weights: str = ""


class Task:
    """What a detector adds to the loop; subclass it and set ``name`` and ``config_type``.

    The loop calls, in this order: ``build_net`` (after seeding, so a network's random
    initialisation is part of the run), then per step ``batch`` and ``loss``; every
    fourth checkpoint and at the end ``validate``; and once trained ``finish``.
    """

    #: label of the progress bar, ``train <name>``
    name: str = "task"
    #: the task's config dataclass, a subclass of :class:`RunConfig`
    config_type: type = RunConfig
    #: what one sample of a batch is, in the DDP message ``2 ranks of 8 <sample> each``
    sample: str = "samples"

    def __init__(self, cfg: RunConfig):
        self.cfg = cfg

    def check_config(self, cfg: RunConfig) -> None:
        """Raise ValueError naming the bad field; by default every config is accepted."""

    def build_net(self) -> torch.nn.Module:
        """A fresh network with ``.save(path)``, ``.config`` and a classmethod
        ``load(path)`` returning a network of equal ``.config``."""
        raise NotImplementedError

    def datasets(self, hia_root: Path, cache: Path) -> tuple:
        """(train, val), built once and cached under ``cache``."""
        raise NotImplementedError

    def batch(self, data, g: torch.Generator, part: tuple) -> tuple:
        """CPU tensors of one step's batch. ``part = (rank, world)``: draw from ``g`` the
        whole batch (``cfg.batch_size``, the same on every rank), return the rank's
        contiguous ``batch_size / world`` share of it."""
        raise NotImplementedError

    def loss(self, model: torch.nn.Module, batch: tuple, device: torch.device, size: int) -> tuple:
        """(loss, parts): the rank's loss normalised by the whole batch (all-reduce the
        normalisers when ``size > 1``), so that the ranks' losses sum to the batch loss;
        ``parts`` maps log names to detached scalar tensors of the same kind, ``loss`` first."""
        raise NotImplementedError

    def validate(self, net: torch.nn.Module, val) -> dict:
        """name -> float on the validation data, added to the log record."""
        return {}

    def finish(self, net: torch.nn.Module, out: Path, val) -> dict:
        """Write the trained weights (and their export) into ``out``; return the fields
        of ``done.json`` after ``steps``."""
        raise NotImplementedError

    def start_from(self, net: torch.nn.Module, start: torch.nn.Module, path: str) -> None:
        """Put the weights of ``start`` (read from ``init_weights``, ``path``) into the
        fresh ``net``; by default the two must be the same network."""
        if start.config != net.config:
            raise SystemExit(f"{path}: network {start.config} differs from the config's {net.config}")
        net.load_state_dict(start.state_dict())

    def describe_data(self, train, val) -> str:
        """One line on the datasets, e.g. ``frames: 1060 train, 210 val``."""
        return ""

    def data_fields(self, train, val) -> dict:
        """Fields of ``done.json`` on the datasets, after the timings; none by default."""
        return {}


# --------------------------------------------------------------------------- config


def load_config(config_type: type, path: Optional[Path]) -> RunConfig:
    """Defaults of ``config_type`` overridden by the JSON object in ``path``; unknown
    fields are an error naming them."""
    cfg = config_type()
    if path is None:
        return cfg
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise SystemExit(f"{path}: cannot read the config ({e})")
    if not isinstance(data, dict):
        raise SystemExit(f"{path}: the config must be a JSON object of {config_type.__name__} fields")
    known = {f.name for f in dataclasses.fields(config_type)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise SystemExit(f"{path}: unknown config field(s) {unknown}; known fields: {sorted(known)}")
    return dataclasses.replace(cfg, **data)


def checked_config(task_type: type, path: Optional[Path]) -> RunConfig:
    """:func:`load_config` of the task's config, then its :meth:`Task.check_config`; a
    ValueError becomes an exit naming the file."""
    cfg = load_config(task_type.config_type, path)
    try:
        if cfg.init_weights and not Path(cfg.init_weights).is_file():
            raise ValueError(f"init_weights: {cfg.init_weights} not found (the run that writes it comes first)")
        task_type(cfg).check_config(cfg)
    except ValueError as e:
        raise SystemExit(f"{path if path is not None else 'the default config'}: {e}")
    return cfg


# ------------------------------------------------------------------------ the loop


def _rng_state(g: torch.Generator) -> dict:
    """The generators of a run: the sampler's, torch's and numpy's global ones (numpy's
    key and, under ``numpy_pos``, its position and cached Gaussian)."""
    _, keys, pos, has_gauss, gauss = np.random.get_state()
    return {"sampler": g.get_state(), "torch": torch.get_rng_state(), "numpy": keys,
            "numpy_pos": (pos, has_gauss, gauss)}


def world() -> tuple:
    """(rank, world size, device) of this process: a torchrun rank joins the process
    group here (gloo on CPU, nccl on CUDA: one GPU per local rank); a plain run is
    (0, 1, cpu)."""
    size = int(os.environ.get("WORLD_SIZE", "1"))
    if size <= 1:
        return 0, 1, torch.device("cpu")
    cuda = torch.cuda.is_available()
    if not dist.is_initialized():
        dist.init_process_group("nccl" if cuda else "gloo")
    device = torch.device("cpu")
    if cuda:
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(device)
    return dist.get_rank(), dist.get_world_size(), device


def barrier(size: int) -> None:
    """Wait for every rank (nothing to wait for in a plain run)."""
    if size > 1:
        dist.barrier()


def _start(task: Task, out: Path, resume: bool, rank: int, size: int) -> tuple:
    """(net, optimizer, scheduler, sampler generator, step): seeded fresh, from
    ``init_weights``, or as ``out/checkpoint.pt`` left them when ``resume``."""
    cfg = task.cfg
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    g = torch.Generator().manual_seed(cfg.seed)
    net = task.build_net()
    if cfg.init_weights:
        task.start_from(net, type(net).load(cfg.init_weights), cfg.init_weights)
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=cfg.lr, total_steps=cfg.steps, pct_start=0.1)
    step = 0
    ckpt = out / "checkpoint.pt"
    if resume and ckpt.is_file():
        state = torch.load(ckpt, weights_only=False, map_location="cpu")
        net.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        sched.load_state_dict(state["scheduler"])
        g.set_state(state["rng"]["sampler"])
        torch.set_rng_state(state["rng"]["torch"])
        # checkpoints without numpy_pos were written by tasks that never drew from numpy's
        # global generator after seeding it: its position was 624
        np.random.set_state(("MT19937", state["rng"]["numpy"], *state["rng"].get("numpy_pos", (624, 0, 0.0))))
        step = state["step"]
        was = state.get("world_size", 1)
        if rank == 0:
            print(f"resuming {out} at step {step}" + ("" if was == size else
                  f" (checkpointed by {was} ranks, resumed by {size}: not an exact continuation)"))
    return net, opt, sched, g, step


def _checkpoint(out: Path, net, opt, sched, g: torch.Generator, step: int, cfg: RunConfig, size: int) -> None:
    tmp = out / "checkpoint.tmp.pt"
    torch.save({"model": {k: v.cpu() for k, v in net.state_dict().items()},
                "optimizer": opt.state_dict(), "scheduler": sched.state_dict(), "rng": _rng_state(g),
                "step": step, "config": asdict(cfg), "world_size": size}, tmp)
    tmp.replace(out / "checkpoint.pt")  # atomic: a crash never leaves a half-written checkpoint


def train(task: Task, out: Path, train_data, val_data, resume: bool, progress: bool = True,
          stop_at: Optional[int] = None) -> torch.nn.Module:
    """Train ``task``'s network (or continue from ``out/checkpoint.pt`` if ``resume``) up
    to ``cfg.steps``, on every rank of a torchrun job (see the module).

    ``stop_at`` ends the call after that step, once its checkpoint is written (an
    interruption: a job's time limit, or the resume test). Returns the network on the
    CPU, in eval mode.
    """
    cfg = task.cfg
    rank, size, device = world()
    if cfg.batch_size % size:
        raise SystemExit(f"batch_size {cfg.batch_size} is not a multiple of the {size} ranks")
    net, opt, sched, g, step = _start(task, out, resume, rank, size)
    net.to(device)
    model = net
    if size > 1:
        from torch.nn.parallel import DistributedDataParallel

        if device.type == "cuda":
            net = torch.nn.SyncBatchNorm.convert_sync_batchnorm(net)
        model = DistributedDataParallel(net, device_ids=[device.index] if device.type == "cuda" else None)
    model.train()
    log = (out / "log.jsonl").open("a") if rank == 0 else None
    bar = tqdm(total=cfg.steps, initial=step, desc=f"train {task.name}", unit="step",
               disable=not progress or rank != 0)
    t0 = time.perf_counter()
    while step < cfg.steps:
        loss, parts = task.loss(model, task.batch(train_data, g, (rank, size)), device, size)
        opt.zero_grad(set_to_none=True)
        (loss * size).backward()  # DDP averages the ranks' gradients; the loss is a share of the batch's
        opt.step()
        sched.step()
        step += 1
        values = torch.stack(list(parts.values()))
        if size > 1:  # the whole batch's: the sum of the ranks' shares
            dist.all_reduce(values)
        values = dict(zip(parts, values.tolist()))
        bar.update(1)
        bar.set_postfix({k: f"{v:.3f}" for k, v in values.items()})
        if step % cfg.checkpoint_every == 0 or step == cfg.steps or step == stop_at:
            if rank == 0:
                rec = {"step": step, **values, "lr": sched.get_last_lr()[0], "seconds": time.perf_counter() - t0,
                       "world_size": size}
                if step % (4 * cfg.checkpoint_every) == 0 or step == cfg.steps:
                    rec.update(task.validate(net, val_data))
                log.write(json.dumps(rec) + "\n")
                log.flush()
                _checkpoint(out, net, opt, sched, g, step, cfg, size)
            barrier(size)
        if stop_at is not None and step >= stop_at:
            break
    bar.close()
    if log is not None:
        log.close()
    plain = task.build_net()
    plain.load_state_dict({k: v.cpu() for k, v in net.state_dict().items()})  # SyncBatchNorm: same keys
    return plain.eval()


# ------------------------------------------------------------------- command line


class _HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """The module docstring as written, and the default of every option that has one
    (an unset option's default is said in its help, e.g. ``--cache``)."""

    def _get_help_string(self, action):
        if action.default in (None, False, argparse.SUPPRESS) or "%(default)" in (action.help or ""):
            return action.help
        return f"{action.help} (default: %(default)s)"


def _parser(task_type: type, doc: str) -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=doc, formatter_class=_HelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="run folder")
    ap.add_argument("--config", type=Path, help=f"JSON object overriding {task_type.config_type.__name__} fields")
    ap.add_argument("--cache", type=Path, help="rendered-frame cache (default: RUN/cache)")
    ap.add_argument("--hia-root", type=Path, default=DEFAULT_HIA_ROOT, help="thesis data root")
    ap.add_argument("--force", action="store_true", help="replace an existing run")
    ap.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    ap.add_argument("--stop-at", type=int, help="end after this step, checkpointed (a job's time limit); "
                    "--resume continues")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    return ap


def _check_run_folder(args, cfg: RunConfig) -> bool:
    """Whether there is anything to do in ``args.out``: a resume needs the run's
    ``config.json`` (equal to ``cfg``) and is done once ``done.json`` is written; a new
    run needs an empty folder or ``--force``. Every rank checks alike, so that all stop
    on the same error."""
    out: Path = args.out
    cfg_file = out / "config.json"
    if args.resume and args.force:
        raise SystemExit("--resume and --force exclude each other")
    if args.resume:
        if not cfg_file.is_file():
            raise SystemExit(f"{out}: nothing to resume ({cfg_file} not found)")
        saved = json.loads(cfg_file.read_text())
        mine = json.loads(json.dumps(asdict(cfg)))
        diff = sorted(k for k in set(saved) | set(mine) if saved.get(k) != mine.get(k))
        if diff:
            src = args.config if args.config is not None else "the defaults (no --config)"
            raise SystemExit(f"cannot resume {out}: config field(s) {diff} of {src} differ from {cfg_file} "
                             f"(e.g. {diff[0]}: {mine.get(diff[0])!r} vs {saved.get(diff[0])!r}); "
                             "pass the run's config or start a new run")
        if (out / "done.json").is_file():
            print(f"{out} is already finished; nothing to do")
            return False
    elif out.exists() and any(out.iterdir()) and not args.force:
        what = "a finished run" if (out / "done.json").is_file() else "not empty"
        raise SystemExit(f"{out} is {what}; pass --force to replace it or --resume to continue it")
    return True


def _prepare_run_folder(args, cfg: RunConfig) -> None:
    """Rank 0: empty a forced folder (keeping its render cache, which does not depend on
    the run) and write a new run's ``config.json``."""
    out: Path = args.out
    if not args.resume and out.exists() and any(out.iterdir()):
        keep_cache = args.cache is None and (out / "cache").is_dir()
        for p in out.iterdir():
            if keep_cache and p.name == "cache":
                continue
            shutil.rmtree(p) if p.is_dir() else p.unlink()
    out.mkdir(parents=True, exist_ok=True)
    if not args.resume:
        (out / "config.json").write_text(json.dumps(asdict(cfg), indent=2))


def main(task_type: type, argv=None, doc: str = "") -> int:
    """The command line of a task's training (``doc``: its help text, the module docstring)."""
    args = _parser(task_type, doc).parse_args(argv)
    cfg = checked_config(task_type, args.config)
    task = task_type(cfg)
    out: Path = args.out
    if not _check_run_folder(args, cfg):
        return 0
    rank, size, _ = world()
    if rank == 0:
        _prepare_run_folder(args, cfg)
    torch.set_num_threads(cfg.threads)
    t_start = time.perf_counter()
    cache = args.cache or out / "cache"
    if rank == 0:  # rank 0 builds (or finds) the datasets, the others read its cache
        train_data, val_data = task.datasets(args.hia_root, cache)
    barrier(size)
    if rank != 0:
        train_data, val_data = task.datasets(args.hia_root, cache)
    t_data = time.perf_counter() - t_start
    if rank == 0:
        print(f"{task.describe_data(train_data, val_data)} ({t_data:.0f} s)"
              + (f"; {size} ranks of {cfg.batch_size // size} {task.sample} each" if size > 1 else ""))
    net = train(task, out, train_data, val_data, args.resume, progress=not args.no_progress, stop_at=args.stop_at)
    if args.stop_at is not None and args.stop_at < cfg.steps:
        if rank == 0:
            print(f"stopped after step {args.stop_at} of {cfg.steps}; --resume continues")
        return 0
    t_total = time.perf_counter() - t_start
    if rank == 0:
        done = {"steps": cfg.steps, **task.finish(net, out, val_data), "seconds_data": t_data,
                "seconds_total": t_total, **task.data_fields(train_data, val_data), "world_size": size}
        (out / "done.json").write_text(json.dumps(done, indent=2))
        print(json.dumps(done, indent=2))
    barrier(size)
    return 0
