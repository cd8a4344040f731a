"""Per-sample data-loading time, split into image decode, map extraction and targets.

Runs on a synthetic world with 1600 x 900 camera images (generated into a temporary folder unless
``--dataroot`` names one), for the network image sizes 128 x 352 and 256 x 704, and compares the
reduced-resolution JPEG decode (``cv2.IMREAD_REDUCED_COLOR_f``) with a full decode. The targets are
also timed on a fixed hand-made map of 30 polylines (the size of the official code's 26 ms figure).
Prints, per sample (6 images), the median over samples of the best of ``--repeats`` timings, in one
process and one thread (OpenCV and torch).

    python benchmarks/data_speed.py [--dataroot D --version V] [--samples 20] [--repeats 3]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from functools import partial
from pathlib import Path

import cv2
import numpy as np
import torch
from shapely.geometry import LineString

from instagram_hdmap.config import load_config
from instagram_hdmap.data.local_map import resample_line
from instagram_hdmap.data.nuscenes import NuScenesMapDataset
from instagram_hdmap.data.rig import CAMERAS
from instagram_hdmap.data.transforms import load_image
from instagram_hdmap.geometry import BEVGrid
from instagram_hdmap.targets import build_targets


def best_ms(fn, repeats: int) -> float:
    """Best of ``repeats`` timed calls after one warm-up call (robust to other load on the machine)."""
    fn()
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, (time.perf_counter() - t) * 1e3)
    return best


def load_all(paths: list, out_hw: tuple[int, int], reduced: bool) -> None:
    for path, wh in paths:
        load_image(path, wh, out_hw, reduced_decode=reduced)


def thirty_polylines(rng: np.random.Generator) -> list[dict]:
    """30 map elements on the 60 m x 30 m grid: 12 dividers, 8 crossings, 10 boundaries, resampled at 1.5 m."""
    out = []
    for i in range(30):
        label = 0 if i < 12 else (1 if i < 20 else 2)
        c = rng.uniform([-28, -13], [28, 13])
        if label == 1:
            a = rng.uniform(0, np.pi)
            R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
            box = np.array([[-3, -1.5], [3, -1.5], [3, 1.5], [-3, 1.5], [-3, -1.5]]) @ R.T + c
            out.append({"pts": resample_line(LineString(box), 1.5, closed=True), "label": 1, "closed": True})
        else:
            x = np.linspace(-25, 25, 30)
            pts = np.c_[x, c[1] + 2 * np.sin(x / 9 + c[0])]
            out.append({"pts": resample_line(LineString(pts), 1.5), "label": label, "closed": False})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataroot", help="an existing world with 1600x900 images (default: generate one)")
    ap.add_argument("--version", default="v1.0-trainval")
    ap.add_argument("--splits-file", help="splits.json of --dataroot (default: its own, if any)")
    ap.add_argument("--samples", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    from instagram_hdmap.benchmark import check_counts

    check_counts(ap, args, samples=1, repeats=1)
    torch.set_num_threads(1)
    cv2.setNumThreads(1)

    tmp = None
    if args.dataroot is None:
        from instagram_hdmap.data.synthetic import generate_world

        tmp = tempfile.TemporaryDirectory(prefix="data_speed_")
        print("generating a synthetic world (1600x900 images) ...", flush=True)
        t = time.perf_counter()
        info = generate_world(out=tmp.name, scenes_train=2, scenes_val=1, samples_per_scene=max(1, args.samples // 2),
                              seed=0, image_size="1600x900", force=True, progress=False)
        print(f"  done in {time.perf_counter() - t:.0f} s", flush=True)
        dataroot, version = tmp.name, info["version"]
    else:
        dataroot, version = args.dataroot, args.version
    splits = args.splits_file
    if splits is None and (Path(dataroot) / "splits.json").is_file():
        splits = str(Path(dataroot) / "splits.json")

    rows = []
    for h, w in ((128, 352), (256, 704)):
        overrides = [f"data.dataroot={dataroot}", f"data.version={version}", f"data.image_size=[{h},{w}]"]
        if splits:
            overrides.append(f"data.splits_file={splits}")
        cfg = load_config(None, overrides)
        ds = NuScenesMapDataset(cfg, cfg.data.train_split, augment=False)
        grid = BEVGrid.from_config(cfg.grid)
        n = min(args.samples, len(ds))
        t_red, t_full, t_map, t_tgt, n_poly = [], [], [], [], []
        for i in range(n):
            sample = ds.nusc.get("sample", ds.sample_tokens[i])
            cams = [ds.nusc.get("sample_data", sample["data"][c]) for c in CAMERAS]
            paths = [(ds.dataroot / sd["filename"], (sd["width"], sd["height"])) for sd in cams]
            for reduced, acc in ((True, t_red), (False, t_full)):
                acc.append(best_ms(partial(load_all, paths, (h, w), reduced), args.repeats))
            polylines = ds.gt_polylines(i)
            t_map.append(best_ms(partial(ds.gt_polylines, i), args.repeats))
            t_tgt.append(best_ms(partial(build_targets, polylines, grid, 3, cfg.data.dt_clip), args.repeats))
            n_poly.append(len(polylines))
        rows.append((f"{h}x{w}", statistics.median(t_red), statistics.median(t_full), statistics.median(t_map),
                     statistics.median(t_tgt), statistics.mean(n_poly)))

    grid = BEVGrid.from_config(load_config().grid)
    fixed = thirty_polylines(np.random.default_rng(0))
    build_targets(fixed, grid)
    t30 = best_ms(lambda: build_targets(fixed, grid), 50)

    print(f"\nms per sample (6 cameras): median over {n} samples of the best of {args.repeats} runs, 1 thread")
    print(f"{'image size':>10} | {'decode reduced':>14} | {'decode full':>11} | {'speed-up':>8} | "
          f"{'map extraction':>14} | {'targets':>7} | {'polylines':>9}")
    print("-" * 94)
    for size, red, full, mp, tg, npoly in rows:
        print(f"{size:>10} | {red:14.1f} | {full:11.1f} | {full / red:7.1f}x | {mp:14.1f} | {tg:7.2f} | {npoly:9.1f}")
    print(f"\ntargets for a fixed map of 30 polylines (paper grid 400x200, S=8): {t30:.2f} ms "
          f"(official InstaGraM GT generation: 26 ms; goal <= 6.5 ms)")
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    from instagram_hdmap.benchmark import script_main

    script_main(main)
