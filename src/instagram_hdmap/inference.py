"""A trained model for inference: the config keys that define a model, loading a checkpoint or an
ONNX export, and a perfect model's outputs built from the GT.

    model, cfg, notes = load_model("runs/x/best.pt", load_config("configs/synthetic/tiny.yaml"))
    onnx_model = OnnxModel("model.onnx", cfg)      # the same output dict, from onnxruntime
    outputs = gt_outputs(batch, grid, num_classes)  # what a perfect model would output

``MODEL_KEYS`` is the one list of the config keys that define a model: its weights and how its
outputs are read (the grid, the model, the image size, the classes, the distance-transform clip).
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
from collections.abc import Sequence
from pathlib import Path

import torch
import torch.nn.functional as F

from .assignment import assign, target_log_assignment
from .checkpoint import CheckpointError, load_checkpoint
from .config import (
    ExperimentConfig,
    UserError,
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
from .geometry import BEVGrid
from .models import build_model
from .models.vertices import vertex_heatmap
from .models.view_transform import CALIBRATION_KEYS
from .postprocess import DECODE_KEYS

# Config keys that define a model: its weights and how its outputs are read.
MODEL_KEYS = ("grid", "model", "data.image_size", "data.classes", "data.dt_clip")
# Of those, the keys an exported graph does not read (post-processing, training-only settings).
NOT_BAKED = (*DECODE_KEYS, "model.backbone.weights", "model.backbone.from_scratch", "model.backbone.grad_checkpoint")

# The exported graph's interface (docs/deploy.md), in argument order.
INPUT_NAMES = ("images", *CALIBRATION_KEYS)
OUTPUT_NAMES = ("pred_vertex_logits", "pred_heatmap", "pred_distance", "pred_vertices_px", "pred_vertex_mask",
                "pred_vertex_scores", "pred_class_log_probs", "pred_log_assignment")
EXPORT_FORMAT = 1  # bump when the graph's inputs, outputs or their meaning change
META_FORMAT = "instagram_hdmap.export_format"
META_CONFIG = "instagram_hdmap.config"
META_CONFIG_SHA = "instagram_hdmap.config_sha256"
META_SHAPES = "instagram_hdmap.shapes"
META_SOURCE = "instagram_hdmap.source"
DEPLOY_EXTRA = 'pip install -e ".[deploy]"'


def output_names(cfg: ExperimentConfig) -> tuple[str, ...]:
    """``OUTPUT_NAMES`` of a model built from ``cfg``: without ``pred_distance`` when it has no distance
    head (``model.bev_heads.distance_head=false``)."""
    return tuple(k for k in OUTPUT_NAMES if k != "pred_distance" or cfg.model.bev_heads.distance_head)


class DeployError(UserError):
    """A missing optional extra, an unsupported export setting, an ONNX file that does not fit."""


# --- a checkpoint ------------------------------------------------------------------------------------


def inference_config(
    cfg: ExperimentConfig, saved: dict, overrides: Sequence[str] = (), source: str = "the checkpoint"
) -> tuple[ExperimentConfig, list[str]]:
    """The config to run a checkpoint with: ``cfg`` (CONFIG file + overrides) with the ``MODEL_KEYS``
    of the checkpoint's ``saved`` config, then the command-line ``overrides`` again (they win).

    Returns the config and human-readable notes on where the CONFIG file was overruled.
    """
    trained = saved_config(saved, source)
    explicit = parse_overrides(list(overrides))
    explicit_keys = list(flatten(explicit))
    merged, trained_d = config_to_dict(cfg), config_to_dict(trained)
    for key in MODEL_KEYS:
        set_key(merged, key, copy.deepcopy(get_key(trained_d, key)))
    deep_update(merged, explicit)
    out = config_from_dict(merged)
    notes = []
    ignored = [k for k in diff_configs(cfg, trained)
               if is_under(k, MODEL_KEYS) and not is_under(k, explicit_keys)]
    if ignored:
        cfg_d = config_to_dict(cfg)
        notes.append("the CONFIG file's model settings differ from those the checkpoint was trained with; using "
                     "the checkpoint's: " + ", ".join(f"{k}={get_key(trained_d, k)!r} (CONFIG: {get_key(cfg_d, k)!r})"
                                                       for k in ignored))
    changed = [k for k in diff_configs(trained, out) if is_under(k, MODEL_KEYS)]
    if changed:
        out_d = config_to_dict(out)
        notes.append("overriding the checkpoint's " + ", ".join(
            f"{k}={get_key(trained_d, k)!r} with {get_key(out_d, k)!r}" for k in changed))
    return out, notes


def saved_config(saved: dict, source: str = "the checkpoint") -> ExperimentConfig:
    """The config saved in a checkpoint, or a ``CheckpointError`` naming ``source``."""
    try:
        return config_from_dict(saved)
    except UserError as e:
        raise CheckpointError(f"{source} holds a config this version cannot read: {e}") from None


def load_weights(model: torch.nn.Module, state: dict, checkpoint: str | Path) -> torch.nn.Module:
    """``model`` with the checkpoint's weights, or a ``CheckpointError``: they do not fit its config."""
    try:
        model.load_state_dict(state["model"])
    except RuntimeError as e:
        first = " ".join(str(e).split())[:300]
        raise CheckpointError(
            f"the weights in {checkpoint} do not fit the model built from its config and the overrides "
            f"({first}); drop overrides that change layer sizes"
        ) from None
    return model


def load_model(
    checkpoint: str | Path, cfg: ExperimentConfig, overrides: Sequence[str] = (), device: torch.device | None = None
) -> tuple[torch.nn.Module, ExperimentConfig, list[str]]:
    """Build the model of ``checkpoint`` (see ``inference_config``), load its weights, eval mode.

    Returns ``(model, config, notes)``; ``device`` defaults to ``train.device`` ("auto": CUDA if any).
    Raises ``CheckpointError`` for a missing / corrupt checkpoint or weights that do not fit.
    """
    state = load_checkpoint(checkpoint)
    notes: list[str] = []
    if isinstance(state.get("config"), dict):
        cfg, notes = inference_config(cfg, state["config"], overrides, f"checkpoint {checkpoint}")
    else:
        notes.append(f"checkpoint {checkpoint} holds no config; building the model from the CONFIG file")
    model = load_weights(build_model(cfg), state, checkpoint)
    device = device if device is not None else resolve_device(cfg.train.device)
    return model.eval().to(device), cfg, notes


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
    return {k: v for k, v in sorted(flat.items()) if is_under(k, MODEL_KEYS) and not is_under(k, NOT_BAKED)}


def config_sha256(baked: dict) -> str:
    return hashlib.sha256(json.dumps(baked, sort_keys=True).encode()).hexdigest()


def config_differences(expected: dict, actual: dict) -> list[str]:
    """``key=value (other: value)`` for every baked key whose values differ."""
    keys = sorted(set(expected) | set(actual))
    return [f"{k}={actual.get(k, '<absent>')!r} (CONFIG: {expected.get(k, '<absent>')!r})"
            for k in keys if expected.get(k, "<absent>") != actual.get(k, "<absent>")]


def read_metadata(path: str | Path) -> dict[str, str]:
    """The ``metadata_props`` of an ONNX file (without loading its weights)."""
    onnx, _ = require_onnx()
    path = Path(path)
    if not path.is_file():
        raise DeployError(f"ONNX file not found: {path}")
    try:
        proto = onnx.load(str(path), load_external_data=False)
    except Exception as e:  # any unreadable file is a user error
        raise DeployError(f"{path} is not a readable ONNX file ({type(e).__name__}: {str(e)[:200]})") from None
    return {p.key: p.value for p in proto.metadata_props}


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
    return {"config": stored, "shapes": shapes, "source": json.loads(meta.get(META_SOURCE, "{}"))}


def check_export(path: str | Path, cfg: ExperimentConfig) -> dict:
    """The metadata of ``path`` (``read_export``) if its baked config is ``cfg``'s; otherwise a one-line
    ``DeployError`` naming the keys that differ."""
    meta = read_export(path)
    differ = config_differences(baked_config(cfg), meta["config"])
    if differ:
        more = f" and {len(differ) - 4} more" if len(differ) > 4 else ""
        raise DeployError(f"{path} was exported from another config: {', '.join(differ[:4])}{more}; pass the "
                          f"config it was exported with, or export the checkpoint again with: instagram-hdmap "
                          f"export-onnx CONFIG --checkpoint CKPT --out FILE")
    return meta


class OnnxModel:
    """An exported ONNX file run by onnxruntime on the CPU: ``model(batch) -> outputs`` as torch tensors
    with the keys and shapes of ``InstaGraM.forward`` (batch 1), so the post-processing is unchanged.

    ``threads``: onnxruntime's intra-op threads (default: ``torch.get_num_threads()``);
    ``optimization``: its graph optimisation level ("all", "extended", "basic", "disabled").
    """

    def __init__(self, path: str | Path, cfg: ExperimentConfig, *, threads: int | None = None,
                 optimization: str = "all", providers: Sequence[str] = ("CPUExecutionProvider",)):
        _, ort = require_onnx()
        self.path = Path(path)
        self.meta = check_export(self.path, cfg)
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads or torch.get_num_threads()
        options.inter_op_num_threads = 1
        levels = {"all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL,
                  "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
                  "basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
                  "disabled": ort.GraphOptimizationLevel.ORT_DISABLE_ALL}
        options.graph_optimization_level = levels[optimization]
        options.log_severity_level = 3  # errors only
        self.session = ort.InferenceSession(str(self.path), options, providers=list(providers))
        self.input_shapes = self.meta["shapes"]["inputs"]
        self.output_names = output_names(cfg)

    def __call__(self, batch: dict) -> dict[str, torch.Tensor]:
        feed = {}
        for name in INPUT_NAMES:
            if name not in batch:
                raise DeployError(f"{self.path}: the batch lacks '{name}' (inputs: {', '.join(INPUT_NAMES)})")
            tensor = batch[name]
            if list(tensor.shape) != self.input_shapes[name]:
                raise DeployError(f"{self.path} takes {name} of shape {self.input_shapes[name]} (static, batch 1); "
                                  f"the batch has {list(tensor.shape)}")
            feed[name] = tensor.detach().to("cpu", torch.float32).contiguous().numpy()
        results = self.session.run(list(self.output_names), feed)
        return {name: torch.from_numpy(value) for name, value in zip(self.output_names, results)}
