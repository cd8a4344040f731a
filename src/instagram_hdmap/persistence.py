"""Element persistence over a drive: a map element found in the previous frames and missed in this one is kept.

    keep = Persistence.from_config(cfg)          # None when model.temporal.persist_frames = 0 (off)
    preds = keep(preds, scenes, frames, poses)   # a batch's polyline dicts, in each scene's frame order

A detector's output changes its mind from frame to frame about elements it keeps seeing (the flicker rate,
evaluation/consistency.py): an element near its confidence or match threshold is found in one frame and missed
in the next. Trackers answer this with a track's age (a track survives ``max_age`` missed frames:
tracking-by-detection, SORT's rule); this is that rule for map elements, with the ego motion known:

* After frame t of a scene, every output element (polyline dict, ego frame of t) is remembered with a count
  of the frames it has been missed.
* At frame t + 1 of the same scene (the next frame index; the ego moved at most ``max_jump_m``), each
  remembered element is moved into the new ego frame by the two ego poses. One that an output element of its
  class lies on (symmetric Chamfer distance, both resampled to 20 points, at most ``match_m``) is dropped:
  the new output stands for it. One that none does, and that has been missed fewer than ``frames`` times, is
  added to the output with its score times ``decay`` (so it ranks below what the model sees now) and its miss
  count + 1; its points beyond the BEV grid are cut away (the longest run of points inside is kept; fewer
  than two: dropped).
* Any other frame (a scene's first, a gap, a repeat, a pose jump) starts the scene anew.

``frames = 0`` is off (the model's output unchanged). Samples of a scene must come in frame order; samples of
several scenes may interleave (streams), each scene's state is its own. Under torchrun, a single-frame model's
evaluation gives each rank every world-size-th sample, so a rank never sees consecutive frames: persistence
then changes nothing (a temporal model's streams walk whole scenes on one rank).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from .geometry import BEVGrid

MATCH_POINTS = 20  # points per polyline for the "is it the same element" Chamfer test


@dataclass
class _Scene:
    frame: int
    pose: np.ndarray  # [4, 4] ego -> world, float64
    elements: list[tuple[dict, int]]  # (polyline dict in this frame's ego frame, frames missed)


def _resample(pts: np.ndarray, n: int) -> np.ndarray:
    """[P, 2] -> [n, 2] equally spaced in arc length."""
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0:
        return np.repeat(pts[:1], n, axis=0)
    t = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(t, s, pts[:, 0]), np.interp(t, s, pts[:, 1])], axis=1)


def _nearest_chamfer(a: np.ndarray, b: np.ndarray, chunk: int = 32) -> np.ndarray:
    """[K, n, 2] against [M, n, 2] -> [K]: each of ``a``'s smallest symmetric Chamfer distance (mean nearest
    distance both ways, halved) to any of ``b``; ``chunk`` rows of ``a`` at a time bound the [k, M, n, n] block."""
    n = a.shape[1]
    out = np.empty(len(a))
    for s in range(0, len(a), chunk):
        d = np.sqrt(((a[s:s + chunk, None, :, None] - b[None, :, None]) ** 2).sum(-1))  # [k, M, n, n]
        out[s:s + chunk] = ((d.min(3).sum(2) + d.min(2).sum(2)) / (2 * n)).min(1)
    return out


def _inside_run(pts: np.ndarray, grid: BEVGrid) -> np.ndarray:
    """The longest run of consecutive points of ``pts`` inside the grid."""
    inside = ((pts[:, 0] >= grid.xmin) & (pts[:, 0] <= grid.xmax) & (pts[:, 1] >= grid.ymin)
              & (pts[:, 1] <= grid.ymax))
    start, best_span = None, (0, 0)
    for i, ok in enumerate([*inside.tolist(), False]):
        if ok and start is None:
            start = i
        elif not ok and start is not None:
            if i - start > best_span[1] - best_span[0]:
                best_span = (start, i)
            start = None
    return pts[best_span[0]:best_span[1]]


class Persistence:
    """The rule of the module docstring; ``__call__`` takes a batch, ``step`` one sample."""

    def __init__(self, grid: BEVGrid, frames: int = 1, decay: float = 0.5, match_m: float = 1.0,
                 max_jump_m: float = 10.0):
        if isinstance(frames, bool) or not isinstance(frames, int) or frames < 0:
            raise ValueError(f"Persistence: frames must be an integer >= 0, got {frames!r}")
        if not (0 < decay <= 1) or not (match_m > 0) or not (max_jump_m > 0):
            raise ValueError(f"Persistence: decay must be in (0, 1], match_m and max_jump_m > 0; got {decay}, "
                             f"{match_m}, {max_jump_m}")
        self.grid, self.frames, self.decay, self.match_m, self.max_jump_m = grid, frames, decay, match_m, max_jump_m
        self.kept = 0  # elements added to an output so far
        self.reset()

    @classmethod
    def from_config(cls, cfg) -> Persistence | None:
        """``model.temporal.persist_*`` of an ``ExperimentConfig``; None when ``persist_frames`` is 0."""
        t = cfg.model.temporal
        if t.persist_frames == 0:
            return None
        return cls(BEVGrid.from_config(cfg.grid), t.persist_frames, t.persist_decay, t.persist_match_m,
                   t.max_jump_m)

    def reset(self) -> None:
        self.scenes: dict[str, _Scene] = {}

    def __call__(self, preds: Sequence[list[dict]], scenes: Sequence[str], frames, poses) -> list[list[dict]]:
        frames = frames.tolist() if hasattr(frames, "tolist") else list(frames)
        poses = poses.detach().cpu().double().numpy() if isinstance(poses, torch.Tensor) else np.asarray(poses)
        return [self.step(p, str(s), int(f), poses[b]) for b, (p, s, f) in enumerate(zip(preds, scenes, frames))]

    def step(self, preds: list[dict], scene: str, frame: int, pose) -> list[dict]:
        """One sample's output with the remembered elements the model missed added (module docstring)."""
        pose = np.asarray(pose.detach().cpu() if isinstance(pose, torch.Tensor) else pose, dtype=np.float64)
        prev = self.scenes.get(scene)
        carried: list[tuple[dict, int]] = []
        if (prev is not None and frame == prev.frame + 1
                and np.linalg.norm(pose[:3, 3] - prev.pose[:3, 3]) <= self.max_jump_m):
            to_now = np.linalg.inv(pose) @ prev.pose  # previous ego frame -> this one
            now: dict[int, list[np.ndarray]] = {}  # class -> resampled outputs of this frame
            for p in preds:
                if len(p["pts"]) >= 2:
                    now.setdefault(int(p["label"]), []).append(_resample(np.asarray(p["pts"], np.float64),
                                                                         MATCH_POINTS))
            moved = []  # (element, missed, its points in this ego frame within the grid)
            for element, missed in prev.elements:
                if missed >= self.frames:
                    continue
                pts = np.asarray(element["pts"], np.float64)
                pts = pts @ to_now[:2, :2].T + to_now[:2, 3]  # the map is the ground plane: x, y of the ego frame
                pts = _inside_run(pts, self.grid)
                if len(pts) >= 2:
                    moved.append((element, missed, pts))
            found = np.zeros(len(moved), dtype=bool)
            for label in {int(element["label"]) for element, _, _ in moved} & set(now):
                rows = [i for i, (element, _, _) in enumerate(moved) if int(element["label"]) == label]
                mine = np.stack([_resample(moved[i][2], MATCH_POINTS) for i in rows])
                found[rows] = _nearest_chamfer(mine, np.stack(now[label])) <= self.match_m  # the model found it again
            for (element, missed, pts), again in zip(moved, found):
                if again:
                    continue
                closed = bool(element.get("closed", False)) and len(pts) == len(element["pts"])
                carried.append(({**element, "pts": pts.astype(np.asarray(element["pts"]).dtype, copy=False),
                                 "closed": closed, "score": float(element["score"]) * self.decay}, missed + 1))
        self.scenes[scene] = _Scene(frame, pose, [(p, 0) for p in preds] + carried)
        self.kept += len(carried)
        return list(preds) + [element for element, _ in carried]
