"""Running a trained model in bf16 or int8 (``--precision``, ``Mapper.from_checkpoint(precision=...)``): what ``auto``
picks from the hardware's flags, the note on an emulated bf16, the folded inference copy computing the same function,
outputs in float32 close to fp32's with the same decoded elements on a trained tiny model, and the precision recorded
where a result is written."""

from __future__ import annotations

import copy
import json
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from efficientnet_pytorch.model import MBConvBlock

from instagram_hdmap import Mapper, precision
from instagram_hdmap.config import load_config
from instagram_hdmap.precision import (
    Bf16Model,
    Int8Model,
    PrecisionError,
    fold_batchnorm,
    native_bf16,
    precision_of,
    resolve_precision,
    with_precision,
)

REPO = Path(__file__).resolve().parents[1]
CPU = torch.device("cpu")


def test_auto_picks_bf16_only_where_the_cpu_computes_it_natively():
    assert resolve_precision("auto", CPU, {"avx2", "avx512f"}) == ("fp32", [])
    chosen, notes = resolve_precision("auto", CPU, {"avx2", "amx_bf16", "avx512_bf16"})
    assert chosen == "bf16" and "natively" in notes[0]
    assert resolve_precision("auto", CPU, {"bf16", "asimd"})[0] == "bf16"  # ARM's BF16
    chosen, notes = resolve_precision("bf16", CPU, {"avx2"})  # forced: it runs, emulated, and says so
    assert chosen == "bf16" and "emulated, slower than fp32" in notes[0]
    assert resolve_precision("fp32", CPU, {"amx_bf16"}) == ("fp32", [])
    assert resolve_precision("int8", CPU, {"amx_bf16"}) == ("int8", [])
    chosen, notes = resolve_precision("int8", CPU, {"avx2"})  # no emulated bf16 in it: its float part is float32
    assert chosen == "int8" and "the rest in float32" in notes[0]
    assert resolve_precision("auto", CPU, {"amx_bf16", "amx_int8"})[0] == "bf16"  # int8 needs training samples
    assert native_bf16(CPU, set()) is False
    with pytest.raises(PrecisionError, match="--precision 'int4': choose one of fp32, bf16, int8, auto"):
        resolve_precision("int4", CPU)
    with pytest.raises(PrecisionError, match="--precision int8 runs on the CPU"):
        resolve_precision("int8", torch.device("cuda"))


def test_the_folded_inference_copy_computes_the_same_function(monkeypatch):
    """BatchNorm folded into the convolutions (with running statistics far from the identity), EfficientNet's
    static "same" paddings (symmetric and the asymmetric ones of its stride-2 convolutions) moved into them: the
    outputs of the original model to float rounding, also channels-last (the blocks' squeeze-and-excitation mean by
    avg_pool2d there), and the original left as it was."""
    from instagram_hdmap.models import build_model

    cfg = load_config(REPO / "configs/synthetic/tiny.yaml", ["model.backbone.name=efficientnet-b0"])
    torch.manual_seed(0)
    model = build_model(cfg).eval()
    for m in model.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.5, 0.5), m.running_var.uniform_(0.5, 2.0)
            m.weight.data.uniform_(0.5, 1.5), m.bias.data.uniform_(-0.2, 0.2)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    folded = fold_batchnorm(model)
    kinds = lambda net, kind: sum(isinstance(m, kind) for m in net.modules())  # noqa: E731
    assert kinds(model, torch.nn.BatchNorm2d) > 20 and kinds(folded, torch.nn.BatchNorm2d) == 0
    assert kinds(folded, torch.nn.ZeroPad2d) == 0 < kinds(model, torch.nn.ZeroPad2d)
    assert any(m.kernel_size == (4, 4) for m in folded.modules() if isinstance(m, torch.nn.Conv2d))  # asymmetric
    assert kinds(folded, precision._InferenceMBConv) == kinds(model, MBConvBlock) > 0
    batch = _rig_batch(cfg)
    pooled = []  # the squeeze-and-excitation's mean: avg_pool2d where the activations are channels-last
    avg_pool2d = torch.nn.functional.avg_pool2d
    monkeypatch.setattr(precision.F, "avg_pool2d", lambda x, k: pooled.append(k) or avg_pool2d(x, k))
    with torch.no_grad():
        a, b = model(batch), folded(batch)
        assert not pooled
        c = copy.deepcopy(folded).to(memory_format=torch.channels_last)(batch)
        assert len(pooled) == kinds(model, MBConvBlock)
    for key in ("pred_vertex_logits", "pred_distance"):
        assert torch.allclose(a[key], b[key], atol=1e-5, rtol=1e-4), key
        assert torch.allclose(a[key], c[key], atol=1e-5, rtol=1e-4), key
    assert all(torch.equal(v, model.state_dict()[k]) for k, v in before.items())


def test_the_bf16_copy_attends_as_the_fused_kernel_does():
    """The bf16 copy's GNN layers take their attention as two products around a softmax with the key mask as a
    bias: scaled_dot_product_attention's function, padded keys ignored, in float32 to rounding and in bfloat16
    close to float32."""
    from instagram_hdmap.models import build_model
    from instagram_hdmap.models.gnn import AttentionalPropagation

    cfg = load_config(REPO / "configs/synthetic/tiny.yaml")
    torch.manual_seed(0)
    model = build_model(cfg).eval()
    half = precision.Bf16Model(model)
    layers = sum(isinstance(m, AttentionalPropagation) for m in model.modules())
    assert sum(type(m) is precision._Bf16Attention for m in half.modules()) == layers == cfg.model.gnn.layers
    layer = AttentionalPropagation(32, 4).eval()
    fast = copy.deepcopy(layer)
    fast.__class__ = precision._Bf16Attention
    g = torch.randn(2, 10, 32)
    keys = (torch.arange(10)[None] < torch.tensor([10, 6])[:, None])[:, None, None, :]
    with torch.no_grad():
        expected = layer(g, keys)
        torch.testing.assert_close(fast(g, keys), expected, atol=1e-5, rtol=1e-5)
        moved = g.clone()
        moved[1, 6:] = 100.0  # what a padded key holds never reaches a real vertex
        torch.testing.assert_close(fast(moved, keys)[1, :6], expected[1, :6], atol=1e-5, rtol=1e-5)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            low = fast(g, keys).float()
    assert (low - expected).abs().max() <= 0.05 * expected.abs().max()


def _rig_batch(cfg, seed: int = 0) -> dict:
    sys.path.insert(0, str(REPO / "benchmarks"))
    from model_speed import example_batch

    torch.manual_seed(seed)
    return example_batch(tuple(cfg.data.image_size), CPU)


@pytest.fixture(scope="module")
def trained(tmp_path_factory, tiny_world, world_overrides):
    """The tiny model trained on four samples of the tiny world until it maps them (benchmarks/overfit.py), saved
    as a checkpoint, and those samples' batch."""
    sys.path.insert(0, str(REPO / "benchmarks"))
    from instagram_hdmap.checkpoint import save_checkpoint
    from instagram_hdmap.config import config_to_dict
    from overfit import TINY_CONFIG, overfit_batch, run_overfit

    cfg = load_config(TINY_CONFIG, [*world_overrides(tiny_world), "data.augment=false", "data.num_workers=0",
                                    "train.device=cpu"])
    batch = overfit_batch(cfg, 4)
    torch.manual_seed(0)
    model = run_overfit(cfg, batch, steps=150, lr=3e-3, every=150, echo=lambda line: None)["model"]
    path = save_checkpoint({"model": model.state_dict(), "config": config_to_dict(cfg)},
                           tmp_path_factory.mktemp("bf16") / "tiny.pt")
    return path, cfg, batch


def _chamfer(a: np.ndarray, b: np.ndarray) -> float:
    d = np.linalg.norm(a[:, None] - b[None], axis=-1)
    return float((d.min(0).mean() + d.min(1).mean()) / 2)


@pytest.mark.parametrize("precision,cpu", [("bf16", "amx"), ("int8", "amx"), ("int8", "avx2")])
def test_outputs_stay_close_to_fp32_and_decode_to_the_same_elements(trained, precision, cpu, monkeypatch):
    import instagram_hdmap.precision as precision_module
    from instagram_hdmap.inference import load_model
    from instagram_hdmap.postprocess import decode_options, postprocess_batch

    ckpt, cfg, batch = trained
    monkeypatch.setattr(precision_module, "cpu_flags", lambda: {"amx": {"avx2", "amx_bf16"}, "avx2": {"avx2"}}[cpu])
    model, cfg, _ = load_model(ckpt, cfg, device=CPU)
    half, _, notes = load_model(ckpt, cfg, device=CPU, precision=precision)  # int8: calibrated on training samples
    assert precision_of(half) == precision and isinstance(half, Int8Model) == (precision == "int8")
    assert half.is_temporal == model.is_temporal  # attributes read through
    # int8: the BEV encoder is two quantized graphs whose last 1x1 layers stay float32; the rest is bf16 where the
    # CPU computes it natively, float32 where it would be emulated (and a note says so)
    rest = torch.float32 if cpu == "avx2" else torch.bfloat16
    assert any("the rest in float32" in n for n in notes) == (cpu == "avx2")
    encoder = {id(m) for m in half.model.bev_heads.modules()} if precision == "int8" else set()
    weights = {type(m).__name__: m.weight.dtype for m in half.modules() if hasattr(m, "weight") and
               isinstance(m.weight, torch.Tensor) and id(m) not in encoder}
    if precision == "int8":
        kinds = {type(m).__module__ for m in half.model.bev_heads.modules()}
        assert any("quantized" in k for k in kinds)
        assert {m.weight.dtype for m in half.model.bev_heads.modules() if type(m) is torch.nn.Conv2d} == {
            torch.float32}
    assert weights["Conv2d"] == weights["Linear"] == rest and weights["LayerNorm"] == torch.float32
    assert next(model.parameters()).dtype == torch.float32
    with torch.no_grad():
        a, b = model(batch), half(batch)
    assert all(v.dtype == torch.float32 for v in b.values() if torch.is_tensor(v) and v.is_floating_point())
    # int8's uint8 activations of the tiny model's 16-channel encoder: coarser at the heatmap's peaks than bf16
    bound = {"bf16": 0.05, "int8": 0.35}[precision]  # (int8 with a float32 rest: the encoder's error alone)
    scale = a["pred_heatmap"].abs().max()
    assert (a["pred_heatmap"] - b["pred_heatmap"]).abs().max() <= bound * scale
    assert (a["pred_distance"] - b["pred_distance"]).abs().max() <= bound * cfg.data.dt_clip
    from instagram_hdmap.geometry import BEVGrid

    grid = BEVGrid.from_config(cfg.grid)
    options = decode_options(cfg.model.gnn, grid)
    fp32, bf16 = postprocess_batch(a, grid, **options), postprocess_batch(b, grid, **options)
    assert sum(map(len, fp32)) >= 3  # a model that maps something
    total = agree = 0
    for pa, pb in zip(fp32, bf16):
        if precision == "bf16":
            assert abs(len(pa) - len(pb)) <= max(1, len(pa) // 5)
        total += len(pa)
        agree += sum(any(q["label"] == p["label"] and _chamfer(np.asarray(p["pts"]), np.asarray(q["pts"])) < 0.5
                         for q in pb) for p in pa)
    # the same map elements, to half a metre (an edge near its threshold may differ)
    assert agree >= {"bf16": 0.8, "int8": 0.5}[precision] * total


def test_the_precision_is_chosen_and_recorded_where_results_are_written(trained, tmp_path, monkeypatch):
    import instagram_hdmap.precision as precision

    ckpt, cfg, _ = trained
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        forced = Mapper.from_checkpoint(ckpt, "cpu", precision="bf16")
    assert isinstance(forced.model, Bf16Model) and repr(forced).endswith("bf16)")
    if not native_bf16(CPU):
        assert any("emulated" in str(w.message) for w in caught)
    monkeypatch.setattr(precision, "cpu_flags", lambda: {"amx_bf16"})  # a CPU with AMX: auto is bf16, and says so
    with pytest.warns(UserWarning, match="precision auto: bf16"):
        assert isinstance(Mapper.from_checkpoint(ckpt, "cpu", precision="auto").model, Bf16Model)
    assert not isinstance(Mapper.from_checkpoint(ckpt, "cpu").model, Bf16Model)  # fp32 unless asked
    monkeypatch.setattr(precision, "cpu_flags", lambda: {"avx2"})
    assert not isinstance(Mapper.from_checkpoint(ckpt, "cpu", precision="auto").model, Bf16Model)
    from instagram_hdmap.evaluate_split import run_evaluation

    run_evaluation(cfg, ckpt, "vector", tmp_path / "e", precision="bf16")
    assert json.loads((tmp_path / "e" / "metrics.json").read_text())["meta"]["precision"] == "bf16"


def test_evaluate_with_the_backbone_compiled_scores_as_the_eager_backbone(trained, tmp_path):
    """``evaluate --compile-backbone`` (``run_evaluation(compile_backbone=True)``): the image backbone through
    torch.compile, the same AP as the eager backbone's, and the metrics say that it was compiled."""
    from instagram_hdmap.evaluate_split import run_evaluation

    ckpt, cfg, _ = trained
    eager = run_evaluation(cfg, ckpt, "vector", tmp_path / "eager")["metrics"]
    result = run_evaluation(cfg, ckpt, "vector", tmp_path / "compiled", compile_backbone=True)
    compiled = json.loads((tmp_path / "compiled" / "metrics.json").read_text())
    assert compiled["meta"]["compile_backbone"] is True and eager["meta"]["compile_backbone"] is False
    assert any("torch.compile" in n for n in result["notes"])
    assert eager["mAP"] > 0  # a model that maps something
    for name, ap in eager["AP_class"].items():  # float rounding of the fused kernels moves no element
        assert compiled["AP_class"][name] == pytest.approx(ap, abs=0.01)


def test_int8_needs_training_samples(trained, tmp_path):
    import dataclasses

    from instagram_hdmap.inference import load_model

    ckpt, cfg, batch = trained
    model, cfg, _ = load_model(ckpt, cfg, device=CPU)
    with pytest.raises(PrecisionError, match="int8 needs calibration batches"):
        with_precision(model, "int8")
    assert isinstance(with_precision(model, "int8", [batch]), Int8Model)
    from instagram_hdmap.precision import calibration_batches

    missing = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, dataroot=str(tmp_path / "nowhere")))
    with pytest.raises(PrecisionError, match="int8 calibrates on training samples, which could not be read"):
        calibration_batches(missing)


def test_an_int8_temporal_model_fuses_its_memory_between_the_two_int8_graphs():
    """The temporal fusion sits after the BEV encoder's first stage: int8 quantizes the stages before and after it
    as two graphs and runs the fusion (in bf16) between them, carrying the memory as the fp32 model does."""
    from instagram_hdmap.models import build_model

    sys.path.insert(0, str(REPO / "tests"))
    from test_temporal import TINY, random_batch

    cfg = load_config(None, [*TINY, "model.temporal.memory=bev"])
    torch.manual_seed(0)
    model = build_model(cfg).eval()
    frames = [random_batch(cfg, B=1, seed=s) for s in range(3)]
    int8 = with_precision(model, "int8", calibration=frames)
    calls = []
    int8.model.temporal.register_forward_hook(lambda *_: calls.append(1))
    memory = memory8 = None
    with torch.no_grad():
        for batch in frames:
            out, out8 = model(batch, memory=memory), int8(batch, memory=memory8)
            memory, memory8 = out["memory"], out8["memory"]
            assert out8["pred_vertex_logits"].dtype == torch.float32
            scale = out["pred_vertex_logits"].abs().max()
            assert (out8["pred_vertex_logits"] - out["pred_vertex_logits"]).abs().max() < 0.35 * scale
    assert len(calls) == len(frames)  # the fusion ran every frame
    assert memory8["bev"].shape == memory["bev"].shape and torch.isfinite(memory8["bev"]).all()


def test_train_amp_auto_is_bf16_only_where_the_device_computes_it_natively():
    from instagram_hdmap.precision import training_amp

    assert training_amp("auto", CPU, {"avx2", "amx_bf16"}) == (
        "bf16", "train.amp auto: bf16, since this CPU computes bfloat16 natively")
    amp, note = training_amp("auto", CPU, {"avx2", "avx512f"})
    assert amp == "none" and "no native bfloat16" in note
    amp, note = training_amp("bf16", CPU, {"avx2"})  # forced: it trains, emulated, and says so
    assert amp == "bf16" and "emulated, slower than float32" in note
    assert training_amp("bf16", CPU, {"avx512_bf16"}) == ("bf16", None)
    assert training_amp("none", CPU, set()) == ("none", None)


TINY = REPO / "configs/synthetic/tiny.yaml"
FAST = ["model.gnn.sinkhorn_iters=5", "model.gnn.num_vertices=128"]


def random_model(cfg, seed: int = 0):
    from instagram_hdmap.models import build_model

    torch.manual_seed(seed)
    return build_model(cfg).eval()


def batch_for(cfg, seed: int) -> dict:
    from instagram_hdmap.deploy import example_inputs

    return example_inputs(cfg, seed)


def test_a_compiled_backbone_computes_the_eager_backbones_function():
    """``compile_backbone`` compiles the image backbone of an inference model in place (inside a precision
    wrapper, not on it): the first forward compiles, the outputs are the eager model's to float rounding."""
    cfg = load_config(TINY, FAST)
    model = fold_batchnorm(random_model(cfg))
    batch = batch_for(cfg, 0)
    with torch.no_grad():
        expected = model(batch)
    compiled = precision.compile_backbone(fold_batchnorm(model))
    assert isinstance(compiled.backbone, precision.CompiledBackbone)
    assert sorted(compiled.state_dict()) == sorted(k.replace("backbone.", "backbone.backbone.", 1)
                                                   for k in model.state_dict())  # each weight once
    with torch.no_grad():
        got = compiled(batch)
    assert compiled.backbone.compiled is not None  # compiled, not fallen back to eager
    for key in ("pred_vertex_logits", "pred_distance"):
        torch.testing.assert_close(got[key], expected[key], atol=1e-4, rtol=1e-4)
    wrapped = Bf16Model(model)
    assert precision.compile_backbone(wrapped) is wrapped and "backbone" not in wrapped._modules
    assert isinstance(wrapped.model.backbone, precision.CompiledBackbone)
    with pytest.raises(PrecisionError, match="has no image backbone"):
        precision.compile_backbone(torch.nn.Linear(2, 2))


def test_a_backbone_that_fails_to_compile_warns_once_and_runs_eagerly(monkeypatch):
    """No C++ compiler, an inductor error: one warning naming the failure, then the eager backbone."""
    import warnings

    cfg = load_config(TINY, FAST)
    model = random_model(cfg).eval()
    batch = batch_for(cfg, 0)
    with torch.no_grad():
        expected = model(batch)

    def failing(module, **kwargs):
        def run(*args):
            raise RuntimeError("C++ compile error\nlong log")
        return run

    monkeypatch.setattr(precision.torch, "compile", failing)
    precision.compile_backbone(model)
    with pytest.warns(UserWarning, match=r"torch.compile failed \(RuntimeError: C\+\+ compile error\); the backbone"):
        first = model(batch)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        second = model(batch)
    for got in (first, second):
        torch.testing.assert_close(got["pred_vertex_logits"], expected["pred_vertex_logits"])


def test_the_bev_encoder_benchmark_counts_macs_and_times_each_precision(capsys):
    """benchmarks/bev_encoder_speed.py: the MAC count of a convolution is C_out x H_out x W_out x C_in / groups x
    kh x kw, and a run prints a row per precision (int8 on any CPU; bf16 where it is native)."""
    sys.path.insert(0, str(REPO / "benchmarks"))
    from bev_encoder_speed import conv_macs, main

    conv = torch.nn.Sequential(torch.nn.Conv2d(6, 4, 3, stride=2, padding=1, groups=2), torch.nn.ReLU())
    assert conv_macs(conv, torch.zeros(1, 6, 10, 12)) == 4 * 5 * 6 * (3 * 3 * 3)
    main(["--config", str(TINY), "--runs", "1", "--threads", str(torch.get_num_threads())])  # (process-wide)
    out = capsys.readouterr().out
    rows = [line.split(" | ")[0].strip("| ") for line in out.splitlines() if line.startswith("| ") and "ms" not in line
            and "---" not in line]
    assert rows == (["fp32", "bf16", "int8"] if native_bf16(CPU) else ["fp32", "int8"])
    assert " GMAC;" in out
