"""predict.py, benchmark.py and the ``evaluate`` / ``predict`` / ``benchmark`` subcommands:
GT-derived predictions, checkpoint config resolution, end-to-end runs on a tiny synthetic world,
the PNGs, the FPS table and the one-line user errors."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from instagram_hdmap.checkpoint import CheckpointError, save_checkpoint
from instagram_hdmap.cli import main
from instagram_hdmap.config import config_to_dict, load_config
from instagram_hdmap.data.base import collate_fn
from instagram_hdmap.geometry import BEVGrid
from instagram_hdmap.inference import gt_outputs, inference_config
from instagram_hdmap.postprocess import postprocess_batch
from instagram_hdmap.predict import adjacency_edges
from instagram_hdmap.targets import build_targets, graph_to_polylines

TINY_YAML = Path(__file__).resolve().parents[1] / "configs" / "synthetic" / "tiny.yaml"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
PNGS = ("prediction_bev.png", "prediction_cameras.png", "prediction_intermediate.png")
K = 3


# --- a tiny synthetic world, a config for it and a random checkpoint ----------------------------------


@pytest.fixture(scope="module")
def world(tiny_world, world_overrides) -> list[str]:
    """Overrides pointing the tiny config at the session's tiny synthetic world (tests/conftest.py)."""
    return [*world_overrides(tiny_world), "data.num_workers=0", "train.device=cpu", "eval.batch_size=2"]


@pytest.fixture(scope="module")
def checkpoint(world, tmp_path_factory) -> Path:
    """A randomly initialised tiny model saved as a checkpoint with its config."""
    from instagram_hdmap.models import build_model

    torch.manual_seed(0)
    cfg = load_config(TINY_YAML, world)
    path = tmp_path_factory.mktemp("ckpt") / "random.pt"
    save_checkpoint({"model": build_model(cfg).state_dict(), "config": config_to_dict(cfg)}, path)
    return path


def _is_png(path: Path) -> bool:
    data = path.read_bytes()
    return len(data) > 1000 and data[:8] == PNG_MAGIC


# --- GT-derived predictions (no dataset needed) -------------------------------------------------------


def _sample(cfg, polylines: list[dict], token: str) -> dict:
    grid = BEVGrid.from_config(cfg.grid)
    return {"sample_token": token, "gt_polylines": polylines,
            **build_targets(polylines, grid, K, cfg.data.dt_clip)}


def _toy_polylines(seed: int) -> list[dict]:
    rng = np.random.default_rng(seed)
    x = np.linspace(-7.5, 7.5, 11)
    polys = [{"pts": np.stack([x, np.full_like(x, rng.uniform(-3, 3))], 1), "label": 0, "closed": False},
             {"pts": np.stack([x, 3.5 + 0.02 * x**2 * rng.uniform(-1, 1)], 1), "label": 2, "closed": False}]
    if seed % 2 == 0:  # a closed crossing, first point repeated
        x0 = rng.uniform(-6, 2)
        polys.append({"pts": np.array([[x0, -3.5], [x0 + 3, -3.5], [x0 + 3, -1], [x0, -1], [x0, -3.5]]),
                      "label": 1, "closed": True})
    return polys


def _canonical(poly: dict) -> tuple:
    pts = [tuple(p) for p in np.round(np.asarray(poly["pts"], dtype=np.float64), 4)]
    if poly["closed"]:
        ring = pts[:-1]
        rots = [ring[i:] + ring[:i] for i in range(len(ring))]
        pts = min(min(rots), min(r[::-1] for r in rots))
    else:
        pts = min(pts, pts[::-1])
    return (int(poly["label"]), bool(poly["closed"]), tuple(pts))


# (no max_edge_px: the toy crossings' sides are 3 m long, unresampled)
DECODERS = [{"decoder": "greedy"}, {"decoder": "mutual"},
            {"decoder": "classwise", "match_threshold": 0.02, "class_min_prob": 0.05}]


@pytest.mark.parametrize("decode", DECODERS, ids=[d["decoder"] for d in DECODERS])
def test_gt_outputs_post_process_to_the_gt_graph_and_padding_changes_nothing(decode):
    cfg = load_config(TINY_YAML)
    grid = BEVGrid.from_config(cfg.grid)
    samples = [_sample(cfg, _toy_polylines(s), f"t{s}") for s in range(3)]
    # batched (padded to the largest M) equals one by one, and equals the GT graph's polylines
    batched = postprocess_batch(gt_outputs(collate_fn(samples), grid, K), grid, **decode)
    for b, s in enumerate(samples):
        single = postprocess_batch(gt_outputs(collate_fn([s]), grid, K), grid, **decode)[0]
        expect = graph_to_polylines(grid.px_to_m(s["gt_vertices_px"].double().numpy()), s["gt_vertex_labels"],
                                    s["gt_vertex_next"])
        assert sorted(map(_canonical, batched[b])) == sorted(map(_canonical, single))
        assert sorted(map(_canonical, single)) == sorted(map(_canonical, expect))
        assert all(math.isclose(p["score"], 1.0, rel_tol=1e-4) for p in single)
        assert any(p["closed"] for p in single) == (b % 2 == 0)
    out = gt_outputs(collate_fn(samples[:1]), grid, K)
    assert out["pred_heatmap"].shape == (1, grid.H, grid.W)
    assert torch.equal(out["pred_heatmap"][0] > 0.5, _vertex_pixels(samples[0]["gt_vertices_px"], grid))


@pytest.mark.parametrize("decode", DECODERS, ids=[d["decoder"] for d in DECODERS])
def test_diagnostics_of_a_perfect_model_are_all_ones(decode):
    """ClassDiagnostics on the GT-derived outputs: every vertex found and right, the distance transform
    exact, every edge decoded, every instance whole and every crossing a closed cycle, per decoder."""
    from instagram_hdmap.diagnostics import ClassDiagnostics
    from instagram_hdmap.losses import Criterion

    cfg = load_config(TINY_YAML)
    grid = BEVGrid.from_config(cfg.grid)
    batch = collate_fn([_sample(cfg, _toy_polylines(s), f"t{s}") for s in range(4)])
    outputs = gt_outputs(batch, grid, K)
    diag = ClassDiagnostics(K, cfg.data.dt_clip, {"match_threshold": 0.1, **decode})
    diag.update(outputs, batch, Criterion(cfg.loss, grid).assign(outputs, batch))
    res = diag.compute()
    assert res["dt_error_px"] == pytest.approx([0.0] * K, abs=1e-5)
    for name in ("vertex_recall", "vertex_precision", "dt_line_recall", "adjacency_accuracy", "edge_recall",
                 "instance_complete"):
        assert res[name] == pytest.approx([1.0] * K), name
    assert res["closed_as_cycle"][1] == 1.0 and res["counts"]["closed_as_cycle"][1] == 2  # the two crossings


def _vertex_pixels(vertices_px: torch.Tensor, grid: BEVGrid) -> torch.Tensor:
    img = torch.zeros(grid.H, grid.W, dtype=torch.bool)
    uv = vertices_px.round().long()
    img[uv[:, 1], uv[:, 0]] = True
    return img


def test_gt_outputs_and_pictures_of_an_empty_map(tmp_path):
    from instagram_hdmap.visualize import intermediate_figure, prediction_bev_figure, save_figure

    cfg = load_config(TINY_YAML)
    grid = BEVGrid.from_config(cfg.grid)
    out = gt_outputs(collate_fn([_sample(cfg, [], "empty")]), grid, K)
    assert postprocess_batch(out, grid) == [[]]
    edges, kept = adjacency_edges(out["pred_log_assignment"][0], out["pred_vertex_mask"][0], 0.1,
                                  torch.zeros(0, 2, dtype=torch.long))
    assert edges.shape == (0, 2) and kept.shape == (0,)
    mask = out["pred_vertex_mask"][0]
    figs = {"bev.png": prediction_bev_figure([], [], grid),
            "inter.png": intermediate_figure(out["pred_heatmap"][0], out["pred_distance"][0],
                                             out["pred_vertices_px"][0][mask], torch.zeros(0), edges, kept, grid),
            # a model without a distance head (configs/paper/fig7_vd_*): no distance panels
            "inter_no_dt.png": intermediate_figure(out["pred_heatmap"][0], None, out["pred_vertices_px"][0][mask],
                                                   torch.zeros(0), edges, kept, grid)}
    assert len(figs["inter_no_dt.png"].axes) < len(figs["inter.png"].axes)
    for name, fig in figs.items():
        assert _is_png(save_figure(fig, tmp_path / name))


def test_adjacency_edges_marks_the_mutual_edges():
    # 4 real vertices + 1 padding, N = 5: chain 0-1-2 (mutual), 2 -> 3 one-sided (3 prefers the dustbin)
    N = 5
    P = torch.full((N + 1, N + 1), 1e-4)
    P[0, 1] = P[0, N] = 0.5
    P[1, 0] = P[1, 2] = 0.5
    P[2, 1] = 0.5
    P[2, 3] = 0.3
    P[3, N] = 0.9
    mask = torch.tensor([True, True, True, True, False])
    neighbours = torch.tensor([[1, -1], [0, 2], [1, -1], [-1, -1], [-1, -1]])
    edges, kept = adjacency_edges(P.log(), mask, 0.1, neighbours)
    assert {tuple(e): bool(k) for e, k in zip(edges.tolist(), kept)} == {(0, 1): True, (1, 2): True, (2, 3): False}


# --- config resolution ---------------------------------------------------------------------------------


def test_checkpoint_config_wins_over_the_config_file_and_overrides_win_over_both():
    trained = load_config(TINY_YAML, ["model.gnn.layers=2"])
    file_cfg = load_config(TINY_YAML, ["model.gnn.layers=5", "data.dataroot=/somewhere"])
    cfg, notes = inference_config(file_cfg, config_to_dict(trained), ["model.gnn.num_vertices=32"])
    assert cfg.model.gnn.layers == 2  # the checkpoint's
    assert cfg.model.gnn.num_vertices == 32  # the override
    assert cfg.data.dataroot == "/somewhere"  # not a model key: the CONFIG file's
    assert any("model.gnn.layers=2" in n for n in notes)
    assert any("model.gnn.num_vertices=64 with 32" in n for n in notes)


# --- end to end on the synthetic world ------------------------------------------------------------------


def test_predict_gt_as_prediction_writes_the_pictures(world, tmp_path, capsys):
    from instagram_hdmap.data.nuscenes import NuScenesMapDataset
    from instagram_hdmap.evaluation import read_submission

    token = NuScenesMapDataset(load_config(TINY_YAML, world), "val", augment=False).sample_tokens[1]
    out = tmp_path / "gt"
    assert main(["predict", str(TINY_YAML), *world, "--token", token, "--out", str(out), "--gt-as-prediction"]) == 0
    assert f"sample {token} (split 'val', index 1)" in capsys.readouterr().out
    for name in PNGS:
        assert _is_png(out / name), name
    sub = read_submission(out / "prediction.json", "pred")
    assert list(sub.samples) == [token]
    assert len(sub.samples[token]) > 0 and all(p["score"] > 0.99 for p in sub.samples[token])


def test_predict_and_evaluate_with_a_random_checkpoint(world, checkpoint, tmp_path, capsys):
    out = tmp_path / "pred"
    assert main(["predict", str(TINY_YAML), *world, "--checkpoint", str(checkpoint), "--index", "-1",
                 "--out", str(out)]) == 0
    for name in PNGS:
        assert _is_png(out / name), name

    ev = tmp_path / "eval"
    assert main(["evaluate", str(TINY_YAML), *world, "--checkpoint", str(checkpoint), "--protocol", "raster",
                 "--out", str(ev)]) == 0
    printed = capsys.readouterr().out
    assert "protocol: raster" in printed and "mAP" in printed
    metrics = json.loads((ev / "metrics.json").read_text())
    assert {"protocol", "thresholds", "classes", "AP", "AP_class", "mAP"} <= metrics.keys()
    assert metrics["protocol"] == "raster"
    assert metrics["classes"] == ["divider", "ped_crossing", "boundary"]
    assert metrics["thresholds"] == [0.5, 1.0, 1.5]
    assert all(len(metrics["AP"][c]) == 3 for c in metrics["classes"])
    assert metrics["meta"]["checkpoint"] == str(checkpoint)
    from instagram_hdmap.data.nuscenes import NuScenesMapDataset
    from instagram_hdmap.evaluation import read_submission

    val = NuScenesMapDataset(load_config(TINY_YAML, world), "val", augment=False)
    sub = read_submission(ev / "submission.json", "pred")
    assert list(sub.samples) == val.sample_tokens


def test_evaluate_scores_gt_derived_predictions_perfectly_on_classes_with_gt(world, tmp_path):
    """The submission written for GT-derived predictions, scored by evaluate-json against the split's
    GT, gives AP = 1 for every class that has GT (vector protocol)."""
    from instagram_hdmap.data.base import gt_submission
    from instagram_hdmap.data.nuscenes import NuScenesMapDataset
    from instagram_hdmap.evaluation import write_submission
    from instagram_hdmap.files import write_json

    cfg = load_config(TINY_YAML, world)
    grid = BEVGrid.from_config(cfg.grid)
    val = NuScenesMapDataset(cfg, "val", augment=False)
    results = {}
    for i in range(len(val)):
        s = val.load_sample(i)
        results[s["sample_token"]] = postprocess_batch(gt_outputs(collate_fn([s]), grid, K), grid)[0]
    write_submission(tmp_path / "pred.json", results)
    write_json(gt_submission(val), tmp_path / "gt.json")
    assert main(["evaluate-json", "--pred", str(tmp_path / "pred.json"), "--gt", str(tmp_path / "gt.json"),
                 "--out", str(tmp_path / "m.json")]) == 0
    metrics = json.loads((tmp_path / "m.json").read_text())
    with_gt = [c for c in metrics["classes"] if metrics["num_gt"][c] > 0]
    assert with_gt
    for c in with_gt:
        assert metrics["AP"][c] == pytest.approx([1.0, 1.0, 1.0]), c


# --- benchmark ------------------------------------------------------------------------------------------


def test_benchmark_prints_an_fps_table(capsys):
    assert main(["benchmark", str(TINY_YAML), "data.dataroot=/nonexistent", "--device", "cpu", "--runs", "2",
                 "--warmup", "1"]) == 0
    printed = capsys.readouterr().out
    assert "FPS" in printed and "float32" in printed and "threads:" in printed and "cpu" in printed
    rows = [line for line in printed.splitlines() if line.startswith(("model ", "model + post-processing"))]
    assert len(rows) == 2
    for row in rows:
        median, p10, p90, fps = (float(v) for v in row.split()[-5:-1])
        assert 0 < p10 <= median <= p90 and fps == pytest.approx(1000 / median, rel=0.03, abs=0.06)  # printed rounded


def test_nuscenes_like_rig_sees_the_road_ahead_in_the_front_camera():
    from instagram_hdmap.data.rig import CAMERAS, nuscenes_like_rig
    from instagram_hdmap.data.transforms import project_to_image

    h, w = 128, 352
    rig = nuscenes_like_rig((h, w))
    ahead = torch.tensor([[10.0, 0.0, 0.0]])  # on the ground, 10 m in front
    seen = []
    for v, cam in enumerate(CAMERAS):
        uv, depth = project_to_image(ahead, *(rig[k][v] for k in ("intrinsics", "cam_to_ego_rot", "cam_to_ego_trans",
                                                                  "post_rot", "post_tran")))
        if depth[0] > 0 and 0 <= uv[0, 0] < w and 0 <= uv[0, 1] < h:
            seen.append(cam)
            assert uv[0, 1] > h / 2  # below the horizon
    assert seen == ["CAM_FRONT"]


# --- bad input -------------------------------------------------------------------------------------------


def _error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert "\n" not in err
    return err


def test_missing_checkpoint_is_a_one_line_error(tmp_path, capsys):
    missing = tmp_path / "nope.pt"
    for cmd in (["evaluate", str(TINY_YAML), "--checkpoint", str(missing)],
                ["predict", str(TINY_YAML), "--checkpoint", str(missing), "--index", "0", "--out", str(tmp_path)],
                ["benchmark", str(TINY_YAML), "--checkpoint", str(missing), "--device", "cpu", "--runs", "1"]):
        assert main(cmd) == 2
        assert f"checkpoint not found: {missing}" in _error_line(capsys)


def test_bad_index_token_and_arguments_are_one_line_errors(world, checkpoint, tmp_path, capsys):
    base = ["predict", str(TINY_YAML), *world, "--out", str(tmp_path)]  # overrides right after CONFIG
    assert main([*base, "--gt-as-prediction", "--index", "99"]) == 2
    assert "--index 99 is out of range" in _error_line(capsys)
    assert main([*base, "--gt-as-prediction", "--token", "no-such-token"]) == 2
    assert "sample token 'no-such-token' is not in split 'val'" in _error_line(capsys)
    assert main([*base, "--index", "0"]) == 2
    assert "--checkpoint" in _error_line(capsys)
    assert main([*base, "--index", "0", "--gt-as-prediction", "--checkpoint", str(checkpoint)]) == 2
    assert "drop --checkpoint" in _error_line(capsys)
    # an override that changes layer sizes cannot load the weights
    assert main(["predict", str(TINY_YAML), *world, "model.gnn.dim=64", "--out", str(tmp_path), "--index", "0",
                 "--checkpoint", str(checkpoint)]) == 2
    assert "do not fit" in _error_line(capsys)


def test_benchmark_device_errors(capsys):
    if not torch.cuda.is_available():
        assert main(["benchmark", str(TINY_YAML), "--device", "cuda"]) == 2
        assert "no CUDA device" in _error_line(capsys)
    assert main(["benchmark", str(TINY_YAML), "--device", "cpu", "--runs", "0"]) == 2
    assert "--runs must be >= 1" in _error_line(capsys)


def test_a_corrupt_checkpoint_is_a_checkpoint_error(tmp_path):
    from instagram_hdmap.inference import load_model

    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="not a PyTorch checkpoint: it is a text file"):
        load_model(bad, load_config(TINY_YAML))
