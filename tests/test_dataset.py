"""data/local_map.py, data/transforms.py, data/nuscenes.py: local map protocol, image warp and
calibration consistency, the sample dict and its collate, bad input."""

from __future__ import annotations

import json
import math
import re
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from instagram_hdmap.config import load_config
from instagram_hdmap.data.local_map import BOUNDARY, DIVIDER, PED_CROSSING, LocalMapBuilder, MapError
from instagram_hdmap.data.transforms import (
    ImageAug,
    ImageError,
    denormalize,
    image_to_ground,
    load_image,
    project_to_image,
)
from instagram_hdmap.geometry import BEVGrid

GRID = BEVGrid(-30.0, 30.0, -15.0, 15.0, 0.15, 8)


# --- a hand-made map expansion file -----------------------------------------------------------------

_LAYERS = ("drivable_area", "road_segment", "road_block", "lane", "ped_crossing", "walkway", "stop_line",
           "carpark_area", "road_divider", "lane_divider", "traffic_light", "lane_connector")


class _MapWriter:
    """Writes the minimal map expansion JSON the devkit's NuScenesMap reads (version 1.3)."""

    def __init__(self, transform=lambda p: p):
        self.tf = transform
        self.obj = {"version": "1.3", "canvas_edge": [3000.0, 3000.0], "node": [], "line": [], "polygon": [],
                    "arcline_path_3": {}, "connectivity": {}, **{k: [] for k in _LAYERS}}

    def _nodes(self, pts) -> list[str]:
        tokens = []
        for x, y in self.tf(np.asarray(pts, dtype=float)):
            tokens.append(f"n{len(self.obj['node'])}")
            self.obj["node"].append({"token": tokens[-1], "x": float(x), "y": float(y)})
        return tokens

    def polygon(self, layer: str, exterior, holes=()) -> None:
        token = f"p{len(self.obj['polygon'])}"
        self.obj["polygon"].append({"token": token, "exterior_node_tokens": self._nodes(exterior),
                                    "holes": [{"node_tokens": self._nodes(h)} for h in holes]})
        rec = {"token": f"{layer}{len(self.obj[layer])}", "polygon_token": token}
        if layer == "lane":
            rec.update(left_lane_divider_segments=[], right_lane_divider_segments=[])
        self.obj[layer].append(rec)

    def line(self, layer: str, pts) -> None:
        token = f"l{len(self.obj['line'])}"
        self.obj["line"].append({"token": token, "node_tokens": self._nodes(pts)})
        self.obj[layer].append({"token": f"{layer}{len(self.obj[layer])}", "line_token": token})

    def write(self, dataroot: Path, location: str) -> None:
        path = dataroot / "maps" / "expansion" / f"{location}.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.obj))


def _rect(x0, x1, y0, y1):
    return [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]


def write_test_map(dataroot: Path, location: str, transform=lambda p: p) -> None:
    """Around the origin: a road x in [-100, 100], y in [-8, 8] with an island x in [5, 15], |y| < 2
    (road_segment), a lane along its right edge, a road divider along y = 0, a lane divider that leaves
    the patch laterally and comes back (two pieces), a ped crossing inside the patch and one cut by its
    front edge, and a lane polygon far away."""
    m = _MapWriter(transform)
    m.polygon("road_segment", _rect(-100, 100, -8, 8), holes=[_rect(5, 15, -2, 2)[::-1]])
    m.polygon("lane", _rect(-100, 100, -8, -4))
    m.polygon("lane", _rect(500, 520, 500, 520))
    m.line("road_divider", [[-100, 0], [100, 0]])
    m.line("lane_divider", [[-10, 4], [0, 20], [10, 4]])
    m.polygon("ped_crossing", _rect(-20, -17, -6, 6))
    m.polygon("ped_crossing", _rect(27, 33, -6, 6))
    m.write(dataroot, location)


def _rotation(yaw: float, t=(0.0, 0.0)):
    c, s = math.cos(yaw), math.sin(yaw)
    return lambda p: p @ np.array([[c, s], [-s, c]]) + np.asarray(t)


@pytest.fixture(scope="module")
def map_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("handmap")
    write_test_map(root, "singapore-onenorth")
    write_test_map(root, "boston-seaport", _rotation(0.7, (1234.5, -321.0)))
    return root


def _by_class(polys, k):
    return [p for p in polys if p["label"] == k]


def test_local_map_protocol(map_root):
    polys = LocalMapBuilder(map_root, GRID, sample_dist=1.5, ped_crossing="union")("singapore-onenorth", 0.0, 0.0, 0.0)
    dividers, peds, bounds = (_by_class(polys, k) for k in (DIVIDER, PED_CROSSING, BOUNDARY))
    assert len(dividers) == 3  # the road divider and the two pieces of the lane divider
    assert len(peds) == 2 and all(p["closed"] for p in peds)
    assert len(bounds) == 3 and sum(p["closed"] for p in bounds) == 1  # two road edges + the island
    for p in polys:
        pts = p["pts"]
        assert pts.dtype == np.float64 and pts.shape[1] == 2
        assert GRID.inside_m(pts).all()  # nothing outside the patch
        steps = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        assert steps.max() <= 1.5 + 1e-6 and steps.min() > 0
        if p["closed"]:
            assert len(pts) >= 4 and np.array_equal(pts[0], pts[-1])
    # the divider along y = 0 spans the whole patch, resampled every 1.5 m plus its end point
    (road_div,) = [p for p in dividers if np.abs(p["pts"][:, 1]).max() < 1e-6]
    assert road_div["pts"][0, 0] == pytest.approx(-30, abs=2e-3)
    assert road_div["pts"][-1, 0] == pytest.approx(30, abs=2e-3)
    assert np.allclose(np.diff(road_div["pts"][:-1, 0]), 1.5)
    # the crossing cut by the front edge stays closed along the edge
    cut = max(peds, key=lambda p: p["pts"][:, 0].max())
    assert cut["pts"][:, 0].max() == pytest.approx(30, abs=2e-3) and cut["pts"][:, 0].min() == pytest.approx(27)
    # road edges are cut 0.2 m inside the patch (the patch border is no boundary); the island is a ring
    edges = [p for p in bounds if not p["closed"]]
    assert sorted(round(float(np.abs(p["pts"][:, 1]).mean()), 3) for p in edges) == [8.0, 8.0]
    for p in edges:
        assert p["pts"][:, 0].min() == pytest.approx(-29.8) and p["pts"][:, 0].max() == pytest.approx(29.8)
    (island,) = [p for p in bounds if p["closed"]]
    assert island["pts"].min(0) == pytest.approx([5, -2]) and island["pts"].max(0) == pytest.approx([15, 2])


def test_local_map_follows_the_pose(map_root):
    """The same map moved by a rigid transform, seen from the moved pose, gives the same local map."""
    builder = LocalMapBuilder(map_root, GRID, sample_dist=1.5)
    a = builder("singapore-onenorth", 3.0, -1.0, 0.3)
    x, y = _rotation(0.7, (1234.5, -321.0))(np.array([[3.0, -1.0]]))[0]
    b = builder("boston-seaport", x, y, 0.3 + 0.7)
    assert len(a) == len(b)
    key = lambda p: (p["label"], round(float(p["pts"][:, 0].mean()), 2), round(float(p["pts"][:, 1].mean()), 2))  # noqa: E731
    for p, q in zip(sorted(a, key=key), sorted(b, key=key)):
        assert p["label"] == q["label"] and p["closed"] == q["closed"] and p["pts"].shape == q["pts"].shape
        assert np.abs(p["pts"] - q["pts"]).max() < 1e-6
    # far from every element: an empty map, no error
    assert builder("singapore-onenorth", 2000.0, 2000.0, 0.0) == []


def test_local_map_long_range_grid(map_root):
    grid = BEVGrid(-50.0, 50.0, -50.0, 50.0, 0.25, 8)
    polys = LocalMapBuilder(map_root, grid)("singapore-onenorth", 0.0, 0.0, math.pi / 2)
    assert all(grid.inside_m(p["pts"]).all() for p in polys)
    # yaw 90 deg: the road runs along the ego's y axis now
    (road_div,) = [p for p in polys if p["label"] == DIVIDER and np.abs(p["pts"][:, 0]).max() < 1e-6]
    assert road_div["pts"][:, 1].min() == pytest.approx(-50, abs=2e-3)


def test_missing_map_file_is_a_user_error(tmp_path):
    with pytest.raises(MapError, match=r"maps/expansion/singapore-hollandvillage\.json"):
        LocalMapBuilder(tmp_path, GRID)("singapore-hollandvillage", 0.0, 0.0, 0.0)
    bad = tmp_path / "maps" / "expansion" / "boston-seaport.json"
    bad.parent.mkdir(parents=True)
    bad.write_text("{not json")
    with pytest.raises(MapError, match="boston-seaport.json"):
        LocalMapBuilder(tmp_path, GRID)("boston-seaport", 0.0, 0.0, 0.0)


# --- image decode / warp ------------------------------------------------------------------------------


def _pattern(u, v):
    return 128 + 60 * np.sin(2 * np.pi * u / 64) + 50 * np.cos(2 * np.pi * v / 48)


@pytest.fixture(scope="module")
def pattern_jpeg(tmp_path_factory) -> Path:
    """A 1600 x 900 JPEG whose blue channel is a smooth function of the original pixel position."""
    v, u = np.mgrid[0:900, 0:1600].astype(np.float64)
    blue = np.clip(_pattern(u, v), 0, 255).astype(np.uint8)
    path = tmp_path_factory.mktemp("img") / "pattern.jpg"
    cv2.imwrite(str(path), np.stack([blue, 255 - blue, blue // 2], -1), [cv2.IMWRITE_JPEG_QUALITY, 97])
    return path


@pytest.mark.parametrize("out_hw", [(128, 352), (256, 704)])
@pytest.mark.parametrize("aug", [ImageAug(), ImageAug(1.05, 0.04, -0.05, 5.4), ImageAug(0.95, -0.05, 0.05, -5.4)])
@pytest.mark.parametrize("reduced", [True, False])
def test_post_rot_tran_describe_the_warp(pattern_jpeg, out_hw, aug, reduced):
    """Every network pixel shows the original image at inverse(post_rot, post_tran) of its position,
    with and without the reduced JPEG decode and augmentation; a 1-original-pixel error in the
    matrices would show (checked against a shifted reference)."""
    image, post_rot, post_tran = load_image(pattern_jpeg, (1600, 900), out_hw, aug, reduced)
    h, w = out_hw
    assert image.shape == (3, h, w) and image.dtype == torch.float32
    assert post_rot.shape == (3, 3) and post_tran.shape == (3,) and post_tran[2] == 0 and post_rot[2, 2] == 1
    blue = denormalize(image)[2].numpy() * 255
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    A, t = post_rot[:2, :2].double().numpy(), post_tran[:2].double().numpy()
    orig = (np.stack([u, v], -1) - t) @ np.linalg.inv(A).T
    inside = (orig[..., 0] > 3) & (orig[..., 0] < 1596) & (orig[..., 1] > 3) & (orig[..., 1] < 896)
    assert inside.mean() > 0.8
    err = np.abs(blue - np.clip(_pattern(orig[..., 0], orig[..., 1]), 0, 255))[inside].mean()
    err_shifted = np.abs(blue - np.clip(_pattern(orig[..., 0] + 1, orig[..., 1]), 0, 255))[inside].mean()
    assert err < 2.5 and err_shifted > err + 1.0, (err, err_shifted)


@pytest.mark.parametrize("aug", [ImageAug(), ImageAug(1.05, 0.04, -0.05, 5.4)])
@pytest.mark.parametrize("reduced", [True, False])
def test_stretch_fit_resizes_the_whole_image_each_axis_on_its_own(pattern_jpeg, aug, reduced):
    """data.image_fit=stretch (the official loader): 1600 x 900 -> 352 x 128 by (352/1600, 128/900), no
    crop, and post_rot / post_tran still describe the warp (same check as above)."""
    image, post_rot, post_tran = load_image(pattern_jpeg, (1600, 900), (128, 352), aug, reduced, fit="stretch")
    if aug == ImageAug():
        sx, sy = 352 / 1600, 128 / 900
        torch.testing.assert_close(post_rot[:2, :2], torch.diag(torch.tensor([sx, sy])))
        torch.testing.assert_close(post_tran[:2], torch.tensor([0.5 * sx - 0.5, 0.5 * sy - 0.5]))
    blue = denormalize(image)[2].numpy() * 255
    v, u = np.mgrid[0:128, 0:352].astype(np.float64)
    A, t = post_rot[:2, :2].double().numpy(), post_tran[:2].double().numpy()
    orig = (np.stack([u, v], -1) - t) @ np.linalg.inv(A).T
    inside = (orig[..., 0] > 3) & (orig[..., 0] < 1596) & (orig[..., 1] > 3) & (orig[..., 1] < 896)
    assert inside.mean() > (0.97 if aug == ImageAug() else 0.8)
    err = np.abs(blue - np.clip(_pattern(orig[..., 0], orig[..., 1]), 0, 255))[inside].mean()
    err_shifted = np.abs(blue - np.clip(_pattern(orig[..., 0] + 1, orig[..., 1]), 0, 255))[inside].mean()
    # a 7x vertical shrink area-averages the pattern's 48-px period (~3 levels), hence a looser bound
    assert err < 4.0 and err_shifted > err + 1.0, (err, err_shifted)


def test_camera_projection_round_trip():
    K = torch.tensor([[1266.0, 0, 816.0], [0, 1266.0, 491.0], [0, 0, 1]])
    # a front camera 1.5 m up, looking along +x (camera z forward, x right, y down)
    rot = torch.tensor([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    trans = torch.tensor([1.7, 0.0, 1.5])
    post_rot = torch.tensor([[0.25, 0.03, 0], [-0.03, 0.25, 0], [0, 0, 1]])
    post_tran = torch.tensor([-24.0, -70.0, 0])
    pts = torch.tensor([[10.0, 2.0, 0.0], [25.0, -4.0, 0.0], [6.0, 0.5, 0.0]])
    uv, depth = project_to_image(pts, K, rot, trans, post_rot, post_tran)
    assert (depth > 0).all()
    assert torch.allclose(image_to_ground(uv, K, rot, trans, post_rot, post_tran), pts, atol=1e-3)


def test_bad_images(tmp_path, pattern_jpeg):
    with pytest.raises(ImageError, match="missing.jpg"):
        load_image(tmp_path / "missing.jpg", (1600, 900), (128, 352))
    truncated = tmp_path / "truncated.jpg"
    truncated.write_bytes(pattern_jpeg.read_bytes()[:5000])
    with pytest.raises(ImageError, match="truncated.jpg"):
        load_image(truncated, (1600, 900), (128, 352))
    garbage = tmp_path / "garbage.jpg"
    garbage.write_bytes(b"this is not an image")
    with pytest.raises(ImageError, match="garbage.jpg"):
        load_image(garbage, (1600, 900), (128, 352))
    with pytest.raises(ImageError, match="expected"):  # the sample_data size is wrong
        load_image(pattern_jpeg, (1280, 720), (128, 352))


# --- splits ----------------------------------------------------------------------------------------


def test_official_and_custom_splits(tmp_path):
    from types import SimpleNamespace

    from instagram_hdmap.data.nuscenes import DatasetError, split_scene_names

    nusc = SimpleNamespace(dataroot=str(tmp_path), scene=[{"name": n} for n in
                                                         ("scene-0061", "scene-0103", "scene-0553", "scene-0001")])
    assert split_scene_names(nusc, "v1.0-mini", "train") == ["scene-0061", "scene-0553"]
    assert split_scene_names(nusc, "v1.0-mini", "val") == ["scene-0103"]
    assert split_scene_names(nusc, "v1.0-trainval", "train") == ["scene-0061", "scene-0001"]
    assert split_scene_names(nusc, "v1.0-trainval", "val") == ["scene-0103", "scene-0553"]
    splits = tmp_path / "splits.json"
    splits.write_text(json.dumps({"train": ["scene-0001"], "val": ["scene-0061", "scene-0103"]}))
    assert split_scene_names(nusc, "anything", "val", str(splits)) == ["scene-0061", "scene-0103"]
    assert split_scene_names(nusc, "anything", "val", "splits.json") == ["scene-0061", "scene-0103"]  # dataroot
    with pytest.raises(DatasetError, match="no official split"):
        split_scene_names(nusc, "v9-custom", "train")
    with pytest.raises(DatasetError, match="has no list of scene names for split 'test'"):
        split_scene_names(nusc, "anything", "test", str(splits))
    splits.write_text(json.dumps({"train": ["scene-9999"]}))
    with pytest.raises(DatasetError, match="scene-9999"):
        split_scene_names(nusc, "anything", "train", str(splits))


# --- the dataset on the synthetic world ---------------------------------------------------------------

SAMPLE_KEYS = {
    "images", "intrinsics", "cam_to_ego_rot", "cam_to_ego_trans", "post_rot", "post_tran", "ego_pose",
    "ground_height", "sample_token", "gt_polylines", "gt_vertex_cells", "gt_distance", "gt_vertices_px",
    "gt_vertex_mask", "gt_vertex_labels", "gt_vertex_instance", "gt_vertex_order", "gt_vertex_next", "gt_vertex_prev",
    "scene", "frame_index", "scene_start", "timestamp_us",
}


def check_scenes(dataset, scene_names: list[str]) -> None:
    """The dataset's drives: each scene's samples contiguous, in time order, frames counted from 0, and
    the sample dict's scene keys (a temporal model's stream; docs/conventions.md)."""
    idx = dataset.scenes
    assert idx.names == scene_names
    assert [i for run in idx.runs for i in run] == list(range(len(dataset)))
    for run in idx.runs:
        assert [idx.frame[i] for i in run] == list(range(len(run)))
        assert all(idx.timestamp_us[a] < idx.timestamp_us[b] for a, b in zip(run, run[1:]))
        assert len({idx.scene[i] for i in run}) == 1
    for i in (idx.runs[-1][0], idx.runs[-1][-1]):
        s = dataset[i]
        assert s["scene"] == idx.scene[i] and int(s["frame_index"]) == idx.frame[i]
        assert bool(s["scene_start"]) == (idx.frame[i] == 0) and int(s["timestamp_us"]) == idx.timestamp_us[i]
        assert s["frame_index"].dtype == torch.int64 and s["scene_start"].dtype == torch.bool
        torch.testing.assert_close(s["ego_pose"], dataset.ego_pose(i))


@pytest.fixture(scope="module")
def train_set(tiny_world_cfg):
    from instagram_hdmap.data.nuscenes import NuScenesMapDataset

    return NuScenesMapDataset(tiny_world_cfg, "train")


def test_sample_keys_shapes_dtypes(train_set, tiny_world_cfg):
    assert len(train_set) == 6
    s = train_set[0]
    assert set(s) == SAMPLE_KEYS
    V, (h, w) = 6, tiny_world_cfg.data.image_size
    g = train_set.grid
    M = len(s["gt_vertices_px"])
    expect = {
        "images": ((V, 3, h, w), torch.float32), "intrinsics": ((V, 3, 3), torch.float32),
        "cam_to_ego_rot": ((V, 3, 3), torch.float32), "cam_to_ego_trans": ((V, 3), torch.float32),
        "post_rot": ((V, 3, 3), torch.float32), "post_tran": ((V, 3), torch.float32),
        "ego_pose": ((4, 4), torch.float32), "ground_height": ((), torch.float32),
        "gt_vertex_cells": ((g.Hc, g.Wc), torch.int64),
        "gt_distance": ((3, g.H, g.W), torch.float32), "gt_vertices_px": ((M, 2), torch.float32),
        "gt_vertex_mask": ((M,), torch.bool),
        **{f"gt_vertex_{k}": ((M,), torch.int64) for k in ("labels", "instance", "order", "next", "prev")},
    }
    for key, (shape, dtype) in expect.items():
        assert tuple(s[key].shape) == shape and s[key].dtype == dtype, key
    assert isinstance(s["sample_token"], str) and s["sample_token"] == train_set.sample_tokens[0]
    assert M > 0 and len(s["gt_polylines"]) > 0
    # normalised images, rotation matrices, a rigid ego pose
    assert -3 < float(s["images"].mean()) < 3 and s["images"].std() > 0.1
    eye = torch.eye(3).expand(V, 3, 3)
    assert torch.allclose(s["cam_to_ego_rot"] @ s["cam_to_ego_rot"].transpose(1, 2), eye, atol=1e-5)
    assert torch.allclose(s["ego_pose"][3], torch.tensor([0.0, 0, 0, 1]))


def test_scenes_frames_and_poses(train_set, tiny_world):
    import json

    splits = json.loads((tiny_world / "splits.json").read_text())
    check_scenes(train_set, splits["train"])
    # consecutive frames of a drive: the ego moves forward a few metres
    run = train_set.scenes.runs[0]
    step = torch.linalg.inv(train_set.ego_pose(run[0])) @ train_set.ego_pose(run[1])
    assert 0.5 < float(step[0, 3]) < 10 and abs(float(step[1, 3])) < 1.0


def with_crossings(cfg, convention: str):
    """``cfg`` with ``data.ped_crossing = convention``."""
    import dataclasses

    return dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, ped_crossing=convention))


@pytest.mark.parametrize("convention", ["edges", "union", "each"])
def test_gt_inside_patch_and_targets_consistent(train_set, convention):
    """Every crossing convention (data.ped_crossing) gives GT inside the patch whose targets round-trip:
    closed crossings (union, each) are cycles of the vertex graph, open ones (edges) paths."""
    from instagram_hdmap.data.nuscenes import NuScenesMapDataset

    check_gt_and_targets(NuScenesMapDataset(with_crossings(train_set.cfg, convention), "train", nusc=train_set.nusc))


def check_gt_and_targets(ds) -> None:
    """The GT of every sample of ``ds`` lies inside the patch, its targets round-trip, and each crossing
    is one cycle (closed conventions) or one path (``edges``) of the vertex graph."""
    from instagram_hdmap.targets import build_targets, cells_to_vertices_px

    convention = ds.data_cfg.ped_crossing
    g, S = ds.grid, ds.grid.cell_size
    n_peds = 0
    for i in range(len(ds)):
        polys = ds.gt_polylines(i)
        for p in polys:
            assert g.inside_m(p["pts"]).all()  # points outside the patch never appear
            assert p["label"] in (0, 1, 2) and p["pts"].shape[0] >= 2
            if p["closed"]:
                assert np.array_equal(p["pts"][0], p["pts"][-1]) and len(p["pts"]) >= 4
            if p["label"] == 1:
                assert p["closed"] == (convention != "edges")
                n_peds += 1
    assert n_peds > 0  # the world has crossings
    s = ds[1]
    t = build_targets(s["gt_polylines"], g)
    for k, v in t.items():
        assert torch.equal(v, s[k]), k
    assert ((s["gt_vertex_cells"] >= 0) & (s["gt_vertex_cells"] <= S * S)).all()
    assert len(cells_to_vertices_px(s["gt_vertex_cells"], S)) == len(s["gt_vertices_px"])
    assert s["gt_distance"].min() == 0 and s["gt_distance"].max() <= 10.0
    # every crossing of the world's GT is one cycle (closed) or one path (open) of the vertex graph
    n_walks = 0
    for i in range(len(ds)):
        polys = ds.gt_polylines(i)
        graph = build_targets(polys, g)
        nxt, prv, inst = graph["gt_vertex_next"].tolist(), graph["gt_vertex_prev"].tolist(), graph["gt_vertex_instance"]
        for k, p in enumerate(polys):
            idx = torch.nonzero(inst == k).flatten().tolist()
            if not (p["label"] == 1 and len(idx) >= 3):
                continue
            j = idx[0] if p["closed"] else next(v for v in idx if prv[v] == -1)
            seen = []
            for _ in idx:
                seen.append(j)
                j = nxt[j]
            assert sorted(seen) == idx and (j == idx[0] if p["closed"] else j == -1)
            n_walks += 1
    assert n_walks > 0


def test_projection_round_trip_with_augmentation(tiny_world_cfg):
    """GT points on the ground, projected into the (augmented) network images and back onto the
    ground plane, return; and the augmented image shows at a projected point what the plain image
    shows at that point's plain projection (calibration and post_rot/post_tran agree with the pixels)."""
    from instagram_hdmap.data.nuscenes import NuScenesMapDataset

    torch.manual_seed(0)
    plain = NuScenesMapDataset(tiny_world_cfg, "train", augment=False)
    aug = NuScenesMapDataset(tiny_world_cfg, "train", nusc=plain.nusc, augment=True)
    a, b = plain[2], aug[2]
    assert not torch.allclose(a["post_rot"], b["post_rot"])  # augmentation is on
    pts = torch.from_numpy(np.concatenate([p["pts"] for p in a["gt_polylines"]])).float()
    pts = torch.cat([pts, torch.zeros(len(pts), 1)], -1)
    h, w = a["images"].shape[-2:]
    n_checked, diffs = 0, []
    for v in range(6):
        calib = [a["intrinsics"][v], a["cam_to_ego_rot"][v], a["cam_to_ego_trans"][v]]
        uv_a, depth = project_to_image(pts, *calib, a["post_rot"][v], a["post_tran"][v])
        uv_b, _ = project_to_image(pts, *calib, b["post_rot"][v], b["post_tran"][v])
        ok = (depth > 1) & (uv_b >= 2).all(-1) & (uv_b[:, 0] < w - 3) & (uv_b[:, 1] < h - 3)
        ok &= (uv_a >= 2).all(-1) & (uv_a[:, 0] < w - 3) & (uv_a[:, 1] < h - 3)
        if not ok.any():
            continue
        back = image_to_ground(uv_b[ok], *calib, b["post_rot"][v], b["post_tran"][v])
        assert torch.allclose(back, pts[ok], atol=2e-2 * float(depth[ok].max()) / 10)
        n_checked += int(ok.sum())

        def at(img, uv):  # bilinear sample [3, h, w] at pixel centres uv [n, 2]
            grid = (uv + 0.5) / uv.new_tensor([w, h]) * 2 - 1
            return torch.nn.functional.grid_sample(img[None], grid[None, None], align_corners=False)[0, :, 0]

        diffs.append((at(a["images"][v], uv_a[ok]) - at(b["images"][v], uv_b[ok])).abs().mean(0))
    assert n_checked > 10
    diffs = torch.cat(diffs)
    # same scene content (normalised units; the images span ~[-2, 2.6]); a wrong matrix gives ~1
    assert float(diffs.median()) < 0.25, float(diffs.median())


def test_collate_equals_one_by_one(train_set):
    from instagram_hdmap.data.base import VERTEX_KEYS, collate_fn

    samples = [train_set[i] for i in (0, 3, 5)]
    batch = collate_fn(samples)
    assert set(batch) == SAMPLE_KEYS
    M = max(len(s["gt_vertices_px"]) for s in samples)
    assert batch["gt_vertices_px"].shape == (3, M, 2) and batch["images"].shape[0] == 3
    assert batch["sample_token"] == [s["sample_token"] for s in samples]
    for b, s in enumerate(samples):
        m = len(s["gt_vertices_px"])
        assert batch["gt_polylines"][b] is s["gt_polylines"]
        for key, value in s.items():
            if isinstance(value, torch.Tensor):
                got = batch[key][b, :m] if key in VERTEX_KEYS else batch[key][b]
                assert torch.equal(got, value), key
        assert not batch["gt_vertex_mask"][b, m:].any()
        for k in ("labels", "instance", "order", "next", "prev"):
            assert (batch[f"gt_vertex_{k}"][b, m:] == -1).all()
        assert (batch["gt_vertices_px"][b, m:] == 0).all()


def test_round_trip_on_world_gt(train_set):
    """World GT -> vertex graph -> polylines: every instance that shares no cell with another one comes
    back within S * res * sqrt(2) / 2 (see tests/test_targets.py::round_trip_error)."""
    from instagram_hdmap.targets import graph_to_polylines, vertex_graph
    from test_targets import round_trip_error

    g = train_set.grid
    bound = g.cell_size * g.resolution * math.sqrt(2) / 2
    n = 0
    for i in range(len(train_set)):
        polys = train_set.gt_polylines(i)
        graph = vertex_graph(polys, g)
        # instances whose candidate cells are shared with another instance lose vertices by design
        cells = [set(map(tuple, (g.px_index(g.m_to_px(p["pts"])) // g.cell_size).tolist())) for p in polys]
        inst = graph["gt_vertex_instance"]
        for k, p in enumerate(polys):
            if any(cells[k] & cells[j] for j in range(len(polys)) if j != k):
                continue
            sel = inst == k
            idx = torch.nonzero(sel).flatten()
            remap = torch.full((len(inst),), -1, dtype=torch.long)
            remap[idx] = torch.arange(len(idx))
            nxt = graph["gt_vertex_next"][idx]
            nxt = torch.where(nxt >= 0, remap[nxt.clamp(min=0)], nxt)
            (q,) = graph_to_polylines(graph["gt_vertices_m"][idx], graph["gt_vertex_labels"][idx], nxt,
                                      min_vertices=1)
            assert round_trip_error(p["pts"], q["pts"]) <= bound
            n += 1
    assert n > 10


# --- bad input -------------------------------------------------------------------------------------


def _world_cfg(root, world_overrides, *extra):
    return load_config(None, [*world_overrides(root), "data.image_size=[64,176]", *extra])


def test_wrong_dataroot_or_version(tiny_world, world_overrides, tmp_path):
    from instagram_hdmap.data.nuscenes import DatasetError, NuScenesMapDataset

    cfg = _world_cfg(tiny_world, world_overrides, f"data.dataroot={tmp_path / 'nowhere'}")
    with pytest.raises(DatasetError, match="dataroot not found: .*nowhere"):
        NuScenesMapDataset(cfg, "train")
    cfg = _world_cfg(tiny_world, world_overrides, "data.version=v0.9-nope")
    version = world_overrides(tiny_world)[1].split("=", 1)[1]
    with pytest.raises(DatasetError, match=rf"'v0.9-nope' not found.*versions in .*: {version}"):
        NuScenesMapDataset(cfg, "train")


def test_missing_map_file(copy_world, world_overrides):
    from instagram_hdmap.data.nuscenes import DatasetError, NuScenesMapDataset

    root = copy_world()
    ds = NuScenesMapDataset(_world_cfg(root, world_overrides), "train")
    location = ds._location(ds.sample_tokens[0])
    (root / "maps" / "expansion" / f"{location}.json").unlink()
    with pytest.raises(MapError, match=rf"maps/expansion/{location}\.json"):
        NuScenesMapDataset(_world_cfg(root, world_overrides), "train", nusc=ds.nusc)
    with pytest.warns(UserWarning, match=rf"{location}\.json"):
        skipping = NuScenesMapDataset(_world_cfg(root, world_overrides, "data.on_bad_sample=skip"), "train",
                                      nusc=ds.nusc)
    at_location = [i for i, t in enumerate(skipping.sample_tokens) if ds._location(t) == location]
    if len(at_location) == len(skipping):  # every sample is at that location: a clear error, no crash
        with pytest.warns(UserWarning), pytest.raises(DatasetError, match="every sample"):
            skipping[0]
    else:
        with pytest.warns(UserWarning):
            s = skipping[at_location[0]]
        assert ds._location(s["sample_token"]) != location


def test_missing_or_corrupt_image(copy_world, world_overrides):
    from instagram_hdmap.data.nuscenes import NuScenesMapDataset

    root = copy_world()
    ds = NuScenesMapDataset(_world_cfg(root, world_overrides), "train")

    def image_of(i, cam):
        sample = ds.nusc.get("sample", ds.sample_tokens[i])
        return root / ds.nusc.get("sample_data", sample["data"][cam])["filename"]

    missing, corrupt = image_of(1, "CAM_BACK"), image_of(3, "CAM_FRONT_LEFT")
    missing.unlink()
    corrupt.write_bytes(corrupt.read_bytes()[: len(corrupt.read_bytes()) // 3])  # truncated JPEG
    with pytest.raises(ImageError, match=rf"{ds.sample_tokens[1]}.*{re.escape(missing.name)}"):
        ds[1]
    with pytest.raises(ImageError, match=rf"{ds.sample_tokens[3]}.*{re.escape(corrupt.name)}"):
        ds[3]
    skip = NuScenesMapDataset(_world_cfg(root, world_overrides, "data.on_bad_sample=skip"), "train", nusc=ds.nusc)
    with pytest.warns(UserWarning, match=re.escape(missing.name)) as record:
        assert skip[1]["sample_token"] == ds.sample_tokens[2]  # the next good sample
    assert len(record) == 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # warned once: no second warning for the same bad sample
        assert skip[1]["sample_token"] == ds.sample_tokens[2]
        assert skip[0]["sample_token"] == ds.sample_tokens[0]
    with pytest.warns(UserWarning, match=re.escape(corrupt.name)):
        assert skip[3]["sample_token"] == ds.sample_tokens[4]


def test_empty_map_around_a_pose(copy_world, world_overrides):
    from instagram_hdmap.data.base import collate_fn
    from instagram_hdmap.data.nuscenes import NuScenesMapDataset, open_nuscenes

    root = copy_world()
    cfg = _world_cfg(root, world_overrides)
    nusc = open_nuscenes(root, cfg.data.version)
    ds = NuScenesMapDataset(cfg, "train", nusc=nusc)
    pose_token = ds._reference_pose(nusc.get("sample", ds.sample_tokens[0]))["token"]
    table = root / cfg.data.version / "ego_pose.json"
    poses = json.loads(table.read_text())
    for p in poses:
        if p["token"] == pose_token:
            p["translation"] = [5e3, 5e3, 0.0]  # far away from every map element (100 km off it is an error: mm?)
    table.write_text(json.dumps(poses))
    ds = NuScenesMapDataset(cfg, "train")
    s = ds[0]
    S = ds.grid.cell_size
    assert s["gt_polylines"] == [] and s["gt_vertices_px"].shape == (0, 2)
    assert (s["gt_vertex_cells"] == S * S).all() and (s["gt_distance"] == cfg.data.dt_clip).all()
    batch = collate_fn([s, ds[1]])
    assert not batch["gt_vertex_mask"][0].any() and batch["gt_vertex_mask"][1].any()


# --- command line ------------------------------------------------------------------------------------


def _cli_args(tiny_world, world_overrides, tmp_path) -> list[str]:
    config = tmp_path / "exp.yaml"
    config.write_text("data:\n  image_size: [128, 352]\n")
    ov = dict(o.split("=", 1) for o in world_overrides(tiny_world))
    extra = [f"data.splits_file={ov['data.splits_file']}"] if "data.splits_file" in ov else []
    return [str(config), *extra, "--dataroot", ov["data.dataroot"], "--version", ov["data.version"]]


def test_export_gt_cli(tiny_world, world_overrides, tiny_world_cfg, tmp_path):
    from instagram_hdmap.cli import main
    from instagram_hdmap.data.nuscenes import NuScenesMapDataset

    out = tmp_path / "gt.json"
    assert main(["export-gt", *_cli_args(tiny_world, world_overrides, tmp_path), "--split", "val",
                 "--out", str(out)]) == 0
    sub = json.loads(out.read_text())
    assert set(sub) == {"meta", "results"} and sub["meta"]["vector"] is True
    val = NuScenesMapDataset(tiny_world_cfg, "val")
    assert list(sub["results"]) == val.sample_tokens
    for i, token in enumerate(val.sample_tokens):
        polys = val.gt_polylines(i)
        assert len(sub["results"][token]) == len(polys)
        for entry, p in zip(sub["results"][token], polys):
            assert set(entry) == {"pts", "pts_num", "type"} and entry["type"] == p["label"]
            assert entry["pts_num"] == len(entry["pts"]) == len(p["pts"])
            assert np.abs(np.array(entry["pts"]) - p["pts"]).max() < 1e-4
    # a wrong dataroot: exit code 2 and a one-line message naming it
    bad = _cli_args(tiny_world, world_overrides, tmp_path)
    bad[bad.index("--dataroot") + 1] = str(tmp_path / "nowhere")
    assert main(["export-gt", *bad, "--out", str(out)]) == 2


def test_show_gt_cli(tiny_world, world_overrides, tmp_path, capsys):
    from instagram_hdmap.cli import main

    args = _cli_args(tiny_world, world_overrides, tmp_path)
    out = str(tmp_path / "png")
    assert main(["show-gt", *args, "--split", "train", "--index", "1", "--augment", "--out", out]) == 0
    names = {p.name for p in (tmp_path / "png").iterdir()}
    assert names == {"bev_polylines.png", "vertex_cells.png", "distance.png", "cameras.png"}
    for name in names:
        assert cv2.imread(str(tmp_path / "png" / name)).std() > 5  # not blank
    assert main(["show-gt", *args, "--index", "99", "--out", str(tmp_path / "png")]) == 2
    assert "out of range" in capsys.readouterr().err


def test_camera_dropout_blanks_the_same_cameras_for_every_model(tiny_world, world_overrides):
    # data.camera_dropout: a camera's image becomes the ImageNet mean (0 after normalisation) with the given
    # probability, drawn from the sample index alone: the same cameras in every epoch and every run
    from instagram_hdmap.config import load_config
    from instagram_hdmap.data import build_dataset
    from instagram_hdmap.data.base import blank_cameras

    cfg = load_config(None, [*world_overrides(tiny_world), "data.image_size=[32,64]"])
    clear = build_dataset(cfg, cfg.data.train_split, augment=False)
    cfg = load_config(None, [*world_overrides(tiny_world), "data.image_size=[32,64]", "data.camera_dropout=0.5"])
    dropped = build_dataset(cfg, cfg.data.train_split, augment=False)
    blanked = 0
    for i in range(len(clear)):
        a, b = clear.load_sample(i)["images"], dropped.load_sample(i)["images"]
        zero = b.flatten(1).abs().amax(1) == 0
        assert torch.equal(a[~zero], b[~zero])
        assert all(bool((a[v] != 0).any()) for v in zero.nonzero().flatten())  # a real image was blanked
        assert torch.equal(b, dropped.load_sample(i)["images"])  # the same draw every time
        blanked += int(zero.sum())
    assert 0 < blanked < 6 * len(clear)
    # over many samples the share blanked is the probability
    share = np.mean([float(blank_cameras(torch.ones(6, 1, 1, 1), 0.3, i).eq(0).float().mean()) for i in range(2000)])
    assert abs(share - 0.3) < 0.02


def test_a_dataset_kept_in_memory_reads_each_sample_from_disk_once(copy_world, world_overrides, capsys):
    """data.cache_in_memory: after the first read, a sample comes from memory (its images may be gone from disk),
    equal to the first read; a caller's keys stay out of the kept copy; the loader keeps it only when the samples
    fit in half the free memory."""
    from instagram_hdmap import training_data
    from instagram_hdmap.data.nuscenes import NuScenesMapDataset

    root = copy_world()
    cfg = _world_cfg(root, world_overrides, "data.cache_in_memory=true", "data.num_workers=0")
    loader, _, _ = training_data.build_loaders(cfg, 1, with_val=False)
    kept = loader.dataset
    assert kept.kept is not None and list(kept.kept) == [0]  # the first sample sized the cache
    from instagram_hdmap.data.base import sample_bytes

    room = 2.5 * sample_bytes(kept[0]) * len(kept)  # more than twice what the samples need: kept
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(training_data, "memory_available", lambda: (room, "this machine has"))
        assert training_data.build_loaders(cfg, 1, with_val=False)[0].dataset.kept is not None
        mp.setattr(training_data, "memory_available", lambda: (room / 4, "this machine has"))
        capsys.readouterr()
        assert training_data.build_loaders(cfg, 1, with_val=False)[0].dataset.kept is None
    assert "each epoch reads them from disk" in capsys.readouterr().out
    first = [kept[i] for i in range(len(kept))]
    for jpeg in root.glob("samples/CAM_*/*.jpg"):
        jpeg.unlink()
    fresh = NuScenesMapDataset(_world_cfg(root, world_overrides), "train", nusc=kept.nusc)
    with pytest.raises(ImageError):
        fresh[0]  # from disk: the images are gone
    for i, sample in enumerate(first):
        again = kept[i]
        assert again["sample_token"] == sample["sample_token"]
        assert torch.equal(again["images"], sample["images"]) and torch.equal(again["gt_distance"],
                                                                             sample["gt_distance"])
    assert kept.scenes.frame[2] != 0 and bool(kept[(2, True)]["scene_start"])  # a streaming read's own dict
    assert not bool(kept[2]["scene_start"])

