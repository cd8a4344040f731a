"""What the BEV memory costs: the fusion's share of the forward pass (batch 1, CPU by default).

    python benchmarks/temporal_speed.py                                   # Table I B0 LSS, nuScenes rig
    python benchmarks/temporal_speed.py model.temporal.memory=bev+graph   # with the graph memory
    python benchmarks/temporal_speed.py --config configs/temporal/av2_b0_lss_256x352.yaml --runs 30

Times, interleaved run by run so that a machine's load shifts all of them alike, under ``torch.no_grad``:
the single-frame model (``model.temporal.memory=none``), the same model with the memory
(``configs/temporal/nuscenes_b0_lss_128x352.yaml``, a valid memory of the previous frame 1.5 m behind,
so the warp and the fusion run on real history), and the fusion module alone on the first-stage features
(``BEVMemoryFusion``: the warp, the gates, the new memory) and, for a graph memory, the drawing of the
frame's predicted graph (``render_graph``). Prints the medians (p10-p90) and the two
shares: (temporal - single) / single and fusion alone / single (budget: <= 10 %).
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]


def timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def main() -> None:
    from instagram_hdmap.config import UserError, load_config
    from instagram_hdmap.deploy import example_inputs
    from instagram_hdmap.models import build_model

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--config", default=str(REPO / "configs" / "temporal" / "nuscenes_b0_lss_128x352.yaml"))
    p.add_argument("--runs", type=int, default=20)
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, help="torch threads (default: torch's)")
    p.add_argument("override", nargs="*", help="config overrides (key=value)")
    args = p.parse_args()
    from instagram_hdmap.benchmark import check_counts

    check_counts(p, args, runs=1, warmup=0, threads=1)
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    cfg = load_config(args.config, ["model.backbone.grad_checkpoint=false", *args.override])
    if cfg.model.temporal.memory == "none":  # a UserError: one line and exit 2, as a wrong flag (was exit 1)
        raise UserError(f"{args.config}: model.temporal.memory is none; give a temporal config (or "
                        "model.temporal.memory=bev)")
    single_cfg = load_config(args.config, ["model.backbone.grad_checkpoint=false", *args.override,
                                           "model.temporal.memory=none"])
    torch.manual_seed(0)
    temporal = build_model(cfg).to(device).eval()
    single = build_model(single_cfg).to(device).eval()
    single.load_state_dict({k: v for k, v in temporal.state_dict().items() if not k.startswith("temporal.")})
    batch = {k: v.to(device) for k, v in example_inputs(cfg).items()}
    batch.update(ego_pose=torch.eye(4, device=device)[None], frame_index=torch.ones(1, dtype=torch.long, device=device),
                 scene_start=torch.zeros(1, dtype=torch.bool, device=device))
    memory = temporal.initial_memory(1, batch["images"])
    memory["valid"][:] = True
    memory["ego_pose"][0, 0, 3] = -1.5
    memory["bev"].normal_()
    first = torch.randn(1, temporal.temporal.channels, *temporal.temporal.size, device=device)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)

    def run(fn):
        def go():
            fn()
            sync()
        return go

    jobs = {"single-frame model": run(lambda: single(batch)),
            "temporal model": run(lambda: temporal(batch, memory=memory)),
            "fusion alone": run(lambda: temporal.temporal(first, batch, memory))}
    with torch.no_grad():
        outputs = temporal(batch, memory=memory)
    if temporal.temporal.graph_channels:  # a graph memory: drawing this frame's graph for the next one
        jobs["graph raster"] = run(lambda: temporal.temporal.remember_graph({"bev": None}, outputs))
    times: dict[str, list[float]] = {k: [] for k in jobs}
    status = int(outputs["memory_status"].item())
    if status != 0:  # an assert: a raw AssertionError, and under python -O the timings of a model that fuses nothing
        from instagram_hdmap.models.temporal import STATUS_NAMES

        raise UserError(f"{args.config}: the memory of the previous frame (1.5 m behind, not turned) is not fused "
                        f"(status {STATUS_NAMES[status]}): model.temporal.max_jump_m="
                        f"{cfg.model.temporal.max_jump_m} (or another override) rules it out, and the timings "
                        "would be those of a model that skips the fusion; raise it above 1.5")
    with torch.no_grad():
        for _ in range(args.warmup):
            for fn in jobs.values():
                fn()
        for _ in range(args.runs):
            for name, fn in jobs.items():
                times[name].append(timed(fn))
    med = {k: statistics.median(v) for k, v in times.items()}
    print(f"{cfg.name}: batch 1, {device}, {torch.get_num_threads()} thread(s), {args.runs} interleaved runs; "
          f"fusion on {temporal.temporal.channels} x {temporal.temporal.size[0]} x {temporal.temporal.size[1]} "
          f"({cfg.model.temporal.fusion}, kernel {cfg.model.temporal.kernel}, {cfg.model.temporal.memory} memory)")
    for name, v in times.items():
        # inclusive: the default ("exclusive") extrapolates beyond the runs (a p10 of -126 ms out of 3 runs); one run
        # has no quantiles (a raw StatisticsError after the work)
        q = statistics.quantiles(v, n=10, method="inclusive") if len(v) > 1 else [v[0], v[0]]
        print(f"  {name:<20}{1000 * med[name]:9.2f} ms  (p10 {1000 * q[0]:.2f}, p90 {1000 * q[-1]:.2f})")
    base = med["single-frame model"]
    print(f"  temporal - single: {100 * (med['temporal model'] - base) / base:+.1f} % of the single-frame forward")
    own = med["fusion alone"] + med.get("graph raster", 0.0)
    print(f"  fusion alone{' + raster' if 'graph raster' in med else ''}: {100 * own / base:.1f} % of the "
          "single-frame forward (budget 10 %)")


if __name__ == "__main__":
    from instagram_hdmap.benchmark import script_main

    script_main(main)
