"""CPU Sinkhorn (100 iterations, with dustbin) with and without the exp() floor, for a fresh model's
scores and a confident model's, as a table of milliseconds and ratios.

    python benchmarks/sinkhorn_speed.py [--batch 4] [--vertices 192] [--real 130] [--iters 100] [--runs 5]

Why: on the CPU, torch's exp() is 40-150x slower per element when its result underflows or is
subnormal (MKL's vector math), and the gradient products of such tiny weights are subnormal too.
A confident model's scores and the NEG_SCORE padding put most Sinkhorn entries there, so a demo
training step doubled in time over a run. ``models/matching.py`` floors exp()'s argument at
``EXP_FLOOR`` (below the row maximum); "no floor" here sets it to -inf, the arithmetic of
``torch.logsumexp``. Rows: the elementwise exp() cost by argument, then ``log_optimal_transport``
forward + backward (training) and under no_grad (inference), on scores scaled like a fresh model's
(spread 3) and a confident one's (spread 12), with ``--real`` of ``--vertices`` real vertices.

The last table compares the ways through the Sinkhorn (all floored): the unrolled backward through
the log-space iterations (SuperGlue's; ``model.gnn.sinkhorn_grad=unrolled``), the implicit backward
(``implicit``, the default) on the log-space forward, and on the CPU's float64 scaling-form forward
(the default on the CPU); under no_grad, the log-space vs the scaling-form iterations.
"""

from __future__ import annotations

import argparse
import statistics

import torch

from instagram_hdmap.benchmark import time_runs
from instagram_hdmap.models import matching
from instagram_hdmap.models.matching import log_optimal_transport, score_matrix


def _ms(fn, runs: int) -> float:
    return 1000 * statistics.median(time_runs(fn, runs=runs, warmup=1, sync=lambda: None))


def exp_rows(n: int, runs: int) -> list[tuple[str, float]]:
    rows = []
    for label, value in [("0", 0.0), ("-50", -50.0), ("-95 (subnormal result)", -95.0),
                         ("-120 (underflow)", -120.0), ("NEG_SCORE", matching.NEG_SCORE)]:
        x = torch.full((n,), value)
        rows.append((f"exp({label}) x {n}", _ms(x.exp, runs)))
    return rows


def sinkhorn_ms(batch: int, vertices: int, real: int, iters: int, spread: float, train: bool, runs: int,
                grad: str = "unrolled") -> float:
    gen = torch.Generator().manual_seed(0)
    emb = torch.randn(batch, vertices, 32, generator=gen) * spread
    mask = torch.arange(vertices)[None] < torch.full((batch, 1), real)
    bin_score = torch.tensor(1.0, requires_grad=True)

    def step():
        scores = score_matrix(emb.requires_grad_(train))
        if train:
            log_optimal_transport(scores, bin_score, mask, iters, grad=grad).sum().backward()
        else:
            with torch.no_grad():
                log_optimal_transport(scores, bin_score, mask, iters)

    return _ms(step, runs)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--vertices", type=int, default=192, help="N, padded vertices (demo config: 192)")
    p.add_argument("--real", type=int, default=130, help="real vertices per sample (a trained demo model: ~130)")
    p.add_argument("--iters", type=int, default=100)
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--threads", type=int, default=2)
    a = p.parse_args()
    from instagram_hdmap.benchmark import check_counts

    check_counts(p, a, batch=1, vertices=1, iters=1, runs=1, threads=1)
    if not 0 < a.real <= a.vertices:
        p.error(f"--real {a.real} must be in 1..--vertices {a.vertices}")
    torch.set_num_threads(a.threads)
    floor = matching.EXP_FLOOR
    print(f"CPU, {torch.get_num_threads()} threads, torch {torch.__version__}; B={a.batch}, N={a.vertices} "
          f"({a.real} real), {a.iters} iterations; EXP_FLOOR {floor}")
    print(f"\n{'elementwise':<34}{'ms':>9}")
    for label, ms in exp_rows(a.batch * (a.vertices + 1) ** 2, a.runs):
        print(f"{label:<34}{ms:>9.2f}")
    print(f"\n{'log_optimal_transport':<34}{'no floor ms':>12}{'floor ms':>10}{'ratio':>8}")
    for spread in (3.0, 12.0):
        for train in (True, False):
            times = []
            for value in (float("-inf"), floor):
                matching.EXP_FLOOR = value
                times.append(sinkhorn_ms(a.batch, a.vertices, a.real, a.iters, spread, train, a.runs))
            matching.EXP_FLOOR = floor
            kind = "fresh" if spread == 3.0 else "confident"
            label = f"{'fwd+bwd' if train else 'no_grad'}, {kind} (spread {spread:g})"
            print(f"{label:<34}{times[0]:>12.1f}{times[1]:>10.1f}{times[1] / times[0]:>7.2f}x")
    scaling = matching._sinkhorn_potentials_scaling
    print(f"\n{'ms (x unrolled log-space)':<34}{'unrolled':>12}{'implicit':>12}{'implicit+scaling':>18}")
    for spread in (3.0, 12.0):
        kind = "fresh" if spread == 3.0 else "confident"
        times = []
        for grad, use_scaling in (("unrolled", False), ("implicit", False), ("implicit", True)):
            matching._sinkhorn_potentials_scaling = scaling if use_scaling else (lambda *args: None)
            times.append(sinkhorn_ms(a.batch, a.vertices, a.real, a.iters, spread, True, a.runs, grad))
        matching._sinkhorn_potentials_scaling = scaling
        cells = "".join(f"{t:>8.1f} ({t / times[0]:.2f})" for t in times)
        print(f"{'fwd+bwd, ' + kind:<34}{cells}")
        nograd = []
        for use_scaling in (False, True):
            matching._sinkhorn_potentials_scaling = scaling if use_scaling else (lambda *args: None)
            nograd.append(sinkhorn_ms(a.batch, a.vertices, a.real, a.iters, spread, False, a.runs))
        matching._sinkhorn_potentials_scaling = scaling
        print(f"{'no_grad, ' + kind + ' (log / scaling)':<34}{nograd[0]:>12.1f}{'':>12}{nograd[1]:>10.1f} "
              f"({nograd[1] / nograd[0]:.2f})")
    return 0


if __name__ == "__main__":
    from instagram_hdmap.benchmark import script_main

    script_main(main)
