"""Datasets of map samples (docs/conventions.md): nuScenes (nuscenes.py) and Argoverse 2 (av2.py)."""

from __future__ import annotations

from .av2 import AV2MapDataset
from .nuscenes import NuScenesMapDataset


def build_dataset(cfg, split: str, augment: bool | None = None, like=None):
    """The dataset of ``cfg.data.dataset`` for ``split``. ``like``: a dataset of the same config whose
    loaded tables may be shared (nuScenes: its ``NuScenes``)."""
    if cfg.data.dataset == "av2":
        return AV2MapDataset(cfg, split, augment=augment)
    return NuScenesMapDataset(cfg, split, nusc=getattr(like, "nusc", None), augment=augment)
