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
import numbers
from collections.abc import Mapping, Sequence

import numpy as np
import torch

from ..errors import as_batch_list, is_real
from ..geometry import BEVGrid
from .chamfer import chamfer_pairs
from .inputs import EvaluationInputError, check_grid, read_polylines
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
        if isinstance(classes, (str, bytes)) or (classes is not None and len(classes) != num_classes):
            raise EvaluationInputError(f"FlickerMeter: classes must name the num_classes = {num_classes} classes, "
                                       f"one name each, got {classes!r:.120}")
        self.grid, self.num_classes = grid, int(num_classes)
        self.classes = tuple(classes) if classes is not None else tuple(str(k) for k in range(num_classes))
        self.threshold_m, self.score_threshold = float(threshold_m), float(score_threshold)
        self.link_m, self.min_shared_points, self.num_points = float(link_m), int(min_shared_points), int(num_points)
        self.detect_points = int(detect_points)
        self.reset()

    def reset(self) -> None:
        self.records: dict[tuple[str, int], dict] = {}

    def update(self, preds: Sequence[Sequence[dict]], gts: Sequence[Sequence[dict]], scenes: Sequence[str],
               frames, poses) -> None:
        """B samples: polylines (metres, ego frame; predictions may be ``MapElement`` lists, what ``Mapper``
        returns), their scene names, frame indices [B] (integers >= 0) and ego poses [B, 4, 4] (tensors or
        arrays; finite rigid transforms [[R, t], [0, 0, 0, 1]], which compute inverts). A
        sample seen twice (streaming padding) counts once. A bad input is an ``EvaluationInputError`` naming
        the sample (scene, frame); nothing of the batch is kept then."""
        if isinstance(scenes, (str, bytes)):
            raise EvaluationInputError(f"FlickerMeter.update: scenes must be a list of B scene names, one per sample, "
                                       f"got one string {scenes!r:.80} (for one sample: [{scenes!r:.80}])")
        scenes = as_batch_list(scenes, "FlickerMeter.update: scenes", "a list of B scene names, one per sample",
                               EvaluationInputError)
        frames = as_batch_list(frames, "FlickerMeter.update: frames", "B frame indices (a list or a [B] tensor)",
                               EvaluationInputError)
        for name, value in (("preds", preds), ("gts", gts)):
            if isinstance(value, (dict, str, bytes)) or not isinstance(value, Sequence):
                raise EvaluationInputError(f"FlickerMeter.update: {name} must be a list of B samples, each a list "
                                           f"of polyline dicts, got {type(value).__name__}")
        try:
            poses = (poses.detach().cpu().double().numpy() if isinstance(poses, torch.Tensor)
                     else np.asarray(poses, dtype=np.float64))
        except (TypeError, ValueError):
            raise EvaluationInputError(f"FlickerMeter.update: poses must be B ego -> world transforms [B, 4, 4], "
                                       f"got {poses!r:.80}") from None
        counts = {"preds": len(preds), "gts": len(gts), "scenes": len(scenes), "frames": len(frames)}
        B = len(gts)
        if poses.shape == (4, 4) and B != 1:
            raise EvaluationInputError(f"FlickerMeter.update: poses is one [4, 4] pose for a batch of {B} samples; "
                                       "give one pose per sample, [B, 4, 4]")
        if poses.ndim == 3 and poses.shape[1:] == (3, 4):  # [R | t] without the last row (a 3x4 per sample)
            poses = np.concatenate([poses, np.broadcast_to([[[0.0, 0.0, 0.0, 1.0]]], (len(poses), 1, 4))], axis=1)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            if poses.shape != (4, 4):
                raise EvaluationInputError(f"FlickerMeter.update: poses must have shape [B, 4, 4] (ego -> world), "
                                           f"got {list(poses.shape)}")
            poses = poses[None]  # one sample's [4, 4]
        counts["poses"] = len(poses)
        if len(set(counts.values())) > 1:
            raise EvaluationInputError("FlickerMeter.update: one entry per sample in each argument, got "
                                       + ", ".join(f"{v} {k}" for k, v in counts.items()))
        keys = []
        for b in range(B):
            f = frames[b]
            if isinstance(f, (bool, np.bool_)) or not is_real(f) or not math.isfinite(f) or f != int(f) or f < 0:
                raise EvaluationInputError(f"FlickerMeter.update: sample {b} (scene '{scenes[b]}'): its frame index "
                                           f"must be an integer >= 0 (the frame's place in its scene), got {f!r}")
            keys.append((str(scenes[b]), int(f)))
        checked = []
        for b, key in enumerate(keys):
            where = f"sample (scene '{key[0]}', frame {key[1]})"
            if not np.isfinite(poses[b]).all():
                raise EvaluationInputError(f"{where}: its ego pose has NaN or infinite values; give a finite 4x4 "
                                           "ego -> world transform")
            if not np.allclose(poses[b][3], (0.0, 0.0, 0.0, 1.0), atol=1e-6) or abs(np.linalg.det(poses[b])) < 1e-9:
                raise EvaluationInputError(f"{where}: its ego pose is not a rigid transform [[R, t], [0, 0, 0, 1]] "
                                           f"(last row {poses[b][3].round(4).tolist()}, det "
                                           f"{np.linalg.det(poses[b]):.3g})")
            p = preds[b]
            if isinstance(p, Sequence) and not isinstance(p, (str, bytes)):
                p = [x.as_polyline() if hasattr(x, "as_polyline") and not isinstance(x, dict)  # MapElement
                     else dict(x, score=x.get("score", 1.0)) if isinstance(x, dict) else x for x in p]
            P = read_polylines(p, role="prediction", num_classes=self.num_classes, where=where, short="drop")
            G = read_polylines(gts[b], role="GT", num_classes=self.num_classes, where=where, short="drop")
            checked.append((P, G))
        for b, (key, (P, G)) in enumerate(zip(keys, checked)):
            if key in self.records:
                continue
            p = [{"pts": x, "label": int(k), "score": float(s)} for x, k, s in zip(P.pts, P.labels, P.scores)]
            g = [{"pts": x, "label": int(k)} for x, k in zip(G.pts, G.labels)]
            self.records[key] = {
                "detected": detected_gt(p, g, self.threshold_m, self.detect_points, self.score_threshold),
                "labels": G.labels.copy(),
                "pts": resample_polylines(G.pts, self.num_points),
                "pose": np.asarray(poses[b], dtype=np.float64),
            }

    def state_dict(self) -> dict:
        return {"records": dict(self.records)}

    def merge(self, state: dict) -> None:
        """Add another meter's ``state_dict()`` (a sample already here is kept once)."""
        records = state.get("records") if isinstance(state, Mapping) else None
        if isinstance(state, FlickerMeter) or not isinstance(records, Mapping) or not all(
                isinstance(k, tuple) and len(k) == 2 and isinstance(r, Mapping)
                and {"detected", "labels", "pts", "pose"} <= set(r) for k, r in records.items()):
            hint = "; pass other.state_dict()" if isinstance(state, FlickerMeter) else ""
            raise EvaluationInputError(
                "FlickerMeter.merge takes another FlickerMeter's state_dict() ({'records': {(scene, frame): ...}}), "
                f"got {type(state).__name__}{hint}")
        bad = [k for k, r in records.items()
               if len(r["labels"]) and not 0 <= int(np.max(r["labels"])) < self.num_classes]
        if bad:
            raise EvaluationInputError(f"FlickerMeter.merge: the state's sample (scene '{bad[0][0]}', frame "
                                       f"{bad[0][1]}) has class ids beyond this meter's {self.num_classes} classes "
                                       "(a state of a meter with other classes)")
        for key, rec in records.items():
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
