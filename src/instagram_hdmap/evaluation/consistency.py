"""Temporal consistency of a map model's output over drives: the **flicker rate** (docs/temporal.md).

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
(MapTracker's consistency-aware mAP needs predicted instance IDs carried across frames; not built.)
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from ..geometry import BEVGrid
from .chamfer import chamfer_pairs
from .evaluator import _samples, check_classes
from .inputs import EvaluationInputError, PolylineSet, _detached, check_grid, read_polylines, sample_name
from .vector_ap import resample_polylines


def detected_gt(preds: Sequence[dict], gts: Sequence[dict], threshold_m: float, num_points: int = 100,
                score_threshold: float = 0.0) -> np.ndarray:
    """[G] bool: GT instance g matched by a prediction (module docstring: greedy by score, same class,
    Chamfer D <= ``threshold_m`` with both polylines resampled to ``num_points`` points)."""
    detected = np.zeros(len(gts), dtype=bool)
    preds = [p for p in preds if p.get("score", 1.0) >= score_threshold and len(p["pts"]) >= 2]
    if not preds or not gts:
        return detected
    pi, gi = np.nonzero(np.array([p["label"] for p in preds])[:, None] == np.array([g["label"] for g in gts])[None])
    if not len(pi):
        return detected
    a = resample_polylines([np.asarray(p["pts"], np.float64) for p in preds], num_points)  # [P, n, 2]
    b = resample_polylines([np.asarray(g["pts"], np.float64) for g in gts], num_points)  # [G, n, 2]
    d_ab, d_ba, _ = chamfer_pairs(a[pi], b[gi])
    chamfer = np.full((len(preds), len(gts)), np.inf)
    chamfer[pi, gi] = (d_ab + d_ba) / 2
    for i in np.argsort([-p.get("score", 1.0) for p in preds], kind="stable"):
        d = np.where(detected, np.inf, chamfer[i])
        j = int(d.argmin())
        if d[j] <= threshold_m:
            detected[j] = True
    return detected


def _dicts(polylines: PolylineSet) -> list[dict]:
    """Checked polylines (``read_polylines``) as the dicts of ``detected_gt``."""
    return [{"pts": pts, "label": int(label), "score": float(score)}
            for pts, label, score in zip(polylines.pts, polylines.labels, polylines.scores)]


def _point_to_polyline(q: np.ndarray, line: np.ndarray) -> np.ndarray:
    """[Q, 2] points, [n, 2] polyline -> [Q] distance of each point to the polyline."""
    a, b = line[:-1], line[1:]
    d = b - a
    t = np.clip(((q[:, None] - a[None]) * d[None]).sum(-1) / np.maximum((d * d).sum(-1), 1e-12), 0.0, 1.0)
    return np.linalg.norm(q[:, None] - (a[None] + t[..., None] * d[None]), axis=-1).min(1)


class FlickerMeter:
    """Accumulates per-sample detection status and computes the flicker rate (module docstring)."""

    def __init__(self, grid: BEVGrid, num_classes: int | None = None, classes: Sequence[str] | None = None,
                 threshold_m: float = 1.0, score_threshold: float = 0.0, link_m: float = 0.5,
                 min_shared_points: int = 2, num_points: int = 20, detect_points: int = 100):
        # checked here: a config given as the grid was a raw AttributeError at compute, and classes of another
        # count than num_classes reported some classes' rates and averaged others into flicker_mean unseen
        self.grid = check_grid(grid, "FlickerMeter")
        if classes is not None:
            classes = check_classes(classes)
            if num_classes is not None and num_classes != len(classes):
                raise EvaluationInputError(f"FlickerMeter: num_classes={num_classes} but {len(classes)} classes "
                                           f"{list(classes)}; give one of them (labels index the classes)")
        self.num_classes = num_classes if num_classes is not None else len(classes) if classes is not None else 3
        self.classes = tuple(classes) if classes is not None else tuple(str(k) for k in range(self.num_classes))
        self.threshold_m, self.score_threshold = threshold_m, score_threshold
        self.link_m, self.min_shared_points, self.num_points = link_m, min_shared_points, num_points
        self.detect_points = detect_points
        self.reset()

    def reset(self) -> None:
        self.records: dict[tuple[str, int], dict] = {}

    def update(self, preds: Sequence[Sequence[dict]], gts: Sequence[Sequence[dict]], scenes: Sequence[str],
               frames, poses) -> None:
        """B samples: polylines (metres, ego frame), their scene names, frame indices [B] and ego poses
        [B, 4, 4] (tensors or arrays). A sample seen twice (streaming padding) counts once."""
        who = "FlickerMeter.update"
        preds, gts = _samples(preds, "predictions", who), _samples(gts, "GT", who)
        n = len(preds)
        if len(gts) != n:
            raise EvaluationInputError(f"FlickerMeter.update: {n} prediction lists but {len(gts)} GT lists")
        if isinstance(scenes, (str, bytes)) or not isinstance(scenes, (Sequence, np.ndarray)):
            raise EvaluationInputError(f"FlickerMeter.update: scenes must be one scene name per sample, got "
                                       f"{scenes!r:.60}")
        frames = _detached(frames)
        frames = np.asarray(frames).reshape(-1) if not isinstance(frames, (list, tuple)) else np.asarray(frames)
        poses = _detached(poses)
        try:
            poses = np.asarray(poses.double() if isinstance(poses, torch.Tensor) else poses, dtype=np.float64)
        except (TypeError, ValueError):  # None, strings, ragged lists: named below by their shape
            poses = np.full((), np.nan)
        if len(scenes) != n or frames.shape != (n,):
            raise EvaluationInputError(f"FlickerMeter.update: {n} samples but {len(scenes)} scene names and "
                                       f"{frames.size} frame indices; give one of each per sample")
        if not (np.issubdtype(frames.dtype, np.integer) or (np.issubdtype(frames.dtype, np.floating)
                                                             and np.all(frames == np.round(frames)))):
            # int() truncated timestamps in seconds (0.0, 0.5 -> 0, 0): the second frame was dropped as a repeat
            raise EvaluationInputError(f"FlickerMeter.update: frames must be integer frame indices in the scene "
                                       f"(0, 1, 2, ...), got {frames.tolist()!r:.80}")
        if poses.shape not in ((n, 4, 4), (n, 3, 4)) or not np.isfinite(poses).all():
            raise EvaluationInputError(f"FlickerMeter.update: poses must be one finite 4x4 (or 3x4) ego -> world "
                                       f"transform per sample, shape [{n}, 4, 4], got shape {list(poses.shape)}")
        if poses.shape[1] == 3:
            poses = np.concatenate([poses, np.broadcast_to([[[0.0, 0.0, 0.0, 1.0]]], (n, 1, 4))], axis=1)
        for b in range(n):
            key = (str(scenes[b]), int(frames[b]))
            if key in self.records:
                continue
            where = sample_name(b, key[0] + f" frame {key[1]}")
            p = _dicts(read_polylines(preds[b], role="prediction", num_classes=self.num_classes, where=where,
                                      short="drop"))
            g = _dicts(read_polylines(gts[b], role="GT", num_classes=self.num_classes, where=where, short="drop"))
            self.records[key] = {
                "detected": detected_gt(p, g, self.threshold_m, self.detect_points, self.score_threshold),
                "labels": np.array([x["label"] for x in g], dtype=np.int64),
                "pts": resample_polylines([x["pts"] for x in g], self.num_points),
                "pose": poses[b],
            }

    def state_dict(self) -> dict:
        return {"records": dict(self.records)}

    def merge(self, state: dict) -> None:
        for key, rec in state["records"].items():
            self.records.setdefault(key, rec)

    def gather(self) -> None:
        """Under torch.distributed: every rank ends with all records (a no-op otherwise)."""
        if not (torch.distributed.is_available() and torch.distributed.is_initialized()):
            return
        states: list[dict | None] = [None] * torch.distributed.get_world_size()
        torch.distributed.all_gather_object(states, self.state_dict())
        self.reset()
        for state in states:
            self.merge(state)

    def _links(self, prev: dict, cur: dict) -> list[tuple[int, int]]:
        """(instance of frame t, instance of frame t + 1) pairs that are one map element."""
        if not len(prev["labels"]) or not len(cur["labels"]):
            return []
        cur_to_prev = np.linalg.inv(prev["pose"]) @ cur["pose"]
        out = []
        for j in range(len(cur["labels"])):
            pts = cur["pts"][j] @ cur_to_prev[:2, :2].T + cur_to_prev[:2, 3]  # frame t+1 -> frame t (ground)
            shared = pts[self.grid.inside_m(pts)]
            if len(shared) < self.min_shared_points:
                continue
            best, best_i = math.inf, -1
            for i in np.flatnonzero(prev["labels"] == cur["labels"][j]):
                d = float(_point_to_polyline(shared, prev["pts"][i]).mean())
                if d < best:
                    best, best_i = d, int(i)
            if best <= self.link_m:
                out.append((best_i, j))
        return out

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
            for i, j in self._links(prev, cur):
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
