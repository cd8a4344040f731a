"""Ground truth for InstaGraM, built from one sample's polylines (docs/conventions.md).

Three targets, all from the same list of polyline dicts ``{"pts": [P, 2] metres, "label", "closed"}``:

* **vertex cells** ``gt_vertex_cells`` [Hc, Wc] int64 in [0, S*S]: per S x S cell the position
  ``c = dy * S + dx`` of the one GT vertex kept in it, ``S*S`` (dustbin) for none;
* **distance transform** ``gt_distance`` [K, H, W] float32: per class, the Euclidean distance in BEV
  pixels to the nearest rasterised line pixel of that class, clipped to ``dt_clip``. Every polyline is
  drawn 1 px wide (8-connected, ``cv2.polylines``) at its rounded BEV pixels, so the distance is
  exactly 0 on the drawn pixels and > 0 elsewhere (``cv2.distanceTransform``, exact L2 mask);
* **vertex graph** ``gt_vertices_px`` [M, 2] and the per-vertex ``gt_vertex_labels``,
  ``gt_vertex_instance``, ``gt_vertex_order``, ``gt_vertex_next``, ``gt_vertex_prev`` [M] int64.

How graph vertices relate to cells (SuperPoint-style subsampling, one vertex per S x S region):

1. every polyline point becomes a candidate vertex at its BEV pixel (``grid.px_index`` of
   ``grid.m_to_px``, clamped into the grid): a vertex position is an integer pixel, so the vertex head
   can represent it exactly. A closed shape's repeated last point is dropped (the cycle closes it); a
   polyline given open whose last point is its first (a loop, >= 3 distinct points) is a closed shape.
2. **One vertex per cell, over the whole sample.** When a cell holds several candidates (consecutive
   points of one instance, a U-turn of one instance, or points of different instances) the kept one
   is the smallest by the key ``(not endpoint, label, instance, order)``: the endpoint of an open
   polyline first (so instance extents survive exactly), then the lower class, then the lower
   instance index, then the earlier point along the instance. Every other candidate is dropped.
3. The kept vertices of each instance, in their original order, form a chain: ``next``/``prev`` join
   consecutive kept vertices, so a dropped vertex is bridged by an edge from its kept predecessor to
   its kept successor (a merge of consecutive same-cell points is the special case). A closed shape
   with >= 3 kept vertices is a cycle (``next`` of its last vertex is its first); with 2 it is one
   open edge, with 1 an isolated vertex. Edges never join vertices of different instances.

So the non-dustbin cells of ``gt_vertex_cells`` and the graph vertices are in one-to-one
correspondence: decoding the cells (``cells_to_vertices_px``) returns exactly ``gt_vertices_px``
(as a set). Vertices are ordered by (instance, order); ``gt_vertex_instance`` is the index of the
polyline in the input list. An empty list gives valid empty targets (all dustbin, DT = dt_clip, M = 0).

Everything is vectorised NumPy / OpenCV (no Python loop over vertices); ~3 ms for 30 polylines on a
400 x 200 grid (``benchmarks/data_speed.py``).
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
import torch

from .geometry import BEVGrid

NO_VERTEX = -1  # sentinel in gt_vertex_next / gt_vertex_prev / gt_vertex_instance (padding)


def _as_numpy(x) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def check_polylines(polylines: Sequence[dict], num_classes: int | None = None, where: str = "targets") -> None:
    """A TypeError / ValueError naming the polyline unless ``polylines`` is a list of dicts with ``pts`` [P, 2] finite
    metres and an integer ``label`` in [0, ``num_classes``): a label of 5 was a raw IndexError, -1 drawn into the last
    class, NaN points a vertex at a grid corner, [P, 3] points reshaped into other points."""
    if isinstance(polylines, (dict, str, bytes)) or not isinstance(polylines, Sequence):
        raise TypeError(f"{where}: polylines must be a list of dicts {{'pts': [P, 2] metres, 'label': int, 'closed': "
                        f"bool}}, got {type(polylines).__name__}")
    for i, p in enumerate(polylines):
        if not isinstance(p, dict) or "pts" not in p or "label" not in p:
            raise TypeError(f"{where}: polyline {i} must be a dict with keys 'pts' and 'label', got {p!r:.80}")
        try:
            pts = _as_numpy(p["pts"]).astype(np.float64)
        except (TypeError, ValueError):
            raise TypeError(f"{where}: polyline {i}: 'pts' must be numbers [P, 2], got {p['pts']!r:.80}") from None
        if pts.size and (pts.ndim != 2 or pts.shape[1] != 2):
            raise ValueError(f"{where}: polyline {i}: 'pts' must be [P, 2] (x, y metres, ego frame), got shape "
                             f"{list(pts.shape)}")
        if not np.isfinite(pts).all():
            raise ValueError(f"{where}: polyline {i}: 'pts' holds NaN or infinite values")
        label = _as_numpy(p["label"])
        ok = label.ndim == 0 and label.dtype.kind in "iuf" and bool(np.isfinite(label)) and float(label) == int(label)
        if not ok or int(label) < 0 or (num_classes is not None and int(label) >= num_classes):
            classes = f"0..{num_classes - 1}" if num_classes is not None else ">= 0"
            raise ValueError(f"{where}: polyline {i}: 'label' must be a class index {classes}, got {p['label']!r:.40}")


def _polyline_pixels(polylines: Sequence[dict], grid: BEVGrid) -> tuple[np.ndarray, np.ndarray]:
    """Integer BEV pixels (u, v) of all points of all polylines, concatenated: [Q, 2] int64 clamped to
    the grid, and the number of points of each polyline [n]."""
    counts = np.array([len(p["pts"]) for p in polylines], dtype=np.int64)
    if counts.sum() == 0:
        return np.zeros((0, 2), dtype=np.int64), counts
    pts_m = np.concatenate([np.asarray(p["pts"], dtype=np.float64).reshape(-1, 2) for p in polylines])
    return np.clip(grid.px_index(grid.m_to_px(pts_m)), 0, [grid.W - 1, grid.H - 1]), counts


def _is_loop(pts) -> bool:
    """A polyline given open (``closed`` False) that ends where it starts, with >= 3 distinct points: a loop (a
    divider around an island, merged into one line). As an open chain its last point shared the first's cell and
    was dropped, and the targets decoded back lost the closing segment with no word."""
    p = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    return len(p) >= 4 and bool((p[0] == p[-1]).all()) and len(np.unique(p, axis=0)) >= 3


def _instance_index(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For concatenated points of instances with ``counts`` points: instance id and order, [Q] each."""
    inst = np.repeat(np.arange(len(counts)), counts)
    return inst, np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)


@torch.no_grad()
def vertex_graph(polylines: Sequence[dict], grid: BEVGrid) -> dict[str, torch.Tensor]:
    """The GT vertex graph (one vertex per S x S cell, see the module docstring).

    Returns M-long tensors: ``gt_vertices_px`` [M, 2] float32 (integer-valued u, v),
    ``gt_vertices_m`` [M, 2] float32 (the same vertices in metres), ``gt_vertex_labels``,
    ``gt_vertex_instance``, ``gt_vertex_order``, ``gt_vertex_next``, ``gt_vertex_prev`` [M] int64.
    """
    check_polylines(polylines, where="vertex_graph")
    S, Wc = grid.cell_size, grid.Wc
    uv, counts = _polyline_pixels(polylines, grid)  # [Q, 2] all candidates, in (instance, order) order; Q may be 0
    closed = np.array([bool(p.get("closed", False)) or _is_loop(p["pts"]) for p in polylines], dtype=bool)
    labels = np.array([int(p["label"]) for p in polylines], dtype=np.int64)
    inst, order = _instance_index(counts)
    # a closed shape repeats its first point at the end: drop it, the cycle closes the shape
    first_uv = uv[(np.cumsum(counts) - counts)[inst]]
    repeat = closed[inst] & (order == counts[inst] - 1) & (order > 0) & (uv == first_uv).all(-1)
    if repeat.any():
        uv = uv[~repeat]
        counts = counts - np.bincount(inst[repeat], minlength=len(counts))
        inst, order = _instance_index(counts)

    is_end = ~closed[inst] & ((order == 0) | (order == counts[inst] - 1))
    cell = (uv[:, 1] // S) * Wc + uv[:, 0] // S

    # one winner per cell: the smallest (not endpoint, label, instance, order); lexsort: last key primary
    rank = np.lexsort((order, inst, labels[inst], ~is_end, cell))
    first = np.diff(cell[rank], prepend=-1) != 0  # cells are >= 0
    keep = np.zeros(len(uv), dtype=bool)
    keep[rank[first]] = True

    uv, inst = uv[keep], inst[keep]  # still in (instance, order) order
    M = len(uv)
    idx = np.arange(M)
    new_start = np.diff(inst, prepend=-1) != 0
    group = np.cumsum(new_start) - 1  # instance groups of kept vertices
    group_start = idx[new_start]
    start = group_start[group]  # first / last kept vertex of each vertex's instance
    end = np.r_[group_start[1:] - 1, M - 1][group]
    nxt = np.where(idx < end, idx + 1, NO_VERTEX)
    prv = np.where(idx > start, idx - 1, NO_VERTEX)
    cyc = closed[inst] & (end - start + 1 >= 3)
    nxt = np.where(cyc & (idx == end), start, nxt)
    prv = np.where(cyc & (idx == start), end, prv)

    vertices_px = uv.astype(np.float32)
    return {
        "gt_vertices_px": torch.from_numpy(vertices_px),
        "gt_vertices_m": torch.from_numpy(grid.px_to_m(vertices_px).astype(np.float32)),
        "gt_vertex_labels": torch.from_numpy(labels[inst]),
        "gt_vertex_instance": torch.from_numpy(inst.astype(np.int64)),
        "gt_vertex_order": torch.from_numpy(idx - start),
        "gt_vertex_next": torch.from_numpy(nxt.astype(np.int64)),
        "gt_vertex_prev": torch.from_numpy(prv.astype(np.int64)),
    }


@torch.no_grad()
def vertex_cells(vertices_px: torch.Tensor, grid: BEVGrid) -> torch.Tensor:
    """Vertex-heatmap target [Hc, Wc] int64 in [0, S*S] from integer vertex pixels [M, 2] (u, v).

    At most one vertex per cell is expected (``vertex_graph`` guarantees it); if several are given,
    the last one written wins.
    """
    S = grid.cell_size
    cells = torch.full((grid.Hc * grid.Wc,), S * S, dtype=torch.int64)
    uv = vertices_px.round().long()
    cells[(uv[:, 1] // S) * grid.Wc + uv[:, 0] // S] = (uv[:, 1] % S) * S + uv[:, 0] % S
    return cells.view(grid.Hc, grid.Wc)


def cells_to_vertices_px(cells: torch.Tensor, cell_size: int) -> torch.Tensor:
    """Inverse of ``vertex_cells``: [Hc, Wc] labels -> integer pixels [M, 2] (u, v) of non-dustbin cells,
    in row-major cell order."""
    S = cell_size
    cv, cu = torch.nonzero(cells < S * S, as_tuple=True)
    c = cells[cv, cu]
    return torch.stack([cu * S + c % S, cv * S + c // S], -1).float()


@torch.no_grad()
def distance_transform(polylines: Sequence[dict], grid: BEVGrid, num_classes: int = 3, dt_clip: float = 10.0
                      ) -> torch.Tensor:
    """Per-class distance transform [K, H, W] float32 in [0, dt_clip] BEV pixels (see module docstring)."""
    check_polylines(polylines, num_classes, where="distance_transform")
    canvas = np.full((num_classes, grid.H, grid.W), 255, dtype=np.uint8)
    uv, counts = _polyline_pixels(polylines, grid)
    pieces = np.split(uv.astype(np.int32).reshape(-1, 1, 2), np.cumsum(counts)[:-1])
    per_class: list[list[np.ndarray]] = [[] for _ in range(num_classes)]
    for poly, piece in zip(polylines, pieces):
        per_class[int(poly["label"])].append(piece)
    out = np.empty(canvas.shape, dtype=np.float32)
    for k in range(num_classes):
        if per_class[k]:
            cv2.polylines(canvas[k], per_class[k], isClosed=False, color=0, thickness=1, lineType=cv2.LINE_8)
        # an image without a zero pixel gives huge distances: clipped to dt_clip below
        cv2.distanceTransform(canvas[k], cv2.DIST_L2, cv2.DIST_MASK_PRECISE, dst=out[k])
    np.minimum(out, dt_clip, out=out)
    return torch.from_numpy(out)


@torch.no_grad()
def build_targets(polylines: Sequence[dict], grid: BEVGrid, num_classes: int = 3, dt_clip: float = 10.0
                 ) -> dict[str, torch.Tensor]:
    """All targets of one sample: the vertex graph (``vertex_graph``), ``gt_vertex_mask`` [M] (all
    True), ``gt_vertex_cells`` [Hc, Wc] and ``gt_distance`` [K, H, W]. ``gt_vertices_m`` is not
    returned (use ``grid.px_to_m(gt_vertices_px)``) so that the keys are those of docs/conventions.md.
    """
    graph = vertex_graph(polylines, grid)
    graph.pop("gt_vertices_m")
    return {
        "gt_vertex_cells": vertex_cells(graph["gt_vertices_px"], grid),
        "gt_distance": distance_transform(polylines, grid, num_classes, dt_clip),
        **graph,
        "gt_vertex_mask": torch.ones(len(graph["gt_vertices_px"]), dtype=torch.bool),
    }


def graph_to_polylines(vertices_m, labels, next_idx, mask=None, min_vertices: int = 2) -> list[dict]:
    """Vertex graph -> polyline dicts (metres): follow ``next`` from every vertex without a
    predecessor; what is left are cycles, returned closed (first point repeated, ``closed=True``).

    vertices_m [M, 2], labels [M], next_idx [M] (``NO_VERTEX`` for none), mask [M] bool (padding
    False; a masked vertex is never visited). Chains are returned in the order of their smallest
    vertex index (for ``vertex_graph`` output: instance order); chains with fewer than
    ``min_vertices`` vertices are dropped. Each chain's label is that of its first vertex.
    """
    pts = _as_numpy(vertices_m).astype(np.float64)
    lab = _as_numpy(labels).astype(np.int64)
    nxt = _as_numpy(next_idx).astype(np.int64)
    M = len(nxt)
    valid = np.ones(M, dtype=bool) if mask is None else _as_numpy(mask).astype(bool)
    nxt = np.where(valid & (nxt >= 0), nxt, NO_VERTEX)
    nxt[nxt >= 0] = np.where(valid[nxt[nxt >= 0]], nxt[nxt >= 0], NO_VERTEX)
    has_prev = np.zeros(M, dtype=bool)
    has_prev[nxt[nxt >= 0]] = True
    visited = ~valid
    chains: list[tuple[int, list[int], bool]] = []
    starts = [i for i in range(M) if valid[i] and not has_prev[i]]
    for phase, candidates in ((0, starts), (1, range(M))):
        for s in candidates:
            if visited[s]:
                continue
            chain, i = [], s
            while i != NO_VERTEX and not visited[i]:
                visited[i] = True
                chain.append(i)
                i = nxt[i]
            chains.append((min(chain), chain, phase == 1 and i == s))
    out = []
    for _, chain, is_cycle in sorted(chains, key=lambda t: t[0]):
        if len(chain) < min_vertices:
            continue
        if is_cycle:
            chain = [*chain, chain[0]]
        out.append({"pts": pts[chain], "label": int(lab[chain[0]]), "closed": bool(is_cycle)})
    return out
