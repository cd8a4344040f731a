"""The Python API: a ``Mapper`` turns camera frames into vectorized map elements.

    mapper = Mapper.from_checkpoint("runs/demo/best.pt")   # or Mapper.from_onnx("model.onnx")
    elements = mapper(Frame(images, intrinsics, cam_to_ego))  # [MapElement(label, points, ...), ...]
    stream = mapper.stream()                                  # a temporal model remembers the road
    for frame in drive: elements = stream.step(frame)

``Frame`` checks a user's own cameras (names, calibration, images of any size or dtype) where it is
made; ``MapElement`` is one decoded polyline or polygon in metres in the ego frame, and
``to_hdmapnet`` writes a list of them as an HDMapNet submission entry. The model under it comes from
inference.py (a checkpoint or an ONNX export), the decoding from postprocess.py.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import MISSING, dataclass, replace
from dataclasses import fields as dataclass_fields
from pathlib import Path

import numpy as np
import torch
from PIL import Image as PILImage

from .checkpoint import CheckpointError, load_checkpoint
from .config import (
    MAP_CLASSES,
    ExperimentConfig,
    UserError,
    as_config,
    config_from_dict,
    config_to_dict,
    deep_update,
    parse_overrides,
)
from .data import rig_cameras
from .data.base import camera_heading_problem
from .data.rig import RigError, camera_named_by, check_calibration, check_upright
from .data.transforms import ImageError, load_image, prepare_image
from .distributed import resolve_device
from .evaluation.io import polylines_to_vectors, submission
from .geometry import BEVGrid
from .inference import DECODE_OPTIONS, OnnxModel, exported_config, load_weights, read_export, run_model, saved_config
from .models import build_model
from .models.temporal import STATUS_NAMES
from .persistence import Persistence, stream_tracker
from .postprocess import decode_options, postprocess_batch
from .precision import calibration_batches, precision_of, resolve_precision, with_precision

# PIL modes of 8-bit pixels, which convert("RGB") keeps; "I;16" (16-bit) saturates at 255 and "F" (float)
# truncates 0..1 values to 0
PIL_8BIT_MODES = ("1", "L", "LA", "La", "P", "PA", "RGB", "RGBA", "RGBa", "RGBX", "CMYK", "YCbCr")
# a frame's ground_height beyond this (metres from the ego origin) is a unit or frame mistake: a vehicle's
# origin lies on the road (nuScenes) or on its rear axle (AV2, 0.33-0.43 m above it)
MAX_GROUND_HEIGHT_M = 5.0
FLOAT_IMAGE_SLACK = 0.25  # a resampled 0..1 image may overshoot a little; 0..255 or mean/std-normalised ones do not


@dataclass(frozen=True)
class MapElement:
    """One map element: its class name, ``points`` [P, 2] in metres in the ego frame (x forward, y
    left; a closed polygon repeats its first point at the end), ``closed``, a ``score`` in [0, 1] and
    ``class_index`` (its index in the model's classes: the HDMapNet ``type``). ``track_id``: out of
    ``Mapper.stream()``, the same integer for the same map element in every frame it is seen in
    (``persistence.InstanceTracker``); None out of a single frame's call."""

    label: str
    points: np.ndarray
    closed: bool
    score: float
    class_index: int
    track_id: int | None = None

    def __post_init__(self) -> None:
        # checked where it is made (a user's own elements too): a score of None crashed repr and to_hdmapnet far
        # from here, and points of another shape wrote a broken submission
        try:
            points = np.asarray(self.points.detach().cpu() if isinstance(self.points, torch.Tensor) else self.points)
            score = float(self.score)
        except (TypeError, ValueError):
            raise TypeError(f"MapElement: points must be a [P, 2] array and score a number in [0, 1], got points "
                            f"{type(self.points).__name__}, score {self.score!r}") from None
        if points.ndim != 2 or points.shape[1] != 2 or not np.issubdtype(points.dtype, np.number):
            raise ValueError(f"MapElement: points must be a [P, 2] array of x, y in metres, got shape "
                             f"{list(points.shape)}")
        if not (math.isfinite(score) and -1e-4 <= score <= 1.0 + 1e-4):  # (a mean of float32 probabilities rounds)
            raise ValueError(f"MapElement: score must be in [0, 1], got {score}")
        if not np.isfinite(points).all():  # to_hdmapnet wrote NaN, which is not JSON
            raise ValueError("MapElement: points hold NaN or infinite coordinates")
        # the class name and class_index (the submission's 'type') must agree: MapElement('boundary', ..., 0) was
        # written as a divider, and a name of no class ('lane') was kept with no word
        index = self.class_index
        if getattr(index, "ndim", None) == 0 and hasattr(index, "item"):  # a 0-d tensor or numpy integer
            index = index.item()
        classes = ", ".join(f"{k} {c}" for k, c in enumerate(MAP_CLASSES))
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or \
                not 0 <= int(index) < len(MAP_CLASSES):
            raise ValueError(f"MapElement: class_index must be the class id 0..{len(MAP_CLASSES) - 1} ({classes}), "
                             f"got {self.class_index!r}")
        if self.label != MAP_CLASSES[int(index)]:
            raise ValueError(f"MapElement: label {self.label!r} with class_index {int(index)}, which is "
                             f"{MAP_CLASSES[int(index)]!r}; the classes are {classes}")
        track = self.track_id
        if track is not None and (isinstance(track, bool) or not isinstance(track, (int, np.integer)) or track < 0):
            raise ValueError(f"MapElement: track_id must be None or an integer >= 0, got {track!r}")
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "class_index", int(index))
        object.__setattr__(self, "track_id", None if track is None else int(track))

    def __eq__(self, other: object) -> bool:
        # the dataclass's own __eq__ compares the points arrays with ==: "The truth value of an array with more than
        # one element is ambiguous" for `element in elements`
        if not isinstance(other, MapElement):
            return NotImplemented
        return (self.label, self.closed, float(self.score), int(self.class_index), self.track_id) == \
            (other.label, other.closed, float(other.score), int(other.class_index), other.track_id) and \
            self.points.shape == other.points.shape and bool(np.array_equal(self.points, other.points))

    def __hash__(self) -> int:  # equal elements hash equal (a set or dict key of elements)
        return hash((self.label, self.closed, float(self.score), int(self.class_index), self.points.shape,
                     np.ascontiguousarray(self.points, dtype=np.float64).tobytes()))

    def as_polyline(self) -> dict:
        """The polyline dict of docs/conventions.md (``pts``, ``label``, ``closed``, ``score``; ``track_id`` when
        it has one)."""
        poly = {"pts": self.points, "label": self.class_index, "closed": self.closed, "score": self.score}
        return poly if self.track_id is None else {**poly, "track_id": self.track_id}

    def to_hdmapnet(self) -> dict:
        """This element as an HDMapNet submission vector (``pts``, ``pts_num``, ``type``, ``confidence_level``;
        ``track_id`` when it has one)."""
        return polylines_to_vectors([self.as_polyline()])[0]

    def __repr__(self) -> str:
        shape = "closed" if self.closed else "open"
        track = "" if self.track_id is None else f", track {self.track_id}"
        return f"MapElement({self.label}, {len(self.points)} points, {shape}, score {self.score:.2f}{track})"


def to_hdmapnet(elements: Mapping[str, Sequence[MapElement]], meta: dict | None = None) -> dict:
    """``{frame name: elements}`` -> the HDMapNet submission JSON document (``{"meta", "results"}``,
    evaluation/io.py), what ``predict`` writes and ``evaluate-json`` reads."""
    # mapper(frame)'s list passed as it is: a raw "'list' object has no attribute 'items'" (the names are the
    # submission's sample tokens, which only the caller knows)
    if not isinstance(elements, Mapping):
        raise TypeError(f"to_hdmapnet takes {{frame name: elements}} (the names are the submission's sample tokens), "
                        f"got a {type(elements).__name__}; e.g. to_hdmapnet({{'frame': mapper(frame)}})")
    for name, els in elements.items():
        bad = next((e for e in els if not isinstance(e, MapElement)), None) if isinstance(els, Sequence) else els
        if bad is not None:
            raise TypeError(f"to_hdmapnet: frame {name!r}: expected a list of MapElement (one frame's "
                            f"mapper(...) result), got {type(bad).__name__}" + (" in it" if bad is not els else ""))
    return submission({name: [e.as_polyline() for e in els] for name, els in elements.items()}, meta)


@dataclass
class Frame:
    """One moment of a camera rig, camera by camera: either mappings by camera name or sequences in
    the order of ``Mapper.cameras``.

    ``images``: RGB ``numpy`` arrays [H, W, 3] (uint8, or float on 0..1), PIL images, tensors [3, H, W]
    (uint8, or float on 0..1), or image file paths, of any size; ``intrinsics``: [3, 3] in the pixels
    of that image; ``cam_to_ego``: [4, 4] (or [3, 4]) camera -> ego transform (rotation | translation in
    metres; the ego frame: x forward, y left, z up, origin on the ground). ``ground_height``: the road's
    height in that ego frame (metres along its z; 0 when its origin lies on the road, about -0.35 for
    AV2's rear axle): the ground plane of the IPM / MLP view transforms (docs/conventions.md).
    ``ego_pose``: [4, 4] ego -> world (any fixed world frame, metres) at this frame, which a temporal
    model's ``MapStream`` needs to move its memory with the ego (a single frame needs none)."""

    images: Mapping | Sequence
    intrinsics: Mapping | Sequence
    cam_to_ego: Mapping | Sequence
    ground_height: float = 0.0
    ego_pose: np.ndarray | torch.Tensor | None = None


def _by_camera(values, field: str, cameras: tuple[str, ...]) -> list:
    """A frame's field as a list in ``cameras`` order; a ``RigError`` naming missing and extra cameras."""
    if isinstance(values, Mapping):
        missing = [c for c in cameras if c not in values]
        extra = [str(c) for c in values if c not in cameras]
        if missing or extra:
            parts = ([f"missing {', '.join(missing)}"] if missing else []) + (
                [f"not in the checkpoint's rig: {', '.join(extra)}"] if extra else [])
            raise RigError(f"the frame's {field} do not match the checkpoint's cameras ({', '.join(cameras)}): "
                           + "; ".join(parts))
        return [values[c] for c in cameras]
    if isinstance(values, (str, bytes)) or not hasattr(values, "__len__"):
        raise RigError(f"the frame's {field} must be a mapping camera name -> value or a sequence of one per camera "
                       f"({', '.join(cameras)}), got {type(values).__name__}")
    if len(values) != len(cameras):
        raise RigError(f"the frame holds {len(values)} {field} for the checkpoint's {len(cameras)} cameras "
                       f"({', '.join(cameras)}): give one per camera, in that order, or a mapping by name")
    return list(values)


def _rgb_array(image, camera: str) -> np.ndarray:
    """An in-memory image as RGB [H, W, 3] uint8 (or float32 on 0..255)."""
    if hasattr(image, "convert") and hasattr(image, "size"):  # a PIL image
        if getattr(image, "mode", "RGB") not in PIL_8BIT_MODES:  # convert("RGB") clips 16-bit and float pixels
            raise RigError(f"camera {camera}: a PIL image of mode {image.mode!r} (16-bit or float pixels) would be "
                           "clipped to 8 bits by its conversion to RGB (all white, or all black); give 8-bit RGB "
                           "(uint8), or a numpy array of floats on 0..1")
        return np.asarray(image.convert("RGB"))
    if isinstance(image, torch.Tensor):
        if image.ndim != 3 or image.shape[0] != 3:
            raise RigError(f"camera {camera}: an image tensor must be [3, H, W] (RGB), got {list(image.shape)}")
        image = image.detach().cpu()
        if image.is_floating_point() and image.dtype not in (torch.float16, torch.float32, torch.float64):
            image = image.float()  # bfloat16 (and float8) have no numpy dtype; their 0..1 values are exact in float32
        image = image.permute(1, 2, 0).numpy()
    if not isinstance(image, np.ndarray):
        raise RigError(f"camera {camera}: an image must be a numpy array, a PIL image, a tensor or a file path, got "
                       f"{type(image).__name__}")
    if image.ndim != 3 or image.shape[2] != 3 or min(image.shape[:2]) < 1:
        raise RigError(f"camera {camera}: an image array must be RGB [H, W, 3], got shape {list(image.shape)}")
    if image.dtype == np.uint8:
        return image
    if not np.issubdtype(image.dtype, np.floating):
        raise RigError(f"camera {camera}: image values must be uint8 (0..255) or floats (0..1), got {image.dtype}")
    if not np.isfinite(image).all():
        raise RigError(f"camera {camera}: the image holds NaN or infinite values")
    lo, hi = float(image.min()), float(image.max())
    if lo < -FLOAT_IMAGE_SLACK or hi > 1 + FLOAT_IMAGE_SLACK:  # 0..255 floats, or an image normalised already
        raise RigError(f"camera {camera}: a float image holds values on 0..1 (raw RGB), this one spans {lo:.3g}.."
                       f"{hi:.3g}; divide 0..255 values by 255 (or pass uint8), and do not normalise it yourself")
    return image.astype(np.float32) * 255


def _ego_pose(pose) -> torch.Tensor:
    """A frame's ego pose as a [4, 4] float32 tensor (the identity when it has none)."""
    if pose is None:
        return torch.eye(4)
    try:
        T = torch.as_tensor(np.asarray(pose, dtype=np.float64)).float()
    except (TypeError, ValueError):
        raise RigError(f"the frame's ego_pose must be a finite 4x4 (or 3x4) ego -> world transform, got "
                       f"{pose!r:.80}") from None
    if T.shape not in ((4, 4), (3, 4)):
        raise RigError(f"the frame's ego_pose must be a finite 4x4 (or 3x4) ego -> world transform, got shape "
                       f"{list(T.shape)}")
    if not bool(torch.isfinite(T).all()):  # the shape is right: say what is wrong (was "got shape [4, 4]")
        raise RigError(f"the frame's ego_pose has NaN or infinite values ({T.flatten().tolist()!s:.160}); give a "
                       "finite 4x4 (or 3x4) ego -> world transform")
    if T.shape == (4, 4) and not torch.allclose(T[3].double(), torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64),
                                                atol=1e-6):
        # a transposed pose (the translation in the last row) kept a rotation and read as "no motion"
        raise RigError(f"the frame's ego_pose has the last row {T[3].double().numpy().round(4).tolist()}, not "
                       "[0, 0, 0, 1]: transposed (the translation in the last row)? give [[R, t], [0, 0, 0, 1]]")
    R = T[:3, :3].double()
    off, det = float((R @ R.T - torch.eye(3, dtype=R.dtype)).abs().max()), float(torch.linalg.det(R))
    if off > 1e-2 or det < 0:  # a temporal model would warp its memory by a non-rigid motion
        raise RigError(f"the frame's ego_pose has a rotation part that is not a rotation (|R R^T - I| = {off:.3g}, "
                       f"det {det:.3g}); give the 4x4 ego -> world transform [R | t]")
    return torch.cat([T[:3], torch.tensor([[0.0, 0.0, 0.0, 1.0]])]) if T.shape == (3, 4) else T


def _cam_to_ego(T, camera: str) -> np.ndarray:
    """A camera's ``cam_to_ego`` as a float64 [4, 4] or [3, 4] array, or a ``RigError`` naming the camera:
    not a matrix of numbers (a ``(R, t)`` pair), another shape, or a 4x4 whose last row is not (0, 0, 0, 1)
    (a transposed matrix: its rotation part is still a rotation, and the translation would be dropped)."""
    if isinstance(T, torch.Tensor):
        T = T.detach().cpu()
    try:
        T = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError):
        raise RigError(f"camera {camera}: 'cam_to_ego' must be one 4x4 (or 3x4) matrix [R | t], got a "
                       f"{type(T).__name__} that is not one array of numbers; stack a (rotation, translation) pair "
                       "with np.c_[R, t]") from None
    if T.shape not in ((4, 4), (3, 4)):
        raise RigError(f"camera {camera}: 'cam_to_ego' must be a 4x4 (or 3x4) transform, got shape "
                       f"{list(T.shape)}")
    if T.shape == (4, 4) and np.isfinite(T).all() and not np.allclose(T[3], (0.0, 0.0, 0.0, 1.0), atol=1e-6):
        raise RigError(f"camera {camera}: 'cam_to_ego' has the last row {T[3].round(4).tolist()}, not [0, 0, 0, 1]: "
                       "transposed (the translation in the last row)? give [[R, t], [0, 0, 0, 1]]")
    return T


def image_size_of(path: str | Path, camera: str) -> tuple[int, int]:
    """(width, height) of an image file from its header; a ``RigError`` naming the camera and the file
    when it is not a readable image."""
    try:
        with PILImage.open(path) as im:
            return im.size
    except (OSError, ValueError) as e:
        raise RigError(f"camera {camera}: image {path} cannot be read as an image ({type(e).__name__}: "
                       f"{str(e)[:120]})") from None


def with_decoding(cfg: ExperimentConfig, options: Mapping, overrides: Sequence[str] = ()) -> ExperimentConfig:
    """``cfg`` with dotted ``overrides`` (``"model.gnn.num_vertices=600"``) and the decoding ``options``
    (``match_threshold=0.2``: ``model.gnn.<name>``, ``DECODE_OPTIONS``) applied and checked."""
    unknown = sorted(set(options) - set(DECODE_OPTIONS))
    if unknown:
        raise UserError(f"unknown decoding option(s) {', '.join(unknown)}; the decoding options are "
                        f"{', '.join(DECODE_OPTIONS)} (config model.gnn.*)")
    if isinstance(overrides, str):  # one "key=value", not its characters
        overrides = [overrides]
    merged = config_to_dict(cfg)
    deep_update(merged, parse_overrides(list(overrides)))
    merged["model"]["gnn"].update(options)
    return config_from_dict(merged)


class Mapper:
    """A trained model on your cameras: frames in, ``MapElement`` lists out.

        mapper = Mapper.from_checkpoint("runs/demo/run/last.pt")
        elements = mapper(images=images, intrinsics=intrinsics, cam_to_ego=cam_to_ego)   # one frame
        per_frame = mapper([frame_a, frame_b])                                           # a list of Frames

    Each camera's image is resized and cropped as the checkpoint's config says (``data.image_size``,
    ``data.image_fit``; data/transforms.py), with the matching ``post_rot``/``post_tran``. The cameras
    are those of the checkpoint's rig (``cameras``; names and order), each with its own intrinsics and
    pose. ``stream()`` runs a sequence of frames through a model that carries a memory from one frame
    to the next (a temporal model); a single-frame model runs frame by frame.

    ``from_onnx`` wraps an ``export-onnx`` file (onnxruntime, CPU, batch 1) behind the same calls.
    """

    def __init__(self, model, config: ExperimentConfig, *, device: torch.device | None = None, source: str = "",
                 notes: Sequence[str] = (), batch_size: int = 4):
        if not (isinstance(model, (torch.nn.Module, OnnxModel))):
            raise TypeError(f"Mapper takes a model (an InstaGraM module or an OnnxModel), got {type(model).__name__}; "
                            "load a trained one with Mapper.from_checkpoint(path) or Mapper.from_onnx(path)")
        config = as_config(config, "Mapper")  # a YAML file's path (or a dict of its keys); None is no config
        self.model, self.config, self.source, self.notes = model, config, source, list(notes)
        self.device = device if device is not None else torch.device("cpu")
        self.grid = BEVGrid.from_config(config.grid)
        # a model built from another config than the one given: its BEV pixels were read as metres of this grid (every
        # element moved and scaled, no word), its images resized to this image size (refused deep in the forward)
        grid, size = getattr(getattr(model, "graph_head", None), "grid", None), getattr(model, "image_size", None)
        differ = ([f"grid {grid} (config: {self.grid})"] if grid is not None and grid != self.grid else []) + (
            [f"data.image_size {list(size)} (config: {list(config.data.image_size)})"]
            if size is not None and tuple(size) != tuple(config.data.image_size) else [])
        if differ:
            raise ValueError(f"Mapper: the model was built for another config than the one given: {'; '.join(differ)}; "
                             "give the config the model was built from (Mapper.from_checkpoint(path) reads it from the "
                             "checkpoint)")
        self.cameras = rig_cameras(config)
        self.classes = tuple(config.data.classes)
        self.decode_options = decode_options(config.model.gnn, self.grid)
        self.batch_size = 1 if isinstance(model, OnnxModel) else batch_size
        self._warned_stream = False  # __call__ with several frames of a temporal model: said once

    @classmethod
    def from_checkpoint(cls, path: str | Path, device: str | torch.device | None = None, *,
                        overrides: Sequence[str] = (), precision: str = "fp32", compile_backbone: bool = False,
                        **decode_overrides) -> Mapper:
        """The model of a ``train`` checkpoint, built from the config saved in it. ``device``: "cpu", "cuda", a
        ``torch.device`` or None (CUDA when available). ``precision``: fp32 (the default), bf16, int8 (calibrated on
        the saved config's training samples, CPU only) or auto (bf16 where the device computes it natively, fp32
        elsewhere; precision.py). ``compile_backbone``: the image backbone through ``torch.compile``
        (``precision.compile_backbone``: the first frame compiles it, tens of seconds; then a faster backbone on the
        CPU). ``decode_overrides``: decoding options (``DECODE_OPTIONS``, e.g.
        ``match_threshold=0.05``); ``overrides``: dotted config keys (``"model.gnn.num_vertices=600"``). Weights that
        do not fit (another architecture, an override of a layer size) are a ``CheckpointError`` naming the keys."""
        config = decode_overrides.pop("config", None)
        if config is not None or isinstance(device, ExperimentConfig) or str(device).endswith((".yaml", ".yml")):
            # from_onnx's config= was "unknown decoding option(s) config", a YAML file "device='x.yaml' is not a device"
            given = config if config is not None else device
            given = "an ExperimentConfig" if isinstance(given, ExperimentConfig) else f"{given!r:.80}"
            raise TypeError(f"Mapper.from_checkpoint builds the model from the config saved in the checkpoint; it "
                            f"takes no config ({given} given): change keys with overrides=['model.gnn.num_vertices=600'"
                            f", ...] (config= is Mapper.from_onnx's)")
        state = load_checkpoint(path)
        if not isinstance(state.get("config"), dict):
            raise CheckpointError(f"checkpoint {path} holds no config, so its model cannot be built; use a "
                                  "checkpoint written by instagram-hdmap train")
        cfg = with_decoding(saved_config(state["config"], f"checkpoint {path}"), decode_overrides, overrides)
        dev = resolve_device(device, key="device")
        chosen, notes = resolve_precision(precision, dev, flag="precision")
        calibration = calibration_batches(cfg, device=dev, flag="precision") if chosen == "int8" else None
        model = with_precision(load_weights(build_model(cfg), state, path).eval().to(dev), chosen, calibration,
                               compile_backbone)
        for note in notes:
            warnings.warn(note, stacklevel=2)
        return cls(model, cfg, device=dev, source=f"checkpoint {path}", notes=notes)

    @classmethod
    def from_onnx(cls, path: str | Path, config: ExperimentConfig | str | Path | None = None, *,
                  overrides: Sequence[str] = (), **decode_overrides) -> Mapper:
        """An ``export-onnx`` file run by onnxruntime. ``config`` (an ``ExperimentConfig`` or a YAML
        file; default: the config the export stamped in its metadata) and ``overrides`` must agree with
        the graph's baked config (a ``DeployError`` names the keys that differ). It runs on the CPU."""
        if "device" in decode_overrides:  # from_checkpoint's argument; here it was "an unknown decoding option"
            device = decode_overrides.pop("device")
            if device is not None and str(device).split(":")[0] != "cpu":
                raise TypeError(f"Mapper.from_onnx runs the ONNX file with onnxruntime on the CPU: device={device!r} "
                                "is not supported; for a GPU use Mapper.from_checkpoint(path, device=...)")
        meta = read_export(path)  # the file is checked before a config is read
        cfg = exported_config(meta) if config is None else as_config(config, "Mapper.from_onnx")
        cfg = with_decoding(cfg, decode_overrides, overrides)
        return cls(OnnxModel(path, cfg), cfg, source=f"ONNX {path} (onnxruntime)")

    # --- frames -> batch -> outputs -> elements -------------------------------------------------------

    def __call__(self, frames: Frame | Sequence[Frame] | None = None, /, **fields):
        """``mapper(frame)`` or ``mapper(images=..., intrinsics=..., cam_to_ego=...)``: the frame's
        elements; ``mapper([frame, ...])``: a list of them per frame."""
        single = frames is None or isinstance(frames, Frame)
        if isinstance(frames, Mapping):  # {name: frame}: iterating gave the names ("expected Frame objects, got str")
            raise TypeError("mapper takes a Frame or a list of Frames, not a dict; for {name: frame} use "
                            "dict(zip(frames, mapper(list(frames.values()))))")
        if frames is None:
            frames = self._frame(fields)
        elif fields:
            raise TypeError("pass a Frame (or a list of them) or the fields images=, intrinsics=, cam_to_ego=, "
                            "not both")
        frames = [frames] if single else list(frames)
        temporal = bool(getattr(self.model, "is_temporal", False))
        persist = self.config.model.temporal.persist_frames > 0
        if len(frames) > 1 and (temporal or persist) and not self._warned_stream:
            # a list of a drive's frames mapped as independent frames: the memory the model was built for (or the
            # persistence the config asks for) unused
            what = ("this is a temporal model: mapper([frames]) maps each frame on its own, without the memory of the "
                    "frames before it" if temporal else "model.temporal.persist_frames is set: mapper([frames]) maps "
                    "each frame on its own, without keeping what the frames before it found")
            warnings.warn(f"{what}; for a drive, in order, use stream = mapper.stream() and stream.step(frame)",
                          UserWarning, stacklevel=2)
            self._warned_stream = True
        results: list[list[MapElement]] = []
        for start in range(0, len(frames), self.batch_size):
            results += self.decode(self.forward(self.batch(frames[start:start + self.batch_size])))
        return results[0] if single else results

    def stream(self) -> MapStream:
        """A ``MapStream`` over a sequence of frames (``step(frame)``, ``reset()`` at a new scene)."""
        return MapStream(self)

    @staticmethod
    def _frame(fields: dict) -> Frame:
        try:
            return Frame(**fields)
        except TypeError:
            optional = [f.name for f in dataclass_fields(Frame) if f.default is not MISSING]
            required = [f.name for f in dataclass_fields(Frame) if f.name not in optional]
            raise TypeError(f"a frame has the fields {', '.join(required)} (and {', '.join(optional)}); got "
                            f"{sorted(fields)}") from None

    def batch(self, frames: Sequence[Frame]) -> dict[str, torch.Tensor]:
        """The model's input batch (docs/conventions.md keys, CPU) of ``frames``: each image resized and
        cropped as the checkpoint's config says, with its calibration (checked: ``RigError``)."""
        if isinstance(frames, Frame):
            frames = [frames]
        frames = list(frames)
        if not frames:  # torch's raw "stack expects a non-empty TensorList"
            raise ValueError("Mapper.batch: no frames; give at least one Frame")
        d = self.config.data
        keys = ("images", "intrinsics", "cam_to_ego_rot", "cam_to_ego_trans", "post_rot", "post_tran")
        out: dict[str, list] = {k: [] for k in keys}
        for frame in frames:
            if not isinstance(frame, Frame):
                raise TypeError(f"expected Frame objects, got {type(frame).__name__}")
            images = _by_camera(frame.images, "images", self.cameras)
            Ks = _by_camera(frame.intrinsics, "intrinsics", self.cameras)
            poses = _by_camera(frame.cam_to_ego, "cam_to_ego poses", self.cameras)
            per: dict[str, list] = {k: [] for k in keys}
            for name, image, K, T in zip(self.cameras, images, Ks, poses):
                T = _cam_to_ego(T, name)
                if isinstance(image, (str, Path)):
                    named = camera_named_by(image, self.cameras)
                    if named is not None and named != name:  # a list of paths in another order than the cameras
                        raise RigError(f"camera {name}: its image {image} is named for camera {named}; give the "
                                       f"images in the order of the checkpoint's cameras ({', '.join(self.cameras)}) "
                                       "or as a mapping by name")
                    size = image_size_of(image, name)
                    calib = check_calibration(name, K, T[:3, :3], T[:3, 3], image_size=size)
                    try:
                        pixels, post_rot, post_tran = load_image(image, size, d.image_size, fit=d.image_fit)
                    except ImageError as e:
                        raise RigError(f"camera {name}: {e}") from None
                else:
                    rgb = _rgb_array(image, name)
                    calib = check_calibration(name, K, T[:3, :3], T[:3, 3], image_size=(rgb.shape[1], rgb.shape[0]))
                    pixels, post_rot, post_tran = prepare_image(rgb, d.image_size, fit=d.image_fit)
                check_upright(calib.rotation, f"camera {name}: 'cam_to_ego'")
                heading = camera_heading_problem(name, calib.rotation)
                if heading is not None:
                    raise RigError(f"camera {name}: 'cam_to_ego': {heading}")
                for key, value in zip(keys, (pixels, calib.intrinsics, calib.rotation, calib.translation, post_rot,
                                             post_tran)):
                    per[key].append(torch.as_tensor(value).float())
            for key in keys:
                out[key].append(torch.stack(per[key]))
        given = [frame.ground_height for frame in frames]
        try:
            heights = [float(h) for h in given]
        except (TypeError, ValueError):
            heights = [math.nan]  # named below
        if not all(math.isfinite(h) for h in heights):
            raise RigError(f"a frame's ground_height must be a finite height in metres, got {given}")
        if any(abs(h) > MAX_GROUND_HEIGHT_M for h in heights):
            raise RigError(f"a frame's ground_height is the road's height in the ego frame, within "
                           f"{MAX_GROUND_HEIGHT_M:g} m of the ego origin (about -0.35 for AV2's rear axle), got "
                           f"{given}: in metres, not millimetres or a height above sea level")
        return {**{k: torch.stack(v) for k, v in out.items()}, "ground_height": torch.tensor(heights),
                "ego_pose": torch.stack([_ego_pose(frame.ego_pose) for frame in frames])}

    def forward(self, batch: dict, memory: dict | None = None) -> dict[str, torch.Tensor]:
        """The model's outputs for ``batch`` (``run_model``), always in eval mode: a model left in training mode
        (``mapper.model.train()`` in a notebook after fine-tuning) would compute batch-norm statistics of this
        batch and update its running ones, so every output would change silently; it is switched to eval for
        the call and back after."""
        if not isinstance(batch, Mapping):  # a Frame or a list of them: "'Frame' object has no attribute 'items'"
            raise TypeError(f"Mapper.forward takes a model input batch (a dict of tensors, Mapper.batch(frames)), got "
                            f"{type(batch).__name__}; to map frames call mapper(frame) or mapper([frames])")
        training = isinstance(self.model, torch.nn.Module) and self.model.training
        if training:
            self.model.eval()
        try:
            return run_model(self.model, batch, memory)
        finally:
            if training:
                self.model.train()

    def elements(self, polylines: Sequence[dict]) -> list[MapElement]:
        """One sample's polyline dicts (postprocess.py) as ``MapElement`` objects."""
        return [MapElement(self.classes[p["label"]], p["pts"], p["closed"], p["score"], p["label"], p.get("track_id"))
                for p in polylines]

    def decode(self, outputs: dict[str, torch.Tensor]) -> list[list[MapElement]]:
        """Model outputs -> each sample's elements (postprocess.py, with the checkpoint's decoding)."""
        if not isinstance(outputs, Mapping):
            raise TypeError(f"Mapper.decode takes the model's outputs (the dict of Mapper.forward), got "
                            f"{type(outputs).__name__}; to map frames call mapper(frame)")
        return [self.elements(sample) for sample in postprocess_batch(outputs, self.grid, **self.decode_options)]

    def __repr__(self) -> str:
        return (f"Mapper({self.source or type(self.model).__name__}; cameras {', '.join(self.cameras)}; images "
                f"{self.config.data.image_size[0]}x{self.config.data.image_size[1]} ({self.config.data.image_fit}); "
                f"classes {', '.join(self.classes)}; decoder {self.config.model.gnn.decoder}; "
                f"{precision_of(self.model) if isinstance(self.model, torch.nn.Module) else 'fp32'})")


class MapStream:
    """Frames of one drive, in order: ``step(frame)`` returns the frame's elements and keeps the model's
    ``out["memory"]`` for the next step (a temporal model's previous BEV features, ego pose and
    validity, moved into each new frame by the frames' ``ego_pose``; a single-frame model has none and
    runs frame by frame); ``reset()`` starts a new scene (the next batch carries ``scene_start`` = True
    and no memory). ``status``: the last step's memory status (``models.temporal.STATUS_NAMES``: fused,
    no_memory, pose_jump: the ego moved more than ``model.temporal.max_jump_m`` or turned more than
    ``model.temporal.max_turn_deg`` since the previous frame, so the memory was reset), and ``counts`` of
    them since the stream began.

    Each element of a frame with an ``ego_pose`` carries a ``track_id``: the same map element keeps its ID
    from frame to frame while it is seen, and for up to ``persistence.TRACK_LOOK_BACK`` (5) frames it is
    missed (``persistence.stream_tracker``: Chamfer matching of the tracks moved by the ego motion, within
    ``TRACK_MATCH_M``, 1.5 m). IDs are never reused by one stream: after ``reset()`` (or a pose jump)
    every element gets a new one. A frame without an ``ego_pose`` cannot be related to the one before:
    its elements have ``track_id`` None."""

    def __init__(self, mapper: Mapper):
        self.mapper = mapper
        self.counts: dict[str, int] = {}
        self.persist = Persistence.from_config(mapper.config)  # model.temporal.persist_frames (persistence.py)
        self.tracker = stream_tracker(mapper.config)
        self.first_id = 0  # the IDs of the scene since the last reset start here
        self.reset()

    def reset(self) -> None:
        self.memory: dict | None = None
        if self.persist is not None:
            self.persist.reset()
        self.first_id += self.tracker.next_id.get("stream", 0)
        self.tracker.reset()
        self.frame_index = 0
        self.status: str | None = None
        self.origin: np.ndarray | None = None  # the scene's first ego position (float64), see _local

    def _local(self, frame: Frame) -> Frame:
        """``frame`` with its ego pose moved by the scene's first ego position (float64): the model reads
        poses in float32, whose step at world coordinates of millions of metres (UTM northings, ECEF) is
        0.25-0.5 m, which would misplace the warped memory by that much; relative poses are unchanged."""
        if frame.ego_pose is None:
            return frame
        pose = frame.ego_pose.detach().cpu() if isinstance(frame.ego_pose, torch.Tensor) else frame.ego_pose
        try:
            T = np.array(pose, dtype=np.float64)
        except (TypeError, ValueError):
            return frame  # Mapper.batch names it
        if T.shape not in ((4, 4), (3, 4)) or not np.isfinite(T).all():
            return frame  # Mapper.batch names it
        dtype = np.dtype(str(pose.dtype).removeprefix("torch.")) if hasattr(pose, "dtype") else np.dtype(np.float64)
        far = float(np.abs(T[:3, 3]).max())
        if dtype.kind == "f" and dtype.itemsize < 8 and float(np.spacing(np.array(far, dtype))) > 0.01:
            raise RigError(f"the frame's ego_pose is {dtype} at {far:.3g} m from the world origin, where {dtype} "
                           f"holds positions only to {float(np.spacing(np.array(far, dtype))):g} m: the memory would "
                           "be misplaced by that much; give ego poses as float64 (the stream moves them near the "
                           "origin itself)")
        if self.origin is None:
            self.origin = T[:3, 3].copy()
        T[:3, 3] -= self.origin
        return replace(frame, ego_pose=T)

    def step(self, frame: Frame | None = None, /, **fields) -> list[MapElement]:
        if frame is not None and fields:  # the fields were dropped with no word
            raise TypeError("MapStream.step takes a Frame or the fields images=, intrinsics=, cam_to_ego=, "
                            "ego_pose=, not both")
        frame = frame if frame is not None else Mapper._frame(fields)
        if not isinstance(frame, Frame):  # a list of frames: a stream takes them one step at a time
            raise TypeError(f"MapStream.step takes one Frame (or the fields images=, intrinsics=, cam_to_ego=, "
                            f"ego_pose=), got {type(frame).__name__}; call step() once per frame, in order")
        temporal = bool(getattr(self.mapper.model, "is_temporal", False))
        if frame.ego_pose is None and (temporal or self.persist is not None):
            what = "a temporal model moves its memory" if temporal else \
                "model.temporal.persist_frames moves the elements it keeps"
            raise RigError(f"{what} with the ego: give every frame of a stream its ego_pose (4x4 ego -> world), e.g. "
                           "Frame(..., ego_pose=pose)")
        batch = self.mapper.batch([self._local(frame)])
        batch["scene_start"] = torch.tensor([self.frame_index == 0])
        batch["frame_index"] = torch.tensor([self.frame_index])
        outputs = self.mapper.forward(batch, self.memory)
        self.memory, self.frame_index = outputs.get("memory"), self.frame_index + 1
        if "memory_status" in outputs:
            self.status = STATUS_NAMES[int(outputs["memory_status"][0])]
            self.counts[self.status] = self.counts.get(self.status, 0) + 1
        polylines = postprocess_batch(outputs, self.mapper.grid, **self.mapper.decode_options)[0]
        if self.persist is not None:
            polylines = self.persist.step(polylines, "stream", self.frame_index - 1, batch["ego_pose"][0])
        if frame.ego_pose is not None:
            ids = self.tracker.step(polylines, "stream", self.frame_index - 1, batch["ego_pose"][0])
            polylines = [{**p, "track_id": self.first_id + i} for p, i in zip(polylines, ids)]
        return self.mapper.elements(polylines)
