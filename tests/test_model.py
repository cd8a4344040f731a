"""The InstaGraM model on tiny CPU configs: shapes, padding, Sinkhorn marginals, equivariance, geometry,
gradients, weight loading, bad configs, and the paper's parameter counts."""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path

import pytest
import torch
from efficientnet_pytorch import EfficientNet

from instagram_hdmap.config import ConfigError, UserError, load_config
from instagram_hdmap.geometry import BEVGrid
from instagram_hdmap.models import build_model, summarize_parameters
from instagram_hdmap.models.backbone import load_pretrained_backbone
from instagram_hdmap.models.gnn import AttentionalGNN, GraphHead, positional_encoding
from instagram_hdmap.models.matching import log_optimal_transport, score_matrix
from instagram_hdmap.models.vertices import (
    cell_features,
    cell_patches,
    depth_to_space,
    extract_vertices,
    superpoint_nms,
    vertex_heatmap,
)
from instagram_hdmap.models.view_transform import (
    IPMViewTransform,
    LSSViewTransform,
    MLPViewTransform,
    ego_to_input_pixels,
    input_pixels_to_ego,
    sum_pool,
)

REPO = Path(__file__).resolve().parents[1]
TINY = REPO / "configs" / "synthetic" / "tiny.yaml"
OUTPUT_KEYS = ("pred_vertex_logits", "pred_heatmap", "pred_distance", "pred_vertices_px", "pred_vertex_mask",
               "pred_vertex_scores", "pred_class_log_probs", "pred_log_assignment")
TO_EGO = torch.tensor([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])  # camera (x right, y down, z forward) -> ego


def rig(batch_size: int, image_size: tuple[int, int], yaws_deg=(55, 0, -55, 110, 180, -110), height=1.6):
    """Calibration of a nuScenes-like rig: 1600x900 images, f = 1266 px, resized to the network width
    and cropped at the top (post_rot / post_tran)."""
    h, w = image_size
    V = len(yaws_deg)
    rots, trans = [], []
    for yaw_deg in yaws_deg:
        a = math.radians(yaw_deg)
        yaw = torch.tensor([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1.0]])
        rots.append(yaw @ TO_EGO)
        trans.append(torch.tensor([math.cos(a), 0.5 * math.sin(a), height]))
    s = w / 1600
    return {
        "intrinsics": torch.tensor([[1266.0, 0, 800], [0, 1266, 450], [0, 0, 1]]).expand(batch_size, V, 3, 3),
        "cam_to_ego_rot": torch.stack(rots).expand(batch_size, V, 3, 3),
        "cam_to_ego_trans": torch.stack(trans).expand(batch_size, V, 3),
        "post_rot": torch.diag(torch.tensor([s, s, 1.0])).expand(batch_size, V, 3, 3),
        "post_tran": torch.tensor([0.0, h - 900 * s, 0]).expand(batch_size, V, 3),
        "ground_height": torch.zeros(batch_size),
    }


def make_batch(cfg, batch_size: int = 2, seed: int = 0) -> dict:
    gen = torch.Generator().manual_seed(seed)
    h, w = cfg.data.image_size
    batch = rig(batch_size, (h, w))
    batch["images"] = torch.randn(batch_size, 6, 3, h, w, generator=gen)
    return batch


def tiny_cfg(*overrides: str):
    return load_config(TINY, list(overrides))


def tiny_model(*overrides: str, seed: int = 0):
    torch.manual_seed(seed)
    return build_model(tiny_cfg(*overrides))


# ---------------------------------------------------------------------------------------------
# Shapes
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["lss", "ipm", "mlp"])
@pytest.mark.parametrize("embedding", ["pe+dt", "pe", "dt", "pe+vd"])
def test_output_shapes_for_every_view_transform_and_embedding(kind, embedding):
    cfg = tiny_cfg(f"model.view_transform.kind={kind}", f"model.gnn.embedding={embedding}")
    model = build_model(cfg).eval()
    with torch.no_grad():
        out = model(make_batch(cfg))
    grid = BEVGrid.from_config(cfg.grid)
    B, S, N, K = 2, grid.cell_size, cfg.model.gnn.num_vertices, len(cfg.data.classes)
    expected = {
        "pred_vertex_logits": (B, S * S + 1, grid.Hc, grid.Wc),
        "pred_heatmap": (B, grid.H, grid.W),
        "pred_distance": (B, K, grid.H, grid.W),
        "pred_vertices_px": (B, N, 2),
        "pred_vertex_mask": (B, N),
        "pred_vertex_scores": (B, N),
        "pred_class_log_probs": (B, N, K),
        "pred_log_assignment": (B, N + 1, N + 1),
    }
    assert {k: tuple(out[k].shape) for k in OUTPUT_KEYS} == expected
    assert out["pred_vertex_mask"].dtype == torch.bool
    assert out["pred_log_assignment"].dtype == torch.float32
    assert all(torch.isfinite(out[k].float()).all() for k in OUTPUT_KEYS)
    dist = out["pred_distance"]
    assert dist.min() >= 0 and dist.max() <= cfg.data.dt_clip


@pytest.mark.parametrize("overrides", [
    ["grid.cell_size=2"],
    ["grid.cell_size=8"],
    ["grid.cell_size=10", "grid.xbound=[-10.0, 10.0]", "grid.ybound=[-5.0, 5.0]"],  # odd factor S/2 = 5
])
def test_vertex_head_reaches_the_cell_grid_for_other_cell_sizes(overrides):
    cfg = tiny_cfg(*overrides)
    grid = BEVGrid.from_config(cfg.grid)
    with torch.no_grad():
        out = build_model(cfg).eval()(make_batch(cfg, batch_size=1))
    S = grid.cell_size
    assert out["pred_vertex_logits"].shape == (1, S * S + 1, grid.Hc, grid.Wc)
    assert out["pred_heatmap"].shape == out["pred_distance"].shape[:1] + out["pred_distance"].shape[2:]


def test_bev_features_are_half_resolution_with_256_channels_in_the_paper_setting():
    from instagram_hdmap.models.bev_heads import BEVHeads

    heads = BEVHeads(in_channels=8, num_classes=3, cell_size=8, dt_clip=10.0).eval()
    with torch.no_grad():
        out = heads(torch.randn(1, 8, 100, 200))  # the view transform's grid: H/2 x W/2
    assert out["bev_features"].shape == (1, 256, 100, 200)
    assert out["pred_vertex_logits"].shape == (1, 65, 25, 50)
    assert out["pred_distance"].shape == (1, 3, 200, 400)


def test_official_layout_full_resolution_splat_gives_the_same_outputs_shapes():
    cfg = tiny_cfg()
    official = build_model(tiny_cfg("model.view_transform.bev_downsample=1")).eval()
    ours = build_model(cfg).eval()
    batch = make_batch(cfg)
    with torch.no_grad():
        a, b = official(batch), ours(batch)
    assert all(a[k].shape == b[k].shape for k in OUTPUT_KEYS)
    assert sum(p.numel() for p in official.parameters()) == sum(p.numel() for p in ours.parameters())


def test_batched_forward_equals_one_sample_at_a_time():
    cfg = tiny_cfg()
    model = build_model(cfg).eval()
    batch = make_batch(cfg, batch_size=2)
    with torch.no_grad():
        both = model(batch)
        for b in range(2):
            one = model({k: v[b : b + 1] for k, v in batch.items()})
            for k in OUTPUT_KEYS:
                torch.testing.assert_close(one[k][0], both[k][b], atol=1e-4, rtol=1e-4)


def test_bf16_autocast_keeps_the_sinkhorn_in_float32():
    cfg = tiny_cfg()
    model = build_model(cfg).eval()
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        out = model(make_batch(cfg))
    assert out["pred_log_assignment"].dtype == torch.float32
    assert torch.isfinite(out["pred_log_assignment"]).all()


# ---------------------------------------------------------------------------------------------
# Vertices
# ---------------------------------------------------------------------------------------------


def test_depth_to_space_follows_the_documented_cell_order():
    S, Hc, Wc = 4, 2, 3
    x = torch.zeros(1, S * S, Hc, Wc)
    dy, dx, hc, wc = 1, 3, 1, 2
    x[0, dy * S + dx, hc, wc] = 1
    full = depth_to_space(x, S)
    assert full.shape == (1, Hc * S, Wc * S)
    assert full[0, hc * S + dy, wc * S + dx] == 1 and full.sum() == 1


def test_extract_vertices_one_per_cell_at_its_max_sorted_thresholded_and_padded():
    S, Hc, Wc = 4, 3, 5
    gen = torch.Generator().manual_seed(0)
    logits = torch.randn(2, S * S + 1, Hc, Wc, generator=gen)
    logits[:, -1] = 4.0  # a likely dustbin makes most cells fall below the threshold
    logits[0, 5, 1, 2] = logits[1, 7, 2, 4] = 9.0  # one certain vertex in each sample
    threshold = 0.05
    out = extract_vertices(logits, S, num_vertices=20, threshold=threshold)  # 20 > 15 cells: padded
    heatmap = vertex_heatmap(logits, S)
    probs = logits.softmax(1)[:, :-1]
    for b in range(2):
        cell_max = probs[b].flatten(1).max(0).values  # [Hc*Wc]
        expected = cell_max[cell_max > threshold].sort(descending=True).values
        n = len(expected)
        assert out["mask"][b].sum() == n and out["mask"][b, :n].all()  # real vertices first
        torch.testing.assert_close(out["scores"][b, :n], expected)
        u, v = out["vertices_px"][b, :n].long().unbind(-1)
        torch.testing.assert_close(heatmap[b, v, u], expected)  # the vertex sits at its heatmap value
        assert torch.equal(out["cells"][b, :n], (v // S) * Wc + u // S)
        assert (out["scores"][b, n:] == 0).all() and (out["vertices_px"][b, n:] == 0).all()
    assert out["vertices_px"][0, 0].tolist() == [2 * S + 5 % S, 1 * S + 5 // S]
    # batched equals one sample at a time
    single = extract_vertices(logits[1:], S, num_vertices=20, threshold=threshold)
    for k in out:
        assert torch.equal(out[k][1:], single[k])


def test_cell_patches_are_the_cells_under_the_vertices():
    S, K, H, W = 4, 3, 8, 12
    dense = torch.randn(2, K, H, W)
    cells = torch.tensor([[0, 5, 4], [2, 3, 1]])
    patches = cell_patches(dense, cells, S)
    Wc = W // S
    for b in range(2):
        for n in range(3):
            r, c = divmod(int(cells[b, n]), Wc)
            torch.testing.assert_close(patches[b, n], dense[b, :, r * S:(r + 1) * S, c * S:(c + 1) * S].flatten())


# ---------------------------------------------------------------------------------------------
# Graph head: padding, equivariance, Sinkhorn
# ---------------------------------------------------------------------------------------------


def _graph_head(embedding="pe+dt", seed=0):
    torch.manual_seed(seed)
    grid = BEVGrid(-8, 8, -4, 4, 0.25, 4)
    head = GraphHead(grid=grid, num_classes=3, dt_clip=10.0, bev_channels=6, num_vertices=8, embedding=embedding,
                     dim=32, pe_frequencies=4, layers=2, heads=4, sinkhorn_iters=100)
    return head.train(), grid  # train mode: no BatchNorm in the graph head, padding must still not matter


def _random_vertices(grid, B, N, n_real, seed=0):
    gen = torch.Generator().manual_seed(seed)
    u = torch.randint(0, grid.W, (B, N), generator=gen)
    v = torch.randint(0, grid.H, (B, N), generator=gen)
    return {
        "vertices_px": torch.stack([u, v], -1).float(),
        "scores": torch.rand(B, N, generator=gen),
        "mask": torch.arange(N)[None].expand(B, N) < torch.as_tensor(n_real)[:, None],
        "cells": (v // grid.cell_size) * grid.Wc + u // grid.cell_size,
    }


@pytest.mark.parametrize("embedding", ["pe+dt", "pe+vd"])
def test_padded_vertices_change_no_real_output(embedding):
    head, grid = _graph_head(embedding)
    distance = torch.rand(1, 3, grid.H, grid.W) * 10
    features = torch.randn(1, 6, grid.H // 2, grid.W // 2)
    n = 5
    padded = _random_vertices(grid, 1, 8, [n])  # 5 real + 3 padded vertices with arbitrary values
    unpadded = {k: v[:, :n] for k, v in padded.items()}
    a = head.associate(padded, distance, features)
    b = head.associate(unpadded, distance, features)
    torch.testing.assert_close(a["pred_class_log_probs"][:, :n], b["pred_class_log_probs"], atol=1e-5, rtol=1e-5)
    real = list(range(n)) + [8]  # real rows / columns and the dustbin of the padded assignment
    torch.testing.assert_close(a["pred_log_assignment"][:, real][:, :, real], b["pred_log_assignment"],
                               atol=1e-4, rtol=1e-5)
    assert torch.isfinite(a["pred_log_assignment"]).all()


def test_gnn_and_graph_head_are_permutation_equivariant():
    head, grid = _graph_head()
    distance = torch.rand(1, 3, grid.H, grid.W) * 10
    vertices = _random_vertices(grid, 1, 8, [6])
    perm = torch.randperm(8, generator=torch.Generator().manual_seed(1))
    permuted = {k: v[:, perm] for k, v in vertices.items()}
    a = head.associate(vertices, distance, None)
    b = head.associate(permuted, distance, None)
    torch.testing.assert_close(b["pred_class_log_probs"], a["pred_class_log_probs"][:, perm], atol=1e-5, rtol=1e-5)
    perm_bin = torch.cat([perm, torch.tensor([8])])
    ma, mb = vertices["mask"][0], permuted["mask"][0]
    la, lb = a["pred_log_assignment"][0], b["pred_log_assignment"][0]
    valid_b = torch.cat([mb, torch.tensor([True])])
    block = valid_b[:, None] & valid_b[None]
    torch.testing.assert_close(lb[block], la[perm_bin][:, perm_bin][block], atol=1e-4, rtol=1e-5)
    assert ma.sum() == mb.sum()
    # the GNN alone
    gnn = AttentionalGNN(dim=16, heads=4, layers=3)
    g = torch.randn(2, 8, 16)
    mask = torch.ones(2, 8, dtype=torch.bool)
    torch.testing.assert_close(gnn(g[:, perm], mask), gnn(g, mask)[:, perm], atol=1e-5, rtol=1e-5)


def test_gnn_layer_has_the_paper_parameter_count():
    per_layer = sum(p.numel() for p in AttentionalGNN(dim=256, heads=4, layers=1).parameters())
    assert abs(per_layer / 0.66e6 - 1) < 0.02  # Table IV: +0.66 M per layer


def test_sinkhorn_rows_and_columns_sum_to_one_over_the_valid_block():
    gen = torch.Generator().manual_seed(0)
    B, N = 3, 12
    scores = score_matrix(torch.randn(B, N, 8, generator=gen) * 2)
    mask = torch.arange(N)[None] < torch.tensor([12, 7, 3])[:, None]
    log_assignment = log_optimal_transport(scores, torch.tensor(1.0), mask, iters=100)
    # degenerate samples (no vertex; one vertex, which can only go to the dustbin) stay finite
    few = torch.arange(N)[None] < torch.tensor([0, 1])[:, None]
    assert torch.isfinite(log_optimal_transport(scores[:2], torch.tensor(1.0), few, iters=100)).all()
    assert log_assignment.shape == (B, N + 1, N + 1) and torch.isfinite(log_assignment).all()
    probs = log_assignment.exp()
    for b in range(B):
        n = int(mask[b].sum())
        idx = torch.cat([torch.arange(n), torch.tensor([N])])
        block = probs[b][idx][:, idx]  # real rows/columns + dustbin
        torch.testing.assert_close(block[:n].sum(1), torch.ones(n), atol=1e-4, rtol=0)  # rows incl. dustbin
        torch.testing.assert_close(block[:, :n].sum(0), torch.ones(n), atol=1e-4, rtol=0)  # columns
        torch.testing.assert_close(block[n].sum(), torch.tensor(float(n)), atol=1e-3, rtol=0)  # dustbin mass n
        assert block[:n, :n].diagonal().max() < 1e-30  # no self-loops
        if n < N:
            assert probs[b, :N, :N][mask[b]][:, ~mask[b]].max() == 0  # no mass on padding


def test_sinkhorn_inference_fast_path_equals_the_autograd_path():
    gen = torch.Generator().manual_seed(0)
    scores = score_matrix(torch.randn(2, 10, 8, generator=gen) * 3)
    mask = torch.arange(10)[None] < torch.tensor([10, 4])[:, None]
    bin_score = torch.tensor(0.5, requires_grad=True)
    slow = log_optimal_transport(scores, bin_score, mask, iters=50, grad="unrolled")  # grad enabled -> autograd path
    with torch.no_grad():
        fast = log_optimal_transport(scores, bin_score, mask, iters=50)
    valid = torch.cat([mask, torch.ones(2, 1, dtype=torch.bool)], 1)
    block = valid[:, :, None] & valid[:, None]
    torch.testing.assert_close(fast[block], slow.detach()[block], atol=1e-5, rtol=1e-5)
    slow[block].sum().backward()
    assert bin_score.grad is not None and torch.isfinite(bin_score.grad)


def _converged_gradients(scores, bin_value, mask, grad, iters, weights):
    scores = scores.clone().requires_grad_(True)
    bin_score = torch.tensor(bin_value, requires_grad=True)
    out = log_optimal_transport(scores, bin_score, mask, iters=iters, grad=grad)
    valid = torch.cat([mask, torch.ones(len(mask), 1, dtype=torch.bool)], 1)
    block = valid[:, :, None] & valid[:, None]
    (torch.where(block, out, torch.zeros_like(out)) * weights).sum().backward()
    return out.detach(), scores.grad, bin_score.grad


@pytest.mark.parametrize("spread", [1.0, 2.0])
def test_implicit_sinkhorn_gradient_equals_the_converged_unrolled_one(spread):
    """The implicit backward (fixed-point differentiation) against an independent reference: plain
    autograd through the same 3000 iterations, which have converged by then. Same forward values."""
    gen = torch.Generator().manual_seed(2)
    B, N = 3, 30
    scores = score_matrix(torch.randn(B, N, 8, generator=gen) * spread)
    mask = torch.arange(N)[None] < torch.tensor([30, 19, 6])[:, None]
    weights = torch.randn(B, N + 1, N + 1, generator=gen)
    out_i, grad_i, bin_i = _converged_gradients(scores, 0.7, mask, "implicit", 3000, weights)
    out_u, grad_u, bin_u = _converged_gradients(scores, 0.7, mask, "unrolled", 3000, weights)
    valid = torch.cat([mask, torch.ones(B, 1, dtype=torch.bool)], 1)
    block = valid[:, :, None] & valid[:, None]
    torch.testing.assert_close(out_i[block], out_u[block], atol=2e-4, rtol=1e-4)
    assert ((grad_i - grad_u).norm() / grad_u.norm()) < 1e-4
    torch.testing.assert_close(bin_i, bin_u, rtol=1e-4, atol=1e-5)
    assert (grad_i[~(mask[:, :, None] & mask[:, None])] == 0).all()  # nothing flows into padding


def test_implicit_sinkhorn_padding_changes_no_real_gradient():
    """Appending padded vertices leaves the gradients of the real scores and of the dustbin score
    unchanged; samples with zero or one real vertex give finite gradients."""
    gen = torch.Generator().manual_seed(3)
    n, N = 9, 14
    base = score_matrix(torch.randn(1, n, 8, generator=gen) * 3)
    padded = torch.full((1, N, N), 5.0)
    padded[:, :n, :n] = base
    w_small = torch.randn(1, n + 1, n + 1, generator=gen)
    w_big = torch.zeros(1, N + 1, N + 1)
    idx = torch.cat([torch.arange(n), torch.tensor([N])])
    w_big[0][idx[:, None], idx[None]] = w_small[0]
    _, g_small, b_small = _converged_gradients(base, 1.0, torch.ones(1, n, dtype=torch.bool), "implicit", 100,
                                               w_small)
    _, g_big, b_big = _converged_gradients(padded, 1.0, torch.arange(N)[None] < n, "implicit", 100, w_big)
    torch.testing.assert_close(g_big[:, :n, :n], g_small, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(b_big, b_small, atol=1e-6, rtol=1e-5)
    few = torch.arange(N)[None] < torch.tensor([0, 1])[:, None]
    _, g_few, b_few = _converged_gradients(padded.expand(2, N, N), 1.0, few, "implicit", 100,
                                           torch.randn(2, N + 1, N + 1, generator=gen))
    assert torch.isfinite(g_few).all() and torch.isfinite(b_few)


def test_implicit_sinkhorn_backward_survives_underflow_and_non_finite_scores():
    """A real row whose plan underflows to 0 (iterations far from converged on extreme scores) gave
    0 / 0 in the backward, and a non-finite sample made MKL's LU return invalid pivots, so lu_solve
    raised in the middle of training: both now give finite gradients, and the other sample of the
    batch keeps exactly the gradient it has alone."""
    gen = torch.Generator().manual_seed(5)
    B, N = 2, 6
    scores = torch.randn(B, N, N, generator=gen)
    scores[0, 1, :] = -3000.0  # its plan underflows: exp(-3000) = 0 in float64
    mask = torch.ones(B, N, dtype=torch.bool)
    weights = torch.randn(B, N + 1, N + 1, generator=gen)
    for poison in (None, float("nan"), float("inf")):
        s = scores.clone()
        if poison is not None:
            s[0, 2, 3] = poison
        s.requires_grad_()
        z = log_optimal_transport(s, torch.tensor(-3000.0), mask, iters=0)
        (torch.where(torch.isfinite(z), z, 0.0) * weights).sum().backward()  # no RuntimeError
        assert torch.isfinite(s.grad).all()
        alone = scores[1:].clone().requires_grad_()
        z1 = log_optimal_transport(alone, torch.tensor(-3000.0), mask[1:], iters=0)
        (z1 * weights[1:]).sum().backward()
        torch.testing.assert_close(s.grad[1:], alone.grad)


@pytest.mark.parametrize(("spread", "route"), [(1.0, torch.float32), (3.4, torch.float32), (6.0, torch.float64),
                                                (400.0, None)])
def test_cpu_scaling_sinkhorn_equals_the_log_space_iterations(spread, route, monkeypatch):
    """The CPU's scaling-form iterations give the log-space iterations' potentials (same iterates): in
    float32 where the real scores span at most 80 (here ~6 and ~68), in float64 where they span more (~200); where
    they span more than float64's exp() range (~1e6) they decline and the log-space path runs."""
    from instagram_hdmap.models import matching

    ran = []
    iterations = matching._scaling_iterations
    monkeypatch.setattr(matching, "_scaling_iterations", lambda c, *a: ran.append(c.dtype) or iterations(c, *a))
    gen = torch.Generator().manual_seed(4)
    scores = score_matrix(torch.randn(3, 20, 8, generator=gen) * spread)
    mask = torch.arange(20)[None] < torch.tensor([20, 11, 1])[:, None]
    B, N = mask.shape
    bins = torch.full((B, 1, 1), 0.5)
    couplings = torch.cat([torch.cat([scores, bins.expand(B, N, 1)], 2), torch.cat([bins.expand(B, 1, N), bins], 2)], 1)
    valid = torch.cat([mask, torch.ones(B, 1, dtype=torch.bool)], 1)
    couplings = couplings.masked_fill(~(valid[:, :, None] & valid[:, None, :]), matching.NEG_SCORE)
    n = mask.sum(1).float().clamp(min=1)
    norm = -(2 * n).log()
    log_mu = torch.cat([norm[:, None].expand(B, N), (n.log() + norm)[:, None]], 1)
    scaled = matching._sinkhorn_potentials_scaling(couplings, log_mu, valid, 50)
    if route is None:
        assert scaled is None and ran == []
        return
    assert ran == [route]
    logspace = matching._sinkhorn_potentials_inplace(couplings, log_mu, valid, 50)
    block = valid[:, :, None] & valid[:, None]
    z_s = couplings + scaled[0][:, :, None] + scaled[1][:, None, :]
    z_l = couplings + logspace[0][:, :, None] + logspace[1][:, None, :]
    torch.testing.assert_close(z_s[block], z_l[block], atol=2e-4, rtol=1e-5)
    assert (scaled[0][~valid] == matching.NEG_SCORE).all() and (scaled[1][~valid] == matching.NEG_SCORE).all()


def test_cpu_scaling_sinkhorn_in_float32_that_fails_runs_again_in_float64(monkeypatch):
    """A float32 scaling run whose scalings leave float32's range is not returned: the float64 run is."""
    from instagram_hdmap.models import matching

    ran = []
    iterations = matching._scaling_iterations

    def flaky(c, *args):
        ran.append(c.dtype)
        return None if c.dtype == torch.float32 else iterations(c, *args)

    monkeypatch.setattr(matching, "_scaling_iterations", flaky)
    couplings = torch.tensor([[[0.0, -1.0, 0.5], [-2.0, matching.NEG_SCORE, 0.5], [0.5, 0.5, 0.5]]])
    valid = torch.ones(1, 3, dtype=torch.bool)
    log_mu = torch.tensor([[-1.4, -1.4, -0.7]])
    out = matching._sinkhorn_potentials_scaling(couplings, log_mu, valid, 20)
    assert ran == [torch.float32, torch.float64]
    expected = matching._sinkhorn_potentials_inplace(couplings, log_mu, valid, 20)
    torch.testing.assert_close(out[0] + out[1][:, :1], expected[0] + expected[1][:, :1], atol=1e-4, rtol=1e-5)


def test_floored_cpu_logsumexp_matches_torch_on_confident_and_padded_rows():
    """The CPU Sinkhorn's log-sum-exp floors exp()'s argument at EXP_FLOOR (speed, see matching.py):
    values and gradients equal torch.logsumexp's to float32 precision, also where most entries lie
    far below the row maximum (a confident model) or at NEG_SCORE (padding, the masked diagonal)."""
    from instagram_hdmap.models.matching import EXP_FLOOR, NEG_SCORE, _logsumexp

    gen = torch.Generator().manual_seed(0)
    x = torch.randn(3, 41, 41, generator=gen) * 40  # most entries e^-30 or more below their row max
    x[:, :, 30:] = NEG_SCORE  # padded columns
    x[:, torch.arange(41), torch.arange(41)] = NEG_SCORE
    assert ((x - x.amax(2, keepdim=True)) < EXP_FLOOR).float().mean() > 0.5
    upstream = torch.randn(3, 41, generator=gen)
    for dim in (1, 2):
        ours, ref = x.clone().requires_grad_(), x.clone().requires_grad_()
        out_ours, out_ref = _logsumexp(ours, dim), torch.logsumexp(ref, dim=dim)
        torch.testing.assert_close(out_ours, out_ref, rtol=1e-6, atol=1e-6)
        (out_ours * upstream).sum().backward()
        (out_ref * upstream).sum().backward()
        torch.testing.assert_close(ours.grad, ref.grad, rtol=0, atol=1e-6)


@pytest.mark.parametrize("spread", [3.0, 12.0])  # a fresh model's scores; a confident one's (hundreds)
def test_exp_floor_leaves_the_sinkhorn_unchanged(monkeypatch, spread):
    from instagram_hdmap.models import matching

    gen = torch.Generator().manual_seed(1)
    scores = score_matrix(torch.randn(2, 24, 16, generator=gen) * spread)
    mask = torch.arange(24)[None] < torch.tensor([24, 9])[:, None]
    valid = torch.cat([mask, torch.ones(2, 1, dtype=torch.bool)], 1)
    block = valid[:, :, None] & valid[:, None]
    runs = {}
    for floor in (matching.EXP_FLOOR, float("-inf")):  # -inf: no floor, torch.logsumexp's arithmetic
        monkeypatch.setattr(matching, "EXP_FLOOR", floor)
        bin_score = torch.tensor(1.0, requires_grad=True)
        with torch.no_grad():
            fast = log_optimal_transport(scores, bin_score, mask, iters=100)
        slow = log_optimal_transport(scores, bin_score, mask, iters=100, grad="unrolled")
        slow[block].exp().sum().backward()
        runs[floor] = (fast[block], slow.detach()[block], bin_score.grad)
    (fast_a, slow_a, grad_a), (fast_b, slow_b, grad_b) = runs.values()
    torch.testing.assert_close(fast_a, fast_b, rtol=1e-5, atol=1e-4)
    torch.testing.assert_close(slow_a, slow_b, rtol=1e-5, atol=1e-4)
    torch.testing.assert_close(grad_a, grad_b, rtol=1e-4, atol=1e-6)


def test_positional_encoding_bands():
    xy = torch.tensor([[0.25, -0.5]])
    pe = positional_encoding(xy, 3)  # bands 1/2, 1, 2 rad per unit
    assert pe.shape == (1, 2 + 4 * 3)
    torch.testing.assert_close(pe[0, :2], xy[0])
    torch.testing.assert_close(pe[0, 2 + 2 * 2], torch.sin(torch.tensor(2 * 0.25)))  # sin, k = 2, x
    torch.testing.assert_close(pe[0, 2 + 6 + 1], torch.cos(torch.tensor(0.5 * -0.5)))  # cos, k = 0, y


# ---------------------------------------------------------------------------------------------
# View-transform geometry
# ---------------------------------------------------------------------------------------------


def test_projection_round_trip():
    calib = rig(2, (128, 352))
    gen = torch.Generator().manual_seed(0)
    uvd = torch.rand(2, 6, 50, 3, generator=gen) * torch.tensor([352.0, 128.0, 40.0]) + torch.tensor([0, 0, 1.0])
    points = input_pixels_to_ego(uvd, calib)
    uv, depth = ego_to_input_pixels(points, calib)
    torch.testing.assert_close(uv, uvd[..., :2], atol=1e-3, rtol=0)
    torch.testing.assert_close(depth, uvd[..., 2], atol=1e-4, rtol=1e-5)


def _ground_point_setup():
    """One front camera whose height makes the ray through feature pixel (row 6, col 11) hit the
    ground exactly 12 m deep (a depth bin): returns calib, the feature pixel, the ground point."""
    h, w = 128, 352
    calib = rig(1, (h, w), yaws_deg=(0,))
    row, col = 6, 11
    uv_in = torch.tensor([16 * col + 7.5, 16 * row + 7.5])  # feature pixel centre, network input pixels
    uv = (uv_in - calib["post_tran"][0, 0, :2]) / calib["post_rot"][0, 0, 0, 0]  # original image pixel
    ray = calib["cam_to_ego_rot"][0, 0] @ torch.linalg.inv(calib["intrinsics"][0, 0]) @ torch.cat([uv, torch.ones(1)])
    depth = 12.0
    trans = calib["cam_to_ego_trans"].clone()
    trans[..., 2] = -depth * ray[2]  # camera height so that the ray meets z = 0 at 12 m depth
    calib["cam_to_ego_trans"] = trans
    point = trans[0, 0] + depth * ray
    assert abs(float(point[2])) < 1e-5
    return calib, (row, col), point, (h, w)


def test_ground_point_lands_where_ipm_and_lss_put_its_feature():
    calib, (row, col), point, image_size = _ground_point_setup()
    grid = BEVGrid(-30, 30, -15, 15, 0.3, 1)  # the view transforms' half-resolution grid
    u, v = grid.px_index(grid.m_to_px(point[:2])).tolist()
    features = torch.zeros(1, 1, 2, 8, 22)
    features[0, 0, 0, row, col] = 1.0  # one-hot feature at the pixel where the point projects
    features[0, 0, 1] = 1.0  # constant channel: shows where the camera sees

    ipm = IPMViewTransform(grid, image_size, channels=2)
    bev = ipm(features, calib)[0, 0]
    assert bev[v, u] > 0.7  # bilinear weight near 1 at the point's cell
    peak_v, peak_u = divmod(int(bev.argmax()), grid.W)
    assert abs(peak_v - v) <= 1 and abs(peak_u - u) <= 1

    lss = LSSViewTransform(grid, image_size, channels=2, depth_bound=(4.0, 45.0, 1.0), zbound=(-10.0, 10.0))
    with torch.no_grad():
        lss.depth_net.weight.zero_()
        lss.depth_net.bias.zero_()
        lss.depth_net.bias[int(12.0 - 4.0)] = 50.0  # all depth mass in the 12 m bin
        lss.depth_net.weight[lss.num_depths:, :, 0, 0] = torch.eye(2)  # context = input features
        bev = lss(features, calib)[0, 0]
    assert abs(float(bev[v, u]) - 1.0) < 1e-4 and abs(float(bev.sum()) - 1.0) < 1e-4


def test_ipm_plane_follows_each_samples_ground_height():
    """Two samples of one batch: the rig of _ground_point_setup, and the same cameras over the same road
    seen from an ego origin 0.38 m above it (AV2's rear axle: ground_height = -0.38, the cameras 0.38 m
    lower in the ego frame). IPM puts the feature at the point's cell in both; a plane at z = 0 would
    put the second sample's feature short of it."""
    calib, (row, col), point, image_size = _ground_point_setup()
    grid = BEVGrid(-30, 30, -15, 15, 0.3, 1)
    u, v = grid.px_index(grid.m_to_px(point[:2])).tolist()
    batch = {k: torch.cat([t, t]) for k, t in calib.items()}
    batch["cam_to_ego_trans"][1, :, 2] -= 0.38  # the ego origin 0.38 m above the road ...
    batch["ground_height"] = torch.tensor([0.0, -0.38])  # ... which lies at z = -0.38
    features = torch.zeros(2, 1, 2, 8, 22)
    features[:, 0, 0, row, col] = 1.0
    bev = IPMViewTransform(grid, image_size, channels=2)(features, batch)[:, 0]
    for b in range(2):
        peak_v, peak_u = divmod(int(bev[b].argmax()), grid.W)
        assert abs(peak_v - v) <= 1 and abs(peak_u - u) <= 1, b
    flat = dict(batch, ground_height=torch.zeros(2))
    peak_u = int(IPMViewTransform(grid, image_size, channels=2)(features, flat)[1, 0].argmax()) % grid.W
    assert grid.px_to_m(torch.tensor([peak_u, v], dtype=torch.float32))[0] < point[0] - 1.0  # compressed


def test_mlp_placement_puts_the_camera_map_in_front_of_the_camera():
    grid = BEVGrid(-30, 30, -15, 15, 0.3, 1)
    calib = rig(1, (128, 352), yaws_deg=(90,))  # looking left (+y)
    mlp = MLPViewTransform(grid, (128, 352), channels=1, camera_bev_size=(40, 80), num_cameras=1)
    maps = torch.zeros(1, 1, 1, 40, 80)
    r, c = 20, 30  # lateral just right of the axis, forward (c + 0.5) / 80 * reach
    maps[0, 0, 0, r, c] = 1.0
    bev = mlp.place(maps, calib)[0, 0]
    forward = (c + 0.5) / 80 * mlp.reach_m
    lateral = ((r + 0.5) / 40 * 2 - 1) * mlp.reach_m  # along the camera x axis (to its right)
    camera_point = torch.tensor([lateral, 0.0, forward])
    expected = (calib["cam_to_ego_rot"][0, 0] @ camera_point + calib["cam_to_ego_trans"][0, 0])[:2]
    peak_v, peak_u = divmod(int(bev.argmax()), grid.W)
    peak_m = grid.px_to_m(torch.tensor([peak_u, peak_v], dtype=torch.float32))
    assert torch.linalg.norm(peak_m - expected) < 1.0  # within one camera-map pixel (~0.9 m)


def test_lss_splat_gradient_equals_plain_autograd_of_a_naive_reference():
    gen = torch.Generator().manual_seed(0)
    B, P, C, cells_n = 2, 40, 5, 7
    values = torch.randn(B, P, C, generator=gen, requires_grad=True)
    cells = torch.randint(-1, cells_n, (B, P), generator=gen)  # -1 = outside the grid
    upstream = torch.randn(B, cells_n, C, generator=gen)
    fast = sum_pool(values, cells, cells_n)
    (grad_fast,) = torch.autograd.grad((fast * upstream).sum(), values)
    one_hot = torch.stack([(cells == k) for k in range(cells_n)], 1).float()  # [B, cells, P]
    naive = one_hot @ values  # plain autograd
    (grad_naive,) = torch.autograd.grad((naive * upstream).sum(), values)
    torch.testing.assert_close(fast, naive)
    torch.testing.assert_close(grad_fast, grad_naive)
    assert (grad_fast[cells < 0] == 0).all()


# ---------------------------------------------------------------------------------------------
# Gradients, devices
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind,embedding", [("lss", "pe+dt"), ("mlp", "pe+vd"), ("ipm", "dt")])
def test_backward_reaches_every_parameter(kind, embedding):
    cfg = tiny_cfg(f"model.view_transform.kind={kind}", f"model.gnn.embedding={embedding}")
    torch.manual_seed(0)
    model = build_model(cfg).train()
    for name, p in model.named_parameters():
        if name.endswith("bn2.weight"):  # zero-initialised residual gammas block the branch at init
            torch.nn.init.ones_(p)
    out = model(make_batch(cfg))
    mask = out["pred_vertex_mask"]
    assert mask.any()
    pair = mask[:, :, None] & mask[:, None, :]
    loss = (out["pred_vertex_logits"].logsumexp(1).mean() + out["pred_distance"].mean()
            + out["pred_class_log_probs"][mask].mean() + out["pred_log_assignment"][:, :-1, :-1][pair].mean()
            + out["pred_log_assignment"][:, :-1, -1][mask].mean())
    loss.backward()
    missing = [n for n, p in model.named_parameters() if p.grad is None or not (p.grad != 0).any()]
    assert not missing, f"no gradient reaches {missing}"
    assert all(torch.isfinite(p.grad).all() for p in model.parameters())


def test_no_device_literals_in_model_code():
    pattern = re.compile(r"\.cuda\(|\.cpu\(\)|[\"'](cuda|cpu)(:\d+)?[\"']")
    offenders = [
        f"{path.name}:{i}: {line.strip()}"
        for path in sorted((REPO / "src" / "instagram_hdmap" / "models").glob("*.py"))
        for i, line in enumerate(path.read_text().splitlines(), 1)
        if pattern.search(line)
    ]
    assert not offenders, offenders


# ---------------------------------------------------------------------------------------------
# Backbone weights, bad configs, parameter counts
# ---------------------------------------------------------------------------------------------


def _saved_bytes_and_grads(backbone, images, seed):
    """One forward + backward in train mode: bytes autograd saved for backward, the gradients."""
    storages = {}

    def pack(t):
        storages[t.untyped_storage().data_ptr()] = t.untyped_storage().nbytes()
        return t

    torch.manual_seed(seed)  # drop-connect masks
    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        out = backbone(images)
    out.square().mean().backward()
    return sum(storages.values()), [p.grad.clone() for p in backbone.parameters()]


def test_backbone_checkpointing_gives_identical_gradients_and_buffers_with_less_saved():
    from instagram_hdmap.models.backbone import EfficientNetBackbone

    torch.manual_seed(0)
    plain = EfficientNetBackbone("efficientnet-b0", 32, (64, 96), grad_checkpoint=False).train()
    ckpt = EfficientNetBackbone("efficientnet-b0", 32, (64, 96), grad_checkpoint=True).train()
    ckpt.load_state_dict(plain.state_dict())
    assert plain.trunk._global_params.drop_connect_rate > 0  # the masks must be replayed, not redrawn
    images = torch.randn(2, 3, 64, 96)
    saved_plain, grads_plain = _saved_bytes_and_grads(plain, images, seed=3)
    saved_ckpt, grads_ckpt = _saved_bytes_and_grads(ckpt, images, seed=3)
    for a, b in zip(grads_plain, grads_ckpt):
        assert torch.equal(a, b)
    # BatchNorm running statistics were updated once, not again by the recomputation.
    state_plain, state_ckpt = plain.state_dict(), ckpt.state_dict()
    assert all(torch.equal(state_plain[k], state_ckpt[k]) for k in state_plain)
    assert int(state_ckpt["trunk._bn0.num_batches_tracked"]) == 1
    assert saved_ckpt < 0.4 * saved_plain, (saved_ckpt, saved_plain)
    # Evaluation and no-grad forwards never checkpoint (nothing to save) and agree with the plain model.
    with torch.no_grad():
        torch.testing.assert_close(ckpt.eval()(images), plain.eval()(images), rtol=0, atol=0)


def test_backbone_checkpointing_is_on_by_default_and_switchable_from_the_config():
    on = build_model(load_config(None, ["model.backbone.name=efficientnet-b0", "data.image_size=[64,96]"]))
    off = build_model(load_config(None, ["model.backbone.name=efficientnet-b0", "data.image_size=[64,96]",
                                         "model.backbone.grad_checkpoint=false"]))
    assert on.backbone.grad_checkpoint is True and off.backbone.grad_checkpoint is False


def test_imagenet_weights_load_from_a_local_file_and_bad_files_are_user_errors(tmp_path):
    torch.manual_seed(0)
    reference = EfficientNet.from_name("efficientnet-b0")
    good = tmp_path / "b0.pth"
    torch.save(reference.state_dict(), good)  # the package's format, classifier head included
    cfg = load_config(None, ["model.backbone.name=efficientnet-b0", f"model.backbone.weights={good}",
                             "model.gnn.layers=0", "model.bev_heads.stage_channels=[8]",
                             "model.bev_heads.channels=8", "model.bev_heads.head_channels=8"])
    # the weights are loaded when training starts (pretrained=True), not by every build (evaluation,
    # model-summary, export load a checkpoint or need none)
    assert not torch.equal(build_model(cfg).backbone.trunk._blocks[3]._depthwise_conv.weight,
                           reference._blocks[3]._depthwise_conv.weight)
    model = build_model(cfg, pretrained=True)
    torch.testing.assert_close(model.backbone.trunk._blocks[3]._depthwise_conv.weight,
                               reference._blocks[3]._depthwise_conv.weight)
    backbone = model.backbone

    with pytest.raises(UserError, match="not found"):
        backbone.load_imagenet_weights(tmp_path / "absent.pth")
    wrong_keys = tmp_path / "wrong_keys.pth"
    torch.save({"conv.weight": torch.zeros(3)}, wrong_keys)
    with pytest.raises(UserError, match="missing"):
        backbone.load_imagenet_weights(wrong_keys)
    b4 = tmp_path / "b4.pth"
    torch.save(EfficientNet.from_name("efficientnet-b4").state_dict(), b4)
    with pytest.raises(UserError, match="model.backbone.weights"):
        backbone.load_imagenet_weights(b4)
    garbage = tmp_path / "garbage.pth"
    garbage.write_text("not a checkpoint")
    with pytest.raises(UserError, match="cannot read"):
        backbone.load_imagenet_weights(garbage)


def _with(cfg, section: str, **changes):
    """Bypass load_config's validation to hand build_model a bad value directly."""
    parts = section.split(".")
    objs = [cfg]
    for p in parts:
        objs.append(getattr(objs[-1], p))
    new = dataclasses.replace(objs[-1], **changes)
    for obj, name in zip(reversed(objs[:-1]), reversed(parts)):
        new = dataclasses.replace(obj, **{name: new})
    return new


@pytest.mark.parametrize(
    "section,changes,key",
    [
        ("model.backbone", {"name": "resnet-50"}, "model.backbone.name"),
        ("grid", {"cell_size": 3}, "grid.cell_size"),  # 64 x 32 is not divisible by 3
        ("model.gnn", {"num_vertices": 0}, "model.gnn.num_vertices"),
        ("data", {"image_size": (64, 150)}, "data.image_size"),
        ("model.gnn", {"embedding": "vd"}, "model.gnn.embedding"),
        ("model.gnn", {"heads": 5}, "model.gnn.heads"),
        ("model.view_transform", {"kind": "mlp", "mlp_bev_downsample": 7}, "model.view_transform.mlp_bev_downsample"),
    ],
)
def test_bad_configs_fail_at_build_time_naming_the_key(section, changes, key):
    with pytest.raises(ConfigError, match=re.escape(key)):
        build_model(_with(tiny_cfg(), section, **changes))


def test_paper_parameter_counts_match_tables_iv_and_v():
    def total(path, *overrides):
        torch.manual_seed(0)
        return sum(p.numel() for p in build_model(load_config(REPO / "configs/paper" / path, list(overrides)))
                   .parameters())

    lss = total("table5_lss.yaml")
    assert abs(lss / 30.7e6 - 1) < 0.05, lss
    mlp = total("table5_mlp.yaml")
    assert abs(mlp / 95.5e6 - 1) < 0.05, mlp
    per_layer = (mlp - total("table4_gnn_layers0.yaml")) / 7
    assert abs(per_layer / 0.66e6 - 1) < 0.02, per_layer


def test_model_summary_lists_components_and_total():
    text = summarize_parameters(tiny_model())
    for word in ("backbone", "view_transform", "bev_heads", "graph_head", "gnn (2 layers", "total"):
        assert word in text


@pytest.mark.parametrize("radius", [0.0, 1.5, 3.0, 5.0])
def test_neighbour_suppression_equals_a_loop_over_cells(radius):
    """Batched cross-cell suppression against a plain loop: a cell winner is dropped iff a stronger
    winner (ties: lower flat index) of one of its 8 neighbouring cells lies within ``radius`` px;
    radius 0 keeps the one-vertex-per-cell extraction unchanged."""
    gen = torch.Generator().manual_seed(5)
    B, S, Hc, Wc = 2, 4, 5, 7
    logits = torch.randn(B, S * S + 1, Hc, Wc, generator=gen) * 3
    logits[0, :, 2, 3] = logits[0, :, 2, 4]  # a tie between neighbours
    out = extract_vertices(logits, S, num_vertices=Hc * Wc, threshold=0.0, nms_radius=radius)
    probs = logits.softmax(1)[:, :-1]
    best, pos = probs.max(1)
    for b in range(B):
        keep = set()
        for r in range(Hc):
            for c in range(Wc):
                u, v = c * S + int(pos[b, r, c]) % S, r * S + int(pos[b, r, c]) // S
                gone = False
                for dr in (-1, 0, 1):
                    for dc in (-1, 0, 1):
                        rr, cc = r + dr, c + dc
                        if (dr, dc) == (0, 0) or not (0 <= rr < Hc and 0 <= cc < Wc):
                            continue
                        nu, nv = cc * S + int(pos[b, rr, cc]) % S, rr * S + int(pos[b, rr, cc]) // S
                        stronger = best[b, rr, cc] > best[b, r, c] or (
                            best[b, rr, cc] == best[b, r, c] and rr * Wc + cc < r * Wc + c)
                        if radius > 0 and stronger and (nu - u) ** 2 + (nv - v) ** 2 <= radius**2:
                            gone = True
                if not gone:
                    keep.add((u, v))
        got = {tuple(int(x) for x in p) for p, m in zip(out["vertices_px"][b], out["mask"][b]) if m}
        assert got == keep
    if radius == 0:
        plain = extract_vertices(logits, S, num_vertices=Hc * Wc, threshold=0.0)
        for k in plain:
            assert torch.equal(plain[k], out[k])


# ---------------------------------------------------------------------------------------------
# Paper fidelity: SuperPoint NMS, no distance head, the official visual descriptor,
# ImageNet weights
# ---------------------------------------------------------------------------------------------


def _loop_superpoint_nms(scores: torch.Tensor, r: int) -> torch.Tensor:
    """SuperPoint's simple_nms written as loops over pixels: maxima of the (2r+1)^2 window, then twice
    the maxima of what lies beyond r (Chebyshev) of every kept pixel."""
    H, W = scores.shape

    def window_max(x, i, j):
        return x[max(0, i - r):i + r + 1, max(0, j - r):j + r + 1].max()

    keep = torch.tensor([[bool(scores[i, j] == window_max(scores, i, j)) for j in range(W)] for i in range(H)])
    for _ in range(2):
        near = torch.tensor([[bool(window_max(keep.float(), i, j) > 0) for j in range(W)] for i in range(H)])
        rest = torch.where(near, torch.zeros_like(scores), scores)
        new = torch.tensor([[bool(rest[i, j] == window_max(rest, i, j)) for j in range(W)] for i in range(H)])
        keep = keep | (new & ~near)
    return keep


def test_superpoint_nms_equals_a_loop_and_keeps_no_two_untied_vertices_within_the_radius():
    gen = torch.Generator().manual_seed(11)
    for r in (1, 2, 4):
        scores = torch.rand(2, 13, 17, generator=gen) * (torch.rand(2, 13, 17, generator=gen) < 0.3)
        scores[0, 5, 5] = scores[0, 5, 7]  # a tie
        kept = superpoint_nms(scores, r)
        for b in range(2):
            assert torch.equal(kept[b], _loop_superpoint_nms(scores[b], r))
            pts = [(i, j) for i, j in zip(*torch.nonzero(kept[b] & (scores[b] > 0), as_tuple=True))]
            for a in pts:
                for c in pts:
                    if a != c and max(abs(int(a[0] - c[0])), abs(int(a[1] - c[1]))) <= r:
                        assert scores[b][a] == scores[b][c]


def test_running_max_equals_max_pool_with_minus_infinity_padding():
    """superpoint_nms's window max (two 1-D running maxima built by doubling) against torch's max_pool2d
    of the (2r+1)^2 window, for odd and even window sizes' powers of two, windows wider than the map,
    and negative values (which the padding must never beat)."""
    from instagram_hdmap.models.vertices import _running_max

    gen = torch.Generator().manual_seed(3)
    x = torch.randn(2, 7, 19, generator=gen) - 5.0
    for r in (0, 1, 2, 3, 4, 5, 7, 12):
        got = _running_max(_running_max(x, r, -1), r, -2)
        if 2 * r + 1 <= 7:  # max_pool2d's padding must stay within half its window and the map
            assert torch.equal(got, torch.nn.functional.max_pool2d(x[:, None], 2 * r + 1, stride=1, padding=r)[:, 0])
        for i, j in ((0, 0), (3, 9), (6, 18)):  # the loop definition, any r (max_pool2d pads at most k/2)
            window = x[:, max(0, i - r): i + r + 1, max(0, j - r): j + r + 1]
            assert torch.equal(got[:, i, j], window.amax(dim=(1, 2))), (r, i, j)


def _cell_winners(S: int, Hc: int, Wc: int, winners: dict) -> torch.Tensor:
    """Vertex logits whose cell (r, c) has its maximum at pixel offset (dy, dx) with the probability given
    in ``winners[(r, c)] = (dy, dx, p)`` (empty cells ~ 1/(S*S+1) everywhere)."""
    logits = torch.zeros(1, S * S + 1, Hc, Wc)
    for (r, c), (dy, dx, p) in winners.items():
        others = math.log((1 - p) / (S * S))  # the other S*S channels share 1 - p
        logits[0, :, r, c] = others
        logits[0, dy * S + dx, r, c] = math.log(p)
    return logits


def test_superpoint_nms_brings_back_a_vertex_whose_suppressor_was_suppressed():
    """Winners A (0.9) at u = 3, B (0.8) at u = 6, C (0.7) at u = 9 on one row, radius 4: B lies within 4 px
    of A and goes; C lies within 4 px of B only, which is gone, so SuperPoint NMS keeps it (the official
    rule). Our 'cells' rule drops C for its stronger neighbour B."""
    S = 4
    logits = _cell_winners(S, 2, 4, {(0, 0): (1, 3, 0.9), (0, 1): (1, 2, 0.8), (0, 2): (1, 1, 0.7)})
    kept = {}
    for nms in ("superpoint", "cells"):
        out = extract_vertices(logits, S, num_vertices=8, threshold=0.1, nms_radius=4, nms=nms)
        kept[nms] = sorted(int(u) for (u, v), m in zip(out["vertices_px"][0], out["mask"][0]) if m)
    assert kept == {"superpoint": [3, 9], "cells": [3]}
    plain = extract_vertices(logits, S, num_vertices=8, threshold=0.1)
    assert int(plain["mask"].sum()) == 3


def test_the_paper_configs_extract_vertices_with_the_official_nms():
    cfg = load_config(REPO / "configs/paper/table1_b4_lss_128x352.yaml")
    assert (cfg.model.gnn.nms, cfg.model.gnn.nms_radius) == ("superpoint", cfg.grid.cell_size // 2)
    with pytest.raises(ConfigError, match="model.gnn.nms_radius"):
        build_model(tiny_cfg("model.gnn.nms=superpoint", "model.gnn.nms_radius=1.5"))
    model = tiny_model("model.gnn.nms=superpoint", "model.gnn.nms_radius=2").eval()
    assert model.graph_head.nms == "superpoint"
    with torch.no_grad():
        out = model(make_batch(tiny_cfg()))
    assert out["pred_vertex_mask"].any()


def test_a_model_without_a_distance_head_builds_runs_and_trains_every_parameter():
    cfg = tiny_cfg("model.bev_heads.distance_head=false", "model.gnn.embedding=pe+vd", "model.gnn.vd_sampling=cell")
    torch.manual_seed(0)
    model = build_model(cfg).train()
    assert model.bev_heads.distance_head is None
    with_head = tiny_model("model.gnn.embedding=pe+vd")
    n_head = sum(p.numel() for p in with_head.bev_heads.distance_head.parameters())
    assert sum(p.numel() for p in with_head.parameters()) - sum(p.numel() for p in model.parameters()) == n_head
    for name, p in model.named_parameters():
        if name.endswith("bn2.weight"):
            torch.nn.init.ones_(p)
    out = model(make_batch(cfg))
    assert "pred_distance" not in out and set(OUTPUT_KEYS) - set(out) == {"pred_distance"}
    mask = out["pred_vertex_mask"]
    pair = mask[:, :, None] & mask[:, None, :]
    loss = (out["pred_vertex_logits"].logsumexp(1).mean() + out["pred_class_log_probs"][mask].mean()
            + out["pred_log_assignment"][:, :-1, :-1][pair].mean()
            + out["pred_log_assignment"][:, :-1, -1][mask].mean())
    loss.backward()
    assert not [n for n, p in model.named_parameters() if p.grad is None or not (p.grad != 0).any()]
    for embedding in ("pe+dt", "dt"):  # those read the distance transform
        with pytest.raises(ConfigError, match="model.bev_heads.distance_head"):
            build_model(tiny_cfg("model.bev_heads.distance_head=false", f"model.gnn.embedding={embedding}"))


def test_the_official_visual_descriptor_is_the_bev_feature_of_the_vertex_cell():
    """vd_sampling=cell: F_bev resized to the cell grid (bilinear, align_corners=True, as the official
    F.interpolate(scale_factor=0.25) at S = 8) and read at the vertex's cell."""
    gen = torch.Generator().manual_seed(2)
    B, C, Hc, Wc, S = 2, 5, 3, 4, 8
    features = torch.randn(B, C, Hc * S // 2, Wc * S // 2, generator=gen)  # F_bev at H/2
    cells = torch.randint(0, Hc * Wc, (B, 6), generator=gen)
    got = cell_features(features, cells, Hc, Wc)
    official = torch.nn.functional.interpolate(features, scale_factor=0.25, mode="bilinear", align_corners=True)
    for b in range(B):
        for n in range(6):
            r, c = divmod(int(cells[b, n]), Wc)
            torch.testing.assert_close(got[b, n], official[b, :, r, c])


def test_imagenet_weights_download_through_an_injectable_function_and_fail_in_one_line(tmp_path):
    """model.backbone.weights=imagenet: the state dict comes from ``download(name)`` (efficientnet_pytorch's
    release through torch's hub cache by default; never the network here); without a network the error
    is one line that says how to give a local file; a local path keeps working."""
    cfg = load_config(None, ["model.backbone.name=efficientnet-b0", "model.backbone.weights=imagenet",
                             "data.image_size=[64,96]", "model.gnn.layers=0", "model.bev_heads.stage_channels=[8]",
                             "model.bev_heads.channels=8", "model.bev_heads.head_channels=8"])
    torch.manual_seed(1)
    reference = EfficientNet.from_name("efficientnet-b0")
    asked = []

    def download(name):
        asked.append(name)
        return reference.state_dict()

    model = build_model(cfg, pretrained=True, download=download)
    assert asked == ["efficientnet-b0"]
    torch.testing.assert_close(model.backbone.trunk._blocks[5]._depthwise_conv.weight,
                               reference._blocks[5]._depthwise_conv.weight)
    assert build_model(cfg, download=download) is not None and asked == ["efficientnet-b0"]  # not pretrained: no call

    def offline(name):
        raise OSError("<urlopen error [Errno -3] Temporary failure\n in name resolution>")

    with pytest.raises(UserError) as err:
        build_model(cfg, pretrained=True, download=offline)
    message = str(err.value)
    assert "\n" not in message and "model.backbone.weights=imagenet" in message
    assert "model.backbone.weights=/path/to/efficientnet-b0.pth" in message and "Temporary failure" in message
    local = tmp_path / "b0.pth"
    torch.save(reference.state_dict(), local)
    backbone = build_model(load_config(None, ["model.backbone.name=efficientnet-b0", f"model.backbone.weights={local}",
                                              "data.image_size=[64,96]"])).backbone
    load_pretrained_backbone(backbone, str(local), download=offline)  # a path never downloads
    torch.testing.assert_close(backbone.trunk._conv_stem.weight, reference._conv_stem.weight)
    with pytest.raises(ConfigError, match="model.backbone.from_scratch"):
        build_model(load_config(None, ["model.backbone.weights=imagenet", "model.backbone.from_scratch=true"]))
