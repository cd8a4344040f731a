"""Training acceptance: the tiny config memorises four synthetic samples on the CPU, and the
training-speed benchmark's code path runs.

The functions are the benchmarks' own (benchmarks/overfit.py ``run_overfit``, benchmarks/train_speed.py
``measure_training``) with smaller budgets; the overfit samples are the first four train samples of
the session's ``tiny_world``.
"""

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from instagram_hdmap.config import UserError, load_config
from instagram_hdmap.geometry import BEVGrid
from overfit import ADJACENCY_TARGET, LOSS_DROP_TARGET, TINY_CONFIG, overfit_batch, run_overfit
from train_speed import format_cpu_table, format_gpu_table, measure_training, plausible_map, training_batch


@pytest.fixture(scope="module")
def overfit_cfg(tiny_world, world_overrides):
    return load_config(TINY_CONFIG, [*world_overrides(tiny_world), "data.augment=false", "data.num_workers=0"])


@pytest.fixture
def one_thread():
    """One torch thread: on the shared 2-core machine, 2 spinning OpenMP threads make a step many times slower."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def test_tiny_config_overfits_four_synthetic_samples(overfit_cfg, one_thread):
    batch = overfit_batch(overfit_cfg, 4)
    assert batch["images"].shape[0] == 4 and bool(batch["gt_vertex_mask"].any(1).all())
    lines: list[str] = []
    result = run_overfit(overfit_cfg, batch, steps=200, lr=3e-3, every=20, echo=lines.append)
    print("\n".join(lines))  # the table, shown with pytest -s
    print(f"loss drop {100 * result['loss_drop']:.1f} %, adjacency accuracy {100 * result['adjacency_accuracy']:.1f} %")
    assert result["rows"][0]["step"] == 1 and result["rows"][-1]["step"] == 200
    assert result["loss_drop"] >= LOSS_DROP_TARGET
    assert result["adjacency_accuracy"] >= ADJACENCY_TARGET
    # the accuracy is over predicted vertices that represent GT vertices: most GT vertices must have one
    assert result["final_eval"]["gt_vertex_recall"] >= 0.9
    assert all(result["passed"].values())


def test_asking_for_more_samples_than_the_split_holds_is_a_user_error(overfit_cfg):
    with pytest.raises(UserError, match="fewer than the 99"):
        overfit_batch(overfit_cfg, 99)


def test_train_speed_map_is_inside_the_grid_and_gives_real_graph_targets():
    cfg = load_config(TINY_CONFIG.parents[1] / "paper" / "table1_b0_lss_128x352.yaml")
    grid = BEVGrid.from_config(cfg.grid)
    polylines = plausible_map(grid, cfg.data.sample_dist, np.random.default_rng(0))
    assert {p["label"] for p in polylines} == {0, 1, 2}
    for p in polylines:
        assert grid.inside_m(p["pts"]).all()
        assert not p["closed"] or (len(p["pts"]) >= 4 and np.allclose(p["pts"][0], p["pts"][-1]))
    batch = training_batch(cfg, 2, seed=1)
    assert batch["images"].shape == (2, 6, 3, *cfg.data.image_size)
    M = batch["gt_vertex_mask"].sum(1)
    assert (M > 150).all() and M[0] != M[1]  # a busy junction, a different pose per sample
    assert (batch["gt_vertex_next"][batch["gt_vertex_mask"]] >= 0).float().mean() > 0.8  # mostly chains


def test_train_speed_measures_fp32_and_bf16_steps_on_the_tiny_config(one_thread):
    cfg = load_config(TINY_CONFIG)
    rows = []
    for amp in ("none", "bf16"):
        r = measure_training(cfg, 2, steps=2, warmup=1, device="cpu", amp=amp)
        assert 0 < r["p10_s"] <= r["step_s"] <= r["p90_s"] and r["cpu_s"] > 0 and r["peak_rss_gb"] > 0
        assert r["peak_allocated_gb"] is None and r["threads"] == torch.get_num_threads()
        assert all(math.isfinite(v) for v in r["losses"].values()) and r["losses"]["loss_adjacency"] > 0
        rows.append({"config": str(TINY_CONFIG), **r})
    rows.append({"config": "configs/paper/table1_b4_lss_128x352.yaml", "batch": 1, "amp": "none", "ckpt": "on",
                 "error": "boom"})
    for table in (format_cpu_table(rows), format_gpu_table(rows)):
        assert table.count("tiny") == 2 and "failed: boom" in table
