"""Camera rigs: the nuScenes camera names in the model's order, the sensor rig of a real nuScenes
log (n015, Singapore; the v1.0-mini calibrated_sensor records), and that rig as the calibration
tensors of a batch.

    CAMERAS                                   # the order of a nuScenes sample's camera tensors
    sensors = rig((800, 450))                 # Sensor per channel, intrinsics scaled to 800 x 450 images
    calib = nuscenes_like_rig((128, 352))     # intrinsics, cam_to_ego_rot / trans, post_rot / post_tran [V, ...]

Six cameras (1600 x 900) and LIDAR_TOP: sensor -> ego translation (m), rotation (w, x, y, z) and
camera intrinsics, exactly as published. Intrinsics are scaled when images of another size are
rendered. The ego frame: x forward, y left, z up, origin at the rear axle on the ground.
"""

from __future__ import annotations

import json
import math
import numbers
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from pyquaternion import Quaternion

from ..config import UserError
from .transforms import image_affine, post_transform

NUSCENES_IMAGE_SIZE = (1600, 900)  # (width, height)
# The order of the camera tensors of a nuScenes sample (data/nuscenes.py): the front row left to
# right, then the back row left to right, as the pictures draw them. A trained model depends on it
# (the MLP view transform has one layer per camera).
CAMERAS = ("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_LEFT", "CAM_BACK", "CAM_BACK_RIGHT")
LIDAR = "LIDAR_TOP"

# channel: (translation, rotation wxyz, (fx, cx, cy)) -- fx == fy on every nuScenes camera. In the
# order of the log's calibrated_sensor records, which ``rig`` keeps: the synthetic world draws its
# per-camera randomness in this order.
_RIG = {
    "CAM_FRONT": ((1.70079118954, 0.0159456324149, 1.51095763913),
                  (0.4998015430569128, -0.5030316162024876, 0.4997798114386805, -0.49737083824542755),
                  (1266.417203046554, 816.2670197447984, 491.50706579294757)),
    "CAM_FRONT_RIGHT": ((1.5508477543, -0.493404796419, 1.49574800619),
                        (0.2060347966337182, -0.2026940577919598, 0.6824507824531167, -0.6713610884174485),
                        (1260.8474446004698, 807.968244525554, 495.3344268742088)),
    "CAM_FRONT_LEFT": ((1.52387798135, 0.494631336551, 1.50932822144),
                       (0.6757265034669446, -0.6736266522251881, 0.21214015046209478, -0.21122827103904068),
                       (1272.5979470598488, 826.6154927353808, 479.75165386361925)),
    "CAM_BACK": ((0.0283260309358, 0.00345136761476, 1.57910346144),
                 (0.5037872666382278, -0.49740249788611096, -0.4941850223835201, 0.5045496097725578),
                 (809.2209905677063, 829.2196003259838, 481.77842384512485)),
    "CAM_BACK_LEFT": ((1.03569100218, 0.484795032713, 1.59097014818),
                      (0.6924185592174665, -0.7031619420114925, -0.11648342771943819, 0.11203317912370753),
                      (1256.7414812095406, 792.1125740759628, 492.7757465151356)),
    "CAM_BACK_RIGHT": ((1.0148780988, -0.480568219723, 1.56239545128),
                       (0.12280980120078765, -0.132400842670559, -0.7004305821388234, 0.690496031265798),
                       (1259.5137405846733, 807.2529053838625, 501.19579884916527)),
}
_LIDAR_TOP = ((0.943713, 0.0, 1.84023),
              (0.7077955119163518, -0.006492242056004365, 0.010646214713995808, -0.7063073142877817))


@dataclass(frozen=True)
class Sensor:
    channel: str
    modality: str  # camera | lidar
    translation: tuple[float, float, float]  # sensor -> ego
    rotation: tuple[float, float, float, float]  # sensor -> ego, w x y z
    intrinsic: np.ndarray | None  # [3, 3] for cameras
    size: tuple[int, int] | None = None  # (w, h) of this camera's images; None: the rig's common size

    @property
    def rot(self) -> np.ndarray:
        """[3, 3] sensor -> ego rotation matrix."""
        return Quaternion(self.rotation).rotation_matrix

    @property
    def trans(self) -> np.ndarray:
        return np.array(self.translation)


# a rig file's camera whose optical axis is steeper than this is a rotation read wrongly (a quaternion in
# [x, y, z, w] order turns four of nuScenes' six cameras 55-71 degrees up or down), not a surround camera
MAX_CAMERA_PITCH_DEG = 45


def parse_image_size(text: str | tuple[int, int] | list[int]) -> tuple[int, int]:
    """'1600x900' (or (1600, 900)) -> (width, height); raises UserError naming the problem."""
    if isinstance(text, (tuple, list)):
        if len(text) != 2:
            raise UserError(f"--image-size {text!r}: expected WIDTHxHEIGHT, e.g. 1600x900")
        if not all(isinstance(v, numbers.Real) and not isinstance(v, bool) and float(v).is_integer() for v in text):
            # (64.5, 48) was cut to 64 with no word; ("a", 48) was a raw ValueError
            raise UserError(f"--image-size {text!r}: expected two whole numbers of pixels (width, height)")
        w, h = (int(v) for v in text)
    else:
        m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", str(text))
        if m is None:
            raise UserError(f"--image-size {text!r}: expected WIDTHxHEIGHT in pixels, e.g. 1600x900")
        w, h = int(m.group(1)), int(m.group(2))
    if not (32 <= w <= 8192 and 32 <= h <= 8192):
        raise UserError(f"--image-size {w}x{h}: width and height must be between 32 and 8192 pixels")
    return w, h


def rig(image_size: tuple[int, int] = NUSCENES_IMAGE_SIZE) -> dict[str, Sensor]:
    """The six cameras (intrinsics scaled to `image_size` = (w, h)) and LIDAR_TOP, by channel, in the
    order of the calibration records."""
    sx = image_size[0] / NUSCENES_IMAGE_SIZE[0]
    sy = image_size[1] / NUSCENES_IMAGE_SIZE[1]
    out = {}
    for ch, (t, q, (f, cx, cy)) in _RIG.items():
        k = np.array([[f * sx, 0.0, cx * sx], [0.0, f * sy, cy * sy], [0.0, 0.0, 1.0]])
        out[ch] = Sensor(ch, "camera", t, q, k)
    out[LIDAR] = Sensor(LIDAR, "lidar", *_LIDAR_TOP, None)
    return out


def nuscenes_like_rig(image_size: tuple[int, int], cameras: int = len(CAMERAS)) -> dict[str, torch.Tensor]:
    """Calibration of one sample [V = 6, ...] in ``CAMERAS`` order: the published calibration of the
    real nuScenes log (``rig``: 1600 x 900 images) and the ``post_rot`` / ``post_tran`` of the dataset's
    resize-and-crop to ``image_size`` (h, w) (``data.transforms.image_affine``), and nuScenes'
    ``ground_height`` 0 (a 0-d tensor: its ego frame lies on the road). ``cameras``: an example rig of
    another size (V = ``cameras``, the six cycled: the shapes of an AV2 model's seven cameras)."""
    sensors = rig(NUSCENES_IMAGE_SIZE)
    post_rot, post_tran = post_transform(image_affine(NUSCENES_IMAGE_SIZE, tuple(image_size)))
    V = cameras
    names = [CAMERAS[i % len(CAMERAS)] for i in range(V)]
    return {
        "intrinsics": torch.stack([torch.from_numpy(sensors[c].intrinsic).float() for c in names]),
        "cam_to_ego_rot": torch.stack([torch.from_numpy(sensors[c].rot).float() for c in names]),
        "cam_to_ego_trans": torch.stack([torch.from_numpy(sensors[c].trans).float() for c in names]),
        "post_rot": post_rot.expand(V, 3, 3).clone(),
        "post_tran": post_tran.expand(V, 3).clone(),
        "ground_height": torch.tensor(0.0),
    }


# --- a user's rig: calibration checks and the rig file -----------------------------------------------------


class RigError(UserError):
    """A camera calibration, a rig file or the images given with it that cannot be used; the message
    names the camera and the field."""


@dataclass(frozen=True)
class CameraCalibration:
    """One camera of a rig: ``intrinsics`` [3, 3] (in the pixels of its images), the camera -> ego
    ``rotation`` [3, 3] and ``translation`` [3] (metres; the ego frame: x forward, y left, z up), and
    the (width, height) of its images where known."""

    name: str
    intrinsics: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    image_size: tuple[int, int] | None = None


def _matrix(value, shape: tuple[int, ...], what: str) -> np.ndarray:
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu()  # numpy refuses a tensor that requires grad
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise RigError(f"{what} must be a {'x'.join(map(str, shape))} array of numbers, got {value!r}") from None
    if m.shape != shape:
        got = "x".join(map(str, m.shape)) or "a single number"
        raise RigError(f"{what} must be {'x'.join(map(str, shape))}, got {got}")
    if not np.isfinite(m).all():
        raise RigError(f"{what} holds a value that is not a finite number")
    return m


# fx < W / 50 (or fy < H / 50): a field of view of more than 2 atan(25) = 175 degrees; intrinsics normalised by
# the image size (fx ~ 1) are far below, every real pinhole camera far above (nuScenes' widest: fx = W / 2)
MAX_FOV_RATIO = 50.0
MAX_CAMERA_OFFSET_M = 100.0  # a camera farther than this from the ego origin is not on the vehicle (mm for m?)


def principal_point_implausible(intrinsics, image_size: tuple[int, int]) -> bool:
    """Whether the principal point of ``intrinsics`` is one no camera of a ``image_size`` (width, height) image has:
    beyond both its right and its bottom edge (the intrinsics of a larger image: scaling moves it away from the
    origin on both axes), or more than an image size outside it. An image cropped off-centre (its rows below the
    horizon, a part of a wide image) puts it outside on one side, validly."""
    K = np.asarray(intrinsics, dtype=np.float64)
    (cx, cy), (w, h) = K[:2, 2], image_size
    return bool((cx > w and cy > h) or not (-w <= cx <= 2 * w and -h <= cy <= 2 * h))


def check_pinhole(K: np.ndarray, what: str, image_size: tuple[int, int] | None = None) -> None:
    """A ``RigError`` "``what`` ..." (the caller's names of the camera and its matrix) for a float64 3x3 ``K`` with a
    focal length <= 0 or a last row other than (0, 0, 1) (transposed) or, given its images' (width, height)
    ``image_size``, a field of view over 175 degrees (normalised, or in millimetres) or a principal point no crop of
    the image has (``principal_point_implausible``: intrinsics in the pixels of another image size)."""
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise RigError(f"{what} has a focal length <= 0 (fx = {K[0, 0]:g}, fy = {K[1, 1]:g}); "
                       "give [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in pixels")
    if not np.allclose(K[2], (0.0, 0.0, 1.0), atol=1e-6):
        raise RigError(f"{what} is not a pinhole matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] (rows "
                       f"{K.round(3).tolist()}); transposed?")
    if image_size is not None:
        w, h = image_size
        if K[0, 0] < w / MAX_FOV_RATIO or K[1, 1] < h / MAX_FOV_RATIO:  # a field of view over 175 degrees
            raise RigError(f"{what} has a focal length of (fx, fy) = ({K[0, 0]:g}, {K[1, 1]:g}) pixels for a {w}x{h} "
                           "image, a field of view over 175 degrees that no pinhole camera has: intrinsics normalised "
                           "by the image size (or in millimetres)? give them in pixels")
        if principal_point_implausible(K, (w, h)):
            raise RigError(f"{what} puts the principal point (cx, cy) = ({K[0, 2]:g}, {K[1, 2]:g}) outside its {w}x{h} "
                           "image: intrinsics of another image size? they are in the pixels of the image given "
                           "(scaled with it when the image is resized)")


def check_camera_offset(t: np.ndarray, what: str) -> None:
    """A ``RigError`` "``what`` ..." for a camera -> ego translation ``t`` [3] more than ``MAX_CAMERA_OFFSET_M``
    from the ego origin: not on the vehicle (millimetres)."""
    if float(np.linalg.norm(t)) > MAX_CAMERA_OFFSET_M:
        raise RigError(f"{what} {t.round(3).tolist()} puts the camera {np.linalg.norm(t):.4g} m from the ego origin "
                       f"(more than {MAX_CAMERA_OFFSET_M:g} m): a calibration in millimetres? give the camera's "
                       "position on the vehicle in metres")


def check_calibration(name: str, intrinsics, rotation, translation, source: str = "",
                      image_size: tuple[int, int] | None = None) -> CameraCalibration:
    """The calibration of camera ``name`` as float64 arrays, or a ``RigError`` naming ``source`` (a rig
    file, say), the camera and the field: intrinsics not 3x3 or no pinhole matrix for the camera's ``image_size``
    (width, height) (``check_pinhole``); a rotation that is not orthonormal with determinant +1; a translation
    that is not 3 numbers in metres within ``MAX_CAMERA_OFFSET_M`` of the ego origin."""
    where = f"{source}: camera {name}" if source else f"camera {name}"
    K = _matrix(intrinsics, (3, 3), f"{where}: 'intrinsics'")
    check_pinhole(K, f"{where}: 'intrinsics'", image_size)
    R = _matrix(rotation, (3, 3), f"{where}: 'rotation'")
    off, det = float(np.abs(R @ R.T - np.eye(3)).max()), float(np.linalg.det(R))
    if off > 1e-2 or det < 0:  # 1e-2: a matrix written with 3 decimals passes
        raise RigError(f"{where}: 'rotation' is not a rotation matrix (|R R^T - I| = {off:.3g}, det {det:.3g}); give "
                       "the camera -> ego rotation (its columns: the camera's x right, y down, z forward in the ego "
                       "frame)")
    t = _matrix(translation, (3,), f"{where}: 'translation'")
    check_camera_offset(t, f"{where}: 'translation'")
    return CameraCalibration(name, K, R, t)


def check_upright(rotation: np.ndarray, where: str, hint: str | None = None) -> None:
    """A ``RigError`` for a camera -> ego rotation that no surround camera has: the optical axis (z) or the
    image's x axis more than ``MAX_CAMERA_PITCH_DEG`` from the horizon (looking at the sky or the road,
    or rolled on its side), or the image's y axis pointing up (upside down). Such a rotation is one read
    wrongly: ego -> camera (the transpose; a front camera's x axis then points up), a quaternion in another
    order, a y-up world, an OpenGL camera (y up, z backward)."""
    R = np.asarray(rotation, dtype=np.float64)
    pitch = float(np.degrees(np.arcsin(np.clip(R[2, 2], -1, 1))))  # the optical axis above the horizon
    # the roll about the optical axis, over the whole circle: the angle between the image's down (y) and the
    # world's down, seen along the optical axis (arcsin(R[2, 0]) alone takes 180 degrees, an image upside
    # down, for 0, and 120 for 60)
    roll = abs(float(np.degrees(np.arctan2(R[2, 0], -R[2, 1]))))
    hint = hint or "is it the camera -> ego rotation (not ego -> camera, its transpose)?"
    if abs(pitch) > MAX_CAMERA_PITCH_DEG:
        raise RigError(f"{where}: the camera looks {abs(pitch):.0f} degrees {'up' if pitch > 0 else 'down'}; a "
                       f"surround camera looks within {MAX_CAMERA_PITCH_DEG} degrees of the horizon: {hint}")
    if roll > 135:  # the image's y axis points up: an OpenGL / Blender camera (y up, z backward) or one upside down
        raise RigError(f"{where}: the camera is upside down (rolled {roll:.0f} degrees: its image's y axis, top to "
                       f"bottom, points up): {hint} The rotation is a camera's with x right, y down, z forward "
                       "(OpenCV's convention; an OpenGL / Blender camera, y up and z backward, is "
                       "R @ diag(1, -1, -1)); "
                       "turn the images of a camera mounted upside down by 180 degrees (with the intrinsics and "
                       "rotation of the turned image)")
    if roll > MAX_CAMERA_PITCH_DEG:
        raise RigError(f"{where}: the camera is rolled {roll:.0f} degrees (its image's x axis, left to right, is "
                       f"that far off the horizon); a surround camera is rolled less than {MAX_CAMERA_PITCH_DEG} "
                       f"degrees: {hint}")


def camera_named_by(path, cameras: Sequence[str]) -> str | None:
    """The one camera of ``cameras`` whose name ``path``'s file name (else its folder's) holds as a whole
    word, case aside (nuScenes' ``...__CAM_FRONT__....jpg``, AV2's ``ring_front_center/....jpg``); None when
    it names none or several. CAM_FRONT inside CAM_FRONT_LEFT does not count."""
    for part in (Path(path).name, Path(path).parent.name):
        spans = [(m.start(), m.end(), c) for c in cameras
                 for m in re.finditer(rf"(?<![A-Za-z0-9]){re.escape(c)}(?![A-Za-z0-9])", part, re.IGNORECASE)]
        named = {c for a, b, c in spans if not any(a2 <= a and b <= b2 and (a2, b2) != (a, b) for a2, b2, _ in spans)}
        if named:
            return named.pop() if len(named) == 1 else None
    return None


def _image_size(value, what: str) -> tuple[int, int]:
    # 1600.0 (a writer of floats: numpy, MATLAB) is a whole number too
    if (not isinstance(value, (list, tuple)) or len(value) != 2
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and float(v).is_integer() and v > 0
                       for v in value)):
        raise RigError(f"{what} must be [width, height] in pixels (positive whole numbers), got {value!r}")
    return int(value[0]), int(value[1])


class RigCameras(list):
    """``read_rig_file``'s cameras (a list of ``CameraCalibration``, the file's order) and the rig's
    ``ground_height`` (metres, the road's height in its ego frame)."""

    def __init__(self, cameras=(), ground_height: float = 0.0):
        super().__init__(cameras)
        self.ground_height = ground_height


def read_rig_file(path) -> RigCameras:
    """The cameras of a rig file (docs/guide.md, "Your own cameras"), in its order:

        {"image_size": [W, H],                       # every camera's, unless a camera gives its own
         "cameras": {"CAM_FRONT": {"intrinsics": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]],
                                   "rotation": [[...], [...], [...]],   # camera -> ego, 3x3
                                   "translation": [x, y, z],            # metres, ego frame
                                   "image_size": [W, H]},               # optional
                     ...}}

    ``rotation`` may instead be ``"quaternion": [w, x, y, z]`` (nuScenes' convention). An optional top-level
    ``"ground_height"`` is the road's height in the rig's ego frame (metres along z; default 0: the origin on
    the road, as nuScenes'; about -0.38 for a rig given in AV2's rear-axle frame), the Python API's
    ``Frame(ground_height=...)``: the returned list's ``ground_height``. Errors are one ``RigError`` line naming
    the file, the camera and the field."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8-sig"))  # a byte-order mark (Windows editors) is no JSON
    except OSError as e:
        raise RigError(f"rig file {path} cannot be read ({e.strerror or e})") from None
    except UnicodeDecodeError:
        raise RigError(f"rig file {path} is not a JSON text file (binary: an image given as --rig?)") from None
    except json.JSONDecodeError as e:
        raise RigError(f"rig file {path} is not valid JSON ({e})") from None
    if not isinstance(data, dict) or not isinstance(data.get("cameras"), dict) or not data["cameras"]:
        raise RigError(f"rig file {path}: expected an object with a non-empty 'cameras' object "
                       '{"CAMERA_NAME": {"intrinsics", "rotation", "translation"}, ...}')
    unknown = sorted(set(data) - {"image_size", "cameras", "ground_height"})
    if unknown:
        raise RigError(f"rig file {path}: unknown field(s) {', '.join(unknown)}; a rig file has 'image_size', "
                       "'cameras' and optionally 'ground_height'")
    # the road's height in the rig's ego frame: without it a rig in AV2's rear-axle frame put the ground plane of the
    # IPM / MLP view transforms 0.38 m too high, with no word (the Python API's Frame has it; the file could not say it)
    ground = data.get("ground_height", 0.0)
    if isinstance(ground, bool) or not isinstance(ground, (int, float)) or not math.isfinite(ground):
        raise RigError(f"rig file {path}: 'ground_height' must be a number of metres (the road's height in the ego "
                       f"frame, e.g. -0.38 for AV2's rear-axle origin), got {ground!r:.40}")
    default = _image_size(data["image_size"], f"rig file {path}: 'image_size'") if "image_size" in data else None
    cameras = []
    for name, cam in data["cameras"].items():
        where = f"rig file {path}: camera {name}"
        if not isinstance(cam, dict):
            raise RigError(f"{where}: expected an object with 'intrinsics', 'rotation' and 'translation'")
        fields = {"intrinsics", "rotation", "quaternion", "translation", "image_size"}
        if set(cam) - fields:
            raise RigError(f"{where}: unknown field(s) {', '.join(sorted(set(cam) - fields))}; a camera has "
                           "'intrinsics', 'rotation' (or 'quaternion'), 'translation' and optionally 'image_size'")
        missing = [f"'{k}'" for k in ("intrinsics", "translation") if k not in cam]
        missing += [] if {"rotation", "quaternion"} & set(cam) else ["'rotation' (or 'quaternion')"]
        if missing:
            raise RigError(f"{where}: {' and '.join(missing)} missing")
        if "rotation" in cam and "quaternion" in cam:
            raise RigError(f"{where}: give 'rotation' or 'quaternion', not both")
        rotation = cam.get("rotation")
        if "quaternion" in cam:
            q = _matrix(cam["quaternion"], (4,), f"{where}: 'quaternion'")
            if abs(np.linalg.norm(q) - 1) > 1e-2:
                raise RigError(f"{where}: 'quaternion' is not a unit quaternion [w, x, y, z] (norm "
                               f"{np.linalg.norm(q):.4g})")
            rotation = Quaternion(q / np.linalg.norm(q)).rotation_matrix
        size = _image_size(cam["image_size"], f"{where}: 'image_size'") if "image_size" in cam else default
        if size is None:
            raise RigError(f"{where}: no 'image_size' (give [width, height] for the rig or for this camera)")
        calib = check_calibration(name, cam["intrinsics"], rotation, cam["translation"], f"rig file {path}", size)
        check_upright(calib.rotation, where, "is the quaternion in [w, x, y, z] order (nuScenes, pyquaternion), not "
                      "[x, y, z, w] (scipy, ROS)?" if "quaternion" in cam else None)
        cameras.append(CameraCalibration(name, calib.intrinsics, calib.rotation, calib.translation, size))
    return RigCameras(cameras, ground_height=float(ground))
