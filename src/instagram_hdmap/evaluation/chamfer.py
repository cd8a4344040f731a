"""Chamfer distances of the two AP protocols, batched.

Shapes: R pairs, P and Q points per polyline (100 in the vector protocol), M and N pixels per
raster instance.

* :func:`chamfer_pairs` -- the vector (MapTR) protocol: Euclidean distances between two point
  sets in float64 (NumPy), the mean of the nearest distances each way. Bit-for-bit the numbers of
  ``scipy.spatial.distance.cdist(a, b)`` followed by ``.min(-1).mean()`` / ``.min(-2).mean()``
  (the reference, ``tpfp_chamfer.py:53-59``), for R pairs at once.
* :func:`cloud_chamfer` -- the raster (HDMapNet) protocol: ``torch.cdist`` in float32 (its
  matrix-product path, with that path's rounding), mean nearest distance each way, averaged
  (``chamfer_distance.py:4-17``); the caller clips it at the threshold.
* :func:`mean_dist_to_box` -- the lower bound both protocols prune candidate pairs with.
"""

from __future__ import annotations

import numpy as np
import torch


def chamfer_pairs(a: np.ndarray, b: np.ndarray, chunk: int = 32) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Chamfer terms of R polyline pairs, in NumPy (single-threaded: no thread contention on a
    shared machine).

    Args:
        a: [R, P, 2] float64 points of the first set of each pair (predictions).
        b: [R, Q, 2] float64 points of the second set (ground truth).
        chunk: pairs per step; small chunks keep the [chunk, P, Q] block in cache.

    Returns:
        d_ab: [R] mean over a's points of the distance to the nearest point of b.
        d_ba: [R] mean over b's points of the distance to the nearest point of a.
        near_a: [R, P] the nearest distance of every point of a (used to pick witness points).
    """
    R, P = a.shape[:2]
    Q = b.shape[1]
    sq_a = np.empty((R, P), dtype=np.float64)
    sq_b = np.empty((R, Q), dtype=np.float64)
    ax, ay = np.ascontiguousarray(a[..., 0], dtype=np.float64), np.ascontiguousarray(a[..., 1], dtype=np.float64)
    bx, by = np.ascontiguousarray(b[..., 0], dtype=np.float64), np.ascontiguousarray(b[..., 1], dtype=np.float64)
    for s in range(0, R, chunk):
        e = s + chunk
        # dx*dx + dy*dy, as scipy's cdist sums it (no |a|^2 + |b|^2 - 2ab rounding).
        sq = ax[s:e, :, None] - bx[s:e, None, :]  # [C, P, Q]
        np.multiply(sq, sq, out=sq)
        dy = ay[s:e, :, None] - by[s:e, None, :]
        np.multiply(dy, dy, out=dy)
        sq += dy
        sq_a[s:e] = sq.min(2)
        sq_b[s:e] = sq.min(1)
    # sqrt is correctly rounded and monotone: sqrt(min(sq)) == min(sqrt(sq)) exactly.
    near_a, near_b = np.sqrt(sq_a), np.sqrt(sq_b)
    # Row means of C-contiguous [R, P] arrays use NumPy's pairwise sum per row, the same summation
    # as the reference's 1-D ``.mean()``: the values are identical, not merely close.
    return near_a.mean(1), near_b.mean(1), near_a


def cloud_chamfer(src: torch.Tensor, dst: torch.Tensor) -> float:
    """Raw (unclipped) raster-protocol Chamfer distance between two pixel clouds.

    Args:
        src: [M, 2] float32 (row * res, col * res) of the predicted instance.
        dst: [N, 2] float32 of the GT instance.

    Returns:
        ``(mean_i min_j |s_i - d_j| + mean_j min_i |s_i - d_j|) / 2`` in float32 arithmetic, as
        ``torch.cdist`` computes it for the reference (``[1, M, 2]`` batches, default compute mode).
    """
    dist = torch.cdist(src[None].float(), dst[None].float())
    d1 = dist.amin(2).mean(-1)  # the same values as .min(2).values, without the indices
    d2 = dist.amin(1).mean(-1)
    return float(((d1 + d2) / 2).item())


def mean_dist_to_box(pts: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """[R, P, 2] points, [R, 2] box corners (low, high) -> [R] mean distance of each set's points to
    its box: a lower bound of the Chamfer term from those points to any set inside the box (both
    protocols prune pairs with it)."""
    d = np.maximum(0.0, np.maximum(lo[:, None] - pts, pts - hi[:, None]))
    return np.sqrt(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1]).mean(1)
