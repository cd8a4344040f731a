"""Streaming AP evaluation under either protocol, DDP-aware.

    ev = Evaluator("vector", thresholds=(0.5, 1.0, 1.5))
    for batch in loader:
        ev.update(pred_polylines, gt_polylines, sample_ids=batch_indices, tokens=batch_tokens)
    ev.gather()                      # under torchrun: every rank ends with the merged state
    metrics = ev.compute()           # {"protocol", "thresholds", "classes", "AP", "AP_class", "mAP", ...}

Memory stays bounded over any number of samples: the vector protocol keeps one (sample id,
score, TP flags) record per detection, the raster protocol per-class sums of per-sample APs.
``sample_ids`` (dataset indices) make the vector protocol's pooled order -- and so its handling
of tied scores -- independent of how the samples were split over updates and processes.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from ..config import ExperimentConfig, as_config
from ..geometry import BEVGrid
from .inputs import EvaluationInputError, Samples, check_grid, gather_states
from .raster_ap import THICKNESS, RasterAP
from .vector_ap import VectorAP

DEFAULT_RASTER_GRID = BEVGrid(-30.0, 30.0, -15.0, 15.0, 0.15)  # the paper's 60 m x 30 m patch at 0.15 m

CLASSES = ("divider", "ped_crossing", "boundary")
PROTOCOLS = ("vector", "raster")
DESCRIPTIONS = {
    "vector": "MapTR vector Chamfer AP: 100-point resampling, 2 m buffer pre-filter, D <= thr, nearest GT only, "
    "dataset-level PR, VOC area AP; mAP counts classes without GT as 0",
    "raster": "HDMapNet/InstaGraM raster instance AP: 5-px masks at the grid resolution, pixel-cloud Chamfer < thr, "
    "greedy matching by distance, per-sample 10-point AP averaged over samples",
}


MAX_THRESHOLD_M = 10.0  # a map patch spans 30-60 m: a Chamfer threshold beyond this matches anything nearby


def check_thresholds(thresholds: Sequence[float]) -> tuple[float, ...]:
    """Thresholds in metres: a non-empty list of finite numbers > 0 (one number: that one threshold)."""
    if isinstance(thresholds, (int, float, np.integer, np.floating)) and not isinstance(thresholds, bool):
        thresholds = (thresholds,)
    try:
        out = tuple(float(t) for t in thresholds)
    except (TypeError, ValueError):
        raise EvaluationInputError(f"thresholds must be numbers in metres, got {thresholds!r}") from None
    if not out:
        raise EvaluationInputError("thresholds: give at least one Chamfer threshold in metres, e.g. 0.5 1.0 1.5")
    bad = [t for t in out if not (math.isfinite(t) and t > 0)]
    if bad:
        raise EvaluationInputError(f"thresholds must be finite and > 0 metres; got {bad}")
    if max(out) > MAX_THRESHOLD_M:  # 50 100 150 (centimetres): every element metres away a true positive, AP ~1
        raise EvaluationInputError(f"thresholds are Chamfer distances in metres (the protocols: 0.5 1.0 1.5); "
                                   f"{max(out):g} m would match elements that far apart: centimetres given? at most "
                                   f"{MAX_THRESHOLD_M:g} m")
    if len(set(out)) != len(out):  # mAP averages over them: one given twice would count twice
        raise EvaluationInputError(f"thresholds: {list(out)} lists a threshold twice, which mAP (their mean) would "
                                   "count twice; give each once")
    return out


def check_classes(classes: Sequence[str]) -> tuple[str, ...]:
    """Class names: a non-empty list of distinct strings (one string would be read as its characters: an
    evaluator of the classes 'd', 'i', 'v', ...)."""
    if isinstance(classes, (str, bytes)) or not isinstance(classes, (Sequence, np.ndarray)):
        raise EvaluationInputError(f"classes must be a list of class names, e.g. ('divider', 'ped_crossing', "
                                   f"'boundary') or ('divider',), got {classes!r:.80}")
    out = tuple(classes)
    if not out or not all(isinstance(c, str) and c for c in out):
        raise EvaluationInputError(f"classes must be a non-empty list of class names (strings), got {list(out)!r:.120}")
    if len(set(out)) != len(out):
        raise EvaluationInputError(f"classes: {list(out)} names a class twice; labels index this list, so each "
                                   "class must appear once")
    return out


# The notes of the counters (those a protocol has), in this order, when not 0.
COUNTER_NOTES = {
    "repeated_samples": "{} samples handed again (data.on_bad_sample=skip puts the next good sample in place of a "
                        "bad one) were scored once",
    "samples_in_two_merged_states": "{} samples were in two merged states (two processes scored them: "
                                    "data.on_bad_sample=skip's replacement, or overlapping shares) and count twice",
    "samples_without_predictions": "{} samples have no predictions (scored as such)",
    "dropped_short_predictions": "{} predictions with fewer than 2 points dropped (as the reference does)",
    "zero_length_predictions": "{} zero-length predictions (all points equal): their buffer is empty, so they are "
                               "always false positives (as in the reference)",
    "dropped_short_gt": "{} GT polylines with fewer than 2 points dropped (as the reference does)",
}


def _samples(value, what: str, who: str = "Evaluator.update") -> list:
    """``preds`` / ``gts`` of ``Evaluator.update``: one list of polylines per sample, as a list (any iterable
    of them: a generator too). A dict {token: polylines} is named: its order and tokens belong in ``tokens``."""
    if isinstance(value, Mapping):
        raise EvaluationInputError(f"{who} takes {what} as one list of polylines per sample, in order, "
                                   "not a dict; for {token: polylines} pass [d[t] for t in tokens] with "
                                   "tokens=tokens")
    if value is None or isinstance(value, (str, bytes)) or not isinstance(value, Iterable):
        raise EvaluationInputError(f"{who} takes {what} as one list of polylines per sample, got "
                                   f"{type(value).__name__}")
    return list(value)


class Evaluator:
    """AP under the ``vector`` (MapTR, default) or ``raster`` (HDMapNet/InstaGraM) protocol.

    Args:
        protocol: "vector" or "raster".
        thresholds: Chamfer thresholds in metres.
        classes: class names, K of them; polyline labels index this tuple.
        grid: BEV grid of the raster protocol's canvas (default: 60 m x 30 m at 0.15 m).
        rank_by: raster only; "ascending" reproduces the reference's PR curve built in ascending
            confidence order (its bug), "descending" fixes it.
        fix_instance_ids: raster only; int32 instance masks and each instance's own confidence
            instead of the reference's misaligned list and uint8 ids.
        num_sample_points, resample_predictions: vector only; MapTR's 100 points and its
            ``eval_use_same_gt_sample_num_flag`` (True in every MapTR config).
        device: raster only; where ``torch.cdist`` runs.
        also: protocols computed as well on the same predictions (``eval.also_protocols``), with the
            same options; ``compute()`` reports each under ``metrics["also"][protocol]``.
    """

    def __init__(self, protocol: Literal["vector", "raster"] = "vector", thresholds: Sequence[float] = (0.5, 1.0, 1.5),
                 classes: Sequence[str] = CLASSES, *, grid: BEVGrid | None = None,
                 rank_by: Literal["ascending", "descending"] = "ascending", fix_instance_ids: bool = False,
                 num_sample_points: int = 100, resample_predictions: bool = True, device: str | torch.device = "cpu",
                 also: Sequence[str] = ()) -> None:
        if protocol not in PROTOCOLS:
            raise EvaluationInputError(f"unknown evaluation protocol {protocol!r}; choose one of {PROTOCOLS}")
        self.also = {
            p: Evaluator(p, thresholds, classes, grid=grid, rank_by=rank_by, fix_instance_ids=fix_instance_ids,
                         num_sample_points=num_sample_points, resample_predictions=resample_predictions,
                         device=device)
            for p in dict.fromkeys(also) if p != protocol
        }
        self.protocol = protocol
        self.thresholds = check_thresholds(thresholds)
        self.classes = check_classes(classes)
        self._seen: set[str] = set()  # tokens scored so far (update)
        self.repeated = 0  # samples handed again and not scored twice
        self.in_two_states = 0  # samples of merged states that another merged state held too (scored twice)
        if protocol == "vector":
            self.impl: VectorAP | RasterAP = VectorAP(self.thresholds, len(self.classes), num_sample_points,
                                                      resample_predictions)
            self.options = {"num_sample_points": num_sample_points, "resample_predictions": resample_predictions}
        else:
            grid = check_grid(grid, "Evaluator") if grid is not None else DEFAULT_RASTER_GRID
            self.impl = RasterAP(self.thresholds, grid, len(self.classes), rank_by, fix_instance_ids, device=device)
            self.options = {"rank_by": rank_by, "fix_instance_ids": fix_instance_ids, "thickness_px": THICKNESS,
                            "grid": {"xbound": [grid.xmin, grid.xmax], "ybound": [grid.ymin, grid.ymax],
                                     "resolution": grid.resolution}}

    @classmethod
    def from_config(cls, cfg: ExperimentConfig | str | Path, device: str | torch.device = "cpu") -> Evaluator:
        """The evaluator a config's ``eval`` section describes (``cfg``: an ``ExperimentConfig`` or a YAML file)."""
        cfg = as_config(cfg, "Evaluator.from_config")
        ev = cfg.eval
        return cls(ev.protocol, ev.thresholds, cfg.data.classes, grid=BEVGrid.from_config(cfg.grid),
                   rank_by=ev.rank_by, fix_instance_ids=ev.fix_instance_ids, device=device, also=ev.also_protocols)

    # --- accumulation ------------------------------------------------------------------------
    def update(self, preds: Samples, gts: Samples, sample_ids: Sequence[int] | None = None,
               tokens: Sequence[str] | None = None) -> None:
        """Add B samples: ``preds[b]`` polyline dicts with "pts" [P, 2] metres, "label", "score";
        ``gts[b]`` the same without "score". Errors name the token (or sample id) and index.

        A token seen before (in this process) is not scored again: with ``data.on_bad_sample=skip`` a
        loader hands the next good sample in place of a bad one, which must not count twice; the
        repeats are counted (``counters["repeated_samples"]``, a note)."""
        preds, gts = _samples(preds, "predictions"), _samples(gts, "GT")
        if len(gts) != len(preds):
            raise EvaluationInputError(f"{self.protocol} AP update: {len(preds)} prediction lists but {len(gts)} GT "
                                       "lists")
        if isinstance(tokens, (str, bytes)):  # one token: its characters would be B tokens
            raise EvaluationInputError(f"{self.protocol} AP update: tokens must be a list of one token per sample, "
                                       f"got the string {tokens!r:.60}")
        if sample_ids is not None:
            sample_ids = list(sample_ids)
        if tokens is not None:
            tokens = list(tokens)  # a numpy array or a pandas column of tokens, too
            if len(tokens) != len(preds):
                raise EvaluationInputError(f"{self.protocol} AP update: {len(tokens)} tokens for {len(preds)} samples "
                                           "of predictions; give one token per sample")
            keep = [b for b, t in enumerate(tokens) if t not in self._seen and t not in tokens[:b]]
            self.repeated += len(tokens) - len(keep)
            if len(keep) < len(tokens):
                preds, gts, tokens = [preds[b] for b in keep], [gts[b] for b in keep], [tokens[b] for b in keep]
                sample_ids = None if sample_ids is None else [sample_ids[b] for b in keep]
            self._seen.update(tokens)
            if not tokens:
                return
        self.impl.update(preds, gts, sample_ids=sample_ids, tokens=tokens)
        for ev in self.also.values():
            ev.update(preds, gts, sample_ids=sample_ids, tokens=tokens)

    def reset(self) -> None:
        self.impl.reset()
        self._seen, self.repeated, self.in_two_states = set(), 0, 0
        for ev in self.also.values():
            ev.reset()

    def state_dict(self) -> dict:
        """Picklable accumulated state (NumPy arrays and numbers); the ``also`` protocols' under "also"."""
        state = {**self.impl.state_dict(), "classes": list(self.classes), "tokens": sorted(self._seen)}
        if self.also:
            state = {**state, "also": {p: ev.state_dict() for p, ev in self.also.items()}}
        return state

    def merge(self, state: dict) -> None:
        """Add another evaluator's ``state_dict()`` (e.g. from another process) to this one (an ``Evaluator``
        itself is taken as its state)."""
        if isinstance(state, Evaluator):
            state = state.state_dict()
        if not isinstance(state, Mapping):
            raise EvaluationInputError(f"Evaluator.merge takes another evaluator's state_dict() (or the evaluator), "
                                       f"got {type(state).__name__}")
        state = dict(state)
        also = state.pop("also", {})
        # a state of other classes: numpy's raw "operands could not be broadcast" (another count), or its AP
        # added to the wrong class (the same count, other names)
        names, num_gt = state.pop("classes", None), state.get("num_gt")
        if (names is not None and list(names) != list(self.classes)) or \
                (num_gt is not None and len(num_gt) != len(self.classes)):
            theirs = ", ".join(map(str, names)) if names is not None else f"{len(num_gt)} classes"
            raise EvaluationInputError(f"cannot merge an evaluation state of the classes {theirs} into an evaluator of "
                                       f"the classes {', '.join(self.classes)}; merge states of the same classes")
        tokens = set(state.pop("tokens", None) or ())
        if tokens and tokens <= self._seen:  # the same state merged twice: every AP count doubled, no word
            raise EvaluationInputError(f"Evaluator.merge: every one of this state's {len(tokens)} sample tokens is "
                                       "already in the evaluator (the same state merged twice?); merge each "
                                       "process's state once")
        self.impl.merge_state(state)
        self.in_two_states += len(tokens & self._seen)
        self._seen.update(tokens)
        for p, ev in self.also.items():
            ev.merge(also[p])

    def gather(self) -> None:
        """Under torch.distributed: every rank ends with the whole dataset's state (``inputs.gather_states``;
        compute and log on rank 0)."""
        gather_states(self)

    # --- result ------------------------------------------------------------------------------
    def compute(self) -> dict:
        """Metrics dict (JSON-ready; NaN where the protocol yields NaN):
        ``protocol``, ``protocol_description``, ``thresholds``, ``classes``, ``AP`` (class -> list
        per threshold), ``AP_class`` (class -> mean over thresholds), ``mAP``, ``num_gt``,
        ``num_pred``, ``counters``, ``options``, ``notes``; ``also`` (protocol -> the same dict) when
        other protocols were computed as well."""
        res = self.impl.compute()
        ap = np.asarray(res["AP"], dtype=np.float64)  # [K, T]
        ap_class = ap.mean(1)  # vector: nuscenes_map_dataset.py:1420; raster: evaluate_json.py:85
        # vector: :1422, the mean of the class means, classes without GT counting 0; raster: :86, the mean of the
        # matrix, NaN if any class is NaN
        m_ap = float(ap_class.mean() if self.protocol == "vector" else ap.mean())
        counters = {**self.impl.counters, "repeated_samples": self.repeated}
        if self.in_two_states:
            counters["samples_in_two_merged_states"] = self.in_two_states
        out = {
            "protocol": self.protocol,
            "protocol_description": DESCRIPTIONS[self.protocol],
            "thresholds": list(self.thresholds),
            "classes": list(self.classes),
            "AP": {c: [float(v) for v in ap[k]] for k, c in enumerate(self.classes)},
            "AP_class": {c: float(ap_class[k]) for k, c in enumerate(self.classes)},
            "mAP": m_ap,
            "num_gt": {c: int(res["num_gt"][k]) for k, c in enumerate(self.classes)},
            "num_pred": {c: int(res["num_pred"][k]) for k, c in enumerate(self.classes)},
            "counters": counters,
            "options": dict(self.options),
            "notes": self._notes(res, counters),
        }
        if self.protocol == "vector":
            with_gt = [k for k in range(len(self.classes)) if res["num_gt"][k] > 0]
            # The other "mAP" of MapTR's logs (eval_map's table, mean_ap.py:316-320), per threshold
            # averaged: classes without GT left out. Not the reported number.
            out["mAP_classes_with_gt"] = float(ap_class[with_gt].mean()) if with_gt else 0.0
        else:
            out["samples_counted"] = {c: int(res["count"][k]) for k, c in enumerate(self.classes)}
        if self.also:
            out["also"] = {p: ev.compute() for p, ev in self.also.items()}
        return out

    def _notes(self, res: dict, counters: dict) -> list[str]:
        notes = [f"{counters['samples']} samples evaluated"]
        notes += [note.format(counters[key]) for key, note in COUNTER_NOTES.items() if counters.get(key)]
        vector = self.protocol == "vector"
        empty = res["num_gt"] if vector else res["count"]  # the classes whose AP the protocol's rule sets
        rule = ("class {} has no GT: its AP is 0 and still averaged into mAP (MapTR's rule); see mAP_classes_with_gt"
                if vector else "class {} has neither GT nor predictions in any sample: AP is NaN (0/0) and so is mAP "
                "(the reference's rule)")
        notes += [rule.format(c) for k, c in enumerate(self.classes) if empty[k] == 0]
        if not vector and self.options["rank_by"] == "ascending":
            notes.append("PR curves ranked by ASCENDING confidence, as the reference (and the InstaGraM paper's "
                         "numbers) did; rank_by='descending' fixes it")
        return notes


def format_table(metrics: dict) -> str:
    """Plain-text table: one row per class (AP per threshold, AP_class), then mAP and the protocol.
    ``metrics``: ``Evaluator.compute()``'s dict (an ``Evaluator`` is computed)."""
    if isinstance(metrics, Evaluator):
        metrics = metrics.compute()
    need = ("protocol", "protocol_description", "thresholds", "classes", "AP", "AP_class", "mAP")
    if not isinstance(metrics, Mapping) or any(k not in metrics for k in need):
        got = (f"a dict without {', '.join(k for k in need if k not in metrics)}" if isinstance(metrics, Mapping)
               else type(metrics).__name__)
        raise EvaluationInputError(f"format_table takes the metrics of Evaluator.compute() (or evaluate-json's "
                                   f"metrics.json), got {got}")
    thr = metrics["thresholds"]
    head = f"{'class':<14}" + "".join(f"{'AP@' + format(t, 'g'):>10}" for t in thr) + f"{'AP_class':>10}"
    lines = [f"protocol: {metrics['protocol']} ({metrics['protocol_description']})", head, "-" * len(head)]
    for c in metrics["classes"]:
        lines.append(f"{c:<14}" + "".join(f"{v:>10.4f}" for v in metrics["AP"][c]) + f"{metrics['AP_class'][c]:>10.4f}")
    lines.append("-" * len(head))
    lines.append(f"{'mAP':<14}" + " " * (10 * len(thr)) + f"{metrics['mAP']:>10.4f}")
    for other in metrics.get("also", {}).values():
        lines += ["", "also computed on the same predictions:", format_table(other)]
    return "\n".join(lines)
