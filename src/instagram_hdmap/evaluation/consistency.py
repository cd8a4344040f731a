"""Temporal consistency of a map model's output over drives: the **flicker rate** (docs/temporal.md) and
MapTracker's **consistency-aware mAP** (``ConsistentAPMeter``, at the end of this module).

    meter = FlickerMeter(grid)
    meter.update(preds, gts, scenes=batch["scene"], frames=batch["frame_index"], poses=batch["ego_pose"])
    meter.gather()                   # under torchrun
    meter.compute()  # {"flicker": {class: rate}, "flicker_mean", "pairs": {class: n}, "flips", ...}

Definition. In each frame, a GT instance is *detected* when a prediction of its class matches it: the
predictions, by descending score, each take the free GT of their class at the smallest Chamfer distance
``D`` (the vector protocol's symmetric mean nearest distance, both polylines resampled to
``detect_points`` = 100 points) if ``D <= threshold_m`` (1.0 m, the vector protocol's middle threshold;
predictions below ``score_threshold`` do not count). A GT instance is *seen in two consecutive frames*
(frames t and t + 1 of one scene) when the GT of frame t + 1 has at least ``min_shared_points`` of its
points inside frame t's grid (moved there by the two ego poses) and those points lie within
``link_m`` (mean distance) of one GT instance of the same class of frame t; that instance is the same
map element (GT instances carry no identity across frames; the link is geometric). The **flicker
rate** of a class is the share of such pairs (instance in t, instance in t + 1) whose detected /
missed status differs; ``flicker_mean`` is the mean over the classes that have pairs. 0 = a model
whose output never changes its mind about an element it keeps seeing; it is 0 for a perfect model
and for one that detects nothing, so read it next to the AP, or read ``flicker_detected``: the same
share among the pairs detected in at least one of the two frames (NaN for a class never detected;
``flicker_detected_mean`` over the classes that have such pairs), which a model cannot lower by
detecting less.

Order-free: every sample's detection status, GT (resampled to ``num_points`` = 20 points) and pose are kept, grouped by
scene and sorted by frame at ``compute``; samples may arrive in any order, from any process.
MapTracker's consistency-aware mAP, which needs instance IDs carried across frames: ``ConsistentAPMeter`` below.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence

import numpy as np
import torch

from ..errors import as_batch_list, as_float64_array, check_rigid_pose, is_real
from ..geometry import BEVGrid
from ..persistence import MATCH_POINTS, InstanceTracker, PersistenceInputError
from .chamfer import chamfer_pairs
from .inputs import EvaluationInputError, PolylineSet, check_grid, gather_states, read_polylines
from .vector_ap import VectorAP, pooled_ap, resample_polylines


def detected_gt(P: PolylineSet, G: PolylineSet, threshold_m: float, num_points: int = 100,
                score_threshold: float = 0.0) -> np.ndarray:
    """[G] bool: GT instance g of a sample's checked GT ``G`` matched by one of its checked predictions ``P``
    (module docstring: greedy by score, same class, Chamfer D <= ``threshold_m`` with both polylines resampled to
    ``num_points`` points)."""
    detected = np.zeros(len(G.pts), dtype=bool)
    keep = np.flatnonzero(P.scores >= score_threshold)
    if not len(keep) or not len(G.pts):
        return detected
    pi, gi = np.nonzero(P.labels[keep][:, None] == G.labels[None])
    if not len(pi):
        return detected
    a = resample_polylines([P.pts[i] for i in keep], num_points)  # [P, n, 2]
    b = resample_polylines(G.pts, num_points)  # [G, n, 2]
    d_ab, d_ba, _ = chamfer_pairs(a[pi], b[gi])
    chamfer = np.full((len(keep), len(G.pts)), np.inf)
    chamfer[pi, gi] = (d_ab + d_ba) / 2
    for i in np.argsort(-P.scores[keep], kind="stable"):
        d = np.where(detected, np.inf, chamfer[i])
        j = int(d.argmin())
        if d[j] <= threshold_m:
            detected[j] = True
    return detected


def _point_to_polyline(q: np.ndarray, line: np.ndarray) -> np.ndarray:
    """[Q, 2] points, [n, 2] polyline -> [Q] distance of each point to the polyline."""
    a, b = line[:-1], line[1:]
    d = b - a
    t = np.clip(((q[:, None] - a[None]) * d[None]).sum(-1) / np.maximum((d * d).sum(-1), 1e-12), 0.0, 1.0)
    return np.linalg.norm(q[:, None] - (a[None] + t[..., None] * d[None]), axis=-1).min(1)


def gt_links(grid: BEVGrid, prev: dict, cur: dict, link_m: float, min_shared_points: int) -> list[tuple]:
    """The geometric link of the GT of two consecutive frames (module docstring): ``(i, j, d)`` for each GT
    instance j of frame t + 1 (``cur``: ``labels`` [G], ``pts`` [G, n, 2], ``pose`` [4, 4]) that is instance i of
    frame t (``prev``), d the mean distance of j's shared points to i (several j may link to one i)."""
    if not len(prev["labels"]) or not len(cur["labels"]):
        return []
    cur_to_prev = np.linalg.inv(prev["pose"]) @ cur["pose"]
    out = []
    for j in range(len(cur["labels"])):
        pts = cur["pts"][j] @ cur_to_prev[:2, :2].T + cur_to_prev[:2, 3]  # frame t+1 -> frame t (ground)
        shared = pts[grid.inside_m(pts)]
        if len(shared) < min_shared_points:
            continue
        best, best_i = math.inf, -1
        for i in np.flatnonzero(prev["labels"] == cur["labels"][j]):
            d = float(_point_to_polyline(shared, prev["pts"][i]).mean())
            if d < best:
                best, best_i = d, int(i)
        if best <= link_m:
            out.append((best_i, j, best))
    return out


def checked_batch(who: str, preds, gts, scenes, frames, poses, num_classes: int) -> list[tuple]:
    """The checks of a drive meter's ``update`` (``FlickerMeter``, ``ConsistentAPMeter``): B samples' predictions
    (polyline dicts or ``MapElement`` lists), GT, scene names, frame indices and ego poses ([B, 4, 4], or
    [B, 3, 4]). Returns per sample ``((scene, frame), P, G, pose)`` (``inputs.read_polylines``' checked sets;
    predictions with fewer than two points dropped); a bad input is an ``EvaluationInputError`` naming the sample,
    raised before anything is returned."""
    if isinstance(scenes, (str, bytes)):
        raise EvaluationInputError(f"{who}: scenes must be a list of B scene names, one per sample, "
                                   f"got one string {scenes!r:.80} (for one sample: [{scenes!r:.80}])")
    scenes = as_batch_list(scenes, f"{who}: scenes", "a list of B scene names, one per sample",
                           EvaluationInputError)
    frames = as_batch_list(frames, f"{who}: frames", "B frame indices (a list or a [B] tensor)",
                           EvaluationInputError)
    for name, value in (("preds", preds), ("gts", gts)):
        if isinstance(value, (dict, str, bytes)) or not isinstance(value, Sequence):
            raise EvaluationInputError(f"{who}: {name} must be a list of B samples, each a list "
                                       f"of polyline dicts, got {type(value).__name__}")
    poses = as_float64_array(poses, f"{who}: poses", "B ego -> world transforms [B, 4, 4]", EvaluationInputError)
    counts = {"preds": len(preds), "gts": len(gts), "scenes": len(scenes), "frames": len(frames)}
    B = len(gts)
    if poses.shape == (4, 4) and B != 1:
        raise EvaluationInputError(f"{who}: poses is one [4, 4] pose for a batch of {B} samples; "
                                   "give one pose per sample, [B, 4, 4]")
    if poses.ndim == 3 and poses.shape[1:] == (3, 4):  # [R | t] without the last row (a 3x4 per sample)
        poses = np.concatenate([poses, np.broadcast_to([[[0.0, 0.0, 0.0, 1.0]]], (len(poses), 1, 4))], axis=1)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        if poses.shape != (4, 4):
            raise EvaluationInputError(f"{who}: poses must have shape [B, 4, 4] (ego -> world), "
                                       f"got {list(poses.shape)}")
        poses = poses[None]  # one sample's [4, 4]
    counts["poses"] = len(poses)
    if len(set(counts.values())) > 1:
        raise EvaluationInputError(f"{who}: one entry per sample in each argument, got "
                                   + ", ".join(f"{v} {k}" for k, v in counts.items()))
    keys = []
    for b in range(B):
        f = frames[b]
        if isinstance(f, (bool, np.bool_)) or not is_real(f) or not math.isfinite(f) or f != int(f) or f < 0:
            raise EvaluationInputError(f"{who}: sample {b} (scene '{scenes[b]}'): its frame index "
                                       f"must be an integer >= 0 (the frame's place in its scene), got {f!r}")
        keys.append((str(scenes[b]), int(f)))
    checked = []
    for b, key in enumerate(keys):
        where = f"sample (scene '{key[0]}', frame {key[1]})"
        check_rigid_pose(poses[b], where, EvaluationInputError)
        p = preds[b]
        if isinstance(p, Sequence) and not isinstance(p, (str, bytes)):  # a dict without a score counts as 1
            p = [dict(x, score=x.get("score", 1.0)) if isinstance(x, dict) else x for x in p]  # (MapElements have one)
        P = read_polylines(p, role="prediction", num_classes=num_classes, where=where, short="drop")
        G = read_polylines(gts[b], role="GT", num_classes=num_classes, where=where, short="drop")
        checked.append((key, P, G, np.asarray(poses[b], dtype=np.float64)))
    return checked


def _records_to_merge(meter, state, keys: set[str], label_keys: tuple[str, ...], form: str) -> Mapping:
    """The ``records`` of another meter's ``state_dict()`` for ``meter.merge``, checked: a state of the form
    ``form`` (the meter itself, or anything else, named), each record with ``keys``, class ids (``label_keys``)
    within ``meter.num_classes``."""
    name = type(meter).__name__
    records = state.get("records") if isinstance(state, Mapping) else None
    if isinstance(state, type(meter)) or not isinstance(records, Mapping) or not all(
            isinstance(k, tuple) and len(k) == 2 and isinstance(r, Mapping) and keys <= set(r)
            for k, r in records.items()):
        hint = "; pass other.state_dict()" if isinstance(state, type(meter)) else ""
        raise EvaluationInputError(f"{name}.merge takes another {name}'s state_dict() ({form}), got "
                                   f"{type(state).__name__}{hint}")
    bad = [k for k, r in records.items()
           if any(len(r[x]) and not 0 <= int(np.max(r[x])) < meter.num_classes for x in label_keys)]
    if bad:
        raise EvaluationInputError(f"{name}.merge: the state's sample (scene '{bad[0][0]}', frame {bad[0][1]}) has "
                                   f"class ids beyond this meter's {meter.num_classes} classes (a state of a meter "
                                   "with other classes)")
    # a pose of NaN, None or another shape was merged as it was: a NaN flicker rate with no word, a raw matmul error
    return {k: {**r, "pose": check_rigid_pose(as_float64_array(r["pose"], f"{name}.merge: the state's pose",
                                                               "a 4x4 ego -> world transform", EvaluationInputError),
                                              f"{name}.merge: the state's sample (scene '{k[0]}', frame {k[1]})",
                                              EvaluationInputError)}
            for k, r in records.items()}


class _DriveMeter:
    """What the drive meters share: per-sample ``records`` keyed by (scene, frame), each sample kept once."""

    def reset(self) -> None:
        self.records: dict[tuple[str, int], dict] = {}

    def state_dict(self) -> dict:
        return {"records": dict(self.records)}

    def _keep(self, records: Mapping) -> None:
        for key, rec in records.items():
            self.records.setdefault(key, rec)

    def gather(self) -> None:
        """Under torch.distributed: every rank ends with all records (a no-op otherwise)."""
        gather_states(self)


class FlickerMeter(_DriveMeter):
    """Accumulates per-sample detection status and computes the flicker rate (module docstring)."""

    def __init__(self, grid: BEVGrid, num_classes: int | None = None, classes: Sequence[str] | None = None,
                 threshold_m: float = 1.0, score_threshold: float = 0.0, link_m: float = 0.5,
                 min_shared_points: int = 2, num_points: int = 20, detect_points: int = 100):
        grid = check_grid(grid, "FlickerMeter")  # a config (or its grid section): the grid it describes
        if isinstance(classes, (str, bytes)):
            raise EvaluationInputError(f"FlickerMeter: classes must be a list of class names, got {classes!r:.80}")
        if num_classes is None:  # classes=["divider"]: one class (num_classes 3 averaged two unseen ones)
            num_classes = len(classes) if classes is not None else 3
        for name, value, least in (("num_classes", num_classes, 1), ("min_shared_points", min_shared_points, 1),
                                   ("num_points", num_points, 2), ("detect_points", detect_points, 2)):
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < least:
                raise EvaluationInputError(f"FlickerMeter: {name} must be an integer >= {least}, got {value!r}")
        for name, value in (("threshold_m", threshold_m), ("link_m", link_m)):
            if not is_real(value) or not (math.isfinite(value) and value > 0):
                raise EvaluationInputError(f"FlickerMeter: {name} must be a finite distance > 0 (metres), "
                                           f"got {value!r}")
        if not is_real(score_threshold) or math.isnan(score_threshold):
            raise EvaluationInputError(f"FlickerMeter: score_threshold must be a number, got {score_threshold!r}")
        if classes is not None and len(classes) != num_classes:
            raise EvaluationInputError(f"FlickerMeter: classes must name the num_classes = {num_classes} classes, "
                                       f"one name each, got {classes!r:.120}")
        self.grid, self.num_classes = grid, int(num_classes)
        self.classes = tuple(classes) if classes is not None else tuple(str(k) for k in range(num_classes))
        self.threshold_m, self.score_threshold = float(threshold_m), float(score_threshold)
        self.link_m, self.min_shared_points, self.num_points = float(link_m), int(min_shared_points), int(num_points)
        self.detect_points = int(detect_points)
        self.reset()

    def update(self, preds: Sequence[Sequence[dict]], gts: Sequence[Sequence[dict]], scenes: Sequence[str],
               frames, poses) -> None:
        """B samples: polylines (metres, ego frame; predictions may be ``MapElement`` lists, what ``Mapper``
        returns), their scene names, frame indices [B] (integers >= 0) and ego poses [B, 4, 4] (tensors or
        arrays; finite rigid transforms [[R, t], [0, 0, 0, 1]], which compute inverts). A
        sample seen twice (streaming padding) counts once. A bad input is an ``EvaluationInputError`` naming
        the sample (scene, frame); nothing of the batch is kept then."""
        for key, P, G, pose in checked_batch("FlickerMeter.update", preds, gts, scenes, frames, poses,
                                             self.num_classes):
            if key in self.records:
                continue
            self.records[key] = {
                "detected": detected_gt(P, G, self.threshold_m, self.detect_points, self.score_threshold),
                "labels": G.labels.copy(),
                "pts": resample_polylines(G.pts, self.num_points),
                "pose": pose,
            }

    def merge(self, state: dict) -> None:
        """Add another meter's ``state_dict()`` (a sample already here is kept once)."""
        self._keep(_records_to_merge(self, state, {"detected", "labels", "pts", "pose"}, ("labels",),
                                     "{'records': {(scene, frame): ...}}"))

    def compute(self) -> dict:
        """``flicker`` (class -> rate, NaN without pairs), ``flicker_mean``, ``flicker_detected``,
        ``flicker_detected_mean``, ``pairs``, ``pairs_detected`` and ``flips`` per class, ``frame_pairs``
        (consecutive frames compared), and the definition's parameters."""
        pairs = np.zeros(self.num_classes, dtype=np.int64)
        flips = np.zeros(self.num_classes, dtype=np.int64)
        seen = np.zeros(self.num_classes, dtype=np.int64)  # pairs detected in at least one frame
        frame_pairs = 0
        for (scene, frame), cur in sorted(self.records.items()):
            prev = self.records.get((scene, frame - 1))
            if prev is None:
                continue
            frame_pairs += 1
            for i, j, _ in gt_links(self.grid, prev, cur, self.link_m, self.min_shared_points):
                k = int(cur["labels"][j])
                pairs[k] += 1
                flips[k] += int(prev["detected"][i] != cur["detected"][j])
                seen[k] += int(prev["detected"][i] or cur["detected"][j])
        rate = [float(f / n) if n else math.nan for f, n in zip(flips, pairs)]
        rate_seen = [float(f / n) if n else math.nan for f, n in zip(flips, seen)]

        def mean(values: list[float]) -> float:
            values = [v for v in values if not math.isnan(v)]
            return float(np.mean(values)) if values else math.nan

        return {
            "flicker": dict(zip(self.classes, rate)),
            "flicker_mean": mean(rate),
            "flicker_detected": dict(zip(self.classes, rate_seen)),
            "flicker_detected_mean": mean(rate_seen),
            "pairs": dict(zip(self.classes, pairs.tolist())),
            "pairs_detected": dict(zip(self.classes, seen.tolist())),
            "flips": dict(zip(self.classes, flips.tolist())),
            "frame_pairs": frame_pairs,
            "samples": len(self.records),
            "definition": {"threshold_m": self.threshold_m, "score_threshold": self.score_threshold,
                           "link_m": self.link_m, "min_shared_points": self.min_shared_points},
        }


class ConsistentAPMeter(_DriveMeter):
    """MapTracker's **consistency-aware mAP** (C-mAP) next to the per-frame vector mAP (docs/temporal.md).

        meter = ConsistentAPMeter(grid, classes=cfg.data.classes)
        meter.update(preds, gts, scenes=batch["scene"], frames=batch["frame_index"], poses=batch["ego_pose"])
        meter.gather()                   # under torchrun
        meter.compute()  # {"C-mAP", "C-AP_class", "C-AP", "mAP", "AP_class", "AP", "switched", ...}

    MapTracker's rule (github.com/woodfrog/maptracker, ``tools/tracking/calculate_cmap.py``,
    ``get_tpfp_from_scene_single``): per scene, class and threshold, the frames in order; every prediction is
    first a TP or FP of its frame as in the per-frame AP (``instance_match``: by score, nearest GT only,
    ``D <= thr``, each GT once); then, with the GT instance IDs across frames (``gt_flag_dict``), the first
    prediction ID matched to a GT track owns it, and a later TP whose prediction ID differs from the owner's
    becomes an FP. AP is then pooled as usual (``get_mAP``), at the thresholds {0.5, 1.0, 1.5} m of the 60 m
    range (``main``). A perfect tracker keeps C-mAP == mAP; a switch in the middle of a track turns all that
    track's later TPs (of the new ID) into FPs, for the rest of the scene.

    Where this differs from MapTracker's scripts, and why:

    * GT instance IDs: MapTracker builds them offline (``tools/tracking/prepare_gt_tracks.py``,
      ``match_two_consecutive_frames`` + ``assign_global_ids``: the previous frame's GT moved by the relative
      pose, drawn as masks, Hungarian on mask IoU > 0.01, an unmatched GT a new ID). Our datasets carry no GT
      instance IDs either; here they come from ``FlickerMeter``'s geometric link (``gt_links``: a GT of frame
      t + 1 whose points moved into frame t lie within ``link_m`` of a GT of its class), made one to one
      (smallest distance first); an unlinked GT, a scene's first frame or a frame after a gap starts a new ID.
    * Predicted instance IDs: MapTracker's model outputs its own; for other models,
      ``tools/tracking/prepare_pred_tracks.py`` matches each frame to the previous 5 by mask IoU after dropping
      predictions scored <= 0.4. Here: the IDs given to ``update(ids=...)`` (a model that tracks), else
      ``persistence.InstanceTracker`` at ``compute`` (the persistence matcher: the previous frame only, all
      predictions, Chamfer <= ``match_m``), run over each scene in frame order after gathering, so the result
      does not depend on the order or the process the samples came from.
    * The per-frame decisions are this project's vector protocol (``VectorAP.match``: MapTR's Chamfer AP, a
      prediction in a frame without GT of its class an FP, which MapTracker's ``_evaluate_single`` leaves out),
      so ``mAP`` here is the vector protocol's and C-mAP <= mAP always. ``mAP`` is pooled in (scene, frame) order:
      with tied scores it can differ from the evaluator's by the tie order.

    Order-free and torchrun-safe like ``FlickerMeter``: per sample (a sample seen twice counts once) it keeps the
    per-frame decisions, the predictions resampled to ``MATCH_POINTS`` (20) points for the tracker (or the given
    IDs), the GT resampled to ``num_points`` and the pose; ``merge`` / ``gather`` pool them, ``compute`` sorts.
    """

    def __init__(self, grid: BEVGrid, num_classes: int | None = None, classes: Sequence[str] | None = None,
                 thresholds: Sequence[float] = (0.5, 1.0, 1.5), match_m: float = 1.0, max_jump_m: float = 10.0,
                 max_turn_deg: float = 180.0, link_m: float = 0.5, min_shared_points: int = 2, num_points: int = 20):
        try:  # the same checks as the flicker meter's
            checks = FlickerMeter(grid, num_classes, classes, 1.0, 0.0, link_m, min_shared_points, num_points)
        except EvaluationInputError as e:
            raise EvaluationInputError(str(e).replace("FlickerMeter", "ConsistentAPMeter")) from None
        self.grid, self.num_classes, self.classes = checks.grid, checks.num_classes, checks.classes
        self.link_m, self.min_shared_points = checks.link_m, checks.min_shared_points
        self.num_points = checks.num_points
        if isinstance(thresholds, (torch.Tensor, np.ndarray)) and thresholds.ndim == 1:  # VectorAP takes them too
            thresholds = thresholds.tolist()
        if isinstance(thresholds, (str, bytes)) or not isinstance(thresholds, Sequence) or not thresholds or not all(
                is_real(t) and math.isfinite(t) and 0 < t < 100 for t in thresholds):
            raise EvaluationInputError(f"ConsistentAPMeter: thresholds must be a list of Chamfer distances in metres, "
                                       f"each in (0, 100), got {thresholds!r:.80}")
        if len(set(thresholds)) != len(thresholds):  # (eval.thresholds' rule) C-mAP, their mean, would count it twice
            raise EvaluationInputError(f"ConsistentAPMeter: thresholds lists a distance twice, which C-mAP (the mean "
                                       f"over them) would count twice; got {list(thresholds)}")
        try:
            InstanceTracker(self.grid, match_m, max_jump_m, max_turn_deg)
        except PersistenceInputError as e:
            raise EvaluationInputError(f"ConsistentAPMeter: {e}") from None
        self.thresholds = tuple(float(t) for t in thresholds)
        self.match_m, self.max_jump_m, self.max_turn_deg = float(match_m), float(max_jump_m), float(max_turn_deg)
        self._ap = VectorAP(self.thresholds, self.num_classes)
        self.reset()

    def update(self, preds: Sequence[Sequence[dict]], gts: Sequence[Sequence[dict]], scenes: Sequence[str],
               frames, poses, ids: Sequence[Sequence[int]] | None = None) -> None:
        """B samples, as ``FlickerMeter.update``; ``ids`` (optional): per sample one integer instance ID per
        prediction (a model that tracks; IDs are compared within a scene), else the tracker's at ``compute``.
        A bad input is an ``EvaluationInputError`` naming the sample; nothing of the batch is kept then."""
        checked = checked_batch("ConsistentAPMeter.update", preds, gts, scenes, frames, poses, self.num_classes)
        if ids is not None:
            if isinstance(ids, (torch.Tensor, np.ndarray)) and ids.ndim == 2:  # [B, P]: the same count per sample
                ids = list(ids)
            if isinstance(ids, (str, bytes, Mapping)) or not isinstance(ids, Sequence) or len(ids) != len(checked):
                raise EvaluationInputError(f"ConsistentAPMeter.update: ids must be a list of B = {len(checked)} "
                                           f"lists, one integer ID per prediction, got {ids!r:.80}")
            ids = [i.tolist() if isinstance(i, (torch.Tensor, np.ndarray)) else i for i in ids]
            for (key, _, _, _), p, i in zip(checked, preds, ids):
                if (isinstance(i, (str, bytes)) or not isinstance(i, Sequence) or len(i) != len(p)
                        or not all(is_real(x) and math.isfinite(x) and x == int(x) and -2**63 <= x < 2**63
                                   for x in i)):  # int64: NaN / inf / a 70-bit integer were raw numpy errors
                    raise EvaluationInputError(f"ConsistentAPMeter.update: sample (scene '{key[0]}', frame {key[1]}): "
                                               f"ids must be one integer per prediction ({len(p)}), got {i!r:.80}")
        matched = self._ap.match(
            [[{"pts": x, "label": int(k), "score": float(s)} for x, k, s in zip(P.pts, P.labels, P.scores)]
             for _, P, _, _ in checked],
            [[{"pts": x, "label": int(k)} for x, k in zip(G.pts, G.labels)] for _, _, G, _ in checked],
            np.arange(len(checked)), [f"scene '{k[0]}', frame {k[1]}" for k, _, _, _ in checked])
        for b, (key, P, G, pose) in enumerate(checked):
            if key in self.records:
                continue
            m = matched["sample"] == b
            self.records[key] = {
                "label": matched["label"][m], "score": matched["score"][m], "tp": matched["tp"][m],
                "gt": matched["gt"][m],
                "ids": None if ids is None else np.asarray([int(ids[b][i]) for i in P.kept], dtype=np.int64),
                "pts": None if ids is not None else resample_polylines(P.pts, MATCH_POINTS).astype(np.float32),
                "gt_labels": G.labels.copy(),
                "gt_pts": resample_polylines(G.pts, self.num_points),
                "pose": pose,
            }

    def state_dict(self) -> dict:
        return {**super().state_dict(), "thresholds": self.thresholds}

    def merge(self, state: dict) -> None:
        """Add another meter's ``state_dict()`` (a sample already here is kept once)."""
        records = _records_to_merge(self, state, {"label", "score", "tp", "gt", "ids", "pts", "gt_labels", "gt_pts",
                                                  "pose"}, ("label", "gt_labels"),
                                    "{'records': {(scene, frame): ...}, 'thresholds': ...}")
        if tuple(state.get("thresholds", ())) != self.thresholds:
            raise EvaluationInputError(f"ConsistentAPMeter.merge: the state is at thresholds "
                                       f"{list(state.get('thresholds', ()))}, this meter at {list(self.thresholds)}")
        self._keep(records)

    def _tracks(self, keys: list[tuple[str, int]]) -> tuple[dict, dict]:
        """Predicted and GT instance IDs per sample (class docstring), ``keys`` sorted by (scene, frame)."""
        given = {self.records[k]["ids"] is not None for k in keys}
        if len(given) > 1:
            raise EvaluationInputError("ConsistentAPMeter: some samples came with prediction ids and some without; "
                                       "give ids for every sample (a model that tracks) or for none")
        tracker = None if given == {True} else InstanceTracker(self.grid, self.match_m, self.max_jump_m,
                                                               self.max_turn_deg)
        pred_ids, gt_ids, next_gt = {}, {}, {}
        for key in keys:
            rec, scene = self.records[key], key[0]
            if tracker is None:
                pred_ids[key] = rec["ids"]
            else:
                pred_ids[key] = np.asarray(tracker.step(
                    [{"pts": x, "label": int(k), "score": float(s)} for x, k, s in zip(rec["pts"], rec["label"],
                                                                                    rec["score"])],
                    scene, key[1], rec["pose"]), dtype=np.int64)
            cur = {"labels": rec["gt_labels"], "pts": rec["gt_pts"], "pose": rec["pose"]}
            prev_key = (scene, key[1] - 1)
            ids = np.full(len(rec["gt_labels"]), -1, dtype=np.int64)
            if prev_key in self.records:
                prev = self.records[prev_key]
                links = gt_links(self.grid, {"labels": prev["gt_labels"], "pts": prev["gt_pts"], "pose": prev["pose"]},
                                 cur, self.link_m, self.min_shared_points)
                taken = set()
                for i, j, _ in sorted(links, key=lambda x: (x[2], x[1], x[0])):  # one to one, nearest first
                    if i not in taken and ids[j] < 0:
                        taken.add(i)
                        ids[j] = gt_ids[prev_key][i]
            n = next_gt.get(scene, 0)
            for j in np.flatnonzero(ids < 0):
                ids[j], n = n, n + 1
            next_gt[scene] = n
            gt_ids[key] = ids
        return pred_ids, gt_ids

    def compute(self) -> dict:
        """``C-AP`` / ``AP`` (class -> one AP per threshold), ``C-AP_class`` / ``AP_class`` (class -> mean over
        the thresholds), ``C-mAP`` / ``mAP`` (mean over classes and thresholds; a class without GT counts 0, the
        vector protocol's rule), ``switched`` (class -> per threshold the TPs that the ID rule turned into FPs),
        ``id_switches`` (class -> per threshold how often a GT track's true positive came with another prediction
        ID than its previous one: MOTA's IDSW over the matches of the AP),
        ``tracks`` (predicted and GT instance IDs over all scenes), ``samples``, ``thresholds``, ``definition``."""
        keys = sorted(self.records)
        pred_ids, gt_ids = self._tracks(keys)
        K, T = self.num_classes, len(self.thresholds)
        owner: dict[tuple, int] = {}  # (scene, class, threshold, GT track) -> the prediction ID that owns it
        last: dict[tuple, int] = {}  # the same key -> the prediction ID that matched it last
        scores, tp, ctp = [[] for _ in range(K)], [[] for _ in range(K)], [[] for _ in range(K)]
        num_gt = np.zeros(K, dtype=np.int64)
        id_switches = np.zeros((K, T), dtype=np.int64)
        for key in keys:
            rec = self.records[key]
            num_gt += np.bincount(rec["gt_labels"], minlength=K)
            c_tp = rec["tp"].copy()
            for i in np.flatnonzero(rec["tp"].any(1)):
                track, pid, c = int(gt_ids[key][rec["gt"][i]]), int(pred_ids[key][i]), int(rec["label"][i])
                for t in np.flatnonzero(rec["tp"][i]):
                    first = owner.setdefault((key[0], c, int(t), track), pid)
                    c_tp[i, t] = first == pid
                    id_switches[c, t] += last.setdefault((key[0], c, int(t), track), pid) != pid
                    last[(key[0], c, int(t), track)] = pid
            for c in range(K):
                m = rec["label"] == c
                scores[c].append(rec["score"][m])
                tp[c].append(rec["tp"][m])
                ctp[c].append(c_tp[m])
        ap, c_ap = np.zeros((K, T)), np.zeros((K, T))
        switched = np.zeros((K, T), dtype=np.int64)
        for c in range(K):
            s = np.concatenate(scores[c]) if scores[c] else np.zeros(0)
            f = np.concatenate(tp[c]) if tp[c] else np.zeros((0, T), bool)
            g = np.concatenate(ctp[c]) if ctp[c] else np.zeros((0, T), bool)
            ap[c], c_ap[c] = pooled_ap(s, f, int(num_gt[c])), pooled_ap(s, g, int(num_gt[c]))
            switched[c] = f.sum(0) - g.sum(0)
        return {
            "C-AP": {n: c_ap[c].tolist() for c, n in enumerate(self.classes)},
            "C-AP_class": {n: float(c_ap[c].mean()) for c, n in enumerate(self.classes)},
            "C-mAP": float(c_ap.mean()) if keys else math.nan,
            "AP": {n: ap[c].tolist() for c, n in enumerate(self.classes)},
            "AP_class": {n: float(ap[c].mean()) for c, n in enumerate(self.classes)},
            "mAP": float(ap.mean()) if keys else math.nan,
            "switched": {n: switched[c].tolist() for c, n in enumerate(self.classes)},
            "id_switches": {n: id_switches[c].tolist() for c, n in enumerate(self.classes)},
            "tracks": {"pred": len({(k[0], int(i)) for k, v in pred_ids.items() for i in v}),
                       "gt": len({(k[0], int(i)) for k, v in gt_ids.items() for i in v})},
            "samples": len(keys),
            "thresholds": list(self.thresholds),
            "definition": {"ids": "given" if keys and self.records[keys[0]]["ids"] is not None else "tracked",
                           "match_m": self.match_m, "link_m": self.link_m,
                           "min_shared_points": self.min_shared_points},
        }
