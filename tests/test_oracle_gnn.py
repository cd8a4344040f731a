"""The GNN oracle (instagram_hdmap.oracle, benchmarks/oracle_gnn.py) on the tiny synthetic world."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from instagram_hdmap import oracle
from instagram_hdmap.assignment import assign_batch, target_log_assignment
from instagram_hdmap.config import ConfigError, load_config
from instagram_hdmap.geometry import BEVGrid
from instagram_hdmap.inference import gt_outputs
from instagram_hdmap.models import build_model
from instagram_hdmap.postprocess import postprocess_batch

TINY_YAML = Path(__file__).resolve().parents[1] / "configs" / "synthetic" / "tiny.yaml"


@pytest.fixture(scope="module")
def cfg(tiny_world, world_overrides):
    return load_config(TINY_YAML, world_overrides(tiny_world))


@pytest.fixture(scope="module")
def samples(cfg):
    return oracle.load_targets(cfg, cfg.data.train_split)


@pytest.fixture(scope="module")
def paper_grid_cfg(tiny_world, world_overrides):
    """The tiny graph head on the paper's grid (60 m x 30 m at 0.15 m, S = 8, N = 400): the tiny world's
    train maps then hold dividers, boundaries and closed ped crossings (each crossing its own ring)."""
    return load_config(TINY_YAML, [*world_overrides(tiny_world), "grid.xbound=[-30.0,30.0]", "grid.ybound=[-15.0,15.0]",
                                   "grid.resolution=0.15", "grid.cell_size=8", "model.gnn.num_vertices=400",
                                   "data.ped_crossing=each"])


@pytest.fixture(scope="module")
def head(cfg):
    torch.manual_seed(0)
    return build_model(cfg).graph_head.eval()


def _vertex_set(px: torch.Tensor) -> set[tuple[int, int]]:
    return {tuple(v) for v in px.round().long().tolist()}


def _canonical(polylines: list[dict]) -> list[tuple]:
    """Polylines up to start point and direction (a traced instance may start at either end)."""
    out = []
    for p in polylines:
        pts = [tuple(np.round(q, 4)) for q in np.asarray(p["pts"])]
        if p["closed"]:
            ring = pts[:-1]
            variants = [ring[i:] + ring[:i] for i in range(len(ring))]
            variants += [v[::-1] for v in variants]
        else:
            variants = [pts, pts[::-1]]
        out.append((p["label"], p["closed"], min(variants)))
    return sorted(out)


def test_extracted_vertices_are_exactly_the_gt_vertices(cfg, samples, head):
    batch = oracle.collate_targets(samples[:4])
    vertices, _ = oracle.oracle_vertices(batch, head)
    mask = vertices["mask"]
    assert mask.shape[1] == max(1, int(batch["gt_vertex_mask"].sum(1).max()))  # cut to the largest real count
    for b in range(len(mask)):
        gt = batch["gt_vertices_px"][b][batch["gt_vertex_mask"][b]]
        assert int(mask[b].sum()) == len(gt)
        assert _vertex_set(vertices["vertices_px"][b][mask[b]]) == _vertex_set(gt)
        assert torch.all(vertices["scores"][b][mask[b]] > 0.99)


def test_cutting_the_padding_changes_no_real_output(cfg, samples, head):
    batch = oracle.collate_targets(samples[:3])
    with torch.no_grad():
        cut = oracle.oracle_forward(head, batch)
        full_vertices = head.extract(gt_outputs(batch, head.grid, 3)["pred_vertex_logits"])  # N = num_vertices
        full = head.associate(full_vertices, batch["gt_distance"], batch["gt_distance"].new_zeros(3, 0, 1, 1))
    n, N = cut["pred_vertex_mask"].shape[1], head.num_vertices
    assert n < N
    for b in range(3):
        real = cut["pred_vertex_mask"][b]
        idx = torch.nonzero(real).flatten()
        cut_rows = cut["pred_log_assignment"][b][idx][:, torch.cat([idx, idx.new_tensor([n])])]
        full_rows = full["pred_log_assignment"][b][idx][:, torch.cat([idx, idx.new_tensor([N])])]
        torch.testing.assert_close(cut_rows, full_rows, rtol=1e-4, atol=1e-4)
        torch.testing.assert_close(cut["pred_class_log_probs"][b][idx], full["pred_class_log_probs"][b][idx])


def test_gt_adjacency_on_the_oracle_vertices_decodes_the_gt_graph(paper_grid_cfg):
    """A perfect graph head on the oracle's inputs (the GT adjacency of the extracted vertices, log of
    the exact target distribution) gives back the GT graph's polylines, open and closed; on these maps
    the GT graph decodes to the GT map: AP 1 for every class."""
    cfg = paper_grid_cfg
    samples = oracle.load_targets(cfg, cfg.data.train_split)
    torch.manual_seed(0)
    head = build_model(cfg).graph_head.eval()
    grid = BEVGrid.from_config(cfg.grid)
    batch = oracle.collate_targets(samples)
    with torch.no_grad():
        outputs = oracle.oracle_forward(head, batch)
    asg = assign_batch(outputs, batch, grid, cfg.loss.match_dist)
    outputs["pred_log_assignment"] = target_log_assignment(asg["target_next"], asg["target_prev"])
    labels = asg["target_class"].clamp(min=0)
    outputs["pred_class_log_probs"] = torch.nn.functional.one_hot(labels, 3).float().clamp(min=1e-6).log()
    ours = postprocess_batch(outputs, grid, cfg.model.gnn.match_threshold)
    reference = postprocess_batch(gt_outputs(batch, grid, 3), grid, cfg.model.gnn.match_threshold)
    assert {(p["label"], p["closed"]) for s in ours for p in s} >= {(0, False), (1, True), (2, False)}
    for a, b in zip(ours, reference):
        assert _canonical(a) == _canonical(b)
    bound = oracle.evaluate_oracle(cfg, samples, None)
    assert all(bound["num_gt"][c] > 0 for c in cfg.data.classes)
    assert bound["mAP"] == pytest.approx(1.0)
    assert bound["diagnostics"]["adjacency_accuracy"] == pytest.approx(1.0)


def test_run_oracle_end_to_end(cfg, samples):
    torch.manual_seed(0)
    result = oracle.run_oracle(cfg, steps=3, batch_size=2, progress=False)
    assert result["train"]["steps"] == 3 and result["train"]["history"][-1]["step"] == 3
    assert result["num_train"] == 4 * len(samples)  # four mirror images of each training map
    for key in ("oracle", "upper_bound"):
        m = result[key]
        assert m["protocol"] == "vector" and m["thresholds"] == [0.5, 1.0, 1.5]
        assert set(m["AP"]) == set(cfg.data.classes) and all(len(v) == 3 for v in m["AP"].values())
        assert 0.0 <= m["mAP"] <= 1.0
        d = m["diagnostics"]
        assert all(math.isfinite(d[k]) for k in oracle.DIAGNOSTICS)
        for c in cfg.data.classes:  # per-class accuracy defined exactly where the class has vertices
            assert math.isfinite(d["adjacency_accuracy_class"][c]) == (d["vertices_class"][c] > 0)
    assert result["upper_bound"]["diagnostics"]["adjacency_accuracy"] == pytest.approx(1.0)


def test_training_fits_the_adjacency_of_a_few_maps(cfg, samples):
    """On two maps, a few dozen Adam steps raise the vertex adjacency accuracy well above its start."""
    torch.manual_seed(0)
    head = build_model(cfg).graph_head
    before = oracle.evaluate_oracle(cfg, samples[:2], head)["diagnostics"]
    oracle.train_oracle(cfg, head, samples[:2], steps=40, batch_size=2, lr=3e-3, progress=False)
    after = oracle.evaluate_oracle(cfg, samples[:2], head)["diagnostics"]
    assert after["loss_adjacency"] < before["loss_adjacency"] - 0.5
    assert after["adjacency_accuracy"] > max(0.8, before["adjacency_accuracy"] + 0.3)


def test_epoch_batches_cover_every_sample_once_with_less_padding():
    rng = np.random.default_rng(0)
    sizes = rng.integers(20, 200, 203)
    batches = oracle.epoch_batches(sizes, 16, rng)
    assert sorted(np.concatenate(batches).tolist()) == list(range(203))
    assert all(len(b) <= 16 for b in batches)
    padded = np.mean([sizes[b].max() for b in batches if len(b) == 16])
    random_padded = np.mean([sizes[p].max() for p in np.array_split(rng.permutation(203)[:192], 12)])
    assert padded < random_padded


def test_mirroring_needs_a_centred_grid_and_vd_needs_features(cfg):
    off = load_config(TINY_YAML, ["grid.xbound=[0.0, 16.0]"])
    with pytest.raises(ConfigError, match="centred"):
        oracle.check_mirror_grid(BEVGrid.from_config(off.grid))
    vd = load_config(TINY_YAML, ["model.gnn.embedding=pe+vd"])
    with pytest.raises(ConfigError, match="pe\\+vd"):
        oracle.check_oracle_config(vd)
    pts = np.array([[1.0, 2.0], [3.0, -4.0]])
    mirrored = oracle.mirror_polylines([{"pts": pts, "label": 0, "closed": False}], -1, 1)
    assert np.array_equal(mirrored[0]["pts"], [[-1.0, 2.0], [-3.0, -4.0]])
