"""InstaGraM: parts passed in, batch dict in, prediction dict out (docs/conventions.md)."""

from __future__ import annotations

import torch
from torch import nn

from .gnn import GraphHead
from .vertices import vertex_heatmap
from .view_transform import CALIBRATION_KEYS

INPUT_KEYS = ("images", *CALIBRATION_KEYS)


class InstaGraM(nn.Module):
    """images -> backbone -> view transform -> BEV heads -> graph head.

    Shapes: B batch, V cameras, h x w network input, S cell size, Hc x Wc cells, H x W BEV grid,
    K classes, N padded vertices.

    forward(batch) with ``images`` [B, V, 3, h, w] and the calibration (``intrinsics``,
    ``cam_to_ego_rot``, ``cam_to_ego_trans``, ``post_rot``, ``post_tran``) returns
      ``pred_vertex_logits`` [B, S*S+1, Hc, Wc], ``pred_heatmap`` [B, H, W],
      ``pred_distance`` [B, K, H, W] (absent without a distance head), ``pred_vertices_px`` [B, N, 2],
      ``pred_vertex_mask`` [B, N],
      ``pred_vertex_scores`` [B, N], ``pred_class_log_probs`` [B, N, K],
      ``pred_log_assignment`` [B, N+1, N+1] (float32).
    """

    def __init__(self, backbone: nn.Module, view_transform: nn.Module, bev_heads: nn.Module, graph_head: GraphHead):
        super().__init__()
        self.backbone = backbone
        self.view_transform = view_transform
        self.bev_heads = bev_heads
        self.graph_head = graph_head

    def forward(self, batch: dict) -> dict[str, torch.Tensor]:
        missing = [k for k in INPUT_KEYS if k not in batch]
        if missing:
            raise KeyError(f"InstaGraM.forward: the batch lacks {missing} (see docs/conventions.md)")
        images = batch["images"]
        B, V = images.shape[:2]
        features = self.backbone(images.flatten(0, 1)).unflatten(0, (B, V))  # [B, V, C, h/16, w/16]
        bev = self.view_transform(features, {k: batch[k] for k in CALIBRATION_KEYS})
        heads = self.bev_heads(bev)
        distance = heads.get("pred_distance")  # None without a distance head
        graph = self.graph_head(heads["pred_vertex_logits"], distance, heads["bev_features"])
        out = {
            "pred_vertex_logits": heads["pred_vertex_logits"],
            "pred_heatmap": vertex_heatmap(heads["pred_vertex_logits"], self.graph_head.grid.cell_size),
        }
        if distance is not None:
            out["pred_distance"] = distance
        return {**out, **graph}
