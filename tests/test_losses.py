"""losses.py: each term against an explicit-loop reference, perfect predictions, padding, gradients."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from instagram_hdmap.assignment import IGNORE_INDEX, target_log_assignment
from instagram_hdmap.config import LossConfig
from instagram_hdmap.losses import Criterion, adjacency_correct
from test_assignment import GRID, graph_tensors, line, square

S, K = 4, 3
H, W = 16, 24  # tiny dense maps: the dense terms do not depend on the grid used for matching
Hc, Wc = H // S, W // S


def make_case(seed: int, N: int = 12, B: int = 2, n_real=(10, 6), grad: bool = False):
    """Random model outputs (leaf tensors, with grad if asked) + a batch with a small GT graph per sample."""
    g = torch.Generator().manual_seed(seed)
    scenes = [[(line([20, 20], [20, 56], 4), 0, False), (square(100, 50, 15), 1, True)],
              [(line([200, 100], [260, 100], 5), 2, False)]][:B]
    batch = graph_tensors(scenes, M=12)
    batch["gt_vertex_cells"] = torch.randint(0, S * S + 1, (B, Hc, Wc), generator=g)
    batch["gt_distance"] = torch.rand(B, K, H, W, generator=g) * 10
    pred_px = torch.rand(B, N, 2, generator=g) * 300
    mask = torch.zeros(B, N, dtype=torch.bool)
    for b, n in enumerate(n_real):
        mask[b, :n] = True
        m = int(batch["gt_vertex_mask"][b].sum())
        k = min(n - 2, m)  # most real predictions near GT vertices, the last two random
        pred_px[b, :k] = batch["gt_vertices_px"][b, :k] + torch.randn(k, 2, generator=g) * 2
    outputs = {
        "pred_vertex_logits": torch.randn(B, S * S + 1, Hc, Wc, generator=g),
        "pred_distance": torch.rand(B, K, H, W, generator=g) * 10,
        "pred_vertices_px": pred_px,
        "pred_vertex_mask": mask,
        "pred_vertex_scores": torch.rand(B, N, generator=g) * mask,
        "pred_class_log_probs": torch.randn(B, N, K, generator=g).log_softmax(-1),
        "pred_log_assignment": torch.randn(B, N + 1, N + 1, generator=g).log_softmax(-1),
    }
    for k in ("pred_vertex_logits", "pred_distance", "pred_class_log_probs", "pred_log_assignment"):
        outputs[k].requires_grad_(grad)
    return outputs, batch


def reference_losses(outputs, batch, asg):
    """Every term by explicit Python loops."""
    logits = outputs["pred_vertex_logits"].detach().double()
    B = logits.shape[0]
    ce = []
    for b in range(B):
        for y in range(Hc):
            for x in range(Wc):
                lp = logits[b, :, y, x].log_softmax(0)
                ce.append(-lp[batch["gt_vertex_cells"][b, y, x]])
    dist = ((outputs["pred_distance"].detach().double() - batch["gt_distance"].double()) ** 2).mean()
    logA = outputs["pred_log_assignment"].detach().double()
    logp = outputs["pred_class_log_probs"].detach().double()
    adj, cls = [], []
    for b in range(B):
        rows = [i for i in range(logA.shape[1] - 1) if outputs["pred_vertex_mask"][b, i]]
        fwd = sum(-logA[b, i, asg["target_next"][b, i]] for i in rows)
        bwd = sum(-logA[b, i, asg["target_prev"][b, i]] for i in rows)
        adj.append((fwd + bwd) / max(len(rows), 1))
        matched = [i for i in rows if asg["target_class"][b, i] != IGNORE_INDEX]
        cls.append(sum(-logp[b, i, asg["target_class"][b, i]] for i in matched) / max(len(matched), 1))
    return {"loss_vertex": sum(ce) / len(ce), "loss_distance": dist,
            "loss_adjacency": sum(adj) / B, "loss_class": sum(cls) / B}


def test_each_term_matches_the_loop_reference_and_the_total_is_weighted():
    crit = Criterion(LossConfig(), GRID)
    assert crit.weight_dict == {"loss_vertex": 1.0, "loss_distance": 1.0, "loss_adjacency": 5e-3,
                                "loss_class": 1e-2}
    for seed in range(3):
        outputs, batch = make_case(seed)
        out = crit(outputs, batch)
        asg = crit.assign(outputs, batch)
        assert (asg["target_class"] != IGNORE_INDEX).any()  # the case exercises the class term
        ref = reference_losses(outputs, batch, asg)
        for name, value in ref.items():
            assert out[name].item() == pytest.approx(float(value), rel=1e-5), name
            assert out[f"{name}_weighted"].item() == pytest.approx(float(value) * crit.weight_dict[name], rel=1e-5)
        total = sum(float(ref[n]) * w for n, w in crit.weight_dict.items())
        assert out["loss_total"].item() == pytest.approx(total, rel=1e-5)
        # a precomputed assignment gives the same numbers
        again = crit(outputs, batch, assignment=asg)
        assert torch.equal(again["loss_total"], out["loss_total"])
        # diagnostics are detached scalars and not named loss_*
        for k in ("adjacency_accuracy", "adjacency_accuracy_all", "class_accuracy", "num_pred_vertices",
                  "matched_fraction", "gt_vertex_recall"):
            assert out[k].dim() == 0 and not out[k].requires_grad
        assert out["num_pred_vertices"] == 8.0


def perfect_outputs(outputs, batch, crit):
    """Replace the outputs by what a perfect model would produce for this batch."""
    asg = crit.assign(outputs, batch)
    cells = batch["gt_vertex_cells"]
    perfect = dict(outputs)
    perfect["pred_vertex_logits"] = torch.nn.functional.one_hot(cells, S * S + 1).permute(0, 3, 1, 2).float() * 50
    perfect["pred_distance"] = batch["gt_distance"].clone()
    perfect["pred_log_assignment"] = target_log_assignment(asg["target_next"], asg["target_prev"], floor=1e-12)
    tc = asg["target_class"].clamp(min=0)
    perfect["pred_class_log_probs"] = (torch.nn.functional.one_hot(tc, K).float() * 50).log_softmax(-1)
    return perfect, asg


def test_perfect_predictions_reach_the_minimum():
    crit = Criterion(LossConfig(), GRID)
    outputs, batch = make_case(0)
    perfect, asg = perfect_outputs(outputs, batch, crit)
    out = crit(perfect, batch)
    assert float(out["loss_vertex"]) < 1e-6
    assert float(out["loss_distance"]) == 0.0
    assert float(out["loss_class"]) < 1e-6
    # the bidirectional NLL cannot go below the targets' entropy: 2 log 2 for a row with two
    # distinct targets (probability 1/2 each), 0 for an isolated vertex (both targets = dustbin)
    floor = []
    for b in range(2):
        real = outputs["pred_vertex_mask"][b]
        two = (asg["target_next"][b] != asg["target_prev"][b])[real]
        floor.append(2 * math.log(2) * float(two.sum()) / int(real.sum()))
    assert float(out["loss_adjacency"]) == pytest.approx(sum(floor) / 2, abs=1e-6)
    assert float(out["adjacency_accuracy"]) == 1.0 and float(out["adjacency_accuracy_all"]) == 1.0
    assert float(out["class_accuracy"]) == 1.0
    # any other row distribution costs more
    noisy = dict(perfect)
    noisy["pred_log_assignment"] = (perfect["pred_log_assignment"] + 0.3 * torch.randn(2, 13, 13)).log_softmax(-1)
    assert float(crit(noisy, batch)["loss_adjacency"]) > float(out["loss_adjacency"])


def test_padding_has_no_effect():
    crit = Criterion(LossConfig(), GRID)
    outputs, batch = make_case(4)
    base = crit(outputs, batch)
    # grow N by 5 padded vertices with junk coordinates (on a GT vertex), scores and log-probs
    B, N, P = 2, 12, 5
    padded = dict(outputs)
    padded["pred_vertices_px"] = torch.cat([outputs["pred_vertices_px"], batch["gt_vertices_px"][:, :P]], 1)
    padded["pred_vertex_mask"] = torch.cat([outputs["pred_vertex_mask"], torch.zeros(B, P, dtype=torch.bool)], 1)
    padded["pred_vertex_scores"] = torch.cat([outputs["pred_vertex_scores"], torch.zeros(B, P)], 1)
    padded["pred_class_log_probs"] = torch.cat(
        [outputs["pred_class_log_probs"], torch.randn(B, P, K).log_softmax(-1)], 1)
    # new assignment: old real block kept, dustbin moved to index N + P; junk in padded rows/cols
    old = outputs["pred_log_assignment"].detach()
    A = torch.randn(B, N + P + 1, N + P + 1)
    A[:, :N, :N] = old[:, :N, :N]
    A[:, :N, N + P] = old[:, :N, N]
    A[:, N + P, :N] = old[:, N, :N]
    A[:, N + P, N + P] = old[:, N, N]
    padded["pred_log_assignment"] = A
    out = crit(padded, batch)
    for k in ("loss_vertex", "loss_distance", "loss_adjacency", "loss_class", "loss_total",
              "adjacency_accuracy", "adjacency_accuracy_all", "class_accuracy", "matched_fraction",
              "num_pred_vertices"):
        assert float(out[k]) == pytest.approx(float(base[k]), rel=1e-6), k


def test_gradients_reach_the_trained_outputs_only():
    crit = Criterion(LossConfig(), GRID)
    outputs, batch = make_case(5, grad=True)
    outputs["pred_vertices_px"].requires_grad_(True)  # the assignment must not be differentiated
    out = crit(outputs, batch)
    out["loss_total"].backward()
    for k in ("pred_vertex_logits", "pred_distance", "pred_class_log_probs", "pred_log_assignment"):
        grad = outputs[k].grad
        assert grad is not None and torch.isfinite(grad).all() and grad.abs().sum() > 0, k
    assert outputs["pred_vertices_px"].grad is None
    gA = outputs["pred_log_assignment"].grad
    mask = outputs["pred_vertex_mask"]
    assert (gA[:, -1] == 0).all()  # the dustbin row is not supervised
    assert (gA[:, :-1][~mask] == 0).all()  # padded rows
    assert (outputs["pred_class_log_probs"].grad[~mask] == 0).all()


def test_no_gt_or_no_predicted_vertices_give_finite_losses():
    crit = Criterion(LossConfig(), GRID)
    outputs, batch = make_case(6, grad=True)
    empty = graph_tensors([[], []], M=0)
    batch.update(empty)
    # padded rows of the assignment hold -inf: must not leak into the loss or its gradient
    with torch.no_grad():
        outputs["pred_log_assignment"][1, 6:12] = -math.inf
    out = crit(outputs, batch)
    out["loss_total"].backward()
    assert all(torch.isfinite(v).all() for v in out.values())
    assert torch.isfinite(outputs["pred_log_assignment"].grad).all()
    assert out["loss_class"].item() == 0.0 and out["matched_fraction"].item() == 0.0
    # without GT every real vertex is trained towards the dustbin in both directions
    logA = outputs["pred_log_assignment"].detach()
    expect = sum(-2 * logA[b, :n, 12].mean() for b, n in enumerate((10, 6))) / 2
    assert out["loss_adjacency"].item() == pytest.approx(float(expect), rel=1e-5)

    # no real predicted vertex at all (and N = 0)
    for N in (4, 0):
        outputs, batch = make_case(7, N=max(N, 2), n_real=(2, 2))
        outputs = {k: v.detach() for k, v in outputs.items()}
        outputs["pred_vertices_px"] = torch.zeros(2, N, 2)
        outputs["pred_vertex_mask"] = torch.zeros(2, N, dtype=torch.bool)
        outputs["pred_vertex_scores"] = torch.zeros(2, N)
        outputs["pred_class_log_probs"] = torch.zeros(2, N, K)
        outputs["pred_log_assignment"] = torch.zeros(2, N + 1, N + 1).requires_grad_(True)
        out = crit(outputs, batch)
        assert all(torch.isfinite(v).all() for v in out.values())
        assert out["loss_adjacency"].item() == 0.0 and out["num_pred_vertices"].item() == 0.0
        out["loss_total"].backward()


def test_adjacency_accuracy_counts_the_two_best_columns():
    N = 4
    # targets: 0 -> 1 (start), 1 -> 2 (prev 0), 2 end (prev 1), 3 isolated
    tn = torch.tensor([[1, 2, N, N]])
    tp = torch.tensor([[N, 0, 1, N]])
    P = torch.full((1, N + 1, N + 1), 0.01)
    P[0, 0, 1], P[0, 0, N] = 0.5, 0.45  # right
    P[0, 1, 0], P[0, 1, 3] = 0.5, 0.45  # wrong second neighbour
    P[0, 2, 1], P[0, 2, N] = 0.45, 0.5  # right (order does not matter)
    P[0, 3, N] = 0.9  # isolated, right
    ok = adjacency_correct(P.log(), torch.ones(1, N, dtype=torch.bool), tn, tp)
    assert ok.tolist() == [[True, False, True, True]]
    # a padded column never counts as a best column
    mask = torch.tensor([[True, True, True, False]])
    P[0, 1, 3] = 0.99
    P[0, 1, 2] = 0.4
    assert adjacency_correct(P.log(), mask, tn, tp).tolist() == [[True, True, True, True]]


def test_autocast_inputs_are_handled_in_float32():
    crit = Criterion(LossConfig(), GRID)
    outputs, batch = make_case(8)
    half = {k: (v.detach().bfloat16() if v.is_floating_point() and k != "pred_vertices_px" else v)
            for k, v in outputs.items()}
    out, ref = crit(half, batch), crit(outputs, batch)
    assert out["loss_total"].dtype == torch.float32
    assert float(out["loss_total"]) == pytest.approx(float(ref["loss_total"]), rel=2e-2)
    assert np.isfinite(float(out["loss_adjacency"]))


def test_config_switches_and_shape_errors():
    outputs, batch = make_case(9)
    # drop the detections of GT vertex 1 of sample 0's line: with skipping, 0 -> 2 is a target edge
    far = outputs["pred_vertices_px"].clone()
    far[0, :4] = batch["gt_vertices_px"][0, :4]
    far[0, 1] = torch.tensor([390.0, 190.0])  # far from every GT vertex
    outputs["pred_vertices_px"] = far
    skip = Criterion(LossConfig(), GRID).assign(outputs, batch)
    strict = Criterion(LossConfig(skip_missed_vertices=False), GRID).assign(outputs, batch)
    assert skip["target_next"][0, 0] == 2 and strict["target_next"][0, 0] == 12
    assert Criterion(LossConfig(adjacency_weight=0.5), GRID).weight_dict["loss_adjacency"] == 0.5
    bad = dict(outputs, pred_log_assignment=torch.zeros(2, 5, 5))
    with pytest.raises(ValueError, match="pred_log_assignment"):
        Criterion(LossConfig(), GRID)(bad, batch)
    with pytest.raises(KeyError, match="gt_distance"):
        Criterion(LossConfig(), GRID)(outputs, {k: v for k, v in batch.items() if k != "gt_distance"})


def test_without_a_distance_head_there_is_no_distance_term_and_the_rest_is_unchanged():
    """model.bev_heads.distance_head=false (the official visual-descriptor variant): no pred_distance, no
    gt_distance needed, no loss_distance; every other term as with the head."""
    outputs, batch = make_case(3)
    full = Criterion(LossConfig(), GRID)(outputs, batch)
    crit = Criterion(LossConfig(), GRID, with_distance=False)
    assert "loss_distance" not in crit.weight_dict
    out = crit({k: v for k, v in outputs.items() if k != "pred_distance"},
               {k: v for k, v in batch.items() if k != "gt_distance"})
    assert "loss_distance" not in out and "loss_distance_weighted" not in out
    for name in ("loss_vertex", "loss_adjacency", "loss_class"):
        assert torch.equal(out[name], full[name])
    assert out["loss_total"].item() == pytest.approx(
        full["loss_total"].item() - full["loss_distance_weighted"].item(), rel=1e-6)
    with pytest.raises(KeyError, match="pred_distance"):  # with the head, the term is required
        Criterion(LossConfig(), GRID)({k: v for k, v in outputs.items() if k != "pred_distance"}, batch)


def test_the_loss_config_selects_the_official_matching_space_and_class_targets():
    outputs, batch = make_case(4)
    ours = Criterion(LossConfig(), GRID).assign(outputs, batch)
    official = Criterion(LossConfig(match_space="patch", class_targets="nearest"), GRID).assign(outputs, batch)
    real = outputs["pred_vertex_mask"]
    assert (official["target_class"][real] != IGNORE_INDEX).all()  # every real vertex has a class
    assert ((ours["target_class"] != IGNORE_INDEX) == (ours["pred_to_gt"] >= 0)).all()
    assert (official["pred_to_gt"] >= 0).sum() >= (ours["pred_to_gt"] >= 0).sum()
