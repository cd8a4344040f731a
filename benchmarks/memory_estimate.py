"""The memory estimate of a training step (resources.py) against the step's measured peak, as a table.

    python benchmarks/memory_estimate.py              # tiny, demo and the Table I / II configs at batch 1-4, CPU
    python benchmarks/memory_estimate.py --quick      # tiny and demo only (seconds)

Each row runs one training step of its config in a fresh process (``benchmarks/train_speed.py --one``: random
images, plausible map targets, forward + criterion + backward + Adam) and reads that process's peak resident set
size; the estimate is ``resources.estimate`` of the same config and batch, without data workers (the measured
process has none). ``ratio`` = estimate / measured: the refusal threshold (``resources.REFUSE_OVER``) covers the
largest ratio seen. GB = 1e9 bytes.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from instagram_hdmap import resources
from instagram_hdmap.config import load_config

ROOT = Path(__file__).resolve().parents[1]
ROWS = [  # (config, batch, backbone checkpointing)
    ("configs/synthetic/tiny.yaml", 1, "off"), ("configs/synthetic/tiny.yaml", 4, "off"),
    ("configs/synthetic/demo.yaml", 4, "on"),
    ("configs/paper/table1_b0_lss_128x352.yaml", 1, "on"), ("configs/paper/table1_b0_lss_128x352.yaml", 1, "off"),
    ("configs/paper/table1_b0_lss_128x352.yaml", 2, "off"),
    ("configs/paper/table1_b4_lss_128x352.yaml", 1, "on"), ("configs/paper/table1_b4_lss_128x352.yaml", 1, "off"),
    ("configs/paper/table2_range100x100.yaml", 1, "on"),
]


def measured_peak(config: str, batch: int, ckpt: str) -> float:
    """Peak RSS in bytes of one training step of ``config`` in a fresh process."""
    cmd = [sys.executable, str(ROOT / "benchmarks" / "train_speed.py"), "--one", str(ROOT / config),
           "--batch", str(batch), "--grad-checkpoint", ckpt, "--steps", "1", "--warmup", "1"]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=900, cwd=ROOT)
    line = next((ln for ln in out.stdout.splitlines() if ln.startswith("RESULT")), None)
    if line is None:
        raise SystemExit(f"{config}: no result ({out.stderr.strip().splitlines()[-1:]})")
    return json.loads(line.split(" ", 1)[1])["peak_rss_gb"] * resources.GB


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="the synthetic configs only")
    args = parser.parse_args()
    rows = [r for r in ROWS if not args.quick or "synthetic" in r[0]]
    print("| config | batch | grad checkpoint | estimate | measured peak RSS | ratio |")
    print("| --- | --- | --- | --- | --- | --- |")
    for config, batch, ckpt in rows:
        cfg = load_config(ROOT / config, [f"train.batch_size={batch}", "data.num_workers=0",
                                          f"model.backbone.grad_checkpoint={ckpt == 'on'}"])
        est, peak = resources.estimate(cfg, "train"), measured_peak(config, batch, ckpt)
        print(f"| {Path(config).stem} | {batch} | {ckpt} | {est / resources.GB:.2f} GB | {peak / resources.GB:.2f} GB "
              f"| {est / peak:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
