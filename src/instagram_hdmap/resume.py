"""What a training run starts from: the initial weights of ``train.init_from`` (which parts, which are
frozen) and the state of ``train --resume``, with the checks that the resumed run is the same run (the
keys that define the model and its targets, the training set, the data streams).
"""

from __future__ import annotations

import hashlib
import math
import os
from pathlib import Path

import torch

from . import distributed as du
from .checkpoint import (
    CheckpointError,
    check_resumable,
    load_checkpoint,
)
from .config import (
    ExperimentConfig,
    UserError,
    config_to_dict,
    diff_configs,
    get_key,
    is_under,
)
from .files import same_path
from .inference import MODEL_KEYS, NOT_BAKED, saved_config
from .postprocess import DECODE_KEYS
from .run_folder import CHECKPOINTS, RUN_FILES
from .training_data import ResumableSampler

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
              "data.split_scheme",
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


# the config keys a checkpoint that starts a fine-tuning (train.init_from) must share with the run: what
# the weights mean (the geometry, the inputs, the outputs); the architecture is checked by the weights'
# names and shapes, and the temporal memory may be new
INIT_KEYS = ("grid", "data.image_size", "data.classes", "data.dt_clip", "data.av2_cameras", "model.view_transform")
# the keys that only a temporal model (model.temporal.memory not none) reads: set on a single-frame model they are
# ignored (element persistence, model.temporal.persist_* and the pose-jump limits it shares, works on any model)
MEMORY_ONLY_KEYS = ("model.temporal.fusion", "model.temporal.kernel", "model.temporal.drop_prob",
                    "model.temporal.edge_samples", "train.stream_frames", "train.stream_warmup")


def check_init_from_outside(cfg: ExperimentConfig, out_dir: Path, resume: str | None) -> None:
    """``train.init_from`` must not be a checkpoint of ``out_dir``'s run: starting over there (``--force``)
    removes it before it is read, and the new run's saves replace it."""
    path = cfg.train.init_from
    if not path or resume is not None:  # a resumed run has its own weights; init_from is not read
        return
    for name in CHECKPOINTS:
        if same_path(Path(path), out_dir / name):  # a link to it, too
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
        # the weights' names alone did not say which setting differs (another backbone, memory, depth)
        differ = init_model_differences(state, cfg) if cfg is not None else ""
        keys = f", as the configs differ in {differ}" if differ else ""
        raise UserError(f"train.init_from: the checkpoint's weights do not fit this model's architecture "
                        f"({'; '.join(wrong[:3])}{more}){keys}; start from a checkpoint of the same model config")
    model.load_state_dict(theirs, strict=False)
    return missing


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


def resume_notes(run, state: dict, path: Path) -> list[str]:
    """What a user resuming ``path`` into ``run`` should know: another run's folder, a later ``last.pt``
    that the next save replaces, training or validation settings other than the checkpoint's, an unread
    ``train.init_from``."""
    notes: list[str] = []
    run_dir = path.resolve().parent  # a symbolic link to the checkpoint: the run it is in
    if run.clock.last < 1.0 and not same_path(run_dir, run.out_dir):  # (a finished one says so itself)
        notes.append(f"note: {path} is a checkpoint of the run in {run_dir}; this run goes on in "
                     f"train.out_dir={run.out_dir} (its checkpoints, log and TensorBoard events go there, the "
                     f"earlier ones stay in {run_dir}; to continue there, pass train.out_dir={run_dir})")
    later = later_last_step(run.out_dir, path, run.position.step)
    if later is not None:  # resuming best.pt on purpose is fine; replacing a later last.pt unsaid is not
        notes.append(f"note: {run.out_dir / 'last.pt'} is at step {later}, later than {path}; this run goes on "
                     f"from step {run.position.step} and its next save replaces that last.pt (to continue "
                     f"from step {later} instead, stop now and pass --resume {run.out_dir / 'last.pt'})")
    best = run.best.get("score", -math.inf)
    saved = saved_config(state["config"], f"checkpoint {path}")
    changed = config_differences(saved, run.cfg, RESUME_NOTED)
    if changed and run.clock.last < 1.0:
        notes.append(f"note: resumed with training settings other than the checkpoint's ({changed}): the "
                     f"{run.position.step} step(s) so far trained with the checkpoint's, the rest train with "
                     "these, and config.yaml and the next checkpoints record only these")
    measured = config_differences(saved, run.cfg, SCORE_KEYS)
    if measured and math.isfinite(best):
        notes.append(f"note: the best score so far ({best:.4g}, best.pt's) was measured with another "
                     f"validation ({measured}); this run's scores replace best.pt only where they exceed it, "
                     "a number of another kind")
    if run.cfg.train.init_from:
        notes.append(f"note: train.init_from={run.cfg.train.init_from} is not read on a resume: the weights are "
                     f"{path}'s (the run's own checkpoint)")
    return notes


def world_change_note(run, saved_world: int | None, path: Path | str) -> str | None:
    """A checkpoint saved part-way through an epoch by another number of processes. The shuffled
    sampler goes on exactly (``ResumableSampler.set_epoch``: its order does not depend on the ranks);
    the streaming one deals the scenes over the streams of all ranks, so under another number its
    epoch is another walk: said, not hidden. Checkpoints written before the world size was saved
    (None) get none."""
    p = run.position
    if saved_world is None or saved_world == run.world or not p.step_in_epoch:
        return None
    if isinstance(run.sampler, ResumableSampler):
        return (f"note: {path} was saved by {saved_world} process(es) at step {p.step_in_epoch} of epoch "
                f"{p.epoch}, resumed by {run.world}: the epoch goes on from the same sample (the batch "
                f"over all processes, train.batch_size={run.cfg.train.batch_size}, is the same)")
    return (f"note: {path} was saved by {saved_world} process(es) at step {p.step_in_epoch} of epoch "
            f"{p.epoch}, resumed by {run.world}: the streams' scenes are dealt over the processes, so "
            f"the rest of epoch {p.epoch} follows the dealing of {run.world} (some of its frames are "
            "walked twice, some not at all) and the streams start without memory; exact from the next "
            "epoch on (to keep this epoch exact, resume with the same number of processes)")


def check_not_finished(run, state: dict, path: Path) -> None:
    """A checkpoint whose schedule is complete has nothing to resume: asking it for more epochs is
    an error (the schedule's progress cannot be extended), resuming it as it was a note."""
    old_epochs = (state.get("config", {}).get("train") or {}).get("epochs")
    if run.clock.last < 1.0:
        p = run.position
        if old_epochs is not None and old_epochs != run.cfg.train.epochs and p.step > run.total_steps:
            # a shorter schedule that ends before the checkpoint: "done" after no step, exit 0, nothing written
            raise UserError(f"train.epochs={run.cfg.train.epochs} ends the schedule at step {run.total_steps}, "
                            f"before checkpoint {path}'s step {p.step} (epoch {p.epoch} of its {old_epochs}): "
                            f"nothing would be trained; resume with train.epochs={p.epoch + 1} or more (or its "
                            f"own {old_epochs}) to finish it")
        return
    if old_epochs is not None and old_epochs != run.cfg.train.epochs:
        raise UserError(f"checkpoint {path} completed its schedule ({old_epochs} epochs, step "
                        f"{run.position.step}); train.epochs={run.cfg.train.epochs} cannot extend a finished "
                        "schedule: start a new run (another train.out_dir)")
    run_dir = Path(path).resolve().parent  # a symbolic link to the checkpoint: the run it is in
    elsewhere = not same_path(run_dir, run.out_dir)
    du.print_main(f"checkpoint {path} completed its schedule: nothing left to train"
                  + (" but its final validation, which was interrupted" if run.validation_pending else "")
                  + (f"; its run's outputs stay in {run_dir}, train.out_dir={run.out_dir} gets no "
                     "checkpoint (to train on from it, start a new run with train.init_from=" + str(path) + ")"
                     if elsewhere else ""))


def init_notes(cfg, init_state: dict, new: list[str]) -> list[str]:
    """What a run started from ``train.init_from`` says: the weights' source (and the new tensors of a temporal
    fusion), model settings other than the checkpoint's, an unread ``model.backbone.weights``."""
    notes = [f"weights from {cfg.train.init_from}" + (f" ({len(new)} new tensors of the temporal fusion start from "
                                                         "their initialisation)" if new else "")]
    other = init_model_differences(init_state, cfg)
    if other:  # weights of the same names and shapes, loaded with no word (8 attention heads from 4)
        notes.append(f"note: the checkpoint of train.init_from was trained with other model settings "
                     f"({other}); its weights have this model's names and shapes and start this run, which "
                     "trains them under these settings")
    if cfg.model.backbone.weights and cfg.model.backbone.name != "tiny":  # unread, with no word
        notes.append(f"note: model.backbone.weights={cfg.model.backbone.weights} is not loaded: the backbone "
                     f"starts from the weights of train.init_from={cfg.train.init_from}, as every other part")
    return notes
