"""Checking the per-sample polyline lists handed to the evaluators.

A sample's map is a list of polyline dicts (docs/conventions.md): ``{"pts": [P, 2] metres,
"label": int}``, predictions add ``"score": float``. Rules (the same for both protocols unless
said otherwise):

* NaN or infinite coordinates or scores, an unknown class id, or ``pts`` not of shape [P, 2]:
  :class:`EvaluationInputError` naming the sample and the polyline index.
* A prediction with fewer than two points is dropped and counted (both references drop it
  silently: MapTR ``mean_ap.py:82-83``, HDMapNet ``rasterize.py:183``).
* A GT polyline with fewer than two points: the vector protocol raises (the MapTR reference
  crashes on it, ``LineString`` needs two points); the raster protocol drops and counts it
  (the HDMapNet reference drops it, ``rasterize.py:183``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch

from ..config import UserError
from ..geometry import BEVGrid, as_grid

Samples = Sequence[Sequence[dict]]  # per sample, its polyline dicts
SAMPLE_COUNTERS = ("samples", "samples_without_predictions", "dropped_short_predictions")  # both protocols count


class EvaluationInputError(UserError, ValueError):
    """A prediction or GT polyline the evaluation cannot use; the message names the sample and index."""


@dataclass
class PolylineSet:
    """One sample's polylines of one role, checked. n polylines, each with P_i >= 2 points."""

    pts: list[np.ndarray] = field(default_factory=list)  # each [P_i, 2] float64, metres
    labels: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # [n]
    scores: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float64))  # [n] (predictions)
    num_short: int = 0  # polylines dropped because they had fewer than two points
    kept: list[int] = field(default_factory=list)  # [n] each polyline's index in the input list


def _detached(value):
    """A tensor as its values on the CPU: a model's outputs in a training loop carry ``requires_grad`` (NumPy's
    raw "Can't call numpy() on Tensor that requires grad"), and may live on the GPU."""
    if not (hasattr(value, "detach") and hasattr(value, "requires_grad")):
        return value
    value = value.detach().cpu()
    return value.float() if value.dtype == torch.bfloat16 else value  # a bf16 model's output: NumPy has no bfloat16


def check_grid(grid, who: str) -> BEVGrid:
    """``geometry.as_grid``: a ``BEVGrid``, a config's grid (a config or its ``grid`` section) taken as the grid it
    describes (it was a raw "'ExperimentConfig' object has no attribute 'xmin'" deep in the evaluation); anything
    else an ``EvaluationInputError``."""
    try:
        return as_grid(grid, who)
    except TypeError as e:
        raise EvaluationInputError(str(e)) from None


def sample_name(index: int, token: str | None) -> str:
    return f"sample '{token}'" if token is not None else f"sample #{index}"


def read_polylines(items: Sequence[dict], *, role: Literal["prediction", "GT"], num_classes: int, where: str,
                   short: Literal["drop", "error"]) -> PolylineSet:
    """Check one sample's polyline dicts and return them as arrays.

    Args:
        items: list of ``{"pts", "label"[, "score"]}`` dicts (or ``MapElement`` objects, taken as their
            ``as_polyline()``).
        role: "prediction" (needs a finite ``score``) or "GT".
        num_classes: K; labels must lie in [0, K).
        where: the sample's name for error messages, e.g. ``"sample 'abc'"``.
        short: what to do with a polyline of fewer than two points.
    """
    if items is None:
        items = []
    if isinstance(items, dict) or not isinstance(items, Sequence):
        raise EvaluationInputError(f"{where}: expected a list of {role} polyline dicts, got {type(items).__name__}")
    out = PolylineSet()
    labels, scores = [], []
    for i, item in enumerate(items):
        what = f"{where}, {role} polyline {i}"
        if hasattr(item, "as_polyline") and not isinstance(item, dict):  # a MapElement: what Mapper returns
            item = item.as_polyline()
        if not isinstance(item, dict) or "pts" not in item or "label" not in item:
            raise EvaluationInputError(f"{what}: expected a dict with keys 'pts' and 'label', got {item!r:.120}")
        try:
            pts = np.asarray(_detached(item["pts"]), dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise EvaluationInputError(f"{what}: 'pts' is not a numeric [P, 2] array ({e})") from None
        if pts.size == 0:
            pts = pts.reshape(0, 2)
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise EvaluationInputError(f"{what}: 'pts' must have shape [P, 2] (x, y in metres), got {pts.shape}")
        if not np.isfinite(pts).all():
            raise EvaluationInputError(f"{what}: 'pts' contains NaN or infinite coordinates; fix the polyline")
        label = _detached(item["label"])
        if getattr(label, "ndim", None) == 0 and hasattr(label, "item"):  # a 0-d tensor or array (a model's labels,
            label = label.item()  # iterated): its Python number, checked below as any label
        if isinstance(label, (bool, np.bool_)) or not isinstance(label, (int, np.integer)):
            raise EvaluationInputError(f"{what}: 'label' must be an integer class id, got {label!r}")
        if not 0 <= int(label) < num_classes:
            names = "0 divider, 1 ped_crossing, 2 boundary" if num_classes == 3 else "the evaluator's classes"
            raise EvaluationInputError(f"{what}: unknown class id {int(label)}; expected 0..{num_classes - 1} "
                                       f"({names})")
        score = 1.0
        if role == "prediction":
            if "score" not in item:
                raise EvaluationInputError(f"{what}: a prediction needs a 'score'")
            try:
                score = float(_detached(item["score"]))
            except (TypeError, ValueError):
                raise EvaluationInputError(f"{what}: 'score' must be a number, got {item['score']!r}") from None
            if not np.isfinite(score):
                raise EvaluationInputError(f"{what}: 'score' is {score}; scores must be finite")
        if len(pts) < 2:
            if short == "error":
                raise EvaluationInputError(f"{what}: has {len(pts)} point(s); a {role} polyline needs at least "
                                           "two (the vector protocol's reference cannot represent it). Remove it "
                                           "from the GT")
            out.num_short += 1
            continue
        out.pts.append(pts)
        out.kept.append(i)
        labels.append(int(label))
        scores.append(score)
    out.labels = np.asarray(labels, dtype=np.int64)
    out.scores = np.asarray(scores, dtype=np.float64)
    return out


def read_sample(pred: Sequence[dict], gt: Sequence[dict], where: str, num_classes: int,
                gt_short: Literal["drop", "error"], counters: dict) -> tuple[PolylineSet, PolylineSet]:
    """One sample's predictions and GT, checked (``read_polylines``; a short prediction is dropped, a short GT
    dropped or refused by ``gt_short``), counted into an AP accumulator's ``counters``."""
    P = read_polylines(pred, role="prediction", num_classes=num_classes, where=where, short="drop")
    G = read_polylines(gt, role="GT", num_classes=num_classes, where=where, short=gt_short)
    counters["dropped_short_predictions"] += P.num_short
    counters["samples_without_predictions"] += int(len(P.pts) == 0)
    if gt_short == "drop":
        counters["dropped_short_gt"] += G.num_short
    return P, G


def check_state(acc, state: dict) -> None:
    """An AP accumulator's ``merge_state`` takes a state of its own protocol and thresholds."""
    if state.get("protocol") != acc.name or list(state["thresholds"]) != acc.thresholds.tolist():
        raise EvaluationInputError(f"cannot merge a {state.get('protocol')} state at thresholds "
                                   f"{list(state.get('thresholds', []))} into a {acc.name} evaluator at "
                                   f"{acc.thresholds.tolist()}; merge states of the same protocol and thresholds")


def concat(parts: list[np.ndarray], empty: np.ndarray) -> np.ndarray:
    """``np.concatenate(parts)``, ``empty`` (of the right dtype and trailing shape) when there are none."""
    return np.concatenate(parts) if parts else empty


def gather_states(meter) -> None:
    """Under torch.distributed: every rank's ``meter.state_dict()`` all-gathered and merged in rank order into
    ``meter`` (reset first), so that every rank holds the whole dataset's state; a no-op without an initialised
    process group. The ``gather`` of ``Evaluator``, ``FlickerMeter`` and ``ConsistentAPMeter``."""
    if not (torch.distributed.is_available() and torch.distributed.is_initialized()):
        return
    states: list[dict | None] = [None] * torch.distributed.get_world_size()
    torch.distributed.all_gather_object(states, meter.state_dict())
    meter.reset()
    for state in states:
        meter.merge(state)
