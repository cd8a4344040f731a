"""``UserError``: the one exception class for errors in what the user gave.

A ``UserError`` (or a subclass: ``ConfigError``, ``CheckpointError``, ``DatasetError``, ...) is a wrong
path, file, key, argument or sample: ``instagram-hdmap`` prints its message on one line and exits
with code 2 (cli.py). Its message names the file / key / sample and says what to do. It sits on the
lowest floor so that every module, files.py included, can raise one; config.py re-exports it.
"""

from __future__ import annotations

import numbers
import re
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

# characters a terminal or an editor shows as a space or not at all, which text copied from a web page, a PDF or a chat
# carries (cli.py's arguments, config.py's YAML files)
INVISIBLE = {"\u00a0": "a non-breaking space", "\u202f": "a narrow non-breaking space", "\u2007": "a figure space",
             "\u200b": "a zero-width space", "\u2060": "a word joiner", "\ufeff": "a byte-order mark"}
# dashes that look like '-' in a web page, a PDF or a word processor (which turn '--' into an en or em dash)
LOOKALIKE_DASHES = "\u2010\u2011\u2012\u2013\u2014\u2015\u2212\ufe63\uff0d"


def invisible_character(argv: Sequence[str]) -> str | None:
    """The message for the first argument holding an ``INVISIBLE`` character (``train.out_dir=runs/x\\xa0`` made a
    folder whose name ends in it; ``--checkpoint best.pt\\xa0`` was "not found: best.pt "), unless it names a file
    that exists so; None if there is none."""
    for arg in map(str, argv):
        chars = [c for c in INVISIBLE if c in arg]
        if chars and not any(Path(part).exists() for part in (arg, arg.split("=", 1)[-1])):
            return (f"argument {arg!r} holds {INVISIBLE[chars[0]]} (U+{ord(chars[0]):04X}), which the terminal does "
                    "not show: copied from a web page, a PDF or a chat? type that argument again")
    return None


def lookalike_dash(argv: Sequence[str], options: set[str]) -> str | None:
    """The message for the first argument that is one of ``options`` (long option names, without dashes) written
    with a ``LOOKALIKE_DASHES`` dash (``—force``, ``–-checkpoint`` copied from a formatted page: argparse took it for
    an override, "must look like key.sub=value", or a positional, then asked for the option the user had given);
    None if there is none. A value such as ``--out —eval`` is not an option name, so it is left alone."""
    for arg in map(str, argv):
        if arg[:1] and arg[:1] in LOOKALIKE_DASHES:
            written = arg.lstrip(LOOKALIKE_DASHES + "-")
            if written.partition("=")[0] in options:
                return (f"argument {arg!r} starts with {arg[0]!r} (U+{ord(arg[0]):04X}), a dash that only looks like "
                        f"'-': type --{written} with plain hyphens (a command copied from a web page or a document "
                        "often carries such dashes)")
    return None


class UserError(Exception):
    """An error in what the user gave (a path, a file, an argument): the CLI prints it on one line
    and exits with code 2. Library code raises subclasses with messages that say what to fix.

    Raised in a DataLoader worker process, it reaches the main process re-created by torch from one
    string (``Caught ImageError in DataLoader worker process 0.`` + the worker's whole traceback);
    the constructor takes that apart again, so the error reads the same with workers as without."""

    def __init__(self, *args: object) -> None:
        if len(args) == 1 and isinstance(args[0], str) and args[0].startswith("Caught "):
            args = (_worker_message(args[0], type(self).__name__),)
        super().__init__(*args)


class ConfigError(UserError, ValueError):
    """A configuration key or value the user must fix."""


def _worker_message(text: str, name: str) -> str:
    """The original message inside torch's DataLoader worker wrapping (see ``UserError``), or ``text``."""
    head, _, rest = text.partition("\n")
    if not re.fullmatch(rf"Caught {name} in DataLoader worker process \d+\.", head):
        return text
    lines = rest.splitlines()
    last = [i for i, line in enumerate(lines) if re.match(rf"([\w.]+\.)?{name}: ", line)]
    # from the traceback's last "module.Name: message" line on
    return "\n".join(lines[last[-1]:]).split(": ", 1)[1].strip() if last else text


def one_line(e: BaseException) -> str:
    """An exception's message on one line, whole (terminal colour codes dropped): for a UserError that
    quotes a library's multi-line explanation."""
    text = re.sub(r"\x1b\[[0-9;]*m", "", str(e))
    return " ".join(text.split()) or type(e).__name__


# --- argument checks shared by the Python API's batch-taking classes (FlickerMeter, Persistence) -------------


def is_real(value) -> bool:
    """A real number (int, float, a NumPy number), not a bool (NumPy's bool is no ``numbers.Real``)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def as_batch_list(values, what: str, expected: str, error: type[UserError] = UserError) -> list:
    """A batch argument (list, tuple, array or tensor) as a list; a string, a mapping, None or another object is
    ``error`` saying ``what`` must be ``expected`` (a string's characters would be read as B entries)."""
    if hasattr(values, "tolist") and not isinstance(values, (str, bytes)):
        values = values.tolist()
    if values is None or isinstance(values, (str, bytes, Mapping)) or not isinstance(values, Sequence):
        raise error(f"{what} must be {expected}, got {values!r:.80}")
    return list(values)


def as_float64_array(values, what: str, expected: str, error: type[UserError] = UserError) -> np.ndarray:
    """A numeric batch argument (an array, a tensor of any dtype on any device, nested lists) as a float64 array;
    one that is not numbers is ``error`` saying ``what`` must be ``expected`` (not numpy's own message)."""
    try:
        return (values.detach().cpu().double().numpy() if hasattr(values, "detach")
                else np.asarray(values, dtype=np.float64))
    except (TypeError, ValueError):
        raise error(f"{what} must be {expected}, got {values!r:.80}") from None


def check_rigid_pose(pose: np.ndarray, where: str, error: type[UserError] = UserError) -> np.ndarray:
    """A float64 [4, 4] ego -> world pose that is finite and rigid ([[R, t], [0, 0, 0, 1]], R a rotation within
    Mapper's tolerance: float16 poses round R by ~1e-3), returned as it is; else ``error`` naming ``where``. The
    one pose check of the drive meters and of persistence."""
    if pose.shape != (4, 4):
        raise error(f"{where}: its ego pose must be a 4x4 ego -> world transform, got shape {list(pose.shape)}")
    if not np.isfinite(pose).all():
        raise error(f"{where}: its ego pose has NaN or infinite values; give a finite 4x4 ego -> world transform")
    R = pose[:3, :3]
    det, off = float(np.linalg.det(R)), float(np.abs(R @ R.T - np.eye(3)).max())
    if not np.allclose(pose[3], (0.0, 0.0, 0.0, 1.0), atol=1e-6) or off > 1e-2 or det <= 0:
        raise error(f"{where}: its ego pose is not a rigid transform [[R, t], [0, 0, 0, 1]] (last row "
                    f"{pose[3].round(4).tolist()}, det(R) {det:.3g})")
    return pose
