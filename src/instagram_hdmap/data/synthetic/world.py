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

The folder is written next to DIR under a temporary name and renamed at the end; on any
failure or Ctrl-C the temporary folder is removed, so nothing half-written is left behind.
"""

from __future__ import annotations

import json
import os
import shutil
from datetime import datetime, timedelta, timezone
from pathlib import Path as FsPath

import numpy as np
from tqdm import tqdm

from ...config import UserError
from .map_writer import write_map_json, write_semantic_prior
from .render import MapPainter, SceneRenderer, scene_look
from .rig import CAMERAS, LIDAR, parse_image_size, rig
from .roads import LOCATIONS, build_network, map_token
from .tables import Tables
from .traffic import ANNOTATION_RANGE_M, KEYFRAME_INTERVAL_S, place_vehicles, plan_drive

VERSION = "v1.0-trainval"
MANIFEST = "world.json"
FORMAT = "instagram-hdmap synthetic nuScenes world"
FORMAT_VERSION = 1
BASE_TIMESTAMP_US = 1532402927647951  # 2018-07-24 03:28:47 UTC, the first mini scene; no wall clock
SCENE_SPACING_US = 3600 * 1_000_000


def scene_names(n_train: int, n_val: int) -> tuple[list[str], list[str]]:
    """The first real nuScenes scene names of the devkit's v1.0-trainval train / val splits."""
    from nuscenes.utils import splits

    train, val = sorted(splits.train), sorted(splits.val)
    if n_train > len(train) or n_val > len(val):
        raise UserError(f"--scenes-train {n_train} / --scenes-val {n_val}: nuScenes has only {len(train)} train "
                        f"and {len(val)} val scene names; ask for fewer scenes")
    return train[:n_train], val[:n_val]


def _check_counts(scenes_train: int, scenes_val: int, samples_per_scene: int) -> None:
    if scenes_train < 0 or scenes_val < 0:
        raise UserError(f"--scenes-train {scenes_train} / --scenes-val {scenes_val}: counts cannot be negative")
    if scenes_train + scenes_val == 0:
        raise UserError("zero scenes requested: give --scenes-train and/or --scenes-val of at least 1")
    if samples_per_scene < 1:
        raise UserError(f"--samples-per-scene {samples_per_scene}: a scene needs at least 1 sample")


def _prepare_out(out: FsPath, force: bool) -> FsPath:
    """Checks --out and creates the temporary sibling folder; returns it."""
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out}: exists and is not a folder; choose another path")
    if out.is_dir() and any(out.iterdir()):
        if not force:
            raise UserError(f"--out {out}: folder is not empty; choose an empty folder or pass --force to replace it")
        if not (out / MANIFEST).is_file():
            raise UserError(f"--out {out}: folder is not empty and holds no synthetic world ({MANIFEST}); "
                            "--force only replaces a world written by 'instagram-hdmap synth'")
    parent = out.resolve().parent
    tmp = parent / f".{out.name}.synth-tmp-{os.getpid()}"
    try:
        parent.mkdir(parents=True, exist_ok=True)
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir()
        probe = tmp / ".write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        shutil.rmtree(tmp, ignore_errors=True)
        raise UserError(f"--out {out}: cannot write there ({e.strerror or e}); choose a writable folder") from e
    return tmp


def generate_world(out, scenes_train: int = 8, scenes_val: int = 2, samples_per_scene: int = 10, seed: int = 0,
                   image_size="1600x900", force: bool = False, progress: bool = True) -> dict:
    """Write a synthetic nuScenes world to `out` (see the module doc). `image_size` is 'WxH' or
    (w, h). Deterministic: the same arguments give byte-identical files. Returns the manifest."""
    size = parse_image_size(image_size)
    _check_counts(scenes_train, scenes_val, samples_per_scene)
    train_names, val_names = scene_names(scenes_train, scenes_val)
    out = FsPath(out)
    tmp = _prepare_out(out, force)
    try:
        manifest = _write(tmp, train_names, val_names, samples_per_scene, seed, size, progress)
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return manifest


def _logfile(location: str, timestamp_us: int) -> tuple[str, str]:
    """A nuScenes-style log name (vehicle, local capture time) and its date."""
    boston = location.startswith("boston")
    tz = timezone(timedelta(hours=-4 if boston else 8))
    t = datetime.fromtimestamp(timestamp_us // 1_000_000, tz=timezone.utc).astimezone(tz)
    vehicle = "n008" if boston else "n015"
    offset = "-0400" if boston else "+0800"
    return f"{vehicle}-{t:%Y-%m-%d-%H-%M-%S}{offset}", f"{t:%Y-%m-%d}"


def _write(root: FsPath, train_names, val_names, samples_per_scene, seed, size, progress) -> dict:
    sensors = rig(size)
    tables = Tables(seed, sensors)
    nets, painters = {}, {}
    for loc in LOCATIONS:
        net = build_network(loc, seed)
        nets[loc] = net
        write_map_json(net.records, net.canvas, root / "maps" / "expansion" / f"{loc}.json")
        prior = root / "maps" / f"{map_token(loc, seed)}.png"
        write_semantic_prior(net.road_filled.union(net.walkway), net.canvas, prior)
    for ch in sensors:
        (root / "samples" / ch).mkdir(parents=True, exist_ok=True)

    scenes = [(name, "train") for name in train_names] + [(name, "val") for name in val_names]
    logs_of: dict[str, list[str]] = {loc: [] for loc in LOCATIONS}
    bar = tqdm(total=len(scenes) * samples_per_scene, desc="synth", unit="sample", disable=not progress)
    for index, (name, split) in enumerate(scenes):
        loc = LOCATIONS[index % len(LOCATIONS)]
        net = nets[loc]
        if loc not in painters:
            painters[loc] = MapPainter(net, seed)
        rng = np.random.default_rng([seed, 1000 + index])
        drive = plan_drive(net, samples_per_scene, rng)
        vehicles = place_vehicles(net, drive, rng)
        look = scene_look(rng)
        renderer = SceneRenderer(painters[loc], look, sensors, size, rng)
        t0 = BASE_TIMESTAMP_US + index * SCENE_SPACING_US
        logfile, date = _logfile(loc, t0)
        chains = [net.stretches[net.lanes[i].stretch].chain for i in drive.lanes]
        lanes = sorted({ch.n_left + ch.n_right for ch in chains})
        description = (f"Synthetic {split} drive in {loc}, {drive.speed:.1f} m/s, "
                       f"{'/'.join(str(n) for n in lanes)}-lane roads, {len(vehicles)} vehicles")
        rec = tables.begin_scene(index, name, description, loc, logfile, date)
        logs_of[loc].append(rec.log)
        poses = drive.poses()
        for k, pose in enumerate(poses):
            t = k * KEYFRAME_INTERVAL_S
            timestamp = t0 + int(round(t * 1e6))
            boxes = [v.box(t) for v in vehicles]
            images, points, counts = renderer.render(pose, boxes)
            sample = rec.add_sample(timestamp, pose, size)
            for ch in CAMERAS:
                (root / rec.filename(ch, timestamp)).write_bytes(images[ch])
            points.tofile(root / rec.filename(LIDAR, timestamp))
            for i, v in enumerate(vehicles):
                centre, yaw, attr = v.state(t)
                if np.hypot(*(centre[:2] - pose[:2])) <= ANNOTATION_RANGE_M:
                    rec.add_annotation(sample, i, v.category, centre, yaw, v.size, attr, int(counts[i]))
            bar.update(1)
        rec.finish()
    bar.close()
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
