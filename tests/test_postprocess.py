"""postprocess.py: log assignment -> polylines / polygons; round trip from the GT graph."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from instagram_hdmap.assignment import target_log_assignment
from instagram_hdmap.postprocess import postprocess_batch, trace_instances, vertex_neighbours
from test_assignment import GRID, graph_tensors, line, random_scene, run_assign, square

K = 3


def perfect_outputs(scenes, N: int, seed: int = 0, endpoint_mass: str = "dustbin"):
    """Predicted vertices = GT vertices (shuffled, padded with junk), graph head = the assignment's
    targets. ``endpoint_mass``: 'dustbin' (1/2 neighbour + 1/2 dustbin at a line end, the training
    target) or 'neighbour' (log 1 on the single neighbour)."""
    gen = torch.Generator().manual_seed(seed)
    gt = graph_tensors(scenes)
    B = len(scenes)
    pred = torch.rand(B, N, 2, generator=gen) * 300  # junk on padding
    mask = torch.zeros(B, N, dtype=torch.bool)
    for b in range(B):
        m = int(gt["gt_vertex_mask"][b].sum())
        perm = torch.randperm(m, generator=gen)
        pred[b, :m] = gt["gt_vertices_px"][b, perm]
        mask[b, :m] = True
    asg = run_assign(pred, mask, gt)
    tn, tp = asg["target_next"], asg["target_prev"]
    if endpoint_mass == "neighbour":
        tn = torch.where((tn == N) & (tp != N), tp, tn)
        tp = torch.where((tp == N) & (tn != N), tn, tp)
    log_assignment = target_log_assignment(tn, tp)
    labels = asg["target_class"].clamp(min=0)
    class_log_probs = (torch.nn.functional.one_hot(labels, K).float() * 0.9 + 0.1 / K).log()
    return {
        "pred_vertices_px": pred,
        "pred_vertex_mask": mask,
        "pred_vertex_scores": mask.float() * 0.8,
        "pred_class_log_probs": class_log_probs,
        "pred_log_assignment": log_assignment,
    }


def canonical(pts: np.ndarray, closed: bool) -> tuple:
    """A polyline up to its direction (and, if closed, its starting point), rounded to 1e-4 m."""
    p = [tuple(np.round(q, 4)) for q in pts]
    if closed:
        assert p[0] == p[-1]
        p = p[:-1]
        cands = []
        for seq in (p, p[::-1]):
            for r in range(len(seq)):
                cands.append(tuple(seq[r:] + seq[:r]))
        return min(cands)
    return min(tuple(p), tuple(p[::-1]))


def as_set(instances) -> set:
    return {(canonical(d["pts"], d["closed"]), d["label"], d["closed"]) for d in instances}


def gt_set(scene) -> set:
    out = set()
    for pts, label, closed in scene:
        pts_m = GRID.px_to_m(np.asarray(pts, np.float64))
        if closed:
            pts_m = np.concatenate([pts_m, pts_m[:1]])
        out.add((canonical(pts_m, closed), label, closed))
    return out


SCENES = [
    [(line([10, 10], [10, 70], 6), 0, False), (square(100, 50, 15), 1, True),
     (line([200, 20], [260, 20], 5), 2, False), (line([300, 100], [320, 100], 2), 0, False),
     (np.array([[150, 150], [180, 150], [165, 175]], np.float32), 1, True)],
    [],
    [(line([50, 150], [50, 100], 4), 2, False)],
]


@pytest.mark.parametrize("endpoint_mass", ["dustbin", "neighbour"])
def test_round_trip_gt_graph_to_polylines(endpoint_mass):
    out = postprocess_batch(perfect_outputs(SCENES, N=40, endpoint_mass=endpoint_mass), GRID)
    assert len(out) == len(SCENES)
    for scene, pred in zip(SCENES, out):
        assert as_set(pred) == gt_set(scene)
        for d in pred:
            assert d["pts"].dtype == np.float64 and d["pts"].shape[1] == 2
            assert d["score"] == pytest.approx(0.9 * 0.8 + 0.1 / K * 0.8, rel=1e-4)
            if d["closed"]:
                assert len(d["pts"]) >= 4 and np.array_equal(d["pts"][0], d["pts"][-1])


def test_round_trip_on_random_scenes_and_batched_equals_one_by_one():
    rng = np.random.default_rng(3)
    scenes = [random_scene(rng, int(rng.integers(0, 6))) for _ in range(4)]
    outputs = perfect_outputs(scenes, N=45, seed=1)
    batched = postprocess_batch(outputs, GRID)
    for b, scene in enumerate(scenes):
        assert as_set(batched[b]) == gt_set(scene)
        n = int(outputs["pred_vertex_mask"][b].sum())
        # one sample alone, without padding (dustbin moved from 45 to n)
        keep = list(range(n)) + [45]
        one = {k: v[b : b + 1, :n] for k, v in outputs.items() if k != "pred_log_assignment"}
        one["pred_log_assignment"] = outputs["pred_log_assignment"][b : b + 1][:, keep][:, :, keep]
        single = postprocess_batch(one, GRID)[0]
        assert len(single) == len(batched[b])
        for x, y in zip(single, batched[b]):
            assert np.array_equal(x["pts"], y["pts"]) and x["label"] == y["label"] and x["closed"] == y["closed"]
            assert x["score"] == pytest.approx(y["score"], rel=1e-6)


def test_empty_inputs():
    for N in (0, 1, 5):
        outputs = {
            "pred_vertices_px": torch.zeros(2, N, 2),
            "pred_vertex_mask": torch.zeros(2, N, dtype=torch.bool),
            "pred_vertex_scores": torch.zeros(2, N),
            "pred_class_log_probs": torch.zeros(2, N, K),
            "pred_log_assignment": torch.zeros(2, N + 1, N + 1),
        }
        assert postprocess_batch(outputs, GRID) == [[], []]
    with pytest.raises(KeyError, match="pred_log_assignment"):
        postprocess_batch({"pred_vertex_mask": torch.zeros(1, 2, dtype=torch.bool)}, GRID)


def chain_outputs(P: torch.Tensor, pts_px=None):
    """Outputs for one sample with the given [N+1, N+1] assignment probabilities."""
    N = P.shape[0] - 1
    pts = torch.stack([torch.full((N,), 50.0), 20.0 + 10 * torch.arange(N, dtype=torch.float32)], 1)
    return {
        "pred_vertices_px": (pts if pts_px is None else pts_px)[None],
        "pred_vertex_mask": torch.ones(1, N, dtype=torch.bool),
        "pred_vertex_scores": torch.ones(1, N),
        "pred_class_log_probs": torch.full((1, N, K), 1.0 / K).log(),
        "pred_log_assignment": P.clamp(min=1e-9).log()[None],
    }


def line_probs(N: int) -> torch.Tensor:
    """A chain 0 - 1 - ... - N-1 with the bidirectional target distribution."""
    P = torch.zeros(N + 1, N + 1)
    for i in range(N):
        for j in (i - 1, i + 1):
            P[i, j if 0 <= j < N else N] += 0.5
    P[N] = 1.0 / (N + 1)
    return P


def test_a_weak_edge_splits_the_chain_and_isolated_vertices_are_dropped():
    P = line_probs(6)
    out = postprocess_batch(chain_outputs(P), GRID)[0]
    assert len(out) == 1 and len(out[0]["pts"]) == 6
    # edge 2-3 just below the threshold in both directions -> two polylines 0..2 and 3..5
    Q = P.clone()
    for i, j in ((2, 3), (3, 2)):
        Q[i, j], Q[i, 6] = 0.09, 0.41
    out = postprocess_batch(chain_outputs(Q), GRID, match_threshold=0.1)[0]
    assert sorted(len(d["pts"]) for d in out) == [3, 3]
    # a lower threshold keeps it
    assert len(postprocess_batch(chain_outputs(Q), GRID, match_threshold=0.05)[0]) == 1
    # weak in one direction only: the mutual rule splits; the greedy one weighs the pair by the geometric
    # mean of its directions, sqrt(0.05 * 0.5) = 0.158 > 0.1, and keeps it
    Q = P.clone()
    Q[2, 3], Q[2, 6] = 0.05, 0.45
    assert sorted(len(d["pts"]) for d in postprocess_batch(chain_outputs(Q), GRID, decoder="mutual")[0]) == [3, 3]
    assert [len(d["pts"]) for d in postprocess_batch(chain_outputs(Q), GRID)[0]] == [6]
    # vertex 5's edge falls below the threshold: it is dropped, the rest stays one polyline
    Q = P.clone()
    for i, j in ((4, 5), (5, 4)):
        Q[i, j], Q[i, 6] = 0.08, 0.42
    out = postprocess_batch(chain_outputs(Q), GRID)[0]
    assert len(out) == 1 and len(out[0]["pts"]) == 5
    kept_y = sorted(np.round(out[0]["pts"][:, 1], 4).tolist())
    all_y = GRID.px_to_m(chain_outputs(Q)["pred_vertices_px"][0].numpy().astype(np.float64))[:, 1]
    assert kept_y == sorted(np.round(all_y[:5], 4).tolist())


def test_only_the_two_best_columns_count():
    # vertex 1 has three neighbours above the threshold: the weakest (to 3) is dropped
    N = 4
    P = torch.zeros(N + 1, N + 1)
    P[0, 1], P[0, N] = 0.5, 0.5
    P[1, 0], P[1, 2], P[1, 3] = 0.4, 0.35, 0.25
    P[2, 1], P[2, N] = 0.5, 0.5
    P[3, 1], P[3, N] = 0.6, 0.4
    P[N] = 0.2
    nbr = vertex_neighbours(P.log()[None], torch.ones(1, N, dtype=torch.bool))[0]
    assert nbr.tolist() == [[1, -1], [0, 2], [1, -1], [-1, -1]]


def test_instance_class_and_score_rule():
    P = line_probs(3)
    outputs = chain_outputs(P)
    probs = torch.tensor([[0.6, 0.3, 0.1], [0.1, 0.5, 0.4], [0.1, 0.45, 0.45]])
    outputs["pred_class_log_probs"] = probs.log()[None]
    outputs["pred_vertex_scores"] = torch.tensor([[0.9, 0.6, 0.3]])
    (inst,) = postprocess_batch(outputs, GRID)[0]
    # mean probs = (0.2667, 0.4167, 0.3167) -> class 1; score = 0.4167 * mean(0.9, 0.6, 0.3) = 0.25
    assert inst["label"] == 1
    assert inst["score"] == pytest.approx((1.25 / 3) * 0.6, rel=1e-5)
    # the official decoder's rule: edges only between vertices of the same argmax class
    split = postprocess_batch(outputs, GRID, same_class_edges=True)[0]
    # argmax classes 0, 1, 1 (a tie resolves to the first index): edge 0-1 goes, 1-2 stays
    assert [(len(d["pts"]), d["label"]) for d in split] == [(2, 1)]


def test_neighbours_are_symmetric_with_degree_at_most_two_on_random_assignments():
    gen = torch.Generator().manual_seed(4)
    B, N = 3, 30
    logA = (torch.randn(B, N + 1, N + 1, generator=gen) * 3).log_softmax(-1)
    mask = torch.rand(B, N, generator=gen) < 0.8
    nbr = vertex_neighbours(logA, mask, 0.05)
    assert (nbr[~mask] == -1).all()
    assert ((nbr[..., 0] >= 0) | (nbr[..., 1] < 0)).all()  # a single neighbour sits in slot 0
    P = logA.exp()
    for b in range(B):
        for i in range(N):
            for j in nbr[b, i].tolist():
                if j >= 0:
                    assert mask[b, j] and j != i and i in nbr[b, j].tolist()
                    assert P[b, i, j] > 0.05 and P[b, j, i] > 0.05
    for b in range(B):  # batched equals one at a time
        one = vertex_neighbours(logA[b : b + 1], mask[b : b + 1], 0.05)
        assert torch.equal(one[0], nbr[b])


def test_trace_instances_paths_cycles_and_min_vertices():
    # path 4-0-2, cycle 1-3-5-6, pair 7-8, isolated 9
    nbr = {0: (4, 2), 2: (0, -1), 4: (0, -1), 1: (3, 6), 3: (1, 5), 5: (3, 6), 6: (5, 1), 7: (8, -1),
           8: (7, -1), 9: (-1, -1)}
    n0 = [nbr[i][0] for i in range(10)]
    n1 = [nbr[i][1] for i in range(10)]
    out = trace_instances(n0, n1)
    assert out == [([2, 0, 4], False), ([7, 8], False), ([1, 3, 5, 6], True)]
    assert trace_instances(n0, n1, min_vertices=3) == [([2, 0, 4], False), ([1, 3, 5, 6], True)]
    assert trace_instances([], []) == []


def test_metres_follow_the_grid():
    P = line_probs(2)
    pts = torch.tensor([[0.0, 0.0], [399.0, 199.0]])
    (inst,) = postprocess_batch(chain_outputs(P, pts), GRID)[0]
    got = sorted(map(tuple, np.round(inst["pts"], 6)))
    assert got == [(-29.925, -14.925), (29.925, 14.925)]
    assert not math.isnan(inst["score"])


def test_round_trip_through_the_target_builder():
    """Polylines (metres) -> targets.vertex_graph -> assignment -> perfect log assignment ->
    postprocess_batch gives back the GT graph's polylines (targets.graph_to_polylines)."""
    from instagram_hdmap.targets import graph_to_polylines, vertex_graph

    rng = np.random.default_rng(5)
    samples = []
    for _ in range(3):
        polys = []
        for k in range(int(rng.integers(1, 6))):
            x0, y0 = rng.uniform(-25, 20), rng.uniform(-12, 10)
            if k % 3 == 2:  # a crossing: closed rectangle, first point repeated
                pts = np.array([[x0, y0], [x0 + 4, y0], [x0 + 4, y0 + 3], [x0, y0 + 3], [x0, y0]])
                polys.append({"pts": pts, "label": 1, "closed": True})
            else:
                t = np.arange(int(rng.integers(2, 12)))[:, None] * 1.5
                d = rng.normal(size=2)
                pts = np.array([x0, y0]) + t * d / np.linalg.norm(d)
                polys.append({"pts": pts, "label": int(rng.choice([0, 2])), "closed": False})
        samples.append(polys)
    graphs = [vertex_graph(p, GRID) for p in samples]
    B, M, N = len(graphs), max(len(g["gt_vertices_px"]) for g in graphs), 64
    gt = {"gt_vertices_px": torch.zeros(B, M, 2), "gt_vertex_mask": torch.zeros(B, M, dtype=torch.bool)}
    for k in ("labels", "next", "prev"):
        gt[f"gt_vertex_{k}"] = torch.full((B, M), -1, dtype=torch.long)
    pred = torch.zeros(B, N, 2)
    mask = torch.zeros(B, N, dtype=torch.bool)
    for b, g in enumerate(graphs):
        m = len(g["gt_vertices_px"])
        gt["gt_vertices_px"][b, :m] = g["gt_vertices_px"]
        gt["gt_vertex_mask"][b, :m] = True
        for k in ("labels", "next", "prev"):
            gt[f"gt_vertex_{k}"][b, :m] = g[f"gt_vertex_{k}"]
        pred[b, :m] = g["gt_vertices_px"].flip(0)  # reversed order
        mask[b, :m] = True
    asg = run_assign(pred, mask, gt)
    outputs = {
        "pred_vertices_px": pred, "pred_vertex_mask": mask, "pred_vertex_scores": mask.float(),
        "pred_class_log_probs": torch.nn.functional.one_hot(asg["target_class"].clamp(min=0), K).float()
        .clamp(min=1e-6).log(),
        "pred_log_assignment": target_log_assignment(asg["target_next"], asg["target_prev"]),
    }
    decoded = postprocess_batch(outputs, GRID)
    n_closed = 0
    for b, g in enumerate(graphs):
        expect = graph_to_polylines(GRID.px_to_m(g["gt_vertices_px"].double().numpy()), g["gt_vertex_labels"],
                                    g["gt_vertex_next"])
        assert len(expect) > 0
        assert as_set(decoded[b]) == as_set(expect)
        assert sum(d["closed"] for d in decoded[b]) == sum(d["closed"] for d in expect)
        n_closed += sum(d["closed"] for d in expect)
    assert n_closed > 0  # the case exercises closed shapes


# --- the greedy decoder (the default) -----------------------------------------------------------------


def square_with_duplicate_probs() -> torch.Tensor:
    """A square 0-1-2-3 (a crossing) and a duplicate vertex 4 next to vertex 0 that takes some of
    vertex 0's row: vertex 0 ranks its closing edge to 3 only third."""
    N = 5
    P = torch.zeros(N + 1, N + 1)
    P[0, 1], P[0, 4], P[0, 3] = 0.4, 0.32, 0.28
    P[1, 0], P[1, 2] = 0.5, 0.5
    P[2, 1], P[2, 3] = 0.5, 0.5
    P[3, 2], P[3, 0] = 0.5, 0.5
    P[4, 0], P[4, N] = 0.2, 0.8
    P[N] = 1.0 / (N + 1)
    return P


def test_greedy_closes_the_polygon_that_the_mutual_rule_opens():
    P = square_with_duplicate_probs()
    pts = torch.tensor([[40.0, 40.0], [40.0, 60.0], [60.0, 60.0], [60.0, 40.0], [41.0, 41.0]])
    outputs = chain_outputs(P, pts)
    (poly,) = postprocess_batch(outputs, GRID)[0]
    # pair weights (geometric means): 1-2 0.5, 2-3 0.5, 0-1 0.447, 3-0 0.374, 0-4 0.253: taken in that
    # order, 0-4 comes when vertex 0 already has two edges; the duplicate loses, the square closes
    assert poly["closed"] and len(poly["pts"]) == 5
    assert as_set([poly]) == {(canonical(GRID.px_to_m(pts[:4].double().numpy())[[0, 1, 2, 3, 0]], True), 0, True)}
    # the mutual rule: 0's two best columns are 1 and 4 (4's best is 0: mutual), so 0-3 is not mutual
    # and the square comes out as the open chain 4-0-1-2-3
    mutual = postprocess_batch(outputs, GRID, decoder="mutual")[0]
    assert not any(d["closed"] for d in mutual)
    assert sorted(len(d["pts"]) for d in mutual) == [5]  # 4-0-1-2-3


def test_greedy_same_class_and_max_edge_options():
    P = line_probs(4)
    pts = torch.tensor([[50.0, 20.0], [50.0, 24.0], [50.0, 28.0], [50.0, 40.0]])  # last gap 12 px
    outputs = chain_outputs(P, pts)
    assert [len(d["pts"]) for d in postprocess_batch(outputs, GRID)[0]] == [4]
    # no edge longer than 8 px: 2-3 goes, vertex 3 is left alone and dropped
    assert [len(d["pts"]) for d in postprocess_batch(outputs, GRID, max_edge_px=8.0)[0]] == [3]
    # classes 0, 0, 1, 1: with same_class_edges the chain splits between 1 and 2
    probs = torch.tensor([[0.8, 0.1, 0.1], [0.7, 0.2, 0.1], [0.2, 0.7, 0.1], [0.1, 0.8, 0.1]])
    outputs["pred_class_log_probs"] = probs.log()[None]
    split = postprocess_batch(outputs, GRID, same_class_edges=True)[0]
    assert sorted((len(d["pts"]), d["label"]) for d in split) == [(2, 0), (2, 1)]
    with pytest.raises(ValueError, match="greedy and classwise"):
        postprocess_batch(outputs, GRID, decoder="mutual", max_edge_px=8.0)
    with pytest.raises(ValueError, match="decoder"):
        postprocess_batch(outputs, GRID, decoder="hungarian")


def test_greedy_neighbours_are_a_greedy_maximal_two_matching_on_random_assignments():
    """Symmetric, degree <= 2, every kept pair above the threshold, and the greedy certificate: a
    pair above the threshold that was not kept has an end whose two kept edges both weigh at least
    as much. Batched equals one sample at a time."""
    from instagram_hdmap.postprocess import greedy_neighbours

    gen = torch.Generator().manual_seed(7)
    B, N, thr = 3, 30, 0.03
    logA = (torch.randn(B, N + 1, N + 1, generator=gen) * 3).log_softmax(-1)
    mask = torch.rand(B, N, generator=gen) < 0.8
    nbr = greedy_neighbours(logA, mask, thr)
    assert (nbr[~mask] == -1).all()
    assert ((nbr[..., 0] >= 0) | (nbr[..., 1] < 0)).all()
    w = 0.5 * (logA[:, :N, :N] + logA[:, :N, :N].transpose(1, 2))
    for b in range(B):
        kept = {(i, j) for i in range(N) for j in nbr[b, i].tolist() if j >= 0}
        for i, j in kept:
            assert (j, i) in kept and i != j and mask[b, i] and mask[b, j]
            assert w[b, i, j] > math.log(thr)
        for i in range(N):
            for j in range(i + 1, N):
                if (i, j) in kept or not (mask[b, i] and mask[b, j]) or w[b, i, j] <= math.log(thr):
                    continue
                full = [v for v in (i, j) if (nbr[b, v] >= 0).all()]
                assert any(all(w[b, v, u] >= w[b, i, j] for u in nbr[b, v].tolist()) for v in full), (b, i, j)
        one = greedy_neighbours(logA[b : b + 1], mask[b : b + 1], thr)
        assert torch.equal(one[0], nbr[b])


def test_decode_options_follow_the_config():
    from instagram_hdmap.config import load_config
    from instagram_hdmap.geometry import BEVGrid
    from instagram_hdmap.postprocess import decode_options

    cfg = load_config(Path(__file__).resolve().parents[1] / "configs" / "synthetic" / "demo.yaml")
    opts = decode_options(cfg.model.gnn, BEVGrid.from_config(cfg.grid))
    assert opts == {"match_threshold": 0.02, "decoder": "classwise", "class_min_prob": 0.05, "same_class_edges": False,
                    "max_edge_px": 10.0, "min_vertices": 4}
    paper = load_config(Path(__file__).resolve().parents[1] / "configs" / "paper" / "table1_b0_lss_128x352.yaml")
    assert decode_options(paper.model.gnn, BEVGrid.from_config(paper.grid)) == {
        "match_threshold": 0.1, "decoder": "official", "class_min_prob": 0.05, "same_class_edges": False,
        "max_edge_px": None, "min_vertices": 2}  # the official export's decoding


# --- the classwise decoder ----------------------------------------------------------------------------


def crossing_on_a_kerb():
    """A boundary 0-1-2 along x = 50 px and a crossing triangle 1-3-4 whose corner is the boundary's
    middle vertex 1 (where a crossing meets the kerb both lines pass through one cell). Vertex 1's
    row has four peaks; its class is split between ped crossing and boundary."""
    N = 5
    P = torch.zeros(N + 1, N + 1)
    P[0, 1], P[0, N] = 0.5, 0.5
    P[1, 0], P[1, 2], P[1, 3], P[1, 4] = 0.25, 0.25, 0.25, 0.25
    P[2, 1], P[2, N] = 0.5, 0.5
    P[3, 1], P[3, 4] = 0.5, 0.5
    P[4, 1], P[4, 3] = 0.5, 0.5
    P[N] = 1.0 / (N + 1)
    pts = torch.tensor([[50.0, 40.0], [50.0, 44.0], [50.0, 48.0], [54.0, 44.0], [54.0, 47.0]])
    probs = torch.tensor([[0.02, 0.01, 0.97], [0.02, 0.49, 0.49], [0.02, 0.01, 0.97], [0.02, 0.96, 0.02],
                          [0.02, 0.96, 0.02]])
    outputs = chain_outputs(P, pts)
    outputs["pred_class_log_probs"] = probs.log()[None]
    return outputs, pts


def test_classwise_gives_a_shared_kerb_vertex_to_both_instances():
    outputs, pts = crossing_on_a_kerb()
    m = GRID.px_to_m(pts.double().numpy())
    got = postprocess_batch(outputs, GRID, 0.1, decoder="classwise", class_min_prob=0.05)[0]
    assert as_set(got) == {(canonical(m[[0, 1, 2]], False), 2, False),
                           (canonical(m[[1, 3, 4, 1]], True), 1, True)}
    crossing = next(d for d in got if d["label"] == 1)
    assert crossing["score"] == pytest.approx((0.49 + 0.96 + 0.96) / 3, rel=1e-5)  # mean p_crossing x score 1
    # one class-agnostic graph can give vertex 1 two edges only: one of the two shapes breaks
    agnostic = postprocess_batch(outputs, GRID, 0.1)[0]
    assert as_set(agnostic) != as_set(got)
    # a vertex below class_min_prob is left out of that class's graph: at 0.5 the shared vertex is in
    # neither, the boundary falls apart and the crossing loses its corner
    strict = postprocess_batch(outputs, GRID, 0.1, decoder="classwise", class_min_prob=0.5)[0]
    assert as_set(strict) == {(canonical(m[[3, 4]], False), 1, False)}


def test_classwise_graphs_are_per_class_and_batched_equals_one_by_one():
    from instagram_hdmap.postprocess import neighbours

    rng = np.random.default_rng(11)
    scenes = [random_scene(rng, int(rng.integers(1, 6))) for _ in range(3)]
    outputs = perfect_outputs(scenes, N=45, seed=2)
    graphs = neighbours(outputs, 0.1, decoder="classwise", class_min_prob=0.05)
    assert graphs.shape == (3, K, 45, 2)
    labels = outputs["pred_class_log_probs"].argmax(2)
    for k in range(K):  # perfect_outputs' classes are confident: class k's graph holds class-k vertices only
        used = (graphs[:, k] >= 0).any(2)
        assert (labels[used] == k).all()
    for b, scene in enumerate(scenes):
        assert as_set(postprocess_batch(outputs, GRID, 0.1, decoder="classwise")[b]) == gt_set(scene)
        one = neighbours({k: v[b : b + 1] for k, v in outputs.items()}, 0.1, decoder="classwise")
        assert torch.equal(one[0], graphs[b])


def edge_probs(N: int, edges=(), one_way=()) -> torch.Tensor:
    """[N+1, N+1] probabilities: 0.5 both ways along ``edges``, 0.5 from i to j only along ``one_way``,
    the rest of each real row on the dustbin."""
    P = torch.zeros(N + 1, N + 1)
    for i, j in edges:
        P[i, j] = P[j, i] = 0.5
    for i, j in one_way:
        P[i, j] = 0.5
    P[:N, N] = (1 - P[:N, :N].sum(1)).clamp(min=0)
    P[N] = 1.0 / (N + 1)
    return P


def decoded_indices(instances, outputs) -> list[list[int]]:
    """Polylines decoded from ``chain_outputs`` (vertex i at v = 20 + 10 i px) -> vertex index lists."""
    v = GRID.m_to_px(np.stack([d["pts"] for d in instances]))[..., 1] if instances else []
    return [[int(round((x - 20) / 10)) for x in row] for row in v]


def test_the_official_decoder_reproduces_the_official_walk():
    """decoder='official' against the official export (postprocess/vectorize.py:104-198 at
    juyebshin/InstaGraM 2b978e4). The expected vertex lists are what that function returns on these
    inputs (run on them, outside this repository): it records a vertex only when the next vertex of
    its walk points back to it, so the last vertex of every walk is lost."""
    cases = [
        (5, dict(edges=[(0, 1), (1, 2), (2, 3), (3, 4)]), [[3, 2, 1, 0]]),  # the path's end 4 is lost
        (3, dict(edges=[(0, 1), (1, 2)]), [[1, 0]]),
        (3, dict(edges=[(1, 0), (0, 2)]), []),  # the lowest index in the middle: two walks of one vertex each
        (5, dict(edges=[(2, 0), (0, 1), (1, 3), (3, 4)]), [[0, 1, 3]]),  # both walks lose their ends
        (2, dict(edges=[(0, 1)]), []),  # a pair gives nothing
        (4, dict(edges=[(0, 1), (1, 2), (2, 3), (3, 0)]), [[0, 1, 2]]),  # a cycle comes out open, one short
        (5, dict(edges=[(0, 1), (1, 2), (3, 4)], one_way=[(2, 3)]), [[3, 1, 0]]),  # walks on over 2 -> 3
    ]
    for n, kw, expected in cases:
        outputs = chain_outputs(edge_probs(n, **kw))
        outputs["pred_class_log_probs"] = torch.tensor([[0.8, 0.1, 0.1]] * n).log()[None]
        out = postprocess_batch(outputs, GRID, decoder="official")[0]
        assert decoded_indices(out, outputs) == expected, (kw, expected)
        assert all(not d["closed"] and d["label"] == 0 and d["score"] == pytest.approx(0.8) for d in out)
    # the class condition: vertex 2 of another argmax class splits 0..4 into two pairs, which both vanish
    outputs = chain_outputs(edge_probs(5, edges=[(0, 1), (1, 2), (2, 3), (3, 4)]))
    outputs["pred_class_log_probs"] = torch.tensor([[0.8, 0.1, 0.1]] * 2 + [[0.1, 0.8, 0.1]] + [[0.8, 0.1, 0.1]] * 2
                                                   ).log()[None]
    assert postprocess_batch(outputs, GRID, decoder="official")[0] == []


def test_the_mutual_decoder_is_the_official_rule_with_whole_instances():
    """decoder='mutual': the official edges (two best real columns, p > 0.1, both ways, the same argmax
    class at both ends) and the official confidence (mean probability of the class, no vertex score),
    traced into whole paths and cycles."""
    outputs = chain_outputs(edge_probs(5, edges=[(0, 1), (1, 2), (2, 3), (3, 4)]))
    probs = torch.tensor([[0.7, 0.2, 0.1], [0.6, 0.3, 0.1], [0.5, 0.4, 0.1], [0.9, 0.05, 0.05], [0.8, 0.1, 0.1]])
    outputs["pred_class_log_probs"] = probs.log()[None]
    outputs["pred_vertex_scores"] = torch.tensor([[0.9, 0.1, 0.5, 0.3, 0.2]])
    (inst,) = postprocess_batch(outputs, GRID, decoder="mutual")[0]
    assert sorted(decoded_indices([inst], outputs)[0]) == [0, 1, 2, 3, 4] and inst["label"] == 0
    assert inst["score"] == pytest.approx(probs[:, 0].mean().item(), rel=1e-6)  # not x mean vertex score
    (greedy,) = postprocess_batch(outputs, GRID)[0]
    assert greedy["score"] == pytest.approx(probs[:, 0].mean().item() * 0.4, rel=1e-6)
    # vertex 2 turns to class 1: no edge joins it to a class-0 vertex, whatever same_class_edges says
    outputs["pred_class_log_probs"] = probs[[0, 1, 3, 3, 4]].clone().index_put_(
        (torch.tensor([2]),), torch.tensor([[0.2, 0.7, 0.1]])).log()[None]
    for flag in (False, True):
        out = postprocess_batch(outputs, GRID, decoder="mutual", same_class_edges=flag)[0]
        assert sorted(sorted(i) for i in decoded_indices(out, outputs)) == [[0, 1], [3, 4]]
    # a cycle stays closed
    outputs = chain_outputs(edge_probs(4, edges=[(0, 1), (1, 2), (2, 3), (3, 0)]))
    (inst,) = postprocess_batch(outputs, GRID, decoder="mutual")[0]
    assert inst["closed"] and len(inst["pts"]) == 5


# --- the vectorised decoding equals the sequential loops ----------------------------------------------------


def _greedy_loop(log_assignment, mask, threshold, class_log_probs=None, same_class=False, vertices=None,
                 max_edge_px=None) -> torch.Tensor:
    """The greedy rule as a plain sequential loop (the reference): dense pair weights, every pair above
    the threshold in order (strongest first, ties row-major), kept while both ends have < 2 edges."""
    B, N = mask.shape
    scores = log_assignment[:, :N, :N].float()
    w = 0.5 * (scores + scores.transpose(1, 2))
    out = torch.full((B, N, 2), -1, dtype=torch.long)
    for b in range(B):
        pairs = []
        for i in range(N):
            for j in range(i + 1, N):
                if not (mask[b, i] and mask[b, j]) or not w[b, i, j] > math.log(threshold):
                    continue
                if same_class and class_log_probs[b, i].argmax() != class_log_probs[b, j].argmax():
                    continue
                if max_edge_px is not None:
                    d = vertices[b, i].double() - vertices[b, j].double()
                    if math.hypot(float(d[0]), float(d[1])) > max_edge_px:
                        continue
                pairs.append((-float(w[b, i, j]), i, j))
        degree = [0] * N
        for _, i, j in sorted(pairs):  # strongest first; equal weights in row-major order
            if degree[i] < 2 and degree[j] < 2:
                out[b, i, degree[i]], out[b, j, degree[j]] = j, i
                degree[i] += 1
                degree[j] += 1
    return out


def _trace_loop(nbr0: list[int], nbr1: list[int], min_vertices: int = 2) -> list[tuple[list[int], bool]]:
    """The walk as a plain loop (the reference): paths from their lower-index end, then cycles from their
    lowest vertex towards its first neighbour."""
    n, seen, out = len(nbr0), [False] * len(nbr0), []
    for s in range(n):
        if seen[s] or nbr0[s] < 0 or nbr1[s] >= 0:
            continue
        path, prev, cur = [s], s, nbr0[s]
        seen[s] = True
        while cur >= 0:
            path.append(cur)
            seen[cur] = True
            prev, cur = cur, (nbr1[cur] if nbr0[cur] == prev else nbr0[cur])
        if len(path) >= min_vertices:
            out.append((path, False))
    for s in range(n):
        if seen[s] or nbr0[s] < 0:
            continue
        cycle, prev, cur = [s], s, nbr0[s]
        seen[s] = True
        while cur != s:
            cycle.append(cur)
            seen[cur] = True
            prev, cur = cur, (nbr1[cur] if nbr0[cur] == prev else nbr0[cur])
        if len(cycle) >= max(min_vertices, 3):
            out.append((cycle, True))
    return out


def _chain_outputs(B: int, N: int, seed: int, noise: float) -> dict:
    """Model outputs whose assignment follows random chains (some closed) plus noise: the decoding then
    meets real paths, cycles, spurious candidates and ties of its greedy rule."""
    gen = torch.Generator().manual_seed(seed)
    nxt = torch.full((B, N), N, dtype=torch.long)
    prv = torch.full((B, N), N, dtype=torch.long)
    for b in range(B):
        perm = torch.randperm(N, generator=gen).tolist()
        k = 0
        while k < N - 1:
            length = int(torch.randint(2, 9, (1,), generator=gen))
            chain = perm[k : k + length]
            for a, c in zip(chain[:-1], chain[1:]):
                nxt[b, a], prv[b, c] = c, a
            if len(chain) >= 3 and float(torch.rand(1, generator=gen)) < 0.3:  # close it
                nxt[b, chain[-1]], prv[b, chain[0]] = chain[0], chain[-1]
            k += length
    log_assignment = target_log_assignment(nxt, prv, floor=1e-3)
    log_assignment = (log_assignment + noise * torch.randn(log_assignment.shape, generator=gen)).log_softmax(-1)
    mask = torch.rand(B, N, generator=gen) < 0.9
    return {"pred_log_assignment": log_assignment, "pred_vertex_mask": mask,
            "pred_vertices_px": torch.randint(0, 60, (B, N, 2), generator=gen).float(),
            "pred_vertex_scores": torch.rand(B, N, generator=gen) * mask,
            "pred_class_log_probs": (2 * torch.randn(B, N, K, generator=gen)).log_softmax(-1)}


@pytest.mark.parametrize("seed", range(4))
def test_vectorised_greedy_equals_the_sequential_loop(seed):
    from instagram_hdmap.postprocess import greedy_neighbours, neighbours

    for outputs in (_chain_outputs(3, 40, seed, 0.5), _chain_outputs(2, 25, seed, 3.0)):
        logA, mask = outputs["pred_log_assignment"], outputs["pred_vertex_mask"]
        clp, verts = outputs["pred_class_log_probs"], outputs["pred_vertices_px"]
        for thr, same, max_edge in ((0.1, False, None), (0.02, True, None), (0.02, False, 14.0)):
            got = greedy_neighbours(logA, mask, thr, clp, same, verts, max_edge)
            assert torch.equal(got, _greedy_loop(logA, mask, thr, clp, same, verts, max_edge)), (thr, same)
        # classwise: the greedy rule per class over the vertices with p_k >= class_min_prob
        graphs = neighbours(outputs, 0.02, decoder="classwise", class_min_prob=0.2, max_edge_px=14.0)
        for k in range(K):
            member = mask & (clp[..., k].exp() >= 0.2)
            assert torch.equal(graphs[:, k], _greedy_loop(logA, member, 0.02, None, False, verts, 14.0)), k


def test_ties_are_broken_in_row_major_order_like_the_loop():
    """Equal pair weights everywhere: the first pairs in row-major order win, as in the sequential loop."""
    N = 6
    logA = torch.zeros(1, N + 1, N + 1).log_softmax(-1)
    mask = torch.ones(1, N, dtype=torch.bool)
    from instagram_hdmap.postprocess import greedy_neighbours

    got = greedy_neighbours(logA, mask, 0.05)
    assert torch.equal(got, _greedy_loop(logA, mask, 0.05))
    assert got[0, 0].tolist() == [1, 2]  # (0, 1) then (0, 2)


@pytest.mark.parametrize("min_vertices", [2, 3, 5])
def test_vectorised_walk_equals_the_loop(min_vertices):
    from instagram_hdmap.postprocess import greedy_neighbours, trace_graphs

    outputs = _chain_outputs(4, 50, 11, 0.8)
    nbr = greedy_neighbours(outputs["pred_log_assignment"], outputs["pred_vertex_mask"], 0.05)  # [B, N, 2]
    vertices, lengths, closed = trace_graphs(nbr.numpy(), min_vertices)
    expected = [([b * 50 + i for i in walk], shut) for b in range(4)
                for walk, shut in _trace_loop(nbr[b, :, 0].tolist(), nbr[b, :, 1].tolist(), min_vertices)]
    bounds = np.concatenate([[0], np.cumsum(lengths)])
    got = [(vertices[a:z].tolist(), bool(c)) for a, z, c in zip(bounds[:-1], bounds[1:], closed)]
    assert got == expected and any(c for _, c in expected) and not all(c for _, c in expected)
    assert trace_instances(nbr[0, :, 0].tolist(), nbr[0, :, 1].tolist(), min_vertices) == \
        _trace_loop(nbr[0, :, 0].tolist(), nbr[0, :, 1].tolist(), min_vertices)


@pytest.mark.parametrize("decoder", ["greedy", "classwise", "mutual", "official"])
def test_postprocess_batch_equals_its_loop_reference(decoder):
    """The whole decoding against one built from the loops: same instances, points, labels and scores
    (exactly), sample by sample."""
    from instagram_hdmap.postprocess import OFFICIAL_CONFIDENCE, neighbours, official_instances
    from test_assignment import GRID as grid

    outputs = _chain_outputs(3, 40, 5, 0.6)
    options = {"match_threshold": 0.05, "min_vertices": 3}
    if decoder in ("greedy", "classwise"):
        options["max_edge_px"] = 20.0
    got = postprocess_batch(outputs, grid, decoder=decoder, **options)
    B, N = outputs["pred_vertex_mask"].shape
    if decoder == "official":
        walks = official_instances(outputs, 0.05)
        traced = [[[(w, False) for w, k in walks[b] if k == g and len(w) >= 3] for g in range(K)] for b in range(B)]
    else:
        opts = {k: v for k, v in options.items() if k != "min_vertices"}
        nbr = neighbours(outputs, decoder=decoder, **opts)
        traced = [[_trace_loop(nbr[b, g, :, 0].tolist(), nbr[b, g, :, 1].tolist(), 3) for g in range(nbr.shape[1])]
                  for b in range(B)]
    pts_m = grid.px_to_m(outputs["pred_vertices_px"].numpy().astype(np.float64))
    probs = outputs["pred_class_log_probs"].exp().numpy()
    scores = outputs["pred_vertex_scores"].numpy()
    for b in range(B):
        expected = []
        for g, instances in enumerate(traced[b]):
            for walk, shut in instances:
                n = np.array([len(walk)])  # an int array: the means are float64, as in the decoding
                mean = (np.add.reduceat(probs[b][walk], [0], axis=0) / n[:, None])[0]
                label = int(mean.argmax()) if len(traced[b]) == 1 else g
                score = mean[label]
                if decoder not in OFFICIAL_CONFIDENCE:
                    score = score * (np.add.reduceat(scores[b][walk], [0]) / n)[0]
                score = float(score)
                expected.append((pts_m[b][walk + [walk[0]] if shut else walk].tolist(), label, shut, score))
        assert [(p["pts"].tolist(), p["label"], p["closed"], p["score"]) for p in got[b]] == expected
    assert sum(len(s) for s in got) > 0
