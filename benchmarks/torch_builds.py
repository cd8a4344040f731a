"""The demo's training step under different torch builds (and thread / data-worker settings), in one run.

    python benchmarks/torch_builds.py --world DATAROOT \\
        --python cpu-2.13=/usr/bin/python3 --python newcomer=/path/to/new-venv/bin/python

Why: `pip install -e ".[dev]"` in a new virtualenv resolves the newest torch the registry serves (a
CUDA build), not the CPU wheel CI installs first, and a newcomer's demo trained ~1.7x slower. Each
(interpreter, threads, data workers) variant runs in its own subprocess with ``PYTHONPATH`` set to
this checkout's ``src`` (so every build runs the same code), the variants interleaved over
``--rounds`` rounds so that machine load hits them alike. Per variant:

* ``train``: samples/s of ``engine.train_one_epoch`` on the demo config over the world's real
  DataLoader (``configs/synthetic/demo.yaml``: JPEG decode, targets, model, criterion, backward,
  Adam), after ``--warmup`` steps; ``data wait``: the share of the wall time spent waiting for the
  next batch; ``cpu/step``: the process's CPU time per step (all its threads);
* micro-benchmarks, median ms: ``conv``: forward + backward of the BEV encoder alone;
  ``backbone``: forward + backward of the image backbone on a 24-image batch; ``exp-sub``: exp()
  of 1M floats whose results are subnormal; ``sinkhorn``: 100 iterations forward + backward at
  the demo's N; ``jpeg``: decoding one 480x270 camera JPEG with the dataset's reader;
* the build: torch version, CUDA build or not, OpenMP / MKL / oneDNN from
  ``torch.__config__.parallel_info()`` and ``show()``.

The table prints every variant with its ratio to the first one.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULT_TAG = "RESULT "


def _median_ms(fn, repeats: int = 7, warmup: int = 2) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return 1000 * statistics.median(times)


def child(args: argparse.Namespace) -> dict:
    import torch

    torch.set_num_threads(int(args.threads))
    from instagram_hdmap.config import load_config
    from instagram_hdmap.demo import default_config_path, world_overrides
    from instagram_hdmap.engine import EpochHooks, Position, StepSettings, train_one_epoch
    from instagram_hdmap.geometry import BEVGrid
    from instagram_hdmap.losses import Criterion
    from instagram_hdmap.models import build_model
    from instagram_hdmap.models.matching import log_optimal_transport
    from instagram_hdmap.train import build_loaders, seed_everything

    cfg = load_config(default_config_path(), [*world_overrides(args.world), f"data.num_workers={args.workers}",
                                              "train.device=cpu", "train.log_every=1000000"])
    seed_everything(0)
    model = build_model(cfg)
    criterion = Criterion(cfg.loss, BEVGrid.from_config(cfg.grid))
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.train.lr)
    loader, sampler, _ = build_loaders(cfg, 1, with_val=False)
    sampler.set_epoch(0)
    marks: list[tuple[str, float, float]] = []

    def before(step: int) -> None:
        marks.append(("got", time.perf_counter(), time.process_time()))

    def after(info) -> None:
        marks.append(("done", time.perf_counter(), time.process_time()))

    n = args.warmup + args.steps
    marks.append(("start", time.perf_counter(), time.process_time()))
    train_one_epoch(model, criterion, loader, optimizer, torch.device("cpu"), Position(0), total=n,
                    settings=StepSettings(grad_clip=cfg.train.grad_clip, log_every=10**9),
                    hooks=EpochHooks(should_stop=lambda s: s >= n, on_step=after, before_step=before))
    done = [m for m in marks if m[0] == "done"]
    got = [m for m in marks if m[0] == "got"]
    t0, c0 = done[args.warmup - 1][1:] if args.warmup else marks[0][1:]
    t1, c1 = done[-1][1:]
    timed = range(args.warmup, n)
    prev_done = [done[i - 1][1] if i > 0 else marks[0][1] for i in timed]
    wait = sum(got[i][1] - p for i, p in zip(timed, prev_done))
    out = {"samples_per_s": args.steps * cfg.train.batch_size / (t1 - t0), "data_wait": wait / (t1 - t0),
           "cpu_per_step_ms": 1000 * (c1 - c0) / args.steps}

    # micro-benchmarks
    batch = next(iter(loader))
    images = batch["images"].flatten(0, 1)
    model.train()

    def backbone():
        model.zero_grad(set_to_none=True)
        model.backbone(images).sum().backward()

    out["backbone_ms"] = _median_ms(backbone, args.micro)
    with torch.no_grad():
        feats = model.backbone(images).unflatten(0, batch["images"].shape[:2])
        bev = model.view_transform(feats, {k: batch[k] for k in ("intrinsics", "cam_to_ego_rot", "cam_to_ego_trans",
                                                                 "post_rot", "post_tran")})

    def conv():
        model.zero_grad(set_to_none=True)
        heads = model.bev_heads(bev)
        (heads["pred_vertex_logits"].sum() + heads["pred_distance"].sum()).backward()

    out["conv_ms"] = _median_ms(conv, args.micro)
    sub = torch.full((1_000_000,), -95.0)
    out["exp_sub_ms"] = _median_ms(lambda: torch.exp(sub), args.micro)
    N = cfg.model.gnn.num_vertices
    g = torch.Generator().manual_seed(0)
    scores0 = (torch.randn(4, N, N, generator=g) * 8).requires_grad_(True)
    mask = torch.arange(N)[None].expand(4, N) < int(0.7 * N)

    def sinkhorn():
        scores0.grad = None
        log_assignment = log_optimal_transport(scores0, torch.tensor(1.0), mask, cfg.model.gnn.sinkhorn_iters)
        log_assignment[:, :-1, :-1].sum().backward()

    out["sinkhorn_ms"] = _median_ms(sinkhorn, args.micro)
    ds = loader.dataset
    out["jpeg_ms"] = _median_ms(lambda: ds.load_cameras(0), args.micro)
    cfg_text = torch.__config__.show()
    par = torch.__config__.parallel_info()
    out["build"] = {
        "torch": torch.__version__, "cuda_build": torch.version.cuda,
        "openmp": next((ln.split(":", 1)[1].strip() for ln in par.splitlines() if "OpenMP" in ln and ":" in ln), "?"),
        "mkl": "MKL" in cfg_text and "USE_MKL=ON" in cfg_text.replace(" ", ""),
        "mkldnn": torch.backends.mkldnn.is_available(), "threads": torch.get_num_threads(),
        "cpu_capability": getattr(torch.backends.cpu, "get_cpu_capability", lambda: "?")(),
    }
    return out


def run_variant(name: str, python: str, threads: int, workers: int, args: argparse.Namespace) -> dict:
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src"), "OMP_NUM_THREADS": str(threads),
           "MKL_NUM_THREADS": str(threads)}
    cmd = [python, __file__, "--child", "--world", args.world, "--threads", str(threads), "--workers", str(workers),
           "--steps", str(args.steps), "--warmup", str(args.warmup), "--micro", str(args.micro)]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith(RESULT_TAG)]
    if proc.returncode != 0 or not lines:
        raise SystemExit(f"variant {name} failed (exit {proc.returncode}):\n{proc.stderr[-3000:]}")
    return json.loads(lines[-1][len(RESULT_TAG):])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--world", required=True, help="dataroot of a synthetic world (the demo's)")
    ap.add_argument("--python", action="append", default=[], metavar="NAME=PYTHON",
                    help="an interpreter to compare (default: this one)")
    ap.add_argument("--threads", default="2", help="comma-separated intra-op thread counts (default 2)")
    ap.add_argument("--workers", default="1", help="comma-separated data-worker counts (default 1, the demo's)")
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--warmup", type=int, default=10)
    ap.add_argument("--micro", type=int, default=7, help="repeats of each micro-benchmark")
    ap.add_argument("--rounds", type=int, default=1)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(RESULT_TAG + json.dumps(child(args)), flush=True)
        return 0
    pythons = [p.partition("=")[::2] for p in args.python] or [("this", sys.executable)]
    variants = [(f"{n} t{t} w{w}", py, int(t), int(w)) for n, py in pythons
                for t in args.threads.split(",") for w in args.workers.split(",")]
    results: dict[str, list[dict]] = {v[0]: [] for v in variants}
    for r in range(args.rounds):
        for name, py, t, w in variants:
            res = run_variant(name, py, t, w, args)
            results[name].append(res)
            print(f"round {r + 1}: {name}: {res['samples_per_s']:.2f} samples/s", file=sys.stderr, flush=True)
    cols = ["samples_per_s", "data_wait", "cpu_per_step_ms", "backbone_ms", "conv_ms", "exp_sub_ms", "sinkhorn_ms",
            "jpeg_ms"]
    first = None
    print(f"load average at the end: {os.getloadavg()[0]:.2f}; {args.steps} timed steps after {args.warmup}, "
          f"{args.rounds} round(s), medians over rounds\n")
    print("| variant | torch | OpenMP | " + " | ".join(cols) + " | x samples/s |")
    print("|" + " --- |" * (len(cols) + 4))
    for name, rs in results.items():
        med = {c: statistics.median(r[c] for r in rs) for c in cols}
        first = first or med
        b = rs[0]["build"]
        build = f"{b['torch']}{' (CUDA ' + b['cuda_build'] + ')' if b['cuda_build'] else ''}"
        cells = [f"{med[c]:.2f}" if c in ("samples_per_s", "data_wait") else f"{med[c]:.1f}" for c in cols]
        print(f"| {name} | {build} | {b['openmp']} | " + " | ".join(cells)
              + f" | {med['samples_per_s'] / first['samples_per_s']:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
