"""``generate_world``: a synthetic world written in the exact nuScenes on-disk layout.

::

    DIR/
      maps/expansion/<location>.json     map expansion v1.3, all four nuScenes locations
      maps/<token>.png                   v1.0 semantic prior of each location (0.1 m/px)
      v1.0-trainval/*.json               the 13 tables
      samples/CAM_*/...jpg               6 cameras per key frame (real nuScenes rig)
      samples/LIDAR_TOP/...pcd.bin       one sweep per key frame (float32 x, y, z, intensity, ring)
      splits.json                        {"train": [scene names], "val": [...]}
      world.json                         manifest: version, seed, image size, counts, scene names

The version is always ``v1.0-trainval`` (the mini split holds only 8 + 2 scenes, and one version
keeps every world loadable the same way): scene names are real nuScenes names, train scenes
from the devkit's ``train`` split and val scenes from ``val``, so
``nuscenes.utils.splits.create_splits_scenes()`` places them correctly. Train and val scenes
drive on the same four maps (as in nuScenes), with different routes, traffic and appearance.

Scenes are rendered by the scene-job pool (jobs.py: each scene from its own generator, in this
process or in ``workers`` spawned ones, byte-identical output; a failure, named, or Ctrl-C leaves
nothing behind): a worker rebuilds the (deterministic) road networks it needs, writes the camera and
lidar files of one scene at a time and sends back only what the tables need; the main process writes
the maps and builds every table in scene order.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from pathlib import Path as FsPath

import numpy as np
from tqdm import tqdm

from ...config import UserError
from ..rig import LIDAR, parse_image_size, rig
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
from .map_writer import write_map_json, write_semantic_prior
from .render import MapPainter, SceneRenderer
from .roads import LOCATIONS, build_network, map_token
from .tables import SceneRecorder, Tables, sample_filename
from .traffic import ANNOTATION_RANGE_M, KEYFRAME_INTERVAL_S

VERSION = "v1.0-trainval"
FORMAT = "instagram-hdmap synthetic nuScenes world"
FORMAT_VERSION = 2  # 2: crossings overlap at junction corners (crossings.overlapping_corners)


def scene_names(n_train: int, n_val: int) -> tuple[list[str], list[str]]:
    """The first real nuScenes scene names of the devkit's v1.0-trainval train / val splits."""
    from nuscenes.utils import splits

    train, val = sorted(splits.train), sorted(splits.val)
    if n_train > len(train) or n_val > len(val):
        raise UserError(f"--scenes-train {n_train} / --scenes-val {n_val}: nuScenes has only {len(train)} train "
                        f"and {len(val)} val scene names; ask for fewer scenes")
    return train[:n_train], val[:n_val]


def generate_world(out, scenes_train: int = 8, scenes_val: int = 2, samples_per_scene: int = 10, seed: int = 0,
                   image_size="1600x900", force: bool = False, progress: bool = True, workers: int = 1,
                   occluders: float = 0.0) -> dict:
    """Write a synthetic nuScenes world to `out` (see the module doc). `image_size` is 'WxH' or
    (w, h). `workers`: processes rendering scenes in parallel (1: all in this process, 0: one per
    CPU core; never more than there are scenes). `occluders`: density in [0, 1] of parked rows along
    kerbs and trucks ahead in the ego's lane (``traffic.place_occluders``; 0: the same bytes as a
    world without the option). Deterministic: the same arguments give byte-identical files whatever
    `workers` is. Returns the manifest.

    With workers > 1 the worker processes are spawned, so they import the caller's main module:
    a script must call this under ``if __name__ == "__main__":``."""
    size = parse_image_size(image_size)
    workers, occluders = check_arguments(scenes_train, scenes_val, samples_per_scene, seed, workers, occluders)
    train_names, val_names = scene_names(scenes_train, scenes_val)
    return write_world(world_folder(out), force, lambda tmp: _write(tmp, train_names, val_names, samples_per_scene,
                                                              seed, size, progress, workers, occluders))


def _logfile(location: str, timestamp_us: int) -> tuple[str, str]:
    """A nuScenes-style log name (vehicle, local capture time) and its date."""
    boston = location.startswith("boston")
    tz = timezone(timedelta(hours=-4 if boston else 8))
    t = datetime.fromtimestamp(timestamp_us // 1_000_000, tz=timezone.utc).astimezone(tz)
    vehicle = "n008" if boston else "n015"
    return f"{vehicle}-{t:%Y-%m-%d-%H-%M-%S%z}", f"{t:%Y-%m-%d}"


@dataclass
class _SceneResult:
    """What the tables need from one rendered scene, whose files are already written."""

    description: str
    logfile: str
    date: str
    timestamps: list[int]  # [samples] microseconds
    poses: np.ndarray  # [samples, 3] ego (x, y, yaw) in the map frame
    annotations: list[list[tuple]]  # per sample: SceneRecorder.add_annotation arguments after the sample token


def render_scene_job(job: SceneJob, net, painter: MapPainter, on_sample: Callable[[], None]) -> _SceneResult:
    """A ``SceneJob``'s render function for the nuScenes layout (the pool calls it by reference)."""
    return _render_scene(job, net, painter, rig(job.size), on_sample)


def _render_scene(job: SceneJob, net, painter: MapPainter, sensors, on_sample: Callable[[], None]) -> _SceneResult:
    """Plans, renders and writes the camera and lidar files of one scene. Every random draw comes
    from the scene's own generator, in a fixed order, so any process gives the same bytes."""
    rng, drive, vehicles, look = plan_scene(job, net, sensors)
    renderer = SceneRenderer(painter, look, sensors, job.size, rng)
    t0 = BASE_TIMESTAMP_US + job.index * SCENE_SPACING_US
    logfile, date = _logfile(job.location, t0)
    chains = [net.stretches[net.lanes[i].stretch].chain for i in drive.lanes]
    lanes = sorted({ch.n_left + ch.n_right for ch in chains})
    description = (f"Synthetic {job.split} drive in {job.location}, {drive.speed:.1f} m/s, "
                   f"{'/'.join(str(n) for n in lanes)}-lane roads, {len(vehicles)} vehicles")
    poses = drive.poses()
    timestamps, annotations = [], []
    for k, pose in enumerate(poses):
        t = k * KEYFRAME_INTERVAL_S
        timestamp = t0 + int(round(t * 1e6))
        images, points, counts = renderer.render(pose, [v.box(t) for v in vehicles])
        for ch, image in images.items():
            (job.root / sample_filename(logfile, ch, timestamp)).write_bytes(image)
        points.tofile(job.root / sample_filename(logfile, LIDAR, timestamp))
        anns = []
        for i, v in enumerate(vehicles):
            centre, yaw, attr = v.state(t)
            if np.hypot(*(centre[:2] - pose[:2])) <= ANNOTATION_RANGE_M:
                anns.append((i, v.category, centre, yaw, v.size, attr, int(counts[i])))
        timestamps.append(timestamp)
        annotations.append(anns)
        on_sample()
    return _SceneResult(description, logfile, date, timestamps, poses, annotations)


def _record(tables: Tables, job: SceneJob, result: _SceneResult) -> str:
    """Adds one rendered scene to the tables; returns its log token."""
    rec = SceneRecorder(tables, job.index, job.name, result.description, job.location, result.logfile, result.date)
    for timestamp, pose, anns in zip(result.timestamps, result.poses, result.annotations):
        sample = rec.add_sample(timestamp, pose, job.size)
        for ann in anns:
            rec.add_annotation(sample, *ann)
    rec.finish()
    return rec.log


def _write(root: FsPath, train_names, val_names, samples_per_scene, seed, size, progress, workers: int,
           occluders: float = 0.0) -> dict:
    sensors = rig(size)
    tables = Tables(seed, sensors)
    nets = {}
    for loc in LOCATIONS:
        net = build_network(loc, seed)
        nets[loc] = net
        write_map_json(net.records, net.canvas, root / "maps" / "expansion" / f"{loc}.json")
        prior = root / "maps" / f"{map_token(loc, seed)}.png"
        write_semantic_prior(net.road_filled.union(net.walkway), net.canvas, prior)
    for ch in sensors:
        (root / "samples" / ch).mkdir(parents=True, exist_ok=True)

    scenes = [(name, "train") for name in train_names] + [(name, "val") for name in val_names]
    jobs = [SceneJob(index, name, split, LOCATIONS[index % len(LOCATIONS)], samples_per_scene, seed, size, root,
                     render_scene_job, occluders) for index, (name, split) in enumerate(scenes)]
    bar = tqdm(total=len(scenes) * samples_per_scene, desc="synth", unit="sample", disable=not progress)
    try:
        results = render_scenes(jobs, workers, lambda: bar.update(1), nets)
    finally:
        bar.close()
    logs_of: dict[str, list[str]] = {loc: [] for loc in LOCATIONS}
    for job in jobs:  # tables in scene order, whichever process rendered the scene
        logs_of[job.location].append(_record(tables, job, results[job.index]))
    for loc in LOCATIONS:
        tok = map_token(loc, seed)
        tables.add_map(tok, logs_of[loc], f"maps/{tok}.png")
    tables.write(root / VERSION)

    splits = {"train": list(train_names), "val": list(val_names)}
    (root / "splits.json").write_text(json.dumps(splits, indent=1) + "\n")
    manifest = {
        "format": FORMAT, "format_version": FORMAT_VERSION, "version": VERSION, "seed": seed,
        "image_size": list(size), "scenes_train": len(train_names), "scenes_val": len(val_names),
        "samples_per_scene": samples_per_scene, "samples": len(scenes) * samples_per_scene,
        "maps": list(LOCATIONS), "splits": splits,
    }
    if occluders > 0:  # absent at 0: such a world is byte-identical to one written before the option
        manifest["occluders"] = occluders
    (root / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
    return manifest


def read_manifest(dataroot) -> dict:
    """The world.json of a synthetic dataroot; raises UserError when it is missing or unreadable."""
    path = FsPath(dataroot) / MANIFEST
    try:
        return json.loads(path.read_text())
    except FileNotFoundError as e:
        raise UserError(f"{path}: not found; is {dataroot} a world written by 'instagram-hdmap synth'?") from e
    except (OSError, json.JSONDecodeError) as e:
        raise UserError(f"{path}: cannot read it ({e})") from e
