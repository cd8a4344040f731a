"""Argoverse 2: the synthetic world in the AV2 sensor layout (data/synthetic/av2_writer.py) read through
the official ``av2`` API, and the AV2 dataset (data/av2.py): the same sample dict, frames and GT
invariants as nuScenes, calibration round trips, the map is the generator's own geometry, dividers land
on paint, bad input, and the CLI jobs. Skipped when the optional extra is not installed."""

from __future__ import annotations

import json
import math
import re
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

av2 = pytest.importorskip("av2", reason='the Argoverse 2 API is the optional extra: pip install -e ".[av2]"')

import cv2  # noqa: E402
import shapely  # noqa: E402
from av2.datasets.sensor.av2_sensor_dataloader import AV2SensorDataLoader  # noqa: E402
from av2.map.lane_segment import LaneMarkType  # noqa: E402
from av2.map.map_api import ArgoverseStaticMap  # noqa: E402
from av2.structures.cuboid import CuboidList  # noqa: E402
from av2.structures.sweep import Sweep  # noqa: E402
from shapely.geometry import LineString, Polygon  # noqa: E402

from conftest import TINY_WORLD  # noqa: E402
from instagram_hdmap.cli import main  # noqa: E402
from instagram_hdmap.config import AV2_RING_CAMERAS, load_config  # noqa: E402
from instagram_hdmap.data.av2 import AV2MapDataset  # noqa: E402
from instagram_hdmap.data.base import DatasetError  # noqa: E402
from instagram_hdmap.data.local_map import MapError  # noqa: E402
from instagram_hdmap.data.synthetic.av2_writer import CAMERA_DELAY_NS, ego_height, generate_av2_world, log_id  # noqa: E402
from instagram_hdmap.data.synthetic.roads import build_network  # noqa: E402
from instagram_hdmap.data.transforms import image_to_ground, project_to_image  # noqa: E402
from test_dataset import SAMPLE_KEYS, check_gt_and_targets, check_scenes, with_crossings  # noqa: E402
from test_dataset import test_collate_equals_one_by_one as check_collate  # noqa: E402
from test_dataset import test_round_trip_on_world_gt as check_round_trip  # noqa: E402

# grey levels by which paint outshines the asphalt 0.9 m to its sides. tests/test_synth.py uses 15 for
# the nuScenes rig; in the AV2 images (lower cameras, 400 x 303) points 1.6 m off a line pass 15 in
# ~12 % of the cases (texture and sensor noise), 20 in ~4 %, while 98 % of the solid-line points pass 20.
PAINT_CONTRAST = 20.0
# av2_world (conftest.py): the tiny world's drives in the AV2 layout, shared with test_bad_inputs.py


def _cfg(root: Path, *extra: str):
    return load_config(None, ["data.dataset=av2", f"data.dataroot={root}", "data.av2_frame_step=1",
                              "data.image_fit=contain", "data.image_size=[96,128]", *extra])


@pytest.fixture(scope="module")
def av2_train(av2_world):
    return AV2MapDataset(_cfg(av2_world), "train")


@pytest.fixture(scope="module")
def manifest(av2_world) -> dict:
    return json.loads((av2_world / "world.json").read_text())


@pytest.fixture(scope="module")
def nets(manifest) -> dict:
    return {loc: build_network(loc, manifest["seed"]) for loc in sorted(set(manifest["maps"].values()))}


def _copy(av2_world: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "av2_copy"
    shutil.copytree(av2_world, dst)
    return dst


# --- the world through the official API ----------------------------------------------------------


def test_world_loads_through_the_av2_api(av2_world, manifest):
    assert manifest["dataset"] == "av2" and len(manifest["logs"]["train"]) == 2 and len(manifest["logs"]["val"]) == 1
    split = av2_world / "train"
    loader = AV2SensorDataLoader(split, split)
    assert loader.get_log_ids() == sorted(manifest["logs"]["train"])
    for log in loader.get_log_ids():
        sweeps = loader.get_ordered_log_lidar_timestamps(log)
        assert len(sweeps) == 3 and np.all(np.diff(sweeps) == 500_000_000)
        assert loader.get_city_name(log) == manifest["cities"][log].split("_")[0]
        for cam in AV2_RING_CAMERAS:
            pin = loader.get_log_pinhole_camera(log, cam)
            w, h = (303, 400) if cam == "ring_front_center" else (400, 303)  # AV2's portrait front camera
            assert (pin.width_px, pin.height_px) == (w, h)
            for ts in sweeps:
                path = loader.get_closest_img_fpath(log, cam, ts)
                assert path.name == f"{ts + CAMERA_DELAY_NS[cam]}.jpg"
                assert cv2.imread(str(path)).shape == (h, w, 3)
                assert loader.get_city_SE3_ego(log, ts + CAMERA_DELAY_NS[cam]) is not None
        sweep = Sweep.from_feather(loader.get_lidar_fpath(log, sweeps[0]))
        # mostly ground, which lies ego_height below the ego origin (the rear axle, as in real AV2)
        assert 0.33 <= ego_height(log) <= 0.43
        assert sweep.xyz.shape[0] > 1000 and abs(float(np.median(sweep.xyz[:, 2])) + ego_height(log)) < 0.02
        assert all(c.category in ("REGULAR_VEHICLE", "BOX_TRUCK", "BUS")
                   for c in CuboidList.from_feather(split / log / "annotations.feather").cuboids)
        avm = ArgoverseStaticMap.from_map_dir(split / log / "map", build_raster=True)  # ground height raster too
        assert avm.get_scenario_lane_segments() and avm.get_scenario_vector_drivable_areas()
        pose = loader.get_city_SE3_ego(log, sweeps[0])
        assert avm.raster_ground_height_layer.get_ground_height_at_xy(pose.translation[None])[0] == 0.0  # the road
        assert pose.translation[2] == pytest.approx(ego_height(log))  # the ego above it


def test_same_drives_as_the_nuscenes_world(av2_world, manifest, tiny_world, tiny_world_cfg):
    """Scene i of both worlds (same arguments) is the same drive: the same ego poses, AV2's ego origin
    ego_height above the road where nuScenes' lies on it."""
    from instagram_hdmap.data.nuscenes import NuScenesMapDataset

    nus = NuScenesMapDataset(tiny_world_cfg, "train")
    nus_poses = torch.stack([nus.ego_pose(i) for i in range(len(nus))])
    av2_set = AV2MapDataset(_cfg(av2_world), "train")
    for i in range(TINY_WORLD["scenes_train"]):
        log = log_id(manifest["seed"], i)
        own = [k for k, (lg, _) in enumerate(av2_set.samples) if lg == log]
        got = torch.stack([av2_set.ego_pose(k) for k in own])
        want = nus_poses[i * TINY_WORLD["samples_per_scene"]:(i + 1) * TINY_WORLD["samples_per_scene"]].clone()
        want[:, 2, 3] += ego_height(log)
        assert torch.allclose(got, want, atol=1e-4)
        assert [av2_set.ground_height(k) for k in own] == pytest.approx([-ego_height(log)] * len(own), abs=1e-4)


# --- the sample dict ------------------------------------------------------------------------------


def test_sample_dict_has_the_nuscenes_keys_shapes_and_frames(av2_train, tiny_world_cfg):
    from instagram_hdmap.data.nuscenes import NuScenesMapDataset

    nus = NuScenesMapDataset(tiny_world_cfg, "train")[0]
    s = av2_train[0]
    assert set(s) == SAMPLE_KEYS == set(nus)
    V, (h, w) = 7, av2_train.data_cfg.image_size
    for key, ref in nus.items():
        if not isinstance(ref, torch.Tensor):
            assert type(s[key]) is type(ref), key
            continue
        assert s[key].dtype == ref.dtype, key
        shape = tuple(ref.shape)
        if key in ("images", "intrinsics", "cam_to_ego_rot", "cam_to_ego_trans", "post_rot", "post_tran"):
            shape = (V, *shape[1:]) if key != "images" else (V, 3, h, w)
        elif key.startswith("gt_vertex") and key != "gt_vertex_cells" or key == "gt_vertices_px":
            shape = (len(s["gt_vertices_px"]), *shape[1:])
        assert tuple(s[key].shape) == shape, key
    assert s["sample_token"] == av2_train.sample_tokens[0] and re.fullmatch(r"[0-9a-f-]{36}/\d+", s["sample_token"])
    assert av2_train.camera_names == AV2_RING_CAMERAS
    # frames: camera -> ego rotations are rotations, optical axes level and pointing where the name says
    eye = torch.eye(3).expand(V, 3, 3)
    assert torch.allclose(s["cam_to_ego_rot"] @ s["cam_to_ego_rot"].transpose(1, 2), eye, atol=1e-5)
    axes = s["cam_to_ego_rot"][:, :, 2]  # optical axis in the ego frame (x forward, y left)
    assert torch.allclose(axes[:, 2], torch.zeros(V), atol=1e-6)
    assert axes[1, 0] > 0.99  # ring_front_center looks forward
    assert axes[0, 1] > 0.5 and axes[2, 1] < -0.5  # front left / front right
    assert torch.allclose(s["ego_pose"][3], torch.tensor([0.0, 0, 0, 1]))
    # six cameras: a configurable subset, in the order given
    six = AV2MapDataset(_cfg(av2_train.dataroot, f"data.av2_cameras={list(AV2_RING_CAMERAS[:6])}"), "train")[0]
    assert six["images"].shape[0] == 6 and torch.equal(six["intrinsics"], s["intrinsics"][:6])


def test_gt_targets_pass_the_nuscenes_invariants(av2_world):
    cfg = _cfg(av2_world)  # the default 60 m x 30 m grid, as tests/test_dataset.py
    train = AV2MapDataset(cfg, "train")
    for convention in ("edges", "union", "each"):
        check_gt_and_targets(AV2MapDataset(with_crossings(cfg, convention), "train"))
    check_round_trip(train)
    check_collate(train)


def test_logs_are_scenes(av2_world, av2_train):
    split = av2_world / "train"
    check_scenes(av2_train, AV2SensorDataLoader(split, split).get_log_ids())  # a log is a scene
    ts = [int(t.split("/")[1]) // 1000 for t in av2_train.sample_tokens]
    assert av2_train.scenes.timestamp_us == ts


def test_frame_step_subsamples_the_sweeps(av2_world):
    split = av2_world / "train"
    loader = AV2SensorDataLoader(split, split)
    second = AV2MapDataset(_cfg(av2_world, "data.av2_frame_step=2"), "train")
    want = [(log, ts) for log in loader.get_log_ids() for ts in loader.get_ordered_log_lidar_timestamps(log)[::2]]
    assert second.samples == want and len(want) == 2 * 2  # sweeps 0 and 2 of each 3-sweep log


@pytest.mark.parametrize("fit", ["contain", "cover"])
def test_calibration_round_trip(av2_world, fit):
    """Ground points in front of each AV2 camera -> network image (AV2 intrinsics, extrinsics and the
    fit's warp) -> ground plane: the same points; and our projection agrees with av2's own."""
    ds = AV2MapDataset(_cfg(av2_world, f"data.image_fit={fit}"), "train")
    s = ds[1]
    log, _ = ds.samples[1]
    cams = ds._log_cameras(log)
    for v, cam in enumerate(ds.camera_names):
        axis = s["cam_to_ego_rot"][v][:, 2]
        fwd, left = axis[:2] / axis[:2].norm(), torch.stack([-axis[1], axis[0]]) / axis[:2].norm()
        d, lat = torch.meshgrid(torch.linspace(4, 20, 9), torch.linspace(-2, 2, 5), indexing="ij")
        ground = s["cam_to_ego_trans"][v][:2] + d.reshape(-1, 1) * fwd + lat.reshape(-1, 1) * left
        pts = torch.cat([ground, torch.zeros(len(ground), 1)], -1)
        calib = (s["intrinsics"][v], s["cam_to_ego_rot"][v], s["cam_to_ego_trans"][v], s["post_rot"][v],
                 s["post_tran"][v])
        uv, depth = project_to_image(pts, *calib)
        assert (depth > 0).all()
        h, w = s["images"].shape[-2:]
        inside = ((uv >= 0) & (uv <= uv.new_tensor([w - 1, h - 1]))).all(-1)
        assert inside.sum() >= 30, cam  # most of the 45 points are in view (the portrait camera is narrow)
        assert torch.allclose(image_to_ground(uv, *calib), pts, atol=1e-3 * 20), cam
        # av2's projection of the same points (original image pixels) -> our network pixels
        uv_av2, _, _ = cams[cam].project_ego_to_img(pts.double().numpy())
        uv_net = torch.from_numpy(uv_av2[:, :2]).float() @ s["post_rot"][v][:2, :2].T + s["post_tran"][v][:2]
        assert torch.allclose(uv_net, uv, atol=1e-2), cam


# --- the map is the generator's geometry, and the cameras see it ------------------------------------


def _painted_lines(net) -> list[LineString]:
    """The generator's own painted dividers: every lane row, and the centre line of stretches without
    a median (a median stretch's centre paint bounds no lane: AV2 has no divider there)."""
    rec = net.records
    no_median = {st.segment for st in net.stretches if st.chain.median == 0}
    out = net.lines("lane_divider")
    out += [LineString(rec.node_xy(rec.lines[r["line_token"].index])) for r in rec.layers["road_divider"]
            if r["road_segment_token"] in no_median]
    return out


def test_map_through_the_api_is_the_generator_geometry(av2_world, manifest, nets):
    """Around every pose, in the 60 m x 30 m patch: the av2 API's drivable areas union to the
    generator's road surface, its crossings are the generator's, and the painted lane boundaries (the
    divider class) are the generator's painted lines."""
    from instagram_hdmap.data.av2 import load_log_map

    for split in ("train", "val"):
        ds = AV2MapDataset(_cfg(av2_world), split)
        for log in manifest["logs"][split]:
            net = nets[manifest["maps"][log]]
            avm = ArgoverseStaticMap.from_map_dir(av2_world / split / log / "map")
            lmap = load_log_map(av2_world / split / log)
            painted = shapely.union_all(_painted_lines(net))
            for k, (lg, _) in enumerate(ds.samples):
                if lg != log:
                    continue
                pose = ds._pose(k)
                x, y = pose.translation[:2]
                patch = ds.map_builder.patch_global(float(x), float(y), math.atan2(pose.rotation[1, 0],
                                                                                    pose.rotation[0, 0]))
                areas = shapely.union_all([Polygon(da.xyz[:, :2]) for da in avm.get_scenario_vector_drivable_areas()])
                assert areas.intersection(patch).symmetric_difference(net.road.intersection(patch)).area < 1e-6
                api_peds = [Polygon(pc.polygon[:, :2]).intersection(patch) for pc in avm.get_scenario_ped_crossings()]
                own_peds = [p.intersection(patch) for p in net.polygons("ped_crossing")]
                api_peds = sorted((g for g in api_peds if g.area > 0), key=lambda g: g.centroid.x)
                own_peds = sorted((g for g in own_peds if g.area > 0), key=lambda g: g.centroid.x)
                assert len(api_peds) == len(own_peds)
                assert all(a.symmetric_difference(b).area < 1e-6 for a, b in zip(api_peds, own_peds))
                dividers = shapely.union_all(list(lmap.dividers)).intersection(patch)
                own = painted.intersection(patch)
                assert dividers.length > 0 or own.length == 0
                assert dividers.symmetric_difference(own).length < 1e-6
                assert dividers.hausdorff_distance(own) < 1e-6 if own.length else True


def _hidden(cuboids, ts: int, origin: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """[P] bool: the sight line from ``origin`` (ego frame) to the ground point ``pts`` [P, 3] (ego frame)
    passes through one of the sweep's annotated vehicles, grown by 0.4 m on every side (its shadow)."""
    hidden = np.zeros(len(pts), bool)
    for c in cuboids:
        if c.timestamp_ns != ts:
            continue
        to_obj = c.dst_SE3_object.inverse()
        o, p = to_obj.transform_point_cloud(origin[None])[0], to_obj.transform_point_cloud(pts)
        half = np.array([c.length_m, c.width_m, c.height_m]) / 2 + 0.4
        d = p - o
        with np.errstate(divide="ignore", invalid="ignore"):  # slab test of the segment o -> p
            t1, t2 = (-half - o) / d, (half - o) / d
        t_in = np.nanmax(np.minimum(t1, t2), axis=1)
        t_out = np.nanmin(np.maximum(t1, t2), axis=1)
        hidden |= (t_in <= t_out) & (t_out >= 0) & (t_in <= 1)
    return hidden


def _pixels(city_xy: np.ndarray, ego_from_city, pin, cuboids, ts) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """City-frame ground points [P, 2] -> rounded image pixels [P, 2], camera depth [P] (av2's
    projection) and whether a vehicle hides them [P]."""
    ego = ego_from_city.transform_point_cloud(np.c_[city_xy, np.zeros(len(city_xy))])
    uv, pc, _ = pin.project_ego_to_img(ego)
    return np.round(uv[:, :2]).astype(int), pc[:, 2], _hidden(cuboids, ts, pin.ego_SE3_cam.translation, ego)


def _paint_stats(av2_world, manifest, solid: bool, offset: float) -> tuple[int, int]:
    """Over all sweeps and ring cameras: (points whose pixels look painted, points tested) along the
    AV2 map's painted lane boundaries (solid or dashed), shifted ``offset`` m sideways, 3-15 m in front
    of the camera, not occluded; ego poses, calibration and images read with the av2 API."""
    painted = total = 0
    for split in ("train", "val"):
        loader = AV2SensorDataLoader(av2_world / split, av2_world / split)
        for log in loader.get_log_ids():
            avm = ArgoverseStaticMap.from_map_dir(av2_world / split / log / "map")
            lines = {}
            for ls in avm.get_scenario_lane_segments():
                for m in (ls.left_lane_marking, ls.right_lane_marking):
                    if m.mark_type in (LaneMarkType.NONE, LaneMarkType.UNKNOWN):
                        continue
                    if (m.mark_type == LaneMarkType.DASHED_WHITE) != (not solid):
                        continue
                    lines[tuple(np.round(m.polyline[:, :2], 2).ravel())] = LineString(m.polyline[:, :2])
            cuboids = CuboidList.from_feather(av2_world / split / log / "annotations.feather").cuboids
            for ts in loader.get_ordered_log_lidar_timestamps(log):
                ego_from_city = loader.get_city_SE3_ego(log, ts).inverse()
                pts, nrm = [], []
                for line in lines.values():
                    s = np.arange(0.25, line.length - 0.25, 0.5)
                    if len(s) == 0:
                        continue
                    p = shapely.get_coordinates(shapely.line_interpolate_point(line, s))
                    q = shapely.get_coordinates(shapely.line_interpolate_point(line, s + 0.05))
                    dvec = (q - p) / np.linalg.norm(q - p, axis=1, keepdims=True)
                    pts.append(p)
                    nrm.append(np.stack([-dvec[:, 1], dvec[:, 0]], axis=1))
                if not pts:
                    continue
                pts, nrm = np.concatenate(pts), np.concatenate(nrm)
                for cam in AV2_RING_CAMERAS:
                    pin = loader.get_log_pinhole_camera(log, cam)
                    gray = cv2.cvtColor(cv2.imread(str(loader.get_closest_img_fpath(log, cam, ts))),
                                        cv2.COLOR_BGR2GRAY).astype(float)
                    on = [_pixels(pts + (offset + t) * nrm, ego_from_city, pin, cuboids, ts)
                          for t in np.linspace(-0.2, 0.2, 5)]
                    off = [_pixels(pts + (offset + t) * nrm, ego_from_city, pin, cuboids, ts) for t in (-0.9, 0.9)]
                    h, w = gray.shape
                    ok = (on[2][1] > 3.0) & (on[2][1] < 15.0)
                    for uv, depth, hidden in on + off:
                        ok &= (depth > 0.5) & (uv[:, 0] >= 2) & (uv[:, 0] < w - 2)
                        ok &= (uv[:, 1] >= 2) & (uv[:, 1] < h - 2) & ~hidden
                    idx = np.nonzero(ok)[0]
                    paint = np.max([gray[uv[idx, 1], uv[idx, 0]] for uv, _, _ in on], axis=0)
                    asphalt = np.mean([gray[uv[idx, 1], uv[idx, 0]] for uv, _, _ in off], axis=0)
                    painted += int(np.sum(paint - asphalt > PAINT_CONTRAST))
                    total += len(idx)
    return painted, total


def test_projected_dividers_land_on_paint(av2_world, manifest, nets):
    painted, total = _paint_stats(av2_world, manifest, solid=True, offset=0.0)
    assert total > 100 and painted / total > 0.75, (painted, total)
    duty = min(n.style.dash / (n.style.dash + n.style.gap) for n in nets.values())
    painted, total = _paint_stats(av2_world, manifest, solid=False, offset=0.0)
    assert total > 100 and painted / total > 0.6 * duty, (painted, total, duty)
    painted, total = _paint_stats(av2_world, manifest, solid=True, offset=1.6)  # control: inside the lane
    assert total > 100 and painted / total < 0.1, (painted, total)


# --- the world writer: determinism, nothing half-written -------------------------------------------


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_workers_give_byte_identical_av2_worlds(tmp_path):
    args = dict(scenes_train=1, scenes_val=1, samples_per_scene=2, seed=4, image_size="160x121", progress=False)
    one = generate_av2_world(tmp_path / "one", workers=1, **args)
    two = generate_av2_world(tmp_path / "two", workers=2, **args)
    assert one == two and _files(tmp_path / "one") == _files(tmp_path / "two")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["one", "two"]


def test_interrupted_av2_synth_leaves_nothing(tmp_path, monkeypatch):
    from instagram_hdmap.data.synthetic import render

    def boom(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(render.SceneRenderer, "render", boom)
    with pytest.raises(KeyboardInterrupt):
        generate_av2_world(tmp_path / "w", scenes_train=1, scenes_val=0, samples_per_scene=1, image_size="160x121",
                           progress=False)
    assert list(tmp_path.iterdir()) == []


# --- bad input -------------------------------------------------------------------------------------


def _one_line_cli_error(capsys, argv) -> str:
    rc = main(argv)
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1, err
    return err


def test_not_an_av2_root(tiny_world, av2_world, capsys, tmp_path):
    config = Path(__file__).resolve().parents[1] / "configs" / "av2" / "synthetic_demo.yaml"
    err = _one_line_cli_error(capsys, ["export-gt", str(config), "--dataroot", str(tiny_world), "--split", "val",
                                       "--out", str(tmp_path / "gt.json")])
    assert "is not an AV2 sensor-dataset root" in err and str(tiny_world) in err
    with pytest.raises(DatasetError, match="dataroot not found"):
        AV2MapDataset(_cfg(tmp_path / "nowhere"), "train")
    with pytest.raises(DatasetError, match=r"no split folder 'test'"):
        AV2MapDataset(_cfg(av2_world), "test")


def _first_log(root: Path) -> tuple[str, list[int]]:
    loader = AV2SensorDataLoader(root / "train", root / "train")
    log = loader.get_log_ids()[0]
    return log, loader.get_ordered_log_lidar_timestamps(log)


def test_log_without_map_archive(av2_world, tmp_path):
    root = _copy(av2_world, tmp_path)
    log, _ = _first_log(root)
    next((root / "train" / log / "map").glob("log_map_archive_*.json")).unlink()
    ds = AV2MapDataset(_cfg(root), "train")
    bad = [i for i, (lg, _) in enumerate(ds.samples) if lg == log]
    with pytest.raises(MapError, match=rf"log {log}: expected one map archive .*{log}/map/log_map_archive_\*\.json"):
        ds[bad[0]]
    skip = AV2MapDataset(_cfg(root, "data.on_bad_sample=skip"), "train")
    with pytest.warns(UserWarning, match=rf"skipping a bad sample .*{log}"):
        tokens = [skip[i]["sample_token"] for i in range(len(skip))]
    assert skip.num_bad_samples == len(bad) and not any(t.startswith(log) for t in tokens)


def test_missing_image_or_calibration_row(av2_world, tmp_path):
    import pyarrow as pa
    from pyarrow import feather

    root = _copy(av2_world, tmp_path)
    log, sweeps = _first_log(root)
    cameras = root / "train" / log / "sensors" / "cameras"
    (cameras / "ring_side_left" / f"{sweeps[1] + CAMERA_DELAY_NS['ring_side_left']}.jpg").unlink()
    ds = AV2MapDataset(_cfg(root), "train")
    k = ds.sample_tokens.index(f"{log}/{sweeps[1]}")
    with pytest.raises(DatasetError, match=rf"sample {log}/{sweeps[1]}: log {log}: no ring_side_left image within 25 ms"
                                           rf" .*ring_side_left"):
        ds[k]
    skip = AV2MapDataset(_cfg(root, "data.on_bad_sample=skip"), "train")
    with pytest.warns(UserWarning, match="ring_side_left"):
        assert skip[k]["sample_token"] == ds.sample_tokens[k + 1]  # the next good sample
    assert skip.num_bad_samples == 1
    # a calibration row goes missing
    path = root / "train" / log / "calibration" / "intrinsics.feather"
    table = feather.read_table(str(path))
    keep = [n != "ring_rear_left" for n in table.column("sensor_name").to_pylist()]
    feather.write_feather(table.filter(pa.array(keep)), str(path))
    ds = AV2MapDataset(_cfg(root), "train")
    with pytest.raises(DatasetError, match=rf"log {log}: .*intrinsics\.feather has no row for camera ring_rear_left"):
        ds[k - 1]
    ds = AV2MapDataset(_cfg(root, "data.av2_cameras=[ring_front_center,ring_front_left]"), "train")
    assert ds[k - 1]["images"].shape[0] == 2  # the cameras not asked for need no calibration


def test_camera_timestamps_that_do_not_match_the_sweeps(av2_world, tmp_path):
    root = _copy(av2_world, tmp_path)
    log, sweeps = _first_log(root)
    folder = root / "train" / log / "sensors" / "cameras" / "ring_rear_right"
    for p in sorted(folder.glob("*.jpg"), reverse=True):  # every image 100 ms late
        p.rename(folder / f"{int(p.stem) + 100_000_000}.jpg")
    ds = AV2MapDataset(_cfg(root), "train")
    k = ds.sample_tokens.index(f"{log}/{sweeps[0]}")
    with pytest.raises(DatasetError, match=rf"log {log}: no ring_rear_right image within 25 ms of lidar sweep "
                                           rf"{sweeps[0]} .*nearest is .*ring_rear_right/\d+\.jpg, 1\d\d\.0 ms away"
                                           ".*timestamps do not match"):
        ds[k]


# --- the jobs on AV2 ---------------------------------------------------------------------------------


def test_train_evaluate_predict_show_export_on_av2(av2_world, tmp_path, capsys):
    config = tmp_path / "av2.yaml"
    config.write_text(
        "_base_: " + str(Path(__file__).resolve().parents[1] / "configs" / "av2" / "synthetic_demo.yaml") + "\n"
        f"data: {{dataroot: {av2_world}, num_workers: 0}}\n"
        f"train: {{out_dir: {tmp_path / 'run'}, max_steps: 2, log_every: 1, val_every: 1000}}\n")
    assert main(["train", str(config)]) == 0
    ckpt = tmp_path / "run" / "last.pt"
    assert main(["evaluate", str(config), "--checkpoint", str(ckpt), "--out", str(tmp_path / "eval")]) == 0
    metrics = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert metrics["meta"]["num_samples"] == 3 and set(metrics["AP_class"]) == {"divider", "ped_crossing", "boundary"}
    assert main(["export-gt", str(config), "--split", "val", "--out", str(tmp_path / "gt.json")]) == 0
    gt = json.loads((tmp_path / "gt.json").read_text())
    sub = json.loads((tmp_path / "eval" / "submission.json").read_text())
    assert set(gt["results"]) == set(sub["results"]) and gt["meta"]["dataset"] == "av2"
    # the GT as the prediction scores AP 1 under the unchanged vector protocol
    perfect = tmp_path / "perfect.json"
    perfect.write_text(json.dumps({"meta": gt["meta"], "results": {
        t: [{**v, "confidence_level": 1.0} for v in vs] for t, vs in gt["results"].items()}}))
    assert main(["evaluate-json", "--pred", str(perfect), "--gt", str(tmp_path / "gt.json"),
                 "--out", str(tmp_path / "perfect_metrics.json")]) == 0
    ap = json.loads((tmp_path / "perfect_metrics.json").read_text())["AP_class"]
    present = {["divider", "ped_crossing", "boundary"][v["type"]] for vs in gt["results"].values() for v in vs}
    assert present and all(ap[k] == 1.0 for k in present)
    assert main(["predict", str(config), "--checkpoint", str(ckpt), "--index", "1",
                 "--out", str(tmp_path / "pred")]) == 0
    assert main(["show-gt", str(config), "--index", "2", "--out", str(tmp_path / "show")]) == 0
    out = capsys.readouterr().out
    assert re.search(r"sample [0-9a-f-]{36}/\d+ \(split 'val', index 1\)", out)
    for png in ("pred/prediction_cameras.png", "pred/prediction_bev.png", "show/cameras.png"):
        img = cv2.imread(str(tmp_path / png))
        assert img is not None and img.std() > 10, png


def test_random_map_baseline_on_av2(av2_world):
    from instagram_hdmap.demo import random_map_baseline

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = random_map_baseline(_cfg(av2_world), "vector")
    assert set(m["AP_class"]) == {"divider", "ped_crossing", "boundary"} and 0 <= m["mAP"] <= 1


def test_cli_synth_av2(tmp_path, capsys):
    out = tmp_path / "w"
    assert main(["synth", "--format", "av2", "--out", str(out), "--scenes-train", "1", "--scenes-val", "0",
                 "--samples-per-scene", "1", "--image-size", "160x121"]) == 0
    assert "AV2 sensor layout" in capsys.readouterr().out
    (log,) = [p.name for p in (out / "train").iterdir()]
    assert (out / "train" / log / "calibration" / "intrinsics.feather").is_file()
    err = _one_line_cli_error(capsys, ["synth", "--format", "av2", "--out", str(out), "--scenes-train", "1"])
    assert "not empty" in err

