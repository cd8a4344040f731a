"""Streaming temporal fusion: the single-frame model unchanged with memory off, the BEV warp on
synthetic drives with turns, the streaming sampler over 2 gloo ranks, the memory's resets and errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from instagram_hdmap.config import load_config
from instagram_hdmap.data.base import collate_fn
from instagram_hdmap.data.streaming import StreamingBatchSampler, deal_scenes
from instagram_hdmap.geometry import BEVGrid
from instagram_hdmap.models import build_model
from instagram_hdmap.models.temporal import (
    DROPPED,
    FUSED,
    MISSING_FRAME,
    NO_MEMORY,
    POSE_JUMP,
    FrameOrderError,
    relative_pose,
    render_graph,
    rigid_inverse,
    warp_bev,
)

TINY = ["model.backbone.name=tiny", "model.backbone.out_channels=16", "data.image_size=[32,64]",
        "grid.xbound=[-8.0,8.0]", "grid.ybound=[-4.0,4.0]", "grid.resolution=0.25", "grid.cell_size=4",
        "model.view_transform.depth_bound=[1.0,12.0,1.0]", "model.bev_heads.channels=32",
        "model.bev_heads.stage_channels=[16,32,32]", "model.bev_heads.head_channels=16",
        "model.gnn.num_vertices=48", "model.gnn.dim=32", "model.gnn.layers=1", "model.gnn.sinkhorn_iters=20"]


def pose(x: float, y: float, yaw: float) -> torch.Tensor:
    c, s = math.cos(yaw), math.sin(yaw)
    return torch.tensor([[c, -s, 0, x], [s, c, 0, y], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=torch.float32)


def random_batch(cfg, B: int = 2, seed: int = 0) -> dict:
    from instagram_hdmap.benchmark import nuscenes_like_rig

    rig = nuscenes_like_rig(tuple(cfg.data.image_size))
    g = torch.Generator().manual_seed(seed)
    h, w = cfg.data.image_size
    batch = {k: v[None].expand(B, *v.shape).contiguous() for k, v in rig.items()}
    batch["images"] = torch.randn(B, rig["intrinsics"].shape[0], 3, h, w, generator=g)
    batch["ego_pose"] = torch.stack([pose(10.0 * b, 0.0, 0.1 * b) for b in range(B)])
    batch["frame_index"] = torch.zeros(B, dtype=torch.long)
    batch["scene_start"] = torch.ones(B, dtype=torch.bool)
    return batch


# --- memory off: the single-frame model, bit for bit -------------------------------------------------


def test_memory_off_is_the_single_frame_model():
    torch.manual_seed(0)
    single = build_model(load_config(None, TINY)).eval()
    torch.manual_seed(0)
    off = build_model(load_config(None, [*TINY, "model.temporal.memory=none"])).eval()
    torch.manual_seed(0)
    temporal = build_model(load_config(None, [*TINY, "model.temporal.memory=bev"])).eval()
    assert not off.is_temporal and temporal.is_temporal
    # same parameters (names, shapes, values); the temporal model only adds its fusion
    assert off.state_dict().keys() == single.state_dict().keys()
    assert all(torch.equal(off.state_dict()[k], v) for k, v in single.state_dict().items())
    extra = set(temporal.state_dict()) - set(single.state_dict())
    assert extra and all(k.startswith("temporal.") for k in extra)
    assert sum(p.numel() for p in off.parameters()) == sum(p.numel() for p in single.parameters())

    batch = random_batch(load_config(None, TINY))
    with torch.no_grad():
        a, b = single(batch), off(batch, memory=None)
    assert a.keys() == b.keys() and "memory" not in b
    assert all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.parametrize("memory, channels", [("bev", 16), ("graph", 3 + 1), ("bev+graph", 16 + 3 + 1)])
def test_gated_fusion_starts_as_the_identity(memory, channels):
    # the gated fusion's output convolution is zero-initialised: an untrained temporal model gives the
    # single-frame model's outputs, with or without memory, whatever its memory holds
    cfg = load_config(None, [*TINY, f"model.temporal.memory={memory}"])
    torch.manual_seed(0)
    temporal = build_model(cfg).eval()
    single = build_model(load_config(None, TINY)).eval()
    single.load_state_dict({k: v for k, v in temporal.state_dict().items() if not k.startswith("temporal.")})
    batch = random_batch(cfg)
    with torch.no_grad():
        first = temporal(batch)
        nxt = dict(batch, scene_start=torch.zeros(2, dtype=torch.bool), frame_index=torch.ones(2, dtype=torch.long))
        second = temporal(nxt, memory=first["memory"])
        ref = single(batch)
    assert first["memory_status"].tolist() == [NO_MEMORY] * 2 and second["memory_status"].tolist() == [FUSED] * 2
    for k in ref:
        torch.testing.assert_close(second[k], ref[k])
    # the memory map: the stage-1 features (16 channels) and / or the graph raster (3 classes + vertices)
    assert first["memory"]["bev"].shape == (2, channels, 16, 32) and not first["memory"]["bev"].requires_grad
    assert first["memory"]["bev"].shape == temporal.initial_memory(2, batch["images"])["bev"].shape


# --- the graph memory: the previous frame's predicted graph as a raster ------------------------------------


def _graph(vertices_px, scores, classes, edges, n_pad: int = 2) -> dict:
    """Graph-head outputs of one sample: vertices [n, 2] px, scores [n], class index per vertex, edges (i, j);
    ``n_pad`` padded slots (mask False) whose rows point nowhere."""
    n = len(vertices_px)
    N = n + n_pad
    px = torch.zeros(1, N, 2)
    px[0, :n] = torch.tensor(vertices_px, dtype=torch.float32)
    mask = torch.zeros(1, N, dtype=torch.bool)
    mask[0, :n] = True
    sc = torch.zeros(1, N)
    sc[0, :n] = torch.tensor(scores)
    log_probs = torch.full((1, N, 3), math.log(1e-6))
    for i, c in enumerate(classes):
        log_probs[0, i, c] = 0.0
    assignment = torch.full((1, N + 1, N + 1), -30.0)
    assignment[0, :, N] = 0.0  # everything else to the dustbin
    for i, j in edges:
        assignment[0, i, j], assignment[0, i, N] = math.log(0.9), math.log(0.1)
    return {"pred_vertices_px": px, "pred_vertex_mask": mask, "pred_vertex_scores": sc,
            "pred_class_log_probs": log_probs, "pred_log_assignment": assignment}


def test_render_graph_draws_the_edges_by_class_and_the_vertices():
    grid = BEVGrid(-8.0, 8.0, -4.0, 4.0, 0.25, 4)  # 64 x 32 px
    # a class-1 polyline along the row v = 9 from u = 4 to u = 20 (three vertices), a lone class-2 vertex
    g = _graph([[4.0, 9.0], [12.0, 9.0], [20.0, 9.0], [40.0, 25.0]], [0.8, 0.6, 0.7, 0.5], [1, 1, 1, 2],
               [(0, 1), (1, 2)])
    raster = render_graph(g, grid, 16, 32, samples=9)  # h x w = 16 x 32: a cell is 2 x 2 px
    assert raster.shape == (1, 4, 16, 32) and raster.min() >= 0 and raster.max() <= 1
    row = 4  # px v = 9 -> cell row floor(9.5 / 2)
    drawn = (raster[0, 1] > 1e-6).nonzero().tolist()  # (a vertex without successor: a weight of e^-30)
    # the edges cover every cell of the row from u = 4 to u = 20 (cells 2 .. 10), nothing else
    assert sorted(drawn) == [[row, c] for c in range(2, 11)]
    assert raster[0, 1, int(row), 2:11].min() >= 0.9 * 0.99  # each cell at least one point of weight ~0.9
    assert raster[0, 0].max() < 1e-4 and raster[0, 2].max() < 1e-4  # no class-0 edge (class probabilities 1e-6)
    vertices = raster[0, 3]
    expected = {(4, 2): 0.8, (4, 6): 0.6, (4, 10): 0.7, (12, 20): 0.5}
    assert {tuple(ij): round(float(vertices[tuple(ij)]), 4) for ij in vertices.nonzero().tolist()} == expected


def test_the_graph_memory_feeds_the_next_frame():
    # a fusion that is not the identity: the next frame's output depends on the previous frame's graph
    # raster when it fuses, and not at a scene start
    cfg = load_config(None, [*TINY, "model.temporal.memory=graph"])
    torch.manual_seed(0)
    model = build_model(cfg).eval()
    with torch.no_grad():
        model.temporal.out.weight.normal_(0, 0.2)
        batch = random_batch(cfg)
        first = model(batch)
        nxt = dict(batch, scene_start=torch.zeros(2, dtype=torch.bool), frame_index=torch.ones(2, dtype=torch.long))
        a = model(nxt, first["memory"])
        other = dict(first["memory"], bev=torch.zeros_like(first["memory"]["bev"]))
        b = model(nxt, other)
        start = dict(nxt, scene_start=torch.ones(2, dtype=torch.bool))
        c, d = model(start, first["memory"]), model(start, other)
    assert first["memory"]["bev"].amax() > 0  # the first frame drew a graph
    assert not torch.allclose(a["pred_vertex_logits"], b["pred_vertex_logits"])
    torch.testing.assert_close(c["pred_vertex_logits"], d["pred_vertex_logits"])


def test_a_memory_of_another_model_is_named():
    cfg = load_config(None, [*TINY, "model.temporal.memory=bev+graph"])
    model = build_model(cfg).eval()
    bev_model = build_model(load_config(None, [*TINY, "model.temporal.memory=bev"])).eval()
    batch = random_batch(cfg)
    with torch.no_grad():
        memory = bev_model(batch)["memory"]
        with pytest.raises(ValueError, match=r"the memory map has 16 channels, this model's "
                                             r"\(model.temporal.memory=bev\+graph\) has 20"):
            model(batch, memory)
    from instagram_hdmap.config import ConfigError

    with pytest.raises(ConfigError, match="model.temporal.fusion"):
        build_model(load_config(None, [*TINY, "model.temporal.memory=graph", "model.temporal.fusion=gru"]))
    gru = build_model(load_config(None, [*TINY, "model.temporal.memory=bev+graph", "model.temporal.fusion=gru"]))
    with torch.no_grad():
        out = gru.eval()(batch)
        assert gru(dict(batch, scene_start=torch.zeros(2, dtype=torch.bool), frame_index=torch.ones(2).long()),
                   out["memory"])["memory_status"].tolist() == [FUSED, FUSED]


# --- the warp ---------------------------------------------------------------------------------------------


def test_rigid_inverse():
    p = pose(3.0, -2.0, 0.7) @ pose(1.0, 5.0, -0.2)
    torch.testing.assert_close(rigid_inverse(p) @ p, torch.eye(4), atol=1e-6, rtol=0)
    torch.testing.assert_close(relative_pose(p[None], p[None])[0], torch.eye(4), atol=1e-6, rtol=0)


def _turning_drive(net, step_m: float = 3.0, frames: int = 10):
    """Poses (x, y, yaw) every ``step_m`` along a lane, a turning connector and the next lane."""
    from instagram_hdmap.data.synthetic.paths import Path

    for con in net.connectors:
        if con.turn == "straight":
            continue
        src, dst = net.lanes[con.src].path, net.lanes[con.dst].path
        if src.length < 15 or dst.length < 15:
            continue
        route = Path.concat([src, con.path, dst])
        s0 = src.length - 12.0
        return route.pose_at(s0 + step_m * np.arange(frames))
    raise AssertionError("no turning connector")


def _gt_map(builder, location: str, p: np.ndarray, grid: BEVGrid, step_m: float = 0.01) -> torch.Tensor:
    """[1, 1, H, W] a BEV map of the GT: each pixel centre's distance (metres) to the nearest GT line of any
    class, to ``step_m`` (geometric, no rasterisation: the warp is measured, not the pixel rounding)."""
    from scipy.spatial import cKDTree

    dense = []
    for line in builder(location, float(p[0]), float(p[1]), float(p[2])):
        for a, b in zip(line["pts"][:-1], line["pts"][1:]):
            t = np.linspace(0.0, 1.0, max(2, int(np.ceil(np.linalg.norm(b - a) / step_m)) + 1))
            dense.append(a + t[:, None] * (b - a))
    dist, _ = cKDTree(np.concatenate(dense)).query(grid.cell_centres_m().reshape(-1, 2))
    return torch.from_numpy(dist.reshape(grid.H, grid.W)).float()[None, None]


def _warp_iou(dist_t, dist_t1, cur_to_prev, grid, erode_px: int = 3, band_m: float = 0.5):
    """IoU of the GT lines (cells within ``band_m`` of a line) of frame t warped into frame t+1 and of frame
    t+1, over the region both see."""
    warped, inside = warp_bev(dist_t, cur_to_prev, grid)
    # the region both see: cells of frame t+1 whose centre frame t covered, away from its edge
    region = -torch.nn.functional.max_pool2d(-inside.float(), 2 * erode_px + 1, 1, erode_px) > 0.5
    a, b = (warped <= band_m) & region, (dist_t1 <= band_m) & region
    return float((a & b).sum()) / max(float((a | b).sum()), 1.0)


def test_warp_overlays_the_gt_of_the_next_frame_on_turns(tiny_world):
    # GT BEV raster of frame t, warped by the relative pose, against the GT of frame t+1 (the temporal
    # IoU >= 0.9 on the region both see), along a drive that turns through a junction of the world's map
    from instagram_hdmap.data.local_map import LocalMapBuilder
    from instagram_hdmap.data.synthetic.roads import LOCATIONS, build_network

    grid = BEVGrid(-30.0, 30.0, -15.0, 15.0, 0.15, 8)
    location = LOCATIONS[0]
    poses = _turning_drive(build_network(location, 0))
    yaw_change = np.degrees(np.abs(np.diff(np.unwrap(poses[:, 2]))))
    assert yaw_change.max() > 5.0, "the drive must turn"
    builder = LocalMapBuilder(tiny_world, grid, 0.5)
    rasters = [_gt_map(builder, location, p, grid) for p in poses]
    mats = [pose(*p) for p in poses]
    ious, wrong = [], []
    for t in range(len(poses) - 1):
        rel = relative_pose(mats[t][None], mats[t + 1][None])
        ious.append(_warp_iou(rasters[t], rasters[t + 1], rel, grid))
        if yaw_change[t] > 5.0:  # the inverse motion must fail: the test sees a wrong warp
            wrong.append(_warp_iou(rasters[t], rasters[t + 1], rigid_inverse(rel), grid))
    assert min(ious) >= 0.9, ious
    assert wrong and max(wrong) < 0.6, wrong


def test_warp_by_the_identity_and_a_pure_shift():
    grid = BEVGrid(-8.0, 8.0, -4.0, 4.0, 0.25, 4)
    feat = torch.randn(1, 3, grid.H, grid.W)
    warped, inside = warp_bev(feat, torch.eye(4)[None], grid)
    torch.testing.assert_close(warped, feat) and bool(inside.all())
    # the ego moved 1 m forward: current cell x = previous cell x + 1 m = 4 BEV pixels to the right
    warped, inside = warp_bev(feat, pose(1.0, 0.0, 0.0)[None], grid)
    torch.testing.assert_close(warped[..., :-4], feat[..., 4:])
    assert inside[..., :-4].all() and not inside[..., -4:].any()


# --- resets, drops and errors ---------------------------------------------------------------------------


def test_memory_resets_and_frame_order():
    cfg = load_config(None, [*TINY, "model.temporal.memory=bev"])
    model = build_model(cfg).eval()
    batch = random_batch(cfg, B=4)
    with torch.no_grad():
        memory = model(batch)["memory"]
        nxt = dict(batch, scene_start=torch.tensor([False, True, False, False]),
                   frame_index=torch.tensor([1, 1, 2, 1]),
                   ego_pose=batch["ego_pose"].clone())
        nxt["ego_pose"][3, 0, 3] += 10.5  # a teleport of 10.5 m > model.temporal.max_jump_m
        status = model(nxt, memory)["memory_status"].tolist()
        # a turn in place: 30 degrees fuses (a sharp real turn is ~15 per half second), 70 or 180 is a pose jump
        turns = []
        for deg in (30, 70, 180):
            spun = dict(nxt, ego_pose=batch["ego_pose"] @ pose(0.0, 0.0, math.radians(deg)))
            turns.append(model(spun, memory)["memory_status"][0].item())
    assert status == [FUSED, NO_MEMORY, MISSING_FRAME, POSE_JUMP]
    assert turns == [FUSED, POSE_JUMP, POSE_JUMP]
    back = dict(nxt, scene="scene-0042", frame_index=torch.tensor([0, 1, 1, 1]))
    back["scene"] = ["scene-0041", "scene-0042", "scene-0043", "scene-0044"]
    memory["frame_index"][:] = torch.tensor([3, 0, 0, 0])
    with pytest.raises(FrameOrderError, match="scene 'scene-0041': frame 0 follows frame 3"):
        model(back, memory)


def test_training_drops_memory():
    cfg = load_config(None, [*TINY, "model.temporal.memory=bev", "model.temporal.drop_prob=0.5"])
    model = build_model(cfg).train()
    batch = random_batch(cfg, B=8)
    torch.manual_seed(0)
    memory = model(batch)["memory"]
    nxt = dict(batch, scene_start=torch.zeros(8, dtype=torch.bool), frame_index=torch.ones(8, dtype=torch.long))
    status = model(nxt, memory)["memory_status"]
    assert set(status.tolist()) == {FUSED, DROPPED}
    assert not memory["bev"].requires_grad  # detached between steps
    model.eval()
    assert model(nxt, memory)["memory_status"].tolist() == [FUSED] * 8


def test_one_frame_scene():
    cfg = load_config(None, [*TINY, "model.temporal.memory=bev"])
    model = build_model(cfg).eval()
    batch = random_batch(cfg, B=1)
    with torch.no_grad():
        out = model(batch)  # no memory: a scene of one frame
        again = model(batch, out["memory"])  # the next scene's first frame
    assert out["memory_status"].tolist() == again["memory_status"].tolist() == [NO_MEMORY]
    torch.testing.assert_close(out["pred_vertex_logits"], again["pred_vertex_logits"])


# --- the streaming sampler --------------------------------------------------------------------------


def test_deal_scenes_balances_whole_scenes():
    dealt = deal_scenes([5, 3, 4, 6, 2], [3, 0, 2, 1, 4], 2)
    assert dealt == [[3, 1, 4], [0, 2]]  # totals 11 and 9


class _SceneDataset(torch.utils.data.Dataset):
    """Samples that are their own (scene, frame) labels, scenes of various lengths."""

    def __init__(self, lengths):
        from instagram_hdmap.data.base import SceneIndex

        names = [f"scene-{s}" for s, n in enumerate(lengths) for _ in range(n)]
        self.scenes = SceneIndex(names, list(range(len(names))))

    def __len__(self):
        return len(self.scenes)

    def __getitem__(self, i):
        return {"scene": self.scenes.scene[i], "frame_index": torch.tensor(self.scenes.frame[i])}


def _collate(samples):
    return {"scene": [s["scene"] for s in samples], "frame_index": torch.stack([s["frame_index"] for s in samples])}


LENGTHS = [5, 3, 4, 6, 2, 5, 4, 7, 1]


def _sampler_worker(rank: int, world: int, init_file: str, out: str) -> None:
    import torch.distributed as dist
    from torch.utils.data import DataLoader

    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=world)
    ds = _SceneDataset(LENGTHS)
    sampler = StreamingBatchSampler(ds.scenes.runs, streams=2, seed=7, rank=dist.get_rank(),
                                    world_size=dist.get_world_size())
    epochs, schedules = [], []
    for epoch in range(2):
        sampler.set_epoch(epoch)
        loader = DataLoader(ds, batch_sampler=sampler, collate_fn=_collate, num_workers=1)
        epochs.append([(b["scene"], b["frame_index"].tolist()) for b in loader])
        schedules.append(sampler.schedule())
    got = [None] * world
    dist.all_gather_object(got, (epochs, schedules))
    if rank == 0:
        torch.save(got, out)
    dist.destroy_process_group()


def test_streaming_sampler_two_gloo_ranks(tmp_path):
    out = tmp_path / "out.pt"
    torch.multiprocessing.spawn(_sampler_worker, args=(2, str(tmp_path / "init"), str(out)), nprocs=2)
    got = torch.load(out, weights_only=False)
    for epoch in range(2):
        steps = {len(got[r][0][epoch]) for r in range(2)}
        assert len(steps) == 1  # the ranks step in lockstep
        walked: dict[str, list[tuple[int, int]]] = {}
        for rank in range(2):
            batches = got[rank][0][epoch]
            schedule = got[rank][1][epoch]
            for row in range(2):
                stream = [(b[0][row], b[1][row]) for b in batches]
                flags = [pad for _, _, pad in schedule[rank * 2 + row]]
                assert flags == sorted(flags), "padding only at a stream's end"
                real = [sf for sf, pad in zip(stream, flags) if not pad]
                for k, (scene, frame) in enumerate(real):  # whole scenes, each in order from frame 0
                    if frame == 0:
                        walked.setdefault(scene, []).append((rank, row))
                    else:
                        assert real[k - 1] == (scene, frame - 1)
                for k, (scene, frame) in enumerate(stream):  # padding starts scenes from frame 0 too
                    assert frame == 0 or stream[k - 1] == (scene, frame - 1)
                assert len(real) == sum(LENGTHS[int(s.split("-")[1])] for s, f in real if f == 0)
        # every scene once per epoch, on one stream of one rank
        assert sorted(walked) == sorted(f"scene-{s}" for s in range(len(LENGTHS)))
        assert all(len(v) == 1 for v in walked.values())
    # the epochs deal differently, in the same number of steps
    assert got[0][0][0] != got[0][0][1] and len(got[0][0][0]) == len(got[0][0][1])


def test_streaming_sampler_resume_and_eval_order():
    runs = _SceneDataset(LENGTHS).scenes.runs
    sampler = StreamingBatchSampler(runs, streams=3, seed=1)
    sampler.set_epoch(4)
    full = list(sampler)
    sampler.set_epoch(4, start=5 * 3)  # samples, whole batches of 3 streams
    assert list(sampler) == full[5:] and len(sampler) == len(full) - 5
    ordered = StreamingBatchSampler(runs, streams=1, shuffle=False)
    walk = [i for batch in ordered for i in batch]  # one stream: every scene whole, in order, no padding
    assert sorted(walk) == list(range(sum(LENGTHS))) and ordered.steps == sum(LENGTHS)
    assert all(walk[walk.index(run[0]):walk.index(run[0]) + len(run)] == run for run in runs)


# --- occluders in the synthetic world ---------------------------------------------------------------------


def _files(root) -> dict:
    import hashlib

    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def test_occluders_add_vehicles_and_change_nothing_else(tmp_path, monkeypatch):
    import json

    from instagram_hdmap.config import UserError
    from instagram_hdmap.data.synthetic import generate_world, jobs

    args = {"scenes_train": 1, "scenes_val": 1, "samples_per_scene": 2, "seed": 0, "image_size": "160x90",
            "progress": False}
    dense = generate_world(out=tmp_path / "dense", occluders=1.0, **args)

    def never(*a, **k):
        raise AssertionError("density 0 draws no occluder")

    monkeypatch.setattr(jobs, "place_occluders", never)
    plain = generate_world(out=tmp_path / "plain", **args)  # the default: density 0
    assert "occluders" not in plain and dense["occluders"] == 1.0  # the manifest of a plain world is unchanged
    a, b = _files(tmp_path / "plain"), _files(tmp_path / "dense")
    assert a.keys() == b.keys()
    tables = "v1.0-trainval/"
    differ = {f for f in a if a[f] != b[f]}
    # the same maps, drives, rig, samples and lidar; the vehicles (annotations, the scene's description
    # counts them) and the camera images differ
    assert differ - {f for f in a if f.startswith("samples/")} == {
        "world.json", f"{tables}instance.json", f"{tables}sample_annotation.json", f"{tables}scene.json"}
    assert any(f.startswith("samples/CAM_") for f in differ)  # the occluders are in the images

    def annotations(root):
        return [(r["instance_token"], r["translation"]) for r in
                json.loads((root / tables / "sample_annotation.json").read_text())]

    plain_ann, dense_ann = annotations(tmp_path / "plain"), annotations(tmp_path / "dense")
    assert len(dense_ann) > len(plain_ann) and set(map(str, plain_ann)) <= set(map(str, dense_ann))
    with pytest.raises(UserError, match="--occluders 1.5"):
        generate_world(out=tmp_path / "bad", occluders=1.5, **args)


def test_occluders_park_along_kerbs_and_drive_ahead():
    from instagram_hdmap.data.synthetic.roads import LOCATIONS, build_network
    from instagram_hdmap.data.synthetic.traffic import place_occluders, place_vehicles, plan_drive

    net = build_network(LOCATIONS[0], 0)
    counts = []
    for density in (0.0, 0.3, 1.0):
        rng = np.random.default_rng([0, 1000])
        drive = plan_drive(net, 6, rng)
        others = place_vehicles(net, drive, rng)
        occ = place_occluders(net, drive, np.random.default_rng([0, 2000]), density, others)
        counts.append(len(occ))
        if density == 1.0:
            ahead = [v for v in occ if not v.parked]
            assert len(ahead) == 1 and ahead[0].category in ("vehicle.truck", "vehicle.bus.rigid")
            ego = drive.poses()
            for k, t in enumerate(0.5 * np.arange(6)):  # stays 8-15 m ahead, in the ego's lane
                gap = np.linalg.norm(ahead[0].state(t)[0][:2] - ego[k, :2]) - ahead[0].size[1] / 2
                assert 7.5 < gap < 15.5
            parked = [v for v in occ if v.parked]
            assert parked and all(v.path is not None and abs(v.lateral) > 0 for v in parked)
    assert counts[0] == 0 and counts[0] < counts[1] < counts[2]


# --- the flicker rate -----------------------------------------------------------------------------------


def test_flicker_rate(tiny_world_cfg):
    from instagram_hdmap.data import build_dataset
    from instagram_hdmap.evaluation.consistency import FlickerMeter

    ds = build_dataset(tiny_world_cfg, "train")
    grid = BEVGrid.from_config(tiny_world_cfg.grid)
    gts = [ds.gt_polylines(i) for i in range(len(ds))]
    poses = torch.stack([ds.ego_pose(i) for i in range(len(ds))])
    scenes, frames = ds.scenes.scene, torch.tensor(ds.scenes.frame)

    def run(preds, order=None):
        meter = FlickerMeter(grid, classes=tiny_world_cfg.data.classes)
        for i in order if order is not None else range(len(ds)):
            meter.update([preds[i]], [gts[i]], [scenes[i]], frames[i:i + 1], poses[i:i + 1])
        return meter.compute()

    perfect = run([[dict(g, score=1.0) for g in gt] for gt in gts])
    assert sum(perfect["pairs"].values()) > 10 and perfect["frame_pairs"] == 4  # 2 scenes x (3 - 1)
    assert perfect["flicker_mean"] == 0.0
    blinking = [[dict(g, score=1.0) for g in gt] if f % 2 == 0 else [] for gt, f in zip(gts, ds.scenes.frame)]
    assert run(blinking)["flicker_mean"] == 1.0  # every element seen twice changes status
    # a shift beyond the 1 m threshold in odd frames flickers as much; the order of the samples does not matter
    shifted = [[dict(g, pts=g["pts"] + [0.0, 3.0 * (f % 2)], score=1.0) for g in gt]
               for gt, f in zip(gts, ds.scenes.frame)]
    res = run(shifted)
    assert res["flicker_mean"] > 0.5 and run(shifted, order=list(range(len(ds)))[::-1]) == res
    nothing = run([[] for _ in gts])
    assert nothing["flicker_mean"] == 0.0 and nothing["pairs"] == perfect["pairs"]
    # among the pairs detected at least once: a model that detects nothing has none (NaN), not 0
    assert math.isnan(nothing["flicker_detected_mean"]) and run(blinking)["flicker_detected_mean"] == 1.0
    assert perfect["flicker_detected_mean"] == 0.0 and perfect["pairs_detected"] == perfect["pairs"]


# --- training and evaluation on drives ---------------------------------------------------------------------


def _drive_cfg(tiny_world, out, *extra):
    return load_config(None, [*TINY, f"train.out_dir={out}", f"data.dataroot={tiny_world}",
                              f"data.splits_file={tiny_world / 'splits.json'}", "data.version=v1.0-trainval",
                              "model.temporal.memory=bev", "train.batch_size=2", "train.log_every=1",
                              "train.checkpoint_every=0", "data.num_workers=0", "train.deterministic=true",
                              "train.epochs=2", *extra])


def test_streaming_training_resumes_exactly_with_its_memory(tiny_world, tmp_path):
    # 2 train scenes x 3 frames, 2 streams: 3 steps per epoch; the interrupted run stops after step 2
    # (mid-scene: the memory of both streams is in last.pt) and resumes
    from instagram_hdmap.checkpoint import load_checkpoint
    from instagram_hdmap.train import build_loaders, train

    def run(where, *extra, resume=None):
        cfg = _drive_cfg(tiny_world, where, *extra)
        return train(cfg, loaders=build_loaders(cfg, 1, with_val=False), validate=False, resume=resume)

    run(tmp_path / "a")
    run(tmp_path / "b", "train.max_steps=2")
    state = load_checkpoint(tmp_path / "b" / "last.pt")
    assert (state["epoch"], state["step"], state["step_in_epoch"]) == (0, 2, 2)
    assert state["memory"] is not None and bool(state["memory"][0]["valid"].all())
    assert state["memory"][0]["frame_index"].tolist() == [1, 1]  # each stream is in frame 1 of its scene
    forgetful = tmp_path / "c"
    forgetful.mkdir()
    torch.save({**state, "memory": None}, forgetful / "last.pt")
    run(tmp_path / "b", resume=str(tmp_path / "b" / "last.pt"))
    run(tmp_path / "c", resume=str(forgetful / "last.pt"))
    a, b, c = (load_checkpoint(tmp_path / x / "last.pt")["model"] for x in "abc")
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=1e-6, msg=k)
    # without its memory the resumed run is another run: the memory is what made it exact
    assert max(float((a[k].float() - c[k].float()).abs().max()) for k in a) > 1e-5


def test_streaming_evaluation_without_memory_is_the_frame_by_frame_ap(tiny_world, tmp_path):
    # the same weights evaluated (a) frame by frame as a single-frame model and (b) streamed as a temporal
    # model whose fusion is still the identity (zero-initialised gate): exactly the same AP and flicker,
    # although (b) walks 2 streams over 1 val scene (one stream is padding) and carries its memory
    from instagram_hdmap.checkpoint import save_checkpoint
    from instagram_hdmap.config import config_to_dict
    from instagram_hdmap.evaluate_split import run_evaluation

    cfg_t = _drive_cfg(tiny_world, tmp_path / "run", "eval.batch_size=2", "model.gnn.conf_threshold=0.0",
                       "model.gnn.match_threshold=0.01")
    cfg_s = _drive_cfg(tiny_world, tmp_path / "run", "eval.batch_size=2", "model.gnn.conf_threshold=0.0",
                       "model.gnn.match_threshold=0.01", "model.temporal.memory=none")
    torch.manual_seed(3)
    temporal = build_model(cfg_t)
    weights = {k: v for k, v in temporal.state_dict().items() if not k.startswith("temporal.")}
    save_checkpoint({"model": temporal.state_dict(), "config": config_to_dict(cfg_t)}, tmp_path / "t.pt")
    save_checkpoint({"model": weights, "config": config_to_dict(cfg_s)}, tmp_path / "s.pt")
    streamed = run_evaluation(cfg_t, tmp_path / "t.pt", out=tmp_path / "et")["metrics"]
    frames = run_evaluation(cfg_s, tmp_path / "s.pt", out=tmp_path / "es")["metrics"]
    assert streamed["memory"] == {"memory_fused": 2, "memory_no_memory": 1, "memory_pose_jump": 0,
                                  "memory_missing_frame": 0, "memory_dropped": 0}
    assert sum(streamed["num_pred"].values()) > 0
    for key in ("AP", "mAP", "num_gt", "num_pred", "consistency"):
        assert streamed[key] == frames[key], key
    assert streamed["counters"]["samples"] == 3
    # predict walks the sample's scene from its first frame: the streamed predictions of the last frame
    from instagram_hdmap.data import build_dataset
    from instagram_hdmap.evaluation.io import read_submission
    from instagram_hdmap.inference import run_model
    from instagram_hdmap.predict import scene_memory

    model = build_model(cfg_t).eval()
    model.load_state_dict(temporal.state_dict())
    model.temporal.out.weight.data.normal_(0, 0.1)  # a fusion that is not the identity: memory matters
    val = build_dataset(cfg_t, "val")
    last = val.scenes.runs[0][-1]
    with torch.no_grad():
        batch = collate_fn([val.load_sample(last)])
        streamed_last = run_model(model, batch, scene_memory(model, val, last))
        alone = model(batch)
    assert streamed_last["memory_status"].tolist() == [FUSED] and alone["memory_status"].tolist() == [NO_MEMORY]
    assert not torch.equal(streamed_last["pred_vertex_logits"], alone["pred_vertex_logits"])
    token = val.sample_tokens[last]
    assert token in read_submission(tmp_path / "et" / "submission.json", "pred").samples


# --- ONNX ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("memory", ["bev", "bev+graph"])
def test_onnx_export_of_the_temporal_model_over_three_frames(tmp_path, memory):
    pytest.importorskip("onnxruntime", reason="the [deploy] extra is not installed")
    import onnx

    from instagram_hdmap import deploy
    from instagram_hdmap.inference import OUTPUT_NAMES, OnnxModel, input_names, output_names
    from instagram_hdmap.postprocess import postprocess_batch

    # the tiny model with every cell a vertex slot (N = 128: top-N never cuts through equal scores)
    cfg = load_config("configs/synthetic/tiny.yaml", ["model.gnn.sinkhorn_iters=5", "model.gnn.num_vertices=128",
                                                      f"model.temporal.memory={memory}", "model.temporal.kernel=3"])
    torch.manual_seed(0)
    model = build_model(cfg).eval()
    with torch.no_grad():
        model.graph_head.match_head.weight.mul_(10)
        model.temporal.out.weight.normal_(0, 0.2)  # a fusion that is not the identity
    path = tmp_path / "t.onnx"
    info = deploy.export_onnx(model, cfg, path)
    proto = onnx.load(str(path))
    assert [i.name for i in proto.graph.input] == list(input_names(cfg))
    assert [o.name for o in proto.graph.output] == list(output_names(cfg))
    assert input_names(cfg)[-4:] == ("memory_bev", "memory_ego_pose", "memory_valid", "memory_frame_index")
    channels = 16 if memory == "bev" else 16 + 3 + 1  # the stage-1 features, the graph raster
    assert info["inputs"]["memory_bev"] == [1, channels, 16, 32] == info["outputs"]["next_memory_bev"]
    onnx_model = OnnxModel(path, cfg)
    assert onnx_model.is_temporal
    grid = BEVGrid.from_config(cfg.grid)
    memory_torch = memory_onnx = None
    statuses = []
    for k in range(3):  # a drive: 1.5 m per frame, turning
        batch = deploy.example_inputs(cfg, seed=10 + k)
        batch.update(ego_pose=pose(1.5 * k, 0.1 * k * k, 0.05 * k)[None], frame_index=torch.tensor([k]),
                     scene_start=torch.tensor([k == 0]))
        with torch.no_grad():
            expected = model(batch, memory=memory_torch)
        got = onnx_model(batch, memory=memory_onnx)
        statuses.append((expected["memory_status"].item(), got["memory_status"].item()))
        e, g = deploy.align_vertex_slots(expected), deploy.align_vertex_slots(got)
        for name in OUTPUT_NAMES:
            if name in ("pred_vertex_mask", "pred_vertices_px"):
                assert torch.equal(g[name], e[name]), (k, name)
            else:
                torch.testing.assert_close(g[name], e[name], atol=1e-4, rtol=1e-5, msg=f"frame {k} {name}")
        # (the graph raster sums exp(log assignment), compared to 1e-4 above)
        torch.testing.assert_close(got["memory"]["bev"], expected["memory"]["bev"], atol=1e-4, rtol=1e-5)
        torch.testing.assert_close(got["memory"]["ego_pose"], expected["memory"]["ego_pose"], atol=1e-5, rtol=1e-5)
        for key in ("valid", "frame_index"):
            assert torch.equal(got["memory"][key], expected["memory"][key])
        threshold = 0.5 * float(e["pred_log_assignment"][0, :-1, :-1].exp().max(1).values.median())
        assert postprocess_batch(e, grid, threshold)[0] and all(
            p["label"] == q["label"] and np.allclose(p["pts"], q["pts"], atol=1e-4)
            for p, q in zip(postprocess_batch(g, grid, threshold)[0], postprocess_batch(e, grid, threshold)[0]))
        memory_torch, memory_onnx = expected["memory"], got["memory"]
    assert statuses == [(NO_MEMORY, NO_MEMORY), (FUSED, FUSED), (FUSED, FUSED)]


# --- bad input ------------------------------------------------------------------------------------------------


def test_scene_index_refuses_frames_out_of_order_and_split_scenes():
    from instagram_hdmap.data.base import DatasetError, SceneIndex

    idx = SceneIndex(["a", "a", "b", "c", "c", "c"], [1, 2, 1, 5, 6, 9])
    assert idx.runs == [[0, 1], [2], [3, 4, 5]] and idx.frame == [0, 1, 0, 0, 1, 2]  # "b": a one-frame scene
    with pytest.raises(DatasetError, match="scene 'a'.*frame 2.*does not come after frame 1"):
        SceneIndex(["a", "a", "a"], [1, 3, 2])
    with pytest.raises(DatasetError, match="scene 'a'.*not contiguous"):
        SceneIndex(["a", "b", "a"], [1, 2, 3])


def test_evaluation_counts_pose_jumps_and_missing_frames():
    from instagram_hdmap.engine import evaluate

    cfg = load_config(None, [*TINY, "model.temporal.memory=bev"])
    model = build_model(cfg)
    frames = []
    for k, (x, frame) in enumerate([(0.0, 0), (2.0, 1), (14.0, 2), (16.0, 4), (18.0, 5)]):
        b = random_batch(cfg, B=1, seed=k)
        b.update(ego_pose=pose(x, 0.0, 0.0)[None], frame_index=torch.tensor([frame]),
                 scene_start=torch.tensor([frame == 0]))
        frames.append(b)
    result = evaluate(model, None, frames, torch.device("cpu"))
    # frame 2 jumped 12 m (> 10 m): reset and counted; frame 4 follows frame 2: a missing frame
    assert result["memory"] == {"memory_fused": 2, "memory_no_memory": 1, "memory_pose_jump": 1,
                                "memory_missing_frame": 1, "memory_dropped": 0}


# --- the public API's stream ----------------------------------------------------------------------------------


def test_map_stream_carries_a_temporal_models_memory():
    from instagram_hdmap.data.rig import RigError, nuscenes_like_rig
    from instagram_hdmap.data.rig import rig as scaled_rig
    from instagram_hdmap.inference import run_model
    from instagram_hdmap.mapper import Frame, Mapper

    cfg = load_config("configs/synthetic/tiny.yaml", ["model.temporal.memory=bev"])
    torch.manual_seed(0)
    model = build_model(cfg).eval()
    with torch.no_grad():
        model.temporal.out.weight.normal_(0, 0.2)  # a fusion that is not the identity
    mapper = Mapper(model, cfg, source="tiny temporal")
    rig = nuscenes_like_rig(tuple(cfg.data.image_size))
    h, w = cfg.data.image_size
    intrinsics = [scaled_rig((w, h))[c].intrinsic for c in mapper.cameras]  # in the pixels of the w x h images
    rng = np.random.default_rng(0)
    cam_to_ego = [np.block([[r.numpy(), t.numpy()[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]])
                  for r, t in zip(rig["cam_to_ego_rot"], rig["cam_to_ego_trans"])]

    def frame(x: float) -> Frame:
        images = [rng.integers(0, 255, (h, w, 3), dtype=np.uint8) for _ in mapper.cameras]
        return Frame(images, intrinsics, cam_to_ego, ego_pose=pose(x, 0.0, 0.0).numpy())

    frames = [frame(x) for x in (0.0, 1.5, 3.0, 30.0)]  # the last one jumps 27 m
    stream = mapper.stream()
    elements, statuses = [], []
    for f in frames:
        elements.append(stream.step(f))
        statuses.append(stream.status)
    assert statuses == ["no_memory", "fused", "fused", "pose_jump"]
    assert stream.counts == {"no_memory": 1, "fused": 2, "pose_jump": 1}
    # the stream's outputs are the model's, frame after frame with its memory
    memory = None
    for k, f in enumerate(frames[:3]):
        batch = mapper.batch([f])
        batch.update(scene_start=torch.tensor([k == 0]), frame_index=torch.tensor([k]))
        out = run_model(model, batch, memory)
        memory = out["memory"]
    assert [e.label for e in elements[2]] == [e.label for e in mapper.decode(out)[0]]
    stream.reset()
    stream.step(frames[2])
    assert stream.status == "no_memory"
    with pytest.raises(RigError, match="ego_pose"):
        stream.step(Frame(frames[0].images, frames[0].intrinsics, frames[0].cam_to_ego))


def test_streams_in_pieces_flag_each_piece_start(tiny_world_cfg):
    from instagram_hdmap.data import build_dataset

    runs = _SceneDataset(LENGTHS).scenes.runs
    sampler = StreamingBatchSampler(runs, streams=3, seed=2, piece_frames=2)
    steps = list(sampler)
    assert all(isinstance(i, tuple) for batch in steps for i in batch)
    for row in range(3):  # each row: pieces of <= 2 consecutive frames of one scene, a start on each first
        stream = [batch[row] for batch in steps]
        for (a, _), (b, b_start) in zip(stream, stream[1:]):
            assert b_start or (b == a + 1 and any(a in r and b in r for r in runs))
    assert sampler.owned() == set(range(sum(LENGTHS)))
    assert len(sampler.runs) == sum((n + 1) // 2 for n in LENGTHS)
    ds = build_dataset(tiny_world_cfg, "train")
    i = ds.scenes.runs[0][1]  # frame 1 of a scene: no scene start, unless it starts a piece
    assert not bool(ds[i]["scene_start"]) and bool(ds[(i, True)]["scene_start"])


def test_single_frame_epochs_before_the_streams():
    runs = _SceneDataset(LENGTHS).scenes.runs
    sampler = StreamingBatchSampler(runs, streams=3, seed=5, piece_frames=3, single_epochs=2)
    for epoch in range(3):
        sampler.set_epoch(epoch)
        items = [i for batch in sampler for i in batch]
        assert sampler.owned() == set(range(sum(LENGTHS)))
        starts = [start for _, start in items]
        assert all(starts) == (epoch < 2)  # shuffled single frames: every sample a start
    sampler.set_epoch(0)
    again = list(sampler)
    sampler.set_epoch(0, start=3 * 4)
    assert list(sampler) == again[4:]  # exact resume inside a single-frame epoch


def test_fine_tuning_the_fusion_from_a_single_frame_checkpoint(tiny_world, tmp_path):
    # train.init_from a single-frame checkpoint + train.trainable=[temporal]: every single-frame weight and
    # BatchNorm statistic stays bit for bit what the checkpoint holds, only the fusion learns
    from instagram_hdmap.checkpoint import load_checkpoint
    from instagram_hdmap.config import UserError
    from instagram_hdmap.train import build_loaders, train

    single_cfg = _drive_cfg(tiny_world, tmp_path / "single", "model.temporal.memory=none", "train.epochs=1")
    train(single_cfg, loaders=build_loaders(single_cfg, 1, with_val=False), validate=False)
    base = load_checkpoint(tmp_path / "single" / "last.pt")["model"]

    cfg = _drive_cfg(tiny_world, tmp_path / "ft", f"train.init_from={tmp_path / 'single' / 'last.pt'}",
                     "train.trainable=[temporal]", "train.epochs=1", "model.temporal.drop_prob=0.0")
    train(cfg, loaders=build_loaders(cfg, 1, with_val=False), validate=False)
    tuned = load_checkpoint(tmp_path / "ft" / "last.pt")["model"]
    assert set(tuned) - set(base) and all(k.startswith("temporal.") for k in set(tuned) - set(base))
    for k, v in base.items():
        assert torch.equal(tuned[k], v), k  # weights and running statistics
    fresh = build_model(cfg).state_dict()
    assert any(not torch.equal(tuned[k], fresh[k]) for k in tuned if k.startswith("temporal.")
               and tuned[k].is_floating_point())

    def refused(*extra) -> str:
        bad = _drive_cfg(tiny_world, tmp_path / "bad", *extra)
        with pytest.raises(UserError) as e:
            train(bad, loaders=build_loaders(bad, 1, with_val=False), validate=False, force=True)
        return str(e.value)

    ckpt = f"train.init_from={tmp_path / 'single' / 'last.pt'}"
    assert "graph_head." in refused(ckpt, "model.gnn.dim=16")  # another architecture: the weights named
    assert "grid.resolution" in refused(ckpt, "grid.resolution=0.5", "grid.cell_size=2")
    msg = refused("train.trainable=[temporl]")
    assert "temporl" in msg and "temporal" in msg


def test_init_from_a_checkpoint_of_another_memory_starts_the_fusion_fresh():
    # a bev checkpoint into a bev+graph model: the fusion's input widths differ, so none of it is taken (a
    # half-trained fusion would not be the identity); everything else is; into a bev model, all of it
    from instagram_hdmap.train import init_weights

    torch.manual_seed(0)
    bev = build_model(load_config(None, [*TINY, "model.temporal.memory=bev"]))
    with torch.no_grad():
        bev.temporal.out.weight.normal_()
    state = {"model": bev.state_dict()}
    both = build_model(load_config(None, [*TINY, "model.temporal.memory=bev+graph"]))
    fresh = {k: v.clone() for k, v in both.state_dict().items()}
    new = init_weights(both, state)
    assert sorted(new) == sorted(k for k in fresh if k.startswith("temporal."))
    for k, v in both.state_dict().items():
        assert torch.equal(v, fresh[k] if k.startswith("temporal.") else state["model"][k]), k
    same = build_model(load_config(None, [*TINY, "model.temporal.memory=bev"]))
    assert init_weights(same, state) == []
    assert torch.equal(same.temporal.out.weight, bev.temporal.out.weight)


def test_the_fusion_keeps_its_memory_weights_through_the_single_frame_epochs(tiny_world, tmp_path):
    # with the memory empty (the single-frame epochs of train.stream_warmup) the fusion's memory weights get
    # no data gradient; Adam with the paper's coupled L2 then pushed them to zero at ~lr per step (a dead
    # fusion: 1e-28 after the demo config's warm-up). The fusion carries no weight decay: they stay as built
    from instagram_hdmap.checkpoint import load_checkpoint
    from instagram_hdmap.train import build_loaders, seed_everything, train

    cfg = _drive_cfg(tiny_world, tmp_path / "warm", "train.epochs=2", "train.stream_warmup=0.5",
                     "train.max_steps=3", "train.weight_decay=0.1", "train.lr=0.01")
    train(cfg, loaders=build_loaders(cfg, 1, with_val=False), validate=False)
    seed_everything(cfg.train.seed)  # as the run did before building its model
    start = build_model(cfg).state_dict()
    tuned = load_checkpoint(tmp_path / "warm" / "last.pt")["model"]
    c = cfg.model.bev_heads.stage_channels[0]
    # [x, warped memory, validity]: the memory's and the validity's weights are untouched, x's trained
    assert torch.equal(tuned["temporal.mix.0.weight"][:, c:], start["temporal.mix.0.weight"][:, c:])
    assert not torch.equal(tuned["temporal.mix.0.weight"][:, :c], start["temporal.mix.0.weight"][:, :c])
    assert not torch.equal(tuned["bev_heads.stem.0.weight"], start["bev_heads.stem.0.weight"])


def test_resume_of_a_temporal_checkpoint_with_one_optimizer_group_is_named(tiny_world, tmp_path):
    # temporal checkpoints written before the fusion had its own parameter group cannot resume exactly
    from instagram_hdmap.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
    from instagram_hdmap.train import build_loaders, train

    cfg = _drive_cfg(tiny_world, tmp_path / "run", "train.max_steps=1")
    train(cfg, loaders=build_loaders(cfg, 1, with_val=False), validate=False)
    state = load_checkpoint(tmp_path / "run" / "last.pt")
    groups = state["optimizer"]["param_groups"]
    assert len(groups) == 2 and groups[1]["weight_decay"] == 0.0
    merged = {**groups[0], "params": groups[0]["params"] + groups[1]["params"]}
    old = save_checkpoint({**state, "optimizer": {**state["optimizer"], "param_groups": [merged]}},
                          tmp_path / "old" / "last.pt")
    cfg = _drive_cfg(tiny_world, tmp_path / "old", "train.max_steps=2")
    with pytest.raises(CheckpointError, match=r"old/last\.pt: its optimizer has 1 parameter group.*train\.init_from"):
        train(cfg, loaders=build_loaders(cfg, 1, with_val=False), validate=False, resume=str(old))


def test_benchmark_names_a_temporal_variant_after_its_own_overrides(monkeypatch, tmp_path):
    """benchmarks/temporal.py --temporal-set: the overrides reach the temporal config only (the single-frame runs of
    the same --out are shared), and the run is named after them, so a variant never reads another's result."""
    import argparse
    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location(
        "bench_temporal", Path(__file__).resolve().parents[1] / "benchmarks" / "temporal.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    variant = ["train.stream_frames=10", "model.temporal.kernel=5"]
    args = argparse.Namespace(memory="bev+graph", temporal_override=variant, out=str(tmp_path), steps=10,
                              minutes=1.0, occluders=0.0, override=["train.lr=0.001"],
                              val_scenes=4, val_occluders=None, val_dropout=None, threads=None)
    assert bench.memory_suffix(args) == "_bev_graph_stream_frames10_kernel5"
    seen = {}

    def fake_train(cfg, force, validate):  # what each config was trained with; no training
        seen[cfg.name] = (cfg.train.stream_frames, cfg.model.temporal.kernel, cfg.train.lr)
        raise RuntimeError("stop")

    monkeypatch.setattr("instagram_hdmap.train.train", fake_train)
    monkeypatch.setattr("instagram_hdmap.demo.world_overrides", lambda root: [])
    for name in ("single", "temporal"):
        with pytest.raises(RuntimeError, match="stop"):
            bench.run_one(name, 0, args, (None, None), name)
    single = load_config(bench.CONFIGS["single"])
    assert seen["temporal_synthetic"] == (10, 5, 0.001)
    assert seen[single.name] == (single.train.stream_frames, single.model.temporal.kernel, 0.001)


# --- persistence: elements kept over missed frames (persistence.py) ----------------------------------------------


def _pose(x: float, y: float, yaw_deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = [x, y]
    return T


def test_persistence_keeps_a_missed_element_moved_by_the_ego():
    from instagram_hdmap.persistence import Persistence

    grid = BEVGrid(-30.0, 30.0, -15.0, 15.0, 0.15)
    poses = [_pose(100.0, 50.0, 0.0), _pose(102.0, 50.5, 10.0), _pose(104.0, 51.5, 20.0)]
    line = {"pts": np.array([[5.0, 3.0], [10.0, 3.0], [15.0, 3.0]]), "label": 2, "closed": False, "score": 0.8}
    world = line["pts"] @ poses[0][:2, :2].T + poses[0][:2, 3]  # the element's place in the world

    def in_frame(t: int) -> np.ndarray:  # the same world points in the ego frame of frame t (independently)
        R, p = poses[t][:2, :2], poses[t][:2, 3]
        return (world - p) @ R

    for frames, expected_scores in ((1, [0.4]), (2, [0.4, 0.2])):
        keep = Persistence(grid, frames=frames, decay=0.5)
        assert keep.step([line], "scene-a", 0, poses[0]) == [line]
        for t in (1, 2):
            out = keep.step([], "scene-a", t, poses[t])
            if t > len(expected_scores):
                assert out == []  # missed more than `frames` times: gone
                continue
            (kept,) = out
            np.testing.assert_allclose(kept["pts"], in_frame(t), atol=1e-9)
            assert kept["score"] == pytest.approx(expected_scores[t - 1])
            assert kept["label"] == 2 and not kept["closed"]

    # found again (within match_m, same class): the model's element stands, nothing is added
    keep = Persistence(grid, frames=1, match_m=1.0)
    keep.step([line], "scene-a", 0, poses[0])
    again = {**line, "pts": in_frame(1) + [0.0, 0.4], "score": 0.6}
    assert keep.step([again], "scene-a", 1, poses[1]) == [again]
    # of another class: not the same element, so the missed one is kept next to it
    other = {**again, "label": 0}
    assert len(keep.step([other], "scene-b", 0, poses[0])) == 1  # another scene starts on its own
    keep = Persistence(grid, frames=1)
    keep.step([line], "scene-a", 0, poses[0])
    assert len(keep.step([other], "scene-a", 1, poses[1])) == 2


def test_persistence_starts_anew_on_a_gap_a_repeat_or_a_jump_and_cuts_at_the_grid():
    from instagram_hdmap.persistence import Persistence

    grid = BEVGrid(-30.0, 30.0, -15.0, 15.0, 0.15)
    line = {"pts": np.array([[5.0, 3.0], [15.0, 3.0]]), "label": 0, "closed": False, "score": 0.9}
    for frame, pose in ((2, _pose(1.0, 0.0, 0.0)),  # frame 1 is missing
                        (0, _pose(1.0, 0.0, 0.0)),  # a repeat of frame 0 (streaming padding)
                        (1, _pose(30.0, 0.0, 0.0))):  # a pose jump of 30 m > max_jump_m
        keep = Persistence(grid, frames=1, max_jump_m=10.0)
        keep.step([line], "s", 0, _pose(0.0, 0.0, 0.0))
        assert keep.step([], "s", frame, pose) == []
    # the ego drives 20 m on: of the points 25..35 m ahead only those inside the grid (x <= 30) stay
    ahead = {**line, "pts": np.stack([np.linspace(25.0, 45.0, 11), np.full(11, 2.0)], 1)}
    keep = Persistence(grid, frames=1)
    keep.step([ahead], "s", 0, _pose(0.0, 0.0, 0.0))
    (kept,) = keep.step([], "s", 1, _pose(8.0, 0.0, 0.0))
    assert kept["pts"][:, 0].max() <= 30.0 and kept["pts"][:, 0].min() == pytest.approx(17.0)
    # a closed polygon cut by the grid is no longer closed
    square = {"pts": np.array([[26.0, 0.0], [34.0, 0.0], [34.0, 4.0], [26.0, 4.0], [26.0, 0.0]]), "label": 1,
              "closed": True, "score": 0.9}
    keep = Persistence(grid, frames=1)
    keep.step([square], "s", 0, _pose(0.0, 0.0, 0.0))
    assert keep.step([], "s", 1, _pose(0.0, 0.0, 0.0))[0]["closed"] is False
    # a batch: interleaved scenes each keep their own state
    keep = Persistence(grid, frames=1)
    keep([[line], []], ["a", "b"], torch.tensor([0, 0]), torch.from_numpy(np.stack([np.eye(4)] * 2)))
    out = keep([[], []], ["a", "b"], [1, 1], np.stack([np.eye(4)] * 2))
    assert [len(o) for o in out] == [1, 0]
    assert Persistence.from_config(load_config(None, [*TINY])) is None  # off by default


def test_evaluation_with_persistence_only_adds_elements(tiny_world, tmp_path):
    # the same single-frame checkpoint evaluated with and without model.temporal.persist_frames: every
    # sample's predictions with it are those without it plus the kept ones, and the note counts them
    from instagram_hdmap.checkpoint import save_checkpoint
    from instagram_hdmap.config import config_to_dict
    from instagram_hdmap.evaluate_split import run_evaluation
    from instagram_hdmap.evaluation.io import read_submission

    cfg = _drive_cfg(tiny_world, tmp_path / "run", "eval.batch_size=2", "model.gnn.conf_threshold=0.0",
                     "model.gnn.match_threshold=0.01", "model.temporal.memory=none")
    torch.manual_seed(3)
    save_checkpoint({"model": build_model(cfg).state_dict(), "config": config_to_dict(cfg)}, tmp_path / "s.pt")
    plain = run_evaluation(cfg, tmp_path / "s.pt", out=tmp_path / "plain")
    kept = run_evaluation(cfg, tmp_path / "s.pt", out=tmp_path / "kept",
                          overrides=["model.temporal.persist_frames=2", "model.temporal.persist_decay=0.5"])
    a = read_submission(tmp_path / "plain" / "submission.json", "pred").samples
    b = read_submission(tmp_path / "kept" / "submission.json", "pred").samples
    assert list(a) == list(b)
    extra = 0
    for token in a:
        assert len(b[token]) >= len(a[token])
        for x, y in zip(a[token], b[token]):
            np.testing.assert_allclose(x["pts"], y["pts"], atol=1e-5)
            assert x["score"] == pytest.approx(y["score"])
        extra += len(b[token]) - len(a[token])
        assert all(y["score"] <= 0.5 for y in b[token][len(a[token]):])  # kept ones: decayed scores
    assert extra > 0, "a random model's output changes from frame to frame: something must have been kept"
    assert any(f"{extra} map elements found in earlier frames" in n for n in kept["notes"])
    assert sum(kept["metrics"]["num_pred"].values()) == sum(plain["metrics"]["num_pred"].values()) + extra


def test_benchmark_persist_evaluates_the_trained_checkpoint_again(monkeypatch, tmp_path):
    """benchmarks/temporal.py --persist: a finished run is evaluated again with the persistence overrides (which win
    over the checkpoint's saved config), into its own result file; nothing is trained."""
    import argparse
    import importlib.util
    import json
    from pathlib import Path

    spec = importlib.util.spec_from_file_location(
        "bench_temporal", Path(__file__).resolve().parents[1] / "benchmarks" / "temporal.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    args = argparse.Namespace(memory="bev+graph", temporal_override=[], out=str(tmp_path), steps=10, minutes=1.0,
                              occluders=0.0, override=[], val_scenes=12, val_occluders=None, val_dropout=None,
                              threads=None, persist=2, persist_decay=0.25)
    assert bench.result_name(args) == "result_val12_persist2x0.25.json"
    run = tmp_path / "single_seed0"
    (run / "run").mkdir(parents=True)
    (run / "result_val12.json").write_text(json.dumps({"steps": 10, "train_s": 1.0}))  # trained before
    calls = []

    def fake_evaluation(cfg, checkpoint, protocol, out, overrides=()):
        calls.append((Path(checkpoint), list(overrides)))
        return {"metrics": {"mAP": 0.5, "AP_class": {"divider": 0.5}, "consistency": {
            "flicker": {}, "flicker_mean": 0.1, "flicker_detected": {}, "flicker_detected_mean": 0.2, "pairs": {},
            "pairs_detected": {}}, "cmap": {"C-mAP": 0.4, "C-AP_class": {"divider": 0.4}}}}

    monkeypatch.setattr("instagram_hdmap.train.train", lambda *a, **k: pytest.fail("trained again"))
    monkeypatch.setattr("instagram_hdmap.evaluate_split.run_evaluation", fake_evaluation)
    monkeypatch.setattr("instagram_hdmap.demo.world_overrides", lambda root: [])
    result = bench.run_one("single", 0, args, (None, None), "single")
    assert calls == [(run / "run" / "last.pt", ["model.temporal.persist_frames=2",
                                                  "model.temporal.persist_decay=0.25", "eval.cmap=true"])]
    assert result["steps"] == 10 and result["C-mAP"] == 0.4 and (run / "result_val12_persist2x0.25.json").is_file()
    # without --persist the evaluation pins persistence off (configs/temporal/synthetic.yaml ships it on): a result
    # named without _persist is of the plain decoding whatever config the checkpoint was trained with
    calls.clear()
    (run / "result_val12_drop0.json").unlink(missing_ok=True)
    args.persist, args.persist_decay, args.val_dropout = 0, 0.5, 0.0
    bench.run_one("single", 0, args, (None, None), "single")
    assert calls[0][1][:2] == ["model.temporal.persist_frames=0", "model.temporal.persist_decay=0.5"]
    from instagram_hdmap.config import load_config

    assert load_config(bench.CONFIGS["temporal"]).model.temporal.persist_frames == 2


def test_benchmark_takes_one_base_checkpoint_named_two_ways(tmp_path, monkeypatch):
    """benchmarks/temporal.py refuses a result trained with other options in the same --out; the same base
    checkpoint named relatively by one command and absolutely (or through a link) by another is the same option."""
    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location(
        "bench_temporal", Path(__file__).resolve().parents[1] / "benchmarks" / "temporal.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    (tmp_path / "runs").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "runs")
    monkeypatch.chdir(tmp_path)
    rel = {"occluders": 0.7, "train": ["train.max_steps=3", "train.init_from=runs/single_seed2/run/last.pt"]}
    for other in (f"{tmp_path}/runs/single_seed2/run/last.pt", "link/single_seed2/run/last.pt"):
        absolute = {"occluders": 0.7, "train": ["train.max_steps=3", f"train.init_from={other}"]}
        assert bench.same_paths(rel) == bench.same_paths(absolute)
    elsewhere = {"occluders": 0.7, "train": ["train.max_steps=3", "train.init_from=runs/single_seed3/run/last.pt"]}
    assert bench.same_paths(rel) != bench.same_paths(elsewhere)
    assert bench.same_paths({"occluders": 0.0}) == {"occluders": 0.0, "train": []}
