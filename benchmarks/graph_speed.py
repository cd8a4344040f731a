"""Speed of the graph supervision and decoding hot paths: assignment, criterion, post-processing.

Realistic sizes: N = 400 predicted vertices, ~30 GT instances of ~10 vertices (M ~ 300 padded to
320), paper grid (200 x 400 BEV, S = 8). Predictions: noisy copies of the GT vertices plus spurious
ones; graph head output: the bidirectional target distribution plus noise, so that decoding traces
real chains. Prints median milliseconds per call over ``--repeats`` runs.

    python benchmarks/graph_speed.py [--batch 1 8 32] [--device cpu|cuda] [--threads 2]

The last lines compare the classwise decoder (the demo's settings) with its targets: <= 2 ms
per sample at batch 1, <= 40 ms for a batch of 32 on the CPU.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from instagram_hdmap.assignment import assign_batch, target_log_assignment
from instagram_hdmap.config import GridConfig, LossConfig
from instagram_hdmap.geometry import BEVGrid
from instagram_hdmap.losses import Criterion
from instagram_hdmap.postprocess import postprocess_batch


def make_batch(B: int, N: int, grid: BEVGrid, device: torch.device, seed: int = 0) -> tuple[dict, dict]:
    rng = np.random.default_rng(seed)
    M = 320
    K, S = 3, grid.cell_size
    batch = {
        "gt_vertices_px": torch.zeros(B, M, 2), "gt_vertex_mask": torch.zeros(B, M, dtype=torch.bool),
        "gt_vertex_labels": torch.zeros(B, M, dtype=torch.long),
        "gt_vertex_next": torch.full((B, M), -1, dtype=torch.long),
        "gt_vertex_prev": torch.full((B, M), -1, dtype=torch.long),
    }
    for b in range(B):
        k = 0
        for _ in range(30):
            P = int(rng.integers(4, 16))
            start = rng.uniform([0, 0], [grid.W, grid.H])
            step = rng.normal(0, 1, 2)
            step = step / np.linalg.norm(step) * 10  # 1.5 m spacing at 0.15 m / px
            pts = start + step * np.arange(P)[:, None] + rng.normal(0, 1.5, (P, 2)).cumsum(0)
            if k + P > M:
                break
            idx = torch.arange(k, k + P)
            batch["gt_vertices_px"][b, idx] = torch.as_tensor(pts, dtype=torch.float32)
            batch["gt_vertex_mask"][b, idx] = True
            batch["gt_vertex_labels"][b, idx] = int(rng.integers(0, K))
            batch["gt_vertex_next"][b, idx[:-1]] = idx[1:]
            batch["gt_vertex_prev"][b, idx[1:]] = idx[:-1]
            k += P
    pred = torch.as_tensor(rng.uniform(0, [grid.W, grid.H], (B, N, 2)), dtype=torch.float32)
    for b in range(B):
        m = int(batch["gt_vertex_mask"][b].sum())
        n = min(m, int(0.75 * N))
        pred[b, :n] = batch["gt_vertices_px"][b, :n] + torch.as_tensor(rng.normal(0, 2, (n, 2)), dtype=torch.float32)
    mask = torch.as_tensor(rng.random((B, N)) < 0.95)
    batch["gt_vertex_cells"] = torch.randint(0, S * S + 1, (B, grid.Hc, grid.Wc))
    batch["gt_distance"] = torch.rand(B, K, grid.H, grid.W) * 10
    outputs = {
        "pred_vertex_logits": torch.randn(B, S * S + 1, grid.Hc, grid.Wc),
        "pred_distance": torch.rand(B, K, grid.H, grid.W) * 10,
        "pred_vertices_px": pred, "pred_vertex_mask": mask,
        "pred_vertex_scores": torch.rand(B, N) * mask,
        "pred_class_log_probs": torch.randn(B, N, K).log_softmax(-1),
    }
    batch = {k: v.to(device) for k, v in batch.items()}
    outputs = {k: v.to(device) for k, v in outputs.items()}
    asg = assign_batch(outputs, batch, grid, 1.5)
    logA = target_log_assignment(asg["target_next"], asg["target_prev"], floor=1e-3)
    outputs["pred_log_assignment"] = (logA + 0.3 * torch.randn_like(logA)).log_softmax(-1)
    return outputs, batch


def timed(fn, repeats: int, device: torch.device) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, nargs="+", default=[1, 8, 32])
    parser.add_argument("--vertices", type=int, default=400)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--repeats", type=int, default=10)
    args = parser.parse_args()
    from instagram_hdmap.benchmark import check_counts

    check_counts(parser, args, batch=1, vertices=1, threads=1, repeats=1)
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    grid = BEVGrid.from_config(GridConfig())
    crit = Criterion(LossConfig(), grid)
    print(f"device {device}, torch threads {torch.get_num_threads()}, N = {args.vertices}, "
          f"median of {args.repeats} (ms per call)")
    decoders = {"mutual": {"decoder": "mutual", "match_threshold": 0.1},
                "greedy": {"decoder": "greedy", "match_threshold": 0.1},
                "classwise": {"decoder": "classwise", "match_threshold": 0.02, "class_min_prob": 0.05,
                              "max_edge_px": 2.5 / grid.resolution}}
    print(f"{'B':>4} | {'assign':>8} | {'criterion fwd':>13} | {'criterion fwd+bwd':>17} | "
          + " | ".join(f"{'post ' + name:>14}" for name in decoders) + f" | {'instances/sample (greedy)':>25}")
    classwise = {}
    for B in args.batch:
        outputs, batch = make_batch(B, args.vertices, grid, device)

        def fwd_bwd(outputs=outputs, batch=batch):
            leaf = {k: (v.detach().requires_grad_(True) if v.is_floating_point() and k != "pred_vertices_px"
                        else v) for k, v in outputs.items()}
            crit(leaf, batch)["loss_total"].backward()

        t_assign = timed(lambda o=outputs, b=batch: assign_batch(o, b, grid, 1.5), args.repeats, device)
        t_fwd = timed(lambda o=outputs, b=batch: crit(o, b), args.repeats, device)
        t_bwd = timed(fwd_bwd, args.repeats, device)
        t_post = [timed(lambda o=outputs, d=d: postprocess_batch(o, grid, **d), args.repeats, device)
                  for d in decoders.values()]
        n_inst = sum(len(s) for s in postprocess_batch(outputs, grid, **decoders["greedy"])) / B
        classwise[B] = t_post[list(decoders).index("classwise")]
        print(f"{B:>4} | {t_assign:>8.2f} | {t_fwd:>13.2f} | {t_bwd:>17.2f} | "
              + " | ".join(f"{t:>14.2f}" for t in t_post) + f" | {n_inst:>25.1f}")
    for B, target in ((1, 2.0), (32, 40.0)):
        if B in classwise:
            print(f"classwise post-processing, batch {B}: {classwise[B]:.2f} ms ({classwise[B] / B:.2f} ms per sample; "
                  f"target <= {target:g} ms): {'met' if classwise[B] <= target else 'NOT met'}")


if __name__ == "__main__":
    from instagram_hdmap.benchmark import script_main

    script_main(main)
