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

Scenes are independent (each draws from its own generator, seeded by ``(seed, 1000 + index)``),
so ``workers > 1`` renders them in that many spawned processes: each worker rebuilds the
(deterministic) road networks it needs, plans, renders and writes the camera and lidar files of
one scene at a time and sends back only what the tables need; the main process writes the maps
and builds every table in scene order. The output is byte-identical for any number of workers.

The folder is written next to DIR under a temporary name and renamed at the end; on any
failure or Ctrl-C the workers are terminated and the temporary folder is removed, so nothing
half-written is left behind. A failing scene is named in the error.
"""

from __future__ import annotations

import json
import multiprocessing
import numbers
import os
import queue
import shutil
import signal
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from pathlib import Path as FsPath

import cv2
import numpy as np
from tqdm import tqdm

from ...config import UserError
from .map_writer import write_map_json, write_semantic_prior
from .render import MapPainter, SceneRenderer, scene_look
from .rig import CAMERAS, LIDAR, parse_image_size, rig
from .roads import LOCATIONS, build_network, map_token
from .tables import Tables, sample_filename
from .traffic import ANNOTATION_RANGE_M, KEYFRAME_INTERVAL_S, place_vehicles, plan_drive

VERSION = "v1.0-trainval"
MANIFEST = "world.json"
FORMAT = "instagram-hdmap synthetic nuScenes world"
FORMAT_VERSION = 2  # 2: crossings overlap at junction corners (roads._overlapping_corners)
BASE_TIMESTAMP_US = 1532402927647951  # 2018-07-24 03:28:47 UTC, the first mini scene; no wall clock
SCENE_SPACING_US = 3600 * 1_000_000
MP_START_METHOD = "spawn"  # workers start clean: no copied locks or threads (torch, OpenCV) from the caller
POLL_S = 0.5  # how often the main process checks that its workers are alive while it waits
STALL_S = 600.0  # a worker that sends nothing for this long (a sample takes seconds) is declared hung


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


def available_cpus() -> int:
    """CPU cores this process may run on (its affinity where the OS reports one)."""
    if hasattr(os, "process_cpu_count"):  # Python >= 3.13
        return os.process_cpu_count() or 1
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0)) or 1
    return os.cpu_count() or 1


def _check_workers(workers) -> int:
    """--workers as a process count: 0 means one per available CPU core."""
    if isinstance(workers, bool) or not isinstance(workers, numbers.Integral) or workers < 0:
        raise UserError(f"--workers {workers}: expected a whole number >= 0 (1: render in this process, "
                        "N: N worker processes, 0: one per CPU core)")
    return int(workers) or available_cpus()


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
                   image_size="1600x900", force: bool = False, progress: bool = True, workers: int = 1) -> dict:
    """Write a synthetic nuScenes world to `out` (see the module doc). `image_size` is 'WxH' or
    (w, h). `workers`: processes rendering scenes in parallel (1: all in this process, 0: one per
    CPU core; never more than there are scenes). Deterministic: the same arguments give
    byte-identical files whatever `workers` is. Returns the manifest.

    With workers > 1 the worker processes are spawned, so they import the caller's main module:
    a script must call this under ``if __name__ == "__main__":``."""
    size = parse_image_size(image_size)
    _check_counts(scenes_train, scenes_val, samples_per_scene)
    workers = _check_workers(workers)
    train_names, val_names = scene_names(scenes_train, scenes_val)
    return _write_atomically(FsPath(out), force, lambda tmp: _write(tmp, train_names, val_names, samples_per_scene,
                                                                     seed, size, progress, workers))


def _write_atomically(out: FsPath, force: bool, write) -> dict:
    """``write(tmp)`` into a temporary sibling of ``out`` (``_prepare_out``), then rename it to ``out``:
    a world is whole or absent, never half-written; returns what ``write`` returns (the manifest)."""
    tmp = _prepare_out(out, force)
    try:
        manifest = write(tmp)
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


@dataclass(frozen=True)
class _SceneJob:
    """One scene to render: all a worker process needs to redo it from scratch."""

    index: int
    name: str
    split: str
    location: str
    samples: int
    seed: int
    size: tuple[int, int]
    root: FsPath
    fmt: str = "nuscenes"  # nuscenes | av2 (av2_writer.py writes the whole log folder)

    def describe(self) -> str:
        return f"synthetic scene {self.name} ({self.split} scene #{self.index}, map {self.location})"


@dataclass
class _SceneResult:
    """What the tables need from one rendered scene, whose files are already written."""

    description: str
    logfile: str
    date: str
    timestamps: list[int]  # [samples] microseconds
    poses: np.ndarray  # [samples, 3] ego (x, y, yaw) in the map frame
    annotations: list[list[tuple]]  # per sample: SceneRecorder.add_annotation arguments after the sample token


class SceneGenerationError(RuntimeError):
    """Rendering one scene of a synthetic world failed; the message names the scene."""


class _WorkerTraceback(Exception):
    """The traceback of an error in a worker process, chained as the cause of SceneGenerationError."""

    def __str__(self) -> str:
        return f'\n"""\n{self.args[0]}"""'


def _render_scene(job: _SceneJob, net, painter: MapPainter, sensors, on_sample: Callable[[], None]) -> _SceneResult:
    """Plans, renders and writes the camera and lidar files of one scene. Every random draw comes
    from the scene's own generator, in a fixed order, so any process gives the same bytes."""
    rng = np.random.default_rng([job.seed, 1000 + job.index])
    drive = plan_drive(net, job.samples, rng)
    vehicles = place_vehicles(net, drive, rng)
    look = scene_look(rng)
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
        for ch in CAMERAS:
            (job.root / sample_filename(logfile, ch, timestamp)).write_bytes(images[ch])
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


def _render_job(job: _SceneJob, net, painter: MapPainter, on_sample: Callable[[], None]):
    """Renders one scene in the job's on-disk format (the same drive, traffic and map either way)."""
    if job.fmt == "av2":
        from .av2_writer import render_log

        return render_log(job, net, painter, on_sample)
    return _render_scene(job, net, painter, rig(job.size), on_sample)


def _record(tables: Tables, job: _SceneJob, result: _SceneResult) -> str:
    """Adds one rendered scene to the tables; returns its log token."""
    rec = tables.begin_scene(job.index, job.name, result.description, job.location, result.logfile, result.date)
    for timestamp, pose, anns in zip(result.timestamps, result.poses, result.annotations):
        sample = rec.add_sample(timestamp, pose, job.size)
        for ann in anns:
            rec.add_annotation(sample, *ann)
    rec.finish()
    return rec.log


def _render_serial(jobs: list[_SceneJob], nets: dict, on_sample) -> dict[int, _SceneResult]:
    """All scenes in this process, one after the other."""
    painters: dict[str, MapPainter] = {}
    results = {}
    for job in jobs:
        net = nets[job.location]
        if job.location not in painters:
            painters[job.location] = MapPainter(net, job.seed)
        try:
            results[job.index] = _render_job(job, net, painters[job.location], on_sample)
        except Exception as e:  # KeyboardInterrupt passes through untouched
            raise SceneGenerationError(f"{job.describe()} failed: {type(e).__name__}: {e}") from e
    return results


def _worker_main(tasks, events, cv_threads: int) -> None:
    """A worker process: renders scenes from `tasks` until None; reports on `events` as
    (kind, pid, scene index, payload) with kind 'start', 'sample', 'done' (payload: _SceneResult)
    or 'error' (payload: (message, traceback text))."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the main process's to handle: it terminates us
    cv2.setNumThreads(cv_threads)
    pid = os.getpid()
    nets, painters = {}, {}
    while (job := tasks.get()) is not None:
        events.put(("start", pid, job.index, None))
        try:
            if job.location not in nets:
                nets[job.location] = build_network(job.location, job.seed)
                painters[job.location] = MapPainter(nets[job.location], job.seed)
            result = _render_job(job, nets[job.location], painters[job.location],
                                 lambda: events.put(("sample", pid, job.index, None)))
        except BaseException as e:  # anything, so that the main process never waits for a lost scene
            events.put(("error", pid, job.index, (f"{type(e).__name__}: {e}", traceback.format_exc())))
            return
        events.put(("done", pid, job.index, result))


def _render_parallel(jobs: list[_SceneJob], workers: int, on_sample) -> dict[int, _SceneResult]:
    """Scenes in `workers` spawned processes, each taking the next scene when it is free. The
    first failure (an exception in a scene, a worker that dies) stops all workers and is raised."""
    ctx = multiprocessing.get_context(MP_START_METHOD)
    tasks, events = ctx.Queue(), ctx.Queue()
    for job in jobs:
        tasks.put(job)
    for _ in range(workers):
        tasks.put(None)
    cv_threads = max(1, available_cpus() // workers)  # OpenCV's own threads share the cores
    procs = [ctx.Process(target=_worker_main, args=(tasks, events, cv_threads), name=f"synth-worker-{i}", daemon=True)
             for i in range(workers)]
    by_index = {job.index: job for job in jobs}
    results: dict[int, _SceneResult] = {}
    running: dict[int, int] = {}  # worker pid -> index of the scene it renders
    finished = False
    try:
        for p in procs:
            p.start()
        last_event = time.monotonic()
        while len(results) < len(jobs):
            try:
                kind, pid, index, payload = events.get(timeout=POLL_S)
            except queue.Empty:
                _check_workers_alive(procs, running, by_index, results)
                if time.monotonic() - last_event > STALL_S:
                    busy = [by_index[i].describe() for i in running.values()] or ["no scene yet"]
                    raise SceneGenerationError(f"no progress from the worker processes for {STALL_S:.0f} s "
                                               f"(rendering: {', '.join(busy)}); they look hung: stopped them. "
                                               "Try --workers 1") from None
                continue
            last_event = time.monotonic()
            if kind == "start":
                running[pid] = index
            elif kind == "sample":
                on_sample()
            elif kind == "done":
                results[index] = payload
                running.pop(pid, None)
            else:
                message, tb = payload
                error = SceneGenerationError(f"{by_index[index].describe()} failed in a worker process: {message}")
                raise error from _WorkerTraceback(tb)
        finished = True
    finally:
        if not finished:  # error or Ctrl-C: stop now, before the caller removes the folder they write to
            for p in procs:
                if p.is_alive():
                    p.terminate()
            tasks.cancel_join_thread()  # scenes nobody will take must not block this process's exit
        for p in procs:
            if p.pid is not None:
                p.join()
        tasks.close()
        events.close()
    return results


def _check_workers_alive(procs, running: dict[int, int], by_index: dict[int, _SceneJob], results) -> None:
    for p in procs:
        if p.exitcode not in (None, 0):
            index = running.get(p.pid)
            what = by_index[index].describe() if index is not None else "a synthetic scene"
            how = f"was killed by signal {-p.exitcode}" if p.exitcode < 0 else f"exited with code {p.exitcode}"
            raise SceneGenerationError(f"a worker process {how} while rendering {what} (out of memory?); "
                                       "try fewer --workers")
    if all(p.exitcode == 0 for p in procs):  # every worker is done, yet scenes are missing
        missing = [by_index[i].name for i in sorted(set(by_index) - set(results))]
        raise SceneGenerationError(f"worker processes exited without rendering scenes {missing}")


def _write(root: FsPath, train_names, val_names, samples_per_scene, seed, size, progress, workers: int) -> dict:
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
    jobs = [_SceneJob(index, name, split, LOCATIONS[index % len(LOCATIONS)], samples_per_scene, seed, size, root)
            for index, (name, split) in enumerate(scenes)]
    workers = min(workers, len(jobs))
    bar = tqdm(total=len(scenes) * samples_per_scene, desc="synth", unit="sample", disable=not progress)
    try:
        if workers > 1:
            results = _render_parallel(jobs, workers, lambda: bar.update(1))
        else:
            results = _render_serial(jobs, nets, lambda: bar.update(1))
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
