"""The scene-job pool both world writers share (world.py: nuScenes layout, av2_writer.py: Argoverse 2).

    jobs = [SceneJob(index, name, split, location, samples, seed, size, root, render_fn) ...]
    manifest = write_world(out, force, lambda tmp: ... render_scenes(jobs, workers, tick, nets) ...)

A ``SceneJob`` is all a process needs to render one scene from scratch, including the writer's
render function (``render(job, net, painter, on_sample)``, a module-level function, so that a job
pickles into a spawned worker by reference). ``render_scenes`` renders the jobs in this process
(``workers`` = 1) or in that many spawned processes, each taking the next scene when it is free;
scenes are independent (each draws from its own generator), so the output is byte-identical for
any number of workers. The first failure (an exception in a scene, a worker that dies or hangs)
stops every worker and is raised as a ``SceneGenerationError`` naming the scene.

``write_world`` writes a world next to ``out`` under a temporary name (``files.atomic_path``) and
renames it at the end; on any failure or Ctrl-C the temporary folder is removed, so nothing
half-written is left behind.
"""

from __future__ import annotations

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
from pathlib import Path as FsPath

import cv2
import numpy as np

from ...config import UserError
from ...files import atomic_path, check_no_broken_link, claim_world, remove_stale_temporaries
from .render import MapPainter, scene_look
from .roads import build_network
from .traffic import place_occluders, place_vehicles, plan_drive

MANIFEST = "world.json"
BASE_TIMESTAMP_US = 1532402927647951  # 2018-07-24 03:28:47 UTC, the first mini scene; no wall clock
SCENE_SPACING_US = 3600 * 1_000_000
MP_START_METHOD = "spawn"  # workers start clean: no copied locks or threads (torch, OpenCV) from the caller
POLL_S = 0.5  # how often the main process checks that its workers are alive while it waits
STALL_S = 600.0  # a worker that sends nothing for this long (a sample takes seconds) is declared hung
# what a world holds at its top level (nuScenes layout: maps, samples, the tables' version folder, splits.json;
# Argoverse 2 layout: a folder per split), and the manifest
WORLD_ENTRIES = frozenset({MANIFEST, "maps", "samples", "sweeps", "v1.0-trainval", "v1.0-mini", "splits.json", "train",
                           "val", "test"})
TMP_TAG = "synth-tmp"  # a world is written at .NAME.synth-tmp-PID (the next generation removes those of dead processes)


class SceneGenerationError(RuntimeError):
    """Rendering one scene of a synthetic world failed; the message names the scene."""


class _WorkerTraceback(Exception):
    """The traceback of an error in a worker process, chained as the cause of SceneGenerationError."""

    def __str__(self) -> str:
        return f'\n"""\n{self.args[0]}"""'


@dataclass(frozen=True)
class SceneJob:
    """One scene to render: all a worker process needs to redo it from scratch."""

    index: int
    name: str
    split: str
    location: str
    samples: int
    seed: int
    size: tuple[int, int]
    root: FsPath
    # render(job, net, painter, on_sample) -> what the writer's tables need; module-level (it pickles by name)
    render: Callable
    occluders: float = 0.0  # density of traffic.place_occluders

    def describe(self) -> str:
        return f"synthetic scene {self.name} ({self.split} scene #{self.index}, map {self.location})"


# --- arguments ------------------------------------------------------------------------------------


def check_arguments(scenes_train: int, scenes_val: int, samples_per_scene: int, seed: int, workers,
                    occluders) -> tuple[int, float]:
    """The arguments of a world: scene and sample counts, the seed (numpy's generators take 0 .. 2**63),
    --workers (0: one per available CPU core) and --occluders; returns (worker processes, occluder density)."""
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or not 0 <= seed < 2**63:
        raise UserError(f"--seed {seed}: a world's seed is a whole number from 0 to 2**63 - 1")
    for flag, value in (("--scenes-train", scenes_train), ("--scenes-val", scenes_val),
                        ("--samples-per-scene", samples_per_scene)):
        if isinstance(value, bool) or not isinstance(value, numbers.Integral):  # 1.0: a raw TypeError deep inside
            raise UserError(f"{flag} {value!r}: a count of scenes or samples is a whole number (an int)")
    if scenes_train < 0 or scenes_val < 0:
        raise UserError(f"--scenes-train {scenes_train} / --scenes-val {scenes_val}: counts cannot be negative")
    if scenes_train + scenes_val == 0:
        raise UserError("zero scenes requested: give --scenes-train and/or --scenes-val of at least 1")
    if samples_per_scene < 1:
        raise UserError(f"--samples-per-scene {samples_per_scene}: a scene needs at least 1 sample")
    if isinstance(workers, bool) or not isinstance(workers, numbers.Integral) or workers < 0:
        raise UserError(f"--workers {workers}: expected a whole number >= 0 (1: render in this process, "
                        "N: N worker processes, 0: one per CPU core)")
    if isinstance(occluders, bool) or not isinstance(occluders, numbers.Real) or not 0 <= occluders <= 1:
        raise UserError(f"--occluders {occluders}: expected a density in [0, 1] (0: today's traffic only, 1: a "
                        "parked row along every free kerb near the drive and a truck ahead in every scene)")
    return int(workers) or available_cpus(), float(occluders)


def available_cpus() -> int:
    """CPU cores this process may run on (its affinity where the OS reports one)."""
    if hasattr(os, "process_cpu_count"):  # Python >= 3.13
        return os.process_cpu_count() or 1
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0)) or 1
    return os.cpu_count() or 1


def plan_scene(job: SceneJob, net, sensors: dict) -> tuple:
    """The scene's generator, seeded by (seed, 1000 + scene), after drawing its drive, traffic and look in
    this order, which both writers share (so scene i is the same in both layouts); returns (rng, drive,
    vehicles, look). The occluders (``traffic.place_occluders``) come from a generator of their own, seeded
    by (seed, 2000 + scene): the scene's own stream of draws is untouched, and density 0 draws nothing."""
    rng = np.random.default_rng([job.seed, 1000 + job.index])
    drive = plan_drive(net, job.samples, rng)
    vehicles = place_vehicles(net, drive, rng)
    if job.occluders > 0:
        vehicles += place_occluders(net, drive, np.random.default_rng([job.seed, 2000 + job.index]), job.occluders,
                                    vehicles)
    return rng, drive, vehicles, scene_look(rng, sensors)


# --- the output folder ------------------------------------------------------------------------------


def _check_out(out: FsPath, force: bool) -> None:
    check_no_broken_link(out, "--out")  # out.resolve() below would follow it (or raise on a loop)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out}: exists and is not a folder; choose another path")
    if out.is_dir() and any(out.iterdir()):
        if not force:
            raise UserError(f"--out {out}: folder is not empty; choose an empty folder or pass --force to replace it")
        if not (out / MANIFEST).is_file():
            raise UserError(f"--out {out}: folder is not empty and holds no synthetic world ({MANIFEST}); "
                            "--force only replaces a world written by 'instagram-hdmap synth'")
        others = sorted(p.name for p in out.iterdir() if p.name not in WORLD_ENTRIES)
        if others:  # a training run or an evaluation kept inside the world: --force removed them with it
            raise UserError(f"--out {out}: besides the synthetic world it holds {', '.join(others[:5])}"
                            f"{f' and {len(others) - 5} more' if len(others) > 5 else ''}, which --force would delete "
                            "with the world; move them out of it first, or choose another --out")


def _unwritable(out: FsPath, e: OSError) -> UserError:
    for parent in out.absolute().parents:  # a file on the way said "File exists", naming neither it nor the cause
        if parent.is_file():
            return UserError(f"--out {out}: cannot write there: {parent} is a file, not a folder; choose another path")
    return UserError(f"--out {out}: cannot write there ({e.strerror or e}); choose a writable folder")


def _make_writable(tmp: FsPath, out: FsPath) -> None:
    """Creates the temporary folder ``tmp`` and checks that a file can be written in it."""
    try:
        if tmp.exists():  # left by an earlier run of this very process id
            shutil.rmtree(tmp)
        tmp.mkdir()
        probe = tmp / ".write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise _unwritable(out, e) from e


def world_folder(out) -> FsPath:
    """The ``out`` argument of the world generators as a path; an empty string is refused (``Path('')`` is the
    current folder: an unset shell variable wrote the world there)."""
    if isinstance(out, str) and not out.strip():
        raise UserError(f"--out {out!r}: an empty path (an unset shell variable?); name the world's folder")
    return FsPath(out)


def write_world(out: FsPath, force: bool, write: Callable[[FsPath], dict]) -> dict:
    """``write(tmp)`` into a temporary sibling folder of ``out``, then rename it to ``out`` (replacing a
    world there with ``force``): a world is whole or absent, never half-written. Returns what ``write``
    returns (the manifest)."""
    out = FsPath(out)
    _check_out(out, force)
    target = out.resolve()
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise _unwritable(out, e) from e
    for stale in remove_stale_temporaries(target, TMP_TAG):
        print(f"removed {stale}: a generation of this world that did not finish (its process is gone)", flush=True)
    claim = claim_world(out, "--out", MANIFEST) if force else None  # a world being read is refused before the work
    if claim is not None:
        claim.close()
    held = None
    try:
        with atomic_path(target, TMP_TAG) as tmp:
            _make_writable(tmp, out)
            manifest = write(tmp)
            if not force and out.is_dir() and any(out.iterdir()):  # filled while this world was rendered: the
                # rename would replace it (another synth of the same --out, started after this one's check)
                raise UserError(f"--out {out}: the folder was filled while this world was generated (another synth "
                                "with the same --out?); it is kept as it is and this world is dropped: choose another "
                                "--out, or pass --force to replace it")
            # and again for the rename (a training started on it meanwhile), held until the world is replaced
            held = claim_world(out, "--out", MANIFEST) if force else None
            return manifest
    finally:
        if held is not None:
            held.close()


# --- rendering ---------------------------------------------------------------------------------------


def render_scenes(jobs: list[SceneJob], workers: int, on_sample: Callable[[], None],
                  nets: dict | None = None) -> dict[int, object]:
    """Every job's result by job index: in this process, one scene after the other (``workers`` <= 1;
    ``nets``: the road networks by location, built here where absent) or in ``min(workers, len(jobs))``
    spawned processes."""
    workers = min(workers, len(jobs))
    if workers > 1:
        return _render_parallel(jobs, workers, on_sample)
    nets, painters, results = dict(nets or {}), {}, {}
    for job in jobs:
        net, painter = _map_of(job, nets, painters)
        try:
            results[job.index] = job.render(job, net, painter, on_sample)
        except Exception as e:  # KeyboardInterrupt passes through untouched
            raise SceneGenerationError(f"{job.describe()} failed: {type(e).__name__}: {e}") from e
    return results


def _map_of(job: SceneJob, nets: dict, painters: dict) -> tuple:
    """The road network and painter of the job's map, built on first use (any process builds the same)."""
    if job.location not in nets:
        nets[job.location] = build_network(job.location, job.seed)
    if job.location not in painters:
        painters[job.location] = MapPainter(nets[job.location], job.seed)
    return nets[job.location], painters[job.location]


def _worker_main(tasks, events, cv_threads: int) -> None:
    """A worker process: renders scenes from `tasks` until None; reports on `events` as
    (kind, pid, scene index, payload) with kind 'start', 'sample', 'done' (payload: the job's result)
    or 'error' (payload: (message, traceback text))."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the main process's to handle: it terminates us
    cv2.setNumThreads(cv_threads)
    pid = os.getpid()
    nets, painters = {}, {}
    while (job := tasks.get()) is not None:
        events.put(("start", pid, job.index, None))
        try:
            net, painter = _map_of(job, nets, painters)
            result = job.render(job, net, painter, lambda: events.put(("sample", pid, job.index, None)))
        except BaseException as e:  # anything, so that the main process never waits for a lost scene
            events.put(("error", pid, job.index, (f"{type(e).__name__}: {e}", traceback.format_exc())))
            return
        events.put(("done", pid, job.index, result))


def _render_parallel(jobs: list[SceneJob], workers: int, on_sample) -> dict[int, object]:
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
    results: dict[int, object] = {}
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


def _check_workers_alive(procs, running: dict[int, int], by_index: dict[int, SceneJob], results) -> None:
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
