"""Batch-1 inference latency of the deployment paths: eager torch (today's ``model(batch)``), the
compiled model (``torch.compile``, ``deploy.fast_forward``) and the ONNX export in onnxruntime, per
Table I config, timed interleaved in one run (each round calls every path once, in turn), so machine
load affects all rows alike.

    python benchmarks/deploy_speed.py                                  # CPU, B0 and B4 LSS 128x352
    python benchmarks/deploy_speed.py --rows eager onnxruntime --runs 30 --onnx-dir /tmp/onnx
    python benchmarks/deploy_speed.py --configs configs/paper/table1_b4_lss_256x704.yaml

Random weights (seed 0) and images, the nuScenes-like rig (``deploy.example_inputs``), eval mode,
``torch.inference_mode``; ``--threads`` for torch and onnxruntime alike. The forward only (the
post-processing is the same Python code behind every path: ``instagram-hdmap benchmark``). Before
timing, each path's outputs are checked against eager torch (``max_diff``). Exports (and compilations) take minutes on a
small CPU: ``--onnx-dir`` keeps the exported files for the next run (re-used when their config and
the check still match).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
import torch

from instagram_hdmap import deploy, inference
from instagram_hdmap.benchmark import device_name
from instagram_hdmap.config import load_config
from instagram_hdmap.models import build_model

CONFIGS = ["configs/paper/table1_b0_lss_128x352.yaml", "configs/paper/table1_b4_lss_128x352.yaml"]
ROWS = ("eager", "compiled", "onnxruntime")


def max_diff(expected: dict, got: dict) -> tuple[float, str]:
    """(max |difference| over the dense outputs and, where both kept the same vertices, the graph
    outputs; "same" or "differ"): ``deploy.compare_outputs``. Random weights give near-equal vertex
    scores, which top-N may cut differently (docs/deploy.md, Parity)."""
    check = deploy.compare_outputs(expected, got)
    worst = max(check["dense"], check["graph"] or 0.0)
    return worst, "same" if check["same_vertices"] else "differ"


def build_paths(path: str, rows: list[str], onnx_dir: Path, threads: int, ort_level: str) -> tuple[dict, dict, dict]:
    """-> (callables by row, setup seconds by row, max |diff| by row), for one config."""
    cfg = load_config(path, ["data.dataroot=/nonexistent"])
    torch.manual_seed(0)
    model = build_model(cfg).eval()
    batch = deploy.example_inputs(cfg, seed=1)
    with torch.inference_mode():
        expected = model(batch)
    paths, setup, diffs = {}, {}, {}
    for row in rows:
        start = time.perf_counter()
        if row == "eager":
            paths[row] = model
        elif row == "compiled":
            with torch.inference_mode():
                paths[row] = deploy.fast_forward(model, batch, compile=True)
        else:
            file = onnx_dir / f"{Path(path).stem}_seed0.onnx"
            if not file.is_file():
                deploy.export_onnx(model, cfg, file, source="benchmarks/deploy_speed.py random weights, seed 0")
            paths[row] = inference.OnnxModel(file, cfg, threads=threads, optimization=ort_level)
        setup[row] = time.perf_counter() - start
        print(f"  {Path(path).stem}: {row} ready in {setup[row]:.0f} s", flush=True)
        with torch.inference_mode():
            diffs[row] = max_diff(expected, paths[row](batch))
        if row == "onnxruntime" and diffs[row][0] > 1e-2:  # a stale file from other weights: export again
            deploy.export_onnx(model, cfg, file, source="benchmarks/deploy_speed.py random weights, seed 0")
            paths[row] = inference.OnnxModel(file, cfg, threads=threads, optimization=ort_level)
            diffs[row] = max_diff(expected, paths[row](batch))
    return paths, setup, diffs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--configs", nargs="+", default=CONFIGS)
    parser.add_argument("--rows", nargs="+", default=list(ROWS), choices=ROWS)
    parser.add_argument("--runs", type=int, default=20, help="timed rounds (each calls every row once)")
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--ort-level", default="all", choices=["all", "extended", "basic", "disabled"],
                        help="onnxruntime graph optimisation level")
    parser.add_argument("--onnx-dir", default=None, help="folder for the exported files (default: a temporary one)")
    args = parser.parse_args()
    from instagram_hdmap.benchmark import check_counts

    check_counts(parser, args, runs=1, warmup=0, threads=1)
    torch.set_num_threads(args.threads)
    if "eager" not in args.rows:
        args.rows.insert(0, "eager")  # the reference of the ratios
    import tempfile

    tmp = tempfile.TemporaryDirectory() if args.onnx_dir is None else None
    onnx_dir = Path(args.onnx_dir or tmp.name)
    onnx_dir.mkdir(parents=True, exist_ok=True)

    print(f"device {device_name(torch.device('cpu'))}, torch {torch.__version__}, {args.threads} threads "
          f"(torch and onnxruntime), batch 1 x 6 cameras, random weights, float32; load average "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())} at the start")
    results = []
    for path in args.configs:
        paths, setup, diffs = build_paths(path, args.rows, onnx_dir, args.threads, args.ort_level)
        batch = deploy.example_inputs(load_config(path, ["data.dataroot=/nonexistent"]), seed=2)
        times: dict[str, list[float]] = {row: [] for row in args.rows}
        with torch.inference_mode():
            for i in range(args.warmup + args.runs):
                for row in args.rows:  # interleaved: every round runs each path once
                    start = time.perf_counter()
                    paths[row](batch)
                    if i >= args.warmup:
                        times[row].append(time.perf_counter() - start)
        eager = float(np.median(times["eager"]))
        for row in args.rows:
            t = 1000 * np.asarray(times[row])
            results.append((Path(path).stem, row, float(np.median(t)), float(np.percentile(t, 90)),
                            float(np.median(t)) / (1000 * eager), setup[row], diffs[row]))
        del paths

    head = (f"{'config':<26}{'path':<13}{'median ms':>10}{'p90 ms':>9}{'x eager':>9}{'setup s':>9}"
            f"{'max |diff|':>12}{'vertices':>10}")
    print(head)
    print("-" * len(head))
    for name, row, median, p90, ratio, setup_s, diff in results:
        print(f"{name:<26}{row:<13}{median:>10.1f}{p90:>9.1f}{ratio:>9.2f}{setup_s:>9.1f}{diff[0]:>12.1e}"
              f"{diff[1]:>10}")
    print(f"{args.runs} interleaved rounds after {args.warmup} warm-up rounds; setup = compile / export + "
          f"session start; max |diff| = vs eager torch (dense outputs, and the log-assignment where the "
          f"vertices are the same: ties of random weights); load average "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())} at the end")
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    from instagram_hdmap.benchmark import script_main

    script_main(main)
