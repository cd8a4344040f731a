"""A trained model for inference: the config keys that define a model, loading a checkpoint or an
ONNX export, and a perfect model's outputs built from the GT.

    model, cfg, notes = load_model("runs/x/best.pt", load_config("configs/synthetic/tiny.yaml"))
    onnx_model = OnnxModel("model.onnx", cfg)      # the same output dict, from onnxruntime
    outputs = gt_outputs(batch, grid, num_classes)  # what a perfect model would output

``MODEL_KEYS`` is the one list of the config keys that define a model: its weights and how its
outputs are read (the grid, the model, the image size, the classes, the distance-transform clip, the
order of the AV2 cameras).
``predict``/``evaluate`` take them from the config saved in the checkpoint (``inference_config``),
``export-onnx`` bakes them into the graph (``baked_config``, less the decoding keys the graph does not
read) and ``train --resume`` refuses a checkpoint that differs on them (train.py, with the keys that
define the training targets).

The ONNX side (``OnnxModel``, ``check_export``): an ``export-onnx`` file (deploy.py writes it; the
interface is ``INPUT_NAMES`` -> ``OUTPUT_NAMES``, docs/deploy.md) run by onnxruntime on the CPU, after
its metadata has been checked against the config. ``onnx`` / ``onnxruntime`` are the optional extra
``[deploy]``: ``require_onnx`` imports them where they are needed, nowhere else.
"""

from __future__ import annotations

import copy
import hashlib
import json
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from .assignment import assign, target_log_assignment
from .checkpoint import CheckpointError, load_checkpoint
from .config import (
    ExperimentConfig,
    UserError,
    as_config,
    config_from_dict,
    config_to_dict,
    deep_update,
    diff_configs,
    flatten,
    get_key,
    is_under,
    parse_overrides,
    set_key,
)
from .distributed import resolve_device
from .engine import move_to
from .files import as_path
from .geometry import BEVGrid
from .models import build_model
from .models.temporal import MEMORY_KEYS
from .models.vertices import vertex_heatmap
from .models.view_transform import CALIBRATION_KEYS
from .postprocess import DECODE_KEYS
from .precision import calibration_batches, resolve_precision, with_precision

# Config keys that define a model: its weights and how its outputs are read.
# data.av2_cameras: the order of the camera tensors (the MLP view transform has one layer per camera)
MODEL_KEYS = ("grid", "model", "data.image_size", "data.classes", "data.dt_clip", "data.av2_cameras")
# What inference takes from the checkpoint: the MODEL_KEYS and how the images were fitted to the model's
# size in training (data.image_fit: cover crops, contain pads; the other would show the model images unlike
# those it learnt from)
CHECKPOINT_KEYS = (*MODEL_KEYS, "data.image_fit")
# The decoding options of Mapper.from_checkpoint(path, **decode_overrides): model.gnn.<name>.
DECODE_OPTIONS = tuple(key.rsplit(".", 1)[1] for key in DECODE_KEYS)
# Of those, the keys an exported graph does not read (post-processing, training-only settings; the AV2 camera
# order, which the export records in its inference metadata and check_export compares).
NOT_BAKED = (*DECODE_KEYS, "data.av2_cameras", "model.backbone.weights", "model.backbone.from_scratch",
             "model.backbone.grad_checkpoint", "model.temporal.drop_prob", "model.temporal.persist_frames",
             "model.temporal.persist_decay", "model.temporal.persist_match_m")

# The exported graph's interface (docs/deploy.md), in argument order.
INPUT_NAMES = ("images", *CALIBRATION_KEYS)
OUTPUT_NAMES = ("pred_vertex_logits", "pred_heatmap", "pred_distance", "pred_vertices_px", "pred_vertex_mask",
                "pred_vertex_scores", "pred_class_log_probs", "pred_log_assignment")
# A temporal model's graph (docs/temporal.md) also takes the frame's pose and place in its scene and the
# memory (models/temporal.MEMORY_KEYS as memory_<key>), and returns the status and the new memory
# (next_memory_<key>: ONNX value names are unique).
TEMPORAL_INPUTS = ("ego_pose", "scene_start", "frame_index")
MEMORY_NAMES = tuple(f"memory_{k}" for k in MEMORY_KEYS)
NEXT_MEMORY_NAMES = tuple(f"next_memory_{k}" for k in MEMORY_KEYS)
EXPORT_FORMAT = 2  # bump when the graph's inputs, outputs or their meaning change (2: ground_height)
META_FORMAT = "instagram_hdmap.export_format"
META_CONFIG = "instagram_hdmap.config"
META_CONFIG_SHA = "instagram_hdmap.config_sha256"
META_SHAPES = "instagram_hdmap.shapes"
META_SOURCE = "instagram_hdmap.source"
META_INFERENCE = "instagram_hdmap.inference"  # what the graph does not bake in: the rig, the image fit, decoding
# SHA-256 of the serialized graph (its nodes and weights): ONNX files carry no checksum of their own, so bits
# flipped on disk or in a transfer would otherwise run as wild weights (exports written before it: not checked)
META_GRAPH_SHA = "instagram_hdmap.graph_sha256"
DEPLOY_EXTRA = 'pip install -e ".[deploy]"'


def is_temporal_config(cfg: ExperimentConfig) -> bool:
    return cfg.model.temporal.memory != "none"


def input_names(cfg: ExperimentConfig) -> tuple[str, ...]:
    """The exported graph's inputs: ``INPUT_NAMES``, and for a temporal model ``TEMPORAL_INPUTS`` and
    ``MEMORY_NAMES``."""
    return (*INPUT_NAMES, *TEMPORAL_INPUTS, *MEMORY_NAMES) if is_temporal_config(cfg) else INPUT_NAMES


def output_names(cfg: ExperimentConfig) -> tuple[str, ...]:
    """``OUTPUT_NAMES`` of a model built from ``cfg``: without ``pred_distance`` when it has no distance
    head (``model.bev_heads.distance_head=false``); a temporal model's add ``memory_status`` and
    ``NEXT_MEMORY_NAMES``."""
    names = tuple(k for k in OUTPUT_NAMES if k != "pred_distance" or cfg.model.bev_heads.distance_head)
    return (*names, "memory_status", *NEXT_MEMORY_NAMES) if is_temporal_config(cfg) else names


class DeployError(UserError):
    """A missing optional extra, an unsupported export setting, an ONNX file that does not fit."""


# --- a checkpoint ------------------------------------------------------------------------------------


def inference_config(
    cfg: ExperimentConfig, saved: dict, overrides: Sequence[str] = (), source: str = "the checkpoint"
) -> tuple[ExperimentConfig, list[str]]:
    """The config to run a checkpoint with: ``cfg`` (CONFIG file + overrides) with the ``CHECKPOINT_KEYS``
    of the checkpoint's ``saved`` config, then the command-line ``overrides`` again (they win).

    Returns the config and human-readable notes on where the CONFIG file was overruled.
    """
    trained = saved_config(saved, source)
    explicit = parse_overrides(list(overrides))
    explicit_keys = list(flatten(explicit))
    merged, trained_d = config_to_dict(cfg), config_to_dict(trained)
    for key in CHECKPOINT_KEYS:
        set_key(merged, key, copy.deepcopy(get_key(trained_d, key)))
    deep_update(merged, explicit)
    out = config_from_dict(merged)
    notes = []
    ignored = [k for k in diff_configs(cfg, trained)
               if is_under(k, CHECKPOINT_KEYS) and not is_under(k, explicit_keys)]
    if ignored:
        cfg_d = config_to_dict(cfg)
        notes.append("the CONFIG file's model settings differ from those the checkpoint was trained with; using "
                     "the checkpoint's: " + ", ".join(f"{k}={get_key(trained_d, k)!r} (CONFIG: {get_key(cfg_d, k)!r})"
                                                       for k in ignored))
    changed = [k for k in diff_configs(trained, out) if is_under(k, CHECKPOINT_KEYS)]
    if changed:
        out_d = config_to_dict(out)
        notes.append("overriding the checkpoint's " + ", ".join(
            f"{k}={get_key(trained_d, k)!r} with {get_key(out_d, k)!r}" for k in changed))
    if trained.data.ped_crossing != out.data.ped_crossing:  # the GT's convention, not the model's: the CONFIG's wins
        notes.append(f"the checkpoint was trained on data.ped_crossing={trained.data.ped_crossing!r} crossings; the GT "
                     f"here draws them as {out.data.ped_crossing!r} (this config's), so its crossings are scored "
                     f"against another convention than the model learnt (docs/conventions.md); data.ped_crossing="
                     f"{trained.data.ped_crossing} scores them as trained")
    same_world = all(getattr(trained.data, k) == getattr(out.data, k) for k in ("dataset", "dataroot", "version",
                                                                               "splits_file", "split_scheme"))
    if same_world and out.data.val_split == trained.data.train_split:  # data.val_split=train: seen samples
        notes.append(f"data.val_split={out.data.val_split!r} is the split the checkpoint was trained on (the same "
                     f"dataroot {out.data.dataroot}): scores on it are of samples the model has seen, not unseen ones")
    return out, notes


def saved_config(saved: dict, source: str = "the checkpoint") -> ExperimentConfig:
    """The config saved in a checkpoint, or a ``CheckpointError`` naming ``source``."""
    try:
        return config_from_dict(saved)
    except UserError as e:
        raise CheckpointError(f"{source} holds a config this version cannot read: {e}") from None


def weight_differences(expected: Mapping[str, torch.Tensor], got: Mapping[str, torch.Tensor], shown: int = 3
                       ) -> list[str]:
    """Where two state dicts differ: keys only one has, and keys of another shape (``shown`` of each)."""
    def some(keys: list[str]) -> str:
        return ", ".join(keys[:shown]) + (f" and {len(keys) - shown} more" if len(keys) > shown else "")

    missing = [k for k in expected if k not in got]
    unexpected = [k for k in got if k not in expected]
    shapes = [f"{k} {list(got[k].shape)} (model {list(expected[k].shape)})" for k in expected
              if k in got and hasattr(got[k], "shape") and got[k].shape != expected[k].shape]
    parts = {"missing": missing, "not in the model:": unexpected, "other shapes:": shapes}
    return [f"{label} {some(keys)}" for label, keys in parts.items() if keys]


def load_weights(model: torch.nn.Module, state: dict, checkpoint: str | Path) -> torch.nn.Module:
    """``model`` with the checkpoint's weights, or a one-line ``CheckpointError`` naming the keys that
    differ: they do not fit the model built from the config (another architecture, an override of a
    layer size)."""
    differ = weight_differences(model.state_dict(), state["model"])
    try:
        if differ:
            raise RuntimeError
        model.load_state_dict(state["model"])
    except RuntimeError as e:
        reason = "; ".join(differ) or " ".join(str(e).split())[:300]
        raise CheckpointError(
            f"the weights in {checkpoint} do not fit the model built from its config and the overrides ({reason}); "
            f"use the config the checkpoint was trained with, and drop overrides that change layer sizes"
        ) from None
    return model


def load_model(
    checkpoint: str | Path, cfg: ExperimentConfig, overrides: Sequence[str] = (), device: torch.device | None = None,
    precision: str = "fp32", calibration: list[dict] | None = None, compile_backbone: bool = False,
) -> tuple[torch.nn.Module, ExperimentConfig, list[str]]:
    """Build the model of ``checkpoint`` (see ``inference_config``), load its weights, eval mode, in
    ``precision`` (precision.py: fp32, bf16, int8 or auto; int8 calibrates on ``calibration`` batches, by default
    on the config's training samples). ``compile_backbone``: the image backbone through ``torch.compile``
    (``precision.compile_backbone``: the first batch compiles it, tens of seconds).

    Returns ``(model, config, notes)``; ``device`` defaults to ``train.device`` ("auto": CUDA if any).
    Raises ``CheckpointError`` for a missing / corrupt checkpoint or weights that do not fit. ``cfg``: an
    ``ExperimentConfig`` or a YAML file.
    """
    cfg = as_config(cfg, "load_model")  # a path was a raw "'str' object does not support item assignment"
    state = load_checkpoint(checkpoint)
    notes: list[str] = []
    if isinstance(state.get("config"), dict):
        cfg, notes = inference_config(cfg, state["config"], overrides, f"checkpoint {checkpoint}")
    else:
        notes.append(f"checkpoint {checkpoint} holds no config; building the model from the CONFIG file")
    model = load_weights(build_model(cfg), state, checkpoint)
    device = device if device is not None else resolve_device(cfg.train.device)
    chosen, precision_notes = resolve_precision(precision, torch.device(device))
    if chosen == "int8" and calibration is None:
        calibration = calibration_batches(cfg, device=device)
    model = with_precision(model.eval().to(device), chosen, calibration, compile_backbone)
    if compile_backbone:
        precision_notes.append("the image backbone runs through torch.compile: the first batch compiles it (tens "
                               "of seconds), the later ones run its compiled kernels")
    return model, cfg, notes + precision_notes


# --- predictions from the GT ---------------------------------------------------------------------------


@torch.no_grad()
def gt_outputs(batch: dict, grid: BEVGrid, num_classes: int, floor: float = 1e-6) -> dict[str, torch.Tensor]:
    """The outputs (docs/conventions.md keys) of a perfect model for the batch's GT targets.

    Vertices = the GT graph vertices (M of them, so N = M), scores 1, class = the GT class, log
    assignment = ``target_log_assignment`` of the assignment targets (each vertex matched to itself),
    vertex logits = the log of the one-hot ``gt_vertex_cells``, distance = ``gt_distance``.
    ``floor`` keeps every log finite. Post-processing these gives back the GT graph's polylines, so
    the pictures and the evaluation path can be checked without a trained model.
    """
    S = grid.cell_size
    verts = batch["gt_vertices_px"].float()  # [B, M, 2]
    mask = batch["gt_vertex_mask"].bool()  # [B, M]
    # a vertex's nearest GT vertex is itself (distance 0); distinct vertices are >= 1 px apart
    asg = assign(verts, mask, verts, mask, batch["gt_vertex_labels"], batch["gt_vertex_next"],
                 batch["gt_vertex_prev"], grid, match_dist_m=0.5 * grid.resolution)
    cells = F.one_hot(batch["gt_vertex_cells"].long(), S * S + 1).permute(0, 3, 1, 2).float()  # [B, S*S+1, Hc, Wc]
    vertex_logits = (cells * (1 - floor) + floor / (S * S + 1)).log()
    labels = F.one_hot(batch["gt_vertex_labels"].long().clamp(min=0), num_classes).float()  # [B, M, K]
    return {
        "pred_vertex_logits": vertex_logits,
        "pred_heatmap": vertex_heatmap(vertex_logits, S),
        "pred_distance": batch["gt_distance"].float(),
        "pred_vertices_px": verts,
        "pred_vertex_mask": mask,
        "pred_vertex_scores": mask.float(),
        "pred_class_log_probs": (labels * (1 - floor) + floor / num_classes).log(),
        "pred_log_assignment": target_log_assignment(asg["target_next"], asg["target_prev"]),
    }


# --- an ONNX export -------------------------------------------------------------------------------------


def require_onnx(export: bool = False):
    """``(onnx, onnxruntime)`` (and, for ``export``, the exporter's onnxscript), or a ``DeployError``
    naming the extra to install."""
    try:
        import onnx
        import onnxruntime

        if export:
            import onnxscript  # noqa: F401  (torch.onnx.export(dynamo=True) imports it)
    except ImportError as e:
        raise DeployError(f"ONNX export and inference need the optional packages onnx, onnxruntime and "
                          f"onnxscript ({e.name} is not installed): {DEPLOY_EXTRA}") from None
    return onnx, onnxruntime


def baked_config(cfg: ExperimentConfig) -> dict:
    """The flat ``{dotted key: value}`` of the config keys the exported graph bakes in (JSON types)."""
    flat = flatten(json.loads(json.dumps(config_to_dict(cfg))))
    # a single-frame graph bakes no model.temporal key: its exports from before the key existed still fit
    skip = NOT_BAKED if is_temporal_config(cfg) else (*NOT_BAKED, "model.temporal")
    return {k: v for k, v in sorted(flat.items()) if is_under(k, MODEL_KEYS) and not is_under(k, skip)}


def config_sha256(baked: dict) -> str:
    return hashlib.sha256(json.dumps(baked, sort_keys=True).encode()).hexdigest()


def config_differences(expected: dict, actual: dict) -> list[str]:
    """``key=value (other: value)`` for every baked key whose values differ."""
    keys = sorted(set(expected) | set(actual))
    return [f"{k}={actual.get(k, '<absent>')!r} (CONFIG: {expected.get(k, '<absent>')!r})"
            for k in keys if expected.get(k, "<absent>") != actual.get(k, "<absent>")]


def read_metadata(path: str | Path) -> dict[str, str]:
    """The ``metadata_props`` of an ONNX file (external weight files are not read); an inline graph is checked
    against the SHA-256 its export stored (``META_GRAPH_SHA``)."""
    onnx, _ = require_onnx()
    path = as_path(path, "ONNX file")
    if path.exists() and not path.is_file() and not path.is_dir():  # said "not found", though it is there
        raise DeployError(f"ONNX file {path} is a pipe or a device, not a file (a process substitution <(...), "
                          "/dev/stdin): it is read more than once (its metadata, then onnxruntime); save it to a file "
                          "first")
    if not path.is_file():
        raise DeployError(f"ONNX file not found: {path}" + (" (it is a folder)" if path.is_dir() else ""))
    try:
        proto = onnx.load(str(path), load_external_data=False)
    except Exception as e:  # any unreadable file is a user error
        with open(path, "rb") as f:
            head = f.read(4)
        if head == b"PK\x03\x04" or head[:1] == b"\x80":  # torch.save's zip (or a legacy pickle): a checkpoint
            raise DeployError(f"{path} is a PyTorch checkpoint, not an ONNX file: give it as a checkpoint "
                              "(--checkpoint, Mapper.from_checkpoint), or export it with: instagram-hdmap export-onnx "
                              "CONFIG --checkpoint CKPT --out FILE") from None
        raise DeployError(f"{path} is not a readable ONNX file ({type(e).__name__}: {str(e)[:200]})") from None
    meta = {p.key: p.value for p in proto.metadata_props}
    if META_GRAPH_SHA in meta and graph_sha256(proto) != meta[META_GRAPH_SHA]:
        raise DeployError(f"{path} is damaged: its graph (nodes and weights) does not match the SHA-256 stored when it "
                          "was exported (bits changed on disk or in a transfer, or an edited file); use another copy "
                          "or export the checkpoint again")
    return meta


def graph_sha256(proto) -> str:
    """SHA-256 of an ONNX model's graph (nodes and weights; not the metadata that stores it)."""
    return hashlib.sha256(proto.graph.SerializeToString(deterministic=True)).hexdigest()


def read_export(path: str | Path) -> dict:
    """The metadata of an export of this format: ``{"config": baked config, "shapes", "source"}``;
    otherwise a one-line ``DeployError``: not ours, an older (or newer) export format, a damaged file."""
    meta = read_metadata(path)
    redo = "export it again with: instagram-hdmap export-onnx CONFIG --checkpoint CKPT --out FILE"
    if META_FORMAT not in meta:
        raise DeployError(f"{path} was not written by instagram-hdmap export-onnx (no {META_FORMAT} in its "
                          f"metadata); {redo}")
    if meta[META_FORMAT] != str(EXPORT_FORMAT):
        raise DeployError(f"{path} is an export of format {meta[META_FORMAT]}; this version reads format "
                          f"{EXPORT_FORMAT} only: {redo}")
    try:
        stored = json.loads(meta[META_CONFIG])
        shapes = json.loads(meta[META_SHAPES])
    except (KeyError, json.JSONDecodeError) as e:
        raise DeployError(f"{path}: damaged export metadata ({e}); {redo}") from None
    if config_sha256(stored) != meta.get(META_CONFIG_SHA):
        raise DeployError(f"{path}: the stored config does not match its SHA-256 (a damaged or edited file); {redo}")
    return {"config": stored, "shapes": shapes, "source": json.loads(meta.get(META_SOURCE, "{}")),
            "inference": json.loads(meta.get(META_INFERENCE, "{}"))}


def inference_metadata(cfg: ExperimentConfig) -> dict:
    """What an export records beside its baked config so that ``Mapper.from_onnx`` can run it without
    the training config: the camera rig, the image fit and the decoding (defaults, overridable)."""
    d = cfg.data
    return {"dataset": d.dataset, "av2_cameras": list(d.av2_cameras), "image_fit": d.image_fit,
            "decoding": {name: getattr(cfg.model.gnn, name) for name in DECODE_OPTIONS}}


def exported_config(meta: dict) -> ExperimentConfig:
    """The config of an export (``read_export``'s metadata): its baked keys and its inference metadata
    (an export written before the latter existed: the defaults, nuScenes cameras)."""
    merged = config_to_dict(ExperimentConfig())
    for key, value in meta["config"].items():
        set_key(merged, key, value)
    extra = meta.get("inference", {})
    merged["data"].update({k: extra[k] for k in ("dataset", "av2_cameras", "image_fit") if k in extra})
    merged["model"]["gnn"].update(extra.get("decoding", {}))
    return config_from_dict(merged)


def check_export(path: str | Path, cfg: ExperimentConfig) -> dict:
    """The metadata of ``path`` (``read_export``) if its baked config is ``cfg``'s; otherwise a one-line
    ``DeployError`` naming the keys that differ."""
    meta = read_export(path)
    differ = config_differences(baked_config(cfg), meta["config"])
    cameras = meta["inference"].get("av2_cameras")  # recorded beside the baked keys (the rig, not the graph)
    if cfg.data.dataset == "av2" and cameras is not None and list(cfg.data.av2_cameras) != list(cameras):
        differ.append(f"data.av2_cameras={cameras!r} (CONFIG: {list(cfg.data.av2_cameras)!r})")
    if differ:
        more = f" and {len(differ) - 4} more" if len(differ) > 4 else ""
        raise DeployError(f"{path} was exported from another config: {', '.join(differ[:4])}{more}; pass the "
                          f"config it was exported with, or export the checkpoint again with: instagram-hdmap "
                          f"export-onnx CONFIG --checkpoint CKPT --out FILE")
    return meta


class OnnxModel:
    """An exported ONNX file run by onnxruntime on the CPU: ``model(batch) -> outputs`` as torch tensors
    with the keys and shapes of ``InstaGraM.forward`` (batch 1), so the post-processing is unchanged.

    The export of a temporal model is called as the model is: ``model(batch, memory)``, ``memory`` the
    previous call's ``outputs["memory"]`` (None: empty), the batch with ``ego_pose`` (``scene_start``
    and ``frame_index`` default to a continuing stream's: False, the memory's + 1).

    ``threads``: onnxruntime's intra-op threads (default: ``torch.get_num_threads()``);
    ``optimization``: its graph optimisation level ("all", "extended", "basic", "disabled").
    """

    def __init__(self, path: str | Path, cfg: ExperimentConfig, *, threads: int | None = None,
                 optimization: str = "all"):
        _, ort = require_onnx()
        self.path = as_path(path, "ONNX file")
        cfg = as_config(cfg, "OnnxModel")  # a YAML file's path: "'str' object has no attribute 'model'" deep inside
        self.meta = check_export(self.path, cfg)
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads or torch.get_num_threads()
        options.inter_op_num_threads = 1
        level = {"all": "ENABLE_ALL", "extended": "ENABLE_EXTENDED", "basic": "ENABLE_BASIC",
                 "disabled": "DISABLE_ALL"}[optimization]
        options.graph_optimization_level = getattr(ort.GraphOptimizationLevel, f"ORT_{level}")
        options.log_severity_level = 3  # errors only
        self.session = ort.InferenceSession(str(self.path), options, providers=["CPUExecutionProvider"])
        self.input_shapes = self.meta["shapes"]["inputs"]
        self.input_types = {i.name: i.type for i in self.session.get_inputs()}  # "tensor(float)", "tensor(bool)", ...
        self.input_names, self.output_names = input_names(cfg), output_names(cfg)
        self.is_temporal = is_temporal_config(cfg)

    def _input(self, name: str, value) -> torch.Tensor:
        """``value`` as the CPU tensor of the graph's input ``name``: floats as float32, integer indices as
        int64, flags as bool; another kind (a float mask, a bool index) is a ``DeployError`` (onnxruntime's own
        error names no input)."""
        try:
            tensor = value.detach().cpu() if isinstance(value, torch.Tensor) else torch.as_tensor(np.asarray(value))
        except (TypeError, ValueError, RuntimeError):
            raise DeployError(f"{self.path}: input {name} must be a tensor (or an array), got "
                              f"{type(value).__name__}") from None
        kind = self.input_types.get(name, "tensor(float)")
        integer = not tensor.is_floating_point() and not tensor.is_complex() and tensor.dtype != torch.bool
        if kind == "tensor(float)" and (tensor.is_floating_point() or integer):
            return tensor.float()
        if kind == "tensor(int64)" and integer:
            return tensor.long()
        if kind == "tensor(bool)" and tensor.dtype == torch.bool:
            return tensor
        want = {"tensor(float)": "floats", "tensor(int64)": "integers (int64)", "tensor(bool)": "booleans"}
        raise DeployError(f"{self.path} takes {name} as {want.get(kind, kind)}; the batch has {tensor.dtype} (pass the "
                          "previous call's outputs['memory'] as it is, or build the input with that dtype)")

    def initial_memory(self) -> dict[str, torch.Tensor]:
        """An empty memory (``valid`` False) of the file's shapes (a temporal export)."""
        return {"bev": torch.zeros(self.input_shapes["memory_bev"]), "ego_pose": torch.eye(4)[None],
                "valid": torch.zeros(1, dtype=torch.bool), "frame_index": torch.zeros(1, dtype=torch.long)}

    def __call__(self, batch: dict, memory: dict[str, torch.Tensor] | None = None) -> dict[str, torch.Tensor]:
        given = dict(batch)
        if self.is_temporal:
            memory = self.initial_memory() if memory is None else memory
            given.update({f"memory_{k}": v for k, v in memory.items()})
            given.setdefault("scene_start", torch.zeros(1, dtype=torch.bool))
            given.setdefault("frame_index", memory["frame_index"] + 1)
        feed = {}
        for name in self.input_names:
            if name not in given:
                raise DeployError(f"{self.path}: the batch lacks '{name}' (inputs: {', '.join(self.input_names)})")
            tensor = self._input(name, given[name])
            if list(tensor.shape) != self.input_shapes[name]:
                raise DeployError(f"{self.path} takes {name} of shape {self.input_shapes[name]} (static, batch 1); "
                                  f"the batch has {list(tensor.shape)}")
            feed[name] = tensor.contiguous().numpy()
        results = dict(zip(self.output_names, (torch.from_numpy(v) for v in self.session.run(
            list(self.output_names), feed))))
        if self.is_temporal:
            results["memory"] = {k: results.pop(f"next_memory_{k}") for k in MEMORY_KEYS}
        return results


@torch.no_grad()
def run_model(model, batch: dict, memory: dict | None = None) -> dict[str, torch.Tensor]:
    """The outputs of ``model`` (an ``InstaGraM`` in eval mode, or an ``OnnxModel``) for ``batch``, moved
    to the model's device. ``memory``: what a temporal model returned as ``out["memory"]`` for the
    previous frame of the scene (None at a scene's start, and always for a single-frame model, which
    returns none; ``batch["scene_start"]`` marks the start)."""
    if isinstance(model, OnnxModel):
        return model(batch, memory) if model.is_temporal else model(batch)
    param = next(model.parameters())
    if param.dtype != torch.float32:  # mapper.model.half() / .double() in a notebook: torch's raw "Input type
        # (torch.FloatTensor) and weight type ... should be the same" from the first convolution
        raise UserError(f"the model's weights are {str(param.dtype).removeprefix('torch.')} (model.half(), "
                        ".double() or .to(dtype)?); the model runs in float32: call model.float(), and for lower "
                        "precision run the calls under torch.autocast(device_type, dtype=torch.bfloat16)")
    batch = move_to(batch, param.device)
    return model(batch) if memory is None else model(batch, memory=memory)
