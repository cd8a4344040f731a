"""Seconds per synthetic sample: 6 camera JPEGs (default 1600x900), one lidar sweep and the table
records, as written by ``instagram-hdmap synth``. Target: <= 1.5 s per sample on 2 CPU cores.

    python benchmarks/synth_speed.py [--scenes 2] [--samples-per-scene 10] [--image-size 1600x900]
                                     [--workers W]

Rows:
  fixed            a world of 1 scene x 1 sample: imports, 4 maps (geometry, JSON, PNG) and 1 sample
  world            a world of SCENES x SAMPLES; per sample = (wall - fixed wall) / samples
  world, W workers the same world with ``generate_world(workers=W)`` (only with --workers other than 1);
                   the last column is its speed-up: world wall / this wall (W spawned processes
                   share the cores; W is at most SCENES)
  render, N thr.   SceneRenderer.render alone (images + lidar, no file writes), OpenCV on N threads
CPU is the CPU time of the process and its finished worker processes (all threads), so CPU / wall > 1
means several cores were used. The machine may be shared: compare CPU with wall when the numbers
look noisy.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from instagram_hdmap.data.rig import parse_image_size, rig
from instagram_hdmap.data.synthetic import generate_world
from instagram_hdmap.data.synthetic.jobs import available_cpus
from instagram_hdmap.data.synthetic.render import MapPainter, SceneRenderer, scene_look
from instagram_hdmap.data.synthetic.roads import build_network
from instagram_hdmap.data.synthetic.traffic import place_vehicles, plan_drive


def _cpu() -> float:
    """CPU seconds of this process and of its children that have been waited for."""
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


def _timed(fn) -> tuple[float, float]:
    w0, c0 = time.perf_counter(), _cpu()
    fn()
    return time.perf_counter() - w0, _cpu() - c0


def _world(tmp: Path, scenes: int, samples: int, size: str, workers: int = 1) -> tuple[float, float]:
    out = tmp / f"w{scenes}x{samples}"
    t = _timed(lambda: generate_world(out, scenes_train=scenes, scenes_val=0, samples_per_scene=samples,
                                      image_size=size, progress=False, workers=workers))
    shutil.rmtree(out)
    return t


def _render_only(size: tuple[int, int], frames: int, threads: int) -> tuple[float, float]:
    cv2.setNumThreads(threads)
    net = build_network("singapore-onenorth", 0)
    rng = np.random.default_rng(0)
    drive = plan_drive(net, frames, rng)
    vehicles = place_vehicles(net, drive, rng)
    renderer = SceneRenderer(MapPainter(net, 0), scene_look(rng, rig(size)), rig(size), size, rng)
    poses = drive.poses()
    renderer.render(poses[0], [v.box(0.0) for v in vehicles])  # warm-up (texture tiles)
    return _timed(lambda: [renderer.render(p, [v.box(0.5 * k) for v in vehicles]) for k, p in enumerate(poses)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=2)
    ap.add_argument("--samples-per-scene", type=int, default=10)
    ap.add_argument("--image-size", default="1600x900")
    ap.add_argument("--workers", type=int, default=1, help="also time the world with this many worker processes "
                    "(0: one per CPU core)")
    args = ap.parse_args()
    from instagram_hdmap.benchmark import check_counts

    check_counts(ap, args, scenes=1, samples_per_scene=1, workers=0)
    if args.scenes * args.samples_per_scene < 2:  # the per-sample time is (world - 1-sample world) / (n - 1)
        ap.error(f"--scenes {args.scenes} x --samples-per-scene {args.samples_per_scene} is one sample: the time per "
                 "sample is measured against a 1-sample world, so give a world of at least 2 samples")
    size = parse_image_size(args.image_size)
    default_threads = cv2.getNumThreads()
    n = args.scenes * args.samples_per_scene
    rows = []
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        fw, fc = _world(tmp, 1, 1, args.image_size)
        rows.append(("fixed (1 scene x 1 sample)", 1, fw, fc, None, None))
        ww, wc = _world(tmp, args.scenes, args.samples_per_scene, args.image_size)
        rows.append((f"world ({args.scenes} x {args.samples_per_scene})", n, ww, wc, (ww - fw) / (n - 1),
                     (wc - fc) / (n - 1)))
        if args.workers != 1:
            pw, pc = _world(tmp, args.scenes, args.samples_per_scene, args.image_size, args.workers)
            used = min(args.workers or available_cpus(), args.scenes)
            rows.append((f"world, {used} workers", n, pw, pc, (pw - fw) / (n - 1), (pc - fc) / (n - 1), ww / pw))
    for threads in sorted({default_threads, 1}, reverse=True):
        rw, rc = _render_only(size, args.samples_per_scene, threads)
        k = args.samples_per_scene
        rows.append((f"render only, {threads} OpenCV thr.", k, rw, rc, rw / k, rc / k))
    cv2.setNumThreads(default_threads)

    print(f"\nsynthetic world speed, images {size[0]}x{size[1]} (6 cameras + LIDAR_TOP per sample)\n")
    print(f"{'run':<32} {'samples':>7} {'wall s':>8} {'CPU s':>8} {'wall s/sample':>14} {'CPU s/sample':>13}"
          f"{' speed-up' if args.workers != 1 else ''}")
    for name, k, w, c, ws, cs, *speedup in rows:
        ws_s = f"{ws:14.3f}" if ws is not None else f"{'':>14}"
        cs_s = f"{cs:13.3f}" if cs is not None else f"{'':>13}"
        sp_s = f" {speedup[0]:8.2f}x" if speedup else ""
        print(f"{name:<32} {k:>7} {w:8.2f} {c:8.2f} {ws_s} {cs_s}{sp_s}")
    print(f"\n{available_cpus()} CPU cores available; 1-minute load average {os.getloadavg()[0]:.2f} at the end")


if __name__ == "__main__":
    from instagram_hdmap.benchmark import script_main

    script_main(main)
