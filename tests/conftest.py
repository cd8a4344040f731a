"""Shared fixtures.

``tiny_world``: a small synthetic nuScenes dataroot (2 train + 1 val scenes x 3 samples, 400 x 225
camera images), generated once per test session; ``av2_world``: the same drives in the Argoverse 2
layout (400 x 303 cameras). ``tiny_world_cfg``: an ``ExperimentConfig`` reading
it (default grid and targets, 128 x 352 network images). Tests that damage a dataroot must work on a
copy (``copy_world``), never on ``tiny_world`` itself.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

TINY_WORLD = {"scenes_train": 2, "scenes_val": 1, "samples_per_scene": 3, "seed": 0, "image_size": "400x225"}
AV2_TINY = {**TINY_WORLD, "image_size": "400x303"}  # the nuScenes tiny world's drives, AV2's 4:3 cameras


def _world_overrides(dataroot: Path) -> list[str]:
    """``data.dataroot`` / ``data.version`` / ``data.splits_file`` overrides for a generated world: the
    version is its one table folder, the splits file its ``splits.json`` if it has one."""
    versions = sorted(p.name for p in Path(dataroot).iterdir() if (p / "sample.json").is_file())
    if len(versions) != 1:
        raise RuntimeError(f"expected one version folder in {dataroot}, found {versions}")
    out = [f"data.dataroot={dataroot}", f"data.version={versions[0]}"]
    if (Path(dataroot) / "splits.json").is_file():
        out.append(f"data.splits_file={Path(dataroot) / 'splits.json'}")
    return out


@pytest.fixture(scope="session")
def tiny_world(tmp_path_factory) -> Path:
    from instagram_hdmap.data.synthetic import generate_world

    root = tmp_path_factory.mktemp("tiny_world") / "nuscenes"
    generate_world(out=str(root), force=True, progress=False, **TINY_WORLD)
    return root


@pytest.fixture(scope="session")
def av2_world(tmp_path_factory) -> Path:
    """The tiny world in the Argoverse 2 sensor layout (skips without the optional extra [av2]). Tests
    that damage it work on a copy."""
    pytest.importorskip("av2", reason='the Argoverse 2 API is the optional extra: pip install -e ".[av2]"')
    from instagram_hdmap.data.synthetic.av2_writer import generate_av2_world

    root = tmp_path_factory.mktemp("av2_world") / "av2"
    generate_av2_world(out=root, force=True, progress=False, **AV2_TINY)
    return root


@pytest.fixture(scope="session")
def tiny_world_cfg(tiny_world):
    from instagram_hdmap.config import load_config

    return load_config(None, [*_world_overrides(tiny_world), "data.image_size=[128,352]"])


@pytest.fixture(scope="session")
def world_overrides():
    """``world_overrides(dataroot)`` -> the config overrides that read a generated world (or a copy)."""
    return _world_overrides


@pytest.fixture
def copy_world(tiny_world, tmp_path):
    """``copy_world()`` -> a private copy of the tiny world (to damage in a test)."""

    def make() -> Path:
        dst = tmp_path / "world_copy"
        shutil.copytree(tiny_world, dst)
        return dst

    return make
