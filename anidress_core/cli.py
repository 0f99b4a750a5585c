"""The ``anidress`` command: every pipeline stage, runnable and timeable on its own.

The Snakemake scripts in workflow/scripts call the same stage functions.
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from . import __version__

log = logging.getLogger("anidress.cli")


def _cmd_synth(args: argparse.Namespace) -> None:
    from .config import load_config, scene_config
    from .stages.synth import run_synth

    cfg = load_config(args.config)
    scene = scene_config(cfg, args.scene)
    if not scene["synthetic"]:
        raise SystemExit(f"scene {args.scene!r} is not synthetic (scenes/{args.scene}/synthetic is false)")
    out = Path(args.out) if args.out else Path("data") / args.scene
    run_synth(scene, args.scene, out, threads=args.threads, progress=not args.quiet)
    print(out)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="anidress",
        description="AniDress pipeline stages (the Snakemake workflow runs the same functions).",
    )
    p.add_argument("--version", action="version", version=f"anidress {__version__}")
    p.add_argument("--log", help="also write the log to this file")
    sub = p.add_subparsers(dest="command", metavar="STAGE", required=True)

    s = sub.add_parser("synth", help="generate a synthetic scene with full ground truth (data/<scene>/)")
    s.add_argument("--config", default="config/config.yaml", help="pipeline config (default: %(default)s)")
    s.add_argument("--scene", required=True, help="scene name, a key of `scenes` in the config")
    s.add_argument("--out", help="output folder (default: data/<scene>)")
    s.add_argument("--threads", type=int, default=2, help="writer threads (default: %(default)s)")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=_cmd_synth)
    return p


def main(argv: list[str] | None = None) -> int:
    from .stages import setup_logging

    args = build_parser().parse_args(argv)
    setup_logging(args.log)
    try:
        args.func(args)
    except (ValueError, FileNotFoundError) as e:
        log.error("%s", e)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
