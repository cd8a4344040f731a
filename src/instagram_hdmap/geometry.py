"""The one BEV grid definition used everywhere: range, resolution, size, and conversions.

Frames and conventions (the same as HDMapNet, MapTR and the official InstaGraM export):

* metres (``*_m``): ego frame, x forward, y to the left.
* BEV pixels (``*_px``): ``(u, v)`` with ``u`` the column along x and ``v`` the row along y.
  A BEV tensor is laid out ``[..., H, W]``: H rows along y, W columns along x.
  Integer pixel coordinates are pixel *centres*: pixel ``(j, i)`` covers
  ``x in [xmin + j*res, xmin + (j+1)*res)``; ``u = (x - xmin) / res - 0.5``.
  (InstaGraM's export uses ``x = u * 0.15 - 29.925``, the same mapping.)
* normalised (``*_norm``): ``[-1, 1]`` over the grid extent, ``-1`` at xmin/ymin, the
  ``align_corners=False`` convention of ``torch.nn.functional.grid_sample``.

Paper default: x in [-30, 30], y in [-15, 15], 0.15 m -> W = 400, H = 200; S = 8 -> 50 x 25 cells.
Long range: 100 m x 100 m at 0.25 m -> 400 x 400.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from .config import ConfigError, GridConfig
from .errors import is_real

ArrayLike = np.ndarray | torch.Tensor


def pair_like(like: torch.Tensor, a: float, b: float) -> torch.Tensor:
    """``[a, b]`` with ``like``'s dtype and device, filled on the device: ``new_tensor`` would copy from
    host memory, which a CUDA graph cannot capture (``deploy.CUDAGraphRunner``)."""
    return torch.stack([like.new_full((), a), like.new_full((), b)])


@dataclass(frozen=True)
class BEVGrid:
    xmin: float
    xmax: float
    ymin: float
    ymax: float
    resolution: float
    cell_size: int = 8

    def __post_init__(self) -> None:
        # a resolution of 0 was a raw ZeroDivisionError at .W, NaN a raw "cannot convert float NaN to integer", and
        # xmax < xmin a grid of -64 columns with no word
        vals = {"xmin": self.xmin, "xmax": self.xmax, "ymin": self.ymin, "ymax": self.ymax,
                "resolution": self.resolution}
        bad = next((k for k, v in vals.items() if not (is_real(v) and math.isfinite(v))), None)
        if bad is not None:
            raise ValueError(f"BEVGrid: {bad} must be a finite number (metres), got {vals[bad]!r:.40}")
        if not (self.xmax > self.xmin and self.ymax > self.ymin and self.resolution > 0):
            raise ValueError(f"BEVGrid(xmin={self.xmin}, xmax={self.xmax}, ymin={self.ymin}, ymax={self.ymax}, "
                             f"resolution={self.resolution}): the upper bounds must exceed the lower ones and the "
                             "resolution (metres per pixel) must be > 0")
        if not (is_real(self.cell_size) and self.cell_size == int(self.cell_size) and self.cell_size >= 1):
            raise ValueError(f"BEVGrid: cell_size must be a whole number of pixels >= 1, got {self.cell_size!r:.40}")

    @classmethod
    def from_config(cls, cfg: GridConfig) -> BEVGrid:
        if hasattr(cfg, "grid") and not hasattr(cfg, "xbound"):  # a whole ExperimentConfig: a raw AttributeError
            cfg = cfg.grid
        if not all(hasattr(cfg, k) for k in ("xbound", "ybound", "resolution", "cell_size")):  # a YAML path: raw error
            raise TypeError(f"BEVGrid.from_config takes a config's grid section (cfg.grid) or the config, got "
                            f"{type(cfg).__name__}; a YAML file is read by instagram_hdmap.config.load_config(path)")
        grid = cls(cfg.xbound[0], cfg.xbound[1], cfg.ybound[0], cfg.ybound[1], cfg.resolution, cfg.cell_size)
        grid.check()
        return grid

    def check(self) -> None:
        for name, extent in (("grid.xbound", self.xmax - self.xmin), ("grid.ybound", self.ymax - self.ymin)):
            n = extent / self.resolution
            if abs(n - round(n)) > 1e-6:
                raise ConfigError(f"config key '{name}': extent {extent} m is not a whole number of "
                                  f"{self.resolution} m pixels")
        if self.W % self.cell_size or self.H % self.cell_size:
            raise ConfigError(f"config key 'grid.cell_size': BEV size {self.H}x{self.W} (HxW) is not divisible by "
                              f"S={self.cell_size}; choose a cell size that divides both")

    # --- sizes -------------------------------------------------------------------------------
    @property
    def W(self) -> int:  # columns, along x
        return round((self.xmax - self.xmin) / self.resolution)

    @property
    def H(self) -> int:  # rows, along y
        return round((self.ymax - self.ymin) / self.resolution)

    @property
    def Wc(self) -> int:
        return self.W // self.cell_size

    @property
    def Hc(self) -> int:
        return self.H // self.cell_size

    # --- conversions (numpy arrays or tensors, [..., 2] with (x, y) / (u, v) last) -------------
    def _origin_scale(self, like: ArrayLike):
        if not isinstance(like, (torch.Tensor, np.ndarray)):  # a list was a raw "'list' object has no attribute"
            raise TypeError(f"BEVGrid: points must be a NumPy array or a torch tensor [..., 2], got "
                            f"{type(like).__name__} (wrap it in np.asarray)")
        lo = [self.xmin, self.ymin]
        if isinstance(like, torch.Tensor):
            return pair_like(like, *lo), self.resolution
        return np.asarray(lo, dtype=like.dtype if like.dtype.kind == "f" else np.float64), self.resolution

    def m_to_px(self, pts_m: ArrayLike) -> ArrayLike:
        lo, res = self._origin_scale(pts_m)
        return (pts_m - lo) / res - 0.5

    def px_to_m(self, pts_px: ArrayLike) -> ArrayLike:
        lo, res = self._origin_scale(pts_px)
        return (pts_px + 0.5) * res + lo

    def _size(self, like: ArrayLike) -> ArrayLike:
        """(W, H) as ``like``'s kind: filled on the tensor's device (``pair_like``), float64 for arrays."""
        return pair_like(like, self.W, self.H) if isinstance(like, torch.Tensor) else np.array([self.W, self.H], float)

    def px_to_norm(self, pts_px: ArrayLike) -> ArrayLike:
        return (pts_px + 0.5) / self._size(pts_px) * 2 - 1

    def norm_to_px(self, pts_norm: ArrayLike) -> ArrayLike:
        return (pts_norm + 1) / 2 * self._size(pts_norm) - 0.5

    def m_to_norm(self, pts_m: ArrayLike) -> ArrayLike:
        return self.px_to_norm(self.m_to_px(pts_m))

    def norm_to_m(self, pts_norm: ArrayLike) -> ArrayLike:
        return self.px_to_m(self.norm_to_px(pts_norm))

    def px_index(self, pts_px: ArrayLike) -> ArrayLike:
        """Integer (column, row) of the BEV pixel holding each point; callers check bounds."""
        if isinstance(pts_px, torch.Tensor):
            return torch.floor(pts_px + 0.5).long()
        return np.floor(pts_px + 0.5).astype(np.int64)

    def inside_m(self, pts_m: ArrayLike) -> ArrayLike:
        x, y = pts_m[..., 0], pts_m[..., 1]
        return (x >= self.xmin) & (x < self.xmax) & (y >= self.ymin) & (y < self.ymax)

    def cell_centres_m(self) -> np.ndarray:
        """Metre coordinates of every BEV pixel centre, [H, W, 2]."""
        u, v = np.meshgrid(np.arange(self.W), np.arange(self.H))
        return self.px_to_m(np.stack([u, v], -1).astype(np.float64))


def as_grid(grid, where: str) -> BEVGrid:
    """``grid`` as a BEVGrid: a BEVGrid, a ``GridConfig`` (``cfg.grid``) or a whole config (its ``grid``); another
    object is a TypeError naming ``where`` (a config given as the grid was a raw AttributeError 'xmin' deep inside)."""
    if isinstance(grid, BEVGrid):
        return grid
    if hasattr(grid, "grid") and hasattr(grid.grid, "xbound"):
        grid = grid.grid
    if isinstance(grid, GridConfig):
        return BEVGrid.from_config(grid)
    raise TypeError(f"{where}: grid must be a BEVGrid (geometry.BEVGrid.from_config(cfg.grid)) or a config, got "
                    f"{type(grid).__name__}")

