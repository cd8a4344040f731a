"""``instagram-hdmap train``: build every part from the config, run the epochs, save and resume.

The output folder holds ``config.yaml`` (resolved), ``log.jsonl`` (one line per epoch and
validation), ``tb/`` (TensorBoard events), ``last.pt`` and ``best.pt``.
A run killed at any point resumes with ``--resume OUT/last.pt`` on the next unseen batch, with the same optimizer,
schedule progress, scaler and RNG states: on CPU with ``train.deterministic=true`` the resumed weights equal those of
an uninterrupted run to float32 rounding (oneDNN's convolutions may round a last bit differently in a new process),
with augmentation and data workers too, since each sample's augmentation is drawn from (train.seed, epoch, index)
alone (``NuScenesMapDataset.augmentation_rng``).

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
import math
import os
import random
import sys
import threading
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from . import distributed as du
from .checkpoint import CheckpointError, rng_preserved, rng_state, save_checkpoint, set_rng_state
from .config import (
    DataConfig,
    ExperimentConfig,
    GraphHeadConfig,
    TrainConfig,
    UserError,
    as_config,
    config_to_dict,
    flatten,
    save_config,
)
from .data.streaming import StreamingBatchSampler
from .engine import EpochHooks, Position, StepInfo, StepSettings, evaluate, train_one_epoch
from .evaluation import Evaluator
from .files import json_safe, json_text, unlock_folder
from .geometry import BEVGrid
from .losses import Criterion
from .models import build_model, random_init_warning
from .models.backbone import imagenet_state
from .persistence import Persistence
from .postprocess import decode_options, postprocess_batch
from .precision import training_amp
from .resources import check_fits, reuse_freed_memory, size_notes, usable_cores
from .resume import (
    MEMORY_ONLY_KEYS,
    best_score_in,
    check_frozen_are_trained,
    check_init_from_outside,
    check_not_finished,
    check_same_train_set,
    folder_id,
    freeze_parameters,
    init_notes,
    init_weights,
    load_init_state,
    load_resume_state,
    memory_state,
    resume_notes,
    resumed_memory,
    train_set_fingerprint,
    world_change_note,
)
from .run_folder import moved_folder_error, prepare_out_dir, purge_log
from .schedule import ProgressClock, final_lr_factor, lr_factor
from .training_data import (
    DataWorkerError,
    ResumableSampler,
    build_loaders,
    data_worker_died,
    loader_batch_size,
    make_cmap_meter,
    make_flicker_meter,
    unused_meter_keys,
)


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)  # noqa: NPY002 (seeds the global stream third-party code uses)
    torch.manual_seed(seed)


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
        run = start_run(cfg, resume=resume, force=force, loaders=loaders, validate=validate)
        with run_threads(run), run_outputs(run):
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

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    chld = getattr(signal, "SIGCHLD", None)
    held: list = []
    owner = os.getpid()

    def interrupt(signum, frame):
        if os.getpid() != owner:  # a forked data-loader worker inherits this handler: the group's signal ends it
            for sig in caught:  # quietly (exit 0, as torch's worker loop does on KeyboardInterrupt), also while it
                signal.signal(sig, signal.SIG_IGN)  # is still starting, outside the loop's own handling, where the
            raise SystemExit(0)  # KeyboardInterrupt came out as a traceback under the run's one-line message
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
            for note in init_notes(cfg, init_state, new):
                du.print_main(note)
        trainable = freeze_parameters(self.model, cfg.train.trainable)
        self.criterion = Criterion(cfg.loss, self.grid, with_distance=cfg.model.bev_heads.distance_head)
        # fused: one kernel for all parameters instead of a loop of small ops (~3 ms of the demo's ~60 ms CPU step)
        self.optimizer = torch.optim.Adam(param_groups(self.model, trainable, cfg.train.weight_decay), lr=cfg.train.lr,
                                          fused=True)
        self.batch_size = loader_batch_size(self.train_loader)
        self.steps_per_epoch = math.ceil(self.sampler.num_samples / self.batch_size)
        # the schedule's length (max_steps only cuts it): a temporal training's single-frame epochs
        # (train.stream_warmup) are shorter than its epochs of pieces, whose longest stream sets their length;
        # epochs x the first epoch's steps ended the last epoch part-way with no word
        self.total_steps = (sum(self.sampler.steps_of_epoch(e) for e in range(cfg.train.epochs))
                            if isinstance(self.sampler, StreamingBatchSampler)
                            else cfg.train.epochs * self.steps_per_epoch)
        self.clock = ProgressClock(cfg.train, self.total_steps)
        self.amp, self.amp_note = training_amp(cfg.train.amp, device)
        self.step_settings = replace(StepSettings.from_config(cfg.train), amp=self.amp)
        self.scaler = torch.amp.GradScaler(device.type) if self.amp == "fp16" else None
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
        note = world_change_note(self, state.get("world"), path)
        if note:
            du.print_main(note)
        on_disk = best_score_in(self.out_dir)  # saved after the checkpoint resumed from (a kill in between)
        if on_disk > self.best.get("score", -math.inf):
            self.best = {**self.best, "score": on_disk}
        set_rng_state(state["rng"])

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
        if self.amp_note:
            du.print_main(self.amp_note)
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
            raise moved_folder_error(self.out_dir, self.position.step, e) from None
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
            settings=self.step_settings, scaler=self.scaler,
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
                           evaluator=Evaluator.from_config(self.cfg), amp=self.amp,
                           flicker=make_flicker_meter(self.cfg), persist=Persistence.from_config(self.cfg),
                           cmap=make_cmap_meter(self.cfg))
        self.summary["val"] = val
        score = val["metrics"]["mAP"] if "metrics" in val else -val["losses"].get("loss_total", math.inf)
        step = self.position.step
        if self.writer is not None:
            for k, v in val["losses"].items():
                self.writer.add_scalar(f"val/{k}", v, step)
            for key, name, value in (("metrics", "mAP", "mAP"), ("consistency", "flicker", "flicker_mean"),
                                     ("cmap", "C-mAP", "C-mAP")):
                if key in val:
                    self.writer.add_scalar(f"val/{name}", val[key][value], step)
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
            raise moved_folder_error(self.out_dir, self.position.step, None)
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


@contextlib.contextmanager
def run_threads(run: TrainingRun):
    """torch's intra-op threads for a CPU run (``cpu_threads``), restored afterwards. A CPU run also has glibc's
    malloc keep the blocks a step frees for the next step (``resources.reuse_freed_memory``, process-wide, as
    inference does): by default the demo's steps faulted ~2000 freed pages a step in again, and a 3-epoch demo
    run spent twice the kernel time (benchmarks/README.md, "The demo's training speed")."""
    before = torch.get_num_threads()
    threads = (cpu_threads(run.cfg, int(os.environ.get("LOCAL_WORLD_SIZE", 1)))
               if run.device.type == "cpu" else None)
    run.chosen_threads = threads
    if run.device.type == "cpu":
        reuse_freed_memory()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)


@contextlib.contextmanager
def run_outputs(run: TrainingRun):
    """Rank 0 writes config.yaml, TensorBoard events (tb/) and log.jsonl; closed at the end."""
    if du.is_main_process():
        save_config(run.cfg, run.out_dir / "config.yaml")
        from torch.utils.tensorboard import SummaryWriter  # slow to import; training only

        # a resumed run hides the events its killed predecessor wrote after the checkpoint (TensorBoard's
        # purge_step): they showed as a second curve over the steps the resume trains again
        purge = run.position.step + 1 if run.position.step else None
        run.writer = SummaryWriter(str(run.out_dir / "tb"), purge_step=purge)
        if run.log_lines is not None:  # the same for the log's lines (a checkpoint that counts them)
            run.log_lines = purge_log(run.out_dir / "log.jsonl", run.log_lines, du.print_main)
        run.log_file = (run.out_dir / "log.jsonl").open("a")
    previous_hook = threading.excepthook

    def thread_failed(args):  # TensorBoard's writer thread, once the folder is gone: said once by fit
        if not (isinstance(args.exc_value, OSError) and run.out_dir_moved()):
            previous_hook(args)

    threading.excepthook = thread_failed
    try:
        yield
    finally:
        threading.excepthook = previous_hook
        for handle in (run.log_file, run.writer):
            if handle is not None:
                try:
                    handle.close()
                except OSError:  # the folder moved away: fit said so; its error is not hidden by this one
                    if not run.out_dir_moved():
                        raise


def start_run(cfg: ExperimentConfig, *, resume: str | None, force: bool, loaders, validate: bool) -> TrainingRun:
    """The run of ``cfg``, set up in the order the RNG streams of an exact resume depend on: the checks that
    need no data, the output folder, the checkpoint to resume, seeds, the initial weights' fit, loaders, model
    and optimizer, the restored state."""
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
    run = TrainingRun(cfg, device, out_dir, loaders, validate, fresh=state is None, init_state=init_state)
    if state is not None:
        run.restore(state, Path(resume))
        check_not_finished(run, state, Path(resume))
        du.print_main(f"resumed from {resume}: epoch {run.position.epoch}, step {run.position.step} "
                      f"({run.position.step_in_epoch} into the epoch)")
        for note in resume_notes(run, state, Path(resume)):
            du.print_main(note)
    if run.world > 1:
        run.net = torch.nn.parallel.DistributedDataParallel(
            run.model, device_ids=[device.index] if device.type == "cuda" else None)
    return run


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


