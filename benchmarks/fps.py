"""FPS of the paper's Table I configurations (batch 1, six cameras), fp32 and bf16, as one table.

    python benchmarks/fps.py --device cuda                 # >= 50 runs each (the paper: RTX 3090)
    python benchmarks/fps.py --device cpu --runs 10 --configs configs/paper/table1_b0_lss_128x352.yaml

Each cell is ``instagram-hdmap benchmark CONFIG --device D --amp A`` (instagram_hdmap.benchmark):
random images and weights, a nuScenes-like rig, synchronised timing, median latency -> FPS, with
the p10-p90 FPS range. Paper (RTX 3090): 24.8 (B0 128x352), 19.2 (B4 128x352), 11.8 (B4 256x704).
"""

from __future__ import annotations

import argparse

import torch

from instagram_hdmap.benchmark import device_name, run_benchmark
from instagram_hdmap.config import load_config

CONFIGS = {
    "configs/paper/table1_b0_lss_128x352.yaml": 24.8,
    "configs/paper/table1_b4_lss_128x352.yaml": 19.2,
    "configs/paper/table1_b4_lss_256x704.yaml": 11.8,
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--runs", type=int, help="default 50 on a GPU, 10 on the CPU")
    parser.add_argument("--warmup", type=int)
    parser.add_argument("--amp", nargs="+", default=["none", "bf16"], choices=["none", "bf16", "fp16"])
    parser.add_argument("--configs", nargs="+", default=list(CONFIGS))
    args = parser.parse_args()
    from instagram_hdmap.benchmark import check_counts

    check_counts(parser, args, runs=1, warmup=0)

    print(f"device {device_name(torch.device(args.device))}, torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads, batch 1 x 6 cameras, random weights")
    head = (f"{'config':<40}{'amp':>6}{'model FPS':>11}{'(p90-p10)':>14}{'+post FPS':>11}{'(p90-p10)':>14}"
            f"{'paper':>8}")
    print(head)
    print("-" * len(head))
    for path in args.configs:
        cfg = load_config(path, ["data.dataroot=/nonexistent"])  # the rig built in code
        for amp in args.amp:
            r = run_benchmark(cfg, device=args.device, amp=amp, runs=args.runs, warmup=args.warmup)
            cells = ""
            for row in ("model", "model + post-processing"):
                s = r["rows"][row]
                spread = f"{1000 / s['p90_ms']:.1f}-{1000 / s['p10_ms']:.1f}"
                cells += f"{s['fps']:>11.1f}{spread:>14}"
            paper = CONFIGS.get(path)
            print(f"{path.rsplit('/', 1)[-1]:<40}{amp:>6}{cells}{paper if paper else '':>8}", flush=True)
    print(f"runs per cell: {r['runs']} after {r['warmup']} warm-up runs")


if __name__ == "__main__":
    from instagram_hdmap.benchmark import script_main

    script_main(main)
