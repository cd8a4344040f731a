"""The InstaGraM model: ``build_model(cfg)`` is the only place that turns config into modules.

    model = build_model(load_config("configs/paper/table1_b4_lss_128x352.yaml"))
    outputs = model(batch)  # dict, docs/conventions.md
    print(summarize_parameters(model))

Bad configurations raise ``ConfigError`` here, naming the key, not as a shape error in forward.

Parameter counts (``instagram-hdmap model-summary configs/paper/<row>.yaml``) against the paper:
B4 + LSS 29.81 M (Table V: 30.7 M), B4 + MLP 92.38 M (95.5 M), B4 + IPM 27.53 M (30.7 M), +0.658 M
per GNN layer (Table IV: +0.66 M). The paper's figures are the official code's, which also counts two
parts that are never used and that we do not build: EfficientNet's classifier head (``_conv_head``,
``_bn1``, ``_fc``: 2.60 M for B4) and a semantic-segmentation head of its BEV encoder (0.59 M). With
those 3.19 M the official IPM model has 30.72 M and the MLP model 95.58 M, as in the paper, and the
official LSS model 33.00 M (its depth net and 256-channel camera features add 2.28 M to IPM): the
paper's 30.7 M for LSS repeats the IPM figure.
"""

from __future__ import annotations

import numpy as np
from torch import nn

from ..config import ConfigError, ExperimentConfig, as_config
from ..geometry import BEVGrid
from .backbone import FEATURE_DOWNSAMPLE, IMAGE_DIVISOR, EfficientNetBackbone, TinyBackbone, load_pretrained_backbone
from .bev_heads import BEVHeads
from .gnn import EMBEDDINGS, GraphHead
from .instagram import InstaGraM
from .temporal import BEVMemoryFusion
from .view_transform import IPMViewTransform, LSSViewTransform, MLPViewTransform

__all__ = ["InstaGraM", "build_model", "random_init_warning", "summarize_parameters"]

BACKBONES = ("efficientnet-b0", "efficientnet-b4", "tiny")


def _require(ok: bool, key: str, message: str) -> None:
    if not ok:
        raise ConfigError(f"config key '{key}': {message}")


def _check(cfg: ExperimentConfig, grid: BEVGrid) -> None:
    m = cfg.model
    _require(m.backbone.name in BACKBONES, "model.backbone.name",
             f"unknown backbone {m.backbone.name!r}; choose one of {', '.join(BACKBONES)}")
    h, w = cfg.data.image_size
    _require(h > 0 and w > 0 and h % IMAGE_DIVISOR == 0 and w % IMAGE_DIVISOR == 0, "data.image_size",
             f"{h}x{w} (h x w) must be positive multiples of {IMAGE_DIVISOR} (the backbone's total stride), "
             f"e.g. 128x352 or 256x704")
    _require(m.backbone.out_channels > 0, "model.backbone.out_channels", "must be > 0")
    _require(m.backbone.weights is None or m.backbone.name != "tiny", "model.backbone.weights",
             "ImageNet weights exist for the EfficientNets only, not for the 'tiny' backbone")
    _require(not (m.backbone.from_scratch and m.backbone.weights), "model.backbone.from_scratch",
             f"true asks for random weights, but model.backbone.weights={m.backbone.weights!r} gives ImageNet "
             "weights; set one of them only")
    _require(grid.cell_size % 2 == 0, "grid.cell_size",
             f"S={grid.cell_size} must be even: F_bev is at half resolution and the vertex head "
             "strides from it to the S x S cell grid")
    vt = m.view_transform
    _require(vt.kind in ("lss", "ipm", "mlp"), "model.view_transform.kind",
             f"unknown view transform {vt.kind!r}; choose lss, ipm or mlp")
    _require(vt.bev_downsample in (1, 2), "model.view_transform.bev_downsample",
             f"must be 1 or 2 (got {vt.bev_downsample})")
    start, stop, step = vt.depth_bound
    _require(0 < start < stop and step > 0, "model.view_transform.depth_bound",
             f"(start, stop, step) = {vt.depth_bound} must satisfy 0 < start < stop and step > 0")
    _require(vt.zbound[0] < vt.zbound[1], "model.view_transform.zbound", "lower bound must be below upper")
    if vt.kind == "lss":  # a frustum of one depth: every feature at one distance from its camera
        bins = len(np.arange(start, stop, step))
        _require(bins >= 2, "model.view_transform.depth_bound",
                 f"(start, stop, step) = {vt.depth_bound} gives {bins} depth bin: every camera feature would be "
                 "put at one depth; choose a step well below stop - start (the paper: [4, 45, 1])")
    if vt.kind == "mlp":
        d = vt.mlp_bev_downsample
        _require(d > 0 and grid.H % d == 0 and grid.W % d == 0, "model.view_transform.mlp_bev_downsample",
                 f"the BEV size {grid.H}x{grid.W} (H x W) must be divisible by {d}")
        _require(vt.num_cameras > 0, "model.view_transform.num_cameras", "must be > 0")
    bh = m.bev_heads
    _require(bh.channels > 0 and bh.head_channels > 0, "model.bev_heads.channels", "widths must be > 0")
    _require(len(bh.stage_channels) > 0 and min(bh.stage_channels) > 0, "model.bev_heads.stage_channels",
             "needs at least one positive width")
    gh = m.gnn
    _require(gh.num_vertices > 0, "model.gnn.num_vertices", f"N must be > 0, got {gh.num_vertices}")
    _require(0 <= gh.conf_threshold < 1, "model.gnn.conf_threshold", "must be in [0, 1)")
    _require(0 <= gh.nms_radius < 2 * grid.cell_size, "model.gnn.nms_radius",
             f"must be in [0, 2 x grid.cell_size = {2 * grid.cell_size}) BEV pixels")
    _require(gh.nms != "superpoint" or float(gh.nms_radius).is_integer(), "model.gnn.nms_radius",
             f"model.gnn.nms=superpoint takes a whole number of pixels (its max-pool window is 2r+1), "
             f"got {gh.nms_radius}; the official radius is S/2 = {grid.cell_size // 2}")
    _require(gh.embedding in EMBEDDINGS, "model.gnn.embedding", f"choose one of {', '.join(EMBEDDINGS)}")
    _require(bh.distance_head or not gh.embedding.endswith("dt"), "model.bev_heads.distance_head",
             f"the embedding {gh.embedding!r} reads the distance transform; without the distance head use "
             "model.gnn.embedding=pe or pe+vd (the official visual-descriptor variant)")
    _require(gh.layers >= 0, "model.gnn.layers", "must be >= 0")
    _require(gh.pe_frequencies >= 0, "model.gnn.pe_frequencies", "must be >= 0")
    _require(gh.heads > 0 and gh.dim % gh.heads == 0, "model.gnn.heads",
             f"the dimension D={gh.dim} must be divisible by the number of heads ({gh.heads})")
    _require(gh.sinkhorn_iters >= 1, "model.gnn.sinkhorn_iters", "must be >= 1")
    _require(m.temporal.memory != "graph" or m.temporal.fusion == "gated", "model.temporal.fusion",
             "a graph memory alone (model.temporal.memory=graph) is fused by the gated fusion: the GRU's state is "
             "BEV features; use model.temporal.fusion=gated, or model.temporal.memory=bev+graph with the GRU")
    _require(m.temporal.kernel % 2 == 1, "model.temporal.kernel", f"must be odd (the fused map keeps its size), "
             f"got {m.temporal.kernel}")


def build_model(cfg: ExperimentConfig, *, pretrained: bool = False, download=None) -> InstaGraM:
    """Config -> InstaGraM, randomly initialised; with ``pretrained`` (a training run that starts,
    not one that resumes or loads a checkpoint) the EfficientNet gets ``model.backbone.weights``
    (``load_pretrained_backbone``; ``download`` replaces the ImageNet download, for tests). ``cfg``: an
    ``ExperimentConfig`` or a YAML file."""
    cfg = as_config(cfg, "build_model")
    grid = BEVGrid.from_config(cfg.grid)  # ConfigError if the grid does not tile into S x S cells
    _check(cfg, grid)
    m, image_size = cfg.model, tuple(cfg.data.image_size)
    channels = m.backbone.out_channels

    if m.backbone.name == "tiny":
        _require(len(m.backbone.tiny_widths) == 5 and min(m.backbone.tiny_widths) > 0,
                 "model.backbone.tiny_widths", "must be 5 positive channel counts")
        backbone: nn.Module = TinyBackbone(channels, tuple(m.backbone.tiny_widths))
    else:
        backbone = EfficientNetBackbone(m.backbone.name, channels, image_size,
                                        grad_checkpoint=m.backbone.grad_checkpoint)
        if pretrained and m.backbone.weights:
            load_pretrained_backbone(backbone, m.backbone.weights, download)

    vt = m.view_transform
    view_grid = BEVGrid(grid.xmin, grid.xmax, grid.ymin, grid.ymax, grid.resolution * vt.bev_downsample, 1)
    if vt.kind == "lss":
        view_transform: nn.Module = LSSViewTransform(view_grid, image_size, channels, vt.depth_bound, vt.zbound,
                                                     FEATURE_DOWNSAMPLE)
    elif vt.kind == "ipm":
        view_transform = IPMViewTransform(view_grid, image_size, channels, vt.ipm_height)
    else:
        camera_bev = (grid.H // vt.mlp_bev_downsample, grid.W // vt.mlp_bev_downsample)
        view_transform = MLPViewTransform(view_grid, image_size, channels, camera_bev, vt.num_cameras, vt.ipm_height,
                                          FEATURE_DOWNSAMPLE)

    num_classes = len(cfg.data.classes)
    bh = m.bev_heads
    bev_heads = BEVHeads(in_channels=channels, num_classes=num_classes, cell_size=grid.cell_size,
                         dt_clip=cfg.data.dt_clip, channels=bh.channels, stage_channels=tuple(bh.stage_channels),
                         head_channels=bh.head_channels, stem_stride=2 // vt.bev_downsample,
                         distance_head=bh.distance_head)
    gh = m.gnn
    graph_head = GraphHead(grid=grid, num_classes=num_classes, dt_clip=cfg.data.dt_clip, bev_channels=bh.channels,
                           num_vertices=gh.num_vertices, conf_threshold=gh.conf_threshold, embedding=gh.embedding,
                           dim=gh.dim, pe_frequencies=gh.pe_frequencies, layers=gh.layers, heads=gh.heads,
                           sinkhorn_iters=gh.sinkhorn_iters, sinkhorn_grad=gh.sinkhorn_grad, nms_radius=gh.nms_radius,
                           nms=gh.nms, vd_sampling=gh.vd_sampling)
    tc = m.temporal
    temporal = None
    if tc.memory != "none":  # fused after the BEV encoder's first stage, at H/2 x W/2 (models/bev_heads.py)
        temporal = BEVMemoryFusion(bh.stage_channels[0], grid, (grid.H // 2, grid.W // 2), tc.fusion, tc.kernel,
                                   tc.drop_prob, tc.max_jump_m, tc.memory, num_classes, tc.edge_samples,
                                   tc.max_turn_deg)
    model = InstaGraM(backbone, view_transform, bev_heads, graph_head, temporal)
    model.image_size = image_size  # forward checks the images' size against it (the view transform assumes it)
    return model


def random_init_warning(cfg: ExperimentConfig) -> str | None:
    """The warning a training run from random EfficientNet weights prints at start, or None (a tiny
    backbone, weights configured, or ``model.backbone.from_scratch`` set on purpose)."""
    b = cfg.model.backbone
    if b.name == "tiny" or b.weights or b.from_scratch:
        return None
    return (f"WARNING: {b.name} starts from RANDOM weights (model.backbone.weights is null). The paper and the "
            "official code start from ImageNet weights; every paper number assumes them. Set "
            "model.backbone.weights=imagenet (or a local file), or model.backbone.from_scratch=true to train "
            "from scratch on purpose and silence this.")


def _count(module: nn.Module | None) -> int:
    return 0 if module is None else sum(p.numel() for p in module.parameters())


def summarize_parameters(model: InstaGraM) -> str:
    """A table of parameters per component and in total (the paper's Tables IV/V count them all)."""
    gh = model.graph_head
    layers = len(gh.gnn.layers)
    embedding = _count(getattr(gh, "vertex_encoder", None)) + _count(getattr(gh, "local_encoder", None))
    per_layer = _count(gh.gnn.layers[0]) if layers else 0
    rows = [
        ("backbone", _count(model.backbone)),
        ("view_transform", _count(model.view_transform)),
        ("bev_heads", _count(model.bev_heads)),
        ("graph_head", _count(gh)),
        (f"  embedding ({gh.embedding})", embedding),
        (f"  gnn ({layers} layers x {per_layer / 1e6:.3f} M)", _count(gh.gnn)),
        ("  class + match heads, dustbin", _count(gh.class_head) + _count(gh.match_head) + gh.bin_score.numel()),
    ]
    if model.temporal is not None:
        rows.append((f"temporal ({model.temporal.fusion} fusion, {model.temporal.memory} memory)",
                     _count(model.temporal)))
    width = max(len(name) for name, _ in rows) + 2
    rows += [("total", _count(model)), ("trainable", sum(p.numel() for p in model.parameters() if p.requires_grad))]
    lines = [f"{'component':<{width}}{'parameters':>14}{'':>10}"]
    lines += [f"{name:<{width}}{n:>14,}{n / 1e6:>9.3f}M" for name, n in rows]
    lines.insert(-2, "-" * (width + 24))
    return "\n".join(lines)
