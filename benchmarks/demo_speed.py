"""The demo's training throughput (samples/s) of two checkouts of the package, in one run.

    python benchmarks/demo_speed.py --world CACHE/synthetic-dc22c27c47 --checkout old=/path/to/old/checkout
    python benchmarks/demo_speed.py --world WORLD --checkout old=OLD --epochs 4 --rounds 2 --extra bf16=train.amp=bf16

Each variant runs ``instagram-hdmap train`` of its checkout (``PYTHONPATH=CHECKOUT/src``) on that checkout's own
``configs/synthetic/demo.yaml``, as the demo would: the demo's world (``--world``: the cached training world the demo
generated, ``~/.cache/instagram_hdmap/synthetic-*`` with 24 training scenes), its data workers, threads and
precision, with ``--epochs`` epochs of the demo's 120 steps (``train.lr_step`` one before the end) into a temporary
run folder. ``--checkout NAME=PATH`` adds another checkout (this one is ``new``); ``--extra NAME=KEY=VALUE[,...]``
adds this checkout with overrides. The variants run in turn, ``--rounds`` times, so machine load hits them alike.

Per variant, from the run's ``log.jsonl`` (each epoch's ``samples_per_s`` and ``train_seconds``): the first epoch
(which reads the world from disk: an in-memory sample cache fills there), the median of the later epochs, and the
whole run's rate (its samples over its seconds); the ratio columns divide the later epochs' and the whole run's rates
by the first variant's. The demo trains 60 epochs, so its rate is close to the later epochs'.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def train_once(checkout: Path, world: Path, epochs: int, overrides: list[str], threads: str | None) -> list[dict]:
    """One ``train`` of ``checkout``'s demo config on ``world``; its log's epoch records."""
    with tempfile.TemporaryDirectory(ignore_cleanup_errors=True) as tmp:
        env = {**os.environ, "PYTHONPATH": str(checkout / "src")}
        env.pop("OMP_NUM_THREADS", None)
        if threads:
            env["OMP_NUM_THREADS"] = threads
        cmd = [sys.executable, "-m", "instagram_hdmap.cli", "train", str(checkout / "configs/synthetic/demo.yaml"),
               f"data.dataroot={world}", "data.version=v1.0-trainval", f"data.splits_file={world / 'splits.json'}",
               f"train.out_dir={tmp}/run", f"train.epochs={epochs}", f"train.lr_step={epochs - 1}",
               "train.val_every=1000000", *overrides]
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
        if proc.returncode:
            raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
        log = Path(tmp) / "run" / "log.jsonl"
        return [r for r in map(json.loads, log.read_text().splitlines()) if "samples_per_s" in r]


def summary(rounds: list[list[dict]]) -> dict:
    """First-epoch and later-epoch rates (medians over the rounds) and the whole runs' rate (their samples over
    their seconds) of a variant's rounds."""
    records = [r for run in rounds for r in run]
    later = [r["samples_per_s"] for r in records if r["epoch"] > 0]
    seconds = sum(r["train_seconds"] for r in records)
    return {"first": statistics.median(r["samples_per_s"] for r in records if r["epoch"] == 0),
            "later": statistics.median(later) if later else float("nan"),
            "whole": sum(r["samples_per_s"] * r["train_seconds"] for r in records) / seconds,
            "threads": records[0].get("cpu_threads")}


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--world", type=Path, required=True, help="the demo's cached training world")
    p.add_argument("--checkout", action="append", default=[], metavar="NAME=PATH",
                   help="another checkout of the package (its own src/ and demo config)")
    p.add_argument("--extra", action="append", default=[], metavar="NAME=KEY=VALUE[,KEY=VALUE]",
                   help="this checkout with overrides")
    p.add_argument("--epochs", type=int, default=4, help="epochs of 120 steps per variant (>= 2)")
    p.add_argument("--rounds", type=int, default=1)
    p.add_argument("--threads", help="OMP_NUM_THREADS for every variant (default: each checkout chooses)")
    args = p.parse_args(argv)
    if args.epochs < 2:
        p.error("--epochs must be at least 2 (the first epoch reads the world from disk)")
    if not (args.world / "splits.json").is_file():
        p.error(f"--world {args.world}: no splits.json there; give a world the demo generated")
    return args


def variants(args: argparse.Namespace) -> list[tuple[str, Path, list[str]]]:
    out = []
    for spec in args.checkout:
        name, _, path = spec.partition("=")
        if not (Path(path) / "src" / "instagram_hdmap").is_dir():
            raise SystemExit(f"--checkout {spec}: {path} holds no src/instagram_hdmap")
        out.append((name, Path(path).resolve(), []))
    out.append(("new", ROOT, []))
    for spec in args.extra:
        name, _, overrides = spec.partition("=")
        out.append((name, ROOT, overrides.split(",")))
    return out


def main(argv: list[str] | None = None) -> int:
    args = parse(argv)
    runs = variants(args)
    records: dict[str, list[list[dict]]] = {name: [] for name, _, _ in runs}
    for r in range(args.rounds):
        for name, checkout, overrides in runs:
            print(f"round {r + 1}/{args.rounds}: {name}", file=sys.stderr, flush=True)
            records[name].append(train_once(checkout, args.world.resolve(), args.epochs, overrides, args.threads))
    print("| variant | threads | first epoch samples/s | later epochs samples/s | whole run samples/s | later x first "
          "| whole x first |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    base = None
    for name, checkout, overrides in runs:
        s = summary(records[name])
        base = base or s
        what = f"{name} ({checkout.name}{' ' + ' '.join(overrides) if overrides else ''})"
        print(f"| {what} | {s['threads']} | {s['first']:.1f} | {s['later']:.1f} | {s['whole']:.1f} | "
              f"{s['later'] / base['later']:.2f} | {s['whole'] / base['whole']:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
