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

import numpy as np

# characters a terminal or an editor shows as a space or not at all, which text copied from a web page, a PDF or a chat
# carries (cli.py's arguments, config.py's YAML files)
INVISIBLE = {"\u00a0": "a non-breaking space", "\u202f": "a narrow non-breaking space", "\u2007": "a figure space",
             "\u200b": "a zero-width space", "\u2060": "a word joiner", "\ufeff": "a byte-order mark"}


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


def _worker_message(text: str, name: str) -> str:
    """The original message inside torch's DataLoader worker wrapping (see ``UserError``), or ``text``."""
    head, _, rest = text.partition("\n")
    if not re.fullmatch(rf"Caught {name} in DataLoader worker process \d+\.", head):
        return text
    lines = rest.splitlines()
    for i in range(len(lines) - 1, -1, -1):  # the traceback's last "module.Name: message" line
        if re.match(rf"([\w.]+\.)?{name}: ", lines[i]):
            return "\n".join(lines[i:]).split(": ", 1)[1].strip()
    return text


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
