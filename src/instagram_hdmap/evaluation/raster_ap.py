"""The ``raster`` protocol: HDMapNet's instance AP as the InstaGraM paper used it, number for number
(EVAL_PROTOCOLS.md, Protocol B; reference: InstaGraM ``2b978e4`` ``data/rasterize.py``,
``evaluation/AP.py``, ``evaluate_json.py``; HDMapNet ``evaluation/chamfer_distance.py``).

1. Rasterise GT and predictions separately (:func:`rasterize_instances`): each polyline is
   clipped to the patch box with shapely, mapped to canvas pixels with the reference's
   arithmetic ``col = (x + trans_x) * (W / patch_w)`` -- derived from the BEV grid, but *not*
   ``BEVGrid.m_to_px``: it has no half-pixel shift and is truncated to int32 -- and drawn with
   ``cv2.polylines(thickness=5)`` into a per-class uint8 mask, instance ids 1, 2, ... running
   over all classes (class 0 first). Later lines overwrite earlier ones. (cv2's thickness-5 line
   covers 7 pixel rows when horizontal -- 1.05 m, not the 0.75 m often quoted; measured in the
   tests.)
2. Every instance id of a class mask becomes the point cloud of its pixels,
   ``(row * res, col * res)`` in float32, in row-major order.
3. Chamfer between pixel clouds with ``torch.cdist`` (float32), mean nearest distance each way,
   averaged, clipped at the threshold.
4. Per sample, class and threshold: greedy matching on the whole CD matrix (global minimum
   first, first in row-major order on ties), stop at ``CD >= thr``; matched = TP (strict
   ``CD < thr``). The PR curve runs over the predictions sorted by confidence -- ASCENDING in the
   reference (``AP.py:113``, a bug: ``rank_by="descending"`` fixes it) -- with a stable sort of
   [matched in matching order, unmatched in id order]; precision made non-increasing; AP = sum
   over r in float32 ``linspace(0.1, 1, 10)`` of the precision at the first point with
   recall >= r (0 if none), / 10, in float32.
5. Per class, the mean over the samples where the class has at least one GT or predicted
   instance (a sample with GT and no prediction counts 0; prediction and no GT counts 0). A class
   with neither anywhere is 0/0 = NaN, and so is the mean over the K x T matrix.

Reproduced quirks (documented in EVAL_PROTOCOLS.md): the confidence/instance misalignment --
one confidence is appended per clipped *line*, but ids run per drawn *part*, so a line cut in two
by the patch shifts every later instance's confidence, a line touching the patch in one point
shifts it the other way, ids past the list read the ``-1`` padding; overdraw; uint8 ids
saturating at 255 (later instances merge into id 255); truncation; one-point predictions and
lines that miss the patch vanish. ``fix_instance_ids=True`` fixes the first and the uint8
saturation (int32 masks, each instance keeps its own line's confidence). Where the reference
crashes, the rules here are: a clipped line that becomes a mix of lines and points
(GeometryCollection / MultiPoint) draws its line parts; more than 299 lines in a sample (the
reference's padding to 300 breaks) are evaluated like any other.

Per-sample APs are computed in float32 like the reference; their sums are accumulated in float64
(the reference sums in float32 on the GPU, so the final numbers agree to ~1e-7, not bit for bit).

Speed: the CD of a pair is computed only when a lower bound (bounding-box gap, mean pixel-to-box
distance) leaves it possibly below the largest threshold plus a margin (:func:`lb_margin`, 0.13 m
on the default grid) larger than any float32 rounding of the reference's ``cdist`` -- otherwise it
is clipped anyway.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal

import cv2
import numpy as np
import shapely
import torch

from ..geometry import BEVGrid, as_grid
from .chamfer import cloud_chamfer, mean_dist_to_box
from .inputs import SAMPLE_COUNTERS, EvaluationInputError, PolylineSet, Samples, check_state, read_sample, sample_name

THICKNESS = 5  # evaluate_json.py --thickness default
SAMPLED_RECALLS = torch.linspace(0.1, 1, 10).numpy()  # the reference's: float32 values, compared in float32
# torch intra-op threads during RasterAP.update(): the many small cdist calls run 40x slower with two OpenMP
# threads than with one on a loaded 2-core machine (measured).
TORCH_THREADS = 1
_LINESTRING = 1  # shapely type ids
_MULTI = (4, 5, 6, 7)  # MultiPoint, MultiLineString, MultiPolygon, GeometryCollection


def lb_margin(extent_sq: float) -> float:
    """Metres by which ``torch.cdist``'s float32 matrix-product path can undershoot one nearest
    distance, for pixel coordinates with ``|p|^2 <= extent_sq``: its ``|x|^2 + |y|^2 - 2 x.y`` is a
    4-term float32 dot product of magnitude <= 4 extent_sq, off by at most ~4 ulp of that; a
    square-root error of at most sqrt(16 u extent_sq), with 1.5x and 1 cm to spare."""
    return 1.5 * math.sqrt(16 * 2.0**-24 * extent_sq) + 0.01


class RasterFrame:
    """The reference's patch box and metre -> canvas transform, from a BEV grid.

    ``patch_box = (centre_x, centre_y, patch_h, patch_w)``, ``trans = -centre + size / 2``,
    ``scale = canvas / size`` (rasterize.py:53-63, dataset.py:26-33): for the default grid
    ``col = (x + 30.0) * (400 / 60.0)``, ``row = (y + 15.0) * (200 / 30.0)``.
    """

    def __init__(self, grid: BEVGrid) -> None:
        grid = as_grid(grid, "RasterFrame")
        patch_x, patch_y = (grid.xmin + grid.xmax) / 2.0, (grid.ymin + grid.ymax) / 2.0
        patch_w, patch_h = grid.xmax - grid.xmin, grid.ymax - grid.ymin
        self.H, self.W = grid.H, grid.W
        self.res = grid.resolution
        self.box = shapely.box(patch_x - patch_w / 2.0, patch_y - patch_h / 2.0,
                               patch_x + patch_w / 2.0, patch_y + patch_h / 2.0)
        self.trans = (-patch_x + patch_w / 2.0, -patch_y + patch_h / 2.0)
        self.scale = (self.W / patch_w, self.H / patch_h)

    def to_canvas(self, pts_m: np.ndarray) -> np.ndarray:
        """[P, 2] metres (x, y), already clipped -> [P, 2] int32 (col, row), truncated like the reference."""
        col = (pts_m[:, 0] + self.trans[0]) * self.scale[0]
        row = (pts_m[:, 1] + self.trans[1]) * self.scale[1]
        return np.stack([col, row], 1).astype(np.int32)


def rasterize_instances(pts: Sequence[np.ndarray], labels: np.ndarray, scores: np.ndarray | None, frame: RasterFrame,
                        num_classes: int = 3, thickness: int = THICKNESS,
                        fix_instance_ids: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The reference's ``rasterize_map``: per-class instance masks and the confidence list.

    Args:
        pts: n polylines [P_i, 2] metres, P_i >= 2; labels: [n] class ids; scores: [n] or None (GT).
    Returns:
        masks: [K, H, W] uint8 (int32 with ``fix_instance_ids``), 0 = background.
        confidence: [I] float32, the confidence of instance id i at index i (index 0 = -1); in the
            reference's misaligned way unless ``fix_instance_ids``.
    """
    labels = np.asarray(labels)  # a list: `labels == c` was False, nothing drawn, no word
    dtype = np.int32 if fix_instance_ids else np.uint8
    masks = np.zeros((num_classes, frame.H, frame.W), dtype=dtype)
    confidence = [-1.0]
    if len(pts) == 0:
        return masks, np.asarray(confidence, dtype=np.float32)
    scores = np.ones(len(pts)) if scores is None else scores
    lines = shapely.linestrings(np.concatenate(pts), indices=np.repeat(np.arange(len(pts)), [len(p) for p in pts]))
    clipped = shapely.intersection(lines, frame.box)  # rasterize.py:71
    types = shapely.get_type_id(clipped)
    empty = shapely.is_empty(clipped)
    idx = 1
    for c in range(num_classes):
        for i in np.flatnonzero(labels == c):
            if empty[i]:
                continue
            if not fix_instance_ids:
                confidence.append(float(scores[i]))  # one per line (rasterize.py:77)
            geom = clipped[i]
            parts = shapely.get_parts(geom) if types[i] in _MULTI else [geom]
            for part in parts:
                if shapely.get_type_id(part) != _LINESTRING:
                    continue  # a point: fewer than two coordinates, nothing drawn (rasterize.py:33)
                coords = frame.to_canvas(shapely.get_coordinates(part))
                cv2.polylines(masks[c], [coords], False, color=idx, thickness=thickness)
                if fix_instance_ids:
                    confidence.append(float(scores[i]))
                idx += 1
    return masks, np.asarray(confidence, dtype=np.float32)


def instance_clouds(mask: np.ndarray, res: float) -> tuple[np.ndarray, list[torch.Tensor], np.ndarray]:
    """Instance ids of one class mask and their pixel clouds (AP.py:5-19).

    Args: mask [H, W]. Returns: ids [I] ascending; clouds: I tensors [M_i, 2] float32
        ``(row * res, col * res)`` in row-major order; boxes [I, 4] (row_min, row_max, col_min, col_max).
    """
    rows, cols = np.nonzero(mask)
    vals = mask[rows, cols]
    order = np.argsort(vals, kind="stable")  # keeps row-major order inside an id
    ids, starts = np.unique(vals[order], return_index=True)
    ends = np.r_[starts[1:], len(order)]
    r32 = rows.astype(np.float32) * np.float32(res)
    c32 = cols.astype(np.float32) * np.float32(res)
    clouds, boxes = [], np.zeros((len(ids), 4))
    for k, (s, e) in enumerate(zip(starts, ends)):
        o = order[s:e]
        clouds.append(torch.from_numpy(np.stack([r32[o], c32[o]], 1)))
        boxes[k] = rows[o].min(), rows[o].max(), cols[o].min(), cols[o].max()
    return ids, clouds, boxes * res


def _cloud_to_box(cloud: np.ndarray, box: np.ndarray) -> float:
    """``chamfer.mean_dist_to_box`` of one pixel cloud [M, 2] and a box (r0, r1, c0, c1) in metres."""
    r0, r1, c0, c1 = box
    return float(mean_dist_to_box(cloud[None], np.array([[r0, c0]]), np.array([[r1, c1]]))[0])


def cd_matrix(pred: list[torch.Tensor], pred_box: np.ndarray, gt: list[torch.Tensor], gt_box: np.ndarray,
              max_thr: float, device: torch.device | None = None) -> np.ndarray:
    """[I_pred, I_gt] float32 raw CD; +inf where a lower bound proves CD >= max_thr (it is clipped anyway).

    Args: pred / gt: CPU pixel clouds [M, 2] float32 and their boxes [I, 4] in metres; device:
        where ``torch.cdist`` runs (default: CPU).
    """
    cd = np.full((len(pred), len(gt)), np.inf, dtype=np.float32)
    extent_sq = float(max(np.abs(pred_box).max(initial=0), np.abs(gt_box).max(initial=0))) ** 2 * 2
    limit = max_thr + lb_margin(extent_sq)
    pred64 = [p.numpy().astype(np.float64) for p in pred]
    gt64 = [g.numpy().astype(np.float64) for g in gt]
    moved: dict[tuple[str, int], torch.Tensor] = {}

    def on_device(kind: str, k: int, x: torch.Tensor) -> torch.Tensor:
        if device is None or device.type == "cpu":
            return x
        if (kind, k) not in moved:
            moved[kind, k] = x.to(device)
        return moved[kind, k]

    for i in range(len(pred)):
        gr = np.maximum(0.0, np.maximum(gt_box[:, 0] - pred_box[i, 1], pred_box[i, 0] - gt_box[:, 1]))
        gc = np.maximum(0.0, np.maximum(gt_box[:, 2] - pred_box[i, 3], pred_box[i, 2] - gt_box[:, 3]))
        for j in np.flatnonzero(np.hypot(gr, gc) < limit):
            lb = 0.5 * (_cloud_to_box(pred64[i], gt_box[j]) + _cloud_to_box(gt64[j], pred_box[i]))
            if lb < limit:
                cd[i, j] = cloud_chamfer(on_device("p", i, pred[i]), on_device("g", j, gt[j]))
    return cd


def greedy_match(cd: np.ndarray, thr: float) -> np.ndarray:
    """AP.py:40-55: repeatedly take the global minimum (first in row-major order) while < thr.

    Args: cd [I_pred, I_gt] float32. Returns: matched prediction rows in matching order.
    """
    thr32 = np.float32(thr)
    i, j = np.nonzero(cd < thr32)
    if i.size == 0:
        return np.zeros(0, dtype=np.int64)
    o = np.lexsort((i * cd.shape[1] + j, cd[i, j]))
    row_taken = np.zeros(cd.shape[0], bool)
    col_taken = np.zeros(cd.shape[1], bool)
    matched = []
    for r, c in zip(i[o], j[o]):
        if not row_taken[r] and not col_taken[c]:
            row_taken[r] = col_taken[c] = True
            matched.append(r)
    return np.asarray(matched, dtype=np.int64)


def sample_ap(confidence: np.ndarray, matched: np.ndarray, num_gt: int, recalls_at: np.ndarray,
              rank_by: Literal["ascending", "descending"] = "ascending") -> np.float32:
    """One sample-class-threshold AP (AP.py:108-164).

    Args:
        confidence: [I_pred] float32 confidence of each predicted instance (ascending id order).
        matched: prediction rows in matching order (all true positives).
        num_gt: GT instances.
        recalls_at: [10] float32 sampled recalls.
    """
    n = len(confidence)
    if n == 0:
        return np.float32(0.0)
    unmatched = np.setdiff1d(np.arange(n), matched)
    seq = np.concatenate([matched, unmatched])  # the matching list's order
    hit = np.zeros(n, dtype=bool)
    hit[: len(matched)] = True
    key = confidence[seq] if rank_by == "ascending" else -confidence[seq]
    o = np.argsort(key, kind="stable")  # Python's sorted() is stable
    tp = np.cumsum(hit[o]).astype(np.float32)
    count = np.arange(1, n + 1, dtype=np.float32)
    precision = tp / count
    with np.errstate(divide="ignore", invalid="ignore"):
        recall = tp / np.float32(num_gt)
    precision = np.maximum.accumulate(precision[::-1])[::-1]  # recall is already non-decreasing
    acc = np.float32(0.0)
    for r in recalls_at:
        k = np.flatnonzero(recall >= r)
        if k.size:
            acc = np.float32(acc + precision[k[0]])
    return np.float32(acc / np.float32(len(recalls_at)))


class RasterAP:
    """Streaming accumulator of the raster protocol: per class, the sum of per-sample AP vectors
    and the number of samples counted."""

    name = "raster"

    def __init__(self, thresholds: Sequence[float], grid: BEVGrid, num_classes: int = 3,
                 rank_by: Literal["ascending", "descending"] = "ascending", fix_instance_ids: bool = False,
                 device: str | torch.device = "cpu") -> None:
        if rank_by not in ("ascending", "descending"):
            raise EvaluationInputError(f"raster protocol: rank_by must be 'ascending' or 'descending', got {rank_by!r}")
        self.thresholds = np.asarray(thresholds, dtype=np.float64)
        self.frame = RasterFrame(grid)
        self.num_classes = num_classes
        self.rank_by = rank_by
        self.fix_instance_ids = fix_instance_ids
        try:
            self.device = torch.device(device)
        except RuntimeError:
            raise EvaluationInputError(f"raster protocol: unknown device {device!r}; use 'cpu' or 'cuda'") from None
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise EvaluationInputError("raster protocol: device 'cuda' requested but CUDA is not available")
        self.reset()

    def reset(self) -> None:
        K, T = self.num_classes, len(self.thresholds)
        self.ap_sum = np.zeros((K, T), dtype=np.float64)
        self.count = np.zeros(K, dtype=np.int64)
        self.num_gt = np.zeros(K, dtype=np.int64)  # GT instances after rasterisation
        self.num_pred = np.zeros(K, dtype=np.int64)  # predicted instances after rasterisation
        self.counters = dict.fromkeys((*SAMPLE_COUNTERS, "dropped_short_gt"), 0)
        self._next_id = 0

    def update(self, preds: Samples, gts: Samples, sample_ids: Sequence[int] | None = None,
               tokens: Sequence[str] | None = None) -> None:
        """Add B samples (lists of polyline dicts, metres, ego frame)."""
        B = len(preds)  # (Evaluator.update checks that gts has as many)
        previous = torch.get_num_threads()
        if self.device.type == "cpu":
            torch.set_num_threads(TORCH_THREADS)
        try:
            for b in range(B):
                sid = int(sample_ids[b]) if sample_ids is not None else self._next_id + b
                where = sample_name(sid, tokens[b] if tokens is not None else None)
                self._add_sample(*read_sample(preds[b], gts[b], where, self.num_classes, "drop", self.counters))
        finally:
            torch.set_num_threads(previous)
        if sample_ids is not None and B:
            self._next_id = max(self._next_id, int(max(sample_ids)) + 1)
        else:
            self._next_id += B
        self.counters["samples"] += B

    def _add_sample(self, P: PolylineSet, G: PolylineSet) -> None:
        """One sample's checked predictions and GT: its AP vector added to each class it has instances of."""
        K, max_thr = self.num_classes, float(self.thresholds.max())
        pred_masks, conf = rasterize_instances(P.pts, P.labels, P.scores, self.frame, K, THICKNESS,
                                               self.fix_instance_ids)
        gt_masks, _ = rasterize_instances(G.pts, G.labels, None, self.frame, K, THICKNESS, self.fix_instance_ids)
        for c in range(K):
            p_ids, p_clouds, p_box = instance_clouds(pred_masks[c], self.frame.res)
            g_ids, g_clouds, g_box = instance_clouds(gt_masks[c], self.frame.res)
            self.num_pred[c] += len(p_ids)
            self.num_gt[c] += len(g_ids)
            if len(p_ids) == 0 and len(g_ids) == 0:
                continue
            cd = cd_matrix(p_clouds, p_box, g_clouds, g_box, max_thr, self.device)
            # Instance id k reads confidence[k]; ids past the list read the -1 padding.
            p_conf = np.where(p_ids < len(conf), conf[np.minimum(p_ids, len(conf) - 1)], np.float32(-1.0))
            for t, thr in enumerate(self.thresholds):
                self.ap_sum[c, t] += sample_ap(p_conf.astype(np.float32), greedy_match(cd, thr), len(g_ids),
                                               SAMPLED_RECALLS, self.rank_by)
            self.count[c] += 1

    def state_dict(self) -> dict:
        return {"protocol": self.name, "thresholds": self.thresholds.tolist(), "ap_sum": self.ap_sum.copy(),
                "count": self.count.copy(), "num_gt": self.num_gt.copy(), "num_pred": self.num_pred.copy(),
                "counters": dict(self.counters)}

    def merge_state(self, state: dict) -> None:
        check_state(self, state)
        self.ap_sum += state["ap_sum"]
        self.count += state["count"]
        self.num_gt += state["num_gt"]
        self.num_pred += state["num_pred"]
        for k, v in state["counters"].items():
            self.counters[k] += v

    def compute(self) -> dict:
        """Returns {"AP": [K, T] (NaN for a class counted in no sample), "count": [K], "num_gt", "num_pred"}."""
        with np.errstate(divide="ignore", invalid="ignore"):
            ap = self.ap_sum / self.count[:, None]
        return {"AP": ap, "count": self.count.copy(), "num_gt": self.num_gt.copy(), "num_pred": self.num_pred.copy()}
