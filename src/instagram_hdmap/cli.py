"""``instagram-hdmap``: one subcommand per job, each a thin wrapper over the library.

Each ``_cmd_*`` function imports what it needs lazily so that ``instagram-hdmap --help`` is fast.
User errors (``config.UserError``) print one line and exit with code 2.
"""

from __future__ import annotations

import argparse
import sys

from .config import UserError


def _add_config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="experiment YAML (overrides of the defaults in config.py)")
    p.add_argument("overrides", nargs="*", help="key.sub=value overrides, e.g. model.gnn.layers=9")


def _load(args: argparse.Namespace):
    from .config import load_config

    return load_config(args.config, args.overrides)


# --- synthetic world -------------------------------------------------------------------------


def _cmd_synth(args: argparse.Namespace) -> int:
    from .data.synthetic import generate_world

    generate_world(
        out=args.out,
        scenes_train=args.scenes_train,
        scenes_val=args.scenes_val,
        samples_per_scene=args.samples_per_scene,
        seed=args.seed,
        image_size=args.image_size,
        force=args.force,
    )
    return 0


def _cmd_synth_preview(args: argparse.Namespace) -> int:
    from .data.synthetic.preview import write_preview

    write_preview(args.dataroot, args.out, index=args.index)
    print(f"wrote {args.out}")
    return 0


# --- model -----------------------------------------------------------------------------------


def _cmd_model_summary(args: argparse.Namespace) -> int:
    from .models import build_model, summarize_parameters

    cfg = _load(args)
    print(summarize_parameters(build_model(cfg)))
    return 0


# --- training --------------------------------------------------------------------------------


def _cmd_train(args: argparse.Namespace) -> int:
    from .train import train

    cfg = _load(args)
    summary = train(cfg, resume=args.resume, force=args.force)
    print(f"done: epoch {summary.get('epoch')}, step {summary.get('step')}; outputs in {summary['out_dir']}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="instagram-hdmap", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("synth", help="write a synthetic world in the nuScenes on-disk format")
    p.add_argument("--out", required=True, help="output dataroot (must be empty or absent)")
    p.add_argument("--scenes-train", type=int, default=8)
    p.add_argument("--scenes-val", type=int, default=2)
    p.add_argument("--samples-per-scene", type=int, default=10)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--image-size", default="1600x900", help="camera image WIDTHxHEIGHT")
    p.add_argument("--force", action="store_true", help="overwrite a non-empty --out")
    p.set_defaults(func=_cmd_synth)

    p = sub.add_parser("synth-preview", help="PNG of one synthetic sample: cameras with map lines, and BEV")
    p.add_argument("dataroot")
    p.add_argument("--out", required=True)
    p.add_argument("--index", type=int, default=0, help="sample index in the dataroot")
    p.set_defaults(func=_cmd_synth_preview)

    p = sub.add_parser("model-summary", help="parameters per component and in total")
    _add_config_args(p)
    p.set_defaults(func=_cmd_model_summary)

    p = sub.add_parser("train", help="train a model; torchrun-aware")
    _add_config_args(p)
    p.add_argument("--resume", help="checkpoint to continue from (e.g. OUT/last.pt)")
    p.add_argument("--force", action="store_true", help="start over in an output folder that holds a run")
    p.set_defaults(func=_cmd_train)

    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args) or 0
    except UserError as e:
        print(f"instagram-hdmap {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"instagram-hdmap {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
