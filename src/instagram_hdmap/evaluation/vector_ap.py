"""The ``vector`` protocol: MapTR's Chamfer AP, number for number (EVAL_PROTOCOLS.md, Protocol A).

What the reference (MapTR ``a6872d8``, ``map_utils/{mean_ap,tpfp,tpfp_chamfer}.py``) does, and
what this module reproduces:

1. Resampling: every GT polyline to 100 points equally spaced in arc length, both ends
   included (``np.linspace(0, L, 100)`` + ``LineString.interpolate``); predictions likewise
   unless they already have exactly 100 points (then their raw points are used).
   :func:`resample_polylines` gives GEOS's interpolated coordinates bit for bit.
2. Chamfer ``D = (mean_p min_g |p-g| + mean_g min_p |p-g|) / 2`` between the 100-point sets, but
   only for pairs whose 2 m buffers (flat caps, mitre joins) intersect; others get ``D = 100``.
3. Per sample and class: detections by descending score (``np.argsort(-score)``); each is
   compared with its nearest GT only (first one on ties); TP if ``D <= thr`` (inclusive) and
   that GT is still free, else FP -- no fallback to the second-nearest GT. No GT: all FP.
4. Per class, all samples pooled in sample order, sorted by ``np.argsort(-score)`` (NumPy's
   default, non-stable: ties are ordered as the reference orders them for the same input);
   cumulative TP/FP; recall ``TP / max(num_gt, eps)``, precision ``TP / max(TP + FP, eps)`` in
   float32; AP = area under the VOC2010 all-points envelope.
5. Per class mean over the thresholds; mAP = mean over the classes, a class without GT counting
   as AP 0 (what MapTR's ``_evaluate_single`` reports).

Quirks reproduced (documented, not bugs to fix): the no-fallback rule; zero-length predictions
(all points equal) have an empty buffer and are always false positives; zero-length GT is never
matched but counts in ``num_gt``; predictions with < 2 points are dropped (counted in the
notes); a GT with < 2 points is an error (the reference crashes).

Speed without changing a single decision: only pairs that can be a detection's *nearest GT
within the largest threshold* matter. Pairs are pruned with exact lower bounds on D (bounding
box gap, mean point-to-box distance); D is computed exactly for the rest; the buffer test runs
only on pairs with ``D <= max(thresholds)``, through a cheap sufficient condition with a
margin, and shapely (the same GEOS buffers as the reference) for the undecided remainder.
Thresholds must be below 100 m: at or above it the reference's ``D = 100`` placeholder for
non-intersecting pairs would itself count as a match.

Shapes: L polylines, S = ``num_sample_points`` (100), R pairs, T thresholds, K classes.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import shapely

from .chamfer import chamfer_pairs, mean_dist_to_box
from .inputs import SAMPLE_COUNTERS, EvaluationInputError, Samples, check_state, concat, read_sample, sample_name

NUM_SAMPLE_POINTS = 100  # mean_ap.py:147
BUFFER_WIDTH = 2.0  # tpfp.py:59 passes linewidth=2. as the buffer distance
MITRE_LIMIT = 5.0  # shapely's default, used by the reference's buffer call
UNMEASURED = 100.0  # tpfp_chamfer.py:40: D of a pair whose buffers do not intersect

# Margins of the sufficient buffer-intersection test (see buffers_intersect). GEOS simplifies the
# buffer input by 1 % of the distance (2 cm) and bevels mitres beyond the limit; these margins are
# an order of magnitude larger than any such effect.
_PERP_MARGIN = 0.2  # metres inside the buffer edge
_END_MARGIN = 1.0  # metres (arc length) away from either end of the line (its flat caps)
_MIN_WITNESS_LENGTH = 0.05  # lines shorter than this are always left to shapely


# ---------------------------------------------------------------------------------------------
# Geometry
# ---------------------------------------------------------------------------------------------


def polyline_lengths(x: np.ndarray) -> np.ndarray:
    """[R, P, 2] -> [R] lengths, summed segment by segment in order (GEOS ``Length::ofLine``), each segment
    ``sqrt(dx*dx + dy*dy)`` as GEOS."""
    if x.shape[1] < 2:
        return np.zeros(len(x))
    d = x[:, 1:] - x[:, :-1]
    return np.cumsum(np.sqrt(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1]), axis=1)[:, -1]


def resample_polylines(lines: Sequence[np.ndarray], num_points: int = NUM_SAMPLE_POINTS) -> np.ndarray:
    """Resample polylines to ``num_points`` points equally spaced in arc length, ends included.

    The same coordinates, bit for bit, as the reference's
    ``[LineString(l).interpolate(d) for d in np.linspace(0, LineString(l).length, num_points)]``:
    GEOS walks the segments with a running length sum, picks the first segment whose end lies
    strictly beyond ``d``, and interpolates ``(p1 - p0) * frac + p0``.

    Args:
        lines: L arrays [P_i, 2] float64 with P_i >= 2.
    Returns:
        [L, num_points, 2] float64.
    """
    L = len(lines)
    if L == 0:
        return np.zeros((0, num_points, 2))
    counts = np.fromiter((len(p) for p in lines), dtype=np.int64, count=L)
    flat = np.concatenate(lines).astype(np.float64, copy=False)
    starts = np.cumsum(counts) - counts
    Pmax = int(counts.max())
    # Pad every line with copies of its last point: zero-length segments change neither the
    # running sums nor which segment is picked.
    idx = starts[:, None] + np.minimum(np.arange(Pmax)[None], counts[:, None] - 1)
    xs, ys = flat[idx, 0], flat[idx, 1]  # [L, Pmax] each
    dx, dy = xs[:, 1:] - xs[:, :-1], ys[:, 1:] - ys[:, :-1]
    seg_len = np.sqrt(dx * dx + dy * dy)  # [L, Pmax-1], sqrt(dx*dx + dy*dy) as GEOS
    cum_end = np.cumsum(seg_len, axis=1)  # running sum after each segment, as GEOS accumulates it
    total = cum_end[:, -1]
    # np.linspace(0, total, n): k * (total / (n - 1)), last element set to total exactly.
    dist = np.arange(num_points, dtype=np.float64)[None] * (total[:, None] / (num_points - 1))
    dist[:, -1] = total
    # First segment whose running end exceeds d (GEOS: totalLength + segLen > length).
    seg = np.empty((L, num_points), dtype=np.int64)
    for i in range(L):
        seg[i] = np.searchsorted(cum_end[i], dist[i], side="right")
    past_end = seg >= Pmax - 1  # d beyond every segment end: the line's last point
    np.minimum(seg, Pmax - 2, out=seg)
    at = np.arange(L)[:, None] * Pmax + seg  # flat index of each segment's start point
    at_seg = at - np.arange(L)[:, None]  # flat index into the [L, Pmax-1] segment arrays
    before = np.where(seg > 0, cum_end.ravel().take(np.maximum(at_seg - 1, 0)), 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = (dist - before) / seg_len.ravel().take(at_seg)
    start = dist <= 0.0  # GEOS: length <= 0 -> the first point
    out = []
    for v in (xs, ys):
        p0, p1 = v.ravel().take(at), v.ravel().take(at + 1)
        # GEOS pointAlongSegmentByFraction: p0 if frac <= 0, p1 if frac >= 1, else (p1 - p0) * frac + p0.
        along = np.where(frac >= 1.0, p1, np.where(frac <= 0.0, p0, (p1 - p0) * frac + p0))
        out.append(np.where(start, v[:, :1], np.where(past_end, v[:, -1:], along)))
    return np.stack(out, -1)


def _witness(x: np.ndarray, y: np.ndarray, cand: np.ndarray, width: float) -> np.ndarray:
    """Sufficient condition for buffer(x) and buffer(y) to intersect: one of x's candidate points
    lies in the rectangle of a segment of y, at most ``width - _PERP_MARGIN`` from it and at least
    ``_END_MARGIN`` (arc length) from y's ends. Such a point is inside buffer(y) with room to
    spare, and is a point of x, so inside (or on the cap of) buffer(x).

    Args: x [R, P, 2], y [R, Q, 2], cand [R, C] indices into x's points. Returns [R] bool.
    """
    R = len(x)
    pts = x[np.arange(R)[:, None], cand]  # [R, C, 2]
    u, e = y[:, :-1], y[:, 1:] - y[:, :-1]  # [R, Q-1, 2]
    l2 = e[..., 0] * e[..., 0] + e[..., 1] * e[..., 1]
    seg_len = np.sqrt(l2)
    arc0 = np.cumsum(seg_len, axis=1) - seg_len  # arc length at each segment start
    total = arc0[:, -1] + seg_len[:, -1]
    w = pts[:, :, None, :] - u[:, None]  # [R, C, Q-1, 2]
    safe = np.where(l2 > 0, l2, 1.0)[:, None]
    t = (w[..., 0] * e[:, None, :, 0] + w[..., 1] * e[:, None, :, 1]) / safe
    perp = np.abs(w[..., 0] * e[:, None, :, 1] - w[..., 1] * e[:, None, :, 0]) / np.sqrt(safe)
    arc = arc0[:, None] + t * seg_len[:, None]
    ok = (
        (l2[:, None] > 0)
        & (t >= 0)
        & (t <= 1)
        & (perp <= width - _PERP_MARGIN)
        & (arc >= _END_MARGIN)
        & (arc <= total[:, None, None] - _END_MARGIN)
    )
    return ok.any(axis=(1, 2))


def buffers_intersect(a: np.ndarray, b: np.ndarray, width: float = BUFFER_WIDTH, hint_a: np.ndarray | None = None,
                      hint_b: np.ndarray | None = None) -> np.ndarray:
    """Do the flat-cap, mitre-join ``width`` buffers of polylines a[r] and b[r] intersect?

    The same decision as ``LineString(a).buffer(width, cap_style=flat, join_style=mitre)
    .intersects(LineString(b).buffer(...))`` (the reference's pre-filter): a zero-length line
    has an empty buffer (never intersects); a cheap sufficient condition (:func:`_witness`)
    settles most other pairs; shapely decides the rest.

    Args:
        a: [R, P, 2], b: [R, Q, 2] float64 polylines.
        hint_a, hint_b: optional [R] indices of a point of a (b) close to the other line, tried
            as witnesses besides ten evenly spaced points.
    Returns: [R] bool.
    """
    R = len(a)
    la, lb = polyline_lengths(a), polyline_lengths(b)
    live = (la > 0) & (lb > 0)
    found = np.zeros(R, dtype=bool)  # a witness found; at the end, the answer
    # Witness candidates: the hinted point (usually enough), then ten evenly spaced points.
    tries = [(x, y, lx, ly, None if hint is None else np.asarray(hint)[:, None])
             for x, y, lx, ly, hint in ((a, b, la, lb, hint_a), (b, a, lb, la, hint_b))]
    tries += [(x, y, lx, ly, np.linspace(0, x.shape[1] - 1, 10).round().astype(np.int64)[None])
              for x, y, lx, ly, _ in tries]
    for x, y, lx, ly, cand in tries:
        todo = np.flatnonzero(live & ~found & (lx >= _MIN_WITNESS_LENGTH) & (ly > 2 * _END_MARGIN))
        if todo.size == 0 or cand is None:
            continue
        for s in range(0, todo.size, 512):
            sel = todo[s : s + 512]
            c = np.broadcast_to(cand, (R, cand.shape[1]))[sel]
            found[sel] = _witness(x[sel], y[sel], c, width)
    rest = np.flatnonzero(live & ~found)
    if rest.size:
        ga, gb = (shapely.buffer(shapely.linestrings(x[rest]), width, cap_style="flat", join_style="mitre",
                                 mitre_limit=MITRE_LIMIT) for x in (a, b))
        found[rest] = shapely.intersects(ga, gb)
    return found


# ---------------------------------------------------------------------------------------------
# AP
# ---------------------------------------------------------------------------------------------


def average_precision_area(recalls: np.ndarray, precisions: np.ndarray) -> np.float32:
    """VOC2010+ 'area' AP of one PR curve, with the reference's float32 arithmetic (mean_ap.py:35-45).

    Args: recalls, precisions: [N] float32, in descending-score order.
    """
    zero = np.zeros(1, dtype=recalls.dtype)
    mrec = np.concatenate([zero, recalls, np.ones(1, dtype=recalls.dtype)])
    mpre = np.concatenate([zero, precisions, zero])
    mpre = np.maximum.accumulate(mpre[::-1])[::-1]  # non-increasing from the right
    ind = np.flatnonzero(mrec[1:] != mrec[:-1])
    return np.float32(np.sum((mrec[ind + 1] - mrec[ind]) * mpre[ind + 1]))


def pooled_ap(scores: np.ndarray, tp: np.ndarray, num_gt: int) -> np.ndarray:
    """Dataset-level AP of one class at T thresholds (mean_ap.py:289-305).

    Args:
        scores: [N] float64 detection scores, pooled in sample order (input order within a sample).
        tp: [N, T] bool, True for a true positive at threshold t (false positive otherwise).
        num_gt: GT polylines of the class over all samples.
    Returns: [T] float32 APs.
    """
    order = np.argsort(-scores)  # the reference's sort: NumPy's default kind, ties as it orders them
    eps = np.finfo(np.float32).eps
    aps = np.zeros(tp.shape[1], dtype=np.float32)
    for t in range(tp.shape[1]):
        hit = tp[order, t]
        tp_cum = np.cumsum(hit.astype(np.float32))
        fp_cum = np.cumsum((~hit).astype(np.float32))
        recalls = tp_cum / np.maximum(num_gt, eps)
        precisions = tp_cum / np.maximum(tp_cum + fp_cum, eps)
        aps[t] = average_precision_area(recalls, precisions)
    return aps


class VectorAP:
    """Streaming accumulator of the vector protocol.

    Keeps, per class, every detection's (sample id, score, TP flag per threshold) and the GT
    count: about 20 bytes per detection (6 000 samples x 50 detections: 6 MB).
    """

    name = "vector"

    def __init__(self, thresholds: Sequence[float], num_classes: int = 3, num_sample_points: int = NUM_SAMPLE_POINTS,
                 resample_predictions: bool = True) -> None:
        self.thresholds = np.asarray(thresholds, dtype=np.float64)
        if self.thresholds.max() >= UNMEASURED:
            raise EvaluationInputError(f"vector protocol: thresholds must be < {UNMEASURED:g} m (the reference marks "
                                       f"pairs whose buffers do not intersect with D = {UNMEASURED:g}); got "
                                       f"{list(thresholds)}")
        self.num_classes = num_classes
        self.num_sample_points = num_sample_points
        self.resample_predictions = resample_predictions
        self.reset()

    def reset(self) -> None:
        K, T = self.num_classes, len(self.thresholds)
        # per class, the parts of each detection's sample id, score and TP flags [T] (concatenated on demand)
        self._empty = {"ids": np.zeros(0, np.int64), "scores": np.zeros(0), "tp": np.zeros((0, T), bool)}
        self._parts: dict[str, list[list[np.ndarray]]] = {key: [[] for _ in range(K)] for key in self._empty}
        self.num_gt = np.zeros(K, dtype=np.int64)
        self.counters = dict.fromkeys((*SAMPLE_COUNTERS, "zero_length_predictions"), 0)
        self._next_id = 0

    # --- accumulation ------------------------------------------------------------------------
    def update(self, preds: Samples, gts: Samples, sample_ids: Sequence[int] | None = None,
               tokens: Sequence[str] | None = None) -> None:
        """Add B samples. ``preds[b]`` / ``gts[b]`` are lists of polyline dicts (metres, ego frame).

        ``sample_ids`` (e.g. dataset indices) fix the pooling order, and so the order of tied
        scores, independently of how samples are split over updates and processes; default: a
        running counter.
        """
        B = len(preds)  # (Evaluator.update checks that gts has as many)
        ids = self._take_ids(B, sample_ids)
        m = self.match(preds, gts, ids, tokens)
        self.num_gt += np.bincount(m["gt_label"], minlength=self.num_classes)
        self.counters["samples"] += B
        for c in range(self.num_classes):
            k = m["label"] == c  # keeps sample order, and input order within a sample
            for key, value in (("ids", ids[m["sample"]]), ("scores", m["score"]), ("tp", m["tp"])):
                self._parts[key][c].append(value[k])

    def match(self, preds: Samples, gts: Samples, ids: np.ndarray, tokens: Sequence[str] | None = None) -> dict:
        """The protocol's decisions for B samples, without accumulating them: per detection (predictions with
        >= 2 points, in sample order, input order within a sample) ``label``, ``score``, ``sample`` (0..B-1),
        ``tp`` [Np, T] and ``gt`` [Np] (the GT it is compared with, an index into that sample's GT list, -1 for
        none: a TP at threshold t matched it); per GT ``gt_label`` and ``gt_sample``. Updates ``counters``
        except ``samples``. ``ids`` only name the samples in error messages."""
        B = len(preds)
        K, S = self.num_classes, self.num_sample_points
        p_pts, p_lab, p_score, p_smp, g_pts, g_lab, g_smp = [], [], [], [], [], [], []
        for b in range(B):
            where = sample_name(int(ids[b]), tokens[b] if tokens is not None else None)
            P, G = read_sample(preds[b], gts[b], where, K, "error", self.counters)
            if not self.resample_predictions:
                for i, pts in enumerate(P.pts):
                    if len(pts) != len(P.pts[0]) or (p_pts and len(pts) != len(p_pts[0])):
                        raise EvaluationInputError(f"{where}, prediction polyline {i}: with resample_predictions=False "
                                                   "every prediction must have the same number of points (the "
                                                   "reference stacks them)")
            p_pts += P.pts
            p_lab.append(P.labels)
            p_score.append(P.scores)
            p_smp.append(np.full(len(P.pts), b))
            g_pts += G.pts
            g_lab.append(G.labels)
            g_smp.append(np.full(len(G.pts), b))
        g_lab = concat(g_lab, np.zeros(0, np.int64)).astype(np.int64)
        g_smp = concat(g_smp, np.zeros(0, np.int64)).astype(np.int64)
        out = {"gt_label": g_lab, "gt_sample": g_smp}
        if not p_pts:
            T = len(self.thresholds)
            return {**out, "label": np.zeros(0, np.int64), "score": np.zeros(0), "sample": np.zeros(0, np.int64),
                    "tp": np.zeros((0, T), bool), "gt": np.zeros(0, np.int64)}
        p_lab, p_score, p_smp = np.concatenate(p_lab), np.concatenate(p_score), np.concatenate(p_smp)

        if self.resample_predictions:
            # The reference keeps a prediction's raw points when it already has exactly S of them.
            resampled = iter(resample_polylines([p for p in p_pts if len(p) != S], S))
            p_pts = [p if len(p) == S else next(resampled) for p in p_pts]
        pred = np.stack(p_pts)
        gt = resample_polylines(g_pts, S)
        self.counters["zero_length_predictions"] += int((polyline_lengths(pred) == 0).sum())

        best_d, best_j = self._nearest_gt(pred, gt, p_smp * K + p_lab, g_smp * K + g_lab)
        tp = self._assign(best_d, best_j, p_score, p_smp * K + p_lab)
        first = np.searchsorted(g_smp, np.arange(B))  # each sample's first GT (g_smp is sorted)
        local = np.where(best_j >= 0, best_j - first[p_smp], -1)
        return {**out, "label": p_lab, "score": p_score, "sample": p_smp, "tp": tp, "gt": local}

    def _take_ids(self, B: int, sample_ids: Sequence[int] | None) -> np.ndarray:
        if sample_ids is None:
            ids = np.arange(self._next_id, self._next_id + B, dtype=np.int64)
        else:
            ids = np.asarray(sample_ids, dtype=np.int64).reshape(-1)
            if len(ids) != B:
                raise EvaluationInputError(f"vector AP update: {B} samples but {len(ids)} sample_ids")
        self._next_id = int(ids.max()) + 1 if B else self._next_id
        return ids

    def _nearest_gt(self, pred: np.ndarray, gt: np.ndarray, group_p: np.ndarray,
                    group_g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each detection's nearest GT of its sample and class among pairs that can matter.

        Args: pred [Np, S, 2], gt [Ng, S', 2]; group_* [N] sample*K + class.
        Returns: best_d [Np] (inf when no GT lies within the largest threshold), best_j [Np]
            (global GT index, -1 for none). A detection's reference row argmax is best_j whenever
            best_d <= max threshold; otherwise the detection is a false positive at every threshold.
        """
        Np = len(pred)
        best_d = np.full(Np, np.inf)
        best_j = np.full(Np, -1, dtype=np.int64)
        max_thr = float(self.thresholds.max())
        # All (detection, GT) pairs of the same sample and class.
        g_order = np.argsort(group_g, kind="stable")
        g_sorted = group_g[g_order]
        lo = np.searchsorted(g_sorted, group_p, side="left")
        cnt = np.searchsorted(g_sorted, group_p, side="right") - lo
        pi = np.repeat(np.arange(Np), cnt)
        within = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        gj = g_order[np.repeat(lo, cnt) + within]
        # 1. Bounding-box gap: D >= every point-to-point distance's minimum >= the gap.
        p_lo, p_hi = pred.min(1), pred.max(1)
        g_lo, g_hi = gt.min(1), gt.max(1)
        gap = np.maximum(0.0, np.maximum(g_lo[gj] - p_hi[pi], p_lo[pi] - g_hi[gj]))
        keep = np.hypot(gap[:, 0], gap[:, 1]) <= max_thr * (1 + 1e-9)
        pi, gj = pi[keep], gj[keep]
        # 2. Mean point-to-box distance each way: a lower bound of each Chamfer term.
        lb = np.empty(len(pi))
        for s in range(0, len(pi), 2048):
            a, b = pi[s : s + 2048], gj[s : s + 2048]
            lb[s : s + 2048] = 0.5 * (
                mean_dist_to_box(pred[a], g_lo[b], g_hi[b]) + mean_dist_to_box(gt[b], p_lo[a], p_hi[a])
            )
        keep = lb <= max_thr * (1 + 1e-9)
        pi, gj = pi[keep], gj[keep]
        # 3. Exact Chamfer; 4. buffer test on the pairs within the largest threshold.
        d_ab, d_ba, near_a = chamfer_pairs(pred[pi], gt[gj])
        d = (d_ba + d_ab) / 2  # tpfp_chamfer.py:59 (negated there)
        near = d <= max_thr
        pi, gj, d, near_a = pi[near], gj[near], d[near], near_a[near]
        hint_a = near_a.argmin(1)  # the point of the prediction nearest to the GT, and the GT's point nearest to it
        dq = gt[gj] - pred[pi][np.arange(len(pi)), hint_a][:, None]
        hint_b = (dq[..., 0] * dq[..., 0] + dq[..., 1] * dq[..., 1]).argmin(1)
        ok = buffers_intersect(pred[pi], gt[gj], BUFFER_WIDTH, hint_a, hint_b)
        pi, gj, d = pi[ok], gj[ok], d[ok]
        if pi.size == 0:
            return best_d, best_j
        # Smallest D per detection; among equal D the first GT (np.argmax's tie rule).
        o = np.lexsort((gj, d, pi))
        first = np.r_[True, pi[o][1:] != pi[o][:-1]]
        best_d[pi[o][first]] = d[o][first]
        best_j[pi[o][first]] = gj[o][first]
        return best_d, best_j

    def _assign(self, best_d: np.ndarray, best_j: np.ndarray, scores: np.ndarray, group: np.ndarray) -> np.ndarray:
        """TP flags [Np, T]: in each sample and class, detections in ``np.argsort(-score)`` order
        take their nearest GT if ``D <= thr`` and it is still free (tpfp.py:65-79)."""
        Np, T = len(scores), len(self.thresholds)
        rank = np.empty(Np, dtype=np.int64)
        order = np.argsort(group, kind="stable")
        bounds = np.flatnonzero(np.r_[True, group[order][1:] != group[order][:-1], True])
        for s, e in zip(bounds[:-1], bounds[1:]):
            idx = order[s:e]
            rank[idx[np.argsort(-scores[idx])]] = np.arange(e - s)
        tp = np.zeros((Np, T), dtype=bool)
        for t, thr in enumerate(self.thresholds):
            elig = np.flatnonzero(best_d <= thr)
            if elig.size == 0:
                continue
            o = elig[np.lexsort((rank[elig], best_j[elig]))]
            first = np.r_[True, best_j[o][1:] != best_j[o][:-1]]  # the first claimant of each GT wins
            tp[o[first], t] = True
        return tp

    # --- state (streaming, DDP) ------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"protocol": self.name, "thresholds": self.thresholds.tolist(), "num_gt": self.num_gt.copy(),
                **self._concat(), "counters": dict(self.counters)}

    def merge_state(self, state: dict) -> None:
        check_state(self, state)
        for key, parts in self._parts.items():
            for c in range(self.num_classes):
                parts[c].append(state[key][c])
        self.num_gt += state["num_gt"]
        for k, v in state["counters"].items():
            self.counters[k] += v
        self._next_id = max(self._next_id, int(max((x.max() + 1 for x in state["ids"] if len(x)), default=0)))

    def _concat(self) -> dict[str, list[np.ndarray]]:
        """``{"ids", "scores", "tp"}``: per class its detections' parts as one array (kept as the one part)."""
        for key, parts in self._parts.items():
            for c in range(self.num_classes):
                parts[c] = [concat(parts[c], self._empty[key])]
        return {key: [p[0] for p in parts] for key, parts in self._parts.items()}

    def compute(self) -> dict:
        """Returns {"AP": [K, T] float64 (float32 values), "num_gt": [K], "num_pred": [K]}."""
        cat = self._concat()
        ids, scores, tp = cat["ids"], cat["scores"], cat["tp"]
        ap = np.zeros((self.num_classes, len(self.thresholds)))
        for c in range(self.num_classes):
            o = np.argsort(ids[c], kind="stable")  # sample order; input order within a sample
            ap[c] = pooled_ap(scores[c][o], tp[c][o], int(self.num_gt[c]))
        return {"AP": ap, "num_gt": self.num_gt.copy(), "num_pred": np.array([len(s) for s in scores])}

