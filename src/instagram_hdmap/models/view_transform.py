"""View transforms: per-camera image features -> one BEV feature map (paper Table V).

Shapes: B batch, V cameras, C channels, fh x fw image features (network input / 16),
Hb x Wb the BEV grid of the view transform (the output grid / ``bev_downsample``; by default the
half-resolution grid of F_bev, W/2 x H/2), P points.

Every transform maps ``features [B, V, C, fh, fw]`` and the calibration dict
(``intrinsics``, ``cam_to_ego_rot``, ``cam_to_ego_trans``, ``post_rot``, ``post_tran``, ``ground_height``
[B]; see docs/conventions.md) to ``bev [B, C, Hb, Wb]`` (rows along y, columns along x).

* :class:`IPMViewTransform` - inverse perspective mapping: every BEV cell centre on the ground plane
  ``z = ground_height + ipm_height`` (the sample's road height in the ego frame: 0 on nuScenes, about
  -0.35 m on AV2, whose ego origin is the rear axle) is projected into every camera with the
  calibration and the image features are bilinearly sampled there; cameras that see the cell are
  averaged. No learned parameters.
* :class:`LSSViewTransform` - Lift-Splat-Shoot: a 1x1 conv predicts a categorical depth distribution
  (bins ``depth_bound``) and a context vector per feature pixel; their outer product is lifted to the
  frustum points and sum-pooled into the BEV cells (``sum_pool``, one batched ``index_add``).
* :class:`MLPViewTransform` - HDMapNet: one two-layer fully connected transform per camera maps the
  flattened feature map (fh*fw) to a camera-aligned top-down map (H/5 x W/5), which is then placed
  into the ego frame with the camera's extrinsics (on the same ground plane as IPM) and averaged over
  the cameras that cover a cell.

Geometry runs in float32 with autocast disabled: bf16 would misplace a point at 30 m by ~10 cm.
Pixel convention: integer network-input pixel coordinates are pixel centres; feature pixel ``j``
covers input pixels ``[16 j, 16 j + 16)`` and its centre is at ``16 j + 7.5``.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from ..geometry import BEVGrid, pair_like

CALIBRATION_KEYS = ("intrinsics", "cam_to_ego_rot", "cam_to_ego_trans", "post_rot", "post_tran", "ground_height")
_MIN_DEPTH = 1e-3  # metres in front of the camera for a projection to count


# ---------------------------------------------------------------------------------------------
# Geometry (plain functions)
# ---------------------------------------------------------------------------------------------


def _ego_to_camera(points_m: torch.Tensor, calib: dict[str, torch.Tensor]) -> torch.Tensor:
    """points_m [B, V, P, 3] (ego frame) -> [B, V, P, 3] in each camera's frame: R^T (p - t), float32."""
    rot, trans = calib["cam_to_ego_rot"].float(), calib["cam_to_ego_trans"].float()
    return torch.einsum("bvji,bvpj->bvpi", rot, points_m.float() - trans[:, :, None])


def ego_to_input_pixels(points_m: torch.Tensor, calib: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """Project ego-frame points into each camera's network input.

    points_m [B, V, P, 3] -> (uv_px [B, V, P, 2] network-input pixels, depth [B, V, P] metres along
    the optical axis). ``uv_px`` is meaningless where ``depth <= 0``.
    """
    with torch.autocast(points_m.device.type, enabled=False):
        pix = torch.einsum("bvij,bvpj->bvpi", calib["intrinsics"].float(), _ego_to_camera(points_m, calib))
        depth = pix[..., 2]
        uvd = torch.cat([pix[..., :2] / depth.clamp(min=_MIN_DEPTH)[..., None], depth[..., None]], -1)
        uvd = torch.einsum("bvij,bvpj->bvpi", calib["post_rot"].float(), uvd) + calib["post_tran"].float()[:, :, None]
    return uvd[..., :2], depth


def inverse_3x3(m: torch.Tensor) -> torch.Tensor:
    """Inverse of a batch of 3x3 matrices [..., 3, 3] by the adjugate (cross products of the rows),
    in plain elementwise ops: it exports to ONNX (which has no matrix inverse), needs no host
    synchronisation (capturable in a CUDA graph) and is exact to float32 rounding for the
    well-conditioned calibration matrices used here."""
    r0, r1, r2 = m[..., 0, :], m[..., 1, :], m[..., 2, :]
    c0, c1, c2 = torch.cross(r1, r2, dim=-1), torch.cross(r2, r0, dim=-1), torch.cross(r0, r1, dim=-1)
    det = (r0 * c0).sum(-1)[..., None, None]
    return torch.stack([c0, c1, c2], -1) / det  # column j = cross product j


def input_pixels_to_ego(uvd: torch.Tensor, calib: dict[str, torch.Tensor]) -> torch.Tensor:
    """Back-project network-input pixels with depths to the ego frame (the LSS frustum geometry).

    uvd [B, V, P, 3] = (u', v', depth) -> points_m [B, V, P, 3].
    """
    with torch.autocast(uvd.device.type, enabled=False):
        uvd = uvd.float() - calib["post_tran"].float()[:, :, None]
        uvd = torch.einsum("bvij,bvpj->bvpi", inverse_3x3(calib["post_rot"].float()), uvd)
        cam = torch.cat([uvd[..., :2] * uvd[..., 2:], uvd[..., 2:]], -1)
        combine = calib["cam_to_ego_rot"].float() @ inverse_3x3(calib["intrinsics"].float())
        return torch.einsum("bvij,bvpj->bvpi", combine, cam) + calib["cam_to_ego_trans"].float()[:, :, None]


def pixel_to_sample_grid(uv_px: torch.Tensor, image_size: tuple[int, int]) -> torch.Tensor:
    """Network-input pixels [..., 2] -> ``grid_sample`` coordinates (align_corners=False) of any
    feature map covering the whole input, e.g. the fh x fw features."""
    h, w = image_size
    return (uv_px + 0.5) / pair_like(uv_px, w, h) * 2 - 1


def sum_pool(values: torch.Tensor, cells: torch.Tensor, num_cells: int) -> torch.Tensor:
    """Sum the values of the points that fall into the same cell (the LSS "splat").

    values [B, P, C], cells [B, P] int64 in [0, num_cells) or -1 (outside, dropped)
    -> [B, num_cells, C]. One batched ``index_add_`` into fresh zeros (its gradient is a gather, exactly
    autograd's); in place, since out of place it copies the zeros, a whole BEV grid, once more.
    """
    B, P, C = values.shape
    trash = B * num_cells  # one extra row collects the points outside the grid
    offset = torch.arange(B, device=cells.device)[:, None] * num_cells
    flat = torch.where(cells >= 0, cells + offset, torch.full_like(cells, trash))
    out = values.new_zeros(trash + 1, C).index_add_(0, flat.reshape(-1), values.reshape(B * P, C))
    return out[:trash].view(B, num_cells, C)


def _bev_cell_centres_m(grid: BEVGrid, height: float) -> torch.Tensor:
    """[Hb * Wb, 3] metre coordinates of the cell centres of ``grid`` at height ``height``."""
    xy = torch.from_numpy(grid.cell_centres_m()).float().reshape(-1, 2)
    return torch.cat([xy, torch.full_like(xy[:, :1], height)], 1)


def _on_ground(cell_centres_m: torch.Tensor, ground_height: torch.Tensor, V: int) -> torch.Tensor:
    """cell_centres_m [P, 3] (z: the plane's offset), ground_height [B] -> [B, V, P, 3] with z raised by
    each sample's ground height."""
    z = ground_height.to(cell_centres_m.dtype).reshape(-1, 1, 1, 1)
    lift = torch.cat([torch.zeros_like(z), torch.zeros_like(z), z], -1)  # [B, 1, 1, 3]
    return (cell_centres_m[None, None] + lift).expand(-1, V, -1, -1)


def _sample_cameras(maps: torch.Tensor, grid: torch.Tensor, valid: torch.Tensor, Hb: int, Wb: int) -> torch.Tensor:
    """maps [B, V, C, h, w] sampled (float32, bilinear) at ``grid`` [B, V, Hb*Wb, 2] and averaged over the
    cameras that see each cell (``valid`` [B, V, Hb*Wb]; zero where none does) -> [B, C, Hb, Wb]."""
    B, V, C = maps.shape[:3]
    # float32: bf16 sampling coordinates would be off by up to a BEV pixel
    sampled = F.grid_sample(maps.flatten(0, 1).float(), grid.view(B * V, Hb, Wb, 2), align_corners=False)
    sampled = sampled.view(B, V, C, Hb, Wb)
    weight = valid.view(B, V, Hb, Wb).to(sampled.dtype)[:, :, None]
    count = weight.sum(1).clamp(min=1)
    return (sampled * weight).sum(1) / count


# ---------------------------------------------------------------------------------------------
# Modules
# ---------------------------------------------------------------------------------------------


class IPMViewTransform(nn.Module):
    """Inverse perspective mapping onto the ground plane ``z = ground_height + height`` (no learned
    parameters; ``height``: config ``ipm_height``, the plane's offset above the sample's road)."""

    def __init__(self, bev_grid: BEVGrid, image_size: tuple[int, int], channels: int, height: float = 0.0):
        super().__init__()
        self.bev_grid, self.image_size, self.out_channels = bev_grid, image_size, channels
        self.register_buffer("cell_centres_m", _bev_cell_centres_m(bev_grid, height), persistent=False)

    def forward(self, features: torch.Tensor, calib: dict[str, torch.Tensor]) -> torch.Tensor:
        """features [B, V, C, fh, fw] -> bev [B, C, Hb, Wb]."""
        points = _on_ground(self.cell_centres_m, calib["ground_height"], features.shape[1])
        uv, depth = ego_to_input_pixels(points, calib)  # [B, V, Hb*Wb, 2], [B, V, Hb*Wb]
        grid = pixel_to_sample_grid(uv, self.image_size)
        valid = (depth > _MIN_DEPTH) & (grid.abs() <= 1).all(-1)
        grid = torch.where(valid[..., None], grid, torch.full_like(grid, -2.0))  # outside -> zeros
        return _sample_cameras(features, grid, valid, self.bev_grid.H, self.bev_grid.W)


class LSSViewTransform(nn.Module):
    """Lift (categorical depth x context) - Splat (sum-pool into BEV cells).

    ``depth_net``: 1x1 conv C -> D + C (depth logits, context), as the official InstaGraM LSS.
    """

    def __init__(self, bev_grid: BEVGrid, image_size: tuple[int, int], channels: int,
                 depth_bound: tuple[float, float, float], zbound: tuple[float, float], downsample: int = 16):
        super().__init__()
        self.bev_grid, self.image_size, self.out_channels, self.zbound = bev_grid, image_size, channels, zbound
        depths = torch.arange(*depth_bound, dtype=torch.float32)  # 4, 5, ..., 44 -> D = 41
        h, w = image_size
        fh, fw = h // downsample, w // downsample
        us = (torch.arange(fw, dtype=torch.float32) + 0.5) * downsample - 0.5  # feature pixel centres
        vs = (torch.arange(fh, dtype=torch.float32) + 0.5) * downsample - 0.5
        d, v, u = torch.meshgrid(depths, vs, us, indexing="ij")
        frustum = torch.stack([u, v, d], -1).reshape(-1, 3)  # [D*fh*fw, 3] in (D, fh, fw) order
        self.register_buffer("frustum", frustum, persistent=False)
        self.num_depths = len(depths)
        self.depth_net = nn.Conv2d(channels, self.num_depths + channels, kernel_size=1)

    def geometry(self, calib: dict[str, torch.Tensor]) -> torch.Tensor:
        """Ego-frame position of every frustum point: [B, V, D*fh*fw, 3]."""
        B, V = calib["intrinsics"].shape[:2]
        return input_pixels_to_ego(self.frustum.expand(B, V, -1, -1), calib)

    def bev_cells(self, points_m: torch.Tensor) -> torch.Tensor:
        """points_m [B, ..., 3] -> flat BEV cell index [B, ...] (row * Wb + col), -1 outside the grid."""
        g = self.bev_grid
        col_row = g.px_index(g.m_to_px(points_m[..., :2]))
        col, row, z = col_row[..., 0], col_row[..., 1], points_m[..., 2]
        inside = (col >= 0) & (col < g.W) & (row >= 0) & (row < g.H) & (z >= self.zbound[0]) & (z < self.zbound[1])
        return torch.where(inside, row * g.W + col, torch.full_like(col, -1))

    def lift(self, features: torch.Tensor) -> torch.Tensor:
        """features [B, V, C, fh, fw] -> frustum features [B, V*D*fh*fw, C] (depth prob x context)."""
        B, V, C, fh, fw = features.shape
        x = self.depth_net(features.flatten(0, 1))  # [B*V, D + C, fh, fw]
        depth_probs = x[:, : self.num_depths].softmax(dim=1)
        context = x[:, self.num_depths :]
        lifted = depth_probs[..., None] * context.permute(0, 2, 3, 1)[:, None]  # [B*V, D, fh, fw, C]
        return lifted.reshape(B, -1, C)

    def forward(self, features: torch.Tensor, calib: dict[str, torch.Tensor]) -> torch.Tensor:
        """features [B, V, C, fh, fw] -> bev [B, C, Hb, Wb]."""
        B, C = features.shape[0], self.out_channels
        cells = self.bev_cells(self.geometry(calib)).reshape(B, -1)  # [B, V*D*fh*fw]
        bev = sum_pool(self.lift(features), cells, self.bev_grid.H * self.bev_grid.W)  # [B, Hb*Wb, C]
        return bev.view(B, self.bev_grid.H, self.bev_grid.W, C).permute(0, 3, 1, 2)


class PerCameraLinear(nn.Module):
    """V independent linear layers applied in one batched matmul: [V, M, fin] -> [V, M, fout]."""

    def __init__(self, num_cameras: int, fin: int, fout: int):
        super().__init__()
        bound = 1 / math.sqrt(fin)  # nn.Linear's default initialisation
        self.weight = nn.Parameter(torch.empty(num_cameras, fin, fout).uniform_(-bound, bound))
        self.bias = nn.Parameter(torch.empty(num_cameras, 1, fout).uniform_(-bound, bound))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.baddbmm(self.bias, x, self.weight)


class MLPViewTransform(nn.Module):
    """HDMapNet's neural view transform and its placement into the ego frame.

    Per camera: Linear(fh*fw -> bh*bw) - ReLU - Linear(bh*bw -> bh*bw) - ReLU, shared over channels,
    giving a camera-aligned top-down map [C, bh, bw]: columns = forward distance along the optical
    axis in [0, R], rows = lateral offset along the camera's x axis in [-R, R], with R the distance
    from the ego origin to the farthest BEV corner plus 2 m. Each BEV cell centre (on the plane
    ``z = height``) is expressed in the camera frame and that map is bilinearly sampled there;
    cameras that cover the cell are averaged.
    """

    def __init__(self, bev_grid: BEVGrid, image_size: tuple[int, int], channels: int, camera_bev_size: tuple[int, int],
                 num_cameras: int, height: float = 0.0, downsample: int = 16):
        super().__init__()
        self.bev_grid, self.image_size, self.out_channels = bev_grid, image_size, channels
        self.num_cameras, self.camera_bev_size = num_cameras, camera_bev_size
        fv = (image_size[0] // downsample) * (image_size[1] // downsample)
        bv = camera_bev_size[0] * camera_bev_size[1]
        self.fc1 = PerCameraLinear(num_cameras, fv, bv)
        self.fc2 = PerCameraLinear(num_cameras, bv, bv)
        g = bev_grid
        self.reach_m = math.hypot(max(abs(g.xmin), abs(g.xmax)), max(abs(g.ymin), abs(g.ymax))) + 2.0
        self.register_buffer("cell_centres_m", _bev_cell_centres_m(bev_grid, height), persistent=False)

    def camera_bev(self, features: torch.Tensor) -> torch.Tensor:
        """features [B, V, C, fh, fw] -> camera-aligned top-down maps [B, V, C, bh, bw]."""
        B, V, C = features.shape[:3]
        if V != self.num_cameras:
            raise ValueError(f"the MLP view transform was built for {self.num_cameras} cameras "
                             f"(model.view_transform.num_cameras) but the batch has {V}")
        x = features.flatten(3).transpose(0, 1).reshape(V, B * C, -1)  # [V, B*C, fh*fw]
        x = F.relu(self.fc2(F.relu(self.fc1(x))))  # [V, B*C, bh*bw]
        return x.view(V, B, C, *self.camera_bev_size).transpose(0, 1)

    def place(self, maps: torch.Tensor, calib: dict[str, torch.Tensor]) -> torch.Tensor:
        """Camera-aligned maps [B, V, C, bh, bw] -> ego-frame bev [B, C, Hb, Wb]."""
        with torch.autocast(maps.device.type, enabled=False):
            cam = _ego_to_camera(_on_ground(self.cell_centres_m, calib["ground_height"].float(), maps.shape[1]), calib)
            lateral, forward = cam[..., 0], cam[..., 2]  # camera frame: x right, z forward
            # grid_sample coordinates: x (columns) <- forward in [0, R], y (rows) <- lateral in [-R, R]
            grid = torch.stack([forward / self.reach_m * 2 - 1, lateral / self.reach_m], -1)
            valid = (forward > 0) & (grid.abs() <= 1).all(-1)
        return _sample_cameras(maps, grid, valid, self.bev_grid.H, self.bev_grid.W)

    def forward(self, features: torch.Tensor, calib: dict[str, torch.Tensor]) -> torch.Tensor:
        """features [B, V, C, fh, fw] -> bev [B, C, Hb, Wb]."""
        return self.place(self.camera_bev(features), calib)
