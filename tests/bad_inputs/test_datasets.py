"""Datasets as they are on disk: nuScenes tables, sample chains, map expansions and downloads in parts; Argoverse 2
logs; splits files; the synthetic worlds and the demo's cache; a bad sample under ``data.on_bad_sample``. A damaged
record is named with its file and token, never a raw crash, a hang or a silently dropped scene.

Each row runs on the tiny synthetic world of tests/conftest.py and a random tiny model (bad_inputs/conftest.py).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch

from bad_inputs.support import (
    add,
    av2_copy,
    av2_dataset,
    av2_error,
    break_image,
    camera_record,
    first,
    row,
    table,
    temporal_checkpoint,
    val_dataset,
    val_scene,
)
from instagram_hdmap.checkpoint import save_checkpoint
from instagram_hdmap.config import UserError, config_to_dict


@row("data.on_bad_sample=skip with eval batch > 1: each good sample scored once, exit 0")
def row_skip_mode_batch(env):
    root = env.shadow_world(copy_samples=True)
    break_image(root, root, 0, "CAM_FRONT", "missing")
    rc, out, err = env.cli("evaluate", env.yaml, f"data.dataroot={root}", "data.on_bad_sample=skip",
                           "eval.batch_size=3", "--checkpoint", env.ckpt, "--out", env.tmp / "eval")
    assert rc == 0, err[-3000:]
    metrics = json.loads((env.tmp / "eval" / "metrics.json").read_text())
    assert metrics["counters"]["samples"] == 2  # the bad one is left out, its replacement not scored twice
    assert "2 samples evaluated" in out and re.search(r"1 bad sample", out)
    submission = json.loads((env.tmp / "eval" / "submission.json").read_text())
    assert len(submission["results"]) == 2


@row("a temporal model with data.on_bad_sample=skip and a bad frame: the frame counts as a missing one (was: "
          "its stand-in came twice and the stream stopped with a frame-order error, exit 2)")
def row_skip_mode_temporal(env):
    from instagram_hdmap.models import build_model

    root = env.shadow_world(copy_samples=True)
    break_image(root, root, 0, "CAM_FRONT", "missing")  # the first frame of the validation scene
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


@row("a sample_data record without 'filename' is named")
def row_sample_data_without_filename(env):
    def damage(tables):
        sd, _ = camera_record(tables, "CAM_BACK")
        del sd["filename"]

    root = env.shadow_world(damage)
    env.error(r"sample_data.*'filename'", "evaluate", env.yaml, f"data.dataroot={root}", "--checkpoint", env.ckpt,
              "--out", env.tmp / "e")


@row("synth --seed -1")
def row_synth_negative_seed(env):
    env.error(r"--seed -1", "synth", "--out", env.tmp / "w", "--seed", "-1", "--scenes-train", "1",
              "--scenes-val", "0", "--samples-per-scene", "1", "--image-size", "160x90")
    assert not (env.tmp / "w").exists()


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
    add(_name, f"nuScenes tables: {_name}", _table_row(_edit, _pattern))


@row("synth-preview of an AV2-layout world is named (was a KeyError)")
def row_synth_preview_av2_world(env):
    world = env.request.getfixturevalue("av2_world")
    env.error(r"Argoverse 2 layout.*show-gt", "synth-preview", world, "--out", env.tmp / "p.png")
    assert not (env.tmp / "p.png").exists()


@row("a sample_data record whose width is a string or 0 is named (was a TypeError / ZeroDivisionError)")
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


@row("numbers written as strings in the tables (an ego pose, intrinsics) are named (numpy read them as numbers, "
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


@row("data.splits_file with data.dataset=av2 is refused (it was ignored: every log of the split folder ran)")
def row_av2_splits_file_ignored(env):
    env.error(r"'data\.splits_file' .* an AV2 split is a folder of logs .*data\.splits_file=null", "show-gt", env.yaml,
              "data.dataset=av2", "--out", env.tmp / "show")


@row("data.split_scheme=geo with a data.splits_file too is refused: both choose the scenes")
def row_geo_split_with_a_splits_file(env):
    env.error(r"'data\.split_scheme' \(geo\) and 'data\.splits_file' .* both choose the scenes", "show-gt", env.yaml,
              "data.split_scheme=geo", "--out", env.tmp / "show")


@row("data.split_scheme=geo with other split names, or on a world of three road networks, is one line")
def row_geo_split_names_and_small_world(env):
    env.error(r"'data\.split_scheme' is geo, whose splits are 'train' and 'val'.*mini_train", "show-gt", env.yaml,
              "data.split_scheme=geo", "data.splits_file=null", "data.train_split=mini_train", "--out",
              env.tmp / "show")
    # the tiny world's three scenes drive three of the four networks: none is left to validate on
    env.error(r"geo split of the synthetic world .*singapore-queenstown.* at least 4 scenes", "show-gt", env.yaml,
              "data.split_scheme=geo", "data.splits_file=null", "--out", env.tmp / "show")


@row("a splits file whose split lists a list (not scene names) is named (was a raw TypeError)")
def row_splits_file_nested_list(env):
    splits = env.tmp / "splits.json"
    names = json.loads((env.world / "splits.json").read_text())
    splits.write_text(json.dumps({**names, "val": [names["val"]]}))
    env.error(r"splits file .*splits\.json: split 'val' must list scene names \(strings\), got \[", "show-gt",
              env.yaml, f"data.splits_file={splits}", "--out", env.tmp / "show")


@row("nuScenes tables: a record that names a token its table does not hold (annotations of a removed sample) is "
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


@row("predict and predict --video of a temporal model with data.on_bad_sample=skip and a bad earlier frame: the "
          "frame is a missing one, as in evaluate (was the bad frame's error, exit 2)")
def row_temporal_predict_skip_mode(env):
    root = env.shadow_world(copy_samples=True)
    break_image(root, root, 0, "CAM_FRONT", "missing")  # the first frame of the validation scene
    ckpt = temporal_checkpoint(env)
    args = (env.yaml, f"data.dataroot={root}", "data.on_bad_sample=skip", "model.temporal.memory=bev",
            "model.gnn.sinkhorn_iters=3", "--checkpoint", ckpt)
    rc, out, err = env.cli("predict", *args, "--index", "1", "--out", env.tmp / "p")
    assert rc == 0 and "no memory, as the frame before it in scene" in out + err, (out + err)[-2000:]
    rc, out, err = env.cli("predict", *args, "--scene", val_scene(env), "--video", env.tmp / "v.mp4")
    assert rc == 0 and "1 bad frame(s) of scene" in out + err and (env.tmp / "v.mp4").is_file(), (out + err)[-2000:]


@row("AV2: a pose table re-saved with timestamp_ns as float64 (pandas makes an int64 column float where a "
            "merge leaves a NaN) was refused as 'has no ego pose at lidar sweep' with no hint that the column was "
            "rounded; a camera folder of PNG images, as 'the folder holds no images'")
def row_av2_rounded_timestamps_and_png_images(env):
    import pyarrow as pa
    from pyarrow import feather

    root, log = av2_copy(env)
    table = feather.read_table(str(log / "city_SE3_egovehicle.feather"))
    rounded = pa.array(table.column("timestamp_ns").to_numpy().astype(np.float64))
    table = table.set_column(table.column_names.index("timestamp_ns"), "timestamp_ns", rounded)
    feather.write_feather(table, str(log / "city_SE3_egovehicle.feather"))
    av2_error(env, root, r"has no ego pose at lidar sweep \d+ .*ns away: its timestamp_ns column was rounded .*"
                          r"write it as int64")
    shutil.rmtree(root)
    root, log = av2_copy(env)
    for image in (log / "sensors" / "cameras" / "ring_side_left").iterdir():
        image.rename(image.with_suffix(".png"))
    av2_error(env, root, r"ring_side_left: the folder holds no \.jpg images .*\.png files: convert them to JPEG")


@row("AV2: a hidden folder in a split folder (Jupyter's .ipynb_checkpoints, a .Trash-1000) made a valid "
            "dataset refused as 'not an AV2 split folder'; it is not a log and is skipped")
def row_av2_hidden_folder_in_the_split(env):
    root, log = av2_copy(env)
    (root / "train" / ".ipynb_checkpoints").mkdir()
    (root / "train" / ".DS_Store").write_text("")
    assert len(av2_dataset(env, "train", root)) == len(av2_dataset(env, "train"))


@row("a nuScenes table saved with a UTF-8 byte-order mark (or not valid JSON): the one line named only the "
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


@row("an Argoverse 2 root read with data.dataset left at nuscenes said 'versions in ROOT: none (set "
            "data.version)'; it says the root is an AV2 one: set data.dataset=av2")
def row_nuscenes_dataset_on_an_av2_root(env):
    av2 = env.request.getfixturevalue("av2_world")
    env.error(r"it is an Argoverse 2 sensor-dataset root: set data\.dataset=av2", "export-gt", env.yaml,
              f"data.dataroot={av2}", "--out", env.tmp / "gt.json")


@row("export-gt / show-gt without --split read the split named 'val' whatever data.val_split said (export-gt "
            "CONFIG data.val_split=train wrote the val GT, exit 0: evaluate scores data.val_split); they take the "
            "config's split now (--split still chooses)")
def row_export_gt_follows_data_val_split(env):
    rc, out, err = env.cli("export-gt", env.yaml, "data.val_split=train", "--out", env.tmp / "gt.json")
    assert rc == 0, err
    gt = json.loads((env.tmp / "gt.json").read_text())
    assert gt["meta"]["split"] == "train" and len(gt["results"]) == len(val_dataset(env.cfg("data.val_split=train")))
    rc, out, err = env.cli("export-gt", env.yaml, "data.val_split=train", "--split", "val", "--out", env.tmp / "v.json")
    assert rc == 0 and json.loads((env.tmp / "v.json").read_text())["meta"]["split"] == "val"


@row("two synth runs of one --out started together (no --force): each found the folder absent at its start, "
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


@row("synth --out WORLD --force where WORLD also holds a training run or an evaluation (train.out_dir or "
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


@row("a config's relative data.dataroot / data.splits_file, the run started from another folder than the "
            "config's: 'dataroot not found: world', which reads as if the world were gone; it says that a relative "
            "path is read from the current folder and names it")
def row_relative_dataroot_from_another_folder(env):
    env.error(r"dataroot not found: world .*a relative path is read from the current folder, .+", "export-gt",
              env.yaml, "data.dataroot=world", "--out", env.tmp / "gt.json")
    env.error(r"splits file not found: nowhere/splits\.json .*a relative path is read from the current folder",
              "export-gt", env.yaml, "data.splits_file=nowhere/splits.json", "--out", env.tmp / "gt.json")


@row("synth --out W --force over an existing world, Ctrl-C (or a kill) while the old world was being removed "
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


def _s18_dataset(env, root: Path, split: str = "train"):
    from instagram_hdmap.data import build_dataset

    return build_dataset(env.cfg(f"data.dataroot={root}"), split, augment=False)


@row("nuScenes tables: a duplicate token (two sample records of one token, the second with its chain cut) "
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


@row("nuScenes sample chains: a 'next' cut short dropped the scene's later samples with no word; a chain "
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


@row("nuScenes map expansion: a node with NaN coordinates or a polygon naming a node the file lacks was a raw "
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


@row("AV2 log files: a NaN drivable-area point was a raw GEOSException and a NaN lane marking silently dropped; "
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
        return av2_copy(env)

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
        av2_dataset(env, "train", root).gt_polylines(0)

    def nan_marking(m):
        for ls in m["lane_segments"].values():
            ls["left_lane_boundary"][0]["y"] = float("nan")

    root, log = copy()
    edit_map(log, nan_marking)
    with pytest.raises(MapError, match=r"lane segment \w+ has NaN or infinite coordinates"):
        av2_dataset(env, "train", root).gt_polylines(0)

    def short_edge(m):
        for crossing in m["pedestrian_crossings"].values():
            crossing["edge1"] = crossing["edge1"][:1]

    root, log = copy()
    edit_map(log, short_edge)
    if json.loads(next((log / "map").glob("log_map_archive_*.json")).read_text())["pedestrian_crossings"]:
        with pytest.warns(UserWarning, match=r"crossing\(s\) with an edge of fewer than 2 points"):
            ds = av2_dataset(env, "train", root)
            for i in range(len(ds)):
                ds.gt_polylines(i)

    root, log = copy()
    poses = pd.read_feather(log / "city_SE3_egovehicle.feather")
    ts = int(sorted(p.stem for p in (log / "sensors" / "lidar").glob("*.feather"))[0])
    extra = poses[poses.timestamp_ns == ts].copy()
    extra["tx_m"] += 100.0
    pd.concat([poses, extra]).reset_index(drop=True).to_feather(log / "city_SE3_egovehicle.feather")
    with pytest.raises(DatasetError, match=rf"holds 2 rows of other ego poses for timestamp_ns {ts}"):
        av2_dataset(env, "train", root).ego_pose(0)

    root, log = copy()
    calib = pd.read_feather(log / "calibration" / "egovehicle_SE3_sensor.feather")
    extra = calib[calib.sensor_name == calib.sensor_name.iloc[0]].copy()
    extra["tx_m"] += 5.0
    pd.concat([calib, extra]).reset_index(drop=True).to_feather(log / "calibration" / "egovehicle_SE3_sensor.feather")
    with pytest.raises(DatasetError, match=r"holds 2 rows of other calibrations for sensor_name \w+"):
        av2_dataset(env, "train", root)[0]

    root, log = copy()
    sim2 = next((log / "map").glob("*___img_Sim2_city.json"))
    sim2.write_text(json.dumps({**json.loads(sim2.read_text()), "s": 0}))
    with pytest.raises(MapError, match=r"cannot read the ground-height raster .*ZeroDivisionError"):
        av2_dataset(env, "train", root).ground_height(0)

    root, log = copy()
    (log / "sensors" / "lidar" / "notes.feather").write_bytes(b"")
    with pytest.raises(DatasetError, match=r"lidar/notes\.feather is not named <timestamp_ns>\.feather"):
        av2_dataset(env, "train", root)


@row("a self-intersecting road_segment / lane polygon of a map expansion was skipped (as the devkit does) with "
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


@row("AV2: a log whose map/ folder holds another log's map files (copied over from a neighbouring log) was "
            "read as that log's map: the GT drew the other place's roads (none here), exit 0. Every map file named "
            "after another log is named")
def row_av2_map_files_of_another_log(env):
    root, log = av2_copy(env)
    other = sorted((root / "train").iterdir())[1]
    shutil.rmtree(log / "map")
    shutil.copytree(other / "map", log / "map")
    av2_error(env, root, rf"log {log.name}: .*map.* is the map file of another log \({other.name}\)")


@row("AV2: data.dataroot given as one log's folder (or a split folder of logs, or a nuScenes root): 'not an AV2 "
            "sensor-dataset root ... its folders: calibration, map, sensors'; the line now names the root and split "
            "that hold it (or data.dataset=nuscenes)")
def row_av2_log_folder_as_the_root(env):
    root, log = av2_copy(env)
    for given, split in ((log, "train"), (log.parent, "train")):
        line = env.error(r"not an AV2 sensor-dataset root", "export-gt", env.yaml, "data.dataset=av2",
                         "data.splits_file=null", f"data.dataroot={given}", "--split", "val", "--out",
                         env.tmp / "gt.json")
        assert f"data.dataroot={root} with the split '{split}'" in line, line
    line = env.error(r"not an AV2 sensor-dataset root", "export-gt", env.yaml, "data.dataset=av2",
                     "data.splits_file=null", "--split", "val", "--out", env.tmp / "gt.json")  # the nuScenes world
    assert "is a nuScenes dataroot (versions v1.0-trainval): set data.dataset=nuscenes" in line, line


_CACHE_WORLD = {"scenes_train": 1, "scenes_val": 1, "samples_per_scene": 2, "seed": 0, "image_size": "160x90"}


@row("demo cache: two demos (or a demo and a training) that found no world both generated it, and the second "
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


@row("demo cache: a cached world damaged part-way (a camera image other than CAM_FRONT deleted, a table JSON "
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


@row("INSTAGRAM_HDMAP_CACHE='~/cache' (as a .env file or a Dockerfile's ENV sets it: no shell expands the ~) "
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


@row("demo cache on a read-only folder (a shared read-only cache, chattr +i): the one line said '--out "
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


@row("a splits file written by hand: a list of sample tokens (or scene tokens) in place of scene names said "
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


@row("a splits file saved by a Windows editor: with a UTF-8 byte-order mark it was refused ('Unexpected UTF-8 "
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


@row("data.dataroot one folder too deep (the version folder, .../v1.0-trainval) or one too high (the folder "
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


@row("a nuScenes table written on Windows (sample_data 'filename' as str() of a WindowsPath, "
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


@row("synth --force over a world that a training (or an evaluation, a prediction) in another process was "
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


@row("the official split names on a world of other scenes (data.splits_file=null, data.train_split=mini_train) "
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


@row("nuScenes as downloaded in parts: the metadata alone (no samples/ folder), some blob parts only, images "
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


@row("a nuScenes download unpacked one level off: the map expansion unpacked into the dataroot or into "
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


@row("a map expansion of an earlier version (1.2) was the devkit's 'outdated map version (%s)!' (its format "
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


@row("evaluate with data.on_bad_sample=skip under PYTHONWARNINGS=ignore (-W ignore): the samples left out "
            "were named only by Python warnings, which vanished ('1 bad sample(s) left out; the warnings name them'); "
            "now the note names their tokens (printed and in metrics.json)")
def row_skipped_samples_named_without_warnings(env):
    import warnings

    root = env.shadow_world(copy_samples=True)
    break_image(root, root, 0, "CAM_FRONT", "missing")
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


@row("export-gt with data.on_bad_sample=skip and unreadable map files: a GT file of 0 samples, 'wrote ...: 0 "
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


@pytest.mark.parametrize("case", table(__name__), ids=str)
def test_datasets(case, env):
    case.run(env)
