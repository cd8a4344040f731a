"""``instagram-hdmap demo`` end to end on a minute-sized budget: a tiny world, a few steps."""

from __future__ import annotations

import json
from collections import namedtuple

import pytest

from instagram_hdmap import demo
from instagram_hdmap.cli import main

WORLD = {"scenes_train": 2, "scenes_val": 1, "samples_per_scene": 3, "seed": 0, "image_size": "240x135"}
VAL_WORLD = {"scenes_train": 0, "scenes_val": 1, "samples_per_scene": 3, "seed": 1, "image_size": "240x135"}
FAST = ["train.max_steps=3", "train.batch_size=2", "data.num_workers=0", "train.log_every=1"]


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("demo")
    metrics = demo.run_demo(root / "out", minutes=10, cache_dir=root / "cache", overrides=FAST, world=WORLD,
                            val_world=VAL_WORLD, progress=False)
    return root, metrics


def test_demo_writes_every_output(demo_run):
    root, metrics = demo_run
    out = root / "out"
    def no_nan(name):
        raise AssertionError(f"metrics.json holds {name}: not standard JSON")

    on_disk = json.loads((out / "metrics.json").read_text(), parse_constant=no_nan)
    assert on_disk == metrics
    for key in ("vector", "raster", "baseline_vector", "baseline_raster"):
        m = on_disk[key]
        assert set(m["AP_class"]) == {"divider", "ped_crossing", "boundary"}
        # None: a class without GT in the split (the raster protocol's NaN)
        assert all(v is None or 0.0 <= v <= 1.0 for v in m["AP_class"].values())
        assert m["mAP"] is None or 0.0 <= m["mAP"] <= 1.0
        assert m["thresholds"] == [0.5, 1.0, 1.5]
    assert on_disk["vector"]["mAP"] is not None
    assert on_disk["train"]["steps"] == 3
    assert set(on_disk["learned"]) == {"divider", "ped_crossing", "boundary"}
    assert (out / "run" / "last.pt").is_file()
    assert (out / "run" / "config.yaml").is_file()
    assert any((out / "run" / "tb").glob("events.out.tfevents.*"))
    assert (out / "eval_vector" / "submission.json").is_file()
    pngs = on_disk["pictures"]
    assert len(pngs) == 3 * demo.PREDICT_SAMPLES
    assert all(p.endswith(".png") and (out / "predict").as_posix() in p for p in pngs)
    for p in pngs:
        with open(p, "rb") as f:
            assert f.read(8) == b"\x89PNG\r\n\x1a\n"


def test_baseline_scores_the_training_maps_it_draws(demo_run):
    """The random-training-map baseline is real AP: drawing, for each validation sample, the map of
    that very sample (train split = val split, picks = identity) scores AP 1 on every class present;
    the random draw over the real training split scores less."""
    from instagram_hdmap.config import load_config
    from instagram_hdmap.data.nuscenes import NuScenesMapDataset

    root, metrics = demo_run
    dataroot = root / "cache" / demo.world_key(WORLD)
    cfg = load_config(demo.default_config_path(), [*demo.world_overrides(dataroot), "data.train_split=val"])
    n_val = WORLD["scenes_val"] * WORLD["samples_per_scene"]
    perfect = demo.random_map_baseline(cfg, "vector", picks=list(range(n_val)))
    val = NuScenesMapDataset(cfg, "val", augment=False)
    labels = {p["label"] for i in range(len(val)) for p in val.gt_polylines(i)}
    present = [cfg.data.classes[k] for k in sorted(labels)]
    assert present and all(perfect["AP_class"][c] == pytest.approx(1.0) for c in present)
    assert metrics["baseline_vector"]["mAP"] < perfect["mAP"]


def test_second_run_reuses_the_world_and_the_run(demo_run, capsys):
    root, _ = demo_run
    stamp = (root / "cache" / demo.world_key(WORLD) / "world.json").stat().st_mtime_ns
    demo.run_demo(root / "out", minutes=10, cache_dir=root / "cache", overrides=FAST, world=WORLD,
                  val_world=VAL_WORLD, progress=False, raster=False)
    text = capsys.readouterr().out
    assert "reused" in text and "already completed its schedule (3 steps)" in text
    assert (root / "cache" / demo.world_key(WORLD) / "world.json").stat().st_mtime_ns == stamp


def test_not_enough_disk_fails_before_generating(tmp_path, monkeypatch):
    Usage = namedtuple("Usage", "total used free")
    monkeypatch.setattr(demo.shutil, "disk_usage", lambda p: Usage(10**9, 10**9 - 1000, 1000))
    with pytest.raises(demo.DemoError, match="not enough free disk"):
        demo.ensure_world(tmp_path / "cache", WORLD, progress=False)
    assert not (tmp_path / "cache").exists()


@pytest.mark.parametrize("minutes", ["1", "0", "-5", "2.2"])
def test_cli_rejects_a_budget_below_the_evaluation_reserve(tmp_path, capsys, minutes):
    assert main(["demo", "--out", str(tmp_path / "o"), "--minutes", minutes, "--cache", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err
    assert f"--minutes {float(minutes)}" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "c").exists()


def test_ctrl_c_during_training_leaves_a_usable_cache_and_a_resumable_run(tmp_path, monkeypatch, capsys):
    """Ctrl-C in the middle of step 3: the CLI exits 130 having saved the weights of step 2; the next
    demo run reuses the cached world and resumes at step 2 instead of starting over."""
    from instagram_hdmap.checkpoint import load_checkpoint
    from instagram_hdmap.losses import Criterion

    forward = Criterion.forward
    calls = {"n": 0}

    def interrupted_on_the_third_step(self, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return forward(self, *args, **kwargs)

    monkeypatch.setattr(demo, "WORLD", WORLD)
    monkeypatch.setattr(demo, "VAL_WORLD", VAL_WORLD)
    monkeypatch.setattr(Criterion, "forward", interrupted_on_the_third_step)
    out, cache = tmp_path / "out", tmp_path / "cache"
    argv = ["demo", "--out", str(out), "--cache", str(cache), "--minutes", "10", "--no-raster", *FAST]
    assert main(argv) == 130
    assert (cache / demo.world_key(WORLD) / "world.json").is_file()  # the world is complete
    assert load_checkpoint(out / "run" / "last.pt")["step"] == 2
    assert not (out / "metrics.json").exists()
    capsys.readouterr()

    monkeypatch.setattr(Criterion, "forward", forward)
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "reused" in text and "resuming" in text and "at step 2" in text
    assert json.loads((out / "metrics.json").read_text())["train"]["steps"] == 3


def test_damaged_or_half_written_worlds_are_named_not_used(tmp_path):
    """A world folder without its manifest (not written by the generator's final rename) and one
    whose camera files went missing are reported with the recovery (delete, run again)."""
    cache = tmp_path / "cache"
    root = cache / demo.world_key(WORLD)
    root.mkdir(parents=True)
    (root / "samples").mkdir()
    with pytest.raises(demo.DemoError, match="not a complete synthetic world.*delete it"):
        demo.ensure_world(cache, WORLD, progress=False)


def test_a_world_missing_images_is_reported(demo_run, tmp_path):
    import shutil

    root, _ = demo_run
    copy = tmp_path / "cache" / demo.world_key(WORLD)
    shutil.copytree(root / "cache" / demo.world_key(WORLD), copy)
    next((copy / "samples" / "CAM_FRONT").glob("*.jpg")).unlink()
    with pytest.raises(demo.DemoError, match="damaged: 8 of its 9 CAM_FRONT images"):
        demo.ensure_world(tmp_path / "cache", WORLD, progress=False)


def test_an_unwritable_cache_or_out_folder_is_one_line(tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    argv = ["demo", "--out", str(tmp_path / "o"), "--cache", str(blocker / "cache"), "--minutes", "10"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "cannot create the cache folder" in err and "Traceback" not in err
    argv = ["demo", "--out", str(blocker / "out"), "--cache", str(tmp_path / "c"), "--minutes", "10"]
    assert main(argv) == 2
    assert "a_file is a file, so nothing can be written below it" in capsys.readouterr().err


def test_no_time_left_to_train_after_the_worlds_is_an_error(demo_run, tmp_path, monkeypatch):
    root, _ = demo_run
    monkeypatch.setattr(demo, "_budget_left", lambda t0, minutes: demo.EVAL_RESERVE_MIN + 0.1)
    with pytest.raises(demo.DemoError, match="leaves 0.10 min to train; the worlds are cached now"):
        demo.run_demo(tmp_path / "out", minutes=10, cache_dir=root / "cache", overrides=FAST, world=WORLD,
                      val_world=VAL_WORLD, progress=False)


def test_metrics_name_the_unseen_validation_world_and_the_schedule(demo_run):
    _, metrics = demo_run
    v = metrics["validation"]
    assert v["seed"] == VAL_WORLD["seed"] != WORLD["seed"] and "unseen" in v["roads"]
    assert "vector_seen_roads" in metrics
    t = metrics["train"]
    # FAST cuts the run at 3 steps: the metrics must say the schedule did not complete
    assert t["final_lr_reached"] is False and 0 < t["progress"] < 1


def test_a_killed_generation_leaves_no_lasting_debris(tmp_path, monkeypatch):
    """kill -9 during generation leaves the temporary folder (never the world's own name); the next
    run removes it when its process is gone, and keeps one whose process still runs."""
    cache = tmp_path / "cache"
    root = cache / demo.world_key(WORLD)
    dead = cache / f".{root.name}.synth-tmp-999999999"
    alive = cache / f".{root.name}.synth-tmp-{__import__('os').getpid()}"
    for d in (dead, alive):
        (d / "samples").mkdir(parents=True)
    monkeypatch.setattr(demo, "check_disk", lambda *a: (_ for _ in ()).throw(demo.DemoError("stop here")))
    with pytest.raises(demo.DemoError, match="stop here"):
        demo.ensure_world(cache, WORLD, progress=False)
    assert not dead.exists() and alive.exists() and not root.exists()


def test_demo_speed_pools_each_epoch_by_its_samples_and_checks_its_options(tmp_path, capsys):
    """benchmarks/demo_speed.py: the whole run's rate is its samples over its seconds (not a mean of the epoch
    rates), per round; the first epoch apart; a world without splits.json and --epochs 1 are refused."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import demo_speed

    # two rounds of 3 epochs of 120 steps (batch 4: 480 samples each); epoch rates 40, 60, 80 then 40, 40, 40
    runs = [[{"epoch": e, "samples_per_s": r, "train_seconds": 480 / r, "cpu_threads": 2} for e, r in enumerate(rates)]
            for rates in ((40, 60, 80), (40, 40, 40))]
    s = demo_speed.summary(runs)
    assert s["first"] == 40 and s["later"] == 50 and s["threads"] == 2  # the median of 60, 80, 40, 40
    assert s["whole"] == pytest.approx(6 * 480 / (480 / 40 * 4 + 480 / 60 + 480 / 80))
    with pytest.raises(SystemExit):
        demo_speed.parse(["--world", str(tmp_path)])
    assert "no splits.json" in capsys.readouterr().err
    (tmp_path / "splits.json").write_text("{}")
    with pytest.raises(SystemExit):
        demo_speed.parse(["--world", str(tmp_path), "--epochs", "1"])
    assert "--epochs must be at least 2" in capsys.readouterr().err
