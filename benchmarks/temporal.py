"""Does the memory help? The single-frame demo model against the temporal one (docs/temporal.md), on a
synthetic world with occluders, the same budget for both, several seeds, unseen-road validation.

    python benchmarks/temporal.py --minutes 15 --seeds 0 1 --occluders 0.7 --out runs/temporal_bench

For every seed, each config (``configs/synthetic/demo.yaml``, single frame; ``configs/temporal/synthetic.yaml``,
BEV memory) trains on the training world (``demo.WORLD`` with ``--occluders``) for ``--minutes`` of wall
time (``train.time_budget_min``: the schedule completes within it, demo.py's rule) or, with ``--steps N``,
for N steps of the same schedule (a fair comparison on a loaded machine, where wall time depends on the
neighbours); then it is evaluated on the validation world (``demo.VAL_WORLD`` with ``--occluders``: a world
of another seed, road networks never seen in training), vector protocol, with the flicker rate and
MapTracker's consistency-aware mAP (evaluation/consistency.py; ``C-mAP`` in each result). Printed: one row
per run, the mean per config, and the temporal / single ratios of mAP and flicker. ``OUT/results.json`` holds
everything; a finished run is reused (delete its folder to redo it).

With ``--finetune STEPS`` (after the runs above, whose single-frame checkpoints are the start), both models
continue from each seed's trained single-frame model for STEPS steps at ``--finetune-lr``: the single-frame
one as it is (``single_ft``), the temporal one (``temporal_ft``) with only ``--finetune-trainable`` (default:
the memory fusion, ``train.trainable=[temporal]``; ``all``: everything) trained on streams from the start.
Both start from the same weights, so the seed's own spread cancels in the paired difference:

    python benchmarks/temporal.py --minutes 12 --seeds 0 1 --configs single --finetune 1200

``--memory`` chooses what the temporal model remembers (``model.temporal.memory``: ``bev`` features, the
previous frame's predicted ``graph`` drawn as a raster, or ``bev+graph``); a temporal run of another memory
than ``bev`` is named after it (``temporal_ft_all_graph``, ...), so several memories share one ``--out``
and its single-frame runs.

``--finetune-base DIR`` takes the single-frame checkpoints of an earlier ``--out`` (nothing is trained but
the fine-tunings; the start is evaluated too, ``single_base``); ``--val-scenes N`` validates on a world of N
scenes instead of the demo's 4 (the AP of 80 frames moves by a few hundredths between equal models).

Worlds are cached (``--cache``, as the demo's). Run one config at a time on a quiet machine with
``OMP_NUM_THREADS`` unset; ``--threads`` sets torch's threads explicitly.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CONFIGS = {"single": REPO / "configs" / "synthetic" / "demo.yaml",
           "temporal": REPO / "configs" / "temporal" / "synthetic.yaml"}


METRICS = {"mAP", "AP_class", "C-mAP", "C-AP_class", "flicker", "flicker_mean", "flicker_detected",
           "flicker_detected_mean"}


def read_result(path: Path) -> dict:
    """A result file of ``run_one``: its metrics that were NaN (a flicker rate with no pairs) are null in the file
    (standard JSON, ``files.write_json``) and NaN again here, for the tables' arithmetic and formats."""
    def nan(value):
        if isinstance(value, dict):
            return {k: nan(v) for k, v in value.items()}
        return math.nan if value is None else value

    return {k: nan(v) if k in METRICS else v for k, v in json.loads(path.read_text()).items()}


def budget_overrides(args) -> list[str]:
    """A from-scratch run's training budget: ``--minutes`` of wall time, or ``--steps`` (epochs of 120 steps)."""
    if args.steps is None:
        return [f"train.time_budget_min={args.minutes}"]
    epochs = math.ceil(args.steps / 120)
    return [f"train.max_steps={args.steps}", f"train.epochs={epochs}", f"train.lr_step={max(1, round(0.8 * epochs))}"]


def run_one(name: str, seed: int, args, roots, config: str | None = None, extra: tuple[str, ...] = (),
            budget: list[str] | None = None, checkpoint: Path | None = None) -> dict:
    """Train ``config`` (``name``'s folder) and evaluate it on the validation world; with ``checkpoint``,
    evaluate that checkpoint only (no training)."""
    from instagram_hdmap.config import load_config
    from instagram_hdmap.demo import world_overrides
    from instagram_hdmap.evaluate_split import run_evaluation
    from instagram_hdmap.files import write_json
    from instagram_hdmap.train import train

    train_root, val_root = roots
    config = config or name
    out = Path(args.out) / f"{name}_seed{seed}"
    done = out / result_name(args)
    if budget is None:
        budget = budget_overrides(args)
    # what the run was trained with (its world's occluders, budget, overrides): a result of other options in the
    # same --out is refused, not reported as this one's (results written before the key: not checked)
    options = None if checkpoint is not None else {"occluders": args.occluders, "train": [
        *budget, *args.override, *extra, *([f"model.temporal.memory={args.memory}", *args.temporal_override]
                                           if config == "temporal" else [])]}
    for path in sorted(out.glob("result*.json")):
        try:
            saved = json.loads(path.read_text()).get("options")
        except (OSError, ValueError, AttributeError):
            continue
        if options is not None and saved is not None and same_paths(saved) != same_paths(options):
            raise SystemExit(f"temporal.py: error: {path} was trained with {saved}, this command asks for {options}: "
                             "use another --out (or the same options)")
    if done.is_file():
        return read_result(done)
    trained = [p for p in out.glob("result*.json") if p != done]  # evaluated on another validation world
    steps = 0
    if checkpoint is None and trained:
        checkpoint = out / "run" / "last.pt"
        steps = json.loads(trained[0].read_text()).get("steps", 0)
    common = [f"train.seed={seed}", f"train.out_dir={out / 'run'}", "train.checkpoint_every=0", *budget,
              *([f"train.cpu_threads={args.threads}"] if args.threads else []), *args.override, *extra]
    summary, train_s = ({"step": steps} if trained else {}), 0.0
    if config == "temporal":  # what the memory holds (--memory) and the temporal model's own overrides
        common += [f"model.temporal.memory={args.memory}", *args.temporal_override]
    if checkpoint is None:
        cfg = load_config(CONFIGS[config], [*world_overrides(train_root), *common])
        t0 = time.perf_counter()
        summary = train(cfg, force=True, validate=False)
        train_s = time.perf_counter() - t0
        checkpoint = out / "run" / "last.pt"
    else:
        train_s = json.loads(trained[0].read_text()).get("train_s", 0.0) if trained else 0.0
    val_only = [] if args.val_dropout is None else [f"data.camera_dropout={args.val_dropout}"]
    val_cfg = load_config(CONFIGS[config], [*world_overrides(val_root), *common, *val_only])
    metrics = run_evaluation(val_cfg, checkpoint, "vector", out / f"eval{result_name(args)[6:-5]}",
                             overrides=[*persist_overrides(args), "eval.cmap=true"])["metrics"]
    result = {"config": name, "seed": seed, "steps": summary.get("step", 0), "train_s": round(train_s, 1),
              "mAP": metrics["mAP"], "AP_class": metrics["AP_class"],
              # MapTracker's consistency-aware mAP (evaluation/consistency.py: ConsistentAPMeter), a few % of the
              # evaluation's time on the CPU
              "C-mAP": metrics["cmap"]["C-mAP"], "C-AP_class": metrics["cmap"]["C-AP_class"],
              **{k: metrics["consistency"][k] for k in ("flicker", "flicker_mean", "flicker_detected",
                                                        "flicker_detected_mean", "pairs", "pairs_detected")},
              "memory": metrics.get("memory"), **({"options": options} if options is not None else {})}
    write_json(result, done, indent=1)  # atomic: a killed benchmark leaves no half-written result to read back
    return result


def memory_off(results: list[dict], args, val_root) -> str:
    """Every temporal run evaluated again with its memory off (``model.temporal.max_jump_m=0.001``: every frame
    a reset), and the mean size of its fusion's weights on the warped memory and its validity channel."""
    import torch

    from instagram_hdmap.config import load_config
    from instagram_hdmap.demo import world_overrides
    from instagram_hdmap.evaluate_split import run_evaluation
    from instagram_hdmap.files import write_json

    lines = ["memory on / off (the same checkpoint; the gated fusion's mean |w| on its inputs):"]
    for r in results:
        if not r["config"].startswith("temporal"):
            continue
        out = Path(args.out) / f"{r['config']}_seed{r['seed']}"
        done = out / result_name(args).replace(".json", "_memoff.json")
        ckpt = out / "run" / "last.pt"
        if not done.is_file():
            off = ["model.temporal.max_jump_m=0.001",
                   *([] if args.val_dropout is None else [f"data.camera_dropout={args.val_dropout}"])]
            cfg = load_config(CONFIGS["temporal"], [*world_overrides(val_root), *args.override,
                                                    f"model.temporal.memory={args.memory}",
                                                    *args.temporal_override, *off])
            metrics = run_evaluation(cfg, ckpt, "vector", out / f"eval{result_name(args)[6:-5]}_memoff",
                                     overrides=[*off, *persist_overrides(args)])["metrics"]
            write_json({"mAP": metrics["mAP"], "AP_class": metrics["AP_class"],
                        "flicker_mean": metrics["consistency"]["flicker_mean"]}, done, indent=1)  # atomic
        off = read_result(done)
        model = torch.load(ckpt, weights_only=True)["model"]
        weights = ""
        if "temporal.mix.0.weight" in model:  # the gated fusion's input: [current, warped memory, validity]
            w = model["temporal.mix.0.weight"]
            c = model["temporal.out.weight"].shape[1]  # the current features' channels
            bev = c if args.memory in ("bev", "bev+graph") else 0  # [current c, bev, graph raster, validity]
            parts = {"current": w[:, :c], "memory bev": w[:, c:c + bev], "memory graph": w[:, c + bev:-1]}
            parts = {k: v for k, v in parts.items() if v.shape[1]}
            weights = "; |w| " + ", ".join(f"{k} {float(v.abs().mean()):.2g}" for k, v in parts.items())
        lines.append(f"  {r['config']} s{r['seed']}: mAP {r['mAP']:.3f} / {off['mAP']:.3f} "
                     f"({r['mAP'] - off['mAP']:+.3f}), flicker {r['flicker_mean']:.3f} / {off['flicker_mean']:.3f}"
                     + weights)
    return "\n".join(lines)


def result_name(args) -> str:
    """A run's result file: ``result.json`` on the demo's validation world, ``result_valN.json`` on N scenes (a
    finished run evaluated on another world is evaluated again, not trained again)."""
    from instagram_hdmap.demo import VAL_WORLD

    name = "result" if args.val_scenes == VAL_WORLD["scenes_val"] else f"result_val{args.val_scenes}"
    if args.val_occluders is not None and args.val_occluders != args.occluders:
        name += f"_occ{args.val_occluders:g}"
    if args.val_dropout is not None:
        name += f"_drop{args.val_dropout:g}"
    if getattr(args, "persist", 0):
        name += f"_persist{args.persist}" + (f"x{args.persist_decay:g}" if args.persist_decay != 0.5 else "")
    return name + ".json"


def persist_overrides(args) -> list[str]:
    """``--persist``: the evaluation's element persistence (persistence.py; a decoding setting, the checkpoint's
    weights unchanged), as overrides that win over the checkpoint's saved config. Always given, 0 (off) too:
    configs/temporal/synthetic.yaml ships persistence on, and a result's name must say what was evaluated
    whatever config a checkpoint was trained with (no ``_persist`` in the name: none, for both models)."""
    frames = getattr(args, "persist", 0)
    return [f"model.temporal.persist_frames={frames}", f"model.temporal.persist_decay={args.persist_decay}"]


def table(results: list[dict]) -> str:
    classes = list(results[0]["AP_class"])
    head = (f"{'run':<18}{'steps':>7}" + "".join(f"{c[:10]:>11}" for c in classes)
            + f"{'mAP':>8}{'flicker':>9}{'flick.det':>10}")
    lines = [head, "-" * len(head)]
    for r in results:
        lines.append(f"{r['config'] + ' s' + str(r['seed']):<18}{r['steps']:>7}"
                     + "".join(f"{r['AP_class'][c]:>11.3f}" for c in classes)
                     + f"{r['mAP']:>8.3f}{r['flicker_mean']:>9.3f}{r['flicker_detected_mean']:>10.3f}")
    lines.append("-" * len(head))
    mean = {}
    temporal = next((r["config"] for r in results if r["config"].startswith("temporal")
                     and not r["config"].startswith("temporal_ft")), "temporal")  # a from-scratch run's name
    for name in ("single", temporal):
        rs = [r for r in results if r["config"] == name]
        if not rs:
            continue
        mean[name] = {"mAP": sum(r["mAP"] for r in rs) / len(rs),
                      "flicker": sum(r["flicker_mean"] for r in rs) / len(rs),
                      "flicker_detected": sum(r["flicker_detected_mean"] for r in rs) / len(rs),
                      "AP_class": {c: sum(r["AP_class"][c] for r in rs) / len(rs) for c in classes}}
        lines.append(f"{name + ' mean':<18}{'':>7}" + "".join(f"{mean[name]['AP_class'][c]:>11.3f}" for c in classes)
                     + f"{mean[name]['mAP']:>8.3f}{mean[name]['flicker']:>9.3f}{mean[name]['flicker_detected']:>10.3f}")
    if len(mean) == 2:
        s, t = mean["single"], mean[temporal]
        lines.append(f"temporal - single: mAP {t['mAP'] - s['mAP']:+.3f} ({times(ratio(t['mAP'], s['mAP']))}); "
                     f"flicker {times(ratio(t['flicker'], s['flicker']))}, among detected "
                     f"{times(ratio(t['flicker_detected'], s['flicker_detected']))} "
                     "(target: mAP +0.05, flicker x0.5)")
    return "\n".join(lines)


FT_NAMES = {"temporal": "temporal_ft", "all": "temporal_ft_all"}  # the fine-tuned temporal runs' names


def memory_suffix(args) -> str:
    """A temporal run's name suffix for ``--memory`` (none for the BEV memory: the first runs' names) and
    ``--temporal-set`` (``train.stream_frames=10`` -> ``_stream_frames10``)."""
    suffix = "" if args.memory == "bev" else "_" + args.memory.replace("+", "_")
    for item in args.temporal_override:
        key, _, value = item.partition("=")
        suffix += "_" + "".join(c if c.isalnum() or c in "-." else "_" for c in key.rsplit(".", 1)[-1] + value)
    return suffix


def same_paths(options: dict) -> dict:
    """``options`` with its ``train.init_from`` checkpoint as a resolved path: the same base checkpoint named
    relatively by one command and absolutely by another (or through a link) is the same option."""
    train = [f"train.init_from={os.path.realpath(item.partition('=')[2])}" if item.startswith("train.init_from=")
             else item for item in options.get("train", [])]
    return {**options, "train": train}


def finetune_runs(seed: int, args, roots) -> list[dict]:
    """Both models continued from seed's single-frame checkpoint for ``args.finetune`` steps (module docstring)."""
    base = Path(args.finetune_base or args.out) / f"single_seed{seed}" / "run" / "last.pt"
    epochs = math.ceil(args.finetune / 120)
    budget = [f"train.max_steps={args.finetune}", f"train.epochs={epochs}", f"train.lr_step={epochs}",
              f"train.lr={args.finetune_lr}", f"train.init_from={base}"]
    trainable = [] if args.finetune_trainable == "all" else ["train.trainable=[temporal]"]
    start = [run_one("single_base", seed, args, roots, "single", checkpoint=base)] if args.finetune_base else []
    return [*start, run_one("single_ft", seed, args, roots, "single", (), budget),
            run_one(FT_NAMES[args.finetune_trainable] + memory_suffix(args), seed, args, roots, "temporal",
                    ("train.stream_warmup=0", *trainable), budget)]


def ratio(a: float, b: float) -> float:
    """a / b, NaN when b is 0 (or NaN): a single-frame model that detects nothing has flicker 0, and
    a / max(b, 1e-9) printed 'flicker x0.00' for two models of flicker 0, the target x0.5 met."""
    return a / b if b > 0 else math.nan


def times(x: float) -> str:
    return f"x{x:.2f}" if math.isfinite(x) else "x n/a (divided by 0)"


def paired(results: list[dict]) -> str:
    """Per seed: temporal_ft - single_ft (the same start), and their means."""
    by = {(r["config"], r["seed"]): r for r in results}
    name = next((c for c, _ in by if c.startswith("temporal_ft")), None)
    seeds = sorted({s for c, s in by if c == name and ("single_ft", s) in by})
    if not seeds:
        return ""
    classes = list(results[0]["AP_class"])
    lines = [f"paired ({name} - single_ft, the same single-frame start):"]
    diffs = []
    for s in seeds:
        t, b = by[(name, s)], by[("single_ft", s)]
        d = {c: t["AP_class"][c] - b["AP_class"][c] for c in classes}
        diffs.append((t["mAP"] - b["mAP"], ratio(t["flicker_mean"], b["flicker_mean"]), d))
        lines.append(f"  seed {s}: mAP {diffs[-1][0]:+.3f}, flicker {times(diffs[-1][1])}; "
                     + ", ".join(f"{c} {v:+.3f}" for c, v in d.items()))
    n = len(diffs)
    lines.append(f"  mean: mAP {sum(x[0] for x in diffs) / n:+.3f}, flicker {times(sum(x[1] for x in diffs) / n)}; "
                 + ", ".join(f"{c} {sum(x[2][c] for x in diffs) / n:+.3f}" for c in classes)
                 + " (target: mAP +0.05, flicker x0.5)")
    return "\n".join(lines)


def check_args(p: argparse.ArgumentParser, args) -> None:
    """The options' ranges, the fine-tuning's start and the overrides, before the worlds are generated (minutes):
    a wrong value is one line (argparse's error, exit 2), not a traceback after the generation."""
    from instagram_hdmap.config import UserError, flatten, load_config, parse_overrides
    from instagram_hdmap.models import build_model
    from instagram_hdmap.train import check_stream_schedule

    def positive(name: str, value, integer: bool = False) -> None:
        if value is not None and not (math.isfinite(value) and value > 0):
            p.error(f"{name} must be {'a whole number >= 1' if integer else 'a number > 0'}, got {value}")

    positive("--minutes", args.minutes)
    positive("--finetune-lr", args.finetune_lr)
    for name in ("steps", "finetune", "val_scenes", "threads", "workers"):
        positive(f"--{name.replace('_', '-')}", getattr(args, name), integer=True)
    for name in ("occluders", "val_occluders", "val_dropout"):
        value = getattr(args, name)
        if value is not None and not 0 <= value <= 1:
            p.error(f"--{name.replace('_', '-')} must be a density in [0, 1], got {value}")
    if not 0 <= args.persist <= 10:
        p.error(f"--persist must be a number of frames in 0..10, got {args.persist}")
    if not 0 < args.persist_decay <= 1:
        p.error(f"--persist-decay must be in (0, 1], got {args.persist_decay}")
    if args.persist_decay != 0.5 and not args.persist:  # it was dropped with no word: the runs without persistence
        p.error(f"--persist-decay {args.persist_decay:g} needs --persist FRAMES (the persistence it sets)")
    if args.val_dropout is not None and args.val_dropout >= 1:  # data.camera_dropout's range: < 1
        p.error(f"--val-dropout must be below 1 (1 blanks every camera of every frame), got {args.val_dropout}")
    try:  # where every run writes (a file of that name, a folder without write permission): now, not after training
        from instagram_hdmap.files import check_output_dir
        check_output_dir(args.out, "--out")
    except UserError as e:
        p.error(str(e))
    if any(seed < 0 for seed in args.seeds):
        p.error(f"--seeds must be >= 0, got {args.seeds}")
    if args.finetune_base and not args.finetune:
        p.error("--finetune-base needs --finetune STEPS (the fine-tuning it starts)")
    if args.finetune_base:
        missing = [str(Path(args.finetune_base) / f"single_seed{seed}" / "run" / "last.pt") for seed in args.seeds
                   if not (Path(args.finetune_base) / f"single_seed{seed}" / "run" / "last.pt").is_file()]
        if missing:
            p.error(f"--finetune-base {args.finetune_base}: no single-frame checkpoint {', '.join(missing)}")
    for flag, overrides in (("--set", args.override), ("--temporal-set", args.temporal_override)):
        def sets_memory(override: str) -> bool:  # model.temporal={memory: bev} sets it too
            try:
                return "model.temporal.memory" in flatten(parse_overrides([override]))
            except UserError:  # named below, where the config is loaded
                return False

        memory_set = [o for o in overrides if sets_memory(o)]
        if memory_set:  # --memory names the runs and is what the memory-off check reads: one place for it
            p.error(f"{flag} {memory_set[0]}: the temporal model's memory is --memory ({args.memory}), not a {flag}")
    for name, path in CONFIGS.items():
        try:  # as run_one builds it: the temporal config with --memory (a --set may not fit that memory)
            memory = [f"model.temporal.memory={args.memory}", *args.temporal_override] if name == "temporal" else []
            cfg = load_config(path, [*budget_overrides(args), *args.override, *memory])
            build_model(cfg)  # the checks across keys live in build_model
        except UserError as e:
            p.error(f"--set (the {name} config{f', --memory {args.memory}' if name == 'temporal' else ''}): {e}")
        if name in args.configs and not (args.finetune and args.finetune_base):  # trained from scratch here
            try:  # a temporal schedule that streams, as train checks (--steps 100 is 1 epoch)
                check_stream_schedule(cfg)
            except UserError as e:
                budget = f"--steps {args.steps}" if args.steps is not None else f"--minutes {args.minutes:g}"
                p.error(f"the {name} run ({budget}): {e}")


def main() -> None:
    from instagram_hdmap.config import UserError
    from instagram_hdmap.demo import VAL_WORLD, WORLD, default_cache_dir, ensure_world
    from instagram_hdmap.files import write_json

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default="runs/temporal_bench")
    p.add_argument("--minutes", type=float, default=15.0, help="training wall budget per run")
    p.add_argument("--steps", type=int, help="instead of --minutes: the same number of steps for every run")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    p.add_argument("--occluders", type=float, default=0.7, help="occluder density of both worlds")
    p.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=list(CONFIGS))
    p.add_argument("--cache", help="world cache (default: the demo's)")
    p.add_argument("--threads", type=int, help="torch threads (train.cpu_threads)")
    p.add_argument("--workers", type=int, default=1, help="world generation processes")
    p.add_argument("--finetune", type=int, metavar="STEPS",
                   help="then continue both models from each seed's single-frame checkpoint for STEPS steps")
    p.add_argument("--finetune-base", metavar="DIR",
                   help="the single-frame checkpoints to start from: DIR/single_seedS/run/last.pt (default: --out)")
    p.add_argument("--val-scenes", type=int, default=VAL_WORLD["scenes_val"],
                   help="scenes of the validation world (more: less noise in the AP and flicker)")
    p.add_argument("--memory-off", action="store_true",
                   help="also evaluate every temporal run with its memory off (does it use its memory?)")
    p.add_argument("--val-occluders", type=float,
                   help="another occluder density for the validation world (default: --occluders); e.g. 0: what "
                        "do the occluders cost a model, the most a memory could win back")
    p.add_argument("--persist", type=int, default=0, metavar="FRAMES",
                   help="evaluate every run with element persistence (model.temporal.persist_frames=FRAMES: an "
                        "element found and then missed is kept for up to FRAMES frames, persistence.py); its own "
                        "result files, the training unchanged")
    p.add_argument("--persist-decay", type=float, default=0.5,
                   help="with --persist: a kept element's score factor per missed frame (model.temporal.persist_decay)")
    p.add_argument("--val-dropout", type=float,
                   help="evaluate with this data.camera_dropout instead of the training's (e.g. 0: every camera "
                        "works; the flicker a model has when no frame lacks anything)")
    p.add_argument("--finetune-lr", type=float, default=2e-4, help="the fine-tuning's constant learning rate")
    p.add_argument("--finetune-trainable", choices=["temporal", "all"], default="temporal",
                   help="what the temporal fine-tuning trains (the single-frame one trains everything)")
    p.add_argument("--memory", choices=["bev", "graph", "bev+graph"], default="bev",
                   help="what the temporal model remembers (model.temporal.memory; docs/temporal.md)")
    p.add_argument("--set", dest="override", nargs="+", default=[], metavar="KEY=VALUE",
                   help="config overrides for both models")
    p.add_argument("--temporal-set", dest="temporal_override", nargs="+", default=[], metavar="KEY=VALUE",
                   help="config overrides for the temporal model only (its runs are named after them, so a "
                        "variant shares --out and the single-frame runs: e.g. train.stream_frames=10)")
    args = p.parse_args()
    check_args(p, args)
    cache = Path(args.cache).expanduser() if args.cache else default_cache_dir()
    val_occluders = args.occluders if args.val_occluders is None else args.val_occluders
    try:  # a damaged or unwritable cache: one line (a raw traceback before)
        train_root, _ = ensure_world(cache, {**WORLD, "occluders": args.occluders}, workers=args.workers)
        val_root, _ = ensure_world(cache, {**VAL_WORLD, "scenes_val": args.val_scenes, "occluders": val_occluders},
                                   workers=args.workers)
    except UserError as e:
        p.error(f"--cache: {e}")
    results = [run_one(name + (memory_suffix(args) if name == "temporal" else ""), seed, args,
                       (train_root, val_root), name)
               for seed in args.seeds for name in args.configs if not (args.finetune and args.finetune_base)]
    if args.finetune:
        results += [r for seed in args.seeds for r in finetune_runs(seed, args, (train_root, val_root))]
    Path(args.out).mkdir(parents=True, exist_ok=True)
    write_json({"args": vars(args), "runs": results}, Path(args.out) / "results.json", indent=1)
    print(f"worlds: {train_root} (train), {val_root} (validation, unseen roads), occluders {args.occluders}")
    print(table(results))
    if args.finetune:
        print(paired(results))
    if args.memory_off:
        print(memory_off(results, args, val_root))


if __name__ == "__main__":
    main()
