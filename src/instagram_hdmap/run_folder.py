"""A training run's folder: what it holds (config, log, checkpoints), made ready for a new run or a
resumed one, its log cut back to the resumed step, and the lock that keeps a second job out.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

from . import distributed as du
from .errors import UserError
from .files import (
    LOCK_FILE,
    check_output_dir,
    held_folder_now,
    lock_folder,
    remove_path,
    remove_stale_temporaries,
    write_text,
)

# What a run writes in its output folder (``--force`` removes these and nothing else)
RUN_FILES = ("config.yaml", "log.jsonl", "tb", "last.pt", "best.pt")
CHECKPOINTS = ("last.pt", "best.pt")


def prepare_out_dir(out_dir: Path, resume: str | Path | None, force: bool) -> None:
    """The output folder, checked before anything is built: a folder (not a file) that can be written;
    one that holds a run (a checkpoint) only with ``--resume`` or ``--force`` (which removes that run's
    files, ``RUN_FILES``, and nothing else); one whose run stopped before its first checkpoint (only
    config.yaml, log.jsonl, tb/) is started over. Partial files of killed saves of this folder's run
    are removed when their process is gone."""
    if force and resume:
        raise UserError("--force starts a run over and --resume continues one; pass one of them, not both")
    check_output_dir(out_dir, "train.out_dir")
    if not du.is_main_process():
        return
    out_dir.mkdir(parents=True, exist_ok=True)
    lock_out_dir(out_dir)  # before anything in it is removed
    for name in RUN_FILES:
        remove_stale_temporaries(out_dir / name)
    content = [p.name for p in out_dir.iterdir() if p.name != LOCK_FILE]
    has_checkpoint = any(name in content for name in CHECKPOINTS)
    only_run_files = all(name in RUN_FILES for name in content)
    if content and not (resume or force):
        if not has_checkpoint and not only_run_files:  # no run to continue: --resume of a checkpoint not there
            raise UserError(f"output folder {out_dir} holds files that are not a run's "
                            f"({', '.join(sorted(content)[:5])}); choose another train.out_dir (a new or empty "
                            "folder), or pass --force to train among them (it removes only a run's own files)")
        if has_checkpoint:
            # a save that failed after best.pt (a full disk) leaves no last.pt; best.pt resumes as well
            ckpt = out_dir / ("last.pt" if "last.pt" in content else "best.pt")
            raise UserError(f"output folder {out_dir} already holds a run; pass --resume {ckpt} to continue it, "
                            "--force to start over in it, or choose another train.out_dir")
        du.print_main(f"{out_dir}: a run stopped before its first checkpoint; starting it over")
        force = True
    # the folder of the checkpoint itself: a symbolic link to it (latest.pt -> run/last.pt) names the run it is in
    source = Path(resume).resolve().parent if resume and Path(resume).is_file() else None
    if source is not None and has_checkpoint and source.resolve() != out_dir.resolve():
        raise UserError(f"--resume {resume} continues the run of {source}, but train.out_dir={out_dir} holds a "
                        "run of its own, whose checkpoints and log it would overwrite; set "
                        f"train.out_dir={source} (or an empty folder to continue it elsewhere)")
    if force:
        for name in RUN_FILES:
            remove_path(out_dir / name, ignore_errors=False)
    # what the run appends to or writes in must be of its kind (they raised a raw FileExistsError from
    # TensorBoard or an IsADirectoryError from open() once the model and loaders were built)
    for name, folder, what in (("tb", True, "TensorBoard events"), ("log.jsonl", False, "log"),
                               ("config.yaml", False, "resolved config")):
        target = out_dir / name
        if target.exists() and target.is_dir() != folder:
            raise UserError(f"train.out_dir {out_dir}: {name} is a {'folder' if target.is_dir() else 'file'}, "
                            f"where the run keeps its {what} in a {'folder' if folder else 'file'}; move it away "
                            "(or pass --force to start the run over)")


def purge_log(path: Path, lines: int, note: Callable[[str], None]) -> int:
    """Keep the first ``lines`` lines of a resumed run's ``log.jsonl``, the lines written before the checkpoint
    it resumes from (its ``log_lines``): a killed run's lines after it (an epoch's line is written before the
    checkpoint of that epoch, so a kill between the two loses none) go, as the resume trains those steps again
    and logs them anew, where they showed twice. Returns how many lines the log holds after."""
    if not path.is_file():
        return 0
    text = path.read_text(encoding="utf-8", errors="replace").splitlines(keepends=True)
    keep = [line for line in text[:lines] if line.endswith("\n")]  # not a line the kill cut short
    if len(keep) < len(text):
        write_text("".join(keep), path)
        note(f"{path}: dropped {len(text) - len(keep)} line(s) written after the checkpoint by the run that was "
             "stopped; the resume trains those steps again and logs them anew")
    return len(keep)


def lock_out_dir(out_dir: Path) -> None:
    """``files.lock_folder`` of ``train.out_dir``: a second training started there is refused before it removes
    or overwrites anything of the first one's."""
    lock_folder(out_dir, "training", "choose another train.out_dir", du.print_main)


def moved_folder_error(out_dir: Path, step: int, cause: OSError | None) -> UserError:
    """The error of a run whose ``train.out_dir`` was moved or removed while it wrote there, saying where it
    is now (when it can be found) and how to resume."""
    now = held_folder_now(out_dir)
    again = "the steps since its last checkpoint are trained again"
    where = ("it was removed, and its checkpoints with it: start the run again" if now == "removed" else
             f"it is now {now}: resume there with --resume {now / 'last.pt'} train.out_dir={now} ({again})"
             if isinstance(now, Path) else "its checkpoints went with it: if it was moved, resume from its "
             f"last.pt there, with train.out_dir set to that folder ({again})")
    name = cause.filename if cause is not None else None
    why = (f" ({cause.strerror or cause}" + (f": {os.fsdecode(name)}" if isinstance(name, (str, bytes)) else "")
           + ")") if cause is not None else ""
    return UserError(f"train.out_dir {out_dir} was moved or removed while this run wrote to it{why}; the run "
                     f"stopped at step {step}; {where}")
