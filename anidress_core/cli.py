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


def _cmd_template(args: argparse.Namespace) -> None:
    from .stages.scene import load_body, read_scene
    from .stages.template import run_template

    scene_dir = Path(args.scene_dir)
    info = read_scene(scene_dir)
    src = args.template or (scene_dir / info["garment_template"] if info.get("garment_template") else None)
    kind = args.kind or info.get("garment_kind")
    if kind is None:
        raise ValueError(f"{scene_dir / 'scene.yaml'}: no garment_kind; pass --kind skirt|dress")
    out = Path(args.out)
    run_template(src, kind, load_body(scene_dir, info), args.vertices, out / "template.ply", out / "template.npz")
    print(out / "template.npz")


def _cmd_motion(args: argparse.Namespace) -> None:
    from .config import load_config
    from .stages.simulate import run_motion

    run_motion(args.name, args.scene_dir, load_config(args.config)["simulate"], args.out)
    print(args.out)


def _cmd_simulate(args: argparse.Namespace) -> None:
    from .config import load_config
    from .stages.simulate import run_simulate

    cloth = load_config(args.config)["simulate"]["cloth"]
    run_simulate(args.template, args.motion, args.scene_dir, cloth, args.out, progress=not args.quiet)
    print(args.out)


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

    s = sub.add_parser("template", help="clean, remesh and attach a garment template (template.ply/.npz)")
    s.add_argument("scene_dir", help="data/<scene> (scene.yaml, body model, garment/template.obj)")
    s.add_argument("--template", help="garment mesh (default: the scene's garment/template.obj; "
                                      "none: the procedural garment of --kind)")
    s.add_argument("--kind", choices=["skirt", "dress"], help="garment kind (default: from scene.yaml)")
    s.add_argument("--vertices", type=int, default=3000, help="target vertex count (default: %(default)s)")
    s.add_argument("-o", "--out", required=True, help="output folder")
    s.set_defaults(func=_cmd_template)

    s = sub.add_parser("motion", help="write a body motion to simulate (seq-<sequence>, lib-<name>, amass-<stem>)")
    s.add_argument("name")
    s.add_argument("scene_dir")
    s.add_argument("--config", default="config/config.yaml")
    s.add_argument("-o", "--out", required=True, help="output .npz")
    s.set_defaults(func=_cmd_motion)

    s = sub.add_parser("simulate", help="simulate the garment template on a body motion (sim/<motion>.npz)")
    s.add_argument("template", help="template.npz from `anidress template`")
    s.add_argument("motion", help="motion .npz from `anidress motion`")
    s.add_argument("scene_dir", help="data/<scene> (for its body model)")
    s.add_argument("--config", default="config/config.yaml", help="cloth parameters: simulate/cloth")
    s.add_argument("-o", "--out", required=True, help="output .npz")
    s.add_argument("--quiet", action="store_true")
    s.set_defaults(func=_cmd_simulate)
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
