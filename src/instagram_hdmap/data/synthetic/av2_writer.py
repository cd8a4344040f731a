"""``generate_av2_world``: the synthetic world in the Argoverse 2 *sensor dataset* on-disk layout.

::

    DIR/
      train/<log_id>/                      one log per synthetic scene (val/<log_id>/ likewise)
        calibration/intrinsics.feather     ring cameras: sensor_name fx_px fy_px cx_px cy_px k1 k2 k3 height_px width_px
        calibration/egovehicle_SE3_sensor.feather   sensor -> ego: sensor_name qw qx qy qz tx_m ty_m tz_m
        city_SE3_egovehicle.feather        ego -> city: timestamp_ns qw qx qy qz tx_m ty_m tz_m
        sensors/cameras/<ring camera>/<timestamp_ns>.jpg
        sensors/lidar/<timestamp_ns>.feather   x y z (float16, ego frame) intensity laser_number offset_ns
        annotations.feather                vehicle cuboids per sweep (ego frame), AV2's columns
        map/log_map_archive_<log_id>____<CITY>_city_<n>.json   lane segments, pedestrian crossings,
                                           drivable areas around the log's drive
        map/<log_id>_ground_height_surface____<CITY>.npy, map/<log_id>___img_Sim2_city.json
      world.json                           manifest: format, seed, image size, counts, log ids per split

so that ``av2``'s readers (``AV2SensorDataLoader``, ``ArgoverseStaticMap.from_map_dir`` with or without
rasters, ``read_city_SE3_ego``, ``PinholeCamera.from_feather``) load it unmodified.

It is the *same world* as ``generate_world``'s with the same arguments: scene ``i`` drives the same
route through the same road network with the same traffic (``jobs.plan_scene``); only the rig (AV2's
seven ring cameras, ``av2_rig``), the image sizes and the files differ. A log holds one sweep per drive
sample, 0.5 s apart: the synthetic logs are already sub-sampled (one sweep in five of a 10 Hz log), so
read them with ``data.av2_frame_step=1``. Each ring camera's timestamp is its sweep's plus a few
milliseconds (``CAMERA_DELAY_NS``, within AV2's 25 ms matching window); the images are rendered at the
sweep's pose, and ``city_SE3_egovehicle`` repeats that pose at the camera timestamps.

Map records (``map_archive``), from the generator's own geometry:

* **lane segments**: every lane of a road stretch, cut into pieces of about ``SEGMENT_LENGTH_M``, its
  left / right boundaries (in its direction of travel) the stretch's row polylines that bound it, with
  AV2 mark types from the paint the renderer draws there: dashed white between lanes of one direction,
  the centre line's paint (``DOUBLE_SOLID_YELLOW`` / ``SOLID_YELLOW`` / ``SOLID_WHITE``) between the
  directions, ``NONE`` along kerbs and median islands. Junction connectors are ``is_intersection``
  segments with ``NONE`` marks. Predecessors, successors and neighbours follow the network. The short
  centre-line paint that leads into a median island's nose bounds no lane, so AV2's lane-segment map
  has no divider there (the nuScenes map has it as a ``road_divider``).
* **pedestrian crossings**: each zebra's two edges across the road (``edge1``, ``edge2``).
* **drivable areas**: the road surface (stretch and junction polygons); AV2 drivable areas have no
  holes, so a stretch with a median island is cut in two across the island. Their union is the
  generator's road surface.

Elements are written whole when they come within ``MAP_MARGIN_M`` of the log's drive (AV2's log maps
are local too). The road is flat at city z = 0 (map z and the ground height raster are 0) and, as in
real AV2 logs (their lidar and ground-height rasters), the ego origin (the rear axle) rides
``ego_height(log)``, 0.33-0.43 m, above it: the ego poses have that ``tz_m``, the rig (``av2_rig``,
AV2's ego-frame calibration: cameras 1.40 m above the ego origin) is rendered that much higher above the
road, and lidar points and cuboids are in the ego frame, where the road lies at z = -ego_height, which
the dataset reads back from the raster (``data.av2.ego_ground_height``).

Scenes are rendered by the scene-job pool (jobs.py: one process or ``workers`` spawned ones,
byte-identical output, nothing left behind by a failure or Ctrl-C).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import uuid
from pathlib import Path as FsPath

import numpy as np
import shapely
from pyquaternion import Quaternion
from shapely.geometry import LineString, Polygon, box
from shapely.ops import split as split_polygon
from tqdm import tqdm

from ...config import AV2_RING_CAMERAS
from ..av2 import require_av2
from ..rig import Sensor, parse_image_size
from .jobs import (
    BASE_TIMESTAMP_US,
    MANIFEST,
    SCENE_SPACING_US,
    SceneJob,
    check_arguments,
    plan_scene,
    render_scenes,
    world_folder,
    write_world,
)
from .network import LOCATIONS, RoadNetwork
from .render import MapPainter, SceneRenderer
from .tables import yaw_quaternion
from .traffic import ANNOTATION_RANGE_M, KEYFRAME_INTERVAL_S

FORMAT = "instagram-hdmap synthetic Argoverse 2 sensor world"
FORMAT_VERSION = 2  # 2: the ego origin above the road (ego_height)
AV2_IMAGE_SIZE = (2048, 1550)  # (w, h) of the landscape ring cameras; ring_front_center is 1550 x 2048
PORTRAIT = "ring_front_center"
LIDAR = "up_lidar"
# The AV2 cities the four synthetic maps stand in for (their map names); the city number is made up.
CITY = {"boston-seaport": "PIT", "singapore-onenorth": "MIA", "singapore-hollandvillage": "ATX",
        "singapore-queenstown": "DTW"}
CAMERA_DELAY_NS = {cam: 2_000_000 * (i + 1) for i, cam in enumerate(AV2_RING_CAMERAS)}  # 2..14 ms after the sweep
SEGMENT_LENGTH_M = 30.0  # lane segments are cut to about this length along the road
MAP_MARGIN_M = 100.0  # map elements within this distance of the drive's bounding box are written
GROUND_HEIGHT_RES_M = 1.0  # metres per pixel of the (flat) ground height raster
EGO_HEIGHT_M = (0.33, 0.43)  # the ego origin above the road (real AV2), one value per log (ego_height)
ID_LANE, ID_CONNECTOR, ID_CROSSING, ID_AREA = 1_000_000, 5_000_000, 7_000_000, 8_000_000
CUBOID_CATEGORY = {"vehicle.car": "REGULAR_VEHICLE", "vehicle.truck": "BOX_TRUCK", "vehicle.bus.rigid": "BUS"}
CENTRE_MARK = {"double_yellow": "DOUBLE_SOLID_YELLOW", "single_yellow": "SOLID_YELLOW", "single_white": "SOLID_WHITE"}

# ring camera: (yaw (deg, left of forward), position in the ego frame (m; the road is ego_height below its
# origin), focal length (px) at full size). AV2-like (the published rig: roof-mounted, about 1.4 m up,
# 2048 x 1550 images, the front centre camera turned portrait), not one log's calibration. Optical axes level.
_RING = {
    "ring_front_center": (0.0, (1.63, 0.0, 1.40), 1765.0),
    "ring_front_left": (45.0, (1.52, 0.26, 1.40), 1685.0),
    "ring_front_right": (-45.0, (1.52, -0.26, 1.40), 1685.0),
    "ring_side_left": (99.0, (1.25, 0.40, 1.40), 1685.0),
    "ring_side_right": (-99.0, (1.25, -0.40, 1.40), 1685.0),
    "ring_rear_left": (153.0, (0.95, 0.30, 1.40), 1685.0),
    "ring_rear_right": (-153.0, (0.95, -0.30, 1.40), 1685.0),
}
# the two stacked lidars (their poses are in the calibration; the sweeps are the upper one's)
_LIDARS = {"up_lidar": ((1.35, 0.0, 1.95), (1.0, 0.0, 0.0, 0.0)),
           "down_lidar": ((1.35, 0.0, 1.80), (1.0, 0.0, 0.0, 0.0))}


def av2_rig(image_size: tuple[int, int] = AV2_IMAGE_SIZE) -> dict[str, Sensor]:
    """The seven ring cameras (``image_size`` = (w, h) of the landscape ones; ring_front_center is
    (h, w)), intrinsics scaled from AV2's full size, and the lidars (up_lidar first), by sensor name."""
    w, h = image_size
    out = {}
    for cam in AV2_RING_CAMERAS:
        yaw_deg, t, f = _RING[cam]
        full_w, full_h = AV2_IMAGE_SIZE[::-1] if cam == PORTRAIT else AV2_IMAGE_SIZE
        size = (h, w) if cam == PORTRAIT else (w, h)
        sx, sy = size[0] / full_w, size[1] / full_h
        k = np.array([[f * sx, 0.0, full_w / 2 * sx], [0.0, f * sy, full_h / 2 * sy], [0.0, 0.0, 1.0]])
        a = math.radians(yaw_deg)
        # cam -> ego: columns are the camera's x (right), y (down), z (optical axis) in the ego frame
        rot = np.array([[math.sin(a), 0.0, math.cos(a)], [-math.cos(a), 0.0, math.sin(a)], [0.0, -1.0, 0.0]])
        q = Quaternion(matrix=rot)
        out[cam] = Sensor(cam, "camera", t, tuple(float(v) for v in q.elements), k, size)
    for name, (t, q) in _LIDARS.items():
        out[name] = Sensor(name, "lidar", t, q, None)
    return out


def log_id(seed: int, index: int) -> str:
    """A deterministic AV2-style log id (a UUID) of scene ``index`` of the world of ``seed``."""
    return str(uuid.UUID(hashlib.md5(f"instagram-hdmap/av2/{seed}/{index}".encode()).hexdigest()))


def ego_height(log: str) -> float:
    """The height of log ``log``'s ego origin above the road, in ``EGO_HEIGHT_M`` (a function of the log id,
    so that the renderer's random draws, shared with the nuScenes-format world, are untouched)."""
    u = int(hashlib.md5(f"ego-height/{log}".encode()).hexdigest()[:8], 16) / 0xFFFFFFFF
    lo, hi = EGO_HEIGHT_M
    return round(lo + (hi - lo) * u, 3)


def city_map_name(location: str) -> str:
    return f"{CITY[location]}_city_{70000 + LOCATIONS.index(location)}"


# --- the world --------------------------------------------------------------------------------


def generate_av2_world(out, scenes_train: int = 8, scenes_val: int = 2, samples_per_scene: int = 10, seed: int = 0,
                       image_size="2048x1550", force: bool = False, progress: bool = True, workers: int = 1,
                       occluders: float = 0.0) -> dict:
    """Write the synthetic world to ``out`` in the AV2 sensor layout (module docstring); returns the
    manifest. ``image_size``: 'WxH' (or (w, h)) of the landscape ring cameras. Deterministic whatever
    ``workers`` is; a script calling it with workers > 1 must do so under ``if __name__ == "__main__":``.
    ``occluders``: as ``generate_world``'s (the same vehicles in the same scenes)."""
    require_av2("instagram-hdmap synth --format av2")
    size = parse_image_size(image_size)
    workers, occluders = check_arguments(scenes_train, scenes_val, samples_per_scene, seed, workers, occluders)
    return write_world(world_folder(out), force, lambda tmp: _write(tmp, scenes_train, scenes_val, samples_per_scene,
                                                              seed, size, progress, workers, occluders))


def _write(root: FsPath, scenes_train, scenes_val, samples, seed, size, progress, workers, occluders=0.0) -> dict:
    splits = ["train"] * scenes_train + ["val"] * scenes_val
    jobs = [SceneJob(i, log_id(seed, i), split, LOCATIONS[i % len(LOCATIONS)], samples, seed, size, root, render_log,
                     occluders) for i, split in enumerate(splits)]
    for split in set(splits):
        (root / split).mkdir()
    with tqdm(total=len(jobs) * samples, desc="synth av2", unit="sweep", disable=not progress) as bar:
        results = render_scenes(jobs, workers, lambda: bar.update(1))
    logs = {split: [job.name for job in jobs if job.split == split] for split in ("train", "val")}
    manifest = {
        "format": FORMAT, "format_version": FORMAT_VERSION, "dataset": "av2", "seed": seed, "image_size": list(size),
        "scenes_train": scenes_train, "scenes_val": scenes_val, "samples_per_scene": samples,
        "samples": len(jobs) * samples, "frame_interval_s": KEYFRAME_INTERVAL_S, "logs": logs,
        "cities": {job.name: results[job.index]["city"] for job in jobs},
        "maps": {job.name: job.location for job in jobs},
    }
    if occluders > 0:  # absent at 0, as in world.py
        manifest["occluders"] = occluders
    (root / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
    return manifest


# --- one log -----------------------------------------------------------------------------------


def _pose_rows(timestamp: int, pose: np.ndarray, height: float) -> dict:
    q = yaw_quaternion(pose[2])
    return {"timestamp_ns": timestamp, "qw": q[0], "qx": q[1], "qy": q[2], "qz": q[3],
            "tx_m": float(pose[0]), "ty_m": float(pose[1]), "tz_m": height}


def _write_feather(rows: list[dict] | dict, path: FsPath, types: dict | None = None) -> None:
    """Rows (list of dicts) or columns (dict of arrays) as an Apache Feather file, AV2's format."""
    import pyarrow as pa
    from pyarrow import feather

    cols = rows if isinstance(rows, dict) else {k: [r[k] for r in rows] for k in rows[0]}
    types = types or {}
    table = pa.table({k: pa.array(v, type=types.get(k)) for k, v in cols.items()})
    path.parent.mkdir(parents=True, exist_ok=True)
    feather.write_feather(table, str(path), compression="lz4")


def render_log(job: SceneJob, net: RoadNetwork, painter: MapPainter, on_sample) -> dict:
    """Plans, renders and writes one complete log folder (world.py's ``_render_scene`` for AV2: the
    same draws in the same order, so the same drive and traffic). Returns {"log_id", "city"}."""
    import pyarrow as pa

    sensors = av2_rig(job.size)  # ego frame
    rng, drive, vehicles, look = plan_scene(job, net, sensors)
    ego_z = ego_height(job.name)  # the renderer's frame lies on the road, AV2's ego origin this much above it
    on_road = {k: dataclasses.replace(s, translation=(*s.translation[:2], s.translation[2] + ego_z))
               for k, s in sensors.items()}
    renderer = SceneRenderer(painter, look, on_road, (max(job.size), max(job.size)), rng)
    log_dir = job.root / job.split / job.name
    for cam in AV2_RING_CAMERAS:
        (log_dir / "sensors" / "cameras" / cam).mkdir(parents=True)
    (log_dir / "sensors" / "lidar").mkdir(parents=True)
    lidar = sensors[LIDAR]
    t0 = (BASE_TIMESTAMP_US + job.index * SCENE_SPACING_US) * 1000
    poses = drive.poses()
    pose_rows, cuboids = [], []
    for k, pose in enumerate(poses):
        t = k * KEYFRAME_INTERVAL_S
        timestamp = t0 + int(round(t * 1e9))
        images, points, counts = renderer.render(pose, [v.box(t) for v in vehicles])
        pose_rows.append(_pose_rows(timestamp, pose, ego_z))
        for cam in AV2_RING_CAMERAS:
            ts_cam = timestamp + CAMERA_DELAY_NS[cam]
            (log_dir / "sensors" / "cameras" / cam / f"{ts_cam}.jpg").write_bytes(images[cam])
            pose_rows.append(_pose_rows(ts_cam, pose, ego_z))  # rendered at the sweep's pose
        xyz = points[:, :3].astype(np.float64) @ lidar.rot.T + lidar.trans  # lidar -> ego frame
        _write_feather({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
                        "intensity": np.clip(points[:, 3], 0, 255).astype(np.uint8),
                        "laser_number": points[:, 4].astype(np.uint8),
                        "offset_ns": np.zeros(len(points), np.uint32)},
                       log_dir / "sensors" / "lidar" / f"{timestamp}.feather",
                       {"x": pa.float16(), "y": pa.float16(), "z": pa.float16()})
        c, s = math.cos(pose[2]), math.sin(pose[2])
        for i, v in enumerate(vehicles):
            centre, yaw, _ = v.state(t)
            d = centre[:2] - pose[:2]
            if np.hypot(*d) > ANNOTATION_RANGE_M:
                continue
            q = yaw_quaternion(yaw - pose[2])
            width, length, height = v.size
            cuboids.append({"timestamp_ns": timestamp, "track_uuid": log_id(job.seed, 100_000 * (job.index + 1) + i),
                            "category": CUBOID_CATEGORY.get(v.category, "REGULAR_VEHICLE"),
                            "length_m": length, "width_m": width, "height_m": height,
                            "qw": q[0], "qx": q[1], "qy": q[2], "qz": q[3],
                            "tx_m": c * d[0] + s * d[1], "ty_m": -s * d[0] + c * d[1],
                            "tz_m": float(centre[2]) - ego_z,
                            "num_interior_pts": int(counts[i])})
        on_sample()
    pose_rows.sort(key=lambda r: r["timestamp_ns"])
    _write_feather(pose_rows, log_dir / "city_SE3_egovehicle.feather", {"timestamp_ns": pa.int64()})
    _write_calibration(sensors, log_dir / "calibration")
    if cuboids:
        _write_feather(cuboids, log_dir / "annotations.feather", {"timestamp_ns": pa.int64()})
    city = city_map_name(job.location)
    lo, hi = poses[:, :2].min(axis=0) - MAP_MARGIN_M, poses[:, :2].max(axis=0) + MAP_MARGIN_M
    region = box(*lo, *hi)
    map_dir = log_dir / "map"
    map_dir.mkdir()
    with open(map_dir / f"log_map_archive_{job.name}____{city}.json", "w") as f:
        json.dump(map_archive(net, region), f, separators=(",", ":"))
    _write_ground_height(map_dir, job.name, city, lo, hi)
    return {"log_id": job.name, "city": city}


def _write_calibration(sensors: dict[str, Sensor], folder: FsPath) -> None:
    cams = [s for s in sensors.values() if s.modality == "camera"]
    _write_feather([{"sensor_name": s.channel, "fx_px": s.intrinsic[0, 0], "fy_px": s.intrinsic[1, 1],
                     "cx_px": s.intrinsic[0, 2], "cy_px": s.intrinsic[1, 2], "k1": 0.0, "k2": 0.0, "k3": 0.0,
                     "height_px": s.size[1], "width_px": s.size[0]} for s in cams],
                   folder / "intrinsics.feather")
    _write_feather([{"sensor_name": s.channel, "qw": s.rotation[0], "qx": s.rotation[1], "qy": s.rotation[2],
                     "qz": s.rotation[3], "tx_m": float(s.translation[0]), "ty_m": float(s.translation[1]),
                     "tz_m": float(s.translation[2])} for s in sensors.values()],
                   folder / "egovehicle_SE3_sensor.feather")


def _write_ground_height(map_dir: FsPath, log: str, city: str, lo: np.ndarray, hi: np.ndarray) -> None:
    """The flat ground (0 m) over the log's map region, with the city -> raster Sim(2)."""
    w, h = (int(math.ceil(v)) for v in (hi - lo) / GROUND_HEIGHT_RES_M)
    np.save(map_dir / f"{log}_ground_height_surface____{city.split('_')[0]}.npy", np.zeros((h, w), np.float16))
    sim2 = {"R": [1.0, 0.0, 0.0, 1.0], "t": [float(-lo[0]), float(-lo[1])], "s": 1.0 / GROUND_HEIGHT_RES_M}
    (map_dir / f"{log}___img_Sim2_city.json").write_text(json.dumps(sim2))


# --- the map archive ---------------------------------------------------------------------------


def _xyz(xy: np.ndarray) -> list[dict]:
    return [{"x": float(x), "y": float(y), "z": 0.0} for x, y in xy]


def _row_mark(net: RoadNetwork, stretch: int, row: int) -> str:
    """AV2 mark type of the paint along row ``row`` of a stretch (what paint.paint_stretch draws there)."""
    st = net.stretches[stretch]
    kind = st.kinds[row]
    if kind == "lane":
        return "DASHED_WHITE"
    if kind == "centre" and st.chain.median == 0:
        return CENTRE_MARK[st.chain.divider]
    return "NONE"  # kerb, median island


def _chunks(s: np.ndarray) -> list[tuple[int, int]]:
    """Column ranges [a, b] (inclusive, consecutive ranges share a column) cutting a stretch into
    pieces of about SEGMENT_LENGTH_M."""
    n = max(1, round(float(s[-1]) / SEGMENT_LENGTH_M))
    cuts = sorted({int(np.argmin(np.abs(s - s[-1] * k / n))) for k in range(1, n)} - {0, len(s) - 1})
    bounds = [0, *cuts, len(s) - 1]
    return list(zip(bounds[:-1], bounds[1:]))


def lane_segments(net: RoadNetwork) -> list[dict]:
    """The network's lanes and junction connectors as AV2 lane-segment records (ids unique in the map)."""
    rec = net.records
    chunks = [_chunks(st.s) for st in net.stretches]
    by_band = {(ln.stretch, ln.lo): ln for ln in net.lanes}  # lane between rows lo and lo + 1

    def seg_id(lane: int, chunk: int) -> int:
        return ID_LANE + 1000 * lane + chunk

    def travel_chunks(lane) -> list[int]:
        order = list(range(len(chunks[lane.stretch])))
        return order if lane.forward else order[::-1]

    into: dict[int, list[int]] = {}
    out_of: dict[int, list[int]] = {}
    for con in net.connectors:
        into.setdefault(con.dst, []).append(ID_CONNECTOR + con.index)
        out_of.setdefault(con.src, []).append(ID_CONNECTOR + con.index)
    segments = []
    for lane in net.lanes:
        st = net.stretches[lane.stretch]
        order = travel_chunks(lane)
        left_row, right_row = (lane.hi, lane.lo) if lane.forward else (lane.lo, lane.hi)
        # the lanes across the left / right boundary (the band above hi, below lo)
        up, down = by_band.get((lane.stretch, lane.hi)), by_band.get((lane.stretch, lane.lo - 1))
        left_nb, right_nb = (up, down) if lane.forward else (down, up)
        for pos, c in enumerate(order):
            a, b = chunks[lane.stretch][c]
            cols = slice(a, b + 1) if lane.forward else slice(b, a - 1 if a > 0 else None, -1)
            segments.append({
                "id": seg_id(lane.index, c), "is_intersection": False, "lane_type": "VEHICLE",
                "left_lane_boundary": _xyz(rec.node_xy(st.ids[left_row, cols])),
                "right_lane_boundary": _xyz(rec.node_xy(st.ids[right_row, cols])),
                "left_lane_mark_type": _row_mark(net, lane.stretch, left_row),
                "right_lane_mark_type": _row_mark(net, lane.stretch, right_row),
                "left_neighbor_id": seg_id(left_nb.index, c) if left_nb is not None else None,
                "right_neighbor_id": seg_id(right_nb.index, c) if right_nb is not None else None,
                "predecessors": [seg_id(lane.index, order[pos - 1])] if pos > 0 else into.get(lane.index, []),
                "successors": [seg_id(lane.index, order[pos + 1])] if pos + 1 < len(order)
                else out_of.get(lane.index, []),
            })
    for con in net.connectors:
        poses = con.path.pose_at(con.path.sample_s(1.0, 0.01))
        half = net.lanes[con.src].width / 2
        nrm = np.stack([-np.sin(poses[:, 2]), np.cos(poses[:, 2])], axis=-1)
        src, dst = net.lanes[con.src], net.lanes[con.dst]
        segments.append({
            "id": ID_CONNECTOR + con.index, "is_intersection": True, "lane_type": "VEHICLE",
            "left_lane_boundary": _xyz(poses[:, :2] + half * nrm),
            "right_lane_boundary": _xyz(poses[:, :2] - half * nrm),
            "left_lane_mark_type": "NONE", "right_lane_mark_type": "NONE",
            "left_neighbor_id": None, "right_neighbor_id": None,
            "predecessors": [seg_id(src.index, travel_chunks(src)[-1])],
            "successors": [seg_id(dst.index, travel_chunks(dst)[0])],
        })
    return segments


def without_holes(poly: Polygon) -> list[Polygon]:
    """Hole-free polygons whose union is ``poly``: cut across each hole along its short axis."""
    if not poly.interiors:
        return [poly]
    hole = Polygon(poly.interiors[0])
    rect = np.asarray(hole.minimum_rotated_rectangle.exterior.coords)
    sides = [rect[1] - rect[0], rect[2] - rect[1]]
    d = min(sides, key=np.linalg.norm)
    d = d / np.linalg.norm(d)
    c = np.asarray(hole.representative_point().coords[0])
    reach = float(np.hypot(*(np.array(poly.bounds[2:]) - poly.bounds[:2])))
    pieces = split_polygon(poly, LineString([c - reach * d, c + reach * d]))
    return [q for piece in shapely.get_parts(pieces) for q in without_holes(piece)]


def map_archive(net: RoadNetwork, region: Polygon | None = None) -> dict:
    """The AV2 ``log_map_archive`` JSON of the network, keeping elements that reach ``region``."""

    def near(*lines) -> bool:
        return region is None or any(LineString(line).intersects(region) for line in lines)

    def pts(records: list[dict]) -> np.ndarray:
        return np.array([[p["x"], p["y"]] for p in records])

    lanes = {str(s["id"]): s for s in lane_segments(net)
             if near(pts(s["left_lane_boundary"]), pts(s["right_lane_boundary"]))}
    crossings = {}
    for i, poly in enumerate(net.polygons("ped_crossing")):
        p0, p1, p2, p3 = np.asarray(poly.exterior.coords)[:4]  # (t0, right), (t1, right), (t1, left), (t0, left)
        if near(np.array([p0, p1, p2, p3, p0])):
            crossings[str(ID_CROSSING + i)] = {"id": ID_CROSSING + i, "edge1": _xyz(np.array([p0, p3])),
                                               "edge2": _xyz(np.array([p1, p2]))}
    pieces = [q for st in net.stretches for q in without_holes(st.shape)] + [jn.shape for jn in net.junctions.values()]
    areas = {}
    for i, poly in enumerate(pieces):
        ring = np.asarray(poly.exterior.coords)
        if near(ring):
            areas[str(ID_AREA + i)] = {"id": ID_AREA + i, "area_boundary": _xyz(ring[:-1])}
    return {"pedestrian_crossings": crossings, "lane_segments": lanes, "drivable_areas": areas}

