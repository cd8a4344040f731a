"""LR schedules over training progress (schedule.py): shapes, the StepLR equivalence, time budgets
that still reach the final LR, and progress that survives a resume exactly."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from instagram_hdmap.checkpoint import load_checkpoint
from instagram_hdmap.config import ConfigError, TrainConfig, load_config
from instagram_hdmap.schedule import ProgressClock, final_lr_factor, lr_factor
from instagram_hdmap.train import train
from test_train import _loaders, _tiny_cfg


def test_step_schedule_equals_torch_steplr_stepped_per_epoch():
    cfg = TrainConfig(epochs=7, lr=1.0, lr_step=3, lr_gamma=0.1)
    spe = 5
    opt = torch.optim.SGD([torch.zeros(1, requires_grad=True)], lr=1.0)
    sched = torch.optim.lr_scheduler.StepLR(opt, step_size=cfg.lr_step, gamma=cfg.lr_gamma)
    for epoch in range(cfg.epochs):
        for i in range(spe):
            step = epoch * spe + i
            assert lr_factor(step / (cfg.epochs * spe), cfg) == pytest.approx(opt.param_groups[0]["lr"], rel=1e-12)
        opt.step()
        sched.step()
    assert final_lr_factor(cfg) == pytest.approx(0.01)  # decays at epochs 3 and 6
    # a milestone at the last epoch never comes, also a rounding error below progress 1 (it did)
    even = TrainConfig(epochs=50, lr=1.0, lr_step=25, lr_gamma=0.1)
    assert lr_factor(1.0 - 1e-12, even) == lr_factor(1.0, even) == final_lr_factor(even) == pytest.approx(0.1)


def test_cosine_and_warmup_shapes():
    cfg = TrainConfig(schedule="cosine", min_lr_factor=0.05, warmup=0.1)
    ps = [i / 200 for i in range(201)]
    f = [lr_factor(p, cfg) for p in ps]
    assert f[0] < 0.01 and f[20] == pytest.approx(1.0)  # linear warm-up to 1 at p = 0.1
    assert all(a <= b + 1e-12 for a, b in zip(f[:20], f[1:21]))  # rising during warm-up
    assert all(a >= b - 1e-12 for a, b in zip(f[20:], f[21:]))  # falling after
    assert f[-1] == pytest.approx(0.05) and final_lr_factor(cfg) == pytest.approx(0.05, abs=1e-6)
    assert lr_factor(0.55, cfg) == pytest.approx(0.05 + 0.95 * 0.5)  # half-way through the cosine
    assert lr_factor(2.0, cfg) == lr_factor(1.0, cfg) and lr_factor(-1.0, cfg) == lr_factor(0.0, cfg)


def test_clock_takes_the_larger_fraction_and_never_goes_back(monkeypatch):
    now = {"t": 100.0}
    monkeypatch.setattr("instagram_hdmap.schedule.time.perf_counter", lambda: now["t"])
    clock = ProgressClock(TrainConfig(time_budget_min=1.0), total_steps=100)
    clock.start()
    assert clock.progress(10) == pytest.approx(0.1)  # steps lead
    now["t"] += 30.0
    assert clock.progress(10) == pytest.approx(0.5)  # time leads: 30 s of 60
    state = clock.state_dict()
    assert state == {"elapsed_s": pytest.approx(30.0), "progress": pytest.approx(0.5)}
    # resume with a doubled budget: elapsed continues, progress does not fall back to 30 / 120
    resumed = ProgressClock(TrainConfig(time_budget_min=2.0), total_steps=100)
    resumed.load_state_dict(state)
    resumed.start()
    assert resumed.progress(10) == pytest.approx(0.5)
    now["t"] += 42.0
    assert resumed.elapsed() == pytest.approx(72.0)
    assert resumed.progress(10) == pytest.approx(72.0 / 120.0)


def test_bad_schedule_keys_are_named():
    for bad, key in (("train.time_budget_min=0", "time_budget_min"), ("train.time_budget_min=-3", "time_budget_min"),
                     ("train.warmup=1.0", "warmup"), ("train.lr_step=0", "lr_step"), ("train.max_steps=0", "max_steps"),
                     ("train.schedule=linear", "schedule")):
        with pytest.raises(ConfigError, match=key):
            load_config(None, [bad])


@pytest.fixture
def ticking_clock(monkeypatch):
    """The clock advances 50 ms on every read: time budgets run out after the same number of steps
    on a quiet machine and on a loaded CI runner (a real clock made these tests depend on the load)."""
    now = {"t": 1000.0}

    def tick():
        now["t"] += 0.05
        return now["t"]

    monkeypatch.setattr("instagram_hdmap.schedule.time.perf_counter", tick)
    return now


def test_tiny_time_budget_still_reaches_the_final_lr(tmp_path, ticking_clock):
    """200 steps could never run in 6 s of a clock that ticks 50 ms per read: the run takes fewer
    steps of the whole schedule, and its last steps run at the final (twice decayed) LR."""
    cfg = _tiny_cfg(tmp_path, "train.epochs=100", "train.lr_step=40", "train.time_budget_min=0.1",
                    "train.deterministic=false")
    summary = train(cfg, loaders=_loaders(cfg), validate=False)
    total = 100 * 2
    assert 0 < summary["step"] < total
    assert summary["progress"] >= 1.0
    assert summary["schedule_complete"]
    assert summary["lr"] == pytest.approx(cfg.train.lr * 0.01)
    state = load_checkpoint(tmp_path / "run" / "last.pt")
    assert state["clock"]["progress"] >= 1.0
    assert state["optimizer"]["param_groups"][0]["lr"] == pytest.approx(cfg.train.lr * 0.01)


def test_a_cut_run_says_its_schedule_is_incomplete(tmp_path):
    cfg = _tiny_cfg(tmp_path, "train.epochs=4", "train.lr_step=2", "train.max_steps=3")
    summary = train(cfg, loaders=_loaders(cfg), validate=False)
    assert summary["step"] == 3 and summary["progress"] == pytest.approx(3 / 8)
    assert not summary["schedule_complete"] and summary["lr"] == pytest.approx(cfg.train.lr)


def test_resume_continues_the_progress_exactly(tmp_path, ticking_clock):
    """A run with a time budget, stopped after 3 steps: the checkpoint holds its elapsed time and
    progress; the resumed run starts from that progress (its first LR is the schedule's LR there),
    adds its own time to the elapsed time, and completes the schedule."""
    budget = 0.1  # 6 s of the ticking clock: the first run's 3 steps take a fraction of it
    part = _tiny_cfg(tmp_path, "train.epochs=50", "train.lr_step=25", f"train.time_budget_min={budget}",
                     "train.max_steps=3", "train.deterministic=false")
    train(part, loaders=_loaders(part), validate=False)
    saved = load_checkpoint(tmp_path / "run" / "last.pt")["clock"]
    # the progress of the third step, a moment before the checkpoint's elapsed time was read
    assert 3 / 100 <= saved["progress"] <= max(3 / 100, saved["elapsed_s"] / (60 * budget)) + 1e-9

    rest = dataclasses.replace(part, train=dataclasses.replace(part.train, max_steps=None))
    seen = []
    original = ProgressClock.progress

    def spy(self, step, sync_device=None):
        p = original(self, step, sync_device)
        seen.append(p)
        return p

    ProgressClock.progress = spy
    try:
        summary = train(rest, loaders=_loaders(rest), validate=False, resume=str(tmp_path / "run" / "last.pt"))
    finally:
        ProgressClock.progress = original
    assert seen[0] >= saved["progress"] and seen[0] == pytest.approx(saved["progress"], abs=0.05)
    assert all(a <= b for a, b in zip(seen, seen[1:]))  # monotone
    assert summary["elapsed_s"] > saved["elapsed_s"]
    assert summary["schedule_complete"] and math.isclose(summary["lr"], rest.train.lr * 0.1, rel_tol=1e-9)
