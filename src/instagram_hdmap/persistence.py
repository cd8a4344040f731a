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
* Any other frame (a scene's first, a gap, a repeat, a pose jump: moved more than ``max_jump_m`` or turned more
  than ``max_turn_deg``, as models/temporal.py's memory) starts the scene anew.

A bad argument (a pose that is not a finite rigid 4x4, a frame index that is not an integer, arguments of
different lengths, an element without ``pts`` [P, 2], ``label`` or ``score``) is a ``PersistenceInputError``
naming it, before anything is remembered.

``frames = 0`` is off (the model's output unchanged). Samples of a scene must come in frame order; samples of
several scenes may interleave (streams), each scene's state is its own. Under torchrun, a single-frame model's
evaluation gives each rank every world-size-th sample, so a rank never sees consecutive frames: persistence
then changes nothing (a temporal model's streams walk whole scenes on one rank).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from .config import ExperimentConfig, GridConfig, as_config
from .errors import UserError, as_batch_list, as_float64_array, check_rigid_pose, is_real
from .geometry import BEVGrid

MATCH_POINTS = 20  # points per polyline for the "is it the same element" Chamfer test


class PersistenceInputError(UserError, ValueError):
    """An argument of ``Persistence`` or its call that it cannot use; the message names it (and the sample)."""


def _check_grid(grid, who: str) -> BEVGrid:
    if isinstance(grid, ExperimentConfig):  # a config's grid: the grid it describes
        grid = grid.grid
    if isinstance(grid, GridConfig):
        grid = BEVGrid.from_config(grid)
    if not isinstance(grid, BEVGrid):
        raise PersistenceInputError(f"{who}: grid must be a BEVGrid (BEVGrid.from_config(cfg.grid)) or a "
                                    f"config, got {type(grid).__name__}")
    return grid


# the ranges of the numeric arguments of Persistence and InstanceTracker
LIMITS = {"decay": lambda v: 0 < v <= 1, "match_m": lambda v: v > 0, "max_jump_m": lambda v: v > 0,
          "max_turn_deg": lambda v: 0 < v <= 180}


def _check_limits(rule: str, values: dict) -> None:
    """Each of ``values`` a finite number in its ``LIMITS`` range, else an error saying ``rule`` and them all."""
    if any(not is_real(v) or not math.isfinite(v) or not LIMITS[k](v) for k, v in values.items()):
        raise PersistenceInputError(f"{rule} (numbers); got " + ", ".join(f"{k}={v!r}" for k, v in values.items()))


def _check_frame(frame, where: str, who: str = "Persistence") -> int:
    if not is_real(frame) or not math.isfinite(frame) or frame != int(frame) or frame < 0:
        raise PersistenceInputError(f"{who}: {where}: its frame index must be an integer >= 0 (the frame's "
                                    f"place in its scene, not a timestamp), got {frame!r}")
    return int(frame)


def _check_pose(pose, where: str, who: str = "Persistence") -> np.ndarray:
    """A finite rigid [4, 4] ego -> world pose (a [3, 4] one gets its last row) as float64."""
    try:
        pose = np.array(pose.detach().cpu() if isinstance(pose, torch.Tensor) else pose, dtype=np.float64)
    except (TypeError, ValueError):
        raise PersistenceInputError(f"{who}: {where}: its ego pose must be a 4x4 ego -> world transform, got "
                                    f"{pose!r:.80}") from None
    if pose.shape == (3, 4):
        pose = np.concatenate([pose, [[0.0, 0.0, 0.0, 1.0]]])
    return check_rigid_pose(pose, f"{who}: {where}", PersistenceInputError)


def _check_preds(preds, where: str, who: str = "Persistence",
                 need: tuple[str, ...] = ("pts", "label", "score")) -> None:
    """A sample's output: a list of polyline dicts, ``pts`` [P, 2] metres, an integer ``label``, a ``score`` (the
    keys of ``need``: the tracker reads no score)."""
    if isinstance(preds, (str, bytes, Mapping)) or not isinstance(preds, Sequence):
        raise PersistenceInputError(f"{who}: {where}: its output must be a list of polyline dicts, got "
                                    f"{type(preds).__name__}")
    for k, p in enumerate(preds):
        if not isinstance(p, Mapping):
            hint = (" (MapElement.as_polyline() gives one; Mapper.stream() applies persistence to its elements "
                    "itself)" if hasattr(p, "as_polyline") else "")
            raise PersistenceInputError(f"{who}: {where}: element {k} must be a polyline dict with 'pts', "
                                        f"'label' and 'score', got {type(p).__name__}{hint}")
        missing = [key for key in need if key not in p]
        if missing:
            needs = f"{', '.join(map(repr, need[:-1]))} and {need[-1]!r}"
            raise PersistenceInputError(f"{who}: {where}: element {k} has no {', '.join(map(repr, missing))} "
                                        f"(a polyline dict needs {needs}: the model's output)")
        try:
            pts = _points(p["pts"])
        except (TypeError, ValueError):
            pts = None
        if pts is None or pts.ndim != 2 or pts.shape[1] != 2:
            got = f"shape {list(pts.shape)}" if pts is not None else f"{p['pts']!r:.60}"
            raise PersistenceInputError(f"{who}: {where}: element {k}'s pts must be [P, 2] (x, y in metres, "
                                        f"ego frame), got {got}")
        if not np.isfinite(pts).all():  # matched nothing, took a new ID / was remembered with no word
            raise PersistenceInputError(f"{who}: {where}: element {k}'s pts hold NaN or infinite coordinates (the "
                                        "evaluation refuses them too); drop or fix that element")
        label, score = p["label"], p.get("score")
        label, score = (x.item() if isinstance(x, torch.Tensor) and x.numel() == 1  # np.size: no bf16
                        else x.item() if hasattr(x, "item") and np.size(x) == 1 else x for x in (label, score))
        if not is_real(label) or not math.isfinite(label) or label != int(label) or label < 0:
            raise PersistenceInputError(f"{who}: {where}: element {k}'s label must be a class index >= 0, got "
                                        f"{p['label']!r:.40}")
        if "score" in need and (not is_real(score) or not math.isfinite(score)):
            raise PersistenceInputError(f"{who}: {where}: element {k}'s score must be a finite number, got "
                                        f"{p['score']!r:.40}")


def _points(pts) -> np.ndarray:
    """An element's ``pts`` as float64 (a tensor of a bf16 / fp16 model's output, on any device, too)."""
    if isinstance(pts, torch.Tensor):
        pts = pts.detach().cpu()
        pts = pts.double() if pts.is_floating_point() else pts
    return np.asarray(pts, dtype=np.float64)


@dataclass
class _Scene:
    frame: int
    pose: np.ndarray  # [4, 4] ego -> world, float64
    # (polyline dict in this frame's ego frame, frames missed) for Persistence; (polyline dict, ID, frames missed)
    # for InstanceTracker
    elements: list[tuple]


def _resample(pts: np.ndarray, n: int) -> np.ndarray:
    """[P, 2] -> [n, 2] equally spaced in arc length."""
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0:
        return np.repeat(pts[:1], n, axis=0)
    t = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(t, s, pts[:, 0]), np.interp(t, s, pts[:, 1])], axis=1)


def _chamfer_matrix(a: np.ndarray, b: np.ndarray, chunk: int = 32) -> np.ndarray:
    """[K, n, 2] against [M, n, 2] -> [K, M]: symmetric Chamfer distances (mean nearest distance both ways,
    halved); ``chunk`` rows of ``a`` at a time bound the [k, M, n, n] block."""
    n = a.shape[1]
    out = np.empty((len(a), len(b)))
    for s in range(0, len(a), chunk):
        d = np.sqrt(((a[s:s + chunk, None, :, None] - b[None, :, None]) ** 2).sum(-1))  # [k, M, n, n]
        out[s:s + chunk] = (d.min(3).sum(2) + d.min(2).sum(2)) / (2 * n)
    return out


def _inside_run(pts: np.ndarray, grid: BEVGrid) -> np.ndarray:
    """The longest run of consecutive points of ``pts`` inside the grid."""
    inside = ((pts[:, 0] >= grid.xmin) & (pts[:, 0] <= grid.xmax) & (pts[:, 1] >= grid.ymin)
              & (pts[:, 1] <= grid.ymax))
    starts, ends = np.flatnonzero(np.diff(np.concatenate([[0], inside.astype(np.int8), [0]]))).reshape(-1, 2).T
    if not len(starts):
        return pts[:0]
    k = int(np.argmax(ends - starts))  # the first of the longest
    return pts[starts[k]:ends[k]]


def _continues(prev: _Scene | None, frame: int, pose: np.ndarray, max_jump_m: float, max_turn_deg: float) -> bool:
    """Frame ``frame`` (ego pose ``pose``) is the next one of ``prev``'s scene: the next frame index, the ego moved
    at most ``max_jump_m`` and turned at most ``max_turn_deg`` (the angle of the relative rotation, as
    models/temporal.memory_status: a spin beyond it is a pose in the wrong unit or frame, which would move what is
    remembered to the wrong place). Anything else starts the scene anew."""
    if prev is None or frame != prev.frame + 1:
        return False
    turn = math.degrees(math.acos(min(1.0, max(-1.0, (np.trace(prev.pose[:3, :3].T @ pose[:3, :3]) - 1) / 2))))
    return turn <= max_turn_deg and float(np.linalg.norm(pose[:3, 3] - prev.pose[:3, 3])) <= max_jump_m


def match_previous(prev_pose: np.ndarray, prev_elements: Sequence[dict], pose: np.ndarray, preds: Sequence[dict],
                   grid: BEVGrid) -> tuple[np.ndarray, list[np.ndarray]]:
    """The matching of a frame's output elements to the previous frame's (the one ``Persistence`` and
    ``InstanceTracker`` share): each previous element (polyline dict, previous ego frame) is moved into this ego
    frame by the two ego poses (ego -> world, [4, 4]) and cut to the grid (the longest run of points inside);
    returns ``D`` [len(prev_elements), len(preds)], the symmetric Chamfer distance (both resampled to
    ``MATCH_POINTS``) of each moved previous element to each output element of its class (inf for another
    class, an element with fewer than two points, or a previous one that left the grid), and the moved points."""
    grid = _check_grid(grid, "match_previous")
    prev_pose, pose = _check_pose(prev_pose, "prev_pose", "match_previous"), _check_pose(pose, "pose", "match_previous")
    _check_preds(prev_elements, "prev_elements", "match_previous", ("pts", "label"))
    _check_preds(preds, "preds", "match_previous", ("pts", "label"))
    to_now = np.linalg.inv(pose) @ prev_pose  # previous ego frame -> this one
    D = np.full((len(prev_elements), len(preds)), np.inf)
    moved = []
    for element in prev_elements:
        pts = _points(element["pts"])
        pts = pts @ to_now[:2, :2].T + to_now[:2, 3]  # the map is the ground plane: x, y of the ego frame
        moved.append(_inside_run(pts, grid))
    now: dict[int, list[int]] = {}  # class -> indices of this frame's outputs
    for j, p in enumerate(preds):
        if len(p["pts"]) >= 2:
            now.setdefault(int(p["label"]), []).append(j)
    for label, cols in now.items():
        rows = [i for i, (e, m) in enumerate(zip(prev_elements, moved)) if int(e["label"]) == label and len(m) >= 2]
        if not rows:
            continue
        mine = np.stack([_resample(moved[i], MATCH_POINTS) for i in rows])
        theirs = np.stack([_resample(_points(preds[j]["pts"]), MATCH_POINTS) for j in cols])
        D[np.ix_(rows, cols)] = _chamfer_matrix(mine, theirs)
    return D, moved


def _batch(who: str, preds, scenes, frames, poses, need: tuple[str, ...] = ("pts", "label", "score")) -> list[tuple]:
    """The batch arguments of ``Persistence`` and ``InstanceTracker`` (``who``), all checked before any state
    changes: per sample ``(preds, scene, frame, pose)``, or a ``PersistenceInputError`` naming the argument and the
    sample (arguments of other lengths were cut short by ``zip``)."""
    preds = as_batch_list(preds, f"{who}: preds", "a list of B samples' outputs, each a list of polyline dicts",
                          PersistenceInputError)
    scenes = as_batch_list(scenes, f"{who}: scenes", "a list of B scene names, one per sample (for one sample: "
                           "[name])", PersistenceInputError)
    frames = as_batch_list(frames, f"{who}: frames", "B frame indices (a list or a [B] tensor)", PersistenceInputError)
    poses = as_float64_array(poses, f"{who}: poses", "B ego -> world transforms [B, 4, 4]", PersistenceInputError)
    if poses.ndim != 3:
        raise PersistenceInputError(f"{who}: poses must be B ego -> world transforms [B, 4, 4], one per sample, got "
                                    f"shape {list(poses.shape)}")
    counts = {"preds": len(preds), "scenes": len(scenes), "frames": len(frames), "poses": len(poses)}
    if len(set(counts.values())) > 1:
        raise PersistenceInputError(f"{who}: one entry per sample in each argument, got "
                                    + ", ".join(f"{v} {k}" for k, v in counts.items()))
    for b, (p, s, f) in enumerate(zip(preds, scenes, frames)):
        where = f"sample {b} (scene '{s}')"
        _check_frame(f, where, who), _check_pose(poses[b], where, who), _check_preds(p, where, who, need)
    return [(p, str(s), int(f), poses[b]) for b, (p, s, f) in enumerate(zip(preds, scenes, frames))]


class Persistence:
    """The rule of the module docstring; ``__call__`` takes a batch, ``step`` one sample."""

    def __init__(self, grid: BEVGrid, frames: int = 1, decay: float = 0.5, match_m: float = 1.0,
                 max_jump_m: float = 10.0, max_turn_deg: float = 180.0):
        grid = _check_grid(grid, "Persistence")
        if not isinstance(frames, numbers.Integral) or isinstance(frames, (bool, np.bool_)) or frames < 0:
            raise PersistenceInputError(f"Persistence: frames must be an integer >= 0, got {frames!r}")
        _check_limits("Persistence: decay must be in (0, 1], match_m and max_jump_m > 0, max_turn_deg in (0, 180]",
                      {"decay": decay, "match_m": match_m, "max_jump_m": max_jump_m, "max_turn_deg": max_turn_deg})
        self.grid, self.frames, self.decay, self.match_m = grid, int(frames), float(decay), float(match_m)
        self.max_jump_m, self.max_turn_deg = float(max_jump_m), float(max_turn_deg)
        self.kept = 0  # elements added to an output so far
        self.reset()

    @classmethod
    def from_config(cls, cfg) -> Persistence | None:
        """``model.temporal.persist_*`` of an ``ExperimentConfig`` (or a YAML file); None when ``persist_frames``
        is 0."""
        cfg = as_config(cfg, "Persistence.from_config")
        t = cfg.model.temporal
        if t.persist_frames == 0:
            return None
        return cls(BEVGrid.from_config(cfg.grid), t.persist_frames, t.persist_decay, t.persist_match_m,
                   t.max_jump_m, t.max_turn_deg)

    def reset(self) -> None:
        self.scenes: dict[str, _Scene] = {}

    def __call__(self, preds: Sequence[list[dict]], scenes: Sequence[str], frames, poses) -> list[list[dict]]:
        return [self.step(*sample) for sample in _batch("Persistence", preds, scenes, frames, poses)]

    def step(self, preds: list[dict], scene: str, frame: int, pose) -> list[dict]:
        """One sample's output with the remembered elements the model missed added (module docstring)."""
        where = f"scene '{scene}', frame {frame!r}"
        frame = _check_frame(frame, where)
        pose = _check_pose(pose, where)
        _check_preds(preds, where)
        prev = self.scenes.get(scene)
        carried: list[tuple[dict, int]] = []
        if _continues(prev, frame, pose, self.max_jump_m, self.max_turn_deg):
            alive = [(element, missed) for element, missed in prev.elements if missed < self.frames]
            D, moved = match_previous(prev.pose, [element for element, _ in alive], pose, preds, self.grid)
            found = D.min(1) <= self.match_m if D.shape[1] else np.zeros(len(alive), dtype=bool)
            for (element, missed), pts, again in zip(alive, moved, found):
                if again or len(pts) < 2:  # the model found it again / it left the grid
                    continue
                closed = bool(element.get("closed", False)) and len(pts) == len(element["pts"])
                dtype = np.asarray(element["pts"]).dtype if not isinstance(element["pts"], torch.Tensor) else np.float32
                carried.append(({**element, "pts": pts.astype(dtype, copy=False),
                                 "closed": closed, "score": float(element["score"]) * self.decay}, missed + 1))
        self.scenes[scene] = _Scene(frame, pose, [(p, 0) for p in preds] + carried)
        self.kept += len(carried)
        return list(preds) + [element for element, _ in carried]


# The track IDs of a stream (Mapper.stream, predict --scene): a missed track waits up to TRACK_LOOK_BACK frames for
# its element to come back (MapTracker's prepare_pred_tracks.py looks back up to 5 frames), and an element is its
# track's within TRACK_MATCH_M (Chamfer), the vector AP's largest threshold: what the AP would score as that element
# is linked to it (the consistency meter's own tracker keeps eval.cmap_match_m and the previous frame only)
TRACK_LOOK_BACK = 5
TRACK_MATCH_M = 1.5



class InstanceTracker:
    """Instance IDs across the frames of a drive, by the persistence matcher (``match_previous``).

        track = InstanceTracker.from_config(cfg)         # or InstanceTracker(grid, match_m=1.0)
        ids = track(preds, scenes, frames, poses)        # per sample, one integer ID per output element

    At the next frame of a scene (``_continues``: the next frame index, no pose jump, as ``Persistence``), the
    tracks (the previous frame's output elements, and with ``look_back`` > 1 the tracks missed for fewer than
    ``look_back`` frames) are moved into this ego frame and matched to this frame's elements, one to one: the
    (track, current) pairs of one class in increasing Chamfer distance (``match_previous``, ties by index), each
    pair taken while both are free and ``D <= match_m``. A matched element takes the track's ID; any other (and
    every element of a scene's first frame, of a frame after a gap or a pose jump) takes a new one. IDs are per
    scene, counted from 0 and never reused in it (a reset after a pose jump gives new IDs). ``look_back`` 1 (the
    default, the consistency meter's) looks at the previous frame only: an element the model missed for a frame
    comes back with a new ID unless ``Persistence`` kept it; MapTracker's ``prepare_pred_tracks.py`` looks back
    up to 5 frames, which ``look_back=5`` does (a missed track moves with the ego while it waits, and is dropped
    when it leaves the grid). Samples of a scene must come in frame order (scenes may interleave); bad input is a
    ``PersistenceInputError`` naming the sample, as ``Persistence``.
    """

    def __init__(self, grid: BEVGrid, match_m: float = 1.0, max_jump_m: float = 10.0, max_turn_deg: float = 180.0,
                 look_back: int = 1):
        grid = _check_grid(grid, "InstanceTracker")
        _check_limits("InstanceTracker: needs match_m and max_jump_m > 0, max_turn_deg in (0, 180]",
                      {"match_m": match_m, "max_jump_m": max_jump_m, "max_turn_deg": max_turn_deg})
        if isinstance(look_back, bool) or not isinstance(look_back, int) or look_back < 1:
            raise PersistenceInputError(f"InstanceTracker: look_back is a count of frames >= 1, got {look_back!r}")
        self.grid, self.match_m = grid, float(match_m)
        self.max_jump_m, self.max_turn_deg, self.look_back = float(max_jump_m), float(max_turn_deg), look_back
        self.reset()

    @classmethod
    def from_config(cls, cfg, look_back: int = 1) -> InstanceTracker:
        """``model.temporal``'s ``persist_match_m``, ``max_jump_m``, ``max_turn_deg`` and the config's grid (an
        ``ExperimentConfig`` or a YAML file)."""
        cfg = as_config(cfg, "InstanceTracker.from_config")
        t = cfg.model.temporal
        return cls(BEVGrid.from_config(cfg.grid), t.persist_match_m, t.max_jump_m, t.max_turn_deg, look_back)

    def reset(self) -> None:
        self.scenes: dict[str, _Scene] = {}  # elements: (polyline dict, its ID, frames missed)
        self.next_id: dict[str, int] = {}

    def __call__(self, preds: Sequence[list[dict]], scenes: Sequence[str], frames, poses) -> list[list[int]]:
        return [self.step(*sample) for sample in _batch("InstanceTracker", preds, scenes, frames, poses,
                                                        ("pts", "label"))]

    def step(self, preds: list[dict], scene: str, frame: int, pose) -> list[int]:
        """One sample's element IDs (class docstring), in the order of ``preds``."""
        where = f"scene '{scene}', frame {frame!r}"
        frame = _check_frame(frame, where, "InstanceTracker")
        pose = _check_pose(pose, where, "InstanceTracker")
        _check_preds(preds, where, "InstanceTracker", ("pts", "label"))
        prev = self.scenes.get(scene)
        ids, waiting = [-1] * len(preds), []
        if _continues(prev, frame, pose, self.max_jump_m, self.max_turn_deg) and prev.elements:
            D, moved = match_previous(prev.pose, [e for e, _, _ in prev.elements], pose, preds, self.grid)
            rows, cols = np.nonzero(D <= self.match_m)
            missed_of = np.array([missed for _, _, missed in prev.elements])
            used = set()
            # the previous frame's tracks first, the waiting ones for what is left; each in increasing distance
            for k in np.lexsort((cols, rows, D[rows, cols], missed_of[rows])):
                i, j = int(rows[k]), int(cols[k])
                if i not in used and ids[j] < 0:
                    used.add(i)
                    ids[j] = prev.elements[i][1]
            for i, (element, track, missed) in enumerate(prev.elements):  # a missed track waits, moved with the ego
                if i not in used and missed + 1 < self.look_back and len(moved[i]) >= 2:
                    waiting.append(({**element, "pts": moved[i]}, track, missed + 1))
        n = self.next_id.get(scene, 0)
        for j in range(len(ids)):
            if ids[j] < 0:
                ids[j], n = n, n + 1
        self.next_id[scene] = n
        self.scenes[scene] = _Scene(frame, pose, [(p, i, 0) for p, i in zip(preds, ids)] + waiting)
        return ids


def stream_tracker(cfg) -> InstanceTracker:
    """The tracker of a stream's IDs (``TRACK_LOOK_BACK``, ``TRACK_MATCH_M``; ``model.temporal``'s pose jumps)."""
    t = cfg.model.temporal
    return InstanceTracker(BEVGrid.from_config(cfg.grid), TRACK_MATCH_M, t.max_jump_m, t.max_turn_deg,
                           TRACK_LOOK_BACK)
