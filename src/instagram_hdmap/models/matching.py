"""Adjacency by optimal transport: score matrix and log-space Sinkhorn with a dustbin (plain functions).

Shapes: B batch, N padded vertices, D embedding dimension.

The score between vertices i and j is the scaled inner product <f_i, f_j> / sqrt(D) (Eq. 4). Self-loops
are excluded: the paper "forces the diagonal to zero" before the Sinkhorn; a zero *score* would still
give a self-loop a sizeable probability, so (as the official code does) the diagonal score is set to
``NEG_SCORE``, a finite stand-in for minus infinity: the self-loop probability is exactly 0 and no
``inf - inf`` can appear. Padded vertices are masked the same way, and the Sinkhorn marginals use the
number of real vertices of each sample, so padding never changes a real entry.
"""

from __future__ import annotations

import math

import torch

NEG_SCORE = -1e9  # log-space "minus infinity" that stays finite (exp() underflows to exactly 0)
# On the CPU, torch's exp() (MKL's vector math) takes 40-150x longer per element when the result
# underflows or is subnormal: exp(-95) 4.7 ms vs exp(0) 33 us for 150k floats, and
# torch.set_flush_denormal does not help; the gradient products of such tiny weights are subnormal
# too, and slow. A trained model's confident scores and the NEG_SCORE padding put most Sinkhorn
# entries there: a CPU training step doubled in time over a demo run. The CPU log-sum-exp therefore
# floors exp()'s argument (x - row max) at EXP_FLOOR: an entry e^30 = 1e13 times below the row's
# largest one adds at most N * 9.4e-14 to a sum >= 1 (float32 resolves 1.2e-7) and at most 9.4e-14
# to a gradient weight. benchmarks/sinkhorn_speed.py measures the difference.
EXP_FLOOR = -30.0
RIDGE = 1e-9  # relative ridge of the implicit backward's linear solve (float64)


def score_matrix(embeddings: torch.Tensor) -> torch.Tensor:
    """Matching embeddings [B, N, D] -> float32 scores [B, N, N], diagonal set to ``NEG_SCORE``
    (float32 also under autocast: in fp16, ``NEG_SCORE`` would become -inf)."""
    with torch.autocast(embeddings.device.type, enabled=False):
        embeddings = embeddings.float()
        scores = embeddings @ embeddings.transpose(1, 2) / math.sqrt(embeddings.shape[-1])
    eye = torch.eye(scores.shape[-1], dtype=torch.bool, device=scores.device)
    return scores.masked_fill(eye, NEG_SCORE)


def log_optimal_transport(scores: torch.Tensor, bin_score: torch.Tensor, mask: torch.Tensor, iters: int,
                          grad: str = "implicit") -> torch.Tensor:
    """SuperGlue's log-space optimal transport with a dustbin row and column, adapted to padding.

    scores [B, N, N], bin_score scalar tensor, mask [B, N] bool (True = real vertex), iters
    -> log assignment [B, N+1, N+1] float32 (row / column N = dustbin). With n real vertices in a
    sample, each real row and real column has mass 1 and the dustbins have mass n (SuperGlue's
    marginals with m = n), so ``exp()`` of a real row or column sums to 1. Padded rows and columns
    are finite and meaningless. Always float32, also under autocast.

    ``grad`` says how gradients flow back through the iterations (the forward values are the same):
    ``"unrolled"`` backpropagates through every iteration (SuperGlue, the official code: 2 x iters
    log-sum-exps kept for backward and replayed); ``"implicit"`` differentiates the fixed point
    instead (``_ImplicitSinkhorn``): one small linear solve per sample, a few percent of the time
    and none of the memory, equal to the unrolled gradient once the iterations have converged.
    """
    with torch.autocast(scores.device.type, enabled=False):
        scores = scores.float()
        B, N, _ = scores.shape
        bins = bin_score.float().expand(B, 1, 1)
        couplings = torch.cat(
            [torch.cat([scores, bins.expand(B, N, 1)], 2), torch.cat([bins.expand(B, 1, N), bins], 2)], 1
        )  # [B, N+1, N+1]
        valid = torch.cat([mask, mask.new_ones(B, 1)], 1)  # the dustbin is always real
        couplings = couplings.masked_fill(~(valid[:, :, None] & valid[:, None, :]), NEG_SCORE)
        n = mask.sum(1).float().clamp(min=1)  # [B] real vertices (>= 1 keeps an empty sample finite)
        norm = -(2 * n).log()  # [B]
        log_mu = torch.cat([norm[:, None].expand(B, N), (n.log() + norm)[:, None]], 1)  # [B, N+1]
        if torch.is_grad_enabled() and (couplings.requires_grad or bin_score.requires_grad):
            if grad == "implicit":
                return _ImplicitSinkhorn.apply(couplings, log_mu, valid, norm, iters)
            if grad != "unrolled":
                raise ValueError(f"grad must be 'implicit' or 'unrolled', got {grad!r}")
            u, v = _sinkhorn_potentials(couplings, log_mu, valid, iters)
        else:
            u, v = _sinkhorn_potentials_fast(couplings, log_mu, valid, iters)
        return couplings + u[:, :, None] + v[:, None, :] - norm[:, None, None]


class _FlooredLogSumExp(torch.autograd.Function):
    """``torch.logsumexp(x, dim)`` with exp()'s argument floored at ``EXP_FLOOR`` (see there); saves
    what torch's own saves for backward (input and result), so memory is unchanged."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, dim: int) -> torch.Tensor:
        peak = x.amax(dim=dim, keepdim=True)
        out = (x - peak).clamp_(min=EXP_FLOOR).exp_().sum(dim=dim, keepdim=True).log_().add_(peak)
        ctx.save_for_backward(x, out)
        ctx.dim = dim
        return out.squeeze(dim)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor, None]:
        x, out = ctx.saved_tensors
        return (x - out).clamp_(min=EXP_FLOOR).exp_().mul_(grad.unsqueeze(ctx.dim)), None


def _logsumexp(x: torch.Tensor, dim: int) -> torch.Tensor:
    """Differentiable log-sum-exp: floored on the CPU, ``torch.logsumexp`` elsewhere (a GPU's exp()
    has no slow path, and one more kernel per call would cost launch time)."""
    return _FlooredLogSumExp.apply(x, dim) if x.is_cpu else torch.logsumexp(x, dim=dim)


def _sinkhorn_potentials(couplings: torch.Tensor, log_mu: torch.Tensor, valid: torch.Tensor, iters: int
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """Row / column potentials u, v [B, N+1] (differentiable). Row and column marginals are equal."""
    u, v = torch.zeros_like(log_mu), torch.zeros_like(log_mu)
    for _ in range(iters):
        u = torch.where(valid, log_mu - _logsumexp(couplings + v[:, None, :], dim=2), NEG_SCORE)
        v = torch.where(valid, log_mu - _logsumexp(couplings + u[:, :, None], dim=1), NEG_SCORE)
    return u, v


@torch.no_grad()
def _sinkhorn_potentials_fast(couplings: torch.Tensor, log_mu: torch.Tensor, valid: torch.Tensor, iters: int
                             ) -> tuple[torch.Tensor, torch.Tensor]:
    """No-grad potentials by the fastest exact route: on the CPU the scaling form in float32 or float64
    (``_sinkhorn_potentials_scaling``), which falls back to the log-space iterations where the
    scores' range is too wide for it; on other devices, and while tracing or exporting, the
    log-space in-place iterations."""
    tracing = torch.jit.is_tracing() or torch.onnx.is_in_onnx_export() or torch.compiler.is_compiling()
    if couplings.is_cpu and not tracing:
        out = _sinkhorn_potentials_scaling(couplings, log_mu, valid, iters)
        if out is not None:
            return out
    return _sinkhorn_potentials_inplace(couplings, log_mu, valid, iters)


# The scaling form's float types by the span of a batch's scores (largest minus smallest real score of a sample;
# NEG_SCORE entries are exact zeros of K): within 80, K's entries (>= e^-80) are normal float32 numbers, and
# float32's iterates give the log-space potentials as closely as float64's (tested to a span of 76), with
# half-size matrices that make each product ~2x faster (the demo's CPU Sinkhorn 6.5 -> 3.6 ms; a trained demo
# model's samples span 27-72); within float64's exp() range, float64; beyond it, the log-space iterations.
SCALING_SPANS = ((80.0, torch.float32), (700.0, torch.float64))


@torch.no_grad()
def _sinkhorn_potentials_scaling(couplings: torch.Tensor, log_mu: torch.Tensor, valid: torch.Tensor, iters: int
                                ) -> tuple[torch.Tensor, torch.Tensor] | None:
    """The same iterations in Sinkhorn's original scaling form: with K = exp(C - max C) and scalings a, b,
    each half-iteration is a = mu / (K b) (resp. b = mu / (K^T a)): one matrix-vector product instead of a
    log-sum-exp with an exp() of the whole matrix, ~10x less CPU time. u = log a - max C, v = log b are the
    log-space potentials (same iterates). They run in float32 where the scores span at most 80, else in
    float64 (``SCALING_SPANS``); a float32 run that under- or overflows runs again in float64. Returns None
    when the float64 scalings under- or overflow too (scores spanning > ~700 in one sample); the caller then
    runs the log-space iterations.

    A padded vertex gets a 1 on K's diagonal, 0 elsewhere in its row and column, and marginal 1: its scalings
    stay 1 and never reach a real entry, so that each half-iteration is one product and one division."""
    real = valid[:, :, None] & valid[:, None, :] & (couplings > NEG_SCORE / 2)
    c = couplings.masked_fill(~real, -math.inf)
    span = (c.flatten(1).amax(1) - c.masked_fill(~real, math.inf).flatten(1).amin(1)).max()
    for limit, dtype in SCALING_SPANS:
        if span <= limit:
            out = _scaling_iterations(c.to(dtype), log_mu, valid, iters)
            if out is not None:
                return out
    return None


def _scaling_iterations(c: torch.Tensor, log_mu: torch.Tensor, valid: torch.Tensor, iters: int
                        ) -> tuple[torch.Tensor, torch.Tensor] | None:
    """``_sinkhorn_potentials_scaling``'s iterations in ``c``'s float type (c: the couplings, -inf where K is
    0); None where a scaling is not a finite normal number of that type (0, subnormal, inf or nan)."""
    dtype = c.dtype
    peak = c.flatten(1).amax(1).clamp(min=torch.finfo(dtype).min)[:, None, None]  # [B, 1, 1]
    kernel = (c - peak).exp() + torch.diag_embed((~valid).to(dtype))  # [B, N+1, N+1], 0 outside the valid block
    kernel_t = kernel.transpose(1, 2).contiguous()
    # row vectors [B, 1, N+1]: x^T M is MKL's fast batched product here (3x faster than M x)
    mu = torch.where(valid, log_mu.to(dtype).exp(), torch.ones_like(log_mu, dtype=dtype))[:, None, :]
    a, b, kb, ka = torch.ones_like(mu), torch.ones_like(mu), torch.empty_like(mu), torch.empty_like(mu)
    for _ in range(iters):
        torch.div(mu, torch.bmm(b, kernel_t, out=kb), out=a)  # (K b)^T = b^T K^T
        torch.div(mu, torch.bmm(a, kernel, out=ka), out=b)  # (K^T a)^T = a^T K
    a, b = a[:, 0], b[:, 0]
    tiny = torch.finfo(dtype).tiny
    ok = torch.where(valid, (a >= tiny) & torch.isfinite(a) & (b >= tiny) & torch.isfinite(b), True)
    if not bool(ok.all()):
        return None
    neg = torch.full_like(a, NEG_SCORE)
    u = torch.where(valid, a.log() - peak[:, 0], neg)
    v = torch.where(valid, b.log(), neg)
    return u.float(), v.float()


@torch.no_grad()
def _sinkhorn_potentials_inplace(couplings: torch.Tensor, log_mu: torch.Tensor, valid: torch.Tensor, iters: int
                                ) -> tuple[torch.Tensor, torch.Tensor]:
    """Same as ``_sinkhorn_potentials`` for inference: one reused buffer, in-place log-sum-exp, and a
    transposed copy so that both reductions run over contiguous memory (~1.5x faster on CPU)."""
    transposed = couplings.transpose(1, 2).contiguous()
    buf = torch.empty_like(couplings)
    floor = couplings.is_cpu  # EXP_FLOOR

    def row_logsumexp(matrix: torch.Tensor, potential: torch.Tensor) -> torch.Tensor:
        torch.add(matrix, potential[:, None, :], out=buf)
        peak = buf.amax(dim=2)
        buf.sub_(peak[:, :, None])
        if floor:
            buf.clamp_(min=EXP_FLOOR)
        buf.exp_()
        return buf.sum(dim=2).log_().add_(peak)

    u, v = torch.zeros_like(log_mu), torch.zeros_like(log_mu)
    for _ in range(iters):
        u = torch.where(valid, log_mu - row_logsumexp(couplings, v), NEG_SCORE)
        v = torch.where(valid, log_mu - row_logsumexp(transposed, u), NEG_SCORE)
    return u, v


class _ImplicitSinkhorn(torch.autograd.Function):
    """Log-space Sinkhorn whose backward differentiates the fixed point (implicit function theorem).

    Forward: the no-grad potentials (``_sinkhorn_potentials_inplace``), output
    ``Z = C + u 1^T + 1 v^T - norm``. With ``P = exp(C + u 1^T + 1 v^T)`` (marginals r = P 1, c = P^T 1
    over the real rows / columns), the fixed point F(u, v, C) = (P 1 - mu, P^T 1 - mu) = 0 has the
    symmetric Jacobian ``J = [[diag r, P], [P^T, diag c]]`` in (u, v), and dF/dC_kl puts P_kl in row k
    and in column l. For an upstream gradient G = dL/dZ with row sums g_r and column sums g_c, the
    adjoint (a, b) = J^-1 (g_r, g_c) gives

        dL/dC = G - (a 1^T + 1 b^T) * P.

    J is singular along the gauge (u + t, v - t); (g_r, g_c) is orthogonal to it once G is zero on
    entries with a padded row or column (meaningless outputs that no loss reads, and whose
    couplings are masked constants), so the Schur complement in b, regularised along the gauge,
    has a unique solution orthogonal to it: S b = g_c - P^T (g_r / r), S = diag c - P^T diag(1/r) P.
    Solved in float64 by Cholesky (S is positive semi-definite; + gauge + ridge, definite), size N+1 per sample.
    """

    @staticmethod
    def forward(ctx, couplings, log_mu, valid, norm, iters):
        u, v = _sinkhorn_potentials_fast(couplings.detach(), log_mu, valid, iters)
        z = couplings + u[:, :, None] + v[:, None, :] - norm[:, None, None]
        ctx.save_for_backward(z, valid, norm)
        return z

    @staticmethod
    def backward(ctx, grad):
        z, valid, norm = ctx.saved_tensors
        pair = valid[:, :, None] & valid[:, None, :]
        g = torch.where(pair, grad, torch.zeros_like(grad)).double()
        p = torch.where(pair, (z + norm[:, None, None]).double().exp(), torch.zeros_like(g))  # [B, N+1, N+1]
        fv = valid.double()
        # padded rows / columns: 1 (their a, b are 0). A real row whose every entry underflows
        # (iterations far from converged on extreme scores) has r = 0: clamped, P / r is 0, not 0 / 0
        tiny = torch.finfo(torch.float64).tiny
        r = torch.where(valid, p.sum(2).clamp(min=tiny), torch.ones_like(fv))
        c = torch.where(valid, p.sum(1).clamp(min=tiny), torch.ones_like(fv))
        g_r, g_c = g.sum(2), g.sum(1)
        schur = torch.diag_embed(c) - p.transpose(1, 2) @ (p / r[:, :, None])
        gauge = fv / fv.sum(1, keepdim=True).sqrt()  # unit vector along the gauge direction of b
        scale = c.mean(1, keepdim=True)[:, :, None]
        # + a ridge of RIDGE x c: a near-permutation plan makes S nearly singular beyond the gauge
        # (independent blocks, each with its own gauge, along which dL/dC does not change)
        schur = schur + scale * gauge[:, :, None] * gauge[:, None, :] + torch.diag_embed(RIDGE * c)
        rhs = g_c - (p.transpose(1, 2) @ (g_r / r)[:, :, None])[..., 0]
        # S + gauge + ridge is symmetric positive definite: Cholesky, not LU. (MKL's batched LU, after
        # some earlier work in the same process with 2 threads, returned garbage pivots on finite
        # matrices and lu_solve raised mid-training; its Cholesky gave the per-sample solution.)
        # A sample whose system is not finite (scores that overflowed upstream) or numerically not
        # positive definite gets b = 0, and below the direct gradient G where the correction is not finite.
        eye = torch.eye(schur.shape[-1], dtype=schur.dtype, device=schur.device)
        ok = torch.isfinite(schur).flatten(1).all(1) & torch.isfinite(rhs).all(1)  # [B]
        schur = torch.where(ok[:, None, None], schur, eye)
        chol, info = torch.linalg.cholesky_ex(schur)
        ok = ok & (info == 0)
        chol = torch.where(ok[:, None, None], chol, eye)
        rhs = torch.where(ok[:, None], rhs, torch.zeros_like(rhs))
        b = torch.cholesky_solve(rhs[..., None], chol)[..., 0]
        b = torch.where(torch.isfinite(b), b, torch.zeros_like(b)) * fv
        a = (g_r - (p @ b[:, :, None])[..., 0]) / r * fv
        dc = g - (a[:, :, None] + b[:, None, :]) * p
        dc = torch.where(torch.isfinite(dc), dc, g)
        return dc.to(grad.dtype), None, None, None, None
