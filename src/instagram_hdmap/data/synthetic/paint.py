"""What is painted on and put beside a synthetic road: lane lines, zebra stripes and road patches
(the markings the cameras see), and the buildings, trees and poles beside the road.
"""

from __future__ import annotations

import math

import numpy as np
from shapely import prepared
from shapely.geometry import Polygon, box

from .network import Box, MapStyle, Markings, RoadNetwork, Stretch
from .paths import Path


def _strip(path: Path, s0: float, s1: float, d: float, width: float) -> np.ndarray:
    """Polygon [P, 2] of a painted strip of `width` centred `d` m left of `path`, over s in [s0, s1]."""
    n = max(2, int(math.ceil((s1 - s0) / 0.5)) + 1)
    poses = path.pose_at(np.linspace(s0, s1, n))
    nrm = np.stack([-np.sin(poses[:, 2]), np.cos(poses[:, 2])], axis=-1)
    left = poses[:, :2] + (d + width / 2) * nrm
    right = poses[:, :2] + (d - width / 2) * nrm
    return np.concatenate([left, right[::-1]])


def paint_stretch(st: Stretch, style: MapStyle, out: Markings) -> None:
    w = style.line_width
    for j, kind in enumerate(st.kinds):
        if kind != "lane":
            continue
        s = 0.5
        while s + style.dash <= st.path.length - 0.5:
            out.white.append(_strip(st.path, s, s + style.dash, float(st.rows[j]), w))
            s += style.dash + style.gap
    spans = [(0.0, st.path.length)]
    if st.island is not None:
        spans = [(0.0, st.island[0]), (st.island[1], st.path.length)]
    for s0, s1 in spans:
        if s1 - s0 < 0.2:
            continue
        if st.chain.divider == "double_yellow":
            off = (style.double_gap + w) / 2
            out.yellow += [_strip(st.path, s0, s1, off, w), _strip(st.path, s0, s1, -off, w)]
        elif st.chain.divider == "single_yellow":
            out.yellow.append(_strip(st.path, s0, s1, 0.0, w))
        else:
            out.white.append(_strip(st.path, s0, s1, 0.0, w))


def zebra(c, u, n, t0, t1, lat0, lat1, bar: float = 0.5, gap: float = 0.5) -> list[np.ndarray]:
    span = lat1 - lat0 - 0.4
    count = int((span + gap) // (bar + gap))
    first = lat0 + 0.2 + (span - (count * bar + (count - 1) * gap)) / 2
    out = []
    for k in range(count):
        l0 = first + k * (bar + gap)
        corners = [(t0, l0), (t1, l0), (t1, l0 + bar), (t0, l0 + bar)]
        out.append(np.array([c + t * u + lat * n for t, lat in corners]))
    return out


def add_patches(stretches: list[Stretch], out: Markings, rng) -> None:
    """Asphalt repair patches (world-fixed): they darken/lighten the road and wear markings away."""
    for st in stretches:
        for _ in range(int(rng.integers(0, 4))):
            s0 = float(rng.uniform(0.0, max(st.path.length - 4.0, 0.1)))
            s1 = min(st.path.length, s0 + float(rng.uniform(1.0, 4.0)))
            d0 = float(rng.uniform(st.rows[0], st.rows[-1] - 1.0))
            d1 = min(float(st.rows[-1]), d0 + float(rng.uniform(0.8, 3.0)))
            out.patches.append((_strip(st.path, s0, s1, (d0 + d1) / 2, d1 - d0), float(rng.uniform(-20.0, 12.0))))


BUILDING_COLORS = [(150, 160, 170), (120, 130, 150), (90, 110, 160), (170, 175, 180), (140, 120, 100),
                   (200, 190, 170), (110, 100, 95), (160, 140, 120)]


TREE_COLORS = [(40, 90, 50), (30, 80, 60), (50, 110, 70), (35, 70, 45)]


def place_props(net: RoadNetwork, outer, rng) -> list[Box]:
    props: list[Box] = []
    free = prepared.prep(box(0, 0, *net.canvas).difference(outer.buffer(1.0)))
    road_near = prepared.prep(net.road_filled.buffer(0.3))
    placed: list[tuple[np.ndarray, float, Polygon]] = []  # (centre, radius, footprint)
    for st in net.stretches:
        for side in (-1.0, 1.0):
            half = st.chain.w_left if side > 0 else st.chain.w_right
            s = float(rng.uniform(0.0, 10.0))
            while s < st.path.length:
                front, depth = float(rng.uniform(8.0, 30.0)), float(rng.uniform(8.0, 25.0))
                setback = float(rng.uniform(1.0, 6.0))
                x, y, yaw = st.path.pose_at(s + front / 2)[0]
                nrm = np.array([-math.sin(yaw), math.cos(yaw)])
                c = np.array([x, y]) + side * (half + net.style.sidewalk + setback + depth / 2) * nrm
                b = Box(float(c[0]), float(c[1]), float(yaw), front, depth, 0.0, float(rng.uniform(6.0, 30.0)),
                        BUILDING_COLORS[int(rng.integers(len(BUILDING_COLORS)))], "building")
                fp = Polygon(b.footprint())
                radius = math.hypot(front, depth) / 2
                clear = all(np.hypot(*(c - c2)) > radius + r2 + 1.0 or fp.distance(p2) >= 1.0
                            for c2, r2, p2 in placed)
                if clear and free.contains(fp):
                    placed.append((c, radius, fp))
                    props.append(b)
                s += front + float(rng.uniform(2.0, 15.0))
            s = float(rng.uniform(0.0, 15.0))
            while s < st.path.length:  # trees on the sidewalk, poles at the kerb
                x, y, yaw = st.path.pose_at(s)[0]
                nrm = np.array([-math.sin(yaw), math.cos(yaw)])
                if rng.random() < 0.5:
                    c = np.array([x, y]) + side * (half + net.style.sidewalk - 0.7) * nrm
                    if not road_near.intersects(square(c, yaw, 0.4)):
                        top = float(rng.uniform(4.5, 8.0))
                        size = float(rng.uniform(2.5, 4.5))
                        props.append(Box(float(c[0]), float(c[1]), float(yaw), 0.35, 0.35, 0.0, 2.8, (40, 60, 80),
                                         "trunk"))
                        props.append(Box(float(c[0]), float(c[1]), float(yaw + rng.uniform(0, 1)), size, size,
                                         2.4, top, TREE_COLORS[int(rng.integers(len(TREE_COLORS)))], "tree"))
                else:
                    c = np.array([x, y]) + side * (half + 0.6) * nrm
                    if not road_near.intersects(square(c, yaw, 0.3)):
                        props.append(Box(float(c[0]), float(c[1]), float(yaw), 0.25, 0.25, 0.0,
                                         float(rng.uniform(4.5, 7.5)), (120, 125, 128), "pole"))
                s += float(rng.uniform(12.0, 30.0))
    return props


def square(c: np.ndarray, yaw: float, size: float) -> Polygon:
    return Polygon(Box(float(c[0]), float(c[1]), yaw, size, size, 0.0, 1.0, (0, 0, 0), "").footprint())
