"""Graph head: vertex embeddings (Eq. 1), attentional GNN (Eq. 2), class and matching heads (Eq. 3),
scores (Eq. 4) and adjacency by Sinkhorn.

Shapes: B batch, N padded vertices, D embedding dimension, K classes, S cell size,
H x W BEV grid, C BEV feature channels, F positional-encoding frequencies.

Widths follow the official InstaGraM code (so that parameter counts match the paper's Tables IV/V):
MLP_V 2+4F+1 -> 64 -> 128 -> 256 -> D, MLP_E K*S*S -> 64 -> 128 -> 256 -> D (C -> ... for the visual
descriptor), per GNN layer a 4-head self-attention (q, k, v, merge: 4 D x D) and an MLP
2D -> 2D -> D (0.658 M parameters at D = 256), MLP_cls D -> K and MLP_match D -> D (one linear layer
each, as the official ``cls_head`` / ``final_proj``), one learnable dustbin score.

Deviation, on purpose: the official MLPs normalise with BatchNorm1d over all N slots, so in training
the padded vertices shift the statistics of the real ones. We use LayerNorm (per vertex, the same
number of parameters): padding never influences a real output, in training as in evaluation.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ..geometry import BEVGrid
from .matching import log_optimal_transport, score_matrix
from .vertices import cell_features, cell_patches, extract_vertices, sample_at_vertices

EMBEDDINGS = ("pe+dt", "pe", "dt", "pe+vd")


def positional_encoding(xy_norm: torch.Tensor, num_frequencies: int) -> torch.Tensor:
    """Sinusoidal gamma (NeRF): [..., 2] in [-1, 1] -> [..., 2 + 4F] = (p, sin(w_k p), cos(w_k p)),
    w_k = 2^(k-1), k < F: the official code's bands (2^k on coordinates in [-0.5, 0.5]). NeRF's extra
    factor pi would alias the top bands at the grid's pixel spacing (period < 1 px at W = 400, F = 10)."""
    freqs = 2.0 ** torch.arange(-1, num_frequencies - 1, device=xy_norm.device, dtype=xy_norm.dtype)
    angles = (xy_norm[..., None, :] * freqs[:, None]).flatten(-2)  # [..., 2F]
    return torch.cat([xy_norm, angles.sin(), angles.cos()], dim=-1)


def mlp(channels: list[int]) -> nn.Sequential:
    """Linear - LayerNorm - ReLU between consecutive widths, a plain Linear (bias 0) at the end."""
    layers: list[nn.Module] = []
    for i in range(1, len(channels)):
        layers.append(nn.Linear(channels[i - 1], channels[i]))
        if i < len(channels) - 1:
            layers += [nn.LayerNorm(channels[i]), nn.ReLU(inplace=True)]
    nn.init.zeros_(layers[-1].bias)
    return nn.Sequential(*layers)


class AttentionalPropagation(nn.Module):
    """One message-passing layer's update: MLP([g || MSA(g)]) (the residual is added by the GNN)."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(dim, 3 * dim)  # = three D x D projections
        self.merge = nn.Linear(dim, dim)
        self.mlp = mlp([2 * dim, 2 * dim, dim])

    def forward(self, g: torch.Tensor, attn_mask: torch.Tensor) -> torch.Tensor:
        """g [B, N, D], attn_mask [B, 1, 1, N] bool (True = may attend) -> update [B, N, D]."""
        q, k, v = self.qkv(g).unflatten(-1, (3, self.heads, -1)).permute(2, 0, 3, 1, 4)  # 3 x [B, h, N, D/h]
        message = self.merge(self.attend(q, k, v, attn_mask).transpose(1, 2).flatten(2))
        return self.mlp(torch.cat([g, message], dim=-1))

    def attend(self, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, attn_mask: torch.Tensor) -> torch.Tensor:
        """Masked multi-head attention: q, k, v [B, h, N, D/h], attn_mask [B, 1, 1, N] -> [B, h, N, D/h]."""
        return F.scaled_dot_product_attention(q, k, v, attn_mask=attn_mask)


class AttentionalGNN(nn.Module):
    """L layers of g <- g + MLP([g || MSA(g)]) with key-padding masked self-attention."""

    def __init__(self, dim: int, heads: int, layers: int):
        super().__init__()
        self.layers = nn.ModuleList(AttentionalPropagation(dim, heads) for _ in range(layers))

    def forward(self, g: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """g [B, N, D], mask [B, N] bool -> [B, N, D]. Real vertices attend to real vertices only; a
        sample without any real vertex attends to all slots (finite, meaningless, masked later)."""
        keys = mask | ~mask.any(dim=1, keepdim=True)
        attn_mask = keys[:, None, None, :]
        for layer in self.layers:
            g = g + layer(g, attn_mask)
        return g


class GraphHead(nn.Module):
    """Vertex heatmap + distance transform (+ F_bev) -> vertices, classes and adjacency."""

    def __init__(self, *, grid: BEVGrid, num_classes: int, dt_clip: float, bev_channels: int, num_vertices: int = 400,
                 conf_threshold: float = 0.01, embedding: str = "pe+dt", dim: int = 256, pe_frequencies: int = 10,
                 layers: int = 7, heads: int = 4, sinkhorn_iters: int = 100, sinkhorn_grad: str = "implicit",
                 nms_radius: float = 0.0, nms: str = "cells", vd_sampling: str = "vertex"):
        super().__init__()
        self.grid, self.dt_clip, self.embedding = grid, dt_clip, embedding
        self.num_vertices, self.conf_threshold, self.nms_radius = num_vertices, conf_threshold, nms_radius
        self.nms, self.vd_sampling = nms, vd_sampling
        self.pe_frequencies, self.sinkhorn_iters, self.sinkhorn_grad = pe_frequencies, sinkhorn_iters, sinkhorn_grad
        hidden = [64, 128, 256]
        S = grid.cell_size
        if embedding.startswith("pe"):
            self.vertex_encoder = mlp([2 + 4 * pe_frequencies + 1, *hidden, dim])  # MLP_V
        if embedding.endswith("dt"):
            self.local_encoder = mlp([num_classes * S * S, *hidden, dim])  # MLP_E
        elif embedding.endswith("vd"):
            self.local_encoder = mlp([bev_channels, *hidden, dim])  # visual descriptor
        self.gnn = AttentionalGNN(dim, heads, layers)
        self.class_head = nn.Linear(dim, num_classes)  # MLP_cls
        self.match_head = nn.Linear(dim, dim)  # MLP_match
        self.bin_score = nn.Parameter(torch.tensor(1.0))

    def extract(self, vertex_logits: torch.Tensor) -> dict[str, torch.Tensor]:
        """[B, S*S+1, Hc, Wc] -> vertices_px, scores, mask, cells (see ``extract_vertices``)."""
        return extract_vertices(vertex_logits, self.grid.cell_size, self.num_vertices, self.conf_threshold,
                                self.nms_radius, self.nms)

    def embed(self, vertices: dict[str, torch.Tensor], distance: torch.Tensor | None, bev_features: torch.Tensor
             ) -> torch.Tensor:
        """Initial graph g0 [B, N, D] (Eq. 1) from the vertices, distance [B, K, H, W] in
        [0, dt_clip] (used by the 'dt' embeddings only; None without a distance head) and
        bev_features [B, C, H/2, W/2] (used by 'pe+vd' only)."""
        g = 0
        xy_norm = self.grid.px_to_norm(vertices["vertices_px"])
        if self.embedding.startswith("pe"):
            pe = positional_encoding(xy_norm, self.pe_frequencies)
            g = g + self.vertex_encoder(torch.cat([pe, vertices["scores"][..., None]], -1))
        if self.embedding.endswith("dt"):
            patches = cell_patches(distance, vertices["cells"], self.grid.cell_size) / self.dt_clip
            g = g + self.local_encoder(patches)
        elif self.embedding.endswith("vd"):
            if self.vd_sampling == "cell":
                g = g + self.local_encoder(cell_features(bev_features, vertices["cells"], self.grid.Hc, self.grid.Wc))
            else:
                g = g + self.local_encoder(sample_at_vertices(bev_features, xy_norm))
        return g

    def match(self, g: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Final graph [B, N, D], mask [B, N] -> log assignment [B, N+1, N+1] float32."""
        return log_optimal_transport(score_matrix(self.match_head(g)), self.bin_score, mask, self.sinkhorn_iters,
                                     self.sinkhorn_grad)

    def associate(self, vertices: dict[str, torch.Tensor], distance: torch.Tensor | None, bev_features: torch.Tensor
                 ) -> dict[str, torch.Tensor]:
        """Given vertices (``vertices_px`` [B, N, 2], ``scores`` [B, N], ``mask`` [B, N], ``cells``
        [B, N]) -> ``pred_class_log_probs`` [B, N, K], ``pred_log_assignment`` [B, N+1, N+1].

        Training under autocast on the CPU runs it in float32: the bfloat16 backward of torch's CPU attention
        takes ~3x float32's, and the head's layers are small (the rest of the model stays in bfloat16)."""
        mask = vertices["mask"]
        if not mask.is_cuda and torch.is_grad_enabled() and torch.is_autocast_enabled(mask.device.type):
            def fp32(t):
                return t.float() if t is not None and t.is_floating_point() else t

            with torch.autocast(mask.device.type, enabled=False):
                return self.associate({k: fp32(v) for k, v in vertices.items()}, fp32(distance), fp32(bev_features))
        g = self.gnn(self.embed(vertices, distance, bev_features), vertices["mask"])
        return {
            "pred_class_log_probs": F.log_softmax(self.class_head(g).float(), dim=-1),
            "pred_log_assignment": self.match(g, vertices["mask"]),
        }

    def forward(self, vertex_logits: torch.Tensor, distance: torch.Tensor | None, bev_features: torch.Tensor
               ) -> dict[str, torch.Tensor]:
        """-> ``pred_vertices_px``, ``pred_vertex_mask``, ``pred_vertex_scores``,
        ``pred_class_log_probs``, ``pred_log_assignment`` (docs/conventions.md)."""
        vertices = self.extract(vertex_logits)
        return {
            "pred_vertices_px": vertices["vertices_px"],
            "pred_vertex_mask": vertices["mask"],
            "pred_vertex_scores": vertices["scores"],
            **self.associate(vertices, distance, bev_features),
        }
