"""``instagram-hdmap demo``: the whole pipeline on the embedded synthetic world, on a CPU, in minutes.

    instagram-hdmap demo --out runs/demo            # <= 20 min on 2 CPU cores, set-up included

1. **World**: a synthetic nuScenes world (``data.synthetic``) is generated once into a cache folder
   (``--cache``, default ``$INSTAGRAM_HDMAP_CACHE`` or ``~/.cache/instagram_hdmap``), named after its
   generation parameters, and reused by every later run. Generation writes into a temporary folder
   that is renamed at the end, so an interrupted generation leaves no half world behind; free disk
   space is checked before it starts.
2. **Training**: ``configs/synthetic/demo.yaml`` (the tiny InstaGraM) in ``OUT/run`` for at most
   ``train.max_steps`` steps and at most the time left of the budget (``--minutes``), keeping a
   reserve for the evaluation. A run that finds ``OUT/run/last.pt`` resumes it (Ctrl-C saves it),
   so an interrupted demo continues where it stopped; a run that already reached its steps goes
   straight to the evaluation.
3. **Evaluation** of ``OUT/run/last.pt`` on the synthetic validation split under the vector
   protocol (the demo's headline mAP) and the raster protocol, and of a trivial baseline, the
   *random training map*: each validation sample is given, as its prediction, the ground-truth map
   of a random training sample (score 1). A model that learned nothing from the cameras scores like
   this map prior, so each class's AP must beat it.
4. **Pictures**: the predict PNGs of a few validation samples (``OUT/predict/<i>/``).
5. ``OUT/metrics.json`` holds all figures; a summary table is printed.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import random
import shutil
import time
from pathlib import Path

from .config import ExperimentConfig, UserError, load_config

# The demo world: 480 x 270 camera images (the network sees 64 x 192), about 0.1 s per sample on
# one core. Changing a value here names a new cache folder.
WORLD = {"scenes_train": 24, "scenes_val": 4, "samples_per_scene": 20, "seed": 0, "image_size": "480x270"}
WORLD_BYTES_PER_SAMPLE = 450_000  # measured: ~400 kB per sample at 480 x 270 (6 JPEGs + the lidar file)
EVAL_RESERVE_MIN = 1.5  # minutes kept for evaluation and pictures after training
PREDICT_SAMPLES = 3


class DemoError(UserError):
    """The demo cannot start: no config, not enough disk, a bad budget."""


def default_cache_dir() -> Path:
    env = os.environ.get("INSTAGRAM_HDMAP_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "instagram_hdmap"


def default_config_path() -> Path:
    """``configs/synthetic/demo.yaml`` of the source tree this package is installed from."""
    path = Path(__file__).resolve().parents[2] / "configs" / "synthetic" / "demo.yaml"
    if not path.is_file():
        raise DemoError(f"{path} not found: the demo needs the repository's configs/ (install with "
                        "`pip install -e .` from a checkout), or pass --config")
    return path


def world_key(world: dict) -> str:
    blob = json.dumps(world, sort_keys=True).encode()
    return f"synthetic-{hashlib.sha1(blob).hexdigest()[:10]}"


def world_samples(world: dict) -> int:
    return (world["scenes_train"] + world["scenes_val"]) * world["samples_per_scene"]


def check_disk(folder: Path, need_bytes: int) -> None:
    """Raise DemoError unless ``folder`` (or its nearest existing parent) has ``need_bytes`` free."""
    probe = folder
    while not probe.exists():
        probe = probe.parent
    free = shutil.disk_usage(probe).free
    if free < need_bytes:
        raise DemoError(f"not enough free disk for the synthetic world in {folder}: it needs about "
                        f"{need_bytes / 1e9:.2f} GB, {probe} has {free / 1e9:.2f} GB free; free some space "
                        "or point --cache (or $INSTAGRAM_HDMAP_CACHE) to another disk")


def ensure_world(cache_dir: Path, world: dict = WORLD, progress: bool = True, workers: int = 1) -> tuple[Path, bool]:
    """The cached world's dataroot, generating it first if absent. Returns (dataroot, reused)."""
    from .data.synthetic import generate_world, read_manifest

    root = Path(cache_dir) / world_key(world)
    if (root / "world.json").is_file():
        manifest = read_manifest(root)
        if all(manifest.get(k) == world[k] for k in ("scenes_train", "scenes_val", "samples_per_scene", "seed")):
            return root, True
        raise DemoError(f"{root} holds another world than the demo's ({manifest}); delete it or use another --cache")
    # twice the estimate: the temporary folder and the margin other writers need
    check_disk(root.parent, 2 * world_samples(world) * WORLD_BYTES_PER_SAMPLE)
    root.parent.mkdir(parents=True, exist_ok=True)
    kwargs = {"workers": workers} if workers != 1 else {}
    generate_world(out=root, progress=progress, force=True, **world, **kwargs)
    return root, False


def world_overrides(dataroot: Path) -> list[str]:
    from .data.synthetic import VERSION

    return [f"data.dataroot={dataroot}", f"data.version={VERSION}", f"data.splits_file={dataroot / 'splits.json'}"]


def random_map_baseline(cfg: ExperimentConfig, protocol: str, seed: int = 0, picks: list[int] | None = None) -> dict:
    """Metrics of the *random training map*: each validation sample predicted by the GT polylines
    of a uniformly drawn training sample (score 1): the map prior without looking at the images.
    ``picks`` (one training index per validation sample) replaces the random draw."""
    from .data import build_dataset
    from .evaluation import Evaluator

    train_set = build_dataset(cfg, cfg.data.train_split, augment=False)
    val_set = build_dataset(cfg, cfg.data.val_split, augment=False, like=train_set)
    rng = random.Random(seed)
    if picks is None:
        picks = [rng.randrange(len(train_set)) for _ in range(len(val_set))]
    cache: dict[int, list[dict]] = {}
    evaluator = Evaluator.from_config(dataclasses.replace(cfg, eval=dataclasses.replace(cfg.eval, protocol=protocol)))
    for i, j in enumerate(picks):
        if j not in cache:
            cache[j] = [{**p, "score": 1.0} for p in train_set.gt_polylines(j)]
        evaluator.update([cache[j]], [val_set.gt_polylines(i)], sample_ids=[i])
    return evaluator.compute()


def _budget_left(t0: float, minutes: float) -> float:
    return minutes - (time.perf_counter() - t0) / 60


def run_demo(out: str | Path, *, minutes: float = 20.0, cache_dir: str | Path | None = None,
             config: str | Path | None = None, overrides: list[str] | tuple[str, ...] = (),
             world: dict | None = None, workers: int = 1, raster: bool = True, progress: bool = True) -> dict:
    """Generate or reuse the world (default ``WORLD``), train (resuming ``OUT/run/last.pt``), evaluate,
    draw. Returns the metrics dict also written to ``OUT/metrics.json``."""
    from .data.nuscenes import write_json
    from .predict import predict_sample, run_evaluation
    from .train import train

    t0 = time.perf_counter()
    world = WORLD if world is None else world
    if minutes <= EVAL_RESERVE_MIN:
        raise DemoError(f"--minutes {minutes}: the budget must exceed the {EVAL_RESERVE_MIN} min kept for evaluation")
    out = Path(out)
    cache_dir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    config = Path(config) if config is not None else default_config_path()

    dataroot, reused = ensure_world(cache_dir, world, progress=progress, workers=workers)
    print(f"world: {dataroot} ({'reused' if reused else 'generated'}, {world_samples(world)} samples)", flush=True)

    run_dir = out / "run"
    last = run_dir / "last.pt"
    resume = str(last) if last.is_file() else None
    train_minutes = _budget_left(t0, minutes) - EVAL_RESERVE_MIN
    cfg = load_config(config, [*world_overrides(dataroot), f"train.out_dir={run_dir}",
                               f"train.max_minutes={max(train_minutes, 0.05):.3f}", *overrides])
    steps_done = _checkpoint_step(last) if resume else 0
    target = cfg.train.max_steps
    t_train = time.perf_counter()
    if target is not None and steps_done >= target:
        print(f"training: {last} already holds {steps_done} steps (max_steps {target}); evaluating it", flush=True)
        summary = {"step": steps_done}
    else:
        if resume:
            print(f"training: resuming {last} at step {steps_done}", flush=True)
        print(f"training: {config} for at most {cfg.train.max_steps} steps / {cfg.train.max_minutes:.1f} min "
              f"in {run_dir} (Ctrl-C saves a resumable checkpoint)", flush=True)
        summary = train(cfg, resume=resume, force=resume is None, validate=False)
    train_s = time.perf_counter() - t_train
    steps = summary.get("step", steps_done)

    new_steps = steps - steps_done
    metrics: dict = {"world": {"dataroot": str(dataroot), **world}, "config": str(config), "train": {
        "steps": steps, "steps_this_run": new_steps, "seconds_this_run": round(train_s, 1),
        "samples_per_s": round(new_steps * cfg.train.batch_size / max(train_s, 1e-9), 2),
        "batch_size": cfg.train.batch_size, "checkpoint": str(last)}}
    protocols = ["vector", "raster"] if raster else ["vector"]
    for protocol in protocols:
        result = run_evaluation(cfg, last, protocol, out / f"eval_{protocol}")
        metrics[protocol] = _brief(result["metrics"])
        metrics[protocol]["samples_per_s"] = result["samples_per_s"]
        metrics[f"baseline_{protocol}"] = _brief(random_map_baseline(cfg, protocol))
    pngs = []
    stride = max(1, _val_len(cfg) // PREDICT_SAMPLES)
    for i in range(PREDICT_SAMPLES):
        r = predict_sample(cfg, out / "predict" / str(i), checkpoint=last, index=i * stride)
        pngs += [str(p) for p in r["paths"] if str(p).endswith(".png")]
    metrics["pictures"] = pngs
    metrics["seconds_total"] = round(time.perf_counter() - t0, 1)
    metrics["learned"] = {c: bool(metrics["vector"]["AP_class"][c] > metrics["baseline_vector"]["AP_class"][c])
                          for c in metrics["vector"]["AP_class"]}
    metrics = _strict_json(metrics)
    write_json(metrics, out / "metrics.json")
    print(format_summary(metrics, out))
    return metrics


def _strict_json(obj):
    """NaN (e.g. the AP of a class absent from the split under the raster protocol) -> None, so
    metrics.json is standard JSON."""
    if isinstance(obj, dict):
        return {k: _strict_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_strict_json(v) for v in obj]
    if isinstance(obj, float) and obj != obj:
        return None
    return obj


def _checkpoint_step(path: Path) -> int:
    from .checkpoint import load_checkpoint

    return int(load_checkpoint(path)["step"])


def _val_len(cfg: ExperimentConfig) -> int:
    from .data.synthetic import read_manifest

    m = read_manifest(cfg.data.dataroot)
    return m["scenes_val"] * m["samples_per_scene"]


def _brief(m: dict) -> dict:
    return {k: m[k] for k in ("protocol", "thresholds", "classes", "AP", "AP_class", "mAP")}


def _cell(v: float | None, width: int) -> str:
    return f"{'-':>{width}}" if v is None else f"{v:>{width}.3f}"


def format_summary(metrics: dict, out: Path) -> str:
    classes = metrics["vector"]["classes"]
    protos = [p for p in ("vector", "raster") if p in metrics]
    head = f"{'':<26}" + "".join(f"{c:>14}" for c in classes) + f"{'mAP':>10}"
    lines = ["", head, "-" * len(head)]
    for p in protos:
        for name, key in ((f"InstaGraM ({p})", p), (f"random training map ({p})", f"baseline_{p}")):
            m = metrics[key]
            lines.append(f"{name:<26}" + "".join(_cell(m["AP_class"][c], 14) for c in classes) + _cell(m["mAP"], 10))
    t = metrics["train"]
    lines += ["-" * len(head),
              f"trained {t['steps']} steps (batch {t['batch_size']}; this run {t['steps_this_run']} steps in "
              f"{t['seconds_this_run'] / 60:.1f} min, {t['samples_per_s']:.1f} samples/s); demo took "
              f"{metrics['seconds_total'] / 60:.1f} min",
              f"metrics: {out / 'metrics.json'}   TensorBoard: tensorboard --logdir {out / 'run' / 'tb'}",
              f"pictures: {out / 'predict'}/*/prediction_*.png"]
    return "\n".join(lines)
