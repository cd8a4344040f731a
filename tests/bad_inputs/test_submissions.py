"""Submission files for ``evaluate-json`` (HDMapNet's and MapTR's formats): a prediction and a GT file swapped or
of another setting, tokens twice, coordinates out of range, encodings, raster-protocol canvases and flags.

Each row runs on the tiny synthetic world of tests/conftest.py and a random tiny model (bad_inputs/conftest.py).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bad_inputs.support import (
    forbid,
    row,
    submission_file,
    table,
)


@row("evaluate-json --resolution 0")
def row_evaluate_json_resolution_0(env):
    gt = env.tmp / "gt.json"
    gt.write_text(json.dumps({"results": {"a": [{"pts": [[0, 0], [1, 1]], "type": 0}]}}))
    pred = env.tmp / "pred.json"
    pred.write_text(json.dumps({"results": {"a": [{"pts": [[0, 0], [1, 1]], "type": 0, "confidence_level": 0.5}]}}))
    env.error(r"--resolution.*> ?0", "evaluate-json", "--pred", pred, "--gt", gt, "--protocol", "raster",
              "--resolution", "0")


@row("evaluate-json: a confidence outside [0, 1] is named")
def row_confidence_out_of_range(env):
    gt = submission_file(env.tmp / "gt.json", {"a": [{"pts": [[0, 0], [1, 1]], "type": 0}]}, True)
    pred = submission_file(env.tmp / "p.json", {"a": [{"pts": [[0, 0], [1, 1]], "type": 0, "confidence_level": 3.5}]},
                       False)
    env.error(r"p\.json.*'a'.*vector 0.*confidence_level.*\[0, 1\]", "evaluate-json", "--pred", pred, "--gt", gt)


@row("evaluate-json: coordinates of 1e308 are named")
def row_huge_coordinates(env):
    gt = submission_file(env.tmp / "gt.json", {"a": [{"pts": [[0, 0], [1, 1]], "type": 0}]}, True)
    vectors = {"a": [{"pts": [[0, 0], [1e308, 1]], "type": 0, "confidence_level": 0.5}]}
    pred = submission_file(env.tmp / "p.json", vectors, False)
    env.error(r"p\.json.*'a'.*vector 0.*pts.*(metres|ego)", "evaluate-json", "--pred", pred, "--gt", gt)


@row("evaluate-json: prediction and GT files swapped")
def row_swapped_submission_files(env):
    gt = submission_file(env.tmp / "gt.json", {"a": [{"pts": [[0, 0], [1, 1]], "type": 0}]}, True)
    pred = submission_file(env.tmp / "p.json", {"a": [{"pts": [[0, 0], [1, 1]], "type": 0, "confidence_level": 0.5}]},
                       False)
    env.error(r"swapped", "evaluate-json", "--pred", gt, "--gt", pred)


@row("evaluate-json: a sample token twice in a dict 'results' is named (json kept the last, dropping vectors)")
def row_submission_token_twice(env):
    gt = submission_file(env.tmp / "gt.json", {"a": [{"pts": [[0, 0], [1, 1]], "type": 0}],
                                           "b": [{"pts": [[0, 2], [3, 2]], "type": 2}]}, True)
    vector = '{"pts": [[0, 0], [1, 1]], "type": 0, "confidence_level": 0.9}'
    pred = env.tmp / "p.json"  # two prediction shards pasted into one object: "a" twice
    pred.write_text('{"meta": {"ground_truth": false}, "results": {"a": [' + vector + '], "b": [], "a": []}}')
    forbid(env, "instagram_hdmap.evaluation.Evaluator.compute", "the evaluation")
    env.error(r"p\.json: the key 'a' appears twice in one JSON object", "evaluate-json", "--pred", pred, "--gt", gt)


@row("evaluate-json --xbound / --resolution that do not tile: the flags are named (was 'config key grid.xbound')")
def row_evaluate_json_bounds_named(env):
    gt = submission_file(env.tmp / "gt.json", {"a": [{"pts": [[0, 0], [1, 1]], "type": 0}]}, True)
    env.error(r"--xbound -30 30: its extent 60 m is not a whole number of --resolution 0\.7 m pixels", "evaluate-json",
              "--pred", gt, "--gt", gt, "--protocol", "raster", "--resolution", "0.7")


@row("evaluate-json: a MapTR-format vector whose cls_name is not its type's class is named (StreamMapNet's "
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


@row("evaluate-json --protocol raster on a canvas smaller than the GT file's stated patch is named (it cropped "
          "the map: AP 1 for a missed line outside the default 60 m x 30 m)")
def row_raster_canvas_crops_the_patch(env):
    meta = {"xbound": [-50.0, 50.0], "ybound": [-50.0, 50.0]}
    near, far = [[0, 0], [5, 0], [10, 0]], [[35, 20], [40, 20], [45, 20]]
    gt = env.tmp / "gt.json"
    gt.write_text(json.dumps({"meta": {**meta, "ground_truth": True},
                              "results": {"a": [{"pts": near, "type": 0}, {"pts": far, "type": 0}]}}))
    pred = submission_file(env.tmp / "p.json", {"a": [{"pts": near, "type": 0, "confidence_level": 0.9}]}, False)
    env.error(r"gt\.json: its meta says the map patch is xbound \[-50, 50\], ybound \[-50, 50\] .*--xbound -50 50 "
              r"--ybound -50 50", "evaluate-json", "--pred", pred, "--gt", gt, "--protocol", "raster")
    rc, out, err = env.cli("evaluate-json", "--pred", pred, "--gt", gt, "--protocol", "raster", "--xbound", "-50", "50",
                           "--ybound", "-50", "50", "--resolution", "0.25")
    assert rc == 0 and re.search(r"divider\s+0\.5000", out), err  # the far line is missed


@row("evaluate-json: raster-only flags (--xbound, --resolution, --rank-by, ...) with the vector protocol are "
          "refused (ignored silently: a range the user meant to evaluate on was not applied)")
def row_evaluate_json_raster_flags_with_vector(env):
    gt = submission_file(env.tmp / "gt.json", {"a": [{"pts": [[0, 0], [1, 1]], "type": 0}]}, True)
    forbid(env, "instagram_hdmap.evaluation.Evaluator.compute", "the evaluation")
    env.error(r"--xbound, --ybound: options of the raster protocol; .*pass --protocol raster", "evaluate-json",
              "--pred", gt, "--gt", gt, "--xbound", "-15", "15", "--ybound", "-7.5", "7.5")
    env.error(r"--rank-by: options of the raster protocol", "evaluate-json", "--pred", gt, "--gt", gt, "--rank-by",
              "descending")


@row("evaluate-json --thresholds with a threshold twice is named (mAP, their mean, counted it twice; "
          "eval.thresholds was checked, the flag not)")
def row_evaluate_json_thresholds_twice(env):
    gt = submission_file(env.tmp / "gt.json", {"a": [{"pts": [[0, 0], [1, 1]], "type": 0}]}, True)
    env.error(r"thresholds: \[0\.5, 0\.5\] lists a threshold twice", "evaluate-json", "--pred", gt, "--gt", gt,
              "--thresholds", "0.5", "0.5")


@row("evaluate-json: a prediction file of other classes or another patch (its meta), or in global coordinates "
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


@row("evaluate-json: a prediction file whose meta states the patch as [min, max, resolution] (HDMapNet's "
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


@row("evaluate-json: a GT file of the official exporters (InstaGraM's / HDMapNet's export_gt_to_json.py: "
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


@row("evaluate-json: a prediction file in MapTR's lidar frame (x right, y forward) against a GT of this "
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


@row("evaluate-json: a submission with a UTF-8 byte-order mark (Windows editors) was refused as not JSON; a "
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


@row("evaluate-json --protocol raster of export-gt's file of a smaller patch (the tiny world's 16 m x 8 m) on "
            "the default canvas was refused as 'which would crop it': a larger canvas crops nothing, it counts "
            "predictions beyond the patch")
def row_raster_canvas_larger_than_the_patch(env):
    gt = env.tmp / "gt.json"
    gt.write_text(json.dumps({"meta": {"xbound": [-8.0, 8.0], "ybound": [-4.0, 4.0], "ground_truth": True},
                              "results": {"a": [{"pts": [[0, 0], [5, 0]], "type": 0}]}}))
    pred = submission_file(env.tmp / "p.json", {"a": [{"pts": [[0, 0], [5, 0]], "type": 0, "confidence_level": 0.9}]},
                       False)
    rc, out, err = env.cli("evaluate-json", "--pred", pred, "--gt", gt, "--protocol", "raster")
    assert rc == 2 and "would crop" not in err and "beyond the patch" in err, err
    assert "--xbound -8 8 --ybound -4 4" in err, err


@row("evaluate-json --protocol raster of a GT file whose meta states a 16 m x 8 m patch (export-gt of the tiny "
            "config): the advice 'pass --xbound -8 8 --ybound -4 4', followed, was refused next ('16 m is not a whole "
            "number of --resolution 0.15 m pixels'); the advice names a --resolution that tiles the patch")
def row_raster_canvas_advice_with_resolution(env):
    line = [[-5.0, 1.0], [5.0, 1.0]]
    gt = env.tmp / "gt.json"
    gt.write_text(json.dumps({"meta": {"ground_truth": True, "xbound": [-8.0, 8.0], "ybound": [-4.0, 4.0]},
                              "results": {"a": [{"pts": line, "type": 0}]}}))
    pred = submission_file(env.tmp / "p.json", {"a": [{"pts": line, "type": 0, "confidence_level": 0.9}]}, False)
    env.error(r"pass --xbound -8 8 --ybound -4 4 --resolution 0\.1 \(", "evaluate-json", "--pred", pred, "--gt", gt,
              "--protocol", "raster")
    rc, out, err = env.cli("evaluate-json", "--pred", pred, "--gt", gt, "--protocol", "raster", "--xbound", "-8", "8",
                           "--ybound", "-4", "4", "--resolution", "0.1")
    assert rc == 0 and re.search(r"divider\s+1\.0000", out), out + err


@row("evaluate-json --protocol raster re-scoring evaluate's predictions against export-gt's GT (a 16 m x 8 m "
            "grid at 0.25 m): the canvas advice named --resolution 0.1, the first that tiles the patch, and the raster "
            "AP at 0.1 m pixels differed from evaluate's at the config's 0.25 m (divider AP@0.5 0.67 against 1.0, "
            "exit 0, no word). export-gt and evaluate state the grid's resolution in the meta; the advice names it "
            "and another resolution is noted")
def row_evaluate_json_raster_resolution_of_the_gt(env):
    from instagram_hdmap.evaluation import evaluate_files
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


@row("a submission whose 'type' and 'pts_num' are whole floats (1.0: numpy's float arrays through tolist(), a "
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


@row("evaluate-json of predictions whose scores are all equal (one confidence_level written for every "
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


@row("evaluate-json --pred /dev/stdin (`zcat pred.json.gz | evaluate-json --pred /dev/stdin`) or a process "
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


@row("evaluate-json --pred gt.json --gt gt.json (export-gt's file, flagged meta.ground_truth, given as the "
            "predictions): a perfect mAP, exit 0, the only note 'predictions without confidence_level scored 1.0'; "
            "still scored (a sanity check), with a note that it scores the GT, not a model")
def row_ground_truth_file_given_as_predictions(env):
    gt, doc, pred = _gt_and_pred(env)
    rc, out, err = env.cli("evaluate-json", "--pred", gt, "--gt", gt)
    assert rc == 0 and re.search(r"gt\.json is a ground-truth file .*the --gt file itself.*not a model", out + err), \
        out + err
    rc, out, err = env.cli("evaluate-json", "--pred", pred, "--gt", gt)
    assert rc == 0 and "ground-truth file" not in out + err, out + err


@pytest.mark.parametrize("case", table(__name__), ids=str)
def test_submissions(case, env):
    case.run(env)
