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

import contextlib
import pickle
import random
import re
import warnings
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .config import UserError, load_yaml
from .errors import one_line
from .files import as_path, atomic_path


class CheckpointError(UserError):
    """A checkpoint file that is missing, truncated, corrupt or from an incompatible config."""


@contextlib.contextmanager
def signals_deferred():
    """SIGINT, SIGTERM, SIGHUP and SIGCHLD that arrive while the block runs are handled after it, by the handlers
    they would have met (main thread only; elsewhere Python runs no handlers). An exception raised by a handler in
    the middle of ``torch.save`` (Ctrl-C's KeyboardInterrupt, training's SIGTERM interrupt, torch's "data-loader
    worker killed" on SIGCHLD when a scheduler's SIGTERM kills the process group) leaves its zip writer half
    done, and its cleanup then raises "unexpected pos" in place of the interrupt: the run ended with exit 1
    instead of saving (seen under load in the row runs::sigterm-saves-last-pt)."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    names = ("SIGINT", "SIGTERM", "SIGHUP", "SIGCHLD")
    got: list[int] = []

    def later(signum, frame):
        got.append(signum)

    previous = {}
    for sig in (getattr(signal, n) for n in names if hasattr(signal, n)):
        handler = signal.getsignal(sig)
        if handler is not signal.SIG_IGN and handler is not None:  # None: set outside Python, left alone
            previous[sig] = signal.signal(sig, later)
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        for sig in dict.fromkeys(got):  # each once, in arrival order, to the handler it was meant for
            signal.raise_signal(sig)


def save_checkpoint(state: dict, path: str | Path) -> Path:
    """Write ``state`` to ``path`` atomically (``files.atomic_path``: a crash leaves the old file or the new one, a
    full disk is a one-line ``OutputError``). A signal that arrives during the write is handled after it
    (``signals_deferred``): Ctrl-C or a scheduler's SIGTERM lands between two whole checkpoints."""
    path = as_path(path, "checkpoint path")
    with signals_deferred(), atomic_path(path) as tmp, open(tmp, "wb") as f:
        torch.save(state, f)  # through Python's file object: a failed write (full disk) keeps its OSError
    return path


# a checkpoint as downloaded or shared: compressed (best.pt.gz), which torch.load does not read
COMPRESSED = ((b"\x1f\x8b", "gzip", "gunzip"), (b"\xfd7zX", "xz", "unxz"), (b"BZh", "bzip2", "bunzip2"),
              (b"\x28\xb5\x2f\xfd", "zstd", "unzstd"))


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict:
    """Load a checkpoint safely; errors name the file and say what is wrong.

    Before unpickling, the zip archive's CRC-32 of every entry is checked (``ZipFile.testzip``), so
    bits flipped on disk or in a transfer are named instead of loading as wild weights; after it,
    the model weights must be finite (a checkpoint of a diverged run is named with the first
    non-finite tensor)."""
    path = as_path(path, "checkpoint path")
    if path.exists() and not path.is_file() and not path.is_dir():  # said "checkpoint not found", though it is there
        raise CheckpointError(f"checkpoint {path} is a pipe or a device, not a file (a process substitution <(...), "
                              "/dev/stdin): a checkpoint is a zip archive, read by seeking in it; save it to a file "
                              "first")
    if not path.is_file():
        run = [path / name for name in ("best.pt", "last.pt") if (path / name).is_file()] if path.is_dir() else []
        raise CheckpointError(f"checkpoint not found: {path}" + (
            f" (it is a folder: a training run's; give the checkpoint in it, {' or '.join(map(str, run))})" if run
            else " (it is a folder)" if path.is_dir() else ""))
    with open(path, "rb") as f:
        head = f.read(4096)  # enough for a text file's or a tar header's signs too
    if not head:
        raise CheckpointError(f"checkpoint {path} is empty (0 bytes): its save never wrote (killed, or a full "
                              "disk); use another checkpoint, e.g. best.pt or an earlier copy")
    if head[:4] == b"PK\x03\x04":  # torch's zip format
        _check_archive(path)
    elif head[:1] != b"\x80":  # neither a zip nor a pickle (torch's legacy format)
        packed = next((f"a {name}-compressed file ({tool} it first)" for magic, name, tool in COMPRESSED
                       if head.startswith(magic)), None)
        what = packed or ("a text file (a config?)" if _is_text(head) else
                          "a tar archive (tar xf it first)" if head[257:262] == b"ustar" else "not a PyTorch file")
        raise CheckpointError(f"{path} is not a PyTorch checkpoint: it is {what}; give a checkpoint written by "
                              "instagram-hdmap train (e.g. OUT/best.pt)")  # (--checkpoint, --resume, init_from)
    try:
        with warnings.catch_warnings():  # a plain pickle (not torch's zip) of protocol > 2: torch's UserWarning with
            # its own source line printed above the one-line message (or above nothing, where the file then loads)
            warnings.filterwarnings("ignore", message="Detected pickle protocol", category=UserWarning)
            state = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as e:
        raise CheckpointError(
            f"checkpoint {path} was refused by the safe loader (torch.load with weights_only=True): it holds "
            f"objects other than tensors and plain containers, which could run code when loaded. torch's reason: "
            f"{_refusal_reason(e)}"
        ) from None
    except (RuntimeError, EOFError, zipfile.BadZipFile, ValueError, KeyError) as e:
        raise CheckpointError(
            f"checkpoint {path} is truncated or corrupt and cannot be loaded ({type(e).__name__}: {one_line(e)})"
        ) from None
    if not isinstance(state, dict) or not isinstance(state.get("model"), dict):
        raise CheckpointError(f"checkpoint {path} holds no 'model' state dict; is it an instagram_hdmap checkpoint?")
    if isinstance(state.get("config"), str):  # a config saved as YAML text (older writers): read as the mapping
        state["config"] = _yaml_config(state["config"], path)
    bad = [k for k, v in state["model"].items()
           if torch.is_tensor(v) and v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        more = f" (and {len(bad) - 1} more tensors)" if len(bad) > 1 else ""
        raise CheckpointError(f"checkpoint {path}: the weights {bad[0]}{more} hold NaN or infinite values (a "
                              "diverged training saved them); use an earlier checkpoint such as best.pt")
    memories = state.get("memory") if isinstance(state.get("memory"), list) else []
    bad = [k for rank in memories if isinstance(rank, dict) for k, v in rank.items()
           if torch.is_tensor(v) and v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:  # a temporal run's streams would fuse them into every frame until their scenes end (a NaN loss)
        raise CheckpointError(f"checkpoint {path}: the temporal streams' saved memory ('{bad[0]}') holds NaN or "
                              "infinite values; the file is corrupt: use an earlier checkpoint such as best.pt")
    return state


def _yaml_config(text: str, path: Path) -> dict:
    import yaml

    try:
        config = load_yaml(text)  # as a config file is read (YAML 1.2 numbers: lr: 1e-3 is a float, not text)
    except yaml.YAMLError as e:
        raise CheckpointError(f"checkpoint {path}: its config is text that is not YAML ({one_line(e)})") from None
    if not isinstance(config, dict):
        raise CheckpointError(f"checkpoint {path}: its config is text that is not a YAML mapping of config keys")
    return config


# What ``train --resume`` needs besides the weights (train.py writes them all)
RESUME_KEYS = ("optimizer", "epoch", "step", "step_in_epoch", "rng", "config")


def check_resumable(state: dict, path: str | Path) -> None:
    """A checkpoint to resume a training from holds the full training state, not just weights."""
    missing = [k for k in RESUME_KEYS if k not in state]
    if missing or not isinstance(state.get("config"), dict):
        raise CheckpointError(f"checkpoint {path} cannot be resumed: it holds no {', '.join(missing or ['config'])} "
                              "(only weights); resume from the last.pt or best.pt that instagram-hdmap train wrote")


def _check_archive(path: Path) -> None:
    """The zip's central directory is readable and every entry matches its CRC-32."""
    try:
        with zipfile.ZipFile(path) as z:
            bad = z.testzip()
            names = z.namelist()
    except (zipfile.BadZipFile, OSError, EOFError) as e:
        raise CheckpointError(f"checkpoint {path} is truncated or corrupt and cannot be loaded "
                              f"({type(e).__name__}: {one_line(e)}); was its save interrupted or the copy cut "
                              "short? Use another checkpoint") from None
    except (zipfile.LargeZipFile, NotImplementedError, RuntimeError) as e:  # damaged headers
        raise CheckpointError(f"checkpoint {path} is damaged ({type(e).__name__}: {one_line(e)}); use another "
                              "copy") from None
    if bad is None and not any(n == "data.pkl" or n.endswith("/data.pkl") for n in names):  # a zip of files
        raise CheckpointError(f"{path} is not a PyTorch checkpoint but a zip archive of {len(names)} file(s) "
                              f"({', '.join(names[:3])}{', ...' if len(names) > 3 else ''}): unzip it and give "
                              "the checkpoint inside")
    if bad is not None:
        raise CheckpointError(f"checkpoint {path} is damaged: its entry {bad} fails the zip's CRC-32 check (bits "
                              "changed on disk or in a transfer); use another copy of the checkpoint")


def _is_text(head: bytes) -> bool:
    try:
        head.decode("utf-8")
    except UnicodeDecodeError:
        return False
    return b"\x00" not in head


def _refusal_reason(e: BaseException) -> str:
    """Why torch's weights_only unpickler refused a file: the lines of its message that name the
    object (e.g. ``Unsupported global: GLOBAL posix.system ...``), whole; all of it if none does."""
    lines = [" ".join(ln.split()) for ln in re.sub(r"\x1b\[[0-9;]*m", "", str(e)).splitlines()]
    reason = [ln for ln in lines if "GLOBAL" in ln or "WeightsUnpickler" in ln or "Unsupported" in ln]
    return " ".join(reason) if reason else one_line(e)


def rng_state() -> dict[str, Any]:
    """Every RNG the training touches, as weights_only-loadable values."""
    np_state = np.random.get_state()  # noqa: NPY002 (the global stream third-party code uses)
    return {
        "python": random.getstate(),
        "numpy": (np_state[0], torch.from_numpy(np_state[1].copy()), *np_state[2:]),
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
    }


@contextlib.contextmanager
def rng_preserved():
    """Every RNG as it was before the block (validation inside a training: the training's random
    streams, which a checkpoint saves for an exact resume, are not drawn from)."""
    state = rng_state()
    try:
        yield
    finally:
        set_rng_state(state)


def set_rng_state(state: dict[str, Any]) -> None:
    py = state["python"]
    random.setstate((py[0], tuple(py[1]), py[2]))
    name, keys, *rest = state["numpy"]
    np.random.set_state((name, keys.numpy().astype(np.uint32), *rest))  # noqa: NPY002
    torch.set_rng_state(state["torch"].cpu())
    if state.get("cuda") and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([s.cpu() for s in state["cuda"]])
