"""What every map dataset shares (nuscenes.py, av2.py): the sample dict of docs/conventions.md built
from the pieces a dataset provides, the augmentation stream, the bad-sample policy, the batching of
samples (``collate_fn``, for every loader: training, evaluation, prediction) and a split's GT in the
submission format (``gt_submission``).

A dataset subclasses ``MapDataset`` (calling ``super().__init__(cfg, split, augment)``, which sets
``cfg``, ``data_cfg``, ``split``, ``grid`` and ``augment``), sets ``dataroot``, ``sample_tokens`` (one
string per sample) and ``camera_names`` (V names, in the order of the camera tensors), calls
``set_scenes(scene names, timestamps)`` (the drive each sample belongs to, its time; a scene's samples
contiguous and in time order, see ``SceneIndex``), and implements

* ``gt_polylines(i)``: the sample's local map (polyline dicts, metres, ego frame), without images;
* ``camera_files(i)``: ``[(image path, (W, H))]`` in camera order, and ``camera_calibration(i)``:
  ``[(intrinsics [3, 3], cam_to_ego_rot [3, 3], cam_to_ego_trans [3])]`` (arrays or lists of numbers)
  in the same order, which ``load_cameras`` reads (one augmentation draw per camera);
* ``ego_pose(i)``: [4, 4] float32, ego -> global (the frame of the map);
* ``ground_height(i)``: the height of the road below the ego origin, metres along the ego frame's z
  (nuScenes: 0, its ego frame lies on the ground; AV2: ~-0.35, from the log's ground-height raster).

Bad input raises a ``UserError`` naming the file and sample; with ``data.on_bad_sample=skip`` a bad
sample is replaced by the next good one (one warning per bad sample, with the running count;
``num_bad_samples`` holds it) instead.
"""

from __future__ import annotations

import operator
import os
import warnings
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset
from tqdm import tqdm

from ..config import ConfigError, ExperimentConfig, UserError
from ..geometry import BEVGrid
from ..targets import build_targets
from .local_map import some_of
from .rig import RigError, check_camera_offset, check_pinhole, check_upright
from .transforms import ImageAug, ImageError, load_image, sample_augmentation

# padding of the per-vertex keys in collate_fn (everything else is -1)
VERTEX_KEYS = ("gt_vertices_px", "gt_vertex_mask", "gt_vertex_labels", "gt_vertex_instance", "gt_vertex_order",
               "gt_vertex_next", "gt_vertex_prev")
_VERTEX_PAD = {"gt_vertices_px": 0.0, "gt_vertex_mask": False}
CAMERA_KEYS = ("images", "intrinsics", "cam_to_ego_rot", "cam_to_ego_trans", "post_rot", "post_tran")


class DatasetError(UserError):
    """The dataroot, version, split or a sample's files cannot be used."""


class SceneIndex:
    """Which drive each sample belongs to: ``scene[i]`` (name), ``frame[i]`` (index in its scene, from 0),
    ``timestamp_us[i]``, and ``runs`` (per scene, in dataset order, its sample indices in time order).

    A scene's samples must be contiguous in the dataset and strictly increasing in time: a
    ``DatasetError`` names the scene otherwise (frames out of order)."""

    def __init__(self, scenes: list[str], timestamps_us: list[int], where: str = "the dataset"):
        if len(scenes) != len(timestamps_us):
            raise ValueError(f"{len(scenes)} scene names for {len(timestamps_us)} timestamps")
        self.scene, self.timestamp_us = list(scenes), [int(t) for t in timestamps_us]
        self.frame: list[int] = []
        self.runs: list[list[int]] = []
        names: list[str] = []
        for i, name in enumerate(self.scene):
            if names and names[-1] == name:
                if self.timestamp_us[i] <= self.timestamp_us[i - 1]:
                    raise DatasetError(
                        f"scene '{name}' of {where}: frame {len(self.runs[-1])} (timestamp {self.timestamp_us[i]} us) "
                        f"does not come after frame {len(self.runs[-1]) - 1} ({self.timestamp_us[i - 1]} us); "
                        "a scene's samples must be in time order")
                self.runs[-1].append(i)
            else:
                if name in names:
                    raise DatasetError(f"scene '{name}' of {where}: its samples are not contiguous (the scene "
                                       "appears twice in the sample list)")
                names.append(name)
                self.runs.append([i])
            self.frame.append(len(self.runs[-1]) - 1)
        self.names = names

    def __len__(self) -> int:
        return len(self.scene)


ORTHONORMAL_TOL = 1e-3  # |R^T R - I| of a calibrated rotation (stored to ~1e-8 in nuScenes and AV2)
MAX_TRANSLATION_M = 1e7  # a translation beyond this (in metres) is corrupt, not a place on Earth


def check_finite(values, what: str, where: str) -> np.ndarray:
    """``values`` as a float64 array, or a DatasetError for a string or bool among them (numpy reads "1.5" as 1.5,
    and the record's raw strings would reach the arithmetic later, a raw error there), a non-number, NaN or an
    infinity."""
    flat = [values] if isinstance(values, (str, bytes)) else np.asarray(values, dtype=object).ravel()
    if any(isinstance(v, (str, bytes, bool, np.bool_)) for v in flat):
        raise DatasetError(f"{where}: {what} is not numeric: {values!r:.120} (numbers, not strings)")
    try:
        a = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise DatasetError(f"{where}: {what} is not numeric: {values!r}") from None
    if not np.isfinite(a).all():
        raise DatasetError(f"{where}: {what} holds NaN or infinite values ({np.array2string(a.ravel(), 120)}); "
                           "the calibration / pose record is corrupt")
    return a


def check_rotation(rotation, what: str, where: str) -> None:
    """A finite 3x3 rotation: orthonormal to ``ORTHONORMAL_TOL`` with determinant +1."""
    R = check_finite(rotation, what, where)
    if R.shape != (3, 3):
        raise DatasetError(f"{where}: {what} must be a 3x3 rotation, got shape {R.shape}")
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    if err > ORTHONORMAL_TOL or np.linalg.det(R) < 0:
        raise DatasetError(f"{where}: {what} is not a rotation (not orthonormal: |R^T R - I| = {err:.3g}, det "
                           f"{np.linalg.det(R):.3g}); the calibration / pose record is corrupt")


def check_translation(translation, what: str, where: str) -> None:
    t = check_finite(translation, what, where)
    if t.shape != (3,) or np.abs(t).max() > MAX_TRANSLATION_M:
        raise DatasetError(f"{where}: {what} must be 3 finite coordinates in metres, got {t.tolist()}")


def check_intrinsics(intrinsics, where: str) -> None:
    """A pinhole camera matrix: finite 3x3, positive focal lengths, last row (0, 0, 1) (``check_pinhole``)."""
    K = check_finite(intrinsics, "the camera intrinsics", where)
    if K.shape != (3, 3):
        raise DatasetError(f"{where}: the camera intrinsics must be a 3x3 matrix, got shape {K.shape}")
    try:
        check_pinhole(K, f"{where}: its intrinsics matrix")
    except RigError as e:
        raise DatasetError(str(e)) from None


MAX_EGO_TILT_DEG = 25  # the ego frame's z axis off the vertical: the steepest public roads are ~20 degrees


def check_camera_plausible(intrinsics, rotation, translation, image_size: tuple[int, int], where: str,
                           hint: str, channel: str | None = None) -> None:
    """A calibration whose every field is well formed but that no surround camera has (the Mapper's checks,
    data/rig.py): a camera far from the ego origin (``check_camera_offset``: millimetres), intrinsics that no
    camera of the ``image_size`` (width, height) image has (``check_pinhole``: normalised, or of another image
    size), a camera looking up or down, rolled or upside down (``check_upright``: ego -> camera, a quaternion in
    another order), and a camera of a known ``channel`` looking where that channel does not
    (``camera_heading_problem``)."""
    try:
        check_camera_offset(np.asarray(translation, dtype=np.float64), f"{where}: its translation")
        check_pinhole(np.asarray(intrinsics, dtype=np.float64), f"{where}: its intrinsics matrix", image_size)
        check_upright(rotation, where, hint)
    except RigError as e:
        raise DatasetError(str(e)) from None
    problem = camera_heading_problem(channel, rotation)
    if problem is not None:
        raise DatasetError(f"{where}: {problem}")


# the optical axis' yaw in the ego frame (degrees, left of forward) of the known surround channels: the real
# nuScenes rig (data/rig.py, n015: 0, +-55, 180, +-110) and the real AV2 log's calibration (../shared/av2_real:
# 0, +-45, +-99, +-153), rounded
NOMINAL_CAMERA_YAW_DEG = {
    "CAM_FRONT": 0.0, "CAM_FRONT_LEFT": 55.0, "CAM_FRONT_RIGHT": -55.0,
    "CAM_BACK": 180.0, "CAM_BACK_LEFT": 110.0, "CAM_BACK_RIGHT": -110.0,
    "ring_front_center": 0.0, "ring_front_left": 45.0, "ring_front_right": -45.0,
    "ring_side_left": 99.0, "ring_side_right": -99.0, "ring_rear_left": 153.0, "ring_rear_right": -153.0,
}
MAX_CAMERA_YAW_OFF_DEG = 60  # every camera of those real rigs lies within 2 degrees of its channel's direction


def camera_heading_problem(channel: str | None, rotation) -> str | None:
    """What is wrong with a camera -> ego ``rotation`` for the known channel ``channel`` (its optical axis
    more than ``MAX_CAMERA_YAW_OFF_DEG`` off the channel's direction: the channels' names swapped, a
    calibration of another camera), or None (an unknown channel name, or None, is not checked)."""
    nominal = NOMINAL_CAMERA_YAW_DEG.get(channel)
    if nominal is None:
        return None
    z = np.asarray(rotation, dtype=np.float64)[:, 2]  # the optical axis in the ego frame
    yaw = float(np.degrees(np.arctan2(z[1], z[0])))
    off = abs((yaw - nominal + 180.0) % 360.0 - 180.0)
    if off <= MAX_CAMERA_YAW_OFF_DEG:
        return None
    return (f"its optical axis points {yaw:.0f} degrees left of the vehicle's forward direction, {off:.0f} degrees "
            f"off where a {channel} camera looks ({nominal:.0f}; within {MAX_CAMERA_YAW_OFF_DEG} on real rigs): the "
            "camera names swapped, or another camera's calibration?")


MAX_CAMERA_DELAY_S = 0.5  # a keyframe's camera image and its sample: real rigs are within ~50 ms


def check_camera_time(sample_us: int, camera_us: int, where: str) -> None:
    """A camera image taken more than ``MAX_CAMERA_DELAY_S`` from its sample (timestamps in microseconds)."""
    gap = abs(int(camera_us) - int(sample_us)) / 1e6
    if gap > MAX_CAMERA_DELAY_S:
        raise DatasetError(f"{where}: the image's timestamp {int(camera_us)} us is {gap:.3g} s from its sample's "
                           f"({int(sample_us)} us); a camera of a sample is taken within {MAX_CAMERA_DELAY_S:g} s of "
                           "it (real rigs: ~50 ms): an image of another moment, or timestamps in another unit")


def check_ego_level(rotation, where: str, hint: str) -> None:
    """An ego -> world rotation whose z axis is more than ``MAX_EGO_TILT_DEG`` off the vertical: no vehicle
    on a road is tilted so; a quaternion read in another order is."""
    R = np.asarray(rotation, dtype=np.float64)
    tilt = float(np.degrees(np.arccos(np.clip(R[2, 2], -1, 1))))
    if tilt > MAX_EGO_TILT_DEG:
        raise DatasetError(f"{where}: its rotation tilts the vehicle {tilt:.0f} degrees off level (a vehicle on a "
                           f"road is tilted less than {MAX_EGO_TILT_DEG}): {hint}")


def check_distinct_images(paths, cameras, where: str) -> None:
    """No image file (symbolic links followed) given for two cameras of one sample."""
    seen: dict = {}
    for cam, path in zip(cameras, paths):
        key = os.path.realpath(path)
        if key in seen:
            raise DatasetError(f"{where}: cameras {seen[key]} and {cam} read the same image file {path}: each camera "
                               "has its own images (a table or a link pointing at the wrong file)")
        seen[key] = cam


class MapDataset(Dataset):
    """Samples of one split as dicts (docs/conventions.md, per sample: no batch dimension)."""

    sample_tokens: list[str]
    camera_names: tuple[str, ...]
    scenes: SceneIndex

    def __init__(self, cfg: ExperimentConfig, split: str, augment: bool | None = None) -> None:
        """``augment``: train-time image augmentation; default ``cfg.data.augment and split == train_split``."""
        d = cfg.data
        if len(d.classes) != 3:
            raise ConfigError(f"config key 'data.classes' must name the 3 map classes (divider, ped_crossing, "
                              f"boundary) that the local map produces, got {list(d.classes)}")
        self.cfg, self.data_cfg, self.split = cfg, d, split
        self.grid = BEVGrid.from_config(cfg.grid)
        self.augment = (d.augment and split == d.train_split) if augment is None else augment
        self.epoch = 0  # see set_epoch
        self._bad: set[int] = set()  # indices of the samples found bad (on_bad_sample=skip)
        self.kept: dict[int, dict] | None = None  # the samples kept in memory (keep_in_memory), by index

    def set_scenes(self, scenes: list[str], timestamps_us: list[int]) -> None:
        """The scene name and timestamp (microseconds) of every sample (``SceneIndex``)."""
        self.scenes = SceneIndex(scenes, timestamps_us, f"split '{self.split}' of {self.dataroot}")

    @property
    def num_bad_samples(self) -> int:
        """How many samples were skipped as bad so far (in this process)."""
        return len(self._bad)

    def __len__(self) -> int:
        return len(self.sample_tokens)

    def gt_polylines(self, index: int) -> list[dict]:
        raise NotImplementedError

    def ego_pose(self, index: int) -> torch.Tensor:
        raise NotImplementedError

    def camera_files(self, index: int) -> list:
        raise NotImplementedError

    def camera_calibration(self, index: int) -> list:
        raise NotImplementedError

    def missing_image_hint(self, path: Path) -> str | None:
        """Why a camera image of ``path`` cannot be read, added to the ``ImageError`` (None: nothing to add)."""
        return None

    def load_cameras(self, index: int, rng: np.random.Generator | None = None) -> dict[str, torch.Tensor]:
        """Images [V, 3, h, w], intrinsics [V, 3, 3], cam_to_ego_rot [V, 3, 3] / trans [V, 3],
        post_rot [V, 3, 3], post_tran [V, 3] of one sample (augmented when ``self.augment``)."""
        d = self.data_cfg
        if self.augment and rng is None:
            rng = self.augmentation_rng(index)
        out: dict[str, list] = {k: [] for k in CAMERA_KEYS}
        for (path, size), calib in zip(self.camera_files(index), self.camera_calibration(index)):
            aug = sample_augmentation(d, rng) if self.augment else ImageAug()  # one draw per camera
            try:
                image, post_rot, post_tran = load_image(path, size, d.image_size, aug, fit=d.image_fit)
            except ImageError as e:
                hint = self.missing_image_hint(path)
                if hint is None:
                    raise
                raise ImageError(f"{e}; {hint}") from None
            calib = [torch.tensor(v, dtype=torch.float32) for v in calib]  # a copy: av2's arrays are read-only
            for key, value in zip(CAMERA_KEYS, (image, *calib, post_rot, post_tran)):
                out[key].append(value)
        return {k: torch.stack(v) for k, v in out.items()}

    def ground_height(self, index: int) -> float:
        raise NotImplementedError

    def scene_of(self, index: int) -> str:
        """The name of the scene (nuScenes) or log (AV2) that sample ``index`` belongs to."""
        return self.scenes.scene[index]

    def scene_indices(self, name: str) -> list[int]:
        """The samples of scene (or log) ``name``, in time order; a ``DatasetError`` naming the split's
        scenes when it has none."""
        names = self.scenes.names
        if name not in names:
            raise DatasetError(f"scene '{name}' is not in split '{self.split}' of {self.dataroot}; its scenes: "
                               f"{some_of(names)}")
        return list(self.scenes.runs[names.index(name)])

    def set_epoch(self, epoch: int) -> None:
        """Select the augmentation draws of ``epoch`` (the training loop calls it before each epoch)."""
        self.epoch = epoch

    def augmentation_rng(self, index: int) -> np.random.Generator:
        """The augmentation stream of sample ``index`` in the current epoch: a function of
        (``train.seed``, epoch, index) alone, so the same sample is augmented the same way whatever
        the worker count, the process or the resume point (exact resume with augmentation)."""
        return np.random.default_rng([self.cfg.train.seed, self.epoch, index])

    def load_sample(self, index: int) -> dict:
        """The sample dict, raising ``UserError`` (naming the sample token) on bad input."""
        token = self.sample_tokens[index]
        try:
            polylines = self.gt_polylines(index)
            cams = self.load_cameras(index)
            ego_pose = self.ego_pose(index)
            ground_height = torch.tensor(self.ground_height(index), dtype=torch.float32)
        except UserError as e:
            msg = str(e) if token in str(e) else f"sample {token}: {e}"
            raise type(e)(msg) from None
        d = self.data_cfg
        if d.camera_dropout > 0:
            cams["images"] = blank_cameras(cams["images"], d.camera_dropout, index)
        targets = build_targets(polylines, self.grid, len(d.classes), d.dt_clip)
        frame = self.scenes.frame[index]
        return {
            **cams,
            "ego_pose": ego_pose,
            "ground_height": ground_height,
            "sample_token": token,
            "scene": self.scenes.scene[index],
            "frame_index": torch.tensor(frame, dtype=torch.long),
            "scene_start": torch.tensor(frame == 0),
            "timestamp_us": torch.tensor(self.scenes.timestamp_us[index], dtype=torch.long),
            "gt_polylines": polylines,
            **targets,
        }

    def _sample_index(self, index) -> int:
        """``dataset[index]``'s index as an int in 0..len - 1 (a negative one counts from the end, as in a list):
        a token, a slice or a float is a TypeError saying what it takes (was a raw "list indices must be
        integers"), an index out of range an IndexError naming the range (with on_bad_sample=skip it wrapped
        around silently)."""
        n = len(self)
        try:
            if isinstance(index, (bool, np.bool_, str, bytes, slice)):
                raise TypeError
            i = operator.index(index)  # int, numpy integer, integer 0-d tensor
        except TypeError:
            if isinstance(index, (str, bytes)):
                hint = "; for a sample token: dataset[dataset.sample_tokens.index(token)]"
            elif isinstance(index, slice):
                hint = "; for several samples: [dataset[i] for i in range(...)] (collate_fn stacks them into a batch)"
            else:
                hint = ""
            raise TypeError(f"{type(self).__name__}[index] takes one sample index, an int in 0..{n - 1} (split "
                            f"'{self.split}', {n} samples), got {type(index).__name__} {index!r:.80}{hint}") from None
        if not -n <= i < n:
            raise IndexError(f"sample index {i} is out of range: split '{self.split}' has {n} samples (0..{n - 1})")
        return i % n

    def keep_in_memory(self, max_bytes: float) -> float:
        """Keep each sample once loaded (``data.cache_in_memory``): a later read of it skips the files and the
        targets. Only for a dataset without augmentation, whose samples are the same in every epoch. The samples'
        bytes are sized from the first one; over ``max_bytes`` nothing is kept. Returns that size."""
        if self.augment:
            raise ValueError("keep_in_memory: an augmented dataset's samples differ in each epoch")
        first = self.load_sample(0) if len(self) else {}
        need = float(sample_bytes(first) * len(self))
        self.kept = {0: first} if need <= max_bytes else None
        return need

    def _load(self, index: int) -> dict:
        if self.kept is None:
            return self.load_sample(index)
        if index not in self.kept:
            self.kept[index] = self.load_sample(index)
        return dict(self.kept[index])  # a new dict: a caller's keys (scene_start, replaced) stay out of it

    def __getitem__(self, index: int | tuple[int, bool]) -> dict:
        """Sample ``index``; ``(index, start)`` (a streaming sampler's pieces, data/streaming.py): the sample
        with ``scene_start`` = ``start``."""
        if isinstance(index, tuple) and len(index) == 2:
            index, start = index
            sample = self[index]
            sample["scene_start"] = torch.tensor(bool(start))
            return sample
        index = self._sample_index(index)
        if self.data_cfg.on_bad_sample == "raise":
            return self._load(index)
        n = len(self)
        for k in range(n):
            j = (index + k) % n
            if j in self._bad:
                continue
            try:
                sample = self._load(j)
            except UserError as e:
                self._bad.add(j)
                warnings.warn(f"skipping a bad sample (data.on_bad_sample=skip, {len(self._bad)} so far): {e}",
                              stacklevel=2)
                continue
            # True: another sample stands in for a bad one; a temporal model counts the bad frame as a
            # missing one (no fusion, the memory resets) and evaluation does not score the stand-in
            sample["replaced"] = torch.tensor(j != index)
            sample["stands_for"] = self.sample_tokens[index]
            return sample
        raise DatasetError(f"every sample of split '{self.split}' in {self.dataroot} is bad; see the warnings")


def sample_bytes(sample: dict) -> int:
    """The bytes of a sample's tensors and arrays (its GT polylines included)."""
    arrays = [v for v in sample.values() if isinstance(v, (torch.Tensor, np.ndarray))]
    arrays += [p for line in sample.get("gt_polylines", ()) for p in line.values() if isinstance(p, np.ndarray)]
    return sum(a.nbytes for a in arrays)


CAMERA_DROPOUT_STREAM = 0xD209  # the random stream of data.camera_dropout, apart from augmentation's


def blank_cameras(images: torch.Tensor, p: float, index: int) -> torch.Tensor:
    """``data.camera_dropout``: each of the V normalised images [V, 3, h, w] set to 0 (the ImageNet mean)
    with probability ``p``, drawn from the sample's ``index`` alone."""
    drop = np.random.default_rng([CAMERA_DROPOUT_STREAM, index]).random(images.shape[0]) < p
    if not drop.any():
        return images
    images = images.clone()
    images[torch.from_numpy(drop)] = 0.0
    return images


def collate_fn(samples: list[dict]) -> dict:
    """Stack per-sample dicts into a batch (docs/conventions.md).

    Same-shape tensors are stacked; ``sample_token`` and ``gt_polylines`` become per-sample lists;
    the per-vertex keys are padded to the batch's largest M: ``gt_vertices_px`` with 0,
    ``gt_vertex_mask`` with False, the integer keys (labels, instance, order, next, prev) with -1.
    """
    if isinstance(samples, dict) or not hasattr(samples, "__iter__"):  # one sample: collate_fn([sample])
        raise TypeError(f"collate_fn takes a list of sample dicts (dataset[i]), got {type(samples).__name__}"
                        + ("; for one sample: collate_fn([sample])" if isinstance(samples, dict) else ""))
    samples = list(samples)
    if not samples:
        raise ValueError("collate_fn: no samples to batch (an empty list)")
    bad = [b for b, s in enumerate(samples) if not isinstance(s, dict)]
    if bad:
        raise TypeError(f"collate_fn takes a list of sample dicts (dataset[i]); sample {bad[0]} is a "
                        f"{type(samples[bad[0]]).__name__}")

    def name(b: int) -> str:
        token = samples[b].get("sample_token")
        return f"sample {b}" + (f" ('{token}')" if isinstance(token, str) else "")

    out: dict = {}
    for key in samples[0]:
        missing = [b for b, s in enumerate(samples) if key not in s]
        if missing:  # a raw KeyError
            raise ValueError(f"collate_fn: {name(missing[0])} has no '{key}', which {name(0)} has: the samples of "
                             "a batch come from datasets of one kind and config")
    M = max(len(s["gt_vertices_px"]) for s in samples) if "gt_vertices_px" in samples[0] else 0
    for key, first in samples[0].items():
        values = [s[key] for s in samples]
        if isinstance(first, torch.Tensor):
            tail = 1 if key in VERTEX_KEYS else 0  # the per-vertex keys are padded along their first dimension
            other = next((b for b, v in enumerate(values)
                          if not isinstance(v, torch.Tensor) or v.shape[tail:] != first.shape[tail:]), None)
            if other is not None:  # torch.stack's raw "stack expects each tensor to be equal size"
                got = (f"shape {list(values[other].shape)}" if isinstance(values[other], torch.Tensor)
                       else type(values[other]).__name__)
                raise ValueError(f"collate_fn: '{key}' has shape {list(first.shape)} in {name(0)} and {got} in "
                                 f"{name(other)}: the samples of a batch come from one config (data.image_size, "
                                 "grid, cameras)")
        if key in VERTEX_KEYS:
            pad = _VERTEX_PAD.get(key, -1)
            batch = first.new_full((len(samples), M, *first.shape[1:]), pad)
            for b, v in enumerate(values):
                batch[b, : len(v)] = v
            out[key] = batch
        elif isinstance(first, torch.Tensor):
            out[key] = torch.stack(values)
        else:
            out[key] = values
    return out


def gt_submission(dataset: MapDataset, progress: bool = False) -> dict:
    """The split's GT polylines in HDMapNet's submission format:
    ``{"meta": {...}, "results": {sample_token: [{"pts": [[x, y], ...], "pts_num": n, "type": k}]}}``
    with points in metres in the ego frame (x forward, y left); a closed shape repeats its first point.
    Images are not read. With ``data.on_bad_sample=skip`` a sample whose map cannot be built is left
    out (with a warning)."""
    d, g = dataset.data_cfg, dataset.cfg.grid
    results: dict[str, list] = {}
    first: UserError | None = None
    for i in tqdm(range(len(dataset)), desc="export-gt", disable=not progress):
        token = dataset.sample_tokens[i]
        try:
            polylines = dataset.gt_polylines(i)
        except UserError as e:
            if d.on_bad_sample == "raise":
                raise
            first = first or e
            warnings.warn(f"export-gt: skipping sample {token}: {e}", stacklevel=2)
            continue
        results[token] = [
            {"pts": np.round(p["pts"], 4).tolist(), "pts_num": len(p["pts"]), "type": int(p["label"])}
            for p in polylines
        ]
    if first is not None and not results:  # a GT file of no samples, exit 0 (every map unreadable)
        raise DatasetError(f"every sample of split '{dataset.split}' in {dataset.dataroot} is bad "
                           f"(data.on_bad_sample=skip), the first: {first}")
    meta = {"use_camera": True, "use_lidar": False, "use_radar": False, "use_external": False, "vector": True,
            "ground_truth": True, "dataset": d.dataset, "version": d.version, "split": dataset.split,
            "frame": "ego, x forward, y left, metres", "classes": list(d.classes), "xbound": list(g.xbound),
            "ybound": list(g.ybound),
            "resolution": g.resolution,  # the raster protocol's pixel in evaluate (evaluate-json: --resolution)
            "sample_dist": d.sample_dist}
    return {"meta": meta, "results": results}

