"""Deployment: the whole model exported as one ONNX graph, and the fast torch paths (``torch.compile``,
CUDA graphs). docs/deploy.md is the user's page; this docstring is the contract.

    info = export_checkpoint(cfg, "runs/x/best.pt", "model.onnx")     # export-onnx
    onnx_model = inference.OnnxModel("model.onnx", cfg)                # predict --onnx (onnxruntime)
    outputs = onnx_model(batch)        # the same dict as model(batch), for postprocess.postprocess_batch
    forward = fast_forward(model, batch, compile=True)                 # benchmark --compile [--cuda-graphs]

Shapes: B = 1 (the export's static batch), V cameras, h x w network input, H x W BEV grid, S cell size,
Hc x Wc = H/S x W/S, K classes, N vertex slots.

The exported graph (``inference.INPUT_NAMES`` -> ``inference.OUTPUT_NAMES``, every shape static, float32
but the bool mask):
  inputs  ``images`` [1, V, 3, h, w] (normalised), ``intrinsics`` [1, V, 3, 3], ``cam_to_ego_rot``
          [1, V, 3, 3], ``cam_to_ego_trans`` [1, V, 3], ``post_rot`` [1, V, 3, 3], ``post_tran`` [1, V, 3],
          ``ground_height`` [1] (the IPM / MLP ground plane; a graph whose view transform does not read it,
          LSS, still takes it, so that every export has the same inputs)
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

The ONNX metadata (``metadata_props``, keys ``inference.META_*``) holds the export format, the config
the graph bakes in (``inference.baked_config``: the ``MODEL_KEYS``, grid, model, image size, classes,
DT clip, less the decoding keys, which only the post-processing reads) and its SHA-256, the shapes,
the checkpoint and the versions. ``inference.OnnxModel`` refuses a file of another format or another
config with a one-line ``DeployError``.

``onnx`` / ``onnxruntime`` / ``onnxscript`` are the optional extra ``[deploy]``, imported through
``inference.require_onnx`` only.
"""

from __future__ import annotations

import copy
import importlib.metadata
import json
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from torch import nn

from .checkpoint import load_checkpoint
from .config import ExperimentConfig, config_to_dict, flatten, is_under, parse_overrides
from .data import rig_cameras
from .data.rig import nuscenes_like_rig
from .files import atomic_path, check_output_file, is_stream
from .inference import (
    EXPORT_FORMAT,
    INPUT_NAMES,
    MEMORY_NAMES,
    META_CONFIG,
    META_CONFIG_SHA,
    META_FORMAT,
    META_GRAPH_SHA,
    META_INFERENCE,
    META_SHAPES,
    META_SOURCE,
    NEXT_MEMORY_NAMES,
    OUTPUT_NAMES,
    TEMPORAL_INPUTS,
    DeployError,
    OnnxModel,
    baked_config,
    config_sha256,
    graph_sha256,
    inference_config,
    inference_metadata,
    input_names,
    load_weights,
    output_names,
    require_onnx,
    saved_config,
)
from .models import build_model
from .models.temporal import MEMORY_KEYS

DEFAULT_OPSET = 18  # the dynamo exporter's own opset; GridSample, ScatterND add, LayerNormalization need >= 17
MIN_OPSET = 18


def package_version() -> str:
    """The installed instagram-hdmap's version (stamped in an export's metadata)."""
    try:
        return importlib.metadata.version("instagram-hdmap")
    except importlib.metadata.PackageNotFoundError:  # a source tree on the path, not installed
        return "unknown"


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
    the form exporters and graph capture take. A temporal model's (``is_temporal``) also take the frame's
    ``TEMPORAL_INPUTS`` and its memory as plain tensors (``memory_bev``, ``memory_ego_pose``,
    ``memory_valid``, ``memory_frame_index``) and return ``memory_status`` and the new memory
    (``next_memory_*``): ``inference.input_names`` / ``output_names``."""

    def __init__(self, model: nn.Module):
        super().__init__()
        self.model = model
        self.temporal = bool(getattr(model, "is_temporal", False))

    def forward(self, *inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        if not self.temporal:
            outputs = self.model(dict(zip(INPUT_NAMES, inputs)))
            return tuple(outputs[k] for k in OUTPUT_NAMES if k in outputs)
        named = dict(zip((*INPUT_NAMES, *TEMPORAL_INPUTS, *MEMORY_NAMES), inputs))
        memory = {k: named.pop(f"memory_{k}") for k in MEMORY_KEYS}
        outputs = self.model(named, memory=memory)
        outputs.update({f"next_memory_{k}": v for k, v in outputs.pop("memory").items()})
        return (*(outputs[k] for k in OUTPUT_NAMES if k in outputs), outputs["memory_status"],
                *(outputs[k] for k in NEXT_MEMORY_NAMES))


def example_call(cfg: ExperimentConfig, model: nn.Module) -> tuple[dict[str, torch.Tensor], dict | None]:
    """``(batch, memory)`` to run ``model`` on: ``example_inputs`` and, for a temporal model, the frame after a
    valid memory (``frame_index`` 1, no scene start, the identity pose; the memory's frame 1 m behind, random
    features), so that an export traces the fused path with real history; a single-frame model's memory is None."""
    batch = example_inputs(cfg)
    if not getattr(model, "is_temporal", False):
        return batch, None
    memory = model.initial_memory(1, batch["images"])
    memory["valid"][:] = True
    memory["ego_pose"][0, 0, 3] = -1.0
    memory["bev"] = torch.randn(memory["bev"].shape, generator=torch.Generator().manual_seed(1))
    batch.update(ego_pose=torch.eye(4)[None], scene_start=torch.zeros(1, dtype=torch.bool),
                 frame_index=torch.ones(1, dtype=torch.long))
    return batch, memory


def example_inputs(cfg: ExperimentConfig, seed: int = 0) -> dict[str, torch.Tensor]:
    """A batch of one: random images and the nuScenes-like rig of ``data.rig.nuscenes_like_rig``, with as
    many cameras as the config's rig (an AV2 model's export took six: a graph its frames could not run)."""
    rig = nuscenes_like_rig(tuple(cfg.data.image_size), len(rig_cameras(cfg)))
    h, w = cfg.data.image_size
    gen = torch.Generator().manual_seed(seed)
    batch = {k: v[None].contiguous() for k, v in rig.items()}
    batch["images"] = torch.randn(1, rig["intrinsics"].shape[0], 3, h, w, generator=gen)
    return batch


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
    batch, memory = example_call(cfg, interface.model)
    batch.update({f"memory_{k}": v for k, v in (memory or {}).items()})
    names_in, names_out = input_names(cfg), output_names(cfg)
    args = tuple(batch[k] for k in names_in)
    with torch.no_grad(), warnings.catch_warnings():
        # torch's notices about its own internals (FutureWarning "isinstance(treespec, LeafSpec) is deprecated"):
        # nothing a user can change; under PYTHONWARNINGS=error (-W error) they stopped the export, torch's traceback
        warnings.filterwarnings("ignore", category=FutureWarning)
        warnings.filterwarnings("ignore", category=DeprecationWarning)
        expected = interface(*args)
        program = torch.onnx.export(interface, args, input_names=list(names_in), output_names=list(names_out),
                                    opset_version=opset, dynamo=True, optimize=optimize, verbose=False)
    proto = program.model_proto
    shapes = {"inputs": {k: list(a.shape) for k, a in zip(names_in, args)},
              "outputs": {k: list(t.shape) for k, t in zip(names_out, expected)}}
    baked = baked_config(cfg)
    sha = config_sha256(baked)
    meta = {META_FORMAT: str(EXPORT_FORMAT), META_CONFIG: json.dumps(baked), META_CONFIG_SHA: sha,
            META_SHAPES: json.dumps(shapes),
            META_INFERENCE: json.dumps(inference_metadata(cfg)),
            META_SOURCE: json.dumps({"checkpoint": source, "config_name": cfg.name, "package": package_version(),
                                     "torch": torch.__version__, "onnx": onnx.__version__, "opset": opset})}
    meta[META_GRAPH_SHA] = graph_sha256(proto)  # after the graph is final: read_metadata checks it
    del proto.metadata_props[:]
    for key, value in meta.items():
        proto.metadata_props.add(key=key, value=value)
    proto.producer_name, proto.doc_string = "instagram-hdmap export-onnx", f"InstaGraM {cfg.name}; docs/deploy.md"
    out = Path(out)
    with atomic_path(out) as tmp:
        onnx.save(proto, str(tmp))
    return {"path": out, "opset": opset, "config_sha256": sha, "nodes": len(proto.graph.node), **shapes}


def export_config(cfg: ExperimentConfig, saved: dict | None, overrides: Sequence[str], checkpoint: str | Path
                  ) -> ExperimentConfig:
    """The config to export ``checkpoint`` with: the CONFIG file (+ overrides) must agree with the config
    saved in the checkpoint on every baked key that the command line does not override; the graph is
    then stamped with it. A disagreement is a ``DeployError`` naming the keys (unlike ``predict``, which
    takes the checkpoint's and notes it: an exported file is an artifact that must say what it is)."""
    if saved is None:
        return cfg
    trained = saved_config(saved, f"checkpoint {checkpoint}")
    explicit = list(flatten(parse_overrides(list(overrides))))
    mine, theirs = baked_config(cfg), baked_config(trained)
    differ = [k for k in sorted(set(mine) | set(theirs))
              if mine.get(k) != theirs.get(k) and not is_under(k, explicit)]
    if differ:
        # the CONFIG's own values (a single-frame config bakes no model.temporal key: show its memory='none',
        # not None), and only the keys whose values differ there
        full = flatten(json.loads(json.dumps(config_to_dict(cfg))))
        differ = [k for k in differ if theirs.get(k, "<absent>") != full.get(k, "<absent>")] or differ
        shown = ", ".join(f"{k}={theirs.get(k, '<absent>')!r} (CONFIG: {full.get(k, '<absent>')!r})"
                          for k in differ[:4])
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
    require_onnx(export=True)
    check_output_file(out, "--out", [(checkpoint, "--checkpoint")])  # before minutes of export
    if verify and is_stream(out):  # /dev/stdout, /dev/null: written, then the check found nothing to read back
        raise DeployError(f"--out {out}: a terminal, pipe or device; export-onnx reads the file back to check it in "
                          "onnxruntime: give a file name (e.g. model.onnx)")
    state = load_checkpoint(checkpoint)
    saved = state.get("config") if isinstance(state.get("config"), dict) else None
    cfg = export_config(cfg, saved, overrides, checkpoint)
    model = load_weights(build_model(cfg), state, checkpoint)
    info = export_onnx(model, cfg, out, opset=opset, source=str(checkpoint))
    if verify:
        reference = inference_copy(model)
        batch, memory = example_call(cfg, reference)
        with torch.no_grad():
            expected = reference(batch) if memory is None else reference(batch, memory=memory)
        info["check"] = compare_outputs(expected, OnnxModel(out, cfg)(batch, memory))
    info["config"] = cfg
    return info


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
    model = inference_copy(model) if compile or cuda_graphs else model.eval()
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
