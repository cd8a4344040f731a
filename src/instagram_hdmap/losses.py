"""The criterion (DETR's SetCriterion pattern): named raw losses, a weight dict, the total in one place.

Shapes: B batch, K classes, H x W BEV grid, S cell size, Hc x Wc = H/S x W/S, N padded predicted
vertices. Terms (paper Eqs. 5-9):

``loss_vertex``     Eq. 5: cross-entropy of ``pred_vertex_logits`` [B, S*S+1, Hc, Wc] against
                    ``gt_vertex_cells`` [B, Hc, Wc], mean over all B*Hc*Wc cells.
``loss_distance``   Eq. 5: squared error of ``pred_distance`` [B, K, H, W] against ``gt_distance``,
                    mean over all B*K*H*W pixels.
``loss_adjacency``  Eq. 7: bidirectional NLL on ``pred_log_assignment`` [B, N+1, N+1]. For every real
                    predicted vertex i the forward target column ``target_next[i]`` and the backward
                    target column ``target_prev[i]`` (both in [0, N], N = dustbin; assignment.py)
                    are supervised in row i: ``-log A[i, next(i)] - log A[i, prev(i)]``, which is
                    Eq. 7's sum over M and M^T (an entry (j, i) of M^T is the row-j entry pointing
                    back to j's predecessor i). Normalisation: each direction's sum is divided by
                    the sample's number of real predicted vertices and the two directions are
                    *added*; samples are averaged (a sample without real vertices adds 0). This is
                    the normalisation of the official implementation (mean NLL forward + mean NLL
                    backward, mean over the batch), under which lambda_3 = 5e-3 was tuned; it
                    equals Eq. 7 x 2 / N_real. Without a 1/N normalisation (a plain sum), the term
                    would scale with the vertex count (~400) and lambda_3 would mean something else.
                    The dustbin row N is not supervised (as in the official code). Unlike the
                    official code, a sample without GT still trains all its vertices to the dustbin.
``loss_class``      Eq. 8: NLL of ``pred_class_log_probs`` [B, N, K] at the class of sigma(i), over
                    the predicted vertices matched within D0 (``loss.class_targets=nearest``: over
                    every real predicted vertex, at the class of its nearest GT vertex, as the
                    official code); mean per sample, mean over samples (a sample without such
                    vertices adds 0).
``loss_distance`` is absent when the model has no distance head (``with_distance=False``).

``weight_dict`` holds lambda_1..4 (``loss.*_weight``); the output has each raw term, each weighted
term (``loss_<name>_weighted``) and ``loss_total`` = the sum of the weighted terms (Eq. 9). Logging
diagnostics (detached, names without the ``loss_`` prefix): ``adjacency_accuracy`` (fraction of
the predicted vertices that represent a GT vertex whose two best columns of their assignment row are
exactly their targets {next, prev}; at a polyline end one of them is the dustbin; where next == prev,
e.g. both the dustbin, the best column must be it), ``adjacency_accuracy_all`` (the same over all
real predicted vertices, most of which should go to the dustbin early on), ``class_accuracy`` (argmax
class over matched vertices), ``num_pred_vertices`` (mean per sample), ``matched_fraction`` (real
predicted vertices within D0 of a GT vertex), ``gt_vertex_recall`` (real GT vertices with a
representative).

The assignment (assignment.py) runs under ``torch.no_grad``, inside ``forward`` unless precomputed
and passed in. All terms are computed in float32 (safe under autocast).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .assignment import IGNORE_INDEX, assign_batch
from .config import LossConfig
from .geometry import BEVGrid, as_grid

REQUIRED_OUTPUTS = (
    "pred_vertex_logits", "pred_distance", "pred_vertices_px", "pred_vertex_mask",
    "pred_class_log_probs", "pred_log_assignment",
)
REQUIRED_TARGETS = ("gt_vertex_cells", "gt_distance")


def _per_sample_mean(values: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """values, valid [B, N] -> [B]: mean of the valid entries of each row (0 where none)."""
    total = torch.where(valid, values, torch.zeros_like(values)).sum(1)
    return total / valid.sum(1).clamp(min=1).to(values.dtype)


def adjacency_nll(log_assignment: torch.Tensor, target_next: torch.Tensor, target_prev: torch.Tensor
                  ) -> torch.Tensor:
    """Bidirectional adjacency NLL per sample (module docstring): [B, N+1, N+1], [B, N], [B, N] -> [B].

    Entries of ``target_*`` equal to IGNORE_INDEX (padding) are skipped.
    """
    N = target_next.shape[1]
    rows = log_assignment[:, :N].float()  # [B, N, N+1], the dustbin row is not supervised
    valid = target_next != IGNORE_INDEX
    nll = torch.zeros((), device=rows.device, dtype=rows.dtype)
    for target in (target_next, target_prev):
        picked = rows.gather(2, target.clamp(min=0)[..., None])[..., 0]  # [B, N]
        nll = nll + _per_sample_mean(-picked, valid)
    return nll


def class_nll(class_log_probs: torch.Tensor, target_class: torch.Tensor) -> torch.Tensor:
    """Vertex class NLL per sample: [B, N, K], [B, N] (IGNORE_INDEX skipped) -> [B]."""
    valid = target_class != IGNORE_INDEX
    picked = class_log_probs.float().gather(2, target_class.clamp(min=0)[..., None])[..., 0]
    return _per_sample_mean(-picked, valid)


@torch.no_grad()
def adjacency_correct(log_assignment: torch.Tensor, pred_vertex_mask: torch.Tensor,
                      target_next: torch.Tensor, target_prev: torch.Tensor) -> torch.Tensor:
    """[B, N] bool: the two best columns of row i (padded columns excluded) are exactly {next, prev}
    (the best one is the target when next == prev, e.g. an isolated vertex -> dustbin)."""
    B, N = target_next.shape
    if N == 0:
        return torch.zeros(B, 0, dtype=torch.bool, device=target_next.device)
    col_ok = torch.cat([pred_vertex_mask.bool(), pred_vertex_mask.new_ones(B, 1, dtype=torch.bool)], 1)
    rows = log_assignment[:, :N].float().masked_fill(~col_ok[:, None, :], -torch.inf)
    top = rows.topk(2, dim=2).indices  # [B, N, 2]; N+1 >= 2 columns
    t0, t1 = top[..., 0], top[..., 1]
    same = target_next == target_prev
    two = ((t0 == target_next) & (t1 == target_prev)) | ((t0 == target_prev) & (t1 == target_next))
    return torch.where(same, t0 == target_next, two)


class Criterion(nn.Module):
    """``Criterion(cfg.loss, grid)(outputs, batch) -> dict`` of named losses and diagnostics."""

    def __init__(self, cfg: LossConfig, grid: BEVGrid, *, with_distance: bool = True):
        super().__init__()
        if not isinstance(cfg, LossConfig) and isinstance(getattr(cfg, "loss", None), LossConfig):
            cfg = cfg.loss  # a whole config: a raw AttributeError 'vertex_weight'
        if not isinstance(cfg, LossConfig):
            raise TypeError(f"Criterion takes cfg.loss (a LossConfig) or a config, got {type(cfg).__name__}")
        self.cfg = cfg
        self.grid = as_grid(grid, "Criterion")
        # with_distance=False (model.bev_heads.distance_head=false): no loss_distance term at all
        self.with_distance = with_distance
        terms = ("vertex", "distance", "adjacency", "class") if with_distance else ("vertex", "adjacency", "class")
        self.weight_dict = {f"loss_{t}": getattr(cfg, f"{t}_weight") for t in terms}

    def assign(self, outputs: dict, batch: dict) -> dict[str, torch.Tensor]:
        """The graph targets for these outputs (no autograd), see assignment.py."""
        return assign_batch(outputs, batch, self.grid, self.cfg.match_dist, self.cfg.skip_missed_vertices,
                            match_space=self.cfg.match_space, class_targets=self.cfg.class_targets)

    def forward(self, outputs: dict, batch: dict, assignment: dict | None = None) -> dict[str, torch.Tensor]:
        skip = () if self.with_distance else ("pred_distance", "gt_distance")
        missing = [k for k in REQUIRED_OUTPUTS if k not in outputs and k not in skip]
        missing += [k for k in REQUIRED_TARGETS if k not in batch and k not in skip]
        if missing:
            raise KeyError(f"the criterion needs {missing}, missing from the model output / batch "
                           "(see docs/conventions.md)")
        B, N = outputs["pred_vertex_mask"].shape
        if outputs["pred_log_assignment"].shape != (B, N + 1, N + 1):
            raise ValueError(f"pred_log_assignment must be [B, N+1, N+1] = [{B}, {N + 1}, {N + 1}] for "
                             f"pred_vertex_mask [{B}, {N}], got {list(outputs['pred_log_assignment'].shape)}")
        if assignment is None:
            assignment = self.assign(outputs, batch)
        losses = {
            "loss_vertex": F.cross_entropy(outputs["pred_vertex_logits"].float(), batch["gt_vertex_cells"].long()),
            "loss_adjacency": adjacency_nll(outputs["pred_log_assignment"], assignment["target_next"],
                                            assignment["target_prev"]).mean(),
            "loss_class": class_nll(outputs["pred_class_log_probs"], assignment["target_class"]).mean(),
        }
        if self.with_distance:
            losses["loss_distance"] = F.mse_loss(outputs["pred_distance"].float(), batch["gt_distance"].float())
        out = dict(losses)
        for name, value in losses.items():
            out[f"{name}_weighted"] = value * self.weight_dict[name]
        out["loss_total"] = sum(out[f"{name}_weighted"] for name in losses)
        out.update(self._diagnostics(outputs, batch, assignment))
        return out

    @torch.no_grad()
    def _diagnostics(self, outputs: dict, batch: dict, assignment: dict) -> dict[str, torch.Tensor]:
        pred_mask = outputs["pred_vertex_mask"].bool()
        correct = adjacency_correct(outputs["pred_log_assignment"], pred_mask, assignment["target_next"],
                                    assignment["target_prev"])
        target_class = assignment["target_class"]

        def frac(hit: torch.Tensor, over: torch.Tensor) -> torch.Tensor:
            return (hit & over).sum().float() / over.sum().clamp(min=1).float()

        return {
            "adjacency_accuracy": frac(correct, assignment["pred_is_representative"]),
            "adjacency_accuracy_all": frac(correct, pred_mask),
            "class_accuracy": frac(outputs["pred_class_log_probs"].argmax(2) == target_class,
                                   target_class != IGNORE_INDEX),
            "num_pred_vertices": pred_mask.sum(1).float().mean(),
            "matched_fraction": frac(assignment["pred_to_gt"] >= 0, pred_mask),
            "gt_vertex_recall": frac(assignment["gt_to_pred"] >= 0, batch["gt_vertex_mask"].bool()),
        }
