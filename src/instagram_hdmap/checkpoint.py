"""Checkpoints: atomic saves (files.py), safe loads (``weights_only=True``), full-state resume.

A checkpoint is a plain dict of tensors and Python scalars/containers, so that it loads with
``torch.load(weights_only=True)``:

    {"model", "optimizer", "scheduler", "scaler" (or None), "epoch", "step", "step_in_epoch",
     "rng": {"python", "numpy", "torch", "cuda"}, "config": <resolved config dict>, "metrics": {...}}

``epoch`` is the epoch in progress and ``step_in_epoch`` the number of its batches already consumed,
so a run killed mid-epoch resumes on the very next batch (the sampler's order is a function of the
seed and the epoch; see distributed.ResumableSampler).
"""

from __future__ import annotations

import pickle
import random
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .config import UserError
from .files import atomic_path


class CheckpointError(UserError):
    """A checkpoint file that is missing, truncated, corrupt or from an incompatible config."""


def save_checkpoint(state: dict, path: str | Path) -> Path:
    """Write ``state`` to ``path`` atomically (``files.atomic_path``: a temporary file in the same
    folder, fsync'ed, then renamed over the target). A crash leaves either the old file or the new one."""
    path = Path(path)
    with atomic_path(path) as tmp:
        torch.save(state, tmp)
    return path


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict:
    """Load a checkpoint safely; errors name the file and say what is wrong."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint not found: {path}")
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except (RuntimeError, EOFError, zipfile.BadZipFile, pickle.UnpicklingError, ValueError) as e:
        raise CheckpointError(
            f"checkpoint {path} is truncated or corrupt and cannot be loaded ({type(e).__name__}: "
            f"{str(e).splitlines()[0][:200]})"
        ) from None
    if not isinstance(state, dict) or "model" not in state:
        raise CheckpointError(f"checkpoint {path} holds no 'model' state; is it an instagram_hdmap checkpoint?")
    return state


def rng_state() -> dict[str, Any]:
    """Every RNG the training touches, as weights_only-loadable values."""
    np_state = np.random.get_state()  # noqa: NPY002 (the global stream third-party code uses)
    state = {
        "python": random.getstate(),
        "numpy": (np_state[0], torch.from_numpy(np_state[1].copy()), *np_state[2:]),
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
    }
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    py = state["python"]
    random.setstate((py[0], tuple(py[1]), py[2]))
    name, keys, *rest = state["numpy"]
    np.random.set_state((name, keys.numpy().astype(np.uint32), *rest))  # noqa: NPY002
    torch.set_rng_state(state["torch"].cpu())
    if state.get("cuda") and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([s.cpu() for s in state["cuda"]])
