"""Inference speed (``instagram-hdmap benchmark``): FPS for batch 1 with six cameras.

    result = run_benchmark(load_config("configs/paper/table1_b0_lss_128x352.yaml"), device=DEVICE, amp="bf16")
    print(format_benchmark(result))

Inputs: random images with a realistic calibration: the rig of the first sample of
``data.val_split`` when ``data.dataroot`` holds a dataset, otherwise a nuScenes-like rig built here
(``data.rig.nuscenes_like_rig``: the published calibration of a nuScenes log, 1600 x 900 images). Timing: eval
mode, ``torch.inference_mode``, autocast per ``--amp`` (``engine.autocast_context``), ``warmup``
untimed runs, then ``runs`` timed runs, each bracketed by a device synchronisation
(``torch.cuda.synchronize`` on a GPU), reported as the median and the 10th / 90th percentiles of
the latency, and FPS = 1 / median. Two rows: the model's forward, and forward + post-processing
(``postprocess.postprocess_batch``, which includes the copy of the outputs to the host).

Random weights give a near-uniform assignment, i.e. few edges to follow, so post-processing is
faster than with a trained model: pass ``--checkpoint`` for a trained model's post-processing cost.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from .config import ExperimentConfig, UserError
from .data import build_dataset, rig_cameras
from .data.rig import nuscenes_like_rig
from .deploy import fast_forward
from .distributed import resolve_device
from .engine import autocast_context
from .errors import one_line
from .geometry import BEVGrid
from .inference import load_model
from .models import build_model
from .postprocess import decode_options, postprocess_batch
from .precision import calibration_batches, resolve_precision, with_precision
from .resources import check_fits, cpu_capability, reuse_freed_memory

DEFAULT_RUNS = {"cuda": 50, "cpu": 10}
DEFAULT_WARMUP = {"cuda": 10, "cpu": 2}


class BenchmarkError(UserError):
    """A device or precision that cannot be benchmarked here."""


def check_counts(parser: argparse.ArgumentParser, args: argparse.Namespace, **minimums: int) -> None:
    """A benchmarks/ script's count flags: ``check_counts(parser, args, runs=1, warmup=0)`` refuses
    ``--runs 0`` (or any item of a list flag below its minimum) with argparse's one line and exit 2,
    before any work: a count of 0 left nothing to take a median or a mean of (a raw ZeroDivisionError
    or StatisticsError after the setup) or printed a table of zeros for no samples with exit 0.
    A flag left at ``None`` (its default chosen later) is not checked. A ``--device`` the script has is
    checked too (``cuda`` on a machine without CUDA, a name that is no device)."""
    for name, minimum in minimums.items():
        value = getattr(args, name)
        for v in value if isinstance(value, (list, tuple)) else [value]:
            if v is not None and v < minimum:
                parser.error(f"--{name.replace('_', '-')} must be >= {minimum}, got {v}")
    if isinstance(getattr(args, "device", None), str):  # --device cuda without CUDA: a raw AssertionError later
        try:
            resolve_device(args.device, key="--device")
        except UserError as e:
            parser.error(str(e))


def script_main(main: Callable[[], object]) -> None:
    """Run a benchmarks/ script's ``main()``: a ``UserError`` (a config, checkpoint, dataroot or size its
    flags named that is wrong) is one line ``SCRIPT: error: MESSAGE`` and exit 2, as a wrong flag is,
    not a traceback around the message; ``main``'s return value is the exit code."""
    try:
        code = main()
    except UserError as e:
        print(f"{Path(sys.argv[0]).name}: error: {one_line(e)}", file=sys.stderr)
        raise SystemExit(2) from None
    raise SystemExit(code)


def benchmark_rig(cfg: ExperimentConfig) -> tuple[dict[str, torch.Tensor], str]:
    """The calibration [V, ...] to benchmark with and where it came from."""
    why = "no data.dataroot"
    if Path(cfg.data.dataroot).is_dir():
        try:
            dataset = build_dataset(cfg, cfg.data.val_split, augment=False)
            cams = dataset.load_cameras(0)
        except UserError as e:
            why = f"the dataset at {cfg.data.dataroot} failed: {e}"
        else:
            cams.pop("images")
            cams["ground_height"] = torch.tensor(dataset.ground_height(0), dtype=torch.float32)
            return cams, f"rig of sample {dataset.sample_tokens[0]} ({cfg.data.dataroot}, split {dataset.split})"
    return nuscenes_like_rig(cfg.data.image_size, len(rig_cameras(cfg))), f"nuScenes-like rig built in code ({why})"


def device_name(device: torch.device) -> str:
    if device.type == "cuda":
        return f"{device} ({torch.cuda.get_device_name(device)})"
    cpuinfo = Path("/proc/cpuinfo")
    models = [line.split(":", 1)[1].strip() for line in (cpuinfo.read_text().splitlines() if cpuinfo.is_file() else [])
              if line.startswith("model name")]
    return f"cpu ({models[0] if models else platform.processor() or platform.machine()})"


def _percentiles_ms(times_s: list[float]) -> dict[str, float]:
    p10, median, p90 = (float(q) for q in np.percentile(1000 * np.asarray(times_s), [10, 50, 90]))
    return {"median_ms": median, "p10_ms": p10, "p90_ms": p90, "fps": 1000.0 / median}


def time_runs(fn: Callable[[], object], runs: int, warmup: int, sync: Callable[[], None]) -> list[float]:
    """Seconds per call of ``fn`` over ``runs`` calls after ``warmup`` untimed ones; ``sync`` waits
    for the device before the clock is read."""
    for _ in range(warmup):
        fn()
    sync()
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - start)
    return times


def _checked_settings(cfg: ExperimentConfig, device: str | None, amp: str, runs: int | None,
                      warmup: int | None) -> tuple[torch.device, int, int]:
    """The device, runs and warm-up runs of a benchmark, each checked (one line naming the option)."""
    if device is None:
        device = str(resolve_device(cfg.train.device))
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):  # "tpu", "gpu": not a torch device string
        raise BenchmarkError(f"--device {device}: choose cpu or cuda (cuda:INDEX)") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise BenchmarkError("--device cuda but no CUDA device is available; use --device cpu")
    if dev.type not in DEFAULT_RUNS:
        raise BenchmarkError(f"--device {device}: choose cpu or cuda")
    if amp not in ("none", "bf16", "fp16"):
        raise BenchmarkError(f"--amp {amp}: choose none, bf16 or fp16")
    runs = DEFAULT_RUNS[dev.type] if runs is None else runs
    warmup = DEFAULT_WARMUP[dev.type] if warmup is None else warmup
    if runs < 1 or warmup < 0:
        raise BenchmarkError(f"--runs must be >= 1 and --warmup >= 0 (got {runs}, {warmup})")
    return dev, runs, warmup


def _random_batch(model, cfg: ExperimentConfig, rig: dict, dev: torch.device, seed: int, notes: list[str]) -> dict:
    """One frame of random images on the benchmark rig (batch 1); a temporal model gets the frame's pose."""
    h, w = cfg.data.image_size
    gen = torch.Generator().manual_seed(seed)
    batch = {k: v[None].to(dev) for k, v in rig.items()}
    V = rig["intrinsics"].shape[0]
    batch["images"] = torch.randn(1, V, 3, h, w, generator=gen).to(dev)
    if getattr(model, "is_temporal", False):  # a temporal model reads the frame's pose (it was a raw KeyError)
        batch["ego_pose"] = torch.eye(4)[None].to(dev)
        notes.append("a temporal model: timed on a scene's first frame (an empty memory); its warp and fusion cost "
                     "the same on every frame")
    return batch


def _timed(forward, forward_post, runs: int, warmup: int, sync, amp: str, dev: torch.device) -> tuple[list, list, dict]:
    """The times of ``runs`` calls of the model and of the model + decoding (after ``warmup``), and one output;
    an autocast the torch build does not support is one line naming ``--amp``."""
    try:
        with torch.inference_mode():
            model_times = time_runs(forward, runs, warmup, sync)
            full_times = time_runs(forward_post, runs, warmup, sync)
            return model_times, full_times, forward()
    except RuntimeError as e:
        if amp != "none" and ("autocast" in str(e).lower() or "not implemented" in str(e).lower()):
            raise BenchmarkError(f"--amp {amp} is not supported on {dev.type} by this torch build: "
                                 f"{str(e).splitlines()[0][:200]}") from None
        raise


def _precision_of(precision: str | None, amp: str, dev: torch.device) -> tuple[str | None, list[str]]:
    """What ``precision`` (precision.py) resolves to on ``dev`` (None: plain ``amp`` autocast), and its notes."""
    if precision is None:
        return None, []
    if amp != "none":  # two answers to one question
        raise BenchmarkError(f"--amp {amp} and --precision {precision}: give one of them")
    return resolve_precision(precision, dev)


def _dtype_label(amp: str, precision: str | None) -> str:
    if precision in ("bf16", "int8"):
        return {"bf16": "bfloat16", "int8": "int8 BEV encoder + bfloat16"}[precision] + (
            f" (--precision {precision}: BatchNorm folded, bf16 weights, channels-last, fp32 islands)")
    return {"none": "float32", "bf16": "bfloat16 autocast", "fp16": "float16 autocast"}[amp]


def _benchmark_model(cfg: ExperimentConfig, checkpoint, overrides, dev: torch.device, seed: int,
                     notes: list[str]) -> tuple[torch.nn.Module, ExperimentConfig]:
    """The checkpoint's model (its notes added to ``notes``), or reproducible random weights. On the CPU, freed
    blocks are kept for reuse, as inference keeps them (``resources.reuse_freed_memory``)."""
    if dev.type == "cpu":
        reuse_freed_memory()
    if checkpoint is not None:
        model, cfg, loaded = load_model(checkpoint, cfg, overrides, device=dev)
        notes += loaded
        return model, cfg
    with torch.random.fork_rng(devices=[]):  # reproducible random weights, global RNG untouched
        torch.manual_seed(seed)
        return build_model(cfg).eval().to(dev), cfg


def _in_precision(model, cfg: ExperimentConfig, precision: str | None, checkpoint, batch: dict,
                  compile_backbone: bool = False):
    """``model`` as inference runs it in ``precision`` (None: as it is); int8 calibrates on the training split of a
    checkpoint's config, else on the timed ``batch``. ``compile_backbone``: its image backbone then through
    ``torch.compile`` (``precision.compile_backbone``)."""
    calibration = None
    if precision == "int8":
        calibration = calibration_batches(cfg, device=batch["images"].device) if checkpoint is not None else [batch]
    return with_precision(model, precision or "fp32", calibration, compile_backbone)  # None: as it is (fp32's)


def _dtype_with_paths(amp: str, precision: str | None, compile: bool, compile_backbone: bool,
                      cuda_graphs: bool) -> str:
    """The result's ``dtype``: the precision, then the fast paths timed with it."""
    paths = (("torch.compile", compile), ("backbone compiled", compile_backbone), ("CUDA graph", cuda_graphs))
    return _dtype_label(amp, precision) + "".join(f", {name}" for name, on in paths if on)


def _run_notes(checkpoint, runs: int, dev: torch.device) -> list[str]:
    """What a reader of the figures should know about the weights and the number of runs."""
    notes = []
    if checkpoint is None:
        notes.append("random weights: few edges pass the match threshold, so post-processing is cheaper than "
                     "with a trained model (pass --checkpoint)")
    if runs < DEFAULT_RUNS[dev.type]:
        notes.append(f"only {runs} runs (default {DEFAULT_RUNS[dev.type]} on {dev.type}): the spread is rough")
    return notes


def run_benchmark(
    cfg: ExperimentConfig,
    *,
    device: str | None = None,
    amp: str = "none",
    runs: int | None = None,
    warmup: int | None = None,
    checkpoint: str | Path | None = None,
    overrides: tuple[str, ...] | list[str] = (),
    seed: int = 0,
    compile: bool = False,
    cuda_graphs: bool = False,
    precision: str | None = None,
    compile_backbone: bool = False,
) -> dict:
    """Time the model (and model + post-processing) on batch 1 with six cameras; see the module docstring.
    ``precision`` (fp32, bf16, int8, auto; precision.py): the model as inference runs it (``with_precision``),
    instead of plain ``amp`` autocast.

    ``device``: "cpu", "cuda" (or "cuda:i"); ``None`` uses ``train.device``. ``runs`` / ``warmup``
    default to 50 / 10 on a GPU and 10 / 2 on the CPU. Returns a dict of settings and per-row
    statistics (``median_ms``, ``p10_ms``, ``p90_ms``, ``fps``). ``compile`` / ``cuda_graphs``: time
    ``deploy.fast_forward`` (``torch.compile``, compiled before the warm-up; CUDA-graph replay).
    ``compile_backbone``: only the image backbone through ``torch.compile`` (``precision.compile_backbone``, as
    ``Mapper`` and ``evaluate --compile-backbone`` run it; it compiles in the first warm-up run).
    """
    if compile_backbone and compile:
        raise BenchmarkError("--compile compiles the whole model, the image backbone included; --compile-backbone "
                             "compiles the backbone alone: give one of them")
    dev, runs, warmup = _checked_settings(cfg, device, amp, runs, warmup)
    precision, notes = _precision_of(precision, amp, dev)
    model, cfg = _benchmark_model(cfg, checkpoint, overrides, dev, seed, notes)
    check_fits(cfg, "infer", dev, batch=1)  # before the warm-up runs
    grid = BEVGrid.from_config(cfg.grid)
    rig, rig_source = benchmark_rig(cfg)
    batch = _random_batch(model, cfg, rig, dev, seed, notes)
    model = _in_precision(model, cfg, precision, checkpoint, batch, compile_backbone)
    h, w = cfg.data.image_size
    V = rig["intrinsics"].shape[0]
    decode = decode_options(cfg.model.gnn, grid)

    def sync() -> None:
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)

    if compile or cuda_graphs:
        with torch.inference_mode():  # the mode of the timed calls (compiled code is specialised to it)
            fast = fast_forward(model, batch, compile=compile, cuda_graphs=cuda_graphs, amp=amp)

    def forward() -> dict:
        if compile or cuda_graphs:
            return fast(batch)
        with autocast_context(dev, amp):
            return model(batch)

    def forward_post() -> list:
        return postprocess_batch(forward(), grid, **decode)

    model_times, full_times, outputs = _timed(forward, forward_post, runs, warmup, sync, amp, dev)
    num_vertices = int(outputs["pred_vertex_mask"].sum())
    num_instances = len(postprocess_batch(outputs, grid, **decode)[0])
    notes += _run_notes(checkpoint, runs, dev)
    return {
        "config_name": cfg.name,
        "device": device_name(dev),
        "cpu": cpu_capability(),
        "dtype": _dtype_with_paths(amp, precision, compile, compile_backbone, cuda_graphs),
        "threads": torch.get_num_threads(),
        "batch": f"1 x {V} cameras x {h}x{w}",
        "backbone": cfg.model.backbone.name,
        "view_transform": cfg.model.view_transform.kind,
        "num_vertices": f"{num_vertices} of N={cfg.model.gnn.num_vertices}",
        "instances": num_instances,
        "runs": runs,
        "warmup": warmup,
        "calibration": rig_source,
        "weights": str(checkpoint) if checkpoint is not None else "random",
        "rows": {"model": _percentiles_ms(model_times), "model + post-processing": _percentiles_ms(full_times)},
        "notes": notes,
    }


def format_benchmark(result: dict, config_path: str | None = None) -> str:
    """The settings, then one line per row: median / p10 / p90 latency and FPS (1 / median)."""
    name = result["config_name"] + (f" ({config_path})" if config_path else "")
    lines = [
        f"config:      {name}; {result['backbone']}, {result['view_transform']}",
        f"device:      {result['device']}",
        f"cpu:         {result.get('cpu', 'not recorded')} (decoding runs on it)",
        f"dtype:       {result['dtype']}",
        f"threads:     {result['threads']} (torch.get_num_threads)",
        f"input:       batch {result['batch']}, calibration: {result['calibration']}",
        f"weights:     {result['weights']}; vertices {result['num_vertices']}, {result['instances']} instances",
        f"timing:      {result['runs']} runs after {result['warmup']} warm-up runs, synchronised",
    ]
    head = f"{'':<26}{'median ms':>11}{'p10 ms':>10}{'p90 ms':>10}{'FPS':>9}{'FPS (p90-p10)':>15}"
    lines += ["", head, "-" * len(head)]
    for row, s in result["rows"].items():
        spread = f"{1000 / s['p90_ms']:.1f}-{1000 / s['p10_ms']:.1f}"
        lines.append(f"{row:<26}{s['median_ms']:>11.1f}{s['p10_ms']:>10.1f}{s['p90_ms']:>10.1f}{s['fps']:>9.1f}"
                     f"{spread:>15}")
    lines += [f"note: {n}" for n in result["notes"]]
    return "\n".join(lines)
