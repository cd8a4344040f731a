"""The data side of a training run: its loaders (samplers that resume mid-epoch, data workers seeded
and given enough open files), a data worker's death told in one line, and the meters that score the
validation's drives (flicker rate, consistency-aware mAP).
"""

from __future__ import annotations

import contextlib
import random
import re

import numpy as np
import torch
from torch.utils.data import DataLoader

from . import distributed as du
from .config import EvalConfig, ExperimentConfig, GraphHeadConfig, UserError
from .data import build_dataset
from .data.base import collate_fn
from .data.streaming import StreamingBatchSampler
from .evaluation.consistency import ConsistentAPMeter, FlickerMeter
from .geometry import BEVGrid
from .resources import data_workers, human, memory_available

WORKER_DIED = re.compile(r"DataLoader worker \(pids?\(?s?\)? ?[\d, ]+\)? (is killed by signal|exited unexpectedly)")


def data_worker_died(e: BaseException) -> str | None:
    """torch's message when a data-loader worker process died (the out-of-memory killer's choice, a ``kill -9``),
    first line only; None for another exception."""
    text = str(e).strip()
    return text.splitlines()[0] if isinstance(e, RuntimeError) and WORKER_DIED.search(text) else None


class DataWorkerError(UserError):
    """A data-loader worker died during a training: ``last.pt`` was saved at the last completed step."""


def _worker_init(worker_id: int) -> None:
    # Each worker's NumPy/random streams derive from torch's per-worker seed (itself a function of
    # the base seed drawn in the main process, which is part of the checkpointed RNG state).
    seed = torch.initial_seed() % 2**32
    np.random.seed(seed)  # noqa: NPY002 (seeds the global stream third-party code uses)
    random.seed(seed)


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


CACHE_SHARE = 0.5  # data.cache_in_memory keeps the samples when they take at most this share of the free memory


def keep_in_memory(dataset) -> None:
    """``data.cache_in_memory``: the dataset keeps its samples once loaded if they fit in ``CACHE_SHARE`` of the
    free memory; otherwise a note, and each epoch reads the files again."""
    room, what = memory_available()
    need = dataset.keep_in_memory(CACHE_SHARE * room)
    if dataset.kept is None:
        du.print_main(f"note: data.cache_in_memory: the {len(dataset)} training samples would hold {human(need)}, "
                      f"more than {CACHE_SHARE:.0%} of the {human(room)} {what} free: each epoch reads them from "
                      "disk")


def build_loaders(cfg: ExperimentConfig, world_size: int, with_val: bool = True):
    """(train loader, its sampler, val loader). A temporal model (``model.temporal.memory`` not none)
    reads drives: each rank's batch rows are streams walking whole scenes in order
    (``data.streaming.StreamingBatchSampler``, ``train.batch_size / world`` streams per rank, in pieces
    of ``train.stream_frames``, after ``train.stream_warmup`` of the epochs on shuffled single frames;
    the validation loader ``eval.batch_size`` streams of whole scenes)."""
    train_set = build_dataset(cfg, cfg.data.train_split, augment=cfg.data.augment)
    if cfg.data.cache_in_memory:
        keep_in_memory(train_set)
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
        batching = ({"batch_sampler": StreamingBatchSampler(val_set.scenes.runs, cfg.eval.batch_size, shuffle=False,
                                                            rank=du.get_rank(), world_size=world_size)} if streaming
                    else {"batch_size": cfg.eval.batch_size, "sampler": ResumableSampler(len(val_set), shuffle=False)})
        workers = data_workers(cfg.data.num_workers, len(val_set))
        val_loader = DataLoader(val_set, collate_fn=collate_fn, num_workers=workers, **batching)
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


ResumableSampler = du.ResumableSampler
