"""``instagram-hdmap demo``: the whole pipeline on the embedded synthetic world, on a CPU, in minutes.

    instagram-hdmap demo --out runs/demo            # <= 20 min on 2 CPU cores, set-up included

1. **World**: a synthetic nuScenes world (``data.synthetic``) is generated once into a cache folder
   (``--cache``, default ``$INSTAGRAM_HDMAP_CACHE``, else ``$XDG_CACHE_HOME/instagram_hdmap``, else
   ``~/.cache/instagram_hdmap``), named after its
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
import math
import numbers
import os
import random
import shutil
import time
from pathlib import Path

from .checkpoint import load_checkpoint
from .config import ExperimentConfig, UserError, as_config, flatten, load_config, parse_overrides
from .data import build_dataset
from .data.synthetic import VERSION, generate_world, read_manifest
from .data.synthetic.jobs import TMP_TAG
from .data.synthetic.world import FORMAT_VERSION
from .distributed import resolve_device
from .evaluate_split import run_evaluation
from .evaluation import Evaluator
from .files import check_output_dir, json_safe, remove_stale_temporaries, write_json
from .inference import saved_config
from .models import build_model
from .predict import predict_sample
from .resources import check_fits
from .resume import RESUME_KEYS, STREAM_RESUME_KEYS, config_differences
from .schedule import final_lr_factor
from .train import train

# The demo's worlds: 480 x 270 camera images (the network sees 64 x 192), about 0.1 s per sample on
# one core. Training uses WORLD's train split. Validation uses VAL_WORLD, a world of another seed:
# its four road networks (layouts, lane counts, junctions, crossings) and its looks (paint, kerbs,
# buildings) were never seen in training, so its mAP measures generalisation, not memorised
# geometry. WORLD's own val split (the same road networks as training, other drives) is scored
# too, vector protocol only, to show the gap. Changing a value here names a new cache folder.
WORLD = {"scenes_train": 24, "scenes_val": 4, "samples_per_scene": 20, "seed": 0, "image_size": "480x270"}
VAL_WORLD = {"scenes_train": 0, "scenes_val": 4, "samples_per_scene": 20, "seed": 1, "image_size": "480x270"}
WORLD_BYTES_PER_SAMPLE = 450_000  # measured: ~400 kB per sample at 480 x 270 (6 JPEGs + the lidar file)
EVAL_RESERVE_MIN = 2.0  # minutes kept for evaluation and pictures after training
MIN_TRAIN_MIN = 0.25  # below this much training time left after the worlds, the demo refuses to start
PREDICT_SAMPLES = 3


class DemoError(UserError):
    """The demo cannot start: no config, not enough disk, a bad budget."""


def default_cache_dir() -> Path:
    # '~/...' as a .env file or a Dockerfile's ENV gives it (no shell expands it there) made a folder named '~' in
    # the working directory; a blank value a folder named '  '
    env = os.environ.get("INSTAGRAM_HDMAP_CACHE", "").strip()
    if env:
        return Path(env).expanduser()
    # the XDG base directory spec's cache home (a relative value is to be ignored): set where the home folder has
    # a quota, it was ignored and the demo's worlds (~0.2 GB each) filled ~/.cache
    xdg = os.environ.get("XDG_CACHE_HOME", "").strip()
    if xdg and Path(xdg).expanduser().is_absolute():
        return Path(xdg).expanduser() / "instagram_hdmap"
    return Path.home() / ".cache" / "instagram_hdmap"


def default_config_path() -> Path:
    """``configs/synthetic/demo.yaml`` of the source tree this package is installed from."""
    path = Path(__file__).resolve().parents[2] / "configs" / "synthetic" / "demo.yaml"
    if not path.is_file():
        raise DemoError(f"{path} not found: the demo needs the repository's configs/ (install with "
                        "`pip install -e .` from a checkout), or pass --config")
    return path


def world_key(world: dict) -> str:
    """The cache folder name of a world: its generation parameters and the generator's format version
    (a world generated by an older generator is not reused)."""
    blob = json.dumps({**world, "format_version": FORMAT_VERSION}, sort_keys=True).encode()
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


def world_damage(root: Path, manifest: dict, samples: int) -> str | None:
    """What is missing from a cached world (a camera or lidar file, a table that is not JSON, a map file),
    or None: the cache is a folder of plain files that anything may have altered since it was generated."""
    folders = (sorted(p for p in (root / "samples").iterdir() if p.is_dir() and not p.name.startswith("."))
               if (root / "samples").is_dir() else [])  # (a hidden .ipynb_checkpoints is no sensor)
    if len(folders) < 7:  # six cameras and the lidar
        return f"its samples/ folder holds {len(folders)} of the 7 sensor folders"
    for folder in folders:
        found = sum(1 for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))
        if found != samples:
            kind = "images" if folder.name.startswith("CAM") else "files"
            return f"{found} of its {samples} {folder.name} {kind} are there"
    version = root / manifest.get("version", VERSION)
    for name in ("attribute", "calibrated_sensor", "category", "ego_pose", "instance", "log", "map", "sample",
                 "sample_annotation", "sample_data", "scene", "sensor", "visibility"):  # the generator's tables
        try:
            json.loads((version / f"{name}.json").read_bytes())
        except (OSError, ValueError) as e:
            return f"its table {version / name}.json cannot be read ({type(e).__name__}: {e})"
    for location in manifest.get("maps", []):
        if not (root / "maps" / "expansion" / f"{location}.json").is_file():
            return f"its map file maps/expansion/{location}.json is missing"
    return None


def ensure_world(cache_dir: Path, world: dict = WORLD, progress: bool = True, workers: int = 1) -> tuple[Path, bool]:
    """The cached world's dataroot, generating it first if absent. Returns (dataroot, reused).

    A world is written under a temporary name and renamed when complete, so a folder of the final
    name is complete unless it was altered later; a folder whose manifest or camera files do not
    match is reported (delete it and run again) rather than used."""
    root = Path(cache_dir) / world_key(world)
    if root.exists() and not (root / "world.json").is_file():
        raise DemoError(f"{root} is not a complete synthetic world (no world.json); delete it and run the demo "
                        "again to regenerate it")
    if (root / "world.json").is_file():
        try:
            manifest = read_manifest(root)
        except UserError as e:  # a world.json cut short: say what to do with the cached world
            raise DemoError(f"{root} is damaged: {e}; delete the folder and run the demo again to regenerate it"
                            ) from None
        if not all(manifest.get(k) == world[k] for k in ("scenes_train", "scenes_val", "samples_per_scene", "seed")):
            raise DemoError(f"{root} holds another world than the demo's ({manifest}); delete it or use another "
                            "--cache")
        damage = world_damage(root, manifest, world_samples(world))
        if damage:  # found here, not as a dataset error minutes later (advising to download nuScenes files)
            raise DemoError(f"{root} is damaged: {damage}; delete the folder and run the demo again to regenerate it")
        return root, True
    for stale in remove_stale_temporaries(root, TMP_TAG):  # before the disk check: they hold space
        print(f"removed {stale}: a world generation that did not finish (its process is gone)", flush=True)
    # twice the estimate: the temporary folder and the margin other writers need
    check_disk(root.parent, 2 * world_samples(world) * WORLD_BYTES_PER_SAMPLE)
    try:
        root.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise DemoError(f"cannot create the cache folder {root.parent} ({e.strerror or e}); point --cache (or "
                        "$INSTAGRAM_HDMAP_CACHE) to a writable folder") from None
    kwargs = {"workers": workers} if workers != 1 else {}
    try:
        # not force: a world of this name that another demo (or training) finished while this one was generated
        # is kept and used; replacing it moved the folder away under that process's feet
        generate_world(out=root, progress=progress, force=False, **world, **kwargs)
    except UserError as e:
        if not (root / "world.json").is_file():  # synth's words ('--out W') for the demo's cache folder
            raise DemoError(str(e).replace(f"--out {root}", f"the cache folder's world {root}").rstrip(". ")
                            + " (the cache folder: --cache, or $INSTAGRAM_HDMAP_CACHE)") from None
        print(f"{root} was generated by another process meanwhile; using it", flush=True)
        return root, True
    return root, False


def world_overrides(dataroot: Path) -> list[str]:
    dataroot = Path(dataroot)
    return [f"data.dataroot={dataroot}", f"data.version={VERSION}", f"data.splits_file={dataroot / 'splits.json'}"]


def random_map_baseline(cfg: ExperimentConfig, protocol: str, seed: int = 0, picks: list[int] | None = None,
                        val_cfg: ExperimentConfig | None = None) -> dict:
    """Metrics of the *random training map*: each validation sample predicted by the GT polylines
    of a uniformly drawn training sample (score 1): the map prior without looking at the images.
    The training split comes from ``cfg``'s world, the validation split from ``val_cfg``'s (default
    the same world). ``picks`` (one training index per validation sample) replaces the random draw.
    ``cfg`` / ``val_cfg``: ``ExperimentConfig`` objects or YAML files."""
    cfg = as_config(cfg, "random_map_baseline")  # a YAML file's path was a raw "'str' object has no attribute 'data'"
    val_cfg = cfg if val_cfg is None else as_config(val_cfg, "random_map_baseline")
    train_set = build_dataset(cfg, cfg.data.train_split, augment=False)
    same_world = val_cfg.data.dataroot == cfg.data.dataroot  # its loaded tables are shared
    val_set = build_dataset(val_cfg, val_cfg.data.val_split, augment=False, like=train_set if same_world else None)
    if picks is None:
        rng = random.Random(seed)
        picks = [rng.randrange(len(train_set)) for _ in range(len(val_set))]
    picks = list(picks)
    # fewer picks scored only that many validation samples, an index past the split was a raw IndexError and a
    # negative one counted from the end, all with no word
    if len(picks) != len(val_set) or not all(isinstance(j, numbers.Integral) and 0 <= j < len(train_set)
                                             for j in picks):
        raise UserError(f"random_map_baseline: picks must be one training-sample index in [0, {len(train_set)}) per "
                        f"validation sample ({len(val_set)}), got {len(picks)} pick(s): {picks[:8]!r:.120}")
    cache: dict[int, list[dict]] = {}
    evaluator = Evaluator.from_config(dataclasses.replace(cfg, eval=dataclasses.replace(cfg.eval, protocol=protocol)))
    for i, j in enumerate(picks):
        if j not in cache:
            cache[j] = [{**p, "score": 1.0} for p in train_set.gt_polylines(j)]
        evaluator.update([cache[j]], [val_set.gt_polylines(i)], sample_ids=[i])
    return evaluator.compute()


def _budget_left(t0: float, minutes: float) -> float:
    return minutes - (time.perf_counter() - t0) / 60


def _check_out(out: Path) -> None:
    check_output_dir(out, "--out")  # a file there, or above it, is named (was "cannot write there (File exists)")
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise DemoError(f"--out {out}: cannot write there ({e.strerror or e}); choose a writable folder") from None


# Keys the demo sets itself: its run folder (OUT/run, which it trains with --force when it holds no
# checkpoint: another folder's run would be deleted), its worlds and its time budget
DEMO_KEYS = {"train.out_dir": "--out (the run goes to OUT/run)", "train.time_budget_min": "--minutes",
             "data.dataroot": "--cache", "data.version": "--cache", "data.splits_file": "--cache"}


def _check_earlier_run(last: Path, cfg: ExperimentConfig, config: Path) -> None:
    """A rerun into OUT goes on with OUT/run/last.pt (or, when its schedule is complete, evaluates it): a run of
    another model or training setting (another --config, other overrides) is refused before the worlds; it was
    evaluated as it was and written up under the new --config's name, exit 0."""
    if not last.is_file():
        return
    state = load_checkpoint(last)
    keys = RESUME_KEYS + (STREAM_RESUME_KEYS if cfg.model.temporal.memory != "none" else ())
    differ = config_differences(saved_config(state.get("config"), f"checkpoint {last}"), cfg, keys)
    if differ:
        raise DemoError(f"--out {last.parent.parent} holds a demo run of other settings ({differ}): the demo would go "
                        f"on with (or evaluate) that run as the one of --config {config}; give another --out, or "
                        f"delete {last.parent} to start over")


def _check_overrides(overrides) -> None:
    """Overrides of ``DEMO_KEYS`` are refused: the demo would overrule them or, for ``train.out_dir``,
    start over in that folder (deleting the run it holds) and then look for its checkpoint in OUT/run."""
    for key in flatten(parse_overrides(list(overrides))):
        if key in DEMO_KEYS:
            raise DemoError(f"the demo sets {key} itself; use {DEMO_KEYS[key]} instead (or run instagram-hdmap train "
                            "and evaluate with your own settings)")


def _check_before_the_worlds(out: Path, minutes: float, cache_dir: Path, config: Path, overrides) -> None:
    """What can be wrong before minutes of world generation, each one line: the budget, the output folder, the
    overrides, the config (its keys, its dataset, the model it builds, the memory of a step) and an earlier
    run in ``out`` of another config."""
    if not (math.isfinite(minutes) and minutes > EVAL_RESERVE_MIN + MIN_TRAIN_MIN):  # inf: no time_budget_min
        raise DemoError(f"--minutes {minutes}: the budget must be a finite number of minutes that exceeds "
                        f"{EVAL_RESERVE_MIN + MIN_TRAIN_MIN:g} min "
                        f"({EVAL_RESERVE_MIN:g} min are kept for evaluation, and training needs some time)")
    _check_out(out)
    _check_overrides(overrides)
    # a wrong config file, key or model setting is named before minutes of world generation
    cfg = load_config(config, list(overrides))
    if cfg.data.dataset != "nuscenes":
        raise DemoError(f"--config {config} sets data.dataset={cfg.data.dataset}, but the demo's synthetic worlds are "
                        "in the nuScenes layout; give a config of data.dataset=nuscenes (configs/synthetic/, "
                        "configs/temporal/synthetic.yaml), or train on your own world with instagram-hdmap train")
    # the checks across model keys (data.image_size, grid.cell_size, ...) live in build_model
    planned = load_config(config, [*world_overrides(cache_dir / "world"), *overrides])
    build_model(planned)
    check_fits(planned, "train", resolve_device(planned.train.device))  # a step that cannot fit: before the worlds
    _check_earlier_run(out / "run" / "last.pt", planned, config)


def run_demo(out: str | Path, *, minutes: float = 20.0, cache_dir: str | Path | None = None,
             config: str | Path | None = None, overrides: list[str] | tuple[str, ...] = (),
             world: dict | None = None, val_world: dict | None = None, workers: int = 1, raster: bool = True,
             progress: bool = True) -> dict:
    """Generate or reuse the worlds (default ``WORLD`` for training, ``VAL_WORLD`` for validation),
    train (resuming ``OUT/run/last.pt``) within the budget, evaluate, draw. Returns the metrics
    dict also written to ``OUT/metrics.json``."""
    t0 = time.perf_counter()
    world = WORLD if world is None else world
    val_world = VAL_WORLD if val_world is None else val_world
    out = Path(out)
    cache_dir = Path(cache_dir).expanduser() if cache_dir is not None else default_cache_dir()
    config = Path(config) if config is not None else default_config_path()
    _check_before_the_worlds(out, minutes, cache_dir, config, overrides)

    dataroot, reused = ensure_world(cache_dir, world, progress=progress, workers=workers)
    print(f"training world: {dataroot} ({'reused' if reused else 'generated'}, {world_samples(world)} samples, "
          f"seed {world['seed']})", flush=True)
    val_root, val_reused = ensure_world(cache_dir, val_world, progress=progress, workers=workers)
    print(f"validation world: {val_root} ({'reused' if val_reused else 'generated'}, "
          f"{world_samples(val_world)} samples, seed {val_world['seed']}: roads never seen in training)", flush=True)

    run_dir = out / "run"
    last = run_dir / "last.pt"
    resume = str(last) if last.is_file() else None
    train_minutes = _budget_left(t0, minutes) - EVAL_RESERVE_MIN
    state = load_checkpoint(last) if resume else None
    if state is None and train_minutes < MIN_TRAIN_MIN:
        spent = minutes - _budget_left(t0, minutes)
        raise DemoError(f"--minutes {minutes}: preparing the worlds took {spent:.1f} min, "
                        f"which leaves {max(train_minutes, 0):.2f} min to train; the worlds are cached now, so run the "
                        "same command again (or give more minutes)")
    budget = train_minutes
    if state is not None:  # continue the interrupted schedule: the same total budget, if this run has the time
        old_budget = state["config"]["train"].get("time_budget_min") or train_minutes
        budget = min(old_budget, state.get("clock", {}).get("elapsed_s", 0.0) / 60 + max(train_minutes, 0.0))
    cfg = load_config(config, [*world_overrides(dataroot), f"train.out_dir={run_dir}",
                               f"train.time_budget_min={max(budget, 0.01):.3f}", *overrides])
    val_cfg = load_config(config, [*world_overrides(val_root), f"train.out_dir={run_dir}", *overrides])
    steps_done = int(state["step"]) if state else 0
    done = state is not None and (state.get("clock", {}).get("progress", 0.0) >= 1.0
                                  or (cfg.train.max_steps is not None and steps_done >= cfg.train.max_steps))
    t_train = time.perf_counter()
    if done:
        print(f"training: {last} already completed its schedule ({steps_done} steps); evaluating it", flush=True)
        summary = {"step": steps_done}
    else:
        if resume:
            print(f"training: resuming {last} at step {steps_done}", flush=True)
        print(f"training: {config}, {cfg.train.schedule} schedule over {cfg.train.epochs} epochs or "
              f"{cfg.train.time_budget_min:.4g} min, whichever is shorter, in {run_dir} (Ctrl-C saves a resumable "
              "checkpoint)", flush=True)
        summary = train(cfg, resume=resume, force=resume is None, validate=False)
    train_s = time.perf_counter() - t_train
    final = load_checkpoint(last)
    steps = int(final["step"])
    clock = final.get("clock") or {}
    schedule = _schedule_report(cfg, final, summary)

    new_steps = steps - steps_done
    metrics: dict = {
        "world": {"dataroot": str(dataroot), **world},
        "validation": {"dataroot": str(val_root), **val_world,
                       "roads": f"unseen: a world of seed {val_world['seed']} (training: seed {world['seed']}), "
                                "whose road networks and looks training never saw"},
        "config": str(config),
        "train": {"steps": steps, "steps_this_run": new_steps, "seconds_this_run": round(train_s, 1),
                  "samples_per_s": round(new_steps * cfg.train.batch_size / max(train_s, 1e-9), 2),
                  "batch_size": cfg.train.batch_size, "checkpoint": str(last),
                  "training_minutes": round(clock.get("elapsed_s", train_s) / 60, 2), **schedule}}
    metrics.update(_evaluate_and_draw(cfg, val_cfg, last, out, world, val_world, raster))
    metrics["seconds_total"] = round(time.perf_counter() - t0, 1)
    metrics["learned"] = {c: bool(metrics["vector"]["AP_class"][c] > metrics["baseline_vector"]["AP_class"][c])
                          for c in metrics["vector"]["AP_class"]}
    metrics = json_safe(metrics)  # NaN -> None, as metrics.json holds it
    write_json(metrics, out / "metrics.json")
    print(format_summary(metrics, out))
    return metrics


def _evaluate_and_draw(cfg: ExperimentConfig, val_cfg: ExperimentConfig, last: Path, out: Path, world: dict,
                       val_world: dict, raster: bool) -> dict:
    """The checkpoint's AP on the unseen roads under each protocol against the random-map baseline, on the
    training roads (the generalisation gap) and pictures of a few validation samples."""
    metrics: dict = {}
    protocols = ["vector", "raster"] if raster else ["vector"]
    for protocol in protocols:
        result = run_evaluation(val_cfg, last, protocol, out / f"eval_{protocol}")
        metrics[protocol] = _brief(result["metrics"])
        metrics[protocol]["samples_per_s"] = result["samples_per_s"]
        metrics[f"baseline_{protocol}"] = _brief(random_map_baseline(cfg, protocol, val_cfg=val_cfg))
    if world["scenes_val"] > 0:  # the same road networks as training: the generalisation gap
        seen = run_evaluation(cfg, last, "vector", out / "eval_vector_seen_roads")
        metrics["vector_seen_roads"] = _brief(seen["metrics"])
    pngs = []
    stride = max(1, world_samples({**val_world, "scenes_train": 0}) // PREDICT_SAMPLES)
    for i in range(PREDICT_SAMPLES):
        r = predict_sample(val_cfg, out / "predict" / str(i), checkpoint=last, index=i * stride)
        pngs += [str(p) for p in r["paths"] if str(p).endswith(".png")]
    metrics["pictures"] = pngs
    return metrics


def _schedule_report(cfg: ExperimentConfig, state: dict, summary: dict) -> dict:
    """Whether the run went through its whole LR schedule (the final LR reached)."""
    clock = state.get("clock") or {}
    lrs = [g["lr"] for g in state["optimizer"]["param_groups"]]
    final = cfg.train.lr * final_lr_factor(cfg.train)
    progress = float(clock.get("progress", 0.0))
    return {"schedule": cfg.train.schedule, "progress": round(progress, 4), "lr": lrs[0], "final_lr": final,
            "final_lr_reached": bool(progress >= 1.0 and math.isclose(lrs[0], final, rel_tol=1e-6)),
            "time_budget_min": cfg.train.time_budget_min, "epochs": cfg.train.epochs,
            "cpu_threads": summary.get("cpu_threads"), "data_workers": cfg.data.num_workers}


def _brief(m: dict) -> dict:
    return {k: m[k] for k in ("protocol", "thresholds", "classes", "AP", "AP_class", "mAP")}


def _cell(v: float | None, width: int) -> str:
    return f"{'-':>{width}}" if v is None else f"{v:>{width}.3f}"


def format_summary(metrics: dict, out: Path) -> str:
    classes = metrics["vector"]["classes"]
    protos = [p for p in ("vector", "raster") if p in metrics]
    head = f"{'':<30}" + "".join(f"{c:>14}" for c in classes) + f"{'mAP':>10}"
    v = metrics["validation"]
    lines = ["", f"validation: {v['roads']} ({world_samples({**v, 'scenes_train': 0})} samples)", head, "-" * len(head)]
    rows = []
    for p in protos:
        rows += [(f"InstaGraM ({p})", p), (f"random training map ({p})", f"baseline_{p}")]
    if "vector_seen_roads" in metrics:
        rows.append(("InstaGraM (vector, seen roads)", "vector_seen_roads"))
    for name, key in rows:
        m = metrics[key]
        lines.append(f"{name:<30}" + "".join(_cell(m["AP_class"][c], 14) for c in classes) + _cell(m["mAP"], 10))
    t = metrics["train"]
    complete = ("whole schedule run, final LR reached" if t["final_lr_reached"]
                else f"schedule NOT complete (progress {t['progress']:.2f}, lr {t['lr']:.2g}, "
                     f"final {t['final_lr']:.2g})")
    lines += ["-" * len(head),
              f"trained {t['steps']} steps in {t['training_minutes']:.1f} min (batch {t['batch_size']}; this run "
              f"{t['steps_this_run']} steps, {t['samples_per_s']:.1f} samples/s); {complete}; demo took "
              f"{metrics['seconds_total'] / 60:.1f} min",
              f"metrics: {out / 'metrics.json'}   TensorBoard: tensorboard --logdir {out / 'run' / 'tb'}",
              f"pictures: {out / 'predict'}/*/prediction_*.png"]
    return "\n".join(lines)
