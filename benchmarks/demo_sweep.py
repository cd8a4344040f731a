"""Sweep variants of the demo config in parallel and print their validation AP as one table.

    python benchmarks/demo_sweep.py --dataroot WORLD --steps 6000 --device cuda \
        --variant base= --variant n64=model.gnn.num_vertices=64 --variant adj05=loss.adjacency_weight=0.05

Each variant (NAME=override[,override...]) trains ``configs/synthetic/demo.yaml`` for ``--steps``
steps in its own process (``instagram-hdmap train``), then is evaluated with the vector protocol
(``instagram-hdmap evaluate``). Steps, not minutes, make variants comparable across machines: the
CPU demo reaches about 6000 steps in its budget on 2 free cores. Used to choose demo.yaml (the
figures are in benchmarks/README.md).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataroot", required=True, help="a synthetic world (instagram-hdmap synth)")
    parser.add_argument("--config", default="configs/synthetic/demo.yaml")
    parser.add_argument("--steps", type=int, default=6000)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", default="runs/demo_sweep")
    parser.add_argument("--threads", type=int, default=2, help="torch threads per variant")
    parser.add_argument("--variant", action="append", required=True, help="NAME=override,override,...")
    args = parser.parse_args()
    from instagram_hdmap.benchmark import check_counts

    check_counts(parser, args, steps=1, threads=1)

    root = Path(args.dataroot)
    common = [f"data.dataroot={root}", f"data.splits_file={root / 'splits.json'}", f"train.device={args.device}"]
    env = {**os.environ, "OMP_NUM_THREADS": str(args.threads)}
    procs = {}
    t0 = time.perf_counter()
    for spec in args.variant:
        name, _, rest = spec.partition("=")
        overrides = [o for o in rest.split(",") if o]
        out = Path(args.out) / name
        out.mkdir(parents=True, exist_ok=True)
        cmd = [sys.executable, "-m", "instagram_hdmap.cli", "train", args.config, *common, *overrides,
               f"train.out_dir={out / 'run'}", f"train.max_steps={args.steps}", "--force"]
        ev = [sys.executable, "-m", "instagram_hdmap.cli", "evaluate", args.config, *common, *overrides,
              "--checkpoint", str(out / "run" / "last.pt"), "--out", str(out / "eval")]
        log = (out / "log.txt").open("w")
        shell = f"{subprocess.list2cmdline(cmd)} && {subprocess.list2cmdline(ev)}"
        procs[name] = (subprocess.Popen(shell, shell=True, stdout=log, stderr=subprocess.STDOUT, env=env), overrides)
    rows = []
    for name, (proc, overrides) in procs.items():
        rc = proc.wait()
        metrics = Path(args.out) / name / "eval" / "metrics.json"
        if rc != 0 or not metrics.is_file():
            rows.append((name, overrides, None, f"failed (rc {rc}), see {Path(args.out) / name / 'log.txt'}"))
            continue
        m = json.loads(metrics.read_text())
        rows.append((name, overrides, m, ""))
    print(f"{len(procs)} variants x {args.steps} steps on {args.device} in {(time.perf_counter() - t0) / 60:.1f} min")
    head = f"{'variant':<12}{'divider':>9}{'ped':>9}{'boundary':>9}{'mAP':>8}  overrides"
    print(head)
    print("-" * len(head))
    for name, overrides, m, err in rows:
        if m is None:
            print(f"{name:<12}{err}")
            continue
        ap = {k: math.nan if v is None else v for k, v in m["AP_class"].items()}  # null: a raster 0/0 (NaN)
        m["mAP"] = math.nan if m["mAP"] is None else m["mAP"]
        print(f"{name:<12}{ap['divider']:>9.3f}{ap['ped_crossing']:>9.3f}{ap['boundary']:>9.3f}{m['mAP']:>8.3f}  "
              f"{' '.join(overrides)}")


if __name__ == "__main__":
    from instagram_hdmap.benchmark import script_main

    script_main(main)
