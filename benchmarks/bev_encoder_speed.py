"""The BEV encoder alone (stem, ResNet stages, up-block, vertex and distance heads) in each CPU precision: its
latency, its convolutions' multiply-accumulates and the rate they run at, printed as a table.

    python benchmarks/bev_encoder_speed.py                     # Table I B4 LSS (the official BEV resolution)
    python benchmarks/bev_encoder_speed.py --runs 15 --threads 2
    python benchmarks/bev_encoder_speed.py --config configs/synthetic/demo.yaml

On the paper configs the encoder runs on the official 200 x 400 grid and is most of a bf16 / int8 forward
(``model_speed.py``'s "BEV heads" row). This script says whether it is bound by the convolutions' arithmetic: the
MACs are counted on the float model (forward hooks on every ``Conv2d``), and GMAC/s is that count over each
precision's median time. Near the CPU's peak for the precision's dot products (its VNNI int8 or BF16
instructions, AMX where there is one), the encoder cannot get faster without fewer MACs: a different
architecture than the official one.

The precisions are ``precision.py``'s inference paths: ``fp32`` the folded copy (``fold_batchnorm``), ``bf16``
``Bf16Model``'s copy under bfloat16 autocast, ``int8`` ``Int8Model``'s two quantized graphs (calibrated on a
random batch: the ranges do not change the speed), each given the input dtype it gets in the model (bfloat16 where
the rest runs in bf16). Random weights; the input is the view transform's output of a
random six-camera batch (``model_speed.example_batch``), channels-last as the LSS splat leaves it. Called in turn,
``--runs`` rounds after a warm-up, medians: the ratios of one run are the figures.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
from pathlib import Path

import torch

from instagram_hdmap.config import load_config
from instagram_hdmap.models import build_model
from instagram_hdmap.models.view_transform import CALIBRATION_KEYS
from instagram_hdmap.precision import Bf16Model, Int8Model, fold_batchnorm, native_bf16
from instagram_hdmap.resources import cpu_capability, reuse_freed_memory

sys.path.insert(0, str(Path(__file__).resolve().parent))
from model_speed import example_batch, time_interleaved

DEFAULT_CONFIG = "configs/paper/table1_b4_lss_128x352.yaml"


def conv_macs(heads: torch.nn.Module, bev: torch.Tensor) -> int:
    """Multiply-accumulates of every convolution of ``heads`` on ``bev`` (one float forward)."""
    counts: list[int] = []

    def count(module: torch.nn.Conv2d, inputs, output: torch.Tensor) -> None:
        counts.append(output.numel() * module.weight[0].numel())  # per output: C_in / groups x kh x kw

    hooks = [m.register_forward_hook(count) for m in heads.modules() if isinstance(m, torch.nn.Conv2d)]
    try:
        with torch.inference_mode():
            heads(bev)
    finally:
        for hook in hooks:
            hook.remove()
    return sum(counts)


def encoder_input(model: torch.nn.Module, cfg) -> torch.Tensor:
    """The view transform's output for a random batch of the config's image size: the encoder's input."""
    batch = example_batch(tuple(cfg.data.image_size), torch.device("cpu"))
    with torch.inference_mode():
        images = batch["images"]
        features = model.backbone(images.flatten(0, 1)).unflatten(0, images.shape[:2])
        return model.view_transform(features, {k: batch[k] for k in CALIBRATION_KEYS}).clone()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default=DEFAULT_CONFIG, help=f"experiment YAML (default {DEFAULT_CONFIG})")
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--threads", type=int, default=2, help="CPU threads (torch.set_num_threads)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    reuse_freed_memory()  # as inference runs (resources.py)
    cfg = load_config(args.config)
    torch.manual_seed(0)
    model = build_model(cfg).eval()
    bev = encoder_input(model, cfg)
    macs = conv_macs(model.bev_heads, bev)
    fp32 = fold_batchnorm(model).bev_heads
    paths = {"fp32": lambda: fp32(bev)}
    half = bev.bfloat16()  # what the bf16 view transform hands the encoder (channels-last kept)
    if native_bf16(torch.device("cpu")):
        bf16 = Bf16Model(model).model.bev_heads

        def run_bf16():
            with torch.autocast("cpu", dtype=torch.bfloat16):
                return bf16(half)

        paths["bf16"] = run_bf16
    else:
        print("this CPU has no native bfloat16: bf16 left out (emulated, it is slower than fp32)")
    # int8's graphs take the rest's output: bf16 where the CPU computes it natively, else float32
    int8 = Int8Model(model, [example_batch(tuple(cfg.data.image_size), torch.device("cpu"))])
    int8_input = half if int8.bf16 else bev
    paths["int8"] = lambda: int8.model.bev_heads(int8_input)
    times = time_interleaved(paths, args.runs, warmup=2, sync=lambda: None)
    medians = {name: 1000 * statistics.median(t) for name, t in times.items()}
    print(f"{cfg.name} ({args.config}): BEV encoder input {list(bev.shape)}, convolutions {macs / 1e9:.2f} GMAC; "
          f"CPU, {args.threads} threads, {args.runs} runs, torch {torch.__version__}, quantized engine "
          f"{torch.backends.quantized.engine}, load average {os.getloadavg()[0]:.1f} at the end; {cpu_capability()}")
    print()
    print("| precision | ms (median) | x fp32 | GMAC/s |")
    print("| --- | --- | --- | --- |")
    for name, ms in medians.items():
        print(f"| {name} | {ms:.1f} | {ms / medians['fp32']:.3f} | {macs / 1e9 / (ms / 1000):.0f} |")


if __name__ == "__main__":
    main()
