"""Post-processing: the graph head's log assignment -> map instances (polylines / polygons in metres).

Shapes: B batch, N padded predicted vertices, K classes; row / column N of the assignment is the
dustbin.

1. Neighbours: an undirected graph of degree <= 2 (disjoint paths and cycles) over the real
   vertices. The training targets are bidirectional (assignment.py): the row of an interior vertex
   has two peaks (successor and predecessor, ~1/2 each), a polyline end one peak plus the dustbin,
   an isolated vertex only the dustbin. Four decoders (``decoder``, config ``model.gnn.decoder``):

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
   benchmarks/README.md, "Decoding": +0.08 to +0.19 mAP over the class-agnostic mutual rule on
   five demo models).
2. Tracing (``trace_graphs``, every graph of the batch at once): paths are walked from their
   lower-index end; cycles from their lowest-index vertex in the direction of that vertex's first
   neighbour. Vertices without an edge (none above the threshold, or none accepted) are dropped;
   instances need ``min_vertices`` (default 2) vertices.
3. Instances: a path becomes a polyline (``closed=False``), a cycle a closed polygon whose first
   point is repeated at the end (``closed=True``, >= 4 points). Class and confidence:
   ``label = argmax_k mean_i p_ik`` (mean class probability over the instance's vertices, a soft
   vote; ``classwise``, ``mutual``, ``official``: the class of its graph) and
   ``score = mean_i p_i,label x mean_i s_i`` with ``s_i = pred_vertex_scores`` (vertex heatmap
   confidence); ``mutual`` and ``official``: ``score = mean_i p_i,label`` (the official confidence).
   Points are converted to metres in the ego frame by ``geometry.BEVGrid``. Output per sample: a
   list of ``{"pts", "label", "closed", "score"}`` (docs/conventions.md).

Speed: no Python loop over pairs, vertices or graphs. The greedy rule reads the sparse candidate
pairs only (``candidate_pairs``) and is evaluated in vectorised rounds (``greedy_two_matching``);
the walks are ranked by pointer jumping; only the output dicts are built one by one.
``benchmarks/graph_speed.py`` times it (benchmarks/README.md, "Decoding speed"); tests/test_postprocess.py
checks it against the sequential loops.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .errors import is_real
from .geometry import BEVGrid, as_grid

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
    if not hasattr(gnn_cfg, "max_edge_m") and hasattr(getattr(gnn_cfg, "model", None), "gnn"):
        gnn_cfg = gnn_cfg.model.gnn  # a whole config: a raw AttributeError 'max_edge_m'
    grid = as_grid(grid, "decode_options")
    max_edge_m = gnn_cfg.max_edge_m
    return {"match_threshold": gnn_cfg.match_threshold, "decoder": gnn_cfg.decoder,
            "same_class_edges": gnn_cfg.same_class_edges, "class_min_prob": gnn_cfg.class_min_prob,
            "max_edge_px": None if max_edge_m is None else max_edge_m / grid.resolution,
            "min_vertices": gnn_cfg.min_vertices}


def _argmax_classes(class_log_probs: torch.Tensor | None) -> torch.Tensor:
    """[B, N, K] -> each vertex's argmax class [B, N], for ``same_class_edges``."""
    if class_log_probs is None:
        raise ValueError("same_class_edges=True needs class_log_probs")
    return class_log_probs.argmax(2)


@torch.no_grad()
def vertex_neighbours(log_assignment: torch.Tensor, pred_vertex_mask: torch.Tensor, match_threshold: float = 0.1,
                      class_log_probs: torch.Tensor | None = None, same_class_edges: bool = False) -> torch.Tensor:
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
        cls = _argmax_classes(class_log_probs)  # [B, N]
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


def candidate_pairs(log_assignment: torch.Tensor, pred_vertex_mask: torch.Tensor, match_threshold: float = 0.1,
                    class_log_probs: torch.Tensor | None = None, same_class_edges: bool = False,
                    vertices_px: torch.Tensor | None = None, max_edge_px: float | None = None,
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The pairs the greedy rule may take: ``(b, i, j, w)`` with i < j both real, in row-major order,
    and their weight ``w = (log P_ij + log P_ji) / 2`` above ``log(match_threshold)`` (float32, as
    the dense ``0.5 * (S + S^T)``), within ``max_edge_px`` (exact Euclidean distance of
    ``vertices_px``) and, with ``same_class_edges``, of one argmax class.

    Sparse: a pair's weight exceeds the threshold only if one of its directions does, and a log
    assignment row has at most 1 / match_threshold such entries, so one comparison over the dense
    [B, N, N] block finds every candidate; nothing else is computed densely.
    """
    N = pred_vertex_mask.shape[1]
    scores = log_assignment[:, :N, :N].float()
    log_t = math.log(match_threshold)
    flat = np.flatnonzero((scores > log_t).cpu().numpy())
    b, rest = np.divmod(flat, N * N)
    i, j = np.divmod(rest, N)
    key = np.unique((b * N + np.minimum(i, j)) * N + np.maximum(i, j))  # each pair once, row-major
    b, rest = np.divmod(key, N * N)
    i, j = np.divmod(rest, N)
    b, i, j = b[i != j], i[i != j], j[i != j]
    bt, it, jt = (torch.from_numpy(a).to(scores.device) for a in (b, i, j))
    w = 0.5 * (scores[bt, it, jt] + scores[bt, jt, it])
    mask = pred_vertex_mask.bool()
    ok = (w > log_t) & mask[bt, it] & mask[bt, jt]
    if same_class_edges:
        cls = _argmax_classes(class_log_probs)
        ok &= cls[bt, it] == cls[bt, jt]
    ok = ok.cpu().numpy()
    if max_edge_px is not None:
        if vertices_px is None:
            raise ValueError("max_edge_px needs vertices_px")
        v = vertices_px.detach().float().cpu().numpy().astype(np.float64)
        d = v[b, i] - v[b, j]
        ok &= np.hypot(d[:, 0], d[:, 1]) <= max_edge_px
    return b[ok], i[ok], j[ok], w.cpu().numpy()[ok]


def greedy_two_matching(graph: np.ndarray, i: np.ndarray, j: np.ndarray, w: np.ndarray, num_graphs: int,
                        N: int) -> np.ndarray:
    """The greedy degree-<=2 rule on candidate pairs ``(graph, i, j)`` with weights ``w``: in each graph,
    pairs strongest first (ties: row-major), each kept unless an end already has two edges.

    Returns the neighbour table [num_graphs, N, 2] (-1 for none; a vertex's first kept edge in slot
    0). Vectorised without changing the result: in one round, a pair is kept when it is among the
    first (2 - edges kept so far) undecided pairs at both of its ends (in the sequential rule, fewer
    than two earlier pairs can then be kept at either end), and the undecided pairs of a vertex that
    has two edges are dropped (both its kept edges come before them). Each round keeps at least the
    strongest undecided pair; the rule's graphs need a few rounds.
    """
    nbr = np.full((num_graphs * N, 2), -1, dtype=np.int64)
    E = len(i)
    if E == 0:
        return nbr.reshape(num_graphs, N, 2)
    order = np.lexsort((i * N + j, -w, graph))  # the sequential order: per graph, strongest first
    i, j = i[order], j[order]
    u, v = graph[order] * N + i, graph[order] * N + j  # vertex ids over all graphs
    # incidences (each pair at both ends), by vertex, then by order
    inc_vertex = np.concatenate([u, v])
    inc_pair = np.concatenate([np.arange(E), np.arange(E)])
    by_vertex = np.lexsort((inc_pair, inc_vertex))
    inc_vertex, inc_pair = inc_vertex[by_vertex], inc_pair[by_vertex]
    at = np.empty(2 * E, dtype=np.int64)
    at[by_vertex] = np.arange(2 * E)  # where pair e sits at its end u (at[e]) and at v (at[E + e])
    first = np.flatnonzero(np.r_[True, inc_vertex[1:] != inc_vertex[:-1]])
    group_start = np.repeat(first, np.diff(np.r_[first, 2 * E]))
    undecided, kept = np.ones(E, dtype=bool), np.zeros(E, dtype=bool)
    degree = np.zeros(num_graphs * N, dtype=np.int64)
    while undecided.any():
        open_ = undecided[inc_pair]
        seen = np.cumsum(open_)
        rank = seen - (seen[group_start] - open_[group_start]) - 1  # among the vertex's undecided pairs
        ok = open_ & (rank < 2 - degree[inc_vertex])
        take = ok[at[:E]] & ok[at[E:]]
        kept |= take
        undecided &= ~take
        degree += np.bincount(u[take], minlength=len(degree)) + np.bincount(v[take], minlength=len(degree))
        full = degree >= 2
        undecided &= ~(full[u] | full[v])
    sel = kept[inc_pair]
    vertex, pair = inc_vertex[sel], inc_pair[sel]
    slot = np.r_[False, vertex[1:] == vertex[:-1]].astype(np.int64)  # the vertex's second kept pair: slot 1
    nbr[vertex, slot] = np.where(u[pair] == vertex, j[pair], i[pair])
    return nbr.reshape(num_graphs, N, 2)


@torch.no_grad()
def greedy_neighbours(log_assignment: torch.Tensor, pred_vertex_mask: torch.Tensor, match_threshold: float = 0.1,
                      class_log_probs: torch.Tensor | None = None, same_class_edges: bool = False,
                      vertices_px: torch.Tensor | None = None, max_edge_px: float | None = None) -> torch.Tensor:
    """Greedy maximum-weight degree-<=2 edges: [B, N+1, N+1] log assignment, [B, N] mask -> [B, N, 2], in
    ``vertex_neighbours``' convention (symmetric, -1 for none, a single neighbour in slot 0): the greedy rule
    (``greedy_two_matching``: strongest first, ties row-major) on the pairs of ``candidate_pairs``.
    ``same_class_edges`` needs ``class_log_probs`` [B, N, K]; ``max_edge_px`` needs ``vertices_px`` [B, N, 2]."""
    B, N = pred_vertex_mask.shape
    b, i, j, w = candidate_pairs(log_assignment, pred_vertex_mask, match_threshold, class_log_probs,
                                 same_class_edges, vertices_px, max_edge_px)
    return torch.from_numpy(greedy_two_matching(b, i, j, w, B, N)).to(log_assignment.device)


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


@torch.no_grad()
def neighbours(outputs: dict, match_threshold: float = 0.1, *, decoder: str = "greedy", same_class_edges: bool = False,
               max_edge_px: float | None = None, class_min_prob: float = 0.05) -> torch.Tensor:
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
        # the pairs of the class-agnostic rule, then class k's: both vertices have p_k >= class_min_prob
        b, i, j, w = candidate_pairs(logA, mask, match_threshold, None, False, vertices, max_edge_px)
        member = (class_log_probs.float().exp() >= class_min_prob).cpu().numpy()  # [B, N, K]
        e, k = np.nonzero(member[b, i] & member[b, j])
        nbr = greedy_two_matching(b[e] * K + k, i[e], j[e], w[e], B * K, N)
        return torch.from_numpy(nbr).view(B, K, N, 2).to(logA.device)
    if decoder in OFFICIAL_CONFIDENCE and max_edge_px is not None:
        raise ValueError("max_edge_px is an option of the greedy and classwise decoders")
    if decoder == "mutual":
        return vertex_neighbours(logA, mask, match_threshold, class_log_probs, True)[:, None]
    if decoder == "official":
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


def _rank_chains(nxt: np.ndarray, live: np.ndarray, end: np.ndarray, dist: np.ndarray, low: np.ndarray,
                 rounds: int | None = None) -> np.ndarray:
    """List ranking by pointer jumping over the half-edges ``live`` (``nxt``: successor or -1), in place:
    ``end`` the last half-edge of each one's chain, ``dist`` the steps to it, ``low`` the smallest of
    ``low`` along the way. At most ``rounds`` rounds; returns the half-edges still unfinished (on a
    cycle, whose ``low`` then covers the whole cycle once 2^rounds exceeds its length)."""
    ptr = nxt.copy()
    live = live[ptr[live] >= 0]
    done = 0
    while live.size and (rounds is None or done < rounds):
        p = ptr[live]
        end[live] = end[p]
        dist[live] += 1 + dist[p]
        low[live] = np.minimum(low[live], low[p])
        ptr[live] = ptr[p]
        live = live[ptr[live] >= 0]
        done += 1
    return live


def trace_graphs(nbr: np.ndarray, min_vertices: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Walk G neighbour graphs of degree <= 2 at once: ``nbr`` [G, N, 2] (symmetric, -1 for none, a
    single neighbour in slot 0) -> ``(vertices, lengths, closed)``: the instances of every graph,
    concatenated, graph by graph; in a graph its paths (walked from their lower-index end, in that
    order), then its cycles (walked from their lowest-index vertex towards its slot-0 neighbour).
    ``vertices`` holds ids ``g * N + i``, ``lengths`` [I] the vertex count of each instance (a cycle's
    first vertex is not repeated), ``closed`` [I] bool. Paths need ``min_vertices`` vertices, cycles
    ``max(min_vertices, 3)``.

    Vectorised: the walks are chains of directed half-edges (x -> y, then y -> its other neighbour),
    ranked by pointer jumping (``_rank_chains``, O(E log L) for E edges and instances of at most L
    vertices); a path's chain from one end finds the other end, a cycle's the lowest vertex, and
    each cycle is cut open at it and ranked again.
    """
    G, N, _ = nbr.shape
    V = G * N
    has = nbr.reshape(V, 2) >= 0
    glob = np.where(has, nbr.reshape(V, 2) + (np.arange(V) // N * N)[:, None], -1)  # neighbours as ids
    half = np.flatnonzero(has.ravel())  # half-edge h = 2 x + slot: x -> glob[x, slot]
    empty = np.zeros(0, dtype=np.int64)
    if half.size == 0:
        return empty, empty, np.zeros(0, dtype=bool)
    tail, head = half // 2, glob.ravel()[half]
    out_slot = (glob[head, 0] == tail).astype(np.int64)  # leave the head by its other slot
    nxt = np.full(2 * V, -1, dtype=np.int64)
    nxt[half] = np.where(has[head, out_slot], 2 * head + out_slot, -1)
    end, dist, low = np.arange(2 * V), np.zeros(2 * V, dtype=np.int64), np.arange(2 * V) // 2
    on_cycle = _rank_chains(nxt, half, end, dist, low, rounds=int(np.ceil(np.log2(max(N, 2)))) + 1)
    # a path starts at its lower-index end: the end whose chain reaches a higher one
    ends = np.flatnonzero(has[:, 0] & ~has[:, 1])
    path_start = ends[ends < head[np.searchsorted(half, end[2 * ends])]]
    cycle_start = np.unique(low[on_cycle])
    for into in (glob[cycle_start, 1], glob[cycle_start, 0]):  # cut each cycle open at its start
        nxt[2 * into + (glob[into, 0] != cycle_start)] = -1
    end[on_cycle], dist[on_cycle] = on_cycle, 0
    _rank_chains(nxt, on_cycle, end, dist, low)
    start = np.concatenate([path_start, cycle_start])
    cycle = np.r_[np.zeros(len(path_start), dtype=bool), np.ones(len(cycle_start), dtype=bool)]
    # an instance's walk: the chain of its start's slot-0 half-edge; steps = its half-edges less one
    owner = np.full(2 * V, -1, dtype=np.int64)
    owner[end[2 * start]] = np.arange(len(start))
    c = owner[end[half]]
    walk = c >= 0
    steps = dist[2 * start]
    c, pos, heads = c[walk], steps[c[walk]] - dist[half[walk]], head[walk]
    back = cycle[c] & (pos == steps[c])  # a cycle's last step returns to its start
    count = steps + 1 + ~cycle  # vertices
    order = np.lexsort((start, cycle, start // N))  # graph, paths before cycles, start vertex
    rank = np.empty(len(start), dtype=np.int64)
    rank[order] = np.arange(len(start))
    sort = np.lexsort((np.r_[np.full(len(start), -1), pos[~back]], np.r_[rank, rank[c[~back]]]))
    vertices = np.r_[start, heads[~back]][sort]
    lengths, closed = count[order], cycle[order]
    kept = lengths >= np.where(closed, max(min_vertices, 3), min_vertices)
    return vertices[np.repeat(kept, lengths)], lengths[kept], closed[kept]


def trace_instances(nbr0: list[int], nbr1: list[int], min_vertices: int = 2) -> list[tuple[list[int], bool]]:
    """One graph's instances (``trace_graphs`` of one graph): ``nbr0[i]``, ``nbr1[i]`` the neighbours of
    vertex i or -1 (a single one in ``nbr0``) -> ``[(vertex indices in order, closed)]``."""
    vertices, lengths, closed = trace_graphs(np.array([nbr0, nbr1], dtype=np.int64).T.reshape(1, -1, 2),
                                             min_vertices)
    bounds = np.concatenate([[0], np.cumsum(lengths)]).tolist()
    return [(vertices[a:z].tolist(), c) for a, z, c in zip(bounds[:-1], bounds[1:], closed.tolist())]


@torch.no_grad()
def postprocess_batch(outputs: dict, grid: BEVGrid, match_threshold: float = 0.1, same_class_edges: bool = False,
                      min_vertices: int = 2, *, decoder: str = "greedy", max_edge_px: float | None = None,
                      class_min_prob: float = 0.05) -> list[list[dict]]:
    """Model outputs (docs/conventions.md keys) -> per sample, a list of polyline dicts in metres.

    Uses ``pred_log_assignment`` [B, N+1, N+1], ``pred_vertices_px`` [B, N, 2], ``pred_vertex_mask``
    [B, N], ``pred_vertex_scores`` [B, N], ``pred_class_log_probs`` [B, N, K]. See the module
    docstring for the rules; ``decode_options(cfg.model.gnn, grid)`` gives the config's options.
    """
    missing = [k for k in REQUIRED_OUTPUTS if k not in outputs]
    if missing:
        raise KeyError(f"post-processing needs {missing}, missing from the model output (docs/conventions.md)")
    grid = as_grid(grid, "postprocess_batch")
    # onnxruntime's outputs (docs/deploy.md, "Using the file without this package") are NumPy arrays: a raw
    # "'numpy.ndarray' object has no attribute 'float'"
    outputs = {k: torch.from_numpy(v) if isinstance(v, np.ndarray) else v for k, v in outputs.items()}
    if not (is_real(match_threshold) and 0 < match_threshold < 1):  # NaN or 5: nothing decoded, no word
        raise ValueError(f"postprocess_batch: match_threshold is an adjacency probability in (0, 1) "
                         f"(model.gnn.match_threshold), got {match_threshold!r:.40}")
    shape = list(getattr(outputs["pred_vertices_px"], "shape", ()))
    if len(shape) != 3 or shape[2] != 2:  # one sample's outputs: a raw "not enough values to unpack"
        raise ValueError(f"postprocess_batch: outputs must be batched, 'pred_vertices_px' [B, N, 2], got shape {shape} "
                         "(one sample's outputs: add the batch dimension, v[None])")
    size = list(getattr(outputs.get("pred_heatmap"), "shape", ()))[-2:]
    if len(size) == 2 and size != [grid.H, grid.W]:  # BEV pixels read as metres of another grid: wrong, no word
        raise ValueError(f"postprocess_batch: the outputs are of a model of another grid ('pred_heatmap' H x W "
                         f"{size[0]} x {size[1]}, the grid {grid.H} x {grid.W}): decode with the grid the model was "
                         "built with (BEVGrid.from_config(cfg.grid) of its config)")
    if decoder == "official":
        if max_edge_px is not None:
            raise ValueError("max_edge_px is an option of the greedy and classwise decoders")
        (B, N), G = outputs["pred_vertex_mask"].shape, outputs["pred_class_log_probs"].shape[2]
        # per sample, one "graph" per class holding its instances in the official order (open; class by class)
        walks = [(b * G + k) * N + np.asarray(w, dtype=np.int64)
                 for b, sample in enumerate(official_instances(outputs, match_threshold))
                 for w, k in sample if len(w) >= min_vertices]
        vertices = np.concatenate(walks) if walks else np.zeros(0, dtype=np.int64)
        lengths = np.array([len(w) for w in walks], dtype=np.int64)
        closed = np.zeros(len(walks), dtype=bool)
    else:
        nbr = neighbours(outputs, match_threshold, decoder=decoder, same_class_edges=same_class_edges,
                         max_edge_px=max_edge_px, class_min_prob=class_min_prob)  # [B, G, N, 2]
        B, G, N, _ = nbr.shape
        vertices, lengths, closed = trace_graphs(nbr.cpu().numpy().reshape(B * G, N, 2), min_vertices)
    results: list[list[dict]] = [[] for _ in range(B)]
    if len(lengths) == 0:
        return results
    # one transfer per tensor for the whole batch; per-vertex values over the B * N vertices
    pts_m = grid.px_to_m(outputs["pred_vertices_px"].detach().float().cpu().numpy().astype(np.float64))
    class_probs = outputs["pred_class_log_probs"].detach().float().exp().cpu().numpy()
    vertex_scores = outputs["pred_vertex_scores"].detach().float().cpu().numpy()
    graph = vertices // N  # b * G + g
    vertex = graph // G * N + vertices % N
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    mean_probs = np.add.reduceat(class_probs.reshape(B * N, -1)[vertex], starts, axis=0) / lengths[:, None]  # [I, K]
    mean_score = np.add.reduceat(vertex_scores.reshape(B * N)[vertex], starts) / lengths  # [I]
    # one class-agnostic graph: the soft vote decides; class graph g: its instances are class g
    labels = mean_probs.argmax(1) if G == 1 else graph[starts] % G
    conf = mean_probs[np.arange(len(labels)), labels]
    if decoder not in OFFICIAL_CONFIDENCE:
        conf = conf * mean_score
    # the points of each instance, a closed one's first repeated at its end
    shift = np.cumsum(closed) - closed  # closed instances before each
    rows = np.empty(len(vertices) + int(closed.sum()), dtype=np.int64)
    rows[np.arange(len(vertices)) + np.repeat(shift, lengths)] = vertex
    rows[(starts + lengths + shift)[closed]] = vertex[starts[closed]]
    pts = pts_m.reshape(B * N, 2)[rows]
    bounds = np.concatenate([[0], np.cumsum(lengths + closed)]).tolist()
    for a, z, b, label, score, shut in zip(bounds[:-1], bounds[1:], (graph[starts] // G).tolist(), labels.tolist(),
                                           conf.tolist(), closed.tolist()):
        results[b].append({"pts": pts[a:z], "label": label, "closed": shut, "score": score})
    return results
