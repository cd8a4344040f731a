"""Synthetic world generation in worker processes: same bytes as in one process, errors name the
scene, failures and Ctrl-C leave no folder and no process behind."""

from __future__ import annotations

import multiprocessing
from pathlib import Path

import pytest

from instagram_hdmap.cli import main
from instagram_hdmap.config import UserError
from instagram_hdmap.data.synthetic import generate_world, world

ARGS = dict(scenes_train=2, scenes_val=1, samples_per_scene=2, seed=5, image_size="200x113", progress=False)


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_workers_give_byte_identical_worlds(tmp_path):
    one = generate_world(tmp_path / "one", workers=1, **ARGS)
    many = generate_world(tmp_path / "many", workers=5, **ARGS)  # more workers than scenes: 3 are used
    assert one == many
    a, b = _files(tmp_path / "one"), _files(tmp_path / "many")
    assert sorted(a) == sorted(b)
    assert sum(name.endswith(".jpg") for name in a) == 3 * 2 * 6
    differing = [name for name in a if a[name] != b[name]]
    assert differing == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["many", "one"]  # no temporary folder left
    assert multiprocessing.active_children() == []


@pytest.mark.parametrize("workers", [-1, 1.5, "2"])
def test_bad_workers_is_a_user_error(tmp_path, workers):
    with pytest.raises(UserError, match="--workers"):
        generate_world(tmp_path / "w", workers=workers, **ARGS)
    assert list(tmp_path.iterdir()) == []


def test_cli_bad_workers_exits_2(tmp_path, capsys):
    rc = main(["synth", "--out", str(tmp_path / "w"), "--workers", "-3", "--scenes-train", "1", "--scenes-val", "0"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "--workers -3" in err and len(err.splitlines()) == 1
    assert list(tmp_path.iterdir()) == []


def _fail_scene_1(monkeypatch):
    """Scene #1 raises inside _render_scene, the others render nothing (so that no forked worker
    runs OpenCV); under 'fork' the workers inherit the patch."""

    def render_scene(job, *args, **kwargs):
        if job.index == 1:
            raise ValueError("paint ran out")

    monkeypatch.setattr(world, "_render_scene", render_scene)


@pytest.mark.parametrize("workers", [1, 2])
def test_scene_error_names_the_scene_and_leaves_nothing(tmp_path, monkeypatch, workers):
    if workers > 1:
        if "fork" not in multiprocessing.get_all_start_methods():
            pytest.skip("needs the 'fork' start method to pass the injected failure to workers")
        monkeypatch.setattr(world, "MP_START_METHOD", "fork")
    _fail_scene_1(monkeypatch)
    name = world.scene_names(ARGS["scenes_train"], ARGS["scenes_val"])[0][1]
    with pytest.raises(world.SceneGenerationError, match=rf"{name} \(train scene #1.*ValueError: paint ran out") as e:
        generate_world(tmp_path / "w", workers=workers, **ARGS)
    assert ("worker process" in str(e.value)) == (workers > 1)
    assert "paint ran out" in str(e.value.__cause__)  # the worker's traceback, or the original error
    assert list(tmp_path.iterdir()) == []
    assert multiprocessing.active_children() == []


def test_interrupt_while_workers_render_leaves_nothing(tmp_path, monkeypatch):
    """Ctrl-C reaches the main process while it waits (here: on the first progress tick)."""

    class InterruptingBar:
        def __init__(self, *args, **kwargs):
            pass

        def update(self, n=1):
            raise KeyboardInterrupt

        def close(self):
            pass

    monkeypatch.setattr(world, "tqdm", InterruptingBar)
    with pytest.raises(KeyboardInterrupt):
        generate_world(tmp_path / "w", workers=2, **ARGS)
    assert list(tmp_path.iterdir()) == []
    assert multiprocessing.active_children() == []
