"""The precision a trained model runs in at inference: ``fp32``, ``bf16`` or ``auto``.

    precision, notes = resolve_precision("auto", device)       # what this machine runs best, and why
    model = with_precision(model, precision)                   # bf16: the forward under bfloat16 autocast

``bf16`` runs the convolutions, linear layers and attention in bfloat16 (``torch.autocast``) with the weights in
channels-last order, and keeps in float32 what needs it: the camera geometry of the view transform, the score
matrix and the log-space Sinkhorn (models/view_transform.py, models/matching.py disable autocast there), and the
decoding, which reads the outputs cast back to float32. ``auto`` picks bf16 where the hardware computes it
natively (a CUDA device that supports it; a CPU with AVX512-BF16 or AMX-BF16, or ARM's BF16, read from its flags,
never assumed) and fp32 elsewhere, and says what it chose. Forcing bf16 on a CPU without native bf16 works (torch
emulates it) but is slower than fp32: a note says so.
"""

from __future__ import annotations

import torch
from torch import nn

from .errors import UserError
from .resources import cpu_flags

PRECISIONS = ("fp32", "bf16", "auto")
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
    """``(fp32 | bf16, notes)`` for the asked ``precision`` on ``device`` (module docstring)."""
    if precision not in PRECISIONS:
        raise PrecisionError(f"{flag} {precision!r}: choose one of {', '.join(PRECISIONS)}")
    native = native_bf16(device, flags) if precision != "fp32" else False
    where = "this GPU" if device.type == "cuda" else "this CPU"
    if precision == "auto":  # a note when it picks bf16; fp32 is the default precision
        return ("bf16", [f"{flag} auto: bf16, since {where} computes bfloat16 natively"]) if native else ("fp32", [])
    if precision == "bf16" and not native:
        if device.type == "cuda":
            raise PrecisionError(f"{flag} bf16: this GPU ({torch.cuda.get_device_name(device)}) has no bfloat16; "
                                 f"use {flag} fp32")
        return "bf16", [f"{flag} bf16 on a CPU without native bfloat16 (no AVX512-BF16 / AMX-BF16 / BF16 flag): torch "
                        f"emulates it, slower than fp32 ({flag} auto picks fp32 here)"]
    return precision, []


def _as_float32(value):
    if isinstance(value, torch.Tensor):
        return value.float() if value.is_floating_point() and value.dtype != torch.float32 else value
    if isinstance(value, dict):
        return {k: _as_float32(v) for k, v in value.items()}
    return value


class Bf16Model(nn.Module):
    """``model``'s forward under bfloat16 autocast on its device, its outputs (and memory) back in float32.

    The wrapped model's attributes (``is_temporal``, its heads) read through; its weights stay float32 (autocast
    casts them per operation), in channels-last order for the convolutions."""

    def __init__(self, model: nn.Module):
        super().__init__()
        self.model = model.to(memory_format=torch.channels_last)

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


def with_precision(model: nn.Module, precision: str) -> nn.Module:
    """``model`` to run in ``precision`` (resolved: fp32 or bf16); fp32 returns it as it is."""
    if precision == "fp32":
        return model
    if precision == "bf16":
        return model if isinstance(model, Bf16Model) else Bf16Model(model)
    raise PrecisionError(f"with_precision: {precision!r} is not fp32 or bf16 (resolve 'auto' first)")


def precision_of(model: nn.Module) -> str:
    """The precision ``model`` runs in: bf16 for a ``Bf16Model``, else fp32."""
    return "bf16" if isinstance(model, Bf16Model) else "fp32"
