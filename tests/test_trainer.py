"""The training loop of ``train/trainer.py`` serves any detector: a toy task (a linear
net on random data) trains, stops, resumes to the weights of an uninterrupted run, and
runs through the command line."""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import pytest
import torch

from train.trainer import RunConfig, Task, main, train


class _Linear(torch.nn.Linear):
    def __init__(self, config=(3, 1)):
        super().__init__(*config)
        self.config = tuple(config)

    def save(self, path):
        torch.save({"config": self.config, "state_dict": self.state_dict()}, path)
        return path

    @classmethod
    def load(cls, path):
        state = torch.load(path)
        net = cls(state["config"])
        net.load_state_dict(state["state_dict"])
        return net


@dataclass
class _ToyConfig(RunConfig):
    noise: float = 0.1  # input noise: draws of torch's and numpy's global generators, whose states resume


class _Toy(Task):
    name = "toy"
    config_type = _ToyConfig

    def check_config(self, cfg):
        if cfg.noise < 0:
            raise ValueError(f"field 'noise' must be >= 0, got {cfg.noise}")

    def build_net(self):
        return _Linear()

    def datasets(self, hia_root, cache):
        g = torch.Generator().manual_seed(7)
        x = torch.randn(32, 3, generator=g)
        return (x, x @ torch.tensor([[1.0], [-2.0], [0.5]])), (x[:8], x[:8].sum(1, keepdim=True))

    def batch(self, data, g, part):
        B, (rank, world) = self.cfg.batch_size, part
        idx = torch.randint(0, len(data[0]), (B,), generator=g)[rank * B // world: (rank + 1) * B // world]
        return data[0][idx], data[1][idx]

    def loss(self, model, batch, device, size):
        x, y = (t.to(device) for t in batch)
        x = x + self.cfg.noise * float(np.random.randn()) * torch.randn(x.shape)
        mse = ((model(x) - y) ** 2).sum() / self.cfg.batch_size
        return mse, {"mse": mse.detach()}

    def validate(self, net, val):
        with torch.no_grad():
            return {"val_mse": float(((net(val[0]) - val[1]) ** 2).mean())}

    def finish(self, net, out, val):
        net.save(out / "toy.pt")
        return self.validate(net, val)

    def describe_data(self, train, val):
        return f"samples: {len(train[0])} train, {len(val[0])} val"


def _log(run):
    return [{k: v for k, v in json.loads(line).items() if k != "seconds"}
            for line in (run / "log.jsonl").read_text().splitlines()]


def test_a_toy_task_trains_stops_and_resumes_exactly(tmp_path):
    task = _Toy(_ToyConfig(steps=6, batch_size=4, checkpoint_every=2, lr=0.05))
    data, val = task.datasets(None, None)
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    straight = train(task, tmp_path / "a", data, val, resume=False, progress=False)
    train(task, tmp_path / "b", data, val, resume=False, progress=False, stop_at=3)
    resumed = train(task, tmp_path / "b", data, val, resume=True, progress=False)
    for (k, a), b in zip(straight.state_dict().items(), resumed.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=0, atol=0, msg=k)
    torch.manual_seed(task.cfg.seed)
    assert not torch.equal(straight.weight, _Linear().weight)  # it trained
    a, b = _log(tmp_path / "a"), _log(tmp_path / "b")
    assert [r["step"] for r in a] == [2, 4, 6] and [r["step"] for r in b] == [2, 3, 4, 6]
    assert b[:1] + b[2:] == a
    assert list(a[-1]) == ["step", "mse", "lr", "world_size", "val_mse"]


def test_a_toy_task_runs_through_the_command_line(tmp_path, capsys):
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({"steps": 4, "batch_size": 4, "checkpoint_every": 2}))
    run = ["--out", str(tmp_path / "run"), "--config", str(cfg), "--no-progress"]
    assert main(_Toy, run + ["--stop-at", "2"]) == 0
    assert "stopped after step 2 of 4" in capsys.readouterr().out
    assert main(_Toy, run + ["--resume"]) == 0
    done = json.loads((tmp_path / "run" / "done.json").read_text())
    assert list(done) == ["steps", "val_mse", "seconds_data", "seconds_total", "world_size"]
    assert _Linear.load(tmp_path / "run" / "toy.pt").config == (3, 1)
    cfg.write_text(json.dumps({"noise": -1.0}))
    with pytest.raises(SystemExit, match=r"cfg\.json: field 'noise'"):
        main(_Toy, ["--out", str(tmp_path / "bad"), "--config", str(cfg)])
    cfg.write_text(json.dumps({"nois": 1.0}))
    with pytest.raises(SystemExit, match=r"cfg\.json: unknown config field.*nois"):
        main(_Toy, ["--out", str(tmp_path / "bad"), "--config", str(cfg)])


def test_a_missing_init_weights_file_stops_the_run_before_any_work(tmp_path):
    from train.hand_localiser import LocaliserTask
    from train.trainer import checked_config

    cfg = tmp_path / "c.json"
    cfg.write_text('{"init_weights": "runs/nothere/hand_localiser.pt"}')
    with pytest.raises(SystemExit, match="init_weights: runs/nothere/hand_localiser.pt not found"):
        checked_config(LocaliserTask, cfg)
