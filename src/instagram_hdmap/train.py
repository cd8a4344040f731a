"""``instagram-hdmap train``: build every part from the config, run the epochs, save and resume.

The output folder holds ``config.yaml`` (resolved), ``log.jsonl`` (one line per epoch and
validation), ``tb/`` (TensorBoard events), ``last.pt`` and ``best.pt``.
A run killed at any point resumes with ``--resume OUT/last.pt`` on the next unseen batch, with
the same optimizer, schedule progress, scaler and RNG states: on CPU with
``train.deterministic=true`` the resumed weights equal those of an uninterrupted run to float32
rounding (oneDNN's convolutions may round a last bit differently in a new process), with
augmentation and data workers too, since each sample's augmentation is drawn from
(train.seed, epoch, index) alone
(``NuScenesMapDataset.augmentation_rng``).

A temporal model (``model.temporal.memory=bev``) trains on drives: its batch rows are streams walking
whole scenes in order (``data.streaming.StreamingBatchSampler``) and each step gets the memory the
previous one returned, detached. The memory is part of the checkpoint: a run stopped part-way through
an epoch saves every rank's memory of its streams with ``last.pt`` and the resumed run continues the
streams with it, so exact resume holds for temporal models too. Only Ctrl-C under torchrun saves no
memory (gathering it is a collective the ranks may not all reach): those streams then resume without
history, as at a scene start (``memory_status`` no_memory), until their next scene.
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import os
import random
import re
import shutil
import sys
import threading
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from . import distributed as du
from .checkpoint import (
    CheckpointError,
    check_resumable,
    load_checkpoint,
    rng_preserved,
    rng_state,
    save_checkpoint,
    set_rng_state,
)
from .config import (
    DataConfig,
    EvalConfig,
    ExperimentConfig,
    GraphHeadConfig,
    TrainConfig,
    UserError,
    as_config,
    config_to_dict,
    diff_configs,
    flatten,
    get_key,
    is_under,
    save_config,
)
from .data import build_dataset
from .data.base import collate_fn
from .data.streaming import StreamingBatchSampler
from .engine import EpochHooks, Position, StepInfo, StepSettings, evaluate, train_one_epoch
from .evaluation import Evaluator
from .evaluation.consistency import ConsistentAPMeter, FlickerMeter
from .files import (
    LOCK_FILE,
    check_output_dir,
    held_folder_now,
    json_safe,
    json_text,
    lock_folder,
    remove_stale_temporaries,
    unlock_folder,
    write_text,
)
from .geometry import BEVGrid
from .inference import MODEL_KEYS, NOT_BAKED, saved_config
from .losses import Criterion
from .models import build_model, random_init_warning
from .models.backbone import imagenet_state
from .persistence import Persistence
from .postprocess import DECODE_KEYS, decode_options, postprocess_batch
from .resources import check_fits, data_workers, size_notes, usable_cores
from .schedule import ProgressClock, final_lr_factor, lr_factor

# Config keys that must match for a checkpoint to be resumed: those that define the model and those
# that define its training targets (training knobs may change).
# train.batch_size: the position in an epoch and the schedule's length are counted in its batches (a new
# one skipped the rest of the epoch and moved the learning rate along the schedule)
# train.seed: the epochs' sample order (the saved position counts batches of that order)
# data.ped_crossing: the crossings' targets (edges or rings), data.image_fit: the images the model learns from (a
# resume with another one switched them mid-run with no word)
RESUME_KEYS = (*MODEL_KEYS, "loss", "data.sample_dist", "data.ped_crossing", "data.image_fit", "train.batch_size",
               "train.trainable", "train.seed")
# a temporal model's epoch is a schedule of streams: its length and the memory rows depend on these too (a
# new value walked other pieces from the saved position, or none, and moved the learning rate)
STREAM_RESUME_KEYS = ("train.stream_frames", "train.stream_warmup")
# the model keys a resume may change: read at inference only (the decoding options, element persistence) or not at
# all on a resume (the ImageNet weights, which the checkpoint's replace), or a training knob that leaves the model's
# computation as it is (gradient checkpointing trades memory for time; the memory dropout's rate); a resume with
# model.backbone.grad_checkpoint=true after running out of memory was refused as "an incompatible config"
RESUME_FREE = tuple(k for k in NOT_BAKED if k != "data.av2_cameras")  # (the AV2 cameras: which images, in which order)
# what the validation score that picks best.pt measures: a resume may change them, but its scores are then of another
# kind than the best score it carries (a raster mAP compared with a vector one, another split's, other decoding's),
# which a note says
SCORE_KEYS = ("eval.protocol", "eval.thresholds", "eval.rank_by", "eval.fix_instance_ids", "data.val_split",
              *DECODE_KEYS, "model.temporal.persist_frames", "model.temporal.persist_decay",
              "model.temporal.persist_match_m")
# the training settings a resume may change, which then hold from its position on (the steps so far were trained with
# the checkpoint's): said in a note, as config.yaml and the next checkpoints record only the new values (a resume with
# another train.lr, train.schedule or train.warmup went on with no word, the run's record rewritten)
RESUME_NOTED = ("train.epochs", "train.lr", "train.weight_decay", "train.schedule", "train.lr_step", "train.lr_gamma",
                "train.warmup", "train.min_lr_factor", "train.grad_clip", "train.amp", "train.on_nonfinite",
                "train.deterministic", "data.augment", "data.aug_scale", "data.aug_rotate_deg", "data.aug_crop_jitter",
                "data.camera_dropout", "data.on_bad_sample", "model.temporal.drop_prob")


def train_set_fingerprint(loader) -> dict | None:
    """The training split a run walks, as its sample count and a hash of its sample tokens in order (None for
    a dataset without tokens). A checkpoint keeps it: its position and schedule count batches of that split."""
    tokens = getattr(getattr(loader, "dataset", None), "sample_tokens", None)
    if not isinstance(tokens, list) or not all(isinstance(t, str) for t in tokens):
        return None
    return {"samples": len(tokens), "sha256": hashlib.sha256("\n".join(tokens).encode()).hexdigest()[:16]}


def check_same_train_set(saved: dict | None, now: dict | None, path: Path | str) -> None:
    """A resume walks the training split its checkpoint counted batches of (``train_set_fingerprint``): another
    one (scenes added or removed, another ``data.splits_file`` or ``data.dataroot``) ended the schedule early
    ("done" after no step when the split shrank) or late, and the saved position skipped or repeated samples,
    with exit 0 and no word."""
    if not isinstance(saved, dict) or now is None or saved == now:
        return
    before, after = saved.get("samples"), now["samples"]
    what = (f"{before} samples then, {after} now" if before != after else
            f"{after} samples then and now, but other samples or another order")
    raise CheckpointError(f"checkpoint {path} was trained on another training split ({what}: data.dataroot, "
                          "data.splits_file or the split's scenes changed); its position and schedule count "
                          "batches of that split, so a resume would skip or repeat samples and end the schedule "
                          "early or late: resume with the data it was trained on, or start a new run from its "
                          f"weights (train.init_from={path})")


WORKER_DIED = re.compile(r"DataLoader worker \(pids?\(?s?\)? ?[\d, ]+\)? (is killed by signal|exited unexpectedly)")


def data_worker_died(e: BaseException) -> str | None:
    """torch's message when a data-loader worker process died (the out-of-memory killer's choice, a ``kill -9``),
    first line only; None for another exception."""
    text = str(e).strip()
    return text.splitlines()[0] if isinstance(e, RuntimeError) and WORKER_DIED.search(text) else None


class DataWorkerError(UserError):
    """A data-loader worker died during a training: ``last.pt`` was saved at the last completed step."""


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)  # noqa: NPY002 (seeds the global stream third-party code uses)
    torch.manual_seed(seed)


def _worker_init(worker_id: int) -> None:
    # Each worker's NumPy/random streams derive from torch's per-worker seed (itself a function of
    # the base seed drawn in the main process, which is part of the checkpointed RNG state).
    seed = torch.initial_seed() % 2**32
    np.random.seed(seed)  # noqa: NPY002 (seeds the global stream third-party code uses)
    random.seed(seed)


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
    if out_dir.is_dir():
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
                target = out_dir / name
                if target.is_dir() and not target.is_symlink():
                    shutil.rmtree(target)
                elif target.exists() or target.is_symlink():
                    target.unlink()
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


def config_differences(old: ExperimentConfig, cfg: ExperimentConfig, keys) -> str:
    """The keys under ``keys`` whose values differ, as "key: checkpoint X vs now Y; ..." ("" if none)."""
    differ = [k for k in diff_configs(old, cfg) if is_under(k, keys)]
    old_d, new_d = config_to_dict(old), config_to_dict(cfg)
    return "; ".join(f"{k}: checkpoint {get_key(old_d, k)!r} vs now {get_key(new_d, k)!r}" for k in differ)


def check_resume_config(ckpt_cfg: dict, cfg: ExperimentConfig, path: Path) -> None:
    old = saved_config(ckpt_cfg, f"checkpoint {path}")
    keys = RESUME_KEYS + (STREAM_RESUME_KEYS if cfg.model.temporal.memory != "none" else ())
    differ = [k for k in diff_configs(old, cfg) if is_under(k, keys) and not is_under(k, RESUME_FREE)]
    lines = config_differences(old, cfg, differ)
    if lines:
        raise CheckpointError(f"checkpoint {path} was trained with an incompatible config ({lines}); resume it with "
                              f"the config it was trained with, or start a new run from its weights with "
                              f"train.init_from={path} and another train.out_dir")


def check_batch_over_ranks(cfg: ExperimentConfig, world_size: int) -> None:
    """``train.batch_size`` is the total over all processes (docs/guide.md, "Distributed training"): each rank takes
    ``batch_size / world``. One that the ranks do not divide trained with another total and no word (3 over 2
    ranks: 2; 1 over 2 ranks: 2), the learning rate and schedule set for the other."""
    b = cfg.train.batch_size
    if world_size > 1 and b % world_size:
        lower, upper = max(b // world_size, 1) * world_size, (b // world_size + 1) * world_size
        raise UserError(f"config key 'train.batch_size'={b} is the batch over all {world_size} processes of torchrun, "
                        f"which it does not divide (each would take {b / world_size:g} samples); use "
                        + (f"{lower} or {upper}" if lower != upper and lower < b else f"{upper}")
                        + f" ({world_size} processes), or run {b} process(es)")


OPEN_FILES_FOR_WORKERS = 4096  # the open-file limit under which data-loader workers hand tensors over by name


def open_files_for_workers(num_workers: int) -> None:
    """Data-loader workers hand each batch's tensors to this process through file descriptors (torch's
    sharing strategy ``file_descriptor``: one per tensor in flight, received over a socket). Under a low
    limit on open files (``ulimit -n``) they ran out: the run hung for good, a thread printing "OSError:
    [Errno 24] Too many open files" tracebacks without end. The soft limit is raised towards the hard one (up
    to ``OPEN_FILES_FOR_WORKERS``); where it stays below that, the tensors go through named shared memory
    (``file_system``), which holds no descriptor."""
    if num_workers <= 0:
        return
    try:
        import resource
    except ImportError:  # not POSIX: torch's default there needs no descriptors
        return
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    unlimited = resource.RLIM_INFINITY
    if soft == unlimited or soft >= OPEN_FILES_FOR_WORKERS:
        return
    raised = OPEN_FILES_FOR_WORKERS if hard == unlimited else min(hard, OPEN_FILES_FOR_WORKERS)
    if raised > soft:
        with contextlib.suppress(ValueError, OSError):
            resource.setrlimit(resource.RLIMIT_NOFILE, (raised, hard))
            soft = raised
    if soft < OPEN_FILES_FOR_WORKERS and torch.multiprocessing.get_sharing_strategy() == "file_descriptor":
        torch.multiprocessing.set_sharing_strategy("file_system")


def build_loaders(cfg: ExperimentConfig, world_size: int, with_val: bool = True):
    """(train loader, its sampler, val loader). A temporal model (``model.temporal.memory`` not none)
    reads drives: each rank's batch rows are streams walking whole scenes in order
    (``data.streaming.StreamingBatchSampler``, ``train.batch_size / world`` streams per rank, in pieces
    of ``train.stream_frames``, after ``train.stream_warmup`` of the epochs on shuffled single frames;
    the validation loader ``eval.batch_size`` streams of whole scenes)."""
    train_set = build_dataset(cfg, cfg.data.train_split, augment=cfg.data.augment)
    open_files_for_workers(cfg.data.num_workers)
    per_rank = max(cfg.train.batch_size // world_size, 1)
    streaming = cfg.model.temporal.memory != "none"
    common = {"collate_fn": collate_fn, "num_workers": data_workers(cfg.data.num_workers, len(train_set)),
              "worker_init_fn": _worker_init,
              "persistent_workers": False,
              # its own generator: making an iterator must not draw from the global torch RNG, whose
              # state the checkpoint restores for exact resume
              "generator": torch.Generator().manual_seed(cfg.train.seed)}
    if streaming:
        sampler = StreamingBatchSampler(train_set.scenes.runs, per_rank, shuffle=True, seed=cfg.train.seed,
                                        rank=du.get_rank(), world_size=world_size,
                                        piece_frames=cfg.train.stream_frames,
                                        single_epochs=round(cfg.train.stream_warmup * cfg.train.epochs))
        train_loader = DataLoader(train_set, batch_sampler=sampler, **common)
        k, runs = cfg.train.stream_frames, train_set.scenes.runs
        if runs and max(len(r) for r in runs) < 2:  # every frame starts a scene: the memory is never fused
            du.print_main(f"note: every scene of the training split '{cfg.data.train_split}' has one frame, so the "
                          f"temporal model (model.temporal.memory={cfg.model.temporal.memory}) never fuses a memory: "
                          "this trains its single-frame parts only (train on drives of several frames)")
        walks = sum(-(-len(r) // k) for r in runs) if k > 0 else len(runs)
        if walks < per_rank * world_size:  # the streams without a scene of their own repeat others' frames (padding)
            what = f"{walks} pieces of train.stream_frames={k} frames" if k > 0 else f"{walks} scenes"
            du.print_main(f"note: train.batch_size={cfg.train.batch_size} streams, but the training split has "
                          f"{what}: {per_rank * world_size - walks} streams walk no scene of their own and repeat "
                          f"others' frames in every batch (padding); a batch of at most {walks} streams trains as much")
    else:
        sampler = ResumableSampler(len(train_set), shuffle=True, seed=cfg.train.seed)
        train_loader = DataLoader(train_set, batch_size=per_rank, sampler=sampler, drop_last=False, **common)
    val_loader = None
    if with_val:
        val_set = build_dataset(cfg, cfg.data.val_split, augment=False, like=train_set)
        shared = set(train_set.sample_tokens) & set(val_set.sample_tokens)
        if shared:  # a custom splits file listing a scene in both: the validation score is not on unseen data
            du.print_main(f"warning: {len(shared)} of the {len(val_set)} samples of split '{cfg.data.val_split}' are "
                          f"also in the training split '{cfg.data.train_split}'; the validation score is not measured "
                          "on unseen data (check data.splits_file)")
        if streaming:
            val_sampler = StreamingBatchSampler(val_set.scenes.runs, cfg.eval.batch_size, shuffle=False,
                                                rank=du.get_rank(), world_size=world_size)
            val_loader = DataLoader(val_set, batch_sampler=val_sampler, collate_fn=collate_fn,
                                    num_workers=data_workers(cfg.data.num_workers, len(val_set)))
        else:
            val_sampler = ResumableSampler(len(val_set), shuffle=False)
            val_loader = DataLoader(val_set, batch_size=cfg.eval.batch_size, sampler=val_sampler,
                                    collate_fn=collate_fn, num_workers=data_workers(cfg.data.num_workers, len(val_set)))
    return train_loader, sampler, val_loader


def loader_batch_size(loader: DataLoader) -> int:
    """Samples per batch of this rank (a streaming loader's batch sampler holds it)."""
    return loader.batch_size or loader.batch_sampler.batch_size


def make_flicker_meter(cfg: ExperimentConfig) -> FlickerMeter | None:
    """The flicker-rate meter of ``eval.flicker`` (evaluation/consistency.py), or None when it is off."""
    if not cfg.eval.flicker:
        return None
    return FlickerMeter(BEVGrid.from_config(cfg.grid), len(cfg.data.classes), cfg.data.classes,
                        threshold_m=cfg.eval.flicker_threshold_m)


def unused_meter_keys(cfg: ExperimentConfig) -> list[str]:
    """Notes for a meter's setting given while the meter is off (its default otherwise), and for a decoder's option
    given with another decoder: it was unused with no word."""
    default, notes = EvalConfig(), []
    gnn, gnn_default = cfg.model.gnn, GraphHeadConfig()
    if gnn.same_class_edges and gnn.decoder == "classwise":  # classwise builds a graph per class of its own rule
        notes.append("model.gnn.same_class_edges=true is not used: an option of the greedy decoder, and "
                     "model.gnn.decoder=classwise (which joins the vertices whose class probability is at least "
                     "model.gnn.class_min_prob)")
    if gnn.class_min_prob != gnn_default.class_min_prob and gnn.decoder != "classwise":
        notes.append(f"model.gnn.class_min_prob={gnn.class_min_prob:g} is not used: an option of the classwise "
                     f"decoder, and model.gnn.decoder={gnn.decoder}")
    for switch, key in (("cmap", "cmap_match_m"), ("flicker", "flicker_threshold_m")):
        if not getattr(cfg.eval, switch) and getattr(cfg.eval, key) != getattr(default, key):
            notes.append(f"eval.{key}={getattr(cfg.eval, key):g} is not used: eval.{switch} is off (set "
                         f"eval.{switch}=true for that meter)")
    if "raster" not in (cfg.eval.protocol, *cfg.eval.also_protocols):  # evaluate-json refuses them with the vector one
        for key in ("rank_by", "fix_instance_ids"):
            if getattr(cfg.eval, key) != getattr(default, key):
                notes.append(f"eval.{key}={getattr(cfg.eval, key)} is not used: an option of the raster protocol, and "
                             f"eval.protocol={cfg.eval.protocol} (set eval.protocol=raster, or "
                             "eval.also_protocols=[raster])")
    return notes


def make_cmap_meter(cfg: ExperimentConfig) -> ConsistentAPMeter | None:
    """The consistency-aware mAP meter of ``eval.cmap`` (evaluation/consistency.py), or None when it is off; the
    predicted instance IDs pass on within ``eval.cmap_match_m`` and start anew at ``model.temporal``'s pose jumps."""
    if not cfg.eval.cmap:
        return None
    t = cfg.model.temporal
    return ConsistentAPMeter(BEVGrid.from_config(cfg.grid), len(cfg.data.classes), cfg.data.classes,
                             thresholds=cfg.eval.thresholds, match_m=cfg.eval.cmap_match_m, max_jump_m=t.max_jump_m,
                             max_turn_deg=t.max_turn_deg)


def memory_state(memory: dict | None, gather: bool = True) -> list | None:
    """A temporal model's memory for a checkpoint: one CPU dict per rank (rank order), or None. Under
    torchrun ``gather`` collects every rank's (a collective); without it only a single process's is kept."""
    mine = None if memory is None else {k: v.detach().cpu() for k, v in memory.items()}
    if du.get_world_size() == 1:
        return None if mine is None else [mine]
    if not gather:
        return None
    states = du.all_gather_object(mine)
    return None if any(m is None for m in states) else states


def resumed_memory(saved: list | None, world: int, device: torch.device) -> dict | None:
    """This rank's memory from a checkpoint's ``memory`` (None where the checkpoint holds none for it:
    its streams then start without history, as at a scene start)."""
    if not saved or len(saved) != world:
        return None
    return {k: v.to(device) for k, v in saved[du.get_rank()].items()}


ResumableSampler = du.ResumableSampler


def cpu_threads(cfg: ExperimentConfig, local_processes: int = 1) -> int | None:
    """Intra-op threads for a CPU training run (``train.cpu_threads``); None: leave torch's setting
    (``OMP_NUM_THREADS`` is set and no explicit value is given). Automatic: this process's share of
    the usable cores minus its data workers, at least 1: on a small machine the data workers' JPEG
    decoding and torch's spin-waiting OpenMP threads otherwise fight over the same cores."""
    if cfg.train.cpu_threads is not None:
        return cfg.train.cpu_threads
    if os.environ.get("OMP_NUM_THREADS", "").strip().isdigit() and int(os.environ["OMP_NUM_THREADS"]) > 0:
        return None  # (0 or "abc": OpenMP says "Invalid value" and takes its default, so this run chooses)
    return max(1, usable_cores() // max(local_processes, 1) - cfg.data.num_workers)


def train(cfg: ExperimentConfig, *, resume: str | None = None, force: bool = False,
          loaders=None, validate: bool = True) -> dict:
    """Train ``cfg``; returns the final summary (epoch, step, last metrics). ``loaders`` =
    (train_loader, sampler, val_loader) may be given (tests); otherwise built from the config. ``cfg``: an
    ``ExperimentConfig`` or a YAML file."""
    cfg = as_config(cfg, "train")
    try:
        run = TrainingRun.start(cfg, resume=resume, force=force, loaders=loaders, validate=validate)
        with run.threads(), run.outputs():
            run.announce()
            run.fit()
        return run.final_summary()
    finally:
        unlock_folder(Path(cfg.train.out_dir))


_SIGNALS_RECEIVED: list[int] = []  # signals _sigterm_as_interrupt turned into KeyboardInterrupt during the run
# True from a training step's start (before_step) to its end (on_step): a Ctrl-C or SIGTERM then waits for the step
# to end. Raised in the middle of it, the interrupt saved last.pt with the step half done (BatchNorm statistics of
# its forward, the optimizer's moments updated before the weights), which the resumed run then did again: its
# weights were not those of an uninterrupted run, with no word
_IN_STEP = [False]


def raise_if_signalled() -> None:
    """The KeyboardInterrupt of a SIGTERM / SIGHUP whose first one was lost (raised inside a destructor)."""
    if _SIGNALS_RECEIVED:
        raise KeyboardInterrupt(f"signal {_SIGNALS_RECEIVED[0]} (received during the step)")


@contextlib.contextmanager
def _sigterm_as_interrupt():
    """SIGTERM raises ``KeyboardInterrupt`` in the main thread while the block runs (so a preempted training
    saves ``last.pt`` as Ctrl-C does, instead of losing the steps since its last save); so does SIGHUP (the
    terminal closed without nohup or tmux) where nothing handles it yet (nohup ignores it: left so); the old
    handlers after."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    chld = getattr(signal, "SIGCHLD", None)
    held: list = []

    def interrupt(signum, frame):
        if signum == signal.SIGINT and _IN_STEP[0] and _SIGNALS_RECEIVED:  # Ctrl-C again while the step ends: the
            _IN_STEP[0] = False  # user's choice (a step that hangs), at once, as before
            raise KeyboardInterrupt("Ctrl-C twice")
        # a SIGTERM to the process group (a scheduler's) kills the data-loader workers too: torch's SIGCHLD handler
        # would raise "worker killed" in the middle of the save below; it is put back after
        if chld is not None and not held:
            held.append(signal.signal(chld, signal.SIG_DFL))
        # a second SIGTERM (scancel or docker stop twice) would abort the save below, keeping the older last.pt
        # and losing the steps since: ignored until the block ends (SIGKILL still stops it)
        for sig in caught:
            if not (sig == signal.SIGINT and _IN_STEP[0]):
                signal.signal(sig, signal.SIG_IGN)
        # remembered too: an exception raised while Python runs a destructor (__del__, a weakref callback) is
        # printed and dropped, and the run would train on with the signal now ignored; the next step raises it
        _SIGNALS_RECEIVED.append(signum)
        if _IN_STEP[0]:  # raised when the step ends (on_step), so that last.pt holds whole steps only
            if signum == signal.SIGINT:
                sys.stderr.write("\nCtrl-C: the step in progress ends first, then last.pt is saved (Ctrl-C again to "
                                 "stop at once, losing that step)\n")
            return
        raise KeyboardInterrupt(f"signal {signum} ({signal.Signals(signum).name})")

    hup = getattr(signal, "SIGHUP", None)  # (not on Windows)
    caught = [signal.SIGTERM] + ([hup] if hup is not None and signal.getsignal(hup) is signal.SIG_DFL else [])
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # Ctrl-C: the same, whole steps
        caught.append(signal.SIGINT)
    def unraisable(info):  # that dropped KeyboardInterrupt is raised again at the next step: no traceback for it
        if not (isinstance(info.exc_value, KeyboardInterrupt) and _SIGNALS_RECEIVED):
            hook(info)

    previous = {sig: signal.signal(sig, interrupt) for sig in caught}
    hook, sys.unraisablehook = sys.unraisablehook, unraisable
    _SIGNALS_RECEIVED.clear()
    try:
        yield
    finally:
        _SIGNALS_RECEIVED.clear()
        _IN_STEP[0] = False
        sys.unraisablehook = hook
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if held:
            signal.signal(chld, held[0])


class TrainingRun:
    """One training run's parts and position; ``train`` calls its steps in order:

    ``start`` (the output folder, the checkpoint to resume, seeds, loaders, model, criterion,
    optimizer, clock, scaler, restored state; in this order, which the RNG streams of an exact resume
    depend on), ``threads`` and ``outputs`` (the threads and the writers, given back at the end),
    ``announce``, ``fit`` (epochs of ``train_epoch``, ``validate``, ``save``, ``log`` until the schedule
    or ``train.max_steps`` is done; Ctrl-C saves ``last.pt`` first), ``final_summary``.
    """

    def __init__(self, cfg: ExperimentConfig, device: torch.device, out_dir: Path, loaders, validate: bool,
                 fresh: bool = True, init_state: dict | None = None):
        self.cfg, self.device, self.out_dir, self.validating = cfg, device, out_dir, validate
        self.world = du.get_world_size()
        self.grid = BEVGrid.from_config(cfg.grid)
        self.decode = decode_options(cfg.model.gnn, self.grid)
        self.train_loader, self.sampler, self.val_loader = loaders
        # ImageNet weights on a fresh start only (a resumed run has its own)
        self.model = build_model(cfg, pretrained=fresh and init_state is None).to(device)
        self.random_init = random_init_warning(cfg) if fresh and init_state is None else None
        if self.random_init:
            du.print_main(self.random_init)
        for note in unused_meter_keys(cfg) if validate else ():
            du.print_main(f"note: {note}")
        if init_state is not None:
            new = init_weights(self.model, init_state, cfg)
            du.print_main(f"weights from {cfg.train.init_from}" + (f" ({len(new)} new tensors of the temporal fusion "
                                                                  "start from their initialisation)" if new else ""))
            other = init_model_differences(init_state, cfg)
            if other:  # weights of the same names and shapes, loaded with no word (8 attention heads from 4)
                du.print_main(f"note: the checkpoint of train.init_from was trained with other model settings "
                              f"({other}); its weights have this model's names and shapes and start this run, which "
                              "trains them under these settings")
            if cfg.model.backbone.weights and cfg.model.backbone.name != "tiny":  # unread, with no word
                du.print_main(f"note: model.backbone.weights={cfg.model.backbone.weights} is not loaded: the backbone "
                              f"starts from the weights of train.init_from={cfg.train.init_from}, as every other part")
        trainable = freeze_parameters(self.model, cfg.train.trainable)
        self.criterion = Criterion(cfg.loss, self.grid, with_distance=cfg.model.bev_heads.distance_head)
        self.optimizer = torch.optim.Adam(param_groups(self.model, trainable, cfg.train.weight_decay), lr=cfg.train.lr)
        self.batch_size = loader_batch_size(self.train_loader)
        self.steps_per_epoch = math.ceil(self.sampler.num_samples / self.batch_size)
        # the schedule's length (max_steps only cuts it): a temporal training's single-frame epochs
        # (train.stream_warmup) are shorter than its epochs of pieces, whose longest stream sets their length;
        # epochs x the first epoch's steps ended the last epoch part-way with no word
        self.total_steps = (sum(self.sampler.steps_of_epoch(e) for e in range(cfg.train.epochs))
                            if isinstance(self.sampler, StreamingBatchSampler)
                            else cfg.train.epochs * self.steps_per_epoch)
        self.clock = ProgressClock(cfg.train, self.total_steps)
        self.scaler = torch.amp.GradScaler(device.type) if cfg.train.amp == "fp16" else None
        self.position = Position(epoch=0)
        self.best: dict = {"score": -math.inf}
        self.memory: dict | None = None  # a temporal model's memory of this rank's streams, mid-epoch
        self.warned_unfused = False  # an epoch of streams whose memory never fused was reported
        self.net: torch.nn.Module = self.model
        self.writer = self.log_file = None
        self.summary: dict = {}
        # a validation that a Ctrl-C / SIGTERM cut short: last.pt records it and the resumed run runs it first (its
        # epoch counted as done, it was skipped, and after the final epoch the run ended never validated, no best.pt)
        self.validation_pending = False
        # lines in log.jsonl when last.pt was saved: a resume drops those written after it (None: not counted)
        self.log_lines: int | None = 0
        self.line_due = False
        # with train.time_budget_min, every rank reads rank 0's clock (the same stop step everywhere)
        self.sync = device if self.world > 1 and cfg.train.time_budget_min is not None else None
        self.out_dir_id = folder_id(out_dir)  # the folder itself: moved or removed during the run, it is named

    # --- start --------------------------------------------------------------------------------------

    @classmethod
    def start(cls, cfg: ExperimentConfig, *, resume: str | None, force: bool, loaders, validate: bool) -> TrainingRun:
        device = du.init_distributed(du.resolve_device(cfg.train.device).type)
        out_dir = Path(cfg.train.out_dir)
        check_init_from_outside(cfg, out_dir, resume)
        check_stream_schedule(cfg)
        for note in setting_notes(cfg):
            du.print_main(note)
        check_batch_over_ranks(cfg, du.get_world_size())
        check_fits(cfg, "train", device)  # a step that cannot fit the memory: one line, before any worker starts
        prepare_out_dir(out_dir, resume, force)
        du.barrier()
        state = load_resume_state(resume, cfg)
        seed_everything(cfg.train.seed + du.get_rank())
        if cfg.train.deterministic:
            torch.use_deterministic_algorithms(True)
        init_state = load_init_state(cfg) if state is None else None  # fails fast, before the loaders
        if init_state is not None or cfg.train.trainable:  # so do the weights' fit and the prefixes (a model: ~1 s)
            with torch.random.fork_rng(devices=[]):  # the run's own model is initialised as without the probe
                probe = build_model(cfg, pretrained=False)
            if init_state is not None:
                init_weights(probe, init_state, cfg)
            freeze_parameters(probe, cfg.train.trainable)
            check_frozen_are_trained(probe, cfg, fresh=state is None and init_state is None)
            del probe
        if (state is None and init_state is None and cfg.model.backbone.name != "tiny"
                and cfg.model.backbone.weights == "imagenet"):
            imagenet_state(cfg.model.backbone.name)  # fail fast (one line) before the loaders' long setup
        if loaders is None:
            loaders = build_loaders(cfg, du.get_world_size(), with_val=validate)
        run = cls(cfg, device, out_dir, loaders, validate, fresh=state is None, init_state=init_state)
        if state is not None:
            run.restore(state, Path(resume))
            run.check_not_finished(state, Path(resume))
            du.print_main(f"resumed from {resume}: epoch {run.position.epoch}, step {run.position.step} "
                          f"({run.position.step_in_epoch} into the epoch)")
            run_dir = Path(resume).resolve().parent  # a symbolic link to the checkpoint: the run it is in
            if run.clock.last < 1.0 and not _same_path(run_dir, out_dir):  # (a finished one says so itself)
                du.print_main(f"note: {resume} is a checkpoint of the run in {run_dir}; this run goes on in "
                              f"train.out_dir={out_dir} (its checkpoints, log and TensorBoard events go there, the "
                              f"earlier ones stay in {run_dir}; to continue there, pass train.out_dir={run_dir})")
            later = later_last_step(out_dir, Path(resume), run.position.step)
            if later is not None:  # resuming best.pt on purpose is fine; replacing a later last.pt unsaid is not
                du.print_main(f"note: {out_dir / 'last.pt'} is at step {later}, later than {resume}; this run goes on "
                              f"from step {run.position.step} and its next save replaces that last.pt (to continue "
                              f"from step {later} instead, stop now and pass --resume {out_dir / 'last.pt'})")
            best = run.best.get("score", -math.inf)
            saved = saved_config(state["config"], f"checkpoint {resume}")
            changed = config_differences(saved, cfg, RESUME_NOTED)
            if changed and run.clock.last < 1.0:
                du.print_main(f"note: resumed with training settings other than the checkpoint's ({changed}): the "
                              f"{run.position.step} step(s) so far trained with the checkpoint's, the rest train with "
                              "these, and config.yaml and the next checkpoints record only these")
            measured = config_differences(saved, cfg, SCORE_KEYS)
            if measured and math.isfinite(best):
                du.print_main(f"note: the best score so far ({best:.4g}, best.pt's) was measured with another "
                              f"validation ({measured}); this run's scores replace best.pt only where they exceed it, "
                              "a number of another kind")
            if cfg.train.init_from:
                du.print_main(f"note: train.init_from={cfg.train.init_from} is not read on a resume: the weights are "
                              f"{resume}'s (the run's own checkpoint)")
        if run.world > 1:
            run.net = torch.nn.parallel.DistributedDataParallel(
                run.model, device_ids=[device.index] if device.type == "cuda" else None)
        return run

    def restore(self, state: dict, path: Path | str = "the checkpoint") -> None:
        """The full state of a checkpoint: weights, optimizer, clock, scaler, position, best, RNGs."""
        self.model.load_state_dict(state["model"])
        saved_groups = len(state["optimizer"].get("param_groups", []))
        if saved_groups != len(self.optimizer.param_groups):  # a temporal run saved before param_groups()
            raise CheckpointError(
                f"checkpoint {path}: its optimizer has {saved_groups} parameter group(s), this version's "
                f"{len(self.optimizer.param_groups)} (the temporal fusion's own group, without weight decay): it "
                f"cannot be resumed exactly; start a new run from its weights with train.init_from=CHECKPOINT")
        self.optimizer.load_state_dict(state["optimizer"])
        self.clock.load_state_dict(state.get("clock") or {})
        if self.scaler is not None and state.get("scaler") is not None:
            self.scaler.load_state_dict(state["scaler"])
        self.position = Position(state["epoch"], state["step"], state["step_in_epoch"])
        self.best = state.get("best", self.best)
        self.validation_pending = bool(state.get("validation_pending", False))
        lines = state.get("log_lines")  # None in a checkpoint saved before the lines were counted
        self.log_lines = lines if isinstance(lines, int) and not isinstance(lines, bool) and lines >= 0 else None
        check_same_train_set(state.get("train_set"), train_set_fingerprint(self.train_loader), path)
        self.memory = resumed_memory(state.get("memory"), self.world, self.device)
        self.note_world_change(state.get("world"), path)
        on_disk = best_score_in(self.out_dir)  # saved after the checkpoint resumed from (a kill in between)
        if on_disk > self.best.get("score", -math.inf):
            self.best = {**self.best, "score": on_disk}
        set_rng_state(state["rng"])

    def note_world_change(self, saved_world: int | None, path: Path | str) -> None:
        """A checkpoint saved part-way through an epoch by another number of processes. The shuffled
        sampler goes on exactly (``ResumableSampler.set_epoch``: its order does not depend on the ranks);
        the streaming one deals the scenes over the streams of all ranks, so under another number its
        epoch is another walk: said, not hidden. Checkpoints written before the world size was saved
        (None) say nothing."""
        p = self.position
        if saved_world is None or saved_world == self.world or not p.step_in_epoch:
            return
        if isinstance(self.sampler, ResumableSampler):
            du.print_main(f"note: {path} was saved by {saved_world} process(es) at step {p.step_in_epoch} of epoch "
                          f"{p.epoch}, resumed by {self.world}: the epoch goes on from the same sample (the batch "
                          f"over all processes, train.batch_size={self.cfg.train.batch_size}, is the same)")
        else:
            du.print_main(f"note: {path} was saved by {saved_world} process(es) at step {p.step_in_epoch} of epoch "
                          f"{p.epoch}, resumed by {self.world}: the streams' scenes are dealt over the processes, so "
                          f"the rest of epoch {p.epoch} follows the dealing of {self.world} (some of its frames are "
                          "walked twice, some not at all) and the streams start without memory; exact from the next "
                          "epoch on (to keep this epoch exact, resume with the same number of processes)")

    def check_not_finished(self, state: dict, path: Path) -> None:
        """A checkpoint whose schedule is complete has nothing to resume: asking it for more epochs is
        an error (the schedule's progress cannot be extended), resuming it as it was a note."""
        old_epochs = (state.get("config", {}).get("train") or {}).get("epochs")
        if self.clock.last < 1.0:
            p = self.position
            if old_epochs is not None and old_epochs != self.cfg.train.epochs and p.step > self.total_steps:
                # a shorter schedule that ends before the checkpoint: "done" after no step, exit 0, nothing written
                raise UserError(f"train.epochs={self.cfg.train.epochs} ends the schedule at step {self.total_steps}, "
                                f"before checkpoint {path}'s step {p.step} (epoch {p.epoch} of its {old_epochs}): "
                                f"nothing would be trained; resume with train.epochs={p.epoch + 1} or more (or its "
                                f"own {old_epochs}) to finish it")
            return
        if old_epochs is not None and old_epochs != self.cfg.train.epochs:
            raise UserError(f"checkpoint {path} completed its schedule ({old_epochs} epochs, step "
                            f"{self.position.step}); train.epochs={self.cfg.train.epochs} cannot extend a finished "
                            "schedule: start a new run (another train.out_dir)")
        run_dir = Path(path).resolve().parent  # a symbolic link to the checkpoint: the run it is in
        elsewhere = not _same_path(run_dir, self.out_dir)
        du.print_main(f"checkpoint {path} completed its schedule: nothing left to train"
                      + (" but its final validation, which was interrupted" if self.validation_pending else "")
                      + (f"; its run's outputs stay in {run_dir}, train.out_dir={self.out_dir} gets no "
                         "checkpoint (to train on from it, start a new run with train.init_from=" + str(path) + ")"
                         if elsewhere else ""))

    @contextlib.contextmanager
    def threads(self):
        """torch's intra-op threads for a CPU run (``cpu_threads``), restored afterwards."""
        before = torch.get_num_threads()
        threads = (cpu_threads(self.cfg, int(os.environ.get("LOCAL_WORLD_SIZE", 1)))
                   if self.device.type == "cpu" else None)
        self.chosen_threads = threads
        if threads is not None:
            torch.set_num_threads(threads)
        try:
            yield
        finally:
            torch.set_num_threads(before)

    @contextlib.contextmanager
    def outputs(self):
        """Rank 0 writes config.yaml, TensorBoard events (tb/) and log.jsonl; closed at the end."""
        if du.is_main_process():
            save_config(self.cfg, self.out_dir / "config.yaml")
            from torch.utils.tensorboard import SummaryWriter  # slow to import; training only

            # a resumed run hides the events its killed predecessor wrote after the checkpoint (TensorBoard's
            # purge_step): they showed as a second curve over the steps the resume trains again
            purge = self.position.step + 1 if self.position.step else None
            self.writer = SummaryWriter(str(self.out_dir / "tb"), purge_step=purge)
            if self.log_lines is not None:  # the same for the log's lines (a checkpoint that counts them)
                self.log_lines = purge_log(self.out_dir / "log.jsonl", self.log_lines, du.print_main)
            self.log_file = (self.out_dir / "log.jsonl").open("a")
        previous_hook = threading.excepthook

        def thread_failed(args):  # TensorBoard's writer thread, once the folder is gone: said once by fit
            if not (isinstance(args.exc_value, OSError) and self.out_dir_moved()):
                previous_hook(args)

        threading.excepthook = thread_failed
        try:
            yield
        finally:
            threading.excepthook = previous_hook
            for handle in (self.log_file, self.writer):
                if handle is not None:
                    try:
                        handle.close()
                    except OSError:  # the folder moved away: fit said so; its error is not hidden by this one
                        if not self.out_dir_moved():
                            raise

    def announce(self) -> None:
        """Start the clock, set the first learning rate, print the threads and the schedule."""
        cfg, clock = self.cfg, self.clock
        clock.start()
        self.set_lr(self.position.step)
        if self.device.type == "cpu":
            how = (" (train.cpu_threads)" if cfg.train.cpu_threads else
                   " (OMP_NUM_THREADS)" if self.chosen_threads is None else "")
            du.print_main(f"cpu: {torch.get_num_threads()} torch thread(s), {cfg.data.num_workers} data worker(s), "
                          f"{usable_cores()} usable core(s)" + how)
        du.print_main(f"schedule: {cfg.train.schedule}, {self.total_steps} steps"
                      + (f" or {cfg.train.time_budget_min:g} min, whichever comes first" if clock.budget_s else "")
                      + f"; progress {clock.last:.3f}, lr {self.optimizer.param_groups[0]['lr']:.3g}")
        if self.random_init:  # again where the log ends up being read
            du.print_main(self.random_init)
            self.summary["warnings"] = [self.random_init]
        self.summary["cpu_threads"] = torch.get_num_threads() if self.device.type == "cpu" else None

    # --- the schedule -------------------------------------------------------------------------------

    def before_step(self, step: int) -> None:
        """Before each step: a signal received since the last one (a skipped non-finite step) is raised, then
        the step runs whole (``_IN_STEP``) at its learning rate."""
        raise_if_signalled()
        _IN_STEP[0] = True
        self.set_lr(step)

    def set_lr(self, step: int) -> None:
        lr = self.cfg.train.lr * lr_factor(self.clock.progress(step, self.sync), self.cfg.train)
        for group in self.optimizer.param_groups:
            group["lr"] = lr

    def should_stop(self, step: int) -> bool:
        done = self.clock.progress(step, self.sync) >= 1.0  # always: clock.last is then the progress of `step` steps
        return done or (self.cfg.train.max_steps is not None and step >= self.cfg.train.max_steps)

    def schedule_summary(self) -> dict:
        lr = self.optimizer.param_groups[0]["lr"]
        final = self.cfg.train.lr * final_lr_factor(self.cfg.train)
        return {"progress": round(self.clock.last, 4), "lr": lr, "final_lr": final,
                "schedule_complete": bool(self.clock.last >= 1.0 and math.isclose(lr, final, rel_tol=1e-6)),
                "elapsed_s": round(self.clock.elapsed(), 1)}

    # --- the loop -----------------------------------------------------------------------------------

    def fit(self) -> None:
        """Epochs until the schedule (or ``train.max_steps``) is done; on Ctrl-C, ``last.pt`` holds the
        weights after the last completed step, which ``position`` names, and the interrupt goes on. A SIGTERM
        (a scheduler's preemption, ``docker stop``, ``timeout``) is a Ctrl-C here (``_sigterm_as_interrupt``)."""
        with _sigterm_as_interrupt():
            self._fit()

    def _fit(self) -> None:
        try:
            finished = self.should_stop(self.position.step)
            max_steps = self.cfg.train.max_steps
            if max_steps is not None and self.position.step >= max_steps:  # a resume past it: say why nothing runs
                du.print_main(f"train.max_steps={max_steps} is reached already (the checkpoint is at step "
                              f"{self.position.step}): nothing to train; raise train.max_steps to continue")
            if self.validation_pending and self.validating and self.val_loader is not None:
                du.print_main(f"the validation after step {self.position.step} was interrupted; running it first")
                self.validate()
                self.log()  # before last.pt: a kill between the two loses no line (the resume drops it, redoes it)
                self.save("last.pt", self.summary.get("val", {}).get("metrics"))
            while not finished:
                stopped = self.train_epoch()
                finished = stopped or self.should_stop(self.position.step)  # also refreshes the clock saved below
                if self.validating and self.val_loader is not None and (
                        finished or self.position.epoch % self.cfg.train.val_every == 0):
                    self.validation_pending = True  # until it ends: an interrupt's last.pt says so
                    self.validate()
                # after the validation, so that it carries the best score (a stop part-way too); the epoch's
                # line first: killed between the two, the resume drops the line and trains the epoch again
                self.log()
                self.save("last.pt", self.summary.get("val", {}).get("metrics") if not stopped else None)
        except KeyboardInterrupt:
            if self.line_due and not self.validation_pending:  # stopped after the epoch's validation, before its line
                self.log()
            self.save("last.pt", gather=False)
            du.print_main(f"interrupted: saved {self.out_dir / 'last.pt'} (resume with --resume "
                          f"{self.out_dir / 'last.pt'})")
            raise
        except OSError as e:  # the run's folder moved or removed under it: one line, not TensorBoard's traceback
            if not self.out_dir_moved():
                raise
            raise self.moved_error(e) from None
        except RuntimeError as e:  # a data-loader worker killed (the OOM killer): saved as for Ctrl-C, one line
            died = data_worker_died(e)
            if died is None:
                raise
            self.save("last.pt", gather=False)
            last = self.out_dir / "last.pt"
            raise DataWorkerError(f"{died.rstrip('. ')} (the out-of-memory killer, or a kill); saved {last} at step "
                                  f"{self.position.step}: resume with --resume {last} (with a lower "
                                  "data.num_workers or train.batch_size if memory ran out)") from None

    def train_epoch(self) -> bool:
        """The rest of the epoch in progress; returns whether it stopped part-way (then ``fit`` saves
        ``last.pt`` at that step, after the final validation, and a resume continues the epoch), else the
        position moves to the next epoch."""
        p = self.position
        # the shuffled sampler skips samples of the epoch over all ranks (exact under another world size),
        # the streaming one whole batches of this rank's streams
        over = self.world if isinstance(self.sampler, ResumableSampler) else 1
        self.sampler.set_epoch(p.epoch, start=p.step_in_epoch * self.batch_size * over)
        if hasattr(self.train_loader.dataset, "set_epoch"):
            self.train_loader.dataset.set_epoch(p.epoch)  # augmentation draws follow (seed, epoch, index)
        result = train_one_epoch(
            self.net, self.criterion, self.train_loader, self.optimizer, self.device, p,
            settings=StepSettings.from_config(self.cfg.train), scaler=self.scaler,
            total=(self.sampler.steps_of_epoch(p.epoch) if isinstance(self.sampler, StreamingBatchSampler)
                   else self.steps_per_epoch),
            hooks=EpochHooks(before_step=self.before_step, on_step=self.on_step, should_stop=self.should_stop,
                             writer=self.writer),
            memory=self.memory if p.step_in_epoch else None,
        )
        _IN_STEP[0] = False  # (an epoch that ended on a skipped non-finite step never reached on_step)
        raise_if_signalled()
        self.memory = result["memory"]
        stats = result["stats"]
        if (isinstance(self.sampler, StreamingBatchSampler) and p.epoch >= self.sampler.single_epochs
                and "memory_fused" in stats and stats["memory_fused"] == 0 and not self.warned_unfused):
            # every frame of an epoch of streams started a new memory (a model.temporal.max_jump_m or max_turn_deg
            # below the drives' motion between frames): the fusion trained on nothing, exit 0 with no word
            self.warned_unfused = True
            why = ", ".join(f"{k.removeprefix('memory_')} {v:.2f}" for k, v in stats.items()
                            if k.startswith("memory_") and v)
            du.print_main(f"warning: the temporal memory was never fused in epoch {p.epoch} (per step: {why}): the "
                          "fusion learns nothing; check model.temporal.max_jump_m / max_turn_deg against the ego "
                          "motion between frames, and that the scenes' frames follow each other")
        self.position = Position(p.epoch, result["global_step"], result["step_in_epoch"])
        self.line_due = True  # the epoch's line in log.jsonl, written by log()
        self.summary = {**self.summary, "epoch": p.epoch, "step": result["global_step"], "train": result["stats"],
                        "train_seconds": round(result["seconds"], 2),
                        "samples_per_s": round(result["samples_per_s"], 2), **self.schedule_summary()}
        if not result["stopped"]:  # else the position stays part-way and a resume continues the epoch
            self.position = Position(p.epoch + 1, result["global_step"], 0)
        return result["stopped"]

    def on_step(self, info: StepInfo) -> None:
        """After each step: the position (for Ctrl-C), and ``last.pt`` every ``train.checkpoint_every`` steps."""
        self.position = Position(info.epoch, info.step, info.step_in_epoch)
        self.memory = info.memory
        _IN_STEP[0] = False
        raise_if_signalled()
        every = self.cfg.train.checkpoint_every
        if every and info.step % every == 0:
            self.save("last.pt")

    def validate(self) -> None:
        """Validation losses and AP; ``best.pt`` when the score (mAP, else -loss) improves."""
        with rng_preserved():  # validation draws nothing from the training's random streams
            val = evaluate(self.net, self.criterion, self.val_loader, self.device,
                           postprocess=lambda out: postprocess_batch(out, self.grid, **self.decode),
                           evaluator=Evaluator.from_config(self.cfg), amp=self.cfg.train.amp,
                           flicker=make_flicker_meter(self.cfg), persist=Persistence.from_config(self.cfg),
                           cmap=make_cmap_meter(self.cfg))
        self.summary["val"] = val
        score = val["metrics"]["mAP"] if "metrics" in val else -val["losses"].get("loss_total", math.inf)
        step = self.position.step
        if self.writer is not None:
            for k, v in val["losses"].items():
                self.writer.add_scalar(f"val/{k}", v, step)
            if "metrics" in val:
                self.writer.add_scalar("val/mAP", val["metrics"]["mAP"], step)
            if "consistency" in val:
                self.writer.add_scalar("val/flicker", val["consistency"]["flicker_mean"], step)
            if "cmap" in val:
                self.writer.add_scalar("val/C-mAP", val["cmap"]["C-mAP"], step)
        self.validation_pending = False
        if not math.isnan(score) and score > self.best["score"]:
            self.best = {"score": score, "epoch": self.position.epoch, "step": step}
            self.save("best.pt", val.get("metrics"))

    def save(self, name: str, metrics: dict | None = None, gather: bool = True) -> None:
        """A full-state checkpoint at ``position`` (rank 0 writes it; the unwrapped model). Part-way through
        an epoch it holds every rank's memory of its streams (a temporal model; ``gather`` is a collective:
        False where the ranks may not all be here, Ctrl-C)."""
        p = self.position
        memories = memory_state(self.memory, gather) if p.step_in_epoch else None
        if not du.is_main_process():
            return
        if self.out_dir_moved():  # the save would make a new folder of that name, with a checkpoint and nothing else
            raise self.moved_error(None)
        save_checkpoint({
            "model": self.model.state_dict(), "optimizer": self.optimizer.state_dict(),
            "clock": self.clock.state_dict(), "scaler": self.scaler.state_dict() if self.scaler else None,
            "epoch": p.epoch, "step": p.step, "step_in_epoch": p.step_in_epoch, "rng": rng_state(),
            "config": config_to_dict(self.cfg), "metrics": metrics or {}, "best": self.best, "memory": memories,
            "validation_pending": self.validation_pending, "train_set": train_set_fingerprint(self.train_loader),
            "world": self.world, "log_lines": self.log_lines,
        }, self.out_dir / name)

    def out_dir_moved(self) -> bool:
        """Whether ``train.out_dir`` is no longer the folder this run started in (renamed, moved or removed)."""
        return self.out_dir_id is not None and folder_id(self.out_dir) != self.out_dir_id

    def moved_error(self, cause: OSError | None) -> UserError:
        now = held_folder_now(self.out_dir)
        again = "the steps since its last checkpoint are trained again"
        where = ("it was removed, and its checkpoints with it: start the run again" if now == "removed" else
                 f"it is now {now}: resume there with --resume {now / 'last.pt'} train.out_dir={now} ({again})"
                 if isinstance(now, Path) else "its checkpoints went with it: if it was moved, resume from its "
                 f"last.pt there, with train.out_dir set to that folder ({again})")
        name = cause.filename if cause is not None else None
        why = (f" ({cause.strerror or cause}" + (f": {os.fsdecode(name)}" if isinstance(name, (str, bytes)) else "")
               + ")") if cause is not None else ""
        return UserError(f"train.out_dir {self.out_dir} was moved or removed while this run wrote to it{why}; the run "
                         f"stopped at step {self.position.step}; {where}")

    def log(self) -> None:
        if self.log_file is not None:
            self.log_file.write(json_text(self.summary, default=lambda x: json_safe(float(x))) + "\n")  # standard JSON
            self.log_file.flush()
            if self.log_lines is not None:
                self.log_lines += 1
        self.line_due = False

    def final_summary(self) -> dict:
        return {"epoch": self.position.epoch, "step": self.position.step,  # a resume that trained nothing
                **self.summary, **self.schedule_summary(), "out_dir": str(self.out_dir)}


# the config keys a checkpoint that starts a fine-tuning (train.init_from) must share with the run: what
# the weights mean (the geometry, the inputs, the outputs); the architecture is checked by the weights'
# names and shapes, and the temporal memory may be new
INIT_KEYS = ("grid", "data.image_size", "data.classes", "data.dt_clip", "data.av2_cameras", "model.view_transform")


def check_stream_schedule(cfg: ExperimentConfig) -> None:
    """A temporal training whose schedule never streams is refused: pieces of one frame
    (``train.stream_frames=1``), or ``train.stream_warmup`` rounding to every epoch of ``train.epochs``
    (0.6 of 1 epoch: the whole run on shuffled single frames, the memory always empty: exit 0, the
    memory never trained)."""
    if cfg.model.temporal.memory == "none":
        return
    if cfg.train.stream_frames == 1:  # pieces of one frame: no history
        raise UserError("train.stream_frames=1: every frame would start a new memory, so the temporal model would "
                        "never train with one (a single-frame training); use 0 (whole scenes) or at least 2")
    single = round(cfg.train.stream_warmup * cfg.train.epochs)
    if single >= cfg.train.epochs:
        raise UserError(f"train.stream_warmup={cfg.train.stream_warmup:g} of train.epochs={cfg.train.epochs} is "
                        f"{single} single-frame epoch(s) of {cfg.train.epochs}: the temporal model would never train "
                        "with its memory (it is empty on single frames); raise train.epochs or lower "
                        "train.stream_warmup")


# the keys that only a temporal model (model.temporal.memory not none) reads: set on a single-frame model they are
# ignored (element persistence, model.temporal.persist_* and the pose-jump limits it shares, works on any model)
MEMORY_ONLY_KEYS = ("model.temporal.fusion", "model.temporal.kernel", "model.temporal.drop_prob",
                    "model.temporal.edge_samples", "train.stream_frames", "train.stream_warmup")


def setting_notes(cfg: ExperimentConfig) -> list[str]:
    """Notes on settings that train, but not as they read: the memory's keys on a model without a memory (the
    run trained a single-frame model on shuffled frames), another schedule's keys, vd_sampling without the pe+vd
    embedding, augmentation keys without data.augment, AV2 keys on nuScenes, validation on the training split, an
    LSS frustum that stops short of the grid (the cells beyond it never get a camera feature)."""
    notes = []
    if cfg.model.temporal.memory == "none":
        default, now = flatten(config_to_dict(ExperimentConfig())), flatten(config_to_dict(cfg))
        unused = [f"{k}={now[k]}" for k in MEMORY_ONLY_KEYS if now[k] != default[k]]
        if unused:
            notes.append(f"note: {', '.join(unused)} set, but model.temporal.memory=none: only a temporal model reads "
                         "them, so this run trains a single-frame model on shuffled frames (docs/temporal.md: set "
                         "model.temporal.memory, e.g. bev, or start from configs/temporal/)")
    t, t0 = cfg.train, TrainConfig()
    own = {"step": ("lr_step", "lr_gamma"), "cosine": ("min_lr_factor",)}  # the keys only that schedule reads
    unread = [f"train.{k}={getattr(t, k):g}" for other, keys in own.items() if other != t.schedule for k in keys
              if getattr(t, k) != getattr(t0, k)]
    if unread:
        notes.append(f"note: {', '.join(unread)} set, but train.schedule={t.schedule} does not read it "
                     "(min_lr_factor is the cosine schedule's; lr_step and lr_gamma the step schedule's)")
    gnn = cfg.model.gnn
    if gnn.vd_sampling != GraphHeadConfig().vd_sampling and gnn.embedding != "pe+vd":
        notes.append(f"note: model.gnn.vd_sampling={gnn.vd_sampling} set, but model.gnn.embedding={gnn.embedding}: "
                     "only the visual-descriptor embedding (pe+vd) reads it")
    d, d0 = cfg.data, DataConfig()
    for keys, unread, why in ((("aug_scale", "aug_rotate_deg", "aug_crop_jitter"), not d.augment,
                               "data.augment=false (set data.augment=true to augment the training images)"),
                              (("av2_cameras", "av2_frame_step"), d.dataset != "av2",
                               f"data.dataset={d.dataset}: only the Argoverse 2 loader reads them")):
        given = [f"data.{k}={config_to_dict(d)[k]}" for k in keys if unread and getattr(d, k) != getattr(d0, k)]
        if given:
            notes.append(f"note: {', '.join(given)} set, but {why}")
    if d.val_split == d.train_split:  # an overfitting check may mean it; a slip made best.pt a pick on training scenes
        notes.append(f"note: data.val_split={d.val_split} is the training split (data.train_split): validation, and "
                     "the choice of best.pt, score the scenes this run trains on, not held-out ones")
    vt, g = cfg.model.view_transform, cfg.grid
    reach = max(abs(g.xbound[0]), abs(g.xbound[1]), abs(g.ybound[0]), abs(g.ybound[1]))
    if vt.kind == "lss" and vt.depth_bound[1] < reach:
        notes.append(f"note: model.view_transform.depth_bound stops at {vt.depth_bound[1]:g} m, but the grid "
                     f"(grid.xbound, grid.ybound) reaches {reach:g} m from the ego: its cells beyond "
                     f"{vt.depth_bound[1]:g} m never get a camera feature (the paper's 60 m x 30 m grid: "
                     "depth_bound [4, 45, 1])")
    return notes + size_notes(cfg)


def check_init_from_outside(cfg: ExperimentConfig, out_dir: Path, resume: str | None) -> None:
    """``train.init_from`` must not be a checkpoint of ``out_dir``'s run: starting over there (``--force``)
    removes it before it is read, and the new run's saves replace it."""
    path = cfg.train.init_from
    if not path or resume is not None:  # a resumed run has its own weights; init_from is not read
        return
    for name in CHECKPOINTS:
        if _same_path(Path(path), out_dir / name):  # a link to it, too
            raise UserError(f"train.init_from={path} is the {name} of train.out_dir={out_dir}, which this run "
                            "starts over (--force removes it, the run's own saves replace it): copy it out of the "
                            "folder first, or choose another train.out_dir")


def folder_id(path: Path) -> tuple[int, int] | None:
    """(device, inode) of the folder ``path`` (None where there is none)."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino


def _same_path(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def load_init_state(cfg: ExperimentConfig) -> dict | None:
    """``train.init_from``'s checkpoint (None without one), its config checked against ``cfg`` (``INIT_KEYS``)."""
    path = cfg.train.init_from
    if not path:
        return None
    try:
        state = load_checkpoint(path)
    except CheckpointError as e:  # named as this key (not --checkpoint)
        raise CheckpointError(f"train.init_from: {str(e).replace(' with --checkpoint', '')}") from None
    if isinstance(state.get("config"), dict):
        lines = config_differences(saved_config(state["config"], f"checkpoint {path}"), cfg, INIT_KEYS)
        if lines:
            raise UserError(f"train.init_from={path}: the checkpoint was trained with other inputs or geometry "
                            f"({lines}); its weights would mean something else here")
    return state


def init_model_differences(state: dict, cfg: ExperimentConfig) -> str:
    """The ``model.*`` keys (but those an inference reads only, ``NOT_BAKED``) on which the config of
    ``train.init_from``'s checkpoint and ``cfg`` differ, as ``config_differences`` says them ("" if none)."""
    if not isinstance(state.get("config"), dict):
        return ""
    old = saved_config(state["config"], "the checkpoint of train.init_from")
    differ = [k for k in diff_configs(old, cfg) if is_under(k, ["model"]) and not is_under(k, NOT_BAKED)]
    return config_differences(old, cfg, differ)


def init_weights(model: torch.nn.Module, state: dict, cfg: ExperimentConfig | None = None) -> list[str]:
    """``state``'s model weights into ``model`` (``train.init_from``); every weight must match by name and
    shape except the temporal fusion's, which the checkpoint may lack (returned: those left as built). A
    checkpoint whose fusion does not fit this model's (another memory or fusion kind: other names or shapes)
    lends none of it: the whole fusion starts from its initialisation (the gated one then is the identity),
    never half trained. A fusion for a model without one is an error (the run's config is not temporal). With
    ``cfg`` the error names the ``model.*`` keys on which the checkpoint's config and ``cfg`` differ."""
    own, theirs = model.state_dict(), state["model"]
    fusion = [k for k in theirs if k.startswith("temporal.")]
    if (any(k.startswith("temporal.") for k in own)  # (into a single-frame model a fusion is an error, below)
            and any(k not in own or own[k].shape != theirs[k].shape for k in fusion)):
        theirs = {k: v for k, v in theirs.items() if not k.startswith("temporal.")}
    missing = [k for k in own if k not in theirs]
    wrong = ([f"{k} (not in this model)" for k in theirs if k not in own]
             + [f"{k} (missing)" for k in missing if not k.startswith("temporal.")]
             + [f"{k} ({tuple(theirs[k].shape)} vs {tuple(own[k].shape)} here)" for k in own
                if k in theirs and theirs[k].shape != own[k].shape])
    if wrong:
        more = f" and {len(wrong) - 3} more" if len(wrong) > 3 else ""
        keys = ""  # the weights' names alone did not say which setting differs (another backbone, memory, depth)
        if cfg is not None and isinstance(state.get("config"), dict):
            old = saved_config(state["config"], "the checkpoint of train.init_from")
            differ = [k for k in diff_configs(old, cfg) if is_under(k, ["model"]) and not is_under(k, NOT_BAKED)]
            keys = f", as the configs differ in {config_differences(old, cfg, differ)}" if differ else ""
        raise UserError(f"train.init_from: the checkpoint's weights do not fit this model's architecture "
                        f"({'; '.join(wrong[:3])}{more}){keys}; start from a checkpoint of the same model config")
    model.load_state_dict(theirs, strict=False)
    return missing


def param_groups(model: torch.nn.Module, params: list[torch.nn.Parameter], weight_decay: float) -> list[dict]:
    """Adam's parameter groups: ``weight_decay`` (the paper's L2, added to the gradient as the official code
    does) on all but the temporal fusion's parameters, which get none. Adam normalises each step by the
    gradient's size, so a parameter whose data gradient is zero (the fusion's memory weights while the
    memory is empty: the single-frame epochs of ``train.stream_warmup``, every scene start) is pushed to
    zero by the L2 term alone at ~lr per step: two thousand warm-up steps at 2e-3 erased the memory
    weights (1e-28) and the fusion ignored its memory for good (benchmarks/README.md, "Temporal")."""
    temporal = {id(p) for name, p in model.named_parameters() if name.startswith("temporal.")}
    decayed = [p for p in params if id(p) not in temporal]
    fusion = [p for p in params if id(p) in temporal]
    return [g for g in ({"params": decayed, "weight_decay": weight_decay}, {"params": fusion, "weight_decay": 0.0})
            if g["params"]]


def freeze_parameters(model: torch.nn.Module, prefixes) -> list[torch.nn.Parameter]:
    """Only the parameters under ``prefixes`` (``train.trainable``; empty: all) keep ``requires_grad``;
    returns them. A prefix naming no parameter is an error listing the model's parts."""
    named = dict(model.named_parameters())
    if not prefixes:
        return list(named.values())
    unused = [p for p in prefixes if not any(is_under(n, [p]) for n in named)]
    if unused:
        parts = sorted({n.split(".")[0] for n in named})
        raise UserError(f"train.trainable: {unused} name no parameter of this model (its parts: {', '.join(parts)}; "
                        "a prefix is a dotted module path, e.g. temporal or bev_heads.encoder)")
    kept = []
    for name, param in named.items():
        param.requires_grad_(is_under(name, prefixes))
        if param.requires_grad:
            kept.append(param)
    return kept


def check_frozen_are_trained(model: torch.nn.Module, cfg: ExperimentConfig, fresh: bool) -> None:
    """A fresh run (no ``train.init_from``, no resume) with ``train.trainable`` would keep the frozen
    parameters at their random initialisation: only a backbone with ``model.backbone.weights`` starts trained."""
    if not fresh or not cfg.train.trainable:
        return
    pretrained = ("backbone",) if cfg.model.backbone.weights else ()
    frozen = sorted({n.split(".")[0] for n, p in model.named_parameters()
                     if not p.requires_grad and not is_under(n, pretrained)})
    if frozen:
        raise UserError(f"train.trainable={list(cfg.train.trainable)} without train.init_from: the frozen parts "
                        f"({', '.join(frozen)}) keep their random initialisation; give train.init_from=CHECKPOINT "
                        "(the weights to fine-tune), or drop train.trainable")


def load_resume_state(resume: str | None, cfg: ExperimentConfig) -> dict | None:
    """The checkpoint to resume (None: a fresh run), checked against ``cfg`` (``RESUME_KEYS``)."""
    if resume is None:
        return None
    path = Path(resume)
    if not path.exists() and path.parent.is_dir() and not any((path.parent / n).exists() for n in RUN_FILES):
        raise CheckpointError(f"checkpoint not found: {path}; {path.parent} holds no training run (no checkpoint, "
                              "config.yaml or log.jsonl): check the path (a run's checkpoints are OUT/last.pt and "
                              "OUT/best.pt, OUT its train.out_dir)")
    if not path.exists() and path.parent.is_dir() and not any((path.parent / n).exists() for n in CHECKPOINTS):
        raise CheckpointError(f"checkpoint not found: {path}; the run in {path.parent} stopped before its first "
                              "checkpoint, so there is nothing to resume: run the same command without --resume")
    if not path.exists() and path.name == "last.pt" and (path.parent / "best.pt").is_file():
        raise CheckpointError(f"checkpoint not found: {path}; the run in {path.parent} stopped before it saved it "
                              f"(a full disk?), after best.pt: resume from that one, "
                              f"--resume {path.parent / 'best.pt'}")
    state = load_checkpoint(path)
    check_resumable(state, path)
    check_resume_config(state["config"], cfg, path)
    return state


def later_last_step(out_dir: Path, resume: Path, step: int) -> int | None:
    """The step of ``out_dir/last.pt`` when it is another file than ``resume`` and later than ``step`` (a run
    resumed from its ``best.pt`` replaces it at its next save), else None."""
    last = out_dir / "last.pt"
    try:
        if not last.is_file() or last.resolve() == resume.resolve():
            return None
        saved = load_checkpoint(last).get("step")
    except (CheckpointError, OSError):
        return None  # an unreadable last.pt is nothing to lose
    return saved if isinstance(saved, int) and saved > step else None


def best_score_in(out_dir: Path) -> float:
    """The validation score of the ``best.pt`` in ``out_dir`` (-inf without a readable one): a resume
    must not replace it with a worse model, whatever the checkpoint it resumes from remembers."""
    path = out_dir / "best.pt"
    if not path.is_file():
        return -math.inf
    try:
        best = load_checkpoint(path).get("best") or {}
    except CheckpointError:
        return -math.inf  # an unreadable best.pt is no model to keep
    score = best.get("score", -math.inf)
    return float(score) if isinstance(score, (int, float)) and not math.isnan(score) else -math.inf
