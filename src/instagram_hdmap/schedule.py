"""Learning-rate schedules as functions of training *progress*, so that a run always completes them.

Progress ``p`` in [0, 1] is the larger of the step fraction and the time fraction:

    p = max(step / total_steps, elapsed_s / (60 * train.time_budget_min))

where ``total_steps`` is ``train.epochs`` x batches per epoch, and the time term is absent without a
time budget. A run stops when ``p`` reaches 1 (or earlier at ``train.max_steps``, a hard stop that
does not shorten the schedule: the run then ends before its final LR). On a machine fast
enough to take every step inside the budget the schedule is the step schedule; on a slower one
the run takes fewer steps of the *same whole schedule* (warm-up, decays, cosine tail) instead of
being cut before its decay.

Shapes of the learning-rate factor ``f(p)`` (the LR is ``train.lr * f(p)``):

* ``step`` (default, the paper's): x ``lr_gamma`` at each progress ``k * lr_step / epochs``
  (k = 1, 2, ...). Without a time budget and with ``total_steps = epochs x batches per epoch`` this
  is exactly torch's ``StepLR(step_size=lr_step)`` stepped once per epoch.
* ``cosine``: half a cosine from 1 down to ``min_lr_factor``.

Both start with a linear warm-up over the first ``warmup`` fraction of progress (0 = none; the
factor then rises from ``1 / (warmup steps)`` rather than from 0, so the first step is not wasted).

Progress is monotone and survives a resume exactly: the checkpoint stores the elapsed training
seconds and the progress reached (``ProgressClock.state_dict``); after a resume ``p`` never falls
below the saved value, even if the new run has another time budget. Under torchrun all ranks use
rank 0's clock (one broadcast per step), so they decay and stop at the same step.
"""

from __future__ import annotations

import math
import time

import torch

from .config import TrainConfig


def lr_factor(progress: float, cfg: TrainConfig) -> float:
    """The LR multiplier at ``progress`` in [0, 1] for ``cfg.schedule`` (module docstring)."""
    p = min(max(progress, 0.0), 1.0)
    if cfg.schedule == "cosine":
        if p < cfg.warmup:
            base = 1.0
        else:
            q = (p - cfg.warmup) / max(1.0 - cfg.warmup, 1e-12)
            base = cfg.min_lr_factor + (1.0 - cfg.min_lr_factor) * 0.5 * (1.0 + math.cos(math.pi * q))
    else:  # step
        # decays at progress k * lr_step / epochs; the small epsilon keeps an exact milestone decayed.
        # A milestone at or after the last epoch never comes (StepLR would step it after training):
        # without the cap, a progress a rounding error below 1 took one decay too many
        decays = math.floor(p * cfg.epochs / cfg.lr_step + 1e-9) if cfg.lr_step > 0 else 0
        decays = min(decays, (cfg.epochs - 1) // cfg.lr_step) if cfg.lr_step > 0 else 0
        base = cfg.lr_gamma ** decays
    if cfg.warmup > 0 and p < cfg.warmup:
        base *= max(p / cfg.warmup, 1e-3)
    return base


def final_lr_factor(cfg: TrainConfig) -> float:
    """The factor of the schedule's last phase (what a complete run ends with)."""
    return lr_factor(1.0, cfg)


class ProgressClock:
    """Steps and elapsed seconds -> progress (module docstring); resumable, synchronised across ranks.

    ``start()`` when the training loop starts; ``progress(step)`` before each step and at the end.
    """

    def __init__(self, cfg: TrainConfig, total_steps: int):
        if total_steps <= 0:
            raise ValueError(f"total_steps must be > 0, got {total_steps}")
        self.total_steps = total_steps
        self.budget_s = None if cfg.time_budget_min is None else 60.0 * cfg.time_budget_min
        self.elapsed_before = 0.0  # training seconds of earlier runs (resume)
        self.floor = 0.0  # progress reached before a resume: never go below it
        self._t0: float | None = None
        self.last = 0.0

    def start(self) -> None:
        self._t0 = time.perf_counter()

    def elapsed(self) -> float:
        """Training seconds so far, earlier runs included."""
        return self.elapsed_before + (0.0 if self._t0 is None else time.perf_counter() - self._t0)

    def progress(self, step: int, sync_device: torch.device | None = None) -> float:
        p = step / self.total_steps
        if self.budget_s is not None:
            p = max(p, self.elapsed() / self.budget_s)
        if sync_device is not None:  # torchrun: every rank takes rank 0's value
            t = torch.tensor([p], dtype=torch.float64, device=sync_device)
            torch.distributed.broadcast(t, src=0)
            p = float(t)
        self.last = max(p, self.floor)
        return self.last

    def state_dict(self) -> dict:
        return {"elapsed_s": self.elapsed(), "progress": self.last}

    def load_state_dict(self, state: dict) -> None:
        self.elapsed_before = float(state.get("elapsed_s", 0.0))
        self.floor = self.last = float(state.get("progress", 0.0))
