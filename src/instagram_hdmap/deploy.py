"""Deployment: the whole model as one ONNX graph run by onnxruntime, and the fast torch paths
(``torch.compile``, CUDA graphs). docs/deploy.md is the user's page; this docstring is the contract.

    info = export_checkpoint(cfg, "runs/x/best.pt", "model.onnx")     # export-onnx
    onnx_model = OnnxModel("model.onnx", cfg)                          # predict --onnx
    outputs = onnx_model(batch)        # the same dict as model(batch), for postprocess.postprocess_batch
    forward = fast_forward(model, batch, compile=True)                 # benchmark --compile [--cuda-graphs]

Shapes: B = 1 (the export's static batch), V cameras, h x w network input, H x W BEV grid, S cell size,
Hc x Wc = H/S x W/S, K classes, N vertex slots.

The exported graph (``INPUT_NAMES`` -> ``OUTPUT_NAMES``, every shape static, float32 but the bool mask):
  inputs  ``images`` [1, V, 3, h, w] (normalised), ``intrinsics`` [1, V, 3, 3], ``cam_to_ego_rot``
          [1, V, 3, 3], ``cam_to_ego_trans`` [1, V, 3], ``post_rot`` [1, V, 3, 3], ``post_tran`` [1, V, 3]
  outputs the model's output dict (docs/conventions.md) in this order: ``pred_vertex_logits``
          [1, S*S+1, Hc, Wc], ``pred_heatmap`` [1, H, W], ``pred_distance`` [1, K, H, W],
          ``pred_vertices_px`` [1, N, 2], ``pred_vertex_mask`` [1, N] bool, ``pred_vertex_scores`` [1, N],
          ``pred_class_log_probs`` [1, N, K], ``pred_log_assignment`` [1, N+1, N+1]
It is exported by ``torch.onnx.export(..., dynamo=True)`` (torch.export, then ONNX standard ops only,
opset ``DEFAULT_OPSET``): the TorchScript exporter refuses the LSS splat (``index_add`` with repeated
indices), which the dynamo exporter writes as ``ScatterND`` with ``reduction="add"``. The top-N vertex
extraction is ``TopK`` with a validity mask; the Sinkhorn is unrolled to ``model.gnn.sinkhorn_iters``
iterations of plain ops with the CPU's floored log-sum-exp (``models/matching.py``): the numerics of
the torch model on the CPU. The export always runs on the CPU, in eval mode, with EfficientNet's plain
swish (``set_swish(memory_efficient=False)``; its memory-efficient one is a custom autograd Function).

The ONNX metadata (``metadata_props``, keys ``META_*``) holds the export format, the config the graph
bakes in (``baked_config``: grid, model, image size, classes, DT clip; not the match threshold, which
only the post-processing reads) and its SHA-256, the shapes, the checkpoint and the versions.
``OnnxModel`` refuses a file of another format or another config with a one-line ``DeployError``.

``onnx`` / ``onnxruntime`` are the optional extra ``[deploy]``; nothing else in the package imports them.
"""

from __future__ import annotations

import copy
import hashlib
import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from torch import nn

from .config import ExperimentConfig, UserError, config_to_dict
from .models.view_transform import CALIBRATION_KEYS
from .postprocess import DECODE_KEYS

EXPORT_FORMAT = 1  # bump when the graph's inputs, outputs or their meaning change
DEFAULT_OPSET = 18  # the dynamo exporter's own opset; GridSample, ScatterND add, LayerNormalization need >= 17
MIN_OPSET = 18
INPUT_NAMES = ("images", *CALIBRATION_KEYS)
OUTPUT_NAMES = ("pred_vertex_logits", "pred_heatmap", "pred_distance", "pred_vertices_px", "pred_vertex_mask",
                "pred_vertex_scores", "pred_class_log_probs", "pred_log_assignment")
# Config keys that shape the graph (predict.MODEL_KEYS) less those the graph does not read.
BAKED_KEYS = ("grid", "model", "data.image_size", "data.classes", "data.dt_clip")
NOT_BAKED = (*DECODE_KEYS, "model.backbone.weights", "model.backbone.from_scratch", "model.backbone.grad_checkpoint")
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


# --- the model as a graph -------------------------------------------------------------------------------


def inference_copy(model: nn.Module) -> nn.Module:
    """A copy of ``model`` in eval mode, without autograd-Function activations (EfficientNet's
    memory-efficient swish becomes ``x * sigmoid(x)``, the same values); the original is untouched."""
    model = copy.deepcopy(model).eval()
    for module in model.modules():
        if hasattr(module, "set_swish") and hasattr(module, "_blocks"):  # efficientnet_pytorch.EfficientNet
            module.set_swish(memory_efficient=False)
    return model


class TensorInterface(nn.Module):
    """``InstaGraM`` with positional tensors in (``INPUT_NAMES``) and a tuple out (``OUTPUT_NAMES``),
    the form exporters and graph capture take."""

    def __init__(self, model: nn.Module):
        super().__init__()
        self.model = model

    def forward(self, *inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        outputs = self.model(dict(zip(INPUT_NAMES, inputs)))
        return tuple(outputs[k] for k in OUTPUT_NAMES if k in outputs)


def example_inputs(cfg: ExperimentConfig, seed: int = 0) -> dict[str, torch.Tensor]:
    """A batch of one: random images and the nuScenes-like rig of ``benchmark.nuscenes_like_rig``."""
    from .benchmark import nuscenes_like_rig

    rig = nuscenes_like_rig(tuple(cfg.data.image_size))
    h, w = cfg.data.image_size
    gen = torch.Generator().manual_seed(seed)
    batch = {k: v[None].contiguous() for k, v in rig.items()}
    batch["images"] = torch.randn(1, rig["intrinsics"].shape[0], 3, h, w, generator=gen)
    return batch


# --- the config an export bakes in ------------------------------------------------------------------------


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        out.update(_flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


def _under(key: str, prefixes: Sequence[str]) -> bool:
    return any(key == p or key.startswith(p + ".") for p in prefixes)


def baked_config(cfg: ExperimentConfig) -> dict:
    """The flat ``{dotted key: value}`` of the config keys the exported graph bakes in (JSON types)."""
    flat = _flat(json.loads(json.dumps(config_to_dict(cfg))))
    return {k: v for k, v in sorted(flat.items()) if _under(k, BAKED_KEYS) and not _under(k, NOT_BAKED)}


def config_sha256(baked: dict) -> str:
    return hashlib.sha256(json.dumps(baked, sort_keys=True).encode()).hexdigest()


def config_differences(expected: dict, actual: dict) -> list[str]:
    """``key=value (other: value)`` for every baked key whose values differ."""
    keys = sorted(set(expected) | set(actual))
    return [f"{k}={actual.get(k, '<absent>')!r} (CONFIG: {expected.get(k, '<absent>')!r})"
            for k in keys if expected.get(k, "<absent>") != actual.get(k, "<absent>")]


def align_vertex_slots(outputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """``outputs`` (batch 1) with the vertex slots, and the assignment's rows and columns, ordered by
    position (row-major over the BEV pixels; padding last, the dustbin stays last). ``TopK`` breaks
    ties between equal scores in its own way (onnxruntime by index, torch unspecified), so two
    implementations may list the same vertices in another order; one vertex per cell makes positions
    unique, and the model is permutation-equivariant, so aligned outputs compare slot by slot."""
    u, v = outputs["pred_vertices_px"][0].float().unbind(-1)
    key = torch.where(outputs["pred_vertex_mask"][0], v * (u.max() + 1) + u, torch.full_like(u, float("inf")))
    order = key.argsort(stable=True)
    out = dict(outputs)
    for name in ("pred_vertices_px", "pred_vertex_mask", "pred_vertex_scores", "pred_class_log_probs"):
        out[name] = outputs[name][:, order]
    full = torch.cat([order, order.new_full((1,), len(order))])
    out["pred_log_assignment"] = outputs["pred_log_assignment"][:, full][:, :, full]
    return out


def compare_outputs(expected: dict[str, torch.Tensor], got: dict[str, torch.Tensor]) -> dict:
    """Two output dicts of batch 1, slots aligned (``align_vertex_slots``) -> ``{"dense": max |diff| of
    the vertex logits, heatmap and distance transform, "same_vertices": bool, "graph": max |diff| of the
    vertex scores, class log-probabilities and log-assignment, or None where the vertices differ}``.
    Vertices differ where top-N cuts through exactly equal scores (random weights), not otherwise."""
    e, g = align_vertex_slots(expected), align_vertex_slots(got)

    def worst(names: tuple[str, ...]) -> float:
        return max(float((e[k].float() - g[k].float()).abs().max()) for k in names)

    same = torch.equal(e["pred_vertex_mask"], g["pred_vertex_mask"]) and torch.equal(
        e["pred_vertices_px"], g["pred_vertices_px"])
    dense = tuple(k for k in ("pred_vertex_logits", "pred_heatmap", "pred_distance") if k in e)
    return {"dense": worst(dense), "same_vertices": same,
            "graph": worst(("pred_vertex_scores", "pred_class_log_probs", "pred_log_assignment")) if same else None}


# --- export ---------------------------------------------------------------------------------------------


def export_onnx(model: nn.Module, cfg: ExperimentConfig, out: str | Path, *, opset: int = DEFAULT_OPSET,
                source: str = "", optimize: bool = True) -> dict:
    """Export ``model`` (built from ``cfg``) to ``out`` as one static ONNX graph with the metadata.

    Returns ``{"path", "opset", "inputs", "outputs", "config_sha256", "nodes"}`` (shapes as lists).
    Raises ``DeployError`` for an unsupported opset or a missing extra.
    """
    onnx, _ = require_onnx(export=True)
    max_opset = onnx.defs.onnx_opset_version()
    if not MIN_OPSET <= opset <= max_opset:
        raise DeployError(f"--opset {opset} is not supported: the export needs opset {MIN_OPSET}..{max_opset} "
                          f"(GridSample, ScatterND add and LayerNormalization; the dynamo exporter starts at "
                          f"{MIN_OPSET}; the installed onnx {onnx.__version__} knows up to {max_opset})")
    interface = TensorInterface(inference_copy(model).cpu()).eval()
    batch = example_inputs(cfg)
    args = tuple(batch[k] for k in INPUT_NAMES)
    with torch.no_grad():
        expected = interface(*args)
        program = torch.onnx.export(interface, args, input_names=list(INPUT_NAMES),
                                    output_names=list(output_names(cfg)), opset_version=opset, dynamo=True,
                                    optimize=optimize, verbose=False)
    proto = program.model_proto
    shapes = {"inputs": {k: list(a.shape) for k, a in zip(INPUT_NAMES, args)},
              "outputs": {k: list(t.shape) for k, t in zip(output_names(cfg), expected)}}
    baked = baked_config(cfg)
    sha = config_sha256(baked)
    from . import __version__

    meta = {META_FORMAT: str(EXPORT_FORMAT), META_CONFIG: json.dumps(baked), META_CONFIG_SHA: sha,
            META_SHAPES: json.dumps(shapes),
            META_SOURCE: json.dumps({"checkpoint": source, "config_name": cfg.name, "package": __version__,
                                     "torch": torch.__version__, "onnx": onnx.__version__, "opset": opset})}
    del proto.metadata_props[:]
    for key, value in meta.items():
        proto.metadata_props.add(key=key, value=value)
    proto.producer_name, proto.doc_string = "instagram-hdmap export-onnx", f"InstaGraM {cfg.name}; docs/deploy.md"
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp-{os.getpid()}")
    try:
        onnx.save(proto, str(tmp))
        os.replace(tmp, out)
    finally:
        if tmp.exists():
            tmp.unlink()
    return {"path": out, "opset": opset, "config_sha256": sha, "nodes": len(proto.graph.node), **shapes}


def export_config(cfg: ExperimentConfig, saved: dict | None, overrides: Sequence[str], checkpoint: str | Path
                  ) -> ExperimentConfig:
    """The config to export ``checkpoint`` with: the CONFIG file (+ overrides) must agree with the config
    saved in the checkpoint on every baked key that the command line does not override; the graph is
    then stamped with it. A disagreement is a ``DeployError`` naming the keys (unlike ``predict``, which
    takes the checkpoint's and notes it: an exported file is an artifact that must say what it is)."""
    from .config import config_from_dict, parse_overrides
    from .predict import inference_config

    if saved is None:
        return cfg
    try:
        trained = config_from_dict(saved)
    except UserError as e:
        raise DeployError(f"checkpoint {checkpoint} holds a config this version cannot read: {e}") from None
    explicit = list(_flat(parse_overrides(list(overrides))))
    mine, theirs = baked_config(cfg), baked_config(trained)
    differ = [k for k in sorted(set(mine) | set(theirs))
              if mine.get(k) != theirs.get(k) and not _under(k, explicit)]
    if differ:
        shown = ", ".join(f"{k}={theirs.get(k)!r} (CONFIG: {mine.get(k)!r})" for k in differ[:4])
        more = f" and {len(differ) - 4} more" if len(differ) > 4 else ""
        raise DeployError(f"checkpoint {checkpoint} is from another config: it was trained with {shown}{more}; "
                          f"pass the config it was trained with (its run folder has config.yaml), or override "
                          f"the key on the command line")
    resolved, _ = inference_config(cfg, saved, overrides, f"checkpoint {checkpoint}")
    return resolved


def export_checkpoint(cfg: ExperimentConfig, checkpoint: str | Path, out: str | Path, *,
                      overrides: Sequence[str] = (), opset: int = DEFAULT_OPSET, verify: bool = True) -> dict:
    """``export-onnx``: load ``checkpoint`` (its config must match ``cfg``, see ``export_config``), export
    it to ``out`` and, with ``verify``, run the file in onnxruntime on the example input: adds
    ``check`` (``compare_outputs`` of onnxruntime against torch) to ``export_onnx``'s result."""
    from .checkpoint import CheckpointError, load_checkpoint
    from .models import build_model

    require_onnx(export=True)
    state = load_checkpoint(checkpoint)
    saved = state.get("config") if isinstance(state.get("config"), dict) else None
    cfg = export_config(cfg, saved, overrides, checkpoint)
    model = build_model(cfg)
    try:
        model.load_state_dict(state["model"])
    except RuntimeError as e:
        first = " ".join(str(e).split())[:300]
        raise CheckpointError(f"the weights in {checkpoint} do not fit the model of the config ({first}); "
                              f"drop overrides that change layer sizes") from None
    info = export_onnx(model, cfg, out, opset=opset, source=str(checkpoint))
    if verify:
        batch = example_inputs(cfg)
        with torch.no_grad():
            expected = inference_copy(model)(batch)
        info["check"] = compare_outputs(expected, OnnxModel(out, cfg)(batch))
    info["config"] = cfg
    return info


# --- onnxruntime ----------------------------------------------------------------------------------------


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


def check_export(path: str | Path, cfg: ExperimentConfig) -> dict:
    """The metadata of ``path`` if it is an export of this format for ``cfg``'s baked config; otherwise a
    one-line ``DeployError``: not ours, an older (or newer) export format, or another config."""
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
    differ = config_differences(baked_config(cfg), stored)
    if differ:
        more = f" and {len(differ) - 4} more" if len(differ) > 4 else ""
        raise DeployError(f"{path} was exported from another config: {', '.join(differ[:4])}{more}; pass the "
                          f"config it was exported with, or {redo.replace('export it', 'export the checkpoint')}")
    return {"config": stored, "shapes": shapes, "source": json.loads(meta.get(META_SOURCE, "{}"))}


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


# --- fast torch paths: torch.compile and CUDA graphs -------------------------------------------------------


class StaticBatch:
    """The fixed input buffers a captured graph reads: ``load(batch)`` copies a batch into them and refuses
    one of another shape, dtype or device (CUDA graphs replay fixed addresses and shapes)."""

    def __init__(self, example: dict[str, torch.Tensor]):
        missing = [k for k in INPUT_NAMES if k not in example]
        if missing:
            raise DeployError(f"the example batch lacks {missing} (inputs: {', '.join(INPUT_NAMES)})")
        self.tensors = {k: example[k].detach().clone().contiguous() for k in INPUT_NAMES}

    def load(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        for name, static in self.tensors.items():
            new = batch[name]
            if new.shape != static.shape or new.dtype != static.dtype or new.device != static.device:
                raise DeployError(f"a captured CUDA graph has static inputs: {name} was captured as "
                                  f"{list(static.shape)} {static.dtype} on {static.device}, this batch has "
                                  f"{list(new.shape)} {new.dtype} on {new.device}")
            static.copy_(new)
        return self.tensors


class CUDAGraphRunner:
    """``forward(batch) -> outputs`` captured once in a ``torch.cuda.CUDAGraph`` and replayed: one launch
    for the whole model (hundreds of small kernels, mostly the Sinkhorn's). The outputs are copies
    (the graph's own buffers are overwritten by the next replay). Needs a CUDA device and a forward that
    never synchronises with the host (tests/test_deploy.py checks the model's on the CPU)."""

    def __init__(self, forward: Callable[[dict], dict], example: dict[str, torch.Tensor], warmup: int = 3):
        device = example["images"].device
        if device.type != "cuda":
            raise DeployError(f"--cuda-graphs needs a CUDA device; the model runs on {device.type}: use "
                              f"--device cuda, or drop --cuda-graphs (--compile works on the CPU)")
        self.static = StaticBatch(example)
        stream = torch.cuda.Stream(device)
        stream.wait_stream(torch.cuda.current_stream(device))
        with torch.cuda.stream(stream):  # warm-up off the default stream: cuBLAS / cuDNN / autotuning
            for _ in range(warmup):
                forward(self.static.tensors)
        torch.cuda.current_stream(device).wait_stream(stream)
        self.graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.graph):
            self.outputs = forward(self.static.tensors)

    def __call__(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        self.static.load(batch)
        self.graph.replay()
        return {k: v.clone() for k, v in self.outputs.items()}


def fast_forward(model: nn.Module, example: dict[str, torch.Tensor], *, compile: bool = False,
                 cuda_graphs: bool = False, amp: str = "none") -> Callable[[dict], dict]:
    """``forward(batch) -> outputs`` of ``model`` (on ``example``'s device) for inference on batches
    shaped like ``example``: eager (both flags off), ``torch.compile`` of the whole model (static
    shapes; on the CPU with inductor's weight freezing: BatchNorm folded into convolutions), and/or
    replayed from a CUDA graph. The first call of a compiled model compiles it; this function makes
    that call (on ``example``) so that the returned forward is warm. Run it under ``torch.no_grad``."""
    device = example["images"].device
    if cuda_graphs and device.type != "cuda":
        raise DeployError(f"--cuda-graphs needs a CUDA device; the model runs on {device.type}: use --device "
                          f"cuda, or drop --cuda-graphs (--compile works on the CPU)")
    if not (compile or cuda_graphs):
        model = model.eval()
    else:
        model = inference_copy(model)
    if compile:
        model = torch.compile(model, dynamic=False)

    def forward(batch: dict) -> dict:
        if amp == "none":
            return model(batch)
        # autocast's cast cache cannot live across CUDA-graph replays
        with torch.autocast(device.type, dtype=torch.bfloat16 if amp == "bf16" else torch.float16,
                            cache_enabled=not cuda_graphs):
            return model(batch)

    if compile:
        import torch._inductor.config as inductor_config

        with torch.no_grad(), inductor_config.patch(freezing=True):
            forward(example)  # compiles (freezing folds the weights in: it needs no_grad)
    if cuda_graphs:
        return CUDAGraphRunner(forward, example)
    return forward
