"""Synthetic world generation in worker processes: same bytes as in one process, errors name the
scene, failures and Ctrl-C leave no folder and no process behind."""

from __future__ import annotations

import multiprocessing
from pathlib import Path

import pytest

from instagram_hdmap.cli import main
from instagram_hdmap.config import UserError
from instagram_hdmap.data.synthetic import generate_world, jobs, world

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


def _render_failing_scene_1(job, *args, **kwargs):
    """Scene #1 raises inside _render_scene; the others render nothing (fast)."""
    if job.index == 1:
        raise ValueError("paint ran out")


def _worker_failing_scene_1(*args):
    """A worker target for 'spawn': the child imports this module by name, patches its own copy of the
    world module, then runs the real worker loop. (Patching in the parent reaches a spawned child only
    this way; 'fork' would copy the patch but also the parent's OpenCV and OpenMP thread pools, whose
    locks can deadlock the child: that hung CI once.)"""
    world._render_scene = _render_failing_scene_1
    _REAL_WORKER_MAIN(*args)


def _worker_hangs(*args):
    """A worker that takes its scene and then never reports again (a deadlocked child)."""
    import time

    tasks, events, _ = args
    job = tasks.get()
    events.put(("start", __import__("os").getpid(), job.index, None))
    time.sleep(3600)


_REAL_WORKER_MAIN = jobs._worker_main


@pytest.mark.parametrize("workers", [1, 2])
def test_scene_error_names_the_scene_and_leaves_nothing(tmp_path, monkeypatch, workers):
    assert jobs.MP_START_METHOD == "spawn"
    monkeypatch.setattr(world, "_render_scene", _render_failing_scene_1)  # the in-process path (workers=1)
    monkeypatch.setattr(jobs, "_worker_main", _worker_failing_scene_1)  # the worker processes
    name = world.scene_names(ARGS["scenes_train"], ARGS["scenes_val"])[0][1]
    with pytest.raises(jobs.SceneGenerationError, match=rf"{name} \(train scene #1.*ValueError: paint ran out") as e:
        generate_world(tmp_path / "w", workers=workers, **ARGS)
    assert ("worker process" in str(e.value)) == (workers > 1)
    assert "paint ran out" in str(e.value.__cause__)  # the worker's traceback, or the original error
    assert list(tmp_path.iterdir()) == []
    assert multiprocessing.active_children() == []


def test_hung_worker_is_stopped_with_a_message(tmp_path, monkeypatch):
    monkeypatch.setattr(jobs, "_worker_main", _worker_hangs)
    monkeypatch.setattr(jobs, "STALL_S", 20.0)  # > a worker's start-up (it imports torch) on a slow machine
    with pytest.raises(jobs.SceneGenerationError, match=r"no progress .* for 20 s \(rendering: .*scene #\d.*hung"):
        generate_world(tmp_path / "w", workers=2, **ARGS)
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
