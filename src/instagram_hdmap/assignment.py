"""Ground truth for the graph head: predicted vertices + GT vertex graph -> adjacency and class targets.

Everything here runs under ``@torch.no_grad()`` and is batched tensor code (no Python loop over
vertices or instances); the criterion (losses.py) only compares its outputs with the model's.

Shapes: B batch, N padded predicted vertices, M padded GT vertices, K classes. Column / row ``N``
of the assignment is the dustbin ("no neighbour").

Matching (paper Eq. 6)
    Each real predicted vertex ``i`` is matched to its nearest real GT vertex ``sigma(i)`` if the
    distance is strictly below ``D0`` (``loss.match_dist``, metres; converted to BEV pixels with the
    grid resolution). Otherwise ``sigma(i) = UNMATCHED``. Ties go to the lowest GT index.
    ``match_space="patch"`` (config ``loss.match_space``) measures that distance, and picks the
    nearest GT vertex, as the official ``GraphLoss`` does (``loss.py:86-88,119,131,143-149`` at
    juyebshin/InstaGraM 2b978e4): a predicted vertex's pixel divided by ``(W - 1, H - 1)``, a GT
    point's metres shifted to the patch corner and divided by the patch extent ``(W, H) x res`` (for
    our pixel-centre GT vertices ``(u + 1/2) / W``), Euclidean distance there, strictly below
    ``|D0 / extent|`` = ``sqrt((D0 / 60)^2 + (D0 / 30)^2)`` on the 60 m x 30 m patch: an ellipse of
    semi-axes 3.35 m (along x) and 1.68 m (along y) at D0 = 1.5 m, and a shift of up to half a pixel
    between the two normalisations at the patch border.

Several predicted vertices on one GT vertex: one representative
    Among the predicted vertices with ``sigma(i) = g``, only the nearest one (ties: lowest index)
    *represents* ``g`` in the graph; the others keep ``sigma`` (so they get a class target: they
    do lie on the element) but have no edges: both their forward and backward targets are the
    dustbin. Reason: the decoded map should hold one vertex per GT vertex; chaining the duplicates
    along the instance (the official code's choice) makes their order arbitrary (two vertices on
    the same GT vertex have no defined order) and teaches zig-zags. With the representative rule
    the targets are a sub-graph of the GT graph, and post-processing drops the dustbin-ed
    duplicates as isolated vertices. (It is "nearest among those matched to g", not strict mutual
    nearest: if g's overall nearest prediction is matched to another GT vertex, g is still
    represented by its nearest *own* prediction.)

Edges, and GT vertices that no prediction represents: skip along the instance
    Forward target of a representative ``i`` with ``g = sigma(i)``: the representative of the first
    GT vertex after ``g`` along the instance (following ``gt_vertex_next``) that *has* a
    representative; the dustbin if the instance ends (open polyline) before one is found. Backward
    the same with ``gt_vertex_prev``. So a missed GT vertex in the middle of a line does not split
    the line in two (the official code skips too, by chaining matched vertices in instance order);
    the target polyline is the GT polyline with its undetected vertices removed. On a closed shape
    the walk goes around the cycle; if ``g`` is the only represented vertex of its cycle, both
    targets are the dustbin. ``skip_missed=False`` (config ``loss.skip_missed_vertices=false``)
    gives the strict rule: the dustbin when the direct successor is not represented. The skip is
    computed by pointer jumping, O(M log M) per sample.

    By construction the forward and backward targets are transposes of each other: ``i -> j``
    forward iff ``j -> i`` backward; every real row has exactly one forward and one backward target
    in ``[0, N]``, and every real predicted vertex is the forward target of at most one vertex.

Outputs (``assign(...)`` dict)
    ``pred_to_gt``            [B, N] int64   sigma(i), UNMATCHED (-1) if none / padding
    ``pred_to_gt_dist_m``     [B, N] float   distance to the nearest real GT vertex (inf if none)
    ``pred_is_representative``[B, N] bool    i represents sigma(i) in the graph
    ``gt_to_pred``            [B, M] int64   representative of each GT vertex, UNMATCHED if none
    ``target_next``           [B, N] int64   forward target column in [0, N] (N = dustbin);
                                             IGNORE_INDEX on padded predicted vertices
    ``target_prev``           [B, N] int64   backward target column, same convention
    ``target_class``          [B, N] int64   class of sigma(i); IGNORE_INDEX if unmatched / padding.
                                             ``class_targets="nearest"`` (config
                                             ``loss.class_targets``): the class of the nearest GT
                                             vertex for every real predicted vertex, at any distance
                                             (the official ``loss.py:157-158``); IGNORE_INDEX only
                                             on padding and in samples without GT
"""

from __future__ import annotations

import math

import torch

from .geometry import BEVGrid

UNMATCHED = -1  # a predicted vertex with no GT vertex within D0 / a GT vertex with no representative
IGNORE_INDEX = -100  # target value the losses skip (torch's nll_loss default ignore_index)

GT_GRAPH_KEYS = ("gt_vertices_px", "gt_vertex_mask", "gt_vertex_labels", "gt_vertex_next", "gt_vertex_prev")


def _next_represented(step: torch.Tensor, represented: torch.Tensor, skip_missed: bool) -> torch.Tensor:
    """For every GT vertex, the first vertex reached by following ``step`` that is represented.

    step:        [B, M+1] int64, successor in [0, M]; M is a sentinel meaning "none" (step[M] = M)
    represented: [B, M+1] bool, represented[:, M] = True (the sentinel is terminal)
    returns      [B, M+1] int64 in [0, M]: M if the walk leaves the instance, or (cycle) comes back
                 to the start vertex without meeting a represented vertex.
    """
    M = step.shape[1] - 1
    first = step  # the direct successor
    idx = torch.arange(M + 1, device=step.device).expand_as(step)
    if not skip_missed:
        ok = represented.gather(1, first)
        out = torch.where(ok, first, torch.full_like(first, M))
    else:
        # T(x) = x if x is terminal else T(step(x)); by pointer jumping on P(x) = x | step(x).
        P = torch.where(represented, idx, step)
        for _ in range(max(1, math.ceil(math.log2(M + 1))) + 1):
            P = P.gather(1, P)
        T = torch.where(represented.gather(1, P), P, torch.full_like(P, M))  # a cycle of misses -> none
        out = T.gather(1, first)
    return torch.where(out == idx, torch.full_like(out, M), out)  # only vertex of its cycle -> none


def _check_shapes(pred_vertices_px, pred_vertex_mask, gt_vertices_px, gt_vertex_mask, gt_vertex_labels, gt_vertex_next,
                  gt_vertex_prev) -> tuple[int, int, int]:
    """B, N and M of ``assign``'s inputs, whose shapes must agree."""
    B, N = pred_vertex_mask.shape
    if pred_vertices_px.shape != (B, N, 2):
        raise ValueError(f"pred_vertices_px must be [B, N, 2] = [{B}, {N}, 2], "
                         f"got {list(pred_vertices_px.shape)}")
    if gt_vertices_px.dim() != 3 or gt_vertices_px.shape[0] != B or gt_vertices_px.shape[2] != 2:
        raise ValueError(f"gt_vertices_px must be [B={B}, M, 2], got {list(gt_vertices_px.shape)}")
    M = gt_vertices_px.shape[1]
    for name, t in (("gt_vertex_mask", gt_vertex_mask), ("gt_vertex_labels", gt_vertex_labels),
                    ("gt_vertex_next", gt_vertex_next), ("gt_vertex_prev", gt_vertex_prev)):
        if t.shape != (B, M):
            raise ValueError(f"{name} must be [B, M] = [{B}, {M}], got {list(t.shape)}")
    return B, N, M


def _in_matching_space(pred_vertices_px: torch.Tensor, gt_vertices_px: torch.Tensor, grid: BEVGrid,
                       match_dist_m: float, match_space: str) -> tuple[torch.Tensor, torch.Tensor, float]:
    """The vertices in the space where Eq. 6 measures distances, and D0 there: pixels (``metres``), or the
    official GraphLoss's normalised coordinates (``patch``, module docstring)."""
    pred_xy, gt_xy = pred_vertices_px.float(), gt_vertices_px.float()
    if match_space == "patch":
        pred_xy = pred_xy / pred_xy.new_tensor([grid.W - 1, grid.H - 1])
        gt_xy = (gt_xy + 0.5) / gt_xy.new_tensor([grid.W, grid.H])
        limit = match_dist_m * math.hypot(1 / (grid.W * grid.resolution), 1 / (grid.H * grid.resolution))
    elif match_space == "metres":
        limit = match_dist_m / grid.resolution
    else:
        raise ValueError(f"match_space must be 'metres' or 'patch', got {match_space!r}")
    return pred_xy, gt_xy, limit


def _class_targets(gt_vertex_labels: torch.Tensor, nearest: torch.Tensor, nearest_d: torch.Tensor,
                   matched: torch.Tensor, class_targets: str) -> torch.Tensor:
    """Each predicted vertex's class target [B, N]: its nearest GT vertex's class where it matched one
    (``matched``), or wherever the sample has a GT vertex (``nearest``); IGNORE_INDEX elsewhere."""
    if class_targets not in ("matched", "nearest"):
        raise ValueError(f"class_targets must be 'matched' or 'nearest', got {class_targets!r}")
    M = gt_vertex_labels.shape[1]
    target = gt_vertex_labels.long().gather(1, nearest.clamp(max=max(M - 1, 0))) if M > 0 else nearest
    has_class = matched if class_targets == "matched" else torch.isfinite(nearest_d)
    return torch.where(has_class, target, torch.full_like(nearest, IGNORE_INDEX))


@torch.no_grad()
def assign(pred_vertices_px: torch.Tensor, pred_vertex_mask: torch.Tensor, gt_vertices_px: torch.Tensor,
           gt_vertex_mask: torch.Tensor, gt_vertex_labels: torch.Tensor, gt_vertex_next: torch.Tensor,
           gt_vertex_prev: torch.Tensor, grid: BEVGrid, match_dist_m: float, skip_missed: bool = True, *,
           match_space: str = "metres", class_targets: str = "matched") -> dict[str, torch.Tensor]:
    """Match predicted to GT vertices and derive the graph targets (module docstring has the rules).

    pred_vertices_px [B, N, 2] (u, v), pred_vertex_mask [B, N] bool;
    gt_vertices_px [B, M, 2], gt_vertex_mask [B, M] bool, gt_vertex_labels / _next / _prev [B, M]
    int64 (next/prev: index within the sample, -1 for none; docs/conventions.md).
    Returns the dict described in the module docstring.
    """
    B, N, M = _check_shapes(pred_vertices_px, pred_vertex_mask, gt_vertices_px, gt_vertex_mask, gt_vertex_labels,
                            gt_vertex_next, gt_vertex_prev)
    device = pred_vertices_px.device
    pred_mask = pred_vertex_mask.bool()
    gt_mask = gt_vertex_mask.bool()

    # --- Eq. 6: nearest real GT vertex within D0 ----------------------------------------------
    pred_xy, gt_xy, limit = _in_matching_space(pred_vertices_px, gt_vertices_px, grid, match_dist_m, match_space)
    if M > 0:
        dist = torch.cdist(pred_xy, gt_xy, compute_mode="donot_use_mm_for_euclid_dist")  # [B, N, M], exact
        dist = dist.masked_fill(~(pred_mask[:, :, None] & gt_mask[:, None, :]), math.inf)
        nearest_d, nearest = dist.min(dim=2)  # [B, N], in the matching space
        offset_px = pred_vertices_px.float() - gt_vertices_px.float().gather(1, nearest[..., None].expand(B, N, 2))
        nearest_px = torch.where(torch.isfinite(nearest_d), offset_px.norm(dim=2), nearest_d)
    else:
        nearest_d = nearest_px = pred_vertices_px.new_full((B, N), math.inf, dtype=torch.float32)
        nearest = torch.zeros(B, N, dtype=torch.long, device=device)
    matched = nearest_d < limit  # inf (padding / no GT) never matches
    pred_to_gt = torch.where(matched, nearest, torch.full_like(nearest, UNMATCHED))

    # --- one representative per GT vertex: nearest of its matches, ties -> lowest index ---------
    slot = torch.where(matched, nearest, torch.full_like(nearest, M))  # M = scratch slot
    best_d = nearest_d.new_full((B, M + 1), math.inf).scatter_reduce(
        1, slot, nearest_d, reduce="amin", include_self=True)
    is_best = matched & (nearest_d == best_d.gather(1, slot))
    pred_idx = torch.arange(N, device=device).expand(B, N)
    slot_best = torch.where(is_best, slot, torch.full_like(slot, M))
    rep = torch.full((B, M + 1), N, dtype=torch.long, device=device).scatter_reduce(
        1, slot_best, pred_idx, reduce="amin", include_self=True)  # [B, M+1], N = none
    rep[:, M] = N  # the sentinel GT vertex is represented by the dustbin
    gt_to_pred = torch.where(rep[:, :M] < N, rep[:, :M], torch.full_like(rep[:, :M], UNMATCHED))
    is_rep = matched & (rep.gather(1, slot) == pred_idx)

    # --- adjacency targets: represented successor / predecessor along the instance -------------
    represented = torch.cat([rep[:, :M] < N, torch.ones(B, 1, dtype=torch.bool, device=device)], 1)
    sentinel = torch.full((B, 1), M, dtype=torch.long, device=device)

    def targets(step: torch.Tensor) -> torch.Tensor:
        step = torch.where((step >= 0) & gt_mask, step.long(), torch.full_like(step, M, dtype=torch.long))
        nxt_gt = _next_represented(torch.cat([step, sentinel], 1), represented, skip_missed)  # [B, M+1]
        nxt_pred = rep.gather(1, nxt_gt)  # [B, M+1] in [0, N]; N = dustbin
        out = nxt_pred.gather(1, slot)  # [B, N]: non-representatives look up the scratch slot...
        out = torch.where(is_rep, out, torch.full_like(out, N))  # ...and go to the dustbin
        return torch.where(pred_mask, out, torch.full_like(out, IGNORE_INDEX))

    return {
        "pred_to_gt": pred_to_gt,
        "pred_to_gt_dist_m": nearest_px * grid.resolution,
        "pred_is_representative": is_rep,
        "gt_to_pred": gt_to_pred,
        "target_next": targets(gt_vertex_next),
        "target_prev": targets(gt_vertex_prev),
        "target_class": _class_targets(gt_vertex_labels, nearest, nearest_d, matched, class_targets),
    }


def assign_batch(outputs: dict, batch: dict, grid: BEVGrid, match_dist_m: float,
                 skip_missed: bool = True, **options) -> dict[str, torch.Tensor]:
    """``assign`` on a model output dict and a collated batch (docs/conventions.md keys); ``options``:
    ``match_space``, ``class_targets``."""
    missing = [k for k in GT_GRAPH_KEYS if k not in batch]
    missing += [k for k in ("pred_vertices_px", "pred_vertex_mask") if k not in outputs]
    if missing:
        raise KeyError(f"assignment needs the keys {missing}, missing from the batch / model output "
                       "(see docs/conventions.md)")
    return assign(outputs["pred_vertices_px"], outputs["pred_vertex_mask"], batch["gt_vertices_px"],
                  batch["gt_vertex_mask"], batch["gt_vertex_labels"], batch["gt_vertex_next"],
                  batch["gt_vertex_prev"], grid, match_dist_m, skip_missed, **options)


@torch.no_grad()
def adjacency_matrix(target_next: torch.Tensor, target_prev: torch.Tensor) -> torch.Tensor:
    """Dense forward target M over [N+1, N+1] (row/column N = dustbin), float 0/1.

    target_next, target_prev [B, N] (from ``assign``) -> [B, N+1, N+1].
    Row i < N (real): one-hot of i's forward target; the dustbin row N has a 1 in column j for every
    real j without a predecessor (backward target = dustbin). So every real row and every real
    column sums to one, and ``M.transpose(1, 2)`` is the backward target. Padded rows/columns and
    the [N, N] corner are zero.
    """
    B, N = target_next.shape
    out = target_next.new_zeros((B, N + 1, N + 1), dtype=torch.float32)
    real = target_next != IGNORE_INDEX
    rows = torch.arange(N, device=target_next.device).expand(B, N)
    b = torch.arange(B, device=target_next.device)[:, None].expand(B, N)
    out[b[real], rows[real], target_next[real]] = 1.0
    starts = real & (target_prev == N)
    out[b[starts], torch.full_like(rows[starts], N), rows[starts]] = 1.0
    return out


@torch.no_grad()
def target_log_assignment(target_next: torch.Tensor, target_prev: torch.Tensor, floor: float = 1e-6
                          ) -> torch.Tensor:
    """The bidirectional target distribution as a log assignment [B, N+1, N+1] (float32).

    Row i (real) = 1/2 one-hot(next) + 1/2 one-hot(prev) (so 1/2 + 1/2 for an interior vertex, 1/2
    neighbour + 1/2 dustbin at a polyline end, 1 on the dustbin for an isolated vertex), mixed with
    ``floor`` so the log is finite; padded rows and the dustbin row are uniform. This is what a
    perfect graph head outputs: tests and GT-derived "predictions" feed it to post-processing.
    """
    B, N = target_next.shape
    probs = target_next.new_zeros((B, N + 1, N + 1), dtype=torch.float32)
    real = target_next != IGNORE_INDEX
    for t in (target_next, target_prev):
        probs[:, :N].scatter_add_(2, t.clamp(min=0)[..., None],
                                  real[..., None].to(probs.dtype) * 0.5)
    probs[:, :N][~real] = 1.0 / (N + 1)
    probs[:, N] = 1.0 / (N + 1)
    return ((1 - floor) * probs + floor / (N + 1)).log()
