"""Time to evaluate N samples (default 1 000) of ~30 GT and ~50 predicted polylines each.

Synthetic but realistic scenes in the 60 m x 30 m patch (x forward, y left): lane dividers and
road boundaries running along x (some curving), a few pedestrian crossings (closed rectangles);
predictions are MapTR-like -- 20 points per instance, noisy copies of most GT lines (some
truncated, some duplicated), plus false positives, 50 per sample with scores in (0, 1).

    python benchmarks/eval_speed.py                      # vector, 1000 samples; raster on 100
    python benchmarks/eval_speed.py --samples 1000 --raster-samples 1000 --threads 2

Prints a table: protocol, samples, seconds, ms/sample, mAP.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np
import torch

from instagram_hdmap.evaluation import Evaluator


def _curve(rng: np.random.Generator, y0: float, n: int) -> np.ndarray:
    x0, x1 = sorted(rng.uniform(-30, 30, 2))
    if x1 - x0 < 10:
        x0, x1 = -30.0, 30.0
    x = np.linspace(x0, x1, n)
    bend = rng.choice([0.0, 0.0, rng.uniform(-0.01, 0.01)])
    return np.stack([x, y0 + bend * (x - x0) ** 2], 1)


def make_scene(rng: np.random.Generator, num_gt: int = 30, num_pred: int = 50) -> tuple[list[dict], list[dict]]:
    """One sample: (predictions, GT) polyline dicts in metres."""
    gt = []
    n_cross = int(rng.integers(2, 6))
    for _ in range(n_cross):
        cx, cy = rng.uniform(-25, 25), rng.uniform(-12, 12)
        w, h = rng.uniform(3, 6), rng.uniform(8, 20)
        rect = np.array([[cx - w / 2, cy - h / 2], [cx + w / 2, cy - h / 2], [cx + w / 2, cy + h / 2],
                         [cx - w / 2, cy + h / 2], [cx - w / 2, cy - h / 2]])
        gt.append({"pts": np.clip(rect, [-30, -15], [30, 15]), "label": 1})
    while len(gt) < num_gt:
        label = int(rng.choice([0, 2]))
        y0 = rng.uniform(-14.5, 14.5)
        n = int(rng.integers(2, 40))  # GT keeps its raw vertices: 2 for a straight piece, more when curved
        pts = _curve(rng, y0, n)
        pts[:, 1] = np.clip(pts[:, 1], -15, 15)
        gt.append({"pts": pts, "label": label})
    pred = []
    for g in gt:
        if len(pred) >= num_pred or rng.random() < 0.15:
            continue
        # 20 points along the GT (uniform in vertex index), as a MapTR decoder outputs them
        u, v = np.linspace(0, 1, 20), np.linspace(0, 1, len(g["pts"]))
        src = np.stack([np.interp(u, v, g["pts"][:, k]) for k in range(2)], 1)
        noisy = src + rng.normal(scale=rng.choice([0.1, 0.3, 0.8]), size=src.shape)
        if rng.random() < 0.2:
            noisy = noisy[: int(rng.integers(5, 20))]
        pred.append({"pts": noisy, "label": g["label"] if rng.random() > 0.05 else int(rng.integers(0, 3)),
                     "score": float(rng.uniform(0.3, 1.0))})
        if rng.random() < 0.1 and len(pred) < num_pred:
            pred.append({"pts": noisy + rng.normal(scale=0.2, size=noisy.shape), "label": pred[-1]["label"],
                         "score": float(rng.uniform(0.1, 0.6))})
    while len(pred) < num_pred:
        a = rng.uniform([-30, -15], [30, 15])
        b = a + rng.normal(size=2) * 10
        t = np.linspace(0, 1, 20)[:, None]
        pred.append({"pts": a + t * (b - a) + rng.normal(scale=0.2, size=(20, 2)), "label": int(rng.integers(0, 3)),
                     "score": float(rng.uniform(0.0, 0.5))})
    return pred, gt


def make_dataset(n: int, seed: int = 0) -> tuple[list[list[dict]], list[list[dict]]]:
    rng = np.random.default_rng(seed)
    scenes = [make_scene(rng) for _ in range(n)]
    return [s[0] for s in scenes], [s[1] for s in scenes]


def time_protocol(protocol: str, preds: list, gts: list, chunk: int, **kw) -> tuple[float, dict]:
    ev = Evaluator(protocol, **kw)
    t0 = time.perf_counter()
    for s in range(0, len(preds), chunk):
        ev.update(preds[s : s + chunk], gts[s : s + chunk], sample_ids=range(s, min(s + chunk, len(preds))))
    metrics = ev.compute()
    return time.perf_counter() - t0, metrics


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=1000)
    ap.add_argument("--raster-samples", type=int, default=100, help="0 to skip the raster protocol")
    ap.add_argument("--chunk", type=int, default=64, help="samples per update() call")
    ap.add_argument("--threads", type=int, default=2, help="torch intra-op threads")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    from instagram_hdmap.benchmark import check_counts

    check_counts(ap, args, samples=1, raster_samples=0, chunk=1, threads=1)
    torch.set_num_threads(args.threads)
    preds, gts = make_dataset(max(args.samples, args.raster_samples), args.seed)
    n_gt = np.mean([len(g) for g in gts])
    n_pred = np.mean([len(p) for p in preds])
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs visible, "
          f"torch threads {torch.get_num_threads()}, load avg {os.getloadavg()[0]:.2f}")
    print(f"data: {n_gt:.1f} GT and {n_pred:.1f} predicted polylines per sample (seed {args.seed})")
    print(f"{'protocol':<10}{'samples':>9}{'seconds':>10}{'ms/sample':>11}{'mAP':>9}")
    runs = [("vector", args.samples, {})]
    if args.raster_samples:
        runs.append(("raster", args.raster_samples, {}))
    for protocol, n, kw in runs:
        secs, m = time_protocol(protocol, preds[:n], gts[:n], args.chunk, **kw)
        print(f"{protocol:<10}{n:>9}{secs:>10.2f}{1000 * secs / n:>11.2f}{m['mAP']:>9.4f}")


if __name__ == "__main__":
    from instagram_hdmap.benchmark import script_main

    script_main(main)
