"""The machinery of the bad-input tables: rows, the environment each row runs in, and the helpers rows of several
input kinds share.

A row is a small function that does the bad thing a hostile but realistic user would do and checks the promise: a
wrong input is named on one line (``UserError``, exit code 2, no traceback), nothing is lost, and no result is
silently wrong. Each ``test_*.py`` here holds the rows of one input kind and runs them as one parametrized test;
``row`` (a decorator) and ``add`` (for rows made in a loop) put a row in the table of the module that defines it.
docs/faults.md cites each row as ``KIND::ID`` (``checkpoints::flipped-bits``).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from instagram_hdmap.checkpoint import save_checkpoint
from instagram_hdmap.cli import main
from instagram_hdmap.config import config_to_dict, load_config

REPO = Path(__file__).resolve().parents[2]
TINY_YAML = REPO / "configs" / "synthetic" / "tiny.yaml"


# --- the tables -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Row:
    id: str  # the situation, in words joined by dashes: checkpoint-flipped-bits
    what: str  # what the user did and what they get
    run: Callable

    def __str__(self) -> str:
        return self.id


TABLES: dict[str, list[Row]] = {}  # module name -> its rows, in the order they are defined


def add(name: str, what: str, run: Callable) -> None:
    """Put the row ``name`` (underscores read as dashes) in the table of the module that defines ``run``."""
    rows = TABLES.setdefault(run.__module__, [])
    row_id = re.sub(r"[^A-Za-z0-9.=+-]+", "-", name).strip("-")
    assert row_id not in {r.id for r in rows}, f"two rows named {row_id}"
    rows.append(Row(row_id, what, run))


def row(what: str):
    """Decorator: the function ``row_NAME`` is the row NAME."""
    def register(fn):
        add(fn.__name__.removeprefix("row_"), what, fn)
        return fn

    return register


def table(module: str) -> list[Row]:
    return TABLES.get(module, [])


# --- the environment a row runs in ------------------------------------------------------------------


@dataclass
class Env:
    world: Path  # the session's tiny synthetic nuScenes world: never damaged
    yaml: Path  # configs/synthetic/tiny.yaml pointed at `world` (num_workers 0, eval batch 2)
    ckpt: Path  # a random tiny model saved with its config
    tmp: Path  # this row's own folder
    capsys: pytest.CaptureFixture
    monkeypatch: pytest.MonkeyPatch
    request: pytest.FixtureRequest  # for the fixtures only some rows need (av2_world)

    def cli(self, *argv) -> tuple[int, str, str]:
        self.capsys.readouterr()
        rc = main([str(a) for a in argv])
        out, err = self.capsys.readouterr()
        return rc, out, err

    def error(self, pattern: str, *argv) -> str:
        """Run the CLI; it must exit 2 with one line on stderr that matches ``pattern``."""
        rc, out, err = self.cli(*argv)
        lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith(("epoch", "eval", "\r"))]
        assert rc == 2, f"exit {rc}, stderr:\n{err[-3000:]}"
        assert len(lines) == 1, f"not one line:\n{err[-3000:]}"
        assert "Traceback" not in err
        assert re.search(pattern, lines[0]), lines[0]
        return lines[0]

    def shadow_world(self, edit_tables: Callable[[dict], None] | None = None, copy_samples: bool = False) -> Path:
        """A world that shares `world`'s maps (and images, unless ``copy_samples``) through symlinks,
        with its own copy of the tables, edited by ``edit_tables({table name: records})``."""
        root = self.tmp / "world"
        root.mkdir()
        for name in ("world.json", "splits.json"):
            shutil.copy(self.world / name, root / name)
        (root / "maps").symlink_to(self.world / "maps")
        if copy_samples:
            shutil.copytree(self.world / "samples", root / "samples")
        else:
            (root / "samples").symlink_to(self.world / "samples")
        version = root / "v1.0-trainval"
        shutil.copytree(self.world / "v1.0-trainval", version)
        if edit_tables is not None:
            tables = {p.stem: json.loads(p.read_text()) for p in version.glob("*.json")}
            edit_tables(tables)
            for name, records in tables.items():
                (version / f"{name}.json").write_text(json.dumps(records))
        return root

    def cfg(self, *overrides):
        return load_config(self.yaml, [f"train.out_dir={self.tmp / 'run'}", *overrides])



# --- helpers shared by rows of several kinds -----------------------------------------------------


def dead_pid() -> int:
    """The id of a process that has exited (and been reaped)."""
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def first(records: list[dict], **match) -> dict:
    return next(r for r in records if all(r[k] == v for k, v in match.items()))


def camera_record(tables: dict, channel: str, sample_index: int = 0) -> tuple[dict, dict]:
    """(sample_data, calibrated_sensor) of camera ``channel`` of the val scene's ``sample_index``-th sample."""
    token = tables["scene"][-1]["first_sample_token"]  # the tiny world's one val scene comes last
    for _ in range(sample_index):
        token = first(tables["sample"], token=token)["next"]
    sensor = first(tables["sensor"], channel=channel)["token"]
    for sd in tables["sample_data"]:
        if sd["sample_token"] == token and sd["is_key_frame"]:
            cs = first(tables["calibrated_sensor"], token=sd["calibrated_sensor_token"])
            if cs["sensor_token"] == sensor:
                return sd, cs
    raise AssertionError(f"no {channel} record for sample {token}")


def val_dataset(cfg):
    from instagram_hdmap.data import build_dataset

    return build_dataset(cfg, cfg.data.val_split, augment=False)


def forbid(env: Env, target: str, what: str) -> None:
    """Make ``target`` (a dotted name) fail the test if it is called: the error must come first."""

    def called(*args, **kwargs):
        raise AssertionError(f"{what} ran before the error")

    env.monkeypatch.setattr(target, called)


def toy_run(env: Env, scores: list[float], *overrides, resume: str | None = None, force: bool = False):
    """A tiny training on in-memory samples whose validations score ``scores`` in turn."""
    from instagram_hdmap import train as train_module
    from test_train import TINY, _loaders

    queue = list(scores)

    def fake_evaluate(*args, **kwargs):
        return {"losses": {"loss_total": 1.0}, "metrics": {"mAP": queue.pop(0)}}

    env.monkeypatch.setattr(train_module, "evaluate", fake_evaluate)
    cfg = load_config(None, [*TINY, f"train.out_dir={env.tmp / 'run'}", *overrides])
    train_loader, sampler, _ = _loaders(cfg)
    summary = train_module.train(cfg, loaders=(train_loader, sampler, [None]), validate=True, resume=resume,
                                 force=force)
    assert not queue, "fewer validations than scores"
    return summary


def av2_copy(env: Env) -> tuple[Path, Path]:
    """A private copy of the tiny AV2 world and the folder of its first train log."""
    root = env.tmp / "av2"
    shutil.copytree(env.request.getfixturevalue("av2_world"), root)
    return root, sorted((root / "train").iterdir())[0]


def av2_error(env: Env, root: Path, pattern: str) -> str:
    return env.error(pattern, "show-gt", env.yaml, "data.dataset=av2", "data.splits_file=null",
                     "data.av2_frame_step=1",
                     "data.image_fit=contain", f"data.dataroot={root}", "--split", "train", "--index", "0",
                     "--out", env.tmp / "show")


def break_image(root: Path, tables_root: Path, sample_index: int, channel: str, how: str) -> Path:
    tables = {p.stem: json.loads(p.read_text()) for p in (tables_root / "v1.0-trainval").glob("*.json")}
    sd, _ = camera_record(tables, channel, sample_index)
    path = root / sd["filename"]
    if how == "missing":
        path.unlink()
    elif how == "truncated":
        path.write_bytes(path.read_bytes()[:500])
    else:
        path.write_bytes(b"\xff\xd8 this is not a JPEG " * 40 + b"\xff\xd9")
    return path


def submission_file(path: Path, vectors: dict, gt: bool) -> Path:
    path.write_text(json.dumps({"meta": {"ground_truth": gt}, "results": vectors}))
    return path


def mapper_frame(env, image_size=(400, 225), intrinsics_size=None):
    """A Mapper of the random tiny checkpoint and one frame of the published nuScenes rig: uint8 images of
    ``image_size`` (w, h), intrinsics for images of ``intrinsics_size`` (default: the same)."""
    from instagram_hdmap import Mapper
    from instagram_hdmap.data.rig import rig

    mapper = Mapper.from_checkpoint(env.ckpt, device="cpu")
    sensors = rig(intrinsics_size or image_size)
    rng = np.random.default_rng(0)
    images = {c: rng.integers(0, 256, (image_size[1], image_size[0], 3), dtype=np.uint8) for c in mapper.cameras}
    poses = {c: np.vstack([np.c_[sensors[c].rot, sensors[c].trans], [0, 0, 0, 1]]) for c in mapper.cameras}
    return mapper, images, {c: sensors[c].intrinsic for c in mapper.cameras}, poses


def rig_files(env, edit: Callable[[dict], None] | None = None) -> tuple[Path, list[Path]]:
    """A rig file of the published nuScenes rig (400 x 225 images) and one JPEG per camera, ``edit``ed."""
    from PIL import Image

    from instagram_hdmap.data.rig import CAMERAS, rig

    sensors = rig((400, 225))
    cameras = {c: {"intrinsics": sensors[c].intrinsic.tolist(), "quaternion": list(sensors[c].rotation),
                   "translation": list(sensors[c].translation)} for c in CAMERAS}
    data = {"image_size": [400, 225], "cameras": cameras}
    if edit is not None:
        edit(data)
    path = env.tmp / "rig.json"
    path.write_text(json.dumps(data))
    images = []
    for k, c in enumerate(CAMERAS):
        images.append(env.tmp / f"{c}.jpg")
        texture = (np.arange(400, dtype=np.uint8) % 16)[None, :, None]  # not blank: a blank frame may repeat
        Image.fromarray(np.full((225, 400, 3), 40 * k, np.uint8) + texture).save(images[-1])
    return path, images


def val_scene(env) -> str:
    return json.loads((env.world / "v1.0-trainval" / "scene.json").read_text())[-1]["name"]


def temporal_checkpoint(env) -> Path:
    """A random tiny temporal checkpoint (``model.temporal.memory=bev``, 3 Sinkhorn iterations)."""
    from instagram_hdmap.models import build_model

    torch.manual_seed(0)
    cfg = env.cfg("model.temporal.memory=bev", "model.gnn.sinkhorn_iters=3")
    return save_checkpoint({"model": build_model(cfg).state_dict(), "config": config_to_dict(cfg)},
                           env.tmp / "temporal.pt")


def evaluate_world(env, edit, pattern: str) -> str:
    """Evaluate on a shadow world whose tables ``edit`` changed; it must stop on one line matching ``pattern``."""
    root = env.tmp / "world"
    if root.exists():
        shutil.rmtree(root)
    return env.error(pattern, "evaluate", env.yaml, f"data.dataroot={env.shadow_world(edit)}", "--checkpoint",
                     env.ckpt, "--out", env.tmp / "eval")


def av2_dataset(env, split: str, root: Path | None = None):
    from instagram_hdmap.data import build_dataset

    root = root or env.request.getfixturevalue("av2_world")
    cfg = env.cfg("data.dataset=av2", "data.splits_file=null", "data.av2_frame_step=1", "data.image_fit=contain",
                  f"data.dataroot={root}")
    return build_dataset(cfg, split, augment=False)


def benchmark_temporal(env, *args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(REPO / "benchmarks" / "temporal.py"), *args, "--cache",
                           str(env.tmp / "cache"), "--out", str(env.tmp / "out")], capture_output=True, text=True,
                          timeout=120, env={**os.environ, "PYTHONPATH": str(REPO / "src")})
