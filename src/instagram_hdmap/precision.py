"""The precision a trained model runs in at inference: ``fp32``, ``bf16``, ``int8`` or ``auto``.

    precision, notes = resolve_precision("auto", device)       # what this machine runs best, and why
    model = with_precision(model, precision)                   # bf16: the forward under bfloat16 autocast
    model = with_precision(model, "int8", calibration=batches) # int8: the BEV encoder calibrated on these batches

``bf16`` runs an inference copy of the model (``fold_batchnorm``: BatchNorm folded into the convolutions) with the
convolutions, linear layers and attention in bfloat16 (``torch.autocast``; their weights stored in bfloat16, the
convolutions' channels-last), and keeps in float32 what needs it: the camera geometry of the view transform, the
score matrix and the log-space Sinkhorn (models/view_transform.py, models/matching.py disable autocast there), and
the decoding, which reads the outputs cast back to float32. ``int8`` quantizes the BEV encoder
by torch's FX graph mode (``x86`` engine: per-channel int8 weights, uint8 activations) as two graphs, before and
after the temporal fusion's place (``BEVHeads.first_stage`` / ``.rest``), the heads' last 1x1 layers kept float32;
its activation ranges are calibrated on training samples, and it runs on the CPU (docs/deploy.md, "Precision", for
its speed and accuracy; onnxruntime's static int8 of the whole graph was measured slower than ``bf16`` eager). The
rest of an int8 model runs as ``bf16`` does where the CPU computes bfloat16 natively, and in float32 (BatchNorm
folded) where it does not: there, emulated bfloat16 is several times slower than float32 (the depthwise
convolutions of EfficientNet fall back to one slow convolution per channel group), while int8 runs on AVX2 too.
``auto`` picks bf16 where the hardware computes it natively (a CUDA device that supports it; a CPU with AVX512-BF16
or AMX-BF16, or ARM's BF16, read from its flags, never assumed) and fp32 elsewhere, and says what it chose; it never
picks int8, which needs training samples. Forcing bf16 on a CPU without native bf16 works (torch emulates it) but
is slower than fp32: a note says so; int8 there says that its float part runs in float32.

``compile_backbone(model)`` (``Mapper.from_checkpoint(..., compile_backbone=True)``) runs such a model's image
backbone through ``torch.compile`` with inductor's weight freezing, the rest eager: on the CPU the part that gains
(docs/deploy.md, "Fast torch paths").
"""

from __future__ import annotations

import copy
import math
import warnings

import torch
import torch.nn.functional as F
from efficientnet_pytorch.model import EfficientNet, MBConvBlock
from efficientnet_pytorch.utils import Conv2dStaticSamePadding, MemoryEfficientSwish, Swish
from torch import nn

from .data import build_dataset
from .data.base import collate_fn
from .errors import UserError
from .models.bev_heads import BasicBlock
from .models.gnn import AttentionalPropagation
from .resources import cpu_flags, reuse_freed_memory

PRECISIONS = ("fp32", "bf16", "int8", "auto")
INT8_CALIBRATION_SAMPLES = 16  # training samples that calibrate the int8 activation ranges
# the CPU flags (/proc/cpuinfo) of native bfloat16 arithmetic: x86's AVX512-BF16 and AMX-BF16, ARM's BF16
NATIVE_BF16_FLAGS = frozenset({"avx512_bf16", "amx_bf16", "bf16"})


class PrecisionError(UserError, ValueError):
    """A precision this machine or this model cannot run."""


def native_bf16(device: torch.device, flags: set[str] | None = None) -> bool:
    """Whether ``device`` computes bfloat16 natively (``flags``: the CPU's, default /proc/cpuinfo's)."""
    if device.type == "cuda":
        return bool(torch.cuda.is_bf16_supported())
    if device.type == "cpu":
        return bool(NATIVE_BF16_FLAGS & (cpu_flags() if flags is None else flags))
    return False


def resolve_precision(precision: str, device: torch.device, flags: set[str] | None = None,
                      flag: str = "--precision") -> tuple[str, list[str]]:
    """``(fp32 | bf16 | int8, notes)`` for the asked ``precision`` on ``device`` (module docstring)."""
    if precision not in PRECISIONS:
        raise PrecisionError(f"{flag} {precision!r}: choose one of {', '.join(PRECISIONS)}")
    if precision == "fp32":
        return "fp32", []
    native = native_bf16(device, flags)
    where = "this GPU" if device.type == "cuda" else "this CPU"
    if precision == "auto":  # a note when it picks bf16; fp32 is the default precision
        return ("bf16", [f"{flag} auto: bf16, since {where} computes bfloat16 natively"]) if native else ("fp32", [])
    if precision == "int8" and device.type != "cpu":
        raise PrecisionError(f"{flag} int8 runs on the CPU (torch's int8 kernels); on {device.type} use {flag} bf16")
    if not native:
        if device.type == "cuda":
            raise PrecisionError(f"{flag} bf16: this GPU ({torch.cuda.get_device_name(device)}) has no bfloat16; "
                                 f"use {flag} fp32")
        if precision == "int8":
            return precision, [f"{flag} int8 on a CPU without native bfloat16: the BEV encoder in int8, the rest in "
                               "float32 (emulated bfloat16 would be slower than float32)"]
        return precision, [f"{flag} {precision} on a CPU without native bfloat16 (no AVX512-BF16 / AMX-BF16 / BF16 "
                           f"flag): its bf16 parts are emulated, slower than fp32 ({flag} auto picks fp32 here)"]
    return precision, []


def training_amp(amp: str, device: torch.device, flags: set[str] | None = None) -> tuple[str, str | None]:
    """``(none | bf16 | fp16, note)`` for ``train.amp`` on ``device``: ``auto`` is bf16 where the device computes
    bfloat16 natively, none elsewhere (with a note saying which); bf16 on a CPU without it gets a note that it is
    emulated and slower than float32."""
    if amp == "auto":
        if native_bf16(device, flags):
            return "bf16", f"train.amp auto: bf16, since this {device.type.upper()} computes bfloat16 natively"
        return "none", f"train.amp auto: float32, since this {device.type.upper()} has no native bfloat16"
    if amp == "bf16" and device.type == "cpu" and not native_bf16(device, flags):
        return amp, ("note: train.amp bf16 on a CPU without native bfloat16 (no AVX512-BF16 / AMX-BF16 / BF16 flag) "
                     "is emulated, slower than float32 (train.amp=auto picks float32 here)")
    return amp, None


# (conv, BatchNorm) attribute pairs of the modules whose forward applies that BatchNorm right after that conv
# (efficientnet_pytorch's blocks and stem; our ResNet block); an nn.Sequential's adjacent pairs fold too
FOLDED_PAIRS = {
    BasicBlock: (("conv1", "bn1"), ("conv2", "bn2")),
    MBConvBlock: (("_expand_conv", "_bn0"), ("_depthwise_conv", "_bn1"), ("_project_conv", "_bn2")),
    EfficientNet: (("_conv_stem", "_bn0"), ("_conv_head", "_bn1")),
}


def _fold_into(conv: nn.Conv2d, bn: nn.BatchNorm2d) -> None:
    """conv <- bn(conv(x)) with bn's running statistics (exact in eval mode: both are affine)."""
    scale = bn.weight / torch.sqrt(bn.running_var + bn.eps) if bn.affine else 1 / torch.sqrt(bn.running_var + bn.eps)
    shift = (bn.bias if bn.affine else 0) - bn.running_mean * scale
    bias = conv.bias if conv.bias is not None else torch.zeros_like(bn.running_mean)
    conv.weight = nn.Parameter((conv.weight * scale.view(-1, 1, 1, 1)).detach())
    conv.bias = nn.Parameter((bias * scale + shift).detach())


def _foldable(conv: nn.Module, bn: nn.Module) -> bool:
    return (isinstance(conv, nn.Conv2d) and isinstance(bn, nn.BatchNorm2d) and bn.track_running_stats
            and bn.num_features == conv.out_channels)


def _pad_in_conv(conv: Conv2dStaticSamePadding) -> None:
    """A static "same" padding as the convolution's own zero padding: no padded copy of the input. Symmetric
    padding moves as it is; padding of (p, p + 1) on a side (TensorFlow's "same" at stride 2) becomes p + 1 on
    both with the kernel one larger, its first row / column zero: output i reads the same inputs with the same
    weights, and the output size is the same."""
    pad = conv.static_padding
    if not isinstance(pad, nn.ZeroPad2d) or tuple(conv.dilation) != (1, 1):
        return
    left, right, top, bottom = pad.padding
    if right - left not in (0, 1) or bottom - top not in (0, 1):
        return
    grow_w, grow_h = right - left, bottom - top
    if grow_w or grow_h:
        weight = conv.weight
        conv.weight = nn.Parameter(F.pad(weight, (grow_w, 0, grow_h, 0)).detach())
        conv.kernel_size = tuple(conv.weight.shape[-2:])
    conv.padding, conv.static_padding = (bottom, right), nn.Identity()


class _InferenceMBConv(MBConvBlock):
    """efficientnet_pytorch's block in ``fold_batchnorm``'s inference copy: its forward in eval mode (no drop
    connect), the squeeze-and-excitation's global mean taken by ``avg_pool2d`` over the whole map where the
    activations are channels-last. There, ``adaptive_avg_pool2d`` is far slower: 11.8 ms against 0.46 ms in
    bfloat16 for B4's first expanded map (6 x 144 x 64 x 176, 2 threads), 1.1 against 0.8 ms in float32; on
    contiguous float32 it is the faster of the two, and stays."""

    def forward(self, inputs: torch.Tensor, drop_connect_rate: float | None = None) -> torch.Tensor:
        x = inputs
        if self._block_args.expand_ratio != 1:
            x = self._swish(self._bn0(self._expand_conv(x)))
        x = self._swish(self._bn1(self._depthwise_conv(x)))
        if self.has_se:
            pooled = (F.avg_pool2d(x, x.shape[-2:]) if x.is_contiguous(memory_format=torch.channels_last)
                      else F.adaptive_avg_pool2d(x, 1))
            x = torch.sigmoid(self._se_expand(self._swish(self._se_reduce(pooled)))) * x
        x = self._bn2(self._project_conv(x))
        args = self._block_args
        if self.id_skip and args.stride == 1 and args.input_filters == args.output_filters:
            x = x + inputs
        return x


def fold_batchnorm(model: nn.Module) -> nn.Module:
    """An inference copy of ``model``: eval mode, every BatchNorm that directly follows a convolution folded
    into it (``FOLDED_PAIRS`` and adjacent pairs of an ``nn.Sequential``; the BatchNorm becomes an identity),
    efficientnet_pytorch's swish (x * sigmoid(x) in two operations) as one ``nn.SiLU``, its symmetric "same"
    paddings inside the convolutions and its blocks' squeeze-and-excitation mean as ``_InferenceMBConv`` takes it.
    The same function up to float rounding, with fewer passes over each activation. ``model`` itself is left as
    it is."""
    model = copy.deepcopy(model).eval()
    with torch.no_grad():
        for module in model.modules():
            if isinstance(module, Conv2dStaticSamePadding):
                _pad_in_conv(module)
            pairs = list(FOLDED_PAIRS.get(type(module), ()))
            if isinstance(module, nn.Sequential):
                names = list(module._modules)
                pairs += list(zip(names, names[1:]))
            for conv_name, bn_name in pairs:
                conv, bn = getattr(module, conv_name, None), getattr(module, bn_name, None)
                if _foldable(conv, bn):
                    _fold_into(conv, bn)
                    setattr(module, bn_name, nn.Identity())
            for name, child in module.named_children():
                if isinstance(child, (MemoryEfficientSwish, Swish)):
                    setattr(module, name, nn.SiLU(inplace=True))  # its inputs are fresh conv outputs
            if type(module) is MBConvBlock:
                module.__class__ = _InferenceMBConv  # the same module and weights, the inference forward
    return model


def _as_float32(value):
    if isinstance(value, torch.Tensor):
        return value.float() if value.is_floating_point() and value.dtype != torch.float32 else value
    if isinstance(value, dict):
        return {k: _as_float32(v) for k, v in value.items()}
    return value


class _Bf16Attention(AttentionalPropagation):
    """The GNN layer in the bf16 inference copy: its attention as two batched products around a softmax, the key
    mask an additive bias of the scores (0 / -inf), where ``scaled_dot_product_attention``'s CPU kernel is ~2x
    slower in bfloat16: 1.22 against 0.72 ms per layer at N = 400, D = 256, 4 heads (2 threads, a Zen 5 EPYC with
    AVX512-BF16). The same function; its probabilities are rounded to bfloat16 where the fused kernel keeps them
    in float32 (the outputs' mean difference from float32 1.4x the kernel's). On a GPU, the fused kernel runs."""

    def attend(self, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, attn_mask: torch.Tensor) -> torch.Tensor:
        if not q.is_cpu:
            return super().attend(q, k, v, attn_mask)
        B, h, N, d = q.shape
        bias = torch.zeros(attn_mask.shape, dtype=q.dtype, device=q.device).masked_fill_(~attn_mask, -math.inf)
        scores = torch.baddbmm(bias.expand(B, h, 1, N).reshape(B * h, 1, N), q.reshape(B * h, N, d),
                               k.reshape(B * h, N, d).transpose(1, 2), alpha=d ** -0.5)  # [B h, N, N]
        return torch.bmm(scores.softmax(-1), v.reshape(B * h, N, d)).view(B, h, N, d)


def _in_bf16(model: nn.Module) -> nn.Module:
    """``model`` (an inference copy) with its convolution and linear weights in bfloat16 (what autocast would cast
    them to at every call), the convolutions' channels-last, its GNN layers' attention as ``_Bf16Attention``
    computes it; other parameters, and the float layers of an int8 encoder (``_Int8Heads``, run with autocast
    off), stay float32. In place."""
    model.to(memory_format=torch.channels_last)
    int8 = {id(m) for heads in model.modules() if isinstance(heads, _Int8Heads) for m in heads.modules()}
    for module in model.modules():
        if isinstance(module, (nn.Conv2d, nn.Linear)) and id(module) not in int8:
            module.to(torch.bfloat16)
        if type(module) is AttentionalPropagation:
            module.__class__ = _Bf16Attention
    return model


class Bf16Model(nn.Module):
    """``model``'s forward under bfloat16 autocast on its device, its outputs (and memory) back in float32. It wraps
    an inference copy (``fold_batchnorm``, then ``_in_bf16``: every parameter but the convolutions' and linear
    layers' stays float32, normalisation and the dustbin score among them), whose attributes (``is_temporal``, its
    heads) read through."""

    def __init__(self, model: nn.Module):
        super().__init__()
        self.model = _in_bf16(fold_batchnorm(model))

    def __getattr__(self, name: str):
        try:
            return super().__getattr__(name)
        except AttributeError:
            return getattr(super().__getattr__("model"), name)

    def forward(self, batch: dict, memory: dict | None = None) -> dict:
        device = batch["images"].device
        with torch.autocast(device.type, dtype=torch.bfloat16):
            out = self.model(batch) if memory is None else self.model(batch, memory=memory)
        return _as_float32(out)


class _Stage(nn.Module):
    """One of the BEV encoder's two stages (``BEVHeads.first_stage`` or ``.rest``) as a module for FX to trace."""

    def __init__(self, heads: nn.Module, stage: str):
        super().__init__()
        self.heads, self.stage = heads, stage

    def forward(self, x: torch.Tensor):
        return getattr(self.heads, self.stage)(x)


class _Int8Heads(nn.Module):
    """The BEV encoder as two int8 graphs, ``BEVHeads.forward``'s split: the stem and first stage, then the
    temporal fusion (``fuse``, in bf16) where there is one, then the rest. Autocast is off in the graphs: their
    float inputs are quantized inside, their outputs come back in float32."""

    def __init__(self, first: nn.Module, rest: nn.Module):
        super().__init__()
        self.first, self.rest = first, rest

    def forward(self, bev: torch.Tensor, fuse=None) -> dict[str, torch.Tensor]:
        with torch.autocast(bev.device.type, enabled=False):
            first = self.first(bev.float())
        if fuse is not None:
            first = fuse(first)
        with torch.autocast(bev.device.type, enabled=False), warnings.catch_warnings():
            # the up-block concatenates the first stage (its own scale) with the upsampled last one: the
            # quantized cat requantizes both to its output's scale, which torch warns of (the AP holds: docs/deploy.md)
            warnings.filterwarnings("ignore", message="All inputs of this cat operator")
            return self.rest(first.float())


def _quantize_bev_heads(model: nn.Module, calibration: list[dict]) -> None:
    """``model.bev_heads`` as ``_Int8Heads``, calibrated on ``calibration`` in float32. The last 1x1 layers of
    the vertex and distance heads (the logits, the distance transform) stay float (with them in int8 too, the
    demo's ped-crossing AP fell by 0.006 more: docs/deploy.md). Sets torch's quantized engine (process-wide) to
    x86 where it has it, else qnnpack."""
    from torch.ao.quantization import get_default_qconfig_mapping
    from torch.ao.quantization.quantize_fx import convert_fx, prepare_fx

    engine = "x86" if "x86" in torch.backends.quantized.supported_engines else "qnnpack"
    torch.backends.quantized.engine = engine
    heads = model.bev_heads
    qconfig = get_default_qconfig_mapping(engine)
    for name in ("vertex_head", "distance_head"):
        if getattr(heads, name) is not None:
            qconfig = qconfig.set_module_name(f"heads.{name}.{len(getattr(heads, name)) - 1}", None)
    inputs = {"first_stage": heads.stem[0].in_channels, "rest": heads.stem[0].out_channels}  # their channels
    with warnings.catch_warnings():  # torch's notices that its FX quantization moves to torchao
        warnings.simplefilter("ignore")
        first, rest = (prepare_fx(_Stage(copy.deepcopy(heads), stage), qconfig, (torch.zeros(1, c, 16, 16),))
                       for stage, c in inputs.items())
        model.bev_heads = _Int8Heads(first, rest)
        with torch.no_grad():
            for batch in calibration:
                model(batch)
        model.bev_heads = _Int8Heads(convert_fx(first), convert_fx(rest))


def calibration_batches(cfg, count: int = INT8_CALIBRATION_SAMPLES, device: torch.device | str = "cpu",
                        flag: str = "--precision") -> list[dict]:
    """``count`` samples of ``cfg``'s training split (evenly spread over it, not augmented), each a batch of one
    as inference runs it: what ``int8`` calibrates its activation ranges on."""
    try:
        dataset = build_dataset(cfg, cfg.data.train_split, augment=False)
    except UserError as e:
        raise PrecisionError(f"{flag} int8 calibrates on training samples, which could not be read: {e}") from None
    if len(dataset) == 0:
        raise PrecisionError(f"{flag} int8 calibrates on training samples: the split '{cfg.data.train_split}' of "
                             f"{cfg.data.dataroot} has none")
    picks = sorted({round(i * (len(dataset) - 1) / max(count - 1, 1)) for i in range(min(count, len(dataset)))})
    batches = [collate_fn([dataset[i]]) for i in picks]
    return [{k: v.to(device) if isinstance(v, torch.Tensor) else v for k, v in b.items()} for b in batches]


class Int8Model(Bf16Model):
    """The BEV encoder in int8 (module docstring), calibrated on ``calibration``: batches as the model takes them
    (``data.collate_fn`` of training samples), run in float32 to record the activation ranges. The rest as
    ``Bf16Model`` runs it where ``bf16`` (default: where this CPU computes bfloat16 natively), else in float32."""

    def __init__(self, model: nn.Module, calibration: list[dict], bf16: bool | None = None):
        if not calibration:
            raise PrecisionError("int8 needs calibration batches (training samples): none given")
        folded = fold_batchnorm(model)
        _quantize_bev_heads(folded, calibration)  # in float32, before the rest goes to bf16 (where it does)
        nn.Module.__init__(self)
        self.bf16 = native_bf16(torch.device("cpu")) if bf16 is None else bf16
        self.model = _in_bf16(folded) if self.bf16 else folded

    def forward(self, batch: dict, memory: dict | None = None) -> dict:
        if self.bf16:
            return super().forward(batch, memory)
        return self.model(batch) if memory is None else self.model(batch, memory=memory)


def with_precision(model: nn.Module, precision: str, calibration: list[dict] | None = None,
                   compile_backbone: bool = False) -> nn.Module:
    """``model`` to run in ``precision`` (resolved: fp32, bf16 or int8; int8 calibrates on ``calibration``);
    fp32 returns it as it is. ``compile_backbone``: then its image backbone through ``torch.compile``
    (``compile_backbone``, in place). On the CPU, the process's allocator keeps the blocks a forward frees for the
    next (``resources.reuse_freed_memory``)."""
    if next(model.parameters(), torch.empty(0)).is_cpu:
        reuse_freed_memory()
    if precision == "bf16":
        model = model if isinstance(model, Bf16Model) else Bf16Model(model)
    elif precision == "int8":
        model = model if isinstance(model, Int8Model) else Int8Model(model, calibration or [])
    elif precision != "fp32":
        raise PrecisionError(f"with_precision: {precision!r} is not fp32, bf16 or int8 (resolve 'auto' first)")
    return _compile_backbone(model) if compile_backbone else model


def precision_of(model: nn.Module) -> str:
    """The precision ``model`` runs in: int8 for an ``Int8Model``, bf16 for a ``Bf16Model``, else fp32."""
    return "int8" if isinstance(model, Int8Model) else "bf16" if isinstance(model, Bf16Model) else "fp32"


class CompiledBackbone(nn.Module):
    """An inference model's image backbone run through ``torch.compile`` (inductor, weight freezing: the weights
    become constants of generated kernels that fuse each convolution's activation and the squeeze-and-excitation
    arithmetic). The first forward compiles (tens of seconds for an EfficientNet; again for another input shape,
    dtype or autocast state); a compilation that fails (no C++ compiler, an inductor error) warns once and the
    backbone runs eagerly from then on. Inference only: the forward runs without autograd."""

    def __init__(self, backbone: nn.Module):
        super().__init__()
        self.backbone = backbone
        # not a submodule (torch.compile's wrapper is a Module): the weights stay listed once, under backbone.*
        object.__setattr__(self, "compiled", torch.compile(backbone, dynamic=False))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        import torch._inductor.config as inductor_config

        with torch.no_grad():
            if self.compiled is not None:
                try:
                    with inductor_config.patch(freezing=True):
                        return self.compiled(images)
                except Exception as e:  # any backend failure: the eager backbone computes the same function
                    self.compiled = None
                    first_line = (str(e).strip().splitlines() or [""])[0][:200]
                    warnings.warn(f"compile_backbone: torch.compile failed ({type(e).__name__}: {first_line}); the "
                                  "backbone runs eagerly", stacklevel=2)
            return self.backbone(images)


def compile_backbone(model: nn.Module) -> nn.Module:
    """``model`` (an inference model: eval mode, e.g. ``with_precision``'s) with its image backbone as a
    ``CompiledBackbone``, in place; the rest stays eager (the whole model compiled,
    ``deploy.fast_forward(compile=True)``, took minutes to compile and ran slower on the CPU: docs/deploy.md).
    Returns ``model``."""
    inner = model
    while "backbone" not in inner._modules and isinstance(inner._modules.get("model"), nn.Module):
        inner = inner._modules["model"]  # Bf16Model / Int8Model wrap the inference copy (and read its attributes)
    if "backbone" not in inner._modules:
        raise PrecisionError(f"compile_backbone: {type(model).__name__} has no image backbone")
    if not isinstance(inner.backbone, CompiledBackbone):
        inner.backbone = CompiledBackbone(inner.backbone.eval())
    return model


_compile_backbone = compile_backbone  # with_precision's argument of the same name shadows the function
