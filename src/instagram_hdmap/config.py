"""Experiment configuration: nested dataclasses, one per component.

A YAML file holds *overrides only* of the defaults below (the defaults are the paper's main
setting: EfficientNet-B4, LSS, 128x352 images, 60 m x 30 m at 0.15 m, S = 8, N = 400, 7 GNN layers;
configs/paper/table1_b4_lss_128x352.yaml adds what the official code does differently from our
defaults: ImageNet weights, SuperPoint NMS, its matching space and class targets, its decoder, the
raster protocol, ...; benchmarks/README.md, "The paper configs against the official code").
A YAML file may name another one to start from with ``_base_: relative/path.yaml``. Command-line
overrides use dotted keys, ``model.gnn.layers=9``, and are parsed as YAML values.

Unknown keys and values of the wrong type are errors that name the key and list what is valid.

    cfg = load_config("configs/paper/table1_b0_lss_128x352.yaml", ["train.batch_size=8"])
    save_config(cfg, "run/config.yaml"); assert load_config("run/config.yaml") == cfg
"""

from __future__ import annotations

import copy
import dataclasses
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Union

import yaml

from .files import write_text


class UserError(Exception):
    """An error in what the user gave (a path, a file, an argument): the CLI prints it on one line
    and exits with code 2. Library code raises subclasses with messages that say what to fix."""


class ConfigError(UserError, ValueError):
    """A configuration key or value the user must fix."""


# ---------------------------------------------------------------------------------------------
# Components
# ---------------------------------------------------------------------------------------------


@dataclass
class GridConfig:
    """The BEV grid (see geometry.BEVGrid). x points forward, y to the left, metres, ego frame."""

    xbound: tuple[float, float] = (-30.0, 30.0)  # along the driving direction
    ybound: tuple[float, float] = (-15.0, 15.0)  # lateral
    resolution: float = 0.15  # metres per BEV pixel
    cell_size: int = 8  # S: one vertex per SxS cell


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
    train_split: str = "train"
    val_split: str = "val"
    image_size: tuple[int, int] = (128, 352)  # (h, w) fed to the backbone
    # cover: resize to cover (h, w), crop (lift-splat-shoot); contain: resize to fit inside, pad with
    # black (for cameras of different aspect ratios, e.g. AV2's portrait ring_front_center); stretch:
    # resize the whole image to (h, w), each axis on its own (the official InstaGraM / HDMapNet
    # loader: 1600 x 900 -> 352 x 128, no crop; configs/paper)
    image_fit: Literal["cover", "contain", "stretch"] = "cover"
    av2_cameras: tuple[str, ...] = AV2_RING_CAMERAS  # av2: the ring cameras fed to the model, in this order
    av2_frame_step: int = 5  # av2: one lidar sweep in N is a sample (AV2's sweeps come at 10 Hz)
    sample_dist: float = 1.5  # metres between resampled map vertices
    # ped-crossing ground truth (data/local_map.py, docs/conventions.md): "edges", each crossing's two
    # longest edges as open polylines (HDMapNet's and the official InstaGraM code's, the paper's);
    # "union", the rings (exterior and interior) of the crossings' union (MapTR); "each", each
    # crossing's own ring (StreamMapNet, the field's AV2 setting)
    ped_crossing: Literal["edges", "union", "each"] = "edges"
    classes: tuple[str, ...] = ("divider", "ped_crossing", "boundary")
    dt_clip: float = 10.0  # distance transform clipped to [0, dt_clip] BEV pixels
    augment: bool = False  # train-time image augmentation (scale, crop, rotate)
    aug_scale: tuple[float, float] = (0.95, 1.05)  # uniform factor on the resize
    aug_rotate_deg: float = 5.4  # uniform in [-aug_rotate_deg, aug_rotate_deg], about the image centre
    aug_crop_jitter: float = 0.05  # crop window shift, uniform in +-fraction of the image size
    # raise: a UserError naming the file and sample; skip: warn once per bad sample, use the next good one
    on_bad_sample: Literal["raise", "skip"] = "raise"
    num_workers: int = 4


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
    out_channels: int = 256
    # Activation checkpointing of the EfficientNet's MBConv blocks (training only): keep each block's
    # input for backward and recompute the block there, with the same drop-connect masks and without
    # updating BatchNorm statistics twice, so gradients and buffers are bit-identical to the plain run.
    # CPU, 128x352, batch 1 (benchmarks/train_speed.py): peak memory B0 2.04 -> 1.54 GB, B4 3.40 ->
    # 1.97 GB, for +6 % / +22 % step time. Set false when memory is plentiful (a large GPU).
    grad_checkpoint: bool = True
    # name=tiny only: channels of its five stride-2 conv stages (the CPU demo's image encoder)
    tiny_widths: tuple[int, ...] = (8, 16, 24, 32, 48)


@dataclass
class ViewTransformConfig:
    kind: Literal["lss", "ipm", "mlp"] = "lss"
    depth_bound: tuple[float, float, float] = (4.0, 45.0, 1.0)  # LSS depth bins: start, stop, step (m)
    # The view transform writes a BEV grid `bev_downsample` times coarser than the output grid: 2 (our
    # default) splats straight onto the half-resolution grid of F_bev (W/2 x H/2); 1 splats at full
    # resolution and the BEV encoder's stem convolution strides by 2 (the official layout, slower).
    bev_downsample: int = 2
    zbound: tuple[float, float] = (-10.0, 10.0)  # LSS vertical extent of the voxel pillar
    # IPM / MLP ground plane: z = the sample's ground height (batch key ground_height: nuScenes 0,
    # AV2 the road below the rear axle, ~-0.35 m) + this offset (m)
    ipm_height: float = 0.0
    mlp_bev_downsample: int = 5  # HDMapNet MLP: per-camera BEV of (H/5) x (W/5)
    num_cameras: int = 6  # MLP only: one fully connected view transform per camera


@dataclass
class BEVHeadsConfig:
    channels: int = 256  # F_bev channels
    # "3 residual blocks": ResNet-18 stages layer1..3, two BasicBlocks each, strides 1, 2, 2
    stage_channels: tuple[int, ...] = (64, 128, 256)
    head_channels: int = 128  # hidden width of the vertex and distance-transform heads
    # the distance-transform (edge map) head and its loss; false: no head, no pred_distance, no
    # loss_distance (the official visual-descriptor variant of Fig. 7, which needs embedding pe+vd)
    distance_head: bool = True


@dataclass
class GraphHeadConfig:
    num_vertices: int = 400  # N, top-N vertices fed to the GNN
    conf_threshold: float = 0.01
    # BEV pixels: a cell's vertex within this distance of a stronger one in a neighbouring cell is
    # dropped (0: one vertex per cell only, the paper's text; models/vertices.py)
    nms_radius: float = 0.0
    # how nms_radius suppresses: "cells" (ours: Euclidean distance to a stronger winner of one of the
    # 8 neighbouring cells, one pass) or "superpoint" (SuperPoint's simple_nms on the map of cell
    # winners: (2r+1)^2 max-pool window, two rescue passes; the official code, radius S/2 px)
    nms: Literal["cells", "superpoint"] = "cells"
    embedding: Literal["pe+dt", "pe", "dt", "pe+vd"] = "pe+dt"
    # pe+vd: where the visual descriptor is read from F_bev: "vertex" (bilinear at the vertex) or
    # "cell" (F_bev resized to the cell grid, the vertex's cell: the official code)
    vd_sampling: Literal["vertex", "cell"] = "vertex"
    dim: int = 256  # D
    pe_frequencies: int = 10  # sinusoidal positional encoding bands per coordinate
    layers: int = 7  # L attentional message-passing layers (0-11 in the paper)
    heads: int = 4
    sinkhorn_iters: int = 100
    # gradient through the Sinkhorn: "implicit" (fixed-point differentiation: one small solve per
    # sample, ~none of the memory) or "unrolled" (through every iteration, as SuperGlue); the
    # forward is the same (models/matching.py)
    sinkhorn_grad: Literal["implicit", "unrolled"] = "implicit"
    match_threshold: float = 0.1  # adjacency probability to follow an edge at inference
    # inference decoder of the adjacency (postprocess.py): "greedy" (strongest pairs first, degree
    # <= 2, one class-agnostic graph), "classwise" (the same per class, over the vertices whose class
    # probability is >= class_min_prob), "mutual" (the official rule: each end ranks the other among
    # its two best, both ends of the same argmax class, confidence = mean class probability) or
    # "official" (the official export's walk over that rule, quirks included: it drops the last
    # vertex of every walk)
    decoder: Literal["classwise", "greedy", "mutual", "official"] = "greedy"
    class_min_prob: float = 0.05  # classwise: a vertex takes part in class k's graph if p_k >= this
    # greedy: an edge needs both vertices' argmax class to agree (mutual and official always do)
    same_class_edges: bool = False
    max_edge_m: float | None = None  # greedy / classwise: no edge longer than this (metres)
    min_vertices: int = 2  # a decoded instance needs at least this many vertices


@dataclass
class ModelConfig:
    backbone: BackboneConfig = field(default_factory=BackboneConfig)
    view_transform: ViewTransformConfig = field(default_factory=ViewTransformConfig)
    bev_heads: BEVHeadsConfig = field(default_factory=BEVHeadsConfig)
    gnn: GraphHeadConfig = field(default_factory=GraphHeadConfig)


@dataclass
class LossConfig:
    vertex_weight: float = 1.0  # lambda_1, vertex cross-entropy over S^2 + 1
    distance_weight: float = 1.0  # lambda_2, distance-transform L2
    adjacency_weight: float = 5e-3  # lambda_3, bidirectional adjacency NLL
    class_weight: float = 1e-2  # lambda_4, vertex class NLL
    match_dist: float = 1.5  # D_0, metres: a predicted vertex farther from every GT vertex is unmatched
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
    epochs: int = 30
    batch_size: int = 32  # in total, over all processes
    lr: float = 1e-3
    weight_decay: float = 1e-7
    # LR schedule as a function of progress = max(steps / total steps, elapsed / time budget)
    # (schedule.py): "step" decays x lr_gamma every lr_step epochs' worth of progress (the paper's
    # StepLR), "cosine" to lr * min_lr_factor; both after a linear warm-up over `warmup` progress
    schedule: Literal["step", "cosine"] = "step"
    lr_step: int = 10  # epochs between decays
    lr_gamma: float = 0.1
    warmup: float = 0.0  # fraction of progress
    min_lr_factor: float = 0.0  # cosine only
    grad_clip: float = 5.0
    amp: Literal["none", "bf16", "fp16"] = "none"
    seed: int = 0
    on_nonfinite: Literal["stop", "skip"] = "stop"
    log_every: int = 10
    val_every: int = 1  # epochs
    max_steps: int | None = None  # stop after this many steps (tests); does not shorten the schedule
    # wall-time budget of the training loop: the schedule completes within it (fewer steps on a
    # slower machine) and training stops when it is spent
    time_budget_min: float | None = None
    checkpoint_every: int = 500  # steps between mid-epoch saves of last.pt (0: epoch ends only)
    deterministic: bool = False  # torch.use_deterministic_algorithms (exact resume on CPU)
    device: Literal["auto", "cpu", "cuda"] = "auto"
    # torch intra-op threads of a CPU training run; null = the cores this process may use minus the
    # data workers (>= 1), unless OMP_NUM_THREADS is set. Two cores shared by two torch threads and
    # a data worker ran the demo 12 % slower than one thread (benchmarks/torch_builds.py)
    cpu_threads: int | None = None


@dataclass
class EvalConfig:
    protocol: Literal["vector", "raster"] = "vector"
    thresholds: tuple[float, ...] = (0.5, 1.0, 1.5)
    batch_size: int = 4
    # raster protocol only: "ascending" reproduces the reference's PR curve order (a bug the
    # InstaGraM paper's numbers carry), "descending" fixes it
    rank_by: Literal["ascending", "descending"] = "ascending"
    fix_instance_ids: bool = False  # raster only: int32 ids, each instance keeps its own confidence
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


def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    if origin in (Union, types.UnionType):
        return " or ".join(_type_name(a) for a in typing.get_args(tp))
    if tp is type(None):
        return "null"
    if origin is tuple:
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"list of {_type_name(args[0])}"
        return f"list of {len(args)} ({', '.join(_type_name(a) for a in args)})"
    return getattr(tp, "__name__", str(tp))


def _coerce(value: Any, tp: Any, key: str) -> Any:
    """Check ``value`` against the annotation ``tp``; return it in canonical form (tuples)."""
    origin = typing.get_origin(tp)
    bad = ConfigError(f"config key '{key}': expected {_type_name(tp)}, got {value!r} ({type(value).__name__})")
    if origin is Literal:
        if value not in typing.get_args(tp):
            raise bad
        return value
    if origin in (Union, types.UnionType):
        for arg in typing.get_args(tp):
            try:
                return _coerce(value, arg, key)
            except ConfigError:
                continue
        raise bad
    if tp is type(None):
        if value is not None:
            raise bad
        return None
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise bad
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], f"{key}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise bad
        return tuple(_coerce(v, a, f"{key}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
    if tp is bool:
        if not isinstance(value, bool):
            raise bad
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise bad
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise bad
        return value
    raise ConfigError(f"config key '{key}': unsupported annotation {tp!r}")


def _merge(obj: Any, updates: dict, prefix: str = "") -> Any:
    """Return a copy of dataclass ``obj`` with the nested ``updates`` applied and checked."""
    if not isinstance(updates, dict):
        raise ConfigError(f"config section '{prefix.rstrip('.') or '<root>'}' must be a mapping, got {updates!r}")
    hints = typing.get_type_hints(type(obj))
    names = [f.name for f in dataclasses.fields(obj)]
    changes = {}
    for name, value in updates.items():
        key = prefix + str(name)
        if name not in names:
            raise ConfigError(
                f"unknown config key '{key}'; valid keys of '{prefix.rstrip('.') or '<root>'}': {', '.join(names)}"
            )
        current = getattr(obj, name)
        if dataclasses.is_dataclass(current):
            changes[name] = _merge(current, value, key + ".")
        else:
            changes[name] = _coerce(value, hints[name], key)
    return dataclasses.replace(obj, **changes)


def _read_yaml(path: Path, seen: tuple[Path, ...] = ()) -> dict:
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}")
    if path.resolve() in seen:
        raise ConfigError(f"config file {path} includes itself through _base_")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as e:
        raise ConfigError(f"config file {path} is not valid YAML: {e}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"config file {path} must hold a mapping at the top level")
    base = data.pop("_base_", None)
    if base is None:
        return data
    merged = _read_yaml(path.parent / base, (*seen, path.resolve()))
    deep_update(merged, data)
    return merged


def deep_update(dst: dict, src: dict) -> None:
    """Merge the nested dict ``src`` into ``dst`` in place (``src`` wins)."""
    for k, v in src.items():
        if isinstance(v, dict) and isinstance(dst.get(k), dict):
            deep_update(dst[k], v)
        else:
            dst[k] = v


def parse_overrides(overrides: list[str]) -> dict:
    """``["model.gnn.layers=9", "data.image_size=[256,704]"]`` -> nested dict of YAML values."""
    nested: dict = {}
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"override '{item}' must look like key.sub=value")
        key, raw = item.split("=", 1)
        try:
            value = yaml.safe_load(raw) if raw != "" else ""
        except yaml.YAMLError:
            value = raw
        if isinstance(value, str):  # YAML 1.1 reads "3e-3" as a string; a number is meant
            try:
                value = float(value) if value.strip().lower() not in ("nan", "inf", "-inf", "+inf") else value
            except ValueError:
                pass
        parts = key.strip().split(".")
        node = nested
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ConfigError(f"override '{item}' sets a sub-key of a value")
        node[parts[-1]] = value
    return nested


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> ExperimentConfig:
    """Defaults <- YAML file (and its ``_base_`` chain) <- command-line overrides; validated."""
    cfg = ExperimentConfig()
    if path is not None:
        cfg = _merge(cfg, _read_yaml(Path(path)))
    if overrides:
        cfg = _merge(cfg, parse_overrides(overrides))
    validate_config(cfg)
    return cfg


def validate_config(cfg: ExperimentConfig) -> None:
    """Cross-field checks that a single type annotation cannot express."""
    g = cfg.grid
    for name in ("xbound", "ybound"):
        lo, hi = getattr(g, name)
        if not hi > lo:
            raise ConfigError(f"config key 'grid.{name}': upper bound must exceed lower, got {(lo, hi)}")
    if g.resolution <= 0:
        raise ConfigError(f"config key 'grid.resolution' must be > 0, got {g.resolution}")
    if g.cell_size < 1:
        raise ConfigError(f"config key 'grid.cell_size' must be >= 1, got {g.cell_size}")
    if cfg.model.gnn.num_vertices <= 0:
        raise ConfigError(f"config key 'model.gnn.num_vertices' must be > 0, got {cfg.model.gnn.num_vertices}")
    if not 0 <= cfg.model.gnn.layers:
        raise ConfigError(f"config key 'model.gnn.layers' must be >= 0, got {cfg.model.gnn.layers}")
    gnn = cfg.model.gnn
    if not 0 < gnn.match_threshold < 1:
        raise ConfigError(f"config key 'model.gnn.match_threshold' is an adjacency probability: it must be in (0, 1), "
                          f"got {gnn.match_threshold}")
    if gnn.max_edge_m is not None and not gnn.max_edge_m > 0:
        raise ConfigError(f"config key 'model.gnn.max_edge_m' must be > 0 metres (or null: no limit), "
                          f"got {gnn.max_edge_m}")
    if gnn.max_edge_m is not None and gnn.decoder in ("mutual", "official"):
        raise ConfigError("config key 'model.gnn.max_edge_m' is an option of the greedy and classwise decoders; "
                          "set model.gnn.decoder=greedy (or classwise), or max_edge_m=null")
    if gnn.min_vertices < 2:
        raise ConfigError(f"config key 'model.gnn.min_vertices' must be >= 2 (an instance is at least one edge), "
                          f"got {gnn.min_vertices}")
    if not 0 <= gnn.class_min_prob < 1:
        raise ConfigError(f"config key 'model.gnn.class_min_prob' is a class probability: it must be in [0, 1), "
                          f"got {gnn.class_min_prob}")
    h, w = cfg.data.image_size
    if h <= 0 or w <= 0:
        raise ConfigError(f"config key 'data.image_size' must be positive, got {(h, w)}")
    d = cfg.data
    if d.av2_frame_step < 1:
        raise ConfigError(f"config key 'data.av2_frame_step' must be >= 1, got {d.av2_frame_step}")
    bad = [c for c in d.av2_cameras if c not in AV2_RING_CAMERAS]
    if not d.av2_cameras or bad or len(set(d.av2_cameras)) != len(d.av2_cameras):
        raise ConfigError(f"config key 'data.av2_cameras' must list distinct AV2 ring cameras out of "
                          f"{', '.join(AV2_RING_CAMERAS)}; got {list(d.av2_cameras)}")
    t = cfg.train
    if t.time_budget_min is not None and not t.time_budget_min > 0:
        raise ConfigError(f"config key 'train.time_budget_min' must be > 0 (or null for none), got {t.time_budget_min}")
    if t.max_steps is not None and t.max_steps <= 0:
        raise ConfigError(f"config key 'train.max_steps' must be > 0 (or null), got {t.max_steps}")
    if t.cpu_threads is not None and t.cpu_threads < 1:
        raise ConfigError(f"config key 'train.cpu_threads' must be >= 1 (or null: automatic), got {t.cpu_threads}")
    if not 0 <= t.warmup < 1:
        raise ConfigError(f"config key 'train.warmup' must be in [0, 1) (a fraction of training), got {t.warmup}")
    if t.lr_step < 1:
        raise ConfigError(f"config key 'train.lr_step' must be >= 1 (epochs between decays), got {t.lr_step}")
    also = cfg.eval.also_protocols
    if cfg.eval.protocol in also or len(set(also)) != len(also):
        raise ConfigError(f"config key 'eval.also_protocols' lists protocols besides eval.protocol="
                          f"{cfg.eval.protocol!r}, each once; got {list(also)}")
    if any(t <= 0 for t in cfg.eval.thresholds):
        raise ConfigError(f"config key 'eval.thresholds' must be > 0, got {cfg.eval.thresholds}")


def config_to_dict(cfg: Any) -> dict:
    """Plain nested dict (tuples as lists), as written to YAML."""

    def plain(v: Any) -> Any:
        if dataclasses.is_dataclass(v):
            return {f.name: plain(getattr(v, f.name)) for f in dataclasses.fields(v)}
        if isinstance(v, (list, tuple)):
            return [plain(x) for x in v]
        return v

    return plain(cfg)


# Keys renamed since a release: (old dotted key, new dotted key). Old saved configs still load.
RENAMED_KEYS = (("train.max_minutes", "train.time_budget_min"),)


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
    write_text(yaml.safe_dump(config_to_dict(cfg), sort_keys=False), path)


# --- dotted keys ("model.gnn.layers") of nested config dicts -----------------------------------------


def flatten(nested: dict, prefix: str = "") -> dict[str, Any]:
    """``{"model": {"gnn": {"layers": 7}}}`` -> ``{"model.gnn.layers": 7}`` (leaves in order)."""
    out: dict[str, Any] = {}
    for k, v in nested.items():
        out.update(flatten(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


def get_key(nested: dict, dotted: str) -> Any:
    """The value at ``dotted`` (``"model.gnn.layers"``) of a nested dict."""
    for part in dotted.split("."):
        nested = nested[part]
    return nested


def set_key(nested: dict, dotted: str, value: Any) -> None:
    """Set the value at ``dotted`` of a nested dict (its parents must exist)."""
    *parents, last = dotted.split(".")
    for part in parents:
        nested = nested[part]
    nested[last] = value


def is_under(key: str, prefixes) -> bool:
    """``key`` is one of ``prefixes`` or lies below one: ``is_under("model.gnn.layers", ["model"])``."""
    return any(key == p or key.startswith(p + ".") for p in prefixes)


def diff_configs(a: ExperimentConfig, b: ExperimentConfig) -> list[str]:
    """Dotted keys whose values differ between two configs."""
    out: list[str] = []

    def walk(x: Any, y: Any, prefix: str) -> None:
        if isinstance(x, dict):
            for k in x:
                walk(x[k], y.get(k), f"{prefix}{k}.")
        elif x != y:
            out.append(prefix.rstrip("."))

    walk(config_to_dict(a), config_to_dict(b), "")
    return out
