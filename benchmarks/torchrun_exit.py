"""How often a finished two-rank torchrun training still fails at its exit.

gloo's threads aborted a rank at random while Python tore the interpreter down ("terminate called without an active
exception", SIGABRT), so torchrun failed a job whose work was done and whose files were written (1 job in 51 on the
2-core machine, three jobs at a time, before ``cli.main`` ended such a rank with ``os._exit``). This runs ``--jobs``
tiny two-rank trainings (configs/synthetic/tiny.yaml, one step) on a small synthetic world, ``--parallel`` at a time
(load makes the race likelier), and prints how many ended with each exit status.

    python benchmarks/torchrun_exit.py --jobs 30 --parallel 3
"""

from __future__ import annotations

import argparse
import collections
import concurrent.futures
import os
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def one_job(world: Path, out: Path) -> tuple[int, bool]:
    """(torchrun's exit status, whether a rank printed gloo's abort)."""
    p = subprocess.run(
        [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_port", str(free_port()),
         "-m", "instagram_hdmap.cli", "train", str(REPO / "configs" / "synthetic" / "tiny.yaml"),
         f"data.dataroot={world}", f"data.splits_file={world / 'splits.json'}", "data.num_workers=0",
         "train.device=cpu", f"train.out_dir={out}", "train.max_steps=1", "train.batch_size=2"],
        capture_output=True, text=True, timeout=600, env={**os.environ, "OMP_NUM_THREADS": "1"})
    return p.returncode, "terminate called" in p.stderr


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--jobs", type=int, default=30, help="two-rank trainings to run (default 30)")
    parser.add_argument("--parallel", type=int, default=3, help="jobs at a time (default 3)")
    args = parser.parse_args()
    if args.jobs < 1 or args.parallel < 1:
        parser.error("--jobs and --parallel must be at least 1")
    with tempfile.TemporaryDirectory() as tmp:
        world = Path(tmp) / "world"
        subprocess.run([sys.executable, "-m", "instagram_hdmap.cli", "synth", "--out", str(world), "--scenes-train",
                        "2", "--scenes-val", "1", "--samples-per-scene", "3", "--image-size", "400x225"],
                       check=True, capture_output=True)
        with concurrent.futures.ThreadPoolExecutor(args.parallel) as pool:
            results = list(pool.map(lambda i: one_job(world, Path(tmp) / f"run{i}"), range(args.jobs)))
    counts = collections.Counter(code for code, _ in results)
    aborts = sum(abort for _, abort in results)
    print("| jobs | parallel | exit 0 | other exit statuses | 'terminate called' seen |")
    print("| --- | --- | --- | --- | --- |")
    print(f"| {args.jobs} | {args.parallel} | {counts.pop(0, 0)} | "
          f"{', '.join(f'{c}: {n}' for c, n in sorted(counts.items())) or 'none'} | {aborts} |")


if __name__ == "__main__":
    main()
