"""A config as users write it: keys, values and ranges, YAML files and their ``_base_``, overrides on the command line,
and the options of each command. A wrong one is one line naming the key (or option) before any work starts; a key
that nothing reads, or one that meets another setting, is a note.

Each row runs on the tiny synthetic world of tests/conftest.py and a random tiny model (bad_inputs/conftest.py).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch

from bad_inputs.support import (
    REPO,
    add,
    benchmark_temporal,
    forbid,
    rig_files,
    row,
    table,
    val_scene,
)
from instagram_hdmap.checkpoint import load_checkpoint, save_checkpoint
from instagram_hdmap.config import UserError, config_to_dict, load_config

for _name, _override, _key in (
    ("sinkhorn_iters_0", "model.gnn.sinkhorn_iters=0", "model.gnn.sinkhorn_iters"),
    ("batch_size_0", "train.batch_size=0", "train.batch_size"),
    ("checkpoint_every_negative", "train.checkpoint_every=-5", "train.checkpoint_every"),
):
    def _run(env, override=_override, key=_key):
        forbid(env, "instagram_hdmap.train.train_one_epoch", "training")
        env.error(rf"'{re.escape(key)}'.*(>= ?[01]|in \[[01], )", "train", env.yaml, override,
                  f"train.out_dir={env.tmp / 'r'}")

    add(_name, f"config: {_override}", _run)


@row("a YAML section written twice is an error, not silently merged")
def row_duplicate_yaml_section(env):
    path = env.tmp / "twice.yaml"
    path.write_text(f"_base_: {env.yaml}\nmodel:\n  gnn:\n    layers: 3\ntrain:\n  lr: 0.01\nmodel:\n  gnn:\n"
                    "    dim: 64\n")
    env.error(r"twice\.yaml.*'model'.*(twice|duplicate)", "model-summary", path)


@row("data.cache_in_memory with augmentation or data workers: the setting that rules it out is named")
def row_cache_in_memory_with_augment_or_workers(env):
    for bad, named in ((("data.augment=true", "data.num_workers=0"), r"data\.augment=true.*set data\.augment=false$"),
                       (("data.num_workers=2",), r"data\.num_workers=2.*set data\.num_workers=0$")):
        env.error(rf"data\.cache_in_memory.*cannot go with {named}", "model-summary", env.yaml,
                  "data.cache_in_memory=true", *bad)


@row("data.classes with unknown names")
def row_unknown_class_names(env):
    env.error(r"data\.classes.*divider.*ped_crossing.*boundary", "model-summary", env.yaml,
              "data.classes=[lane,crossing,kerb]")


@row("predict --index of a temporal model says where its memory comes from (ran silently)")
def row_temporal_predict_says_its_memory(env):
    from instagram_hdmap.models import build_model

    temporal = ["model.temporal.memory=bev", "model.gnn.sinkhorn_iters=3"]
    torch.manual_seed(0)
    cfg = env.cfg(*temporal)
    ckpt = save_checkpoint({"model": build_model(cfg).state_dict(), "config": config_to_dict(cfg)},
                           env.tmp / "temporal.pt")
    for index, said in ((1, r"its memory comes from the 1 earlier frame\(s\) of scene"), (0, r"no memory")):
        rc, out, err = env.cli("predict", env.yaml, *temporal, "--checkpoint", ckpt, "--index", index,
                               "--out", env.tmp / f"p{index}")
        assert rc == 0 and re.search(said, out + err), (out + err)[-2000:]


@row("evaluate: a flicker of nan (no element seen in two consecutive frames: one-frame scenes) is explained")
def row_flicker_nan_explained(env):
    import instagram_hdmap.cli as cli

    real = cli.run_evaluation

    def one_frame_scenes(*args, **kwargs):  # the real evaluation, as a world of one-frame scenes would end it
        result = real(*args, **kwargs)
        nan = float("nan")
        result["metrics"]["consistency"] = {"flicker": {"divider": 0.25, "ped_crossing": nan, "boundary": nan},
                                            "flicker_mean": 0.25}
        return result

    env.monkeypatch.setattr(cli, "run_evaluation", one_frame_scenes)
    rc, out, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "e")
    assert rc == 0, err[-2000:]
    assert "nan: no element of ped_crossing, boundary was seen in two consecutive frames" in out


@row("grid.resolution=.nan")
def row_nan_resolution(env):
    env.error(r"grid\.resolution.*(finite|NaN)", "model-summary", env.yaml, "grid.resolution=.nan")


for _override, _key in (("train.lr=.nan", "train.lr"), ("train.lr=-1", "train.lr"),
                        ("train.epochs=0", "train.epochs"), ("train.epochs=-2", "train.epochs"),
                        ("data.num_workers=-1", "data.num_workers"), ("eval.batch_size=0", "eval.batch_size")):
    def _run(env, override=_override, key=_key):
        forbid(env, "instagram_hdmap.train.train_one_epoch", "training")
        env.error(rf"'{re.escape(key)}'", "train", env.yaml, override, f"train.out_dir={env.tmp / 'r'}")

    add(_override.replace("=-", "=minus-"), f"config: {_override}", _run)


@row("data.dt_clip=0 is named (not a NaN loss blamed on the learning rate)")
def row_dt_clip_0(env):
    env.error(r"data\.dt_clip.*> ?0", "train", env.yaml, "data.dt_clip=0", f"train.out_dir={env.tmp / 'r'}")


@row("an override quoted as a string stays a string (name=\"2024\" was read as the float 2024.0)")
def row_quoted_override_is_a_string(env):
    assert load_config(env.yaml, ['name="2024"']).name == "2024"
    assert load_config(env.yaml, ["train.lr=1e-3"]).train.lr == 0.001  # unquoted: still a number


@row("an empty value (train.out_dir=$UNSET) is named, not a training into the working directory")
def row_empty_string_value(env):
    forbid(env, "instagram_hdmap.train.train_one_epoch", "training")
    env.error(r"'train\.out_dir' is empty", "train", env.yaml, "train.out_dir=")
    assert sorted(p.name for p in env.tmp.iterdir()) == []


@row("benchmark --device tpu is named (was a raw RuntimeError)")
def row_benchmark_unknown_device(env):
    env.error(r"--device tpu: choose cpu or cuda", "benchmark", env.yaml, "--device", "tpu")


@row("demo: a missing --config or a wrong key is named before the worlds are generated (minutes)")
def row_demo_config_checked_first(env):
    forbid(env, "instagram_hdmap.demo.ensure_world", "world generation")
    env.error(r"config file not found: .*nothere\.yaml", "demo", "--out", env.tmp / "demo", "--cache",
              env.tmp / "cache", "--config", env.tmp / "nothere.yaml")
    env.error(r"unknown config key 'train\.nope'", "demo", "--out", env.tmp / "demo", "--cache", env.tmp / "cache",
              "train.nope=1")


@row("a custom splits file with a scene in both splits: training warns that validation is not unseen")
def row_train_val_overlap_warning(env):
    from instagram_hdmap.train import build_loaders

    splits = json.loads((env.world / "splits.json").read_text())
    splits["train"] = [*splits["train"], *splits["val"]]
    path = env.tmp / "splits.json"
    path.write_text(json.dumps(splits))
    env.capsys.readouterr()
    build_loaders(env.cfg(f"data.splits_file={path}"), 1)
    out = env.capsys.readouterr().out
    assert re.search(r"warning: 3 of the 3 samples of split 'val' are also in the training split", out), out


@row("demo: train.out_dir (or another key the demo sets) as an override is refused before the worlds (it "
          "trained with --force in that folder, deleting the run there, then failed looking for OUT/run/last.pt)")
def row_demo_refuses_its_own_keys(env):
    other = env.tmp / "other_run"
    other.mkdir()
    (other / "best.pt").write_bytes(b"the user's model")
    forbid(env, "instagram_hdmap.demo.ensure_world", "world generation")
    env.error(r"the demo sets train\.out_dir itself; use --out", "demo", "--out", env.tmp / "demo", "--cache",
              env.tmp / "cache", f"train.out_dir={other}")
    env.error(r"the demo sets data\.dataroot itself", "demo", "--out", env.tmp / "demo", "--cache", env.tmp / "cache",
              f"data.dataroot={env.world}")
    env.error(r"--minutes inf: the budget must be a finite number", "demo", "--out", env.tmp / "demo", "--cache",
              env.tmp / "cache", "--minutes", "inf")  # was a config error on train.time_budget_min after the worlds
    assert (other / "best.pt").read_bytes() == b"the user's model"


@row("a device torch knows but this package does not run on (mps, xpu, meta) is named (predict-images --device "
          "mps and Mapper.from_checkpoint(device='mps') were a raw RuntimeError)")
def row_device_not_supported(env):
    from instagram_hdmap import Mapper

    with pytest.raises(UserError, match=r"device=mps is not supported; use auto, cpu, cuda"):
        Mapper.from_checkpoint(env.ckpt, device="mps")
    rig, images = rig_files(env)
    env.error(r"--device=mps is not supported|device=mps is not supported", "predict-images", "--checkpoint", env.ckpt,
              "--rig", rig, "--out", env.tmp / "out", "--device", "mps", *images)


@row("demo: a model setting that cannot be built (data.image_size=[30,30]) or an AV2 config is named before the "
          "worlds are generated (minutes; the AV2 config then failed on data.splits_file)")
def row_demo_model_checked_first(env):
    forbid(env, "instagram_hdmap.demo.ensure_world", "world generation")
    env.error(r"'data\.image_size': 30x30 .*multiples of 32", "demo", "--out", env.tmp / "demo", "--cache",
              env.tmp / "cache", "data.image_size=[30,30]")
    env.error(r"--config .*synthetic_demo\.yaml sets data\.dataset=av2, but the demo's synthetic worlds are in the "
              r"nuScenes layout", "demo", "--out", env.tmp / "demo", "--cache", env.tmp / "cache", "--config",
              REPO / "configs" / "av2" / "synthetic_demo.yaml")


@row("eval.thresholds with a threshold twice is named (mAP, their mean, counted it twice)")
def row_eval_thresholds_twice(env):
    env.error(r"'eval\.thresholds' lists a threshold twice", "model-summary", env.yaml, "eval.thresholds=[0.5,0.5,1.0]")


@row("a config whose _base_ is missing or a folder names the file that includes it (said 'config file not "
          "found: base.yaml', the user's file being there)")
def row_missing_base_named(env):
    (env.tmp / "exp.yaml").write_text("_base_: base.yaml\ntrain:\n  lr: 0.1\n")
    env.error(r"config file .*exp\.yaml: its _base_ base\.yaml .* is not a file", "model-summary", env.tmp / "exp.yaml")


@row("train.stream_frames=1 with a temporal model is refused (every frame started a new memory: the fusion never "
          "trained with one, a single-frame training, exit 0)")
def row_temporal_stream_frames_1(env):
    forbid(env, "instagram_hdmap.train.train_one_epoch", "training")
    env.error(r"train\.stream_frames=1: every frame would start a new memory", "train", env.yaml,
              "model.temporal.memory=bev", "train.stream_frames=1", f"train.out_dir={env.tmp / 'r'}")


@row("a path key written ~/... in a YAML file or a quoted override is the home folder (train.out_dir: ~/runs "
          "made a folder named '~' in the working directory, and said 'outputs in ~/runs')")
def row_tilde_in_path_keys(env):
    home = env.tmp / "home"
    env.monkeypatch.setenv("HOME", str(home))
    path = env.tmp / "exp.yaml"
    path.write_text(f"_base_: {env.yaml}\ntrain:\n  out_dir: ~/runs/x\n")
    cfg = load_config(path, ["train.init_from=~/best.pt", "data.dataroot=~/data/nuscenes"])
    assert (cfg.train.out_dir, cfg.train.init_from, cfg.data.dataroot) == (
        str(home / "runs" / "x"), str(home / "best.pt"), str(home / "data" / "nuscenes"))
    # a bare ~ (YAML's null) on a path that cannot be null is the home folder (it was refused as "expected str, got
    # None"); on an optional one it stays null: none
    cfg = load_config(env.yaml, ["train.out_dir=~", "data.dataroot=~", "train.init_from=~"])
    assert (cfg.train.out_dir, cfg.data.dataroot, cfg.train.init_from) == (str(home), str(home), None)


@row("evaluate with data.camera_dropout (a training config's setting) says that the images were blanked (the AP "
          "of dropped cameras, reported as the model's)")
def row_evaluate_notes_camera_dropout(env):
    rc, out, err = env.cli("evaluate", env.yaml, "data.camera_dropout=0.3", "--checkpoint", env.ckpt, "--out",
                           env.tmp / "eval")
    assert rc == 0 and re.search(r"note: data\.camera_dropout=0\.3: each camera image of the split is blanked in 30%",
                                 out), out


@row("a temporal training whose train.stream_warmup rounds to every epoch (0.6 of 1 epoch; the benchmark's "
          "--steps 100) is refused before the loaders: it ran on single frames only, its memory never trained, exit 0")
def row_temporal_warmup_covers_every_epoch(env):
    forbid(env, "instagram_hdmap.train.build_loaders", "the data loaders")
    env.error(r"train\.stream_warmup=0\.6 of train\.epochs=1 is 1 single-frame epoch\(s\) of 1: the temporal model "
              r"would never train with its memory", "train", env.yaml, f"train.out_dir={env.tmp / 'r'}",
              "model.temporal.memory=graph", "train.stream_warmup=0.6", "train.epochs=1")
    p = benchmark_temporal(env, "--steps", "100")
    assert p.returncode == 2 and re.search(r"the temporal run \(--steps 100\): train\.stream_warmup=0\.6 of "
                                           r"train\.epochs=1", p.stderr), p.stderr[-2000:]
    assert not (env.tmp / "cache").exists()


@row("predict (and predict --video) with data.camera_dropout > 0 (a training config's setting) blanked cameras "
          "of the frame without a word (evaluate said so already)")
def row_predict_notes_camera_dropout(env):
    rc, out, err = env.cli("predict", env.yaml, "data.camera_dropout=0.5", "--checkpoint", env.ckpt, "--index", "0",
                           "--out", env.tmp / "pred")
    assert rc == 0, err
    assert re.search(r"note: data\.camera_dropout=0\.5: each camera image of the split is blanked .* not the "
                     r"predictions of the full images", out + err), out + err


@row("a config's _base_ written ~/... (the home folder, as the path keys read it) was joined to the "
          "config's folder and refused as not a file")
def row_base_with_tilde(env):
    env.monkeypatch.setenv("HOME", str(env.tmp / "home"))
    (env.tmp / "home" / "configs").mkdir(parents=True)
    shutil.copy(env.yaml, env.tmp / "home" / "configs" / "base.yaml")
    (env.tmp / "exp").mkdir()
    exp = env.tmp / "exp" / "exp.yaml"
    exp.write_text("_base_: ~/configs/base.yaml\ntrain:\n  lr: 0.002\n")
    cfg = load_config(exp)
    assert cfg.train.lr == 0.002 and cfg.data.dataroot == load_config(env.yaml).data.dataroot


@row("a YAML or --set of an older release's key (train.max_minutes, which checkpoints still load) was "
            "refused as an unknown key with the list of valid keys; it names the new key")
def row_renamed_config_key_named(env):
    old = env.tmp / "old.yaml"
    old.write_text(f"_base_: {env.yaml}\ntrain:\n  max_minutes: 5\n")
    env.error(r"'train\.max_minutes' was renamed 'train\.time_budget_min'", "model-summary", old)
    env.error(r"'train\.max_minutes' was renamed 'train\.time_budget_min'", "model-summary", env.yaml,
              "train.max_minutes=5")


@row("an override written before the CONFIG file (model-summary train.lr=0.1 CONFIG) was refused as 'config "
            "file not found: train.lr=0.1'; the line says that overrides go after the CONFIG file")
def row_override_before_the_config(env):
    env.error(r"config file not found: train\.lr=0\.1; key=value overrides go after the CONFIG file",
              "model-summary", "train.lr=0.1", env.yaml)


@row("Chamfer thresholds given in centimetres (evaluate-json --thresholds 50 100 150, eval.thresholds, "
            "Evaluator(thresholds=...)) were taken as metres: every prediction of the right class within 1.5 m... "
            "150 m a true positive, AP near 1 with exit 0; a threshold above 10 m is named")
def row_thresholds_in_centimetres(env):
    from instagram_hdmap.evaluation import EvaluationInputError, Evaluator
    from instagram_hdmap.evaluation.io import write_submission

    gt = {"pts": np.array([[0.0, 2.0], [10.0, 2.0]]), "label": 0}
    write_submission(env.tmp / "gt.json", {"a": [gt]}, meta={"ground_truth": True})
    write_submission(env.tmp / "pred.json", {"a": [{**gt, "pts": gt["pts"] + [0, 5.0], "score": 0.9}]})
    env.error(r"150 m would match elements that far apart: centimetres given\?", "evaluate-json", "--pred",
              env.tmp / "pred.json", "--gt", env.tmp / "gt.json", "--thresholds", "50", "100", "150")
    env.error(r"'eval\.thresholds\[0\]' must be in \(0, 10\] \(Chamfer thresholds in metres \(centimetres given\?\)\)",
              "model-summary", env.yaml, "eval.thresholds=[50,100,150]")
    with pytest.raises(EvaluationInputError, match="centimetres given"):
        Evaluator(thresholds=(50, 100, 150))
    assert Evaluator(thresholds=(2.0, 4.0, 6.0)).thresholds == (2.0, 4.0, 6.0)  # wide but metres: taken


@row("predict --index 0 --fps 5 (the frame rate of a --scene video given to one sample's pictures) was "
            "ignored with no word; it is one line before the model runs")
def row_predict_fps_without_video(env):
    forbid(env, "instagram_hdmap.cli.predict_sample", "the prediction")
    env.error(r"--fps is the frame rate of a --scene video .* drop --fps", "predict", env.yaml, "--checkpoint",
              env.ckpt, "--index", "0", "--fps", "5", "--out", env.tmp / "out")


@row("predict --precision bf16 with an --onnx export (a float32 graph in onnxruntime) is one line before any file "
     "is read")
def row_precision_of_an_onnx_export(env):
    env.error(r"--precision bf16 runs a checkpoint; an --onnx export runs in float32", "predict", env.yaml, "--onnx",
              env.tmp / "model.onnx", "--index", "0", "--out", env.tmp / "out", "--precision", "bf16")


@row("--compile-backbone with what has no torch backbone to compile (predict --onnx, predict --gt-as-prediction) or "
     "with benchmark --compile (which compiles the backbone already) is one line before any model is built")
def row_compile_backbone_with_nothing_to_compile(env):
    env.error(r"--compile-backbone compiles a checkpoint's backbone .* an --onnx export runs in onnxruntime", "predict",
              env.yaml, "--onnx", env.tmp / "model.onnx", "--index", "0", "--out", env.tmp / "out",
              "--compile-backbone")
    env.error(r"--gt-as-prediction loads no model: drop --compile-backbone", "predict", env.yaml, "--gt-as-prediction",
              "--index", "0", "--out", env.tmp / "out", "--compile-backbone")
    env.error(r"--compile compiles the whole model.* give one of them", "benchmark", env.yaml, "--device", "cpu",
              "--compile", "--compile-backbone")


@row("predict --gt-as-prediction model.temporal.persist_frames=2 dropped the persistence with no word; a note "
            "says it is not applied to the GT")
def row_persist_with_gt_as_prediction(env):
    rc, out, err = env.cli("predict", env.yaml, "--gt-as-prediction", "--index", "0", "--out", env.tmp / "p",
                           "model.temporal.persist_frames=2")
    assert rc == 0, err
    assert "model.temporal.persist_frames=2 is not applied to --gt-as-prediction" in out + err


@row("the same override given twice on the command line (train.lr=1e-3 ... train.lr=1e-2, a slip in a long "
            "command): the last one won with no word; it still wins, and a note names both")
def row_same_override_given_twice(env):
    rc, out, err = env.cli("model-summary", env.yaml, "model.gnn.layers=2", "model.gnn.layers=3")
    assert rc == 0, err
    assert ("model-summary: note: model.gnn.layers is given 2 times (model.gnn.layers=2, model.gnn.layers=3); the "
            "last, model.gnn.layers=3, is used") in err
    rc, out, err = env.cli("model-summary", env.yaml, "model.gnn.layers=2", "model.gnn.heads=2")
    assert rc == 0 and "given 2 times" not in err


@row("eval.cmap_match_m had no upper bound: 100 (centimetres meant) ran C-mAP with a tracker that passes IDs "
            "across 100 m, with no word; it is bounded as model.temporal.persist_match_m (<= 10 m)")
def row_cmap_match_m_bounded(env):
    env.error(r"config key 'eval.cmap_match_m' must be in \(0, 10\] \(metres.*centimetres given\?\)\), got 100",
              "evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "eval", "eval.cmap=true",
              "eval.cmap_match_m=100")
    assert not (env.tmp / "eval").exists()


@row("model.gnn.min_vertices above model.gnn.num_vertices (min_vertices=100 with N = 64, or num_vertices=1): no "
            "element could ever be decoded, and evaluate / predict-images --decode wrote empty predictions, exit 0")
def row_min_vertices_above_num_vertices(env):
    forbid(env, "instagram_hdmap.predict.save_figure", "drawing")
    env.error(r"'model\.gnn\.min_vertices' is 100, but the model keeps model\.gnn\.num_vertices=64 vertices: no "
              r"element could ever be decoded", "evaluate", env.yaml, "--checkpoint", env.ckpt, "--out",
              env.tmp / "eval", "model.gnn.min_vertices=100")
    rig, images = rig_files(env)
    env.error(r"'model\.gnn\.min_vertices' is 100", "predict-images", "--checkpoint", env.ckpt, "--rig", rig, "--out",
              env.tmp / "out", "--device", "cpu", "--decode", "min_vertices=100", *images)
    env.error(r"'model\.gnn\.min_vertices' is 2, but the model keeps model\.gnn\.num_vertices=1", "model-summary",
              env.yaml, "model.gnn.num_vertices=1")
    assert not (env.tmp / "eval").exists()


@row("every loss weight 0 (loss.vertex_weight, distance_weight, adjacency_weight, class_weight): the loss was 0 "
            "and the run trained nothing, exit 0; an LSS depth_bound of one bin ([1, 13, 20]: every camera feature at "
            "one depth) trained too")
def row_loss_all_zero_and_one_depth_bin(env):
    forbid(env, "instagram_hdmap.train.build_loaders", "the training")
    env.error(r"'loss\.vertex_weight', .* are all 0: the loss would be 0", "train", env.yaml,
              f"train.out_dir={env.tmp / 'run'}", "loss.vertex_weight=0", "loss.distance_weight=0",
              "loss.adjacency_weight=0", "loss.class_weight=0")
    env.error(r"'model\.view_transform\.depth_bound': \(start, stop, step\) = \(1\.0, 13\.0, 20\.0\) gives 1 depth bin",
              "model-summary", env.yaml, "model.view_transform.depth_bound=[1,13,20]")
    assert env.cli("model-summary", env.yaml, "loss.vertex_weight=0")[0] == 0  # one weight 0: an ablation, valid


@row("demo --out OUT run again with another --config (or other model overrides) after OUT's run completed: it "
            "evaluated OUT's old model and wrote metrics.json naming the new config, exit 0, no word (an unfinished "
            "run failed later, after the worlds, with the resume's message)")
def row_demo_rerun_with_other_settings(env):
    run = env.tmp / "demo" / "run"
    run.mkdir(parents=True)
    shutil.copy(env.ckpt, run / "last.pt")  # a run of configs/synthetic/tiny.yaml's model in OUT
    forbid(env, "instagram_hdmap.demo.ensure_world", "world generation")
    env.error(r"--out .*demo holds a demo run of other settings \(.*data\.image_size: checkpoint \[64, 160\] vs now "
              r"\[64, 192\].*give another --out, or delete .*run to start over", "demo", "--out", env.tmp / "demo",
              "--cache", env.tmp / "cache")


@row("the temporal memory's keys on a single-frame model (train.stream_frames=4, model.temporal.fusion=gru with "
            "model.temporal.memory=none) trained a single-frame model on shuffled frames with no word; an LSS frustum "
            "that stops short of the grid (depth_bound to 13 m, grid.xbound [-16, 16]) likewise")
def row_training_notes_on_unread_settings(env):
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={env.tmp / 'run'}", "train.max_steps=1",
                           "train.stream_frames=4", "model.temporal.fusion=gru", "grid.xbound=[-16,16]")
    assert rc == 0, err[-2000:]
    assert ("note: model.temporal.fusion=gru, train.stream_frames=4 set, but model.temporal.memory=none: only a "
            "temporal model reads them") in out, out
    assert "note: model.view_transform.depth_bound stops at 13 m, but the grid" in out and "reaches 16 m" in out, out
    rc, out, _ = env.cli("train", env.yaml, f"train.out_dir={env.tmp / 'run2'}", "train.max_steps=1")
    assert rc == 0 and "but model.temporal.memory=none" not in out and "stops at" not in out, out  # tiny itself


@row("a temporal training of more streams (train.batch_size) than the training split has scenes (or pieces of "
            "train.stream_frames): the streams without a scene walked others' frames again in every batch (padding), "
            "no word; on a world of one-frame scenes the memory was never fused, no word")
def row_more_streams_than_scenes(env):
    from instagram_hdmap.data.synthetic import generate_world

    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={env.tmp / 'run'}", "train.max_steps=1",
                           "model.temporal.memory=bev", "train.batch_size=8")
    assert rc == 0, err[-2000:]
    assert re.search(r"note: train\.batch_size=8 streams, but the training split has 2 scenes: 6 streams walk no scene "
                     r"of their own", out), out
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={env.tmp / 'run2'}", "train.max_steps=1",
                           "model.temporal.memory=bev", "train.batch_size=2")
    assert rc == 0 and "streams walk no scene" not in out and "has one frame" not in out, err[-2000:]
    world = env.tmp / "w1"  # a world of one-frame scenes: the memory is never fused
    generate_world(out=world, scenes_train=2, scenes_val=1, samples_per_scene=1, image_size="400x225", progress=False)
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={env.tmp / 'run3'}", "train.max_steps=1",
                           "model.temporal.memory=bev", "train.batch_size=2", f"data.dataroot={world}",
                           f"data.splits_file={world / 'splits.json'}")
    assert rc == 0 and "note: every scene of the training split 'train' has one frame" in out, err[-2000:]


@row("predict-images --decode match_threshold=0.1 ... --decode match_threshold=0.3 (one option twice, a slip in "
            "a long command): the last was used with no word, where an override given twice is noted")
def row_decode_option_given_twice(env):
    rig, images = rig_files(env)
    rc, out, err = env.cli("predict-images", "--checkpoint", env.ckpt, "--rig", rig, "--out", env.tmp / "out",
                           "--device", "cpu", "--decode", "match_threshold=0.1", "--decode", "match_threshold=0.3",
                           *images)
    assert rc == 0, err[-2000:]
    assert ("note: --decode match_threshold is given 2 times (match_threshold=0.1, match_threshold=0.3); the last, "
            "match_threshold=0.3, is used") in err, err[-2000:]


@row("evaluate (and a training's validation) with eval.rank_by=descending or eval.fix_instance_ids=true under "
            "the vector protocol: unused with no word (evaluate-json refuses --rank-by with the vector protocol)")
def row_raster_options_under_the_vector_protocol(env):
    rc, out, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "eval",
                           "eval.rank_by=descending", "eval.fix_instance_ids=true")
    assert rc == 0, err[-2000:]
    for key in ("eval.rank_by=descending", "eval.fix_instance_ids=True"):
        assert f"note: {key} is not used: an option of the raster protocol, and eval.protocol=vector" in out, out
    rc, out, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "eval2",
                           "--protocol", "raster", "eval.rank_by=descending")
    assert rc == 0 and "is not used" not in out, err[-2000:]


@row("evaluate of a checkpoint trained on data.ped_crossing=edges under a CONFIG of another crossing convention "
            "(configs/synthetic/demo.yaml's 'each', as README's 'Scoring a checkpoint on any world' does): the model's "
            "open crossing edges scored against closed rings, the crossing AP near 0, exit 0, and the note on the "
            "CONFIG's model settings did not name it (the key is the GT's, not the model's); a note names both")
def row_evaluate_under_another_crossing_convention(env):
    rc, out, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "eval",
                           "data.ped_crossing=each")
    assert rc == 0, err
    assert ("note: the checkpoint was trained on data.ped_crossing='edges' crossings; the GT here draws them as 'each'"
            in out + err) and "data.ped_crossing=edges scores them as trained" in out + err
    rc, out, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "eval2")
    assert rc == 0 and "data.ped_crossing=" not in out + err


@row("eval.cmap_match_m (or eval.flicker_threshold_m) given while eval.cmap (eval.flicker) is off: the setting "
            "was unused with no word; evaluate and train say so once")
def row_meter_setting_without_its_meter(env):
    rc, out, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "eval",
                           "eval.cmap_match_m=2", "eval.flicker=false", "eval.flicker_threshold_m=0.5")
    assert rc == 0, err
    assert "note: eval.cmap_match_m=2 is not used: eval.cmap is off (set eval.cmap=true" in out + err
    assert "note: eval.flicker_threshold_m=0.5 is not used: eval.flicker is off" in out + err
    rc, out, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "eval2", "eval.cmap=true",
                           "eval.cmap_match_m=2")
    assert rc == 0 and "is not used" not in out + err


@row("evaluate --protocol raster eval.also_protocols=[vector] on a config of the vector protocol (tiny, demo): "
            "refused as 'lists protocols besides eval.protocol='vector'', the protocol --protocol replaces; the "
            "request is valid (raster, and vector as well) and runs")
def row_evaluate_protocol_flag_with_also_protocols(env):
    rc, out, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "eval", "--protocol",
                           "raster", "eval.also_protocols=[vector]")
    assert rc == 0, err
    metrics = json.loads((env.tmp / "eval" / "metrics.json").read_text())
    assert metrics["protocol"] == "raster" and metrics["also"]["vector"]["protocol"] == "vector"
    rc, out, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "eval2", "--protocol",
                           "raster", "eval.also_protocols=[raster]")  # --protocol listed again: the duplicate dropped
    assert rc == 0, err
    env.error(r"eval\.also_protocols' lists protocols besides eval\.protocol='vector'", "evaluate", env.yaml,
              "--checkpoint", env.ckpt, "--out", env.tmp / "eval3", "eval.also_protocols=[vector]")


@row("a temporal training with train.stream_warmup: the schedule counted train.epochs x the first (single-frame)"
            " epoch's steps, but an epoch of streams lasts as long as its longest stream: one scene of 3 frames on 4 "
            "streams ran 1 of its 3 steps and the run ended there, exit 0. Every epoch is counted as it is walked")
def row_temporal_epochs_of_streams_counted_whole(env):
    splits = env.tmp / "splits.json"
    names = json.loads((env.world / "splits.json").read_text())
    splits.write_text(json.dumps({"train": names["train"][:1], "val": names["val"]}))
    run = env.tmp / "run"
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={run}", f"data.splits_file={splits}",
                           "model.temporal.memory=bev", "train.epochs=2", "train.stream_warmup=0.5",
                           "train.batch_size=4", "train.val_every=100")
    assert rc == 0, err[-2000:]
    state = load_checkpoint(run / "last.pt")
    assert state["step"] == 1 + 3, state["step"]  # 1 step of shuffled frames, then the 3 frames of the scene


@row("a temporal training whose memory never fused (model.temporal.max_jump_m=0.01: every frame a pose jump, "
            "as a max_jump_m in other units or drives faster than it would): the fusion trained on nothing, exit 0, "
            "no word (log.jsonl alone counted the statuses). A warning names the statuses and the keys")
def row_temporal_memory_never_fused_warned(env):
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={env.tmp / 'run'}", "model.temporal.memory=bev",
                           "model.temporal.max_jump_m=0.01", "train.epochs=1", "train.val_every=100")
    assert rc == 0, err[-2000:]
    assert re.search(r"warning: the temporal memory was never fused in epoch 0 \(per step: .*pose_jump", out), out


@row("predict --video --fps 0.001 (one frame per 1000 s, in range '> 0') ended after the model had run in "
            "'OpenCV cannot write MP4 here; check the folder is writable and OpenCV was built with FFmpeg', the wrong "
            "cause; the range says where OpenCV's writer stops, before the work, and 0.01 still writes")
def row_video_fps_below_the_time_base(env):
    argv = ("predict", env.yaml, "--checkpoint", env.ckpt, "--scene", val_scene(env))
    env.error(r"--fps 0\.001: frames per second must be over 0\.001 and at most 1000", *argv, "--video",
              env.tmp / "v.mp4", "--fps", "0.001")
    rc, _, err = env.cli(*argv, "--video", env.tmp / "slow.mp4", "--fps", "0.01")
    assert rc == 0 and (env.tmp / "slow.mp4").stat().st_size > 0, err[-2000:]


@row("an argument copied from a web page with a non-breaking space (U+00A0) the terminal does not show: "
            "train.out_dir=runs/x\\xa0 trained into a new folder whose name ends in it (exit 0), --checkpoint "
            "best.pt\\xa0 was 'not found: best.pt ', model.gnn.layers=3\\xa0 'expected int, got 3.0 (float)'. "
            "In a YAML file the same said \"unknown config key '  epochs'\" or made an invisible out_dir. Each names "
            "the argument (or file and line) and the character; a file whose name holds one still opens")
def row_invisible_character_in_an_argument(env):
    nbsp = "\u00a0"
    env.error(r"argument 'train\.out_dir=.*run\\xa0' holds a non-breaking space \(U\+00A0\)", "train", env.yaml,
              f"train.out_dir={env.tmp / 'run'}{nbsp}", "train.max_steps=1")
    assert not any(p.name.startswith("run") for p in env.tmp.iterdir())
    env.error(r"argument '.*\.pt\\xa0' holds a non-breaking space", "evaluate", env.yaml, "--checkpoint",
              f"{env.ckpt}{nbsp}", "--out", env.tmp / "eval")
    env.error(r"argument 'model\.gnn\.layers=3\\u200b' holds a zero-width space \(U\+200B\)", "model-summary",
              env.yaml, "model.gnn.layers=3\u200b")
    named = env.tmp / f"best{nbsp}copy.yaml"  # a file that exists with the character in its name
    shutil.copy(env.yaml, named)
    rc, _, err = env.cli("model-summary", named)
    assert rc == 0, err[-2000:]
    config = env.tmp / "copied.yaml"  # the same in a YAML file: "unknown config key '  epochs'", an invisible out_dir
    for text, shown in ((f"train:\n{nbsp}{nbsp}epochs: 3\n", r"'\\xa0\\xa0epochs: 3'"),
                        (f"train:\n  out_dir: runs/x{nbsp}\n", r"'out_dir: runs/x\\xa0'")):
        config.write_text(f"_base_: {env.yaml}\n" + text)
        env.error(rf"config file .*copied\.yaml, line 3: {shown} holds a non-breaking space", "model-summary", config)
    config.write_text(f"_base_: {env.yaml}\n# copied{nbsp}from a page\ntrain:\n  epochs: 3  # a{nbsp}note\n")
    assert load_config(config).train.epochs == 3  # in a comment it does no harm


@row("evaluate with data.val_split=train (a debugging override left in a config, or copied) scored the very "
            "samples the checkpoint was trained on and reported that AP with no word; a note says the split is the "
            "checkpoint's training split")
def row_evaluate_on_the_training_split(env):
    rc, out, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "seen",
                           "data.val_split=train")
    assert rc == 0, err[-2000:]
    assert "data.val_split='train' is the split the checkpoint was trained on" in out + err, (out + err)[-2000:]
    rc, out, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "unseen")
    assert rc == 0 and "the split the checkpoint was trained on" not in out + err, (out + err)[-2000:]


@row("a mapping given on the command line after one of its keys (model.gnn.layers=3 model.gnn={dim: 64}) "
            "replaced the section the first had set: model.gnn.layers silently went back to the YAML's value; the "
            "mapping now merges into the keys before it, and a key given by both is noted (the last wins); an override "
            "that is not a string (Python API) was a raw TypeError naming nothing")
def row_override_mapping_keeps_earlier_keys(env):
    cfg = env.cfg("model.gnn.layers=3", "model.gnn={dim: 64}")
    assert (cfg.model.gnn.layers, cfg.model.gnn.dim) == (3, 64)
    cfg = env.cfg("model.gnn.layers=3", "model={gnn: {heads: 2}}")
    assert (cfg.model.gnn.layers, cfg.model.gnn.heads) == (3, 2)
    rc, out, err = env.cli("model-summary", env.yaml, "model.gnn.layers=3", "model.gnn={layers: 1, dim: 64}")
    assert rc == 0, err
    assert ("note: model.gnn.layers is given 2 times (model.gnn.layers=3, model.gnn={layers: 1, dim: 64}); the last, "
            "model.gnn={layers: 1, dim: 64}, is used") in err
    assert env.cfg("model.gnn.layers=3", "model.gnn={layers: 1, dim: 64}").model.gnn.layers == 1
    for item in (3, None, b"train.lr=1"):  # an override that is not a string: a raw "argument of type 'int' ..."
        with pytest.raises(TypeError, match=r"an override is a 'key\.sub=value' string, got"):
            load_config(env.yaml, ["train.lr=1e-3", item])


@row("YAML 1.1's integers: a leading zero made an octal number (train.seed: 0123 ran with seed 83, "
            "train.epochs=010 trained 8 epochs) and colons a base-60 one (train.time_budget_min: 1:30:00 was 5400 "
            "minutes), exit 0; a leading zero is now decimal (YAML 1.2), and 1:30 is text that a number key refuses")
def row_yaml_leading_zero_and_base_60(env):
    path = env.tmp / "c.yaml"
    path.write_text(f"_base_: {env.yaml}\ntrain:\n  seed: 0123\n  epochs: 010\n  max_steps: 0_10\n")
    cfg = load_config(path)
    assert (cfg.train.seed, cfg.train.epochs, cfg.train.max_steps) == (123, 10, 10)
    assert env.cfg("train.epochs=010").train.epochs == 10
    assert env.cfg("train.seed=0x1F").train.seed == 31  # hexadecimal stays (YAML 1.2 has it too)
    path.write_text(f"_base_: {env.yaml}\ntrain:\n  time_budget_min: 1:30:00\n")
    env.error(r"config key 'train\.time_budget_min': expected float or null, got '1:30:00'", "model-summary", path)
    env.error(r"config key 'train\.max_steps': expected int or null, got '1:30'", "model-summary", env.yaml,
              "train.max_steps=1:30")
    assert env.cfg("name=1:30").name == "1:30"


@row("a text key whose text reads as a YAML 1.2 float (name: '3e-4', an experiment named after its learning "
            "rate): save_config wrote it bare (PyYAML's YAML 1.1 sees text), so the run's config.yaml no longer "
            "loaded ('expected str, got 0.0003'); it is written quoted and loads as saved")
def row_saved_config_text_that_reads_as_a_number(env):
    from instagram_hdmap.config import save_config

    for overrides in (["name='3e-4'"], ["name='1e3'", "data.train_split='1e3'"], ["name='010'"], ["name='1:30'"]):
        cfg = env.cfg(*overrides)
        save_config(cfg, env.tmp / "saved.yaml")
        assert load_config(env.tmp / "saved.yaml") == cfg, overrides


@row("a YAML file (or override) nested hundreds of levels deep: a raw RecursionError traceback naming nothing; "
            "a value of a million items (YAML aliases) given to a number key: a 58 MB error message; now one line "
            "naming the file and cut short")
def row_deep_or_huge_yaml_values(env):
    deep = env.tmp / "deep.yaml"
    deep.write_text(f"_base_: {env.yaml}\nmodel: " + "[" * 3000 + "]" * 3000 + "\n")
    env.error(r"config file .*deep\.yaml: its lists or mappings are nested too deeply", "model-summary", deep)
    env.error(r"override 'model=\[\[.*': its lists or mappings are nested too deeply", "model-summary", env.yaml,
              "model=" + "[" * 3000 + "]" * 3000)
    huge = env.tmp / "huge.yaml"  # a list whose last item holds 2^20 leaves, through aliases
    huge.write_text(f"_base_: {env.yaml}\nmodel:\n  gnn:\n    dim: [&a0 [x, x], "
                    + ", ".join(f"&a{i} [*a{i - 1}, *a{i - 1}]" for i in range(1, 21)) + "]\n")
    line = env.error(r"config key 'model\.gnn\.dim': expected int, got \[\[", "model-summary", huge)
    assert len(line) < 400, len(line)


@row("a text key given a number or a YAML 1.1 word (name: 2024, data.version: 1.0, data.val_split: no) and a "
            "whole-number key given 1e3: refused saying only 'expected str, got 2024 (int)' (a key `on:`: 'unknown "
            "key True'; a section of commented-out keys: 'must be a mapping, got None'); the message now says to "
            "quote the text, how to write the whole number or a list, what YAML did")
def row_text_key_given_a_number_says_quote_it(env):
    path = env.tmp / "text.yaml"
    path.write_text(f"_base_: {env.yaml}\nname: 2024\n")  # in a file (command line: text-keys-on-the-command-line-...)
    env.error(r"config key 'name': expected str, got 2024 \(int\); .*quote the text .*\(name: \"\.\.\.\" in the YAML",
              "model-summary", path)
    path.write_text(f"_base_: {env.yaml}\ndata:\n  val_split: no\n")
    env.error(r"config key 'data\.val_split': expected str, got False \(bool\); .*quote", "model-summary", path)
    env.error(r"config key 'train\.epochs': expected int, got 1000\.0 \(float\); write the whole number as 1000",
              "model-summary", env.yaml, "train.epochs=1e3")
    assert env.cfg("name='2024'").name == "2024"
    env.error(r"config key 'train\.trainable': expected list of str, got 'temporal' \(str\); a list is written in "
              r"brackets: \[a, b\] \(one item: \[a\]\)", "model-summary", env.yaml, "train.trainable=temporal")
    path = env.tmp / "on.yaml"
    path.write_text(f"_base_: {env.yaml}\non: 1\n")  # a key `on` (a typo, or a CI file's) is YAML 1.1's true
    env.error(r"unknown config key 'True' \(YAML reads a key on / off / yes / no as true / false\)", "model-summary",
              path)


@row("eval.flicker_threshold_m in centimetres (100): every GT element counted as detected, the flicker rate 0, "
            "exit 0, while its siblings eval.cmap_match_m and eval.thresholds refuse more than 10 m; refused the same")
def row_flicker_threshold_in_centimetres(env):
    env.error(r"config key 'eval\.flicker_threshold_m' must be in \(0, 10\] \(metres.*centimetres given\?\)",
              "model-summary", env.yaml, "eval.flicker_threshold_m=100")
    assert env.cfg("eval.flicker_threshold_m=10").eval.flicker_threshold_m == 10


@row("data.val_split equal to data.train_split (a slip, or an overfitting check): validation and the choice "
            "of best.pt scored the training scenes with no word; training notes it at the start")
def row_validation_on_the_training_split_noted(env):
    from instagram_hdmap.train import setting_notes

    notes = setting_notes(env.cfg("data.val_split=train"))
    assert any("data.val_split=train is the training split" in n for n in notes), notes
    assert not any("training split" in n for n in setting_notes(env.cfg()))


@row("a decoder's option given with another decoder (model.gnn.same_class_edges=true with decoder=classwise, "
            "model.gnn.class_min_prob with greedy): unused with no word, while max_edge_m with mutual is refused; "
            "evaluate and training's validation note it")
def row_decoder_option_of_another_decoder_noted(env):
    from instagram_hdmap.train import unused_meter_keys

    notes = unused_meter_keys(env.cfg("model.gnn.decoder=classwise", "model.gnn.same_class_edges=true"))
    assert any("model.gnn.same_class_edges=true is not used" in n for n in notes), notes
    notes = unused_meter_keys(env.cfg("model.gnn.class_min_prob=0.2"))
    assert any("model.gnn.class_min_prob=0.2 is not used" in n and "decoder=greedy" in n for n in notes), notes
    assert not unused_meter_keys(env.cfg("model.gnn.decoder=classwise", "model.gnn.class_min_prob=0.2"))
    assert not unused_meter_keys(env.cfg("model.gnn.same_class_edges=true"))


@row("a key that only another setting reads (train.min_lr_factor under the step schedule, train.lr_step / "
            "lr_gamma under cosine, model.gnn.vd_sampling without the pe+vd embedding, data.aug_* without "
            "data.augment, data.av2_* on nuScenes) trained as if unset, with no word; training notes it at the start")
def row_key_of_another_setting_noted(env):
    from instagram_hdmap.train import setting_notes

    def notes(*overrides):
        return " | ".join(setting_notes(env.cfg(*overrides)))

    assert "train.min_lr_factor=0.1 set, but train.schedule=step does not read it" in notes("train.min_lr_factor=0.1")
    assert "train.lr_step=5, train.lr_gamma=0.5 set, but train.schedule=cosine" in notes(
        "train.schedule=cosine", "train.lr_step=5", "train.lr_gamma=0.5")
    assert "model.gnn.vd_sampling=cell set, but model.gnn.embedding=pe+dt" in notes("model.gnn.vd_sampling=cell")
    assert "data.aug_rotate_deg=10.0 set, but data.augment=false" in notes("data.aug_rotate_deg=10")
    assert "data.av2_frame_step=2 set, but data.dataset=nuscenes" in notes("data.av2_frame_step=2")
    for ok in (["train.schedule=cosine", "train.min_lr_factor=0.1"], ["train.lr_step=5", "train.lr_gamma=0.5"],
               ["model.gnn.vd_sampling=cell", "model.gnn.embedding=pe+vd", "model.bev_heads.distance_head=false"],
               ["data.aug_rotate_deg=10", "data.augment=true"]):
        assert "does not read" not in notes(*ok) and "reads it" not in notes(*ok), ok


@row("a key one letter off (model.gnn.layer, train.max_step, MODEL.gnn.layers) was refused with the section's "
            "whole list of keys to read through (model.gnn has 18); the nearest key is named first (and a dotted key "
            "in a YAML file is told to nest)")
def row_unknown_key_names_the_nearest(env):
    for override, near in (("model.gnn.layer=3", "model.gnn.layers"), ("train.max_step=9", "train.max_steps"),
                           ("MODEL.gnn.layers=3", "model"), ("eval.threshold=[1]", "eval.thresholds")):
        env.error(rf"unknown config key '[^']+' \(did you mean '{re.escape(near)}'\?\); valid keys of", "model-summary",
                  env.yaml, override)
    line = env.error(r"unknown config key 'model\.gnn\.xyz'; valid keys of", "model-summary", env.yaml,
                     "model.gnn.xyz=3")
    assert "did you mean" not in line
    path = env.tmp / "dotted.yaml"
    path.write_text(f"_base_: {env.yaml}\nmodel.gnn.layers: 3\n")  # the command line's dotted form in a file
    env.error(r"unknown config key 'model\.gnn\.layers' \(a YAML file nests the keys", "model-summary", path)


@row("an override written with a flag, as the benchmarks' --set or other tools' --model.gnn.layers=9: "
            "'unrecognized arguments: --set' said nothing of how to write it; it says that overrides are key=value "
            "words after CONFIG")
def row_override_written_with_a_flag(env):
    for argv in (["--set", "model.gnn.layers=3"], ["--model.gnn.layers=3"]):
        with pytest.raises(SystemExit) as e:
            env.cli("model-summary", env.yaml, *argv)
        err = env.capsys.readouterr().err
        assert e.value.code == 2 and "config overrides are key=value words after CONFIG, without a flag" in err, err
    with pytest.raises(SystemExit):
        env.cli("model-summary", env.yaml, "--bogus")
    assert "key=value words" not in env.capsys.readouterr().err


@row("a text key given on the command line a value YAML reads as a number, a date or a boolean (name=2024, "
            "train.out_dir=2024-12-05, data.val_split=no) was refused (the shell eats the quotes the message asked "
            "for); it is the text typed, as Hydra's grammar keeps it. A YAML section whose keys are all commented "
            "out is an empty section (it was refused: 'must be a mapping, got None'); an override giving a section "
            "no keys (model.gnn=~) is named")
def row_text_keys_on_the_command_line_and_empty_sections(env):
    cfg = env.cfg("name=2024", "train.out_dir=2024-12-05", "data.val_split=no", "data.version=1.0", "name=3e-4")
    assert (cfg.name, cfg.train.out_dir, cfg.data.val_split, cfg.data.version) == ("3e-4", "2024-12-05", "no", "1.0")
    assert env.cfg("train.epochs=010", "train.lr=3e-3").train.epochs == 10  # number keys read numbers
    path = env.tmp / "empty.yaml"
    path.write_text(f"_base_: {env.yaml}\nmodel:\n  # gnn:\n  #   layers: 3\ntrain:\n")
    base = load_config(env.yaml)
    cfg = load_config(path)
    assert (cfg.model, cfg.train) == (base.model, base.train)  # the base's sections, not emptied
    env.error(r"override 'model\.gnn=~' gives the section model\.gnn no keys; set its keys \(model\.gnn\.KEY=VALUE\)",
              "model-summary", env.yaml, "model.gnn=~")


@row("a config given as a pipe (`train <(envsubst < in.yaml)`, `... | model-summary /dev/stdin`): 'config "
            "file not found: /dev/fd/63', though it was there; now read (once, as a file is). A checkpoint given as "
            "a pipe: 'checkpoint not found' (an ONNX file: 'ONNX file not found'); an image of predict-images as a "
            "pipe: 'cannot be read as an image' (a named pipe: a hang); now named as pipes (read more than once)")
def row_config_from_a_pipe(env):
    env_vars = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    p = subprocess.run([sys.executable, "-m", "instagram_hdmap.cli", "model-summary", "/dev/stdin"],
                       input=env.yaml.read_bytes(), capture_output=True, env=env_vars, timeout=300)
    assert p.returncode == 0 and b"trainable" in p.stdout, p.stderr[-2000:]
    p = subprocess.run([sys.executable, "-m", "instagram_hdmap.cli", "evaluate", str(env.yaml), "--checkpoint",
                        "/dev/stdin", "--out", str(env.tmp / "eval")], input=env.ckpt.read_bytes(), capture_output=True,
                       text=False, env=env_vars, timeout=300)
    assert p.returncode == 2 and b"checkpoint /dev/stdin is a pipe or a device, not" in p.stderr, p.stderr[-2000:]
    rig, images = rig_files(env)  # an image as a pipe: read by checks, then decoded (a named pipe hung)
    p = subprocess.run([sys.executable, "-m", "instagram_hdmap.cli", "predict-images", "--checkpoint", str(env.ckpt),
                        "--rig", str(rig), "--out", str(env.tmp / "out"), "--device", "cpu", "/dev/stdin",
                        *map(str, images[1:])], input=images[0].read_bytes(), capture_output=True, env=env_vars,
                       timeout=300)
    assert p.returncode == 2 and b"image /dev/stdin is a pipe or a device, not a file" in p.stderr, p.stderr[-2000:]
    import importlib.util

    if importlib.util.find_spec("onnx") and importlib.util.find_spec("onnxruntime"):  # --onnx as a pipe
        p = subprocess.run([sys.executable, "-m", "instagram_hdmap.cli", "predict-images", "--onnx", "/dev/stdin",
                            "--rig", str(rig), "--out", str(env.tmp / "out"), *map(str, images)], input=b"onnx",
                           capture_output=True, env=env_vars, timeout=300)
        assert p.returncode == 2 and b"ONNX file /dev/stdin is a pipe or a device" in p.stderr, p.stderr[-2000:]


@row("an option copied from a formatted page with a typographic dash (`\u2014force`, `\u2013-checkpoint R`): "
            "'override must look like key.sub=value', or '--checkpoint is required' though it was given; now the dash "
            "is named and the option to type")
def row_typographic_dash_in_an_option(env):
    for argv, option in ((["train", env.yaml, "\u2014force"], "--force"),
                         (["evaluate", env.yaml, "\u2013-checkpoint", env.ckpt], "--checkpoint"),
                         (["evaluate", env.yaml, f"\u2212\u2212checkpoint={env.ckpt}"], "--checkpoint=")):
        with pytest.raises(SystemExit) as e:
            env.cli(*argv)
        err = env.capsys.readouterr().err
        assert e.value.code == 2 and "a dash that only looks like '-'" in err and f"type {option}" in err, err[-2000:]
    rc, out, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "\u2014eval")  # a value
    assert rc == 0, err[-2000:]


@pytest.mark.parametrize("case", table(__name__), ids=str)
def test_config(case, env):
    case.run(env)
