"""The scripts of ``benchmarks/`` and the ``benchmark`` command: their options, their caches and result files.

Each row runs on the tiny synthetic world of tests/conftest.py and a random tiny model (bad_inputs/conftest.py).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest

from bad_inputs.support import (
    REPO,
    TINY_YAML,
    benchmark_temporal,
    forbid,
    row,
    table,
)
from instagram_hdmap.config import UserError, load_config


@row("benchmark of a temporal model (configs/temporal) runs (was a raw KeyError: the batch lacked ego_pose)")
def row_benchmark_temporal_model(env):
    rc, out, err = env.cli("benchmark", env.yaml, "model.temporal.memory=bev", "model.gnn.sinkhorn_iters=3",
                           "--device", "cpu", "--runs", "1", "--warmup", "0")
    assert rc == 0 and "Traceback" not in err, err[-2000:]
    assert "a temporal model: timed on a scene's first frame" in out


@row("benchmarks/temporal.py: an option out of range (--steps 0, --occluders 2), a --finetune-base without its "
          "checkpoints or a wrong --set key is one line before the worlds are generated (a traceback after minutes)")
def row_benchmark_temporal_options_checked_first(env):
    cache = env.tmp / "cache"
    for args in (["--steps", "0"], ["--occluders", "2"], ["--finetune", "5", "--finetune-base", str(env.tmp / "none")],
                 ["--set", "train.nope=1"]):
        p = subprocess.run([sys.executable, str(REPO / "benchmarks" / "temporal.py"), *args, "--cache", str(cache),
                            "--out", str(env.tmp / "out")], capture_output=True, text=True, timeout=120)
        assert p.returncode == 2 and "Traceback" not in p.stderr, p.stderr[-2000:]
        assert re.search(r"temporal\.py: error: (--steps|--occluders|--finetune-base|--set)", p.stderr), p.stderr
    assert not cache.exists()  # no world generated


@row("benchmarks/temporal.py: a --set that does not fit --memory (model.temporal.fusion=gru with --memory graph) "
          "is one line before the worlds are generated (it passed the check, then a traceback after minutes), and "
          "--set model.temporal.memory=... is refused (--memory overrode it without a word)")
def row_benchmark_temporal_set_against_memory(env):
    for args, pattern in ((["--memory", "graph", "--set", "model.temporal.fusion=gru"],
                           r"--set \(the temporal config, --memory graph\): config key 'model\.temporal\.fusion'"),
                          (["--memory", "graph", "--set", "model.temporal.memory=bev"],
                           r"--set model\.temporal\.memory=bev: the temporal model's memory is --memory \(graph\)"),
                          (["--memory", "graph", "--temporal-set", "model.temporal.memory=bev"],
                           r"--temporal-set model\.temporal\.memory=bev: the temporal model's memory is --memory")):
        p = benchmark_temporal(env, *args, "--steps", "2")
        assert p.returncode == 2 and "Traceback" not in p.stderr, p.stderr[-2000:]
        assert re.search(pattern, p.stderr), p.stderr[-2000:]
    assert not (env.tmp / "cache").exists()  # no world generated


def _bench_temporal(env, **options):
    """benchmarks/temporal.py loaded as a module, and its parsed arguments with ``options`` (``--out`` in env.tmp)."""
    import argparse
    import importlib.util

    from instagram_hdmap.demo import VAL_WORLD

    spec = importlib.util.spec_from_file_location("bench_temporal", REPO / "benchmarks" / "temporal.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    args = dict(out=str(env.tmp / "out"), steps=200, minutes=15.0, occluders=0.7, override=[], memory="graph",
                val_scenes=VAL_WORLD["scenes_val"], val_occluders=None, val_dropout=None, threads=None,
                temporal_override=[])
    return bench, argparse.Namespace(**{**args, **options})


@row("benchmarks/temporal.py: a run folder of --out holding a result trained with other options (another "
          "--steps, --set or --occluders) is refused; it was reported as this command's result, exit 0")
def row_benchmark_temporal_stale_result(env):
    bench, args = _bench_temporal(env)
    folder = env.tmp / "out" / "temporal_graph_seed0"
    folder.mkdir(parents=True)
    old = {"config": "temporal_graph", "seed": 0, "mAP": 0.5,
           "options": {"occluders": 0.7, "train": ["train.max_steps=100", "train.epochs=1", "train.lr_step=1",
                                                   "model.temporal.memory=graph"]}}
    (folder / "result.json").write_text(json.dumps(old))
    forbid(env, "instagram_hdmap.train.train", "a training")
    with pytest.raises(SystemExit, match=r"result\.json was trained with .*max_steps=100.*this command asks for "
                                         r".*max_steps=200.*use another --out"):
        bench.run_one("temporal_graph", 0, args, (None, None), "temporal")
    args.steps = 100  # the same options: the result is this command's
    assert bench.run_one("temporal_graph", 0, args, (None, None), "temporal")["mAP"] == 0.5
    del old["options"]  # a result written before the options were recorded is taken as it is
    (folder / "result.json").write_text(json.dumps(old))
    args.steps = 200
    assert bench.run_one("temporal_graph", 0, args, (None, None), "temporal")["mAP"] == 0.5


@row("benchmarks/temporal.py: --val-dropout 1 (data.camera_dropout must be < 1) and an --out that is a file "
          "passed the checks, then stopped on a traceback after the worlds and the trainings")
def row_benchmark_temporal_val_dropout_and_out(env):
    def bench(*args, out):
        return subprocess.run([sys.executable, str(REPO / "benchmarks" / "temporal.py"), *args, "--steps", "400",
                               "--cache", str(env.tmp / "cache"), "--out", str(out)], capture_output=True, text=True,
                              timeout=120, env={**os.environ, "PYTHONPATH": str(REPO / "src")})

    p = bench("--val-dropout", "1", out=env.tmp / "out")
    assert p.returncode == 2 and "--val-dropout must be below 1" in p.stderr, p.stderr[-2000:]
    (env.tmp / "results").write_text("notes")
    p = bench(out=env.tmp / "results")
    assert p.returncode == 2 and re.search(r"--out .*results: is a file, not a folder", p.stderr), p.stderr[-2000:]
    assert not (env.tmp / "cache").exists()


@row("benchmarks/*.py: a count flag of 0 (eval_speed --samples 0, sinkhorn_speed --runs 0) crashed with a "
            "ZeroDivisionError / StatisticsError after the setup, ped_crossing_diagnosis --limit 0 printed a table "
            "of AP 0.000 for no samples with exit 0, synth_speed of a 1-sample world divided by 0 after rendering, "
            "a missing checkpoint was a CheckpointError traceback, decoders --variant NAME (no '=') an IndexError, a "
            "graph_head_sweep variant's unknown key failed after the outputs were cached, and --device mps / cuda "
            "without CUDA was a raw error; each is one 'SCRIPT: error:' line, exit 2")
def row_benchmark_count_flags(env):
    def script(name, *args):
        p = subprocess.run([sys.executable, str(REPO / "benchmarks" / name), *map(str, args)], capture_output=True,
                           text=True, timeout=300, cwd=REPO)
        lines = [ln for ln in p.stderr.splitlines() if ln.startswith(name)]
        assert p.returncode == 2 and "Traceback" not in p.stderr and len(lines) == 1, p.stderr[-2000:]
        return lines[0]

    assert "--samples must be >= 1, got 0" in script("eval_speed.py", "--samples", "0", "--raster-samples", "0")
    assert "--runs must be >= 1, got 0" in script("sinkhorn_speed.py", "--runs", "0")
    assert "--limit must be >= 1, got 0" in script("ped_crossing_diagnosis.py", f"a={env.ckpt}", "--world", env.world,
                                                   "--limit", "0")
    assert re.search(r"error: checkpoint not found: .*missing\.pt",
                     script("decoders.py", f"a={env.tmp / 'missing.pt'}", "--world", env.world))
    assert "--variant 'novalue': expected NAME=key=value" in script("decoders.py", f"a={env.ckpt}", "--world",
                                                                     env.world, "--variant", "novalue")
    assert "--device=mps is not supported" in script("graph_speed.py", "--device", "mps", "--repeats", "1")
    assert "is one sample: the time per sample is measured against a 1-sample world" in script(
        "synth_speed.py", "--scenes", "1", "--samples-per-scene", "1")
    assert "variant a=model.gnn.nosuch=1: unknown config key 'model.gnn.nosuch'" in script(
        "graph_head_sweep.py", "a=model.gnn.nosuch=1", "--checkpoint", env.ckpt, "--world", env.world, "--val-world",
        env.world)


@row("benchmarks/temporal.py --persist-decay D without --persist trained and evaluated the runs without "
            "persistence, the decay dropped with no word; it is one 'temporal.py: error:' line, exit 2")
def row_benchmark_persist_decay_alone(env):
    p = subprocess.run([sys.executable, str(REPO / "benchmarks" / "temporal.py"), "--persist-decay", "0.7", "--out",
                        str(env.tmp / "b")], capture_output=True, text=True, timeout=120, cwd=REPO)
    lines = [ln for ln in p.stderr.splitlines() if ln.startswith("temporal.py")]
    assert p.returncode == 2 and len(lines) == 1 and "Traceback" not in p.stderr, p.stderr[-2000:]
    assert "--persist-decay 0.7 needs --persist FRAMES" in lines[0] and not (env.tmp / "b").exists()


@row("benchmarks/cmap_of_submissions.py: --match-m 0 was taken as not given (scored at the default 1.0 m, no "
            "word); a bad --match-m was a raw ConfigError traceback; a submission of another split or world printed "
            "C-mAP nan with exit 0, and one lacking samples was scored on the rest with no word")
def row_cmap_of_submissions_options(env):
    rc, _, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "ev")
    assert rc == 0, err
    sub = json.loads((env.tmp / "ev" / "submission.json").read_text())
    for name, keep in (("other", lambda t: t + "x"), ("part", None)):
        results = ({keep(t): v for t, v in sub["results"].items()} if keep else
                   dict(list(sub["results"].items())[:1]))
        (env.tmp / name).mkdir()
        (env.tmp / name / "submission.json").write_text(json.dumps({**sub, "results": results}))
    data = load_config(env.yaml).data

    def bench(*args):
        return subprocess.run([sys.executable, str(REPO / "benchmarks" / "cmap_of_submissions.py"), "--config",
                               str(env.yaml), "--dataroot", str(data.dataroot), *map(str, args)],
                              capture_output=True, text=True, timeout=300)

    for args, pattern in ((("--match-m", "0", env.tmp / "ev"), r"error: config key 'eval.cmap_match_m \(--match-m\)' "
                                                                 r"must be in \(0, 10\].*, got 0.0"),
                          (("--match-m", "-1", env.tmp / "ev"), r"must be in \(0, 10\].*, got -1.0"),
                          ((env.tmp / "other",), r"has none of the \d+ samples of split 'val'")):
        p = bench(*args)
        assert p.returncode == 2 and "Traceback" not in p.stderr and re.search(pattern, p.stderr), p.stderr
    p = bench(env.tmp / "part")
    assert p.returncode == 0 and re.search(r"note: .*part/submission.json lacks \d+ of the \d+ samples", p.stderr), \
        p.stderr


@row("demo.random_map_baseline (benchmarks/README.md's python -c command): a YAML path as the config was a raw "
            "\"'str' object has no attribute 'data'\", picks of another length scored that many validation samples, "
            "no word, one past the training split a raw IndexError and a negative one counted from its end; a path "
            "is read, the picks are checked")
def row_random_map_baseline_arguments(env):
    from instagram_hdmap.demo import random_map_baseline

    by_path = random_map_baseline(str(env.yaml), "vector")
    assert by_path["AP_class"] == random_map_baseline(env.cfg(), "vector")["AP_class"]
    n = by_path["counters"]["samples"]
    for picks in ([0] * (n - 1), [0] * (n - 1) + [10**6], [-1] * n):
        with pytest.raises(UserError, match=r"random_map_baseline: picks must be one training-sample index in \[0, "):
            random_map_baseline(env.cfg(), "vector", picks=picks)
    random_map_baseline(env.cfg(), "vector", picks=[np.int64(0)] * n)  # numpy indices: taken


@row("benchmarks/temporal.py with a tiny budget: a single-frame model that detects nothing has flicker 0, and "
            "the summary divided by max(0, 1e-9): 'flicker x0.00 (target: ... flicker x0.5)', the target met by two "
            "models that found nothing. A ratio over 0 is now 'n/a'")
def row_benchmark_temporal_flicker_ratio_over_zero(env):
    bench, _ = _bench_temporal(env)
    nothing = {"steps": 6, "AP_class": {"divider": 0.0}, "mAP": 0.0, "flicker_mean": 0.0,
               "flicker_detected_mean": float("nan")}
    results = [{**nothing, "config": "single", "seed": 0}, {**nothing, "config": "temporal", "seed": 0}]
    text = bench.table(results) + bench.paired([{**r, "config": r["config"] + "_ft"} for r in results])
    assert "x0.00" not in text and "n/a" in text, text


@row("benchmarks/temporal.py on a damaged world cache (a world folder without world.json, a cached world "
            "missing a file): a raw traceback ending in the demo's DemoError. One line, exit 2")
def row_benchmark_temporal_damaged_cache(env):
    from instagram_hdmap.demo import WORLD, world_key

    (env.tmp / "cache" / world_key({**WORLD, "occluders": 0.5})).mkdir(parents=True)  # no world.json
    p = benchmark_temporal(env, "--steps", "240", "--occluders", "0.5")
    lines = [ln for ln in p.stderr.splitlines() if "error" in ln]
    assert p.returncode == 2 and "Traceback" not in p.stderr, p.stderr[-2000:]
    assert re.search(r"--cache: .* is not a complete synthetic world \(no world.json\)", lines[-1]), p.stderr[-2000:]


@row("benchmarks/temporal.py --set model={temporal: {memory: bev}} (the memory as a mapping, not the dotted "
            "key): the check that --memory alone sets the memory read the dotted key only, so the single-frame "
            "baseline ran with a memory; it reads the keys the override sets")
def row_benchmark_temporal_memory_set_as_a_mapping(env):
    for args in (["--set", "model={temporal: {memory: bev}}"], ["--temporal-set", "model.temporal={memory: bev}"]):
        p = benchmark_temporal(env, "--memory", "graph", *args, "--steps", "2")
        assert p.returncode == 2 and "Traceback" not in p.stderr, p.stderr[-2000:]
        assert re.search(r"--(temporal-)?set model.*memory: bev}+: the temporal model's memory is --memory \(graph\)",
                         p.stderr), p.stderr[-2000:]
    assert not (env.tmp / "cache").exists()


@row("benchmarks/temporal_speed.py with model.temporal.max_jump_m=1 (the benchmark's previous frame is 1.5 m "
            "behind): a bare `assert` of the fusion, a raw AssertionError, and under python -O the timings of a "
            "model that fuses nothing with exit 0; now one line naming the key, exit 2. --runs 1 (allowed): a raw "
            "StatisticsError after the work; its p10 / p90 of a few runs were extrapolated (a p10 of -126 ms); a "
            "config without memory: exit 1, now 2 as every wrong input")
def row_temporal_speed_memory_not_fused(env):
    env_vars = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    script = [str(REPO / "benchmarks" / "temporal_speed.py"), "--config", str(TINY_YAML), "--runs", "1", "--warmup",
              "0", "model.temporal.memory=bev"]
    p = subprocess.run([sys.executable, "-O", *script, "model.temporal.max_jump_m=1"], capture_output=True, text=True,
                       env=env_vars, timeout=300)
    assert p.returncode == 2 and "Traceback" not in p.stderr, (p.returncode, p.stdout[-1000:], p.stderr[-2000:])
    assert re.search(r"not fused \(status pose_jump\): model\.temporal\.max_jump_m=1\.0", p.stderr), p.stderr
    p = subprocess.run([sys.executable, *script], capture_output=True, text=True, env=env_vars, timeout=300)
    assert p.returncode == 0 and "fusion alone" in p.stdout, p.stderr[-2000:]
    p = subprocess.run([sys.executable, *script[:-1]], capture_output=True, text=True, env=env_vars, timeout=300)
    assert p.returncode == 2 and "model.temporal.memory is none" in p.stderr, (p.returncode, p.stderr[-2000:])


@row("benchmarks/temporal.py reads back a finished run's result file (a rerun of the same --out): written "
            "as standard JSON, a flicker rate with no pairs is null there; the tables took it as a number (TypeError "
            "formatting None); now it is NaN again when read")
def row_benchmark_temporal_result_with_null(env):
    bench, args = _bench_temporal(env, steps=100, memory="bev")
    folder = env.tmp / "out" / "single_seed0"
    folder.mkdir(parents=True)
    (folder / bench.result_name(args)).write_text(json.dumps(  # as files.write_json writes a NaN: null
        {"config": "single", "seed": 0, "steps": 100, "mAP": 0.0, "AP_class": {"divider": 0.0}, "flicker_mean": 0.0,
         "flicker_detected_mean": None}))
    forbid(env, "instagram_hdmap.train.train", "a training")
    result = bench.run_one("single", 0, args, (None, None))
    assert result["flicker_detected_mean"] != result["flicker_detected_mean"]  # NaN
    assert "nan" in bench.table([result])


def _gpu_sh(**settings) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(REPO / "benchmarks" / "gpu.sh")], capture_output=True, text=True, timeout=300,
                          env={**os.environ, **settings})


@row("benchmarks/gpu.sh's CPU check (DEVICE=cpu, the tiny config, one run): one Markdown table, a row per precision "
     "and mode with the model's and the model + decoding's FPS, headed by the device and the CPU's extensions")
def row_gpu_sh_writes_one_markdown_table(env):
    p = _gpu_sh(DEVICE="cpu", CONFIGS="configs/synthetic/tiny.yaml", MODES="eager", RUNS="1", WARMUP="0", TRAIN="0")
    assert p.returncode == 0, p.stderr[-2000:]
    lines = p.stdout.splitlines()
    assert lines[0].startswith("device cpu") and "cpu: " in lines[0] and "torch kernels: " in lines[0]
    assert lines[1] == "| config | amp | mode | model FPS | (p90-p10) | +decoding FPS | (p90-p10) | paper |"
    assert lines[2] == "|---|---|---|---|---|---|---|---|"
    rows = [ln.split(" | ") for ln in lines[3:] if ln.startswith("| ")]
    assert [(r[0], r[1], r[2]) for r in rows] == [("| tiny.yaml", "none", "eager"), ("| tiny.yaml", "bf16", "eager")]
    assert all(float(r[3]) > 0 and float(r[5]) > 0 for r in rows), rows
    assert lines[-1] == "runs per cell: 1 after 0 warm-up runs"


@row("benchmarks/gpu.sh with a setting that is not a number, TRAIN other than 0 / 1, or CUDA graphs on the CPU: "
     "one line, exit 2, before any model is built")
def row_gpu_sh_bad_settings(env):
    for settings, message in [({"RUNS": "ten"}, "RUNS, WARMUP and BUDGET_S must be whole numbers"),
                              ({"TRAIN": "yes"}, "TRAIN must be 0 or 1, got yes"),
                              ({"DEVICE": "cpu", "MODES": "cuda_graphs", "TRAIN": "0"},
                               "--modes cuda_graphs needs --device cuda (got --device cpu)")]:
        p = _gpu_sh(**settings)
        assert p.returncode == 2 and message in p.stderr.splitlines()[-1], (settings, p.stderr[-2000:])
        assert "Traceback" not in p.stderr and "|" not in p.stdout, settings


@pytest.mark.parametrize("case", table(__name__), ids=str)
def test_benchmark_scripts(case, env):
    case.run(env)
