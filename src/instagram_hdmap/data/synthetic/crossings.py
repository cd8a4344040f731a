"""Where a junction's zebra crossings lie: which corners get two overlapping crossings (as real
junctions have) and the band of road each crossing covers.
"""

from __future__ import annotations

import numpy as np

from .network import STOP_LINE_WIDTH, Junction

# Real crossings overlap where two of them meet at a junction corner: in the real AV2 log of
# ../shared/av2_real, all 9 pairs of crossings on adjacent arms of a junction overlap, by 1.1-4.7 m^2
# (median 2.9 m^2; 10 of its 11 crossings overlap a neighbour); AV2 logs show 1-12 m^2 over more junctions.
OVERLAP_FILLET_M = (0.5, 1.5)  # kerb radii of a junction whose crossings overlap (a tight city corner)
OVERLAP_GAP_M = 0.3  # there, the crossings start this far past the kerb corner (elsewhere 1 m)
OVERLAP_DEPTH_M = (1.0, 2.2)  # how far each crossing reaches into the other's band: 1.0-4.8 m^2
# ... but a crossing is stretched at most this far past the kerb: where the roads' widths differ a lot,
# the other crossing lies too far out and the corner's crossings stay apart
OVERLAP_MAX_REACH_M = 8.0
CITY_JUNCTION_P = 0.5  # a 4-way junction has a crossing on every arm with this probability (else 0.75 each)


def overlapping_corners(codes: list[int], crossing: dict[int, bool], fillet: dict[int, float],
                         rng: np.random.Generator) -> dict[int, tuple[float, float]]:
    """The junction corners whose two arms (a, a + 1) both have a crossing (every arm of a 4-way junction
    has one with probability ``CITY_JUNCTION_P``, where the four crossings ring the junction as in the
    real log) get crossings that overlap there, as real ones do (the rate above): the overlap's depths
    along the two arms (``crossing_corners`` stretches both crossings past the kerb that far into each
    other's band), and the junction tight kerb radii (``fillet`` set in place) so that the crossings lie
    near the corner.
    Returns {corner a: (depth along a, depth along a + 1)}; ``drop_far_overlaps`` keeps the reachable."""
    if len(codes) == 4 and rng.random() < CITY_JUNCTION_P:  # a crossing on every arm (``crossing`` in place)
        crossing.update({a: True for a in codes})
    out = {}
    for a in codes:
        b = (a + 1) % 4
        if b in codes and crossing[a] and crossing[b]:
            out[a] = (float(rng.uniform(*OVERLAP_DEPTH_M)), float(rng.uniform(*OVERLAP_DEPTH_M)))
    if out:
        fillet.update({a: float(rng.uniform(*OVERLAP_FILLET_M)) for a in codes})
    return out


def drop_far_overlaps(jn: Junction) -> None:
    """Keep the overlapping corners of ``jn`` whose two crossings reach each other within
    ``OVERLAP_MAX_REACH_M`` past the kerb."""
    def reach(a: int) -> float:
        b = (a + 1) % 4
        depth_a, depth_b = jn.overlap[a]
        return max(crossing_band(jn, b)[0] + depth_b - jn.wl[a], crossing_band(jn, a)[0] + depth_a - jn.wr[b])

    jn.overlap = {a: d for a, d in jn.overlap.items() if reach(a) <= OVERLAP_MAX_REACH_M}


def crossing_band(jn: Junction, a: int) -> tuple[float, float]:
    """(t0, t1): distances from the junction centre along arm a between which its crossing lies (4 m
    wide, 0.8 m before the stop line)."""
    t1 = jn.D[a] - 0.3 - STOP_LINE_WIDTH - 0.8
    return t1 - 4.0, t1


def crossing_corners(jn: Junction, a: int) -> list[tuple[float, float]]:
    """The crossing polygon of arm a as (t along the arm, lateral offset to its left) corners: across the
    road (-wr to wl), and, at a corner whose crossings overlap, past the kerb into the neighbouring
    crossing's band (``Junction.overlap``; the zebra paint stays on the road)."""
    t0, t1 = crossing_band(jn, a)
    left, right = jn.wl[a], -jn.wr[a]
    if a in jn.overlap:  # corner (a, a + 1): arm a + 1 runs along the left of arm a
        left = crossing_band(jn, (a + 1) % 4)[0] + jn.overlap[a][1]
    prev = (a - 1) % 4
    if prev in jn.overlap:  # corner (a - 1, a): arm a - 1 runs along the right of arm a
        right = -(crossing_band(jn, prev)[0] + jn.overlap[prev][0])
    return [(t0, right), (t1, right), (t1, left), (t0, left)]
