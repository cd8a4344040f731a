"""Read and write the HDMapNet submission JSON.

Format (x forward, y left, metres, ego frame)::

    {"meta": {...},
     "results": {sample_token: [{"pts": [[x, y], ...], "pts_num": n, "type": k,
                                 "confidence_level": s}, ...]}}

``confidence_level`` is absent in GT files (the official exporters' GT files carry 1 on every vector:
``Submission.reference_gt``). A UTF-8 byte-order mark is read; gzip and pickle files are named. Also
accepted: ``results`` as a list of ``{"sample_token", "vectors"}`` (InstaGraM's and MapTR's form), a dict
value ``{"vectors": [...]}``, and ``GTs`` instead of ``results`` (MapTR's GT file). Classes: 0 divider, 1 ped_crossing,
2 boundary. Rules:

* ``pts_num`` may be absent (= ``len(pts)``); if smaller than ``len(pts)`` only the first
  ``pts_num`` points are used (the HDMapNet reference's ``pts[:pts_num]``) and a note says how
  many; larger is an error.
* A prediction without ``confidence_level`` gets 1.0 (the HDMapNet reference's default) and a
  note says how many.
* Malformed JSON, a missing ``results``, a repeated sample token (in a dict ``results`` too: a key
  written twice in any object is an error, where Python's ``json`` keeps the last), coordinates
  that are not finite numbers of shape [P, 2] within ``MAX_COORD_M`` of the ego vehicle, a non-integer or
  unknown ``type``, a ``cls_name`` (MapTR's files) that is not the ``type``'s class, a ``confidence_level``
  outside [0, 1]: :class:`SubmissionError` naming the
  file, the token and the vector index.
* Polylines with fewer than two points are passed on; the evaluators apply each protocol's rule.
* ``track_id`` (optional; ``predict --scene`` and ``Mapper.stream()`` write it): the element's ID along its
  scene, an integer >= 0, kept as the polyline's ``track_id``. AP ignores it; the consistency-aware mAP
  (``benchmarks/cmap_of_submissions.py``) can score with it.

Every file is written as standard JSON (``files.write_json``): a NaN (the raster protocol's 0/0 cases in a metrics
file) is written as ``null``, and a non-finite score is refused (``null`` would read back as the default 1.0).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from ..config import MAP_CLASSES, UserError
from ..files import as_path, write_json

# Points are metres in the ego frame; a map patch spans tens of metres. Beyond this, the file is in
# another frame (global coordinates) or in other units, or broken (1e308 overflows the distances).
MAX_COORD_M = 1e4


_COUNTS = ("defaulted_confidence", "truncated", "confidences", "unit_confidences")  # what a reader counts


class SubmissionError(UserError, ValueError):
    """A submission / GT JSON file that cannot be read; the message names the file, token and index."""


class _RepeatedKey(Exception):
    def __init__(self, key: str):
        self.key = key


def _unique_keys(pairs: list[tuple[str, object]]) -> dict:
    """``json.load``'s ``object_pairs_hook``: an object with a key written twice (Python's json keeps the
    last one silently: a sample token twice in a dict ``results`` would lose the first one's vectors)."""
    out: dict = {}
    for key, value in pairs:
        if key in out:
            raise _RepeatedKey(key)
        out[key] = value
    return out


@dataclass
class Submission:
    path: str
    meta: dict
    samples: dict[str, list[dict]]  # token -> polyline dicts {"pts" [P, 2], "label"[, "score"]}, file order
    notes: list[str] = field(default_factory=list)
    confidences: int = 0  # vectors that carry a confidence_level (a GT file has none)
    unit_confidences: int = 0  # of those, the ones of exactly 1 (the official GT exports write 1 on every vector)

    def looks_like(self) -> Literal["pred", "gt"] | None:
        """What the file itself says it is: its ``meta.ground_truth`` flag, else whether its vectors
        carry confidences; None when it holds no vectors and no flag."""
        flag = self.meta.get("ground_truth")
        if isinstance(flag, bool):
            return "gt" if flag else "pred"
        if any(self.samples.values()):
            return "pred" if self.confidences else "gt"
        return None

    def reference_gt(self) -> bool:
        """A GT file of the official exporters (HDMapNet's and InstaGraM's ``export_gt_to_json.py``): no
        ``meta.ground_truth`` flag and ``confidence_level`` 1 on every vector."""
        n = sum(len(v) for v in self.samples.values())
        return "ground_truth" not in self.meta and n > 0 and self.confidences == self.unit_confidences == n


def read_submission(path: str | Path, role: Literal["pred", "gt"], num_classes: int = 3) -> Submission:
    """Read a submission (role "pred") or GT (role "gt") file into polyline dicts per token."""
    if role not in ("pred", "gt"):  # any other word was read as a GT: a prediction file's scores dropped, no word
        raise ValueError(f"read_submission: role must be 'pred' (a submission, with confidence_level) or 'gt', got "
                         f"{role!r}")
    path = as_path(path, "the submission file")
    if path.is_dir():  # evaluate's --out folder: the file in it is meant
        inside = [path / name for name in ("submission.json", "gt.json") if (path / name).is_file()]
        raise SubmissionError(f"{path}: is a folder, not a submission file" + (
            f"; the file in it: {inside[0]}" if inside else " (give the JSON file)"))
    try:
        with open(path, "rb") as f:  # read once: a pipe (`--pred /dev/stdin`, `<(zcat pred.json.gz)`) is read only once
            raw = f.read()
        kind = {b"\x1f\x8b": "gzip-compressed file (gunzip it)"}.get(raw[:2]) or (
            "Python pickle (mmcv.dump to .pkl; dump to .json)" if raw[:1] == b"\x80" else None)  # magic numbers
        if kind is not None:
            raise SubmissionError(f"{path}: a {kind}, not JSON; expected the HDMapNet submission format")
        # a byte-order mark (Windows editors) is not part of the JSON
        data = json.loads(raw.decode("utf-8-sig"), object_pairs_hook=_unique_keys)
    except FileNotFoundError:
        raise SubmissionError(f"{path}: no such file") from None
    except _RepeatedKey as e:
        raise SubmissionError(f"{path}: the key '{e.key}' appears twice in one JSON object (a sample token twice in "
                              "'results', or a field twice in one vector); Python's json would keep only the last one "
                              "and drop the first silently: merge them") from None
    except json.JSONDecodeError as e:
        raise SubmissionError(f"{path}: not valid JSON ({e}); expected the HDMapNet submission format") from None
    except (OSError, UnicodeDecodeError) as e:
        raise SubmissionError(f"{path}: cannot read ({e})") from None
    if not isinstance(data, dict):
        raise SubmissionError(f"{path}: expected a JSON object with 'meta' and 'results', got {type(data).__name__}")
    key = "results" if "results" in data else "GTs" if "GTs" in data else None
    if key is None:
        metrics = "mAP" in data or "AP" in data  # evaluate's metrics.json, written beside its submission.json
        raise SubmissionError(
            f"{path}: no 'results' key; expected {{'meta': {{...}}, 'results': {{token: [vectors]}}}}"
            + (f" (this is a metrics file; evaluate writes the submission as {path.parent / 'submission.json'})"
               if metrics else "")
        )
    results = data[key]
    meta = data.get("meta") if isinstance(data.get("meta"), dict) else {}
    if isinstance(results, dict):
        items = list(results.items())
    elif isinstance(results, list):
        items = []
        for i, entry in enumerate(results):
            if not isinstance(entry, dict) or "sample_token" not in entry or "vectors" not in entry:
                raise SubmissionError(f"{path}: {key}[{i}] must be a dict with 'sample_token' and 'vectors'")
            items.append((entry["sample_token"], entry["vectors"]))
    else:
        raise SubmissionError(f"{path}: '{key}' must be a dict token -> vectors or a list of "
                              f"{{'sample_token', 'vectors'}}, got {type(results).__name__}")
    samples: dict[str, list[dict]] = {}
    counts = dict.fromkeys(_COUNTS, 0)
    for token, vectors in items:
        if not isinstance(token, str):
            raise SubmissionError(f"{path}: sample token {token!r} is not a string")
        if token in samples:
            raise SubmissionError(f"{path}: sample token '{token}' appears twice")
        if isinstance(vectors, dict) and "vectors" in vectors:
            vectors = vectors["vectors"]
        samples[token] = vectors_to_polylines(vectors, role, num_classes, f"{path}: sample '{token}'", counts)
    notes = []
    if counts["defaulted_confidence"]:
        notes.append(f"{path}: {counts['defaulted_confidence']} predictions without 'confidence_level' scored 1.0 "
                     "(the HDMapNet reference's default)")
    if counts["truncated"]:
        notes.append(f"{path}: {counts['truncated']} vectors had pts_num < len(pts); the first pts_num points were "
                     "used")
    if role == "pred":
        notes += _tied_score_notes(path, samples)
    return Submission(str(path), meta, samples, notes, counts["confidences"], counts["unit_confidences"])


def _tied_score_notes(path: Path, samples: dict[str, list[dict]]) -> list[str]:
    """A class whose predictions all carry one score: their ranking, and so the AP, follows their order in the file
    (the same file reversed scored otherwise), where a score ranks them."""
    scores: dict[int, set[float]] = {}
    counts: dict[int, int] = {}
    for polys in samples.values():
        for p in polys:
            scores.setdefault(p["label"], set()).add(p["score"])
            counts[p["label"]] = counts.get(p["label"], 0) + 1
    notes = []
    for k in sorted(scores):
        if counts[k] > 1 and len(scores[k]) == 1:
            name = MAP_CLASSES[k] if k < len(MAP_CLASSES) else f"class {k}"
            notes.append(f"{path}: all {counts[k]} predictions of {name} have the same confidence_level "
                         f"{next(iter(scores[k])):g}: their ranking, and so the AP, follows their order in the file "
                         "(reordered, it scores otherwise); give each prediction its model's score")
    return notes


def _whole(value: object) -> object:
    """A whole float as the int it is (1.0, from numpy's float arrays or a MATLAB writer: class 1); else as given."""
    return int(value) if isinstance(value, float) and value.is_integer() else value


def vectors_to_polylines(vectors: object, role: Literal["pred", "gt"], num_classes: int, where: str,
                         counts: dict | None = None) -> list[dict]:
    """One sample's submission vectors -> polyline dicts, checked (see the module docstring); ``counts`` (the
    defaulted confidences, truncated vectors, confidences and confidences of 1) counted into."""
    counts = counts if counts is not None else dict.fromkeys(_COUNTS, 0)
    if not isinstance(vectors, list):
        raise SubmissionError(f"{where}: expected a list of vectors, got {type(vectors).__name__}")
    out = []
    for i, v in enumerate(vectors):
        what = f"{where}, vector {i}"
        if not isinstance(v, dict) or "pts" not in v or "type" not in v:
            raise SubmissionError(f"{what}: expected a dict with 'pts' and 'type', got {v!r:.120}")
        pts = _points(v["pts"], what)
        n = _whole(v.get("pts_num", len(pts)))
        if isinstance(n, bool) or not isinstance(n, int) or n < 0 or n > len(pts):
            raise SubmissionError(f"{what}: 'pts_num' must be an integer in 0..{len(pts)} (len(pts)), got {n!r}")
        if n < len(pts):
            counts["truncated"] += 1
            pts = pts[:n]
        k = _whole(v["type"])
        if isinstance(k, bool) or not isinstance(k, int) or not 0 <= k < num_classes:
            raise SubmissionError(f"{what}: 'type' must be a class id 0..{num_classes - 1} "
                                  f"(0 divider, 1 ped_crossing, 2 boundary), got {k!r}")
        name = v.get("cls_name")  # MapTR writes the class name beside its id: they must agree
        if name is not None and (k >= len(MAP_CLASSES) or name != MAP_CLASSES[k]):
            raise SubmissionError(f"{what}: 'cls_name' {name!r} disagrees with 'type' {k} (the class ids are 0 "
                                  "divider, 1 ped_crossing, 2 boundary, MapTR's order; StreamMapNet numbers "
                                  "ped_crossing 0, divider 1): renumber 'type'")
        poly = {"pts": pts, "label": k}
        s = v.get("confidence_level")
        counts["confidences"] += "confidence_level" in v
        counts["unit_confidences"] += s == 1 and not isinstance(s, bool)
        if role == "pred":
            if s is None:
                counts["defaulted_confidence"] += 1
                s = 1.0
            if isinstance(s, bool) or not isinstance(s, (int, float)) or not math.isfinite(s):
                raise SubmissionError(f"{what}: 'confidence_level' must be a finite number, got {s!r}")
            if not -1e-6 <= s <= 1 + 1e-6:  # a probability (to float32 rounding)
                raise SubmissionError(f"{what}: 'confidence_level' must be a probability in [0, 1], got {s!r} "
                                      "(rescale the scores, e.g. with a sigmoid, before writing them)")
            poly["score"] = float(s)
        track = _whole(v.get("track_id"))
        if track is not None:  # a tracked stream's element ID: kept for consistency meters, AP ignores it
            if isinstance(track, bool) or not isinstance(track, int) or track < 0:
                raise SubmissionError(f"{what}: 'track_id' must be an integer >= 0 (the element's ID along its scene), "
                                      f"got {track!r}")
            poly["track_id"] = track
        out.append(poly)
    return out


def _points(raw: object, what: str) -> np.ndarray:
    try:
        pts = np.asarray(raw, dtype=np.float64)
    except (TypeError, ValueError):
        raise SubmissionError(f"{what}: 'pts' must be a list of [x, y] numbers") from None
    if pts.size == 0:
        return pts.reshape(0, 2)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise SubmissionError(f"{what}: 'pts' must be a list of [x, y] pairs, got shape {pts.shape}")
    if not np.isfinite(pts).all():
        raise SubmissionError(f"{what}: 'pts' contains NaN or infinite coordinates")
    if np.abs(pts).max() > MAX_COORD_M:
        raise SubmissionError(f"{what}: 'pts' has a coordinate of {np.abs(pts).max():.6g}; points are metres in the "
                              f"ego frame (|x|, |y| <= {MAX_COORD_M:g}): is the file in global coordinates or "
                              "another unit?")
    return pts


def polylines_to_vectors(polylines: list[dict]) -> list[dict]:
    """Polyline dicts (or ``MapElement`` objects) -> submission vectors (``confidence_level`` from "score" when
    present)."""
    out = []
    for p in polylines:
        if hasattr(p, "as_polyline"):  # a MapElement (mapper.py), what Mapper returns
            p = p.as_polyline()
        pts = np.asarray(p["pts"], dtype=np.float64)
        v = {"pts": pts.tolist(), "pts_num": len(pts), "type": int(p["label"])}
        if "score" in p:
            v["confidence_level"] = float(p["score"])
            if not math.isfinite(v["confidence_level"]):  # JSON has no NaN: null would read back as the default 1.0
                raise ValueError(f"a polyline's score is {v['confidence_level']} (class {v['type']}, {len(pts)} "
                                 "points); scores must be finite (a diverged model?)")
        if p.get("track_id") is not None:
            v["track_id"] = int(p["track_id"])
        out.append(v)
    return out


def submission(samples: Mapping[str, list[dict]], meta: dict | None = None) -> dict:
    """Polyline dicts per token -> the submission document ``{"meta", "results": {token: vectors}}``."""
    if not isinstance(samples, Mapping):
        got = ("a path (the arguments are (path, samples))" if isinstance(samples, (str, Path))
               else f"a {type(samples).__name__}")
        raise TypeError(f"a submission takes {{sample token: polylines}}, got {got}; the tokens are the GT's sample "
                        "tokens")
    for token, polys in samples.items():
        if not isinstance(token, (str, int, np.integer)) or isinstance(token, bool):
            # json.dump's "keys must be str, int, float, bool or None, not tuple", or a token the GT never matches
            raise TypeError(f"a submission's sample tokens are strings, got {token!r} ({type(token).__name__})")
        if isinstance(polys, (Mapping, str, bytes)) or not isinstance(polys, (list, tuple)):
            raise TypeError(f"sample {token!r}: expected a list of polyline dicts (pts, label, score) or MapElement "
                            f"objects, got {type(polys).__name__}")
        bad = next((p for p in polys if not (isinstance(p, Mapping) or hasattr(p, "as_polyline"))), None)
        if bad is not None:
            raise TypeError(f"sample {token!r}: expected polyline dicts (pts, label, score) or MapElement objects, "
                            f"got {type(bad).__name__} in the list")
    if meta is not None and not isinstance(meta, Mapping):  # ** of it: a raw "'str' object is not a mapping"
        raise TypeError(f"a submission's meta is a dict of its settings (e.g. {{'split': 'val'}}), got "
                        f"{type(meta).__name__} {meta!r:.60}")
    results = {}
    for token, polys in samples.items():
        try:
            results[str(token)] = polylines_to_vectors(polys)
        except ValueError as e:
            raise ValueError(f"sample {token!r}: {e}") from None
    return {"meta": {"vector": True, **(meta or {})}, "results": results}


def write_submission(path: str | Path, samples: Mapping[str, list[dict]], meta: dict | None = None) -> None:
    """Write polyline dicts per token in the submission format (``results`` as a dict)."""
    write_json(submission(samples, meta), path)
