"""FPS of the paper's Table I configurations (batch 1, six cameras), fp32 and bf16, as one table.

    python benchmarks/fps.py --device cuda                 # >= 50 runs each (the paper: RTX 3090)
    python benchmarks/fps.py --device cpu --runs 10 --configs configs/paper/table1_b0_lss_128x352.yaml
    python benchmarks/fps.py --device cuda --modes eager compile cuda_graphs --markdown   # benchmarks/gpu.sh

Each cell is ``instagram-hdmap benchmark CONFIG --device D --amp A [--compile | --cuda-graphs]``
(instagram_hdmap.benchmark): random images and weights, a nuScenes-like rig, synchronised timing, median
latency -> FPS, with the p10-p90 FPS range. ``--modes``: eager, ``compile`` (torch.compile, compiled before
the warm-up) and ``cuda_graphs`` (CUDA-graph replay; a GPU only). ``--markdown`` prints the table as
Markdown, for benchmarks/README.md. Paper (RTX 3090): 24.8 (B0 128x352), 19.2 (B4 128x352), 11.8 (B4 256x704).
"""

from __future__ import annotations

import argparse

import torch

from instagram_hdmap.benchmark import device_name, run_benchmark
from instagram_hdmap.config import load_config
from instagram_hdmap.resources import cpu_capability

CONFIGS = {
    "configs/paper/table1_b0_lss_128x352.yaml": 24.8,
    "configs/paper/table1_b4_lss_128x352.yaml": 19.2,
    "configs/paper/table1_b4_lss_256x704.yaml": 11.8,
}
MODES = {"eager": {}, "compile": {"compile": True}, "cuda_graphs": {"cuda_graphs": True}}
COLUMNS = ("config", "amp", "mode", "model FPS", "(p90-p10)", "+decoding FPS", "(p90-p10)", "paper")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--runs", type=int, help="default 50 on a GPU, 10 on the CPU")
    parser.add_argument("--warmup", type=int)
    parser.add_argument("--amp", nargs="+", default=["none", "bf16"], choices=["none", "bf16", "fp16"])
    parser.add_argument("--modes", nargs="+", default=["eager"], choices=list(MODES))
    parser.add_argument("--configs", nargs="+", default=list(CONFIGS))
    parser.add_argument("--markdown", action="store_true", help="print the table as Markdown")
    args = parser.parse_args(argv)
    from instagram_hdmap.benchmark import check_counts

    check_counts(parser, args, runs=1, warmup=0)
    if "cuda_graphs" in args.modes and not args.device.startswith("cuda"):
        parser.error(f"--modes cuda_graphs needs --device cuda (got --device {args.device})")
    return args


def table_row(path: str, amp: str, mode: str, result: dict) -> list[str]:
    """One row of the table: the config's file name, the precision and mode, FPS and p10-p90 spread of the model
    and of the model + decoding, and the paper's FPS where it has one."""
    cells = [path.rsplit("/", 1)[-1], amp, mode]
    for row in ("model", "model + post-processing"):
        s = result["rows"][row]
        cells += [f"{s['fps']:.1f}", f"{1000 / s['p90_ms']:.1f}-{1000 / s['p10_ms']:.1f}"]
    paper = CONFIGS.get(path)
    return cells + [f"{paper}" if paper else ""]


def format_row(cells: list[str], markdown: bool) -> str:
    if markdown:
        return "| " + " | ".join(cells) + " |"
    widths = (40, 6, 12, 11, 14, 15, 14, 8)
    return f"{cells[0]:<{widths[0]}}" + "".join(f"{c:>{w}}" for c, w in zip(cells[1:], widths[1:]))


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    print(f"device {device_name(torch.device(args.device))}, torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads, batch 1 x 6 cameras, random weights; cpu: {cpu_capability()}")
    head = format_row(list(COLUMNS), args.markdown)
    print(head)
    print("|" + "---|" * len(COLUMNS) if args.markdown else "-" * len(head))
    for path in args.configs:
        cfg = load_config(path, ["data.dataroot=/nonexistent"])  # the rig built in code
        for amp in args.amp:
            for mode in args.modes:
                r = run_benchmark(cfg, device=args.device, amp=amp, runs=args.runs, warmup=args.warmup,
                                  **MODES[mode])
                print(format_row(table_row(path, amp, mode, r), args.markdown), flush=True)
    print(f"runs per cell: {r['runs']} after {r['warmup']} warm-up runs")


if __name__ == "__main__":
    from instagram_hdmap.benchmark import script_main

    script_main(main)
