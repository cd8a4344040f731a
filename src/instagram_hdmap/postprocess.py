"""Post-processing: the graph head's log assignment -> map instances (polylines / polygons in metres).

Shapes: B batch, N padded predicted vertices, K classes; row / column N of the assignment is the
dustbin.

1. Neighbours (batched tensor code, ``vertex_neighbours``). The training targets are bidirectional
   (assignment.py): the row of an interior vertex has two peaks (successor and predecessor, ~1/2
   each), a polyline end one peak plus the dustbin, an isolated vertex only the dustbin. So, as
   in the official decoder, vertex i's candidate neighbours are the (up to) two best *real*
   columns j != i of its row whose probability exceeds ``match_threshold`` (default 0.1 =
   ``model.gnn.match_threshold``, the official value, strict ``>``). An edge {i, j} is kept only if
   it is mutual: j is a candidate of i and i a candidate of j. The result is an undirected graph
   of degree <= 2, i.e. disjoint paths and cycles. Optionally (``same_class_edges``, the official
   decoder's behaviour) an edge also needs both vertices to have the same argmax class; by default
   the graph is class-agnostic and the class is decided per instance (below), so one vertex with a
   flipped class does not split an instance.
2. Tracing (``trace_instances``): a linear walk over the neighbour pointers, O(N) per sample. Paths
   are walked from their lower-index end; what remains are cycles, walked from their lowest-index
   vertex in the direction of that vertex's first neighbour. Vertices without an edge (below the
   threshold, dustbin, or not mutual) are dropped; instances need ``min_vertices`` (default 2)
   vertices.
3. Instances: a path becomes a polyline (``closed=False``), a cycle a closed polygon whose first
   point is repeated at the end (``closed=True``, >= 4 points). Class and confidence:
   ``label = argmax_k mean_i p_ik`` (mean class probability over the instance's vertices, a soft
   vote) and ``score = mean_i p_i,label x mean_i s_i`` with ``s_i = pred_vertex_scores`` (vertex
   heatmap confidence). Points are converted to metres in the ego frame by ``geometry.BEVGrid``.
   Output per sample: a list of ``{"pts", "label", "closed", "score"}`` (docs/conventions.md).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .geometry import BEVGrid

REQUIRED_OUTPUTS = ("pred_log_assignment", "pred_vertices_px", "pred_vertex_mask", "pred_vertex_scores",
                    "pred_class_log_probs")


@torch.no_grad()
def vertex_neighbours(
    log_assignment: torch.Tensor,
    pred_vertex_mask: torch.Tensor,
    match_threshold: float = 0.1,
    class_log_probs: torch.Tensor | None = None,
    same_class_edges: bool = False,
) -> torch.Tensor:
    """Mutual best neighbours: [B, N+1, N+1] log assignment, [B, N] mask -> [B, N, 2] int64.

    Entry (b, i, k) is the k-th neighbour of vertex i (a real vertex index) or -1; a single
    neighbour is always in slot 0. Symmetric: j is listed for i iff i is listed for j. Padded
    vertices have no neighbours. ``class_log_probs`` [B, N, K] is needed for ``same_class_edges``.
    """
    B, N = pred_vertex_mask.shape
    device = log_assignment.device
    if N < 2:
        return torch.full((B, N, 2), -1, dtype=torch.long, device=device)
    mask = pred_vertex_mask.bool()
    scores = log_assignment[:, :N, :N].float()  # [B, N, N] real rows, real columns
    eye = torch.eye(N, dtype=torch.bool, device=device)
    scores = scores.masked_fill(~mask[:, None, :] | eye, -math.inf)
    values, nbr = scores.topk(2, dim=2)  # [B, N, 2]
    cand = (values > math.log(match_threshold)) & mask[:, :, None]
    if same_class_edges:
        if class_log_probs is None:
            raise ValueError("same_class_edges=True needs class_log_probs")
        cls = class_log_probs.argmax(2)  # [B, N]
        cand = cand & (cls.gather(1, nbr.flatten(1)).view(B, N, 2) == cls[:, :, None])
    nbr = torch.where(cand, nbr, torch.full_like(nbr, -1))
    # mutual: i must be among the candidates of each of its candidates
    back = nbr.clamp(min=0).flatten(1)  # [B, 2N]
    back_nbr = nbr.gather(1, back[..., None].expand(B, 2 * N, 2)).view(B, N, 2, 2)
    me = torch.arange(N, device=device)[None, :, None, None]
    mutual = cand & (back_nbr == me).any(3)
    nbr = torch.where(mutual, nbr, torch.full_like(nbr, -1))
    swap = (nbr[..., 0] < 0)[..., None]  # keep a single neighbour in slot 0
    return torch.where(swap, nbr.flip(2), nbr)


def trace_instances(nbr0: list[int], nbr1: list[int], min_vertices: int = 2) -> list[tuple[list[int], bool]]:
    """Walk a degree <= 2 symmetric neighbour graph: -> [(vertex indices in order, closed)].

    ``nbr0[i]``, ``nbr1[i]``: the neighbours of vertex i or -1 (a single one in ``nbr0``). Paths
    first (from their lower-index end), then cycles (from their lowest-index vertex). O(N).
    """
    n = len(nbr0)
    seen = [False] * n
    out: list[tuple[list[int], bool]] = []
    for s in range(n):  # paths: start at an end (exactly one neighbour)
        if seen[s] or nbr0[s] < 0 or nbr1[s] >= 0:
            continue
        path, prev, cur = [s], s, nbr0[s]
        seen[s] = True
        while cur >= 0:
            path.append(cur)
            seen[cur] = True
            a, b = nbr0[cur], nbr1[cur]
            prev, cur = cur, (b if a == prev else a)
        if len(path) >= min_vertices:
            out.append((path, False))
    for s in range(n):  # what is left with neighbours lies on a cycle
        if seen[s] or nbr0[s] < 0:
            continue
        cycle, prev, cur = [s], s, nbr0[s]
        seen[s] = True
        while cur != s:
            cycle.append(cur)
            seen[cur] = True
            a, b = nbr0[cur], nbr1[cur]
            prev, cur = cur, (b if a == prev else a)
        if len(cycle) >= max(min_vertices, 3):
            out.append((cycle, True))
    return out


@torch.no_grad()
def postprocess_batch(
    outputs: dict,
    grid: BEVGrid,
    match_threshold: float = 0.1,
    same_class_edges: bool = False,
    min_vertices: int = 2,
) -> list[list[dict]]:
    """Model outputs (docs/conventions.md keys) -> per sample, a list of polyline dicts in metres.

    Uses ``pred_log_assignment`` [B, N+1, N+1], ``pred_vertices_px`` [B, N, 2], ``pred_vertex_mask``
    [B, N], ``pred_vertex_scores`` [B, N], ``pred_class_log_probs`` [B, N, K]. See the module
    docstring for the rules.
    """
    missing = [k for k in REQUIRED_OUTPUTS if k not in outputs]
    if missing:
        raise KeyError(f"post-processing needs {missing}, missing from the model output (docs/conventions.md)")
    mask = outputs["pred_vertex_mask"]
    nbr = vertex_neighbours(outputs["pred_log_assignment"], mask, match_threshold,
                            outputs["pred_class_log_probs"], same_class_edges)
    # one transfer per tensor for the whole batch
    pts_m = grid.px_to_m(outputs["pred_vertices_px"].detach().float().cpu().numpy().astype(np.float64))  # [B, N, 2]
    class_probs = outputs["pred_class_log_probs"].detach().float().exp().cpu().numpy()  # [B, N, K]
    vertex_scores = outputs["pred_vertex_scores"].detach().float().cpu().numpy()  # [B, N]
    nbr_lists = nbr.cpu().tolist()

    results: list[list[dict]] = []
    for b, rows in enumerate(nbr_lists):
        instances = trace_instances([r[0] for r in rows], [r[1] for r in rows], min_vertices)
        if not instances:
            results.append([])
            continue
        order = np.fromiter((i for idx, _ in instances for i in idx), dtype=np.int64)
        lengths = np.array([len(idx) for idx, _ in instances])
        starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
        mean_probs = np.add.reduceat(class_probs[b][order], starts, axis=0) / lengths[:, None]  # [I, K]
        mean_score = np.add.reduceat(vertex_scores[b][order], starts) / lengths  # [I]
        labels = mean_probs.argmax(1)
        conf = mean_probs[np.arange(len(labels)), labels] * mean_score
        sample = []
        for k, (idx, closed) in enumerate(instances):
            pts = pts_m[b][idx + [idx[0]] if closed else idx]
            sample.append({"pts": pts, "label": int(labels[k]), "closed": closed, "score": float(conf[k])})
        results.append(sample)
    return results
