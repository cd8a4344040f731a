"""evaluation/: both AP protocols number for number (EVAL_PROTOCOLS.md), streaming, I/O, CLI.

Hand-computed cases work the numbers out in comments. Two slow references, written step by step
from the specification (shapely/scipy per pair for the vector protocol; shapely affinity, cv2,
per-pair torch.cdist and the list-based PR curve for the raster protocol), check the fast code on
random cases including the edge cases (duplicates, tied scores, zero-length lines, clipping).
"""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
import shapely
import torch
from scipy.spatial import distance
from shapely import affinity
from shapely.geometry import LineString, box

from instagram_hdmap.cli import main
from instagram_hdmap.evaluation import EvaluationInputError, Evaluator, SubmissionError, read_submission
from instagram_hdmap.evaluation.chamfer import chamfer_pairs
from instagram_hdmap.evaluation.io import write_submission
from instagram_hdmap.evaluation.raster_ap import RasterFrame, greedy_match, rasterize_instances
from instagram_hdmap.evaluation.vector_ap import buffers_intersect, resample_polylines
from instagram_hdmap.geometry import BEVGrid

THR = (0.5, 1.0, 1.5)
GRID = BEVGrid(-30.0, 30.0, -15.0, 15.0, 0.15)


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """The references call torch.cdist per pair: one thread avoids OpenMP contention on a shared machine."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


def seg(x0, y0, x1, y1, label=0, score=None, n=2):
    """A straight polyline of n points as a polyline dict."""
    t = np.linspace(0, 1, n)[:, None]
    d = {"pts": np.array([x0, y0]) + t * np.array([x1 - x0, y1 - y0]), "label": label}
    if score is not None:
        d["score"] = score
    return d


def run(protocol, preds, gts, thresholds=THR, **kw):
    ev = Evaluator(protocol, thresholds, **kw)
    ev.update(preds, gts)
    return ev.compute()


# ---------------------------------------------------------------------------------------------
# Slow references, one pair at a time, from the specification
# ---------------------------------------------------------------------------------------------


def vector_reference(preds, gts, thresholds=THR, K=3):
    """Protocol A step by step: returns AP [K, T] (float32 values)."""

    def sample(pts, keep_100):
        line = LineString(pts)
        if keep_100 and len(pts) == 100:
            return np.asarray(line.coords)
        return np.array([line.interpolate(d).coords[0] for d in np.linspace(0, line.length, 100)])

    def area_ap(rec, prec):
        mrec = np.hstack([np.zeros(1, rec.dtype), rec, np.ones(1, rec.dtype)])
        mpre = np.hstack([np.zeros(1, rec.dtype), prec, np.zeros(1, rec.dtype)])
        for i in range(len(mpre) - 1, 0, -1):
            mpre[i - 1] = max(mpre[i - 1], mpre[i])
        ind = np.where(mrec[1:] != mrec[:-1])[0]
        return np.float32(np.sum((mrec[ind + 1] - mrec[ind]) * mpre[ind + 1]))

    out = np.zeros((K, len(thresholds)))
    for c in range(K):
        per_sample = []
        for P, G in zip(preds, gts):
            det = [(sample(p["pts"], True), p["score"]) for p in P if p["label"] == c and len(p["pts"]) >= 2]
            gt = [sample(g["pts"], False) for g in G if g["label"] == c]
            score = np.full((len(det), len(gt)), -100.0)
            bufs = [LineString(x).buffer(2.0, cap_style="flat", join_style="mitre") for x, _ in det]
            gbufs = [LineString(x).buffer(2.0, cap_style="flat", join_style="mitre") for x in gt]
            for i, (x, _) in enumerate(det):
                for j, y in enumerate(gt):
                    if bufs[i].intersects(gbufs[j]):
                        dm = distance.cdist(x, y, "euclidean")
                        score[i, j] = -(dm.min(-2).mean() + dm.min(-1).mean()) / 2
            per_sample.append((np.array([s for _, s in det], dtype=np.float64), score, len(gt)))
        for t, thr in enumerate(thresholds):
            tps, fps = [], []
            for scores, score, m in per_sample:
                tp = np.zeros(len(scores), np.float32)
                fp = np.zeros(len(scores), np.float32)
                if m == 0:
                    fp[:] = 1
                elif len(scores):
                    best, arg = score.max(1), score.argmax(1)
                    taken = np.zeros(m, bool)
                    for i in np.argsort(-scores):
                        if best[i] >= -thr and not taken[arg[i]]:
                            taken[arg[i]] = True
                            tp[i] = 1
                        else:
                            fp[i] = 1
                tps.append(tp)
                fps.append(fp)
            all_scores = np.concatenate([s for s, _, _ in per_sample])
            num_gts = sum(m for _, _, m in per_sample)
            o = np.argsort(-all_scores)
            tp_c, fp_c = np.cumsum(np.hstack(tps)[o]), np.cumsum(np.hstack(fps)[o])
            eps = np.finfo(np.float32).eps
            out[c, t] = area_ap(tp_c / np.maximum(num_gts, eps), tp_c / np.maximum(tp_c + fp_c, eps))
    return out


def raster_reference(preds, gts, thresholds=THR, rank_by="ascending", K=3):
    """Protocol B step by step, with the reference's tensors; returns AP [K, T] (NaN where 0/0)."""
    patch = affinity.rotate(box(-30.0, -15.0, 30.0, 15.0), 0.0, origin=(0.0, 0.0))

    def rasterize(vectors):
        conf, idx, masks = [-1], 1, []
        by_class = {c: [(LineString(v["pts"]), v.get("score", 1)) for v in vectors
                        if v["label"] == c and len(v["pts"]) >= 2] for c in range(K)}
        for c in range(K):
            mask = np.zeros((200, 400), np.uint8)
            for line, s in by_class[c]:
                new = line.intersection(patch)
                if new.is_empty:
                    continue
                new = affinity.affine_transform(new, [1.0, 0.0, 0.0, 1.0, 30.0, 15.0])
                new = affinity.scale(new, xfact=400 / 60.0, yfact=200 / 30.0, origin=(0, 0))
                conf.append(s)
                for part in (new.geoms if new.geom_type == "MultiLineString" else [new]):
                    coords = np.asarray(list(part.coords), np.int32).reshape(-1, 2)
                    if len(coords) < 2:
                        continue
                    cv2.polylines(mask, [coords], False, color=idx, thickness=5)
                    idx += 1
            masks.append(mask)
        return torch.tensor(np.stack(masks)), torch.tensor(conf + [-1] * (300 - len(conf)))

    def instances(mask):
        out = {}
        for i in torch.unique(mask).tolist():
            if i:
                r, c = torch.where(mask == i)
                out[i] = torch.stack([r.float() * 0.15, c.float() * 0.15], -1)
        return out

    def cd(a, b, thr):
        dist = torch.cdist(a[None].float(), b[None].float())
        return min((dist.min(2)[0].mean(-1) + dist.min(1)[0].mean(-1)) / 2, thr)

    recalls_at = torch.linspace(0.1, 1, 10)
    ap_sum = torch.zeros(K, len(thresholds), dtype=torch.float64)
    count = torch.zeros(K, 1, dtype=torch.float64)
    for P, G in zip(preds, gts):
        pm, conf = rasterize(P)
        gm, _ = rasterize(G)
        for c in range(K):
            pl, gl = instances(pm[c]), instances(gm[c])
            if not pl and not gl:
                continue
            kp, kg = list(pl), list(gl)
            for t, thr in enumerate(thresholds):
                CD = torch.zeros(len(kp), len(kg))
                for i, a in enumerate(kp):
                    for j, b in enumerate(kg):
                        CD[i, j] = cd(pl[a], gl[b], thr)
                matches, taken = [], set()
                if kp and kg:
                    while True:
                        k = int(torch.argmin(CD))
                        i, j = k // CD.shape[1], k % CD.shape[1]
                        if CD[i, j] >= thr:
                            break
                        matches.append((conf[kp[i]], True))
                        taken.add(i)
                        CD[i, :] = thr
                        CD[:, j] = thr
                matches += [(conf[kp[i]], False) for i in range(len(kp)) if i not in taken]
                matches = sorted(matches, key=lambda m: m[0], reverse=rank_by == "descending")
                tp = torch.tensor([0] + list(np.cumsum([m[1] for m in matches])))[1:]
                fp = torch.tensor([0] + list(np.cumsum([not m[1] for m in matches])))[1:]
                precision, recall = tp / (tp + fp), tp / len(kg)
                for i in range(len(precision) - 1, 0, -1):
                    precision[:i][precision[:i] < precision[i]] = precision[i]
                acc = 0.0
                for r in recalls_at:
                    hit = torch.where(recall >= r)[0]
                    if len(hit):
                        acc += precision[hit[0]]
                ap_sum[c, t] += float(acc / 10)
            count[c] += 1
    return (ap_sum / count).numpy()


def random_vector_data(rng, n_samples):
    """Small random scenes with the vector protocol's edge cases: tied scores, duplicates,
    zero-length and one-point predictions, raw 100-point predictions, near and far lines."""
    preds, gts = [], []
    for _ in range(n_samples):
        G = []
        for _ in range(rng.integers(0, 6)):
            a = rng.uniform(-20, 20, 2)
            pts = a + np.cumsum(rng.normal(size=(rng.integers(2, 8), 2)) * rng.choice([0.3, 3.0]), 0)
            G.append({"pts": pts, "label": int(rng.integers(0, 3))})
        P = []
        for g in G:
            for _ in range(rng.integers(0, 3)):
                P.append({"pts": g["pts"] + rng.normal(scale=rng.choice([0.05, 0.4, 1.0]), size=g["pts"].shape),
                          "label": g["label"], "score": float(rng.choice([0.5, 0.7, rng.random()]))})
        for _ in range(rng.integers(0, 4)):
            kind = rng.integers(0, 4)
            a = rng.uniform(-20, 20, 2)
            if kind == 0:
                pts = np.repeat(a[None], 3, 0)  # zero length
            elif kind == 1:
                pts = a[None]  # one point: dropped
            elif kind == 2:
                pts = a + np.linspace(0, 1, 100)[:, None] * rng.normal(size=2) * 5  # raw 100 points
            else:
                pts = a + np.cumsum(rng.normal(size=(5, 2)), 0)
            P.append({"pts": pts, "label": int(rng.integers(0, 3)), "score": float(rng.choice([0.5, rng.random()]))})
        if P and rng.random() < 0.3:
            P.append(dict(P[0]))  # exact duplicate, same score
        preds.append(P)
        gts.append(G)
    return preds, gts


def random_raster_data(rng, n_samples):
    """Random scenes for the raster protocol: lines crossing the patch border (clipped, some into
    two parts), predictions shifted by 0..1.6 m (CD around the thresholds), duplicates, tied
    scores, false positives."""
    preds, gts = [], []
    for _ in range(n_samples):
        G = []
        for _ in range(rng.integers(1, 7)):
            a = rng.uniform([-34, -17], [34, 17])
            b = a + rng.normal(size=2) * 8
            pts = np.stack([a, (a + b) / 2 + rng.normal(size=2), b])
            if rng.random() < 0.15:  # a U leaving and re-entering the patch at the top
                x = rng.uniform(-25, 25)
                pts = np.array([[x, 12.0], [x, 18.0], [x + 4, 18.0], [x + 4, 12.0]])
            G.append({"pts": pts, "label": int(rng.integers(0, 3))})
        P = []
        for g in G:
            if rng.random() < 0.8:
                shift = rng.normal(size=2)
                shift *= rng.uniform(0, 1.6) / np.linalg.norm(shift)
                score = float(rng.choice([0.5, rng.random()]))  # 0.5: ties
                P.append({"pts": g["pts"] + shift, "label": g["label"], "score": score})
                if rng.random() < 0.15:
                    P.append(dict(P[-1], score=float(rng.random())))  # duplicate, overdrawn
        for _ in range(rng.integers(0, 3)):
            a = rng.uniform([-30, -15], [30, 15])
            P.append({"pts": np.stack([a, a + rng.normal(size=2) * 4]), "label": int(rng.integers(0, 3)),
                      "score": float(rng.random())})
        preds.append(P)
        gts.append(G)
    return preds, gts


# ---------------------------------------------------------------------------------------------
# Building blocks: fast paths equal slow references
# ---------------------------------------------------------------------------------------------


def test_resample_is_bitwise_shapely_interpolate():
    rng = np.random.default_rng(0)
    lines = []
    for i in range(300):
        p = np.cumsum(rng.normal(size=(rng.integers(2, 30), 2)) * rng.choice([0.01, 1.0, 5.0]), 0)
        if i % 7 == 0:
            p[rng.integers(0, len(p))] = p[0]  # a repeated vertex
        if i % 11 == 0:
            p = np.round(p)
        if i % 13 == 0:
            p[:] = p[0]  # zero length
        lines.append(p)
    got = resample_polylines(lines, 100)
    for p, g in zip(lines, got):
        line = LineString(p)
        ref = np.array([line.interpolate(d).coords[0] for d in np.linspace(0, line.length, 100)])
        assert np.array_equal(ref, g)


def test_chamfer_pairs_equals_plain_loop():
    rng = np.random.default_rng(1)
    a, b = rng.uniform(-30, 30, (37, 100, 2)), rng.uniform(-30, 30, (37, 100, 2))
    b[0] = a[0]  # identical sets: D = 0
    d_ab, d_ba, near_a = chamfer_pairs(a, b)
    for r in range(len(a)):
        dm = distance.cdist(a[r], b[r], "euclidean")
        assert d_ab[r] == dm.min(-1).mean() and d_ba[r] == dm.min(-2).mean()  # bit for bit
        assert np.array_equal(near_a[r], dm.min(-1))
    assert d_ab[0] == 0 and d_ba[0] == 0


def test_buffer_prefilter_matches_shapely():
    rng = np.random.default_rng(2)
    A, B = [], []
    for _ in range(1500):
        a = np.cumsum(rng.normal(size=(rng.integers(2, 12), 2)) * rng.choice([0.02, 0.5, 3.0]), 0)
        mode = rng.integers(0, 4)
        if mode == 0:
            b = a + rng.normal(size=2) * rng.choice([0.5, 2.0, 4.0])  # parallel, near the 4 m limit
        elif mode == 1:
            b = a[::-1] + rng.normal(size=a.shape) * 0.3
        elif mode == 2:  # collinear continuation: flat caps decide
            d = (a[-1] - a[-2]) / (np.linalg.norm(a[-1] - a[-2]) + 1e-12)
            gap = rng.choice([0.0, 0.01, 0.5])
            b = np.stack([a[-1] + d * gap, a[-1] + d * (gap + rng.uniform(0.01, 5))])
        else:
            b = rng.uniform(-4, 4, (rng.integers(2, 6), 2))
        if rng.random() < 0.03:
            b = np.repeat(a[:1], 3, 0)  # zero length: empty buffer
        A.append(a)
        B.append(b)
    a, b = resample_polylines(A), resample_polylines(B)
    ref = shapely.intersects(
        shapely.buffer(shapely.linestrings(a), 2.0, cap_style="flat", join_style="mitre"),
        shapely.buffer(shapely.linestrings(b), 2.0, cap_style="flat", join_style="mitre"),
    )
    assert 0.2 < ref.mean() < 0.95  # both outcomes well represented
    assert np.array_equal(buffers_intersect(a, b), ref)


# ---------------------------------------------------------------------------------------------
# Vector protocol: hand-computed cases (thresholds 0.5, 1.0, 1.5 m)
# ---------------------------------------------------------------------------------------------


def test_vector_perfect_and_empty():
    gts = [[seg(0, 0, 10, 0, 0), seg(0, 5, 4, 9, 1), seg(-5, -5, 5, -8, 2)], [seg(3, 3, 9, 3, 0)]]
    perfect = [[dict(g, score=0.9) for g in G] for G in gts]
    m = run("vector", perfect, gts)
    assert m["mAP"] == 1.0 and all(v == [1.0, 1.0, 1.0] for v in m["AP"].values())
    m = run("vector", [[], []], gts)  # no predictions: recall stays 0
    assert m["mAP"] == 0.0
    assert "2 samples have no predictions" in " ".join(m["notes"])


def test_vector_class_without_gt_counts_zero():
    # Perfect divider and boundary; no ped_crossing anywhere (GT or prediction): its AP is 0 and
    # mAP = (1 + 0 + 1) / 3, MapTR's reported number; the other "mAP" (classes with GT) is 1.
    gts = [[seg(0, 0, 10, 0, 0), seg(0, 5, 10, 5, 2)]]
    m = run("vector", [[dict(g, score=0.8) for g in gts[0]]], gts)
    assert m["AP"]["ped_crossing"] == [0.0, 0.0, 0.0]
    assert m["mAP"] == pytest.approx(2 / 3) and m["mAP_classes_with_gt"] == 1.0


def test_vector_threshold_is_inclusive():
    # GT (0,0)-(10,0); predictions offset by 0.5 m and 0.6 m. Both resample to x = k * 10/99, so
    # every nearest distance is exactly the offset: D = 0.5 (TP at 0.5: D <= thr) and D = 0.6
    # (FP at 0.5, TP at 1.0 and 1.5). One detection, one GT: AP = 1 or 0.
    gts = [[seg(0, 0, 10, 0)]]
    assert run("vector", [[seg(0, 0.5, 10, 0.5, score=0.9)]], gts)["AP"]["divider"] == [1.0, 1.0, 1.0]
    assert run("vector", [[seg(0, 0.6, 10, 0.6, score=0.9)]], gts)["AP"]["divider"] == [0.0, 1.0, 1.0]


def test_vector_no_fallback_to_second_nearest_gt():
    # GT A at y=0, GT B at y=1.2. P1 (y=0.1, score 0.9): nearest A, D=0.1 -> TP. P2 (y=0.3,
    # score 0.8): nearest A (D=0.3; B is at D=0.9) but A is taken -> FP at every threshold, although
    # B is free and within 1.0 and 1.5. Pooled: [TP, FP], 2 GT: recall [.5, .5], precision [1, .5]
    # -> area AP = 0.5 * 1 (recall 0 -> .5) + 0.5 * 0 (.5 -> 1, envelope 0) = 0.5.
    gts = [[seg(0, 0, 10, 0), seg(0, 1.2, 10, 1.2)]]
    preds = [[seg(0, 0.1, 10, 0.1, score=0.9), seg(0, 0.3, 10, 0.3, score=0.8)]]
    assert run("vector", preds, gts)["AP"]["divider"] == [0.5, 0.5, 0.5]


def test_vector_dataset_level_pooling_and_score_order():
    # Sample 1: GT g1, TP (0.9). Sample 2: GT g2, a far FP (0.95) and a TP (0.5).
    # Pooled by score: FP .95, TP .9, TP .5; 2 GT: recall [0, .5, 1], precision [0, .5, 2/3];
    # envelope of precision: 2/3 everywhere up to recall 1 -> AP = .5 * 2/3 + .5 * 2/3 = 2/3.
    gts = [[seg(0, 0, 10, 0)], [seg(0, 5, 10, 5)]]
    preds = [[seg(0, 0, 10, 0, score=0.9)], [seg(-20, -10, -10, -10, score=0.95), seg(0, 5, 10, 5, score=0.5)]]
    ap = run("vector", preds, gts)["AP"]["divider"]
    assert ap == pytest.approx([2 / 3] * 3, abs=1e-6)  # float32 arithmetic


def test_vector_single_point_duplicate_and_zero_length_predictions():
    g1, g2 = seg(0, 0, 10, 0), seg(0, 5, 10, 5)
    # A one-point prediction is dropped, not counted: AP stays 1.
    m = run("vector", [[seg(0, 0, 10, 0, score=0.9), {"pts": np.array([[1.0, 1.0]]), "label": 0, "score": 1.0}]],
            [[g1]])
    assert m["AP"]["divider"] == [1.0] * 3 and m["counters"]["dropped_short_predictions"] == 1
    # Duplicate of g1's match (0.8) between the two TPs: pooled [TP .9, FP .8, TP .7], 2 GT:
    # recall [.5, .5, 1], precision [1, .5, 2/3] -> AP = .5 * 1 + .5 * 2/3 = 5/6.
    preds = [[seg(0, 0, 10, 0, score=0.9), seg(0, 0, 10, 0, score=0.8), seg(0, 5, 10, 5, score=0.7)]]
    assert run("vector", preds, [[g1, g2]])["AP"]["divider"] == pytest.approx([5 / 6] * 3, abs=1e-6)  # float32
    # A zero-length prediction (3 equal points) on a 1 m GT: its D would be ~0.13 m, but its buffer
    # is empty, so it is an FP; with the perfect one (0.8) after it: [FP, TP] -> recall [0, 1],
    # precision [0, .5] -> AP = 1 * .5 = 0.5.
    zero = {"pts": np.full((3, 2), 0.5) * [1, 0], "label": 0, "score": 0.9}
    m = run("vector", [[zero, seg(0, 0, 1, 0, score=0.8)]], [[seg(0, 0, 1, 0)]])
    assert m["AP"]["divider"] == [0.5] * 3 and m["counters"]["zero_length_predictions"] == 1


def test_vector_buffer_prefilter_gives_d100():
    # GT (0,0)-(0.2,0) and a collinear prediction (0.9,0)-(1.1,0): every prediction point's nearest
    # GT point is the end x=0.2, so d_pg = mean(x_p) - 0.2 = 1.0 - 0.2 = 0.8, and likewise d_gp = 0.9
    # - mean(x_g) = 0.8: D = 0.8 <= 1.0. But the flat-capped 2 m buffers (x in [0, .2] and
    # [.9, 1.1]) do not intersect, so the reference never measures the pair: D = 100, FP, AP 0.
    gts = [[seg(0, 0, 0.2, 0)]]
    assert run("vector", [[seg(0.9, 0, 1.1, 0, score=1.0)]], gts)["AP"]["divider"] == [0.0, 0.0, 0.0]
    # Shifted sideways by 1 m instead, the buffers overlap and D = 1.0: TP at 1.0 and 1.5.
    assert run("vector", [[seg(0, 1, 0.2, 1, score=1.0)]], gts)["AP"]["divider"] == [0.0, 1.0, 1.0]


def test_vector_does_not_clip_lines():
    # Lines are not clipped in the vector protocol: a prediction covering half of a 20 m GT has
    # d_pg = 0.0505 (its points fall between GT points 20/99 m apart) and d_gp = 2.525 (half the GT
    # points at ~0, half at 0..10 m: ~2.5), D = 1.288: TP only at 1.5.
    # (The raster protocol clips both to the patch and scores the same pair 1: test_raster_clipping.)
    m = run("vector", [[seg(20, 0, 30, 0, score=1.0)]], [[seg(20, 0, 40, 0)]])
    assert m["AP"]["divider"] == [0.0, 0.0, 1.0]


def test_vector_matches_slow_reference_on_random_cases():
    rng = np.random.default_rng(3)
    preds, gts = random_vector_data(rng, 40)
    m = run("vector", preds, gts)
    ref = vector_reference(preds, gts)
    got = np.array([m["AP"][c] for c in m["classes"]])
    assert np.array_equal(got, ref), (got, ref)
    assert 0.05 < m["mAP"] < 0.95


def test_vector_raw_prediction_points_option():
    # resample_predictions=False (MapTR's eval_use_same_gt_sample_num_flag off): raw points, all
    # predictions with the same count. With exactly 100 points both modes use the raw points.
    rng = np.random.default_rng(8)
    preds, gts = random_vector_data(rng, 10)
    preds = [[dict(p, pts=resample_polylines([p["pts"]])[0]) for p in P if len(p["pts"]) >= 2] for P in preds]
    a = run("vector", preds, gts)
    b = run("vector", preds, gts, resample_predictions=False)
    assert a["AP"] == b["AP"]
    with pytest.raises(EvaluationInputError, match="same number of points"):
        run("vector", [[seg(0, 0, 1, 0, score=1.0), seg(0, 0, 1, 0, score=1.0, n=3)]], [[]],
            resample_predictions=False)


def test_vector_gt_with_one_point_is_an_error():
    with pytest.raises(EvaluationInputError, match=r"sample 'tok'.*GT polyline 1.*1 point"):
        Evaluator("vector").update([[]], [[seg(0, 0, 1, 0), {"pts": [[0.0, 0.0]], "label": 0}]], tokens=["tok"])


# ---------------------------------------------------------------------------------------------
# Raster protocol: hand-computed cases
# ---------------------------------------------------------------------------------------------


def test_raster_perfect_and_empty():
    gts = [[seg(-10, 0, 10, 0, 0), seg(0, 5, 4, 9, 1), seg(-5, -5, 5, -8, 2)]]
    m = run("raster", [[dict(g, score=0.9) for g in gts[0]]], gts)
    assert m["mAP"] == 1.0
    m = run("raster", [[]], gts)  # GT but no prediction: each class counts one sample with AP 0
    assert m["mAP"] == 0.0 and m["samples_counted"] == {"divider": 1, "ped_crossing": 1, "boundary": 1}


def test_raster_band_and_strict_threshold():
    # A line across the whole patch at y = 0.1 m -> row (0.1 + 15) * 200/30 = 100.67 -> 100; cv2's
    # thickness-5 line covers rows 97..103 (7 rows, measured below) and every column.
    masks, _ = rasterize_instances([np.array([[-40.0, 0.1], [40.0, 0.1]])], np.array([0]), np.array([1.0]),
                                   RasterFrame(GRID))
    rows, cols = np.nonzero(masks[0])
    assert set(rows) == set(range(97, 104)) and len(rows) == 7 * 400
    # The prediction at y = 1.15 -> row 107: band 104..110, 7 rows below the GT band. Each column
    # alike: prediction rows are 1..7 px from the GT band -> mean 4 px = 0.6 m each way, CD = 0.6:
    # FP at 0.5, TP at 1.0 and 1.5.
    gts = [[seg(-40, 0.1, 40, 0.1)]]
    m = run("raster", [[seg(-40, 1.15, 40, 1.15, score=0.9)]], gts)
    assert m["AP"]["divider"] == [0.0, 1.0, 1.0]
    # Strict CD < thr in the matching: a CD equal to the threshold is not matched.
    cd = np.array([[0.5, 0.2], [0.1, 0.5]], np.float32)
    assert greedy_match(cd, 0.5).tolist() == [1, 0]  # global minimum 0.1 first, then 0.2
    assert greedy_match(np.array([[0.5]], np.float32), 0.5).tolist() == []
    assert greedy_match(np.array([[0.5]], np.float32), 0.5001).tolist() == [0]


def test_raster_per_sample_mean_and_ascending_quirk():
    # The data of test_vector_dataset_level_pooling_and_score_order. Sample 1: one TP -> AP 1.
    # Sample 2: FP (0.95), TP (0.5).
    #   ascending (reference): [TP .5, FP .95] -> precision [1, .5], recall [1, 1]; every sampled
    #   recall is first reached at the first point -> AP 1. Mean over samples (1 + 1) / 2 = 1.
    #   descending (fixed): [FP, TP] -> precision [0, .5] -> smoothed [.5, .5], recall [0, 1] -> AP .5.
    #   Mean (1 + .5) / 2 = 0.75. (The vector protocol pools instead: 2/3.)
    gts = [[seg(0, 0, 10, 0)], [seg(0, 5, 10, 5)]]
    preds = [[seg(0, 0, 10, 0, score=0.9)], [seg(-20, -10, -10, -10, score=0.95), seg(0, 5, 10, 5, score=0.5)]]
    assert run("raster", preds, gts)["AP"]["divider"] == [1.0, 1.0, 1.0]
    assert run("raster", preds, gts, rank_by="descending")["AP"]["divider"] == [0.75, 0.75, 0.75]


def test_raster_nan_rules():
    # Sample 1: a perfect divider only. Sample 2: a boundary prediction, no boundary GT.
    # divider: 1 (one sample counted). boundary: prediction without GT -> recall 0/0 = NaN, never
    # >= r -> AP 0, counted once -> 0. ped_crossing: nowhere -> 0/0 = NaN, and the mean is NaN.
    gts = [[seg(0, 0, 10, 0)], [seg(0, 0, 10, 0)]]
    preds = [[seg(0, 0, 10, 0, score=0.9)], [seg(0, 0, 10, 0, score=0.9), seg(0, 5, 10, 5, 2, score=0.9)]]
    m = run("raster", preds, gts)
    assert m["AP"]["divider"] == [1.0] * 3 and m["AP"]["boundary"] == [0.0] * 3
    assert all(math.isnan(v) for v in m["AP"]["ped_crossing"]) and math.isnan(m["mAP"])
    assert math.isnan(m["AP_class"]["ped_crossing"]) and m["samples_counted"]["boundary"] == 1


def test_raster_duplicates_and_single_points():
    # An exact duplicate overdraws the first copy, whose id vanishes: one predicted instance, AP 1.
    # A one-point prediction vanishes without trace (no FP, no confidence).
    gts = [[seg(-10, 0, 10, 0)]]
    preds = [[seg(-10, 0, 10, 0, score=0.9), seg(-10, 0, 10, 0, score=0.3),
              {"pts": np.array([[5.0, 5.0]]), "label": 0, "score": 1.0}]]
    m = run("raster", preds, gts)
    assert m["AP"]["divider"] == [1.0] * 3 and m["num_pred"]["divider"] == 1
    assert m["counters"]["dropped_short_predictions"] == 1


def test_raster_clipping_and_confidence_misalignment():
    frame = RasterFrame(GRID)
    # The GT leaves the patch at x = 30; clipped, it equals the prediction: AP 1.
    m = run("raster", [[seg(20, 0, 30, 0, score=1.0)]], [[seg(20, 0, 40, 0)]])
    assert m["AP"]["divider"] == [1.0] * 3
    # A U-shaped line leaving and re-entering the patch is clipped into two parts (ids 1, 2) but
    # appends one confidence; the next line gets id 3 and reads index 3 of [-1, .9, .4]: past the
    # end, i.e. the -1 padding. Id 2 reads .4, the second line's score.
    u = np.array([[0.0, 10.0], [0.0, 20.0], [5.0, 20.0], [5.0, 10.0]])
    pts = [u, np.array([[-10.0, -5.0], [10.0, -5.0]])]
    masks, conf = rasterize_instances(pts, np.array([0, 0]), np.array([0.9, 0.4]), frame)
    assert sorted(set(np.unique(masks[0])) - {0}) == [1, 2, 3] and conf.tolist() == pytest.approx([-1, 0.9, 0.4])
    masks, conf = rasterize_instances(pts, np.array([0, 0]), np.array([0.9, 0.4]), frame, fix_instance_ids=True)
    assert conf.tolist() == pytest.approx([-1, 0.9, 0.9, 0.4])
    # uint8 ids saturate: 300 separate lines -> ids 1..254 and 255 for all the rest.
    many = [np.array([[-29.0 + 0.19 * i, -14.0], [-29.0 + 0.19 * i, 14.0]]) for i in range(300)]
    masks, _ = rasterize_instances(many, np.zeros(300, int), np.ones(300), frame, num_classes=1, thickness=1)
    assert masks.max() == 255 and len(np.unique(masks)) == 256
    masks, _ = rasterize_instances(many, np.zeros(300, int), np.ones(300), frame, num_classes=1, thickness=1,
                                   fix_instance_ids=True)
    assert masks.max() == 300


def test_raster_matches_slow_reference_on_random_cases():
    rng = np.random.default_rng(4)
    preds, gts = random_raster_data(rng, 10)
    for rank_by in ("ascending", "descending"):
        m = run("raster", preds, gts, rank_by=rank_by)
        got = np.array([m["AP"][c] for c in m["classes"]])
        ref = raster_reference(preds, gts, rank_by=rank_by)
        np.testing.assert_allclose(got, ref, atol=1e-6)


# ---------------------------------------------------------------------------------------------
# Streaming, DDP-style merging
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("protocol", ["vector", "raster"])
def test_streaming_and_merge_equal_one_shot(protocol):
    rng = np.random.default_rng(5)
    preds, gts = random_vector_data(rng, 24) if protocol == "vector" else random_raster_data(rng, 8)
    ids = list(range(len(preds)))
    one = Evaluator(protocol)
    one.update(preds, gts, sample_ids=ids)
    chunked = Evaluator(protocol)
    for s, e in ((0, 1), (1, 4), (4, len(preds))):
        chunked.update(preds[s:e], gts[s:e], sample_ids=ids[s:e])
    # Two "ranks" with strided samples (DistributedSampler order), merged as gather() does.
    ranks = [Evaluator(protocol) for _ in range(2)]
    for r, ev in enumerate(ranks):
        ev.update(preds[r::2], gts[r::2], sample_ids=ids[r::2])
    merged = Evaluator(protocol)
    for ev in ranks:
        merged.merge(ev.state_dict())
    a, b, c = one.compute(), chunked.compute(), merged.compute()
    assert a["AP"] == b["AP"] and a["mAP"] == b["mAP"]
    for k in a["classes"]:
        np.testing.assert_allclose(a["AP"][k], c["AP"][k], rtol=0, atol=1e-12)


# ---------------------------------------------------------------------------------------------
# Input checks, JSON I/O, CLI
# ---------------------------------------------------------------------------------------------


def test_evaluator_from_config():
    from instagram_hdmap.config import load_config

    ev = Evaluator.from_config(load_config(None, ["eval.protocol=raster", "eval.rank_by=descending"]))
    assert ev.protocol == "raster" and ev.options["rank_by"] == "descending" and ev.thresholds == THR


def test_also_protocols_score_the_same_predictions_and_merge_like_the_main_one():
    """eval.also_protocols (the paper configs: raster, and vector as well): each protocol as if run alone,
    streamed and merged across "ranks" together with the main one, reported under metrics["also"]."""
    from instagram_hdmap.config import load_config
    from instagram_hdmap.evaluation import format_table

    rng = np.random.default_rng(6)
    preds, gts = random_raster_data(rng, 8)
    ids = list(range(len(preds)))
    cfg = load_config(None, ["eval.protocol=raster", "eval.also_protocols=[vector]"])
    ranks = [Evaluator.from_config(cfg) for _ in range(2)]
    for r, ev in enumerate(ranks):
        ev.update(preds[r::2], gts[r::2], sample_ids=ids[r::2])
    merged = Evaluator.from_config(cfg)
    for ev in ranks:
        merged.merge(ev.state_dict())
    got = merged.compute()
    alone = {}
    for protocol in ("raster", "vector"):
        ev = Evaluator(protocol, grid=BEVGrid.from_config(cfg.grid))
        ev.update(preds, gts, sample_ids=ids)
        alone[protocol] = ev.compute()
    assert got["protocol"] == "raster" and list(got["also"]) == ["vector"] and "also" not in got["also"]["vector"]
    for name, metrics in (("raster", got), ("vector", got["also"]["vector"])):
        assert metrics["protocol"] == name
        np.testing.assert_allclose(metrics["mAP"], alone[name]["mAP"], rtol=0, atol=1e-12)
    table = format_table(got)
    assert "protocol: raster" in table and "protocol: vector" in table
    # the override of one protocol (evaluate --protocol vector) does not score vector twice
    assert list(Evaluator("vector", also=("vector", "raster")).also) == ["raster"]


def test_bad_inputs_raise_clear_errors():
    with pytest.raises(EvaluationInputError, match="> 0"):
        Evaluator("vector", thresholds=(0.5, 0.0))
    with pytest.raises(EvaluationInputError, match="at most 10 m"):
        Evaluator("vector", thresholds=(150.0,))
    ev = Evaluator("vector")
    with pytest.raises(EvaluationInputError, match=r"sample 'a', prediction polyline 0: .*NaN"):
        ev.update([[{"pts": [[0, 0], [np.nan, 1]], "label": 0, "score": 1.0}]], [[]], tokens=["a"])
    with pytest.raises(EvaluationInputError, match="unknown class id 3"):
        ev.update([[seg(0, 0, 1, 1, 3, score=1.0)]], [[]])
    with pytest.raises(EvaluationInputError, match="score"):
        ev.update([[seg(0, 0, 1, 1)]], [[]])
    # Raster: a one-point GT is dropped and counted (the reference drops it).
    m = run("raster", [[]], [[{"pts": np.zeros((1, 2)), "label": 0}]])
    assert m["counters"]["dropped_short_gt"] == 1


def test_submission_io(tmp_path):
    path = tmp_path / "sub.json"
    write_submission(path, {"t1": [seg(0, 0, 1, 1, 2, score=0.25)], "t2": []}, meta={"note": "x"})
    sub = read_submission(path, "pred")
    assert list(sub.samples) == ["t1", "t2"] and sub.meta["vector"] is True
    p = sub.samples["t1"][0]
    assert p["label"] == 2 and p["score"] == 0.25 and np.array_equal(p["pts"], [[0, 0], [1, 1]])
    # InstaGraM's list form, pts_num truncation, missing confidence -> 1.0 with notes.
    path.write_text(json.dumps({"meta": {}, "results": [
        {"sample_token": "t", "vectors": [{"pts": [[0, 0], [1, 0], [9, 9]], "pts_num": 2, "type": 0}]}]}))
    sub = read_submission(path, "pred")
    assert sub.samples["t"][0]["pts"].shape == (2, 2) and sub.samples["t"][0]["score"] == 1.0
    assert len(sub.notes) == 2
    bad = {
        "{not json": "not valid JSON",
        json.dumps({"meta": {}}): "no 'results'",
        json.dumps({"results": {"t": [{"pts": [[0, 0], [1, "x"]], "type": 0}]}}): r"sample 't', vector 0",
        json.dumps({"results": {"t": [{"pts": [[0, 0], [1, 1]], "type": 5}]}}): "type",
        json.dumps({"results": {"t": [{"pts": [[0, 0], [1, 1]], "pts_num": 3, "type": 0}]}}): "pts_num",
        json.dumps({"results": [{"sample_token": "t", "vectors": []}, {"sample_token": "t", "vectors": []}]}): "twice",
    }
    for text, msg in bad.items():
        path.write_text(text)
        with pytest.raises(SubmissionError, match=msg):
            read_submission(path, "pred")
    path.write_text('{"results": {"t": [{"pts": [[0, 0], [NaN, 1]], "type": 0}]}}')
    with pytest.raises(SubmissionError, match="NaN"):
        read_submission(path, "gt")


def test_cli_evaluate_json(tmp_path, capsys):
    gts = {"a": [seg(0, 0, 10, 0)], "b": [seg(0, 5, 10, 5, 2)], "c": [seg(-5, -5, 5, -5, 1)]}
    preds = {"a": [seg(0, 0, 10, 0, score=0.9)], "b": [seg(0, 5, 10, 5, 2, score=0.8)]}  # "c" missing
    write_submission(tmp_path / "gt.json", gts)
    write_submission(tmp_path / "pred.json", preds)
    out = tmp_path / "m.json"
    args = ["evaluate-json", "--pred", str(tmp_path / "pred.json"), "--gt", str(tmp_path / "gt.json")]
    assert main([*args, "--out", str(out)]) == 0
    m = json.loads(out.read_text())
    assert m["protocol"] == "vector" and m["classes"] == ["divider", "ped_crossing", "boundary"]
    assert m["AP"]["ped_crossing"] == [0.0] * 3 and m["mAP"] == pytest.approx(2 / 3)
    assert any("1 of 3 GT samples have no entry" in n for n in m["notes"])
    printed = capsys.readouterr().out
    assert "protocol: vector" in printed and "mAP" in printed
    # Raster: "c" counts a ped_crossing sample with AP 0; NaN nowhere here.
    assert main([*args, "--protocol", "raster", "--out", str(out)]) == 0
    m = json.loads(out.read_text())
    assert m["AP_class"] == {"divider": 1.0, "ped_crossing": 0.0, "boundary": 1.0}
    # NaN is written as null (standard JSON): raster with no boundary anywhere.
    write_submission(tmp_path / "gt2.json", {"a": gts["a"]})
    assert main(["evaluate-json", "--pred", str(tmp_path / "pred.json"), "--gt", str(tmp_path / "gt2.json"),
                 "--protocol", "raster", "--out", str(out), "--ignore-extra-predictions"]) == 0
    assert json.loads(out.read_text(), parse_constant=pytest.fail)["mAP"] is None
    # Prediction tokens missing from the GT: an error unless ignored; a bad threshold: an error.
    capsys.readouterr()
    assert main(["evaluate-json", "--pred", str(tmp_path / "pred.json"), "--gt", str(tmp_path / "gt2.json")]) == 2
    assert "1 of 2 sample tokens are not in the GT file" in capsys.readouterr().err
    assert main([*args, "--thresholds", "0.5", "-1"]) == 2
    assert "> 0" in capsys.readouterr().err


def _ddp_worker(rank, world, init_file, out_file):
    torch.distributed.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=world)
    try:
        result = {}
        for protocol, (preds, gts) in _ddp_data().items():
            ev = Evaluator(protocol)
            ids = list(range(rank, len(preds), world))  # DistributedSampler(shuffle=False) order
            ev.update([preds[i] for i in ids], [gts[i] for i in ids], sample_ids=ids)
            ev.gather()  # every rank now holds the merged state
            result[protocol] = ev.compute()["AP"]
        if rank == 0:
            with open(out_file, "w") as f:
                json.dump(result, f)
    finally:
        torch.distributed.destroy_process_group()


def _ddp_data():
    return {"vector": random_vector_data(np.random.default_rng(6), 12),
            "raster": random_raster_data(np.random.default_rng(6), 4)}


def test_gather_under_torch_distributed(tmp_path):
    # Two gloo processes, strided samples, gather() then compute() == one process over all samples.
    out = tmp_path / "ap.json"
    torch.multiprocessing.spawn(_ddp_worker, args=(2, str(tmp_path / "init"), str(out)), nprocs=2)
    got = json.loads(out.read_text())
    for protocol, (preds, gts) in _ddp_data().items():
        ref = run(protocol, preds, gts)["AP"]
        for c in ref:
            np.testing.assert_allclose(got[protocol][c], ref[c], rtol=0, atol=1e-12)
