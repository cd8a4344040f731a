"""assignment.py: predicted vertices + GT vertex graph -> adjacency and class targets."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from instagram_hdmap.assignment import (
    IGNORE_INDEX,
    UNMATCHED,
    adjacency_matrix,
    assign,
    target_log_assignment,
)
from instagram_hdmap.geometry import BEVGrid

GRID = BEVGrid(-30.0, 30.0, -15.0, 15.0, 0.15, 8)  # 400 x 200 px, D0 = 1.5 m = 10 px
D0 = 1.5


# ---------------------------------------------------------------------------------------------
# helpers (also used by test_losses.py / test_postprocess.py)
# ---------------------------------------------------------------------------------------------


def graph_tensors(samples: list[list[tuple[np.ndarray, int, bool]]], M: int | None = None) -> dict:
    """Per sample a list of instances (pts_px [P, 2] without a repeated closing point, label, closed)
    -> the GT graph keys of docs/conventions.md, padded to M (padding holds junk coordinates)."""
    sizes = [sum(len(p) for p, _, _ in s) for s in samples]
    M = max(sizes + [0]) if M is None else M
    B = len(samples)
    out = {
        "gt_vertices_px": torch.full((B, M, 2), 123.0),  # junk on padding
        "gt_vertex_mask": torch.zeros(B, M, dtype=torch.bool),
        "gt_vertex_labels": torch.zeros(B, M, dtype=torch.long),
        "gt_vertex_instance": torch.full((B, M), -1, dtype=torch.long),
        "gt_vertex_order": torch.zeros(B, M, dtype=torch.long),
        "gt_vertex_next": torch.full((B, M), -1, dtype=torch.long),
        "gt_vertex_prev": torch.full((B, M), -1, dtype=torch.long),
    }
    for b, sample in enumerate(samples):
        k = 0
        for inst, (pts, label, closed) in enumerate(sample):
            P = len(pts)
            idx = torch.arange(k, k + P)
            out["gt_vertices_px"][b, idx] = torch.as_tensor(np.asarray(pts), dtype=torch.float32)
            out["gt_vertex_mask"][b, idx] = True
            out["gt_vertex_labels"][b, idx] = label
            out["gt_vertex_instance"][b, idx] = inst
            out["gt_vertex_order"][b, idx] = torch.arange(P)
            nxt, prv = idx + 1, idx - 1
            if closed:
                nxt[-1], prv[0] = k, k + P - 1
            else:
                nxt[-1], prv[0] = -1, -1
            out["gt_vertex_next"][b, idx] = nxt
            out["gt_vertex_prev"][b, idx] = prv
            k += P
    return out


def line(start, end, n):
    return np.linspace(start, end, n).astype(np.float32)


def square(cx, cy, r):
    return np.array([[cx - r, cy - r], [cx + r, cy - r], [cx + r, cy + r], [cx - r, cy + r]], np.float32)


def run_assign(pred_px, pred_mask, gt, **kw):
    return assign(pred_px, pred_mask, gt["gt_vertices_px"], gt["gt_vertex_mask"], gt["gt_vertex_labels"],
                  gt["gt_vertex_next"], gt["gt_vertex_prev"], GRID, D0, **kw)


def random_scene(rng: np.random.Generator, n_inst: int) -> list[tuple[np.ndarray, int, bool]]:
    """Random lines and squares on a 12 px spacing lattice (vertices > 2*D0 apart within a shape)."""
    out = []
    for k in range(n_inst):
        if rng.random() < 0.3:
            out.append((square(30 + 60 * k, 40 + rng.integers(0, 100), 12), 1, True))
        else:
            P = int(rng.integers(2, 7))
            x0, y0 = 20 + 60 * k, 20 + rng.integers(0, 100)
            pts = np.stack([np.full(P, x0) + rng.integers(-3, 4), y0 + 12 * np.arange(P)], 1)
            out.append((pts.astype(np.float32), int(rng.choice([0, 2])), False))
    return out


# ---------------------------------------------------------------------------------------------
# tests
# ---------------------------------------------------------------------------------------------


def test_perfect_predictions_reproduce_the_gt_graph():
    gen = torch.Generator().manual_seed(0)
    scene = [(line([10, 10], [10, 70], 6), 0, False), (square(100, 50, 15), 1, True),
             (line([200, 20], [260, 20], 5), 2, False), (line([300, 100], [320, 100], 2), 0, False)]
    gt = graph_tensors([scene], M=24)
    M_real = int(gt["gt_vertex_mask"].sum())
    # predictions = the GT vertices in a random order, then padding
    perm = torch.randperm(M_real, generator=gen)
    N = M_real + 5
    pred = torch.zeros(1, N, 2)
    pred[0, :M_real] = gt["gt_vertices_px"][0, perm]
    mask = torch.zeros(1, N, dtype=torch.bool)
    mask[0, :M_real] = True
    out = run_assign(pred, mask, gt)

    pred_of_gt = torch.empty(M_real, dtype=torch.long)
    pred_of_gt[perm] = torch.arange(M_real)  # GT vertex g is predicted vertex pred_of_gt[g]
    assert torch.equal(out["pred_to_gt"][0, :M_real], perm)
    assert torch.equal(out["gt_to_pred"][0, :M_real], pred_of_gt)
    assert out["pred_is_representative"][0, :M_real].all()
    for key, gt_key in (("target_next", "gt_vertex_next"), ("target_prev", "gt_vertex_prev")):
        g_nb = gt[gt_key][0, perm]  # GT neighbour of each predicted vertex's GT vertex
        expect = torch.where(g_nb >= 0, pred_of_gt[g_nb.clamp(min=0)], torch.full_like(g_nb, N))
        assert torch.equal(out[key][0, :M_real], expect), key
    assert torch.equal(out["target_class"][0, :M_real], gt["gt_vertex_labels"][0, perm])
    assert (out["pred_to_gt_dist_m"][0, :M_real] == 0).all()
    # padding is ignored, never a target
    for key in ("target_next", "target_prev", "target_class"):
        assert (out[key][0, M_real:] == IGNORE_INDEX).all()
    assert (out["pred_to_gt"][0, M_real:] == UNMATCHED).all()

    # the dense forward matrix is the GT adjacency (relabelled), rows and columns sum to one
    A = adjacency_matrix(out["target_next"], out["target_prev"])[0]
    assert torch.equal(A[:M_real].sum(1), torch.ones(M_real))
    assert torch.equal(A[:, :M_real].sum(0), torch.ones(M_real))
    assert A[M_real:N].sum() == 0 and A[:, M_real:N].sum() == 0
    edges = {(int(i), int(j)) for i, j in zip(*torch.nonzero(A[:M_real, :M_real], as_tuple=True))}
    gt_edges = {(int(pred_of_gt[g]), int(pred_of_gt[n])) for g, n in enumerate(gt["gt_vertex_next"][0, :M_real])
                if n >= 0}
    assert edges == gt_edges
    # number of ends = number of open polylines (2 + 1 + 1 lines, the square has none)
    assert int(A[:M_real, N].sum()) == 3


def test_vertices_beyond_d0_go_to_the_dustbin():
    gt = graph_tensors([[(line([50, 50], [50, 74], 3), 2, False)]])
    D0_px = D0 / GRID.resolution  # 10 px
    # 0: exactly on vertex 0; 1: just inside D0 of vertex 1; 2: exactly D0 from vertex 2 (strict <);
    # 3: far from everything
    pred = torch.tensor([[[50.0, 50.0], [50.0 + D0_px - 0.01, 62.0], [50.0 + D0_px, 74.0], [150.0, 150.0]]])
    mask = torch.ones(1, 4, dtype=torch.bool)
    out = run_assign(pred, mask, gt)
    N = 4
    assert out["pred_to_gt"].tolist() == [[0, 1, UNMATCHED, UNMATCHED]]
    assert out["target_next"].tolist() == [[1, N, N, N]]  # vertex 2 of the GT line is not represented
    assert out["target_prev"].tolist() == [[N, 0, N, N]]
    assert out["target_class"].tolist() == [[2, 2, IGNORE_INDEX, IGNORE_INDEX]]
    assert out["pred_to_gt_dist_m"][0, 3] > D0
    assert out["pred_to_gt_dist_m"][0, 1] == pytest.approx((D0_px - 0.01) * GRID.resolution, abs=1e-5)


def test_targets_carry_no_gradient_of_the_predicted_vertices():
    """Targets are constants of the loss: nothing of the assignment is differentiated back into the vertices."""
    gt = graph_tensors([[(line([50, 50], [50, 74], 3), 2, False)]])
    pred = torch.tensor([[[50.0, 50.0], [51.0, 62.0]]], requires_grad=True)
    out = run_assign(pred, torch.ones(1, 2, dtype=torch.bool), gt)
    assert not any(v.requires_grad for v in out.values())


def test_several_predictions_on_one_gt_vertex_keep_the_nearest():
    gt = graph_tensors([[(line([50, 50], [50, 74], 3), 0, False)]])
    # 0, 1, 2 all nearest to GT vertex 1; vertex 2 is the closest; 3 sits on GT vertex 0;
    # 4 and 5 tie on GT vertex 2 (same distance): the lower index (4) represents it
    pred = torch.tensor([[[53.0, 62.0], [50.0, 64.0], [50.0, 61.0], [50.0, 50.0], [52.0, 74.0], [48.0, 74.0]]])
    mask = torch.ones(1, 6, dtype=torch.bool)
    out = run_assign(pred, mask, gt)
    N = 6
    assert out["pred_to_gt"].tolist() == [[1, 1, 1, 0, 2, 2]]
    assert out["pred_is_representative"].tolist() == [[False, False, True, True, True, False]]
    assert out["gt_to_pred"].tolist() == [[3, 2, 4]]
    # the chain 3 -> 2 -> 4; duplicates 0, 1, 5 go to the dustbin both ways but keep their class
    assert out["target_next"].tolist() == [[N, N, 4, 2, N, N]]
    assert out["target_prev"].tolist() == [[N, N, 3, N, 2, N]]
    assert out["target_class"].tolist() == [[0] * 6]


def test_undetected_gt_vertices_are_skipped_along_the_instance():
    gt = graph_tensors([[(line([20, 20], [20, 80], 6), 0, False), (square(100, 50, 15), 1, True),
                         (square(200, 50, 15), 1, True)]])
    V = gt["gt_vertices_px"][0]
    # line: GT 0..5, detect 0, 1, 4 (2 and 3 missed); square A: GT 6..9, detect 6, 8 (7, 9 missed);
    # square B: GT 10..13, detect only 12
    keep = [0, 1, 4, 6, 8, 12]
    pred = V[keep][None]
    mask = torch.ones(1, len(keep), dtype=torch.bool)
    N = len(keep)
    out = run_assign(pred, mask, gt)
    #                       0  1  4  6  8  12   (GT index of each prediction)
    assert out["target_next"].tolist() == [[1, 2, N, 4, 3, N]]
    assert out["target_prev"].tolist() == [[N, 0, 1, 4, 3, N]]
    strict = run_assign(pred, mask, gt, skip_missed=False)
    assert strict["target_next"].tolist() == [[1, N, N, N, N, N]]
    assert strict["target_prev"].tolist() == [[N, 0, N, N, N, N]]


def test_forward_and_backward_targets_are_transposes_on_random_scenes():
    rng = np.random.default_rng(1)
    for _ in range(5):
        gt = graph_tensors([random_scene(rng, 5) for _ in range(3)], M=40)
        B = 3
        N = 50
        pred = torch.as_tensor(rng.uniform(0, 400, (B, N, 2)), dtype=torch.float32)
        # half the predictions are noisy copies of GT vertices (some dropped, some duplicated)
        for b in range(B):
            real = torch.nonzero(gt["gt_vertex_mask"][b])[:, 0]
            pick = real[torch.as_tensor(rng.integers(0, len(real), N // 2))]
            pred[b, : N // 2] = gt["gt_vertices_px"][b, pick] + torch.as_tensor(
                rng.normal(0, 4, (N // 2, 2)), dtype=torch.float32)
        mask = torch.as_tensor(rng.random((B, N)) < 0.9)
        out = run_assign(pred, mask, gt)
        A = adjacency_matrix(out["target_next"], out["target_prev"])
        for b in range(B):
            real = mask[b]
            # every real row and column sums to one, padding carries nothing
            assert torch.equal(A[b, :N][real].sum(1), torch.ones(int(real.sum())))
            assert torch.equal(A[b, :, :N][:, real].sum(0), torch.ones(int(real.sum())))
            assert A[b, :N][~real].sum() == 0 and A[b, :, :N][:, ~real].sum() == 0
            # forward i -> j iff backward j -> i
            tn, tp = out["target_next"][b], out["target_prev"][b]
            for i in torch.nonzero(real)[:, 0].tolist():
                if tn[i] < N:
                    assert tp[tn[i]] == i
                if tp[i] < N:
                    assert tn[tp[i]] == i
            # edges only between representatives of consecutive GT vertices of one instance
            rep = out["pred_is_representative"][b]
            sig = out["pred_to_gt"][b]
            inst = gt["gt_vertex_instance"][b]
            for i in torch.nonzero(real & (tn < N))[:, 0].tolist():
                j = int(tn[i])
                assert rep[i] and rep[j] and inst[sig[i]] == inst[sig[j]]
            assert (tn[real & ~rep] == N).all() and (tp[real & ~rep] == N).all()


def test_batched_equals_one_by_one_and_padding_has_no_effect():
    rng = np.random.default_rng(2)
    scenes = [random_scene(rng, 4), [], random_scene(rng, 2)]
    gt = graph_tensors(scenes, M=30)
    B, N = 3, 40
    pred = torch.as_tensor(rng.uniform(0, 300, (B, N, 2)), dtype=torch.float32)
    for b in (0, 2):
        n_real = int(gt["gt_vertex_mask"][b].sum())
        pred[b, :n_real] = gt["gt_vertices_px"][b, :n_real] + torch.as_tensor(rng.normal(0, 3, (n_real, 2)),
                                                                              dtype=torch.float32)
    n_pred = [35, 12, 20]
    mask = torch.zeros(B, N, dtype=torch.bool)
    for b, n in enumerate(n_pred):
        mask[b, :n] = True
    # padded predictions placed exactly on GT vertices must change nothing
    pred[0, 35:] = gt["gt_vertices_px"][0, :5]
    out = run_assign(pred, mask, gt)
    for b in range(B):
        n, m = n_pred[b], max(int(gt["gt_vertex_mask"][b].sum()), 1)
        one_gt = {k: v[b : b + 1, :m] for k, v in gt.items()}
        one = run_assign(pred[b : b + 1, :n], mask[b : b + 1, :n], one_gt)
        for key in ("pred_to_gt", "pred_is_representative", "target_class"):
            assert torch.equal(out[key][b, :n], one[key][0]), (b, key)
        assert torch.equal(out["gt_to_pred"][b, :m], one["gt_to_pred"][0])
        assert torch.allclose(out["pred_to_gt_dist_m"][b, :n], one["pred_to_gt_dist_m"][0])
        for key in ("target_next", "target_prev"):  # the dustbin index is N in each
            a = out[key][b, :n]
            c = one[key][0]
            assert torch.equal(torch.where(a == N, n, a), c), (b, key)


def test_no_gt_or_no_predictions():
    gt_empty = graph_tensors([[], []], M=0)
    pred = torch.rand(2, 7, 2) * 100
    mask = torch.ones(2, 7, dtype=torch.bool)
    out = run_assign(pred, mask, gt_empty)
    assert (out["pred_to_gt"] == UNMATCHED).all()
    assert (out["target_next"] == 7).all() and (out["target_prev"] == 7).all()
    assert (out["target_class"] == IGNORE_INDEX).all()
    assert out["gt_to_pred"].shape == (2, 0)
    # GT but no real predictions (and N = 0)
    gt = graph_tensors([[(line([20, 20], [20, 44], 3), 0, False)]])
    out = run_assign(torch.zeros(1, 5, 2), torch.zeros(1, 5, dtype=torch.bool), gt)
    assert (out["gt_to_pred"] == UNMATCHED).all() and (out["target_next"] == IGNORE_INDEX).all()
    out = run_assign(torch.zeros(1, 0, 2), torch.zeros(1, 0, dtype=torch.bool), gt)
    assert out["target_next"].shape == (1, 0) and (out["gt_to_pred"] == UNMATCHED).all()


def test_target_log_assignment_is_the_bidirectional_target_distribution():
    gt = graph_tensors([[(line([20, 20], [20, 56], 4), 0, False), (square(100, 50, 15), 1, True)]])
    pred = torch.cat([gt["gt_vertices_px"], torch.tensor([[[300.0, 150.0], [0.0, 0.0]]])], 1)  # + isolated, pad
    mask = torch.tensor([[True] * 9 + [False]])
    out = run_assign(pred, mask, gt)
    P = target_log_assignment(out["target_next"], out["target_prev"]).exp()[0]
    N = 10
    assert torch.allclose(P.sum(1), torch.ones(N + 1), atol=1e-5)
    assert P[0, 1] == pytest.approx(0.5, abs=1e-4) and P[0, N] == pytest.approx(0.5, abs=1e-4)  # line end
    assert P[1, 0] == pytest.approx(0.5, abs=1e-4) and P[1, 2] == pytest.approx(0.5, abs=1e-4)  # interior
    assert P[4, 5] == pytest.approx(0.5, abs=1e-4) and P[4, 7] == pytest.approx(0.5, abs=1e-4)  # square
    assert P[8, N] == pytest.approx(1.0, abs=1e-4)  # isolated


def official_graph_loss_matching(pred_px: np.ndarray, gt_m: np.ndarray, gt_labels: np.ndarray, grid: BEVGrid,
                                 d0: float) -> tuple[np.ndarray, np.ndarray]:
    """A direct reading of the official GraphLoss (juyebshin/InstaGraM @2b978e4, loss.py:9-13,86-88,119,
    131,143-149,157-158): predicted pixels normalised by nx - 1, GT metres by (pt + bound) / (2 bound),
    the nearest GT point in that space, matched iff closer than norm(d0 / (2 bound)); every predicted
    vertex takes the type of its nearest GT point. -> (matched nearest index or -1, class) per vertex."""
    dx = np.array([grid.resolution, grid.resolution])
    bx = np.array([grid.xmin, grid.ymin]) + dx / 2.0
    nx = np.array([(grid.xmax - grid.xmin) / grid.resolution, (grid.ymax - grid.ymin) / grid.resolution])
    bound = dx / 2 - bx
    threshold = np.linalg.norm(d0 / (2 * bound))
    position = pred_px / (nx - 1)
    position_gt = (gt_m + bound) / (2 * bound)
    cdist = np.linalg.norm(position[:, None] - position_gt[None], axis=-1)
    nearest, nearest_dist = cdist.argmin(-1), cdist.min(-1)
    return np.where(nearest_dist < threshold, nearest, -1), gt_labels[nearest]


def test_patch_space_matching_and_nearest_class_targets_follow_the_official_graph_loss():
    """loss.match_space=patch and loss.class_targets=nearest against a direct reading of the official
    rule on random vertices, many of them near the ellipse's border (3.35 m along x, 1.68 m along y)."""
    rng = np.random.default_rng(7)
    B, N, M = 3, 60, 25
    gt_px = rng.integers(0, [GRID.W, GRID.H], size=(B, M, 2)).astype(np.float32)  # integer pixels, as targets.py
    labels = rng.integers(0, 3, size=(B, M))
    # predicted vertices: offsets from a GT vertex up to ~4 m along x and ~2 m along y, some far away
    base = gt_px[np.arange(B)[:, None], rng.integers(0, M, size=(B, N))]
    offset = rng.uniform(-1, 1, size=(B, N, 2)) * np.array([27.0, 14.0])
    pred_px = np.clip(np.round(base + offset), 0, [GRID.W - 1, GRID.H - 1]).astype(np.float32)
    pred_px[:, :5] = rng.integers(0, [GRID.W, GRID.H], size=(B, 5, 2))
    gt = {"gt_vertices_px": torch.from_numpy(gt_px), "gt_vertex_mask": torch.ones(B, M, dtype=torch.bool),
          "gt_vertex_labels": torch.from_numpy(labels), "gt_vertex_next": torch.full((B, M), -1),
          "gt_vertex_prev": torch.full((B, M), -1)}
    mask = torch.ones(B, N, dtype=torch.bool)
    out = run_assign(torch.from_numpy(pred_px), mask, gt, match_space="patch", class_targets="nearest")
    metres = run_assign(torch.from_numpy(pred_px), mask, gt)
    n_matched = n_circle = 0
    for b in range(B):
        ref_match, ref_class = official_graph_loss_matching(pred_px[b].astype(np.float64),
                                                            GRID.px_to_m(gt_px[b].astype(np.float64)), labels[b],
                                                            GRID, D0)
        assert out["pred_to_gt"][b].tolist() == ref_match.tolist()
        assert out["target_class"][b].tolist() == ref_class.tolist()
        n_matched += int((ref_match >= 0).sum())
        n_circle += int((metres["pred_to_gt"][b] >= 0).sum())
    assert n_matched > n_circle  # the ellipse reaches 3.35 m along x: more vertices match than within 1.5 m
    # matched-only class targets (ours) leave the unmatched vertices without a class
    assert ((metres["target_class"] == IGNORE_INDEX) == (metres["pred_to_gt"] == UNMATCHED)).all()


def test_patch_space_is_an_ellipse_of_3_35_m_by_1_68_m_at_the_centre():
    gt = graph_tensors([[(np.array([[199.5, 99.5]], np.float32), 0, False)]])  # the patch centre, (0, 0) m
    along_x = [[199.5 + d / GRID.resolution, 99.5] for d in (3.30, 3.40)]
    along_y = [[199.5, 99.5 + d / GRID.resolution] for d in (1.64, 1.72)]
    pred = torch.tensor([along_x + along_y])
    out = run_assign(pred, torch.ones(1, 4, dtype=torch.bool), gt, match_space="patch")
    assert out["pred_to_gt"].tolist() == [[0, UNMATCHED, 0, UNMATCHED]]
    circle = run_assign(pred, torch.ones(1, 4, dtype=torch.bool), gt)
    assert circle["pred_to_gt"].tolist() == [[UNMATCHED] * 4]


def test_nearest_class_targets_without_gt_or_on_padding_are_ignored():
    gt = graph_tensors([[(line([50, 50], [50, 74], 3), 2, False)], []], M=3)
    pred = torch.tensor([[[50.0, 50.0], [300.0, 150.0], [0.0, 0.0]], [[50.0, 50.0], [1.0, 1.0], [2.0, 2.0]]])
    mask = torch.tensor([[True, True, False], [True, True, True]])
    out = run_assign(pred, mask, gt, class_targets="nearest")
    assert out["target_class"].tolist() == [[2, 2, IGNORE_INDEX], [IGNORE_INDEX] * 3]
    assert out["pred_to_gt"].tolist() == [[0, UNMATCHED, UNMATCHED], [UNMATCHED] * 3]
