"""deploy.py and the ``export-onnx`` / ``predict --onnx`` / ``benchmark --compile --cuda-graphs`` commands:
onnxruntime parity with torch for each view transform, identical polylines, the export's metadata checks,
the one-line errors, and the GPU path's logic on the CPU (no host synchronisation, static inputs).

Parity tolerance (docs/deploy.md): every float output within ``ATOL + RTOL * |torch|`` of torch's, the
vertex slots (positions, mask) exactly equal, and the decoded polylines identical."""

from __future__ import annotations

import contextlib
import io
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from instagram_hdmap import benchmark, deploy, inference, resources
from instagram_hdmap.checkpoint import save_checkpoint
from instagram_hdmap.cli import main
from instagram_hdmap.config import config_to_dict, load_config
from instagram_hdmap.geometry import BEVGrid
from instagram_hdmap.models import build_model
from instagram_hdmap.models.view_transform import inverse_3x3
from instagram_hdmap.postprocess import postprocess_batch

REPO = Path(__file__).resolve().parents[1]
TINY = REPO / "configs" / "synthetic" / "tiny.yaml"
ATOL, RTOL = 1e-4, 1e-5  # the documented parity tolerance (log-assignment after the Sinkhorn: ~1e-4)
# Few Sinkhorn iterations keep the export (one unrolled copy per iteration) within seconds; the
# iteration count changes the graph's length, not its ops (the slow test exports the default 100).
# N = 128 = every cell of the tiny grid: a random model's vertex scores are nearly equal, and where N
# cuts through equal scores, torch and onnxruntime may keep different cells; with every cell kept only
# the order of the slots may differ, which ``deploy.align_vertex_slots`` undoes.
FAST = ["model.gnn.sinkhorn_iters=5", "model.gnn.num_vertices=128"]


def tiny_cfg(*overrides: str):
    return load_config(TINY, [*FAST, *overrides])


def random_model(cfg, seed: int = 0):
    """A random model in eval mode whose matching embeddings are spread (a sharper assignment)."""
    torch.manual_seed(seed)
    model = build_model(cfg).eval()
    with torch.no_grad():
        model.graph_head.match_head.weight.mul_(10)
    return model


def batch_for(cfg, seed: int) -> dict:
    return deploy.example_inputs(cfg, seed)


def assert_parity(expected: dict, got: dict) -> None:
    """Equal within the tolerance, up to the order of the vertex slots; the same vertices exactly."""
    # every output, pred_distance but for a model without a distance head
    assert set(got) == set(expected) and set(inference.OUTPUT_NAMES) - set(expected) <= {"pred_distance"}
    expected, got = deploy.align_vertex_slots(expected), deploy.align_vertex_slots(got)
    for name in expected:
        e, g = expected[name], got[name]
        assert g.shape == e.shape and g.dtype == e.dtype, name
        if name in ("pred_vertex_mask", "pred_vertices_px"):
            assert torch.equal(g, e), name
        else:
            torch.testing.assert_close(g, e, atol=ATOL, rtol=RTOL, msg=name)


def decoding_threshold(outputs: dict) -> float:
    """A match threshold at which a random model's map is not empty: half the median, over the real
    vertices, of the best match probability (a random model's assignment is too flat for 0.1)."""
    mask = outputs["pred_vertex_mask"][0]
    probs = outputs["pred_log_assignment"][0, :-1, :-1][mask][:, mask].exp()
    return 0.5 * float(probs.max(1).values.median())


def canonical(preds: list[dict]) -> list[tuple]:
    """Polylines independent of where their walk starts and of their order: (label, closed, points)
    with an open line read from its smaller end and a closed one from its smallest point, sorted."""
    out = []
    for p in preds:
        pts = [tuple(q) for q in p["pts"].round(5).tolist()]
        closed = p.get("closed", len(pts) >= 4 and pts[0] == pts[-1])  # read_submission has no "closed"
        if closed:
            ring = pts[:-1]
            pts = min(min(r[i:] + r[:i] for i in range(len(r))) for r in (ring, ring[::-1]))
        else:
            pts = min(pts, pts[::-1])
        out.append((p["label"], closed, tuple(pts)))
    return sorted(out)


def _error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err, err
    return err


# --- the GPU path's logic, on the CPU ---------------------------------------------------------------------


class _HostSyncTripwire(torch.utils._python_dispatch.TorchDispatchMode):
    """Records the ops that would copy host data to a GPU or wait for it: ``lift_fresh`` (a tensor made
    from Python data), ``_local_scalar_dense`` (``.item()``, ``bool(t)``), ``nonzero`` (data-dependent
    shape). A CUDA graph cannot capture any of them."""

    BAD = {torch.ops.aten.lift_fresh.default, torch.ops.aten._local_scalar_dense.default,
           torch.ops.aten.nonzero.default}

    def __init__(self):
        super().__init__()
        self.hits: list[str] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if func in self.BAD:
            self.hits.append(str(func))
        return func(*args, **(kwargs or {}))


@pytest.mark.parametrize("overrides", [["model.view_transform.kind=lss"], ["model.view_transform.kind=ipm"],
                                       ["model.view_transform.kind=mlp", "model.gnn.embedding=pe+vd"],
                                       ["model.backbone.name=efficientnet-b0"]])
def test_forward_never_synchronises_with_the_host(overrides, monkeypatch):
    """The condition for CUDA-graph capture, checked on the CPU on the path a GPU runs: CPU-only fast
    paths are switched off (a scaling-form CPU Sinkhorn, where present, checks its result on the host
    and falls back to the log-space iterations that GPUs run; ``raising=False``: absent in older code)."""
    from instagram_hdmap.models import matching

    monkeypatch.setattr(matching, "_sinkhorn_potentials_scaling", lambda *args: None, raising=False)
    cfg = tiny_cfg(*overrides)
    model = deploy.inference_copy(random_model(cfg))
    batch = batch_for(cfg, 0)
    with torch.no_grad():
        reference = model(batch)
        tripwire = _HostSyncTripwire()
        with tripwire:
            outputs = model(batch)
    assert tripwire.hits == []
    assert_parity(reference, outputs)


def test_static_batch_copies_in_place_and_refuses_other_shapes():
    cfg = tiny_cfg()
    static = deploy.StaticBatch(batch_for(cfg, 0))
    addresses = {k: t.data_ptr() for k, t in static.tensors.items()}
    new = batch_for(cfg, 1)
    loaded = static.load(new)
    assert {k: t.data_ptr() for k, t in loaded.items()} == addresses
    assert all(torch.equal(loaded[k], new[k]) for k in inference.INPUT_NAMES)
    # a model run on the static buffers equals one on the batch itself
    model = random_model(cfg)
    with torch.no_grad():
        assert_parity(model(new), model(loaded))
    wrong = {**new, "images": new["images"][:, :5]}
    with pytest.raises(inference.DeployError,
                       match=r"images was captured as \[1, 6, 3, 64, 160\].*\[1, 5, 3, 64, 160\]"):
        static.load(wrong)
    with pytest.raises(inference.DeployError, match="float64"):
        static.load({**new, "post_rot": new["post_rot"].double()})


def test_cuda_graphs_need_a_cuda_device(capsys):
    if torch.cuda.is_available():
        pytest.skip("a CUDA device is present")
    cfg = tiny_cfg()
    with pytest.raises(inference.DeployError, match="--cuda-graphs needs a CUDA device"):
        deploy.fast_forward(random_model(cfg), batch_for(cfg, 0), cuda_graphs=True)
    assert main(["benchmark", str(TINY), "--device", "cpu", "--cuda-graphs", "--runs", "1"]) == 2
    assert "--cuda-graphs needs a CUDA device" in _error_line(capsys)


def test_inverse_3x3_equals_linalg_inv():
    gen = torch.Generator().manual_seed(0)
    m = torch.randn(4, 6, 3, 3, generator=gen, dtype=torch.float64) + 2 * torch.eye(3, dtype=torch.float64)
    torch.testing.assert_close(inverse_3x3(m), torch.linalg.inv(m), rtol=1e-10, atol=1e-12)
    K = torch.tensor([[1266.0, 0, 800], [0, 1266, 450], [0, 0, 1]])
    torch.testing.assert_close(inverse_3x3(K), torch.linalg.inv(K))


def test_the_whole_model_is_one_graph_for_torch_compile():
    """No graph break (dynamo traces the forward, Sinkhorn included, as one static graph): what lets
    --compile fuse across the model and --cuda-graphs with --compile capture it whole. LSS (the splat);
    IPM and MLP add grid sampling only, and Table I B0 was checked by hand (one graph, no break)."""
    cfg = tiny_cfg()
    model = deploy.inference_copy(random_model(cfg))
    torch._dynamo.reset()
    with torch.inference_mode():
        explained = torch._dynamo.explain(model)(batch_for(cfg, 0))
    assert (explained.graph_count, explained.graph_break_count) == (1, 0), explained.break_reasons


@pytest.mark.slow
def test_compiled_model_equals_eager():
    cfg = tiny_cfg("model.gnn.sinkhorn_iters=3")  # the unrolled iterations only lengthen the compilation
    model = random_model(cfg)
    with torch.inference_mode():
        forward = deploy.fast_forward(model, batch_for(cfg, 0), compile=True)  # compiles (a minute on 2 cores)
        other = batch_for(cfg, 1)
        assert_parity(model(other), forward(other))


def test_benchmark_flags_reach_the_fast_forward(monkeypatch, capsys):
    """``benchmark --compile`` times ``deploy.fast_forward(..., compile=True)`` (the compilation itself is
    tested above; here a stand-in forward keeps this fast)."""
    calls = []

    def spy(model, example, *, compile=False, cuda_graphs=False, amp="none"):
        calls.append((compile, cuda_graphs, amp, tuple(example["images"].shape)))
        return model

    monkeypatch.setattr(benchmark, "fast_forward", spy)  # the name benchmark.py calls
    assert main(["benchmark", str(TINY), *FAST, "data.dataroot=/nonexistent", "--device", "cpu", "--compile",
                 "--runs", "1", "--warmup", "0"]) == 0
    assert calls == [(True, False, "none", (1, 6, 3, 64, 160))]
    assert "float32, torch.compile" in capsys.readouterr().out


def test_benchmark_compile_backbone_compiles_the_image_backbone_alone(monkeypatch, capsys):
    """``benchmark --compile-backbone`` times the model with ``precision.compile_backbone`` applied (its
    compilation is tested in test_precision.py; a stand-in keeps this fast)."""
    from instagram_hdmap import precision

    compiled = []  # what with_precision(..., compile_backbone=True) compiles
    monkeypatch.setattr(precision, "_compile_backbone", lambda model: compiled.append(model) or model)
    args = ["benchmark", str(TINY), *FAST, "data.dataroot=/nonexistent", "--device", "cpu", "--runs", "1",
            "--warmup", "0"]
    assert main([*args, "--compile-backbone"]) == 0
    assert len(compiled) == 1 and "float32, backbone compiled" in capsys.readouterr().out


# --- ONNX: import hygiene and the missing extra ------------------------------------------------------------


def test_the_package_does_not_import_onnx():
    code = ("import sys, instagram_hdmap.cli, instagram_hdmap.deploy, instagram_hdmap.predict, "
            "instagram_hdmap.benchmark; instagram_hdmap.cli.build_parser(); "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('onnx', 'onnxruntime', 'onnxscript')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_a_missing_extra_is_a_one_line_error_naming_it(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # import onnxruntime -> ImportError
    with pytest.raises(inference.DeployError, match=r'pip install -e "\.\[deploy\]"'):
        inference.require_onnx()
    assert main(["export-onnx", str(TINY), "--checkpoint", str(tmp_path / "x.pt"), "--out",
                 str(tmp_path / "m.onnx")]) == 2
    assert 'pip install -e ".[deploy]"' in _error_line(capsys)


# --- ONNX: parity -------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def ort():
    pytest.importorskip("onnx", reason="the [deploy] extra (onnx) is not installed")
    return pytest.importorskip("onnxruntime", reason="the [deploy] extra (onnxruntime) is not installed")


@pytest.fixture(scope="module")
def tiny_export(ort, tmp_path_factory):
    """``tiny_export(*overrides) -> (cfg, model, path)``: a random tiny model exported once per module."""
    cache: dict[tuple, tuple] = {}

    def get(*overrides: str):
        if overrides not in cache:
            cfg = tiny_cfg(*overrides)
            model = random_model(cfg)
            path = tmp_path_factory.mktemp("tiny_export") / "m.onnx"
            info = deploy.export_onnx(model, cfg, path)
            assert info["inputs"]["images"] == [1, 6, 3, 64, 160]
            assert info["outputs"]["pred_log_assignment"] == [1, 129, 129]
            cache[overrides] = (cfg, model, path)
        return cache[overrides]

    return get


@pytest.mark.parametrize("overrides", [["model.view_transform.kind=lss"], ["model.view_transform.kind=ipm"],
                                       # and the official Fig. 7 VD variant's parts: no distance head, the
                                       # cell's descriptor, SuperPoint NMS
                                       ["model.view_transform.kind=mlp", "model.gnn.embedding=pe+vd",
                                        "model.bev_heads.distance_head=false", "model.gnn.vd_sampling=cell",
                                        "model.gnn.nms=superpoint", "model.gnn.nms_radius=2"]])
def test_onnxruntime_equals_torch_and_decodes_the_same_polylines(tiny_export, overrides):
    cfg, model, path = tiny_export(*overrides)
    onnx_model = inference.OnnxModel(path, cfg)
    grid = BEVGrid.from_config(cfg.grid)
    decoded = 0
    for seed in (1, 2):  # not the export's example input
        batch = batch_for(cfg, seed)
        if seed == 2:  # an AV2-like ground 0.38 m below the ego origin: the graph reads it, IPM / MLP use it
            batch["ground_height"] = torch.tensor([-0.38])
            with torch.no_grad():
                flat = model(dict(batch, ground_height=torch.zeros(1)))["pred_vertex_logits"]
                moved = not torch.equal(model(batch)["pred_vertex_logits"], flat)
            assert moved == (cfg.model.view_transform.kind != "lss")
        with torch.no_grad():
            expected = model(batch)
        got = onnx_model(batch)
        assert_parity(expected, got)
        threshold = decoding_threshold(expected)
        polylines = canonical(postprocess_batch(expected, grid, threshold)[0])
        assert canonical(postprocess_batch(got, grid, threshold)[0]) == polylines
        decoded += len(polylines)
    assert decoded > 0  # the comparison is not between two empty maps


def test_the_graph_uses_standard_ops_only_with_the_documented_interface(tiny_export):
    import onnx

    cfg, _, path = tiny_export("model.view_transform.kind=lss")
    proto = onnx.load(str(path))
    onnx.checker.check_model(proto)
    assert {op.domain for op in proto.opset_import} <= {"", "ai.onnx"}
    assert {node.domain for node in proto.graph.node} <= {"", "ai.onnx"}
    assert [i.name for i in proto.graph.input] == list(inference.INPUT_NAMES)
    assert [o.name for o in proto.graph.output] == list(inference.OUTPUT_NAMES)
    ops = {node.op_type for node in proto.graph.node}
    assert {"TopK", "ScatterND"} <= ops and "Loop" not in ops  # top-N extraction, LSS splat, unrolled Sinkhorn
    for value in [*proto.graph.input, *proto.graph.output]:  # every dimension static
        assert all(d.HasField("dim_value") for d in value.type.tensor_type.shape.dim), value.name
    meta = {p.key: p.value for p in proto.metadata_props}
    assert meta[inference.META_FORMAT] == str(inference.EXPORT_FORMAT)
    assert json.loads(meta[inference.META_CONFIG]) == inference.baked_config(cfg)
    assert json.loads(meta[inference.META_CONFIG])["model.gnn.sinkhorn_iters"] == 5


# --- ONNX: the commands and their errors ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def world(tiny_world, world_overrides) -> list[str]:
    return [*world_overrides(tiny_world), *FAST, "data.num_workers=0", "train.device=cpu"]


@pytest.fixture(scope="module")
def checkpoint(world, tmp_path_factory) -> Path:
    cfg = load_config(TINY, world)
    path = tmp_path_factory.mktemp("ckpt") / "random.pt"
    save_checkpoint({"model": random_model(cfg).state_dict(), "config": config_to_dict(cfg)}, path)
    return path


@pytest.fixture(scope="module")
def export_run(ort, world, checkpoint, tmp_path_factory) -> tuple[Path, str]:
    """``export-onnx`` of the checkpoint: (the file, what the command printed)."""
    out = tmp_path_factory.mktemp("onnx") / "model.onnx"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main(["export-onnx", str(TINY), *world, "--checkpoint", str(checkpoint), "--out", str(out)]) == 0
    return out, printed.getvalue()


@pytest.fixture(scope="module")
def exported(export_run) -> Path:
    return export_run[0]


def test_predict_onnx_draws_the_same_pictures_as_predict(world, checkpoint, exported, tmp_path, capsys, monkeypatch):
    """Same polylines in prediction.json, the same camera picture, and the BEV and Fig. 6 pictures drawn
    from the same data (their titles name the source, so their pixels differ there)."""
    from matplotlib.image import imread

    from instagram_hdmap import predict, visualize
    from instagram_hdmap.evaluation import read_submission

    drawn: dict[str, list] = {"bev": [], "intermediate": []}
    bev, intermediate = visualize.prediction_bev_figure, visualize.intermediate_figure

    def record_bev(predictions, *args, **kwargs):
        drawn["bev"].append(canonical(predictions))
        return bev(predictions, *args, **kwargs)

    def record_intermediate(heatmap, distance, vertices_px, vertex_labels, *args, **kwargs):
        rows = sorted(zip(vertices_px.tolist(), vertex_labels.tolist()))
        drawn["intermediate"].append((heatmap.clone(), distance.clone(), rows))
        return intermediate(heatmap, distance, vertices_px, vertex_labels, *args, **kwargs)

    monkeypatch.setattr(predict, "prediction_bev_figure", record_bev)  # the names predict.py calls
    monkeypatch.setattr(predict, "intermediate_figure", record_intermediate)
    capsys.readouterr()
    base = ["predict", str(TINY), *world, "model.gnn.match_threshold=0.03", "--index", "1"]
    assert main([*base, "--checkpoint", str(checkpoint), "--out", str(tmp_path / "torch")]) == 0
    assert main([*base, "--onnx", str(exported), "--out", str(tmp_path / "onnx")]) == 0
    assert "predicted instances" in capsys.readouterr().out

    torch_preds, onnx_preds = (read_submission(tmp_path / kind / "prediction.json", "pred").samples
                               for kind in ("torch", "onnx"))
    assert list(onnx_preds) == list(torch_preds)
    (token,) = torch_preds
    assert torch_preds[token] and canonical(onnx_preds[token]) == canonical(torch_preds[token])
    assert drawn["bev"][0] == drawn["bev"][1]
    (heat_t, dist_t, rows_t), (heat_o, dist_o, rows_o) = drawn["intermediate"]
    torch.testing.assert_close(heat_o, heat_t, atol=ATOL, rtol=RTOL)
    torch.testing.assert_close(dist_o, dist_t, atol=ATOL, rtol=RTOL)
    assert rows_o == rows_t
    a, b = (imread(tmp_path / kind / "prediction_cameras.png") for kind in ("torch", "onnx"))
    assert a.shape == b.shape and (abs(a - b).max(-1) > 0).mean() < 1e-3
    for name in ("prediction_bev.png", "prediction_intermediate.png"):
        assert (tmp_path / "onnx" / name).stat().st_size > 1000


def test_export_prints_the_interface_and_the_parity_of_its_check(export_run):
    out, printed = export_run
    assert f"wrote {out}" in printed and "opset 18" in printed
    assert "images [1, 6, 3, 64, 160]" in printed and "pred_log_assignment [1, 129, 129]" in printed
    assert "onnxruntime check on an example input" in printed and "on the graph outputs" in printed


def test_bad_exports_are_one_line_errors(ort, world, checkpoint, exported, tmp_path, capsys):
    import onnx

    export = ["export-onnx", str(TINY), *world, "--checkpoint", str(checkpoint), "--out", str(tmp_path / "x.onnx")]
    # a checkpoint of another config
    other = tmp_path / "other.yaml"
    other.write_text(f"_base_: {TINY}\nmodel:\n  gnn:\n    layers: 3\n")
    assert main([export[0], str(other), *export[2:]]) == 2
    err = _error_line(capsys)
    assert f"checkpoint {checkpoint} is from another config: it was trained with model.gnn.layers=2 (CONFIG: 3)" in err
    # an unsupported setting
    assert main([*export, "--opset", "13"]) == 2
    assert "--opset 13 is not supported" in _error_line(capsys)
    # an override that changes layer sizes
    assert main([*export, "model.gnn.dim=64"]) == 2
    assert "do not fit" in _error_line(capsys)

    predict = ["predict", str(TINY), *world, "--index", "0", "--out", str(tmp_path / "p")]
    # an ONNX file of another config (N is baked into the graph); the world's own num_vertices left out (a key given
    # twice is noted on a line of its own)
    other_n = ["predict", str(TINY), *[o for o in world if not o.startswith("model.gnn.num_vertices=")], "--index",
               "0", "--out", str(tmp_path / "p")]
    assert main([*other_n, "model.gnn.num_vertices=32", "--onnx", str(exported)]) == 2
    assert "was exported from another config: model.gnn.num_vertices=128 (CONFIG: 32)" in _error_line(capsys)
    # an older export, and a file that is not ours
    proto = onnx.load(str(exported))
    for prop in proto.metadata_props:
        if prop.key == inference.META_FORMAT:
            prop.value = "0"
    onnx.save(proto, str(tmp_path / "old.onnx"))
    assert main([*predict, "--onnx", str(tmp_path / "old.onnx")]) == 2
    assert f"is an export of format 0; this version reads format {deploy.EXPORT_FORMAT}" in _error_line(capsys)
    del proto.metadata_props[:]
    onnx.save(proto, str(tmp_path / "foreign.onnx"))
    assert main([*predict, "--onnx", str(tmp_path / "foreign.onnx")]) == 2
    assert "was not written by instagram-hdmap export-onnx" in _error_line(capsys)
    (tmp_path / "junk.onnx").write_bytes(b"not onnx")
    assert main([*predict, "--onnx", str(tmp_path / "junk.onnx")]) == 2
    assert "is not a readable ONNX file" in _error_line(capsys)
    assert main([*predict, "--onnx", str(exported), "--checkpoint", str(checkpoint)]) == 2
    assert "--onnx" in _error_line(capsys)


@pytest.mark.slow
def test_default_sinkhorn_iterations_export_with_parity(ort, tmp_path, monkeypatch):
    """The exported graph runs the log-space Sinkhorn iterations (what GPUs and tracing run); on the CPU
    the eager model runs the same iterations in scaling form, whose rounding differs by more
    than the tolerance after 100 iterations on these sharp random scores: compare with the traced path."""
    from instagram_hdmap.models import matching

    monkeypatch.setattr(matching, "_sinkhorn_potentials_scaling", lambda *args: None, raising=False)
    cfg = load_config(TINY, FAST[1:])
    assert cfg.model.gnn.sinkhorn_iters == 100
    model = random_model(cfg)
    deploy.export_onnx(model, cfg, tmp_path / "m.onnx")
    batch = batch_for(cfg, 1)
    with torch.no_grad():
        expected = model(batch)
    got = inference.OnnxModel(tmp_path / "m.onnx", cfg)(batch)
    assert_parity(expected, got)
    grid = BEVGrid.from_config(cfg.grid)
    threshold = decoding_threshold(expected)
    polylines = canonical(postprocess_batch(expected, grid, threshold)[0])
    assert canonical(postprocess_batch(got, grid, threshold)[0]) == polylines and polylines


def test_cpu_capability_reads_the_flags_it_is_given(tmp_path):
    """A figure carries what it was measured on: the CPU's extensions from its flags, never assumed."""
    amx = tmp_path / "amx"
    amx.write_text("processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f avx512_vnni avx512_bf16 amx_bf16 amx_int8 "
                   "amx_tile\nprocessor\t: 1\nflags\t\t: fpu\n")
    plain = tmp_path / "plain"
    plain.write_text("processor\t: 0\nflags\t\t: fpu sse2 sse4_2\n")
    assert resources.cpu_flags(amx) >= {"avx2", "amx_bf16"} and resources.cpu_flags(tmp_path / "none") == set()
    level = torch.backends.cpu.get_cpu_capability()
    assert resources.cpu_capability(amx) == (f"AVX2 AVX512 AVX512-VNNI AVX512-BF16 AMX-BF16 AMX-INT8; torch kernels: "
                                             f"{level}")
    assert resources.cpu_capability(plain) == f"none of AVX2 / AVX512 / AMX; torch kernels: {level}"


def test_inference_keeps_the_memory_a_forward_frees_for_the_next(monkeypatch):
    """On glibc a large freed block stays in the process for the next forward to reuse (by default glibc unmaps
    every block over 32 MiB when freed, and the next forward faults it in page by page again); on another C
    library nothing is changed."""
    import platform

    if platform.libc_ver()[0] != "glibc":
        pytest.skip("glibc's mallopt only")
    assert resources.reuse_freed_memory()
    block = torch.ones(200 * 2**20 // 4)  # 200 MiB, every page touched
    held = resources.resident_bytes()
    del block
    assert held - resources.resident_bytes() < 20 * 2**20  # kept, not returned to the kernel
    monkeypatch.setattr(platform, "libc_ver", lambda: ("", ""))
    assert resources.reuse_freed_memory() is False


def test_benchmark_prints_the_cpu_it_ran_on(capsys):
    assert main(["benchmark", str(TINY), *FAST, "data.dataroot=/nonexistent", "--device", "cpu", "--runs", "1",
                 "--warmup", "0"]) == 0
    out = capsys.readouterr().out
    assert f"cpu:         {resources.cpu_capability()} (decoding runs on it)" in out and "dtype:       float32" in out
