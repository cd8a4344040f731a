"""The GNN oracle: the graph head alone, trained and evaluated on ground-truth vertices and distances.

It isolates the paper's association step (Eqs. 1-3 + Sinkhorn, the adjacency / class losses and the
post-processing): if the graph head cannot map clean GT inputs to near-perfect polylines, the head,
its targets or the decoding are wrong, whatever the image side does.

    samples = load_targets(cfg, "train")                      # GT targets only, no image decoding
    head = build_model(cfg).graph_head
    history = train_oracle(cfg, head, samples, steps=300)     # Adam on the graph-head terms
    result = evaluate_oracle(cfg, load_targets(cfg, "val"), head)       # vector-protocol metrics
    bound = evaluate_oracle(cfg, load_targets(cfg, "val"), None)        # the GT graph (upper bound)

Inputs the graph head sees, per batch (``oracle_vertices``):

* vertices: ``inference.gt_outputs`` turns ``gt_vertex_cells`` into (log) one-hot vertex logits and
  ``GraphHead.extract`` reads them exactly as it reads the vertex head's logits (top-N cells above
  ``conf_threshold``, sorted by score, padded, mask), so count, order and padding are the model's;
* distance: ``gt_distance``; BEV features: none (the ``pe+vd`` embedding cannot run here).

Padding never changes a real output (docs/conventions.md: masked attention, per-vertex LayerNorm,
Sinkhorn marginals over the real vertices), so the N padded slots are cut to the batch's largest
real count: the same real outputs, several times faster at N = 400.

Training uses ``losses.Criterion`` as is: the vertex and distance terms compare GT with GT (constant,
no gradient to the graph head), so the graph head is trained by exactly the adjacency and class
terms, with the configured weights, as inside the full model.

Evaluation post-processes with ``postprocess.postprocess_batch`` (``model.gnn.match_threshold``) and
scores against the split's GT polylines with ``evaluation.Evaluator.from_config``. ``graph_head=None``
evaluates ``inference.gt_outputs`` instead: the GT vertex graph decoded as is, the ceiling any graph
head can reach with these targets (below 1 where one-vertex-per-cell subsampling changes a shape).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence

import numpy as np
import torch
from tqdm import tqdm

from .config import ConfigError, ExperimentConfig
from .data.base import collate_fn
from .data.nuscenes import NuScenesMapDataset, open_nuscenes
from .engine import move_to
from .evaluation import Evaluator
from .geometry import BEVGrid
from .inference import gt_outputs
from .losses import Criterion, adjacency_correct
from .models import build_model
from .postprocess import decode_options, postprocess_batch
from .targets import build_targets

# diagnostics of losses.Criterion averaged over the evaluated batches
DIAGNOSTICS = ("loss_adjacency", "loss_class", "adjacency_accuracy", "adjacency_accuracy_all", "class_accuracy")
# (sx, sy): the map as is, mirrored front <-> back, left <-> right, and both (a 180 degree turn)
MIRRORS = ((1, 1), (-1, 1), (1, -1), (-1, -1))


def check_oracle_config(cfg: ExperimentConfig) -> None:
    """The oracle has no BEV features: the ``pe+vd`` embedding needs them."""
    if cfg.model.gnn.embedding == "pe+vd":
        raise ConfigError("config key 'model.gnn.embedding': the GNN oracle feeds GT vertices and GT distance "
                          "transforms and has no BEV features for 'pe+vd'; use pe+dt, pe or dt")


def mirror_polylines(polylines: Sequence[dict], sx: int, sy: int) -> list[dict]:
    """The map mirrored in the ego frame: ``sx = -1`` swaps front and back, ``sy = -1`` left and right."""
    return [{**p, "pts": np.asarray(p["pts"]) * np.array([sx, sy], dtype=np.float64)} for p in polylines]


def check_mirror_grid(grid: BEVGrid) -> None:
    """Mirroring keeps the BEV pixels and cells only on a grid centred on the ego vehicle."""
    if grid.xmin != -grid.xmax or grid.ymin != -grid.ymax:
        raise ConfigError(f"config keys 'grid.xbound' / 'grid.ybound': ({grid.xmin}, {grid.xmax}) / ({grid.ymin}, "
                          f"{grid.ymax}) are not centred on the ego vehicle, so the map cannot be mirrored; "
                          "train the oracle without mirroring (--no-mirror)")


@torch.no_grad()
def load_targets(cfg: ExperimentConfig, split: str, nusc=None, limit: int | None = None, mirror: bool = False,
                 progress: bool = False) -> list[dict]:
    """Per-sample GT of ``split`` without decoding any image: the dataset's local map
    (``NuScenesMapDataset.gt_polylines``) and ``targets.build_targets``.

    Returns a list of sample dicts (docs/conventions.md keys, no batch dimension): ``sample_token``,
    ``gt_polylines``, ``gt_vertex_cells`` [Hc, Wc], ``gt_distance`` [K, H, W], the vertex graph [M]
    keys and ``index`` (the dataset index). ``nusc`` shares an already loaded ``NuScenes``.
    ``mirror``: also the three mirror images of each map (``MIRRORS``, a 4x larger training set;
    the association task is symmetric), each built into its own targets; needs a centred grid.
    """
    grid, d = BEVGrid.from_config(cfg.grid), cfg.data
    if mirror:
        check_mirror_grid(grid)
    dataset = NuScenesMapDataset(cfg, split, nusc=nusc, augment=False)
    n = len(dataset) if limit is None else min(limit, len(dataset))
    out = []
    for i in tqdm(range(n), desc=f"GT targets ({split})", disable=not progress, dynamic_ncols=True):
        polylines = dataset.gt_polylines(i)
        for sx, sy in MIRRORS if mirror else MIRRORS[:1]:
            seen = mirror_polylines(polylines, sx, sy) if (sx, sy) != (1, 1) else polylines
            out.append({"index": i, "sample_token": dataset.sample_tokens[i], "gt_polylines": seen,
                        **build_targets(seen, grid, len(d.classes), d.dt_clip)})
    return out


def collate_targets(samples: Sequence[dict], device: torch.device | str = "cpu") -> dict:
    """``data.base.collate_fn`` over ``load_targets`` samples, tensors moved to ``device``;
    ``index`` becomes a list of dataset indices."""
    return move_to(collate_fn(list(samples)), torch.device(device))


@torch.no_grad()
def oracle_vertices(batch: dict, graph_head) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """The GT vertices as the model would extract them, and the GT outputs they come from.

    batch: collated targets (``gt_vertex_cells`` [B, Hc, Wc], ``gt_distance`` [B, K, H, W], the
    vertex graph [B, M]). Returns ``(vertices, gt)``: ``vertices`` = ``GraphHead.extract`` of the GT
    one-hot vertex logits (``vertices_px`` [B, n, 2], ``scores`` [B, n], ``mask`` [B, n], ``cells``
    [B, n]), cut from N to n = the batch's largest real count (at least 1); ``gt`` =
    ``inference.gt_outputs(batch)`` (its ``pred_vertex_logits`` and ``pred_distance`` are the inputs).
    """
    gt = gt_outputs(batch, graph_head.grid, batch["gt_distance"].shape[1])
    vertices = graph_head.extract(gt["pred_vertex_logits"])
    n = max(1, int(vertices["mask"].sum(1).max()))
    return {k: v[:, :n] for k, v in vertices.items()}, gt


def oracle_forward(graph_head, batch: dict) -> dict[str, torch.Tensor]:
    """The graph head on the batch's GT vertices and distances -> model outputs
    (docs/conventions.md keys; ``pred_vertex_logits`` / ``pred_heatmap`` / ``pred_distance`` are the
    GT's, N = the batch's largest real vertex count)."""
    vertices, gt = oracle_vertices(batch, graph_head)
    distance = gt["pred_distance"]
    no_features = distance.new_zeros(distance.shape[0], 0, 1, 1)  # unused by pe / dt / pe+dt
    graph = graph_head.associate(vertices, distance, no_features)
    return {
        "pred_vertex_logits": gt["pred_vertex_logits"],
        "pred_heatmap": gt["pred_heatmap"],
        "pred_distance": distance,
        "pred_vertices_px": vertices["vertices_px"],
        "pred_vertex_mask": vertices["mask"],
        "pred_vertex_scores": vertices["scores"],
        **graph,
    }


def epoch_batches(sizes: np.ndarray, batch_size: int, rng: np.random.Generator, pool: int = 8) -> list[np.ndarray]:
    """One epoch of mini-batches (sample indices) over samples with ``sizes`` [n] vertices: shuffled,
    then sorted by size within pools of ``pool`` batches, so that a batch pads little (the Sinkhorn's
    cost grows with the square of the batch's largest vertex count); batch order shuffled."""
    order = rng.permutation(len(sizes))
    out = []
    for start in range(0, len(order), pool * batch_size):
        part = order[start:start + pool * batch_size]
        part = part[np.argsort(sizes[part], kind="stable")]
        out += [part[i:i + batch_size] for i in range(0, len(part), batch_size)]
    return [out[i] for i in rng.permutation(len(out))]


def train_oracle(
    cfg: ExperimentConfig,
    graph_head,
    samples: Sequence[dict],
    *,
    steps: int = 300,
    minutes: float | None = None,
    batch_size: int = 4,
    lr: float = 1e-3,
    seed: int = 0,
    progress: bool = True,
    schedule: str = "cosine",
    log_every: int = 10,
    on_step: Callable[[int, dict], None] | None = None,
) -> dict:
    """Adam on ``graph_head`` with ``losses.Criterion(cfg.loss)`` over random mini-batches of ``samples``
    (``load_targets``; batches of similar vertex counts, ``epoch_batches``), at most ``steps`` steps and ``minutes``
    of wall time; gradient norm clipped to ``train.grad_clip``. The head is trained where its parameters are.
    ``schedule``: "constant" lr, or "cosine" from ``lr`` to 0 over the run, whose progress is the
    larger of the step and the wall-time fractions (so a run cut by ``minutes`` still anneals).
    ``on_step(step, losses)`` is called after every step (e.g. to evaluate or save along the way).

    Returns ``{"steps", "seconds", "history": [{"step", "seconds", "lr", "loss_adjacency", "loss_class",
    "adjacency_accuracy", "class_accuracy"}, ...]}`` (one entry every ``log_every`` steps and at the end).
    """
    check_oracle_config(cfg)
    if schedule not in ("constant", "cosine"):
        raise ConfigError(f"schedule must be 'constant' or 'cosine', got {schedule!r}")
    if not samples:
        raise ConfigError("the GNN oracle got no training samples; check data.train_split and the dataroot")
    device = next(graph_head.parameters()).device
    criterion = Criterion(cfg.loss, BEVGrid.from_config(cfg.grid))
    optimizer = torch.optim.Adam(graph_head.parameters(), lr=lr)
    rng = np.random.default_rng(seed)
    graph_head.train()
    history: list[dict] = []
    t0 = time.perf_counter()
    bar = tqdm(range(steps), desc="oracle train", disable=not progress, dynamic_ncols=True)

    def log(done: int, losses: dict) -> None:
        row = {"step": done, "seconds": time.perf_counter() - t0, "lr": optimizer.param_groups[0]["lr"],
               **{k: float(losses[k].detach()) for k in
                  ("loss_adjacency", "loss_class", "adjacency_accuracy", "class_accuracy")}}
        history.append(row)
        bar.set_postfix(adj=f"{row['loss_adjacency']:.3f}", acc=f"{row['adjacency_accuracy']:.3f}")

    done, losses = 0, {}
    sizes = np.array([len(s["gt_vertices_px"]) for s in samples])
    batches: list[np.ndarray] = []
    for step in bar:
        elapsed = time.perf_counter() - t0
        if minutes is not None and elapsed > 60 * minutes:
            break
        if schedule == "cosine":
            progress_frac = max(step / steps, elapsed / (60 * minutes) if minutes else 0.0)
            for group in optimizer.param_groups:
                group["lr"] = 0.5 * lr * (1 + math.cos(math.pi * min(progress_frac, 1.0)))
        if not batches:  # a new epoch
            batches = epoch_batches(sizes, batch_size, rng)
        batch = collate_targets([samples[i] for i in batches.pop()], device)
        losses = criterion(oracle_forward(graph_head, batch), batch)
        optimizer.zero_grad(set_to_none=True)
        losses["loss_total"].backward()
        if cfg.train.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(graph_head.parameters(), cfg.train.grad_clip)
        optimizer.step()
        done = step + 1
        if on_step is not None:
            on_step(done, losses)
        if done % log_every == 0:
            log(done, losses)
    if done and (not history or history[-1]["step"] != done):
        log(done, losses)  # the last step, also when the time budget ended the run
    bar.close()
    return {"steps": done, "seconds": time.perf_counter() - t0, "history": history}


@torch.no_grad()
def evaluate_oracle(
    cfg: ExperimentConfig,
    samples: Sequence[dict],
    graph_head=None,
    *,
    batch_size: int = 8,
    device: torch.device | str | None = None,
    progress: bool = False,
) -> dict:
    """Vector- (or ``eval.protocol``-) protocol metrics of the oracle on ``samples``.

    ``graph_head``: the trained head (``oracle_forward``), or None for the GT vertex graph decoded as
    is (``inference.gt_outputs``, the upper bound). Returns the ``Evaluator.compute()`` dict plus
    ``diagnostics``: the criterion's adjacency / class terms and accuracies (``DIAGNOSTICS``),
    averaged over batches, and per class, over all vertices that represent a GT vertex of that
    class: ``adjacency_accuracy_class`` (the criterion's per-vertex rule: the row's two best columns
    are exactly the GT successor and predecessor) and ``vertices_class`` (their number).
    One wrong row in a polyline of P vertices breaks it, so the instance AP needs these close to 1.
    """
    grid = BEVGrid.from_config(cfg.grid)
    if graph_head is not None:
        check_oracle_config(cfg)
        graph_head.eval()
        device = next(graph_head.parameters()).device
    device = torch.device(device or "cpu")
    criterion = Criterion(cfg.loss, grid)
    evaluator = Evaluator.from_config(cfg)
    sums: dict[str, float] = dict.fromkeys(DIAGNOSTICS, 0.0)
    num_classes = len(cfg.data.classes)
    per_class = torch.zeros(num_classes, 2, dtype=torch.long)  # [K, (correct, total)]
    starts = range(0, len(samples), batch_size)
    for s in tqdm(starts, desc="oracle eval", disable=not progress, dynamic_ncols=True):
        batch = collate_targets(samples[s:s + batch_size], device)
        outputs = gt_outputs(batch, grid, num_classes) if graph_head is None else oracle_forward(graph_head, batch)
        assignment = criterion.assign(outputs, batch)
        losses = criterion(outputs, batch, assignment)
        for k in DIAGNOSTICS:
            sums[k] += float(losses[k])
        correct = adjacency_correct(outputs["pred_log_assignment"], outputs["pred_vertex_mask"],
                                    assignment["target_next"], assignment["target_prev"])
        for k in range(num_classes):  # vertices that represent a GT vertex of class k
            of_class = assignment["pred_is_representative"] & (assignment["target_class"] == k)
            per_class[k] += torch.stack([(correct & of_class).sum(), of_class.sum()]).cpu()
        preds = postprocess_batch(outputs, grid, **decode_options(cfg.model.gnn, grid))
        evaluator.update(preds, batch["gt_polylines"], sample_ids=batch["index"], tokens=batch["sample_token"])
    metrics = evaluator.compute()
    metrics["diagnostics"] = {k: (v / len(starts) if starts else math.nan) for k, v in sums.items()}
    metrics["diagnostics"]["adjacency_accuracy_class"] = {
        c: (int(per_class[k, 0]) / int(per_class[k, 1]) if per_class[k, 1] else math.nan)
        for k, c in enumerate(cfg.data.classes)}
    metrics["diagnostics"]["vertices_class"] = {c: int(per_class[k, 1]) for k, c in enumerate(cfg.data.classes)}
    return metrics


def run_oracle(
    cfg: ExperimentConfig,
    *,
    steps: int = 300,
    minutes: float | None = None,
    batch_size: int = 16,
    lr: float = 1e-3,
    schedule: str = "cosine",
    mirror: bool = True,
    device: torch.device | str = "cpu",
    seed: int = 0,
    progress: bool = True,
) -> dict:
    """The whole oracle on ``cfg``'s dataset: GT targets of ``data.train_split`` (mirrored if
    ``mirror``) and ``data.val_split``, a fresh graph head (``models.build_model(cfg).graph_head``,
    seeded with ``seed``) trained by ``train_oracle``, then evaluated by ``evaluate_oracle`` next to
    the GT-graph upper bound.

    Returns ``{"oracle": metrics, "upper_bound": metrics, "train": train_oracle's dict,
    "num_train": samples (mirror images included), "num_val", "seconds": {"targets", "train", "eval"}}``.
    """
    check_oracle_config(cfg)
    t0 = time.perf_counter()
    nusc = open_nuscenes(cfg.data.dataroot, cfg.data.version)
    train_samples = load_targets(cfg, cfg.data.train_split, nusc=nusc, mirror=mirror, progress=progress)
    val_samples = load_targets(cfg, cfg.data.val_split, nusc=nusc, progress=progress)
    t1 = time.perf_counter()
    torch.manual_seed(seed)
    graph_head = build_model(cfg).graph_head.to(device)
    train = train_oracle(cfg, graph_head, train_samples, steps=steps, minutes=minutes, batch_size=batch_size, lr=lr,
                         seed=seed, schedule=schedule, progress=progress)
    t2 = time.perf_counter()
    metrics = evaluate_oracle(cfg, val_samples, graph_head, batch_size=batch_size, progress=progress)
    bound = evaluate_oracle(cfg, val_samples, None, batch_size=batch_size, device=device)
    return {"oracle": metrics, "upper_bound": bound, "train": train, "num_train": len(train_samples),
            "num_val": len(val_samples),
            "seconds": {"targets": t1 - t0, "train": t2 - t1, "eval": time.perf_counter() - t2}}
