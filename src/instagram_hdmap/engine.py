"""The training and evaluation loops (DETR's engine.py pattern): ``train_one_epoch`` and ``evaluate``.

Everything else (building parts, checkpoints, schedules) lives in train.py; these two functions
only iterate, step, log and measure.
"""

from __future__ import annotations

import contextlib
import math
import sys
import time
from collections import defaultdict
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import torch
from tqdm import tqdm

from . import distributed as du
from .config import UserError
from .models.temporal import STATUS_NAMES


class NonFiniteLossError(UserError):
    """The loss became NaN/inf; the message names the step and the terms."""


@dataclass
class Position:
    """Where training stands: the epoch in progress, optimisation steps done in total and batches of
    this epoch consumed (a resumed run starts an epoch part-way)."""

    epoch: int
    step: int = 0
    step_in_epoch: int = 0


@dataclass
class StepInfo:
    epoch: int
    step: int  # global optimisation step, after this step
    step_in_epoch: int  # batches of this epoch consumed, after this step
    losses: dict[str, float]
    memory: dict | None = None  # a temporal model's memory after this step (saved for exact resume)


def bar_interval() -> float:
    """Seconds between two drawings of a progress bar: 0.1 on a terminal, 60 where stderr is a file or a pipe
    (``train ... 2> log``, nohup): a bar drawn at every step filled the log of a long training with megabytes of
    carriage-return-separated lines (one ``tail`` line of a whole epoch)."""
    try:
        return 0.1 if sys.stderr.isatty() else 60.0
    except (AttributeError, ValueError, OSError):  # closed or replaced
        return 60.0


def is_temporal(model: torch.nn.Module) -> bool:
    """A temporal model (models/temporal.py), DDP-wrapped or not: it streams its memory from batch to batch."""
    return bool(getattr(getattr(model, "module", model), "is_temporal", False))


def memory_counts(outputs: dict) -> dict[str, float]:
    """A temporal model's per-batch ``memory_status`` as counts ``memory_<status>`` (empty otherwise)."""
    status = outputs.get("memory_status")
    if status is None:
        return {}
    counts = torch.bincount(status.detach().flatten().cpu(), minlength=len(STATUS_NAMES))
    return {f"memory_{name}": float(c) for name, c in zip(STATUS_NAMES, counts.tolist())}


@dataclass
class StepSettings:
    """How each optimisation step runs (the ``train.*`` keys of the same names)."""

    amp: str = "none"  # autocast: none | bf16 | fp16 (fp16 with a GradScaler)
    grad_clip: float = 0.0  # max gradient norm; 0: none
    on_nonfinite: str = "stop"  # a NaN/inf loss: stop (NonFiniteLossError) | skip the step
    log_every: int = 10  # steps between logged (reduced) losses

    @classmethod
    def from_config(cls, train_cfg) -> StepSettings:
        return cls(amp=train_cfg.amp, grad_clip=train_cfg.grad_clip, on_nonfinite=train_cfg.on_nonfinite,
                   log_every=train_cfg.log_every)


@dataclass
class EpochHooks:
    """What the caller of ``train_one_epoch`` does around each step (every hook optional)."""

    before_step: Callable[[int], None] | None = None  # steps done so far -> (the LR schedule sets the LR)
    on_step: Callable[[StepInfo], None] | None = None  # after each step (mid-epoch checkpoints)
    should_stop: Callable[[int], bool] | None = None  # steps done -> end the epoch now
    writer: object | None = None  # a TensorBoard SummaryWriter for the logged scalars


def autocast_context(device: torch.device, amp: str):
    """``torch.autocast`` for "bf16"/"fp16", a no-op for "none" (``train.amp=auto`` is resolved before:
    ``precision.training_amp``)."""
    if amp == "none":
        return contextlib.nullcontext()
    dtypes = {"bf16": torch.bfloat16, "fp16": torch.float16}
    if amp not in dtypes:
        raise ValueError(f"autocast_context: amp must be none, bf16 or fp16, got {amp!r}")
    return torch.autocast(device_type=device.type, dtype=dtypes[amp])


def move_to(batch: dict, device: torch.device) -> dict:
    """Tensors of the batch to ``device``; lists (polylines, tokens) stay on the host."""
    return {k: v.to(device, non_blocking=True) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}


def _scalars(d: dict) -> dict[str, float]:
    """The scalar entries of a loss dict as Python floats (for logging)."""
    return {k: float(v.detach() if torch.is_tensor(v) else v) for k, v in d.items()
            if (torch.is_tensor(v) and v.numel() == 1) or isinstance(v, (int, float))}


def optimisation_step(loss: torch.Tensor, model: torch.nn.Module, optimizer: torch.optim.Optimizer,
                      scaler: torch.amp.GradScaler | None, grad_clip: float) -> torch.Tensor:
    """Backward, gradient clipping (``grad_clip`` > 0; 0: none), optimizer step (through the fp16
    ``scaler`` if any); returns the gradient norm before clipping."""
    optimizer.zero_grad(set_to_none=True)
    (loss if scaler is None else scaler.scale(loss)).backward()
    if scaler is not None:
        scaler.unscale_(optimizer)
    grad_norm = torch.nn.utils.clip_grad_norm_(model.parameters(), grad_clip if grad_clip > 0 else math.inf)
    if scaler is not None:
        scaler.step(optimizer)
        scaler.update()
    else:
        optimizer.step()
    return grad_norm


def scored_tokens(loader) -> set[str] | None:
    """The sample tokens a streaming loader's rank owns (``StreamingBatchSampler.owned``), None for
    another loader (every sample it yields is scored)."""
    sampler = getattr(loader, "batch_sampler", None)
    if not hasattr(sampler, "owned"):
        return None
    tokens = loader.dataset.sample_tokens
    return {tokens[i] for i in sampler.owned()}


def _bar(batches, loader, total: int | None, desc: str, initial: int = 0) -> tqdm:
    """Rank 0's progress bar over the iterator ``batches`` of ``loader``: ``total`` batches, None: the loader's
    length (given its iterator, tqdm no longer sees the loader), unknown for an iterable-style dataset."""
    if total is None:
        with contextlib.suppress(TypeError):
            total = len(loader)
    return tqdm(batches, total=total, initial=initial, desc=desc, dynamic_ncols=True,
                disable=not du.is_main_process(), leave=False, mininterval=bar_interval())


def shut_down_workers(batches) -> None:
    """The data-loader workers of a loop cut short (Ctrl-C, a SIGTERM, an error), shut down now. Left to the
    iterator's ``__del__``, the shutdown ran later, after the run had saved and printed its one-line message,
    where a worker that the same signal had killed (a scheduler signals the whole process group) raised torch's
    "DataLoader worker ... is killed by signal" as an "Exception ignored" traceback under that line, or in the
    middle of the save of ``last.pt``; the shutdown also takes the workers' pids off torch's SIGCHLD watch.
    A worker's death reported during the shutdown is the one the loop is ending on: not raised again."""
    shutdown = getattr(batches, "_shutdown_workers", None)  # torch's multi-process iterator (a private method)
    if shutdown is None:
        return
    try:
        shutdown()
    except RuntimeError as e:
        if "DataLoader worker" not in str(e):
            raise


def _skip_nonfinite(losses: dict, settings: StepSettings, epoch: int, global_step: int) -> None:
    """A step whose loss is not finite: raised under ``train.on_nonfinite=stop``, else said and skipped."""
    terms = ", ".join(f"{k}={float(v.detach()):.4g}" for k, v in losses.items() if k.startswith("loss_"))
    if settings.on_nonfinite == "stop":
        raise NonFiniteLossError(
            f"non-finite loss at epoch {epoch}, step {global_step}: {terms}. Lower train.lr, try "
            "train.amp=none, or set train.on_nonfinite=skip to skip such steps"
        )
    du.print_main(f"warning: skipping step {global_step} with non-finite loss ({terms})")


def _step_values(losses: dict, grad_norm, outputs: dict) -> dict[str, float]:
    """What a step logs: its losses, the gradient norm, the memory statuses and the vertices per sample."""
    values = _scalars(losses)
    values["grad_norm"] = float(grad_norm)
    values.update(memory_counts(outputs))
    if "pred_vertex_mask" in outputs:
        values["num_vertices"] = float(outputs["pred_vertex_mask"].sum(1).float().mean())
    return values


def _log_step(bar, writer, values: dict, throughput: float, lr: float, step: int, device: torch.device) -> None:
    """A logged step's values (averaged over the ranks) on the progress bar and in TensorBoard."""
    logged = du.reduce_dict(values, device if device.type == "cuda" else None)
    bar.set_postfix(refresh=bar_interval() < 1, loss=f"{logged['loss_total']:.3f}",
                    **{k[5:]: f"{v:.3f}" for k, v in logged.items()
                       if k.startswith("loss_") and k != "loss_total" and not k.endswith("_weighted")})
    if writer is not None:
        for k, v in logged.items():
            writer.add_scalar(f"train/{k}", v, step)
        writer.add_scalar("train/lr", lr, step)
        writer.add_scalar("train/samples_per_s", throughput, step)


def train_one_epoch(
    model: torch.nn.Module,
    criterion: Callable[[dict, dict], dict],
    loader: Iterable[dict],
    optimizer: torch.optim.Optimizer,
    device: torch.device,
    position: Position,
    *,
    settings: StepSettings | None = None,
    scaler: torch.amp.GradScaler | None = None,
    hooks: EpochHooks | None = None,
    total: int | None = None,
    memory: dict | None = None,
) -> dict:
    """One pass over ``loader`` from ``position`` (the loader already starts at its ``step_in_epoch``
    on resume); ``total``: batches in the whole epoch (for the progress bar).

    ``hooks.before_step(global_step)`` runs before each step with the number of steps done so far
    (the LR schedule sets the learning rate there). Returns ``{"stats": mean of each logged scalar,
    "global_step", "step_in_epoch", "stopped", "seconds", "samples_per_s"}``; ``stopped`` is True
    when ``hooks.should_stop(global_step)`` ended the epoch early; ``"memory"``: see below.

    A temporal model (``is_temporal``) gets each batch with the memory its previous batch returned
    (the loader's rows are streams, data/streaming.py; the memory is detached, so no gradient crosses
    a step), starting from ``memory`` (None: empty; a resumed run passes the saved one); the result's
    ``"memory"`` is the last one (None for a single-frame model).
    """
    settings, hooks = settings or StepSettings(), hooks or EpochHooks()
    epoch, global_step, step_in_epoch = position.epoch, position.step, position.step_in_epoch
    model.train()
    streaming = is_temporal(model)
    sums: dict[str, float] = defaultdict(float)
    count = n_samples = n_last = 0
    stopped = False
    t_epoch = t_last = time.perf_counter()
    batches = iter(loader)
    bar = _bar(batches, loader, total, f"epoch {epoch}", initial=step_in_epoch)
    try:
        for batch in bar:
            batch = move_to(batch, device)
            if hooks.before_step is not None:
                hooks.before_step(global_step)
            with autocast_context(device, settings.amp):
                outputs = model(batch, memory=memory) if streaming else model(batch)
            if streaming:
                memory = outputs["memory"]
            losses = criterion(outputs, batch)  # the criterion casts to float32 where it matters
            global_step += 1
            step_in_epoch += 1
            if not torch.isfinite(losses["loss_total"]):
                _skip_nonfinite(losses, settings, epoch, global_step)
                optimizer.zero_grad(set_to_none=True)
                memory = None  # a memory of non-finite features would poison the next steps
                continue
            grad_norm = optimisation_step(losses["loss_total"], model, optimizer, scaler, settings.grad_clip)
            values = _step_values(losses, grad_norm, outputs)
            for k, v in values.items():
                sums[k] += v
            count += 1
            rows = batch["images"].shape[0] * du.get_world_size()  # the samples of this step over all ranks
            n_samples += rows
            if global_step % settings.log_every == 0 or step_in_epoch == 1:
                now = time.perf_counter()
                throughput = rows * (count - n_last) / max(now - t_last, 1e-9)
                t_last, n_last = now, count
                _log_step(bar, hooks.writer, values, throughput, optimizer.param_groups[0]["lr"], global_step, device)
            if hooks.on_step is not None:
                hooks.on_step(StepInfo(epoch, global_step, step_in_epoch, values, memory))
            if hooks.should_stop is not None and hooks.should_stop(global_step):
                stopped = True
                break
    except BaseException:
        shut_down_workers(batches)
        raise
    bar.close()
    stats = _mean_over_ranks(sums, count, device)
    seconds = time.perf_counter() - t_epoch
    return {"stats": stats, "global_step": global_step, "step_in_epoch": step_in_epoch, "stopped": stopped,
            "seconds": seconds, "samples_per_s": n_samples / max(seconds, 1e-9), "memory": memory}


def _rows_to_score(batch: dict, owned: set | None, streaming: bool) -> tuple[list[int], list[int]]:
    """The rows of ``batch`` to score and, for a temporal model, those whose memory status counts. A streaming
    loader's padding is not scored: each sample it ``owned`` once (even twice in a batch), and a stand-in for a
    bad frame is scored in its own place; a bad frame counts as a missing one, once (not in padding)."""
    tokens, keep = batch.get("sample_token"), list(range(batch["images"].shape[0]))
    replaced = batch["replaced"].tolist() if streaming and "replaced" in batch else [False] * len(keep)
    if owned is not None:
        keep = []
        for b, t in enumerate(tokens):
            if t in owned and not replaced[b]:
                keep.append(b)
                owned.discard(t)
    counted = list(keep)
    if streaming:
        for b, r in enumerate(replaced):
            if r and (owned is None or batch["stands_for"][b] in owned):
                counted.append(b)
                if owned is not None:
                    owned.discard(batch["stands_for"][b])
    return keep, counted


def _scored_predictions(preds: list[list[dict]], batch: dict, keep: list[int], persist) -> tuple[list, int]:
    """The predictions of the rows ``keep``, with the elements ``persist`` keeps from earlier frames, and how many
    it kept. The scored samples only: a stream's padding walks a scene again (at the same time as the stream that
    owns it, when there are more streams than scenes) and would overwrite that scene's remembered elements
    between its frames."""
    persisted = 0
    if persist is not None and keep:
        with_kept = persist([preds[b] for b in keep], [batch["scene"][b] for b in keep],
                            batch["frame_index"][keep], batch["ego_pose"][keep])
        for b, p in zip(keep, with_kept):
            persisted += len(p) - len(preds[b])  # the kept ones come last
            preds[b] = p
    return [preds[b] for b in keep], persisted


def _mean_over_ranks(sums: dict, count: int, device: torch.device) -> dict[str, float]:
    """The mean of each summed value over the ``count`` batches of every rank."""
    return du.reduce_dict({k: v / max(count, 1) for k, v in sums.items()}, device if device.type == "cuda" else None)


def meter_results(flicker, cmap, evaluator) -> dict:
    """Each meter's result over all ranks: the flicker rate, the consistency-aware mAP and the AP metrics."""
    result = {}
    for key, meter in (("consistency", flicker), ("cmap", cmap), ("metrics", evaluator)):
        if meter is not None:
            meter.gather()
            result[key] = meter.compute()
    return result


@torch.no_grad()
def evaluate(
    model: torch.nn.Module,
    criterion: Callable[[dict, dict], dict] | None,
    loader: Iterable[dict],
    device: torch.device,
    *,
    postprocess: Callable[[dict], list[list[dict]]] | None = None,
    evaluator=None,
    amp: str = "none",
    on_predictions: Callable[[list[str], list[list[dict]]], None] | None = None,
    total: int | None = None,
    flicker=None,
    scored: set[str] | None = None,
    persist=None,
    cmap=None,
) -> dict:
    """Validation pass: mean losses and, with ``postprocess`` + ``evaluator``, the AP metrics.

    ``postprocess(outputs) -> per-sample polyline dicts`` (metres, ego frame);
    ``evaluator.update(predictions, ground_truths, tokens=...)``; ``evaluator.gather()`` then ``compute()``.
    ``on_predictions(tokens, predictions)`` receives every batch's predictions (e.g. to write JSON).

    A temporal model (``is_temporal``) walks the loader's streams with its memory (the loader must
    yield streams: data/streaming.py); ``result["memory"]`` counts the samples per memory status
    (fused, no_memory, pose_jump, missing_frame). A streaming loader's padding is not scored: only the
    samples its batch sampler ``owned()`` (or the tokens in ``scored``), once each. ``flicker``: a
    ``FlickerMeter`` updated with every batch's predictions (needs ``postprocess``);
    ``result["consistency"]`` is its ``compute()``. ``persist``: a ``persistence.Persistence`` applied to
    the scored samples' predictions (each scene's samples in frame order; not a stream's padding) before
    they are scored; ``result["persisted"]`` counts the elements it kept (summed over the ranks). ``cmap``: a
    ``ConsistentAPMeter`` updated like ``flicker`` (after persistence); ``result["cmap"]`` is its ``compute()``.
    """
    model.eval()
    streaming, memory = is_temporal(model), None
    owned = set(scored) if scored is not None else scored_tokens(loader)
    sums: dict[str, float] = defaultdict(float)
    status_counts: dict[str, float] = defaultdict(float)
    count = persisted = 0
    t0 = time.perf_counter()
    n_samples = 0
    batches = iter(loader)
    try:
        for batch in _bar(batches, loader, total, "eval"):
            batch = move_to(batch, device)
            with autocast_context(device, amp):
                outputs = model(batch, memory=memory) if streaming else model(batch)
            keep, counted = _rows_to_score(batch, owned, streaming)
            if streaming:
                memory = outputs["memory"]
                for k, v in memory_counts({"memory_status": outputs["memory_status"][counted]}).items():
                    status_counts[k] += v
            if criterion is not None:
                for k, v in _scalars(criterion(outputs, batch)).items():
                    sums[k] += v
                count += 1
            n_samples += batch["images"].shape[0]
            if postprocess is not None:
                preds, kept = _scored_predictions(postprocess(outputs), batch, keep, persist)
                persisted += kept
                tokens, gts = [batch["sample_token"][b] for b in keep], [batch["gt_polylines"][b] for b in keep]
                if evaluator is not None:
                    evaluator.update(preds, gts, tokens=tokens)
                if on_predictions is not None:
                    on_predictions(tokens, preds)
                for meter in (flicker, cmap):
                    if meter is not None:
                        meter.update(preds, gts, [batch["scene"][b] for b in keep], batch["frame_index"][keep],
                                     batch["ego_pose"][keep])
    except BaseException:
        shut_down_workers(batches)
        raise
    result = {"losses": _mean_over_ranks(sums, count, device)}
    if streaming:  # the memory status counts summed over the ranks: their mean, times the ranks
        result["memory"] = {k: int(round(v * du.get_world_size()))
                            for k, v in _mean_over_ranks(status_counts, 1, device).items()}
    result.update(meter_results(flicker, cmap, evaluator))
    if persist is not None:  # summed over ranks (under torchrun a temporal model's scenes are spread over them)
        result["persisted"] = sum(du.all_gather_object(persisted))
    result["samples_per_s"] = n_samples / max(time.perf_counter() - t0, 1e-9)
    return result
