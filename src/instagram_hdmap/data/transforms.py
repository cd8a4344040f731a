"""Camera images: fast decode, resize / crop / rotate, normalise, and the matching post_rot/post_tran.

Pixel convention (OpenCV's): integer image coordinates are pixel *centres*. The network image is an
affine warp of the original image: ``p_net = post_rot[:2, :2] @ p_orig + post_tran[:2]`` with
``p = (u, v)`` in original-image pixels (the frame of the calibration intrinsics). post_rot/post_tran
are 3x3 / 3 as in LSS (third row/entry identity/zero, so they act on (u, v, depth)).

The warp, in original pixels: uniform resize ``r = max(h / H, w / W) * scale`` (``fit="cover"``: cover
the output, as lift-splat-shoot), crop a (h, w) window (horizontally centred, vertically at the bottom
so the road is kept and the sky cut; jittered by augmentation), rotate about the output centre. With
``fit="contain"`` (``data.image_fit``) the resize is ``r = min(h / H, w / W) * scale``: the whole image
fits, centred, and the rest of the window is black (cameras of mixed aspect ratios, e.g. AV2's).
With ``fit="stretch"`` each axis is resized on its own, ``(r_x, r_y) = (w / W, h / H) * scale``: the
whole image fills the window, its aspect ratio changed (the official InstaGraM / HDMapNet loader,
``data/dataset.py:100-104`` and ``data/image.py:34-49`` at juyebshin/InstaGraM 2b978e4: 1600 x 900 ->
352 x 128, no crop).

Decoding: JPEG images are decoded with OpenCV's reduced-resolution DCT decode
(``cv2.IMREAD_REDUCED_COLOR_{2,4,8}``; other formats, PNG, at full resolution) at the largest factor f
in {1, 2, 4, 8} with ``r * f <= 1`` (so the warp never upsamples the decoded image); decoded pixel ``i``
covers original pixels ``[i f, (i + 1) f)``, i.e. ``u_orig = f * u_dec + (f - 1) / 2``. That factor is
composed into the warp, so post_rot/post_tran always map *original* pixels, whatever the decode. When
the remaining scale is below 1/2 (full decode of a large image) the image is first shrunk with
``INTER_AREA``; the final resample is one bilinear ``cv2.warpAffine``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from ..config import DataConfig, UserError

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
_REDUCED_FLAGS = {1: cv2.IMREAD_COLOR, 2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4,
                  8: cv2.IMREAD_REDUCED_COLOR_8}


_NORM_SCALE = 1 / (255 * torch.tensor(IMAGENET_STD).view(3, 1, 1))
_NORM_OFFSET = -torch.tensor(IMAGENET_MEAN).view(3, 1, 1) / torch.tensor(IMAGENET_STD).view(3, 1, 1)


class ImageError(UserError):
    """A camera image is missing, unreadable, truncated or of an unexpected size."""


@dataclass(frozen=True)
class ImageAug:
    """One draw of the train-time augmentation (identity by default)."""

    scale: float = 1.0  # multiplies the base resize
    crop_dx: float = 0.0  # crop window offset, fraction of the output width
    crop_dy: float = 0.0  # fraction of the output height (negative: moves the window up)
    rotate_deg: float = 0.0  # about the output image centre, counter-clockwise on screen


def sample_augmentation(cfg: DataConfig, rng: np.random.Generator) -> ImageAug:
    """Random scale, crop jitter and rotation within the ``data.aug_*`` ranges."""
    j = cfg.aug_crop_jitter
    return ImageAug(scale=float(rng.uniform(*cfg.aug_scale)), crop_dx=float(rng.uniform(-j, j)),
                    crop_dy=float(rng.uniform(-j, j)),
                    rotate_deg=float(rng.uniform(-cfg.aug_rotate_deg, cfg.aug_rotate_deg)))


def _scale_matrix(sx: float, sy: float) -> np.ndarray:
    """3x3 affine of a resize by (sx, sy) in pixel-centre coordinates: x' = (x + 0.5) sx - 0.5."""
    return np.array([[sx, 0, 0.5 * sx - 0.5], [0, sy, 0.5 * sy - 0.5], [0, 0, 1]], dtype=np.float64)


def image_affine(orig_wh: tuple[int, int], out_hw: tuple[int, int], aug: ImageAug = ImageAug(),
                 fit: str = "cover") -> np.ndarray:
    """3x3 affine: original-image pixel (u, v, 1) -> network-input pixel (see module docstring)."""
    W, H = orig_wh
    h, w = out_hw
    if fit == "stretch":
        rx, ry = w / W * aug.scale, h / H * aug.scale
    else:
        rx = ry = (max if fit == "cover" else min)(h / H, w / W) * aug.scale
    new_w, new_h = W * rx, H * ry
    crop_x = (new_w - w) / 2 + aug.crop_dx * w
    # keep the bottom of a taller image; centre a shorter one (contain)
    crop_y = (new_h - h if new_h >= h else (new_h - h) / 2) + aug.crop_dy * h
    crop_x = min(max(crop_x, min(0.0, new_w - w)), max(0.0, new_w - w))
    crop_y = min(max(crop_y, min(0.0, new_h - h)), max(0.0, new_h - h))
    A = _scale_matrix(rx, ry)
    A = np.array([[1, 0, -crop_x], [0, 1, -crop_y], [0, 0, 1]]) @ A
    if aug.rotate_deg:
        c = np.array([(w - 1) / 2, (h - 1) / 2])
        a = math.radians(aug.rotate_deg)
        rot = np.array([[math.cos(a), math.sin(a)], [-math.sin(a), math.cos(a)]])  # y points down
        R = np.eye(3)
        R[:2, :2] = rot
        R[:2, 2] = c - rot @ c
        A = R @ A
    return A


def decode_factor(scale: float, reduced: bool = True) -> int:
    """Largest f in {1, 2, 4, 8} with scale * f <= 1 (1 when ``reduced`` is off)."""
    if not reduced:
        return 1
    f = 1
    while f < 8 and scale * f * 2 <= 1 + 1e-9:
        f *= 2
    return f


def read_image(path: str | Path, factor: int = 1) -> tuple[np.ndarray, int]:
    """Decode an image at 1/factor resolution (BGR uint8 [h, w, 3]) and return it with the factor used:
    ``factor`` for a JPEG (OpenCV's DCT-domain reduced decode, ceil(W / f) pixels), 1 for any other format
    (OpenCV shrinks those after decoding, to floor(W / f) pixels: a warp by 1 / f would misplace them).
    ``ImageError`` naming the file when it is missing, unreadable or a truncated JPEG."""
    path = Path(path)
    try:
        buf = np.fromfile(path, dtype=np.uint8)
    except OSError as e:
        raise ImageError(f"camera image not found or unreadable: {path} ({e.strerror})") from None
    if not len(buf):  # was "cannot be decoded (corrupt or not an image)"
        raise ImageError(f"camera image is empty (0 bytes): {path}: a download or extraction cut short? extract or "
                         "copy it again")
    is_jpeg = len(buf) >= 4 and buf[0] == 0xFF and buf[1] == 0xD8
    if is_jpeg and not (buf[-2] == 0xFF and buf[-1] == 0xD9) and b"\xff\xd9" not in buf[-64:].tobytes():
        raise ImageError(f"camera image is truncated (no JPEG end marker): {path}")
    if is_jpeg and b"Exif" in buf[:65536].tobytes():
        orientation = _exif_orientation(buf)
        if orientation not in (None, 1):
            # OpenCV turns the pixels as the tag says (a 180-degree tag: the model saw the image upside down,
            # exit 0); the header's size, and so the calibration's check, is that of the stored pixels
            raise ImageError(f"camera image {path} carries the EXIF orientation tag {orientation} "
                             f"({_ORIENTATIONS.get(orientation, 'unknown')}), which decoders apply: its pixels "
                             "would be turned away from those the calibration describes; save the image without "
                             "the tag (e.g. exiftool -Orientation= FILE), or turn the pixels for good "
                             "(PIL.ImageOps.exif_transpose) with intrinsics of the turned image")
    factor = factor if is_jpeg else 1
    img = cv2.imdecode(buf, _REDUCED_FLAGS[factor]) if len(buf) else None
    if img is None:
        raise ImageError(f"camera image cannot be decoded ({_undecodable_kind(buf)}): {path}")
    return img, factor


def _pil_header(source, read):
    """``read(image)`` of PIL's lazily opened image of ``source`` (a path or a buffer's bytes), or None where PIL
    cannot read it either (not an image, a damaged header)."""
    import io

    from PIL import Image

    try:
        with Image.open(io.BytesIO(source.tobytes()) if isinstance(source, np.ndarray) else source) as im:
            return read(im)
    except Exception:
        return None


def _undecodable_kind(buf: np.ndarray) -> str:
    """Why OpenCV decoded nothing: a valid image of a kind it does not read (a float TIFF, an animated GIF:
    PIL opens them) or no image at all."""
    kind = _pil_header(buf, lambda im: f"{im.format} {im.mode}{', animated' if getattr(im, 'is_animated', 0) else ''}")
    if kind is None:
        return "corrupt or not an image"
    return f"a {kind} image, which OpenCV does not read; save it as an 8-bit RGB JPEG or PNG"


_ORIENTATIONS = {2: "mirrored", 3: "rotated 180 degrees", 4: "flipped upside down", 5: "transposed",
                 6: "rotated 90 degrees", 7: "transversed", 8: "rotated 270 degrees"}


def _exif_orientation(buf: np.ndarray) -> int | None:
    """The EXIF orientation tag (274) of a JPEG's bytes, or None (no tag, or a header PIL cannot read: the image is
    decoded, or named, as any other)."""
    value = _pil_header(buf, lambda im: im.getexif().get(0x0112))
    return int(value) if isinstance(value, int) else None


def _axis_scales(A: np.ndarray) -> tuple[float, float]:
    """The resize along each original axis (rotation aside): the column norms of A's linear part."""
    return math.hypot(A[0, 0], A[1, 0]), math.hypot(A[0, 1], A[1, 1])


def load_image(path: str | Path, orig_wh: tuple[int, int], out_hw: tuple[int, int], aug: ImageAug = ImageAug(),
               reduced_decode: bool = True, fit: str = "cover") -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Decode, warp and normalise one camera image.

    orig_wh: (W, H) of the image file (as in its nuScenes ``sample_data`` record).
    fit: "cover", "contain" or "stretch" (module docstring).
    Returns ``image`` [3, h, w] float32 (RGB, ImageNet-normalised), ``post_rot`` [3, 3] and
    ``post_tran`` [3] float32 mapping original pixels to network pixels.
    """
    W, H = orig_wh
    A = image_affine(orig_wh, out_hw, aug, fit)
    f = decode_factor(max(_axis_scales(A)), reduced_decode)
    img, f = read_image(path, f)
    exp_w, exp_h = math.ceil(W / f), math.ceil(H / f)
    if img.shape[1] != exp_w or img.shape[0] != exp_h:
        # a dataset whose images were resized (a half-resolution copy) or rotated: say what the file is (the
        # header's exact size; a reduced decode rounds it) and what to do, not only the reduced-decode sizes
        size = _pil_header(path, lambda im: "{}x{}".format(*im.size)) or f"about {img.shape[1] * f}x{img.shape[0] * f}"
        raise ImageError(f"camera image {path} decodes to {img.shape[1]}x{img.shape[0]} at 1/{f}, expected {exp_w}x"
                         f"{exp_h} from its recorded size {W}x{H} (nuScenes sample_data, AV2 intrinsics.feather): the "
                         f"file is {size}, a resized or rotated copy? the calibration is that of the recorded size: "
                         "use the dataset's original images")
    return _warp(img, A, f, out_hw, bgr=True)


def prepare_image(image: np.ndarray, out_hw: tuple[int, int], aug: ImageAug = ImageAug(),
                  fit: str = "cover") -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``load_image`` for an image already in memory: RGB [H, W, 3], uint8 (or float32 on 0..255).
    The same warp and normalisation as ``load_image`` of the same pixels decoded at full resolution
    (``load_image`` decodes a JPEG at a reduced size where the warp shrinks it by 2 or more)."""
    H, W = image.shape[:2]
    return _warp(np.ascontiguousarray(image), image_affine((W, H), out_hw, aug, fit), 1, out_hw, bgr=False)


def _warp(img: np.ndarray, A: np.ndarray, f: int, out_hw: tuple[int, int], bgr: bool
          ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``img`` decoded at 1/``f`` of the original size -> (network image, post_rot, post_tran) of the
    warp ``A`` (original pixels -> network pixels)."""
    h, w = out_hw
    sx, sy = _axis_scales(A)
    # decoded pixel -> original pixel (the inverse of a resize by s is the resize by 1 / s)
    to_orig = _scale_matrix(f, f)
    rx, ry = sx * f, sy * f
    if min(rx, ry) < 0.5:  # big shrink left (full decode): area-average first, bilinear cannot
        sw, sh = max(1, round(img.shape[1] * rx)), max(1, round(img.shape[0] * ry))
        sx, sy = sw / img.shape[1], sh / img.shape[0]
        img = cv2.resize(img, (sw, sh), interpolation=cv2.INTER_AREA)
        to_orig = to_orig @ _scale_matrix(1 / sx, 1 / sy)
    M = (A @ to_orig)[:2]
    out = cv2.warpAffine(img, M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    channels = torch.from_numpy(out).permute(2, 0, 1)  # [3, h, w]
    rgb = channels.flip(0) if bgr else channels  # OpenCV decodes BGR
    image = torch.addcmul(_NORM_OFFSET, rgb.float(), _NORM_SCALE)  # (x / 255 - mean) / std
    return (image, *post_transform(A))


def post_transform(A: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """``post_rot`` [3, 3] and ``post_tran`` [3] (float32, LSS's: identity / zero on the depth axis) of the
    3x3 image affine ``A``."""
    post_rot = torch.eye(3)
    post_rot[:2, :2] = torch.from_numpy(A[:2, :2]).float()
    post_tran = torch.zeros(3)
    post_tran[:2] = torch.from_numpy(A[:2, 2]).float()
    return post_rot, post_tran


def denormalize(images: torch.Tensor) -> torch.Tensor:
    """[..., 3, h, w] normalised -> RGB in [0, 1]."""
    mean = images.new_tensor(IMAGENET_MEAN).view(3, 1, 1)
    std = images.new_tensor(IMAGENET_STD).view(3, 1, 1)
    return (images * std + mean).clamp(0, 1)


# --- camera geometry with post_rot / post_tran ------------------------------------------------


def project_to_image(pts_ego: torch.Tensor, intrinsics: torch.Tensor, cam_to_ego_rot: torch.Tensor,
                     cam_to_ego_trans: torch.Tensor, post_rot: torch.Tensor, post_tran: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """Ego-frame points [N, 3] -> network-image pixels [N, 2] (u, v) and camera depth [N] (one camera).

    Points with depth <= 0 are behind the camera; their pixels are meaningless.
    """
    cam = (pts_ego - cam_to_ego_trans) @ cam_to_ego_rot  # R^T (p - t), as rows
    depth = cam[:, 2]
    uv1 = (cam / depth.clamp(min=1e-6).unsqueeze(-1)) @ intrinsics.T
    net = uv1 @ post_rot.T + post_tran
    return net[:, :2], depth


def image_to_ground(uv_net: torch.Tensor, intrinsics: torch.Tensor, cam_to_ego_rot: torch.Tensor,
                    cam_to_ego_trans: torch.Tensor, post_rot: torch.Tensor, post_tran: torch.Tensor,
                    ground_z: float = 0.0) -> torch.Tensor:
    """Network-image pixels [N, 2] -> the ego-frame points [N, 3] where their rays meet z = ground_z."""
    net = torch.cat([uv_net, torch.ones_like(uv_net[:, :1])], -1)
    uv1 = (net - post_tran) @ torch.linalg.inv(post_rot).T
    rays = (uv1 @ torch.linalg.inv(intrinsics).T) @ cam_to_ego_rot.T  # ego-frame directions
    t = (ground_z - cam_to_ego_trans[2]) / rays[:, 2]
    return cam_to_ego_trans + t.unsqueeze(-1) * rays
