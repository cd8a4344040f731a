"""Post-processing: the graph head's log assignment -> map instances (polylines / polygons in metres).

Shapes: B batch, N padded predicted vertices, K classes; row / column N of the assignment is the
dustbin.

1. Neighbours: an undirected graph of degree <= 2 (disjoint paths and cycles) over the real
   vertices. The training targets are bidirectional (assignment.py): the row of an interior vertex
   has two peaks (successor and predecessor, ~1/2 each), a polyline end one peak plus the dustbin,
   an isolated vertex only the dustbin. Two decoders (``decoder``, config ``model.gnn.decoder``):

   - ``"greedy"`` (default, ``greedy_neighbours``): each pair {i, j} is weighed by the geometric
     mean of its two directions, ``w_ij = (log P_ij + log P_ji) / 2``; pairs with ``w_ij >
     log(match_threshold)`` are taken strongest first, each kept unless one of its vertices already
     has two edges (the greedy maximum-weight 2-matching, a 1/2-approximation). A vertex whose row
     has three peaks (a duplicate vertex next to the line) keeps its two strongest *available*
     edges, and a closing edge of a polygon whose ends are both free is taken, where the mutual
     rule below drops an edge as soon as either end ranks it third. Options: ``same_class_edges``
     (both vertices must have the same argmax class: a crossing that touches a kerb stays apart
     from the boundary) and ``max_edge_px`` (no edge longer than that).
   - ``"classwise"``: the greedy rule once per class k, over the vertices whose class-k probability
     is at least ``class_min_prob``; graph k's paths and cycles are class-k instances. A vertex not
     ruled out for two classes can serve both: where a crossing meets a kerb, one BEV cell (one
     vertex) lies on both lines, and one class-agnostic graph of degree <= 2 cannot give it to both.
   - ``"mutual"`` (``vertex_neighbours``, the official decoder's rule, ``postprocess/vectorize.py:
     104-198`` at juyebshin/InstaGraM 2b978e4): vertex i's candidate neighbours are the (up to) two
     best real columns j of its row whose probability exceeds ``match_threshold`` (the official 0.1,
     strict ``>``, ``:133-137``) and whose argmax class is i's (``:139,142-146``: one graph per
     class); an edge {i, j} is kept only if it is mutual: j is a candidate of i and i a candidate of
     j. The instance's class is that shared class and its confidence the mean probability of it
     over the instance's vertices (``:152,161,195``), without the vertex scores.
   - ``"official"`` (``official_instances``): the official export's own walk over the same
     directed candidate edges, reproduced with its quirks, since the paper's numbers carry them:
     per class, starting from the lowest-index vertex with an out-edge, it follows out-edges
     (one-sided ones too) in both directions and records a vertex only when the next vertex of the
     walk points back to it, so the last vertex of every walk is never recorded (a 3-vertex path
     whose middle vertex has the lowest index gives nothing; benchmarks/README.md, "The paper configs
     against the official code"). ``mutual`` is the same rule without the walk's losses.

   ``greedy``'s graph is class-agnostic and the class is decided per instance (below), so one
   vertex with a flipped class does not split an instance. The demo model (a tiny graph head
   after ~3500 steps) gives true edges probabilities of only ~0.02-0.3 and its crossings touch
   the kerbs: it decodes ``classwise`` with ``match_threshold`` 0.02, ``class_min_prob`` 0.05,
   ``model.gnn.max_edge_m`` 2.5 and ``min_vertices`` 4 (configs/synthetic/demo.yaml;
   benchmarks/README.md, "Decoding": +0.08 to +0.19 mAP over the class-agnostic mutual rule of
   before issue 18 on five demo models).
2. Tracing (``trace_instances``): a linear walk over the neighbour pointers, O(N) per sample. Paths
   are walked from their lower-index end; what remains are cycles, walked from their lowest-index
   vertex in the direction of that vertex's first neighbour. Vertices without an edge (none above
   the threshold, or none accepted) are dropped; instances need ``min_vertices`` (default 2)
   vertices.
3. Instances: a path becomes a polyline (``closed=False``), a cycle a closed polygon whose first
   point is repeated at the end (``closed=True``, >= 4 points). Class and confidence:
   ``label = argmax_k mean_i p_ik`` (mean class probability over the instance's vertices, a soft
   vote; ``classwise``, ``mutual``, ``official``: the class of its graph) and
   ``score = mean_i p_i,label x mean_i s_i`` with ``s_i = pred_vertex_scores`` (vertex heatmap
   confidence); ``mutual`` and ``official``: ``score = mean_i p_i,label`` (the official confidence).
   Points are converted to metres in the
   ego frame by ``geometry.BEVGrid``. Output per sample: a list of ``{"pts", "label", "closed",
   "score"}`` (docs/conventions.md).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .geometry import BEVGrid

REQUIRED_OUTPUTS = ("pred_log_assignment", "pred_vertices_px", "pred_vertex_mask", "pred_vertex_scores",
                    "pred_class_log_probs")
DECODERS = ("classwise", "greedy", "mutual", "official")
# the decoders whose confidence is the official one (mean class probability, no vertex score)
OFFICIAL_CONFIDENCE = ("mutual", "official")
# the config keys read here (decode_options), at inference only: an ONNX export leaves them free
DECODE_KEYS = ("model.gnn.match_threshold", "model.gnn.decoder", "model.gnn.class_min_prob",
               "model.gnn.same_class_edges", "model.gnn.max_edge_m", "model.gnn.min_vertices")


def decode_options(gnn_cfg, grid: BEVGrid) -> dict:
    """The keyword arguments of ``postprocess_batch`` from ``model.gnn`` (config.py, ``DECODE_KEYS``):
    ``postprocess_batch(outputs, grid, **decode_options(cfg.model.gnn, grid))``; ``graph_options`` of
    them for ``neighbours``."""
    max_edge_m = gnn_cfg.max_edge_m
    return {"match_threshold": gnn_cfg.match_threshold, "decoder": gnn_cfg.decoder,
            "same_class_edges": gnn_cfg.same_class_edges, "class_min_prob": gnn_cfg.class_min_prob,
            "max_edge_px": None if max_edge_m is None else max_edge_m / grid.resolution,
            "min_vertices": gnn_cfg.min_vertices}


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
    vertices have no neighbours. ``class_log_probs`` [B, N, K] is needed for ``same_class_edges``
    (which the ``mutual`` decoder always sets: the official rule).
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


@torch.no_grad()
def greedy_neighbours(
    log_assignment: torch.Tensor,
    pred_vertex_mask: torch.Tensor,
    match_threshold: float = 0.1,
    class_log_probs: torch.Tensor | None = None,
    same_class_edges: bool = False,
    vertices_px: torch.Tensor | None = None,
    max_edge_px: float | None = None,
) -> torch.Tensor:
    """Greedy maximum-weight degree-<=2 edges: [B, N+1, N+1] log assignment, [B, N] mask -> [B, N, 2].

    Same output convention as ``vertex_neighbours`` (symmetric, -1 for none, a single neighbour in
    slot 0). Pair weight ``(log P_ij + log P_ji) / 2``; pairs above ``log(match_threshold)`` are
    accepted strongest first while both ends have fewer than two edges (ties: row-major pair order).
    ``same_class_edges`` needs ``class_log_probs`` [B, N, K]; ``max_edge_px`` needs ``vertices_px``
    [B, N, 2]. The weights are batched tensor code; the acceptance loop runs over the candidate
    pairs only (those above the threshold), in Python, per sample.
    """
    B, N = pred_vertex_mask.shape
    device = log_assignment.device
    out = torch.full((B, N, 2), -1, dtype=torch.long)
    if N < 2:
        return out.to(device)
    mask = pred_vertex_mask.bool()
    scores = log_assignment[:, :N, :N].float()
    w = 0.5 * (scores + scores.transpose(1, 2))  # [B, N, N], symmetric
    allowed = mask[:, :, None] & mask[:, None, :]
    allowed &= torch.ones(N, N, dtype=torch.bool, device=device).triu(1)  # each pair once, no self edge
    if same_class_edges:
        if class_log_probs is None:
            raise ValueError("same_class_edges=True needs class_log_probs")
        cls = class_log_probs.argmax(2)
        allowed &= cls[:, :, None] == cls[:, None, :]
    if max_edge_px is not None:
        if vertices_px is None:
            raise ValueError("max_edge_px needs vertices_px")
        v = vertices_px.float()
        allowed &= torch.cdist(v, v) <= max_edge_px
    allowed &= w > math.log(match_threshold)
    b_idx, i_idx, j_idx = allowed.nonzero(as_tuple=True)
    vals = w[b_idx, i_idx, j_idx]
    # strongest first within each sample: sort by weight, then (stably) by sample
    order = torch.sort(vals, descending=True, stable=True).indices
    order = order[torch.sort(b_idx[order], stable=True).indices]
    cand = torch.stack([b_idx[order], i_idx[order], j_idx[order]], 1).cpu().tolist()
    nbr = out.view(-1).tolist()  # flat [B * N * 2]
    deg = [0] * (B * N)
    for b, i, j in cand:
        u, v = b * N + i, b * N + j
        if deg[u] < 2 and deg[v] < 2:
            nbr[2 * u + deg[u]] = j
            nbr[2 * v + deg[v]] = i
            deg[u] += 1
            deg[v] += 1
    return torch.tensor(nbr, dtype=torch.long).view(B, N, 2).to(device)


@torch.no_grad()
def official_edges(log_assignment: torch.Tensor, pred_vertex_mask: torch.Tensor, class_log_probs: torch.Tensor,
                   match_threshold: float = 0.1) -> torch.Tensor:
    """The official decoder's directed candidate edges: [B, N+1, N+1], [B, N], [B, N, K] -> [B, N, N]
    bool, (i, j) True iff i and j are real, j is among the two largest real columns of row i (the
    diagonal included as a column, as ``vectorize.py:134`` ranks it; its probability is 0),
    ``P_ij > match_threshold`` and i and j share their argmax class."""
    B, N = pred_vertex_mask.shape
    mask = pred_vertex_mask.bool()
    if N < 2:
        return torch.zeros(B, N, N, dtype=torch.bool, device=mask.device)
    probs = log_assignment[:, :N, :N].float().exp()
    ranked = probs.masked_fill(~mask[:, None, :], -1.0)  # real columns only
    top2 = torch.zeros_like(mask[:, :, None].expand(B, N, N)).scatter_(2, ranked.topk(2, dim=2).indices, True)
    cls = class_log_probs.argmax(2)
    same = cls[:, :, None] == cls[:, None, :]
    return top2 & (probs > match_threshold) & same & mask[:, :, None] & mask[:, None, :]


def official_walks(out_edges: dict[int, list[int]]) -> list[list[int]]:
    """The official export's walk (``vectorize.py:154-196``) over one class's directed edges
    ``{source: [targets, ascending]}`` -> instances (vertex lists in the official order, >= 2).

    While edges remain: the source ``s`` of the first remaining edge (in (source, target) order)
    starts an instance; for each of its out-edges at that time, the first remaining edge
    ``(cur, nxt)`` is removed and walked: if ``cur`` is not yet taken and ``nxt`` has a remaining
    edge back to it, ``cur`` is taken; the walk stops when ``nxt == cur``; else ``cur <- nxt``, ``nxt``
    becomes its last out-target not yet taken (or stays), and ``cur``'s out-edges are removed. After
    each walk the taken list is reversed. A vertex is taken only when its successor confirms it, so
    the last vertex of a walk never is.
    """
    out = {a: list(bs) for a, bs in out_edges.items() if bs}
    sources = sorted(out)
    k = 0

    def first_source() -> int | None:
        nonlocal k
        while k < len(sources) and not out[sources[k]]:
            k += 1
        return sources[k] if k < len(sources) else None

    instances = []
    while (start := first_source()) is not None:
        taken, seen = [start], {start}
        for _ in range(len(out[start])):
            cur = first_source()
            nxt = out[cur].pop(0)
            while True:
                if cur not in seen and cur in out.get(nxt, ()):
                    taken.append(cur)
                    seen.add(cur)
                if cur == nxt:
                    break
                cur = nxt
                for b in out.get(cur, ()):
                    if b not in seen:
                        nxt = b
                if cur in out:
                    out[cur] = []
            taken.reverse()
        if len(taken) >= 2:
            instances.append(taken)
    return instances


@torch.no_grad()
def official_instances(outputs: dict, match_threshold: float = 0.1) -> list[list[tuple[list[int], int]]]:
    """The ``official`` decoder: per sample, ``[(vertex indices in the official order, class)]``,
    class by class (``official_edges`` then ``official_walks``)."""
    edges = official_edges(outputs["pred_log_assignment"], outputs["pred_vertex_mask"],
                           outputs["pred_class_log_probs"], match_threshold)
    cls = outputs["pred_class_log_probs"].argmax(2)
    K = outputs["pred_class_log_probs"].shape[2]
    b_idx, i_idx, j_idx = (t.cpu().tolist() for t in edges.nonzero(as_tuple=True))  # row-major: sorted
    cls_list = cls.cpu().tolist()
    per: list[list[dict[int, list[int]]]] = [[{} for _ in range(K)] for _ in range(edges.shape[0])]
    for b, i, j in zip(b_idx, i_idx, j_idx):
        per[b][cls_list[b][i]].setdefault(i, []).append(j)
    return [[(walk, k) for k in range(K) for walk in official_walks(per[b][k])] for b in range(len(per))]


def graph_options(decode: dict) -> dict:
    """``decode_options`` less the instance rule (``min_vertices``): the keyword arguments of ``neighbours``."""
    return {k: v for k, v in decode.items() if k != "min_vertices"}


def _repeat_per_class(t: torch.Tensor | None, K: int) -> torch.Tensor | None:
    """[B, ...] -> [B * K, ...]: each sample's tensor once per class (a view where possible)."""
    return None if t is None else t[:, None].expand(t.shape[0], K, *t.shape[1:]).reshape(-1, *t.shape[1:])


@torch.no_grad()
def neighbours(
    outputs: dict,
    match_threshold: float = 0.1,
    *,
    decoder: str = "greedy",
    same_class_edges: bool = False,
    max_edge_px: float | None = None,
    class_min_prob: float = 0.05,
) -> torch.Tensor:
    """The decoder's neighbour graphs of model outputs: [B, G, N, 2] (module docstring, step 1).

    G = 1 for ``greedy`` and ``mutual`` (one graph; mutual's edges join vertices of one argmax class
    only); G = K for ``classwise``: graph k holds the class-k instances, and for ``official``: graph k
    joins consecutive vertices of its class-k instances.
    """
    logA, mask = outputs["pred_log_assignment"], outputs["pred_vertex_mask"]
    class_log_probs, vertices = outputs.get("pred_class_log_probs"), outputs.get("pred_vertices_px")
    if decoder == "greedy":
        return greedy_neighbours(logA, mask, match_threshold, class_log_probs, same_class_edges, vertices,
                                 max_edge_px)[:, None]
    if decoder == "classwise":
        if class_log_probs is None:
            raise ValueError("the classwise decoder needs pred_class_log_probs")
        B, N = mask.shape
        K = class_log_probs.shape[2]
        # class k's vertices: those whose class-k probability is at least class_min_prob
        member = mask.bool()[:, None, :] & (class_log_probs.float().exp().transpose(1, 2) >= class_min_prob)
        nbr = greedy_neighbours(_repeat_per_class(logA, K), member.reshape(B * K, N), match_threshold, None, False,
                                _repeat_per_class(vertices, K), max_edge_px)
        return nbr.view(B, K, N, 2)
    if decoder == "mutual":
        if max_edge_px is not None:
            raise ValueError("max_edge_px is an option of the greedy and classwise decoders")
        return vertex_neighbours(logA, mask, match_threshold, class_log_probs, True)[:, None]
    if decoder == "official":
        if max_edge_px is not None:
            raise ValueError("max_edge_px is an option of the greedy and classwise decoders")
        B, N = mask.shape
        K = class_log_probs.shape[2]
        nbr = torch.full((B, K, N, 2), -1, dtype=torch.long)
        for b, instances in enumerate(official_instances(outputs, match_threshold)):
            for walk, k in instances:
                for i, j in zip(walk[:-1], walk[1:]):
                    nbr[b, k, i, int(nbr[b, k, i, 0] >= 0)] = j
                    nbr[b, k, j, int(nbr[b, k, j, 0] >= 0)] = i
        return nbr.to(logA.device)
    raise ValueError(f"decoder must be one of {DECODERS}, got {decoder!r}")


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
    *,
    decoder: str = "greedy",
    max_edge_px: float | None = None,
    class_min_prob: float = 0.05,
) -> list[list[dict]]:
    """Model outputs (docs/conventions.md keys) -> per sample, a list of polyline dicts in metres.

    Uses ``pred_log_assignment`` [B, N+1, N+1], ``pred_vertices_px`` [B, N, 2], ``pred_vertex_mask``
    [B, N], ``pred_vertex_scores`` [B, N], ``pred_class_log_probs`` [B, N, K]. See the module
    docstring for the rules; ``decode_options(cfg.model.gnn, grid)`` gives the config's options.
    """
    missing = [k for k in REQUIRED_OUTPUTS if k not in outputs]
    if missing:
        raise KeyError(f"post-processing needs {missing}, missing from the model output (docs/conventions.md)")
    if decoder == "official":
        if max_edge_px is not None:
            raise ValueError("max_edge_px is an option of the greedy and classwise decoders")
        K = outputs["pred_class_log_probs"].shape[2]
        walks = official_instances(outputs, match_threshold)
        # per sample, one "graph" per class holding its instances in the official order (open)
        traced = [[[(w, False) for w, k in sample if k == g and len(w) >= min_vertices] for g in range(K)]
                  for sample in walks]
    else:
        nbr = neighbours(outputs, match_threshold, decoder=decoder, same_class_edges=same_class_edges,
                         max_edge_px=max_edge_px, class_min_prob=class_min_prob)  # [B, G, N, 2]
        traced = [[trace_instances([r[0] for r in rows], [r[1] for r in rows], min_vertices) for rows in graphs]
                  for graphs in nbr.cpu().tolist()]
    # one transfer per tensor for the whole batch
    pts_m = grid.px_to_m(outputs["pred_vertices_px"].detach().float().cpu().numpy().astype(np.float64))  # [B, N, 2]
    class_probs = outputs["pred_class_log_probs"].detach().float().exp().cpu().numpy()  # [B, N, K]
    vertex_scores = outputs["pred_vertex_scores"].detach().float().cpu().numpy()  # [B, N]
    official_confidence = decoder in OFFICIAL_CONFIDENCE

    results: list[list[dict]] = []
    for b, graphs in enumerate(traced):
        sample = []
        for g, instances in enumerate(graphs):
            if not instances:
                continue
            order = np.fromiter((i for idx, _ in instances for i in idx), dtype=np.int64)
            lengths = np.array([len(idx) for idx, _ in instances])
            starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
            mean_probs = np.add.reduceat(class_probs[b][order], starts, axis=0) / lengths[:, None]  # [I, K]
            mean_score = np.add.reduceat(vertex_scores[b][order], starts) / lengths  # [I]
            # one class-agnostic graph: the soft vote decides; class graph g: its instances are class g
            labels = mean_probs.argmax(1) if len(graphs) == 1 else np.full(len(instances), g)
            conf = mean_probs[np.arange(len(labels)), labels]
            if not official_confidence:
                conf = conf * mean_score
            for k, (idx, closed) in enumerate(instances):
                pts = pts_m[b][idx + [idx[0]] if closed else idx]
                sample.append({"pts": pts, "label": int(labels[k]), "closed": closed, "score": float(conf[k])})
        results.append(sample)
    return results
