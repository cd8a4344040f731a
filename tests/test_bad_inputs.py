"""Bad inputs and faults, one row per case (issue 21 and the sweeps after it).

Each row is a small function that does the bad thing a hostile but realistic user would do and
checks the promise: a wrong input is named on one line (``UserError``, exit code 2, no traceback),
nothing is lost, and no result is silently wrong. ``ROWS`` is the table; ``case`` is the number of
the case in issue 21 (``S`` marks a case found by the sweep that fixed them, ``S2`` one found by a
second sweep of the same kind after it, ``S3`` one found by a third sweep, ``S4`` one found by a
fourth, ``S5`` one found by a fifth, ``S6`` one found by a sixth, ``S7`` one found by a seventh, ``S8`` one
found by an eighth, ``S9`` one found by a ninth, ``S10`` one found by a tenth, ``S11`` one found by an
eleventh, ``S12`` one found by a twelfth, ``S13`` one found by a thirteenth, ``S14`` one found by a
fourteenth, ``S15`` one found by a fifteenth, ``S16`` one found by a sixteenth, ``S17`` one found by a
seventeenth, ``S18`` one found by an eighteenth, ``S19`` one found by a nineteenth, ``S20`` one found by a
twentieth; a ninth-, tenth-, eleventh-, fourteenth-, nineteenth- or twentieth-sweep row of a valid input that was
refused checks that it runs).
``S21`` marks a case found by a twenty-first sweep (the researcher's workflow through the docs and the Python API).
``S22`` marks a case found by a twenty-second sweep (the temporal and AV2 workflows end to end, the demo's world cache).
``S23`` marks a case found by a twenty-third sweep (valid but unusual inputs checked against independent computations).
``S24`` marks a case found by a twenty-fourth sweep (synth's flags, split files written by hand).
``S25`` marks a case found by a twenty-fifth sweep (the issue's own kind, done blind).
``S26`` marks a case found by a twenty-sixth sweep (the config as users write it: keys, overrides, YAML files).
``S27`` marks a case found by a twenty-seventh sweep (resume, reuse and runs that meet other runs).
``S28`` marks a case found by a twenty-eighth sweep (the files written as other programs read them, the terminal).
``S29`` marks a case found by a twenty-ninth sweep (the real datasets as downloaded: nuScenes in parts, AV2 as shipped).
``S30`` marks a case found by a thirtieth sweep (the issue's own kind done blind a second time).
Everything runs on the tiny synthetic world of conftest.py and a random tiny model: no training longer than a few steps.
"""

from __future__ import annotations

import fnmatch
import json
import os
import re
import shutil
import subprocess
import sys
import time
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from instagram_hdmap.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from instagram_hdmap.cli import main
from instagram_hdmap.config import UserError, config_to_dict, load_config

REPO = Path(__file__).resolve().parents[1]
TINY_YAML = REPO / "configs" / "synthetic" / "tiny.yaml"


# --- the table ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Row:
    id: str
    case: str  # issue 21's case number, "S" (the sweep that fixed them), "S2" (the sweep after it), "S3" ... "S27"
    what: str
    run: Callable


ROWS: list[Row] = []


def row(case: str, what: str):
    def register(fn):
        ROWS.append(Row(fn.__name__.removeprefix("row_"), case, what, fn))
        return fn

    return register


# --- shared fixtures: a config file for the tiny world, a random checkpoint ------------------------


@dataclass
class Env:
    world: Path  # the session's tiny synthetic nuScenes world: never damaged
    yaml: Path  # configs/synthetic/tiny.yaml pointed at `world` (num_workers 0, eval batch 2)
    ckpt: Path  # a random tiny model saved with its config
    tmp: Path  # this row's own folder
    capsys: pytest.CaptureFixture
    monkeypatch: pytest.MonkeyPatch
    request: pytest.FixtureRequest  # for the fixtures only some rows need (av2_world)

    def cli(self, *argv) -> tuple[int, str, str]:
        self.capsys.readouterr()
        rc = main([str(a) for a in argv])
        out, err = self.capsys.readouterr()
        return rc, out, err

    def error(self, pattern: str, *argv) -> str:
        """Run the CLI; it must exit 2 with one line on stderr that matches ``pattern``."""
        rc, out, err = self.cli(*argv)
        lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith(("epoch", "eval", "\r"))]
        assert rc == 2, f"exit {rc}, stderr:\n{err[-3000:]}"
        assert len(lines) == 1, f"not one line:\n{err[-3000:]}"
        assert "Traceback" not in err
        assert re.search(pattern, lines[0]), lines[0]
        return lines[0]

    def shadow_world(self, edit_tables: Callable[[dict], None] | None = None, copy_samples: bool = False) -> Path:
        """A world that shares `world`'s maps (and images, unless ``copy_samples``) through symlinks,
        with its own copy of the tables, edited by ``edit_tables({table name: records})``."""
        root = self.tmp / "world"
        root.mkdir()
        for name in ("world.json", "splits.json"):
            shutil.copy(self.world / name, root / name)
        (root / "maps").symlink_to(self.world / "maps")
        if copy_samples:
            shutil.copytree(self.world / "samples", root / "samples")
        else:
            (root / "samples").symlink_to(self.world / "samples")
        version = root / "v1.0-trainval"
        shutil.copytree(self.world / "v1.0-trainval", version)
        if edit_tables is not None:
            tables = {p.stem: json.loads(p.read_text()) for p in version.glob("*.json")}
            edit_tables(tables)
            for name, records in tables.items():
                (version / f"{name}.json").write_text(json.dumps(records))
        return root

    def cfg(self, *overrides):
        return load_config(self.yaml, [f"train.out_dir={self.tmp / 'run'}", *overrides])


@pytest.fixture(scope="module")
def shared(tiny_world, world_overrides, tmp_path_factory):
    from instagram_hdmap.models import build_model

    root = tmp_path_factory.mktemp("bad_inputs")
    yaml = root / "tiny_world.yaml"
    data = dict(o.split("=", 1) for o in world_overrides(tiny_world))
    yaml.write_text(
        f"_base_: {TINY_YAML}\n"
        f"data:\n  dataroot: {data['data.dataroot']}\n  version: {data['data.version']}\n"
        f"  splits_file: {data['data.splits_file']}\n  num_workers: 0\n"
        "train:\n  device: cpu\n  epochs: 1\n  batch_size: 2\n  checkpoint_every: 0\n  log_every: 1\n"
        "eval:\n  batch_size: 2\n"
    )
    torch.manual_seed(0)
    cfg = load_config(yaml)
    ckpt = save_checkpoint({"model": build_model(cfg).state_dict(), "config": config_to_dict(cfg)}, root / "random.pt")
    return tiny_world, yaml, ckpt


# --- helpers --------------------------------------------------------------------------------------


def dead_pid() -> int:
    """The id of a process that has exited (and been reaped)."""
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def first(records: list[dict], **match) -> dict:
    return next(r for r in records if all(r[k] == v for k, v in match.items()))


def camera_record(tables: dict, channel: str, sample_index: int = 0) -> tuple[dict, dict]:
    """(sample_data, calibrated_sensor) of camera ``channel`` of the val scene's ``sample_index``-th sample."""
    token = tables["scene"][-1]["first_sample_token"]  # the tiny world's one val scene comes last
    for _ in range(sample_index):
        token = first(tables["sample"], token=token)["next"]
    sensor = first(tables["sensor"], channel=channel)["token"]
    for sd in tables["sample_data"]:
        if sd["sample_token"] == token and sd["is_key_frame"]:
            cs = first(tables["calibrated_sensor"], token=sd["calibrated_sensor_token"])
            if cs["sensor_token"] == sensor:
                return sd, cs
    raise AssertionError(f"no {channel} record for sample {token}")


def val_dataset(cfg):
    from instagram_hdmap.data import build_dataset

    return build_dataset(cfg, cfg.data.val_split, augment=False)


def forbid(env: Env, target: str, what: str) -> None:
    """Make ``target`` (a dotted name) fail the test if it is called: the error must come first."""

    def called(*args, **kwargs):
        raise AssertionError(f"{what} ran before the error")

    env.monkeypatch.setattr(target, called)


# ==================================================================================================
# Data lost or results silently wrong
# ==================================================================================================


def _toy_run(env: Env, scores: list[float], *overrides, resume: str | None = None, force: bool = False):
    """A tiny training on in-memory samples whose validations score ``scores`` in turn."""
    from instagram_hdmap import train as train_module
    from test_train import TINY, _loaders

    queue = list(scores)

    def fake_evaluate(*args, **kwargs):
        return {"losses": {"loss_total": 1.0}, "metrics": {"mAP": queue.pop(0)}}

    env.monkeypatch.setattr(train_module, "evaluate", fake_evaluate)
    cfg = load_config(None, [*TINY, f"train.out_dir={env.tmp / 'run'}", *overrides])
    train_loader, sampler, _ = _loaders(cfg)
    summary = train_module.train(cfg, loaders=(train_loader, sampler, [None]), validate=True, resume=resume,
                                 force=force)
    assert not queue, "fewer validations than scores"
    return summary


@row("1", "best.pt is only replaced by a better validated model, across resumes")
def row_best_survives_a_resume(env):
    run = env.tmp / "run"
    # 4 samples, batch 2: 2 steps per epoch; max_steps=1 stops mid-epoch 0, then validates (0.6)
    _toy_run(env, [0.6], "train.epochs=3", "train.max_steps=1")
    assert load_checkpoint(run / "best.pt")["metrics"]["mAP"] == 0.6
    assert load_checkpoint(run / "last.pt")["best"]["score"] == 0.6  # last.pt saved after that validation
    _toy_run(env, [0.3, 0.4, 0.2], "train.epochs=3", resume=str(run / "last.pt"))
    assert load_checkpoint(run / "best.pt")["metrics"]["mAP"] == 0.6
    # a last.pt older than best.pt (killed between the two saves) does not lose best.pt either
    state = load_checkpoint(run / "last.pt")
    state["best"] = {"score": float("-inf")}
    state["epoch"], state["step"], state["step_in_epoch"] = 2, 4, 0
    state["clock"] = {**state["clock"], "progress": 4 / 6}  # 3 epochs of 2 steps
    save_checkpoint(state, run / "last.pt")
    _toy_run(env, [0.5], "train.epochs=3", resume=str(run / "last.pt"))
    assert load_checkpoint(run / "best.pt")["metrics"]["mAP"] == 0.6


def _calibration_row(channel: str, edit: Callable[[dict], None], pattern: str):
    def run(env):
        def damage(tables):
            sd, cs = camera_record(tables, channel)
            edit(cs)

        root = env.shadow_world(damage)
        env.error(pattern, "evaluate", env.yaml, f"data.dataroot={root}", "--checkpoint", env.ckpt,
                  "--out", env.tmp / "eval")

    return run


for _name, _channel, _edit, _pattern in (
    ("nan_camera_translation", "CAM_FRONT", lambda cs: cs["translation"].__setitem__(0, float("nan")),
     r"CAM_FRONT.*translation.*(NaN|finite)"),
    ("nan_camera_rotation", "CAM_BACK", lambda cs: cs["rotation"].__setitem__(1, float("nan")),
     r"CAM_BACK.*rotation.*(NaN|finite)"),
    ("camera_rotation_not_unit", "CAM_BACK_LEFT",
     lambda cs: cs.__setitem__("rotation", [2 * q for q in cs["rotation"]]),
     r"CAM_BACK_LEFT.*rotation.*(unit|orthonormal)"),
    ("negative_focal_length", "CAM_FRONT_LEFT", lambda cs: cs["camera_intrinsic"][0].__setitem__(0, -500.0),
     r"CAM_FRONT_LEFT.*intrinsic.*focal"),
    ("nan_intrinsics", "CAM_FRONT_RIGHT", lambda cs: cs["camera_intrinsic"][1].__setitem__(2, float("nan")),
     r"CAM_FRONT_RIGHT.*intrinsic.*(NaN|finite)"),
):
    row("2", f"calibration: {_name}")(_calibration_row(_channel, _edit, _pattern))
    ROWS[-1] = Row(_name, "2", ROWS[-1].what, ROWS[-1].run)


@row("2", "an ego pose with NaN is named, not a GEOS exception")
def row_nan_ego_pose(env):
    def damage(tables):
        sd, _ = camera_record(tables, "CAM_FRONT")
        lidar = first(tables["sample_data"], sample_token=sd["sample_token"], fileformat="pcd")
        first(tables["ego_pose"], token=lidar["ego_pose_token"])["translation"][0] = float("nan")

    root = env.shadow_world(damage)
    env.error(r"ego.?pose.*(NaN|finite)", "evaluate", env.yaml, f"data.dataroot={root}", "--checkpoint", env.ckpt,
              "--out", env.tmp / "eval")


def _av2_copy(env: Env) -> tuple[Path, Path]:
    """A private copy of the tiny AV2 world and the folder of its first train log."""
    root = env.tmp / "av2"
    shutil.copytree(env.request.getfixturevalue("av2_world"), root)
    return root, sorted((root / "train").iterdir())[0]


def _av2_error(env: Env, root: Path, pattern: str) -> str:
    return env.error(pattern, "show-gt", env.yaml, "data.dataset=av2", "data.splits_file=null",
                     "data.av2_frame_step=1",
                     "data.image_fit=contain", f"data.dataroot={root}", "--split", "train", "--index", "0",
                     "--out", env.tmp / "show")


def _edit_feather(path: Path, column: str, row: int, value: float) -> None:
    import pyarrow as pa
    from pyarrow import feather

    table = feather.read_table(str(path))
    values = table.column(column).to_pylist()
    values[row] = value
    feather.write_feather(table.set_column(table.column_names.index(column), column, pa.array(values)), str(path))


@row("2", "AV2: a camera calibration with NaN is named")
def row_av2_nan_calibration(env):
    root, log = _av2_copy(env)
    _edit_feather(log / "calibration" / "egovehicle_SE3_sensor.feather", "tx_m", 0, float("nan"))
    _av2_error(env, root, rf"log {log.name}: .*egovehicle_SE3_sensor\.feather.*(NaN|finite)")


@row("2", "AV2: an intrinsics row with a negative focal length is named")
def row_av2_negative_focal_length(env):
    root, log = _av2_copy(env)
    _edit_feather(log / "calibration" / "intrinsics.feather", "fx_px", 2, -100.0)
    _av2_error(env, root, rf"log {log.name}: camera \w+ in .*intrinsics\.feather.*focal")


@row("2", "AV2: an ego pose with NaN is named")
def row_av2_nan_ego_pose(env):
    root, log = _av2_copy(env)
    _edit_feather(log / "city_SE3_egovehicle.feather", "ty_m", 0, float("nan"))
    _av2_error(env, root, rf"log {log.name}: the ego pose .*city_SE3_egovehicle\.feather.*(NaN|finite)")


@row("10", "AV2: a missing camera folder is named as such, not blamed on timestamps")
def row_av2_missing_camera_folder(env):
    root, log = _av2_copy(env)
    shutil.rmtree(log / "sensors" / "cameras" / "ring_side_left")
    line = _av2_error(env, root, r"camera folder .*ring_side_left does not exist")
    assert "timestamps" not in line


def _flip_bits(path: Path, entry: str) -> None:
    """Flip the exponent bits of the first float stored in ``entry`` of a zip checkpoint."""
    with zipfile.ZipFile(path) as z:
        info = z.getinfo(entry)
    data = bytearray(path.read_bytes())
    name_len, extra_len = int.from_bytes(data[info.header_offset + 26:info.header_offset + 28], "little"), \
        int.from_bytes(data[info.header_offset + 28:info.header_offset + 30], "little")
    start = info.header_offset + 30 + name_len + extra_len
    data[start + 3] ^= 0x7F  # float32 little-endian: the byte with the sign and most of the exponent
    path.write_bytes(bytes(data))


@row("3", "a checkpoint with flipped bits is named by the zip CRC")
def row_flipped_bits(env):
    path = env.tmp / "flipped.pt"
    shutil.copy(env.ckpt, path)
    with zipfile.ZipFile(path) as z:
        entry = next(n for n in z.namelist() if "/data/" in n and z.getinfo(n).file_size >= 64)
    _flip_bits(path, entry)
    with pytest.raises(CheckpointError, match=rf"flipped\.pt.*{re.escape(entry.split('/', 1)[1])}.*(CRC|damaged)"):
        load_checkpoint(path)
    env.error(r"flipped\.pt.*(CRC|damaged)", "evaluate", env.yaml, "--checkpoint", path, "--out", env.tmp / "e")


@row("3", "a checkpoint with non-finite weights is named with the tensor")
def row_nonfinite_weights(env):
    state = load_checkpoint(env.ckpt)
    key = next(k for k, v in state["model"].items() if v.is_floating_point() and v.numel() > 4)
    state["model"][key][3] = float("nan")
    path = save_checkpoint(state, env.tmp / "nan.pt")
    env.error(rf"nan\.pt.*{re.escape(key)}.*(NaN|non-finite)", "evaluate", env.yaml, "--checkpoint", path,
              "--out", env.tmp / "e")


for _name, _override, _key in (
    ("sinkhorn_iters_0", "model.gnn.sinkhorn_iters=0", "model.gnn.sinkhorn_iters"),
    ("batch_size_0", "train.batch_size=0", "train.batch_size"),
    ("checkpoint_every_negative", "train.checkpoint_every=-5", "train.checkpoint_every"),
):
    def _run(env, override=_override, key=_key):
        forbid(env, "instagram_hdmap.train.train_one_epoch", "training")
        env.error(rf"'{re.escape(key)}'.*(>= ?[01]|in \[[01], )", "train", env.yaml, override,
                  f"train.out_dir={env.tmp / 'r'}")

    ROWS.append(Row(_name, "4", f"config: {_override}", _run))


@row("4", "a YAML section written twice is an error, not silently merged")
def row_duplicate_yaml_section(env):
    path = env.tmp / "twice.yaml"
    path.write_text(f"_base_: {env.yaml}\nmodel:\n  gnn:\n    layers: 3\ntrain:\n  lr: 0.01\nmodel:\n  gnn:\n"
                    "    dim: 64\n")
    env.error(r"twice\.yaml.*'model'.*(twice|duplicate)", "model-summary", path)


@row("4", "data.classes with unknown names")
def row_unknown_class_names(env):
    env.error(r"data\.classes.*divider.*ped_crossing.*boundary", "model-summary", env.yaml,
              "data.classes=[lane,crossing,kerb]")


@row("5", "--force starts over: the old run's log.jsonl lines and TensorBoard events go")
def row_force_clears_the_old_log(env):
    run = env.tmp / "run"
    _toy_run(env, [0.2, 0.3], "train.epochs=2")
    old_events = sorted((run / "tb").rglob("events.*"))
    assert len(old_events) == 1 and len((run / "log.jsonl").read_text().splitlines()) == 2
    _toy_run(env, [0.1], "train.epochs=1", force=True)
    lines = (run / "log.jsonl").read_text().splitlines()
    assert len(lines) == 1 and json.loads(lines[0])["val"]["metrics"]["mAP"] == 0.1
    events = sorted((run / "tb").rglob("events.*"))
    assert len(events) == 1 and events != old_events
    assert load_checkpoint(run / "best.pt")["metrics"]["mAP"] == 0.1  # not the old run's 0.3


# ==================================================================================================
# Crashes instead of a message
# ==================================================================================================


def _break_image(root: Path, tables_root: Path, sample_index: int, channel: str, how: str) -> Path:
    tables = {p.stem: json.loads(p.read_text()) for p in (tables_root / "v1.0-trainval").glob("*.json")}
    sd, _ = camera_record(tables, channel, sample_index)
    path = root / sd["filename"]
    if how == "missing":
        path.unlink()
    elif how == "truncated":
        path.write_bytes(path.read_bytes()[:500])
    else:
        path.write_bytes(b"\xff\xd8 this is not a JPEG " * 40 + b"\xff\xd9")
    return path


@row("6", "data.on_bad_sample=skip with eval batch > 1: each good sample scored once, exit 0")
def row_skip_mode_batch(env):
    root = env.shadow_world(copy_samples=True)
    _break_image(root, root, 0, "CAM_FRONT", "missing")
    rc, out, err = env.cli("evaluate", env.yaml, f"data.dataroot={root}", "data.on_bad_sample=skip",
                           "eval.batch_size=3", "--checkpoint", env.ckpt, "--out", env.tmp / "eval")
    assert rc == 0, err[-3000:]
    metrics = json.loads((env.tmp / "eval" / "metrics.json").read_text())
    assert metrics["counters"]["samples"] == 2  # the bad one is left out, its replacement not scored twice
    assert "2 samples evaluated" in out and re.search(r"1 bad sample", out)
    submission = json.loads((env.tmp / "eval" / "submission.json").read_text())
    assert len(submission["results"]) == 2


@row("S4", "a temporal model with data.on_bad_sample=skip and a bad frame: the frame counts as a missing one (was: "
          "its stand-in came twice and the stream stopped with a frame-order error, exit 2)")
def row_skip_mode_temporal(env):
    from instagram_hdmap.models import build_model

    root = env.shadow_world(copy_samples=True)
    _break_image(root, root, 0, "CAM_FRONT", "missing")  # the first frame of the validation scene
    temporal = ["model.temporal.memory=bev", "model.gnn.sinkhorn_iters=3"]
    torch.manual_seed(0)
    cfg = env.cfg(*temporal)
    ckpt = save_checkpoint({"model": build_model(cfg).state_dict(), "config": config_to_dict(cfg)},
                           env.tmp / "temporal.pt")
    rc, out, err = env.cli("evaluate", env.yaml, f"data.dataroot={root}", "data.on_bad_sample=skip", *temporal,
                           "--checkpoint", ckpt, "--out", env.tmp / "eval")
    assert rc == 0, err[-3000:]
    metrics = json.loads((env.tmp / "eval" / "metrics.json").read_text())
    assert metrics["counters"]["samples"] == 2 and re.search(r"1 bad sample", out)
    # the bad frame is a missing one; the stand-in is not fused, and the next frame starts a new memory
    memory = metrics["memory"]
    assert memory["memory_missing_frame"] == 1 and memory["memory_fused"] == 1, memory


@row("S4", "the temporary file of an export-onnx killed mid-write (kill -9) is removed by the next export to that path")
def row_killed_export_leaves_no_temporary(env):
    pytest.importorskip("onnxruntime", reason="the [deploy] extra is not installed")
    from instagram_hdmap.deploy import export_onnx
    from instagram_hdmap.models import build_model

    out = env.tmp / "model.onnx"
    stale = out.with_name(f".model.onnx.tmp-{dead_pid()}")
    stale.write_bytes(b"half an ONNX file")
    cfg = env.cfg("model.gnn.sinkhorn_iters=3")
    torch.manual_seed(0)
    export_onnx(build_model(cfg).eval(), cfg, out)
    assert out.is_file() and not stale.exists()
    assert [p.name for p in env.tmp.iterdir() if p.name.startswith(".")] == []


@row("S4", "Mapper: a ground_height of 50 (millimetres, or a height above sea level) is a RigError (the IPM plane "
          "was put 50 m under the cameras: exit 0)")
def row_mapper_ground_height_out_of_range(env):
    from instagram_hdmap import Frame
    from instagram_hdmap.data.rig import RigError

    mapper, images, K, poses = _mapper_frame(env)
    for height in (50.0, -350.0):
        with pytest.raises(RigError, match=r"ground_height is the road's height in the ego frame, within 5 m"):
            mapper(Frame(images=images, intrinsics=K, cam_to_ego=poses, ground_height=height))
    assert isinstance(mapper(Frame(images=images, intrinsics=K, cam_to_ego=poses, ground_height=-0.35)), list)  # AV2


@row("S4", "predict/evaluate take data.image_fit from the checkpoint, with a note when the CONFIG differs (images were "
          "fitted unlike in training without a word)")
def row_checkpoint_image_fit(env):
    from instagram_hdmap.inference import inference_config

    trained = load_config(TINY_YAML, ["data.image_fit=contain"])
    out, notes = inference_config(load_config(TINY_YAML), config_to_dict(trained))
    assert out.data.image_fit == "contain"
    assert any("data.image_fit='contain' (CONFIG: 'cover')" in n for n in notes), notes
    out, notes = inference_config(load_config(TINY_YAML, ["data.image_fit=stretch"]), config_to_dict(trained),
                                  ["data.image_fit=stretch"])  # the command line wins, and says so
    assert out.data.image_fit == "stretch" and any("data.image_fit='contain' with 'stretch'" in n for n in notes)


@row("S4", "predict --index of a temporal model says where its memory comes from (ran silently)")
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


@row("S4", "evaluate: a flicker of nan (no element seen in two consecutive frames: one-frame scenes) is explained")
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


@row("S4", "a checkpoint whose config is YAML text (older writers) is read as its config (the note said it held none "
          "and built the model from the CONFIG file)")
def row_checkpoint_config_as_yaml_text(env):
    import yaml

    state = load_checkpoint(env.ckpt)
    text = save_checkpoint({**state, "config": yaml.safe_dump(state["config"])}, env.tmp / "yaml_config.pt")
    assert load_checkpoint(text)["config"] == state["config"]
    rc, out, err = env.cli("evaluate", env.yaml, "--checkpoint", text, "--out", env.tmp / "e")
    assert rc == 0 and "holds no config" not in out + err, (out + err)[-2000:]
    junk = save_checkpoint({**state, "config": "- just\n- a list\n"}, env.tmp / "junk_config.pt")
    env.error(r"junk_config\.pt: its config is text that is not a YAML mapping", "evaluate", env.yaml,
              "--checkpoint", junk, "--out", env.tmp / "e2")


@row("S5", "Mapper: ego -> camera poses given as cam_to_ego (the inverses) are named: a surround camera is not rolled "
          "on its side (the sweep left it: accepted, a map from the wrong rays, exit 0)")
def row_mapper_ego_to_camera_poses(env):
    from instagram_hdmap import Frame
    from instagram_hdmap.data.rig import RigError

    mapper, images, K, poses = _mapper_frame(env)
    inverse = {c: np.linalg.inv(T) for c, T in poses.items()}
    with pytest.raises(RigError, match=r"camera CAM_FRONT(_LEFT)?: .cam_to_ego.: the camera is (rolled \d+ degrees|"
                                       r"upside down).*camera -> ego rotation \(not ego -> camera"):
        mapper(Frame(images=images, intrinsics=K, cam_to_ego=inverse))
    assert isinstance(mapper(Frame(images=images, intrinsics=K, cam_to_ego=poses)), list)  # the published rig


@row("7", "a 0-byte .pt is named as empty")
def row_empty_checkpoint(env):
    path = env.tmp / "empty.pt"
    path.write_bytes(b"")
    env.error(r"empty\.pt.*empty", "evaluate", env.yaml, "--checkpoint", path, "--out", env.tmp / "e")


@row("8", "a sample_data record without 'filename' is named")
def row_sample_data_without_filename(env):
    def damage(tables):
        sd, _ = camera_record(tables, "CAM_BACK")
        del sd["filename"]

    root = env.shadow_world(damage)
    env.error(r"sample_data.*'filename'", "evaluate", env.yaml, f"data.dataroot={root}", "--checkpoint", env.ckpt,
              "--out", env.tmp / "e")


@row("8", "a binary file given as the config (checkpoint and config swapped)")
def row_config_and_checkpoint_swapped(env):
    env.error(r"random\.pt.*(binary|not a text|checkpoint)", "evaluate", env.ckpt, "--checkpoint", env.yaml,
              "--out", env.tmp / "e")


@row("8", "a YAML config given as the checkpoint")
def row_yaml_as_checkpoint(env):
    env.error(r"tiny_world\.yaml.*not a (PyTorch )?checkpoint", "evaluate", env.yaml, "--checkpoint", env.yaml,
              "--out", env.tmp / "e")


@row("8", "grid.resolution=.nan")
def row_nan_resolution(env):
    env.error(r"grid\.resolution.*(finite|NaN)", "model-summary", env.yaml, "grid.resolution=.nan")


@row("8", "evaluate-json --resolution 0")
def row_evaluate_json_resolution_0(env):
    gt = env.tmp / "gt.json"
    gt.write_text(json.dumps({"results": {"a": [{"pts": [[0, 0], [1, 1]], "type": 0}]}}))
    pred = env.tmp / "pred.json"
    pred.write_text(json.dumps({"results": {"a": [{"pts": [[0, 0], [1, 1]], "type": 0, "confidence_level": 0.5}]}}))
    env.error(r"--resolution.*> ?0", "evaluate-json", "--pred", pred, "--gt", gt, "--protocol", "raster",
              "--resolution", "0")


@row("8", "synth --seed -1")
def row_synth_negative_seed(env):
    env.error(r"--seed -1", "synth", "--out", env.tmp / "w", "--seed", "-1", "--scenes-train", "1",
              "--scenes-val", "0", "--samples-per-scene", "1", "--image-size", "160x90")
    assert not (env.tmp / "w").exists()


for _override, _key in (("train.lr=.nan", "train.lr"), ("train.lr=-1", "train.lr"),
                        ("train.epochs=0", "train.epochs"), ("train.epochs=-2", "train.epochs"),
                        ("data.num_workers=-1", "data.num_workers"), ("eval.batch_size=0", "eval.batch_size")):
    def _run(env, override=_override, key=_key):
        forbid(env, "instagram_hdmap.train.train_one_epoch", "training")
        env.error(rf"'{re.escape(key)}'", "train", env.yaml, override, f"train.out_dir={env.tmp / 'r'}")

    ROWS.append(Row(_override.replace(".", "_").replace("=", "_"), "9", f"config: {_override}", _run))


def _worker_image_row(how: str):
    def run(env):
        root = env.shadow_world(copy_samples=True)
        path = _break_image(root, root, 1, "CAM_BACK_RIGHT", how)
        line = env.error(rf"{re.escape(path.name)}", "evaluate", env.yaml, f"data.dataroot={root}",
                         "data.num_workers=1", "--checkpoint", env.ckpt, "--out", env.tmp / "e")
        assert "worker" not in line.lower()

    return run


for _how in ("missing", "truncated", "undecodable"):
    ROWS.append(Row(f"{_how}_image_with_a_worker", "10", f"a {_how} image with data.num_workers=1: one line",
                    _worker_image_row(_how)))


@row("S", "a checkpoint whose 'model' is not a state dict is named (was a TypeError)")
def row_model_not_a_state_dict(env):
    path = env.tmp / "list.pt"
    torch.save({"model": [1, 2], "config": {}}, path)
    env.error(r"list\.pt holds no 'model' state dict", "evaluate", env.yaml, "--checkpoint", path,
              "--out", env.tmp / "e")


@row("S", "--resume from a weights-only checkpoint is named (was a KeyError)")
def row_resume_from_weights_only(env):
    path = env.tmp / "weights.pt"
    save_checkpoint({"model": load_checkpoint(env.ckpt)["model"]}, path)
    forbid(env, "instagram_hdmap.train.train_one_epoch", "training")
    env.error(r"weights\.pt cannot be resumed: it holds no optimizer, epoch, step, step_in_epoch, rng, config",
              "train", env.yaml, f"train.out_dir={env.tmp / 'r'}", "--resume", path)


@row("S", "model.backbone.weights that is not a torch file: one line, not torch's multi-line text")
def row_backbone_weights_not_a_checkpoint(env):
    env.error(r"model\.backbone\.weights: cannot read .*tiny_world\.yaml as a torch checkpoint", "train", env.yaml,
              "model.backbone.name=efficientnet-b0", "data.image_size=[64,160]", f"model.backbone.weights={env.yaml}",
              f"train.out_dir={env.tmp / 'r'}")


# ==================================================================================================
# Too late or misleading
# ==================================================================================================


@row("11", "evaluate --out that is a file: refused before the evaluation runs")
def row_evaluate_out_is_a_file(env):
    (env.tmp / "taken").write_text("x")
    forbid(env, "instagram_hdmap.predict.evaluate", "the evaluation")
    env.error(r"taken", "evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "taken")


@row("11", "train.out_dir that is a file: refused before training")
def row_train_out_dir_is_a_file(env):
    (env.tmp / "taken").write_text("x")
    forbid(env, "instagram_hdmap.train.train_one_epoch", "training")
    env.error(r"taken", "train", env.yaml, f"train.out_dir={env.tmp / 'taken'}")


@row("11", "predict --out below a file: refused before the model runs")
def row_predict_out_not_writable(env):
    (env.tmp / "taken").write_text("x")
    forbid(env, "instagram_hdmap.predict.save_figure", "drawing")
    env.error(r"taken", "predict", env.yaml, "--checkpoint", env.ckpt, "--index", "0", "--out",
              env.tmp / "taken" / "pics")


@row("11", "export-gt --out below a file: refused before the export")
def row_export_gt_out_not_writable(env):
    (env.tmp / "taken").write_text("x")
    forbid(env, "instagram_hdmap.cli.gt_submission", "the export")
    env.error(r"taken", "export-gt", env.yaml, "--out", env.tmp / "taken" / "gt.json")


@row("11", "evaluate-json --out below a file: refused before the evaluation")
def row_evaluate_json_out_not_writable(env):
    (env.tmp / "taken").write_text("x")
    gt = env.tmp / "gt.json"
    gt.write_text(json.dumps({"results": {"a": [{"pts": [[0, 0], [1, 1]], "type": 0}]}}))
    forbid(env, "instagram_hdmap.evaluation.Evaluator.compute", "the evaluation")
    env.error(r"taken", "evaluate-json", "--pred", gt, "--gt", gt, "--out", env.tmp / "taken" / "m.json")


@row("S", "export-gt --out that is a folder: refused before the export (was an IsADirectoryError after it)")
def row_export_gt_out_is_a_folder(env):
    (env.tmp / "folder").mkdir()
    forbid(env, "instagram_hdmap.cli.gt_submission", "the export")
    env.error(r"--out .*folder.*is a folder", "export-gt", env.yaml, "--out", env.tmp / "folder")


@row("S", "evaluate-json --out that is a folder: refused before the evaluation (was an IsADirectoryError)")
def row_evaluate_json_out_is_a_folder(env):
    (env.tmp / "folder").mkdir()
    gt = _submission(env.tmp / "gt.json", {"a": [{"pts": [[0, 0], [1, 1]], "type": 0}]}, True)
    forbid(env, "instagram_hdmap.evaluation.Evaluator.compute", "the evaluation")
    env.error(r"--out .*folder.*is a folder", "evaluate-json", "--pred", gt, "--gt", gt, "--out", env.tmp / "folder")


@row("S", "train --force --resume: refused, the checkpoint to resume is not deleted")
def row_force_and_resume(env):
    run = env.tmp / "run"
    _toy_run(env, [0.2], "train.epochs=2", "train.max_steps=1")
    before = (run / "last.pt").read_bytes()
    env.error(r"--force.*--resume", "train", env.yaml, f"train.out_dir={run}", "--force", "--resume", run / "last.pt")
    assert (run / "last.pt").read_bytes() == before


@row("S", "--resume of a finished run with more train.epochs is named, not a silent exit 0")
def row_resume_a_finished_schedule(env):
    run = env.tmp / "run"
    _toy_run(env, [0.2], "train.epochs=1")
    with pytest.raises(UserError, match=r"last\.pt .*completed its schedule.*train\.epochs"):
        _toy_run(env, [], "train.epochs=3", resume=str(run / "last.pt"))


@row("12", "a run killed before its first checkpoint can be run again")
def row_rerun_before_first_checkpoint(env):
    run = env.tmp / "run"
    (run / "tb").mkdir(parents=True)
    (run / "config.yaml").write_text("name: killed\n")
    (run / "log.jsonl").write_text("")
    (run / "tb" / "events.out.tfevents.1.host.1.0").write_bytes(b"old")
    env.error(r"last\.pt.*(no checkpoint|before its first checkpoint).*without --resume", "train", env.yaml,
              f"train.out_dir={run}", "--resume", run / "last.pt")
    _toy_run(env, [0.2], "train.epochs=1")
    assert (run / "last.pt").is_file() and not (run / "tb" / "events.out.tfevents.1.host.1.0").exists()


@row("12", "a full disk during a checkpoint save is named (and the old checkpoint kept)")
def row_full_disk(env):
    old = save_checkpoint({"model": {"w": torch.ones(3)}}, env.tmp / "last.pt")
    code = (
        "import resource, signal, torch, sys\n"
        "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (100_000, 100_000))\n"
        "from instagram_hdmap.checkpoint import save_checkpoint\n"
        "from instagram_hdmap.config import UserError\n"
        "try:\n"
        f"    save_checkpoint({{'model': {{'w': torch.zeros(200_000)}}}}, {str(old)!r})\n"
        "except UserError as e:\n"
        "    print('USER', e); sys.exit(2)\n"
    )
    env_vars = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env_vars, timeout=120)
    assert p.returncode == 2, p.stderr[-2000:]
    assert re.search(r"USER .*last\.pt.*(disk|space|too large)", p.stdout), p.stdout
    assert torch.equal(load_checkpoint(old)["model"]["w"], torch.ones(3))
    assert sorted(x.name for x in env.tmp.iterdir()) == ["last.pt"]


@row("12", "a full disk while writing a JSON result is named (and the old file kept)")
def row_full_disk_json(env):
    old = env.tmp / "metrics.json"
    old.write_text('{"old": 1}')
    code = (
        "import resource, signal, sys\n"
        "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (100_000, 100_000))\n"
        "from instagram_hdmap.files import write_json\n"
        "from instagram_hdmap.config import UserError\n"
        "try:\n"
        f"    write_json({{'x': 'a' * 200_000}}, {str(old)!r})\n"
        "except UserError as e:\n"
        "    print('USER', e); sys.exit(2)\n"
    )
    env_vars = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env_vars, timeout=120)
    assert p.returncode == 2, p.stderr[-2000:]
    assert re.search(r"USER cannot write .*metrics\.json: File too large \(the disk is full", p.stdout), p.stdout
    assert old.read_text() == '{"old": 1}' and sorted(x.name for x in env.tmp.iterdir()) == ["metrics.json"]


@row("S", "a full disk outside the atomic writes (a training's log line) is one line, not a traceback")
def row_full_disk_in_a_log_write(env):
    import errno

    from instagram_hdmap.train import TrainingRun

    def full(self):
        raise OSError(errno.ENOSPC, "No space left on device", str(self.out_dir / "log.jsonl"))

    env.monkeypatch.setattr(TrainingRun, "log", full)
    env.error(r"No space left on device writing .*log\.jsonl: the disk is full", "train", env.yaml,
              f"train.out_dir={env.tmp / 'run'}", "train.max_steps=1")


@row("12", "data.dt_clip=0 is named (not a NaN loss blamed on the learning rate)")
def row_dt_clip_0(env):
    env.error(r"data\.dt_clip.*> ?0", "train", env.yaml, "data.dt_clip=0", f"train.out_dir={env.tmp / 'r'}")


@row("13", "partial checkpoints of killed saves are removed by the next run in that folder")
def row_stale_checkpoint_temporaries(env):
    run = env.tmp / "run"
    _toy_run(env, [0.2], "train.epochs=2", "train.max_steps=1")
    dead, alive = dead_pid(), os.getppid()
    for name in (f".last.pt.tmp-{dead}", f".best.pt.tmp-{dead}", f".last.pt.tmp-{alive}"):
        (run / name).write_bytes(b"partial")
    _toy_run(env, [0.1, 0.1], "train.epochs=2", resume=str(run / "last.pt"))
    left = sorted(p.name for p in run.iterdir() if p.name.startswith("."))
    assert left == [f".last.pt.tmp-{alive}"]  # another live process's file is not ours to remove


@row("13", "temporary folders of killed world generations are removed by the next one")
def row_stale_synth_temporaries(env):
    from instagram_hdmap.data.synthetic import generate_world

    dead, alive = dead_pid(), os.getppid()
    for pid in (dead, alive):
        (env.tmp / f".w.synth-tmp-{pid}" / "samples").mkdir(parents=True)
    generate_world(env.tmp / "w", scenes_train=1, scenes_val=0, samples_per_scene=1, image_size="160x90",
                   progress=False)
    left = sorted(p.name for p in env.tmp.iterdir() if p.name.startswith("."))
    assert left == [f".w.synth-tmp-{alive}"]


def _submission(path: Path, vectors: dict, gt: bool) -> Path:
    path.write_text(json.dumps({"meta": {"ground_truth": gt}, "results": vectors}))
    return path


@row("14", "evaluate-json: a confidence outside [0, 1] is named")
def row_confidence_out_of_range(env):
    gt = _submission(env.tmp / "gt.json", {"a": [{"pts": [[0, 0], [1, 1]], "type": 0}]}, True)
    pred = _submission(env.tmp / "p.json", {"a": [{"pts": [[0, 0], [1, 1]], "type": 0, "confidence_level": 3.5}]},
                       False)
    env.error(r"p\.json.*'a'.*vector 0.*confidence_level.*\[0, 1\]", "evaluate-json", "--pred", pred, "--gt", gt)


@row("14", "evaluate-json: coordinates of 1e308 are named")
def row_huge_coordinates(env):
    gt = _submission(env.tmp / "gt.json", {"a": [{"pts": [[0, 0], [1, 1]], "type": 0}]}, True)
    pred = _submission(env.tmp / "p.json", {"a": [{"pts": [[0, 0], [1e308, 1]], "type": 0, "confidence_level": 0.5}]},
                       False)
    env.error(r"p\.json.*'a'.*vector 0.*pts.*(metres|ego)", "evaluate-json", "--pred", pred, "--gt", gt)


@row("14", "evaluate-json: prediction and GT files swapped")
def row_swapped_submission_files(env):
    gt = _submission(env.tmp / "gt.json", {"a": [{"pts": [[0, 0], [1, 1]], "type": 0}]}, True)
    pred = _submission(env.tmp / "p.json", {"a": [{"pts": [[0, 0], [1, 1]], "type": 0, "confidence_level": 0.5}]},
                       False)
    env.error(r"swapped", "evaluate-json", "--pred", gt, "--gt", pred)


@row("15", "a malicious checkpoint: torch's reason for refusing it is kept whole")
def row_malicious_checkpoint(env):
    path = env.tmp / "evil.pt"
    torch.save({"model": {}, "payload": print}, path)  # any callable global: refused by weights_only
    line = env.error(r"evil\.pt.*weights_only", "evaluate", env.yaml, "--checkpoint", path, "--out", env.tmp / "e")
    assert re.search(r"reason: .*Unsupported global: GLOBAL (builtins\.)?print was not an allowed global", line), line


# ==================================================================================================
# The second sweep (S2): cases found by a sweep of the same kind after the fixes above
# ==================================================================================================


@row("S2", "an override quoted as a string stays a string (name=\"2024\" was read as the float 2024.0)")
def row_quoted_override_is_a_string(env):
    assert load_config(env.yaml, ['name="2024"']).name == "2024"
    assert load_config(env.yaml, ["train.lr=1e-3"]).train.lr == 0.001  # unquoted: still a number


@row("S2", "an empty value (train.out_dir=$UNSET) is named, not a training into the working directory")
def row_empty_string_value(env):
    forbid(env, "instagram_hdmap.train.train_one_epoch", "training")
    env.error(r"'train\.out_dir' is empty", "train", env.yaml, "train.out_dir=")
    assert sorted(p.name for p in env.tmp.iterdir()) == []


@row("S2", "out of memory (torch's CPU allocator, CUDA, numpy) is one line naming the sizes to lower")
def row_out_of_memory(env):
    for error in (RuntimeError("[enforce fail at alloc_cpu.cpp:127] err == 0. DefaultCPUAllocator: can't allocate "
                               "memory: you tried to allocate 4096000064 bytes. Error code 12"),
                  torch.OutOfMemoryError("CUDA out of memory. Tried to allocate 2.00 GiB.\nSee documentation"),
                  MemoryError("Unable to allocate 49.1 TiB for an array with shape (3, 3000000, 6000000)")):
        def boom(*args, error=error, **kwargs):
            raise error

        env.monkeypatch.setattr("instagram_hdmap.cli.summarize_parameters", boom)
        env.error(r"out of memory .*train\.batch_size", "model-summary", env.yaml)


def _table_row(edit: Callable[[dict], None], pattern: str):
    def run(env):
        root = env.shadow_world(edit)
        env.error(pattern, "evaluate", env.yaml, f"data.dataroot={root}", "--checkpoint", env.ckpt,
                  "--out", env.tmp / "e")

    return run


for _name, _edit, _pattern in (
    ("table_not_a_list", lambda t: t.__setitem__("sample", {"a": 1}), r"sample\.json holds a JSON dict"),
    ("table_records_not_objects", lambda t: t.__setitem__("calibrated_sensor", [[1, 2]]),
     r"calibrated_sensor\.json: record 0 is not an object"),
    ("empty_map_table", lambda t: t.__setitem__("map", []), r"map\.json holds no records"),
    ("dangling_first_sample_token", lambda t: t["scene"][-1].__setitem__("first_sample_token", "deadbeef"),
     r"sample\.json .* has no record deadbeef"),
    ("looping_sample_chain",  # was walked forever
     lambda t: first(t["sample"], token=t["scene"][-1]["last_sample_token"]).__setitem__(
         "next", t["scene"][-1]["first_sample_token"]),
     r"scene .*'next' links loop back"),
):
    ROWS.append(Row(_name, "S2", f"nuScenes tables: {_name} (was a raw crash or a hang)", _table_row(_edit, _pattern)))


@row("S2", "synth-preview of an AV2-layout world is named (was a KeyError)")
def row_synth_preview_av2_world(env):
    world = env.request.getfixturevalue("av2_world")
    env.error(r"Argoverse 2 layout.*show-gt", "synth-preview", world, "--out", env.tmp / "p.png")
    assert not (env.tmp / "p.png").exists()


@row("S2", "an output path that is one of the job's inputs is refused before the work (was overwritten)")
def row_output_is_an_input(env):
    gt = _submission(env.tmp / "gt.json", {"a": [{"pts": [[0, 0], [1, 1]], "type": 0}]}, True)
    pred = _submission(env.tmp / "p.json", {"a": [{"pts": [[0, 0], [1, 1]], "type": 0, "confidence_level": 0.5}]},
                       False)
    before = gt.read_bytes()
    env.error(r"--out .*gt\.json is the --gt file", "evaluate-json", "--pred", pred, "--gt", gt, "--out", gt)
    assert gt.read_bytes() == before
    config = env.tmp / "cfg.yaml"
    shutil.copy(env.yaml, config)
    env.error(r"--out .*cfg\.yaml is the CONFIG file", "export-gt", config, "--out", config)
    ckpt = env.tmp / "model.pt"
    shutil.copy(env.ckpt, ckpt)
    forbid(env, "instagram_hdmap.deploy.export_onnx", "the export")
    env.error(r"--out .*model\.pt is the --checkpoint file", "export-onnx", env.yaml, "--checkpoint", ckpt,
              "--out", ckpt)
    assert ckpt.read_bytes() == env.ckpt.read_bytes()


def _mapper_frame(env, image_size=(400, 225), intrinsics_size=None):
    """A Mapper of the random tiny checkpoint and one frame of the published nuScenes rig: uint8 images of
    ``image_size`` (w, h), intrinsics for images of ``intrinsics_size`` (default: the same)."""
    from instagram_hdmap import Mapper
    from instagram_hdmap.data.rig import rig

    mapper = Mapper.from_checkpoint(env.ckpt, device="cpu")
    sensors = rig(intrinsics_size or image_size)
    rng = np.random.default_rng(0)
    images = {c: rng.integers(0, 256, (image_size[1], image_size[0], 3), dtype=np.uint8) for c in mapper.cameras}
    poses = {c: np.vstack([np.c_[sensors[c].rot, sensors[c].trans], [0, 0, 0, 1]]) for c in mapper.cameras}
    return mapper, images, {c: sensors[c].intrinsic for c in mapper.cameras}, poses


@row("S2", "Mapper: a float image on 0..255, with NaN, or normalised already is named (was silently wrong)")
def row_mapper_float_images(env):
    from instagram_hdmap.data.rig import RigError

    mapper, images, K, poses = _mapper_frame(env)
    mapper(images={c: v.astype(np.float32) / 255 for c, v in images.items()}, intrinsics=K, cam_to_ego=poses)  # fine
    for image in (images["CAM_FRONT"].astype(np.float32),  # 0..255
                  np.full(images["CAM_FRONT"].shape, np.nan, np.float32),
                  (images["CAM_FRONT"] / 255.0 - 0.45) / 0.225,  # normalised already
                  torch.from_numpy(images["CAM_FRONT"]).permute(2, 0, 1).float()):  # a tensor on 0..255
        with pytest.raises(RigError, match=r"camera CAM_FRONT: .*(0\.\.1|NaN)"):
            mapper(images={**images, "CAM_FRONT": image}, intrinsics=K, cam_to_ego=poses)


@row("S2", "Mapper: intrinsics of another image size, transposed, or a camera 1700 m away is named (was silent)")
def row_mapper_calibration_mistakes(env):
    from instagram_hdmap.data.rig import RigError

    mapper, images, K, poses = _mapper_frame(env, intrinsics_size=(1600, 900))  # K of the full-size images
    with pytest.raises(RigError, match=r"camera CAM_FRONT_LEFT: 'intrinsics' put the principal point .* outside its "
                                       r"400x225 image"):
        mapper(images=images, intrinsics=K, cam_to_ego=poses)
    mapper, images, K, poses = _mapper_frame(env)
    with pytest.raises(RigError, match=r"camera CAM_FRONT: 'intrinsics' is not a pinhole matrix .*transposed"):
        mapper(images=images, intrinsics={**K, "CAM_FRONT": K["CAM_FRONT"].T}, cam_to_ego=poses)
    mm = poses["CAM_BACK"].copy()
    mm[:3, 3] *= 1000
    with pytest.raises(RigError, match=r"camera CAM_BACK: 'translation' .* m from the ego origin"):
        mapper(images=images, intrinsics=K, cam_to_ego={**poses, "CAM_BACK": mm})


@row("S2", "Mapper: an ego_pose whose rotation is not one is named (a temporal model would warp by it)")
def row_mapper_ego_pose_not_rigid(env):
    from instagram_hdmap import Frame
    from instagram_hdmap.data.rig import RigError

    mapper, images, K, poses = _mapper_frame(env)
    pose = np.eye(4)
    pose[:3, :3] *= 2
    with pytest.raises(RigError, match=r"ego_pose has a rotation part that is not a rotation"):
        mapper(Frame(images=images, intrinsics=K, cam_to_ego=poses, ego_pose=pose))


def _rig_files(env, edit: Callable[[dict], None] | None = None) -> tuple[Path, list[Path]]:
    """A rig file of the published nuScenes rig (400 x 225 images) and one JPEG per camera, ``edit``ed."""
    from PIL import Image

    from instagram_hdmap.data.rig import CAMERAS, rig

    sensors = rig((400, 225))
    cameras = {c: {"intrinsics": sensors[c].intrinsic.tolist(), "quaternion": list(sensors[c].rotation),
                   "translation": list(sensors[c].translation)} for c in CAMERAS}
    data = {"image_size": [400, 225], "cameras": cameras}
    if edit is not None:
        edit(data)
    path = env.tmp / "rig.json"
    path.write_text(json.dumps(data))
    images = []
    for k, c in enumerate(CAMERAS):
        images.append(env.tmp / f"{c}.jpg")
        texture = (np.arange(400, dtype=np.uint8) % 16)[None, :, None]  # not blank: a blank frame may repeat
        Image.fromarray(np.full((225, 400, 3), 40 * k, np.uint8) + texture).save(images[-1])
    return path, images


def _rig_row(edit, pattern: str, *extra):
    def run(env):
        path, images = _rig_files(env, edit)
        forbid(env, "instagram_hdmap.predict.save_figure", "drawing")
        env.error(pattern, "predict-images", "--checkpoint", env.ckpt, "--rig", path, "--out", env.tmp / "out",
                  "--device", "cpu", *extra, *images)

    return run


def _full_size_intrinsics(data: dict) -> None:
    """Every camera's intrinsics for 1600 x 900 images (4x), the images staying 400 x 225."""
    for cam in data["cameras"].values():
        cam["intrinsics"] = (np.array(cam["intrinsics"]) * [[4], [4], [1]]).tolist()


for _name, _edit, _pattern in (
    ("rig_intrinsics_last_row", lambda d: d["cameras"]["CAM_FRONT"]["intrinsics"].__setitem__(2, [5, 5, 5]),
     r"rig\.json: camera CAM_FRONT: 'intrinsics' is not a pinhole matrix"),
    ("rig_translation_in_millimetres",
     lambda d: d["cameras"]["CAM_BACK"].__setitem__("translation", [28.3, 3.5, 1579.1]),
     r"rig\.json: camera CAM_BACK: 'translation' .* m from the ego origin"),
    ("rig_intrinsics_of_the_full_size_images", _full_size_intrinsics,
     r"'intrinsics' put the principal point .* outside its 400x225 image"),
):
    ROWS.append(Row(_name, "S2", f"predict-images: {_name} (was silently wrong)", _rig_row(_edit, _pattern)))


def _quaternions_xyzw(data: dict) -> None:
    """Every camera's quaternion written [x, y, z, w] (scipy's, ROS's order) where [w, x, y, z] is read."""
    for cam in data["cameras"].values():
        cam["quaternion"] = [*cam["quaternion"][1:], cam["quaternion"][0]]


ROWS.append(Row("rig_quaternion_xyzw", "S4", "predict-images: a rig file's quaternions in [x, y, z, w] order are named "
                "(four of six cameras looked 55-71 degrees up or down: a map from the sky, exit 0)",
                _rig_row(_quaternions_xyzw, r"camera CAM_FRONT_LEFT: the camera looks 55 degrees up.*\[x, y, z, w\]")))


@row("S2", "predict-images: a binary file given as --rig is named (was a UnicodeDecodeError)")
def row_rig_file_binary(env):
    path, images = _rig_files(env)
    env.error(r"rig file .*CAM_FRONT\.jpg is not a JSON text file", "predict-images", "--checkpoint", env.ckpt,
              "--rig", images[1], "--out", env.tmp / "out", "--device", "cpu", *images)


@row("S2", "predict-images: --config with --checkpoint is refused (was silently ignored)")
def row_predict_images_config_with_checkpoint(env):
    path, images = _rig_files(env)
    env.error(r"--config goes with --onnx", "predict-images", "--checkpoint", env.ckpt, "--config", env.yaml,
              "--rig", path, "--out", env.tmp / "out", *images)


@row("S2", "predict-images: the same image for two cameras is named")
def row_same_image_for_two_cameras(env):
    path, images = _rig_files(env)
    images[4] = images[1]
    env.error(r"cameras CAM_FRONT and CAM_BACK are given the same image", "predict-images", "--checkpoint",
              env.ckpt, "--rig", path, "--out", env.tmp / "out", "--device", "cpu", *images)


def _val_scene(env) -> str:
    return json.loads((env.world / "v1.0-trainval" / "scene.json").read_text())[-1]["name"]


@row("S2", "predict --video below a file, or --fps 1e9, is refused before the model runs (was a raw error after)")
def row_video_out_checked_first(env):
    (env.tmp / "taken").write_text("x")
    forbid(env, "instagram_hdmap.predict.load_predictor", "the model")
    env.error(r"--video .*taken.* is a file", "predict", env.yaml, "--checkpoint", env.ckpt, "--scene",
              _val_scene(env), "--video", env.tmp / "taken" / "v.mp4")
    env.error(r"--fps 1e\+09: .*at most", "predict", env.yaml, "--checkpoint", env.ckpt, "--scene", _val_scene(env),
              "--video", env.tmp / "v.mp4", "--fps", "1e9")


@row("S2", "predict --video on a full disk: named, no broken MP4 (OpenCV's writer reports nothing; was exit 0)")
def row_video_on_a_full_disk(env):
    import cv2

    real = cv2.VideoWriter

    class FullDisk:  # writes as OpenCV does, then loses the file's end as a full disk would
        def __init__(self, path, *args):
            self.path, self.writer = path, real(path, *args)

        def __getattr__(self, name):
            return getattr(self.writer, name)

        def release(self):
            self.writer.release()
            data = Path(self.path).read_bytes()
            Path(self.path).write_bytes(data[:len(data) // 2])

    env.monkeypatch.setattr("instagram_hdmap.predict.cv2.VideoWriter", FullDisk)
    video = env.tmp / "scene.mp4"
    env.error(r"cannot write --video .*scene\.mp4: the MP4 file OpenCV wrote is incomplete", "predict", env.yaml,
              "--checkpoint", env.ckpt, "--scene", _val_scene(env), "--video", video)
    assert sorted(p.name for p in env.tmp.iterdir()) == []


@row("S2", "a full disk while drawing PNGs names the file and leaves no empty PNG (show-gt, predict)")
def row_png_on_a_full_disk(env):
    import errno

    from matplotlib.figure import Figure

    def full(self, path, *args, **kwargs):
        Path(path).write_bytes(b"")
        raise OSError(errno.ENOSPC, "No space left on device")

    env.monkeypatch.setattr(Figure, "savefig", full)
    env.error(r"cannot write .*bev_polylines\.png: No space left on device", "show-gt", env.yaml, "--out",
              env.tmp / "gt")
    assert list((env.tmp / "gt").iterdir()) == []


@row("S2", "benchmark --device tpu is named (was a raw RuntimeError)")
def row_benchmark_unknown_device(env):
    env.error(r"--device tpu: choose cpu or cuda", "benchmark", env.yaml, "--device", "tpu")


@row("S2", "demo: a missing --config or a wrong key is named before the worlds are generated (minutes)")
def row_demo_config_checked_first(env):
    forbid(env, "instagram_hdmap.demo.ensure_world", "world generation")
    env.error(r"config file not found: .*nothere\.yaml", "demo", "--out", env.tmp / "demo", "--cache",
              env.tmp / "cache", "--config", env.tmp / "nothere.yaml")
    env.error(r"unknown config key 'train\.nope'", "demo", "--out", env.tmp / "demo", "--cache", env.tmp / "cache",
              "train.nope=1")


@row("S2", "a second training in the folder of a running one is refused (it deleted the first one's log)")
def row_second_training_in_a_running_folder(env):
    from instagram_hdmap.train import LOCK_FILE

    run = env.tmp / "run"
    (run / "tb").mkdir(parents=True)
    (run / "log.jsonl").write_text('{"step": 1}\n')  # the first run, before its first checkpoint
    holder = subprocess.Popen(  # the first run's lock, as lock_out_dir takes it
        [sys.executable, "-c", "import fcntl, os, sys, time\n"
         f"f = open({str(run / LOCK_FILE)!r}, 'a+'); fcntl.flock(f, fcntl.LOCK_EX); f.write(str(os.getpid()))\n"
         "f.flush(); print('locked', flush=True); time.sleep(60)"], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        forbid(env, "instagram_hdmap.train.train_one_epoch", "training")
        env.error(rf"another training is running in .*run \(process {holder.pid}\)", "train", env.yaml,
                  f"train.out_dir={run}")
        env.error(r"another training is running", "train", env.yaml, f"train.out_dir={run}", "--force")
        assert (run / "log.jsonl").read_text() == '{"step": 1}\n' and (run / "tb").is_dir()
    finally:
        holder.kill()
        holder.wait()


@row("S2", "a run whose last.pt save failed after best.pt (a full disk) points at best.pt, which resumes")
def row_resume_from_best_after_a_failed_save(env):
    run = env.tmp / "run"
    _toy_run(env, [0.2], "train.epochs=2", "train.max_steps=1")
    (run / "last.pt").unlink()  # best.pt is saved first; the disk filled up before last.pt
    env.error(rf"already holds a run; pass --resume {re.escape(str(run / 'best.pt'))}", "train", env.yaml,
              f"train.out_dir={run}")
    env.error(rf"stopped before it saved it .*--resume {re.escape(str(run / 'best.pt'))}", "train", env.yaml,
              f"train.out_dir={run}", "--resume", run / "last.pt")
    summary = _toy_run(env, [0.3, 0.1], "train.epochs=2", resume=str(run / "best.pt"))
    assert summary["step"] == 4 and load_checkpoint(run / "best.pt")["metrics"]["mAP"] == 0.3


@row("S2", "--resume of one folder's checkpoint into another folder holding a run is refused (it overwrote that "
          "run's last.pt and log)")
def row_resume_into_another_run(env):
    other, run = env.tmp / "other", env.tmp / "run"
    _toy_run(env, [0.2], "train.epochs=2", "train.max_steps=1")
    shutil.move(run, other)
    _toy_run(env, [0.5], "train.epochs=1")
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}
    forbid(env, "instagram_hdmap.train.train_one_epoch", "training")
    env.error(r"--resume .*other.*last\.pt continues the run of .*other, but train\.out_dir=.*run holds a run of its "
              "own", "train", env.yaml, f"train.out_dir={run}", "train.epochs=2", "--resume", other / "last.pt")
    assert {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()} == before


@row("S2", "--resume with another train.batch_size is refused (it skipped the rest of the epoch, moved the schedule)")
def row_resume_with_another_batch_size(env):
    run = env.tmp / "run"
    _toy_run(env, [0.2], "train.epochs=2", "train.max_steps=1")  # stopped mid-epoch
    with pytest.raises(CheckpointError, match=r"train\.batch_size: checkpoint 2 vs now 4"):
        _toy_run(env, [], "train.epochs=2", "train.batch_size=4", resume=str(run / "last.pt"))


@row("S2", "evaluate --out whose metrics.json is a folder: refused before the evaluation (was after it, with a new "
          "submission.json next to the old metrics)")
def row_evaluate_metrics_path_is_a_folder(env):
    (env.tmp / "e" / "metrics.json").mkdir(parents=True)
    forbid(env, "instagram_hdmap.predict.evaluate", "the evaluation")
    env.error(r"metrics\.json: is a folder", "evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "e")


@row("S2", "a custom splits file with a scene in both splits: training warns that validation is not unseen")
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


# ==================================================================================================
# The third sweep (S3): cases found by a third sweep of the same kind
# ==================================================================================================


@row("S3", "evaluate-json: a sample token twice in a dict 'results' is named (json kept the last, dropping vectors)")
def row_submission_token_twice(env):
    gt = _submission(env.tmp / "gt.json", {"a": [{"pts": [[0, 0], [1, 1]], "type": 0}],
                                           "b": [{"pts": [[0, 2], [3, 2]], "type": 2}]}, True)
    vector = '{"pts": [[0, 0], [1, 1]], "type": 0, "confidence_level": 0.9}'
    pred = env.tmp / "p.json"  # two prediction shards pasted into one object: "a" twice
    pred.write_text('{"meta": {"ground_truth": false}, "results": {"a": [' + vector + '], "b": [], "a": []}}')
    forbid(env, "instagram_hdmap.evaluation.Evaluator.compute", "the evaluation")
    env.error(r"p\.json: the key 'a' appears twice in one JSON object", "evaluate-json", "--pred", pred, "--gt", gt)


@row("S3", "demo: train.out_dir (or another key the demo sets) as an override is refused before the worlds (it "
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


@row("S3", "train CONFIG where CONFIG is OUT/config.yaml (the experiment kept in its run folder): refused (the run "
          "started over, removing it, and wrote its resolved config there: comments and _base_ lost)")
def row_config_inside_out_dir(env):
    exp = env.tmp / "exp"
    exp.mkdir()
    config = exp / "config.yaml"
    text = f"# my experiment\n_base_: {env.yaml}\ntrain:\n  out_dir: {exp}\n"
    config.write_text(text)
    forbid(env, "instagram_hdmap.train.train_one_epoch", "training")
    env.error(r"CONFIG .*config\.yaml is .*config\.yaml, where the run writes its resolved config", "train", config)
    assert config.read_text() == text


@row("S3", "--resume of a temporal run with another train.stream_frames is refused (it walked other pieces from "
          "the saved position and moved the schedule)")
def row_resume_temporal_with_other_stream_frames(env):
    run = env.tmp / "run"
    common = [env.yaml, "model.temporal.memory=bev", "train.epochs=2", f"train.out_dir={run}"]
    rc, _, err = env.cli("train", *common, "train.max_steps=1")  # stopped mid-epoch (3 steps an epoch)
    assert rc == 0, err[-3000:]
    forbid(env, "instagram_hdmap.train.train_one_epoch", "training")
    env.error(r"train\.stream_frames: checkpoint 0 vs now 2", "train", *common, "train.stream_frames=2",
              "--resume", run / "last.pt")
    env.error(r"train\.stream_warmup: checkpoint 0\.0 vs now 0\.5", "train", *common, "train.stream_warmup=0.5",
              "--resume", run / "last.pt")


@row("S3", "MapStream: ego poses in UTM coordinates (millions of metres) warp the memory as poses near the origin "
          "(float32 moved it by up to 0.5 m)")
def row_mapstream_utm_poses(env):
    from instagram_hdmap import Frame, Mapper
    from instagram_hdmap.models import build_model

    cfg = load_config(env.yaml, ["model.temporal.memory=bev", "model.temporal.fusion=gru"])
    torch.manual_seed(0)
    path = save_checkpoint({"model": build_model(cfg).state_dict(), "config": config_to_dict(cfg)},
                           env.tmp / "temporal.pt")
    mapper = Mapper.from_checkpoint(path, device="cpu")
    _, images, K, poses = _mapper_frame(env)

    def pose(x: float, yaw: float, origin) -> np.ndarray:
        T = np.eye(4)
        T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
        T[:2, 3] = [origin[0] + x, origin[1] + 0.3 * x]
        return T

    memories = []
    for origin in ((0.0, 0.0), (512_345.678, 5_412_345.678)):  # UTM easting, northing
        stream = mapper.stream()
        for x, yaw in ((0.0, 0.0), (1.3, 0.05)):
            stream.step(Frame(images=images, intrinsics=K, cam_to_ego=poses, ego_pose=pose(x, yaw, origin)))
        assert stream.status == "fused"
        memories.append(stream.memory["bev"])
    torch.testing.assert_close(memories[1], memories[0], atol=1e-5, rtol=1e-5)


@row("S3", "a sample_data record whose width is a string or 0 is named (was a TypeError / ZeroDivisionError)")
def row_sample_data_bad_width(env):
    for value in ("400", 0):
        def damage(tables, value=value):
            sd, _ = camera_record(tables, "CAM_BACK")
            sd["width"] = value

        root = env.shadow_world(damage)
        env.error(rf"sample_data .*\(CAM_BACK\) in .*sample_data\.json: 'width' must be the image's size in pixels, "
                  rf"a whole number >= 1, got {value!r}", "evaluate", env.yaml, f"data.dataroot={root}",
                  "--checkpoint", env.ckpt, "--out", env.tmp / "e")
        shutil.rmtree(root)


@row("S3", "numbers written as strings in the tables (an ego pose, intrinsics) are named (numpy read them as numbers, "
          "then a raw error came from the map or torch)")
def row_table_numbers_as_strings(env):
    def pose_strings(tables):
        for record in tables["ego_pose"]:
            record["translation"] = [str(x) for x in record["translation"]]

    def intrinsics_strings(tables):
        _, cs = camera_record(tables, "CAM_FRONT_RIGHT")
        cs["camera_intrinsic"] = [[str(x) for x in r] for r in cs["camera_intrinsic"]]

    for edit, pattern in ((pose_strings, r"ego_pose .*ego_pose\.json: its translation is not numeric"),
                          (intrinsics_strings, r"camera CAM_FRONT_RIGHT: .*the camera intrinsics is not numeric")):
        root = env.shadow_world(edit)
        env.error(pattern, "evaluate", env.yaml, f"data.dataroot={root}", "--checkpoint", env.ckpt, "--out",
                  env.tmp / "e")
        shutil.rmtree(root)


@row("S3", "export-gt --out a table of the dataset it reads (v1.0-trainval/sample.json) is refused (it was replaced "
          "by the GT file: the dataset destroyed, exit 0)")
def row_export_gt_over_a_table(env):
    root = env.shadow_world()
    table = root / "v1.0-trainval" / "sample.json"
    before = table.read_bytes()
    for _ in range(2):  # a GT file of its own right in the dataroot is fine, and may be written again
        rc, _, err = env.cli("export-gt", env.yaml, f"data.dataroot={root}", "--out", root / "gt_val.json")
        assert rc == 0, err[-2000:]
    forbid(env, "instagram_hdmap.cli.gt_submission", "the export")
    env.error(r"--out .*sample\.json is a file of the dataset the export reads", "export-gt", env.yaml,
              f"data.dataroot={root}", "--out", table)
    assert table.read_bytes() == before


@row("S3", "evaluate-json --xbound / --resolution that do not tile: the flags are named (was 'config key grid.xbound')")
def row_evaluate_json_bounds_named(env):
    gt = _submission(env.tmp / "gt.json", {"a": [{"pts": [[0, 0], [1, 1]], "type": 0}]}, True)
    env.error(r"--xbound -30 30: its extent 60 m is not a whole number of --resolution 0\.7 m pixels", "evaluate-json",
              "--pred", gt, "--gt", gt, "--protocol", "raster", "--resolution", "0.7")


@row("S3", "Mapper: a ground_height or an ego_pose that is not a number is a RigError (was a raw ValueError)")
def row_mapper_values_not_numbers(env):
    from instagram_hdmap import Frame
    from instagram_hdmap.data.rig import RigError

    mapper, images, K, poses = _mapper_frame(env)
    with pytest.raises(RigError, match=r"ground_height must be a finite height in metres, got \['abc'\]"):
        mapper(Frame(images=images, intrinsics=K, cam_to_ego=poses, ground_height="abc"))
    with pytest.raises(RigError, match=r"ego_pose must be a finite 4x4 .* got 'abc'"):
        mapper.stream().step(Frame(images=images, intrinsics=K, cam_to_ego=poses, ego_pose="abc"))


@row("S3", "--resume past train.max_steps says that nothing is left to train (printed 'done: epoch None, step None')")
def row_resume_past_max_steps(env):
    run = env.tmp / "run"
    _toy_run(env, [0.2], "train.epochs=2", "train.max_steps=1")
    env.capsys.readouterr()
    summary = _toy_run(env, [], "train.epochs=2", "train.max_steps=1", resume=str(run / "last.pt"))
    assert (summary["epoch"], summary["step"]) == (0, 1)
    assert "train.max_steps=1 is reached already" in env.capsys.readouterr().out


@row("S3", "an ONNX export with flipped bits in its weights is named before it runs (onnxruntime ran it: exit 0)")
def row_onnx_flipped_bits(env):
    pytest.importorskip("onnxruntime", reason="the [deploy] extra is not installed")
    import onnx

    from instagram_hdmap import Mapper
    from instagram_hdmap.deploy import export_onnx
    from instagram_hdmap.inference import DeployError
    from instagram_hdmap.models import build_model

    cfg = load_config(TINY_YAML, ["model.gnn.sinkhorn_iters=3"])
    torch.manual_seed(0)
    path = env.tmp / "m.onnx"
    export_onnx(build_model(cfg).eval(), cfg, path)
    Mapper.from_onnx(path)  # intact: loads
    weights = max(onnx.load(str(path)).graph.initializer, key=lambda t: len(t.raw_data)).raw_data
    data = bytearray(path.read_bytes())
    at = data.find(weights)
    assert at > 0
    data[at + 3] ^= 0x7F  # the first float's sign and exponent: a weight of about 1e38
    damaged = env.tmp / "damaged.onnx"
    damaged.write_bytes(bytes(data))
    with pytest.raises(DeployError, match=r"damaged\.onnx is damaged: its graph .* does not match the SHA-256"):
        Mapper.from_onnx(damaged)
    rig, images = _rig_files(env)
    env.error(r"damaged\.onnx is damaged", "predict-images", "--onnx", damaged, "--rig", rig, "--out",
              env.tmp / "out", *images)


@row("S4", "an MLP view transform with another model.view_transform.num_cameras than the rig's cameras (AV2's seven) "
          "is named before the model runs (was a raw ValueError in forward)")
def row_mlp_num_cameras_of_the_rig(env):
    env.error(r"'model\.view_transform\.num_cameras' is 6, .* the 7 cameras of data\.dataset=av2 .*num_cameras=7",
              "model-summary", env.yaml, "data.dataset=av2", "data.splits_file=null", "model.view_transform.kind=mlp",
              "model.view_transform.mlp_bev_downsample=4")
    env.error(r"num_cameras' is 6, .* the 3 cameras", "model-summary", env.yaml, "data.dataset=av2",
              "data.splits_file=null", "model.view_transform.kind=mlp", "model.view_transform.mlp_bev_downsample=4",
              "data.av2_cameras=[ring_front_left,ring_front_center,ring_front_right]")
    rc, _, err = env.cli("model-summary", env.yaml, "data.dataset=av2", "data.splits_file=null",
                         "model.view_transform.kind=mlp", "model.view_transform.mlp_bev_downsample=4",
                         "model.view_transform.num_cameras=7")
    assert rc == 0, err


@row("S4", "data.splits_file with data.dataset=av2 is refused (it was ignored: every log of the split folder ran)")
def row_av2_splits_file_ignored(env):
    env.error(r"'data\.splits_file' .* an AV2 split is a folder of logs .*data\.splits_file=null", "show-gt", env.yaml,
              "data.dataset=av2", "--out", env.tmp / "show")


@row("S4", "a splits file whose split lists a list (not scene names) is named (was a raw TypeError)")
def row_splits_file_nested_list(env):
    splits = env.tmp / "splits.json"
    names = json.loads((env.world / "splits.json").read_text())
    splits.write_text(json.dumps({**names, "val": [names["val"]]}))
    env.error(r"splits file .*splits\.json: split 'val' must list scene names \(strings\), got \[", "show-gt",
              env.yaml, f"data.splits_file={splits}", "--out", env.tmp / "show")


@row("S4", "evaluate-json: a MapTR-format vector whose cls_name is not its type's class is named (StreamMapNet's "
          "class ids scored dividers as crossings: exit 0)")
def row_cls_name_disagrees_with_type(env):
    line = [[0, 0], [5, 0], [10, 0]]
    gt = env.tmp / "gt.json"
    gt.write_text(json.dumps({"GTs": [{"sample_token": "a", "vectors": [
        {"pts": line, "pts_num": 3, "cls_name": "divider", "type": 0}]}]}))
    pred = env.tmp / "p.json"
    vector = {"pts": line, "pts_num": 3, "cls_name": "divider", "type": 1, "confidence_level": 0.9}
    pred.write_text(json.dumps({"results": [{"sample_token": "a", "vectors": [vector]}]}))
    env.error(r"p\.json: sample 'a', vector 0: 'cls_name' 'divider' disagrees with 'type' 1", "evaluate-json", "--pred",
              pred, "--gt", gt)
    pred.write_text(json.dumps({"results": [{"sample_token": "a", "vectors": [{**vector, "type": 0}]}]}))
    rc, out, err = env.cli("evaluate-json", "--pred", pred, "--gt", gt)  # MapTR's own file: agreed, scored
    assert rc == 0 and re.search(r"divider\s+1\.0000", out), err


@row("S4", "evaluate-json --protocol raster on a canvas smaller than the GT file's stated patch is named (it cropped "
          "the map: AP 1 for a missed line outside the default 60 m x 30 m)")
def row_raster_canvas_crops_the_patch(env):
    meta = {"xbound": [-50.0, 50.0], "ybound": [-50.0, 50.0]}
    near, far = [[0, 0], [5, 0], [10, 0]], [[35, 20], [40, 20], [45, 20]]
    gt = env.tmp / "gt.json"
    gt.write_text(json.dumps({"meta": {**meta, "ground_truth": True},
                              "results": {"a": [{"pts": near, "type": 0}, {"pts": far, "type": 0}]}}))
    pred = _submission(env.tmp / "p.json", {"a": [{"pts": near, "type": 0, "confidence_level": 0.9}]}, False)
    env.error(r"gt\.json: its meta says the map patch is xbound \[-50, 50\], ybound \[-50, 50\] .*--xbound -50 50 "
              r"--ybound -50 50", "evaluate-json", "--pred", pred, "--gt", gt, "--protocol", "raster")
    rc, out, err = env.cli("evaluate-json", "--pred", pred, "--gt", gt, "--protocol", "raster", "--xbound", "-50", "50",
                           "--ybound", "-50", "50", "--resolution", "0.25")
    assert rc == 0 and re.search(r"divider\s+0\.5000", out), err  # the far line is missed


@row("S4", "benchmark of a temporal model (configs/temporal) runs (was a raw KeyError: the batch lacked ego_pose)")
def row_benchmark_temporal_model(env):
    rc, out, err = env.cli("benchmark", env.yaml, "model.temporal.memory=bev", "model.gnn.sinkhorn_iters=3",
                           "--device", "cpu", "--runs", "1", "--warmup", "0")
    assert rc == 0 and "Traceback" not in err, err[-2000:]
    assert "a temporal model: timed on a scene's first frame" in out


@row("S4", "a checkpoint's AV2 camera order wins over the CONFIG file's, with a note (an MLP model's per-camera layers "
          "met other cameras: exit 0)")
def row_checkpoint_av2_camera_order(env):
    from instagram_hdmap.config import AV2_RING_CAMERAS
    from instagram_hdmap.inference import inference_config

    order = [AV2_RING_CAMERAS[-1], *AV2_RING_CAMERAS[:-1]]
    mlp = ["data.dataset=av2", "model.view_transform.kind=mlp", "model.view_transform.num_cameras=7"]
    trained = load_config(TINY_YAML, [*mlp, f"data.av2_cameras=[{','.join(order)}]"])
    out, notes = inference_config(load_config(TINY_YAML, mlp), config_to_dict(trained))
    assert list(out.data.av2_cameras) == order
    assert any("data.av2_cameras=" in n and "using the checkpoint's" in n for n in notes), notes

@row("S4", "export-onnx (and benchmark without a dataset) of an AV2 model takes its rig's camera count (the graph took "
          "six cameras: AV2 frames could not run it; an MLP model's export was a raw ValueError)")
def row_av2_export_takes_seven_cameras(env):
    pytest.importorskip("onnxruntime", reason="the [deploy] extra is not installed")
    from instagram_hdmap.deploy import export_onnx
    from instagram_hdmap.models import build_model

    av2 = ["data.dataset=av2", "data.dataroot=absent", "model.gnn.sinkhorn_iters=3"]
    rc, out, err = env.cli("benchmark", TINY_YAML, *av2, "model.view_transform.kind=mlp",
                           "model.view_transform.num_cameras=7", "--device", "cpu", "--runs", "1", "--warmup", "0")
    assert rc == 0 and "Traceback" not in err, err[-2000:]
    cfg = load_config(TINY_YAML, av2)
    torch.manual_seed(0)
    info = export_onnx(build_model(cfg).eval(), cfg, env.tmp / "av2.onnx")
    assert info["inputs"]["images"][1] == 7

# ==================================================================================================
# The fifth sweep (S5): cases found by a fifth sweep of the same kind
# ==================================================================================================


@row("S5", "Mapper: a transposed 4x4 cam_to_ego (its rotation still a rotation, the translation dropped), a (R, t) "
          "pair and intrinsics that require grad are named or taken (silently wrong / raw ValueError / raw "
          "RuntimeError)")
def row_mapper_cam_to_ego_transposed(env):
    from instagram_hdmap.data.rig import RigError

    mapper, images, K, poses = _mapper_frame(env)
    with pytest.raises(RigError, match=r"camera CAM_FRONT: 'cam_to_ego' has the last row \[1\.70.*, 1\.0\], not "
                                       r"\[0, 0, 0, 1\]: transposed"):
        mapper(images=images, intrinsics=K, cam_to_ego={**poses, "CAM_FRONT": poses["CAM_FRONT"].T})
    with pytest.raises(RigError, match=r"camera CAM_FRONT_LEFT: 'cam_to_ego' must be one 4x4 .* np\.c_\[R, t\]"):
        mapper(images=images, intrinsics=K, cam_to_ego={c: (T[:3, :3], T[:3, 3]) for c, T in poses.items()})
    grads = {c: torch.tensor(k, requires_grad=True) for c, k in K.items()}
    assert mapper(images=images, intrinsics=grads, cam_to_ego=poses) == mapper(images=images, intrinsics=K,
                                                                              cam_to_ego=poses)


@row("S5", "Mapper / predict-images: intrinsics normalised by the image size (fx ~ 1) are named (accepted: the "
          "principal point (0.5, 0.5) lies inside the image)")
def row_normalised_intrinsics(env):
    from instagram_hdmap.data.rig import RigError

    mapper, images, K, poses = _mapper_frame(env)
    normalised = {c: k / np.array([[400.0], [225.0], [1.0]]) for c, k in K.items()}
    with pytest.raises(RigError, match=r"camera CAM_FRONT_LEFT: 'intrinsics' has a focal length of .* field of view "
                                       r"over 175 degrees .* normalised by the image size"):
        mapper(images=images, intrinsics=normalised, cam_to_ego=poses)

    def normalise(data):
        for cam in data["cameras"].values():
            cam["intrinsics"] = (np.array(cam["intrinsics"]) / [[400], [225], [1]]).tolist()

    _rig_row(normalise, r"rig\.json: camera CAM_FRONT_LEFT: 'intrinsics' has a focal length")(env)


@row("S5", "Mapper: a PIL image of 16-bit or float pixels is named (convert('RGB') made it all white or all black)")
def row_mapper_pil_16bit_and_float(env):
    from PIL import Image

    from instagram_hdmap.data.rig import RigError

    mapper, images, K, poses = _mapper_frame(env)
    gray = images["CAM_FRONT"][..., 0]
    for image in (Image.fromarray(gray.astype(np.uint16) * 256), Image.fromarray(gray.astype(np.float32) / 255)):
        with pytest.raises(RigError, match=rf"camera CAM_FRONT: a PIL image of mode '{re.escape(image.mode)}' .* "
                                           r"clipped to 8 bits"):
            mapper(images={**images, "CAM_FRONT": image}, intrinsics=K, cam_to_ego=poses)
    mapper(images={**images, "CAM_FRONT": Image.fromarray(gray)}, intrinsics=K, cam_to_ego=poses)  # 8-bit gray: fine


@row("S5", "Mapper / predict-images: PNG frames whose size is not a multiple of the decode factor run (refused: "
          "'decodes to 200x112 at 1/8, expected 200x113': OpenCV shrinks a PNG to floor(W / f), a JPEG to ceil)")
def row_png_frames(env):
    from PIL import Image

    from instagram_hdmap import Frame
    from instagram_hdmap.data.rig import rig

    mapper, _, _, poses = _mapper_frame(env)
    sensors = rig((1600, 900))  # nuScenes' size; the tiny model's 64 x 160 images decode a JPEG at 1/8
    v, u = np.mgrid[:900, :1600]
    arrays = {c: np.stack([(u + 40 * k) % 256, v % 256, (u + v) % 256], -1).astype(np.uint8)
              for k, c in enumerate(mapper.cameras)}
    paths = {}
    for c, a in arrays.items():
        paths[c] = env.tmp / f"{c}.png"
        Image.fromarray(a).save(paths[c])
    K = {c: sensors[c].intrinsic for c in mapper.cameras}
    from_files = mapper.batch([Frame(images=paths, intrinsics=K, cam_to_ego=poses)])
    in_memory = mapper.batch([Frame(images=arrays, intrinsics=K, cam_to_ego=poses)])
    for key in ("images", "post_rot", "post_tran"):  # the PNG decoded whole: the same pixels as the arrays
        torch.testing.assert_close(from_files[key], in_memory[key])


@row("S5", "a device torch knows but this package does not run on (mps, xpu, meta) is named (predict-images --device "
          "mps and Mapper.from_checkpoint(device='mps') were a raw RuntimeError)")
def row_device_not_supported(env):
    from instagram_hdmap import Mapper

    with pytest.raises(UserError, match=r"device=mps is not supported; use auto, cpu, cuda"):
        Mapper.from_checkpoint(env.ckpt, device="mps")
    rig, images = _rig_files(env)
    env.error(r"--device=mps is not supported|device=mps is not supported", "predict-images", "--checkpoint", env.ckpt,
              "--rig", rig, "--out", env.tmp / "out", "--device", "mps", *images)


@row("S5", "an ONNX export of a temporal model given a memory as numpy arrays, int32 indices or a float mask: taken, "
          "or named (raw onnxruntime errors / AttributeError)")
def row_onnx_memory_dtypes(env):
    pytest.importorskip("onnxruntime", reason="the [deploy] extra is not installed")
    from instagram_hdmap import Frame, Mapper
    from instagram_hdmap.deploy import export_onnx
    from instagram_hdmap.inference import DeployError
    from instagram_hdmap.models import build_model

    cfg = load_config(TINY_YAML, ["model.gnn.sinkhorn_iters=3", "model.temporal.memory=bev"])
    torch.manual_seed(0)
    path = env.tmp / "t.onnx"
    export_onnx(build_model(cfg).eval(), cfg, path)
    mapper = Mapper.from_onnx(path)
    _, images, K, poses = _mapper_frame(env)
    batch = mapper.batch([Frame(images=images, intrinsics=K, cam_to_ego=poses, ego_pose=np.eye(4))])
    model = mapper.model
    memory = model(batch)["memory"]
    expected = model(batch, memory)["pred_heatmap"]
    numpy_memory = {k: v.numpy() for k, v in memory.items()}
    numpy_memory["frame_index"] = numpy_memory["frame_index"].astype(np.int32)
    torch.testing.assert_close(model(batch, numpy_memory)["pred_heatmap"], expected)
    with pytest.raises(DeployError, match=r"t\.onnx takes memory_valid as booleans; the batch has torch\.float32"):
        model(batch, {**memory, "valid": memory["valid"].float()})
    with pytest.raises(DeployError, match=r"t\.onnx takes scene_start as booleans; the batch has torch\.int64"):
        model({**batch, "scene_start": torch.ones(1, dtype=torch.long)}, memory)


@row("S5", "an output path through a symbolic link that leads nowhere (a loop, an unmounted disk) is named before the "
          "work (evaluate, train, synth: raw FileExistsError / RuntimeError), and a result written at a symbolic link "
          "updates the file it points to (the link was replaced, the file left stale)")
def row_output_path_broken_symlink(env):
    dangling, loop = env.tmp / "dangling", env.tmp / "loop"
    dangling.symlink_to(env.tmp / "unmounted" / "runs")
    loop.symlink_to(env.tmp / "loop2")
    (env.tmp / "loop2").symlink_to(loop)
    forbid(env, "instagram_hdmap.predict.evaluate", "the evaluation")
    env.error(r"--out .*dangling: .*dangling is a symbolic link to .*unmounted/runs, which leads nowhere", "evaluate",
              env.yaml, "--checkpoint", env.ckpt, "--out", dangling)
    env.error(r"--out .*loop/e: .*loop is a symbolic link to .*loop2, which leads nowhere", "evaluate", env.yaml,
              "--checkpoint", env.ckpt, "--out", loop / "e")
    forbid(env, "instagram_hdmap.train.train_one_epoch", "training")
    env.error(r"train\.out_dir .*loop: .*leads nowhere", "train", env.yaml, f"train.out_dir={loop}")
    env.error(r"--out .*dangling: .*leads nowhere", "synth", "--out", dangling, "--scenes-train", "1", "--scenes-val",
              "0", "--samples-per-scene", "1", "--image-size", "160x90")
    assert not (env.tmp / "unmounted").exists()
    target, link = env.tmp / "shared_metrics.json", env.tmp / "metrics.json"
    target.write_text('{"old": 1}')
    link.symlink_to(target)
    gt = _submission(env.tmp / "gt.json", {"a": [{"pts": [[0, 0], [1, 1]], "type": 0}]}, True)
    env.monkeypatch.undo()
    rc, _, err = env.cli("evaluate-json", "--pred", gt, "--gt", gt, "--out", link)
    assert rc == 0, err[-2000:]
    assert link.is_symlink() and json.loads(target.read_text())["protocol"] == "vector"


@row("S5", "demo: a model setting that cannot be built (data.image_size=[30,30]) or an AV2 config is named before the "
          "worlds are generated (minutes; the AV2 config then failed on data.splits_file)")
def row_demo_model_checked_first(env):
    forbid(env, "instagram_hdmap.demo.ensure_world", "world generation")
    env.error(r"'data\.image_size': 30x30 .*multiples of 32", "demo", "--out", env.tmp / "demo", "--cache",
              env.tmp / "cache", "data.image_size=[30,30]")
    env.error(r"--config .*synthetic_demo\.yaml sets data\.dataset=av2, but the demo's synthetic worlds are in the "
              r"nuScenes layout", "demo", "--out", env.tmp / "demo", "--cache", env.tmp / "cache", "--config",
              REPO / "configs" / "av2" / "synthetic_demo.yaml")


@row("S5", "nuScenes tables: a record that names a token its table does not hold (annotations of a removed sample) is "
          "explained (was 'KeyError: <token>')")
def row_table_dangling_reference(env):
    def remove_a_sample(tables):
        sd, _ = camera_record(tables, "CAM_FRONT", 2)  # the val scene's last sample, with its annotations kept
        token = sd["sample_token"]
        tables["sample"] = [s for s in tables["sample"] if s["token"] != token]
        tables["sample_data"] = [s for s in tables["sample_data"] if s["sample_token"] != token]
        first(tables["sample"], next=token)["next"] = ""

    root = env.shadow_world(remove_a_sample)
    env.error(r"a record refers to token '\w+' that no record of the table it points into holds", "evaluate", env.yaml,
              f"data.dataroot={root}", "--checkpoint", env.ckpt, "--out", env.tmp / "e")


@row("S5", "MapStream.step given a list of frames is a TypeError that says to step once per frame (was an "
          "AttributeError on 'ego_pose')")
def row_stream_step_list(env):
    from instagram_hdmap import Frame

    mapper, images, K, poses = _mapper_frame(env)
    with pytest.raises(TypeError, match=r"MapStream\.step takes one Frame .* got list; call step\(\) once per frame"):
        mapper.stream().step([Frame(images=images, intrinsics=K, cam_to_ego=poses)])


@row("S5", "Mapper.from_checkpoint(overrides='key=value'), a string: one override (its characters were read as "
          "overrides: \"override 'm' must look like key.sub=value\")")
def row_mapper_overrides_string(env):
    from instagram_hdmap import Mapper

    assert Mapper.from_checkpoint(env.ckpt, device="cpu", overrides="model.gnn.num_vertices=32").config.model.gnn \
        .num_vertices == 32


@row("S5", "export-onnx of a temporal checkpoint with a single-frame CONFIG names model.temporal.memory='bev' (CONFIG: "
          "'none') (it listed four keys as 'CONFIG: None')")
def row_export_onnx_temporal_config_named(env):
    pytest.importorskip("onnxruntime", reason="the [deploy] extra is not installed")
    from instagram_hdmap.models import build_model

    cfg = load_config(env.yaml, ["model.temporal.memory=bev"])
    ckpt = save_checkpoint({"model": build_model(cfg).state_dict(), "config": config_to_dict(cfg)}, env.tmp / "t.pt")
    forbid(env, "instagram_hdmap.deploy.export_onnx", "the export")
    line = env.error(r"t\.pt is from another config: it was trained with model\.temporal\.memory='bev' \(CONFIG: "
                     r"'none'\); pass the config", "export-onnx", env.yaml, "--checkpoint", ckpt, "--out",
                     env.tmp / "t.onnx")
    assert "None" not in line


@row("S5", "eval.thresholds with a threshold twice is named (mAP, their mean, counted it twice)")
def row_eval_thresholds_twice(env):
    env.error(r"'eval\.thresholds' lists a threshold twice", "model-summary", env.yaml, "eval.thresholds=[0.5,0.5,1.0]")



# ==================================================================================================
# The sixth sweep (S6): cases found by a sixth sweep of the same kind
# ==================================================================================================


@row("S6", "train --force with train.init_from a checkpoint of train.out_dir is refused (--force removed the "
          "checkpoint before it was read: 'checkpoint not found', the weights lost)")
def row_init_from_inside_out_dir(env):
    run = env.tmp / "run"
    _toy_run(env, [0.2], "train.epochs=1")
    before = (run / "best.pt").read_bytes()
    forbid(env, "instagram_hdmap.train.train_one_epoch", "training")
    env.error(r"train\.init_from=.*best\.pt is the best\.pt of train\.out_dir=.*run, which this run starts over .*copy "
              r"it out of the folder", "train", env.yaml, f"train.out_dir={run}", f"train.init_from={run / 'best.pt'}",
              "--force")
    assert (run / "best.pt").read_bytes() == before


@row("S6", "train.init_from's errors name the key, and its weights' fit and train.trainable's prefixes are checked "
          "before the data loaders (a long setup on nuScenes; the message said '--checkpoint')")
def row_init_from_and_trainable_checked_first(env):
    forbid(env, "instagram_hdmap.train.build_loaders", "the data loaders")
    env.error(r"train\.init_from: .*tiny_world\.yaml is not a PyTorch checkpoint", "train", env.yaml,
              f"train.out_dir={env.tmp / 'r1'}", f"train.init_from={env.yaml}")
    line = env.error(r"train\.trainable: \['temporl'\] name no parameter of this model", "train", env.yaml,
                     f"train.out_dir={env.tmp / 'r2'}", "train.trainable=[temporl]")
    assert "--checkpoint" not in line
    env.error(r"train\.init_from: the checkpoint's weights do not fit .*temporal\.", "train", env.yaml,
              f"train.out_dir={env.tmp / 'r3'}", "model.gnn.sinkhorn_iters=3",  # a temporal model's weights
              f"train.init_from={_temporal_checkpoint(env)}")


def _temporal_checkpoint(env) -> Path:
    """A random tiny temporal checkpoint (``model.temporal.memory=bev``, 3 Sinkhorn iterations)."""
    from instagram_hdmap.models import build_model

    torch.manual_seed(0)
    cfg = env.cfg("model.temporal.memory=bev", "model.gnn.sinkhorn_iters=3")
    return save_checkpoint({"model": build_model(cfg).state_dict(), "config": config_to_dict(cfg)},
                           env.tmp / "temporal.pt")


@row("S6", "Mapper: a camera upside down (an OpenGL / Blender pose, y up and z backward, or a 180 degree roll) is "
          "named (accepted: rays from the wrong side of the car, exit 0), and a roll of 120 degrees is not reported "
          "as 60")
def row_mapper_camera_upside_down(env):
    from instagram_hdmap.data.rig import RigError

    mapper, images, K, poses = _mapper_frame(env)
    for flip in (np.diag([1.0, -1.0, -1.0, 1.0]), np.diag([-1.0, -1.0, 1.0, 1.0])):  # OpenGL axes; rolled 180
        with pytest.raises(RigError, match=r"camera CAM_FRONT_LEFT: 'cam_to_ego': the camera is upside down .*OpenGL"):
            mapper(images=images, intrinsics=K, cam_to_ego={c: T @ flip for c, T in poses.items()})
    c, s = np.cos(np.radians(120)), np.sin(np.radians(120))
    roll = np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])  # about the optical axis
    with pytest.raises(RigError, match=r"rolled 120 degrees"):
        mapper(images=images, intrinsics=K, cam_to_ego={c: T @ roll for c, T in poses.items()})
    c, s = np.cos(np.radians(-20)), np.sin(np.radians(-20))
    pitched = np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1]])  # 20 degrees down: a real rig
    assert isinstance(mapper(images=images, intrinsics=K, cam_to_ego={c: T @ pitched for c, T in poses.items()}), list)


@row("S6", "predict-images: images named for other cameras than the rig file's order gives them (in the model's order, "
          "or shuffled) are named (a map from swapped cameras, exit 0)")
def row_images_named_for_other_cameras(env):
    def reverse(data):
        data["cameras"] = dict(reversed(list(data["cameras"].items())))

    rig, images = _rig_files(env, reverse)  # the images in the model's order, the rig file's cameras reversed
    forbid(env, "instagram_hdmap.predict.save_figure", "drawing")
    env.error(r"image .*CAM_FRONT_LEFT\.jpg is named for camera CAM_FRONT_LEFT but is given for camera CAM_BACK_RIGHT: "
              r"give the images in the rig file's order", "predict-images", "--checkpoint", env.ckpt, "--rig", rig,
              "--out", env.tmp / "out", "--device", "cpu", *images)
    mapper, arrays, K, poses = _mapper_frame(env)
    with pytest.raises(UserError, match=r"camera CAM_FRONT_LEFT: its image .*CAM_FRONT\.jpg is named for camera "
                                        r"CAM_FRONT"):
        mapper(images=[images[1], images[0], *images[2:]], intrinsics=[K[c] for c in mapper.cameras],
               cam_to_ego=[poses[c] for c in mapper.cameras])


@row("S6", "evaluate-json: raster-only flags (--xbound, --resolution, --rank-by, ...) with the vector protocol are "
          "refused (ignored silently: a range the user meant to evaluate on was not applied)")
def row_evaluate_json_raster_flags_with_vector(env):
    gt = _submission(env.tmp / "gt.json", {"a": [{"pts": [[0, 0], [1, 1]], "type": 0}]}, True)
    forbid(env, "instagram_hdmap.evaluation.Evaluator.compute", "the evaluation")
    env.error(r"--xbound, --ybound: options of the raster protocol; .*pass --protocol raster", "evaluate-json",
              "--pred", gt, "--gt", gt, "--xbound", "-15", "15", "--ybound", "-7.5", "7.5")
    env.error(r"--rank-by: options of the raster protocol", "evaluate-json", "--pred", gt, "--gt", gt, "--rank-by",
              "descending")


@row("S6", "a config whose _base_ is missing or a folder names the file that includes it (said 'config file not "
          "found: base.yaml', the user's file being there)")
def row_missing_base_named(env):
    (env.tmp / "exp.yaml").write_text("_base_: base.yaml\ntrain:\n  lr: 0.1\n")
    env.error(r"config file .*exp\.yaml: its _base_ base\.yaml .* is not a file", "model-summary", env.tmp / "exp.yaml")


@row("S6", "a write whose folder is removed while the job runs (or a file system that takes no new files) is one line "
          "naming the file (was a raw FileNotFoundError)")
def row_output_folder_removed_during_the_write(env):
    from instagram_hdmap.files import OutputError, atomic_path

    target = env.tmp / "out" / "metrics.json"
    with pytest.raises(OutputError, match=r"cannot write .*out/metrics\.json: No such file or directory"):
        with atomic_path(target) as tmp:
            shutil.rmtree(target.parent)  # another process cleaning up, a network folder unmounted
            tmp.write_text("{}")


@row("S6", "RANK and WORLD_SIZE left in the environment without MASTER_ADDR (a shell, a job script; not torchrun) are "
          "one line (was torch's raw ValueError)")
def row_rank_without_torchrun(env):
    env.monkeypatch.setenv("RANK", "0")
    env.monkeypatch.setenv("WORLD_SIZE", "2")
    env.monkeypatch.delenv("MASTER_ADDR", raising=False)
    env.monkeypatch.delenv("MASTER_PORT", raising=False)
    env.error(r"RANK and WORLD_SIZE are set .* but MASTER_ADDR and MASTER_PORT are not: launch with torchrun, or "
              r"unset", "train", env.yaml, f"train.out_dir={env.tmp / 'r'}")


@row("S6", "predict and predict --video of a temporal model with data.on_bad_sample=skip and a bad earlier frame: the "
          "frame is a missing one, as in evaluate (was the bad frame's error, exit 2)")
def row_temporal_predict_skip_mode(env):
    root = env.shadow_world(copy_samples=True)
    _break_image(root, root, 0, "CAM_FRONT", "missing")  # the first frame of the validation scene
    ckpt = _temporal_checkpoint(env)
    args = (env.yaml, f"data.dataroot={root}", "data.on_bad_sample=skip", "model.temporal.memory=bev",
            "model.gnn.sinkhorn_iters=3", "--checkpoint", ckpt)
    rc, out, err = env.cli("predict", *args, "--index", "1", "--out", env.tmp / "p")
    assert rc == 0 and "no memory, as the frame before it in scene" in out + err, (out + err)[-2000:]
    rc, out, err = env.cli("predict", *args, "--scene", _val_scene(env), "--video", env.tmp / "v.mp4")
    assert rc == 0 and "1 bad frame(s) of scene" in out + err and (env.tmp / "v.mp4").is_file(), (out + err)[-2000:]


@row("S6", "train.stream_frames=1 with a temporal model is refused (every frame started a new memory: the fusion never "
          "trained with one, a single-frame training, exit 0)")
def row_temporal_stream_frames_1(env):
    forbid(env, "instagram_hdmap.train.train_one_epoch", "training")
    env.error(r"train\.stream_frames=1: every frame would start a new memory", "train", env.yaml,
              "model.temporal.memory=bev", "train.stream_frames=1", f"train.out_dir={env.tmp / 'r'}")


@row("S6", "MapStream: float32 ego poses at UTM coordinates are named (float32 had rounded them to 0.5 m before the "
          "stream's float64 shift: the memory misplaced by that much, exit 0)")
def row_mapstream_float32_utm_poses(env):
    from instagram_hdmap import Frame, Mapper
    from instagram_hdmap.data.rig import RigError

    _, images, K, poses = _mapper_frame(env)
    mapper = Mapper.from_checkpoint(_temporal_checkpoint(env), device="cpu")
    pose = np.eye(4)
    pose[:3, 3] = [4.4e6, 5.8e5, 300.0]  # UTM northing, easting, height
    for given in (pose.astype(np.float32), torch.tensor(pose, dtype=torch.float32)):
        with pytest.raises(RigError, match=r"ego_pose is float32 at 4\.4e\+06 m .* only to 0\.5 m.* float64"):
            mapper.stream().step(Frame(images=images, intrinsics=K, cam_to_ego=poses, ego_pose=given))
    assert isinstance(mapper.stream().step(Frame(images=images, intrinsics=K, cam_to_ego=poses, ego_pose=pose)), list)


@row("S6", "evaluate-json --thresholds with a threshold twice is named (mAP, their mean, counted it twice; "
          "eval.thresholds was checked, the flag not)")
def row_evaluate_json_thresholds_twice(env):
    gt = _submission(env.tmp / "gt.json", {"a": [{"pts": [[0, 0], [1, 1]], "type": 0}]}, True)
    env.error(r"thresholds: \[0\.5, 0\.5\] lists a threshold twice", "evaluate-json", "--pred", gt, "--gt", gt,
              "--thresholds", "0.5", "0.5")


@row("S6", "a path key written ~/... in a YAML file or a quoted override is the home folder (train.out_dir: ~/runs "
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
    # None"; sweep 12, K12); on an optional one it stays null: none
    cfg = load_config(env.yaml, ["train.out_dir=~", "data.dataroot=~", "train.init_from=~"])
    assert (cfg.train.out_dir, cfg.data.dataroot, cfg.train.init_from) == (str(home), str(home), None)


# ==================================================================================================
# The seventh sweep (S7): cases found by a seventh sweep of the same kind
# ==================================================================================================


def _evaluate_world(env, edit, pattern: str) -> str:
    """Evaluate on a shadow world whose tables ``edit`` changed; it must stop on one line matching ``pattern``."""
    root = env.tmp / "world"
    if root.exists():
        shutil.rmtree(root)
    return env.error(pattern, "evaluate", env.yaml, f"data.dataroot={env.shadow_world(edit)}", "--checkpoint",
                     env.ckpt, "--out", env.tmp / "eval")


@row("S7", "nuScenes tables: a camera calibration in millimetres, intrinsics of another image size, a quaternion in "
          "x, y, z, w order or an ego -> camera rotation are named (the Mapper refused them; the dataset ran, exit 0)")
def row_dataset_calibration_consistent_but_wrong(env):
    from pyquaternion import Quaternion

    def edit(change, channel="CAM_FRONT"):
        return lambda tables: change(camera_record(tables, channel)[1])

    def mm(cs):
        cs["translation"] = [v * 1000 for v in cs["translation"]]

    def intrinsics_1600x900(cs):
        cs["camera_intrinsic"] = (np.array(cs["camera_intrinsic"]) * [[4], [4], [1]]).tolist()

    def xyzw(cs):
        w, x, y, z = cs["rotation"]
        cs["rotation"] = [x, y, z, w]

    def inverse(cs):
        cs["rotation"] = list(Quaternion(cs["rotation"]).inverse.elements)

    where = r"camera CAM_FRONT: calibrated_sensor \w+ in .*calibrated_sensor\.json: "
    _evaluate_world(env, edit(mm), where + r"its translation .* puts the camera \d{4} m from the ego .*millimetres")
    _evaluate_world(env, edit(intrinsics_1600x900), where + r"its principal point .* outside its 400x225 image")
    for change in (xyzw, inverse):  # CAM_FRONT's quaternion read so still gives a level camera: a rig's trips on others
        _evaluate_world(env, edit(change, "CAM_FRONT_LEFT"), r"camera CAM_FRONT_LEFT: .*: the camera (looks|is "
                        r"rolled|is upside down).*\(w, x, y, z\) order")


@row("S7", "AV2: an egovehicle_SE3_sensor translation in millimetres or intrinsics of the full-size image are named "
          "(ran, exit 0)")
def row_av2_calibration_consistent_but_wrong(env):
    from pyarrow import feather

    root, log = _av2_copy(env)
    extrinsics = log / "calibration" / "egovehicle_SE3_sensor.feather"
    _edit_feather(extrinsics, "tx_m", 0, 1000 * feather.read_table(str(extrinsics)).column("tx_m")[0].as_py())
    _av2_error(env, root, rf"log {log.name}: camera \w+ in .*egovehicle_SE3_sensor\.feather .*from the ego origin")
    root, log = _av2_copy(env) if shutil.rmtree(root) is None else (None, None)
    intrinsics = log / "calibration" / "intrinsics.feather"
    _edit_feather(intrinsics, "cx_px", 0, 5 * feather.read_table(str(intrinsics)).column("cx_px")[0].as_py())
    _av2_error(env, root, rf"log {log.name}: camera \w+ in .*intrinsics\.feather: its principal point .* outside")


@row("S7", "nuScenes tables: ego poses whose quaternion is in x, y, z, w order, or in millimetres, are named (the GT "
          "map was cut at another heading or far off the map, exit 0)")
def row_dataset_ego_pose_consistent_but_wrong(env):
    from pyquaternion import Quaternion

    def xyzw(tables):
        for pose in tables["ego_pose"]:
            w, x, y, z = Quaternion(axis=[0, 0, 1], degrees=90).elements  # heading 90 degrees, read in xyzw order
            pose["rotation"] = [x, y, z, w]

    def mm(tables):
        for pose in tables["ego_pose"]:
            pose["translation"] = [v * 1000 for v in pose["translation"]]

    _evaluate_world(env, xyzw, r"ego_pose \w+ of LIDAR_TOP .*: its rotation tilts the vehicle 90 degrees .*"
                               r"\(x, y, z, w\)")
    _evaluate_world(env, mm, r"the ego position \(\d+\.\d, \d+\.\d\) lies \d+ km outside the map of location "
                             r".*millimetres")


@row("S7", "nuScenes tables: two cameras of a sample reading the same image file is named (ran, exit 0)")
def row_dataset_same_image_for_two_cameras(env):
    def same(tables):
        front, _ = camera_record(tables, "CAM_FRONT")
        left, _ = camera_record(tables, "CAM_FRONT_LEFT")
        left["filename"] = front["filename"]

    _evaluate_world(env, same, r"cameras CAM_FRONT_LEFT and CAM_FRONT read the same image file .*CAM_FRONT__")


@row("S7", "evaluate-json: a prediction file of other classes or another patch (its meta), or in global coordinates "
          "or normalised to [0, 1], is named (AP 0 or class ids mixed up, exit 0)")
def row_submission_in_another_setting(env):
    line = {"a": [{"pts": [[float(x), float(x) / 4] for x in range(-8, 9)], "type": 0}]}
    meta = {"classes": ["divider", "ped_crossing", "boundary"], "xbound": [-8.0, 8.0], "ybound": [-4.0, 4.0]}
    gt = env.tmp / "gt.json"
    gt.write_text(json.dumps({"meta": {**meta, "ground_truth": True}, "results": line}))

    def pred(change_meta=None, move=lambda p: p):
        vectors = {"a": [{**v, "pts": [move(np.array(q)).tolist() for q in v["pts"]], "confidence_level": 0.9}
                         for v in line["a"]]}
        path = env.tmp / "pred.json"
        path.write_text(json.dumps({"meta": {**meta, **(change_meta or {}), "ground_truth": False},
                                    "results": vectors}))
        return path

    assert env.cli("evaluate-json", "--pred", pred(), "--gt", gt)[0] == 0
    env.error(r"pred\.json: its meta says classes = \['ped_crossing', 'divider', 'boundary'\], the GT file .*'s says",
              "evaluate-json", "--pred", pred({"classes": ["ped_crossing", "divider", "boundary"]}), "--gt", gt)
    env.error(r"its meta says xbound = \[-30\.0, 30\.0\]", "evaluate-json", "--pred", pred({"xbound": [-30.0, 30.0]}),
              "--gt", gt)
    env.error(r"100% of its points lie outside twice the GT's map patch .*global coordinates", "evaluate-json",
              "--pred", pred(move=lambda p: p + [4.4e3, 5.8e3]), "--gt", gt)
    env.error(r"every point lies in \[0, 1\] x \[0, 1\] .*normalised", "evaluate-json", "--pred",
              pred(move=lambda p: (p + [8, 4]) / [16, 8]), "--gt", gt)


@row("S7", "train.trainable without train.init_from is refused before the loaders (the frozen parts stayed random: a "
          "training of the rest on random features, exit 0)")
def row_trainable_without_init_from(env):
    forbid(env, "instagram_hdmap.train.build_loaders", "the data loaders")
    env.error(r"train\.trainable=\['backbone'\] without train\.init_from: the frozen parts \(bev_heads, graph_head, "
              r"view_transform\) keep their random initialisation", "train", env.yaml, f"train.out_dir={env.tmp / 'r'}",
              "train.trainable=[backbone]")


@row("S7", "--resume with another train.seed is refused (the saved position counted batches of the old seed's order: "
          "the rest of the epoch saw some samples twice and others never, exit 0)")
def row_resume_with_another_seed(env):
    _toy_run(env, [0.2], "train.epochs=2", "train.max_steps=1")
    with pytest.raises(UserError, match=r"incompatible config \(train\.seed: checkpoint 0 vs now 7\)"):
        _toy_run(env, [], "train.epochs=2", "train.seed=7", resume=str(env.tmp / "run" / "last.pt"))


@row("S7", "evaluate with data.camera_dropout (a training config's setting) says that the images were blanked (the AP "
          "of dropped cameras, reported as the model's)")
def row_evaluate_notes_camera_dropout(env):
    rc, out, err = env.cli("evaluate", env.yaml, "data.camera_dropout=0.3", "--checkpoint", env.ckpt, "--out",
                           env.tmp / "eval")
    assert rc == 0 and re.search(r"note: data\.camera_dropout=0\.3: each camera image of the split is blanked in 30%",
                                 out), out


@row("S7", "benchmarks/temporal.py: an option out of range (--steps 0, --occluders 2), a --finetune-base without its "
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


@row("S7", "nuScenes tables: a camera image taken seconds from its sample (timestamps of another moment or unit) is "
          "named with the sample, the camera and the gap (ran, exit 0); every sample of the synthetic worlds passes")
def row_camera_image_of_another_moment(env):
    from instagram_hdmap.data.base import check_camera_time

    def late(tables):
        for sd in tables["sample_data"]:
            if sd["fileformat"] == "jpg" and "CAM_BACK__" in sd["filename"]:
                sd["timestamp"] += 5_000_000

    _evaluate_world(env, late, r"sample \w+: camera CAM_BACK: sample_data \w+ in .*sample_data\.json: the image's "
                               r"timestamp \d+ us is 5 s from its sample's")
    for split in ("train", "val"):  # the synthetic worlds' every sample (AV2: av2's 25 ms synchronisation, checked)
        for ds in (val_dataset(env.cfg(f"data.val_split={split}")), _av2_dataset(env, split)):
            for i in range(len(ds)):
                ds.camera_files(i)
    with pytest.raises(UserError, match=r"camera ring_rear_left: .* 0\.6 s from its sample's"):
        check_camera_time(1_000_000, 1_600_000, "camera ring_rear_left: x.jpg")
    check_camera_time(1_000_000, 1_050_000, "a real rig's 50 ms")


def _av2_dataset(env, split: str, root: Path | None = None):
    from instagram_hdmap.data import build_dataset

    root = root or env.request.getfixturevalue("av2_world")
    cfg = env.cfg("data.dataset=av2", "data.splits_file=null", "data.av2_frame_step=1", "data.image_fit=contain",
                  f"data.dataroot={root}")
    return build_dataset(cfg, split, augment=False)


REAL_AV2 = REPO.parent / "shared" / "av2_real"


@row("S7", "a camera whose optical axis points where its channel does not (CAM_FRONT and CAM_BACK swapped in the "
          "sensor table, a Mapper given the back camera's pose as the front's) is named (ran, exit 0); every camera "
          "of the real nuScenes rig, the real AV2 log and the synthetic worlds passes")
def row_camera_heading_of_another_channel(env):
    from instagram_hdmap import Frame
    from instagram_hdmap.data.base import NOMINAL_CAMERA_YAW_DEG, camera_heading_problem
    from instagram_hdmap.data.rig import RigError, rig
    from instagram_hdmap.data.synthetic.av2_writer import av2_rig

    def swap(tables):
        for s in tables["sensor"]:
            s["channel"] = {"CAM_FRONT": "CAM_BACK", "CAM_BACK": "CAM_FRONT"}.get(s["channel"], s["channel"])

    _evaluate_world(env, swap, r"camera CAM_(FRONT|BACK): calibrated_sensor \w+ in .*: its optical axis points "
                               r"-?\d+ degrees left of the vehicle's forward direction, 180 degrees off where a CAM_")
    mapper, images, K, poses = _mapper_frame(env)
    with pytest.raises(RigError, match=r"camera CAM_FRONT: 'cam_to_ego': its optical axis points 180 degrees left .* "
                                       r"off where a CAM_FRONT camera looks \(0;"):
        mapper(Frame(images=images, intrinsics=K, cam_to_ego={**poses, "CAM_FRONT": poses["CAM_BACK"]}))
    # the real rigs and the synthetic ones pass; the AV2 world's cameras pass when its dataset loads them
    real = {c: s.rot for c, s in rig().items() if s.modality == "camera"}
    real |= {c: s.rot for c, s in av2_rig().items() if s.modality == "camera"}
    if (REAL_AV2 / "val").is_dir():
        from av2.utils.io import read_ego_SE3_sensor

        for log in (REAL_AV2 / "val").iterdir():
            real |= {f"{c} of {log.name}": p.rotation for c, p in read_ego_SE3_sensor(log).items()
                     if c.startswith("ring")}
        real_ds = _av2_dataset(env, "val", REAL_AV2)
        real_ds._log_cameras(real_ds.samples[0][0])  # the dataset's own checks (heading included) pass
    assert len(real) >= 13 and set(NOMINAL_CAMERA_YAW_DEG) <= {c.split(" ")[0] for c in real}
    assert {c: camera_heading_problem(c.split(" ")[0], R) for c, R in real.items()} == dict.fromkeys(real)
    ds = _av2_dataset(env, "val")
    ds._log_cameras(ds.samples[0][0])
    assert camera_heading_problem("my_roof_camera", poses["CAM_BACK"][:3, :3]) is None  # unknown names: not checked


@row("S7", "train.init_from with --resume says in one note that init_from is not read on a resume (silently ignored)")
def row_init_from_with_resume_notes(env):
    _toy_run(env, [0.2], "train.epochs=2", "train.max_steps=1")
    last = env.tmp / "run" / "last.pt"
    env.capsys.readouterr()
    _toy_run(env, [0.3, 0.4], "train.epochs=2", f"train.init_from={env.ckpt}", resume=str(last))
    out = env.capsys.readouterr().out
    assert len(re.findall(r"note: train\.init_from=.*random\.pt is not read on a resume: the weights are .*last\.pt's",
                          out)) == 1, out


@row("S7", "nuScenes tables: every camera image of a sample given one calibrated_sensor is named as a duplicate "
          "calibration (was 'has no CAM_FRONT_LEFT image', naming no cause)")
def row_cameras_share_one_calibration(env):
    def share(tables):
        token = camera_record(tables, "CAM_FRONT")[1]["token"]
        for sd in tables["sample_data"]:
            if sd["fileformat"] == "jpg":
                sd["calibrated_sensor_token"] = token

    _evaluate_world(env, share, r"sample \w+ has no CAM_FRONT_LEFT image: 6 of its key-frame sample_data records "
                                r"\(calibrated_sensor \w+\) are calibrated as CAM_FRONT .*a duplicate calibration")


@row("S7", "an atomic write over a file with a second (hard-linked) name replaces the name written; the other name "
          "keeps the old content, as os.replace does (the promise docs/faults.md states)")
def row_atomic_write_over_a_hard_link(env):
    from instagram_hdmap.files import write_json

    old, other = env.tmp / "metrics.json", env.tmp / "backup.json"
    old.write_text('{"mAP": 0.5}')
    os.link(old, other)
    write_json({"mAP": 0.7}, old)
    assert json.loads(old.read_text()) == {"mAP": 0.7} and json.loads(other.read_text()) == {"mAP": 0.5}
    assert not old.samefile(other)


# ==================================================================================================
# The eighth sweep (S8): cases found by an eighth sweep of the same kind
# ==================================================================================================


def _memory_checkpoint(env, name: str, *overrides) -> Path:
    from instagram_hdmap.models import build_model

    cfg = env.cfg("model.gnn.sinkhorn_iters=3", *overrides)
    return save_checkpoint({"model": build_model(cfg).state_dict(), "config": config_to_dict(cfg)}, env.tmp / name)


@row("S8", "Mapper.forward with the memory of a temporal model of another grid (the same memory channels) is a "
          "ValueError naming both sizes (a raw RuntimeError of a reshape deep in the warp)")
def row_memory_of_a_model_of_another_grid(env):
    from instagram_hdmap import Mapper

    coarse = _memory_checkpoint(env, "coarse.pt", "model.temporal.memory=graph", "grid.resolution=0.5")
    fine = _memory_checkpoint(env, "fine.pt", "model.temporal.memory=graph")
    a, b = Mapper.from_checkpoint(coarse, device="cpu"), Mapper.from_checkpoint(fine, device="cpu")
    _, images, K, poses = _mapper_frame(env)
    from instagram_hdmap import Frame

    frame = Frame(images=images, intrinsics=K, cam_to_ego=poses, ego_pose=np.eye(4))
    memory = a.forward(a.batch([frame]) | {"ego_pose": torch.eye(4)[None]})["memory"]
    with pytest.raises(ValueError, match=r"the memory map is 8 x 16 cells, this model's 16 x 32 \(another grid\)"):
        b.forward(b.batch([frame]) | {"ego_pose": torch.eye(4)[None], "frame_index": torch.tensor([2])}, memory)
    own = b.forward(b.batch([frame]) | {"ego_pose": torch.eye(4)[None]})["memory"]  # its own memory fuses
    out = b.forward(b.batch([frame]) | {"ego_pose": torch.eye(4)[None], "frame_index": torch.tensor([2])}, own)
    assert out["memory_status"].tolist() == [0]


def _benchmark_temporal(env, *args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(REPO / "benchmarks" / "temporal.py"), *args, "--cache",
                           str(env.tmp / "cache"), "--out", str(env.tmp / "out")], capture_output=True, text=True,
                          timeout=120, env={**os.environ, "PYTHONPATH": str(REPO / "src")})


@row("S8", "benchmarks/temporal.py: a --set that does not fit --memory (model.temporal.fusion=gru with --memory graph) "
          "is one line before the worlds are generated (it passed the check, then a traceback after minutes), and "
          "--set model.temporal.memory=... is refused (--memory overrode it without a word)")
def row_benchmark_temporal_set_against_memory(env):
    for args, pattern in ((["--memory", "graph", "--set", "model.temporal.fusion=gru"],
                           r"--set \(the temporal config, --memory graph\): config key 'model\.temporal\.fusion'"),
                          (["--memory", "graph", "--set", "model.temporal.memory=bev"],
                           r"--set model\.temporal\.memory=bev: the temporal model's memory is --memory \(graph\)"),
                          (["--memory", "graph", "--temporal-set", "model.temporal.memory=bev"],
                           r"--temporal-set model\.temporal\.memory=bev: the temporal model's memory is --memory")):
        p = _benchmark_temporal(env, *args, "--steps", "2")
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


@row("S8", "benchmarks/temporal.py: a run folder of --out holding a result trained with other options (another "
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


@row("S8", "evaluate-json: a prediction file whose meta states the patch as [min, max, resolution] (HDMapNet's "
          "xbound) and a file whose one element lies in [0, 1] x [0, 1] where its GT does are valid (both refused)")
def row_submission_valid_but_refused(env):
    meta = {"classes": ["divider", "ped_crossing", "boundary"], "xbound": [-8.0, 8.0], "ybound": [-4.0, 4.0]}
    line = {"a": [{"pts": [[float(x), float(x) / 4] for x in range(-8, 9)], "type": 0}]}
    near = {"a": [{"pts": [[0.1 * i, 0.5] for i in range(10)], "type": 1}]}
    for vectors, pred_meta in ((line, {**meta, "xbound": [-8.0, 8.0, 0.25], "ybound": [-4.0, 4.0, 0.25]}),
                               (near, meta)):
        gt, pred = env.tmp / "gt.json", env.tmp / "pred.json"
        gt.write_text(json.dumps({"meta": {**meta, "ground_truth": True}, "results": vectors}))
        pred.write_text(json.dumps({"meta": {**pred_meta, "ground_truth": False}, "results": {
            "a": [{**v, "confidence_level": 0.9} for v in vectors["a"]]}}))
        rc, out, err = env.cli("evaluate-json", "--pred", pred, "--gt", gt)
        assert rc == 0, err
    env.error(r"its meta says xbound = \[-15\.0, 15\.0, 0\.15\]", "evaluate-json", "--pred", _rewrite(  # another patch
        pred, xbound=[-15.0, 15.0, 0.15], results=line), "--gt", _rewrite(gt, results=line))


def _rewrite(path: Path, results: dict, **meta) -> Path:
    doc = json.loads(path.read_text())
    doc["meta"].update(meta)
    doc["results"] = {k: [{**v, **({"confidence_level": 0.9} if not doc["meta"]["ground_truth"] else {})} for v in vs]
                      for k, vs in results.items()}
    path.write_text(json.dumps(doc))
    return path


@row("S8", "a checkpoint whose saved temporal memory holds NaN (weights finite) is named when it loads (a resume "
          "stopped on a 'non-finite loss' advising a lower learning rate)")
def row_checkpoint_with_nonfinite_memory(env):
    state = torch.load(env.ckpt, weights_only=True)
    memory = {"bev": torch.zeros(1, 4, 16, 32), "ego_pose": torch.eye(4)[None],
              "valid": torch.ones(1, dtype=torch.bool), "frame_index": torch.ones(1, dtype=torch.long)}
    save_checkpoint({**state, "memory": [memory]}, env.tmp / "ok.pt")
    load_checkpoint(env.tmp / "ok.pt")  # a finite memory loads
    memory["bev"][0, 0, 3, 4] = float("nan")
    path = save_checkpoint({**state, "memory": [memory]}, env.tmp / "last.pt")
    with pytest.raises(CheckpointError, match=r"last\.pt: the temporal streams' saved memory \('bev'\) holds NaN"):
        load_checkpoint(path)


@row("S8", "a temporal training whose train.stream_warmup rounds to every epoch (0.6 of 1 epoch; the benchmark's "
          "--steps 100) is refused before the loaders: it ran on single frames only, its memory never trained, exit 0")
def row_temporal_warmup_covers_every_epoch(env):
    forbid(env, "instagram_hdmap.train.build_loaders", "the data loaders")
    env.error(r"train\.stream_warmup=0\.6 of train\.epochs=1 is 1 single-frame epoch\(s\) of 1: the temporal model "
              r"would never train with its memory", "train", env.yaml, f"train.out_dir={env.tmp / 'r'}",
              "model.temporal.memory=graph", "train.stream_warmup=0.6", "train.epochs=1")
    p = _benchmark_temporal(env, "--steps", "100")
    assert p.returncode == 2 and re.search(r"the temporal run \(--steps 100\): train\.stream_warmup=0\.6 of "
                                           r"train\.epochs=1", p.stderr), p.stderr[-2000:]
    assert not (env.tmp / "cache").exists()


# ==================================================================================================
# The ninth sweep (S9): cases found by a ninth sweep of the same kind
# ==================================================================================================


@row("S9", "an image cropped off-centre (the rows below the horizon, the right part of a wide image) with its "
          "intrinsics shifted puts the principal point outside the image, validly: the Mapper and the datasets "
          "refused it as intrinsics of another image size; those (beyond both far edges) are still named")
def row_principal_point_of_a_cropped_image(env):
    from instagram_hdmap.data.base import DatasetError, check_camera_plausible
    from instagram_hdmap.data.rig import RigError, rig

    mapper, images, K, poses = _mapper_frame(env)
    for axis, cut in ((0, 130), (1, 220)):  # rows 130.. (cy < 0), columns 220.. of CAM_FRONT (cx < 0)
        cropped, shifted = dict(images), {c: k.copy() for c, k in K.items()}
        for cam in (mapper.cameras if axis == 0 else ["CAM_FRONT"]):
            cropped[cam] = np.ascontiguousarray(images[cam][cut:] if axis == 0 else images[cam][:, cut:])
            shifted[cam][1 - axis, 2] -= cut
        assert min(k[1 - axis, 2] for k in shifted.values()) < 0
        mapper(images=cropped, intrinsics=shifted, cam_to_ego=poses)  # runs
    sensor = rig((1600, 900))["CAM_FRONT"]
    crop = sensor.intrinsic.copy()
    crop[1, 2] -= 520  # the 1600 x 380 rows below the horizon
    check_camera_plausible(crop, sensor.rot, sensor.trans, (1600, 380), "CAM_FRONT", "hint", channel="CAM_FRONT")
    with pytest.raises(DatasetError, match=r"principal point .* outside its 400x225 image"):  # K of 1600 x 900
        check_camera_plausible(sensor.intrinsic, sensor.rot, sensor.trans, (400, 225), "CAM_FRONT", "hint")
    mapper, images, K, poses = _mapper_frame(env, intrinsics_size=(800, 450))  # K of twice the size
    with pytest.raises(RigError, match=r"principal point .* outside its 400x225 image"):
        mapper(images=images, intrinsics=K, cam_to_ego=poses)


def _gt_and_pred(env, pred_tf=None, pred_meta=None):
    """The tiny world's GT (export-gt) and a prediction file of its vectors (confidence 0.8), points mapped by
    ``pred_tf``; returns (gt path, its document, pred path)."""
    gt = env.tmp / "gt.json"
    rc, out, err = env.cli("export-gt", env.yaml, "--out", gt)
    assert rc == 0, err
    doc = json.loads(gt.read_text())
    tf = pred_tf or (lambda p: p)
    pred = env.tmp / "pred.json"
    pred.write_text(json.dumps({"meta": {**doc["meta"], "ground_truth": False} if pred_meta is None else pred_meta,
                                "results": {k: [{**v, "pts": tf(v["pts"]), "confidence_level": 0.8} for v in vs]
                                            for k, vs in doc["results"].items()}}))
    return gt, doc, pred


@row("S9", "evaluate-json: a GT file of the official exporters (InstaGraM's / HDMapNet's export_gt_to_json.py: "
          "confidence_level 1 on every vector, no ground_truth flag) was refused as a prediction file; files "
          "swapped are still named")
def row_official_gt_file_with_unit_confidences(env):
    gt, doc, pred = _gt_and_pred(env)
    official = env.tmp / "official_gt.json"
    official.write_text(json.dumps({"meta": {"use_camera": True, "use_lidar": False, "use_radar": False,
                                             "use_external": False, "vector": True},
                                    "results": {k: [{**v, "confidence_level": 1} for v in vs]
                                                for k, vs in doc["results"].items()}}))
    rc, out, err = env.cli("evaluate-json", "--pred", pred, "--gt", official)
    assert rc == 0 and re.search(r"^mAP\s+0\.6667", out, re.M), err + out
    env.error(r"official_gt\.json: given as the GT but it is a prediction file .* are --pred and --gt swapped",
              "evaluate-json", "--pred", gt, "--gt", official)


@row("S9", "evaluate-json: a prediction file in MapTR's lidar frame (x right, y forward) against a GT of this "
          "package's frame, or the reverse (a MapTR GT file without meta), lies within twice the patch: mAP 0, "
          "exit 0; its points beyond the stated patch are named, with the axes' hint. Meta patches [min, max, "
          "resolution] of two raster resolutions state the same patch (were refused)")
def row_submission_with_swapped_axes(env):
    gt, doc, pred = _gt_and_pred(env, pred_tf=lambda p: [[-y, x] for x, y in p])  # MapTR: (x, y) = (-y, x)
    hint = r"x right, y forward \(MapTR's lidar frame\)\? points are x forward, y left"
    env.error(r"pred\.json: \d+% of its points lie beyond the map patch .*gt\.json's meta states .*" + hint,
              "evaluate-json", "--pred", pred, "--gt", gt)
    maptr_gt = env.tmp / "maptr_gt.json"  # MapTR's GT form: {"GTs": [{"sample_token", "vectors"}]}, no meta
    maptr_gt.write_text(json.dumps({"GTs": [{"sample_token": k, "vectors": [{**v, "pts": [[-y, x] for x, y in v["pts"]]}
                                                                             for v in vs]}
                                            for k, vs in doc["results"].items()]}))
    gt, doc, pred = _gt_and_pred(env)
    env.error(r"maptr_gt\.json: \d+% of its points lie beyond the map patch .*pred\.json's meta states .*" + hint,
              "evaluate-json", "--pred", pred, "--gt", maptr_gt)
    meta3 = {**doc["meta"], "xbound": [-8.0, 8.0, 0.15], "ybound": [-4.0, 4.0, 0.15]}  # another raster resolution
    gt.write_text(json.dumps({**doc, "meta": meta3}))
    rc, out, err = env.cli("evaluate-json", "--pred", pred, "--gt", gt)  # the same patch: scored
    assert rc == 0 and re.search(r"^mAP\s+0\.6667", out, re.M), err + out


@row("S9", "benchmarks/temporal.py: --val-dropout 1 (data.camera_dropout must be < 1) and an --out that is a file "
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


@row("S9", "a training stopped by SIGTERM (a scheduler's preemption, docker stop, timeout) lost every step since its "
          "last save; it now saves last.pt as Ctrl-C does, and puts the old handler back")
def row_sigterm_saves_last_pt(env):
    import signal

    from instagram_hdmap.train import TrainingRun

    received = []

    def ours(signum, frame):  # the handler before the run (unfixed, the run kept training through the signal)
        received.append(signum)

    previous = signal.signal(signal.SIGTERM, ours)
    try:
        on_step = TrainingRun.on_step

        def step_then_term(self, info):
            on_step(self, info)
            if info.step == 2:
                os.kill(os.getpid(), signal.SIGTERM)

        env.monkeypatch.setattr(TrainingRun, "on_step", step_then_term)
        rc, out, err = env.cli("train", env.yaml, f"train.out_dir={env.tmp / 'run'}", "train.epochs=2",
                               "train.checkpoint_every=0")
        assert rc == 130 and "interrupted: saved" in out + err, (rc, err[-2000:])
        state = torch.load(env.tmp / "run" / "last.pt", weights_only=True)
        assert (state["epoch"], state["step"]) == (0, 2), (state["epoch"], state["step"])
        assert not received and signal.getsignal(signal.SIGTERM) is ours  # the run's handler, then ours again
    finally:
        signal.signal(signal.SIGTERM, previous)
    # a scheduler's SIGTERM to the whole process group kills the data-loader worker too: still saved, one line
    run = env.tmp / "group"
    p = subprocess.Popen([sys.executable, "-m", "instagram_hdmap.cli", "train", str(env.yaml), f"train.out_dir={run}",
                          "train.epochs=50", "train.batch_size=1", "data.num_workers=1", "train.checkpoint_every=0",
                          "train.val_every=100"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True, env={**os.environ, "PYTHONPATH": str(REPO / "src")})
    try:
        for _ in range(600):
            if (run / "last.pt").exists() or p.poll() is not None:
                break
            time.sleep(0.2)
        time.sleep(1.0)  # part-way through the next epoch
        os.killpg(p.pid, signal.SIGTERM)
        out, err = p.communicate(timeout=300)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    assert p.returncode == 130 and "Traceback" not in err and "interrupted: saved" in out, (p.returncode, err[-2000:])


@row("S9", "evaluate-json: a submission with a UTF-8 byte-order mark (Windows editors) was refused as not JSON; a "
          "gzip-compressed file or a pickle (mmcv.dump to .pkl) is named as such (was a 'utf-8' codec error)")
def row_submission_file_encodings(env):
    import gzip
    import pickle

    gt, doc, pred = _gt_and_pred(env)
    bom = env.tmp / "bom.json"
    bom.write_bytes(b"\xef\xbb\xbf" + pred.read_bytes())
    rc, out, err = env.cli("evaluate-json", "--pred", bom, "--gt", gt)
    assert rc == 0 and re.search(r"^mAP\s+0\.6667", out, re.M), err + out
    (env.tmp / "pred.json.gz").write_bytes(gzip.compress(pred.read_bytes()))
    env.error(r"pred\.json\.gz: a gzip-compressed file \(gunzip it\), not JSON", "evaluate-json", "--pred",
              env.tmp / "pred.json.gz", "--gt", gt)
    (env.tmp / "pred.pkl").write_bytes(pickle.dumps(json.loads(pred.read_text())))
    env.error(r"pred\.pkl: a Python pickle \(mmcv\.dump to \.pkl; dump to \.json\), not JSON", "evaluate-json",
              "--pred", env.tmp / "pred.pkl", "--gt", gt)


@row("S9", "predict (and predict --video) with data.camera_dropout > 0 (a training config's setting) blanked cameras "
          "of the frame without a word (evaluate said so already)")
def row_predict_notes_camera_dropout(env):
    rc, out, err = env.cli("predict", env.yaml, "data.camera_dropout=0.5", "--checkpoint", env.ckpt, "--index", "0",
                           "--out", env.tmp / "pred")
    assert rc == 0, err
    assert re.search(r"note: data\.camera_dropout=0\.5: each camera image of the split is blanked .* not the "
                     r"predictions of the full images", out + err), out + err


@row("S9", "a config's _base_ written ~/... (the home folder, as the path keys read it since S6) was joined to the "
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


@row("S9", "AV2: a camera frame dropped at a lidar sweep (no image within 25 ms) was two lines: av2's own logging "
          "warning ('No corresponding ring image at ...') above the one-line error")
def row_av2_dropped_camera_frame_one_line(env):
    root, log = _av2_copy(env)
    sorted((log / "sensors" / "cameras" / "ring_side_left").iterdir())[0].unlink()
    p = subprocess.run([sys.executable, "-m", "instagram_hdmap.cli", "show-gt", str(env.yaml), "data.dataset=av2",
                        "data.splits_file=null", "data.av2_frame_step=1", "data.image_fit=contain",
                        f"data.dataroot={root}", "--split", "train", "--index", "0", "--out", str(env.tmp / "show")],
                       capture_output=True, text=True, timeout=120, env={**os.environ, "PYTHONPATH": str(REPO / "src")})
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert p.returncode == 2 and len(lines) == 1, p.stderr[-2000:]
    assert re.search(r"no ring_side_left image within 25 ms of lidar sweep", lines[0]), lines[0]


# --- the tenth sweep ----------------------------------------------------------------------------------


@row("S10", "a second SIGTERM during the save that the first one started (scancel or docker stop twice, a supervisor "
            "that repeats it) aborted that save: the older last.pt stayed, the steps since were lost")
def row_second_sigterm_during_the_save(env):
    import signal

    from instagram_hdmap.train import TrainingRun

    on_step, save = TrainingRun.on_step, TrainingRun.save

    def step_then_term(self, info):
        on_step(self, info)
        if info.step == 2:
            os.kill(os.getpid(), signal.SIGTERM)

    def save_under_a_second_term(self, name, metrics=None, gather=True):
        if not gather:  # the interrupt's save: the second signal arrives as it starts
            os.kill(os.getpid(), signal.SIGTERM)
        save(self, name, metrics, gather)

    previous = signal.getsignal(signal.SIGTERM)
    env.monkeypatch.setattr(TrainingRun, "on_step", step_then_term)
    env.monkeypatch.setattr(TrainingRun, "save", save_under_a_second_term)
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={env.tmp / 'run'}", "train.epochs=2",
                           "train.checkpoint_every=0")
    assert rc == 130 and "interrupted: saved" in out + err, (rc, err[-2000:])
    state = torch.load(env.tmp / "run" / "last.pt", weights_only=True)
    assert (state["epoch"], state["step"]) == (0, 2), (state["epoch"], state["step"])
    assert signal.getsignal(signal.SIGTERM) is previous  # the handler before the run, again


@row("S10", "evaluate-json --protocol raster of export-gt's file of a smaller patch (the tiny world's 16 m x 8 m) on "
            "the default canvas was refused as 'which would crop it': a larger canvas crops nothing, it counts "
            "predictions beyond the patch")
def row_raster_canvas_larger_than_the_patch(env):
    gt = env.tmp / "gt.json"
    gt.write_text(json.dumps({"meta": {"xbound": [-8.0, 8.0], "ybound": [-4.0, 4.0], "ground_truth": True},
                              "results": {"a": [{"pts": [[0, 0], [5, 0]], "type": 0}]}}))
    pred = _submission(env.tmp / "p.json", {"a": [{"pts": [[0, 0], [5, 0]], "type": 0, "confidence_level": 0.9}]},
                       False)
    rc, out, err = env.cli("evaluate-json", "--pred", pred, "--gt", gt, "--protocol", "raster")
    assert rc == 2 and "would crop" not in err and "beyond the patch" in err, err
    assert "--xbound -8 8 --ybound -4 4" in err, err


@row("S10", "synth-preview --out without a picture suffix (a name such as 'preview', or an existing file 'notes'): "
            "matplotlib's raw ValueError about the format 'tmp-PID' of the temporary file; a seed of 2**70 was "
            "refused as not 'a whole number >= 0'")
def row_synth_preview_out_without_suffix(env):
    env.error(r"--out .*preview: the picture's format comes from its suffix; .*\.png", "synth-preview", env.world,
              "--out", env.tmp / "preview")
    (env.tmp / "notes").write_text("mine")
    env.error(r"--out .*notes: the picture's format", "synth-preview", env.world, "--out", env.tmp / "notes")
    assert (env.tmp / "notes").read_text() == "mine"
    env.error(r"--seed 1180591620717411303424: .* from 0 to 2\*\*63 - 1", "synth", "--out", env.tmp / "w", "--seed",
              str(2**70), "--scenes-train", "1", "--scenes-val", "1", "--samples-per-scene", "1")
    rc, out, err = env.cli("synth-preview", env.world, "--out", env.tmp / "p.PNG")  # the suffix in any case
    assert rc == 0 and (env.tmp / "p.PNG").stat().st_size > 0, err[-2000:]


@row("S10", "export-onnx --out naming the CONFIG file (the YAML given first) replaced the config with the ONNX graph, "
            "exit 0 (--out naming the checkpoint was refused already)")
def row_export_onnx_out_is_the_config(env):
    pytest.importorskip("onnx", reason="the [deploy] extra is not installed")
    config = env.tmp / "exp.yaml"
    shutil.copy(env.yaml, config)
    before = config.read_bytes()
    env.error(r"--out .*exp\.yaml is the CONFIG file the job reads", "export-onnx", config, "--checkpoint", env.ckpt,
              "--out", config)
    assert config.read_bytes() == before


@row("S10", "a training whose terminal closed (SIGHUP: an ssh session dropped, without nohup or tmux) died without "
            "saving, losing every step since its last save; it now saves last.pt as for SIGTERM, and a SIGHUP that "
            "nohup ignores stays ignored")
def row_sighup_saves_last_pt(env):
    import signal

    if not hasattr(signal, "SIGHUP"):
        pytest.skip("no SIGHUP on this platform")
    from instagram_hdmap.train import TrainingRun

    on_step = TrainingRun.on_step

    def step_then_hup(self, info):
        on_step(self, info)
        if info.step == 2:
            os.kill(os.getpid(), signal.SIGHUP)

    previous = signal.signal(signal.SIGHUP, signal.SIG_DFL)  # a terminal's process: the default (death)
    try:
        env.monkeypatch.setattr(TrainingRun, "on_step", step_then_hup)
        rc, out, err = env.cli("train", env.yaml, f"train.out_dir={env.tmp / 'run'}", "train.epochs=2",
                               "train.checkpoint_every=0")
        assert rc == 130 and "interrupted: saved" in out + err, (rc, err[-2000:])
        state = torch.load(env.tmp / "run" / "last.pt", weights_only=True)
        assert (state["epoch"], state["step"]) == (0, 2), (state["epoch"], state["step"])
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_DFL
        signal.signal(signal.SIGHUP, signal.SIG_IGN)  # under nohup: the signal stays ignored, the run goes on
        env.monkeypatch.setattr(TrainingRun, "on_step", step_then_hup)
        rc, out, err = env.cli("train", env.yaml, f"train.out_dir={env.tmp / 'nohup'}", "train.epochs=1",
                               "train.checkpoint_every=0")
        assert rc == 0 and "interrupted" not in out + err, (rc, err[-2000:])
    finally:
        signal.signal(signal.SIGHUP, previous)



# --- the eleventh sweep -------------------------------------------------------------------------------


@row("S11", "Mapper: an image tensor in bfloat16 (0..1, a mixed-precision pipeline's) crashed with torch's raw "
            "'TypeError: Got unsupported ScalarType BFloat16' (float16 and float64 tensors were accepted)")
def row_mapper_bfloat16_image(env):
    from instagram_hdmap import Frame, Mapper
    from instagram_hdmap.data.rig import rig

    mapper = Mapper.from_checkpoint(env.ckpt, device="cpu")
    calib = rig((64, 36))
    poses = {c: np.vstack([np.c_[calib[c].rot, calib[c].trans], [0, 0, 0, 1]]) for c in mapper.cameras}
    intrinsics = {c: calib[c].intrinsic for c in mapper.cameras}
    pixels = torch.rand(3, 36, 64, generator=torch.Generator().manual_seed(0)).to(torch.bfloat16)
    got = mapper.batch([Frame({c: pixels for c in mapper.cameras}, intrinsics, poses)])["images"]
    want = mapper.batch([Frame({c: pixels.float() for c in mapper.cameras}, intrinsics, poses)])["images"]
    assert torch.equal(got, want)


@row("S11", "Evaluator.update: tokens given as a numpy array (a pandas column's values) crashed with numpy's raw "
            "'truth value of an array ... is ambiguous'; fewer tokens than samples, with a raw IndexError; an unknown "
            "class id of an Evaluator of two classes was named with the three default class names")
def row_evaluator_tokens_array_and_count(env):
    from instagram_hdmap.evaluation import EvaluationInputError, Evaluator

    line = {"pts": np.array([[0.0, 0.0], [5.0, 0.0]]), "label": 0}
    ev = Evaluator("vector")
    ev.update([[{**line, "score": 0.9}], []], [[line], [line]], tokens=np.array(["a", "b"]))
    ev.update([[{**line, "score": 0.9}]], [[line]], tokens=np.array(["a"]))  # seen: not scored twice
    metrics = ev.compute()
    assert metrics["counters"]["samples"] == 2 and metrics["num_gt"]["divider"] == 2, metrics["counters"]
    with pytest.raises(EvaluationInputError, match="1 tokens for 2 samples"):
        Evaluator("raster").update([[], []], [[line], [line]], tokens=["a"])
    with pytest.raises(EvaluationInputError, match=r"unknown class id 2; expected 0\.\.1 \(the evaluator's classes\)"):
        Evaluator("vector", classes=("lane", "kerb")).update([[{**line, "label": 2, "score": 0.5}]], [[line]])


@row("S11", "AV2: a pose table re-saved with timestamp_ns as float64 (pandas makes an int64 column float where a "
            "merge leaves a NaN) was refused as 'has no ego pose at lidar sweep' with no hint that the column was "
            "rounded; a camera folder of PNG images, as 'the folder holds no images'")
def row_av2_rounded_timestamps_and_png_images(env):
    import pyarrow as pa
    from pyarrow import feather

    root, log = _av2_copy(env)
    table = feather.read_table(str(log / "city_SE3_egovehicle.feather"))
    rounded = pa.array(table.column("timestamp_ns").to_numpy().astype(np.float64))
    table = table.set_column(table.column_names.index("timestamp_ns"), "timestamp_ns", rounded)
    feather.write_feather(table, str(log / "city_SE3_egovehicle.feather"))
    _av2_error(env, root, r"has no ego pose at lidar sweep \d+ .*ns away: its timestamp_ns column was rounded .*"
                          r"write it as int64")
    shutil.rmtree(root)
    root, log = _av2_copy(env)
    for image in (log / "sensors" / "cameras" / "ring_side_left").iterdir():
        image.rename(image.with_suffix(".png"))
    _av2_error(env, root, r"ring_side_left: the folder holds no \.jpg images .*\.png files: convert them to JPEG")


@row("S11", "AV2: a hidden folder in a split folder (Jupyter's .ipynb_checkpoints, a .Trash-1000) made a valid "
            "dataset refused as 'not an AV2 split folder'; it is not a log and is skipped")
def row_av2_hidden_folder_in_the_split(env):
    root, log = _av2_copy(env)
    (root / "train" / ".ipynb_checkpoints").mkdir()
    (root / "train" / ".DS_Store").write_text("")
    assert len(_av2_dataset(env, "train", root)) == len(_av2_dataset(env, "train"))


@row("S11", "a path option written --out=~/eval (the shell expands no ~ after '='; nor in quotes) wrote a folder "
            "named '~' under the working directory while saying 'wrote ~/eval/...'; it is the home folder, as "
            "the config's path keys read it")
def row_tilde_in_cli_paths(env):
    home = env.tmp / "home"
    home.mkdir()
    env.monkeypatch.setenv("HOME", str(home))
    rc, out, err = env.cli("export-gt", env.yaml, "--out=~/gt.json")
    assert rc == 0 and (home / "gt.json").is_file() and not (env.tmp / "~").exists(), err[-2000:]
    env.error(r"checkpoint not found: .*home/nope\.pt", "evaluate", env.yaml, "--checkpoint=~/nope.pt",
              "--out", env.tmp / "eval")



@row("S11", "predict-images: a rig file saved with a UTF-8 byte-order mark (Windows Notepad, PowerShell's "
            "Out-File) and CRLF line ends was refused as 'not valid JSON (Unexpected UTF-8 BOM)'; a submission "
            "file with one was read already (S9)")
def row_rig_file_with_a_byte_order_mark(env):
    path, images = _rig_files(env)
    text = json.dumps(json.loads(path.read_text()), indent=1).replace("\n", "\r\n")
    path.write_bytes(b"\xef\xbb\xbf" + text.encode())
    rc, out, err = env.cli("predict-images", "--checkpoint", env.ckpt, "--rig", path, "--out", env.tmp / "out",
                           "--device", "cpu", *images)
    assert rc == 0 and (env.tmp / "out" / "prediction.json").is_file(), err[-2000:]


@row("S11", "--resume OUT/best.pt while a later last.pt sits in the folder: the run goes on from best.pt (a valid "
            "choice) and its next save replaced last.pt without a word; now a note names both steps and the "
            "--resume that continues the later one")
def row_resume_best_with_a_later_last_pt(env):
    run = env.tmp / "run"
    _toy_run(env, [0.6, 0.3], "train.epochs=2")  # best.pt at step 2 (0.6), last.pt at step 4
    assert load_checkpoint(run / "best.pt")["step"] == 2 and load_checkpoint(run / "last.pt")["step"] == 4
    env.capsys.readouterr()
    _toy_run(env, [0.2, 0.1], "train.epochs=3", resume=str(run / "best.pt"))
    out = env.capsys.readouterr().out
    assert re.search(rf"note: {re.escape(str(run / 'last.pt'))} is at step 4, later than .*best\.pt; this run goes "
                     rf"on from step 2 .*--resume {re.escape(str(run / 'last.pt'))}", out), out
    env.capsys.readouterr()
    _toy_run(env, [], "train.epochs=3", "train.max_steps=6", resume=str(run / "last.pt"))  # its own last.pt: no note
    assert "note:" not in env.capsys.readouterr().out


@row("S11", "a nuScenes table saved with a UTF-8 byte-order mark (or not valid JSON): the one line named only the "
            "version folder and json's 'Unexpected UTF-8 BOM'; it now names the table file and what to do")
def row_nuscenes_table_with_a_byte_order_mark(env):
    root = env.shadow_world()
    table = root / "v1.0-trainval" / "calibrated_sensor.json"
    text = table.read_text()
    table.write_bytes(b"\xef\xbb\xbf" + text.encode())
    env.error(r"v1\.0-trainval: calibrated_sensor\.json starts with a UTF-8 byte-order mark, which the nuScenes "
              r"devkit cannot read; save it as UTF-8 without one", "export-gt", env.yaml, f"data.dataroot={root}",
              "--out", env.tmp / "gt.json")
    table.write_text(text[:-20])  # cut short
    env.error(r"v1\.0-trainval: calibrated_sensor\.json is not valid JSON: ", "export-gt", env.yaml,
              f"data.dataroot={root}", "--out", env.tmp / "gt.json")


# --- the twelfth sweep -------------------------------------------------------------------------------


@row("S12", "Mapper: a model moved to another precision in a notebook (mapper.model.half(), .double(), "
            ".bfloat16()) crashed with torch's raw 'Input type (torch.FloatTensor) and weight type ... should be "
            "the same' from the first convolution; one line names the dtype, model.float() and torch.autocast")
def row_mapper_model_of_another_dtype(env):
    from instagram_hdmap import Frame, Mapper
    from instagram_hdmap.data.rig import rig

    mapper = Mapper.from_checkpoint(env.ckpt, device="cpu")
    calib = rig((64, 36))
    frame = Frame({c: np.zeros((36, 64, 3), np.uint8) for c in mapper.cameras},
                  {c: calib[c].intrinsic for c in mapper.cameras},
                  {c: np.vstack([np.c_[calib[c].rot, calib[c].trans], [0, 0, 0, 1]]) for c in mapper.cameras})
    for cast, name in ((torch.nn.Module.half, "float16"), (torch.nn.Module.double, "float64")):
        cast(mapper.model)
        with pytest.raises(UserError, match=rf"model's weights are {name} .*call model\.float\(\).*torch\.autocast"):
            mapper(frame)
    mapper.model.float()
    with torch.autocast("cpu", dtype=torch.bfloat16):  # the way the message gives to lower the precision
        assert isinstance(mapper(frame), list)


@row("S12", "a Mapper whose model was left in training mode (mapper.model.train() after fine-tuning in a notebook) "
            "computed batch-norm statistics of each call's batch and updated the running ones: every output changed, "
            "without a word (sweep 12, B7); it now runs in eval mode and the model's mode is given back")
def row_mapper_model_left_in_training_mode(env):
    from instagram_hdmap import Frame, Mapper
    from instagram_hdmap.data.rig import rig

    mapper = Mapper.from_checkpoint(env.ckpt, device="cpu")
    calib = rig((64, 36))
    images = np.random.default_rng(0).integers(0, 255, (len(mapper.cameras), 36, 64, 3), dtype=np.uint8)
    frame = Frame(dict(zip(mapper.cameras, images)), {c: calib[c].intrinsic for c in mapper.cameras},
                  {c: np.vstack([np.c_[calib[c].rot, calib[c].trans], [0, 0, 0, 1]]) for c in mapper.cameras})
    batch = mapper.batch([frame])
    with torch.no_grad():
        expected = mapper.forward(batch)["pred_vertex_logits"]
        state = {k: v.clone() for k, v in mapper.model.state_dict().items()}
        mapper.model.train()
        got = mapper.forward(batch)["pred_vertex_logits"]
    assert torch.equal(got, expected)
    assert mapper.model.training  # the user's mode, given back
    assert all(torch.equal(v, state[k]) for k, v in mapper.model.state_dict().items())  # no running statistic moved
    in_training_mode = [(e.label, e.score) for e in mapper(frame)]
    mapper.model.eval()
    assert in_training_mode == [(e.label, e.score) for e in mapper(frame)]

@row("S12", "a YAML or --set of an older release's key (train.max_minutes, which checkpoints still load) was "
            "refused as an unknown key with the list of valid keys; it names the new key")
def row_renamed_config_key_named(env):
    old = env.tmp / "old.yaml"
    old.write_text(f"_base_: {env.yaml}\ntrain:\n  max_minutes: 5\n")
    env.error(r"'train\.max_minutes' was renamed 'train\.time_budget_min'", "model-summary", old)
    env.error(r"'train\.max_minutes' was renamed 'train\.time_budget_min'", "model-summary", env.yaml,
              "train.max_minutes=5")


@row("S12", "Evaluator.merge of the state of an evaluator of other classes (two classes into three) crashed with "
            "numpy's raw 'operands could not be broadcast together'; one of the same count but other names added its "
            "AP to the wrong classes. Both are named")
def row_evaluator_merge_of_other_classes(env):
    from instagram_hdmap.evaluation import EvaluationInputError, Evaluator

    line = {"pts": np.array([[0.0, 2.0], [10.0, 2.0]]), "label": 0}
    for protocol in ("vector", "raster"):
        three = Evaluator(protocol)
        three.update([[{**line, "score": 0.9}]], [[line]], tokens=["a"])
        for classes in (("divider", "boundary"), ("boundary", "ped_crossing", "divider")):
            with pytest.raises(EvaluationInputError, match="state of the classes divider, ped_crossing, boundary into "
                                                           "an evaluator of the classes " + ", ".join(classes)):
                Evaluator(protocol, classes=classes).merge(three.state_dict())
        same = Evaluator(protocol)
        same.merge(three.state_dict())  # the same classes: merged as before
        assert same.compute()["AP_class"]["divider"] == 1.0


@row("S12", "Evaluator.update: a label given as a 0-d tensor (a model's labels tensor iterated, as MapTR's "
            "labels_3d) was refused as 'must be an integer class id, got tensor(0)' while numpy integers were "
            "taken; a 0-d integer tensor or array is its integer, a float or bool one is still refused")
def row_evaluator_label_as_a_0d_tensor(env):
    from instagram_hdmap.evaluation import EvaluationInputError, Evaluator

    gt = {"pts": np.array([[0.0, 2.0], [10.0, 2.0]]), "label": 0}
    for label in (torch.tensor(0), np.array(0)):
        ev = Evaluator("vector")
        ev.update([[{**gt, "label": label, "score": torch.tensor(0.9)}]], [[gt]])
        assert ev.compute()["AP_class"]["divider"] == 1.0
    for label in (torch.tensor(0.0), torch.tensor(True)):
        with pytest.raises(EvaluationInputError, match="'label' must be an integer class id"):
            Evaluator("vector").update([[{**gt, "label": label, "score": 0.9}]], [[gt]])


@row("S12", "to_hdmapnet given mapper(frame)'s list as it is (or a list of frames' lists under one name) crashed "
            "with a raw \"'list' object has no attribute 'items'\"; a TypeError says it takes {frame name: elements}")
def row_to_hdmapnet_of_a_list(env):
    from instagram_hdmap import MapElement, to_hdmapnet

    element = MapElement("divider", np.zeros((3, 2), np.float32), False, np.float32(0.5), 0)
    with pytest.raises(TypeError, match=r"takes \{frame name: elements\}.*got a list"):
        to_hdmapnet([element])
    with pytest.raises(TypeError, match=r"frame 'a': expected a list of MapElement .*got list in it"):
        to_hdmapnet({"a": [[element]]})
    doc = json.loads(json.dumps(to_hdmapnet({"a": [element], "b": []})))
    assert doc["results"]["a"][0]["confidence_level"] == 0.5 and doc["results"]["b"] == []


@row("S12", "a dataset whose camera images were resized (a half-resolution copy of nuScenes) or rotated was refused "
            "as 'decodes to 100x57 at 1/2, expected 200x113 from its recorded size 400x225', reduced-decode sizes "
            "that name neither the file's size nor what to do; the line says both")
def row_resized_dataset_images_named(env):
    from PIL import Image

    root = env.shadow_world(copy_samples=True)
    for image in (root / "samples" / "CAM_FRONT").iterdir():
        with Image.open(image) as im:
            size = im.size
            im.resize((size[0] // 2, size[1] // 2)).save(image)
    env.error(rf"the file is {size[0] // 2}x{size[1] // 2}, a resized or rotated copy\? .*use the dataset's original "
              "images", "evaluate", env.yaml, f"data.dataroot={root}", "--checkpoint", env.ckpt, "--out", env.tmp / "e")


@row("S12", "an override written before the CONFIG file (model-summary train.lr=0.1 CONFIG) was refused as 'config "
            "file not found: train.lr=0.1'; the line says that overrides go after the CONFIG file")
def row_override_before_the_config(env):
    env.error(r"config file not found: train\.lr=0\.1; key=value overrides go after the CONFIG file",
              "model-summary", "train.lr=0.1", env.yaml)


@row("S13", "Evaluator(classes='divider') (one class given as a string) built an evaluator of the seven classes 'd', "
            "'i', 'v', ... and scored against them with exit 0; classes must be a list of distinct names, and one "
            "threshold given as a number is that threshold")
def row_evaluator_classes_as_a_string(env):
    from instagram_hdmap.evaluation import EvaluationInputError, Evaluator

    with pytest.raises(EvaluationInputError, match=r"classes must be a list of class names.*got 'divider'"):
        Evaluator("vector", classes="divider")
    with pytest.raises(EvaluationInputError, match="names a class twice"):
        Evaluator("vector", classes=("divider", "divider"))
    ev = Evaluator("vector", thresholds=1.0, classes=("divider",))
    assert ev.thresholds == (1.0,) and ev.classes == ("divider",)


@row("S13", "Evaluator.update given a dict {token: polylines} (KeyError: 0), a generator or None (\"object of type "
            "'generator' has no len()\") crashed, and one token given as a string was read as its characters; a "
            "generator is taken, the others are one line saying what update takes")
def row_evaluator_update_of_other_containers(env):
    from instagram_hdmap.evaluation import EvaluationInputError, Evaluator

    gt = {"pts": np.array([[0.0, 2.0], [10.0, 2.0]]), "label": 0}
    pred = {**gt, "score": 0.9}
    with pytest.raises(EvaluationInputError, match=r"not a dict; for \{token: polylines\} pass"):
        Evaluator().update({"a": [pred]}, {"a": [gt]})
    with pytest.raises(EvaluationInputError, match="one list of polylines per sample, got NoneType"):
        Evaluator().update(None, None)
    with pytest.raises(EvaluationInputError, match="tokens must be a list of one token per sample, got the string"):
        Evaluator().update([[pred], [pred]], [[gt], [gt]], tokens="ab")
    ev = Evaluator()
    ev.update(([pred] for _ in range(2)), ([gt] for _ in range(2)), sample_ids=iter([0, 1]))
    assert ev.compute()["AP_class"]["divider"] == 1.0 and ev.compute()["num_gt"]["divider"] == 2


@row("S13", "Evaluator.update given a model's outputs in a training loop (points and scores with requires_grad) "
            "crashed with torch's \"Can't call numpy() on Tensor that requires grad\", under both protocols; the "
            "values are taken, detached")
def row_evaluator_update_tensors_with_grad(env):
    from instagram_hdmap.evaluation import Evaluator

    gt = {"pts": np.array([[0.0, 2.0], [10.0, 2.0]]), "label": 0}
    pred = {"pts": torch.tensor(gt["pts"], requires_grad=True), "label": torch.tensor(0),
            "score": torch.tensor(0.9, requires_grad=True)}
    for protocol in ("vector", "raster"):
        ev = Evaluator(protocol)
        ev.update([[pred]], [[gt]])
        assert ev.compute()["AP_class"]["divider"] == 1.0


@row("S13", "Evaluator.merge given the other Evaluator (not its state_dict()) or None, and format_table given an "
            "Evaluator or a dict of other keys, crashed with raw TypeError / KeyError; an Evaluator is taken as its "
            "state (or computed), anything else is one line")
def row_evaluator_merge_and_format_table_of_other_objects(env):
    from instagram_hdmap.evaluation import EvaluationInputError, Evaluator
    from instagram_hdmap.evaluation.evaluator import format_table

    gt = {"pts": np.array([[0.0, 2.0], [10.0, 2.0]]), "label": 0}
    other = Evaluator()
    other.update([[{**gt, "score": 0.9}]], [[gt]], tokens=["a"])
    ev = Evaluator()
    ev.merge(other)
    assert ev.compute()["num_gt"]["divider"] == 1
    with pytest.raises(EvaluationInputError, match=r"takes another evaluator's state_dict\(\).*got NoneType"):
        ev.merge(None)
    assert format_table(ev) == format_table(ev.compute())
    with pytest.raises(EvaluationInputError, match="format_table takes the metrics of Evaluator.compute.*without"):
        format_table({"mAP": 0.5})


@row("S13", "read_submission with a role other than 'pred' / 'gt' ('prediction') read a submission as a GT, "
            "dropping its scores, with no word; write_submission of a list, with its arguments swapped, or keyed by "
            "a tuple crashed raw (AttributeError, json's TypeError); MapElement lists and bytes paths are taken")
def row_submission_read_write_misuse(env):
    from instagram_hdmap import MapElement
    from instagram_hdmap.evaluation.io import read_submission, write_submission

    pred = {"pts": np.array([[0.0, 2.0], [10.0, 2.0]]), "label": 0, "score": 0.25}
    path = env.tmp / "pred.json"
    write_submission(path, {"a": [pred], "b": [MapElement("boundary", pred["pts"], False, 0.5, 2)]})
    sub = read_submission(os.fsencode(path), "pred")
    assert sub.samples["a"][0]["score"] == 0.25 and sub.samples["b"][0]["label"] == 2
    with pytest.raises(ValueError, match="role must be 'pred'.*got 'prediction'"):
        read_submission(path, "prediction")
    with pytest.raises(TypeError, match=r"takes \{sample token: polylines\}, got a list"):
        write_submission(env.tmp / "x.json", [[pred]])
    with pytest.raises(TypeError, match=r"got a path \(the arguments are \(path, samples\)\)"):
        write_submission({"a": [pred]}, env.tmp / "x.json")
    with pytest.raises(TypeError, match=r"sample tokens are strings, got \('a', 1\)"):
        write_submission(env.tmp / "x.json", {("a", 1): [pred]})
    with pytest.raises(TypeError, match="submission file must be a file path.*got dict"):
        read_submission({"results": {}}, "pred")
    assert not (env.tmp / "x.json").exists()


@row("S13", "Mapper.forward(frame) / decode(frame) (\"'Frame' object has no attribute 'items'\"), batch([]) "
            "(torch's 'stack expects a non-empty TensorList'), mapper({name: frame}) ('expected Frame objects, got "
            "str') and Mapper(None, cfg) crashed raw; each is one line saying what the call takes, and Mapper takes "
            "a config file's path as the config")
def row_mapper_calls_of_other_objects(env):
    from instagram_hdmap import Frame, Mapper
    from instagram_hdmap.data.rig import rig

    mapper = Mapper.from_checkpoint(env.ckpt, device="cpu")
    calib = rig((64, 36))
    images = np.zeros((len(mapper.cameras), 36, 64, 3), dtype=np.uint8)
    frame = Frame(dict(zip(mapper.cameras, images)), {c: calib[c].intrinsic for c in mapper.cameras},
                  {c: np.vstack([np.c_[calib[c].rot, calib[c].trans], [0, 0, 0, 1]]) for c in mapper.cameras})
    with pytest.raises(TypeError, match=r"forward takes a model input batch .*got Frame; to map frames call"):
        mapper.forward(frame)
    with pytest.raises(TypeError, match=r"decode takes the model's outputs .*got Frame"):
        mapper.decode(frame)
    with pytest.raises(ValueError, match="Mapper.batch: no frames"):
        mapper.batch([])
    with pytest.raises(TypeError, match=r"not a dict; for \{name: frame\} use"):
        mapper({"a": frame})
    with pytest.raises(TypeError, match="Mapper takes a model .*got NoneType"):
        Mapper(None, mapper.config)
    env.yaml_copy = env.tmp / "cfg.yaml"
    from instagram_hdmap.config import save_config

    save_config(mapper.config, env.yaml_copy)
    again = Mapper(mapper.model, env.yaml_copy)
    assert again.config == mapper.config
    assert [(e.label, e.score) for e in again(frame)] == [(e.label, e.score) for e in mapper(frame)]


@row("S13", "load_config given a dict of keys or an ExperimentConfig, and Evaluator.from_config given a YAML path, "
            "crashed with pathlib's 'expected str, bytes or os.PathLike object, not dict' / \"'str' object has no "
            "attribute 'eval'\", and one override string was read as its characters; each is taken")
def row_load_config_of_a_dict_or_config(env):
    from instagram_hdmap.evaluation import Evaluator

    cfg = load_config({"train": {"lr": 0.01}, "eval": {"thresholds": [1.0]}})
    assert cfg.train.lr == 0.01
    again = load_config(cfg, "train.lr=0.02")
    assert again.train.lr == 0.02 and cfg.train.lr == 0.01  # a copy
    with pytest.raises(UserError, match="unknown config key 'train.lrr'"):
        load_config({"train": {"lrr": 0.1}})
    with pytest.raises(TypeError, match="config file must be a file path.*got int"):
        load_config(3)
    assert load_config(os.fsencode(env.yaml)) == load_config(env.yaml)
    ev = Evaluator.from_config(env.yaml)
    assert ev.classes == tuple(load_config(env.yaml).data.classes)


@row("S13", "MapElement compared (element in elements, a == b) raised numpy's 'truth value of an array ... is "
            "ambiguous' and could not be hashed (a set of elements); equal elements are equal and hash alike")
def row_map_element_equality_and_hash(env):
    from instagram_hdmap import MapElement

    pts = np.array([[0.0, 1.0], [2.0, 3.0], [4.0, 5.0]], np.float32)
    a, b = MapElement("divider", pts, False, 0.5, 0), MapElement("divider", pts.copy(), False, 0.5, 0)
    c = MapElement("divider", pts + 1, False, 0.5, 0)
    assert a == b and a != c and a in [c, b] and len({a, b, c}) == 2 and hash(a) == hash(b)


@row("S13", "a MapElement made with score None or points of another shape crashed later, in repr ('unsupported "
            "format string passed to NoneType') or to_hdmapnet (float(None)); it is refused where it is made")
def row_map_element_checked(env):
    from instagram_hdmap import MapElement

    pts = np.zeros((3, 2))
    with pytest.raises(TypeError, match="score a number in \\[0, 1\\], got .*score None"):
        MapElement("divider", pts, False, None, 0)
    with pytest.raises(ValueError, match=r"points must be a \[P, 2\] array .*got shape \[3, 3\]"):
        MapElement("divider", np.zeros((3, 3)), False, 0.5, 0)
    with pytest.raises(ValueError, match="score must be in \\[0, 1\\], got 2.0"):
        MapElement("divider", pts, False, 2.0, 0)
    assert repr(MapElement("divider", torch.zeros(3, 2), True, np.float32(0.5), 0)) == \
        "MapElement(divider, 3 points, closed, score 0.50)"


def _flicker_meter(env, **kwargs):
    """A FlickerMeter of the tiny config's grid, one GT divider 10 m long, and a valid update's arguments
    (two frames of one scene, the ego 1 m further along in the second)."""
    from instagram_hdmap.evaluation.consistency import FlickerMeter
    from instagram_hdmap.geometry import BEVGrid

    meter = FlickerMeter(BEVGrid.from_config(env.cfg().grid), **kwargs)
    gt = {"pts": np.array([[-5.0, 2.0], [5.0, 2.0]]), "label": 0}
    poses = np.stack([np.eye(4), np.eye(4)])
    poses[1, 0, 3] = 1.0
    return meter, gt, poses


@row("S13", "FlickerMeter.update given a label beyond num_classes, a negative or a fractional one crashed later in "
            "compute with a raw IndexError (or was cast); an EvaluationInputError names the sample (scene, frame)")
def row_flicker_meter_bad_labels(env):
    from instagram_hdmap.evaluation import EvaluationInputError

    meter, gt, poses = _flicker_meter(env)
    for label, pattern in ((3, r"unknown class id 3; expected 0\.\.2"), (-1, "unknown class id -1"),
                           (1.5, "'label' must be an integer class id, got 1.5")):
        with pytest.raises(EvaluationInputError, match=rf"sample \(scene 'a', frame 1\), GT polyline 0: {pattern}"):
            meter.update([[], []], [[gt], [dict(gt, label=label)]], ["a", "a"], [0, 1], poses)
    with pytest.raises(EvaluationInputError, match=r"scene 'a', frame 0\), prediction polyline 0: unknown class id 7"):
        meter.update([[dict(gt, label=7, score=0.9)]], [[gt]], ["a"], [0], poses[:1])
    assert meter.records == {}  # nothing of a refused batch is kept
    meter.update([[dict(gt, score=0.9)], [gt]], [[gt], [gt]], ["a", "a"], [0, 1], poses)  # no score: counts as 1
    assert meter.compute()["pairs"]["0"] == 1 and meter.compute()["flicker_mean"] == 0.0


@row("S13", "FlickerMeter.update given one [4, 4] pose for a batch (LinAlgError or a row taken for a pose), or a "
            "NaN pose or GT point (flicker 0.0, silently) now says which sample and what is wrong")
def row_flicker_meter_bad_poses_and_nan(env):
    from instagram_hdmap.evaluation import EvaluationInputError

    meter, gt, poses = _flicker_meter(env)
    with pytest.raises(EvaluationInputError, match=r"one \[4, 4\] pose for a batch of 2 samples; .*\[B, 4, 4\]"):
        meter.update([[], []], [[gt], [gt]], ["a", "a"], [0, 1], poses[0])
    with pytest.raises(EvaluationInputError, match=r"poses must have shape \[B, 4, 4\] .*got \[2, 3, 3\]"):
        meter.update([[], []], [[gt], [gt]], ["a", "a"], [0, 1], poses[:, :3, :3])
    nan = poses.copy()
    nan[1, 1, 3] = np.nan
    with pytest.raises(EvaluationInputError, match=r"sample \(scene 'a', frame 1\): its ego pose has NaN"):
        meter.update([[], []], [[gt], [gt]], ["a", "a"], [0, 1], torch.from_numpy(nan))
    with pytest.raises(EvaluationInputError, match=r"sample \(scene 'a', frame 0\), GT polyline 0: .*NaN"):
        meter.update([[], []], [[dict(gt, pts=np.array([[np.nan, 0.0], [1.0, 0.0]]))], [gt]], ["a", "a"], [0, 1],
                     poses)
    meter.update([[]], [[gt]], ["a"], [0], poses[0])  # one sample's [4, 4] is its pose
    assert len(meter.records) == 1


@row("S13", "FlickerMeter.update given Mapper's MapElement lists as predictions crashed with a raw AttributeError "
            "('MapElement' object has no attribute 'get'); they are read through MapElement.as_polyline()")
def row_flicker_meter_map_elements(env):
    from instagram_hdmap import MapElement

    results = []
    for as_element in (False, True):
        meter, gt, poses = _flicker_meter(env, classes=("divider", "ped_crossing", "boundary"))
        preds = [[MapElement("divider", gt["pts"], False, 0.8, 0)], []]
        if not as_element:
            preds = [[e.as_polyline() for e in p] for p in preds]
        meter.update(preds, [[gt], [gt]], ["a", "a"], [0, 1], poses)
        results.append(meter.compute())
    assert results[0] == results[1] and results[1]["flicker"]["divider"] == 1.0  # detected, then missed


@row("S13", "FlickerMeter.update given scenes as one string ('scene-0001': each character taken for a scene, NaN), "
            "or arguments of different lengths (zip cut them silently) is an EvaluationInputError naming the counts")
def row_flicker_meter_scenes_and_counts(env):
    from instagram_hdmap.evaluation import EvaluationInputError

    meter, gt, poses = _flicker_meter(env)
    with pytest.raises(EvaluationInputError, match=r"scenes must be a list of B scene names.*\['scene-0001'\]"):
        meter.update([[]], [[gt]], "scene-0001", [0], poses[:1])
    with pytest.raises(EvaluationInputError, match=r"one entry per sample .*got 1 preds, 2 gts, 2 scenes, 2 frames, "
                                                   r"2 poses"):
        meter.update([[]], [[gt], [gt]], ["a", "a"], [0, 1], poses)


@row("S13", "FlickerMeter.update given a frame index of 1.5 (cast to 1), -1 or a string is named with its sample")
def row_flicker_meter_bad_frames(env):
    from instagram_hdmap.evaluation import EvaluationInputError

    meter, gt, poses = _flicker_meter(env)
    for frame in (1.5, -1, "1", float("nan")):
        with pytest.raises(EvaluationInputError, match=r"sample 1 \(scene 'a'\): its frame index must be an integer"):
            meter.update([[], []], [[gt], [gt]], ["a", "a"], [0, frame], poses)
    meter.update([[], []], [[gt], [gt]], ["a", "a"], torch.tensor([0.0, 1.0]), poses)  # float-typed whole numbers
    assert sorted(meter.records) == [("a", 0), ("a", 1)]


@row("S13", "FlickerMeter(threshold_m=-1, num_points=1, classes of another length, ...) was taken (wrong or crashing "
            "later), and merge(meter) crashed raw; both name the argument")
def row_flicker_meter_bad_arguments(env):
    from instagram_hdmap.evaluation import EvaluationInputError

    for kwargs, pattern in (({"threshold_m": -1.0}, "threshold_m must be a finite distance > 0"),
                            ({"link_m": float("nan")}, "link_m must be a finite distance > 0"),
                            ({"num_points": 1}, "num_points must be an integer >= 2"),
                            ({"detect_points": 2.5}, "detect_points must be an integer >= 2"),
                            ({"min_shared_points": 0}, "min_shared_points must be an integer >= 1"),
                            ({"num_classes": 0}, "num_classes must be an integer >= 1"),
                            ({"num_classes": 3, "classes": ("divider", "boundary")},
                                 "classes must name the num_classes = 3 classes")):
        with pytest.raises(EvaluationInputError, match=rf"FlickerMeter: {pattern}"):
            _flicker_meter(env, **kwargs)
    meter, gt, poses = _flicker_meter(env)
    other, _, _ = _flicker_meter(env)
    other.update([[]], [[gt]], ["a"], [0], poses[:1])
    with pytest.raises(EvaluationInputError, match=r"merge takes another FlickerMeter's state_dict\(\).*got "
                                                   r"FlickerMeter; pass other\.state_dict\(\)"):
        meter.merge(other)
    with pytest.raises(EvaluationInputError, match=r"merge takes another FlickerMeter's state_dict\(\).*got dict"):
        meter.merge({"a": 1})
    meter.merge(other.state_dict())
    assert list(meter.records) == [("a", 0)]


@row("S13", "dataset['<sample token>'] and dataset[0:2] raised raw TypeErrors ('list indices must be integers'), "
            "an index past the end a bare 'list index out of range': they say what the index is and its range")
def row_dataset_index_not_an_int(env):
    ds = val_dataset(env.cfg())
    n, token = len(ds), ds.sample_tokens[1]
    with pytest.raises(TypeError, match=rf"takes one sample index, an int in 0\.\.{n - 1} .*got str .*"
                                        r"dataset\[dataset\.sample_tokens\.index\(token\)\]"):
        ds[token]
    with pytest.raises(TypeError, match=r"takes one sample index, .*got slice .*for several samples"):
        ds[0:2]
    with pytest.raises(IndexError, match=rf"sample index {n} is out of range: split 'val' has {n} samples"):
        ds[n]
    assert ds[ds.sample_tokens.index(token)]["sample_token"] == token == ds[np.int64(1)]["sample_token"]
    assert ds[-1]["sample_token"] == ds.sample_tokens[-1]


@row("S13", "Mapper: an ego_pose with NaN was refused as 'must be a finite 4x4 ... got shape [4, 4]' (the right "
            "shape); the RigError says it has NaN or infinite values")
def row_mapper_nan_ego_pose(env):
    from instagram_hdmap import Frame
    from instagram_hdmap.data.rig import RigError

    mapper, images, K, poses = _mapper_frame(env)
    pose = np.eye(4)
    pose[0, 3] = np.nan
    with pytest.raises(RigError, match=r"the frame's ego_pose has NaN or infinite values"):
        mapper.stream().step(Frame(images=images, intrinsics=K, cam_to_ego=poses, ego_pose=pose))


@row("S12", "Evaluator.merge of the same state twice (a notebook cell run again, a rank's state gathered twice) "
            "doubled every count and changed the AP with no word; a state whose every sample token is already in "
            "the evaluator is refused, samples in two merged states are a note, and merging states of other "
            "thresholds says which")
def row_evaluator_merge_of_the_same_state_twice(env):
    from instagram_hdmap.evaluation import EvaluationInputError, Evaluator

    gt = {"pts": np.array([[0.0, 2.0], [10.0, 2.0]]), "label": 0}
    far = {"pts": np.array([[0.0, -9.0], [10.0, -9.0]]), "label": 0, "score": 0.9}
    a, b = Evaluator(), Evaluator()
    a.update([[{**gt, "score": 0.8}], [far]], [[gt], [gt]], tokens=["s1", "s2"])
    b.update([[{**gt, "score": 0.7}]], [[gt]], tokens=["s3"])
    ev = Evaluator()
    ev.merge(a.state_dict())
    ev.merge(b.state_dict())
    expected = ev.compute()
    with pytest.raises(EvaluationInputError, match="every one of this state's 2 sample tokens is already in the "
                                                   "evaluator"):
        ev.merge(a.state_dict())
    assert ev.compute()["num_gt"] == expected["num_gt"] and ev.compute()["mAP"] == expected["mAP"]
    c = Evaluator()
    c.update([[{**gt, "score": 0.6}], [{**gt, "score": 0.6}]], [[gt], [gt]], tokens=["s3", "s4"])
    ev.merge(c)  # s3 is in two states: counted twice, and said
    metrics = ev.compute()
    assert metrics["counters"]["samples_in_two_merged_states"] == 1
    assert any("1 samples were in two merged states" in n for n in metrics["notes"])
    with pytest.raises(EvaluationInputError, match=r"cannot merge a vector state at thresholds \[0.5, 1.0, 1.5\] "
                                                   r"into a vector evaluator at \[1.0\]"):
        Evaluator(thresholds=1.0).merge(a.state_dict())



@row("S12", "Chamfer thresholds given in centimetres (evaluate-json --thresholds 50 100 150, eval.thresholds, "
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

@row("S14", "Evaluator(protocol='raster', grid=cfg) (a config given as the canvas) crashed with a raw "
            "\"'ExperimentConfig' object has no attribute 'xmin'\"; a config (or its grid section) is taken as the "
            "grid it describes, another object is one line; and Evaluator.update refused the MapElement lists that "
            "Mapper returns ('expected a dict with keys pts and label'): they are taken as their polylines")
def row_evaluator_grid_of_a_config_and_map_elements(env):
    from instagram_hdmap import MapElement
    from instagram_hdmap.evaluation import EvaluationInputError, Evaluator
    from instagram_hdmap.geometry import BEVGrid

    cfg = env.cfg()
    line = np.array([[0.0, 1.0], [5.0, 1.0]])
    gt, pred = {"pts": line, "label": 0}, {"pts": line, "label": 0, "score": 0.9}
    expected = Evaluator("raster", grid=BEVGrid.from_config(cfg.grid))
    expected.update([[pred]], [[gt]])
    for grid in (cfg, cfg.grid):
        ev = Evaluator("raster", grid=grid)
        ev.update([[pred]], [[gt]])
        assert ev.options["grid"] == expected.options["grid"] and ev.compute()["AP"]["divider"] == [1.0, 1.0, 1.0]
    with pytest.raises(EvaluationInputError, match="grid must be a BEVGrid .* got tuple"):
        Evaluator("raster", grid=(-8, 8, -4, 4))
    ev = Evaluator()
    ev.update([[MapElement("divider", line, False, 0.9, 0)]], [[gt]])
    assert ev.compute()["AP_class"]["divider"] == 1.0


@row("S14", "FlickerMeter.update given scenes as one string, fewer frame indices or poses than samples, one pose "
            "for all, poses None or a config as the grid crashed with raw IndexError / LinAlgError / AttributeError; "
            "frames given as timestamps in seconds (0.0, 0.5) were truncated to one frame and the second dropped as "
            "a repeat, and classes of another count than num_classes averaged a class unseen into flicker_mean "
            "(exit 0); each is one line, MapElement lists, 3x4 poses and a config's grid are taken")
def row_flicker_meter_inputs(env):
    from instagram_hdmap import MapElement
    from instagram_hdmap.evaluation import EvaluationInputError
    from instagram_hdmap.evaluation.consistency import FlickerMeter
    from instagram_hdmap.geometry import BEVGrid

    cfg = env.cfg()
    grid = BEVGrid.from_config(cfg.grid)
    line = np.array([[0.0, 1.0], [5.0, 1.0], [6.0, 2.0]])
    gt, pred = [{"pts": line, "label": 0}], [{"pts": line, "label": 0, "score": 0.9}]
    poses = np.stack([np.eye(4)] * 2)

    def meter_update(meter=None, **kw):
        meter = meter or FlickerMeter(grid)
        args = {"preds": [pred, []], "gts": [gt, gt], "scenes": ["s", "s"], "frames": [0, 1], "poses": poses, **kw}
        meter.update(**args)
        return meter.compute()

    for kw, pattern in (({"scenes": "s"}, "scenes must be a list of B scene names, one per sample, got one string"),
                        ({"frames": [0]}, "one entry per sample in each argument, got 2 preds, 2 gts, 2 scenes, 1 "
                                          "frames"),
                        ({"poses": np.eye(4)}, r"poses is one \[4, 4\] pose for a batch of 2 samples"),
                        ({"poses": None}, r"poses must have shape \[B, 4, 4\] \(ego -> world\), got \[\]"),
                        ({"frames": [0.0, 0.5]}, r"its frame index must be an integer >= 0 .*got 0.5"),
                        ({"gts": [[{"pts": line, "label": 5}], gt]}, "unknown class id 5")):
        with pytest.raises(EvaluationInputError, match=pattern):
            meter_update(**kw)
    with pytest.raises(EvaluationInputError, match=r"classes must name the num_classes = 3 classes"):
        FlickerMeter(grid, 3, ["divider"])
    with pytest.raises(EvaluationInputError, match="grid must be a BEVGrid"):
        FlickerMeter("grid")
    assert FlickerMeter(grid, classes=["divider"]).num_classes == 1
    base = meter_update()
    assert base["pairs"]["0"] == 1 and base["flips"]["0"] == 1  # detected in frame 0, missed in frame 1
    element = [MapElement("divider", line, False, 0.9, 0)]
    for same in (meter_update(FlickerMeter(cfg)), meter_update(poses=poses[:, :3]),
                 meter_update(preds=[element, []]), meter_update(frames=torch.tensor([0, 1])),
                 meter_update(frames=[0.0, 1.0])):
        assert same["pairs"] == base["pairs"] and same["flips"] == base["flips"]
    import instagram_hdmap.evaluation

    assert instagram_hdmap.evaluation.FlickerMeter is FlickerMeter  # the package's own name for it, too


@row("S14", "MapElement('boundary', pts, ..., class_index=0) (a name and a class id that disagree) was written as "
            "a divider by to_hdmapnet, a name of no class ('lane') was kept, and points with NaN wrote NaN into the "
            "submission (not JSON), all with no word; each is refused where the element is made")
def row_map_element_class_and_points(env):
    from instagram_hdmap import MapElement

    pts = np.array([[0.0, 0.0], [1.0, 0.0]])
    with pytest.raises(ValueError, match="label 'boundary' with class_index 0, which is 'divider'"):
        MapElement("boundary", pts, False, 0.5, 0)
    with pytest.raises(ValueError, match="label 'lane' with class_index 0"):
        MapElement("lane", pts, False, 0.5, 0)
    with pytest.raises(ValueError, match=r"class_index must be the class id 0..2 .* got 3"):
        MapElement("divider", pts, False, 0.5, 3)
    with pytest.raises(ValueError, match="points hold NaN or infinite coordinates"):
        MapElement("divider", np.array([[0.0, 0.0], [np.nan, 1.0]]), False, 0.5, 0)
    element = MapElement("boundary", pts, True, 0.5, torch.tensor(2))
    assert element.class_index == 2 and element.to_hdmapnet()["type"] == 2
    assert MapElement("ped_crossing", pts, True, 0.5, np.int64(1)).class_index == 1


@row("S14", "to_hdmapnet(elements, meta='vector') / write_submission(..., meta=...) of a meta that is not a dict "
            "crashed with Python's raw \"'str' object is not a mapping\"; it is a TypeError saying what meta is")
def row_submission_meta_not_a_dict(env):
    from instagram_hdmap import MapElement, to_hdmapnet
    from instagram_hdmap.evaluation import write_submission

    elements = {"tok": [MapElement("divider", np.array([[0.0, 0.0], [1.0, 0.0]]), False, 0.5, 0)]}
    with pytest.raises(TypeError, match=r"a submission's meta is a dict of its settings .* got str 'vector'"):
        to_hdmapnet(elements, meta="vector")
    with pytest.raises(TypeError, match="a submission's meta is a dict"):
        write_submission(env.tmp / "s.json", elements, meta=[("split", "val")])
    assert not (env.tmp / "s.json").exists()
    assert to_hdmapnet(elements, meta={"split": "val"})["meta"] == {"vector": True, "split": "val"}


@row("S14", "a camera JPEG carrying an EXIF orientation tag (a phone or an editor: 3, rotated 180 degrees) was "
            "decoded turned by OpenCV while its calibration and size check read the stored pixels: the model saw "
            "the image upside down, exit 0 (a 90-degree tag was blamed on 'a resized or rotated copy'); the tag is "
            "named, in the Mapper (predict-images) and in a dataset")
def row_exif_orientation(env):
    from PIL import Image

    from instagram_hdmap.data.transforms import ImageError, read_image

    src = next((env.world / "samples" / "CAM_FRONT").glob("*.jpg"))
    for tag, what in ((3, "rotated 180 degrees"), (6, "rotated 90 degrees")):
        exif = Image.Exif()
        exif[0x0112] = tag
        path = env.tmp / f"tag{tag}.jpg"
        with Image.open(src) as im:
            im.save(path, quality=95, exif=exif)
        with pytest.raises(ImageError, match=rf"carries the EXIF orientation tag {tag} \({what}\)"):
            read_image(path, 2)
    exif = Image.Exif()
    exif[0x0112] = 1  # the normal orientation (and a tag-less image, the datasets' own) decode as before
    with Image.open(src) as im:
        im.save(env.tmp / "tag1.jpg", quality=95, exif=exif)
    assert read_image(env.tmp / "tag1.jpg", 2)[0].shape == read_image(src, 2)[0].shape
    # a dataset copy whose camera images were re-saved with the tag: the sample names it
    world = env.shadow_world(copy_samples=True)
    for image in (world / "samples" / "CAM_BACK").glob("*.jpg"):
        exif = Image.Exif()
        exif[0x0112] = 3
        with Image.open(image) as im:
            im.load()
            im.save(image, quality=95, exif=exif)
    cfg = load_config(env.yaml, [f"data.dataroot={world}"])
    with pytest.raises(UserError, match="EXIF orientation tag 3"):
        val_dataset(cfg)[0]


@row("S14", "predict --index 0 --fps 5 (the frame rate of a --scene video given to one sample's pictures) was "
            "ignored with no word; it is one line before the model runs")
def row_predict_fps_without_video(env):
    forbid(env, "instagram_hdmap.cli.predict_sample", "the prediction")
    env.error(r"--fps is the frame rate of a --scene video .* drop --fps", "predict", env.yaml, "--checkpoint",
              env.ckpt, "--index", "0", "--fps", "5", "--out", env.tmp / "out")


@row("S14", "train --resume CONFIG.yaml (or a GT JSON; a text file as the checkpoint to resume) said 'give a "
            "checkpoint ... with --checkpoint', a flag train does not have; the line names no flag now")
def row_text_file_as_resume_checkpoint(env):
    gt = env.tmp / "gt.json"
    gt.write_text('{"results": {}}')
    line = env.error(r"gt.json is not a PyTorch checkpoint: it is a text file", "train", env.yaml,
                     f"train.out_dir={env.tmp / 'run'}", "--resume", gt)
    assert "--checkpoint" not in line


@row("S14", "mapper([frame0, frame1]) on a temporal model mapped every frame of the drive on its own, without the "
            "memory the model was built for, with no word; it warns once that mapper.stream() carries the memory "
            "(a single-frame model, or one frame, says nothing)")
def row_mapper_list_of_frames_of_a_temporal_model(env):
    import warnings

    from instagram_hdmap import Frame, Mapper
    from instagram_hdmap.data.rig import rig
    from instagram_hdmap.models import build_model

    cfg = load_config(env.yaml, ["model.temporal.memory=bev"])
    torch.manual_seed(0)
    mapper = Mapper(build_model(cfg).eval(), cfg)
    calib = rig((64, 36))
    images = np.zeros((len(mapper.cameras), 36, 64, 3), dtype=np.uint8)
    frame = Frame(dict(zip(mapper.cameras, images)), {c: calib[c].intrinsic for c in mapper.cameras},
                  {c: np.vstack([np.c_[calib[c].rot, calib[c].trans], [0, 0, 0, 1]]) for c in mapper.cameras},
                  ego_pose=np.eye(4))
    with pytest.warns(UserWarning, match=r"temporal model: mapper\(\[frames\]\) maps each frame on its own.*"
                                         r"mapper\.stream\(\)"):
        assert len(mapper([frame, frame])) == 2
    single = Mapper.from_checkpoint(env.ckpt, device="cpu")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mapper([frame, frame])  # said once
        mapper(frame)
        single([frame, frame])
    # a single-frame model whose config asks for persistence (sweep 16): the list keeps nothing either
    persisting = Mapper.from_checkpoint(env.ckpt, device="cpu", overrides=["model.temporal.persist_frames=1"])
    with pytest.warns(UserWarning, match=r"persist_frames is set: mapper\(\[frames\]\) maps each frame on its own"):
        persisting([frame, frame])



@row("S15", "benchmarks/*.py: a count flag of 0 (eval_speed --samples 0, sinkhorn_speed --runs 0) crashed with a "
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


@row("S15", "Mapper / MapStream: an ego_pose whose last row is not [0, 0, 0, 1] (a transposed pose, the translation in "
            "the last row: its rotation part is still a rotation and its translation column 0, so a temporal model "
            "fused its memory as if the ego stood still) was taken with no word; it is a RigError as cam_to_ego was. "
            "MapStream.step(frame, images=...) dropped the fields with no word; it is a TypeError")
def row_ego_pose_transposed(env):
    from instagram_hdmap import Frame, Mapper
    from instagram_hdmap.data.rig import RigError, rig

    mapper = Mapper.from_checkpoint(env.ckpt, device="cpu")
    calib = rig((64, 36))
    images = dict(zip(mapper.cameras, np.zeros((len(mapper.cameras), 36, 64, 3), dtype=np.uint8)))
    pose = np.eye(4)
    pose[:3, 3] = [12.0, -3.0, 0.0]
    frame = Frame(images, {c: calib[c].intrinsic for c in mapper.cameras},
                  {c: np.vstack([np.c_[calib[c].rot, calib[c].trans], [0, 0, 0, 1]]) for c in mapper.cameras},
                  ego_pose=pose)
    mapper(frame)  # the right way round maps
    with pytest.raises(RigError, match=r"ego_pose has the last row \[12.0, -3.0, 0.0, 1.0\], not \[0, 0, 0, 1\]: "
                                       r"transposed"):
        mapper(Frame(frame.images, frame.intrinsics, frame.cam_to_ego, ego_pose=pose.T.copy()))
    with pytest.raises(TypeError, match="MapStream.step takes a Frame or the fields .* not both"):
        mapper.stream().step(frame, images=images)


@row("S15", "Mapper.from_onnx / predict --onnx of a PyTorch checkpoint said 'not a readable ONNX file (DecodeError: "
            "... Wire format was corrupt)', of a folder 'ONNX file not found', and from_onnx(path, device='cuda') "
            "'unknown decoding option(s) device'; each says what it is now (device='cpu' is taken)")
def row_onnx_given_a_checkpoint(env):
    pytest.importorskip("onnx")
    from instagram_hdmap import Mapper
    from instagram_hdmap.inference import DeployError

    with pytest.raises(DeployError, match=r"random\.pt is a PyTorch checkpoint, not an ONNX file"):
        Mapper.from_onnx(env.ckpt)
    with pytest.raises(DeployError, match=r"ONNX file not found: .* \(it is a folder\)"):
        Mapper.from_onnx(env.tmp)
    with pytest.raises(TypeError, match=r"runs the ONNX file with onnxruntime on the CPU: device='cuda'"):
        Mapper.from_onnx(env.tmp / "model.onnx", device="cuda")
    env.error(r"random\.pt is a PyTorch checkpoint, not an ONNX file", "predict", env.yaml, "--onnx", env.ckpt,
              "--index", "0", "--out", env.tmp / "out")


@row("S15", "predict-images --rig RIG FOLDER (the folder of the camera images instead of the files) said '1 image(s) "
            "for the 6 cameras'; the folder is named as a folder. --name '' (an unset shell variable) wrote the frame "
            "under the key '' with exit 0; it is refused")
def row_predict_images_folder(env):
    path, images = _rig_files(env)
    env.error(r"--name '' is empty: give the frame's name in prediction\.json", "predict-images", "--checkpoint",
              env.ckpt, "--rig", path, "--out", env.tmp / "out", "--device", "cpu", "--name", "", *images)
    env.error(r"is a folder: give the image files themselves, one per camera of rig file .*CAM_FRONT_LEFT",
              "predict-images", "--checkpoint", env.ckpt, "--rig", path, "--out", env.tmp / "out", "--device", "cpu",
              env.tmp)


@row("S15", "an Argoverse 2 root read with data.dataset left at nuscenes said 'versions in ROOT: none (set "
            "data.version)'; it says the root is an AV2 one: set data.dataset=av2")
def row_nuscenes_dataset_on_an_av2_root(env):
    av2 = env.request.getfixturevalue("av2_world")
    env.error(r"it is an Argoverse 2 sensor-dataset root: set data\.dataset=av2", "export-gt", env.yaml,
              f"data.dataroot={av2}", "--out", env.tmp / "gt.json")


@row("S15", "export-gt / show-gt without --split read the split named 'val' whatever data.val_split said (export-gt "
            "CONFIG data.val_split=train wrote the val GT, exit 0: evaluate scores data.val_split); they take the "
            "config's split now (--split still chooses)")
def row_export_gt_follows_data_val_split(env):
    rc, out, err = env.cli("export-gt", env.yaml, "data.val_split=train", "--out", env.tmp / "gt.json")
    assert rc == 0, err
    gt = json.loads((env.tmp / "gt.json").read_text())
    assert gt["meta"]["split"] == "train" and len(gt["results"]) == len(val_dataset(env.cfg("data.val_split=train")))
    rc, out, err = env.cli("export-gt", env.yaml, "data.val_split=train", "--split", "val", "--out", env.tmp / "v.json")
    assert rc == 0 and json.loads((env.tmp / "v.json").read_text())["meta"]["split"] == "val"


@row("S15", "two synth runs of one --out started together (no --force): each found the folder absent at its start, "
            "and the later one's final rename replaced the earlier one's world, both exit 0; the later one now "
            "keeps the folder and says so")
def row_synth_out_filled_while_generating(env):
    from instagram_hdmap.data.synthetic.jobs import write_world

    out = env.tmp / "world"

    def write(tmp):  # the other run finishes while this one renders
        out.mkdir()
        (out / "world.json").write_text('{"seed": 1}')
        (tmp / "world.json").write_text('{"seed": 2}')
        return {"seed": 2}

    with pytest.raises(UserError, match=r"the folder was filled while this world was generated .* pass --force"):
        write_world(out, False, write)
    assert json.loads((out / "world.json").read_text()) == {"seed": 1}
    assert [p.name for p in env.tmp.iterdir()] == ["world"]  # this run's temporary folder is gone
    out2 = env.tmp / "other"
    assert write_world(out2, False, lambda tmp: (tmp / "world.json").write_text("{}") and {}) == {}  # alone: written
    assert (out2 / "world.json").is_file()


@row("S15", "train --resume ANOTHER_RUN/last.pt into a new train.out_dir, of a run whose schedule was complete, "
            "printed 'nothing left to train' and ended on 'outputs in NEW_DIR' with no checkpoint there; the note "
            "says the outputs stay in the checkpoint's run and how to train on from it (train.init_from)")
def row_resume_a_finished_run_into_another_folder(env):
    first = env.tmp / "run"
    _toy_run(env, [0.5], "train.epochs=1")
    env.capsys.readouterr()
    other = env.tmp / "other"
    _toy_run(env, [], "train.epochs=1", f"train.out_dir={other}", resume=str(first / "last.pt"))
    out, err = env.capsys.readouterr()
    assert re.search(rf"completed its schedule: nothing left to train; its run's outputs stay in "
                     rf"{re.escape(str(first))}, train\.out_dir={re.escape(str(other))} gets no checkpoint "
                     r".*train\.init_from=", out + err)
    assert not (other / "last.pt").exists()


@row("S16", "persistence.Persistence (the element persistence of model.temporal.persist_frames, a documented API: "
            "keep(preds, scenes, frames, poses)): scenes given as one string or fewer frames than samples silently "
            "returned fewer outputs than samples (zip), frames as timestamps (0.0, 0.5) were truncated to one frame "
            "(nothing kept, no word), one [4, 4] pose for a batch, poses None, a singular or NaN pose, 3-D pts, a "
            "class name as label, an element without 'score' and Persistence(cfg) were raw IndexError / LinAlgError "
            "/ KeyError / AttributeError or a silent restart; each is a PersistenceInputError (a ValueError) naming "
            "the argument and sample (a config's grid, numpy integers and 3x4 poses are taken). A turn beyond "
            "model.temporal.max_turn_deg (a pose in the wrong frame) carried the elements to the wrong place; it "
            "starts the scene anew as the temporal memory does")
def row_persistence_inputs(env):
    from instagram_hdmap.geometry import BEVGrid
    from instagram_hdmap.persistence import Persistence, PersistenceInputError

    cfg = env.cfg("model.temporal.persist_frames=1")
    grid = BEVGrid.from_config(cfg.grid)
    el = {"pts": np.array([[-2.0, 1.0], [0.0, 1.0], [2.0, 1.0]], np.float32), "label": 0, "score": 0.9}
    eye, moved = np.eye(4), np.eye(4)
    moved[0, 3] = 1.0
    two = np.stack([eye, moved])
    for args, pattern in [
        (([[el], [el]], "s", [0, 1], two), r"scenes must be a list of B scene names"),
        (([[el], [el]], ["s", "s"], [0], two), r"one entry per sample in each argument, got 2 preds, 2 scenes, 1 "),
        (([[el], []], ["s", "s"], [0.0, 0.5], two), r"sample 1 \(scene 's'\): its frame index must be an integer"),
        (([[el], [el]], ["s", "s"], [0, 1], eye), r"poses must be B ego -> world transforms \[B, 4, 4\]"),
        (([[el], [el]], ["s", "s"], [0, 1], None), r"poses must be B ego -> world transforms"),
    ]:
        keep = Persistence(grid, frames=1)
        with pytest.raises(PersistenceInputError, match=pattern):
            keep(*args)
    bad_steps = [
        ([el], np.full((4, 4), np.nan), r"frame 1: its ego pose has NaN or infinite values"),
        ([el], np.zeros((4, 4)), r"frame 1: its ego pose is not a rigid transform"),
        ([{**el, "pts": np.zeros((3, 3))}], moved, r"element 0's pts must be \[P, 2\]"),
        ([{**el, "label": "divider"}], moved, r"element 0's label must be a class index"),
        ([{"pts": el["pts"], "label": 0}], moved, r"element 0 has no 'score'"),
    ]
    for preds, pose, pattern in bad_steps:
        keep = Persistence(grid, frames=1)
        keep.step([el], "s", 0, eye)
        with pytest.raises(ValueError, match=pattern):
            keep.step(preds, "s", 1, pose)
    keep = Persistence(cfg, frames=np.int64(1))  # a config's grid, a numpy integer
    keep.step([el], "s", 0, eye[:3])  # a 3x4 pose
    out = keep.step([], "s", 1, moved[:3])
    assert len(out) == 1 and out[0]["score"] == pytest.approx(0.45)
    turned = np.eye(4)
    turned[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]  # 90 degrees in one frame
    keep = Persistence.from_config(cfg)  # model.temporal.max_turn_deg = 60
    keep.step([el], "s", 0, eye)
    assert keep.step([], "s", 1, turned) == [] and keep.kept == 0


@row("S16", "predict --gt-as-prediction model.temporal.persist_frames=2 dropped the persistence with no word; a note "
            "says it is not applied to the GT")
def row_persist_with_gt_as_prediction(env):
    rc, out, err = env.cli("predict", env.yaml, "--gt-as-prediction", "--index", "0", "--out", env.tmp / "p",
                           "model.temporal.persist_frames=2")
    assert rc == 0, err
    assert "model.temporal.persist_frames=2 is not applied to --gt-as-prediction" in out + err


@row("S16", "benchmarks/temporal.py --persist-decay D without --persist trained and evaluated the runs without "
            "persistence, the decay dropped with no word; it is one 'temporal.py: error:' line, exit 2")
def row_benchmark_persist_decay_alone(env):
    p = subprocess.run([sys.executable, str(REPO / "benchmarks" / "temporal.py"), "--persist-decay", "0.7", "--out",
                        str(env.tmp / "b")], capture_output=True, text=True, timeout=120, cwd=REPO)
    lines = [ln for ln in p.stderr.splitlines() if ln.startswith("temporal.py")]
    assert p.returncode == 2 and len(lines) == 1 and "Traceback" not in p.stderr, p.stderr[-2000:]
    assert "--persist-decay 0.7 needs --persist FRAMES" in lines[0] and not (env.tmp / "b").exists()


@row("S16", "instagram_hdmap.data: collate_fn of samples of two image sizes was torch's raw 'stack expects each tensor "
            "to be equal size' naming no key, of a sample without a key a raw KeyError, of [] 'max() arg is an empty "
            "sequence', of one sample dict 'string indices must be integers'; build_dataset(path, ...) was "
            "\"'str' object has no attribute 'data'\", split=['val'] 'unhashable type', split=None read the split "
            "'None', augment='no' augmented. Each names the key / sample / argument (a YAML path is loaded)")
def row_collate_and_build_dataset_arguments(env):
    from instagram_hdmap.data import build_dataset
    from instagram_hdmap.data.base import collate_fn

    ds = build_dataset(env.cfg(), "val", augment=False)
    small = build_dataset(env.cfg("data.image_size=[32,96]"), "val", augment=False)
    s0, s1 = ds[0], ds[1]
    with pytest.raises(ValueError, match=r"'images' has shape \[6, 3, 64, 160\] in sample 0 .* and shape "
                                         r"\[6, 3, 32, 96\] in sample 1"):
        collate_fn([s0, small[0]])
    with pytest.raises(ValueError, match=r"sample 1 \('\w+'\) has no 'ego_pose'"):
        collate_fn([s0, {k: v for k, v in s1.items() if k != "ego_pose"}])
    with pytest.raises(ValueError, match="no samples to batch"):
        collate_fn([])
    with pytest.raises(TypeError, match=r"for one sample: collate_fn\(\[sample\]\)"):
        collate_fn(s0)
    assert collate_fn((s0, s1))["images"].shape[0] == 2  # a tuple, as before
    assert len(build_dataset(env.yaml, "val")) == len(ds)  # a YAML path is loaded
    for split in (["val"], None):
        with pytest.raises(TypeError, match="split must be one split name"):
            build_dataset(env.cfg(), split)
    with pytest.raises(TypeError, match="augment must be True, False or None"):
        build_dataset(env.cfg(), "val", augment="no")


def _torchrun_cli(*argv) -> subprocess.CompletedProcess:
    """``torchrun --nproc_per_node 2 -m instagram_hdmap.cli ARGV`` (gloo on the CPU) on a free port."""
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    return subprocess.run([sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_port",
                           str(port), "-m", "instagram_hdmap.cli", *map(str, argv)],
                          capture_output=True, text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"})


@row("S16", "evaluate under torchrun with model.temporal.persist_frames: the note (and metrics.json) counted the "
            "elements kept on rank 0 only (a temporal model's scenes are spread over the ranks: 8 of 16, exit 0); "
            "the count is summed over the ranks")
def row_persisted_count_under_torchrun(env):
    from instagram_hdmap.models import build_model

    torch.manual_seed(0)
    cfg = env.cfg("model.temporal.memory=bev")
    ckpt = save_checkpoint({"model": build_model(cfg).state_dict(), "config": config_to_dict(cfg)},
                           env.tmp / "temporal.pt")
    args = ["evaluate", str(env.yaml), "--checkpoint", str(ckpt), "model.temporal.persist_frames=2",
            "model.gnn.conf_threshold=0.0", "model.gnn.match_threshold=0.01", "eval.batch_size=1",
            "data.val_split=train"]

    def kept(metrics: Path) -> int:
        notes = json.loads(metrics.read_text())["meta"]["config_notes"]
        return int(next(re.search(r"persist_frames=2: (\d+) map elements", n).group(1) for n in notes
                        if "persist_frames=2:" in n))

    rc, out, err = env.cli(*args, "--out", env.tmp / "one")
    assert rc == 0, err
    p = _torchrun_cli(*args, "--out", env.tmp / "two")
    assert p.returncode == 0, p.stderr[-3000:]
    assert kept(env.tmp / "one" / "metrics.json") > 0
    assert kept(env.tmp / "two" / "metrics.json") == kept(env.tmp / "one" / "metrics.json")


@row("S16", "torchrun --nproc_per_node 2 train with train.batch_size=3 (or 1): the README says it is the batch over "
            "all processes, but each rank took 3 // 2 = 1 (at least 1), so it trained with a total of 2, exit 0, no "
            "word; a batch the ranks do not divide is one 'train: error:' line per rank, exit 2, before the run folder")
def row_train_batch_not_divided_by_ranks(env):
    out = env.tmp / "run"
    p = _torchrun_cli("train", env.yaml, f"train.out_dir={out}", "train.max_steps=1", "train.batch_size=3")
    lines = [ln for ln in p.stderr.splitlines() if ln.startswith("instagram-hdmap train: error:")]
    assert p.returncode != 0 and len(lines) == 2, p.stderr[-3000:]  # one per rank
    assert "'train.batch_size'=3 is the batch over all 2 processes of torchrun" in lines[0]
    assert not out.exists()


@row("S16", "torchrun --nproc_per_node 2 train: every rank printed 'done: epoch E, step S; outputs in OUT' (the run's "
            "other lines are rank 0's); it is printed once (and train.batch_size=2 over 2 ranks trains)")
def row_train_done_printed_once_under_torchrun(env):
    p = _torchrun_cli("train", env.yaml, f"train.out_dir={env.tmp / 'r'}", "train.max_steps=1", "train.batch_size=2")
    assert p.returncode == 0, p.stderr[-3000:]
    assert [ln for ln in p.stdout.splitlines() if ln.startswith("done:")] == [
        f"done: epoch 0, step 1; outputs in {env.tmp / 'r'}"], p.stdout


# ==================================================================================================
# Sweep 17: faults, killed runs, the file system
# ==================================================================================================


@row("S17", "Ctrl-C (or a SIGTERM) during a training's validation: last.pt was saved with the epoch counted as "
            "done, so the resume skipped that validation; after the final epoch it said 'completed its schedule: "
            "nothing left to train', exit 0, with the run never validated and no best.pt. last.pt records the cut "
            "validation and the resume runs it first")
def row_interrupted_validation_runs_on_resume(env):
    from instagram_hdmap import train as train_module

    real, calls = train_module.evaluate, []

    def ctrl_c_in_the_first(*args, **kwargs):
        calls.append(1)
        if len(calls) == 1:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    env.monkeypatch.setattr(train_module, "evaluate", ctrl_c_in_the_first)
    run = env.tmp / "run"
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={run}")
    assert rc == 130 and (run / "last.pt").is_file() and not (run / "best.pt").exists(), (rc, err[-2000:])
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={run}", "--resume", run / "last.pt")
    assert rc == 0, err[-2000:]
    assert len(calls) == 2, "the interrupted validation was not run again"
    assert re.search(r"validation after step \d+ was interrupted; running it first", out), out
    assert (run / "best.pt").is_file() and not load_checkpoint(run / "last.pt")["validation_pending"]
    assert len((run / "log.jsonl").read_text().splitlines()) == 1  # the epoch's line, written once


@row("S17", "train --resume after the training split changed (a scene removed from data.splits_file, another "
            "data.dataroot): the schedule was recounted over the new split, so a run of 6 samples resumed on 3 said "
            "'done' after no step, exit 0, and the saved position skipped or repeated samples; the checkpoint keeps "
            "the split's sample count and token hash, and another split is named (the same data moved elsewhere "
            "resumes)")
def row_resume_with_another_training_split(env):
    run = env.tmp / "run"
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={run}", "train.epochs=2", "train.max_steps=1")
    assert rc == 0, err[-2000:]
    splits = json.loads((env.world / "splits.json").read_text())
    fewer = env.tmp / "fewer.json"
    fewer.write_text(json.dumps({**splits, "train": splits["train"][:1]}))
    env.error(r"last\.pt was trained on another training split \(\d+ samples then, \d+ now.*train\.init_from=",
              "train", env.yaml, f"train.out_dir={run}", "train.epochs=2", f"data.splits_file={fewer}",
              "--resume", run / "last.pt")
    moved = env.tmp / "moved"
    moved.symlink_to(env.world)
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={run}", "train.epochs=2", "train.max_steps=2",
                           f"data.dataroot={moved}", "--resume", run / "last.pt")
    assert rc == 0, err[-2000:]


@row("S17", "evaluate --out OLD killed between its two writes (submission.json, then metrics.json): OLD held the new "
            "checkpoint's submission beside the metrics of the evaluation before, a pair that looked whole; both are "
            "written to temporaries and renamed together, so the earlier pair stays as it was")
def row_evaluate_killed_between_its_two_files(env):
    from instagram_hdmap import predict as predict_module

    out = env.tmp / "e"
    rc, _, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", out)
    assert rc == 0 and (out / "metrics.json").is_file(), err[-2000:]
    before = {name: (out / name).read_bytes() for name in ("submission.json", "metrics.json")}

    def killed(*args, **kwargs):
        raise KeyboardInterrupt

    env.monkeypatch.setattr(predict_module, "write_json", killed)
    rc, _, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", out, "data.val_split=train")
    assert rc == 130, err[-2000:]
    assert {name: (out / name).read_bytes() for name in before} == before  # the earlier pair, whole
    assert sorted(p.name for p in out.iterdir()) == ["metrics.json", "submission.json"]  # no temporaries


@row("S17", "an output path on a read-only file system (a read-only mount or snapshot) was 'no permission to write "
            "in DIR', which sends the user to chmod; it is named as a read-only file system")
def row_read_only_file_system_named(env):
    from types import SimpleNamespace

    from instagram_hdmap import files

    ro = env.tmp / "ro"
    ro.mkdir()
    real_access, real_statvfs = os.access, os.statvfs
    env.monkeypatch.setattr(files.os, "access", lambda p, mode, *a, **k: False if Path(p) == ro else
                            real_access(p, mode, *a, **k))
    env.monkeypatch.setattr(files.os, "statvfs", lambda p: SimpleNamespace(f_flag=os.ST_RDONLY) if Path(p) == ro
                            else real_statvfs(p))
    env.error(r"--out .*gt\.json: .*ro is on a read-only file system", "export-gt", env.yaml, "--out", ro / "gt.json")
    env.error(r"--out .*ro: is on a read-only file system", "evaluate", env.yaml, "--checkpoint", env.ckpt,
              "--out", ro)


@row("S17", "train --resume DIR/last.pt where DIR holds no run at all (a wrong folder): 'the run in DIR stopped before "
            "its first checkpoint ... run the same command without --resume', a run that never was; it says DIR "
            "holds no training run")
def row_resume_from_a_folder_without_a_run(env):
    empty = env.tmp / "elsewhere"
    empty.mkdir()
    env.error(r"checkpoint not found: .*elsewhere/last\.pt; .*elsewhere holds no training run", "train", env.yaml,
              f"train.out_dir={env.tmp / 'run'}", "--resume", empty / "last.pt")


@row("S17", "synth --out WORLD --force where WORLD also holds a training run or an evaluation (train.out_dir or "
            "evaluate --out inside the dataset root): the run was deleted with the old world, exit 0; such entries are "
            "named and nothing is generated")
def row_synth_force_over_a_world_holding_a_run(env):
    world = env.tmp / "w"
    (world / "run").mkdir(parents=True)
    (world / "world.json").write_text("{}")
    (world / "run" / "last.pt").write_bytes(b"a checkpoint")
    env.error(r"--out .*w: besides the synthetic world it holds run, which --force would delete", "synth", "--out",
              world, "--force", "--scenes-train", "1", "--scenes-val", "1", "--samples-per-scene", "1",
              "--image-size", "320x180")
    assert (world / "run" / "last.pt").read_bytes() == b"a checkpoint"


@row("S17", "a config's relative data.dataroot / data.splits_file, the run started from another folder than the "
            "config's: 'dataroot not found: world', which reads as if the world were gone; it says that a relative "
            "path is read from the current folder and names it")
def row_relative_dataroot_from_another_folder(env):
    env.error(r"dataroot not found: world .*a relative path is read from the current folder, .+", "export-gt",
              env.yaml, "data.dataroot=world", "--out", env.tmp / "gt.json")
    env.error(r"splits file not found: nowhere/splits\.json .*a relative path is read from the current folder",
              "export-gt", env.yaml, "data.splits_file=nowhere/splits.json", "--out", env.tmp / "gt.json")


@row("S17", "train.out_dir a folder of other files (train.out_dir=. in a project folder): refused, but told to 'pass "
            "--resume ./last.pt to continue it' (no such checkpoint: a second error); it says what to do instead")
def row_out_dir_of_other_files(env):
    out = env.tmp / "project"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    line = env.error(r"holds files that are not a run's \(notes\.txt\); choose another train\.out_dir", "train",
                     env.yaml, f"train.out_dir={out}")
    assert "--resume" not in line


@row("S17", "synth --out W --force over an existing world, Ctrl-C (or a kill) while the old world was being removed "
            "(seconds for a large world): W was left half-deleted but looking whole (world.json, tables and maps, "
            "part of its images) and the new world was removed with the temporaries; the old world is renamed aside "
            "and removed only once the new one is in place")
def row_synth_force_interrupted_while_removing_the_old_world(env):
    import shutil as shutil_module

    world = env.tmp / "w"
    small = ["--scenes-train", "1", "--scenes-val", "1", "--samples-per-scene", "1", "--image-size", "320x180"]
    rc, _, err = env.cli("synth", "--out", world, *small)
    assert rc == 0, err[-2000:]
    real = shutil_module.rmtree

    def ctrl_c_half_way(path, *args, **kwargs):  # the removal of the old world, cut after its images
        name = Path(path).name
        if name == "w" or name.startswith(".w.old-"):
            real(Path(path) / "samples")
            raise KeyboardInterrupt
        return real(path, *args, **kwargs)

    env.monkeypatch.setattr(shutil_module, "rmtree", ctrl_c_half_way)
    rc, _, err = env.cli("synth", "--out", world, "--force", "--seed", "1", *small)
    env.monkeypatch.setattr(shutil_module, "rmtree", real)
    assert rc == 130, err[-2000:]
    assert json.loads((world / "world.json").read_text())["seed"] == 1, "the new world is not in place"
    assert any((world / "samples").rglob("*.jpg")), "the world at --out lost its images"


@row("S17", "a low limit on open files (ulimit -n 40) with data.num_workers=1: the workers pass each tensor through a "
            "file descriptor, which ran out; the run hung for good, a thread printing 'OSError: [Errno 24] Too many "
            "open files' tracebacks without end. The soft limit is raised towards the hard one, and below 4096 the "
            "tensors go through named shared memory: the run works")
def row_open_file_limit_with_data_workers(env):
    import resource

    def low_limit():
        resource.setrlimit(resource.RLIMIT_NOFILE, (40, 40))

    run = env.tmp / "run"
    try:
        p = subprocess.run([sys.executable, "-m", "instagram_hdmap.cli", "train", str(env.yaml), f"train.out_dir={run}",
                            "train.max_steps=1", "data.num_workers=1"], capture_output=True, text=True, timeout=150,
                           preexec_fn=low_limit, env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path),
                                                      "OMP_NUM_THREADS": "1"})
    except subprocess.TimeoutExpired as e:
        raise AssertionError("the training hung (too many open files)") from e
    assert p.returncode == 0 and "Too many open files" not in p.stderr, p.stderr[-3000:]
    assert (run / "last.pt").is_file()


@row("S17", "a training killed after its last checkpoint (kill -9, a power cut) and resumed: the steps it had trained "
            "since were logged to TensorBoard twice, the killed run's and the resumed run's (a second curve over "
            "them, other values where the resume changed train.lr); the resumed run purges the killed one's events "
            "after its checkpoint")
def row_tensorboard_after_a_kill_and_resume(env):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from instagram_hdmap.train import TrainingRun

    class Killed(BaseException):  # not an exception the run handles: no save at the kill, as with kill -9
        pass

    on_step = TrainingRun.on_step

    def killed_after_step_3(self, info):
        on_step(self, info)
        if info.step == 3:
            raise Killed

    env.monkeypatch.setattr(TrainingRun, "on_step", killed_after_step_3)
    run = env.tmp / "run"
    args = ["train", env.yaml, f"train.out_dir={run}", "train.epochs=2", "train.checkpoint_every=2",
            "train.val_every=100"]
    with pytest.raises(Killed):
        env.cli(*args)
    assert torch.load(run / "last.pt", weights_only=True)["step"] == 2
    env.monkeypatch.setattr(TrainingRun, "on_step", on_step)
    rc, _, err = env.cli(*args, "--resume", run / "last.pt")
    assert rc == 0, err[-2000:]
    events = EventAccumulator(str(run / "tb"))
    events.Reload()
    steps = [e.step for e in events.Scalars("train/lr")]
    assert steps == sorted(set(steps)) and 3 in steps, steps


@row("S17", "predict --out DIR over an earlier predict of another sample, killed part-way (Ctrl-C, kill -9, a full "
            "disk): DIR mixed the new sample's first pictures with the old one's last picture and prediction.json, a "
            "set that looked whole; the pictures and prediction.json are written to temporaries and renamed together")
def row_predict_killed_part_way_over_an_earlier_set(env):
    from instagram_hdmap import predict as predict_module

    out = env.tmp / "p"
    rc, _, err = env.cli("predict", env.yaml, "--checkpoint", env.ckpt, "--index", "0", "--out", out)
    assert rc == 0, err[-2000:]
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    real, calls = predict_module.save_figure, []

    def killed_at_the_second(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    env.monkeypatch.setattr(predict_module, "save_figure", killed_at_the_second)
    rc, _, err = env.cli("predict", env.yaml, "--checkpoint", env.ckpt, "--index", "2", "--out", out)
    assert rc == 130, err[-2000:]
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


@row("S17", "show-gt --out DIR over an earlier show-gt of another sample, killed part-way: DIR mixed both samples' "
            "pictures (only bev_polylines.png names its sample); the pictures are renamed together")
def row_show_gt_killed_part_way_over_an_earlier_set(env):
    from instagram_hdmap import visualize

    out = env.tmp / "g"
    rc, _, err = env.cli("show-gt", env.yaml, "--index", "0", "--out", out)
    assert rc == 0, err[-2000:]
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    real, calls = visualize.save_figure, []

    def killed_at_the_third(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    env.monkeypatch.setattr(visualize, "save_figure", killed_at_the_third)
    rc, _, err = env.cli("show-gt", env.yaml, "--index", "1", "--out", out)
    assert rc == 130, err[-2000:]
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


@row("S17", "a data-loader worker killed during a training (the out-of-memory killer's choice, a kill -9): torch's "
            "'DataLoader worker (pid N) is killed by signal: Killed.' ended the run in two chained tracebacks, the "
            "steps since the last checkpoint lost; last.pt is saved at the last completed step and one line says so "
            "(evaluate: one line, nothing written)")
def row_data_worker_killed(env):
    from instagram_hdmap import predict as predict_module
    from instagram_hdmap.train import TrainingRun

    on_step = TrainingRun.on_step

    def worker_killed_after_step_2(self, info):
        on_step(self, info)
        if info.step == 2:
            raise RuntimeError("DataLoader worker (pid 4242) is killed by signal: Killed. ")

    env.monkeypatch.setattr(TrainingRun, "on_step", worker_killed_after_step_2)
    run = env.tmp / "run"
    env.error(r"DataLoader worker \(pid 4242\) is killed by signal: Killed .*saved .*last\.pt at step 2: resume with "
              r"--resume", "train", env.yaml, f"train.out_dir={run}", "train.epochs=2")
    assert torch.load(run / "last.pt", weights_only=True)["step"] == 2

    def worker_died(*args, **kwargs):
        raise RuntimeError("DataLoader worker (pid(s) 4243) exited unexpectedly")

    env.monkeypatch.setattr(predict_module, "evaluate", worker_died)
    env.error(r"evaluate: error: DataLoader worker .*exited unexpectedly .*nothing was written", "evaluate", env.yaml,
              "--checkpoint", env.ckpt, "--out", env.tmp / "e")


@row("S17", "train.out_dir on a file system that takes no file lock (NFS without lockd, some FUSE mounts: flock fails "
            "with ENOLCK): 'another training is running in OUT (process ?)', so no training could run there at all; "
            "it trains without the lock, with a note")
def row_out_dir_without_file_locks(env):
    import errno
    import fcntl

    def no_locks(fd, operation):
        raise OSError(errno.ENOLCK, "No locks available")

    env.monkeypatch.setattr(fcntl, "flock", no_locks)
    run = env.tmp / "run"
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={run}", "train.max_steps=1")
    assert rc == 0, err[-2000:]
    assert "takes no file lock (No locks available)" in out and (run / "last.pt").is_file()


@row("S17", "train --resume into a run folder whose tb is a file or whose log.jsonl is a folder: a raw "
            "FileExistsError (TensorBoard's makedirs) or IsADirectoryError (open) traceback once the model and the "
            "loaders were built; one line names the entry before the work")
def row_run_files_of_the_wrong_kind(env):
    run = env.tmp / "run"
    rc, _, err = env.cli("train", env.yaml, f"train.out_dir={run}", "train.epochs=2", "train.max_steps=1")
    assert rc == 0, err[-2000:]
    shutil.rmtree(run / "tb")
    (run / "tb").write_text("")
    env.error(r"tb is a file, where the run keeps its TensorBoard events in a folder", "train", env.yaml,
              f"train.out_dir={run}", "train.epochs=2", "--resume", run / "last.pt")
    (run / "tb").unlink()
    (run / "log.jsonl").unlink()
    (run / "log.jsonl").mkdir()
    env.error(r"log\.jsonl is a folder, where the run keeps its log in a file", "train", env.yaml,
              f"train.out_dir={run}", "train.epochs=2", "--resume", run / "last.pt")


@row("S17", "train --resume latest.pt, a symbolic link to OUT/last.pt (kept beside the runs), with train.out_dir=OUT: "
            "refused as 'continues the run of ., but OUT holds a run of its own ... set train.out_dir=.' (the link's "
            "folder, where following the advice would split the run); the checkpoint's own folder is its run")
def row_resume_through_a_symbolic_link(env):
    run = env.tmp / "run"
    rc, _, err = env.cli("train", env.yaml, f"train.out_dir={run}", "train.epochs=2", "train.max_steps=1")
    assert rc == 0, err[-2000:]
    (env.tmp / "latest.pt").symlink_to(run / "last.pt")
    rc, _, err = env.cli("train", env.yaml, f"train.out_dir={run}", "train.epochs=2", "train.max_steps=2",
                         "--resume", env.tmp / "latest.pt")
    assert rc == 0, err[-2000:]
    assert torch.load(run / "last.pt", weights_only=True)["step"] == 2


@row("S17", "long file names: export-gt --out of a valid 250-byte name failed after the work with a raw ENAMETOOLONG "
            "(its temporary .NAME.tmp-PID was longer than a file name may be); a name over 255 bytes in "
            "train.out_dir or evaluate --out was a raw OSError from the first stat. The temporary's name is cut to "
            "fit, and a name too long is one line")
def row_long_file_names(env):
    name = "g" * 245 + ".json"
    rc, _, err = env.cli("export-gt", env.yaml, "--out", env.tmp / name)
    assert rc == 0 and (env.tmp / name).is_file(), err[-2000:]
    too_long = env.tmp / ("a" * 300)
    env.error(r"train\.out_dir .*: the name a+\.\.\. is 300 bytes long, more than a file name can be \(255\)", "train",
              env.yaml, f"train.out_dir={too_long}")
    env.error(r"--out .*: the name a+\.\.\. is 300 bytes long", "evaluate", env.yaml, "--checkpoint", env.ckpt,
              "--out", too_long)


@row("S17", "train --resume with another eval.protocol (or data.val_split, eval.thresholds): the run compared its "
            "raster mAP with the vector mAP best.pt was kept for, to decide whether to replace best.pt, with no word; "
            "a note names the difference")
def row_resume_with_another_validation(env):
    run = env.tmp / "run"
    rc, _, err = env.cli("train", env.yaml, f"train.out_dir={run}", "train.epochs=2", "train.max_steps=1")
    assert rc == 0 and (run / "best.pt").is_file(), err[-2000:]
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={run}", "train.epochs=2", "train.max_steps=2",
                           "eval.protocol=raster", "--resume", run / "last.pt")
    assert rc == 0, err[-2000:]
    assert re.search(r"note: the best score so far .* was measured with another validation \(eval\.protocol: "
                     r"checkpoint 'vector' vs now 'raster'\)", out), out


@row("S16", "a run saved part-way through an epoch by 2 torchrun processes and resumed by 1: the shuffled sampler "
            "skipped samples of this rank's share (computed for the old number of ranks), so part of the epoch was "
            "walked twice or not at all, no word; it goes on from the same sample of the epoch's order, and says so")
def row_resume_under_another_number_of_processes(env):
    out = env.tmp / "r"
    p = _torchrun_cli("train", env.yaml, f"train.out_dir={out}", "train.max_steps=1", "train.batch_size=2")
    assert p.returncode == 0, p.stderr[-3000:]
    rc, stdout, err = env.cli("train", env.yaml, f"train.out_dir={out}", "--resume", out / "last.pt",
                              "train.max_steps=2", "train.batch_size=2")
    assert rc == 0, err
    assert (f"note: {out / 'last.pt'} was saved by 2 process(es) at step 1 of epoch 0, resumed by 1: the epoch goes "
            "on from the same sample") in stdout
    assert load_checkpoint(out / "last.pt")["world"] == 1


@row("S16", "evaluate of a temporal model with model.temporal.persist_frames and more streams than scenes: a stream's "
            "padding walks a scene at the same time as the stream that owns it, and persistence was applied to it "
            "too, so it replaced that scene's remembered elements between its frames (the scored output depended on "
            "eval.batch_size; the note counted the padding's kept elements); only the scored samples persist now")
def row_persistence_not_applied_to_padding(env):
    from instagram_hdmap.data import build_dataset
    from instagram_hdmap.evaluation.io import read_submission
    from instagram_hdmap.models import build_model
    from instagram_hdmap.persistence import Persistence

    torch.manual_seed(0)
    cfg = env.cfg("model.temporal.memory=bev", "model.temporal.persist_frames=2")
    ckpt = save_checkpoint({"model": build_model(cfg).state_dict(), "config": config_to_dict(cfg)},
                           env.tmp / "temporal.pt")
    subs, kept = {}, None
    for persist in (0, 2):  # 3 streams over the split's 2 scenes: the third walks padding only
        out = env.tmp / f"p{persist}"
        rc, stdout, err = env.cli("evaluate", env.yaml, "--checkpoint", ckpt, "--out", out,
                                  f"model.temporal.persist_frames={persist}", "model.gnn.conf_threshold=0.0",
                                  "model.gnn.match_threshold=0.01", "eval.batch_size=3", "data.val_split=train")
        assert rc == 0, err
        subs[persist] = read_submission(out / "submission.json", "pred").samples
        if persist:
            notes = json.loads((out / "metrics.json").read_text())["meta"]["config_notes"]
            kept = int(next(re.search(r"persist_frames=2: (\d+) map elements", n).group(1) for n in notes
                            if "persist_frames=2:" in n))
    # the reference: persistence applied by hand to the plain run's outputs, scene by scene in frame order
    ds, reference = build_dataset(cfg, "train"), Persistence.from_config(cfg)
    for scene in ds.scenes.names:
        for i in ds.scene_indices(scene):
            token = ds.sample_tokens[i]
            expected = reference.step(subs[0][token], scene, int(ds.scenes.frame[i]), ds.ego_pose(i).double().numpy())
            assert len(subs[2][token]) == len(expected), (scene, i)
            for got, want in zip(subs[2][token], expected):
                np.testing.assert_allclose(got["pts"], want["pts"], atol=1e-5)
                assert got["label"] == want["label"] and got["score"] == pytest.approx(want["score"], abs=1e-6)
    assert kept == reference.kept > 0


@row("S16", "the same override given twice on the command line (train.lr=1e-3 ... train.lr=1e-2, a slip in a long "
            "command): the last one won with no word; it still wins, and a note names both")
def row_same_override_given_twice(env):
    rc, out, err = env.cli("model-summary", env.yaml, "model.gnn.layers=2", "model.gnn.layers=3")
    assert rc == 0, err
    assert ("model-summary: note: model.gnn.layers is given 2 times (model.gnn.layers=2, model.gnn.layers=3); the "
            "last, model.gnn.layers=3, is used") in err
    rc, out, err = env.cli("model-summary", env.yaml, "model.gnn.layers=2", "model.gnn.heads=2")
    assert rc == 0 and "given 2 times" not in err


def _s18_dataset(env, root: Path, split: str = "train"):
    from instagram_hdmap.data import build_dataset

    return build_dataset(env.cfg(f"data.dataroot={root}"), split, augment=False)


@row("S18", "nuScenes tables: a duplicate token (two sample records of one token, the second with its chain cut) "
            "silently kept the last (a scene read short), and two scenes of one name were read as one drive; both "
            "are named at load, as is a duplicate scene record")
def row_nuscenes_duplicate_tokens_and_scene_names(env):
    from instagram_hdmap.data.base import DatasetError

    def dup_sample(tables):
        tables["sample"].append(dict(tables["sample"][1], next=""))

    with pytest.raises(DatasetError, match=r"sample\.json holds two records with token \w+ \(records 1 and \d+\)"):
        _s18_dataset(env, env.shadow_world(dup_sample))
    shutil.rmtree(env.tmp / "world")

    def same_name(tables):
        tables["scene"][0]["name"] = tables["scene"][1]["name"]

    with pytest.raises(DatasetError, match=r"scene\.json names two scenes 'scene-\d+' \(records 0 and 1"):
        _s18_dataset(env, env.shadow_world(same_name))


@row("S18", "nuScenes sample chains: a 'next' cut short dropped the scene's later samples with no word; a chain "
            "that ran into another scene's samples (or a first_sample_token of another scene) was blamed on time "
            "order; a scene's log_token naming no log was a raw KeyError. Each is named")
def row_nuscenes_broken_sample_chain(env):
    from instagram_hdmap.data.base import DatasetError

    def cut(tables):
        first(tables["sample"], prev="")["next"] = ""

    with pytest.raises(DatasetError, match=r"scene scene-\d+: 2 of its samples .* are not on its chain"):
        _s18_dataset(env, env.shadow_world(cut))
    shutil.rmtree(env.tmp / "world")

    def into_other_scene(tables):
        scenes = tables["scene"]
        scenes[0]["first_sample_token"] = scenes[1]["first_sample_token"]

    with pytest.raises(DatasetError, match=r"its samples' chain .* reaches sample \w+, whose scene_token is \w+, "
                                           r"not this scene's"):
        _s18_dataset(env, env.shadow_world(into_other_scene))
    shutil.rmtree(env.tmp / "world")

    def no_log(tables):
        for scene in tables["scene"]:
            scene["log_token"] = "0" * 32

    with pytest.raises(DatasetError, match=r"log\.json in .* has no record 0{32}"):
        _s18_dataset(env, env.shadow_world(no_log))


@row("S18", "nuScenes map expansion: a node with NaN coordinates or a polygon naming a node the file lacks was a raw "
            "GEOSException / KeyError naming nothing; a divider line of one point was a raw GEOSException. The "
            "first two name the file and the record; one-point lines are skipped and reported once per map; a file "
            "holding a list or an empty object is said to be no map expansion (was 'an outdated map version (%s)')")
def row_map_expansion_bad_records(env):
    from instagram_hdmap.data.local_map import MapError

    def with_maps(edit):
        root = env.tmp / "world"
        if root.exists():
            shutil.rmtree(root)
        root = env.shadow_world()
        (root / "maps").unlink()
        shutil.copytree(env.world / "maps", root / "maps")
        for path in (root / "maps" / "expansion").glob("*.json"):
            m = json.loads(path.read_text())
            edit(m)
            path.write_text(json.dumps(m))
        return root

    def nan_nodes(m):
        lines = {ln["token"]: ln for ln in m["line"]}
        ids = {t for d in m["road_divider"] + m["lane_divider"] for t in lines[d["line_token"]]["node_tokens"]}
        for node in m["node"]:
            if node["token"] in ids:
                node["x"] = float("nan")

    with pytest.raises(MapError, match=r"expansion/[\w-]+\.json: (road|lane)_divider record \w+: its nodes hold NaN"):
        _s18_dataset(env, with_maps(nan_nodes))

    def missing_node(m):
        polygons = {p["token"]: p for p in m["polygon"]}
        for r in m["road_segment"]:
            polygons[r["polygon_token"]]["exterior_node_tokens"].append("0" * 32)

    with pytest.raises(MapError, match=r"road_segment record \w+ names node 0{32}, which the file's node table"):
        _s18_dataset(env, with_maps(missing_node))

    def one_point(m):
        lines = {ln["token"]: ln for ln in m["line"]}
        for d in m["road_divider"] + m["lane_divider"]:
            lines[d["line_token"]]["node_tokens"] = lines[d["line_token"]]["node_tokens"][:1]

    with pytest.warns(UserWarning, match=r"expansion/[\w-]+\.json: \d+ divider line\(s\) of one point skipped"):
        ds = _s18_dataset(env, with_maps(one_point))
    assert all(p["label"] != 0 for p in ds.gt_polylines(0))

    root = with_maps(lambda m: None)
    for path in (root / "maps" / "expansion").glob("*.json"):
        path.write_text("[]")  # the devkit: "You are using an outdated map version (%s)!"
    with pytest.raises(MapError, match=r"expansion/[\w-]+\.json: it holds a JSON list, not a map expansion"):
        _s18_dataset(env, root)


@row("S18", "AV2 log files: a NaN drivable-area point was a raw GEOSException and a NaN lane marking silently dropped; "
            "two pose rows of one timestamp_ns or two calibration rows of one camera silently kept one; a "
            "ground-height Sim2 of scale 0 was a raw ZeroDivisionError; a non-timestamp file in sensors/lidar a "
            "raw 'invalid literal for int()'; a crossing edge of one point lost the crossing with no word. Each is "
            "named")
def row_av2_log_file_damage(env):
    import pandas as pd

    from instagram_hdmap.data.base import DatasetError
    from instagram_hdmap.data.local_map import MapError

    def copy():
        if (env.tmp / "av2").exists():
            shutil.rmtree(env.tmp / "av2")
        return _av2_copy(env)

    def edit_map(log, edit):
        path = next((log / "map").glob("log_map_archive_*.json"))
        m = json.loads(path.read_text())
        edit(m)
        path.write_text(json.dumps(m))

    def nan_area(m):
        for area in m["drivable_areas"].values():
            area["area_boundary"][0]["x"] = float("nan")

    root, log = copy()
    edit_map(log, nan_area)
    with pytest.raises(MapError, match=r"map archive .*: drivable area \w+ has NaN or infinite coordinates"):
        _av2_dataset(env, "train", root).gt_polylines(0)

    def nan_marking(m):
        for ls in m["lane_segments"].values():
            ls["left_lane_boundary"][0]["y"] = float("nan")

    root, log = copy()
    edit_map(log, nan_marking)
    with pytest.raises(MapError, match=r"lane segment \w+ has NaN or infinite coordinates"):
        _av2_dataset(env, "train", root).gt_polylines(0)

    def short_edge(m):
        for crossing in m["pedestrian_crossings"].values():
            crossing["edge1"] = crossing["edge1"][:1]

    root, log = copy()
    edit_map(log, short_edge)
    if json.loads(next((log / "map").glob("log_map_archive_*.json")).read_text())["pedestrian_crossings"]:
        with pytest.warns(UserWarning, match=r"crossing\(s\) with an edge of fewer than 2 points"):
            ds = _av2_dataset(env, "train", root)
            for i in range(len(ds)):
                ds.gt_polylines(i)

    root, log = copy()
    poses = pd.read_feather(log / "city_SE3_egovehicle.feather")
    ts = int(sorted(p.stem for p in (log / "sensors" / "lidar").glob("*.feather"))[0])
    extra = poses[poses.timestamp_ns == ts].copy()
    extra["tx_m"] += 100.0
    pd.concat([poses, extra]).reset_index(drop=True).to_feather(log / "city_SE3_egovehicle.feather")
    with pytest.raises(DatasetError, match=rf"holds 2 rows of other ego poses for timestamp_ns {ts}"):
        _av2_dataset(env, "train", root).ego_pose(0)

    root, log = copy()
    calib = pd.read_feather(log / "calibration" / "egovehicle_SE3_sensor.feather")
    extra = calib[calib.sensor_name == calib.sensor_name.iloc[0]].copy()
    extra["tx_m"] += 5.0
    pd.concat([calib, extra]).reset_index(drop=True).to_feather(log / "calibration" / "egovehicle_SE3_sensor.feather")
    with pytest.raises(DatasetError, match=r"holds 2 rows of other calibrations for sensor_name \w+"):
        _av2_dataset(env, "train", root)[0]

    root, log = copy()
    sim2 = next((log / "map").glob("*___img_Sim2_city.json"))
    sim2.write_text(json.dumps({**json.loads(sim2.read_text()), "s": 0}))
    with pytest.raises(MapError, match=r"cannot read the ground-height raster .*ZeroDivisionError"):
        _av2_dataset(env, "train", root).ground_height(0)

    root, log = copy()
    (log / "sensors" / "lidar" / "notes.feather").write_bytes(b"")
    with pytest.raises(DatasetError, match=r"lidar/notes\.feather is not named <timestamp_ns>\.feather"):
        _av2_dataset(env, "train", root)


@row("S18", "targets.build_targets / vertex_graph / distance_transform of bad polylines: a label of 5 was a raw "
            "IndexError, -1 drawn into the last class, 1.5 truncated, a class name a raw int() error, NaN points a "
            "vertex at a grid corner, [P, 3] points a raw broadcast error, a dict for the list a raw TypeError; "
            "each is a TypeError / ValueError naming the polyline")
def row_targets_of_bad_polylines(env):
    from instagram_hdmap.geometry import BEVGrid
    from instagram_hdmap.targets import build_targets, vertex_graph

    grid = BEVGrid(-8.0, 8.0, -4.0, 4.0, 0.25, 4)

    def line(pts=((0.0, 0.0), (3.0, 1.0)), label=0):
        return {"pts": np.asarray(pts, dtype=np.float64), "label": label, "closed": False}

    assert build_targets([line()], grid)["gt_vertices_px"].shape == (2, 2)
    assert build_targets([line(label=np.int64(2)), line(label=torch.tensor(1))], grid)["gt_distance"].shape[0] == 3
    for label in (5, -1, 1.5, "divider", float("nan")):
        with pytest.raises(ValueError, match=r"polyline 0: 'label' must be a class index"):
            build_targets([line(label=label)], grid)
    with pytest.raises(ValueError, match=r"polyline 1: 'pts' holds NaN"):
        build_targets([line(), line(pts=((0.0, 0.0), (np.nan, 1.0)))], grid)
    with pytest.raises(ValueError, match=r"polyline 0: 'pts' must be \[P, 2\] .* got shape \[2, 3\]"):
        build_targets([line(pts=((0.0, 0.0, 0.0), (3.0, 1.0, 0.0)))], grid)
    with pytest.raises(TypeError, match=r"vertex_graph: polylines must be a list of dicts"):
        vertex_graph(line(), grid)


@row("S18", "BEVGrid of resolution 0, NaN, xmax < xmin (a grid of -64 columns, no word) or cell_size 0 was a raw "
            "ZeroDivisionError / ValueError or nothing: a ValueError naming the field; BEVGrid.from_config, "
            "RasterFrame, Criterion, decode_options and postprocess_batch take a whole config where they took its "
            "grid / part (raw AttributeErrors); grid.m_to_px of a list is a TypeError; rasterize_instances of a list "
            "of labels drew nothing")
def row_bev_grid_and_config_arguments(env):
    from instagram_hdmap.evaluation.raster_ap import RasterFrame, rasterize_instances
    from instagram_hdmap.geometry import BEVGrid
    from instagram_hdmap.losses import Criterion
    from instagram_hdmap.postprocess import decode_options

    for args, pattern in (((-8, 8, -4, 4, 0), "the resolution .* must be > 0"), ((8, -8, -4, 4, 0.25), "upper bounds"),
                          ((-8, 8, -4, 4, float("nan")), "resolution must be a finite number"),
                          ((-8, 8, -4, 4, 0.25, 0), "cell_size must be a whole number of pixels >= 1")):
        with pytest.raises(ValueError, match=pattern):
            BEVGrid(*args)
    cfg = env.cfg()
    grid = BEVGrid.from_config(cfg)
    assert grid == BEVGrid.from_config(cfg.grid)
    with pytest.raises(TypeError, match=r"points must be a NumPy array or a torch tensor"):
        grid.m_to_px([[1.0, 2.0]])
    frame = RasterFrame(cfg)
    assert (frame.W, frame.H) == (grid.W, grid.H)
    pts = [np.array([[0.0, 0.0], [3.0, 1.0]]), np.array([[-2.0, -1.0], [2.0, 2.0]])]
    masks, _ = rasterize_instances(pts, [0, 1], None, frame)
    assert masks[0].any() and masks[1].any()
    assert Criterion(cfg, cfg).grid == grid
    assert decode_options(cfg, cfg) == decode_options(cfg.model.gnn, grid)


@row("S18", "InstaGraM.forward of a batch of other shapes or dtypes: one sample's images without the batch "
            "dimension, channels last, another image size, float64 or uint8 images, an empty batch were raw torch "
            "errors from deep inside; intrinsics of another batch size were broadcast with no word; a list of "
            "samples read as 'lacks images'. postprocess_batch of one sample's outputs was a raw unpack error and a "
            "NaN match_threshold decoded nothing with no word. Each is a TypeError / ValueError naming the key")
def row_model_forward_batch_checked(env):
    from instagram_hdmap.data import build_dataset
    from instagram_hdmap.data.base import collate_fn
    from instagram_hdmap.models import build_model
    from instagram_hdmap.postprocess import decode_options, postprocess_batch

    cfg = env.cfg()
    model = build_model(cfg).eval()
    ds = build_dataset(cfg, "val", augment=False)
    batch = collate_fn([ds[0], ds[1]])

    def run(**change):
        with torch.no_grad():
            return model({**batch, **change})

    out = run()
    images = batch["images"]
    for change, error, pattern in (
        ({"images": images[0]}, ValueError, r"'images' must be a tensor \[B, V, 3, h, w\].*images\[None\]"),
        ({"images": images.permute(0, 1, 3, 4, 2)}, ValueError, r"channels last"),
        ({"images": images[..., ::2, ::2]}, ValueError, r"the model was built for data.image_size"),
        ({"images": images.double()}, TypeError, r"'images' are torch.float64, the model's weights torch.float32"),
        ({"images": images.to(torch.uint8)}, TypeError, r"'images' are torch.uint8"),
        ({"images": images[:0]}, ValueError, r"an empty batch"),
        ({"intrinsics": batch["intrinsics"][:1]}, ValueError, r"'intrinsics' must be a tensor \[B=2, V=\d+, \.\.\.\]"),
    ):
        with pytest.raises(error, match=pattern):
            run(**change)
    with pytest.raises(TypeError, match=r"takes one batch dict .* got list"):
        model([ds[0]])
    grid = _s18_grid(cfg)
    options = decode_options(cfg.model.gnn, grid)
    assert len(postprocess_batch(out, cfg, **options)) == 2
    with pytest.raises(ValueError, match=r"outputs must be batched"):
        postprocess_batch({k: v[0] for k, v in out.items() if isinstance(v, torch.Tensor)}, grid, **options)
    with pytest.raises(ValueError, match=r"match_threshold is an adjacency probability"):
        postprocess_batch(out, grid, **{**options, "match_threshold": float("nan")})


def _s18_grid(cfg):
    from instagram_hdmap.geometry import BEVGrid

    return BEVGrid.from_config(cfg.grid)


@row("S16", "two evaluations into one --out at once: each wrote its pair of files at the end, so the folder could hold "
            "one's submission beside the other's metrics (a pair that looked whole); the second is refused while "
            "the first runs, and a refused or failed evaluation leaves no folder it created")
def row_two_evaluations_into_one_out(env):
    from instagram_hdmap.files import LOCK_FILE, locked_folder
    from instagram_hdmap.predict import load_model

    out = env.tmp / "eval"
    out.mkdir()
    (out / "metrics.json").write_text("{}")  # the first evaluation's earlier pair
    holder = subprocess.Popen(  # the first evaluation's lock, as files.lock_folder takes it
        [sys.executable, "-c", "import fcntl, os, sys, time\n"
         f"f = open({str(out / LOCK_FILE)!r}, 'a+'); fcntl.flock(f, fcntl.LOCK_EX); f.write(str(os.getpid()))\n"
         "f.flush(); print('locked', flush=True); time.sleep(60)"], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        forbid(env, "instagram_hdmap.predict.load_model", "the evaluation")
        env.error(rf"another evaluation is running in .*eval \(process {holder.pid}\); wait for it to end \(or stop "
                  r"it\), or choose another --out", "evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", out)
        assert (out / "metrics.json").read_text() == "{}"
    finally:
        holder.kill()
        holder.wait()
    nested = env.tmp / "new" / "eval"  # created for a job that fails before writing: removed again
    with pytest.raises(RuntimeError, match="the job failed"), locked_folder(nested, "evaluation", "choose another"):
        assert (nested / LOCK_FILE).is_file()
        raise RuntimeError("the job failed")
    assert not (env.tmp / "new").exists()
    env.monkeypatch.setattr("instagram_hdmap.predict.load_model", load_model)
    rc, out_, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", nested)
    assert rc == 0, err
    assert sorted(p.name for p in nested.iterdir()) == ["metrics.json", "submission.json"]  # the lock file gone


@row("S19", "ConsistentAPMeter.update(ids=...): an ID of NaN, inf or beyond int64 was a raw numpy ValueError / "
            "OverflowError; ids as one [B, P] tensor or array (the docstring's 'tensors or arrays') and thresholds as "
            "an array were refused; thresholds listing a distance twice counted it twice in C-mAP (eval.thresholds "
            "refuses that). Now named / accepted")
def row_cmap_prediction_ids(env):
    from instagram_hdmap.evaluation.consistency import ConsistentAPMeter, EvaluationInputError
    from instagram_hdmap.geometry import BEVGrid

    grid = BEVGrid(-15.0, 15.0, -30.0, 30.0, 0.15)

    def line(x, score=None):
        d = {"pts": np.array([[x, -5.0], [x, 5.0]]), "label": 0}
        return d if score is None else {**d, "score": score}

    def cmap(ids, **kw):
        meter = ConsistentAPMeter(grid, **kw)
        meter.update([[line(1, 0.9), line(3, 0.8)]], [[line(1), line(3)]], ["s"], [0], np.eye(4)[None], ids=ids)
        return meter.compute()["C-mAP"]

    for bad in (float("nan"), float("inf"), 2**70):
        with pytest.raises(EvaluationInputError, match=r"sample \(scene 's', frame 0\): ids must be one integer"):
            cmap([[bad, 1]])
    expected = cmap([[0, 1]])
    assert cmap(torch.tensor([[0, 1]])) == cmap(np.array([[0, 1]])) == expected
    assert ConsistentAPMeter(grid, thresholds=np.array([0.5, 1.0])).thresholds == (0.5, 1.0)
    assert ConsistentAPMeter(grid, thresholds=torch.tensor([0.5, 1.0])).thresholds == (0.5, 1.0)
    with pytest.raises(EvaluationInputError, match=r"thresholds lists a distance twice"):
        ConsistentAPMeter(grid, thresholds=[1.0, 1.0])


@row("S19", "persistence.match_previous (public, shared by Persistence and InstanceTracker) checked nothing: torch "
            "poses were a raw TypeError, an element without 'label' / 'pts' a raw KeyError, grid None a raw "
            "AttributeError, a singular pose a raw LinAlgError. InstanceTracker's errors named Persistence (and its "
            "decay, for match_m=0), it refused elements without the 'score' it never reads (GT polylines), and a "
            "NaN label was a raw ValueError in both. Now named / accepted")
def row_match_previous_and_tracker_arguments(env):
    from instagram_hdmap.geometry import BEVGrid
    from instagram_hdmap.persistence import InstanceTracker, Persistence, PersistenceInputError, match_previous

    grid = BEVGrid(-15.0, 15.0, -30.0, 30.0, 0.15)
    line = {"pts": np.array([[1.0, -5.0], [1.0, 5.0]]), "label": 0, "score": 0.9}
    D, _ = match_previous(torch.eye(4), [line], torch.eye(4, dtype=torch.float64), [line], grid)
    assert D.tolist() == [[0.0]]
    for args, pattern in (
        ((np.eye(4), [{"pts": [[0, 0], [1, 1]]}], np.eye(4), [line], grid), r"prev_elements: element 0 has no 'label'"),
        ((np.eye(4), [line], np.eye(4), [{"label": 0}], grid), r"preds: element 0 has no 'pts'"),
        ((np.eye(4), [line], np.eye(4), [line], None), r"match_previous: grid must be a BEVGrid"),
        ((np.zeros((4, 4)), [line], np.eye(4), [line], grid), r"prev_pose: its ego pose is not a rigid transform"),
    ):
        with pytest.raises(PersistenceInputError, match=pattern):
            match_previous(*args)
    with pytest.raises(PersistenceInputError, match=r"^InstanceTracker: needs match_m and max_jump_m > 0.*match_m=0"):
        InstanceTracker(grid, match_m=0)
    gt = {k: v for k, v in line.items() if k != "score"}
    tracker = InstanceTracker(grid)
    assert tracker.step([gt], "s", 0, np.eye(4)) == [0] and tracker.step([gt], "s", 1, np.eye(4)) == [0]
    with pytest.raises(PersistenceInputError, match=r"^InstanceTracker: scene 's', frame 2: element 0's pts"):
        tracker.step([{"pts": [1.0, 2.0], "label": 0}], "s", 2, np.eye(4))
    for who in (InstanceTracker(grid), Persistence(grid)):
        with pytest.raises(PersistenceInputError, match=r"element 0's label must be a class index"):
            who.step([{**line, "label": float("nan")}], "s", 0, np.eye(4))


@row("S19", "a bf16 model's polylines (pts a bfloat16 tensor) were refused by the evaluation's polyline check, "
            "FlickerMeter / ConsistentAPMeter and Persistence ('Got unsupported ScalarType BFloat16'; NumPy has no "
            "bfloat16); they are read as float")
def row_bf16_polylines(env):
    from instagram_hdmap.evaluation.consistency import ConsistentAPMeter
    from instagram_hdmap.geometry import BEVGrid
    from instagram_hdmap.persistence import InstanceTracker, Persistence

    grid = BEVGrid(-15.0, 15.0, -30.0, 30.0, 0.15)
    pts = torch.tensor([[1.0, -5.0], [1.0, 5.0]])
    pred = {"pts": pts.bfloat16(), "label": 0, "score": torch.tensor(0.9, dtype=torch.bfloat16)}
    meter = ConsistentAPMeter(grid)
    meter.update([[pred]], [[{"pts": pts, "label": 0}]], ["s"], [0], np.eye(4)[None])
    assert meter.compute()["AP_class"]["0"] == 1.0
    keep = Persistence(grid)
    keep.step([pred], "s", 0, np.eye(4))
    kept = keep.step([], "s", 1, np.eye(4))
    assert len(kept) == 1 and np.allclose(kept[0]["pts"], pts.numpy())
    tracker = InstanceTracker(grid)
    assert tracker.step([pred], "s", 0, np.eye(4)) == [0] and tracker.step([pred], "s", 1, np.eye(4)) == [0]


@row("S19", "InstaGraM.forward under torch.autocast: bf16 images into an fp32 model (and fp32 images into a bf16 "
            "model) ran before sweep 18 and were then refused by its dtype check ('give images of the weights' "
            "dtype'); autocast casts them itself, so they run again (a dtype autocast does not reconcile is still "
            "named)")
def row_forward_under_autocast(env):
    from instagram_hdmap.data import build_dataset
    from instagram_hdmap.data.base import collate_fn
    from instagram_hdmap.models import build_model

    cfg = env.cfg()
    torch.manual_seed(0)
    model = build_model(cfg).eval()
    batch = collate_fn([build_dataset(cfg, "val", augment=False)[0]])
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        out = model({**batch, "images": batch["images"].bfloat16()})
        assert isinstance(out, dict)
        model.bfloat16()
        model(batch)
    with torch.no_grad(), pytest.raises(TypeError, match=r"'images' are torch.float32, the model's weights torch.bfl"):
        model(batch)  # no autocast: still named


@row("S19", "benchmarks/cmap_of_submissions.py: --match-m 0 was taken as not given (scored at the default 1.0 m, no "
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


@row("S19", "files.lock_folder (evaluate's --out, train.out_dir): a folder named .instagram_hdmap.lock where the lock "
            "file goes was a raw IsADirectoryError traceback (exit 1); it is one line naming it")
def row_lock_file_is_a_folder(env):
    out = env.tmp / "eval"
    (out / ".instagram_hdmap.lock").mkdir(parents=True)
    env.error(r"eval/\.instagram_hdmap\.lock \(the lock this evaluation holds on .*eval\) is a folder, not the lock "
              r"file; remove it, or choose another --out", "evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", out)
    run = env.tmp / "run"
    (run / ".instagram_hdmap.lock").mkdir(parents=True)
    env.error(r"is a folder, not the lock file; remove it, or choose another train.out_dir", "train", env.yaml,
              f"train.out_dir={run}", "train.max_steps=1")


@row("S19", "eval.cmap_match_m had no upper bound: 100 (centimetres meant) ran C-mAP with a tracker that passes IDs "
            "across 100 m, with no word; it is bounded as model.temporal.persist_match_m (<= 10 m)")
def row_cmap_match_m_bounded(env):
    env.error(r"config key 'eval.cmap_match_m' must be in \(0, 10\] \(metres.*centimetres given\?\)\), got 100",
              "evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "eval", "eval.cmap=true",
              "eval.cmap_match_m=100")
    assert not (env.tmp / "eval").exists()


@row("S19", "train --resume RUN/last.pt of an unfinished run with another train.out_dir (the config's default when "
            "none is given): the run went on in that folder, its earlier checkpoints, log and events left in RUN, and "
            "only the final 'outputs in' line named it; a note says where it goes on and how to continue in RUN")
def row_resume_into_another_folder_noted(env):
    run = env.tmp / "run"
    _toy_run(env, [0.6], "train.epochs=3", "train.max_steps=1")
    other = env.tmp / "elsewhere"
    _toy_run(env, [0.3, 0.4, 0.2], "train.epochs=3", f"train.out_dir={other}", resume=str(run / "last.pt"))
    out = env.capsys.readouterr().out
    assert (f"note: {run / 'last.pt'} is a checkpoint of the run in {run.resolve()}; this run goes on in "
            f"train.out_dir={other}") in out and f"pass train.out_dir={run.resolve()}" in out
    assert (other / "last.pt").is_file()
    _toy_run(env, [0.3, 0.4, 0.2], "train.epochs=3", resume=str(run / "last.pt"))  # its own folder: no note
    assert "is a checkpoint of the run in" not in env.capsys.readouterr().out


@row("S20", "model.gnn.min_vertices above model.gnn.num_vertices (min_vertices=100 with N = 64, or num_vertices=1): no "
            "element could ever be decoded, and evaluate / predict-images --decode wrote empty predictions, exit 0")
def row_min_vertices_above_num_vertices(env):
    forbid(env, "instagram_hdmap.predict.save_figure", "drawing")
    env.error(r"'model\.gnn\.min_vertices' is 100, but the model keeps model\.gnn\.num_vertices=64 vertices: no "
              r"element could ever be decoded", "evaluate", env.yaml, "--checkpoint", env.ckpt, "--out",
              env.tmp / "eval", "model.gnn.min_vertices=100")
    rig, images = _rig_files(env)
    env.error(r"'model\.gnn\.min_vertices' is 100", "predict-images", "--checkpoint", env.ckpt, "--rig", rig, "--out",
              env.tmp / "out", "--device", "cpu", "--decode", "min_vertices=100", *images)
    env.error(r"'model\.gnn\.min_vertices' is 2, but the model keeps model\.gnn\.num_vertices=1", "model-summary",
              env.yaml, "model.gnn.num_vertices=1")
    assert not (env.tmp / "eval").exists()


@row("S20", "every loss weight 0 (loss.vertex_weight, distance_weight, adjacency_weight, class_weight): the loss was 0 "
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


@row("S20", "demo --out OUT run again with another --config (or other model overrides) after OUT's run completed: it "
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


@row("S20", "the temporal memory's keys on a single-frame model (train.stream_frames=4, model.temporal.fusion=gru with "
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


@row("S20", "predict-images: a rig file's image_size written as floats ([400.0, 225.0], numpy's or MATLAB's JSON) was "
            "refused as not 'positive whole numbers'; an image OpenCV cannot read (a float TIFF, an animated GIF) was "
            "'corrupt or not an image'")
def row_rig_float_size_and_unreadable_image_kinds(env):
    from PIL import Image

    from instagram_hdmap.data.transforms import ImageError, read_image

    rig, images = _rig_files(env, lambda d: d.update(image_size=[400.0, 225.0]))
    rc, _, err = env.cli("predict-images", "--checkpoint", env.ckpt, "--rig", rig, "--out", env.tmp / "out",
                         "--device", "cpu", *images)
    assert rc == 0, err[-2000:]
    env.error(r"'image_size' must be \[width, height\] .* got \[400\.5, 225\]", "predict-images", "--checkpoint",
              env.ckpt, "--rig", _rig_files(env, lambda d: d.update(image_size=[400.5, 225]))[0], "--out",
              env.tmp / "out2", "--device", "cpu", *images)
    tif = env.tmp / "float.tif"
    Image.fromarray(np.full((225, 400), 0.5, np.float32), mode="F").save(tif)
    with pytest.raises(ImageError, match=r"cannot be decoded \(a TIFF F image, which OpenCV does not read; save it as "
                                         r"an 8-bit RGB JPEG or PNG\)"):
        read_image(tif)
    junk = env.tmp / "junk.jpg"
    junk.write_bytes(b"\x00" * 100)
    with pytest.raises(ImageError, match=r"corrupt or not an image"):
        read_image(junk)


@row("S20", "a command's output piped into a reader that stops early (`model-summary CONFIG | head -1`, export-gt's "
            "'wrote' line into `head -0`): a raw BrokenPipeError traceback, exit 1; now quiet, exit 141 as Unix "
            "tools (SIGPIPE)")
def row_output_pipe_closed_early(env):
    env_vars = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    for argv in (["model-summary", str(env.yaml)], ["export-gt", str(env.yaml), "--out", str(env.tmp / "gt.json")]):
        p = subprocess.Popen([sys.executable, "-m", "instagram_hdmap.cli", *argv], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, env=env_vars)
        p.stdout.close()  # the reader is gone before the first line (`| head -0`)
        err = p.stderr.read().decode()
        assert p.wait(timeout=120) == 141, err[-2000:]
        assert "Traceback" not in err and "BrokenPipe" not in err, err[-2000:]
    assert (env.tmp / "gt.json").is_file()  # the work was done; only its report had no reader


@row("S20", "a temporal training of more streams (train.batch_size) than the training split has scenes (or pieces of "
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


@row("S20", "predict-images --decode match_threshold=0.1 ... --decode match_threshold=0.3 (one option twice, a slip in "
            "a long command): the last was used with no word, where an override given twice is noted")
def row_decode_option_given_twice(env):
    rig, images = _rig_files(env)
    rc, out, err = env.cli("predict-images", "--checkpoint", env.ckpt, "--rig", rig, "--out", env.tmp / "out",
                           "--device", "cpu", "--decode", "match_threshold=0.1", "--decode", "match_threshold=0.3",
                           *images)
    assert rc == 0, err[-2000:]
    assert ("note: --decode match_threshold is given 2 times (match_threshold=0.1, match_threshold=0.3); the last, "
            "match_threshold=0.3, is used") in err, err[-2000:]


@row("S20", "evaluate (and a training's validation) with eval.rank_by=descending or eval.fix_instance_ids=true under "
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


@row("S20", "export-gt --out - (stdout for Unix tools): a file named '-' written in the working directory, 'wrote -', "
            "exit 0 (show-gt --out -: a folder '-'); --out /dev/stdout still writes the JSON to the terminal")
def row_dash_as_output_path(env):
    forbid(env, "instagram_hdmap.cli.gt_submission", "the export")
    env.error(r"--out -: the output is written to a file, not to stdout", "export-gt", env.yaml, "--out", "-")
    env.error(r"--out -: the output is written to a file, not to stdout", "show-gt", env.yaml, "--out", "-")
    forbid(env, "instagram_hdmap.demo.ensure_world", "world generation")
    env.error(r"--out -: the output is written to a file", "demo", "--out", "-", "--cache", env.tmp / "cache")
    assert not Path("-").exists()  # the row runs in its own folder (monkeypatch.chdir)


@row("S20", "predict-images: a byte-identical copy of one camera's image given for another camera (CAM_FRONT.jpg "
            "copied to fill CAM_FRONT_RIGHT) ran, exit 0 (the same path twice, or a link to it, was named)")
def row_predict_images_copy_of_an_image(env):
    rig, images = _rig_files(env)
    shutil.copy(images[1], images[2])
    forbid(env, "instagram_hdmap.predict.save_figure", "drawing")
    env.error(r"cameras CAM_FRONT and CAM_FRONT_RIGHT are given the same image: .*CAM_FRONT_RIGHT\.jpg is a copy of "
              r".*CAM_FRONT\.jpg \(the same bytes\)", "predict-images", "--checkpoint", env.ckpt, "--rig", rig, "--out",
              env.tmp / "out", "--device", "cpu", *images)


@row("S20", "predict-images: one image for two cameras (the same file or a copy) was refused even where it is a blank "
            "frame, the image a failed camera gives (the model trains with such cameras: data.camera_dropout), so a "
            "frame with two failed cameras could not be run at all; a one-colour image may stand for several")
def row_predict_images_blank_frames_may_repeat(env):
    import cv2

    rig, images = _rig_files(env)
    black = env.tmp / "black.png"
    cv2.imwrite(str(black), np.zeros((225, 400, 3), np.uint8))
    for a, b in ((1, 2), (3, 4)):
        shutil.copy(black, images[a])
        shutil.copy(black, images[b])
    rc, _, err = env.cli("predict-images", "--checkpoint", env.ckpt, "--rig", rig, "--out", env.tmp / "blank",
                         "--device", "cpu", images[0], images[1], images[2], black, black, *images[5:])
    assert rc == 0, err[-2000:]


@row("S17", "a training killed (kill -9, a power cut) between an epoch's last.pt and its line in log.jsonl: the "
            "resume went on after that epoch and its line (losses, validation, samples/s) was never written; now the "
            "line goes first, the checkpoint counts the lines before it, and a resume drops a killed run's lines "
            "after its checkpoint (here the resume trains the epoch's end again and logs it once)")
def row_log_line_survives_a_kill_between_line_and_checkpoint(env):
    from instagram_hdmap.train import TrainingRun

    class Killed(BaseException):  # not an exception the run handles: no save at the kill, as with kill -9
        pass

    real = {name: getattr(TrainingRun, name) for name in ("train_epoch", "log", "save")}
    armed = []

    def train_epoch(self):
        stopped = real["train_epoch"](self)
        armed.append(self.position.epoch == 1)  # epoch 0 just ended
        return stopped

    def killed_after(name):
        def wrapped(self, *args, **kwargs):
            real[name](self, *args, **kwargs)
            if armed and armed[-1]:  # the first of the epoch's two writes, whichever it is
                raise Killed
        return wrapped

    env.monkeypatch.setattr(TrainingRun, "train_epoch", train_epoch)
    env.monkeypatch.setattr(TrainingRun, "log", killed_after("log"))
    env.monkeypatch.setattr(TrainingRun, "save", killed_after("save"))
    run = env.tmp / "run"
    args = ["train", env.yaml, f"train.out_dir={run}", "train.epochs=2", "train.checkpoint_every=1",
            "train.val_every=100"]
    with pytest.raises(Killed):
        env.cli(*args)
    for name, method in real.items():
        env.monkeypatch.setattr(TrainingRun, name, method)
    rc, _, err = env.cli(*args, "--resume", run / "last.pt")
    assert rc == 0, err[-2000:]
    lines = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert [line["epoch"] for line in lines] == [0, 1], lines
    assert load_checkpoint(run / "last.pt")["log_lines"] == 2


@row("S20", "torchrun jobs never destroyed their process group: at the interpreter's exit gloo's worker threads, still "
            "running, aborted a rank now and then (SIGABRT, 'terminate called without an active exception') and the "
            "job failed, exit 1, after all its work was done (twice in one loaded full suite); a command that ends "
            "well destroys it on every rank (here a one-process group, as torchrun --nproc_per_node 1 makes)")
def row_process_group_destroyed_at_the_end(env):
    import socket

    import torch.distributed as dist

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    for key, value in {"RANK": "0", "WORLD_SIZE": "1", "LOCAL_RANK": "0", "MASTER_ADDR": "127.0.0.1",
                       "MASTER_PORT": str(port)}.items():
        env.monkeypatch.setenv(key, value)
    try:
        rc, _, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "e")
        assert rc == 0, err[-2000:]
        assert (env.tmp / "e" / "metrics.json").is_file()
        assert not dist.is_initialized(), "the process group outlived the command"
    finally:
        if dist.is_initialized():
            dist.destroy_process_group()


_LATE_WORKER_DEATH = """
import os, signal, sys, time
import torch
from torch.utils.data import DataLoader, Dataset
from torch.utils.data import dataloader
from instagram_hdmap import engine

class Frames(Dataset):
    def __len__(self):
        return 8

    def __getitem__(self, i):
        return {"images": torch.zeros(1, 3, 4, 4)}

class Interrupted(torch.nn.Module):
    def forward(self, batch):
        raise KeyboardInterrupt  # a SIGTERM, as a training turns it into one

real = dataloader._MultiProcessingDataLoaderIter._shutdown_workers

def signal_arrives_late(self):  # the same signal reaches the worker during the shutdown (a loaded machine)
    if not self._shutdown:
        for worker in self._workers:
            os.kill(worker.pid, signal.SIGKILL)
        time.sleep(0.3)
    return real(self)

dataloader._MultiProcessingDataLoaderIter._shutdown_workers = signal_arrives_late
try:
    engine.evaluate(Interrupted(), None, DataLoader(Frames(), batch_size=2, num_workers=1), torch.device("cpu"))
except KeyboardInterrupt:
    print("interrupted: saved", flush=True)
sys.exit(130)
"""


@row("S20", "a loop over data-loader workers cut short by a scheduler's SIGTERM to the whole process group, on a "
            "loaded machine (seen once in a full suite, in S9-sigterm_saves_last_pt): the workers were shut down "
            "later by the iterator's __del__, where the worker's death came in as an 'Exception ignored ... "
            "DataLoader worker is killed by signal' traceback under the run's one-line message (or in the middle of "
            "the save of last.pt); the loop shuts its workers down as it ends")
def row_workers_shut_down_when_a_loop_is_cut_short(env):
    p = subprocess.run([sys.executable, "-c", _LATE_WORKER_DEATH], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "PYTHONPATH": str(REPO / "src")})
    assert p.returncode == 130 and p.stdout.strip() == "interrupted: saved", (p.returncode, p.stdout, p.stderr)
    assert "Traceback" not in p.stderr and "Exception ignored" not in p.stderr, p.stderr[-2000:]


@row("S21", "model.backbone.weights: an ImageNet file with NaN weights loaded silently (every loss NaN from the first "
            "step); a file saved from a DataParallel model ('module.' keys) was called 'another EfficientNet "
            "variant?', one wrapped as {'state_dict': ...} 'not a state dict'; a folder, the release URL or name were "
            "'weight file not found' alone. NaN is named, the wrappers are read, the others say what to give")
def row_backbone_weights_of_other_shapes(env):
    from efficientnet_pytorch import EfficientNet

    from instagram_hdmap.models import build_model

    state = EfficientNet.from_name("efficientnet-b0").state_dict()
    base = ["model.backbone.name=efficientnet-b0", "data.image_size=[64,160]", "model.gnn.num_vertices=64"]

    def build(weights):
        return build_model(load_config(None, [*base, f"model.backbone.weights={weights}"]), pretrained=True)

    files = {"nan": {k: v.float() * float("nan") if v.is_floating_point() else v for k, v in state.items()},
             "module": {f"module.{k}": v for k, v in state.items()}, "wrapped": {"state_dict": state}}
    for name, value in files.items():
        torch.save(value, env.tmp / f"{name}.pth")
    with pytest.raises(UserError, match=r"nan\.pth: the weights _conv_stem\.weight \(and \d+ more tensors\) hold NaN"):
        build(env.tmp / "nan.pth")
    for name in ("module", "wrapped"):
        stem = build(env.tmp / f"{name}.pth").backbone.trunk._conv_stem.weight
        assert torch.equal(stem, state["_conv_stem.weight"]), name
    (env.tmp / "folder").mkdir()
    with pytest.raises(UserError, match=r"folder \(it is a folder: give the \.pth file in it\)"):
        build(env.tmp / "folder")
    for given in ("efficientnet-b0", "ImageNet"):
        with pytest.raises(UserError, match=rf"not found: {given} \(to download efficientnet-b0's ImageNet release, "
                                            r"give model\.backbone\.weights=imagenet\)"):
            build(given)


@row("S21", "Mapper(model, config) with a config of another grid than the model was built with (a model built and "
            "loaded by hand, the YAML file of another run): the model's BEV pixels were read as metres of the config's "
            "grid, every element moved and scaled, exit 0; another image size was refused deep in the forward as "
            "'resize them (... Mapper do)'. Both named when the Mapper is made")
def row_mapper_model_of_another_config(env):
    from instagram_hdmap import Mapper
    from instagram_hdmap.models import build_model

    cfg = env.cfg()
    model = build_model(cfg).eval()
    Mapper(model, cfg)  # the model's own config: taken
    for overrides, named in ((["grid.resolution=0.5", "grid.cell_size=2"], r"grid BEVGrid\(.*resolution=0\.25"),
                             (["grid.xbound=[-16,16]", "grid.ybound=[-8,8]", "grid.resolution=0.5"], "grid BEVGrid"),
                             (["data.image_size=[128,320]"], r"data\.image_size \[64, 160\] \(config: \[128, 320\]\)")):
        with pytest.raises(ValueError, match=rf"Mapper: the model was built for another config .*{named}"):
            Mapper(model, env.cfg(*overrides))


@row("S21", "evaluate of a checkpoint trained on data.ped_crossing=edges under a CONFIG of another crossing convention "
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


@row("S21", "demo.random_map_baseline (benchmarks/README.md's python -c command): a YAML path as the config was a raw "
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


@row("S21", "train.init_from of a checkpoint of another architecture (another backbone, GNN depth, a temporal one into "
            "a single-frame model): the error listed weight names only ('backbone.stages.0.0.weight (not in this "
            "model)'); it now names the model keys on which the two configs differ")
def row_init_from_other_architecture_names_the_keys(env):
    base = ["train.max_steps=1", f"train.init_from={env.ckpt}", f"train.out_dir={env.tmp / 'run'}"]
    env.error(r"do not fit this model's architecture .*, as the configs differ in model\.gnn\.layers: checkpoint 2 vs "
              r"now 3; start from", "train", env.yaml, *base, "model.gnn.layers=3")
    env.error(r"as the configs differ in model\.backbone\.name: checkpoint 'tiny' vs now 'efficientnet-b0'", "train",
              env.yaml, *base, "model.backbone.name=efficientnet-b0", "model.backbone.from_scratch=true")
    assert not (env.tmp / "run" / "last.pt").exists()


@row("S21", "Mapper.from_checkpoint(path, config=cfg) (Mapper.from_onnx takes one) was 'unknown decoding option(s) "
            "config', from_checkpoint(path, 'x.yaml') \"device='x.yaml' is not a device\"; both say that the model is "
            "built from the checkpoint's own config and that overrides= changes keys")
def row_mapper_from_checkpoint_given_a_config(env):
    from instagram_hdmap import Mapper

    for args, kwargs in (((), {"config": env.cfg()}), ((str(env.yaml),), {}), ((env.cfg(),), {})):
        with pytest.raises(TypeError, match=r"Mapper\.from_checkpoint builds the model from the config saved in the "
                                            r"checkpoint; it takes no config \(.*given\): change keys with overrides="):
            Mapper.from_checkpoint(env.ckpt, *args, **kwargs)
    Mapper.from_checkpoint(env.ckpt, "cpu", overrides=["model.gnn.match_threshold=0.2"])


@row("S21", "Persistence and InstanceTracker took an element whose pts hold NaN (the evaluation refuses it): it "
            "matched nothing, was remembered and carried, or took a new ID each frame, with no word; both name the "
            "element")
def row_persistence_nan_points(env):
    from instagram_hdmap.geometry import BEVGrid
    from instagram_hdmap.persistence import InstanceTracker, Persistence, PersistenceInputError

    grid = BEVGrid(-15, 15, -7.5, 7.5, 0.15, 4)
    good = {"pts": np.array([[0.0, 1.0], [5.0, 1.0]]), "label": 0, "score": 0.9}
    for bad in ([[np.nan, 1.0], [5.0, 1.0]], torch.tensor([[0.0, np.inf], [5.0, 1.0]])):
        for meter in (Persistence(grid, frames=2), InstanceTracker(grid)):
            with pytest.raises(PersistenceInputError, match=r"sample 0 \(scene 's'\).*element 1's pts hold NaN or "
                                                            r"infinite coordinates"):
                meter([[good, {**good, "pts": bad}]], ["s"], [0], [np.eye(4)])
            meter([[good]], ["s"], [0], [np.eye(4)])  # finite: taken


@row("S21", "a self-intersecting road_segment / lane polygon of a map expansion was skipped (as the devkit does) with "
            "no word: the samples near it lost that boundary; the skipped records are counted in one warning per map "
            "naming the file")
def row_map_self_intersecting_area_polygons_counted(env):
    from instagram_hdmap.data.local_map import load_location_map

    maps = env.tmp / "root" / "maps"
    shutil.copytree(env.world / "maps", maps)
    path = next((maps / "expansion").glob("*.json"))
    m = json.loads(path.read_text())
    tokens = [f"bowtie{i}" for i in range(4)]
    m["node"] += [{"token": t, "x": x, "y": y} for t, (x, y) in zip(tokens, [(0, 0), (10, 10), (10, 0), (0, 10)])]
    polygons = {p["token"]: p for p in m["polygon"]}
    bad = m["road_segment"][0]
    polygons[bad["polygon_token"]].update(exterior_node_tokens=tokens, holes=[])
    path.write_text(json.dumps(m))
    with pytest.warns(UserWarning, match=rf"{path.name}: 1 invalid \(self-intersecting\) road_segment / lane "
                                         rf"polygon\(s\) skipped, their boundaries not drawn \({bad['token']}\)"):
        load_location_map(env.tmp / "root", path.stem)


@row("S21", "train stopped by train.max_steps before the end of its schedule: README says the run 'ends before its "
            "final LR, and says so', but it printed only 'done: epoch 0, step 1' (log.jsonl's schedule_complete alone "
            "held it); a note says so and how to finish")
def row_max_steps_says_the_schedule_is_cut(env):
    run = env.tmp / "run"
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={run}", "train.max_steps=1", "train.epochs=2")
    assert rc == 0, err
    assert re.search(r"note: train\.max_steps=1 stopped the run before the end of its schedule \(progress 0\.\d+; "
                     r"lr .*\): resume with a larger train\.max_steps", out), out
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={run}", "train.epochs=2", "--resume", run / "last.pt")
    assert rc == 0 and "stopped the run before the end" not in out, out + err


@row("S21", "eval.cmap_match_m (or eval.flicker_threshold_m) given while eval.cmap (eval.flicker) is off: the setting "
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


@row("S21", "evaluate --protocol raster eval.also_protocols=[vector] on a config of the vector protocol (tiny, demo): "
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


@row("S21", "train --resume with another data.ped_crossing (the crossings' targets: edges or rings) or data.image_fit "
            "(the images the model learns from): the run went on with the other targets / images, mixed into one "
            "model, exit 0, no word; both are checked as the other keys that define the training targets")
def row_resume_with_another_crossing_convention_or_image_fit(env):
    run = env.tmp / "run"
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={run}", "train.max_steps=1", "train.epochs=2")
    assert rc == 0, err
    for override, named in (("data.ped_crossing=each", "data.ped_crossing: checkpoint 'edges' vs now 'each'"),
                            ("data.image_fit=stretch", "data.image_fit: checkpoint 'cover' vs now 'stretch'")):
        env.error(rf"last\.pt was trained with an incompatible config \({re.escape(named)}\); resume it with the "
                  r"config it was trained with, or start a new run from its weights with train\.init_from=", "train",
                  env.yaml, f"train.out_dir={run}", "train.epochs=2", override, "--resume", run / "last.pt")
    assert load_checkpoint(run / "last.pt")["step"] == 1


@row("S21", "FlickerMeter.merge / ConsistentAPMeter.merge of a state whose pose is NaN, None or 3x3 (a hand-built or "
            "damaged state): merged as it was; the flicker rate came out NaN with no word, or compute() failed in a "
            "raw matmul error / named the tracker's frame, not the merged state; merge names the state's sample")
def row_drive_meter_merge_checks_poses(env):
    import copy

    from instagram_hdmap.evaluation.consistency import ConsistentAPMeter, FlickerMeter
    from instagram_hdmap.evaluation.inputs import EvaluationInputError
    from instagram_hdmap.geometry import BEVGrid

    grid = BEVGrid(-15, 15, -7.5, 7.5, 0.15, 4)
    pred = {"pts": np.array([[0.0, 1.0], [5.0, 1.0]]), "label": 0, "score": 0.9}
    gt = {"pts": np.array([[0.0, 1.0], [5.0, 1.0]]), "label": 0}
    for meter in (FlickerMeter, ConsistentAPMeter):
        mine, other = meter(grid), meter(grid)
        mine.update([[pred]], [[gt]], ["s"], [0], [np.eye(4)])
        other.update([[pred]], [[gt]], ["s"], [1], [np.eye(4)])
        for pose, named in ((np.full((4, 4), np.nan), "NaN or infinite"), (None, r"4x4 .*got shape \[\]"),
                            (np.eye(3), r"4x4 .*got shape \[3, 3\]")):
            state = copy.deepcopy(other.state_dict())
            state["records"][("s", 1)]["pose"] = pose
            with pytest.raises(EvaluationInputError, match=rf"{meter.__name__}\.merge: the state's sample \(scene 's', "
                                                          rf"frame 1\): its ego pose .*{named}"):
                copy.deepcopy(mine).merge(state)
        state = copy.deepcopy(other.state_dict())
        state["records"][("s", 1)]["pose"] = np.eye(4).tolist()  # a list: taken
        mine.merge(state)
        mine.compute()


@row("S21", "a YAML path where the Python API takes a config (build_model, inference.load_model, "
            "Persistence.from_config, InstanceTracker.from_config, train, predict.run_evaluation; build_dataset and "
            "Evaluator.from_config took one): a raw \"'str' object has no attribute 'grid'\" (or 'does not support "
            "item assignment') from deep inside; each reads the file (config.as_config, one helper), "
            "BEVGrid.from_config(path) and a None config (Mapper(model, None) took the default config) are a "
            "TypeError naming the function")
def row_yaml_path_where_a_config_goes(env):
    from instagram_hdmap import Mapper
    from instagram_hdmap.geometry import BEVGrid
    from instagram_hdmap.inference import load_model
    from instagram_hdmap.models import build_model
    from instagram_hdmap.persistence import InstanceTracker, Persistence

    path = str(env.yaml)
    assert type(build_model(path)).__name__ == "InstaGraM"
    assert load_model(env.ckpt, path)[1].grid == env.cfg().grid
    assert Persistence.from_config(path) is None  # persist_frames 0
    assert Persistence.from_config({"model": {"temporal": {"persist_frames": 2}}}).frames == 2
    assert InstanceTracker.from_config(path).match_m == env.cfg().model.temporal.persist_match_m
    with pytest.raises(TypeError, match=r"load_model takes an ExperimentConfig .* or a YAML file, got NoneType"):
        load_model(env.ckpt, None)
    with pytest.raises(TypeError, match=r"Mapper takes an ExperimentConfig"):  # was the default config: another grid
        Mapper(build_model(path), None)
    with pytest.raises(TypeError, match=r"BEVGrid\.from_config takes a config's grid section \(cfg\.grid\) or the "
                                        r"config, got str"):
        BEVGrid.from_config(path)


@row("S21", "docs/deploy.md's 'Using the file without this package': onnxruntime's outputs (NumPy arrays) handed to "
            "postprocess.postprocess_batch, as the page says, were a raw \"'numpy.ndarray' object has no attribute "
            "'float'\"; outputs of a model of another grid size decoded with this grid came out in wrong metres, "
            "exit 0. NumPy outputs are read, a grid of another size is named")
def row_postprocess_numpy_outputs_and_grid(env):
    from instagram_hdmap.data import build_dataset
    from instagram_hdmap.data.base import collate_fn
    from instagram_hdmap.geometry import BEVGrid
    from instagram_hdmap.inference import load_model
    from instagram_hdmap.postprocess import decode_options, postprocess_batch

    model, cfg, _ = load_model(env.ckpt, env.cfg())
    grid = BEVGrid.from_config(cfg.grid)
    batch = collate_fn([build_dataset(cfg, cfg.data.val_split, augment=False)[0]])
    with torch.no_grad():
        outputs = model(batch)
    options = decode_options(cfg.model.gnn, grid)
    ref = postprocess_batch(outputs, grid, **options)
    got = postprocess_batch({k: v.numpy() for k, v in outputs.items()}, grid, **options)
    assert [[(p["label"], p["pts"].tolist()) for p in s] for s in got] == [
        [(p["label"], p["pts"].tolist()) for p in s] for s in ref]
    with pytest.raises(ValueError, match=r"postprocess_batch: the outputs are of a model of another grid "
                                         r"\('pred_heatmap' H x W 32 x 64, the grid 100 x 200\)"):
        postprocess_batch(outputs, BEVGrid(-15, 15, -7.5, 7.5, 0.15, 4), **options)


@row("S21", "train.init_from with model.backbone.weights set (a paper config, whose weights=imagenet, fine-tuned from "
            "a checkpoint): the ImageNet file was not loaded (the checkpoint's backbone wins), with no word; a note "
            "says so")
def row_init_from_with_backbone_weights_noted(env):
    from efficientnet_pytorch import EfficientNet

    from instagram_hdmap.models import build_model

    b0 = ["model.backbone.name=efficientnet-b0", "model.backbone.from_scratch=true"]
    cfg = env.cfg(*b0)
    ckpt = save_checkpoint({"model": build_model(cfg).state_dict(), "config": config_to_dict(cfg)}, env.tmp / "b0.pt")
    torch.save(EfficientNet.from_name("efficientnet-b0").state_dict(), env.tmp / "imagenet.pth")
    rc, out, err = env.cli("train", env.yaml, "model.backbone.name=efficientnet-b0",
                           f"model.backbone.weights={env.tmp / 'imagenet.pth'}", f"train.init_from={ckpt}",
                           "train.max_steps=1", f"train.out_dir={env.tmp / 'run'}")
    assert rc == 0, err
    assert (f"note: model.backbone.weights={env.tmp / 'imagenet.pth'} is not loaded: the backbone starts from the "
            f"weights of train.init_from={ckpt}") in out


@row("S21", "evaluate-json --protocol raster of a GT file whose meta states a 16 m x 8 m patch (export-gt of the tiny "
            "config): the advice 'pass --xbound -8 8 --ybound -4 4', followed, was refused next ('16 m is not a whole "
            "number of --resolution 0.15 m pixels'); the advice names a --resolution that tiles the patch")
def row_raster_canvas_advice_with_resolution(env):
    line = [[-5.0, 1.0], [5.0, 1.0]]
    gt = env.tmp / "gt.json"
    gt.write_text(json.dumps({"meta": {"ground_truth": True, "xbound": [-8.0, 8.0], "ybound": [-4.0, 4.0]},
                              "results": {"a": [{"pts": line, "type": 0}]}}))
    pred = _submission(env.tmp / "p.json", {"a": [{"pts": line, "type": 0, "confidence_level": 0.9}]}, False)
    env.error(r"pass --xbound -8 8 --ybound -4 4 --resolution 0\.1 \(", "evaluate-json", "--pred", pred, "--gt", gt,
              "--protocol", "raster")
    rc, out, err = env.cli("evaluate-json", "--pred", pred, "--gt", gt, "--protocol", "raster", "--xbound", "-8", "8",
                           "--ybound", "-4", "4", "--resolution", "0.1")
    assert rc == 0 and re.search(r"divider\s+1\.0000", out), out + err


@row("S22", "Ctrl-C (or a SIGTERM) in the middle of a training step saved last.pt with the step half done (the "
            "BatchNorm statistics of its forward, the optimizer's moments), which the resume did again: its weights "
            "differed from an uninterrupted run's, with no word. The signal now waits for the step's end")
def row_interrupt_mid_step_resumes_exactly(env):
    import signal

    from instagram_hdmap import engine

    real, calls = engine.optimisation_step, []

    def ctrl_c_in_the_second_step(*args, **kwargs):  # after the forward, before the optimizer's step
        calls.append(1)
        if len(calls) == 2:
            os.kill(os.getpid(), signal.SIGINT)
        return real(*args, **kwargs)

    common = ["train.batch_size=1", "train.val_every=100"]
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={env.tmp / 'whole'}", *common)
    assert rc == 0, err[-2000:]
    env.monkeypatch.setattr(engine, "optimisation_step", ctrl_c_in_the_second_step)
    run = env.tmp / "run"
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={run}", *common)
    assert rc == 130 and load_checkpoint(run / "last.pt")["step"] == 2, (rc, err[-2000:])
    env.monkeypatch.setattr(engine, "optimisation_step", real)
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={run}", "--resume", run / "last.pt", *common)
    assert rc == 0, err[-2000:]
    whole, resumed = load_checkpoint(env.tmp / "whole" / "last.pt")["model"], load_checkpoint(run / "last.pt")["model"]
    assert all(torch.equal(whole[k], resumed[k]) for k in whole), "the resumed weights differ"


@row("S22", "a temporal training with train.stream_warmup: the schedule counted train.epochs x the first (single-frame)"
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


@row("S22", "AV2: a log whose map/ folder holds another log's map files (copied over from a neighbouring log) was "
            "read as that log's map: the GT drew the other place's roads (none here), exit 0. Every map file named "
            "after another log is named")
def row_av2_map_files_of_another_log(env):
    root, log = _av2_copy(env)
    other = sorted((root / "train").iterdir())[1]
    shutil.rmtree(log / "map")
    shutil.copytree(other / "map", log / "map")
    _av2_error(env, root, rf"log {log.name}: .*map.* is the map file of another log \({other.name}\)")


@row("S22", "AV2: data.dataroot given as one log's folder (or a split folder of logs, or a nuScenes root): 'not an AV2 "
            "sensor-dataset root ... its folders: calibration, map, sensors'; the line now names the root and split "
            "that hold it (or data.dataset=nuscenes)")
def row_av2_log_folder_as_the_root(env):
    root, log = _av2_copy(env)
    for given, split in ((log, "train"), (log.parent, "train")):
        line = env.error(r"not an AV2 sensor-dataset root", "export-gt", env.yaml, "data.dataset=av2",
                         "data.splits_file=null", f"data.dataroot={given}", "--split", "val", "--out",
                         env.tmp / "gt.json")
        assert f"data.dataroot={root} with the split '{split}'" in line, line
    line = env.error(r"not an AV2 sensor-dataset root", "export-gt", env.yaml, "data.dataset=av2",
                     "data.splits_file=null", "--split", "val", "--out", env.tmp / "gt.json")  # the nuScenes world
    assert "is a nuScenes dataroot (versions v1.0-trainval): set data.dataset=nuscenes" in line, line


_CACHE_WORLD = {"scenes_train": 1, "scenes_val": 1, "samples_per_scene": 2, "seed": 0, "image_size": "160x90"}


@row("S22", "demo cache: two demos (or a demo and a training) that found no world both generated it, and the second "
            "replaced the first's finished world with --force, moving it away under the process reading it. The "
            "second now keeps the world the first finished and uses it")
def row_demo_cache_world_finished_by_another_process(env):
    from instagram_hdmap import demo

    real = demo.generate_world

    def another_process_finishes_first(out, **kwargs):
        real(out=out, **{**kwargs, "force": True})  # the other demo's generation, done first
        (Path(out) / "mark").write_text("the other process's world")
        return real(out=out, **kwargs)

    env.monkeypatch.setattr(demo, "generate_world", another_process_finishes_first)
    root, reused = demo.ensure_world(env.tmp / "cache", _CACHE_WORLD, progress=False)
    assert reused and (root / "mark").is_file(), "the world another process finished was replaced"


@row("S22", "demo cache: a cached world damaged part-way (a camera image other than CAM_FRONT deleted, a table JSON "
            "cut short or removed, a map file removed, world.json cut short) was reused: a dataset error minutes "
            "later, advising to download the nuScenes map expansion. Named before the run, with 'delete the folder "
            "and run again'")
def row_demo_cache_world_damaged(env):
    from instagram_hdmap import demo
    from instagram_hdmap.config import UserError

    cache = env.tmp / "cache"
    root, _ = demo.ensure_world(cache, _CACHE_WORLD, progress=False)
    pristine = env.tmp / "pristine"
    shutil.copytree(root, pristine)
    damages = {"CAM_BACK": lambda: next((root / "samples" / "CAM_BACK").iterdir()).unlink(),
               "sample_data": lambda: (root / "v1.0-trainval" / "sample_data.json").write_text('[{"token": "a'),
               "boston-seaport": lambda: (root / "maps" / "expansion" / "boston-seaport.json").unlink(),
               "instance": lambda: (root / "v1.0-trainval" / "instance.json").unlink(),
               "world.json": lambda: (root / "world.json").write_text('{"format": "instagram')}
    for what, damage in damages.items():
        shutil.rmtree(root)
        shutil.copytree(pristine, root)
        damage()
        with pytest.raises(UserError, match=rf"is damaged: .*{what}.*delete the folder and run the demo again"):
            demo.ensure_world(cache, _CACHE_WORLD, progress=False)


@row("S22", "INSTAGRAM_HDMAP_CACHE='~/cache' (as a .env file or a Dockerfile's ENV sets it: no shell expands the ~) "
            "generated the demo's world into a folder named '~' in the working directory; a blank value into one "
            "named '  '; XDG_CACHE_HOME was ignored. '~' is the home folder, a blank value the default, "
            "$XDG_CACHE_HOME/instagram_hdmap the default where it is set")
def row_demo_cache_env_tilde(env):
    from instagram_hdmap import demo

    env.monkeypatch.setenv("HOME", str(env.tmp / "home"))
    env.monkeypatch.setenv("INSTAGRAM_HDMAP_CACHE", "~/cache")
    assert demo.default_cache_dir() == env.tmp / "home" / "cache"
    env.monkeypatch.setenv("INSTAGRAM_HDMAP_CACHE", "  ")
    env.monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    assert demo.default_cache_dir() == env.tmp / "home" / ".cache" / "instagram_hdmap"
    env.monkeypatch.setenv("XDG_CACHE_HOME", str(env.tmp / "xdg"))  # was ignored: the worlds filled ~/.cache
    assert demo.default_cache_dir() == env.tmp / "xdg" / "instagram_hdmap"
    env.monkeypatch.setenv("XDG_CACHE_HOME", "relative/cache")  # the spec: a relative value is ignored
    assert demo.default_cache_dir() == env.tmp / "home" / ".cache" / "instagram_hdmap"


@row("S22", "benchmarks/temporal.py with a tiny budget: a single-frame model that detects nothing has flicker 0, and "
            "the summary divided by max(0, 1e-9): 'flicker x0.00 (target: ... flicker x0.5)', the target met by two "
            "models that found nothing. A ratio over 0 is now 'n/a'")
def row_benchmark_temporal_flicker_ratio_over_zero(env):
    bench, _ = _bench_temporal(env)
    nothing = {"steps": 6, "AP_class": {"divider": 0.0}, "mAP": 0.0, "flicker_mean": 0.0,
               "flicker_detected_mean": float("nan")}
    results = [{**nothing, "config": "single", "seed": 0}, {**nothing, "config": "temporal", "seed": 0}]
    text = bench.table(results) + bench.paired([{**r, "config": r["config"] + "_ft"} for r in results])
    assert "x0.00" not in text and "n/a" in text, text


@row("S22", "a temporal training whose memory never fused (model.temporal.max_jump_m=0.01: every frame a pose jump, "
            "as a max_jump_m in other units or drives faster than it would): the fusion trained on nothing, exit 0, "
            "no word (log.jsonl alone counted the statuses). A warning names the statuses and the keys")
def row_temporal_memory_never_fused_warned(env):
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={env.tmp / 'run'}", "model.temporal.memory=bev",
                           "model.temporal.max_jump_m=0.01", "train.epochs=1", "train.val_every=100")
    assert rc == 0, err[-2000:]
    assert re.search(r"warning: the temporal memory was never fused in epoch 0 \(per step: .*pose_jump", out), out


@row("S22", "demo cache on a read-only folder (a shared read-only cache, chattr +i): the one line said '--out "
            "CACHE/synthetic-...: cannot write there; choose a writable folder', synth's option, which the demo does "
            "not have. It names the cache folder and --cache / $INSTAGRAM_HDMAP_CACHE")
def row_demo_cache_read_only(env):
    from instagram_hdmap import demo
    from instagram_hdmap.config import UserError

    def read_only(out, **kwargs):  # what synth says of an --out it cannot write (data/synthetic/jobs.py)
        raise UserError(f"--out {out}: cannot write there (Operation not permitted); choose a writable folder")

    env.monkeypatch.setattr(demo, "generate_world", read_only)
    with pytest.raises(UserError) as e:
        demo.ensure_world(env.tmp / "cache", _CACHE_WORLD, progress=False)
    assert "--out" not in str(e.value) and "--cache" in str(e.value), str(e.value)


@row("S22", "benchmarks/temporal.py on a damaged world cache (a world folder without world.json, a cached world "
            "missing a file): a raw traceback ending in the demo's DemoError. One line, exit 2")
def row_benchmark_temporal_damaged_cache(env):
    from instagram_hdmap.demo import WORLD, world_key

    (env.tmp / "cache" / world_key({**WORLD, "occluders": 0.5})).mkdir(parents=True)  # no world.json
    p = _benchmark_temporal(env, "--steps", "240", "--occluders", "0.5")
    lines = [ln for ln in p.stderr.splitlines() if "error" in ln]
    assert p.returncode == 2 and "Traceback" not in p.stderr, p.stderr[-2000:]
    assert re.search(r"--cache: .* is not a complete synthetic world \(no world.json\)", lines[-1]), p.stderr[-2000:]


@row("S23", "predict-images: a rig file could not give the road's height in its ego frame (the Python API's "
            "Frame(ground_height=...)): a rig in AV2's rear-axle frame (the road 0.38 m below the origin) ran with the "
            "ground plane at z = 0, 0.38 m too high for the IPM / MLP view transforms, with no word, and "
            "'ground_height' in the file was an unknown field. The rig file takes \"ground_height\" and passes it to "
            "the model")
def row_predict_images_rig_ground_height(env):
    from instagram_hdmap.inference import Mapper

    rig, images = _rig_files(env, lambda d: d.__setitem__("ground_height", -0.38))
    seen = []
    forward = Mapper.forward

    def spy(self, batch, memory=None):
        seen.append(batch["ground_height"].tolist())
        return forward(self, batch, memory)

    env.monkeypatch.setattr(Mapper, "forward", spy)
    from instagram_hdmap import predict

    drawn = []
    figures = predict.prediction_figures

    def spy_figures(*args, ground_z=0.0, **kwargs):
        drawn.append(ground_z)  # the pictures project the elements onto the same road
        return figures(*args, ground_z=ground_z, **kwargs)

    env.monkeypatch.setattr(predict, "prediction_figures", spy_figures)
    rc, _, err = env.cli("predict-images", "--checkpoint", env.ckpt, "--rig", rig, "--out", env.tmp / "out",
                         "--device", "cpu", *images)
    assert rc == 0, err[-2000:]
    assert seen and np.allclose(seen[0], [-0.38]), seen
    assert drawn and np.isclose(drawn[0], -0.38), drawn
    rig, _ = _rig_files(env, lambda d: d.__setitem__("ground_height", "low"))
    env.error(r"rig\.json: 'ground_height' must be a number of metres", "predict-images", "--checkpoint", env.ckpt,
              "--rig", rig, "--out", env.tmp / "out2", "--device", "cpu", *images)


@row("S23", "evaluate-json --protocol raster re-scoring evaluate's predictions against export-gt's GT (a 16 m x 8 m "
            "grid at 0.25 m): the canvas advice named --resolution 0.1, the first that tiles the patch, and the raster "
            "AP at 0.1 m pixels differed from evaluate's at the config's 0.25 m (divider AP@0.5 0.67 against 1.0, "
            "exit 0, no word). export-gt and evaluate state the grid's resolution in the meta; the advice names it "
            "and another resolution is noted")
def row_evaluate_json_raster_resolution_of_the_gt(env):
    from instagram_hdmap.evaluation.evaluator import evaluate_files
    from instagram_hdmap.geometry import BEVGrid

    gt = env.tmp / "gt.json"
    assert env.cli("export-gt", env.yaml, "--out", gt)[0] == 0
    data = json.loads(gt.read_text())
    assert data["meta"]["resolution"] == 0.25, data["meta"]
    rng = np.random.default_rng(0)
    preds = {t: [{"pts": (np.array(v["pts"]) + rng.normal(0, 0.8, 2)).tolist(), "type": v["type"],
                  "confidence_level": float(rng.uniform())} for v in vs] for t, vs in data["results"].items()}
    meta = {k: data["meta"][k] for k in ("classes", "xbound", "ybound", "frame", "dataset")}
    pred = env.tmp / "pred.json"
    pred.write_text(json.dumps({"meta": {**meta, "ground_truth": False}, "results": preds}))
    line = env.error(r"pass --xbound -8 8 --ybound -4 4 --resolution 0\.25 ", "evaluate-json", "--pred", pred, "--gt",
                     gt, "--protocol", "raster")
    assert "--resolution 0.1" not in line, line
    m = evaluate_files(pred, gt, "raster", grid=BEVGrid(-8, 8, -4, 4, 0.1, cell_size=1))
    assert any("--resolution 0.25 to reproduce evaluate's number" in n for n in m["notes"]), m["notes"]
    m = evaluate_files(pred, gt, "raster", grid=BEVGrid(-8, 8, -4, 4, 0.25, cell_size=1))
    assert not any("pixels" in n for n in m["notes"]), m["notes"]


@row("S23", "targets of a polyline given open whose last point is its first (a divider loop around an island, "
            "line-merged into one line): the last point shared the first's cell and was dropped, so the GT graph, "
            "decoded back to metres (the oracle's ceiling, the training targets), lost the closing segment with no "
            "word. Such a loop is a cycle, decoded back closed")
def row_targets_of_an_open_loop(env):
    from instagram_hdmap.geometry import BEVGrid
    from instagram_hdmap.inference import gt_outputs
    from instagram_hdmap.postprocess import postprocess_batch
    from instagram_hdmap.targets import build_targets

    grid = BEVGrid(-30.0, 30.0, -15.0, 15.0, 0.15, 8)
    loop = np.array([[-4.0, -2.0], [4.0, -2.0], [4.0, 2.0], [-4.0, 2.0], [-4.0, -2.0]])
    targets = build_targets([{"pts": loop, "label": 0, "closed": False}], grid)
    (decoded,) = postprocess_batch(gt_outputs({k: v[None] for k, v in targets.items()}, grid, 3), grid)
    assert len(decoded) == 1, decoded
    pts = np.asarray(decoded[0]["pts"])
    assert len(pts) == 5 and np.allclose(pts[0], pts[-1]) and np.abs(pts - loop).max() <= 0.075 + 1e-6, pts
    u = np.array([[-4.0, -2.0], [4.0, -2.0], [4.0, 2.0], [-4.0, 2.0]])  # an open U stays open
    targets = build_targets([{"pts": u, "label": 0, "closed": False}], grid)
    (decoded,) = postprocess_batch(gt_outputs({k: v[None] for k, v in targets.items()}, grid, 3), grid)
    assert len(decoded) == 1 and len(decoded[0]["pts"]) == 4 and not decoded[0]["closed"], decoded


@row("S24", "a splits file written by hand: a list of sample tokens (or scene tokens) in place of scene names said "
            "only 'names 2 scene(s) not in version', a JSON list of lists said 'it has: none', a YAML file said only "
            "'not valid JSON', split names other than train/val did not point at data.train_split / data.val_split. "
            "Each now says what it holds and what to write")
def row_splits_file_written_by_hand(env):
    names = json.loads((env.world / "splits.json").read_text())
    samples = json.loads((env.world / "v1.0-trainval" / "sample.json").read_text())
    scenes = json.loads((env.world / "v1.0-trainval" / "scene.json").read_text())
    val_scenes = [s for s in scenes if s["name"] in names["val"]]
    cases = {
        "tokens.json": ({**names, "val": [r["token"] for r in samples if r["scene_token"] == val_scenes[0]["token"]]},
                        r"split 'val' names \d+ scene\(s\) not in .*these are sample tokens: .*'name' of scene\.json"),
        "scene_tokens.json": ({**names, "val": [s["token"] for s in val_scenes]},
                              r"these are scene tokens: a splits file lists scene names"),
        "lists.json": ([names["train"], names["val"]], r"lists\.json holds a JSON list, not an object of splits"),
        "names.json": ({"mytrain": names["train"], "myval": names["val"]},
                       r"it has: mytrain, myval \(set data\.train_split / data\.val_split"),
    }
    for name, (content, pattern) in cases.items():
        path = env.tmp / name
        path.write_text(json.dumps(content))
        env.error(pattern, "show-gt", env.yaml, f"data.splits_file={path}", "--out", env.tmp / "show")
    path = env.tmp / "splits.yaml"
    path.write_text("train:\n" + "".join(f"- {n}\n" for n in names["train"]) + "val:\n"
                    + "".join(f"- {n}\n" for n in names["val"]))
    env.error(r"splits\.yaml is not valid JSON: .*a YAML file\? write it as JSON", "show-gt", env.yaml,
              f"data.splits_file={path}", "--out", env.tmp / "show")


@row("S24", "generate_world (the Python API of synth) given a count as a float (scenes_train=1.0) was a raw "
            "TypeError 'slice indices must be integers' (samples_per_scene=1.0 wrote 'samples: 2.0' into world.json), "
            "an image_size of (64.5, 48) was cut to 64 px with no word, ('a', 48) a raw ValueError. Each is named; "
            "numpy integers and whole floats of pixels still work")
def row_synth_api_counts_not_whole(env):
    from instagram_hdmap.data.synthetic import generate_world

    small = dict(scenes_train=1, scenes_val=1, samples_per_scene=1, image_size="64x48", progress=False, workers=1)
    for change, pattern in (({"scenes_train": 1.0}, r"--scenes-train 1\.0: .* whole number"),
                            ({"samples_per_scene": 1.0}, r"--samples-per-scene 1\.0: .* whole number"),
                            ({"image_size": (64.5, 48)}, r"--image-size \(64\.5, 48\): expected two whole numbers"),
                            ({"image_size": ("a", 48)}, r"--image-size \('a', 48\): expected two whole numbers")):
        with pytest.raises(UserError, match=pattern):
            generate_world(env.tmp / "w", **{**small, **change})
        assert not (env.tmp / "w").exists()
    manifest = generate_world(env.tmp / "w", **{**small, "scenes_val": np.int64(1), "image_size": [64.0, 48.0]})
    assert manifest["image_size"] == [64, 48] and manifest["samples"] == 2, manifest


@row("S24", "a splits file saved by a Windows editor: with a UTF-8 byte-order mark it was refused ('Unexpected UTF-8 "
            "BOM'), as UTF-16 (Windows PowerShell's Out-File) a raw UnicodeDecodeError traceback, exit 1; a folder "
            "given as the splits file said 'not found'. Both encodings are read; the folder is named as one")
def row_splits_file_with_a_byte_order_mark(env):
    text = (env.world / "splits.json").read_text()
    for name, data in (("bom.json", b"\xef\xbb\xbf" + text.encode()), ("utf16.json", text.encode("utf-16"))):
        path = env.tmp / name
        path.write_bytes(data)
        rc, _, err = env.cli("show-gt", env.yaml, f"data.splits_file={path}", "--out", env.tmp / f"show_{name}")
        assert rc == 0, err[-3000:]
    (env.tmp / "folder.json").mkdir()
    env.error(r"splits file .*folder\.json is a folder \(config key data\.splits_file\)", "show-gt", env.yaml,
              f"data.splits_file={env.tmp / 'folder.json'}", "--out", env.tmp / "show")


@row("S24", "synth --out below a file (notes.txt/world): 'cannot write there (File exists)', naming neither the file "
            "nor the cause; now names the file that is not a folder")
def row_synth_out_below_a_file(env):
    (env.tmp / "notes.txt").write_text("x")
    env.error(r"--out .*notes\.txt/world: .*notes\.txt is a file, not a folder", "synth", "--out",
              env.tmp / "notes.txt" / "world", "--scenes-train", "1", "--scenes-val", "1", "--samples-per-scene", "1",
              "--image-size", "64x48")


@row("S24", "synth --out '' (an unset shell variable, --out \"$WORLD\") was taken for the current folder: refused "
            "there only because it was not empty (an empty one got the world). An empty --out is named")
def row_synth_out_empty_string(env):
    env.error(r"--out '': an empty path", "synth", "--out", "", "--scenes-train", "1", "--scenes-val", "1",
              "--samples-per-scene", "1", "--image-size", "64x48")
    from instagram_hdmap.data.synthetic import generate_world

    with pytest.raises(UserError, match=r"--out '': an empty path"):  # the Python API too
        generate_world("", scenes_train=1, scenes_val=1, samples_per_scene=1, image_size="64x48", progress=False)


@row("S25", "export-onnx --out runs/x/best.pt while exporting last.pt (a slip of the file name) replaced the best "
            "checkpoint with the ONNX graph, exit 0; export-gt and evaluate-json --out did the same with JSON. An "
            "existing PyTorch checkpoint as an output file is refused before the work")
def row_output_over_another_checkpoint(env):
    best = env.tmp / "best.pt"
    shutil.copy(env.ckpt, best)
    before = best.read_bytes()
    gt = env.tmp / "gt.json"
    rc, _, err = env.cli("export-gt", env.yaml, "--out", gt)
    assert rc == 0, err[-2000:]
    pattern = r"--out .*best\.pt is a PyTorch checkpoint; writing the result there would destroy it"
    env.error(pattern, "export-gt", env.yaml, "--out", best)
    env.error(pattern, "evaluate-json", "--gt", gt, "--pred", gt, "--out", best)
    env.error(pattern, "export-onnx", env.yaml, "--checkpoint", env.ckpt, "--out", best)
    assert best.read_bytes() == before
    rc, _, err = env.cli("evaluate-json", "--gt", gt, "--pred", gt, "--out", env.tmp / "metrics.json")  # any other file
    assert rc == 0, err[-2000:]


@row("S25", "predict --video --fps 0.001 (one frame per 1000 s, in range '> 0') ended after the model had run in "
            "'OpenCV cannot write MP4 here; check the folder is writable and OpenCV was built with FFmpeg', the wrong "
            "cause; the range says where OpenCV's writer stops, before the work, and 0.01 still writes")
def row_video_fps_below_the_time_base(env):
    argv = ("predict", env.yaml, "--checkpoint", env.ckpt, "--scene", _val_scene(env))
    env.error(r"--fps 0\.001: frames per second must be over 0\.001 and at most 1000", *argv, "--video",
              env.tmp / "v.mp4", "--fps", "0.001")
    rc, _, err = env.cli(*argv, "--video", env.tmp / "slow.mp4", "--fps", "0.01")
    assert rc == 0 and (env.tmp / "slow.mp4").stat().st_size > 0, err[-2000:]


@row("S25", "data.dataroot one folder too deep (the version folder, .../v1.0-trainval) or one too high (the folder "
            "holding the nuScenes folder) said 'versions in ...: none (set data.version or --version)', pointing at "
            "the wrong key, and a file given as the dataroot was 'not found'; each now names the dataroot to set")
def row_dataroot_one_folder_off(env):
    version = env.cfg().data.version
    env.error(rf"is a version folder itself: set data\.dataroot to the folder above it, .*{env.world.name}\)",
              "export-gt", env.yaml, f"data.dataroot={env.world / version}", "--out", env.tmp / "gt.json")
    (env.tmp / "data").mkdir()
    (env.tmp / "data" / "nuscenes").symlink_to(env.world, target_is_directory=True)
    env.error(rf"the dataroot is the folder that holds {version}: set data\.dataroot to .*data/nuscenes\)",
              "export-gt", env.yaml, f"data.dataroot={env.tmp / 'data'}", "--out", env.tmp / "gt.json")
    (env.tmp / "gt_val.json").write_text("{}")  # a file where the folder goes: it was "not found"
    env.error(r"dataroot .*gt_val\.json is a file, not a folder", "export-gt", env.yaml,
              f"data.dataroot={env.tmp / 'gt_val.json'}", "--out", env.tmp / "gt.json")


@row("S25", "a submission whose 'type' and 'pts_num' are whole floats (1.0: numpy's float arrays through tolist(), a "
            "MATLAB or R writer) was refused as \"'type' must be a class id 0..2, got 1.0\" (valid input refused); "
            "a whole float is read as its class, 1.5 is still named")
def row_submission_whole_float_ids(env):
    gt = env.tmp / "gt.json"
    rc, _, err = env.cli("export-gt", env.yaml, "--out", gt)
    assert rc == 0, err[-2000:]
    sub = json.loads(gt.read_text())
    sub["meta"]["ground_truth"] = False
    for vectors in sub["results"].values():
        for v in vectors:
            v.update(type=float(v["type"]), pts_num=float(v["pts_num"]), confidence_level=0.9)
    pred = env.tmp / "pred.json"
    pred.write_text(json.dumps(sub))
    rc, out, err = env.cli("evaluate-json", "--gt", gt, "--pred", pred)
    assert rc == 0, err[-2000:]
    assert float(re.search(r"mAP\s+([0-9.]+)", out).group(1)) > 0.5, out
    token = next(t for t, vectors in sub["results"].items() if vectors)
    sub["results"][token][0]["type"] = 1.5
    pred.write_text(json.dumps(sub))
    env.error(r"'type' must be a class id 0\.\.2 .*got 1\.5", "evaluate-json", "--gt", gt, "--pred", pred)


@row("S25", "an argument copied from a web page with a non-breaking space (U+00A0) the terminal does not show: "
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


@row("S25", "OMP_NUM_THREADS=0 or =abc (a laptop's shell profile): OpenMP said 'Invalid value' and took its default, "
            "and the training left the threads alone as for a value the user chose, printing '(OMP_NUM_THREADS)'; an "
            "invalid value now counts as unset (the run chooses its threads), a valid one is still left alone")
def row_invalid_omp_num_threads(env):
    from instagram_hdmap.train import cpu_threads

    cfg = env.cfg()
    for value in ("0", "abc", " "):
        env.monkeypatch.setenv("OMP_NUM_THREADS", value)
        assert isinstance(cpu_threads(cfg), int) and cpu_threads(cfg) >= 1, value
    env.monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert cpu_threads(cfg) is None


@row("S25", "a checkpoint as shared or downloaded, packed: best.pt.gz / .xz said 'not a PyTorch file', a zip archive "
            "holding best.pt 'truncated or corrupt (RuntimeError: Expected hasRecord(\"version\"))', a tar archive "
            "'not a PyTorch file'; each now says what it is and how to unpack it")
def row_packed_checkpoint(env):
    import gzip
    import lzma
    import tarfile

    data = env.ckpt.read_bytes()
    (env.tmp / "best.pt.gz").write_bytes(gzip.compress(data))
    (env.tmp / "best.pt.xz").write_bytes(lzma.compress(data))
    with zipfile.ZipFile(env.tmp / "best.zip", "w") as z:
        z.write(env.ckpt, "run/best.pt")
    with tarfile.open(env.tmp / "best.tar", "w") as t:
        t.add(env.ckpt, "run/best.pt")
    for name, pattern in (("best.pt.gz", r"a gzip-compressed file \(gunzip it first\)"),
                          ("best.pt.xz", r"a xz-compressed file \(unxz it first\)"),
                          ("best.zip", r"not a PyTorch checkpoint but a zip archive of 1 file\(s\) \(run/best\.pt\): "
                                       r"unzip it"),
                          ("best.tar", r"a tar archive \(tar xf it first\)")):
        with pytest.raises(CheckpointError, match=pattern):
            load_checkpoint(env.tmp / name)
    env.error(r"best\.pt\.gz is not a PyTorch checkpoint: it is a gzip-compressed file", "evaluate", env.yaml,
              "--checkpoint", env.tmp / "best.pt.gz", "--out", env.tmp / "eval")


@row("S25", "the file's folder given for the file: evaluate-json --pred EVAL_OUT said 'cannot read ([Errno 21] Is a "
            "directory)', --pred EVAL_OUT/metrics.json 'no results key'; each now names the file that is meant "
            "(a checkpoint's run folder: S27-checkpoint_given_as_a_run_folder)")
def row_folder_given_for_its_file(env):
    rc, _, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "eval")
    assert rc == 0, err[-2000:]
    gt = env.tmp / "gt.json"
    rc, _, err = env.cli("export-gt", env.yaml, "--out", gt)
    assert rc == 0, err[-2000:]
    env.error(r"eval: is a folder, not a submission file; the file in it: .*eval/submission\.json", "evaluate-json",
              "--gt", gt, "--pred", env.tmp / "eval")
    env.error(r"metrics\.json: no 'results' key.*this is a metrics file; evaluate writes the submission as "
              r".*eval/submission\.json", "evaluate-json", "--gt", gt, "--pred", env.tmp / "eval" / "metrics.json")


@row("S25", "a nuScenes table written on Windows (sample_data 'filename' as str() of a WindowsPath, "
            "samples\\\\CAM_FRONT\\\\x.jpg) was 'camera image not found' on Linux (valid input refused); the "
            "backslashes are read as the separators they are when no file of the literal name exists")
def row_windows_separators_in_a_table(env):
    def backslashes(tables):
        for record in tables["sample_data"]:
            record["filename"] = record["filename"].replace("/", "\\")

    root = env.shadow_world(backslashes)
    windows, plain = _s18_dataset(env, root, "val"), _s18_dataset(env, env.world, "val")
    assert torch.equal(windows.load_sample(0)["images"], plain.load_sample(0)["images"])
    rc, _, err = env.cli("evaluate", env.yaml, f"data.dataroot={root}", "--checkpoint", env.ckpt, "--out",
                         env.tmp / "eval")
    assert rc == 0, err[-2000:]


@row("S25", "predict-images with a temporal checkpoint ran it on one frame with an empty memory and no word, where "
            "predict says so for a scene's first frame; it now notes that the frame has no memory and how to carry one")
def row_predict_images_temporal_model(env):
    from instagram_hdmap.models import build_model

    cfg = env.cfg("model.temporal.memory=bev", "model.gnn.sinkhorn_iters=3")
    ckpt = save_checkpoint({"model": build_model(cfg).state_dict(), "config": config_to_dict(cfg)},
                           env.tmp / "temporal.pt")
    rig, images = _rig_files(env)
    rc, out, err = env.cli("predict-images", "--checkpoint", ckpt, "--rig", rig, "--out", env.tmp / "out", *images)
    assert rc == 0 and "a temporal model (bev memory) on one frame: no memory" in out + err, (out + err)[-2000:]
    rc, out, err = env.cli("predict-images", "--checkpoint", env.ckpt, "--rig", rig, "--out", env.tmp / "o2", *images)
    assert rc == 0 and "temporal" not in out + err, (out + err)[-2000:]


@row("S25", "demo --out a file, or a path below a file: 'cannot write there (File exists)', naming neither the file "
            "nor the cause (synth's was fixed in sweep 24); the demo takes the output-folder check of the other jobs")
def row_demo_out_a_file(env):
    (env.tmp / "notes.txt").write_text("mine")
    env.error(r"--out .*notes\.txt: is a file, not a folder", "demo", "--out", env.tmp / "notes.txt", "--cache",
              env.tmp / "cache")
    env.error(r"--out .*notes\.txt/run: .*notes\.txt is a file", "demo", "--out", env.tmp / "notes.txt" / "run",
              "--cache", env.tmp / "cache")
    assert (env.tmp / "notes.txt").read_text() == "mine"


@row("S25", "evaluate with data.val_split=train (a debugging override left in a config, or copied) scored the very "
            "samples the checkpoint was trained on and reported that AP with no word; a note says the split is the "
            "checkpoint's training split")
def row_evaluate_on_the_training_split(env):
    rc, out, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "seen",
                           "data.val_split=train")
    assert rc == 0, err[-2000:]
    assert "data.val_split='train' is the split the checkpoint was trained on" in out + err, (out + err)[-2000:]
    rc, out, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "unseen")
    assert rc == 0 and "the split the checkpoint was trained on" not in out + err, (out + err)[-2000:]


@row("S26", "a mapping given on the command line after one of its keys (model.gnn.layers=3 model.gnn={dim: 64}) "
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


@row("S26", "YAML 1.1's integers: a leading zero made an octal number (train.seed: 0123 ran with seed 83, "
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


@row("S26", "a text key whose text reads as a YAML 1.2 float (name: '3e-4', an experiment named after its learning "
            "rate): save_config wrote it bare (PyYAML's YAML 1.1 sees text), so the run's config.yaml no longer "
            "loaded ('expected str, got 0.0003'); it is written quoted and loads as saved")
def row_saved_config_text_that_reads_as_a_number(env):
    from instagram_hdmap.config import save_config

    for overrides in (["name='3e-4'"], ["name='1e3'", "data.train_split='1e3'"], ["name='010'"], ["name='1:30'"]):
        cfg = env.cfg(*overrides)
        save_config(cfg, env.tmp / "saved.yaml")
        assert load_config(env.tmp / "saved.yaml") == cfg, overrides


@row("S26", "a YAML file (or override) nested hundreds of levels deep: a raw RecursionError traceback naming nothing; "
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


@row("S26", "a text key given a number or a YAML 1.1 word (name: 2024, data.version: 1.0, data.val_split: no) and a "
            "whole-number key given 1e3: refused saying only 'expected str, got 2024 (int)' (a key `on:`: 'unknown "
            "key True'; a section of commented-out keys: 'must be a mapping, got None'); the message now says to "
            "quote the text, how to write the whole number or a list, what YAML did")
def row_text_key_given_a_number_says_quote_it(env):
    path = env.tmp / "text.yaml"
    path.write_text(f"_base_: {env.yaml}\nname: 2024\n")  # in a file (command line: S25-text_keys_...)
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


@row("S26", "eval.flicker_threshold_m in centimetres (100): every GT element counted as detected, the flicker rate 0, "
            "exit 0, while its siblings eval.cmap_match_m and eval.thresholds refuse more than 10 m; refused the same")
def row_flicker_threshold_in_centimetres(env):
    env.error(r"config key 'eval\.flicker_threshold_m' must be in \(0, 10\] \(metres.*centimetres given\?\)",
              "model-summary", env.yaml, "eval.flicker_threshold_m=100")
    assert env.cfg("eval.flicker_threshold_m=10").eval.flicker_threshold_m == 10


@row("S26", "data.val_split equal to data.train_split (a slip, or an overfitting check): validation and the choice "
            "of best.pt scored the training scenes with no word; training notes it at the start")
def row_validation_on_the_training_split_noted(env):
    from instagram_hdmap.train import setting_notes

    notes = setting_notes(env.cfg("data.val_split=train"))
    assert any("data.val_split=train is the training split" in n for n in notes), notes
    assert not any("training split" in n for n in setting_notes(env.cfg()))


@row("S26", "a checkpoint whose config is YAML text (written by hand from the experiment YAML) was read as YAML 1.1, "
            "not as a config file is: lr: 1e-3 was text ('holds a config this version cannot read: expected float, "
            "got '1e-3''), layers: 010 octal 8; it is read as config files are")
def row_checkpoint_config_text_read_as_a_config_file(env):
    import yaml

    from instagram_hdmap.config import config_from_dict

    state = load_checkpoint(env.ckpt)
    text = yaml.safe_dump(state["config"]).replace("lr: 0.001", "lr: 1e-3").replace("seed: 0\n", "seed: 010\n")
    assert "lr: 1e-3" in text and "seed: 010" in text
    path = save_checkpoint({**state, "config": text}, env.tmp / "text_config.pt")
    cfg = config_from_dict(load_checkpoint(path)["config"])
    assert (cfg.train.lr, cfg.train.seed) == (1e-3, 10)


@row("S26", "a decoder's option given with another decoder (model.gnn.same_class_edges=true with decoder=classwise, "
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


@row("S26", "a key that only another setting reads (train.min_lr_factor under the step schedule, train.lr_step / "
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


@row("S26", "benchmarks/temporal.py --set model={temporal: {memory: bev}} (the memory as a mapping, not the dotted "
            "key): the check that --memory alone sets the memory read the dotted key only, so the single-frame "
            "baseline ran with a memory; it reads the keys the override sets")
def row_benchmark_temporal_memory_set_as_a_mapping(env):
    for args in (["--set", "model={temporal: {memory: bev}}"], ["--temporal-set", "model.temporal={memory: bev}"]):
        p = _benchmark_temporal(env, "--memory", "graph", *args, "--steps", "2")
        assert p.returncode == 2 and "Traceback" not in p.stderr, p.stderr[-2000:]
        assert re.search(r"--(temporal-)?set model.*memory: bev}+: the temporal model's memory is --memory \(graph\)",
                         p.stderr), p.stderr[-2000:]
    assert not (env.tmp / "cache").exists()


@row("S26", "a key one letter off (model.gnn.layer, train.max_step, MODEL.gnn.layers) was refused with the section's "
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


@row("S26", "an override written with a flag, as the benchmarks' --set or other tools' --model.gnn.layers=9: "
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


@row("S27", "synth --force over a world that a training (or an evaluation, a prediction) in another process was "
            "reading replaced it under that process, both exit 0: the new world's images have the old one's file "
            "names, so the training went on with them and the old world's maps and poses; the synth is now refused, "
            "naming --out")
def row_synth_force_over_a_world_being_read(env):
    world = env.tmp / "w"
    shutil.copytree(env.world, world)
    code = ("import sys, time\n"
            "from instagram_hdmap.config import load_config\n"
            "from instagram_hdmap.data import build_dataset\n"
            f"cfg = load_config({str(env.yaml)!r}, ['data.dataroot={world}',\n"
            f"                  'data.splits_file={world / 'splits.json'}'])\n"
            "dataset = build_dataset(cfg, cfg.data.train_split)  # held while it lives\n"
            "print('reading', flush=True); time.sleep(60)\n")
    reader = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                              env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    try:
        assert reader.stdout.readline().strip() == "reading"
        before = (world / "world.json").read_text()
        env.error(r"--out .*w: the world there is being read by another process .*choose another --out", "synth",
                  "--out", world, "--force", "--seed", "7", "--scenes-train", "1", "--scenes-val", "0",
                  "--samples-per-scene", "1", "--image-size", "160x90")
        assert (world / "world.json").read_text() == before
    finally:
        reader.kill()
        reader.wait()


@row("S27", "train.out_dir renamed while the run wrote to it: a raw FileNotFoundError traceback from TensorBoard's "
            "writer thread (or, when the next save came first, a new folder of the old name holding a lone last.pt); "
            "now one line naming the folder, the step, and where it is now to resume")
def row_run_folder_renamed_during_training(env):
    from instagram_hdmap import train as train_module

    run, moved = env.tmp / "run", env.tmp / "run2"
    save = train_module.save_checkpoint

    def save_then_rename(state, path):  # the user's `mv run run2` right after the first epoch's checkpoint
        out = save(state, path)
        if not moved.exists() and Path(path).name == "last.pt":
            run.rename(moved)
        return out

    env.monkeypatch.setattr(train_module, "save_checkpoint", save_then_rename)
    with pytest.raises(UserError, match=rf"train.out_dir {re.escape(str(run))} was moved or removed while this run "
                                        rf"wrote to it.*stopped at step \d+; it is now {re.escape(str(moved))}: "
                                        rf"resume there with --resume {re.escape(str(moved / 'last.pt'))}"):
        _toy_run(env, [0.2, 0.3], "train.epochs=2", "train.batch_size=2")
    assert not run.exists() and (moved / "last.pt").is_file()
    assert load_checkpoint(moved / "last.pt")["step"] >= 1


@row("S27", "--resume with a model key that leaves the model's computation as it is was refused as 'an incompatible "
            "config': model.backbone.grad_checkpoint (turned on after running out of memory), the decoding options "
            "(model.gnn.decoder, read at validation only); now it resumes, and a decoding option is named in the note "
            "that best.pt's score was measured with another validation")
def row_resume_with_a_memory_or_decoding_setting(env):
    run = env.tmp / "run"
    _toy_run(env, [0.2], "train.epochs=2", "train.max_steps=1")
    env.capsys.readouterr()
    summary = _toy_run(env, [0.3, 0.1], "train.epochs=2", "model.backbone.grad_checkpoint=false",
                       "model.gnn.decoder=mutual", resume=str(run / "last.pt"))
    out = env.capsys.readouterr().out
    assert summary["step"] == 4
    assert re.search(r"note: the best score so far .*another validation \(model\.gnn\.decoder: checkpoint 'greedy' "
                     r"vs now 'mutual'\)", out), out
    assert "grad_checkpoint" not in out  # the same model, the same scores: nothing to say


@row("S27", "--resume with another train.lr, train.schedule, train.warmup, data.augment ... went on with no word, and "
            "config.yaml was rewritten with the new values as if the whole run had been trained with them; now a note "
            "names each changed training setting and says the steps so far were trained with the checkpoint's")
def row_resume_with_other_training_settings_noted(env):
    run = env.tmp / "run"
    _toy_run(env, [0.2], "train.epochs=2", "train.max_steps=1")
    env.capsys.readouterr()
    summary = _toy_run(env, [0.3, 0.1], "train.epochs=2", "train.lr=0.01", "train.warmup=0.5",
                       "train.max_steps=null", resume=str(run / "last.pt"))
    out = env.capsys.readouterr().out
    assert summary["step"] == 4
    note = next((ln for ln in out.splitlines() if ln.startswith("note: resumed with training settings")), "")
    assert "train.lr: checkpoint 0.001 vs now 0.01" in note and "train.warmup: checkpoint 0.0 vs now 0.5" in note, out
    assert "the 1 step(s) so far trained with the checkpoint's" in note and "max_steps" not in note, note


@row("S27", "evaluate --out into the folder of a running training (a run folder as the evaluation's output) was "
            "refused as 'another evaluation is running in RUN': the lock named the job of the process refused, not "
            "the one holding it; now 'another training is running'")
def row_lock_names_the_job_that_holds_it(env):
    run = env.tmp / "run"
    run.mkdir()
    code = ("import time\nfrom instagram_hdmap.files import lock_folder\n"
            f"lock_folder({str(run)!r}, 'training', 'choose another train.out_dir')\n"
            "print('locked', flush=True); time.sleep(60)\n")
    holder = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                              env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    try:
        assert holder.stdout.readline().strip() == "locked"
        env.error(rf"another training is running in .*run \(process {holder.pid}\); .*choose another --out",
                  "evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", run)
    finally:
        holder.kill()
        holder.wait()


@row("S27", "train.init_from of a checkpoint of another model config whose weights have the same names and shapes "
            "(model.gnn.heads 4 -> 8: each attention projection split into other heads; another model.gnn.nms or "
            "num_vertices) loaded with no word; now a note names the model keys that differ")
def row_init_from_other_model_settings_noted(env):
    _toy_run(env, [0.2], "train.epochs=1", "train.max_steps=1")
    ckpt = shutil.copy(env.tmp / "run" / "last.pt", env.tmp / "heads4.pt")
    env.capsys.readouterr()
    _toy_run(env, [0.2], "train.epochs=1", "train.max_steps=1", f"train.init_from={ckpt}", "model.gnn.heads=8",
             "model.gnn.decoder=mutual", force=True)
    out = env.capsys.readouterr().out
    note = next((ln for ln in out.splitlines() if ln.startswith("note: the checkpoint of train.init_from")), "")
    assert "model.gnn.heads: checkpoint 4 vs now 8" in note, out
    assert "decoder" not in note  # read at inference only: nothing to say


@row("S27", "evaluate --checkpoint RUN (a training run's folder, as train.out_dir names it): 'checkpoint not found: "
            "RUN (it is a folder)', not which file to give; now it names RUN/best.pt and RUN/last.pt")
def row_checkpoint_given_as_a_run_folder(env):
    run = env.tmp / "run"
    run.mkdir()
    shutil.copy(env.ckpt, run / "best.pt")
    shutil.copy(env.ckpt, run / "last.pt")
    env.error(rf"checkpoint not found: .*run \(it is a folder: a training run's; give the checkpoint in it, "
              rf"{re.escape(str(run / 'best.pt'))} or {re.escape(str(run / 'last.pt'))}\)",
              "evaluate", env.yaml, "--checkpoint", run, "--out", env.tmp / "eval")


@row("S27", "--resume with a train.epochs whose schedule ends before the checkpoint's step (3 epochs cut to 1 at "
            "step 3 of epoch 1): 'done', exit 0, after no step, with last.pt and config.yaml still of the 3-epoch run; "
            "now refused, naming the step where the new schedule ends and the epochs that would finish it")
def row_resume_with_fewer_epochs_than_done(env):
    run = env.tmp / "run"
    _toy_run(env, [0.2, 0.25], "train.epochs=3", "train.max_steps=3")  # two steps an epoch: step 3 is in epoch 1
    with pytest.raises(UserError, match=r"train\.epochs=1 ends the schedule at step 2, before checkpoint .*last\.pt's "
                                        r"step 3 \(epoch 1 of its 3\): nothing would be trained; resume with "
                                        r"train\.epochs=2 or more"):
        _toy_run(env, [], "train.epochs=1", resume=str(run / "last.pt"))
    assert _toy_run(env, [0.3], "train.epochs=2", resume=str(run / "last.pt"))["step"] == 4  # cut to 2: runs


@row("S25", "a text key given on the command line a value YAML reads as a number, a date or a boolean (name=2024, "
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


@row("S29", "the official split names on a world of other scenes (data.splits_file=null, data.train_split=mini_train) "
            "said only \"split 'mini_train' ... has no samples\"; it names the devkit's split, the version's scenes "
            "and the official splits that hold them. A v1.0-test folder (no annotations) with its official split "
            "'test' was refused as 'version v1.0-test has no official split'; it is read")
def row_nuscenes_official_split_names_and_v1_0_test(env):
    from nuscenes.utils.splits import create_splits_scenes

    from instagram_hdmap.data.base import DatasetError

    def test_scenes(tables):
        names = sorted(create_splits_scenes()["test"])
        for scene, name in zip(tables["scene"], names):
            scene["name"] = name
        tables["sample_annotation"], tables["instance"] = [], []

    with pytest.raises(DatasetError, match=r"official split 'mini_train' \(8 scenes, .*names none of the \d+ "
                                           r"scene\(s\) of version 'v1\.0-trainval'.*official split\(s\) \w"):
        val_dataset(env.cfg("data.splits_file=null", "data.val_split=mini_train"))
    root = env.shadow_world(test_scenes)
    (root / "v1.0-trainval").rename(root / "v1.0-test")
    ds = val_dataset(env.cfg(f"data.dataroot={root}", "data.version=v1.0-test", "data.splits_file=null",
                             "data.val_split=test"))
    assert len(ds) == len(json.loads((root / "v1.0-test" / "sample.json").read_text()))
    with pytest.raises(DatasetError, match=r"official split\(s\) test: set data\.train_split / data\.val_split"):
        val_dataset(env.cfg(f"data.dataroot={root}", "data.version=v1.0-test", "data.splits_file=null"))


@row("S29", "nuScenes as downloaded in parts: the metadata alone (no samples/ folder), some blob parts only, images "
            "under upper-case names (.JPG) and 0-byte images (a download cut short) were each one 'camera image not "
            "found' or 'cannot be decoded (corrupt or not an image)'; they say that samples/ is missing, how many of "
            "the split's images are missing (and data.on_bad_sample=skip), the name in the other case, '0 bytes'; a "
            "samples/ that is a link to a disk not mounted is said to be one")
def row_nuscenes_images_downloaded_in_parts(env):
    from instagram_hdmap.data.transforms import ImageError

    meta = env.tmp / "meta"
    meta.mkdir()
    for name in ("maps", "v1.0-trainval"):
        (meta / name).symlink_to(env.world / name)
    env.error(r"has no samples/ folder: the camera images are not downloaded, only the metadata \(v1\.0-trainval/\)",
              "show-gt", env.yaml, f"data.dataroot={meta}", "--index", "0", "--out", env.tmp / "show")
    (meta / "samples").symlink_to(env.tmp / "unmounted")  # the blobs on a disk that is not mounted
    env.error(r"samples is a symbolic link to \S+unmounted, which does not exist \(a disk not mounted",
              "show-gt", env.yaml, f"data.dataroot={meta}", "--index", "0", "--out", env.tmp / "show")
    root = env.shadow_world(copy_samples=True)
    tables = {p.stem: json.loads(p.read_text()) for p in (root / "v1.0-trainval").glob("*.json")}
    image = root / camera_record(tables, "CAM_FRONT")[0]["filename"]
    ds = val_dataset(env.cfg(f"data.dataroot={root}"))
    image.rename(image.with_suffix(".JPG"))
    with pytest.raises(ImageError, match=r"the folder holds \S+CAM_FRONT\S+\.JPG, its name in another case"):
        ds[0]
    image.with_suffix(".JPG").unlink()
    with pytest.raises(ImageError, match=r"1 of the \d+ camera images of split 'val' are not in .*partial download.*"
                                         r"data\.on_bad_sample=skip"):
        val_dataset(env.cfg(f"data.dataroot={root}"))[0]
    image.write_bytes(b"")
    with pytest.raises(ImageError, match=r"camera image is empty \(0 bytes\): \S+CAM_FRONT"):
        ds[0]


@row("S29", "a nuScenes download unpacked one level off: the map expansion unpacked into the dataroot or into "
            "maps/ said 'download the map expansion', an empty (0-byte) table 'not valid JSON: Expecting value', "
            "tables one folder too deep (v1.0-trainval/v1.0-trainval) and archives not extracted 'versions in X: "
            "none', no maps/*.png "
            "a bare 'AssertionError: map mask'; each names where the files are, what is missing or that the table "
            "is empty")
def row_nuscenes_unpacked_one_level_off(env):
    from instagram_hdmap.data.base import DatasetError
    from instagram_hdmap.data.local_map import MapError

    for where in ("expansion", "maps"):
        root = env.tmp / f"off_{where}"
        (root / "maps").mkdir(parents=True)
        for name in ("samples", "v1.0-trainval"):
            (root / name).symlink_to(env.world / name)
        for png in (env.world / "maps").glob("*.png"):  # the basemaps the devkit's tables need
            (root / "maps" / png.name).symlink_to(png)
        shutil.copytree(env.world / "maps" / "expansion", root / where, dirs_exist_ok=True)
        with pytest.raises(MapError, match=rf"{root / where}/\S+\.json is there: move its folder's map files to "
                                           rf"{root / 'maps' / 'expansion'}"):
            _s18_dataset(env, root)
    root = env.shadow_world()
    (root / "v1.0-trainval" / "sample_data.json").write_text("")
    with pytest.raises(DatasetError, match=r"sample_data\.json is empty \(0 bytes\): a download or extraction cut"):
        _s18_dataset(env, root)
    nested = env.tmp / "nested"
    (nested / "v1.0-trainval").mkdir(parents=True)
    (nested / "v1.0-trainval" / "v1.0-trainval").symlink_to(env.world / "v1.0-trainval")
    with pytest.raises(DatasetError, match=r"its tables are one folder too deep, in \S+nested/v1\.0-trainval/"
                                           r"v1\.0-trainval: move them up"):
        _s18_dataset(env, nested)
    archives = env.tmp / "archives"
    archives.mkdir()
    (archives / "v1.0-trainval_meta.tgz").write_bytes(b"")
    with pytest.raises(DatasetError, match=r"holds the archives v1\.0-trainval_meta\.tgz: extract them there"):
        _s18_dataset(env, archives)
    no_png = env.tmp / "no_png"
    no_png.mkdir()
    (no_png / "v1.0-trainval").symlink_to(env.world / "v1.0-trainval")
    with pytest.raises(DatasetError, match=r"the map mask \S+\.png does not exist: the basemap PNGs \(maps/\*\.png\) "
                                           r"come with the metadata archive"):
        _s18_dataset(env, no_png)


@row("S29", "AV2: a camera folder of <timestamp_ns>.JPG images was 'the folder holds no images; the log's camera and "
            "lidar timestamps do not match' (both wrong); it names the .JPG files and says to rename them. A log with "
            "no sensors/cameras at all (the real log of shared/av2_real) was told to choose cameras with "
            "data.av2_cameras; it says the log has no images and that export-gt needs none. A root one level up "
            "(ROOT/sensor/train, as s5cmd copies the bucket) names the subfolder, and a renamed log folder (every map "
            "file naming another log) is said to be one")
def row_av2_camera_images_upper_case_or_absent(env):
    root, log = _av2_copy(env)
    for image in (log / "sensors" / "cameras" / "ring_side_left").iterdir():
        image.rename(image.with_suffix(".JPG"))
    up = env.tmp / "up"
    up.mkdir()
    (up / "sensor").symlink_to(root)  # s5cmd's copy of the bucket's av2/sensor/ folder
    _av2_error(env, up, r"its folders: sensor .*; its subfolder \S+up/sensor holds the split folder 'train': "
                        r"data\.dataroot=\S+up/sensor")
    line = _av2_error(env, root, r"ring_side_left: the folder holds no \.jpg images .*\.JPG files: rename them")
    assert "timestamps do not match" not in line
    cameras = log / "sensors" / "cameras"
    shutil.rmtree(cameras)
    cameras.symlink_to(env.tmp / "unmounted")
    _av2_error(env, root, r"sensors/cameras is a symbolic link to \S+unmounted, which does not exist")
    cameras.unlink()
    for other in sorted((root / "train").iterdir()):
        shutil.rmtree(other / "sensors" / "cameras", ignore_errors=True)
    _av2_error(env, root, r"sensors/cameras does not exist: the log has no camera images at all .*export-gt does not")
    rc, out, err = env.cli("export-gt", env.yaml, "data.dataset=av2", "data.splits_file=null", f"data.dataroot={root}",
                           "--split", "train", "--out", env.tmp / "gt.json")
    assert rc == 0, err[-2000:]
    log.rename(log.with_name("0" * 8 + log.name[8:]))  # a log folder renamed: its map files name the old id
    _av2_error(env, root, r"is the map file of another log .*or the log folder was renamed: all its map files name "
                          r"log ")


@row("S29", "a map expansion of an earlier version (1.2) was the devkit's 'outdated map version (%s)!' (its format "
            "string unfilled); it names the file's version and the 1.3 the devkit reads. export-gt with "
            "data.on_bad_sample=skip where every sample's map fails wrote an empty GT file with exit 0; it is refused, "
            "and a partial one notes how many samples were left out")
def row_map_expansion_of_an_earlier_version(env):
    root = env.tmp / "old_maps"
    (root / "maps" / "expansion").mkdir(parents=True)
    for name in ("samples", "v1.0-trainval"):
        (root / name).symlink_to(env.world / name)
    for png in (env.world / "maps").glob("*.png"):
        (root / "maps" / png.name).symlink_to(png)
    for path in (env.world / "maps" / "expansion").glob("*.json"):
        (root / "maps" / "expansion" / path.name).write_text(json.dumps({**json.loads(path.read_text()),
                                                                         "version": "1.2"}))
    out = env.tmp / "gt.json"
    env.error(r"expansion/\S+\.json: its version is 1\.2, an earlier map expansion; the devkit reads version 1\.3",
              "export-gt", env.yaml, f"data.dataroot={root}", "--out", out)
    with pytest.warns(UserWarning, match="export-gt: skipping sample"):  # (its progress bar on stderr too)
        rc, _, err = env.cli("export-gt", env.yaml, f"data.dataroot={root}", "data.on_bad_sample=skip", "--out", out)
    assert rc == 2 and "Traceback" not in err, err[-2000:]
    assert re.search(r"error: every sample of split 'val' in \S+old_maps is bad \(data\.on_bad_sample=skip\), the "
                     r"first: .*version is 1\.2", err), err[-2000:]
    assert not out.exists()


# --- the twenty-eighth sweep ---------------------------------------------------------------------------


def _strict_json(text: str):
    """``text`` read as standard JSON: ``NaN`` / ``Infinity`` (Python's extension) refused, as jq, JavaScript and Go
    refuse them."""
    def refuse(constant):
        raise AssertionError(f"{constant} is not JSON")

    return json.loads(text, parse_constant=refuse)


@row("S28", "metrics.json (evaluate, evaluate-json) and log.jsonl held NaN (a flicker rate with no pairs, the "
            "raster AP of a class with no GT): not JSON, jq and JavaScript refuse the file; now null. A NaN score "
            "given to write_submission is refused (null would read back as the default confidence 1.0)")
def row_json_outputs_hold_no_nan(env):
    from instagram_hdmap.evaluation.io import write_submission

    run = env.tmp / "run"
    rc, _, err = env.cli("train", env.yaml, f"train.out_dir={run}", "train.epochs=1", "train.checkpoint_every=0")
    assert rc == 0, err[-2000:]
    lines = (run / "log.jsonl").read_text().splitlines()
    assert lines and all(isinstance(_strict_json(ln), dict) for ln in lines)
    assert _strict_json(lines[-1])["val"]["consistency"]["flicker_detected_mean"] is None  # a random model: no pairs
    rc, _, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "eval")
    assert rc == 0, err[-2000:]
    _strict_json((env.tmp / "eval" / "submission.json").read_text())
    metrics = _strict_json((env.tmp / "eval" / "metrics.json").read_text())
    assert metrics["consistency"]["flicker_detected_mean"] is None
    line = {"pts": [[0.0, 1.0], [5.0, 1.0]], "label": 0, "score": 0.5}
    write_submission(env.tmp / "gt.json", {"a": [{"pts": line["pts"], "label": 0}]}, {"ground_truth": True})
    write_submission(env.tmp / "pred.json", {"a": [line]})
    rc, out, err = env.cli("evaluate-json", "--pred", env.tmp / "pred.json", "--gt", env.tmp / "gt.json", "--protocol",
                           "raster", "--out", env.tmp / "m.json")
    assert rc == 0 and "nan" in out, err[-2000:]  # printed as nan on the terminal
    metrics = _strict_json((env.tmp / "m.json").read_text())
    assert metrics["AP_class"]["divider"] == 1.0 and metrics["AP_class"]["boundary"] is None and metrics["mAP"] is None
    with pytest.raises(ValueError, match=r"sample 'a': a polyline's score is nan .*scores must be finite"):
        write_submission(env.tmp / "nan.json", {"a": [{**line, "score": float("nan")}]})
    assert not (env.tmp / "nan.json").exists()


@row("S28", "the reader of the output went away (`evaluate-json ... --out m.json | head -1`, `train ... 2>&1 | head`, "
            "with PYTHONUNBUFFERED=1 as in many containers): the first message after it stopped the job, exit 141 "
            "with m.json never written, a training stopped before its first step; now the job goes on, writes its "
            "files and exits 141")
def row_output_reader_gone_job_goes_on(env):
    env_vars = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path), "PYTHONUNBUFFERED": "1"}
    gt, pred = env.tmp / "gt.json", env.tmp / "pred.json"
    line = [[0.0, 1.0], [5.0, 1.0]]
    gt.write_text(json.dumps({"meta": {"ground_truth": True}, "results": {"a": [{"pts": line, "type": 0}]}}))
    pred.write_text(json.dumps({"results": {"a": [{"pts": line, "type": 0, "confidence_level": 0.5}]}}))
    jobs = [(["evaluate-json", "--pred", pred, "--gt", gt, "--out", env.tmp / "m.json"], subprocess.PIPE),
            (["train", env.yaml, f"train.out_dir={env.tmp / 'run'}", "train.epochs=1", "train.checkpoint_every=0"],
             subprocess.STDOUT)]  # 2>&1: the progress bar's stream has no reader either
    for argv, stderr in jobs:
        p = subprocess.Popen([sys.executable, "-m", "instagram_hdmap.cli", *map(str, argv)], stdout=subprocess.PIPE,
                             stderr=stderr, env=env_vars)
        p.stdout.close()  # the reader is gone before the first line (`| head -0`)
        err = p.stderr.read().decode() if p.stderr else ""
        assert p.wait(timeout=300) == 141, err[-2000:]
        assert "Traceback" not in err, err[-2000:]
    assert json.loads((env.tmp / "m.json").read_text())["mAP"] == pytest.approx(1 / 3)  # divider 1, the others 0
    assert (env.tmp / "run" / "last.pt").is_file() and (env.tmp / "run" / "log.jsonl").read_text().count("\n") == 1


@row("S28", "stderr closed at the start (`2>&-`, a launcher that closes it): the first progress bar wrote to None, a "
            "raw AttributeError nobody could see, exit 1, nothing written (export-gt, evaluate, train, synth); now "
            "the messages are dropped and the job runs")
def row_standard_error_closed(env):
    env_vars = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    argv = ["export-gt", str(env.yaml), "--out", str(env.tmp / "gt.json")]
    p = subprocess.run([sys.executable, "-m", "instagram_hdmap.cli", *argv], stdout=subprocess.PIPE, env=env_vars,
                       preexec_fn=lambda: os.close(2), timeout=300)
    assert p.returncode == 0 and b"wrote" in p.stdout, p.stdout[-2000:]
    assert json.loads((env.tmp / "gt.json").read_text())["results"]


@row("S28", "train / evaluate with stderr in a file (`2> log`, nohup, not a terminal): the progress bar was drawn "
            "twice a step, each drawing a carriage-return line of ~200 bytes: megabytes a day, one `tail` line per "
            "epoch; now drawn at most once a minute off a terminal")
def row_progress_bar_in_a_log_file(env):
    rc, _, err = env.cli("train", env.yaml, f"train.out_dir={env.tmp / 'run'}", "train.epochs=1",
                         "train.checkpoint_every=0", "train.log_every=1")
    assert rc == 0, err[-2000:]
    assert err.count("epoch 0:") <= 2, err  # the bar's start and (a run longer than a minute) its refreshes


@row("S28", "evaluate-json of predictions whose scores are all equal (one confidence_level written for every "
            "vector): the AP followed the order of the vectors in the file (the same file reversed scored another "
            "AP), no word; now a note says so")
def row_predictions_with_one_score(env):
    gt = {"a": [{"pts": [[0.0, 1.0], [5.0, 1.0]], "type": 0}, {"pts": [[0.0, -1.0], [5.0, -1.0]], "type": 0}]}
    pred = {"a": [{"pts": [[0.0, 1.0], [5.0, 1.0]], "type": 0, "confidence_level": 0.5},
                  {"pts": [[0.0, 8.0], [5.0, 8.0]], "type": 0, "confidence_level": 0.5},
                  {"pts": [[0.0, -9.0], [5.0, -9.0]], "type": 2, "confidence_level": 0.5},
                  {"pts": [[0.0, -1.0], [5.0, -1.0]], "type": 2, "confidence_level": 0.9}]}
    (env.tmp / "gt.json").write_text(json.dumps({"meta": {"ground_truth": True}, "results": gt}))
    aps = []
    for name, vectors in (("pred.json", pred["a"]), ("reversed.json", pred["a"][::-1])):
        (env.tmp / name).write_text(json.dumps({"results": {"a": vectors}}))
        rc, out, err = env.cli("evaluate-json", "--pred", env.tmp / name, "--gt", env.tmp / "gt.json")
        assert rc == 0, err[-2000:]
        assert re.search(rf"note: .*{name}: all 2 predictions of divider have the same confidence_level 0\.5: their "
                         r"ranking, and so the AP, follows their order in the file", out), out
        assert "predictions of boundary" not in out  # two scores
        aps.append(re.search(r"^divider .* ([0-9.]+)$", out, re.M).group(1))
    assert aps[0] != aps[1], aps  # why the note: the order decides


@row("S28", "a non-ASCII path on a terminal that is not UTF-8 (PYTHONIOENCODING=ascii, a Windows console): export-gt "
            "wrote the file, then its 'wrote ...' line crashed (UnicodeEncodeError traceback, exit 1); now the "
            "letter is escaped and the exit status is 0")
def row_non_ascii_path_on_an_ascii_terminal(env):
    env_vars = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path), "PYTHONIOENCODING": "ascii"}
    out = env.tmp / "gt \u00e4.json"
    p = subprocess.run([sys.executable, "-m", "instagram_hdmap.cli", "export-gt", str(env.yaml), "--out", str(out)],
                       capture_output=True, env=env_vars, timeout=300)
    assert p.returncode == 0 and b"Traceback" not in p.stderr, p.stderr[-2000:]
    assert b"gt \\xe4.json" in p.stdout and out.is_file(), p.stdout


@row("S28", "export-onnx under PYTHONWARNINGS=error (-W error, as CI runs): torch's FutureWarning about its own "
            "internals ('isinstance(treespec, LeafSpec) is deprecated') stopped the export with torch's traceback, "
            "exit 1, nothing a user could change; now those notices of torch are ignored during the export")
def row_export_onnx_under_warnings_as_errors(env):
    import warnings

    pytest.importorskip("onnx")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rc, out, err = env.cli("export-onnx", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "m.onnx")
    assert rc == 0 and (env.tmp / "m.onnx").is_file(), err[-2000:]


@row("S28", "benchmarks/temporal_speed.py with model.temporal.max_jump_m=1 (the benchmark's previous frame is 1.5 m "
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


@row("S28", "evaluate with data.on_bad_sample=skip under PYTHONWARNINGS=ignore (-W ignore): the samples left out "
            "were named only by Python warnings, which vanished ('1 bad sample(s) left out; the warnings name them'); "
            "now the note names their tokens (printed and in metrics.json)")
def row_skipped_samples_named_without_warnings(env):
    import warnings

    root = env.shadow_world(copy_samples=True)
    _break_image(root, root, 0, "CAM_FRONT", "missing")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rc, out, err = env.cli("evaluate", env.yaml, f"data.dataroot={root}", "data.on_bad_sample=skip",
                               "--checkpoint", env.ckpt, "--out", env.tmp / "eval")
    assert rc == 0, err[-3000:]
    submission = json.loads((env.tmp / "eval" / "submission.json").read_text())
    tables = json.loads((root / "v1.0-trainval" / "sample.json").read_text())
    left = sorted({t["token"] for t in tables} - set(submission["results"]) - _train_tokens(root))
    assert len(left) == 1, left
    assert re.search(rf"note: 1 bad sample\(s\) of \d+ left out .*: {left[0]}$", out, re.M), out
    notes = json.loads((env.tmp / "eval" / "metrics.json").read_text())["meta"]["config_notes"]
    assert any(left[0] in n for n in notes), notes


def _train_tokens(root: Path) -> set[str]:
    tables = {n: json.loads((root / "v1.0-trainval" / f"{n}.json").read_text()) for n in ("sample", "scene")}
    train = set(json.loads((root / "splits.json").read_text())["train"])
    scenes = {s["token"] for s in tables["scene"] if s["name"] in train}
    return {t["token"] for t in tables["sample"] if t["scene_token"] in scenes}


@row("S28", "export-gt with data.on_bad_sample=skip and unreadable map files: a GT file of 0 samples, 'wrote ...: 0 "
            "samples', exit 0; samples left out were named only by Python warnings (-W ignore hides them); now every "
            "sample bad is one error, and a note names the samples left out")
def row_export_gt_samples_left_out(env):
    import warnings

    root = env.shadow_world()
    (root / "maps").unlink()
    shutil.copytree(env.world / "maps", root / "maps")
    tables = {n: json.loads((root / "v1.0-trainval" / f"{n}.json").read_text()) for n in ("scene", "log")}
    location = {t["token"]: t["location"] for t in tables["log"]}
    train = json.loads((root / "splits.json").read_text())["train"]
    places = [location[s["log_token"]] for s in tables["scene"] if s["name"] in train]
    argv = ["export-gt", env.yaml, f"data.dataroot={root}", "data.on_bad_sample=skip", "--split", "train"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        (root / "maps" / "expansion" / f"{places[0]}.json").write_text("{")  # one location's map unreadable
        rc, out, err = env.cli(*argv, "--out", env.tmp / "gt.json")
        assert rc == 0, err[-2000:]
        kept = json.loads((env.tmp / "gt.json").read_text())["results"]
        note = re.search(r"note: (\d+) bad sample\(s\) of (\d+) left out .*: (\w+)", out)
        assert note and int(note[1]) + len(kept) == int(note[2]) and note[3] not in kept, out
        for place in set(places):
            (root / "maps" / "expansion" / f"{place}.json").write_text("{")
        env.error(r"every sample of split 'train' in .* is bad \(data\.on_bad_sample=skip\), the first: sample \w+: "
                  r"cannot read map expansion file", *argv, "--out", env.tmp / "gt2.json")
    assert not (env.tmp / "gt2.json").exists()


@row("S28", "train with stderr on a full disk (`2> log`, the log's disk full): the progress bar's next write stopped "
            "the training, exit 1, no checkpoint and no word anywhere; now stderr's messages are dropped, the "
            "training ends and a note on stdout says the messages were lost")
def row_standard_error_on_a_full_disk(env):
    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full")
    env_vars = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    argv = ["train", str(env.yaml), f"train.out_dir={env.tmp / 'run'}", "train.epochs=1", "train.checkpoint_every=0"]
    with open("/dev/full", "w") as full:
        p = subprocess.run([sys.executable, "-m", "instagram_hdmap.cli", *argv], stdout=subprocess.PIPE, stderr=full,
                           text=True, env=env_vars, timeout=300)
    assert p.returncode == 0 and (env.tmp / "run" / "last.pt").is_file(), (p.returncode, p.stdout[-2000:])
    assert "note: the standard error could not be written from some point on (No space left on device)" in p.stdout


@row("S28", "benchmarks/temporal.py reads back a finished run's result file (a rerun of the same --out): written "
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


@row("S28", "export-gt / evaluate-json --out /dev/stdout (what the refusal of --out - advises, for `| jq`): refused "
            "('cannot write /proc/PID/fd/pipe:[N]', on a terminal 'cannot write /dev/pts/0'); --out /dev/null or "
            "another device run as root: the device node was replaced by a regular file (a temporary renamed over "
            "it); now a terminal, pipe or device is written directly, the report goes to stderr")
def row_output_to_a_pipe_or_device(env):
    env_vars = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    cli = [sys.executable, "-m", "instagram_hdmap.cli"]
    p = subprocess.run([*cli, "export-gt", str(env.yaml), "--out", "/dev/stdout"], capture_output=True, text=True,
                       env=env_vars, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    gt = json.loads(p.stdout)  # the JSON alone: "wrote ..." went to stderr
    assert gt["meta"]["ground_truth"] and gt["results"] and "wrote /dev/stdout" in p.stderr
    (env.tmp / "gt.json").write_text(p.stdout)
    p = subprocess.run([*cli, "evaluate-json", "--pred", str(env.tmp / "gt.json"), "--gt", str(env.tmp / "gt.json"),
                        "--out", "/dev/stdout"], capture_output=True, text=True, env=env_vars, timeout=300)
    assert p.returncode == 0 and "mAP" in p.stderr, p.stderr[-2000:]
    assert json.loads(p.stdout)["AP_class"]["divider"] == 1.0
    if os.geteuid() == 0:  # a device node of its own (as /dev/null is): it stays one
        import importlib.util
        import stat

        device = env.tmp / "null"
        os.mknod(device, 0o666 | stat.S_IFCHR, os.makedev(1, 3))
        rc, out, err = env.cli("export-gt", env.yaml, "--out", device)
        assert rc == 0 and stat.S_ISCHR(device.stat().st_mode), (err[-2000:], device.stat())
        if importlib.util.find_spec("onnx") is not None:  # it reads its file back: a device is refused first
            env.error(r"--out .*null: a terminal, pipe or device; export-onnx reads the file back", "export-onnx",
                      env.yaml, "--checkpoint", env.ckpt, "--out", device)
            assert stat.S_ISCHR(device.stat().st_mode)


@row("S28", "evaluate-json --pred /dev/stdin (`zcat pred.json.gz | evaluate-json --pred /dev/stdin`) or a process "
            "substitution `<(...)`: refused as 'not valid JSON' (the pipe was opened twice: a look at its first "
            "bytes, then the read, which found them gone); now it is read once")
def row_submission_read_from_a_pipe(env):
    gt = {"meta": {"ground_truth": True}, "results": {"a": [{"pts": [[0.0, 1.0], [5.0, 1.0]], "type": 0}]}}
    pred = {"results": {"a": [{"pts": [[0.0, 1.0], [5.0, 1.0]], "type": 0, "confidence_level": 0.5}]}}
    (env.tmp / "gt.json").write_text(json.dumps(gt))
    (env.tmp / "pred.json").write_text(json.dumps(pred))
    env_vars = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    p = subprocess.run([sys.executable, "-m", "instagram_hdmap.cli", "evaluate-json", "--pred", "/dev/stdin", "--gt",
                        str(env.tmp / "gt.json"), "--out", str(env.tmp / "m.json")],
                       input=(env.tmp / "pred.json").read_bytes(), capture_output=True, env=env_vars, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    assert json.loads((env.tmp / "m.json").read_text())["AP_class"]["divider"] == 1.0


@row("S28", "a config given as a pipe (`train <(envsubst < in.yaml)`, `... | model-summary /dev/stdin`): 'config "
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
    rig, images = _rig_files(env)  # an image as a pipe: read by checks, then decoded (a named pipe hung)
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


@row("S30", "an option copied from a formatted page with a typographic dash (`\u2014force`, `\u2013-checkpoint R`): "
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


@row("S30", "evaluate-json --pred gt.json --gt gt.json (export-gt's file, flagged meta.ground_truth, given as the "
            "predictions): a perfect mAP, exit 0, the only note 'predictions without confidence_level scored 1.0'; "
            "still scored (a sanity check), with a note that it scores the GT, not a model")
def row_ground_truth_file_given_as_predictions(env):
    gt, doc, pred = _gt_and_pred(env)
    rc, out, err = env.cli("evaluate-json", "--pred", gt, "--gt", gt)
    assert rc == 0 and re.search(r"gt\.json is a ground-truth file .*the --gt file itself.*not a model", out + err), \
        out + err
    rc, out, err = env.cli("evaluate-json", "--pred", pred, "--gt", gt)
    assert rc == 0 and "ground-truth file" not in out + err, out + err


@row("S30", "a checkpoint that is a plain pickle (not torch's zip) of protocol 4 with an object that runs code: the "
            "one-line refusal came under torch's 'Detected pickle protocol 4' UserWarning and its source line")
def row_plain_pickle_checkpoint_one_line(env):
    import pickle

    class Evil:
        def __reduce__(self):
            return (os.system, ("true",))

    bad = env.tmp / "evil.pt"
    bad.write_bytes(pickle.dumps({"model": Evil()}, protocol=4))
    env_vars = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}  # a process of its own: pytest catches warnings
    p = subprocess.run([sys.executable, "-m", "instagram_hdmap.cli", "evaluate", str(env.yaml), "--checkpoint",
                        str(bad), "--out", str(env.tmp / "eval")], capture_output=True, text=True, env=env_vars,
                       timeout=300)
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert p.returncode == 2 and len(lines) == 1 and "evil.pt was refused by the safe loader" in lines[0], p.stderr


# --- the test: every row of the table ---------------------------------------------------------------


@pytest.mark.parametrize("row", ROWS, ids=[f"{r.case}-{r.id}" for r in ROWS])
def test_bad_input(row: Row, shared, tmp_path, capsys, monkeypatch, request):
    world, yaml, ckpt = shared
    monkeypatch.chdir(tmp_path)
    row.run(Env(world, yaml, ckpt, tmp_path, capsys, monkeypatch, request))


def test_faults_page_cites_every_row_and_only_rows():
    """docs/faults.md promises, each backed by a row: every id it cites names a row (or, as `4-*`, some rows) of this
    table, and every row is cited, so neither a promise without a test nor a test without its promise is left."""
    doc = (Path(__file__).resolve().parents[1] / "docs" / "faults.md").read_text(encoding="utf-8")
    ids = {f"{r.case}-{r.id}" for r in ROWS}
    cited = set(re.findall(r"`((?:\d+|S\d*)-[A-Za-z0-9_*-]+)`", doc))
    assert len(cited) > 100, "the citation pattern found almost nothing: has the page's format changed?"
    unknown = sorted(c for c in cited if not fnmatch.filter(ids, c))
    assert not unknown, f"docs/faults.md cites ids that are not rows: {unknown}"
    uncited = sorted(i for i in ids if not any(fnmatch.fnmatchcase(i, c) for c in cited))
    assert not uncited, f"rows that docs/faults.md does not cite: {uncited}"
