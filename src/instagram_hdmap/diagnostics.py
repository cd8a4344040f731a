"""Where a trained model fails, per class: vertex detection, distance transform, adjacency, instances.

Shapes: B batch, N padded predicted vertices, M padded GT vertices, K classes, H x W BEV grid.

``ClassDiagnostics`` accumulates, over batches of model outputs and their GT, per class k:

* ``vertex_recall``: GT vertices of class k that some predicted vertex represents (nearest within
  ``loss.match_dist``, assignment.py) / GT vertices of class k;
* ``vertex_precision``: predicted vertices whose argmax class is k and whose nearest GT vertex
  within ``match_dist`` has class k / predicted vertices of argmax class k;
* ``dt_error_px``: mean |predicted - GT distance| (BEV pixels) of channel k over the pixels within
  ``dt_clip`` of a class-k line (the band the distance transform describes); ``dt_line_recall``:
  GT line pixels of class k where the prediction is below 1 px;
* ``adjacency_accuracy``: predicted vertices representing a class-k GT vertex whose two best
  assignment columns are exactly their {next, prev} targets (losses.adjacency_correct);
* ``edge_recall``: target edges i -> next(i) between two representatives of class k that the
  decoded graph (post-processing's mutual neighbours) contains;
* ``instance_complete``: GT instances of class k with >= 2 represented vertices whose represented
  vertices all lie on one decoded path / cycle and nothing else; for closed GT shapes also
  ``closed_as_cycle``: such an instance decoded as a cycle (the polygon's closing edge found).

All counts are batched tensor code except the per-instance check, a loop over the decoded
components of each sample (tens per sample).
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import torch

from .assignment import IGNORE_INDEX, UNMATCHED
from .losses import adjacency_correct
from .postprocess import graph_options, neighbours, trace_instances

METRICS = ("vertex_recall", "vertex_precision", "dt_error_px", "dt_line_recall", "adjacency_accuracy",
           "edge_recall", "instance_complete", "closed_as_cycle")


class ClassDiagnostics:
    """``update(outputs, batch, assignment)`` per batch, then ``compute() -> {metric: [K floats]}``."""

    def __init__(self, num_classes: int, dt_clip: float, decode: dict | None = None):
        self.K = num_classes
        self.dt_clip = dt_clip
        # the post-processing's neighbour rule (postprocess.decode_options; default: greedy at 0.1), for edge
        # recall and instances
        self.graph = graph_options(decode or {"match_threshold": 0.1})
        self.hits: dict[str, np.ndarray] = defaultdict(lambda: np.zeros(num_classes))
        self.totals: dict[str, np.ndarray] = defaultdict(lambda: np.zeros(num_classes))

    def _add(self, name: str, hits: torch.Tensor, over: torch.Tensor, cls: torch.Tensor) -> None:
        """Count ``hits & over`` and ``over`` per class ``cls`` (all the same shape)."""
        c = cls[over].long().clamp(min=0).cpu()
        self.hits[name] += np.bincount(c[hits[over].cpu()].numpy(), minlength=self.K)[: self.K]
        self.totals[name] += np.bincount(c.numpy(), minlength=self.K)[: self.K]

    @torch.no_grad()
    def update(self, outputs: dict, batch: dict, assignment: dict) -> None:
        pred_mask = outputs["pred_vertex_mask"].bool()
        gt_mask = batch["gt_vertex_mask"].bool()
        gt_labels = batch["gt_vertex_labels"].long()
        B, N = pred_mask.shape
        # vertices
        self._add("vertex_recall", assignment["gt_to_pred"] >= 0, gt_mask, gt_labels)
        pred_cls = outputs["pred_class_log_probs"].argmax(2)
        pred_to_gt = assignment["pred_to_gt"]
        matched_cls = gt_labels.gather(1, pred_to_gt.clamp(min=0)) if gt_labels.shape[1] else pred_cls
        ok = (pred_to_gt != UNMATCHED) & (matched_cls == pred_cls)
        self._add("vertex_precision", ok, pred_mask, pred_cls)
        # distance transform (none without a distance head)
        pred_dt, gt_dt = outputs.get("pred_distance"), batch["gt_distance"].float()
        if pred_dt is not None:  # sums over (batch, H, W) per class channel
            band, line = gt_dt < self.dt_clip, gt_dt == 0
            err = torch.where(band, (pred_dt.float() - gt_dt).abs(), 0.0)
            for name, hits, over in (("dt_error_px", err, band), ("dt_line_recall", line & (pred_dt < 1.0), line)):
                self.hits[name] += hits.sum((0, 2, 3)).double().cpu().numpy()
                self.totals[name] += over.sum((0, 2, 3)).cpu().numpy()
        # adjacency (representatives of GT vertices of class k)
        rep = assignment["pred_is_representative"]
        rep_cls = gt_labels.gather(1, pred_to_gt.clamp(min=0)) if gt_labels.shape[1] else pred_cls
        correct = adjacency_correct(outputs["pred_log_assignment"], pred_mask,
                                    assignment["target_next"], assignment["target_prev"])
        self._add("adjacency_accuracy", correct, rep, rep_cls)
        graphs = neighbours(outputs, **self.graph)  # [B, G, N, 2]
        # the graph each vertex's instances come from: the one graph, or (classwise) its GT class's
        g = rep_cls.clamp(0, graphs.shape[1] - 1) if graphs.shape[1] > 1 else torch.zeros_like(rep_cls)
        nbr = graphs.gather(1, g[:, None, :, None].expand(B, 1, N, 2)).squeeze(1)  # [B, N, 2]
        tnext = assignment["target_next"]
        edge = rep & (tnext >= 0) & (tnext < N) & (tnext != IGNORE_INDEX)
        found = (nbr == tnext.clamp(min=0)[..., None]).any(2)
        self._add("edge_recall", found, edge, rep_cls)
        self._instances(graphs, assignment, batch)

    def _instances(self, graphs: torch.Tensor, assignment: dict, batch: dict) -> None:
        """Whole instances and closed cycles: GT instance of class k against graph k (classwise) or
        the one class-agnostic graph."""
        gt_to_pred = assignment["gt_to_pred"].cpu().numpy()
        inst = batch["gt_vertex_instance"].cpu().numpy()
        labels = batch["gt_vertex_labels"].cpu().numpy()
        gt_mask = batch["gt_vertex_mask"].cpu().numpy()
        closed_of = [[bool(p.get("closed", False)) for p in polys] for polys in batch["gt_polylines"]]
        graphs_l = graphs.cpu().tolist()
        for b in range(len(graphs_l)):
            comps = []  # per graph: predicted vertex -> (component id, is cycle, length)
            for rows in graphs_l[b]:
                comp = {}
                for cid, (path, closed) in enumerate(trace_instances([r[0] for r in rows], [r[1] for r in rows], 2)):
                    for i in path:
                        comp[i] = (cid, closed, len(path))
                comps.append(comp)
            for g_inst in np.unique(inst[b][gt_mask[b]]):
                sel = gt_mask[b] & (inst[b] == g_inst)
                preds = gt_to_pred[b][sel]
                preds = preds[preds >= 0]
                if len(preds) < 2:
                    continue
                k = int(labels[b][sel][0])
                comp = comps[min(k, len(comps) - 1)]
                found = {comp.get(int(i), (None, False, 0)) for i in preds}
                whole = len(found) == 1 and next(iter(found))[0] is not None and next(iter(found))[2] == len(preds)
                self.hits["instance_complete"][k] += whole
                self.totals["instance_complete"][k] += 1
                if closed_of[b][int(g_inst)] and len(preds) >= 3:
                    self.hits["closed_as_cycle"][k] += whole and next(iter(found))[1]
                    self.totals["closed_as_cycle"][k] += 1

    def compute(self) -> dict[str, list[float]]:
        out = {name: [float(h / t) if t > 0 else float("nan") for h, t in zip(self.hits[name], self.totals[name])]
               for name in METRICS}
        out["counts"] = {name: [int(v) for v in self.totals[name]] for name in METRICS}
        return out


def format_table(results: dict[str, dict], classes: list[str]) -> str:
    """``{row name: compute() result}`` -> a markdown table, one row per (name, class)."""
    head = "| model | class | " + " | ".join(METRICS) + " |"
    lines = [head, "|" + " --- |" * (len(METRICS) + 2)]
    for name, res in results.items():
        for k, c in enumerate(classes):
            cells = []
            for m in METRICS:
                v = res[m][k]
                cells.append("-" if v != v else (f"{v:.2f}" if m == "dt_error_px" else f"{v:.3f}"))
            lines.append(f"| {name} | {c} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
