"""Argoverse 2 *sensor dataset* for HD-map learning, read through the official ``av2`` package (the
optional extra ``pip install -e ".[av2]"``): the same sample dict as the nuScenes dataset
(docs/conventions.md; data/base.py), ``data.dataset=av2``.

    data.dataroot/                      an AV2 sensor-dataset root (or a world of `synth --format av2`)
      train/<log_id>/ val/<log_id>/ test/<log_id>/   logs, as the dataset's tarballs unpack

Samples: every ``data.av2_frame_step``-th lidar sweep of every log of the split folder
(``data.train_split`` / ``data.val_split`` name the folders), in ``AV2SensorDataLoader`` order (logs
sorted, sweeps in time); under ``data.split_scheme=geo`` the logs of StreamMapNet's list, wherever they lie
under ``train/``, ``val/`` and ``test/`` (data/geo_split.py). A sample's token is
``"<log_id>/<sweep timestamp_ns>"``. Its pose is the ego pose at the sweep
(``city_SE3_egovehicle.feather``, ``read_city_SE3_ego``); its cameras are the ring cameras of
``data.av2_cameras`` (default all seven; ``V = len(data.av2_cameras)``), each the image the
av2 synchronisation picks for the sweep (``get_closest_img_fpath``: the nearest within 25 ms), with the
log's calibration (``PinholeCamera.from_feather``: intrinsics, camera -> ego). As for nuScenes, one ego
pose serves all cameras (lift-splat-shoot's simplification). AV2's ring_front_center is portrait
(1550 x 2048) and the others landscape (2048 x 1550): at about AV2's aspect ratio the default crop
(``data.image_fit=cover``) only cuts the portrait camera's sky; for a wide window such as 128 x 352,
fit the cameras inside instead (``contain``; configs/av2/).

Map (``AV2LocalMapBuilder``): each log's ``map/log_map_archive_*.json`` through
``ArgoverseStaticMap.from_json``, turned into the three classes of the field's AV2 setting
(StreamMapNet's and MapTR v2's extraction), then clipped, ringed and resampled exactly as the nuScenes
local map (data/local_map.py: the same patch, edge margin and ``sample_dist``):

* **divider**: lane-segment boundaries that are painted, i.e. whose mark type is not ``NONE`` or
  ``UNKNOWN`` (``LaneSegment.left/right_lane_marking.mark_type``); a boundary shared by two lane
  segments (each lists it) is kept once (equal points to 1 cm, either direction); each boundary is
  clipped to the patch and a clipped piece lying along the drivable-area edge (more than half its
  length within ``BOUNDARY_OVERLAP_M``) is left to the boundary class (the rule judges the clipped
  pieces, as StreamMapNet's ``remove_boundary_dividers`` in ``plugin/datasets/map_utils/utils.py``,
  applied after clipping in ``av2map_extractor.py``: a boundary that runs along a kerb elsewhere is
  still a divider where it is paint in the middle of the road); the kept pieces are merged end to end
  (``line_merge``).
* **ped_crossing**: each crossing's polygon (``PedestrianCrossing.polygon``) or, under ``edges``, its
  two principal edges (``edge1``, ``edge2``), in the convention of ``data.ped_crossing``
  (docs/conventions.md; configs/av2 use ``each``, the field's AV2 convention).
* **boundary**: the edges of the union of the drivable areas (``get_scenario_vector_drivable_areas``),
  exterior and interior rings.

Ground height (``ground_height``): AV2's ego origin is the rear axle, 0.33-0.43 m above the road; the
sample's ``ground_height`` is the road's height below it in the ego frame, from the log's ground-height
raster (``GroundHeightLayer``, ``map/*_ground_height_surface____*.npy``) around the ego, mapped through
the full SE(3) of the pose (``ego_ground_height``).

Bad input (a dataroot without the split folder of logs, a log without a map archive, ground-height
raster, poses or calibration, a missing calibration row or camera image, a camera whose images do not match the
sweeps' timestamps) raises a ``DatasetError`` / ``MapError`` naming the log and the file (data/base.py).
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
from pathlib import Path

import numpy as np
import shapely
import torch
from shapely.geometry import LineString, Polygon

from ..config import ExperimentConfig, UserError
from ..files import relative_path_note
from .base import (
    DatasetError,
    MapDataset,
    check_camera_plausible,
    check_camera_time,
    check_distinct_images,
    check_ego_level,
    check_intrinsics,
    check_rotation,
    check_translation,
)
from .geo_split import GeoSplit, check_split, from_list, from_networks, synthetic_manifest
from .local_map import LocalMapBuilder, MapError, _LocationMap, collect_crossings, heading

AV2_EXTRA = 'pip install -e ".[av2]"'
BOUNDARY_OVERLAP_M = 0.3  # a painted lane boundary this close to a drivable-area edge is that edge
DEDUP_DECIMALS = 2  # shared lane boundaries are equal to 1 cm
GROUND_DISC_M = 1.5  # the ground height at the ego: the median of the raster within this radius ...
GROUND_RES_M = 0.3  # ... sampled at the raster's resolution (AV2: 30 cm)
CAMERA_WINDOW_MS = 25  # av2's SynchronizationDB: a ring image within half a 20 Hz frame of the sweep


def require_av2(what: str) -> None:
    """Raise a one-line ``UserError`` naming the extra when the ``av2`` package cannot be imported."""
    try:
        import av2.map.map_api  # noqa: F401  (pulls pyarrow, pandas: a broken install fails here too)
    except ImportError as e:
        raise UserError(f"{what} needs the Argoverse 2 API, the optional extra 'av2': {AV2_EXTRA} "
                        f"(import failed: {e})") from None


# --- map ---------------------------------------------------------------------------------------


def _line_key(xy: np.ndarray) -> tuple:
    """The same key for a polyline and its reverse (points rounded to DEDUP_DECIMALS)."""
    a = tuple(np.round(xy, DEDUP_DECIMALS).ravel().tolist())
    b = tuple(np.round(xy[::-1], DEDUP_DECIMALS).ravel().tolist())
    return min(a, b)


def painted_dividers(avm) -> list[LineString]:
    """Painted lane boundaries of an ``ArgoverseStaticMap`` (module docstring), city frame, each shared
    boundary once; not merged (the divider-on-kerb rule judges each clipped piece, then the builder
    merges the kept ones)."""
    from av2.map.lane_segment import LaneMarkType

    unpainted = (LaneMarkType.NONE, LaneMarkType.UNKNOWN)
    seen: set[tuple] = set()
    lines = []
    for ls in avm.get_scenario_lane_segments():
        for marking in (ls.left_lane_marking, ls.right_lane_marking):
            xy = np.asarray(marking.polyline, dtype=np.float64)[:, :2]
            if marking.mark_type in unpainted or len(xy) < 2:
                continue
            key = _line_key(xy)
            if key not in seen:
                seen.add(key)
                lines.append(LineString(xy))
    return [ln for ln in lines if ln.length > 0]


def _crossings(avm):
    """``(id, ring, edges)`` of the map's crossings for ``collect_crossings``: the ring is
    ``PedestrianCrossing.polygon``'s (edge1, then edge2 backwards), built here so that an edge of other
    than two points does not raise; the edges run as the ring does (edge1, edge2 backwards). AV2 stores
    both edges pointing the same way: left so, the official join of collinear edges (``connect_lines``,
    ``data.local_map.join_collinear_edges``), made for a ring's antiparallel edges, would join a narrow
    crossing's two edges into one chord between their far ends (it does on the real log)."""
    for pc in avm.get_scenario_ped_crossings():
        e1, e2 = (np.asarray(e.xyz, dtype=np.float64)[:, :2] for e in (pc.edge1, pc.edge2))
        yield pc.id, np.concatenate([e1, e2[::-1]]), (e1, e2[::-1])


# AV2 names a log's map files after the log (map/log_map_archive_<log id>____<CITY>_city_<n>.json,
# <log id>___img_Sim2_city.json, <log id>_ground_height_surface____<CITY>.npy)
_MAP_FILE_LOG = re.compile(r"^(?:log_map_archive_)?([0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12})_")


def check_map_files_of_the_log(log_dir: Path) -> None:
    """A ``MapError`` when a file of ``log_dir/map`` is named after another log: the map of another log copied
    in (another city or another part of it) gave that log's roads as the GT, or none, with no word."""
    paths = sorted((log_dir / "map").glob("*")) if (log_dir / "map").is_dir() else []
    named = {m.group(1) for m in map(_MAP_FILE_LOG.match, (p.name for p in paths)) if m}
    for path in paths:
        m = _MAP_FILE_LOG.match(path.name)
        if m and m.group(1) != log_dir.name and _MAP_FILE_LOG.match(log_dir.name + "_"):
            # every map file naming one other log: the log folder renamed more likely than three files copied in
            renamed = (f", or the log folder was renamed: all its map files name log {m.group(1)}, as its "
                       "other files may" if named == {m.group(1)} and len(paths) > 1 else "")
            raise MapError(f"log {log_dir.name}: {path} is the map file of another log ({m.group(1)}); every log "
                           "has its own map/ files, named after it (re-extract the log's map/ folder from the AV2 "
                           f"sensor dataset{renamed})")


def load_log_map(log_dir: Path) -> _LocationMap:
    """Read a log's map archive with ``ArgoverseStaticMap`` and index its divider, crossing and
    drivable-area geometry (city frame) for ``LocalMapBuilder``."""
    from av2.map.map_api import ArgoverseStaticMap

    map_dir = log_dir / "map"
    check_map_files_of_the_log(log_dir)
    files = sorted(map_dir.glob("log_map_archive_*.json")) if map_dir.is_dir() else []
    if len(files) != 1:
        raise MapError(f"log {log_dir.name}: expected one map archive {map_dir}/log_map_archive_*.json, found "
                       f"{len(files)}; the log folder is incomplete (re-extract it from the AV2 sensor dataset)")
    try:
        avm = ArgoverseStaticMap.from_json(files[0])
    except (KeyError, ValueError, TypeError, AttributeError, OSError, json.JSONDecodeError) as e:
        raise MapError(f"log {log_dir.name}: cannot read map archive {files[0]}: {type(e).__name__}: {e}") from None
    for what, items in (("drivable area", [(da.id, da.xyz) for da in avm.get_scenario_vector_drivable_areas()]),
                        ("lane segment", [(ls.id, m.polyline) for ls in avm.get_scenario_lane_segments()
                                          for m in (ls.left_lane_marking, ls.right_lane_marking)])):
        bad = next((rid for rid, xyz in items if not np.isfinite(np.asarray(xyz, dtype=np.float64)).all()), None)
        if bad is not None:  # a NaN area was a raw GEOSException, a NaN lane marking silently dropped
            raise MapError(f"log {log_dir.name}: map archive {files[0]}: {what} {bad} has NaN or infinite "
                           "coordinates; the file is corrupt (re-extract it from the AV2 sensor dataset)")
    areas = [Polygon(np.asarray(da.xyz)[:, :2]) for da in avm.get_scenario_vector_drivable_areas()]
    areas = np.array([p for p in areas if p.is_valid and not p.is_empty], dtype=object)
    edges = shapely.union_all(areas).boundary if len(areas) else LineString()
    peds, ped_edges, report = collect_crossings(_crossings(avm), str(files[0]))
    dividers = np.array(painted_dividers(avm), dtype=object)
    return _LocationMap(dividers, peds, ped_edges, areas,
                        divider_exclusion=edges.buffer(BOUNDARY_OVERLAP_M) if not edges.is_empty else None,
                        merge_dividers=True, crossing_report=report)


def load_ground_height(log_dir: Path):
    """The log's ground-height raster (``GroundHeightLayer.from_file``: ``map/*_ground_height_surface____*.npy``
    and ``map/*___img_Sim2_city.json``), or a ``MapError`` naming the folder."""
    from av2.map.map_api import GroundHeightLayer

    map_dir = log_dir / "map"
    check_map_files_of_the_log(log_dir)
    try:
        return GroundHeightLayer.from_file(map_dir)
    except (RuntimeError, KeyError, ValueError, OSError, ZeroDivisionError, json.JSONDecodeError) as e:
        raise MapError(f"log {log_dir.name}: cannot read the ground-height raster in {map_dir} "
                       f"(*_ground_height_surface____*.npy and *___img_Sim2_city.json): {type(e).__name__}: {e}; "
                       "the log folder is incomplete (re-extract it from the AV2 sensor dataset)") from None


def ego_ground_height(layer, city_SE3_ego) -> float:
    """The height of the road below the ego origin in the ego frame (metres along its z; about -0.3 to
    -0.4 on AV2, whose ego origin is the rear axle): the raster's city-frame ground points within
    ``GROUND_DISC_M`` of the ego's (x, y), mapped into the ego frame by the full SE(3), their median z
    (robust to a missing or noisy raster cell). NaN where the raster has no value there."""
    xy = np.asarray(city_SE3_ego.translation, dtype=np.float64)[:2]
    step = GROUND_RES_M
    offsets = np.stack(np.meshgrid(*[np.arange(-GROUND_DISC_M, GROUND_DISC_M + 1e-9, step)] * 2), -1).reshape(-1, 2)
    offsets = offsets[np.hypot(offsets[:, 0], offsets[:, 1]) <= GROUND_DISC_M]
    points = np.c_[xy + offsets, np.zeros(len(offsets))]
    points[:, 2] = layer.get_ground_height_at_xy(points)
    points = points[np.isfinite(points[:, 2])]
    if not len(points):
        return math.nan
    return float(np.median(city_SE3_ego.inverse().transform_point_cloud(points)[:, 2]))


def _unique_rows(path: Path, key: str, where: str, what: str) -> None:
    """A DatasetError if two rows of the feather table ``path`` share ``key`` with other values: av2's readers keep one
    of them (a dict by ``key``) with no word."""
    import pandas as pd

    table = pd.read_feather(path)
    if key not in table.columns or table[key].dtype.kind == "f":
        return  # av2's reader names a missing column; _pose says what a float64 timestamp column did
    clash = table.drop_duplicates().duplicated(key, keep=False)
    if clash.any():
        value = table[key][clash].iloc[0]
        raise DatasetError(f"{where}: {path} holds {int(clash.sum())} rows of other {what} for {key} {value} (rows "
                           f"{', '.join(map(str, table.index[clash][:4]))}): one row per {key}; the file is corrupt")


class AV2LocalMapBuilder(LocalMapBuilder):
    """``builder(log_id, x, y, yaw) -> polyline dicts``: data/local_map.py's builder over the log maps
    of the dataset's logs (the nuScenes "location" is the log)."""

    def __init__(self, *args, log_dirs: dict[str, Path] | None = None, **kwargs):
        super().__init__(*args, **kwargs)
        self.log_dirs = log_dirs or {}  # log id -> its folder (a dataset's); else dataroot / log id

    def location_map(self, location: str) -> _LocationMap:
        if location not in self._maps:
            self._maps[location] = load_log_map(self.log_dirs.get(location, self.dataroot / location))
        return self._maps[location]


# --- dataset -----------------------------------------------------------------------------------


# a lidar sweep's pose in a timestamp_ns column rounded by float64 (a step of 64 ns at AV2's 3.2e17 ns) lies
# this close; the poses themselves are ~6 ms apart
ROUNDED_TIMESTAMP_NS = 1000
GEO_FOLDERS = ("train", "val", "test")  # a geo split's logs may lie in any of them (StreamMapNet's converter)


class AV2MapDataset(MapDataset):
    """Samples of one split folder of an AV2 sensor-dataset root (module docstring)."""

    def __init__(self, cfg: ExperimentConfig, split: str, augment: bool | None = None):
        require_av2("data.dataset=av2")
        from av2.datasets.sensor.av2_sensor_dataloader import AV2SensorDataLoader

        super().__init__(cfg, split, augment)
        d = cfg.data
        self.camera_names = tuple(d.av2_cameras)
        self.dataroot = Path(d.dataroot)
        self.split_dir = self.dataroot / split
        # the folders of logs read: the split's own, or (a geo split) every split folder of the root
        folders = [self.split_dir]
        if d.split_scheme == "geo":
            check_split(split)
            folders = [f for f in (self.dataroot / name for name in GEO_FOLDERS) if f.is_dir()] or folders
        self.loaders: dict[Path, object] = {}
        self.log_dirs: dict[str, Path] = {}  # log id -> its folder
        for folder in folders:
            self._check_root(folder)
            self.loaders[folder] = AV2SensorDataLoader(data_dir=folder, labels_dir=folder)
            for log in self.loaders[folder].get_log_ids():
                if not log.startswith("."):  # a hidden folder (_check_root), which av2 lists as a log
                    self.log_dirs.setdefault(log, folder / log)
        geo = self._geo_split(split) if d.split_scheme == "geo" else None
        self.samples: list[tuple[str, int]] = []
        for log in sorted(geo.names) if geo else self.log_dirs:
            sweeps = self._loader(log).get_ordered_log_lidar_timestamps(log)
            if not sweeps:
                raise DatasetError(f"log {log}: no lidar sweeps in {self.log_dirs[log] / 'sensors' / 'lidar'} "
                                   "(AV2 samples are the sweeps); the log folder is incomplete")
            self.samples += [(log, int(ts)) for ts in sweeps[:: d.av2_frame_step]]
        if geo is not None:
            print(geo.line(str(self.dataroot), len(self.samples)), flush=True)
        self.sample_tokens = [f"{log}/{ts}" for log, ts in self.samples]
        self.map_builder = AV2LocalMapBuilder(self.dataroot, self.grid, d.sample_dist, d.ped_crossing,
                                              log_dirs=self.log_dirs)
        self.set_scenes([log for log, _ in self.samples], [ts // 1000 for _, ts in self.samples])  # ns -> us
        self._poses: dict[str, dict] = {}
        self._grounds: dict[str, object] = {}
        self._cameras: dict[str, dict] = {}

    def _loader(self, log: str):
        return self.loaders[self.log_dirs[log].parent]

    def _geo_split(self, split: str) -> GeoSplit:
        """The logs of ``split`` under ``data.split_scheme=geo``: StreamMapNet's list, or the held-out road network
        of a synthetic world (data/geo_split.py)."""
        manifest = synthetic_manifest(self.dataroot)
        if manifest is not None:
            networks = manifest.get("maps") if isinstance(manifest.get("maps"), dict) else {}
            return from_networks(split, {log: networks.get(log, "?") for log in sorted(self.log_dirs)},
                                 str(self.dataroot))
        return from_list("av2", split, sorted(self.log_dirs), str(self.dataroot))

    def _check_root(self, split_dir: Path) -> None:
        root = self.dataroot
        if not root.is_dir():
            raise DatasetError(f"AV2 dataroot not found: {root} (set data.dataroot{relative_path_note(root)})")
        if not split_dir.is_dir():
            found = sorted(p.name for p in root.iterdir() if p.is_dir())
            # a log folder, or a split folder of logs, given as the root: say which root holds it
            if (root / "sensors").is_dir():
                hint = (f"; {root} is one log (it holds sensors/): the root is the folder above its split folder, "
                        f"data.dataroot={root.parent.parent} with the split '{root.parent.name}'")
            elif found and all((root / name / "sensors").is_dir() for name in found if not name.startswith(".")):
                hint = (f"; {root} is a split folder of logs: the root is the folder above it, "
                        f"data.dataroot={root.parent} with the split '{root.name}'")
            elif below := sorted(p for p in root.iterdir() if (p / split_dir.name).is_dir()):
                # s5cmd's copy of s3://argoverse/datasets/av2/sensor/ is ROOT/sensor/{train,val,test}: "its folders:
                # sensor" said nothing of it
                hint = f"; its subfolder {below[0]} holds the split folder '{split_dir.name}': data.dataroot={below[0]}"
            elif any(root.glob("*/sample.json")):  # (the converse, data.dataset=nuscenes on an AV2 root, says so too)
                versions = sorted(p.parent.name for p in root.glob("*/sample.json"))
                hint = f"; {root} is a nuScenes dataroot (versions {', '.join(versions)}): set data.dataset=nuscenes"
            else:
                hint = ""
            raise DatasetError(f"{root} is not an AV2 sensor-dataset root: it has no split folder '{split_dir.name}' "
                               f"of logs (expected {root}/{{train,val,test}}/<log_id>/sensors/...); its folders: "
                               f"{', '.join(found) or 'none'} (set data.dataroot, data.train_split / data.val_split)"
                               + hint)
        # a hidden folder (.ipynb_checkpoints, .Trash-1000, .git) is not a log; av2's loader skips it too
        logs = [p for p in split_dir.iterdir() if p.is_dir() and not p.name.startswith(".")]
        if not logs:
            raise DatasetError(f"split folder {split_dir} holds no logs (expected {split_dir}/<log_id>/sensors/...)")
        for log in logs:
            if not (log / "sensors").is_dir():
                raise DatasetError(f"{split_dir} is not an AV2 split folder: {log.name} has no sensors/ folder "
                                   f"(expected {log}/sensors/lidar, sensors/cameras, calibration/, map/)")
            odd = next((p for p in sorted((log / "sensors" / "lidar").glob("*.feather")) if not p.stem.isdigit()), None)
            if odd is not None:  # av2's loader: a raw "invalid literal for int()"
                raise DatasetError(f"log {log.name}: {odd} is not named <timestamp_ns>.feather, as every lidar sweep "
                                   "of an AV2 log is; move it out of the sensors/lidar folder")

    # --- per log, cached ------------------------------------------------------------------------
    def _log_poses(self, log: str) -> dict:
        if log not in self._poses:
            from av2.utils.io import read_city_SE3_ego

            path = self.log_dirs[log] / "city_SE3_egovehicle.feather"
            if not path.is_file():
                raise DatasetError(f"log {log}: ego poses not found: {path}")
            try:
                self._poses[log] = read_city_SE3_ego(self.log_dirs[log])
                _unique_rows(path, "timestamp_ns", f"log {log}", "ego poses")
            except (KeyError, ValueError, OSError) as e:
                raise DatasetError(f"log {log}: cannot read {path}: {type(e).__name__}: {e}") from None
        return self._poses[log]

    def _log_cameras(self, log: str) -> dict:
        """Ring camera name -> av2 ``PinholeCamera`` of a log, for the cameras of data.av2_cameras."""
        if log not in self._cameras:
            from av2.geometry.camera.pinhole_camera import PinholeCamera
            from av2.utils.io import read_ego_SE3_sensor, read_feather

            log_dir = self.log_dirs[log]
            intr_path = log_dir / "calibration" / "intrinsics.feather"
            extr_path = log_dir / "calibration" / "egovehicle_SE3_sensor.feather"
            for path in (intr_path, extr_path):
                if not path.is_file():
                    raise DatasetError(f"log {log}: calibration file not found: {path}")
            try:
                for path in (intr_path, extr_path):
                    _unique_rows(path, "sensor_name", f"log {log}", "calibrations")
                intr_names = set(read_feather(intr_path)["sensor_name"])
                extr_names = set(read_ego_SE3_sensor(log_dir))
                cams = {}
                for cam in self.camera_names:
                    for names, path in ((intr_names, intr_path), (extr_names, extr_path)):
                        if cam not in names:
                            raise DatasetError(f"log {log}: {path} has no row for camera {cam}")
                    cams[cam] = PinholeCamera.from_feather(log_dir, cam)
            except (KeyError, ValueError, OSError) as e:
                raise DatasetError(f"log {log}: cannot read its calibration ({intr_path}, {extr_path}): "
                                   f"{type(e).__name__}: {e}") from None
            for cam, pin in cams.items():
                check_intrinsics(pin.intrinsics.K, f"log {log}: camera {cam} in {intr_path}")
                if not (pin.width_px >= 1 and pin.height_px >= 1):  # the image size scales the resize
                    raise DatasetError(f"log {log}: camera {cam} in {intr_path}: width_px x height_px is "
                                       f"{pin.width_px} x {pin.height_px}; the image's size in pixels must be >= 1")
                where = f"log {log}: camera {cam} in {extr_path}"
                check_rotation(pin.ego_SE3_cam.rotation, "its rotation (camera -> ego)", where)
                check_translation(pin.ego_SE3_cam.translation, "its translation (camera -> ego)", where)
                check_camera_plausible(pin.intrinsics.K, pin.ego_SE3_cam.rotation, pin.ego_SE3_cam.translation,
                                       (pin.width_px, pin.height_px), f"{where} and {intr_path.name}",
                                       "is (qw, qx, qy, qz) the camera -> ego rotation, in that order (not ego -> "
                                       "camera, its inverse; not qx, qy, qz, qw)?", channel=cam)
            self._cameras[log] = cams
        return self._cameras[log]

    def _pose(self, index: int):
        log, ts = self.samples[index]
        poses = self._log_poses(log)
        path = self.log_dirs[log] / "city_SE3_egovehicle.feather"
        if ts not in poses:
            near = min(poses, key=lambda t: abs(int(t) - ts), default=None)
            rounded = (f"; its nearest is {int(near)}, {abs(int(near) - ts)} ns away: its timestamp_ns column was "
                       "rounded (saved as float64, which holds 15-16 digits of a timestamp's 18; pandas turns an "
                       "int64 column into floats where a merge or concat leaves a NaN): write it as int64"
                       if near is not None and 0 < abs(int(near) - ts) < ROUNDED_TIMESTAMP_NS else "")
            raise DatasetError(f"log {log}: {path} has no ego pose at lidar sweep {ts} (sensors/lidar/{ts}.feather)"
                               + rounded)
        pose = poses[ts]
        where = f"log {log}: the ego pose at lidar sweep {ts} in {path}"
        check_rotation(pose.rotation, "its rotation", where)
        check_translation(pose.translation, "its translation", where)
        check_ego_level(pose.rotation, where, "(qw, qx, qy, qz) in another order?")
        return pose

    def _image_path(self, log: str, cam: str, ts: int) -> Path:
        folder = self.log_dirs[log] / "sensors" / "cameras" / cam
        if folder.parent.is_symlink() and not folder.parent.exists():  # images on another disk
            raise DatasetError(f"log {log}: {folder.parent} is a symbolic link to {os.readlink(folder.parent)}, "
                               "which does not exist (a disk not mounted, or the images moved?)")
        if not folder.parent.is_dir():  # "choose the cameras with data.av2_cameras" offered a way out there is not
            raise DatasetError(f"log {log}: {folder.parent} does not exist: the log has no camera images at all (a "
                               "download without the sensor data's images?); training, evaluate, predict and "
                               "show-gt need them, export-gt does not")
        if not folder.is_dir():
            raise DatasetError(f"log {log}: camera folder {folder} does not exist; the log has no {cam} images "
                               "(an incomplete log, or choose the cameras with data.av2_cameras)")
        sync_log = logging.getLogger("av2.utils.synchronization_database")
        level = sync_log.level
        sync_log.setLevel(logging.ERROR)  # its "No corresponding ring image" warning: the error below says it
        try:
            path = self._loader(log).get_closest_img_fpath(log, cam, ts)
        finally:
            sync_log.setLevel(level)
        if path is None or not path.is_file():
            stamps = [int(p.stem) for p in self._loader(log).get_ordered_log_cam_fpaths(log, cam)]
            nearest = min(stamps, key=lambda t: abs(t - ts)) if stamps else None
            # .JPG too: a folder of upper-case names was "the folder holds no images"
            others = sorted({q.suffix for q in folder.iterdir() if q.is_file() and q.suffix != ".jpg"})
            fix = ("rename them to <timestamp_ns>.jpg, in lower case" if {o.lower() for o in others} == {".jpg"}
                   else "convert them to JPEG")
            detail = (f"the nearest is {folder / f'{nearest}.jpg'}, {abs(nearest - ts) / 1e6:.1f} ms away"
                      if nearest is not None else
                      f"the folder holds no .jpg images (AV2's loader reads only <timestamp_ns>.jpg; it holds "
                      f"{', '.join(others)} files: {fix})" if others else "the folder holds no images")
            raise DatasetError(f"log {log}: no {cam} image within {CAMERA_WINDOW_MS} ms of lidar sweep {ts} "
                               f"(sensors/lidar/{ts}.feather) in {folder}: {detail}"
                               + ("; the log's camera and lidar timestamps do not match" if nearest is not None
                                  else ""))
        if path.stem.isdigit():  # av2's synchronisation keeps a ring camera within 25 ms: any other within 0.5 s
            check_camera_time(ts // 1000, int(path.stem) // 1000, f"log {log}, lidar sweep {ts}: camera {cam}: {path}")
        return path

    # --- pieces ---------------------------------------------------------------------------------
    def gt_polylines(self, index: int) -> list[dict]:
        log, _ = self.samples[index]
        pose = self._pose(index)
        x, y = pose.translation[:2]
        return self.map_builder(log, float(x), float(y), heading(pose.rotation))

    def ego_pose(self, index: int) -> torch.Tensor:
        return torch.tensor(self._pose(index).transform_matrix, dtype=torch.float32)

    def ground_height(self, index: int) -> float:
        """The road's height below the ego origin at the sample's pose (``ego_ground_height``)."""
        log, ts = self.samples[index]
        if log not in self._grounds:
            self._grounds[log] = load_ground_height(self.log_dirs[log])
        z = ego_ground_height(self._grounds[log], self._pose(index))
        if not math.isfinite(z):
            raise DatasetError(f"log {log}: the ground-height raster in {self.log_dirs[log] / 'map'} has no value "
                               f"at the ego position of lidar sweep {ts}")
        return z

    def camera_files(self, index: int) -> list[tuple[Path, tuple[int, int]]]:
        log, ts = self.samples[index]
        cams = self._log_cameras(log)
        files = [(self._image_path(log, cam, ts), (cams[cam].width_px, cams[cam].height_px))
                 for cam in self.camera_names]
        check_distinct_images([path for path, _ in files], self.camera_names, f"log {log}, lidar sweep {ts}")
        return files

    def camera_calibration(self, index: int) -> list[tuple]:
        cams = self._log_cameras(self.samples[index][0])
        return [(cams[cam].intrinsics.K, cams[cam].ego_SE3_cam.rotation, cams[cam].ego_SE3_cam.translation)
                for cam in self.camera_names]
