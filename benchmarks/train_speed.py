"""Training-step time and peak memory of the Table I LSS models, printed as a table.

    python benchmarks/train_speed.py                          # CPU: B0 and B4 at 128x352, batch 1 and 2
    python benchmarks/train_speed.py --steps 9 --warmup 3
    python benchmarks/train_speed.py --device cuda            # GPU: samples/s at batch 8, fp32 and bf16
    python benchmarks/train_speed.py --official OFFICIAL --rounds 3  # + the official code's step, same run
    python benchmarks/train_speed.py --one CONFIG --batch 2   # one variant in this process (what the table runs)

One step is one iteration of ``engine.train_one_epoch`` (called as is, on a loader that yields the
same batch): forward under ``engine.autocast_context``, ``losses.Criterion`` (assignment, the four
losses), backward, gradient clipping at ``train.grad_clip`` and an Adam step (``train.lr``,
``train.weight_decay``), in train mode. Its time is read between the engine's per-step callbacks,
each after a device synchronisation (``torch.cuda.synchronize`` on a GPU); ``--warmup`` untimed
steps come first, then ``--steps`` timed ones: median and 10th-90th percentiles of the wall time,
and the median CPU time of the process per step (``time.process_time``). On a shared machine the
wall time of a 2-thread run can grow ten-fold when other jobs hold the cores (the OpenMP threads
wait for each other); with ``--threads 1`` the CPU time per step is close to the wall time on an
idle machine, a load-robust figure to read next to the wall time.

Input: random images (six cameras, the network input size of the config) with the calibration of
a nuScenes sample (``data.rig.nuscenes_like_rig``: the published rig, 1600x900 images resized and
cropped like the dataset does), and the targets the dataset would give for a plausible local map
(``plausible_map``: a four-lane road with a divider and lane dividers, a side road with its own
divider, three zebra crossings and the road boundaries, at a random offset and heading per sample,
clipped and resampled every ``data.sample_dist`` like data/local_map.py), turned into targets by
``targets.build_targets`` and batched by the dataset's ``collate_fn``; about 200-250 GT vertices per
sample on the paper grid, so assignment and graph losses do the work of a real batch.

Memory. CPU: each variant runs in a fresh subprocess (this script with ``--one``) and the figure is
that process's peak resident set size (``resources.peak_resident_bytes``, Linux's VmHWM): everything
the process ever held (Python, the torch libraries, model, optimizer state, batch, activations and
the allocator's caches), measured over model building, warm-up and timed steps. GPU: also
``torch.cuda.max_memory_allocated`` over the warm-up and timed steps (tensors only, not the
caching allocator's reserve). GB = 1e9 bytes.

The official implementation (``--official OFFICIAL``, a local checkout of its code; benchmarks/official.py):
its training step (its train.py's forward, losses, backward, clipping and Adam, on the same batch's
targets in its formats) runs as one more variant per config and batch, in a fresh process like ours,
with the same torch and thread count. ``--rounds R`` runs every variant R times in turn (round
robin), so a change of the machine's load hits every variant alike; the times of a variant are
pooled over its rounds and its memory is its largest peak. The ratio columns compare each of our
rows with the official row of the same config and batch *of the same run*. Targets: <= 0.7x
the official time and <= 0.8x its memory at batch 1. Torch's default thread count is kept (printed).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import shapely
import torch
from shapely import affinity
from shapely.geometry import LineString, Polygon, box

from instagram_hdmap.benchmark import BenchmarkError, device_name
from instagram_hdmap.config import ExperimentConfig, load_config
from instagram_hdmap.data.base import collate_fn
from instagram_hdmap.data.local_map import resample_line
from instagram_hdmap.data.rig import nuscenes_like_rig
from instagram_hdmap.engine import EpochHooks, Position, StepSettings, move_to, train_one_epoch
from instagram_hdmap.geometry import BEVGrid
from instagram_hdmap.losses import Criterion
from instagram_hdmap.models import build_model
from instagram_hdmap.resources import peak_resident_bytes
from instagram_hdmap.targets import build_targets

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ["configs/paper/table1_b0_lss_128x352.yaml", "configs/paper/table1_b4_lss_128x352.yaml"]
TIME_TARGET, MEMORY_TARGET = 0.7, 0.8  # x the official step time and peak memory, batch 1
DEFAULTS = {"cpu": {"batch": [1, 2], "amp": ["none"], "ckpt": ["off", "on"], "steps": 5, "warmup": 2},
            "cuda": {"batch": [8], "amp": ["none", "bf16"], "ckpt": ["off"], "steps": 20, "warmup": 5}}
RESULT_TAG = "RESULT "
DIVIDER, PED_CROSSING, BOUNDARY = 0, 1, 2
EDGE_MARGIN_M = 0.2  # boundaries stop this far inside the patch (HDMapNet, data/local_map.py)


# --------------------------------------------------------------------------------------------------
# Input: a plausible local map -> targets, random images, a nuScenes rig
# --------------------------------------------------------------------------------------------------


def _road_layout() -> list[tuple[object, int]]:
    """A junction in its own frame (metres, x along the main road): (shapely geometry, class) pairs.

    Main road: 4 lanes of 3.5 m (y in [-7, 7]) with a road divider at y = 0 and lane dividers at
    y = +-3.5, interrupted by a side road (x in [5, 15], 2 lanes) with its own divider at x = 10;
    zebra crossings on the main road before the junction and on both side-road arms; the boundary
    is the outline of the union of both roads (a Polygon: its rings are cut by the patch later).
    """
    x0, x1 = 5.0, 15.0  # side-road kerbs
    lines = []
    for y in (-3.5, 0.0, 3.5):
        lines += [LineString([(-80, y), (x0, y)]), LineString([(x1, y), (80, y)])]
    lines += [LineString([(10, 7), (10, 60)]), LineString([(10, -7), (10, -60)])]
    crossings = [box(x0 - 4.0, -7, x0 - 1.0, 7), box(x0, 8, x1, 11), box(x0, -11, x1, -8)]
    road = box(-80, -7, 80, 7).union(box(x0, -60, x1, 60))
    return ([(g, DIVIDER) for g in lines] + [(g, PED_CROSSING) for g in crossings] + [(road, BOUNDARY)])


def plausible_map(grid: BEVGrid, sample_dist: float, rng: np.random.Generator) -> list[dict]:
    """Polyline dicts (docs/conventions.md) of ``_road_layout`` seen from a random ego pose near the
    junction (heading +-0.15 rad, offsets of a few metres), clipped to the grid and resampled every
    ``sample_dist`` metres (``local_map.resample_line``); boundaries stop 0.2 m inside the patch."""
    yaw = rng.uniform(-0.15, 0.15)
    dx, dy = rng.uniform(-8.0, 2.0), rng.uniform(-1.5, 1.5)
    eps = 1e-3  # points strictly inside the grid
    patch = box(grid.xmin + eps, grid.ymin + eps, grid.xmax - eps, grid.ymax - eps)
    inner = box(grid.xmin + EDGE_MARGIN_M, grid.ymin + EDGE_MARGIN_M, grid.xmax - EDGE_MARGIN_M,
                grid.ymax - EDGE_MARGIN_M)
    out: list[dict] = []

    def add(line: LineString, label: int, closed: bool) -> None:
        out.append({"pts": resample_line(line, sample_dist, closed=closed), "label": label, "closed": closed})

    for geom, label in _road_layout():
        geom = affinity.translate(affinity.rotate(geom, yaw, origin=(0, 0), use_radians=True), dx, dy)
        if label == DIVIDER:
            for part in shapely.get_parts(shapely.line_merge(geom.intersection(patch))):
                if part.geom_type == "LineString" and part.length > 0.1:
                    add(part, label, closed=False)
        elif label == PED_CROSSING:
            for part in shapely.get_parts(geom.intersection(patch)):
                if isinstance(part, Polygon) and part.area > 0.1:
                    add(LineString(part.exterior.coords), label, closed=True)
        else:
            rings = shapely.get_parts(shapely.line_merge(geom.boundary.intersection(inner)))
            for part in rings:
                if part.geom_type == "LineString" and part.length > 0.1:
                    add(part, label, closed=part.is_ring)
    return out


def training_batch(cfg: ExperimentConfig, batch_size: int, seed: int = 0) -> dict:
    """A collated batch (docs/conventions.md) of ``batch_size`` samples: random images, a nuScenes rig,
    targets of ``plausible_map`` (a different pose per sample)."""
    rng = np.random.default_rng(seed)
    gen = torch.Generator().manual_seed(seed)
    grid = BEVGrid.from_config(cfg.grid)
    rig = nuscenes_like_rig(cfg.data.image_size)
    h, w = cfg.data.image_size
    V = rig["intrinsics"].shape[0]
    samples = []
    for i in range(batch_size):
        polylines = plausible_map(grid, cfg.data.sample_dist, rng)
        samples.append({
            "images": torch.randn(V, 3, h, w, generator=gen),
            **{k: v.clone() for k, v in rig.items()},
            "ego_pose": torch.eye(4),
            "sample_token": f"train-speed-{seed}-{i}",
            "gt_polylines": polylines,
            **build_targets(polylines, grid, len(cfg.data.classes), cfg.data.dt_clip),
        })
    return collate_fn(samples)


# --------------------------------------------------------------------------------------------------
# One variant (run in a fresh process by the table)
# --------------------------------------------------------------------------------------------------


def measure_training(cfg: ExperimentConfig, batch_size: int, *, steps: int, warmup: int, device: str = "cpu",
                     amp: str = "none", seed: int = 0) -> dict:
    """Time ``warmup + steps`` training steps (``engine.train_one_epoch``) on one batch; see the module docstring.

    Returns the settings and ``step_s`` (median wall time), ``p10_s``, ``p90_s``, ``times_s`` (every timed step),
    ``cpu_s`` (median process CPU time per step), ``samples_per_s`` (batch / median), ``peak_rss_gb`` (this
    process, so far), ``peak_allocated_gb`` (CUDA only, else None), the parameter count,
    GT / predicted vertices per sample and the last step's losses.
    """
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise BenchmarkError("--device cuda but no CUDA device is available; use --device cpu")
    if amp not in ("none", "bf16", "fp16"):
        raise BenchmarkError(f"--amp {amp}: choose none, bf16 or fp16")
    if steps < 1 or warmup < 0:
        raise BenchmarkError(f"--steps must be >= 1 and --warmup >= 0 (got {steps}, {warmup})")

    def sync() -> None:
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)

    with torch.random.fork_rng(devices=[]):  # reproducible random weights, the caller's RNG untouched
        torch.manual_seed(seed)
        model = build_model(cfg).to(dev)
    criterion = Criterion(cfg.loss, BEVGrid.from_config(cfg.grid))
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.train.lr, weight_decay=cfg.train.weight_decay)
    scaler = torch.amp.GradScaler(dev.type) if amp == "fp16" else None
    batch = move_to(training_batch(cfg, batch_size, seed), dev)
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats(dev)

    stamps: list[float] = []
    cpu_stamps: list[float] = []
    last: dict[str, float] = {}

    def on_step(info) -> None:
        sync()
        stamps.append(time.perf_counter())
        cpu_stamps.append(time.process_time())
        last.update(info.losses)

    total = warmup + steps
    sync()
    start, cpu_start = time.perf_counter(), time.process_time()
    with contextlib.redirect_stderr(io.StringIO()):  # the engine's progress bar
        train_one_epoch(model, criterion, [batch] * total, optimizer, dev, Position(0), scaler=scaler, total=total,
                        settings=StepSettings(amp=amp, grad_clip=cfg.train.grad_clip, log_every=total + 1),
                        hooks=EpochHooks(on_step=on_step))
    times = np.diff([start, *stamps])[warmup:]
    cpu_times = np.diff([cpu_start, *cpu_stamps])[warmup:]
    median = float(np.median(times))
    return {
        "config_name": cfg.name,
        "backbone": cfg.model.backbone.name,
        "image_size": list(cfg.data.image_size),
        "device": device_name(dev),
        "amp": amp,
        "ckpt": "on" if cfg.model.backbone.grad_checkpoint else "off",
        "threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "batch": batch_size,
        "steps": steps,
        "warmup": warmup,
        "params_m": sum(p.numel() for p in model.parameters()) / 1e6,
        "gt_vertices": float(batch["gt_vertex_mask"].sum(1).float().mean()),
        "pred_vertices": last.get("num_vertices", math.nan),
        "losses": {k: v for k, v in last.items() if k.startswith("loss_") and not k.endswith("_weighted")},
        "step_s": median,
        "p10_s": float(np.percentile(times, 10)),
        "p90_s": float(np.percentile(times, 90)),
        "samples_per_s": batch_size / median,
        "cpu_s": float(np.median(cpu_times)),
        "times_s": [round(float(t), 4) for t in times],
        "peak_rss_gb": peak_resident_bytes() / 1e9,
        "peak_allocated_gb": torch.cuda.max_memory_allocated(dev) / 1e9 if dev.type == "cuda" else None,
    }


def measure_official(cfg: ExperimentConfig, batch_size: int, official_dir: str, *, steps: int, warmup: int,
                     seed: int = 0) -> dict:
    """Time ``warmup + steps`` steps of the official code's training (benchmarks/official.py) on the batch
    ``training_batch`` gives ours, CPU; the same keys as ``measure_training``."""
    from official import OfficialTrainer, build_official, load_official, uses_standins

    if steps < 1 or warmup < 0:
        raise BenchmarkError(f"--steps must be >= 1 and --warmup >= 0 (got {steps}, {warmup})")
    code = load_official(official_dir)
    model = build_official(code, cfg.model.backbone.name, tuple(cfg.data.image_size), seed)
    batch = training_batch(cfg, batch_size, seed)
    trainer = OfficialTrainer(code, model, batch, lr=cfg.train.lr, weight_decay=cfg.train.weight_decay)
    times, cpu_times, loss = [], [], math.nan
    for i in range(warmup + steps):
        start, cpu_start = time.perf_counter(), time.process_time()
        loss = trainer.step()
        if i >= warmup:
            times.append(time.perf_counter() - start)
            cpu_times.append(time.process_time() - cpu_start)
    median = float(np.median(times))
    return {
        "impl": "official", "config_name": cfg.name, "backbone": cfg.model.backbone.name,
        "image_size": list(cfg.data.image_size), "device": device_name(torch.device("cpu")), "amp": "none",
        "ckpt": "-", "threads": torch.get_num_threads(), "torch": torch.__version__, "batch": batch_size,
        "steps": steps, "warmup": warmup, "params_m": sum(p.numel() for p in model.parameters()) / 1e6,
        "gt_vertices": float(batch["gt_vertex_mask"].sum(1).float().mean()), "pred_vertices": math.nan,
        "losses": {"loss_total": loss}, "step_s": median, "p10_s": float(np.percentile(times, 10)),
        "p90_s": float(np.percentile(times, 90)), "samples_per_s": batch_size / median,
        "cpu_s": float(np.median(cpu_times)), "times_s": [round(float(t), 4) for t in times],
        "peak_rss_gb": peak_resident_bytes() / 1e9,
        "peak_allocated_gb": None, "standins": uses_standins(), "official": str(code.root),
    }


def run_variant(config: str, batch: int, args: argparse.Namespace, amp: str, ckpt: str, impl: str = "ours") -> dict:
    """``measure_training`` (or ``measure_official``) in a fresh Python process (so that its peak RSS is
    this variant's alone)."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--one", str(Path(config).resolve()), "--batch", str(batch),
           "--amp", amp, "--grad-checkpoint", "on" if ckpt == "on" else "off", "--device", args.device,
           "--steps", str(args.steps),
           "--warmup", str(args.warmup),
           "--seed", str(args.seed), *(["--threads", str(args.threads)] if args.threads else []),
           *(["--official", args.official, "--impl", impl] if impl == "official" else [])]
    what = {"config": config, "batch": batch, "amp": amp, "ckpt": ckpt, "impl": impl}
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout, cwd=ROOT)
    except subprocess.TimeoutExpired:
        return {**what, "error": f"timed out after {args.timeout} s"}
    for line in proc.stdout.splitlines():
        if line.startswith(RESULT_TAG):
            return {"config": config, "impl": impl, **json.loads(line[len(RESULT_TAG):])}
    tail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
    return {**what, "error": f"exit {proc.returncode}: {tail[:200]}"}


def pool_rounds(runs: list[dict]) -> dict:
    """One variant's results of several rounds as one: times pooled, the largest peak memory."""
    ok = [r for r in runs if "error" not in r]
    if len(ok) < len(runs):
        return next(r for r in runs if "error" in r)
    times = [t for r in ok for t in r["times_s"]]
    out = dict(ok[-1])
    out.update(step_s=float(np.median(times)), p10_s=float(np.percentile(times, 10)),
               p90_s=float(np.percentile(times, 90)), times_s=times, rounds=len(ok),
               cpu_s=float(np.median([r["cpu_s"] for r in ok])),
               samples_per_s=ok[-1]["batch"] / float(np.median(times)),
               peak_rss_gb=max(r["peak_rss_gb"] for r in ok))
    return out


# --------------------------------------------------------------------------------------------------
# Tables
# --------------------------------------------------------------------------------------------------


def _verdict(ratio: float, target: float) -> str:
    return "pass" if ratio <= target else "FAIL"


def format_cpu_table(rows: list[dict]) -> str:
    """Step time and peak RSS; with an official row of the same config and batch in ``rows`` (the same
    run), each of our rows as a ratio of it (module docstring)."""
    official = {(r["config"], r["batch"]): r for r in rows if r.get("impl") == "official" and "error" not in r}
    head = (f"{'config':<30}{'impl':>9}{'params':>8}{'batch':>6}{'amp':>5}{'ckpt':>5}{'step s':>8}{'p10-p90 s':>12}"
            f"{'CPU s':>7}{'x offic.':>9}{'<=0.7x':>7}{'peak GB':>9}{'x offic.':>9}{'<=0.8x':>7}{'GT/pred vtx':>13}")
    lines = [head, "-" * len(head)]
    for r in rows:
        name, impl = Path(r["config"]).stem, r.get("impl", "ours")
        if "error" in r:
            lines.append(f"{name:<30}{impl:>9}{'':>8}{r['batch']:>6}{r['amp']:>5}{r['ckpt']:>5}  failed: {r['error']}")
            continue
        ref = official.get((r["config"], r["batch"])) if impl == "ours" and r["amp"] == "none" else None
        cells = (f"{name:<30}{impl:>9}{r['params_m']:>7.2f}M{r['batch']:>6}{r['amp']:>5}{r['ckpt']:>5}"
                 f"{r['step_s']:>8.2f}{r['p10_s']:>6.2f}-{r['p90_s']:<5.2f}{r['cpu_s']:>7.2f}")
        if ref is None:
            cells += f"{'-':>9}{'':>7}{r['peak_rss_gb']:>9.2f}{'-':>9}{'':>7}"
        else:
            t, m = r["step_s"] / ref["step_s"], r["peak_rss_gb"] / ref["peak_rss_gb"]
            vt, vm = (_verdict(t, TIME_TARGET), _verdict(m, MEMORY_TARGET)) if r["batch"] == 1 else ("", "")
            cells += f"{t:>9.2f}{vt:>7}{r['peak_rss_gb']:>9.2f}{m:>9.2f}{vm:>7}"
        cells += f"{r['gt_vertices']:>7.0f}/{r['pred_vertices']:<5.0f}"
        lines.append(cells)
    lines.append("step s: wall time (median over every timed step of every round); CPU s: the process's CPU time per "
                 "step (median; with 1 thread ~ the wall time of an idle machine, with more it includes OpenMP "
                 "spinning). peak GB: the process's peak RSS (VmHWM), 1 GB = 1e9 B. ckpt: "
                 "model.backbone.grad_checkpoint (recompute the EfficientNet blocks in backward). x offic.: our row / "
                 "the official row of the same config and batch in this run (verdicts at batch 1 only)")
    standins = sorted({s for r in official.values() for s in r.get("standins", [])})
    if standins:
        lines.append(f"official code built with stand-ins for {', '.join(standins)} (benchmarks/official.py)")
    return "\n".join(lines)


def format_gpu_table(rows: list[dict]) -> str:
    """Samples/s and memory per config x precision."""
    head = (f"{'config':<30}{'params':>8}{'batch':>6}{'amp':>6}{'ckpt':>5}{'step ms':>9}{'p10-p90 ms':>14}"
            f"{'samples/s':>11}{'max alloc GB':>14}{'peak RSS GB':>13}")
    lines = [head, "-" * len(head)]
    for r in rows:
        name = Path(r["config"]).stem
        if "error" in r:
            lines.append(f"{name:<30}{'':>8}{r['batch']:>6}{r['amp']:>6}{r['ckpt']:>5}  failed: {r['error']}")
            continue
        alloc = r["peak_allocated_gb"]
        lines.append(f"{name:<30}{r['params_m']:>7.2f}M{r['batch']:>6}{r['amp']:>6}{r['ckpt']:>5}"
                     f"{1000 * r['step_s']:>9.1f}"
                     f"{1000 * r['p10_s']:>7.1f}-{1000 * r['p90_s']:<6.1f}{r['samples_per_s']:>11.2f}"
                     f"{(f'{alloc:.2f}' if alloc is not None else '-'):>14}{r['peak_rss_gb']:>13.2f}")
    lines.append("amp none = fp32; bf16 = torch.autocast bfloat16 (engine.autocast_context); max alloc: "
                 "torch.cuda.max_memory_allocated over the steps; 1 GB = 1e9 B")
    return "\n".join(lines)


def kind_of(device: str) -> str:
    return "cuda" if device.startswith("cuda") else "cpu"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu", help="cpu or cuda[:i]")
    parser.add_argument("--configs", nargs="+", default=CONFIGS)
    parser.add_argument("--batch", type=int, nargs="+", help="batch sizes (default 1 2 on the CPU, 8 on a GPU)")
    parser.add_argument("--amp", nargs="+", choices=["none", "bf16", "fp16"],
                        help="precisions (default none on the CPU, none bf16 on a GPU)")
    parser.add_argument("--grad-checkpoint", nargs="+", choices=["off", "on"],
                        help="model.backbone.grad_checkpoint variants (default off on on the CPU, off on a GPU)")
    parser.add_argument("--steps", type=int, help="timed steps (default 5 on the CPU, 20 on a GPU)")
    parser.add_argument("--warmup", type=int, help="untimed steps first (default 2 on the CPU, 5 on a GPU)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--timeout", type=int, default=900, help="seconds per variant")
    parser.add_argument("--threads", type=int, help="torch.set_num_threads in each variant (default: torch's own)")
    parser.add_argument("--one", metavar="CONFIG", help="measure this config in this process, print one RESULT line")
    parser.add_argument("--official", metavar="DIR",
                        help="a local checkout of the official InstaGraM code: time its training step too (CPU)")
    parser.add_argument("--impl", choices=["ours", "official"], default="ours", help="with --one: whose step")
    parser.add_argument("--rounds", type=int, default=1, help="run every variant this many times in turn")
    args = parser.parse_args()
    from instagram_hdmap.benchmark import check_counts

    check_counts(parser, args, batch=1, steps=1, warmup=0, threads=1, timeout=1)
    if args.official and kind_of(args.device) != "cpu":
        parser.error("--official times the training step on the CPU only")
    if args.rounds < 1:
        parser.error("--rounds must be >= 1")
    if args.official:
        args.official = str(Path(args.official).resolve())
    kind = kind_of(args.device)
    d = DEFAULTS[kind]
    args.batch = args.batch or d["batch"]
    args.amp = args.amp or d["amp"]
    args.grad_checkpoint = args.grad_checkpoint or d["ckpt"]
    args.steps = d["steps"] if args.steps is None else args.steps
    args.warmup = d["warmup"] if args.warmup is None else args.warmup

    if args.threads:
        torch.set_num_threads(args.threads)
    if args.one:
        cfg = load_config(args.one, [f"model.backbone.grad_checkpoint={args.grad_checkpoint[0] == 'on'}"])
        if args.impl == "official":
            r = measure_official(cfg, args.batch[0], args.official, steps=args.steps, warmup=args.warmup,
                                 seed=args.seed)
        else:
            r = measure_training(cfg, args.batch[0], steps=args.steps, warmup=args.warmup, device=args.device,
                                 amp=args.amp[0], seed=args.seed)
        print(RESULT_TAG + json.dumps(r))
        return 0

    load = os.getloadavg()
    print(f"device {device_name(torch.device(args.device)) if kind == 'cpu' else args.device}, torch "
          f"{torch.__version__}, "
          f"torch threads {torch.get_num_threads()} ({'--threads' if args.threads else 'default'}), "
          f"{os.cpu_count()} CPUs, load average {load[0]:.1f} at start")
    print(f"{args.warmup} warm-up + {args.steps} timed steps per variant and round, {args.rounds} round(s), each "
          "variant in a fresh process; random images, nuScenes-like rig, targets of a plausible junction map "
          "(module docstring)" + (f"; official code: {args.official}" if args.official else ""))
    variants = [(config, batch, amp, ckpt, "ours") for config in args.configs for batch in args.batch
                for amp in args.amp for ckpt in args.grad_checkpoint]
    if args.official:
        variants += [(config, batch, "none", "-", "official") for config in args.configs for batch in args.batch]
        variants.sort(key=lambda v: (args.configs.index(v[0]), args.batch.index(v[1])))
    results: dict[tuple, list[dict]] = {v: [] for v in variants}
    for round_ in range(args.rounds):
        for v in variants:
            config, batch, amp, ckpt, impl = v
            r = run_variant(config, batch, args, amp, ckpt, impl)
            results[v].append(r)
            what = f"  round {round_ + 1}: {config} batch {batch} {impl} {amp} grad checkpoint {ckpt}"
            if "error" in r:
                print(f"{what}: failed ({r['error']})", flush=True)
            else:
                print(f"{what}: {r['step_s']:.3f} s/step, peak RSS {r['peak_rss_gb']:.2f} GB", flush=True)
    rows = [pool_rounds(results[v]) for v in variants]
    if rows and "error" not in rows[0]:
        print(f"{rows[0]['device']}; child processes used {rows[0]['threads']} torch threads")
    print(f"load average {os.getloadavg()[0]:.1f} at the end (the machine is shared: CPU times are upper bounds)")
    print()
    print(format_gpu_table(rows) if kind == "cuda" else format_cpu_table(rows))
    return 1 if any("error" in r for r in rows) else 0


if __name__ == "__main__":
    from instagram_hdmap.benchmark import script_main

    script_main(main)
