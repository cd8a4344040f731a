"""Forward latency of InstaGraM per component (batch 1, six cameras), printed as a table.

    python benchmarks/model_speed.py                      # CPU, 2 threads, B0 and B4 with LSS, 128x352
    python benchmarks/model_speed.py --runs 9 --threads 2
    python benchmarks/model_speed.py --official OFFICIAL  # + the official model, timed in the same run
    python benchmarks/model_speed.py --precision fp32     # our fp32 alone (default: fp32, bf16 and int8;
                                                          # bf16 only where the CPU has it natively)
    python benchmarks/model_speed.py --device cuda        # + GPU latency / FPS, fp32 and bf16 autocast
    python benchmarks/model_speed.py --official OFFICIAL --compile-backbone  # + each precision, backbone compiled

Each component is timed by calling the model's parts in the order of ``InstaGraM.forward`` (backbone,
view transform, BEV heads, then the graph head's vertex extraction, embedding + GNN + class head,
matching head + Sinkhorn); "total" times ``model(batch)`` itself. Medians over ``--runs`` after a
warm-up. Random weights and images, a nuScenes-like six-camera rig; eval mode, no autograd.

``--official OFFICIAL`` (a local checkout of the official InstaGraM code, benchmarks/official.py)
builds the official LSS model of each config's backbone and image size (random weights) and times
its fp32 forward on the same batch, interleaved with ours (each round runs our forward + decoding in each
``--precision``, as ``Mapper`` runs it (``precision.with_precision``), then theirs), in the same process with the
same torch and thread count: the ratio rows are the comparison, and they are what this script is for. Absolute
times depend on the machine and its load; a ratio of two paths
timed in turn is load-robust to the extent the load is steady.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import time
from collections.abc import Callable

import torch
import torch.nn.functional as F

from instagram_hdmap.benchmark import time_runs
from instagram_hdmap.config import load_config
from instagram_hdmap.geometry import BEVGrid
from instagram_hdmap.models import build_model
from instagram_hdmap.models.view_transform import CALIBRATION_KEYS
from instagram_hdmap.postprocess import decode_options, postprocess_batch
from instagram_hdmap.precision import PRECISIONS, compile_backbone, native_bf16, resolve_precision, with_precision
from instagram_hdmap.resources import cpu_capability, reuse_freed_memory

CPU_CONFIGS = ["configs/paper/table1_b0_lss_128x352.yaml", "configs/paper/table1_b4_lss_128x352.yaml"]
GPU_CONFIGS = [*CPU_CONFIGS, "configs/paper/table1_b4_lss_256x704.yaml"]


def example_batch(image_size: tuple[int, int], device: torch.device, num_cameras: int = 6) -> dict:
    """Batch of one sample: random images, a nuScenes-like rig (1266 px focal length on 1600x900
    images resized to the network width and cropped at the top)."""
    h, w = image_size
    to_ego = torch.tensor([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])  # camera (x right, y down, z fwd) -> ego
    rots, trans = [], []
    for yaw_deg in (55, 0, -55, 110, 180, -110)[:num_cameras]:
        a = math.radians(yaw_deg)
        yaw = torch.tensor([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1.0]])
        rots.append(yaw @ to_ego)
        trans.append(torch.tensor([math.cos(a), 0.5 * math.sin(a), 1.6]))
    scale = w / 1600
    batch = {
        "images": torch.randn(1, num_cameras, 3, h, w),
        "intrinsics": torch.tensor([[1266.0, 0, 800], [0, 1266, 450], [0, 0, 1]]).expand(1, num_cameras, 3, 3),
        "cam_to_ego_rot": torch.stack(rots)[None],
        "cam_to_ego_trans": torch.stack(trans)[None],
        "post_rot": torch.diag(torch.tensor([scale, scale, 1.0])).expand(1, num_cameras, 3, 3),
        "post_tran": torch.tensor([0.0, h - 900 * scale, 0]).expand(1, num_cameras, 3),
        "ground_height": torch.zeros(1),
    }
    return {k: v.to(device) for k, v in batch.items()}


def _median_ms(fn: Callable[[], object], runs: int, sync: Callable[[], None], warmup: int) -> float:
    return 1000 * statistics.median(time_runs(fn, runs, warmup, sync))


@torch.inference_mode()
def time_components(model, batch: dict, runs: int, sync: Callable[[], None], warmup: int = 1) -> dict[str, float]:
    """Median milliseconds per component and for the whole forward."""
    images = batch["images"]
    B, V = images.shape[:2]
    calib = {k: batch[k] for k in CALIBRATION_KEYS}
    gh = model.graph_head
    # Intermediate results, computed once, feed the next component's timing.
    features = model.backbone(images.flatten(0, 1)).unflatten(0, (B, V))
    bev = model.view_transform(features, calib)
    heads = model.bev_heads(bev)
    vertices = gh.extract(heads["pred_vertex_logits"])
    g = gh.gnn(gh.embed(vertices, heads["pred_distance"], heads["bev_features"]), vertices["mask"])

    def graph_network():
        out = gh.gnn(gh.embed(vertices, heads["pred_distance"], heads["bev_features"]), vertices["mask"])
        return F.log_softmax(gh.class_head(out), dim=-1)

    parts = {
        "backbone": lambda: model.backbone(images.flatten(0, 1)),
        "view transform": lambda: model.view_transform(features, calib),
        "BEV heads": lambda: model.bev_heads(bev),
        "vertex extraction": lambda: gh.extract(heads["pred_vertex_logits"]),
        "embedding + GNN": graph_network,
        "Sinkhorn (+ match head)": lambda: gh.match(g, vertices["mask"]),
        "total forward": lambda: model(batch),
    }
    return {name: _median_ms(fn, runs, sync, warmup) for name, fn in parts.items()}


def time_interleaved(fns: dict[str, Callable[[], object]], runs: int, warmup: int,
                     sync: Callable[[], None]) -> dict[str, list[float]]:
    """Seconds per call of each function, called in turn: ``warmup`` untimed rounds, then ``runs``
    timed ones (each round calls every function once, in order), so that a change of the machine's
    load during the run hits every function alike."""
    with torch.inference_mode():
        for _ in range(warmup):
            for fn in fns.values():
                fn()
        times: dict[str, list[float]] = {name: [] for name in fns}
        for _ in range(runs):
            for name, fn in fns.items():
                sync()
                start = time.perf_counter()
                fn()
                sync()
                times[name].append(time.perf_counter() - start)
    return times


def _table(columns: dict[str, dict[str, float]], official: dict[str, dict[str, float]] | None = None) -> str:
    names = list(next(iter(columns.values())))
    width = max(len(n) for n in [*names, "ours int8+cb / official forward"]) + 2
    cw = max(22, *(len(c) + 2 for c in columns))
    lines = [f"{'ms (median)':<{width}}" + "".join(f"{c:>{cw}}" for c in columns)]
    lines += [f"{n:<{width}}" + "".join(f"{col[n]:>{cw}.1f}" for col in columns.values()) for n in names]
    if official:
        ours = [k for k in next(iter(official.values())) if k.startswith("ours ")]
        rows = [(f"{k} + decoding, interleaved", k) for k in ours] + [("official forward, interleaved", "official")]
        for label, key in rows:
            lines.append(f"{label:<{width}}" + "".join(f"{official[c][key]:>{cw}.1f}" for c in official))
        for key in ours:
            lines.append(f"{key + ' / official forward':<{width}}"
                         + "".join(f"{official[c][key] / official[c]['official']:>{cw}.3f}" for c in official))
        lines.append(f"{'official parameters':<{width}}"
                     + "".join(f"{official[c]['params_m']:>{cw - 1}.2f}M" for c in official))
    return "\n".join(lines)


def _components(model, precision: str, batch: dict, runs: int) -> dict[str, float]:
    """The component table of ``model`` as ``precision`` runs it (bf16, int8: the wrapped inference copy under
    autocast, as ``Bf16Model.forward`` runs it)."""
    if precision == "fp32":
        return time_components(model, batch, runs, lambda: None)
    bf16 = getattr(model, "bf16", True)  # int8's float part: bf16 where the CPU computes it natively, else float32
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
        return time_components(model.model, batch, runs, lambda: None)


def run_cpu(args: argparse.Namespace) -> None:
    torch.set_num_threads(args.threads)
    reused = reuse_freed_memory()  # as inference runs (precision.with_precision), for every model timed here
    code = None
    if args.official:
        from official import build_official, load_official, official_inputs, uses_standins

        code = load_official(args.official)
    cpu = torch.device("cpu")
    asked = args.precision
    if asked is None:  # the default: bf16 only where it is native (emulated, one forward of B4 takes seconds)
        asked = ["fp32", "bf16", "int8"]
        if not native_bf16(cpu):
            asked.remove("bf16")
            print("this CPU has no native bfloat16: bf16 left out (--precision bf16 to time it emulated)")
    precisions = [resolve_precision(p, cpu, flag="--precision")[0] for p in asked]
    columns, official = {}, {}
    for path in args.configs or CPU_CONFIGS:
        cfg = load_config(path)
        fp32 = build_model(cfg).eval()
        name = cfg.model.backbone.name
        batch = example_batch(cfg.data.image_size, cpu)
        # int8 calibrates on the timed batch (random weights and images: only its speed is measured here)
        def as_run(p: str, model=fp32, batch=batch):
            return with_precision(model, p, [batch] if p == "int8" else None)

        models = {p: as_run(p) for p in dict.fromkeys(precisions)}
        if args.compile_backbone:  # each precision again with its backbone compiled (compiles in the warm-up call)
            models.update({f"{p}+cb": compile_backbone(as_run(p)) for p in dict.fromkeys(precisions)})
        for p, model in models.items():
            columns[f"{name} {p}"] = _components(model, p.removesuffix("+cb"), batch, args.runs)
        if code is not None:
            grid = BEVGrid.from_config(cfg.grid)
            decode = decode_options(cfg.model.gnn, grid)
            theirs = build_official(code, name, tuple(cfg.data.image_size)).eval()
            inputs = official_inputs(batch)
            fns = {f"ours {p}": (lambda m=m, b=batch, g=grid, d=decode: postprocess_batch(m(b), g, **d))
                   for p, m in models.items()}
            fns["official"] = lambda m=theirs, x=inputs: m(*x)
            times = time_interleaved(fns, args.runs, 1, lambda: None)
            official[name] = {k: 1000 * statistics.median(v) for k, v in times.items()}
            official[name]["params_m"] = sum(p.numel() for p in theirs.parameters()) / 1e6
    print(f"CPU, {args.threads} threads, batch 1 x 6 cameras, LSS, {args.runs} runs, torch {torch.__version__}, "
          f"load average {os.getloadavg()[0]:.1f} at the end; {cpu_capability()}; freed memory "
          f"{'kept for reuse' if reused else 'returned (not glibc)'}")
    if code is not None:
        standins = uses_standins()
        print(f"official code: {code.root}, fp32" + (f" (stand-ins for {', '.join(standins)}: benchmarks/official.py)"
                                                      if standins else ""))
    print(_table(columns, official or None))


def run_gpu(args: argparse.Namespace) -> None:
    device = torch.device(args.device)
    sync = torch.cuda.synchronize
    print(f"GPU {torch.cuda.get_device_name(device)}, batch 1 x 6 cameras, {args.runs} runs; host CPU: "
          f"{cpu_capability()}")
    rows = []
    for path in args.configs or GPU_CONFIGS:
        cfg = load_config(path)
        model = build_model(cfg).eval().to(device)
        batch = example_batch(cfg.data.image_size, device)
        label = f"{cfg.model.backbone.name} {cfg.data.image_size[0]}x{cfg.data.image_size[1]}"
        for precision in ("fp32", "bf16"):
            with torch.autocast("cuda", dtype=torch.bfloat16, enabled=precision == "bf16"):
                parts = time_components(model, batch, args.runs, sync, warmup=5)
            rows.append((label, precision, parts))
    width = max(len(r[0]) for r in rows) + 2
    short = ["backbone", "view", "BEV heads", "vertices", "GNN", "Sinkhorn", "total"]
    print("ms (median)")
    print(f"{'model':<{width}}{'prec':>6}" + "".join(f"{n:>11}" for n in short) + f"{'FPS':>8}")
    for label, precision, parts in rows:
        print(f"{label:<{width}}{precision:>6}" + "".join(f"{t:>11.2f}" for t in parts.values())
              + f"{1000 / parts['total forward']:>8.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu", help="cpu or cuda[:i]")
    parser.add_argument("--threads", type=int, default=2, help="CPU threads (torch.set_num_threads)")
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--configs", nargs="*", help="experiment YAMLs (default: the Table I LSS rows)")
    parser.add_argument("--precision", nargs="+", choices=PRECISIONS,
                        help="CPU: the precisions of our model to time (precision.py; default fp32 bf16 int8, "
                             "bf16 only where the CPU computes it natively)")
    parser.add_argument("--compile-backbone", action="store_true",
                        help="CPU: also time each precision with its image backbone compiled (compile_backbone; "
                             "'+cb' in the column names; each compiles in its warm-up call, tens of seconds)")
    parser.add_argument("--official", metavar="DIR",
                        help="a local checkout of the official InstaGraM code: time its model too (CPU only)")
    args = parser.parse_args()
    from instagram_hdmap.benchmark import check_counts

    check_counts(parser, args, threads=1, runs=1)
    if args.device.startswith("cuda"):
        if args.official:
            parser.error("--official times on the CPU only (the official model's forward is compared on --device cpu)")
        run_gpu(args)
    else:
        run_cpu(args)


if __name__ == "__main__":
    from instagram_hdmap.benchmark import script_main

    script_main(main)
