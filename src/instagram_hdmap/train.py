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
"""

from __future__ import annotations

import json
import math
import os
import random
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from . import distributed as du
from .checkpoint import CheckpointError, load_checkpoint, rng_state, save_checkpoint, set_rng_state
from .config import ExperimentConfig, UserError, config_from_dict, config_to_dict, diff_configs, save_config
from .engine import evaluate, train_one_epoch
from .geometry import BEVGrid
from .schedule import ProgressClock, final_lr_factor, lr_factor

# Config sections that must match for a checkpoint to be resumed (training knobs may change).
_RESUME_MUST_MATCH = ("grid", "model", "loss", "data.image_size", "data.classes", "data.sample_dist")


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


def resolve_device(cfg: ExperimentConfig) -> str:
    if cfg.train.device == "cuda" and not torch.cuda.is_available():
        raise UserError("train.device=cuda but no CUDA device is available; use train.device=cpu")
    if cfg.train.device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return cfg.train.device


def prepare_out_dir(out_dir: Path, resume: bool, force: bool) -> None:
    """Refuse to write into a folder that already holds a run unless resuming or forced."""
    if not du.is_main_process():
        return
    if out_dir.exists() and any(out_dir.iterdir()) and not (resume or force):
        raise UserError(
            f"output folder {out_dir} already holds a run; pass --resume {out_dir / 'last.pt'} to continue it, "
            "--force to start over in it, or choose another train.out_dir"
        )
    out_dir.mkdir(parents=True, exist_ok=True)


def check_resume_config(ckpt_cfg: dict, cfg: ExperimentConfig, path: Path) -> None:
    try:
        old = config_from_dict(ckpt_cfg)
    except UserError as e:
        raise CheckpointError(f"checkpoint {path} holds a config this version cannot read: {e}") from None
    differ = [k for k in diff_configs(old, cfg) if k.startswith(_RESUME_MUST_MATCH)]
    if differ:
        old_d, new_d = config_to_dict(old), config_to_dict(cfg)

        def get(d, key):
            for p in key.split("."):
                d = d[p]
            return d

        lines = "; ".join(f"{k}: checkpoint {get(old_d, k)!r} vs now {get(new_d, k)!r}" for k in differ)
        raise CheckpointError(f"checkpoint {path} was trained with an incompatible config ({lines})")


def build_loaders(cfg: ExperimentConfig, world_size: int, with_val: bool = True):
    from .data import build_dataset
    from .data.nuscenes import collate_fn

    train_set = build_dataset(cfg, cfg.data.train_split, augment=cfg.data.augment)
    per_rank = max(cfg.train.batch_size // world_size, 1)
    sampler = ResumableSampler(len(train_set), shuffle=True, seed=cfg.train.seed)
    train_loader = DataLoader(train_set, batch_size=per_rank, sampler=sampler, collate_fn=collate_fn,
                              num_workers=cfg.data.num_workers, worker_init_fn=_worker_init,
                              drop_last=False, persistent_workers=False,
                              # its own generator: making an iterator must not draw from the global
                              # torch RNG, whose state the checkpoint restores for exact resume
                              generator=torch.Generator().manual_seed(cfg.train.seed))
    val_loader = None
    if with_val:
        val_set = build_dataset(cfg, cfg.data.val_split, augment=False, like=train_set)
        val_sampler = ResumableSampler(len(val_set), shuffle=False)
        val_loader = DataLoader(val_set, batch_size=cfg.eval.batch_size, sampler=val_sampler,
                                collate_fn=collate_fn, num_workers=cfg.data.num_workers)
    return train_loader, sampler, val_loader


ResumableSampler = du.ResumableSampler


def make_evaluator(cfg: ExperimentConfig):
    from .evaluation import Evaluator

    return Evaluator.from_config(cfg)


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity mask; all cores where there is none)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


def cpu_threads(cfg: ExperimentConfig, local_processes: int = 1) -> int | None:
    """Intra-op threads for a CPU training run (``train.cpu_threads``); None: leave torch's setting
    (``OMP_NUM_THREADS`` is set and no explicit value is given). Automatic: this process's share of
    the usable cores minus its data workers, at least 1: on a small machine the data workers' JPEG
    decoding and torch's spin-waiting OpenMP threads otherwise fight over the same cores."""
    if cfg.train.cpu_threads is not None:
        return cfg.train.cpu_threads
    if os.environ.get("OMP_NUM_THREADS"):
        return None
    return max(1, usable_cores() // max(local_processes, 1) - cfg.data.num_workers)


def train(cfg: ExperimentConfig, *, resume: str | None = None, force: bool = False,
          loaders=None, validate: bool = True) -> dict:
    """Train ``cfg``; returns the final summary (epoch, step, last metrics). ``loaders`` =
    (train_loader, sampler, val_loader) may be given (tests); otherwise built from the config."""
    from .losses import Criterion
    from .models import build_model, random_init_warning
    from .postprocess import decode_options, postprocess_batch

    device = du.init_distributed(resolve_device(cfg))
    world = du.get_world_size()
    out_dir = Path(cfg.train.out_dir)
    prepare_out_dir(out_dir, resume is not None, force)
    du.barrier()

    state = None
    if resume is not None:
        state = load_checkpoint(resume)
        check_resume_config(state["config"], cfg, Path(resume))

    seed_everything(cfg.train.seed + du.get_rank())
    if cfg.train.deterministic:
        torch.use_deterministic_algorithms(True)
    grid = BEVGrid.from_config(cfg.grid)
    decode = decode_options(cfg.model.gnn, grid)

    if state is None and cfg.model.backbone.name != "tiny" and cfg.model.backbone.weights == "imagenet":
        from .models.backbone import imagenet_state

        imagenet_state(cfg.model.backbone.name)  # fail fast (one line) before the loaders' long setup
    if loaders is None:
        loaders = build_loaders(cfg, world, with_val=validate)
    train_loader, sampler, val_loader = loaders

    # ImageNet weights on a fresh start only (a resumed run has its own)
    model = build_model(cfg, pretrained=state is None).to(device)
    random_init = random_init_warning(cfg) if state is None else None
    if random_init:
        du.print_main(random_init)
    criterion = Criterion(cfg.loss, grid, with_distance=cfg.model.bev_heads.distance_head)
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.train.lr, weight_decay=cfg.train.weight_decay)
    steps_per_epoch = math.ceil(sampler.num_samples / train_loader.batch_size)
    total_steps = cfg.train.epochs * steps_per_epoch  # the schedule's length; max_steps only cuts it
    clock = ProgressClock(cfg.train, total_steps)
    scaler = torch.amp.GradScaler(device.type) if cfg.train.amp == "fp16" else None

    epoch, global_step, step_in_epoch, best = 0, 0, 0, {"score": -math.inf}
    if state is not None:
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        clock.load_state_dict(state.get("clock") or {})
        if scaler is not None and state.get("scaler") is not None:
            scaler.load_state_dict(state["scaler"])
        epoch, global_step, step_in_epoch = state["epoch"], state["step"], state["step_in_epoch"]
        best = state.get("best", best)
        set_rng_state(state["rng"])
        du.print_main(f"resumed from {resume}: epoch {epoch}, step {global_step} ({step_in_epoch} into the epoch)")

    net = model
    if world > 1:
        net = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[device.index] if device.type == "cuda" else None)

    writer = None
    if du.is_main_process():
        save_config(cfg, out_dir / "config.yaml")
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(str(out_dir / "tb"))

    def checkpoint(path: Path, ep: int, step: int, in_epoch: int, metrics: dict | None = None) -> None:
        if du.is_main_process():
            save_checkpoint({
                "model": model.state_dict(), "optimizer": optimizer.state_dict(),
                "clock": clock.state_dict(), "scaler": scaler.state_dict() if scaler else None,
                "epoch": ep, "step": step, "step_in_epoch": in_epoch, "rng": rng_state(),
                "config": config_to_dict(cfg), "metrics": metrics or {}, "best": best,
            }, path)

    sync = device if world > 1 and cfg.train.time_budget_min is not None else None

    def set_lr(step: int) -> None:
        lr = cfg.train.lr * lr_factor(clock.progress(step, sync), cfg.train)
        for group in optimizer.param_groups:
            group["lr"] = lr

    def should_stop(step: int) -> bool:
        done = clock.progress(step, sync) >= 1.0  # always: clock.last is then the progress of `step` steps
        return done or (cfg.train.max_steps is not None and step >= cfg.train.max_steps)

    progress = {"epoch": epoch, "step": global_step, "in_epoch": step_in_epoch}

    def schedule_summary() -> dict:
        lr = optimizer.param_groups[0]["lr"]
        final = cfg.train.lr * final_lr_factor(cfg.train)
        return {"progress": round(clock.last, 4), "lr": lr, "final_lr": final,
                "schedule_complete": bool(clock.last >= 1.0 and math.isclose(lr, final, rel_tol=1e-6)),
                "elapsed_s": round(clock.elapsed(), 1)}

    def on_step(info) -> None:
        progress.update(epoch=info.epoch, step=info.step, in_epoch=info.step_in_epoch)
        every = cfg.train.checkpoint_every
        if every and info.step % every == 0:
            checkpoint(out_dir / "last.pt", info.epoch, info.step, info.step_in_epoch)

    log = (out_dir / "log.jsonl").open("a") if du.is_main_process() else None
    summary: dict = {}
    stopped = False
    threads_before = torch.get_num_threads()
    threads = cpu_threads(cfg, int(os.environ.get("LOCAL_WORLD_SIZE", 1))) if device.type == "cpu" else None
    if threads is not None:
        torch.set_num_threads(threads)  # restored when train() returns (the finally below)
    clock.start()
    set_lr(global_step)
    if device.type == "cpu":
        du.print_main(f"cpu: {torch.get_num_threads()} torch thread(s), {cfg.data.num_workers} data worker(s), "
                      f"{usable_cores()} usable core(s)" + (" (train.cpu_threads)" if cfg.train.cpu_threads
                                                           else " (OMP_NUM_THREADS)" if threads is None else ""))
    du.print_main(f"schedule: {cfg.train.schedule}, {total_steps} steps"
                  + (f" or {cfg.train.time_budget_min:g} min, whichever comes first" if clock.budget_s else "")
                  + f"; progress {clock.last:.3f}, lr {optimizer.param_groups[0]['lr']:.3g}")
    if random_init:  # again where the log ends up being read
        du.print_main(random_init)
        summary["warnings"] = [random_init]
    try:
        summary["cpu_threads"] = torch.get_num_threads() if device.type == "cpu" else None
        finished = should_stop(global_step)
        while not finished:
            sampler.set_epoch(epoch, start=step_in_epoch * train_loader.batch_size)
            if hasattr(train_loader.dataset, "set_epoch"):
                train_loader.dataset.set_epoch(epoch)  # augmentation draws follow (seed, epoch, index)
            result = train_one_epoch(
                net, criterion, train_loader, optimizer, device, epoch, global_step=global_step,
                step_in_epoch=step_in_epoch, amp=cfg.train.amp, scaler=scaler, grad_clip=cfg.train.grad_clip,
                on_nonfinite=cfg.train.on_nonfinite, log_every=cfg.train.log_every, writer=writer,
                should_stop=should_stop, on_step=on_step, before_step=set_lr, total=steps_per_epoch,
            )
            global_step, step_in_epoch, stopped = result["global_step"], result["step_in_epoch"], result["stopped"]
            progress.update(epoch=epoch, step=global_step, in_epoch=step_in_epoch)
            summary = {**summary, "epoch": epoch, "step": global_step, "train": result["stats"],
                       "train_seconds": round(result["seconds"], 2), "samples_per_s": round(result["samples_per_s"], 2),
                       **schedule_summary()}
            if stopped:  # part-way through the epoch: resume continues it
                checkpoint(out_dir / "last.pt", epoch, global_step, step_in_epoch)
            else:
                epoch, step_in_epoch = epoch + 1, 0
                progress.update(epoch=epoch, in_epoch=0)
            finished = stopped or should_stop(global_step)  # also refreshes the clock saved below
            if validate and val_loader is not None and (finished or epoch % cfg.train.val_every == 0):
                val = evaluate(net, criterion, val_loader, device,
                               postprocess=lambda out: postprocess_batch(out, grid, **decode),
                               evaluator=make_evaluator(cfg), amp=cfg.train.amp)
                summary["val"] = val
                score = val["metrics"]["mAP"] if "metrics" in val else -val["losses"].get("loss_total", math.inf)
                if writer is not None:
                    for k, v in val["losses"].items():
                        writer.add_scalar(f"val/{k}", v, global_step)
                    if "metrics" in val:
                        writer.add_scalar("val/mAP", val["metrics"]["mAP"], global_step)
                if not math.isnan(score) and score > best["score"]:
                    best = {"score": score, "epoch": epoch, "step": global_step}
                    checkpoint(out_dir / "best.pt", epoch, global_step, step_in_epoch, val.get("metrics"))
            if not stopped:
                metrics = summary.get("val", {}).get("metrics")
                checkpoint(out_dir / "last.pt", epoch, global_step, step_in_epoch, metrics)
            if log is not None:
                log.write(json.dumps(summary, default=float) + "\n")
                log.flush()
    except KeyboardInterrupt:
        # The weights are those after the last completed step, which ``progress`` names.
        checkpoint(out_dir / "last.pt", progress["epoch"], progress["step"], progress["in_epoch"])
        du.print_main(f"interrupted: saved {out_dir / 'last.pt'} (resume with --resume {out_dir / 'last.pt'})")
        raise
    finally:
        if log is not None:
            log.close()
        if writer is not None:
            writer.close()
        torch.set_num_threads(threads_before)
    summary.update(schedule_summary())
    summary["out_dir"] = str(out_dir)
    return summary
