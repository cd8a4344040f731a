"""Map elements that keep their identity along a drive: the track IDs of ``Mapper.stream()`` against the synthetic
world's own crossings (their map-expansion records), new IDs after a reset, none without an ego pose, the
look-back tracker, and the IDs in the HDMapNet JSON (which AP ignores)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch
from pyquaternion import Quaternion
from shapely.geometry import Point, Polygon

from instagram_hdmap import Frame, Mapper, to_hdmapnet
from instagram_hdmap.checkpoint import save_checkpoint
from instagram_hdmap.config import config_to_dict, load_config
from instagram_hdmap.data import build_dataset
from instagram_hdmap.data.rig import CAMERAS
from instagram_hdmap.evaluation.io import read_submission, vectors_to_polylines
from instagram_hdmap.geometry import BEVGrid
from instagram_hdmap.models import build_model
from instagram_hdmap.persistence import InstanceTracker

TINY = __import__("pathlib").Path(__file__).resolve().parents[1] / "configs" / "synthetic" / "tiny.yaml"

# the tiny model on a 60 m x 30 m grid: whole crossings stay in view for several frames
GRID = ["grid.xbound=[-30,30]", "grid.ybound=[-15,15]", "grid.resolution=0.5", "data.ped_crossing=each"]
DRIVE = {"scenes_train": 1, "scenes_val": 0, "samples_per_scene": 12, "seed": 5, "image_size": "160x90"}


@pytest.fixture(scope="module")
def drive(tmp_path_factory, world_overrides):
    from instagram_hdmap.data.synthetic import generate_world

    root = tmp_path_factory.mktemp("drive") / "world"
    generate_world(out=str(root), force=True, progress=False, **DRIVE)
    cfg = load_config(TINY, [*world_overrides(root), *GRID, "data.num_workers=0"])
    return root, cfg, build_dataset(cfg, "train", augment=False)


@pytest.fixture(scope="module")
def mapper(drive, tmp_path_factory):
    _, cfg, _ = drive
    torch.manual_seed(0)
    path = save_checkpoint({"model": build_model(cfg).state_dict(), "config": config_to_dict(cfg)},
                           tmp_path_factory.mktemp("ckpt") / "tiny.pt")
    return Mapper.from_checkpoint(path, "cpu")


def _frame(dataset, index: int) -> Frame:
    nusc, record = dataset.nusc, dataset.nusc.get("sample", dataset.sample_tokens[index])
    intrinsics, cam_to_ego = [], []
    for cam in CAMERAS:
        cs = nusc.get("calibrated_sensor", nusc.get("sample_data", record["data"][cam])["calibrated_sensor_token"])
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = Quaternion(cs["rotation"]).rotation_matrix, cs["translation"]
        intrinsics.append(np.array(cs["camera_intrinsic"]))
        cam_to_ego.append(T)
    images = [str(p) for p, _ in dataset.camera_files(index)]
    return Frame(images, intrinsics, cam_to_ego, ego_pose=dataset.ego_pose(index).double().numpy())


def _scored(polylines: list[dict]) -> list[dict]:
    return [{"closed": False, **p, "score": 1.0} for p in polylines]


def _world_crossings(root, location: str) -> dict[str, Polygon]:
    """The world's ped-crossing records (map expansion) as polygons in world coordinates, by token."""
    m = json.loads((root / "maps" / "expansion" / f"{location}.json").read_text())
    nodes = {n["token"]: (n["x"], n["y"]) for n in m["node"]}
    polygons = {p["token"]: p for p in m["polygon"]}
    return {r["token"]: Polygon([nodes[t] for t in polygons[r["polygon_token"]]["exterior_node_tokens"]])
            for r in m["ped_crossing"]}


def _in_view(polygon: Polygon, pose: np.ndarray, grid: BEVGrid) -> bool:
    xy = np.asarray(polygon.exterior.coords) - pose[:2, 3]
    ego = xy @ pose[:2, :2]  # world -> ego (the rotation's inverse)
    return bool((ego[:, 0] > grid.xmin).all() and (ego[:, 0] < grid.xmax).all() and (ego[:, 1] > grid.ymin).all()
                and (ego[:, 1] < grid.ymax).all())


def _world_token(element, pose: np.ndarray, crossings: dict[str, Polygon]) -> str | None:
    world = element.points @ pose[:2, :2].T + pose[:2, 3]
    centre = Point(world[:-1].mean(0))
    return next((t for t, poly in crossings.items() if poly.contains(centre)), None)


def test_a_stream_keeps_each_crossings_id_while_it_stays_in_view(drive, mapper, monkeypatch):
    """The stream's input is the drive's own map (the model's decoding replaced by each frame's GT): every world
    crossing that stays whole in view from one frame to the next keeps its track ID, distinct crossings have
    distinct IDs, and after a reset every element gets an ID never given before."""
    import instagram_hdmap.mapper as mapper_module

    root, cfg, dataset = drive
    grid = BEVGrid.from_config(cfg.grid)
    crossings = _world_crossings(root, dataset._location(dataset.sample_tokens[0]))
    outputs = iter([[_scored(dataset.gt_polylines(i))] for i in range(len(dataset))] * 2)
    monkeypatch.setattr(mapper_module, "postprocess_batch", lambda *a, **k: next(outputs))
    stream = mapper.stream()
    seen: list[dict[str, int]] = []  # per frame: world crossing token -> track ID
    for i in range(len(dataset)):
        pose = dataset.ego_pose(i).double().numpy()
        elements = stream.step(_frame(dataset, i))
        ids = [e.track_id for e in elements]
        assert all(isinstance(t, int) for t in ids) and len(set(ids)) == len(ids)
        tokens = {}
        for e in elements:
            token = _world_token(e, pose, crossings) if e.label == "ped_crossing" else None
            if token is not None and _in_view(crossings[token], pose, grid):
                tokens[token] = e.track_id
        seen.append(tokens)
    kept = [(seen[k - 1][t], seen[k][t]) for k in range(1, len(seen)) for t in seen[k] if t in seen[k - 1]]
    assert len(kept) >= 3, seen  # the drive passes crossings that stay in view
    assert all(a == b for a, b in kept)
    by_token = {t: {s[t] for s in seen if t in s} for t in set().union(*seen)}
    assert all(len(v) == 1 for v in by_token.values())  # a crossing in view keeps one ID along the drive
    assert len({next(iter(v)) for v in by_token.values()}) == len(by_token)  # distinct crossings, distinct IDs
    before = max(t for s in seen for t in s.values())
    stream.reset()
    again = stream.step(_frame(dataset, 0))
    assert again and min(e.track_id for e in again) > before  # a reset: new IDs, never a reused one
    assert all(e.track_id is None for e in mapper.stream().step(dataclasses.replace(_frame(dataset, 1),
                                                                                    ego_pose=None)))


def test_the_ids_go_into_the_hdmapnet_json_and_ap_ignores_them(mapper, drive, monkeypatch, tmp_path):
    import instagram_hdmap.mapper as mapper_module

    _, _, dataset = drive
    monkeypatch.setattr(mapper_module, "postprocess_batch", lambda *a, **k: [_scored(dataset.gt_polylines(0))])
    elements = mapper.stream().step(_frame(dataset, 0))
    doc = to_hdmapnet({"t": elements})
    assert [v["track_id"] for v in doc["results"]["t"]] == [e.track_id for e in elements]
    path = tmp_path / "s.json"
    path.write_text(json.dumps(doc))
    polys = read_submission(path, "pred", 3).samples["t"]
    assert [p["track_id"] for p in polys] == list(range(len(elements)))
    from instagram_hdmap.evaluation import evaluate_files
    from instagram_hdmap.evaluation.io import submission

    gt = tmp_path / "gt.json"  # the same elements as GT: AP 1 with the IDs there, as without them
    gt.write_text(json.dumps(submission({"t": [{"pts": e.points, "label": e.class_index} for e in elements]},
                                        {"ground_truth": True})))
    untracked = tmp_path / "u.json"
    untracked.write_text(json.dumps(to_hdmapnet({"t": [dataclasses.replace(e, track_id=None) for e in elements]})))
    assert evaluate_files(path, gt)["mAP"] == evaluate_files(untracked, gt)["mAP"]
    with pytest.raises(Exception, match="'track_id' must be an integer >= 0"):
        vectors_to_polylines([{"pts": [[0, 0], [1, 0]], "type": 0, "track_id": -1}], "pred", 3, "here")


def test_a_track_missed_for_a_frame_comes_back_with_its_id_when_the_tracker_looks_back():
    grid = BEVGrid.from_config(load_config(None).grid)
    line = {"pts": np.array([[0.0, 2.0], [10.0, 2.0]]), "label": 0}
    other = {"pts": np.array([[0.0, -6.0], [10.0, -6.0]]), "label": 0}
    poses = [np.eye(4) for _ in range(4)]
    for k, p in enumerate(poses):
        p[0, 3] = 1.0 * k  # 1 m forward a frame: the line moves back by 1 m in the ego frame
    frames = [[line, other], [other], [{**line, "pts": line["pts"] - [2.0, 0.0]}, other], [other]]
    once, back = InstanceTracker(grid), InstanceTracker(grid, look_back=5)
    ids_once = [once.step(f, "s", k, poses[k]) for k, f in enumerate(frames)]
    ids_back = [back.step(f, "s", k, poses[k]) for k, f in enumerate(frames)]
    assert ids_once[2] == [2, 1]  # the previous frame only: the line came back as a new element
    assert ids_back[2] == [0, 1] and ids_back[3] == [1]  # it waited, moved with the ego, and kept its ID
    with pytest.raises(Exception, match="look_back is a count of frames >= 1"):
        InstanceTracker(grid, look_back=0)
