"""Vertex heatmap -> top-N vertices with scores and a padding mask, and per-vertex local inputs.

Shapes: B batch, S cell size, Hc x Wc cells, H x W = Hc*S x Wc*S BEV pixels, K classes,
N padded vertices, C channels. Inside a cell the position index is ``c = dy * S + dx``
(docs/conventions.md), ``c = S*S`` is the dustbin.

All batched: one vertex per cell at the cell's most likely position (the paper's "one distinctive
vertex per S x S cell, acting similar to NMS"), optionally thinned across cells (``nms_radius``: the
official code always runs SuperPoint's ``simple_nms`` with radius S/2 on the cell winners,
``model/base.py:501``), kept if its probability exceeds the threshold, the N most confident cells by
``torch.topk``, padded with ``mask = False``. The official code loops over the batch with
``nonzero`` and Python lists.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def depth_to_space(cell_values: torch.Tensor, cell_size: int) -> torch.Tensor:
    """[B, S*S, Hc, Wc] -> [B, Hc*S, Wc*S], channel ``c = dy * S + dx`` to pixel offset (dy, dx)."""
    B, _, Hc, Wc = cell_values.shape
    S = cell_size
    return cell_values.reshape(B, S, S, Hc, Wc).permute(0, 3, 1, 4, 2).reshape(B, Hc * S, Wc * S)


def vertex_heatmap(vertex_logits: torch.Tensor, cell_size: int) -> torch.Tensor:
    """Logits [B, S*S+1, Hc, Wc] -> heatmap [B, H, W]: softmax over S*S+1, dustbin dropped."""
    return depth_to_space(vertex_logits.softmax(dim=1)[:, :-1], cell_size)


def neighbour_suppression(best_prob: torch.Tensor, u: torch.Tensor, v: torch.Tensor, radius: float) -> torch.Tensor:
    """Cross-cell suppression of the cell winners: [B, Hc, Wc] probabilities and pixel coordinates
    -> [B, Hc, Wc] bool, True where a *stronger* winner of one of the 8 neighbouring cells lies
    within ``radius`` pixels (ties: the lower flat cell index wins).

    One vertex per cell is the paper's NMS; a line that runs along a cell border (or whose position
    the image side knows to +-1 cell) still fires in two cells side by side, and the weaker copy is
    a duplicate the graph head must send to the dustbin (assignment.py). Batched: 8 shifted copies.
    """
    B, Hc, Wc = best_prob.shape
    idx = torch.arange(Hc * Wc, device=best_prob.device).view(1, Hc, Wc).expand(B, Hc, Wc)
    pad = (1, 1, 1, 1)
    P = F.pad(best_prob, pad, value=-1.0)
    U = F.pad(u.float(), pad, value=1e9)
    V = F.pad(v.float(), pad, value=1e9)
    I = F.pad(idx.float(), pad, value=-1.0)
    suppressed = torch.zeros_like(best_prob, dtype=torch.bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy == 0 and dx == 0:
                continue
            sl = (slice(None), slice(1 + dy, 1 + dy + Hc), slice(1 + dx, 1 + dx + Wc))
            p, nu, nv, ni = P[sl], U[sl], V[sl], I[sl]
            stronger = (p > best_prob) | ((p == best_prob) & (ni < idx) & (ni >= 0))
            close = (nu - u) ** 2 + (nv - v) ** 2 <= radius**2
            suppressed |= stronger & close
    return suppressed


def _running_max(x: torch.Tensor, radius: int, dim: int) -> torch.Tensor:
    """The max over each element's window of 2r+1 along ``dim`` (centred, -inf beyond the ends): a
    square window's max is the row max of column maxes, and a window of k is the max of two
    overlapping windows of the largest power of two p <= k, built by doubling (log2 k + 1 elementwise
    maxima instead of max_pool2d's k^2 comparisons per pixel; the same values)."""
    k, n = 2 * radius + 1, x.shape[dim]
    pad = [0, 0] * (x.dim() - 1 - dim % x.dim()) + [radius, radius]
    y, p = F.pad(x, pad, value=float("-inf")), 1
    while 2 * p <= k:  # y[i] = max of the window of p starting at i
        y = torch.maximum(y.narrow(dim, 0, y.shape[dim] - p), y.narrow(dim, p, y.shape[dim] - p))
        p *= 2
    return torch.maximum(y.narrow(dim, 0, n), y.narrow(dim, k - p, n))


def superpoint_nms(scores: torch.Tensor, radius: int) -> torch.Tensor:
    """SuperPoint's non-maximum suppression (``simple_nms``, as the official InstaGraM code applies it
    to the map of cell winners with radius S/2): [B, H, W] scores -> [B, H, W] bool, True where kept.

    A pixel is kept if it is the maximum of its (2r+1) x (2r+1) window (ties: all kept); then, twice,
    the pixels within r (Chebyshev) of a kept one are set aside and a pixel that is the maximum of its
    window among what is left is kept too: a vertex suppressed only by one that was itself suppressed
    comes back. Padding never wins a window (max-pooling pads with -inf).
    """

    def window_max(x: torch.Tensor) -> torch.Tensor:  # = max_pool2d(x, 2r+1, stride 1, padding r), faster
        return _running_max(_running_max(x, radius, -1), radius, -2)

    keep = scores == window_max(scores)
    for _ in range(2):
        near_kept = window_max(keep.to(scores.dtype)) > 0
        rest = torch.where(near_kept, torch.zeros_like(scores), scores)
        keep = keep | ((rest == window_max(rest)) & ~near_kept)
    return keep


def _cell_pixels(cells: torch.Tensor, pos: torch.Tensor, Wc: int, S: int) -> tuple[torch.Tensor, torch.Tensor]:
    """BEV pixel (u, v) of position ``pos`` (``dy * S + dx``) inside flat cell ``cells`` (``row * Wc + col``)."""
    u = (cells % Wc) * S + pos % S
    v = torch.div(cells, Wc, rounding_mode="floor") * S + torch.div(pos, S, rounding_mode="floor")
    return u, v


def extract_vertices(vertex_logits: torch.Tensor, cell_size: int, num_vertices: int, threshold: float,
                     nms_radius: float = 0.0, nms: str = "cells") -> dict[str, torch.Tensor]:
    """Top-N vertices, one per cell, and with ``nms_radius`` > 0 pixels a suppression of the cell
    winners: ``nms="cells"`` drops a winner within that distance of a stronger winner of a
    neighbouring cell (``neighbour_suppression``); ``nms="superpoint"`` runs ``superpoint_nms`` with
    the integer radius on the map that holds each cell's winner (zeros elsewhere), the official code.

    vertex_logits [B, S*S+1, Hc, Wc] -> dict of
      ``vertices_px`` [B, N, 2] float (u, v) BEV pixels (0 on padding),
      ``scores``      [B, N] softmax probability of the vertex (0 on padding; differentiable),
      ``mask``        [B, N] bool, True for real vertices (sorted first, by decreasing score),
      ``cells``       [B, N] int64 flat cell index ``row * Wc + col`` (0 on padding).
    """
    B, _, Hc, Wc = vertex_logits.shape
    S = cell_size
    probs = vertex_logits.softmax(dim=1)[:, :-1].flatten(2)  # [B, S*S, Hc*Wc]
    best_prob, best_pos = probs.max(dim=1)  # [B, Hc*Wc]: the one vertex of each cell
    if nms_radius > 0:
        cu, cv = _cell_pixels(torch.arange(Hc * Wc, device=best_pos.device), best_pos, Wc, S)  # each cell's winner
        if nms == "superpoint":
            winners = torch.zeros_like(probs).scatter_(1, best_pos[:, None], best_prob[:, None])  # [B, S*S, Hc*Wc]
            kept = superpoint_nms(depth_to_space(winners.view(B, S * S, Hc, Wc), S), round(nms_radius))  # [B, H, W]
            gone = ~kept.flatten(1).gather(1, cv * (Wc * S) + cu)  # [B, Hc*Wc] at each cell's winner pixel
        else:
            grid = (B, Hc, Wc)
            gone = neighbour_suppression(best_prob.view(grid), cu.view(grid), cv.view(grid), nms_radius).flatten(1)
        best_prob = torch.where(gone, torch.zeros_like(best_prob), best_prob)  # below any threshold
    k = min(num_vertices, Hc * Wc)
    # Cells below the threshold sort after every real vertex and are masked out below.
    ranked = torch.where(best_prob > threshold, best_prob, best_prob - 2.0)
    _, cells = ranked.topk(k, dim=1)  # [B, k], by decreasing probability
    scores = best_prob.gather(1, cells)
    mask = scores > threshold
    vertices = torch.stack(_cell_pixels(cells, best_pos.gather(1, cells), Wc, S), -1).to(scores.dtype)
    zero = scores.new_zeros(())
    out = {
        "vertices_px": torch.where(mask[..., None], vertices, zero),
        "scores": torch.where(mask, scores, zero),
        "mask": mask,
        "cells": torch.where(mask, cells, torch.zeros_like(cells)),
    }
    if k < num_vertices:  # fewer cells than N: pad
        out = {name: torch.cat([t, t.new_zeros(B, num_vertices - k, *t.shape[2:])], 1) for name, t in out.items()}
    return out


def cell_patches(dense: torch.Tensor, cells: torch.Tensor, cell_size: int) -> torch.Tensor:
    """The S x S patch of every channel under each vertex's cell (Eq. 1's d_i).

    dense [B, K, H, W], cells [B, N] flat cell index -> [B, N, K*S*S] (class-major, then dy, dx).
    """
    B, K, H, W = dense.shape
    S = cell_size
    Hc, Wc = H // S, W // S
    patches = dense.reshape(B, K, Hc, S, Wc, S).permute(0, 2, 4, 1, 3, 5).reshape(B, Hc * Wc, K * S * S)
    return patches.gather(1, cells[..., None].expand(-1, -1, K * S * S))


def sample_at_vertices(features: torch.Tensor, vertices_norm: torch.Tensor) -> torch.Tensor:
    """Bilinear interpolation of a feature map covering the BEV grid at the vertices (the
    "visual descriptor" of PolyWorld, paper Fig. 7).

    features [B, C, h, w] (any resolution of the grid), vertices_norm [B, N, 2] in [-1, 1]
    (``BEVGrid.px_to_norm``) -> [B, N, C].
    """
    sampled = F.grid_sample(features.float(), vertices_norm[:, :, None].float(), align_corners=False)
    return sampled[..., 0].transpose(1, 2)


def cell_features(features: torch.Tensor, cells: torch.Tensor, Hc: int, Wc: int) -> torch.Tensor:
    """The feature of each vertex's cell (the official visual descriptor): the feature map is resized
    to the cell grid (bilinear, ``align_corners=True``, as the official code's ``F.interpolate``) and
    read at the vertex's cell.

    features [B, C, h, w] (any resolution of the grid), cells [B, N] flat cell index -> [B, N, C].
    """
    coarse = F.interpolate(features.float(), size=(Hc, Wc), mode="bilinear", align_corners=True)
    return coarse.flatten(2).gather(2, cells[:, None, :].expand(-1, coarse.shape[1], -1)).transpose(1, 2)
