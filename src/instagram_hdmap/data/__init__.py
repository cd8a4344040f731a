"""Datasets of map samples (docs/conventions.md): nuScenes (nuscenes.py) and Argoverse 2 (av2.py)."""

from __future__ import annotations

import weakref

from ..config import as_config
from ..files import hold_world, release_world
from .av2 import AV2MapDataset
from .nuscenes import NuScenesMapDataset
from .rig import CAMERAS


def build_dataset(cfg, split: str, augment: bool | None = None, like=None):
    """The dataset of ``cfg.data.dataset`` for ``split``. ``like``: a dataset of the same config whose
    loaded tables may be shared (nuScenes: its ``NuScenes``). ``cfg``: an ``ExperimentConfig`` or a YAML file."""
    cfg = as_config(cfg, "build_dataset")  # a path was a raw "'str' object has no attribute 'data'"
    if not isinstance(split, str):  # a list was a raw "unhashable type", None read as the split 'None'
        raise TypeError(f"build_dataset: split must be one split name (a str such as {cfg.data.val_split!r}), got "
                        f"{split!r:.60}")
    if augment is not None and not isinstance(augment, bool):  # augment="no" is truthy: it augmented
        raise TypeError(f"build_dataset: augment must be True, False or None (the split's default), got "
                        f"{augment!r:.40}")
    # a synthetic world: synth --force in another process does not replace it while the dataset lives
    lock = hold_world(cfg.data.dataroot)
    try:
        if cfg.data.dataset == "av2":
            dataset = AV2MapDataset(cfg, split, augment=augment)
        else:
            dataset = NuScenesMapDataset(cfg, split, nusc=getattr(like, "nusc", None), augment=augment)
    except BaseException:
        if lock is not None:
            release_world(lock)
        raise
    if lock is not None:
        weakref.finalize(dataset, release_world, lock)
    return dataset


def rig_cameras(cfg) -> tuple[str, ...]:
    """The camera names of ``cfg.data.dataset``'s samples, in the order of their camera tensors (the
    order a model trained on them expects): nuScenes' six, or ``data.av2_cameras``."""
    return tuple(cfg.data.av2_cameras) if cfg.data.dataset == "av2" else CAMERAS
