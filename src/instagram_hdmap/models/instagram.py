"""InstaGraM: parts passed in, batch dict in, prediction dict out (docs/conventions.md)."""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import nn

from .gnn import GraphHead
from .temporal import BEVMemoryFusion
from .vertices import vertex_heatmap
from .view_transform import CALIBRATION_KEYS

INPUT_KEYS = ("images", *CALIBRATION_KEYS)


class InstaGraM(nn.Module):
    """images -> backbone -> view transform -> BEV heads -> graph head, with an optional temporal
    memory fused into the BEV encoder (models/temporal.py).

    Shapes: B batch, V cameras, h x w network input, S cell size, Hc x Wc cells, H x W BEV grid,
    K classes, N padded vertices.

    forward(batch, memory=None) with ``images`` [B, V, 3, h, w] and the calibration (``intrinsics``,
    ``cam_to_ego_rot``, ``cam_to_ego_trans``, ``post_rot``, ``post_tran``) returns
      ``pred_vertex_logits`` [B, S*S+1, Hc, Wc], ``pred_heatmap`` [B, H, W],
      ``pred_distance`` [B, K, H, W] (absent without a distance head), ``pred_vertices_px`` [B, N, 2],
      ``pred_vertex_mask`` [B, N],
      ``pred_vertex_scores`` [B, N], ``pred_class_log_probs`` [B, N, K],
      ``pred_log_assignment`` [B, N+1, N+1] (float32).
    A temporal model (``temporal`` is a ``BEVMemoryFusion``) also reads ``ego_pose`` [B, 4, 4] and, where
    present, ``scene_start`` [B] bool and ``frame_index`` [B] int64, and adds ``memory`` (the dict to
    pass back with the next frame of the same streams; ``None``: empty) and ``memory_status`` [B] int64
    (``temporal.STATUS_NAMES``). A single-frame model (``temporal=None``) ignores ``memory``.
    """

    def __init__(self, backbone: nn.Module, view_transform: nn.Module, bev_heads: nn.Module, graph_head: GraphHead,
                 temporal: BEVMemoryFusion | None = None):
        super().__init__()
        self.backbone = backbone
        self.view_transform = view_transform
        self.bev_heads = bev_heads
        self.graph_head = graph_head
        self.temporal = temporal

    def train(self, mode: bool = True) -> InstaGraM:
        """As ``nn.Module.train``, but a BatchNorm layer whose parameters are all frozen (``train.trainable``)
        stays in eval mode: a frozen part keeps the running statistics it was trained with."""
        super().train(mode)
        if mode:
            for module in self.modules():
                params = list(module.parameters(recurse=False))
                if (isinstance(module, nn.modules.batchnorm._BatchNorm) and params
                        and not any(p.requires_grad for p in params)):
                    module.eval()
        return self

    @property
    def is_temporal(self) -> bool:
        return self.temporal is not None

    def initial_memory(self, batch_size: int, like: torch.Tensor) -> dict[str, torch.Tensor]:
        """An empty memory of ``batch_size`` streams (a temporal model only), on ``like``'s device."""
        if self.temporal is None:
            raise ValueError("a single-frame model (model.temporal.memory=none) has no memory")
        return self.temporal.initial_memory(batch_size, like)

    image_size: tuple[int, int] | None = None  # (h, w) of data.image_size, set by build_model

    def _check_batch(self, batch) -> None:
        """A TypeError / ValueError naming the key for a batch of other shapes or dtypes than docs/conventions.md's:
        they were raw torch errors from deep inside (a conv's channel count, an index_add_ size, a reshape of 0
        elements) or, for a calibration of another batch size, broadcast over the images with no word."""
        if not isinstance(batch, Mapping):
            raise TypeError(f"InstaGraM.forward takes one batch dict (data.base.collate_fn of sample dicts), got "
                            f"{type(batch).__name__}")
        images = batch["images"]
        shape = list(getattr(images, "shape", ()))
        if not isinstance(images, torch.Tensor) or images.dim() != 5 or shape[2] != 3:
            hint = (" (one sample without the batch dimension: images[None])" if len(shape) == 4 and shape[1] == 3 else
                    " (channels last: images.permute(0, 1, 4, 2, 3))" if len(shape) == 5 and shape[-1] == 3 else "")
            raise ValueError(f"InstaGraM.forward: 'images' must be a tensor [B, V, 3, h, w], got "
                             f"{type(images).__name__} of shape {shape}{hint}")
        B, V = shape[:2]
        if B == 0 or V == 0:
            raise ValueError(f"InstaGraM.forward: an empty batch ('images' of shape {shape}): give at least one sample "
                             "of at least one camera")
        weight = next(self.parameters(), None)
        # under torch.autocast the convolutions cast float images and weights themselves (bf16 images into an fp32
        # model, fp32 images into a bf16 one): only a dtype autocast does not reconcile is refused
        autocast = images.is_floating_point() and torch.is_autocast_enabled(images.device.type)
        if weight is not None and images.dtype != weight.dtype and not autocast:
            raise TypeError(f"InstaGraM.forward: 'images' are {images.dtype}, the model's weights "
                            f"{weight.dtype}: give normalised float images of the weights' dtype (as the datasets and "
                            "Mapper do), e.g. images.to(model dtype)")
        if self.image_size is not None and tuple(shape[-2:]) != tuple(self.image_size):
            raise ValueError(f"InstaGraM.forward: 'images' are {shape[-2]}x{shape[-1]} (h x w), the model was built "
                             f"for data.image_size {list(self.image_size)}: resize them (data.transforms.load_image, "
                             "Mapper do) or build the model for that size")
        for key in CALIBRATION_KEYS:
            value = batch[key]
            lead = [B] if key == "ground_height" else [B, V]  # ground_height: one per sample, [B]
            if not isinstance(value, torch.Tensor) or list(value.shape[:len(lead)]) != lead:
                want = f"[B={B}]" if key == "ground_height" else f"[B={B}, V={V}, ...]"
                raise ValueError(f"InstaGraM.forward: {key!r} must be a tensor {want} like 'images', got "
                                 f"{type(value).__name__} of shape {list(getattr(value, 'shape', ()))}")

    def forward(self, batch: dict, memory: dict[str, torch.Tensor] | None = None) -> dict[str, torch.Tensor]:
        if not isinstance(batch, Mapping):
            self._check_batch(batch)
        required = INPUT_KEYS if self.temporal is None else (*INPUT_KEYS, "ego_pose")
        missing = [k for k in required if k not in batch]
        if missing:
            raise KeyError(f"InstaGraM.forward: the batch lacks {missing} (see docs/conventions.md)")
        if not (torch.jit.is_tracing() or torch.compiler.is_compiling() or torch.onnx.is_in_onnx_export()):
            self._check_batch(batch)  # shapes only: nothing to trace or export, no device sync
        images = batch["images"]
        B, V = images.shape[:2]
        features = self.backbone(images.flatten(0, 1)).unflatten(0, (B, V))  # [B, V, C, h/16, w/16]
        bev = self.view_transform(features, {k: batch[k] for k in CALIBRATION_KEYS})
        temporal: dict[str, torch.Tensor] = {}
        if self.temporal is None:
            heads = self.bev_heads(bev)
        else:
            def fuse(first: torch.Tensor) -> torch.Tensor:
                fused, temporal["memory"], temporal["memory_status"] = self.temporal(first, batch, memory)
                return fused

            heads = self.bev_heads(bev, fuse=fuse)
        distance = heads.get("pred_distance")  # None without a distance head
        graph = self.graph_head(heads["pred_vertex_logits"], distance, heads["bev_features"])
        if self.temporal is not None:  # a graph memory holds this frame's predicted graph
            temporal["memory"] = self.temporal.remember_graph(temporal["memory"], graph)
        out = {
            "pred_vertex_logits": heads["pred_vertex_logits"],
            "pred_heatmap": vertex_heatmap(heads["pred_vertex_logits"], self.graph_head.grid.cell_size),
        }
        if distance is not None:
            out["pred_distance"] = distance
        return {**out, **graph, **temporal}
