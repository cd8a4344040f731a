"""The Python API called as a notebook would: ``Mapper``, ``MapStream``, ``Evaluator``, the drive meters,
``MapElement``, persistence and the tracker, submission helpers, targets, ``BEVGrid`` and the model's forward, given
arguments of other types or shapes. A wrong one is a ``TypeError`` or ``ValueError`` naming the argument.

Each row runs on the tiny synthetic world of tests/conftest.py and a random tiny model (bad_inputs/conftest.py).
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from bad_inputs.support import (
    mapper_frame,
    row,
    table,
    val_dataset,
)
from instagram_hdmap.checkpoint import save_checkpoint
from instagram_hdmap.config import UserError, config_to_dict, load_config


@row("MapStream.step given a list of frames is a TypeError that says to step once per frame (was an "
          "AttributeError on 'ego_pose')")
def row_stream_step_list(env):
    from instagram_hdmap import Frame

    mapper, images, K, poses = mapper_frame(env)
    with pytest.raises(TypeError, match=r"MapStream\.step takes one Frame .* got list; call step\(\) once per frame"):
        mapper.stream().step([Frame(images=images, intrinsics=K, cam_to_ego=poses)])


@row("Mapper.from_checkpoint(overrides='key=value'), a string: one override (its characters were read as "
          "overrides: \"override 'm' must look like key.sub=value\")")
def row_mapper_overrides_string(env):
    from instagram_hdmap import Mapper

    assert Mapper.from_checkpoint(env.ckpt, device="cpu", overrides="model.gnn.num_vertices=32").config.model.gnn \
        .num_vertices == 32


def _memory_checkpoint(env, name: str, *overrides) -> Path:
    from instagram_hdmap.models import build_model

    cfg = env.cfg("model.gnn.sinkhorn_iters=3", *overrides)
    return save_checkpoint({"model": build_model(cfg).state_dict(), "config": config_to_dict(cfg)}, env.tmp / name)


@row("Mapper.forward with the memory of a temporal model of another grid (the same memory channels) is a "
          "ValueError naming both sizes (a raw RuntimeError of a reshape deep in the warp)")
def row_memory_of_a_model_of_another_grid(env):
    from instagram_hdmap import Mapper

    coarse = _memory_checkpoint(env, "coarse.pt", "model.temporal.memory=graph", "grid.resolution=0.5")
    fine = _memory_checkpoint(env, "fine.pt", "model.temporal.memory=graph")
    a, b = Mapper.from_checkpoint(coarse, device="cpu"), Mapper.from_checkpoint(fine, device="cpu")
    _, images, K, poses = mapper_frame(env)
    from instagram_hdmap import Frame

    frame = Frame(images=images, intrinsics=K, cam_to_ego=poses, ego_pose=np.eye(4))
    memory = a.forward(a.batch([frame]) | {"ego_pose": torch.eye(4)[None]})["memory"]
    with pytest.raises(ValueError, match=r"the memory map is 8 x 16 cells, this model's 16 x 32 \(another grid\)"):
        b.forward(b.batch([frame]) | {"ego_pose": torch.eye(4)[None], "frame_index": torch.tensor([2])}, memory)
    own = b.forward(b.batch([frame]) | {"ego_pose": torch.eye(4)[None]})["memory"]  # its own memory fuses
    out = b.forward(b.batch([frame]) | {"ego_pose": torch.eye(4)[None], "frame_index": torch.tensor([2])}, own)
    assert out["memory_status"].tolist() == [0]


@row("Evaluator.update: tokens given as a numpy array (a pandas column's values) crashed with numpy's raw "
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


@row("Mapper: a model moved to another precision in a notebook (mapper.model.half(), .double(), "
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


@row("a Mapper whose model was left in training mode (mapper.model.train() after fine-tuning in a notebook) "
            "computed batch-norm statistics of each call's batch and updated the running ones: every output changed, "
            "without a word; it now runs in eval mode and the model's mode is given back")
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


@row("Evaluator.merge of the state of an evaluator of other classes (two classes into three) crashed with "
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


@row("Evaluator.update: a label given as a 0-d tensor (a model's labels tensor iterated, as MapTR's "
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


@row("to_hdmapnet given mapper(frame)'s list as it is (or a list of frames' lists under one name) crashed "
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


@row("Evaluator(classes='divider') (one class given as a string) built an evaluator of the seven classes 'd', "
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


@row("Evaluator.update given a dict {token: polylines} (KeyError: 0), a generator or None (\"object of type "
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


@row("Evaluator.update given a model's outputs in a training loop (points and scores with requires_grad) "
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


@row("Evaluator.merge given the other Evaluator (not its state_dict()) or None, and format_table given an "
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


@row("read_submission with a role other than 'pred' / 'gt' ('prediction') read a submission as a GT, "
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


@row("Mapper.forward(frame) / decode(frame) (\"'Frame' object has no attribute 'items'\"), batch([]) "
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


@row("load_config given a dict of keys or an ExperimentConfig, and Evaluator.from_config given a YAML path, "
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


@row("MapElement compared (element in elements, a == b) raised numpy's 'truth value of an array ... is "
            "ambiguous' and could not be hashed (a set of elements); equal elements are equal and hash alike")
def row_map_element_equality_and_hash(env):
    from instagram_hdmap import MapElement

    pts = np.array([[0.0, 1.0], [2.0, 3.0], [4.0, 5.0]], np.float32)
    a, b = MapElement("divider", pts, False, 0.5, 0), MapElement("divider", pts.copy(), False, 0.5, 0)
    c = MapElement("divider", pts + 1, False, 0.5, 0)
    assert a == b and a != c and a in [c, b] and len({a, b, c}) == 2 and hash(a) == hash(b)


@row("a MapElement made with score None or points of another shape crashed later, in repr ('unsupported "
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


@row("FlickerMeter.update given a label beyond num_classes, a negative or a fractional one crashed later in "
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


@row("FlickerMeter.update given one [4, 4] pose for a batch (LinAlgError or a row taken for a pose), or a "
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


@row("FlickerMeter.update given Mapper's MapElement lists as predictions crashed with a raw AttributeError "
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


@row("FlickerMeter.update given scenes as one string ('scene-0001': each character taken for a scene, NaN), "
            "or arguments of different lengths (zip cut them silently) is an EvaluationInputError naming the counts")
def row_flicker_meter_scenes_and_counts(env):
    from instagram_hdmap.evaluation import EvaluationInputError

    meter, gt, poses = _flicker_meter(env)
    with pytest.raises(EvaluationInputError, match=r"scenes must be a list of B scene names.*\['scene-0001'\]"):
        meter.update([[]], [[gt]], "scene-0001", [0], poses[:1])
    with pytest.raises(EvaluationInputError, match=r"one entry per sample .*got 1 preds, 2 gts, 2 scenes, 2 frames, "
                                                   r"2 poses"):
        meter.update([[]], [[gt], [gt]], ["a", "a"], [0, 1], poses)


@row("FlickerMeter.update given a frame index of 1.5 (cast to 1), -1 or a string is named with its sample")
def row_flicker_meter_bad_frames(env):
    from instagram_hdmap.evaluation import EvaluationInputError

    meter, gt, poses = _flicker_meter(env)
    for frame in (1.5, -1, "1", float("nan")):
        with pytest.raises(EvaluationInputError, match=r"sample 1 \(scene 'a'\): its frame index must be an integer"):
            meter.update([[], []], [[gt], [gt]], ["a", "a"], [0, frame], poses)
    meter.update([[], []], [[gt], [gt]], ["a", "a"], torch.tensor([0.0, 1.0]), poses)  # float-typed whole numbers
    assert sorted(meter.records) == [("a", 0), ("a", 1)]


@row("FlickerMeter(threshold_m=-1, num_points=1, classes of another length, ...) was taken (wrong or crashing "
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


@row("dataset['<sample token>'] and dataset[0:2] raised raw TypeErrors ('list indices must be integers'), "
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


@row("Evaluator.merge of the same state twice (a notebook cell run again, a rank's state gathered twice) "
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


@row("Evaluator(protocol='raster', grid=cfg) (a config given as the canvas) crashed with a raw "
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


@row("FlickerMeter.update given scenes as one string, fewer frame indices or poses than samples, one pose "
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


@row("MapElement('boundary', pts, ..., class_index=0) (a name and a class id that disagree) was written as "
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


@row("to_hdmapnet(elements, meta='vector') / write_submission(..., meta=...) of a meta that is not a dict "
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


@row("mapper([frame0, frame1]) on a temporal model mapped every frame of the drive on its own, without the "
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
    # a single-frame model whose config asks for persistence: the list keeps nothing either
    persisting = Mapper.from_checkpoint(env.ckpt, device="cpu", overrides=["model.temporal.persist_frames=1"])
    with pytest.warns(UserWarning, match=r"persist_frames is set: mapper\(\[frames\]\) maps each frame on its own"):
        persisting([frame, frame])


@row("persistence.Persistence (the element persistence of model.temporal.persist_frames, a documented API: "
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


@row("instagram_hdmap.data: collate_fn of samples of two image sizes was torch's raw 'stack expects each tensor "
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


@row("evaluate of a temporal model with model.temporal.persist_frames and more streams than scenes: a stream's "
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


@row("targets.build_targets / vertex_graph / distance_transform of bad polylines: a label of 5 was a raw "
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


@row("BEVGrid of resolution 0, NaN, xmax < xmin (a grid of -64 columns, no word) or cell_size 0 was a raw "
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


@row("InstaGraM.forward of a batch of other shapes or dtypes: one sample's images without the batch "
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


@row("ConsistentAPMeter.update(ids=...): an ID of NaN, inf or beyond int64 was a raw numpy ValueError / "
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


@row("persistence.match_previous (public, shared by Persistence and InstanceTracker) checked nothing: torch "
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


@row("a bf16 model's polylines (pts a bfloat16 tensor) were refused by the evaluation's polyline check, "
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


@row("InstaGraM.forward under torch.autocast: bf16 images into an fp32 model (and fp32 images into a bf16 "
            "model) were refused by the forward's dtype check ('give images of the weights' "
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


@row("Mapper(model, config) with a config of another grid than the model was built with (a model built and "
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


@row("Mapper.from_checkpoint(path, config=cfg) (Mapper.from_onnx takes one) was 'unknown decoding option(s) "
            "config', from_checkpoint(path, 'x.yaml') \"device='x.yaml' is not a device\"; both say that the model is "
            "built from the checkpoint's own config and that overrides= changes keys")
def row_mapper_from_checkpoint_given_a_config(env):
    from instagram_hdmap import Mapper

    for args, kwargs in (((), {"config": env.cfg()}), ((str(env.yaml),), {}), ((env.cfg(),), {})):
        with pytest.raises(TypeError, match=r"Mapper\.from_checkpoint builds the model from the config saved in the "
                                            r"checkpoint; it takes no config \(.*given\): change keys with overrides="):
            Mapper.from_checkpoint(env.ckpt, *args, **kwargs)
    Mapper.from_checkpoint(env.ckpt, "cpu", overrides=["model.gnn.match_threshold=0.2"])


@row("Persistence and InstanceTracker took an element whose pts hold NaN (the evaluation refuses it): it "
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


@row("FlickerMeter.merge / ConsistentAPMeter.merge of a state whose pose is NaN, None or 3x3 (a hand-built or "
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


@row("a YAML path where the Python API takes a config (build_model, inference.load_model, "
            "Persistence.from_config, InstanceTracker.from_config, train, evaluate_split.run_evaluation; build_dataset "
            "and Evaluator.from_config took one): a raw \"'str' object has no attribute 'grid'\" (or 'does not support "
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


@row("docs/deploy.md's 'Using the file without this package': onnxruntime's outputs (NumPy arrays) handed to "
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


@row("targets of a polyline given open whose last point is its first (a divider loop around an island, "
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


@row("generate_world (the Python API of synth) given a count as a float (scenes_train=1.0) was a raw "
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


@pytest.mark.parametrize("case", table(__name__), ids=str)
def test_python_api(case, env):
    case.run(env)
