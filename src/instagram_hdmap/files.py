"""Files written whole or not at all: the one atomic write, and JSON files on top of it.

    with atomic_path("runs/x/last.pt") as tmp:     # a temporary sibling, renamed over the target
        torch.save(state, tmp)
    write_json(metrics, "eval/metrics.json")

``atomic_path`` yields a temporary sibling of the target (``.NAME.TAG-PID``, in the same folder, so
the rename cannot cross file systems). When the block finishes, a file is flushed to disk and the
temporary is renamed over the target (a folder at the target is removed first); when the block
raises (an error, Ctrl-C), the temporary is removed and the target is as it was. A crash leaves
either the old target or the new one, and at worst a ``.NAME.TAG-PID`` file or folder that names
the process that left it.

It sits on the lowest floor (with config.py, which saves configs through it), so every module that
writes a result file uses it: configs, checkpoints, submissions and metrics, ONNX exports, synthetic
worlds.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


def temporary_sibling(path: str | Path, tag: str = "tmp") -> Path:
    """``.NAME.TAG-PID`` next to ``path``: where ``atomic_path`` writes before the rename."""
    path = Path(path)
    return path.with_name(f".{path.name}.{tag}-{os.getpid()}")


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    elif path.exists() or path.is_symlink():
        path.unlink()


def _replace(src: Path, dst: Path) -> None:
    """The rename step (a function of its own so tests can interrupt between write and rename)."""
    os.replace(src, dst)


@contextmanager
def atomic_path(path: str | Path, tag: str = "tmp") -> Iterator[Path]:
    """Yield a temporary sibling of ``path`` to write a file or a folder at; on success it replaces
    ``path`` (a file is fsync'ed first), on any exception it is removed (module docstring)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_sibling(path, tag)
    try:
        yield tmp
        if tmp.is_file():
            with open(tmp, "rb+") as f:
                os.fsync(f.fileno())
        elif tmp.is_dir() and path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)  # os.replace renames a folder only over an empty one
        _replace(tmp, path)
    finally:
        _remove(tmp)


def write_text(text: str, path: str | Path) -> Path:
    """Write ``text`` to ``path`` atomically; returns the path."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return path


def write_json(obj, path: str | Path, indent: int | None = None) -> Path:
    """Write ``obj`` as JSON atomically; returns the path. NaN and infinity are written as NaN /
    Infinity (what Python's json reads back)."""
    return write_text(json.dumps(obj, indent=indent), path)
