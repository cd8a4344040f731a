"""Experiment configuration: nested dataclasses, one per component.

A YAML file holds *overrides only* of the defaults below (the defaults are the paper's main
setting: EfficientNet-B4, LSS, 128x352 images, 60 m x 30 m at 0.15 m, S = 8, N = 400, 7 GNN layers;
configs/paper/table1_b4_lss_128x352.yaml adds what the official code does differently from our
defaults: ImageNet weights, SuperPoint NMS, its matching space and class targets, its decoder, the
raster protocol, ...; benchmarks/README.md, "The paper configs against the official code").
A YAML file may name another one to start from with ``_base_: relative/path.yaml``. Command-line
overrides use dotted keys, ``model.gnn.layers=9``, and are parsed as YAML values.

Unknown keys and values of the wrong type are errors that name the key and list what is valid. The YAML is
read strictly, as YAML 1.2 reads it, and written so that it reads back the same (config_text.py). Every
float must be finite, and every numeric key declares its range where it is defined
(``bounded(default, ge=..., gt=..., le=..., lt=...)``): ``validate_config`` checks them all, so a new
key gets the check by declaring its bounds (tests/test_config.py checks that every numeric key does).

    cfg = load_config("configs/paper/table1_b0_lss_128x352.yaml", ["train.batch_size=8"])
    save_config(cfg, "run/config.yaml"); assert load_config("run/config.yaml") == cfg
"""

from __future__ import annotations

import copy
import dataclasses
import datetime
import functools
import os
import types
import typing
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Union

import yaml

from .config_text import (  # noqa: F401 (get_key, is_under, set_key: re-exported)
    RENAMED_KEYS,
    _Dumper,
    _DuplicateKey,
    _merge,
    _read_yaml,
    _show,
    _TooDeep,
    deep_update,
    flatten,
    get_key,
    is_under,
    load_yaml,
    set_key,
)
from .errors import ConfigError, UserError  # noqa: F401 (re-exported: every floor raises them)
from .files import as_path, write_text


@dataclass(frozen=True)
class Range:
    """The valid values of a numeric config key (of each element of a list key): ge / gt / le / lt
    bounds, any of them None; ``note`` says what the key is, for the error message."""

    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    note: str = ""

    def __contains__(self, v: float) -> bool:
        return ((self.ge is None or v >= self.ge) and (self.gt is None or v > self.gt)
                and (self.le is None or v <= self.le) and (self.lt is None or v < self.lt))

    def describe(self) -> str:
        def num(x: float) -> str:
            return str(x) if isinstance(x, int) else f"{x:g}"

        lo = f"[{num(self.ge)}" if self.ge is not None else f"({num(self.gt)}" if self.gt is not None else None
        hi = f"{num(self.le)}]" if self.le is not None else f"{num(self.lt)})" if self.lt is not None else None
        if lo and hi:
            return f"in {lo}, {hi}"
        if lo:
            return f"{'>=' if lo[0] == '[' else '>'} {lo[1:]}"
        return f"{'<=' if hi[-1] == ']' else '<'} {hi[:-1]}" if hi else "any number"


def bounded(default: Any, *, ge: float | None = None, gt: float | None = None, le: float | None = None,
            lt: float | None = None, note: str = "") -> Any:
    """A dataclass field of a numeric key with its declared ``Range`` (checked by ``validate_config``)."""
    return field(default=default, metadata={"range": Range(ge, gt, le, lt, note)})


# The nuScenes camera rig's size (data/rig.py CAMERAS: six cameras)
NUSCENES_CAMERA_COUNT = 6

# The map classes of the local map builders (data/local_map.py, data/av2.py), in label order
MAP_CLASSES = ("divider", "ped_crossing", "boundary")


# ---------------------------------------------------------------------------------------------
# Components
# ---------------------------------------------------------------------------------------------


@dataclass
class GridConfig:
    """The BEV grid (see geometry.BEVGrid). x points forward, y to the left, metres, ego frame."""

    xbound: tuple[float, float] = bounded((-30.0, 30.0), ge=-1000, le=1000)  # along the driving direction
    ybound: tuple[float, float] = bounded((-15.0, 15.0), ge=-1000, le=1000)  # lateral
    resolution: float = bounded(0.15, gt=0)  # metres per BEV pixel
    cell_size: int = bounded(8, ge=1, le=256)  # S: one vertex per SxS cell


# The seven ring cameras of the Argoverse 2 sensor dataset, clockwise from the front left (data/av2.py)
AV2_RING_CAMERAS = ("ring_front_left", "ring_front_center", "ring_front_right", "ring_side_right",
                    "ring_rear_right", "ring_rear_left", "ring_side_left")


@dataclass
class DataConfig:
    """Dataset, local map, images and targets (data/nuscenes.py, data/av2.py, data/local_map.py,
    data/transforms.py, targets.py)."""

    dataset: Literal["nuscenes", "av2"] = "nuscenes"  # av2: the Argoverse 2 sensor dataset (extra [av2])
    dataroot: str = "data/nuscenes"
    version: str = "v1.0-trainval"  # v1.0-trainval | v1.0-mini | any version folder of the dataroot
    # custom splits.json {"train": [scene names], "val": [...]}, overrides the official splits; a
    # relative path is looked up in the working directory, then in the dataroot
    splits_file: str | None = None
    # official: the dataset's own splits (the devkit's scenes, AV2's split folders); geo: StreamMapNet's
    # geographically disjoint lists, shipped with the package, or a synthetic world's held-out road
    # network (data/geo_split.py)
    split_scheme: Literal["official", "geo"] = "official"
    train_split: str = "train"
    val_split: str = "val"
    image_size: tuple[int, int] = bounded((128, 352), ge=1, le=8192)  # (h, w) fed to the backbone
    # cover: resize to cover (h, w), crop (lift-splat-shoot); contain: resize to fit inside, pad with
    # black (for cameras of different aspect ratios, e.g. AV2's portrait ring_front_center); stretch:
    # resize the whole image to (h, w), each axis on its own (the official InstaGraM / HDMapNet
    # loader: 1600 x 900 -> 352 x 128, no crop; configs/paper)
    image_fit: Literal["cover", "contain", "stretch"] = "cover"
    # each camera image of a sample is blanked (the ImageNet mean: a camera that failed) with this
    # probability, drawn from the sample's index alone (the same cameras in every epoch, for every model,
    # in training and evaluation): a world where one frame lacks what the frame before saw (the temporal
    # benchmark, docs/temporal.md); 0: off
    camera_dropout: float = bounded(0.0, ge=0, lt=1)
    av2_cameras: tuple[str, ...] = AV2_RING_CAMERAS  # av2: the ring cameras fed to the model, in this order
    av2_frame_step: int = bounded(5, ge=1)  # av2: one lidar sweep in N is a sample (AV2's sweeps come at 10 Hz)
    sample_dist: float = bounded(1.5, gt=0)  # metres between resampled map vertices
    # ped-crossing ground truth (data/local_map.py, docs/conventions.md): "edges", each crossing's two
    # longest edges as open polylines (HDMapNet's and the official InstaGraM code's, the paper's);
    # "union", the rings (exterior and interior) of the crossings' union (MapTR); "each", each
    # crossing's own ring (StreamMapNet, the field's AV2 setting)
    ped_crossing: Literal["edges", "union", "each"] = "edges"
    classes: tuple[str, ...] = MAP_CLASSES
    # distance transform clipped to [0, dt_clip] BEV pixels
    dt_clip: float = bounded(10.0, gt=0, note="BEV pixels; the distance-transform targets are divided by it")
    augment: bool = False  # train-time image augmentation (scale, crop, rotate)
    aug_scale: tuple[float, float] = bounded((0.95, 1.05), gt=0)  # uniform factor on the resize
    # uniform in [-aug_rotate_deg, aug_rotate_deg], about the image centre
    aug_rotate_deg: float = bounded(5.4, ge=0, le=180)
    aug_crop_jitter: float = bounded(0.05, ge=0, le=1)  # crop window shift, uniform in +-fraction of the image size
    # raise: a UserError naming the file and sample; skip: warn once per bad sample, use the next good one
    on_bad_sample: Literal["raise", "skip"] = "raise"
    num_workers: int = bounded(4, ge=0, note="data-loader processes; 0 loads in the main process")
    # keep each training sample in memory once loaded: later epochs skip the image decoding and the targets
    # (a world that fits in RAM; the loader checks the room after the first sample). Needs data.augment off
    # (a kept sample would repeat its first draw) and data.num_workers=0 (a worker's copy ends with its epoch)
    cache_in_memory: bool = False


@dataclass
class BackboneConfig:
    name: Literal["efficientnet-b0", "efficientnet-b4", "tiny"] = "efficientnet-b4"
    # ImageNet weights of the EfficientNet, loaded when training starts (not on resume): "imagenet"
    # downloads them through efficientnet_pytorch (torch's hub cache), a path reads a local file in
    # that package's state-dict format, null starts from random weights (models/backbone.py)
    weights: str | None = None
    # train an EfficientNet from random weights on purpose: without it (and without weights) training
    # warns loudly at start, since every paper number starts from ImageNet weights
    from_scratch: bool = False
    # C of the per-camera features handed to the view transform (reduction 4 + 5 fused by an up-block).
    # The official code uses 256 with LSS and 64 with IPM / MLP (configs/paper/table5_*.yaml).
    out_channels: int = bounded(256, ge=1, le=8192)
    # Activation checkpointing of the EfficientNet's MBConv blocks (training only): keep each block's
    # input for backward and recompute the block there, with the same drop-connect masks and without
    # updating BatchNorm statistics twice, so gradients and buffers are bit-identical to the plain run.
    # CPU, 128x352, batch 1 (benchmarks/train_speed.py): peak memory B0 2.04 -> 1.54 GB, B4 3.40 ->
    # 1.97 GB, for +6 % / +22 % step time (under load). Set false when memory is plentiful (a large GPU).
    grad_checkpoint: bool = True
    # name=tiny only: channels of its five stride-2 conv stages (the CPU demo's image encoder)
    tiny_widths: tuple[int, ...] = bounded((8, 16, 24, 32, 48), ge=1)


@dataclass
class ViewTransformConfig:
    kind: Literal["lss", "ipm", "mlp"] = "lss"
    depth_bound: tuple[float, float, float] = bounded((4.0, 45.0, 1.0), gt=0)  # LSS depth bins: start, stop, step (m)
    # The view transform writes a BEV grid `bev_downsample` times coarser than the output grid: 2 (our
    # default) splats straight onto the half-resolution grid of F_bev (W/2 x H/2); 1 splats at full
    # resolution and the BEV encoder's stem convolution strides by 2 (the official layout, slower).
    bev_downsample: int = bounded(2, ge=1, le=2)
    zbound: tuple[float, float] = bounded((-10.0, 10.0), ge=-1000, le=1000)  # LSS vertical extent of the voxel pillar
    # IPM / MLP ground plane: z = the sample's ground height (batch key ground_height: nuScenes 0,
    # AV2 the road below the rear axle, ~-0.35 m) + this offset (m)
    ipm_height: float = bounded(0.0, ge=-100, le=100)
    mlp_bev_downsample: int = bounded(5, ge=1)  # HDMapNet MLP: per-camera BEV of (H/5) x (W/5)
    num_cameras: int = bounded(6, ge=1)  # MLP only: one fully connected view transform per camera


@dataclass
class BEVHeadsConfig:
    channels: int = bounded(256, ge=1, le=8192)  # F_bev channels
    # "3 residual blocks": ResNet-18 stages layer1..3, two BasicBlocks each, strides 1, 2, 2
    stage_channels: tuple[int, ...] = bounded((64, 128, 256), ge=1, le=8192)
    head_channels: int = bounded(128, ge=1, le=8192)  # hidden width of the vertex and distance-transform heads
    # the distance-transform (edge map) head and its loss; false: no head, no pred_distance, no
    # loss_distance (the official visual-descriptor variant of Fig. 7, which needs embedding pe+vd)
    distance_head: bool = True


@dataclass
class GraphHeadConfig:
    num_vertices: int = bounded(400, ge=1)  # N, top-N vertices fed to the GNN
    conf_threshold: float = bounded(0.01, ge=0, lt=1)
    # BEV pixels: a cell's vertex within this distance of a stronger one in a neighbouring cell is
    # dropped (0: one vertex per cell only, the paper's text; models/vertices.py)
    nms_radius: float = bounded(0.0, ge=0)
    # how nms_radius suppresses: "cells" (ours: Euclidean distance to a stronger winner of one of the
    # 8 neighbouring cells, one pass) or "superpoint" (SuperPoint's simple_nms on the map of cell
    # winners: (2r+1)^2 max-pool window, two rescue passes; the official code, radius S/2 px)
    nms: Literal["cells", "superpoint"] = "cells"
    embedding: Literal["pe+dt", "pe", "dt", "pe+vd"] = "pe+dt"
    # pe+vd: where the visual descriptor is read from F_bev: "vertex" (bilinear at the vertex) or
    # "cell" (F_bev resized to the cell grid, the vertex's cell: the official code)
    vd_sampling: Literal["vertex", "cell"] = "vertex"
    dim: int = bounded(256, ge=1, le=8192)  # D
    pe_frequencies: int = bounded(10, ge=0, le=64)  # sinusoidal positional encoding bands per coordinate
    layers: int = bounded(7, ge=0, le=64)  # L attentional message-passing layers (0-11 in the paper)
    heads: int = bounded(4, ge=1, le=64)
    sinkhorn_iters: int = bounded(100, ge=1, le=10000, note="0 iterations leave the score matrix unnormalised")
    # gradient through the Sinkhorn: "implicit" (fixed-point differentiation: one small solve per
    # sample, ~none of the memory) or "unrolled" (through every iteration, as SuperGlue); the
    # forward is the same (models/matching.py)
    sinkhorn_grad: Literal["implicit", "unrolled"] = "implicit"
    # adjacency probability to follow an edge at inference
    match_threshold: float = bounded(0.1, gt=0, lt=1, note="an adjacency probability")
    # inference decoder of the adjacency (postprocess.py): "greedy" (strongest pairs first, degree
    # <= 2, one class-agnostic graph), "classwise" (the same per class, over the vertices whose class
    # probability is >= class_min_prob), "mutual" (the official rule: each end ranks the other among
    # its two best, both ends of the same argmax class, confidence = mean class probability) or
    # "official" (the official export's walk over that rule, quirks included: it drops the last
    # vertex of every walk)
    decoder: Literal["classwise", "greedy", "mutual", "official"] = "greedy"
    # classwise: a vertex takes part in class k's graph if p_k >= this
    class_min_prob: float = bounded(0.05, ge=0, lt=1, note="a class probability")
    # greedy: an edge needs both vertices' argmax class to agree (mutual and official always do)
    same_class_edges: bool = False
    # greedy / classwise: no edge longer than this (metres)
    max_edge_m: float | None = bounded(None, gt=0, note="metres, or null: no limit")
    # a decoded instance needs at least this many vertices
    min_vertices: int = bounded(2, ge=2, note="an instance is at least one edge")


@dataclass
class TemporalConfig:
    """Streaming temporal fusion (models/temporal.py, docs/temporal.md). ``memory=none`` is the paper's
    single-frame model, bit for bit; ``bev`` carries the previous frame's BEV features, warped into
    the current ego frame by the relative pose, and fuses them with the current ones in the BEV encoder;
    ``graph`` carries the previous frame's predicted map graph (vertices, edges and their classes) drawn as a
    raster and fuses that; ``bev+graph`` both."""

    memory: Literal["none", "bev", "graph", "bev+graph"] = "none"
    # gated: x + sigmoid(g) * d from a conv of [x, warped memory, validity], d zero-initialised (the
    # model starts as the single-frame one); gru: StreamMapNet's ConvGRU (gates, LayerNorm)
    fusion: Literal["gated", "gru"] = "gated"
    # the fusion convolutions' kernel (1 as StreamMapNet's ConvGRU; 3 sees +-1 cell)
    kernel: int = bounded(1, ge=1, le=7, note="odd")
    # training: each sample's memory is dropped with this probability at each step (the model keeps
    # working on a scene's first frame, StreamMapNet's random drop)
    drop_prob: float = bounded(0.1, ge=0, lt=1)
    # a jump of the ego position larger than this between consecutive frames resets the memory
    max_jump_m: float = bounded(10.0, gt=0)
    # so does a turn of the ego larger than this (degrees; 180: never): real drives turn <= ~15 degrees in the
    # half second between nuScenes keyframes (the synthetic worlds up to 35); more is a pose in the wrong unit or frame
    max_turn_deg: float = bounded(60.0, gt=0, le=180)
    # graph memory: points drawn along each predicted edge of the previous frame (models/temporal.py render_graph)
    edge_samples: int = bounded(8, ge=2, le=64)
    # decoding over a drive (persistence.py, any model): a map element found in the previous frames and missed in
    # this one is kept for up to persist_frames missed frames (0: off, the model's output as it is), moved by the
    # ego motion, its score times persist_decay per missed frame; "found again" = an output of its class within
    # persist_match_m (Chamfer). Applied by evaluate (and training's validation), predict and Mapper.stream()
    persist_frames: int = bounded(0, ge=0, le=10)
    persist_decay: float = bounded(0.5, gt=0, le=1)
    persist_match_m: float = bounded(1.0, gt=0, le=10)


@dataclass
class ModelConfig:
    backbone: BackboneConfig = field(default_factory=BackboneConfig)
    view_transform: ViewTransformConfig = field(default_factory=ViewTransformConfig)
    bev_heads: BEVHeadsConfig = field(default_factory=BEVHeadsConfig)
    gnn: GraphHeadConfig = field(default_factory=GraphHeadConfig)
    temporal: TemporalConfig = field(default_factory=TemporalConfig)


@dataclass
class LossConfig:
    vertex_weight: float = bounded(1.0, ge=0)  # lambda_1, vertex cross-entropy over S^2 + 1
    distance_weight: float = bounded(1.0, ge=0)  # lambda_2, distance-transform L2
    adjacency_weight: float = bounded(5e-3, ge=0)  # lambda_3, bidirectional adjacency NLL
    class_weight: float = bounded(1e-2, ge=0)  # lambda_4, vertex class NLL
    # D_0, metres: a predicted vertex farther from every GT vertex is unmatched
    match_dist: float = bounded(1.5, gt=0)
    # the space of Eq. 5's distance (assignment.py): "metres" (a circle of radius D_0) or "patch" (the
    # official GraphLoss: offsets divided by the patch extent and compared with D_0 divided the same
    # way, an ellipse of 3.35 m x 1.68 m on the 60 m x 30 m patch; the nearest GT vertex too)
    match_space: Literal["metres", "patch"] = "metres"
    # class targets (Eq. 7): "matched" (the predicted vertices within D_0 of a GT vertex) or "nearest"
    # (every real predicted vertex takes the class of its nearest GT vertex at any distance: official)
    class_targets: Literal["matched", "nearest"] = "matched"
    # adjacency targets skip GT vertices that no prediction represents (assignment.py); False: dustbin
    skip_missed_vertices: bool = True


@dataclass
class TrainConfig:
    out_dir: str = "runs/instagram"
    epochs: int = bounded(30, ge=1)
    batch_size: int = bounded(32, ge=1)  # in total, over all processes
    lr: float = bounded(1e-3, gt=0)
    # Adam's L2, added to the gradient as the official code does; not on a temporal fusion's parameters
    # (param_groups in train.py: with the memory empty, the L2 alone would erase its memory weights)
    weight_decay: float = bounded(1e-7, ge=0)
    # LR schedule as a function of progress = max(steps / total steps, elapsed / time budget)
    # (schedule.py): "step" decays x lr_gamma every lr_step epochs' worth of progress (the paper's
    # StepLR), "cosine" to lr * min_lr_factor; both after a linear warm-up over `warmup` progress
    schedule: Literal["step", "cosine"] = "step"
    lr_step: int = bounded(10, ge=1, note="epochs between decays")
    lr_gamma: float = bounded(0.1, gt=0)
    warmup: float = bounded(0.0, ge=0, lt=1, note="a fraction of training")  # fraction of progress
    min_lr_factor: float = bounded(0.0, ge=0, le=1)  # cosine only
    grad_clip: float = bounded(5.0, ge=0, note="0: no clipping")
    # autocast: auto = bf16 where the device computes bfloat16 natively (AMX / AVX512-BF16 CPUs, most GPUs), else none
    amp: Literal["none", "bf16", "fp16", "auto"] = "none"
    seed: int = bounded(0, ge=0, lt=2**32)
    on_nonfinite: Literal["stop", "skip"] = "stop"
    log_every: int = bounded(10, ge=1)
    val_every: int = bounded(1, ge=1)  # epochs
    # stop after this many steps (tests); does not shorten the schedule
    max_steps: int | None = bounded(None, ge=1, note="or null")
    # wall-time budget of the training loop: the schedule completes within it (fewer steps on a
    # slower machine) and training stops when it is spent
    time_budget_min: float | None = bounded(None, gt=0, note="or null for none")
    checkpoint_every: int = bounded(500, ge=0)  # steps between mid-epoch saves of last.pt (0: epoch ends only)
    deterministic: bool = False  # torch.use_deterministic_algorithms (exact resume on CPU)
    device: Literal["auto", "cpu", "cuda"] = "auto"
    # torch intra-op threads of a CPU training run; null = the cores this process may use minus the
    # data workers (>= 1), unless OMP_NUM_THREADS is set. Two cores shared by two torch threads and
    # a data worker ran the demo 12 % slower than one thread (benchmarks/torch_builds.py)
    cpu_threads: int | None = bounded(None, ge=1, note="or null: automatic")
    # temporal models (model.temporal): training streams walk scenes in pieces of at most this many
    # frames, each piece a new start of the memory (0: whole scenes). Shorter pieces make consecutive
    # batches less alike (data/streaming.py; StreamMapNet's seq_split_num)
    stream_frames: int = bounded(0, ge=0, note="0: whole scenes")
    # temporal models: the first epochs on shuffled single frames (the memory always empty) before the
    # streams, as a fraction of train.epochs (StreamMapNet trains 1/6 of its epochs so); consecutive
    # frames in a batch stream are alike, which slows the early learning of the single-frame parts
    stream_warmup: float = bounded(0.0, ge=0, lt=1, note="a fraction of train.epochs")
    # fine-tuning: a fresh run starts from this checkpoint's model weights (not a resume: optimizer,
    # schedule and position start anew; a resumed run has its own weights). Every weight must match by
    # name and shape; the only ones the checkpoint may lack are the temporal fusion's (a temporal model
    # started from a trained single-frame one, docs/temporal.md)
    init_from: str | None = None
    # parameter-name prefixes to train, e.g. [temporal] (only the memory fusion) or [temporal,
    # bev_heads]; empty: all. Frozen BatchNorm layers keep their running statistics (eval mode)
    trainable: tuple[str, ...] = ()


@dataclass
class EvalConfig:
    protocol: Literal["vector", "raster"] = "vector"
    thresholds: tuple[float, ...] = bounded((0.5, 1.0, 1.5), gt=0, le=10,
                                            note="Chamfer thresholds in metres (centimetres given?)")
    batch_size: int = bounded(4, ge=1)
    # raster protocol only: "ascending" reproduces the reference's PR curve order (a bug the
    # InstaGraM paper's numbers carry), "descending" fixes it
    rank_by: Literal["ascending", "descending"] = "ascending"
    fix_instance_ids: bool = False  # raster only: int32 ids, each instance keeps its own confidence
    # temporal consistency next to the AP (evaluation/consistency.py, docs/temporal.md): the flicker
    # rate, per class the share of GT elements seen in two consecutive frames whose detected / missed
    # status (a prediction within flicker_threshold_m, Chamfer) flips
    flicker: bool = True
    flicker_threshold_m: float = bounded(1.0, gt=0, le=10, note="metres, as eval.thresholds (centimetres given?)")
    # MapTracker's consistency-aware mAP next to the AP (evaluation/consistency.py: ConsistentAPMeter,
    # docs/temporal.md) at eval.thresholds: a TP whose predicted instance ID (carried from frame to frame by
    # the persistence matcher) differs from the first ID that matched its GT element counts as an FP
    cmap: bool = False
    # the Chamfer distance (m) within which an element of the previous frame, moved by the ego motion, passes its
    # ID on (the persistence matcher's test). C-mAP measures the model and this tracker together: it rises with
    # this distance, so compare models at one value
    cmap_match_m: float = bounded(1.0, gt=0, le=10, note="metres, as model.temporal.persist_match_m (centimetres "
                                  "given?)")
    # protocols computed as well, on the same predictions, reported under metrics["also"][protocol]
    also_protocols: tuple[Literal["vector", "raster"], ...] = ()


@dataclass
class ExperimentConfig:
    name: str = "instagram"
    grid: GridConfig = field(default_factory=GridConfig)
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)


# ---------------------------------------------------------------------------------------------
# Loading, overriding, saving
# ---------------------------------------------------------------------------------------------


def _key_type(dotted: str) -> Any:
    """The annotation of the config key ``dotted`` (``train.out_dir``), a dataclass for a section; None if unknown."""
    tp: Any = ExperimentConfig
    for part in dotted.split("."):
        if not (isinstance(tp, type) and dataclasses.is_dataclass(tp)):
            return None
        tp = typing.get_type_hints(tp).get(part)
        if tp is None:
            return None
    return tp


def _text_key(dotted: str) -> bool:
    """Whether the config key ``dotted`` holds text only (``str`` or ``str | None``), so that a command-line value
    YAML reads as a number, a date or a boolean (``name=2024``, ``train.out_dir=2024-12-05``, ``data.val_split=no``)
    is the text typed: the shell eats the quotes a YAML file would need, and Hydra's command-line grammar keeps such
    values text too. A YAML file's value stays as YAML reads it (quote it there)."""
    tp = _key_type(dotted)
    args = typing.get_args(tp) if typing.get_origin(tp) in (Union, types.UnionType) else (tp,)
    return str in args and all(a in (str, type(None)) for a in args)


def parse_overrides(overrides: list[str]) -> dict:
    """``["model.gnn.layers=9", "data.image_size=[256,704]"]`` -> nested dict of YAML values."""
    nested: dict = {}
    for item in overrides:
        if not isinstance(item, str):  # a raw "argument of type 'int' is not iterable"
            raise TypeError(f"an override is a 'key.sub=value' string, got {_show(item)} ({type(item).__name__})")
        if "=" not in item:
            raise ConfigError(f"override '{item}' must look like key.sub=value")
        key, raw = item.split("=", 1)
        key = key.strip()
        try:
            value = load_yaml(raw) if raw != "" else ""
        except (_DuplicateKey, _TooDeep) as e:
            raise ConfigError(f"override '{item if len(item) < 80 else item[:60] + '...'}': {e}") from None
        except yaml.YAMLError:
            value = raw
        if raw.strip() == "~" and key in HOME_NOT_NULL:  # YAML's null, but these paths cannot be null:
            value = "~"  # the shell's home folder is meant (train.out_dir=~); expand_home reads it
        quoted = raw.strip()[:1] in ("'", '"')  # name="2024": a string is meant
        # a YAML file's empty section is no keys; an override's would be dropped with no word
        if value is None and dataclasses.is_dataclass(_key_type(key)):
            raise ConfigError(f"override '{item}' gives the section {key} no keys; set its keys ({key}.KEY=VALUE)")
        text_key = _text_key(key)
        if not quoted and isinstance(value, (bool, int, float, datetime.date)) and text_key:
            value = raw.strip()  # name=2024, train.out_dir=2024-12-05: the text as typed (the shell ate the quotes)
        elif isinstance(value, str) and not quoted and not text_key:  # YAML 1.1 reads "3e-3" as text: a number
            try:
                value = float(value) if value.strip().lower() not in ("nan", "inf", "-inf", "+inf") else value
            except ValueError:
                pass
        parts = key.split(".")
        node = nested
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ConfigError(f"override '{item}' sets a sub-key of a value")
        if isinstance(value, dict) and isinstance(node.get(parts[-1]), dict):
            deep_update(node[parts[-1]], value)  # model.gnn.layers=4 model.gnn={dim: 64}: both (layers was dropped)
        else:
            node[parts[-1]] = value
    return nested


def repeated_overrides(overrides: Sequence[str]) -> list[str]:
    """A note per key given more than once in ``overrides`` (the last one wins, as a later YAML file's value
    does; on a command line a key typed twice is most often a slip, so it is said)."""
    values: dict[str, list[str]] = {}
    for item in overrides:
        if isinstance(item, str) and "=" in item:
            key, raw = item.split("=", 1)
            key, leaves = key.strip(), [""]
            if raw.strip().startswith("{"):  # model.gnn={layers: 3}: it gives model.gnn.layers too
                try:
                    value = load_yaml(raw)
                except yaml.YAMLError:
                    value = None
                leaves = ["." + k for k in flatten(value)] if isinstance(value, dict) and value else leaves
            for leaf in leaves:
                values.setdefault(key + leaf, []).append(f"{key}={raw}")
    return [f"{key} is given {len(given)} times ({', '.join(given)}); the last, {given[-1]}, is used"
            for key, given in values.items() if len(given) > 1]


def load_config(path: str | Path | dict | ExperimentConfig | None = None,
                overrides: list[str] | str | None = None) -> ExperimentConfig:
    """Defaults <- YAML file (and its ``_base_`` chain) <- command-line overrides; validated.

    ``path`` may also be a nested dict of keys (as a YAML file holds them) or an ``ExperimentConfig`` (a copy,
    the overrides applied); ``overrides`` a list of ``"key=value"`` strings (one string: one override)."""
    if isinstance(overrides, str):  # one "key=value", not its characters ("override 't' must look like ...")
        overrides = [overrides]
    if overrides is not None and not isinstance(overrides, (list, tuple)):
        raise TypeError(f"overrides must be a list of 'key.sub=value' strings, got {type(overrides).__name__}")
    cfg = ExperimentConfig()
    if isinstance(path, ExperimentConfig):
        cfg = copy.deepcopy(path)
    elif isinstance(path, dict):  # the nested keys of a YAML file, given in Python
        cfg = _merge(cfg, _rename_old_keys(path))
    elif path is not None:
        cfg = _merge(cfg, _read_yaml(as_path(path, "the config file")))
    if overrides:
        cfg = _merge(cfg, parse_overrides(overrides))
    expand_home(cfg)
    validate_config(cfg)
    return cfg


def as_config(cfg: ExperimentConfig | str | Path | dict, who: str) -> ExperimentConfig:
    """``cfg`` for a function that takes a config (``who`` names it): an ``ExperimentConfig`` as it is, a YAML file's
    path or a dict of its keys loaded (``load_config``); anything else a ``TypeError`` naming ``who`` (a path was a
    raw "'str' object has no attribute 'model'" from deep inside)."""
    if isinstance(cfg, ExperimentConfig):
        return cfg
    if isinstance(cfg, (str, Path, dict)):
        return load_config(cfg)
    raise TypeError(f"{who} takes an ExperimentConfig (instagram_hdmap.config.load_config(path)) or a YAML file, got "
                    f"{type(cfg).__name__}")


# the keys that hold a file or folder path: a leading ~ is the user's home, as a shell would read it (a YAML
# file or a quoted override keeps it: train.out_dir=~/runs made a folder named "~" in the working directory)
PATH_KEYS = ("data.dataroot", "data.splits_file", "model.backbone.weights", "train.out_dir", "train.init_from")
# the path keys that cannot be null: a bare ~ override there is the home folder (on the optional ones, such as
# train.init_from=~, it stays YAML's null: none)
HOME_NOT_NULL = ("data.dataroot", "train.out_dir")


def expand_home(cfg: ExperimentConfig) -> None:
    for key in PATH_KEYS:
        section, name = key.rsplit(".", 1)
        obj = functools.reduce(getattr, section.split("."), cfg)
        value = getattr(obj, name)
        if isinstance(value, str) and (value == "~" or value.startswith("~/")):
            setattr(obj, name, os.path.expanduser(value))


def check_ranges(obj: Any, prefix: str = "") -> None:
    """Every key of the (nested) config dataclass ``obj`` declared with ``bounded`` is in its range."""
    for f in dataclasses.fields(obj):
        key, value = prefix + f.name, getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            check_ranges(value, key + ".")
            continue
        rng = f.metadata.get("range")
        if rng is None or value is None:
            continue
        for i, v in enumerate(value) if isinstance(value, tuple) else [(None, value)]:
            if v not in rng:
                where = key if i is None else f"{key}[{i}]"
                note = f" ({rng.note})" if rng.note else ""
                raise ConfigError(f"config key '{where}' must be {rng.describe()}{note}, got {v!r}")


def validate_config(cfg: ExperimentConfig) -> None:
    """Each key in its declared range (``check_ranges``), then the checks across keys."""
    check_ranges(cfg)
    g = cfg.grid
    for name in ("xbound", "ybound"):
        lo, hi = getattr(g, name)
        if not hi > lo:
            raise ConfigError(f"config key 'grid.{name}': upper bound must exceed lower, got {(lo, hi)}")
    gnn = cfg.model.gnn
    if gnn.max_edge_m is not None and gnn.decoder in ("mutual", "official"):
        raise ConfigError("config key 'model.gnn.max_edge_m' is an option of the greedy and classwise decoders; "
                          "set model.gnn.decoder=greedy (or classwise), or max_edge_m=null")
    if gnn.min_vertices > gnn.num_vertices:  # every element needs more vertices than the model keeps: none decoded
        raise ConfigError(f"config key 'model.gnn.min_vertices' is {gnn.min_vertices}, but the model keeps "
                          f"model.gnn.num_vertices={gnn.num_vertices} vertices: no element could ever be decoded "
                          "(each needs min_vertices of them); lower min_vertices or raise num_vertices")
    loss = cfg.loss
    if not any((loss.vertex_weight, loss.distance_weight, loss.adjacency_weight, loss.class_weight)):
        raise ConfigError("config keys 'loss.vertex_weight', 'loss.distance_weight', 'loss.adjacency_weight' and "
                          "'loss.class_weight' are all 0: the loss would be 0 and training would learn nothing; "
                          "give at least one a positive weight")
    d = cfg.data
    if tuple(d.classes) != MAP_CLASSES:
        raise ConfigError(f"config key 'data.classes' must be {list(MAP_CLASSES)}: the local map's classes, in the "
                          f"order of their labels 0, 1, 2 (the names are not free); got {list(d.classes)}")
    lo, hi = d.aug_scale
    if lo > hi:
        raise ConfigError(f"config key 'data.aug_scale': (low, high) with low <= high, got {(lo, hi)}")
    clashes = [what for clash, what in ((d.augment, "data.augment=true (a kept sample would repeat its first "
                                                   "augmentation): set data.augment=false"),
                                        (d.num_workers, f"data.num_workers={d.num_workers} (a worker's copy ends with "
                                                        "its epoch): set data.num_workers=0")) if clash]
    if d.cache_in_memory and clashes:
        raise ConfigError("config key 'data.cache_in_memory' keeps each training sample as first loaded, in the "
                          f"process that loads it; it cannot go with {' or '.join(clashes)}")
    bad = [c for c in d.av2_cameras if c not in AV2_RING_CAMERAS]
    if not d.av2_cameras or bad or len(set(d.av2_cameras)) != len(d.av2_cameras):
        raise ConfigError(f"config key 'data.av2_cameras' must list distinct AV2 ring cameras out of "
                          f"{', '.join(AV2_RING_CAMERAS)}; got {list(d.av2_cameras)}")
    if d.split_scheme == "geo" and d.splits_file is not None:  # two answers to "which scenes"
        raise ConfigError(f"config keys 'data.split_scheme' (geo) and 'data.splits_file' ({d.splits_file}) both choose "
                          "the scenes of each split: set one of them (data.splits_file=null or "
                          "data.split_scheme=official)")
    if d.split_scheme == "geo" and not {d.train_split, d.val_split} <= {"train", "val"}:
        raise ConfigError(f"config key 'data.split_scheme' is geo, whose splits are 'train' and 'val'; got "
                          f"data.train_split={d.train_split!r}, data.val_split={d.val_split!r}")
    if d.dataset == "av2" and d.splits_file is not None:  # it was ignored: every log of the split folder ran
        raise ConfigError(f"config key 'data.splits_file' ({d.splits_file}) chooses nuScenes scenes; an AV2 split is a "
                          "folder of logs (data.train_split / data.val_split name it), so the file would be ignored: "
                          "set data.splits_file=null, or move the logs into the split folders")
    vt = cfg.model.view_transform
    cameras = len(d.av2_cameras) if d.dataset == "av2" else NUSCENES_CAMERA_COUNT
    if vt.kind == "mlp" and vt.num_cameras != cameras:  # its per-camera layers would meet another camera count
        raise ConfigError(f"config key 'model.view_transform.num_cameras' is {vt.num_cameras}, but the MLP view "
                          f"transform (one layer per camera) gets the {cameras} cameras of data.dataset={d.dataset}"
                          + (" (data.av2_cameras)" if d.dataset == "av2" else "")
                          + f": set model.view_transform.num_cameras={cameras}")
    also = cfg.eval.also_protocols
    if cfg.eval.protocol in also or len(set(also)) != len(also):
        raise ConfigError(f"config key 'eval.also_protocols' lists protocols besides eval.protocol="
                          f"{cfg.eval.protocol!r}, each once; got {list(also)}")
    if not cfg.eval.thresholds:
        raise ConfigError("config key 'eval.thresholds' needs at least one Chamfer threshold in metres")
    if len(set(cfg.eval.thresholds)) != len(cfg.eval.thresholds):  # mAP averages over them: one would count twice
        raise ConfigError(f"config key 'eval.thresholds' lists a threshold twice, which mAP (their mean) would count "
                          f"twice; got {list(cfg.eval.thresholds)}")


def config_to_dict(cfg: Any) -> dict:
    """Plain nested dict (tuples as lists), as written to YAML."""

    def plain(v: Any) -> Any:
        if dataclasses.is_dataclass(v):
            return {f.name: plain(getattr(v, f.name)) for f in dataclasses.fields(v)}
        if isinstance(v, (list, tuple)):
            return [plain(x) for x in v]
        return v

    return plain(cfg)


def _rename_old_keys(data: dict) -> dict:
    data = copy.deepcopy(data)
    for old, new in RENAMED_KEYS:
        *path, leaf = old.split(".")
        section = data
        for p in path:
            section = section.get(p) if isinstance(section, dict) else None
        if isinstance(section, dict) and leaf in section:
            value = section.pop(leaf)
            section.setdefault(new.rsplit(".", 1)[1], value)
    return data


def config_from_dict(data: dict) -> ExperimentConfig:
    """A config saved by ``save_config`` / in a checkpoint (renamed keys of older versions accepted)."""
    cfg = _merge(ExperimentConfig(), _rename_old_keys(data))
    validate_config(cfg)
    return cfg


def save_config(cfg: ExperimentConfig, path: str | Path) -> None:
    """Write the fully resolved config as YAML (atomically)."""
    write_text(yaml.dump(config_to_dict(cfg), Dumper=_Dumper, sort_keys=False), path)


def diff_configs(a: ExperimentConfig, b: ExperimentConfig) -> list[str]:
    """Dotted keys whose values differ between two configs."""
    x, y = flatten(config_to_dict(a)), flatten(config_to_dict(b))
    return [key for key in x if x[key] != y.get(key)]
