"""AP of a submission file against a GT file (``instagram-hdmap evaluate-json``), with the checks that the two
files share a frame (classes, patch, coordinate frame) and that their points lie in that patch.

    metrics = evaluate_files("pred.json", "gt.json", "raster")

Both files are in the HDMapNet format (evaluation/io.py); the scoring is ``Evaluator``'s (evaluation/evaluator.py).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..geometry import BEVGrid
from .evaluator import DEFAULT_RASTER_GRID, Evaluator
from .inputs import EvaluationInputError
from .io import SubmissionError, read_submission


def _meta_resolution(sub) -> float | None:
    """The grid resolution (metres per pixel) a submission's meta states (export-gt and evaluate write the config's
    ``grid.resolution``), or None."""
    r = sub.meta.get("resolution")
    if isinstance(r, bool) or not isinstance(r, (int, float)) or not (math.isfinite(r) and r > 0):
        return None
    return float(r)


def _patch(meta: dict, head: bool = False) -> tuple[float, float, float, float] | None:
    """The map patch (x0, x1, y0, y1) a file's meta states as ``xbound`` / ``ybound`` [min, max] (with ``head``: the
    first two values of each, HDMapNet's configs write [min, max, resolution]), or None."""
    try:
        bounds = [meta.get(k)[:2] if head else meta.get(k) for k in ("xbound", "ybound")]
        (x0, x1), (y0, y1) = ([float(v) for v in b] for b in bounds)
    except (TypeError, ValueError):
        return None
    return x0, x1, y0, y1


def _check_canvas(gt, grid: BEVGrid) -> None:
    """The raster canvas is the map patch the GT file's meta states (export-gt writes ``xbound`` /
    ``ybound``): a smaller canvas crops the map silently (a 100 m x 100 m GT scored on 60 m x 30 m), a larger one
    counts predictions beyond the patch (the message says which)."""
    patch = _patch(gt.meta)  # None: no patch stated (a GT file of another tool)
    if patch is None or patch == (grid.xmin, grid.xmax, grid.ymin, grid.ymax):
        return
    x0, x1, y0, y1 = patch
    crops = x0 < grid.xmin or x1 > grid.xmax or y0 < grid.ymin or y1 > grid.ymax
    why = ("which would crop it" if crops else  # a larger canvas: predictions beyond the patch would count
           "which would score predictions beyond the patch that the GT's own canvas leaves out")

    def tiles(r: float) -> bool:
        return all(abs(e / r - round(e / r)) < 1e-6 for e in (x1 - x0, y1 - y0))

    # the advice alone was refused next when the resolution does not tile that patch (16 m at 0.15 m); the GT's
    # own grid resolution first (export-gt states it): evaluate's raster AP of that config used it
    res = next((r for r in (_meta_resolution(gt), grid.resolution, 0.1, 0.125, 0.2, 0.25, 0.05)
                if r is not None and tiles(r)), None)
    also = f" --resolution {res:g}" if res is not None and res != grid.resolution else ""
    raise SubmissionError(f"{gt.path}: its meta says the map patch is xbound [{x0:g}, {x1:g}], ybound [{y0:g}, "
                          f"{y1:g}] but the raster canvas is [{grid.xmin:g}, {grid.xmax:g}] x [{grid.ymin:g}, "
                          f"{grid.ymax:g}], {why}: pass --xbound {x0:g} {x1:g} --ybound {y0:g} {y1:g}{also} (to "
                          "score another canvas on purpose, drop xbound/ybound from the GT file's meta)")


FRAME_META_KEYS = ("classes", "xbound", "ybound", "frame", "dataset")  # what the ids and coordinates mean


def _check_same_frame(pred, gt) -> None:
    """The prediction file is in the GT file's classes and frame: a meta key both files state (``classes``,
    ``xbound`` / ``ybound``, ``frame``, ``dataset``) agrees, and the predicted points lie mostly within twice
    the GT's map patch (the meta's, else the GT points' extent) and not all on [0, 1] (global coordinates,
    pixels, other units, coordinates normalised by the patch: AP 0 with no word otherwise)."""
    for key in FRAME_META_KEYS:
        a, b = pred.meta.get(key), gt.meta.get(key)
        if a is not None and b is not None and json.dumps(a) != json.dumps(b):
            try:
                a_, b_ = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
                shapes = {a_.shape, b_.shape}
                if key in ("xbound", "ybound") and shapes <= {(2,), (3,)} and (3,) in shapes:
                    # [min, max, resolution] (HDMapNet's configs) states the patch [min, max] (the raster's resolution
                    # is no part of the coordinates)
                    a_, b_ = a_[:2], b_[:2]
                if np.allclose(a_, b_):
                    continue
            except (TypeError, ValueError):
                pass
            raise SubmissionError(f"{pred.path}: its meta says {key} = {a!r}, the GT file {gt.path}'s says {b!r}: the "
                                  f"{'class ids' if key == 'classes' else 'coordinates'} mean other things; write the "
                                  "predictions in the GT's setting (or evaluate against a GT of theirs)")
    pts = [p["pts"] for polys in pred.samples.values() for p in polys]
    if not pts:
        return
    pts = np.concatenate(pts)
    patch = _patch(gt.meta)
    if patch is None:
        gts = [p["pts"] for polys in gt.samples.values() for p in polys]
        if not gts:
            return
        # no patch stated (a GT file of another tool): the GT points' extent, with room for a patch of tens of metres
        (x0, y0), (x1, y1) = np.concatenate(gts).min(0) - 30, np.concatenate(gts).max(0) + 30
        patch = x0, x1, y0, y1
    x0, x1, y0, y1 = patch
    w, h = x1 - x0, y1 - y0
    outside = _beyond(pts, patch, 0.5)
    if outside > 0.5:
        raise SubmissionError(f"{pred.path}: {outside:.0%} of its points lie outside twice the GT's map "
                              f"patch (x {x0:g}..{x1:g}, y {y0:g}..{y1:g} m): predictions in global coordinates, "
                              "pixels or another unit? points are metres in the ego frame")
    _check_within_patch(pred, gt)
    unit = [np.asarray(p["pts"], dtype=float) for name in pred.samples for p in gt.samples.get(name, [])]
    gt_unit = bool(unit) and bool(((np.concatenate(unit) >= 0) & (np.concatenate(unit) <= 1)).mean() >= 0.5)
    if len(pts) >= 10 and min(w, h) > 4 and ((pts >= 0) & (pts <= 1)).all() and not gt_unit:
        # (unless the GT of those samples lies there too: a small element near the ego, predicted well)
        raise SubmissionError(f"{pred.path}: every point lies in [0, 1] x [0, 1] on a GT map patch of {w:g} x {h:g} m: "
                              "coordinates normalised by the patch (MapTR's raw output)? points are metres in the "
                              "ego frame")


BEYOND_PATCH_SHARE = 0.2  # of a file's points beyond its patch (+10%): a valid file has ~none (both clip to it)


def _beyond(pts: np.ndarray, bounds: tuple[float, float, float, float], margin: float = 0.1) -> float:
    """The share of ``pts`` beyond the patch ``bounds`` (x0, x1, y0, y1) enlarged by ``margin`` of its size on each
    side."""
    x0, x1, y0, y1 = bounds
    mx, my = margin * (x1 - x0), margin * (y1 - y0)
    inside = (pts[:, 0] >= x0 - mx) & (pts[:, 0] <= x1 + mx) & (pts[:, 1] >= y0 - my) & (pts[:, 1] <= y1 + my)
    return float(1.0 - inside.mean())


def _check_within_patch(pred, gt) -> None:
    """Predictions and GT both lie within the map patch a file's meta states (the GT's, else the prediction's):
    the exporters clip to it. A file of another frame whose axes are swapped (MapTR's lidar frame: x right,
    y forward) lies within twice the patch but beyond it (AP 0 with no word otherwise)."""
    def bounds(sub):
        patch = _patch(sub.meta, head=True)
        return patch if patch is not None and patch[1] > patch[0] and patch[3] > patch[2] else None

    patch, stated_by = (bounds(gt), gt) if bounds(gt) is not None else (bounds(pred), pred)
    if patch is None:
        return
    for sub in (pred, gt):
        polys = [p["pts"] for polys in sub.samples.values() for p in polys if len(p["pts"])]
        if not polys:
            continue
        pts = np.concatenate(polys)
        share = _beyond(pts, patch)
        if share <= BEYOND_PATCH_SHARE:
            continue
        x0, x1, y0, y1 = patch
        swapped = _beyond(pts[:, ::-1], patch) < 0.05
        hint = ("its axes are another frame's: x right, y forward (MapTR's lidar frame)? points are x forward, y "
                "left: (x, y) -> (y, -x)" if swapped else
                f"{'predictions' if sub is pred else 'a GT'} of a larger patch, or another frame?")
        raise SubmissionError(f"{sub.path}: {share:.0%} of its points lie beyond the map patch {stated_by.path}'s "
                              f"meta states (x {x0:g}..{x1:g}, y {y0:g}..{y1:g} m), where the exporters clip them: "
                              f"{hint}")


def evaluate_files(pred_path: str | Path, gt_path: str | Path, protocol: str = "vector",
                   thresholds: Sequence[float] = (0.5, 1.0, 1.5), *, grid: BEVGrid | None = None,
                   rank_by: str = "ascending", fix_instance_ids: bool = False, device: str = "cpu",
                   ignore_extra_predictions: bool = False, progress: bool = False, chunk: int = 64) -> dict:
    """AP of the submission file ``pred_path`` against the GT file ``gt_path`` (both in the HDMapNet
    format, evaluation/io.py) under ``protocol`` (``instagram-hdmap evaluate-json``).

    The GT file's samples, in its order, are scored (``chunk`` at a time); a GT sample without
    predictions is scored as a sample without predictions (a note says how many). A prediction token
    that is not in the GT file is a ``SubmissionError`` unless ``ignore_extra_predictions``. Returns
    ``Evaluator.compute``'s metrics with ``notes`` (both files' and the evaluator's) and ``inputs``.
    """
    gt = read_submission(gt_path, "gt")
    pred = read_submission(pred_path, "pred")
    if gt.looks_like() == "pred" and not (gt.reference_gt() and pred.looks_like() != "gt"):
        # (a GT of the official exporters carries confidence_level 1 on every vector: a GT unless --pred is one)
        swapped = (f"; are --pred and --gt swapped? ({pred_path} looks like a GT file)"
                   if pred.looks_like() == "gt" else "; give the GT file of the split (instagram-hdmap export-gt)")
        raise SubmissionError(f"{gt_path}: given as the GT but it is a prediction file (meta.ground_truth false or "
                              f"confidence_level on {gt.confidences} vectors){swapped}")
    if not gt.samples:
        raise SubmissionError(f"{gt_path}: the GT file holds no samples")
    if protocol == "raster":
        _check_canvas(gt, grid if grid is not None else DEFAULT_RASTER_GRID)
    _check_same_frame(pred, gt)
    extra = [t for t in pred.samples if t not in gt.samples]
    if extra and not ignore_extra_predictions:
        raise SubmissionError(f"{pred_path}: {len(extra)} of {len(pred.samples)} sample tokens are not in the GT file "
                              f"{gt_path} (e.g. '{extra[0]}'); evaluate against the GT of the same split, or pass "
                              "--ignore-extra-predictions")
    missing = sum(t not in pred.samples for t in gt.samples)
    ev = Evaluator(protocol, thresholds, grid=grid, rank_by=rank_by, fix_instance_ids=fix_instance_ids,
                   device=device)
    tokens = list(gt.samples)  # the GT file's order is the pooling order
    try:
        for s in tqdm(range(0, len(tokens), chunk), desc=f"evaluate-json ({protocol})", unit="chunk",
                      disable=not progress):
            part = tokens[s : s + chunk]
            ev.update([pred.samples.get(t, []) for t in part], [gt.samples[t] for t in part],
                      sample_ids=range(s, s + len(part)), tokens=part)
    except EvaluationInputError as e:
        raise SubmissionError(f"evaluating {pred_path} against {gt_path}: {e}") from None
    metrics = ev.compute()
    notes = [*gt.notes, *pred.notes]
    if pred.meta.get("ground_truth") is True:  # export-gt's file given as --pred: a perfect score that said nothing
        same = Path(pred_path).resolve() == Path(gt_path).resolve()
        notes.insert(0, f"{pred_path} is a ground-truth file (meta.ground_truth true, as export-gt writes), "
                     f"{'the --gt file itself' if same else 'not a submission'}: these figures score the GT, not a "
                     "model; give evaluate's submission.json as --pred")
    if missing:
        notes.append(f"{missing} of {len(tokens)} GT samples have no entry in {pred_path}: scored as samples "
                     "without predictions")
    if extra:
        notes.append(f"{len(extra)} sample tokens only in {pred_path} were ignored (--ignore-extra-predictions)")
    stated = _meta_resolution(gt)
    used = (grid if grid is not None else DEFAULT_RASTER_GRID).resolution
    if protocol == "raster" and stated is not None and abs(stated - used) > 1e-9:
        # the raster AP depends on the pixel (5-px lines): evaluate of that config scored at its grid's resolution,
        # and the same predictions re-scored here at another gave another number with no word
        notes.append(f"{gt_path} was exported from a config whose grid has {stated:g} m pixels (evaluate's raster AP "
                     f"of that config used them); this raster canvas has {used:g} m pixels, so its AP differs: pass "
                     f"--resolution {stated:g} to reproduce evaluate's number")
    metrics["notes"] = notes + metrics["notes"]
    metrics["inputs"] = {"pred": str(pred_path), "gt": str(gt_path)}
    return metrics
