"""Analytic planar paths made of straight pieces and circular arcs.

A :class:`Path` is the one description of every curve in the synthetic world: road centre lines,
lane centre lines (offsets of the road's), junction connectors and the ego's route. Poses are
``(x, y, yaw)`` in metres / radians, yaw counter-clockwise from +x. An arc of signed curvature
``k`` (> 0 turns left) and length ``L`` maps one-to-one to a nuScenes ``arcline_path_3`` record.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

STRAIGHT_RADIUS = 999.0  # radius written for straight arcline records (the devkit ignores it: sign 0)


@dataclass(frozen=True)
class Prim:
    """One primitive: start pose, signed curvature k (1/m, > 0 turns left), length (m)."""

    x: float
    y: float
    yaw: float
    k: float
    length: float

    def at(self, t: np.ndarray) -> np.ndarray:
        """Poses [n, 3] at distances t [n] from the start of this primitive."""
        t = np.asarray(t, dtype=np.float64)
        if self.k == 0.0:
            c, s = math.cos(self.yaw), math.sin(self.yaw)
            return np.stack([self.x + t * c, self.y + t * s, np.full_like(t, self.yaw)], axis=-1)
        yaw = self.yaw + self.k * t
        x = self.x + (np.sin(yaw) - math.sin(self.yaw)) / self.k
        y = self.y - (np.cos(yaw) - math.cos(self.yaw)) / self.k
        return np.stack([x, y, yaw], axis=-1)

    def end(self) -> tuple[float, float, float]:
        x, y, yaw = self.at(np.array([self.length]))[0]
        return float(x), float(y), float(yaw)


class Path:
    """A chain of primitives, each starting where the previous one ends."""

    def __init__(self, prims: list[Prim] | tuple[Prim, ...]):
        self.prims = tuple(p for p in prims if p.length > 1e-9)
        if not self.prims:
            raise ValueError("a Path needs at least one primitive of positive length")
        lengths = np.array([p.length for p in self.prims])
        self.starts = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
        self.length = float(lengths.sum())

    # --- evaluation ---------------------------------------------------------------------------
    def pose_at(self, s: np.ndarray | float) -> np.ndarray:
        """Poses [n, 3] at arc lengths s [n] (clipped to [0, length])."""
        s = np.clip(np.atleast_1d(np.asarray(s, dtype=np.float64)), 0.0, self.length)
        idx = np.clip(np.searchsorted(self.starts, s, side="right") - 1, 0, len(self.prims) - 1)
        out = np.empty((s.shape[0], 3))
        for i, p in enumerate(self.prims):
            m = idx == i
            if m.any():
                out[m] = p.at(s[m] - self.starts[i])
        return out

    def start_pose(self) -> tuple[float, float, float]:
        p = self.prims[0]
        return p.x, p.y, p.yaw

    def end_pose(self) -> tuple[float, float, float]:
        return self.prims[-1].end()

    def sample_s(self, max_step: float = 2.0, max_sagitta: float = 0.004) -> np.ndarray:
        """Arc lengths [n] that sample the path: every primitive end, straight pieces every
        <= max_step metres, arcs finely enough that chords stay within max_sagitta of the arc."""
        out = [np.zeros(1)]
        for p, s0 in zip(self.prims, self.starts):
            step = max_step
            if p.k != 0.0:
                step = min(max_step, math.sqrt(8.0 / abs(p.k) * max_sagitta))
            n = max(1, math.ceil(p.length / step - 1e-9))
            out.append(s0 + np.linspace(0.0, p.length, n + 1)[1:])
        s = np.concatenate(out)
        s[-1] = self.length
        return s

    # --- derived paths ------------------------------------------------------------------------
    def offset(self, d: float) -> Path:
        """The parallel path d metres to the left (d < 0: to the right)."""
        prims = []
        for p in self.prims:
            scale = 1.0 - p.k * d
            if scale <= 1e-6:
                raise ValueError(f"offset {d} m exceeds the radius {1 / p.k:.2f} m of an arc")
            prims.append(Prim(p.x - d * math.sin(p.yaw), p.y + d * math.cos(p.yaw), p.yaw, p.k / scale,
                              p.length * scale))
        return Path(prims)

    def reversed(self) -> Path:
        prims = []
        for p in reversed(self.prims):
            x, y, yaw = p.end()
            prims.append(Prim(x, y, yaw + math.pi, -p.k, p.length))
        return Path(prims)

    @staticmethod
    def concat(paths: list[Path]) -> Path:
        return Path([p for path in paths for p in path.prims])

    def arclines(self) -> list[dict]:
        """The path as nuScenes ``arcline_path_3`` records (one per primitive)."""
        out = []
        for p in self.prims:
            x1, y1, yaw1 = p.end()
            if p.k == 0.0:
                shape, radius, seg = "LSR", STRAIGHT_RADIUS, [0.0, p.length, 0.0]
            else:
                shape, radius, seg = ("LSL" if p.k > 0 else "RSR"), 1.0 / abs(p.k), [p.length, 0.0, 0.0]
            out.append({"start_pose": [p.x, p.y, principal_angle(p.yaw)], "end_pose": [x1, y1, principal_angle(yaw1)],
                        "shape": shape, "radius": radius, "segment_length": seg})
        return out


def principal_angle(a: float) -> float:
    """Angle in [-pi, pi)."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


class Turtle:
    """Builds a Path by driving: ``Turtle(x, y, yaw).straight(10).arc(math.pi / 2, 20).path()``."""

    def __init__(self, x: float, y: float, yaw: float):
        self.pose = (x, y, yaw)
        self.prims: list[Prim] = []

    def straight(self, length: float) -> Turtle:
        if length > 1e-9:
            self._add(Prim(*self.pose, 0.0, length))
        return self

    def arc(self, angle: float, radius: float) -> Turtle:
        """Turn by `angle` radians (> 0 left) on a circle of `radius` metres."""
        if abs(angle) > 1e-12:
            self._add(Prim(*self.pose, math.copysign(1.0 / radius, angle), abs(angle) * radius))
        return self

    def _add(self, p: Prim) -> None:
        self.prims.append(p)
        self.pose = p.end()

    def path(self) -> Path:
        return Path(self.prims)


def connect(start: tuple[float, float, float], end: tuple[float, float, float]) -> Path | None:
    """A smooth path from pose `start` to pose `end` when their headings differ by 0 or +-90 deg:
    straight, an S-curve of two equal arcs, or straight-arc-straight. None when impossible
    (U-turn, or the end is not ahead)."""
    x0, y0, yaw0 = start
    dx_w, dy_w = end[0] - x0, end[1] - y0
    c, s = math.cos(yaw0), math.sin(yaw0)
    dx, dy = c * dx_w + s * dy_w, -s * dx_w + c * dy_w
    dyaw = principal_angle(end[2] - yaw0)
    t = Turtle(*start)
    if abs(dyaw) < 1e-6:
        if dx <= 0.5:
            return None
        if abs(dy) < 1e-6:
            return t.straight(dx).path()
        theta = 2.0 * math.atan2(abs(dy), dx)
        r = dx / (2.0 * math.sin(theta))
        sign = math.copysign(1.0, dy)
        return t.arc(sign * theta, r).arc(-sign * theta, r).path()
    if abs(abs(dyaw) - math.pi / 2) < 1e-6:
        sign = math.copysign(1.0, dyaw)
        if dx <= 0.5 or sign * dy <= 0.5:
            return None
        r = min(dx, sign * dy)
        return t.straight(dx - r).arc(sign * math.pi / 2, r).straight(sign * dy - r).path()
    return None
