"""Files written whole or not at all: the one atomic write, and JSON files on top of it.

    with atomic_path("runs/x/last.pt") as tmp:     # a temporary sibling, renamed over the target
        torch.save(state, tmp)
    write_json(metrics, "eval/metrics.json")

``atomic_path`` yields a temporary sibling of the target (``.NAME.TAG-PID``, in the same folder, so
the rename cannot cross file systems). When the block finishes, a file is flushed to disk and the
temporary is renamed over the target (a folder at the target is removed first); when the block
raises (an error, Ctrl-C), the temporary is removed and the target is as it was. A crash leaves
either the old target or the new one, and at worst a ``.NAME.TAG-PID`` file or folder that names
the process that left it, which the next writer of that target removes (``remove_stale_temporaries``)
once that process is gone. A full disk or an unwritable place is an ``OutputError`` naming the file;
``check_output_file`` / ``check_output_dir`` check an output path before the work that fills it.

It sits on the lowest floor (with config.py, which saves configs through it), so every module that
writes a result file uses it: configs, checkpoints, submissions and metrics, ONNX exports, synthetic
worlds.
"""

from __future__ import annotations

import contextlib
import errno
import json
import math
import os
import shutil
import stat
import tempfile
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from .errors import UserError

try:
    import fcntl
except ImportError:  # not POSIX: no file locks
    fcntl = None

# errnos that mean "no room": the disk (or the user's quota) is full, or a file-size limit is reached
NO_ROOM = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG}


class OutputError(UserError):
    """An output path that cannot be written: a folder where a file goes (or the reverse), no write
    permission, a full disk. The message names the path and the cause."""


def as_path(value, what: str = "path") -> Path:
    """``value`` (a str, an ``os.PathLike`` or bytes, as ``open`` takes) as a ``Path``; anything else (a dict, a
    config object, None) is a ``TypeError`` naming ``what`` instead of pathlib's "expected str, bytes or
    os.PathLike object, not dict" (which names neither the argument nor what was meant)."""
    if isinstance(value, bytes):
        return Path(os.fsdecode(value))
    if isinstance(value, (str, os.PathLike)):
        return Path(value)
    raise TypeError(f"{what} must be a file path (str or pathlib.Path), got {type(value).__name__}")


def os_error_in(e: BaseException) -> OSError | None:
    """The OSError that caused ``e``: ``e`` itself or one in its chain (torch.save reports a failed
    write as a RuntimeError raised while handling the OSError of Python's file object)."""
    seen = set()
    while e is not None and id(e) not in seen:
        if isinstance(e, OSError):
            return e
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return None


def relative_path_note(path: str | Path) -> str:
    """For a message about a path not found: where a relative one was looked for (the current folder, not the
    config file's, which a run started from another folder is easily taken for); "" for an absolute path."""
    path = Path(path)
    try:
        return "" if path.is_absolute() else f"; a relative path is read from the current folder, {Path.cwd()}"
    except OSError:  # the current folder was removed
        return "; a relative path is read from the current folder, which no longer exists"


def _first_existing(path: Path) -> Path:
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def check_no_broken_link(path: str | Path, flag: str = "output path") -> None:
    """``path`` and the folders above it up to the first that exists are not symbolic links that lead
    nowhere (a loop of links, or a link to a disk that is not mounted): creating a folder or a file there
    would fail with a raw ``FileExistsError`` after the work."""
    path = Path(path)
    probe = path
    while not probe.exists() and probe != probe.parent:
        if probe.is_symlink():
            try:
                target = os.readlink(probe)
            except OSError:
                target = "?"
            raise OutputError(f"{flag} {path}: {probe} is a symbolic link to {target}, which leads nowhere (a loop "
                              "of links, or a disk that is not mounted); fix or remove the link, or choose another "
                              "path")
        probe = probe.parent


def read_only_file_system(path: Path) -> bool:
    """Whether ``path`` lies on a file system mounted read-only (a read-only bind mount, a snapshot, a CD): no
    permission of the user's would help there, so the message says that instead of "no permission"."""
    try:
        return bool(os.statvfs(path).f_flag & os.ST_RDONLY)
    except (OSError, AttributeError):  # no statvfs (Windows)
        return False


def check_name_lengths(path: Path, flag: str) -> None:
    """Each name in ``path`` fits in a file name (``NAME_MAX`` bytes): a longer one raised a raw ENAMETOOLONG
    from the first ``stat``."""
    for part in path.parts:
        size = len(os.fsencode(part))
        if size > NAME_MAX:
            raise OutputError(f"{flag} {path}: the name {part[:40]}... is {size} bytes long, more than a file name "
                              f"can be ({NAME_MAX}); choose a shorter one")


def _check_parent(path: Path, flag: str) -> None:
    check_no_broken_link(path, flag)
    base = _first_existing(path.parent)
    if not base.is_dir():
        raise OutputError(f"{flag} {path}: {base} is a file, so nothing can be written below it; choose another path")
    if not os.access(base, os.W_OK | os.X_OK):
        if read_only_file_system(base):
            raise OutputError(f"{flag} {path}: {base} is on a read-only file system; choose a folder on a writable one")
        raise OutputError(f"{flag} {path}: no permission to write in {base}; choose a writable folder")


def _is_torch_checkpoint(path: Path) -> bool:
    """Whether ``path`` is an existing file in torch.save's zip format (an entry ``ARCHIVE/data.pkl``)."""
    import zipfile

    try:
        with open(path, "rb") as f:
            if f.read(4) != b"PK\x03\x04":
                return False
        with zipfile.ZipFile(path) as archive:
            return any(name == "data.pkl" or name.endswith("/data.pkl") for name in archive.namelist())
    except (OSError, zipfile.BadZipFile):
        return False


def same_path(a: Path, b: Path) -> bool:
    """Whether ``a`` and ``b`` both exist and are one file or folder (through links, too)."""
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def check_not_dash(path: str | Path, flag: str) -> None:
    """``-`` (stdout for Unix tools) names no file here: a file or folder called '-' was written in the working
    directory, and the one line said only "wrote -"."""
    if str(path) == "-":
        raise OutputError(f"{flag} -: the output is written to a file, not to stdout; give a file or folder name "
                          "(on Linux, /dev/stdout writes a file's text to the terminal)")


def is_stream(path: str | Path) -> bool:
    """Whether ``path`` is a terminal, a pipe or another device (``/dev/stdout``, ``/dev/null``, a named pipe): no
    temporary can be renamed over it, so ``atomic_path`` writes it directly."""
    try:
        mode = os.stat(path).st_mode  # through links: /dev/stdout -> /proc/self/fd/1 -> a pipe or /dev/pts/N
    except (OSError, ValueError):
        return False
    return stat.S_ISCHR(mode) or stat.S_ISFIFO(mode) or stat.S_ISSOCK(mode)


def check_output_file(path: str | Path, flag: str = "output file",
                      inputs: Iterable[tuple[str | Path | None, str]] = ()) -> Path:
    """Before the work: ``path`` can be written as a file (it is not a folder, and it or the first
    existing folder above it is writable). ``flag`` names the option in the message (``--out``).
    ``inputs``: (path, option) pairs of the job's input files, which the output must not replace."""
    check_not_dash(path, flag)
    if is_stream(path):  # /dev/stdout (`| jq`), /dev/null: written directly, whatever the folder /dev allows
        return Path(path)
    path = Path(path)
    check_name_lengths(path, flag)
    for source, option in inputs:
        if source is not None and same_path(path, Path(source)):
            raise OutputError(f"{flag} {path} is the {option} file the job reads; writing the result there would "
                              "destroy it: choose another output path")
    if path.is_dir():
        raise OutputError(f"{flag} {path}: is a folder; give a file name (e.g. {path / 'out.json'})")
    if _is_torch_checkpoint(path):  # export-onnx ... --out runs/x/best.pt: no job here writes a checkpoint
        raise OutputError(f"{flag} {path} is a PyTorch checkpoint; writing the result there would destroy it: choose "
                          "another output path (or remove the checkpoint first)")
    if path.exists() and not os.access(path, os.W_OK):
        if read_only_file_system(path):
            raise OutputError(f"{flag} {path}: the file is on a read-only file system; choose a path on a writable one")
        raise OutputError(f"{flag} {path}: the file is not writable; choose another path")
    _check_parent(path, flag)
    return path


def check_output_dir(path: str | Path, flag: str = "output folder") -> Path:
    """Before the work: ``path`` can be an output folder (it is not a file, and it or the first
    existing folder above it is writable)."""
    check_not_dash(path, flag)
    path = Path(path)
    check_name_lengths(path, flag)
    check_no_broken_link(path, flag)
    if path.exists() and not path.is_dir():
        raise OutputError(f"{flag} {path}: is a file, not a folder; choose another path")
    if path.is_dir():
        if not os.access(path, os.W_OK | os.X_OK):
            if read_only_file_system(path):
                raise OutputError(f"{flag} {path}: is on a read-only file system; choose a folder on a writable one")
            raise OutputError(f"{flag} {path}: no permission to write in it; choose a writable folder")
    else:
        _check_parent(path, flag)
    return path


def process_alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this machine (one of another user counts as alive)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    return True


def remove_stale_temporaries(path: str | Path, tag: str = "tmp") -> list[Path]:
    """Remove the ``.NAME.TAG-PID`` siblings of ``path`` (``atomic_path``'s temporaries) that processes
    which are gone left behind (``kill -9``, a power cut): the next writer of ``path`` owns them. One
    whose PID is alive (another process writing now) is left alone. Returns the paths removed."""
    path = Path(path)
    removed: list[Path] = []
    if not path.parent.is_dir():
        return removed
    # .NAME.TAG-PID, and .STEM.TAG-PID.SUFFIX (keep_suffix)
    for prefix, suffix in ((f".{_fitted(path.name, tag)}.{tag}-", ""),
                           (f".{_fitted(path.stem, tag, path.suffix)}.{tag}-", path.suffix)):
        for tmp in path.parent.glob(prefix + "*"):
            pid = tmp.name[len(prefix):len(tmp.name) - len(suffix)]
            if (tmp.name.endswith(suffix) and pid.isdigit() and int(pid) != os.getpid()
                    and not process_alive(int(pid)) and tmp not in removed):
                remove_path(tmp)
                removed.append(tmp)
    return removed


NAME_MAX = 255  # bytes in one file name (ext4, XFS, Btrfs, tmpfs, NFS)


def _fitted(name: str, tag: str, suffix: str = "") -> str:
    """``name`` cut (on a character) so that ``.NAME.TAG-PID{suffix}`` fits in ``NAME_MAX`` bytes for any PID: a
    valid file name of 240 bytes had a temporary name too long to create (a raw ENAMETOOLONG after the work)."""
    room = NAME_MAX - len(f"..{tag}-{suffix}".encode()) - 10  # a PID has at most 10 digits
    return name.encode()[:max(room, 0)].decode(errors="ignore")  # a character cut in two is dropped


def temporary_sibling(path: str | Path, tag: str = "tmp", keep_suffix: bool = False) -> Path:
    """``.NAME.TAG-PID`` next to ``path``: where ``atomic_path`` writes before the rename
    (``.STEM.TAG-PID.SUFFIX`` with ``keep_suffix``, for writers that choose a format by the suffix); a long NAME
    is cut to keep it a valid file name (``_fitted``)."""
    path = Path(path)
    if keep_suffix:
        return path.with_name(f".{_fitted(path.stem, tag, path.suffix)}.{tag}-{os.getpid()}{path.suffix}")
    return path.with_name(f".{_fitted(path.name, tag)}.{tag}-{os.getpid()}")


def remove_path(path: Path, ignore_errors: bool = True) -> None:
    """Remove the file or folder at ``path`` (a symbolic link itself, not what it points to); nothing if none."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=ignore_errors)
    elif os.path.lexists(path):
        path.unlink()


def _replace(src: Path, dst: Path) -> None:
    """The rename step (a function of its own so tests can interrupt between write and rename)."""
    os.replace(src, dst)


_TARGET_OF: dict[Path, Path] = {}  # a live temporary -> the file it becomes (named in the errors of writes into it)
OLD_TAG = "old"  # .NAME.old-PID: a folder being replaced, renamed aside until the new one is in place


def _replace_folder(tmp: Path, path: Path) -> None:
    """``tmp`` over the folder ``path`` (os.replace renames a folder only over an empty one): the old folder is
    renamed aside, the new one renamed in, and only then is the old one removed. Removing it first (a large
    synthetic world takes seconds) left, on a Ctrl-C or a kill during the removal, a half-deleted folder at
    ``path`` that still looked whole (its manifest, tables and maps, part of its images), and the new one was
    removed with the temporaries. A kill now leaves ``.NAME.old-PID``, which the next writer removes."""
    old = temporary_sibling(path, OLD_TAG)
    remove_path(old)  # left by an earlier write of this very process id
    os.replace(path, old)
    try:
        _replace(tmp, path)
    except BaseException:
        os.replace(old, path)
        raise
    remove_path(old)


@contextmanager
def atomic_path(path: str | Path, tag: str = "tmp", keep_suffix: bool = False) -> Iterator[Path]:
    """Yield a temporary sibling of ``path`` (``temporary_sibling``) to write a file or a folder at (module
    docstring); every atomic writer removes its target's leftovers first. A symbolic link at ``path`` is written
    through (a rename over the link would replace it and leave the file it points to as it was). A terminal, pipe
    or device (``/dev/stdout``, ``is_stream``) gets the file's bytes once it is complete (no temporary can be made
    beside it: /dev/stdout was refused, though the refusal of ``--out -`` advised it)."""
    path = Path(path)
    if is_stream(path):
        with tempfile.TemporaryDirectory(prefix=".instagram_hdmap-", ignore_cleanup_errors=True) as folder:
            tmp = Path(folder) / path.name
            yield tmp
            if tmp.is_dir():
                raise OutputError(f"{path}: a terminal, pipe or device takes a file, not a folder; choose a path")
            if tmp.is_file():  # (not shutil.copyfile: it refuses a named pipe)
                with open(tmp, "rb") as src, open(path, "wb") as dst:
                    shutil.copyfileobj(src, dst)
        return
    if path.is_symlink() and path.exists():
        path = Path(os.path.realpath(path))
    tmp = temporary_sibling(path, tag, keep_suffix)
    shown = _TARGET_OF.get(path, path)  # a set written together writes each file through a temporary of its own
    _TARGET_OF[tmp] = shown
    try:
        check_no_broken_link(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(path, tag)
        remove_stale_temporaries(path, OLD_TAG)
        yield tmp
        if tmp.is_file():
            if path.is_dir() and not path.is_symlink():
                raise OutputError(f"{path}: is a folder, so a file cannot be written there; choose another path")
            with open(tmp, "rb+") as f:
                os.fsync(f.fileno())
        if tmp.is_dir() and path.is_dir() and not path.is_symlink():
            _replace_folder(tmp, path)
        else:
            _replace(tmp, path)
    except Exception as e:  # a full disk or an unwritable place, named (Ctrl-C passes through)
        cause = os_error_in(e)
        if cause is None or isinstance(e, UserError):
            raise
        if cause.errno in NO_ROOM:
            raise OutputError(f"cannot write {shown}: {cause.strerror or cause} (the disk is full or a file-size "
                              f"limit is reached); {shown.name} is as it was before; free some space and run "
                              "again") from e
        if cause.errno in (errno.EACCES, errno.EROFS, errno.ENOTDIR, errno.EISDIR, errno.EPERM):
            raise OutputError(f"cannot write {shown}: {cause.strerror or cause}; choose a writable path") from e
        if cause.filename is not None and str(cause.filename) in (str(tmp), str(path), str(path.parent)):
            # another failure of the write itself (a file system that takes no new files, such as /proc, or a
            # folder removed while the job ran): named, not a traceback
            raise OutputError(f"cannot write {shown}: {cause.strerror or cause}; choose another path") from e
        raise
    finally:
        _TARGET_OF.pop(tmp, None)
        remove_path(tmp)


def write_text(text: str, path: str | Path) -> Path:
    """Write ``text`` to ``path`` atomically; returns the path."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return path


def json_safe(obj):
    """``obj`` with every NaN or infinite number (a float, or a NumPy / torch scalar) as None: JSON has no NaN, and
    the ``NaN`` / ``Infinity`` that Python's json writes by default are refused by strict readers (jq, JavaScript,
    Go, pandas' ``lines=True`` reader in some versions, ``json.loads(..., parse_constant=...)``): they read
    ``null``. Other scalars become ints or floats; dicts, lists and tuples are copied."""
    if obj is None or isinstance(obj, (str, bool, int)):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if hasattr(obj, "item") and getattr(obj, "ndim", None) == 0:  # numpy.float32 / int64, a 0-d tensor
        return json_safe(obj.item())
    return obj


def json_text(obj, indent: int | None = None, **kwargs) -> str:
    """``obj`` as standard JSON: NaN and infinities as ``null`` (``json_safe``)."""
    return json.dumps(json_safe(obj), indent=indent, allow_nan=False, **kwargs)


def write_json(obj, path: str | Path, indent: int | None = None) -> Path:
    """Write ``obj`` as standard JSON atomically; returns the path. NaN and infinity (e.g. the raster AP of a class
    with no GT, a flicker rate with no pairs) are written as ``null``, which every JSON reader takes (``NaN`` is not
    JSON)."""
    return write_text(json_text(obj, indent=indent), path)


LOCK_FILE = ".instagram_hdmap.lock"  # held (flock) by the process whose job writes the folder
_LOCKS: dict[str, object] = {}  # resolved folder -> the open lock file this process holds


def lock_folder(folder: str | Path, job: str, advice: str, note: Callable[[str], None] = print) -> None:
    """Hold an exclusive lock on ``FOLDER/.instagram_hdmap.lock`` while this process's ``job`` writes
    ``folder``: a second one started there (the same command run twice: two trainings into one
    ``train.out_dir``, two evaluations into one ``--out``) is refused before it removes or overwrites anything of
    the first one's, "another JOB is running in FOLDER (process PID); ... or ADVICE". The OS drops the lock when the
    process ends, however it ends (``kill -9`` too): the file a killed job leaves locks nothing. Re-entrant within
    a process. No lock where ``fcntl`` is missing; on a file system without locks (NFS without lockd, some FUSE
    mounts: ENOLCK) the job goes on and ``note`` says so."""
    if fcntl is None:
        return
    folder = Path(folder)
    key = str(folder.resolve())
    if key in _LOCKS:
        return
    try:
        handle = os.fdopen(os.open(folder / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644), "r+")
    except OSError as e:  # a folder of that name was a raw IsADirectoryError
        what = "is a folder, not the lock file; remove it" if (folder / LOCK_FILE).is_dir() else (
            f"cannot be opened ({e.strerror or e})")
        raise UserError(f"{folder / LOCK_FILE} (the lock this {job} holds on {folder}) {what}, or {advice}") from None
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:  # EWOULDBLOCK: another process holds it
        owner, _, theirs = handle.read().strip().partition(" ")  # "PID JOB" (a bare PID: a lock of an older version)
        handle.close()  # (their job, not ours: an evaluation into a running training's folder was "another evaluation")
        raise UserError(f"another {theirs or job} is running in {folder} (process {owner or '?'}); wait for it to end "
                        f"(or stop it), or {advice}") from None
    except OSError as e:  # no locks on this file system: was read as "another job is running"
        handle.close()
        with contextlib.suppress(OSError):
            (folder / LOCK_FILE).unlink()
        note(f"note: {folder} takes no file lock ({e.strerror or e}): a second {job} started in it while this one "
             "runs is not refused there")
        return
    handle.seek(0)
    handle.truncate()
    handle.write(f"{os.getpid()} {job}\n")
    handle.flush()
    _LOCKS[key] = handle


def unlock_folder(folder: str | Path) -> None:
    """Give up ``lock_folder``'s lock on ``folder`` (the end of the job) and remove its file; nothing if not held."""
    try:
        key = str(Path(folder).resolve())
    except (OSError, RuntimeError):  # a loop of links (check_output_dir named it): no lock was taken
        return
    handle = _LOCKS.pop(key, None)
    if handle is not None:
        with contextlib.suppress(OSError):
            (Path(folder) / LOCK_FILE).unlink()  # while still held: the folder is left as the job wrote it
        handle.close()


# The synthetic worlds' manifests (world.json) that this process reads the world of: a shared lock on each, held while
# a dataset of it lives, tells a world generator in another process not to replace the world under it
_READING: dict[str, list] = {}


def hold_world(root: str | Path, manifest: str = "world.json"):
    """A shared lock (flock) on ``root/manifest`` when there is one (a world written by ``synth``), as an open file
    (None where none is taken) that the caller gives back with ``release_world`` (``data.build_dataset``: when its
    dataset is collected). While it is held, ``claim_world`` in another process (``synth --force`` of that folder) is
    refused instead of replacing the world under this one's datasets (the same file names, other scenes: a training
    went on with the new world's images and the old world's maps and poses, exit 0). Nothing where there is no
    manifest, no fcntl or no file locks (read-only folders lock too: the file is opened for reading)."""
    if fcntl is None:
        return None
    try:
        path = Path(root) / manifest
        key = str(path.resolve())
        if not path.is_file():
            return None
        handle = open(path, "rb")  # given back by release_world
    except (OSError, RuntimeError, TypeError, ValueError):  # (a dataroot the dataset itself names)
        return None
    try:
        fcntl.flock(handle, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:  # a generator replacing it right now, or no locks here: nothing held
        handle.close()
        return None
    _READING.setdefault(key, []).append(handle)
    return handle


def release_world(handle) -> None:
    """Give back a lock of ``hold_world`` (nothing if already given back)."""
    for held in _READING.values():
        if handle in held:
            held.remove(handle)
    handle.close()


def claim_world(root: str | Path, what: str, manifest: str = "world.json"):
    """An exclusive lock on the world at ``root`` that is about to be replaced (None where there is none to lock),
    held by the caller until the replacement is done. This process's own ``hold_world`` of it is given up (its
    own doing); another process's is a ``UserError`` naming ``what`` (the argument, e.g. --out)."""
    if fcntl is None:
        return None
    path = Path(root) / manifest
    try:
        if not path.is_file():
            return None
        for own in _READING.pop(str(path.resolve()), []):  # this process's own datasets: its own doing
            own.close()
        handle = open(path, "rb")  # the caller closes it
    except (OSError, RuntimeError):
        return None
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.close()
        raise UserError(f"{what} {root}: the world there is being read by another process (a training, evaluation "
                        f"or prediction with data.dataroot={root}); replacing it now would change its images under "
                        "it (the same file names, other scenes): wait for that process to end, or choose another "
                        f"{what}") from None
    except OSError:  # no locks on this file system
        handle.close()
        return None
    return handle


def held_folder_now(folder: str | Path) -> Path | str | None:
    """Where the folder this process holds ``lock_folder``'s lock on is now (moved or renamed since: its lock file,
    followed through /proc): its path, "removed" when its lock file was deleted (the folder removed), None where
    that is not known (no lock held, no /proc)."""
    try:
        handle = _LOCKS.get(str(Path(folder).resolve()))
        if handle is None:
            return None
        target = os.readlink(f"/proc/self/fd/{handle.fileno()}")
    except (OSError, RuntimeError, ValueError):
        return None
    return "removed" if target.endswith(" (deleted)") else Path(target).parent


@contextmanager
def locked_folder(folder: str | Path, job: str, advice: str, note: Callable[[str], None] = print,
                  enabled: bool = True) -> Iterator[Path]:
    """``folder`` created if missing and held with ``lock_folder`` while the block runs (``enabled``: False on the
    processes that do not write it, under torchrun); given up after, and the folders it created removed again when
    the block fails before writing anything into them (nothing left of a refused or failed job)."""
    folder = Path(folder)
    if not enabled:
        yield folder
        return
    created = [p for p in (folder, *folder.parents) if not p.exists()]  # innermost first
    folder.mkdir(parents=True, exist_ok=True)
    ok = False
    try:
        lock_folder(folder, job, advice, note)
        yield folder
        ok = True
    finally:
        unlock_folder(folder)
        if not ok:
            for p in created:  # innermost first; rmdir only removes empty folders
                with contextlib.suppress(OSError):
                    p.rmdir()
