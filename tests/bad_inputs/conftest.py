"""Fixtures of the bad-input tables: the session's tiny world with a config file for it and a random checkpoint
(``shared``), and each row's ``Env`` in its own folder (``env``)."""

from __future__ import annotations

import pytest
import torch

from bad_inputs.support import TINY_YAML, Env
from instagram_hdmap.checkpoint import save_checkpoint
from instagram_hdmap.config import config_to_dict, load_config


@pytest.fixture(scope="session")
def shared(tiny_world, world_overrides, tmp_path_factory):
    from instagram_hdmap.models import build_model

    root = tmp_path_factory.mktemp("bad_inputs")
    yaml = root / "tiny_world.yaml"
    data = dict(o.split("=", 1) for o in world_overrides(tiny_world))
    yaml.write_text(
        f"_base_: {TINY_YAML}\n"
        f"data:\n  dataroot: {data['data.dataroot']}\n  version: {data['data.version']}\n"
        f"  splits_file: {data['data.splits_file']}\n  num_workers: 0\n"
        "train:\n  device: cpu\n  epochs: 1\n  batch_size: 2\n  checkpoint_every: 0\n  log_every: 1\n"
        "eval:\n  batch_size: 2\n"
    )
    torch.manual_seed(0)
    cfg = load_config(yaml)
    ckpt = save_checkpoint({"model": build_model(cfg).state_dict(), "config": config_to_dict(cfg)}, root / "random.pt")
    return tiny_world, yaml, ckpt


@pytest.fixture
def env(shared, tmp_path, capsys, monkeypatch, request) -> Env:
    world, yaml, ckpt = shared
    monkeypatch.chdir(tmp_path)
    return Env(world, yaml, ckpt, tmp_path, capsys, monkeypatch, request)
