"""``gausslite map``: single-agent mapping of a posed RGB-D sequence (or the synthetic default)."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

log = logging.getLogger("gausslite.map")


def add_mapping_args(p: argparse.ArgumentParser) -> None:
    """Arguments shared by ``map`` and ``ablate``: dataset selection and config overrides."""
    p.add_argument("--dataset", type=Path, default=None,
                   help="sequence folder (Replica/TUM/7-Scenes layout); default: generate the synthetic scene")
    p.add_argument("--downscale", type=float, default=1.0, help="image downscale factor (intrinsics scale too)")
    p.add_argument("--max-frames", type=int, default=None, help="use only the first N frames")
    p.add_argument("--stride", type=int, default=1, help="map every k-th frame; the others are held-out views")
    p.add_argument("--task-id", default=None, help="task id from the dataset's tasks.json (ROI + metrics)")
    p.add_argument("--config", type=Path, default=None, help="YAML mapper config")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config field, e.g. --set iters_per_frame=60 --set lr.means=1e-4")
    p.add_argument("--iters", type=int, default=None, help="Adam iterations per mapped frame")
    p.add_argument("--seeds-per-frame", dest="seeds_per_frame", type=int, default=None,
                   help="new Gaussians per mapped frame at most (mapper.seeds_per_frame)")
    p.add_argument("--max-gaussians", type=int, default=None, help="global Gaussian budget")
    p.add_argument("--backend", default=None, choices=["auto", "warp", "torch", "gsplat"])
    p.add_argument("--seed", type=int, default=None, help="random seed")
    p.add_argument("--undistort", action=argparse.BooleanOptionalAction, default=None,
                   help="TUM only: undistort with the Freiburg coefficients (onto the alpha=0 optimal pinhole "
                        "camera); on by default for TUM (hand-held profile), --no-undistort to opt out")
    p.add_argument("--interpolate-poses", action=argparse.BooleanOptionalAction, default=None,
                   help="TUM only: interpolate ground-truth poses at the colour timestamps; on by default for "
                        "TUM, --no-interpolate-poses to opt out")
    p.add_argument("--no-progress", action="store_true")


def resolve_dataset(args: argparse.Namespace, out: Path):
    """Load ``--dataset``, or generate the synthetic default scene into ``out/scene`` (agent_a).

    The dataset's layout picks a sensor profile (:mod:`gausslite.mapping.profiles`): its loader
    options apply unless a flag says otherwise, and it is stored in ``args.profile`` for
    :func:`config_from_args`. The chosen profile is logged and printed.
    """
    from gausslite.datasets import detect_layout, load_dataset
    from gausslite.mapping.profiles import profile_for_layout

    path = args.dataset
    if path is None:
        from gausslite.synthetic import make_scene

        scene_dir = out / "scene"
        if not (scene_dir / "agent_a" / "traj.txt").exists():
            log.info("no --dataset: generating the synthetic default scene in %s", scene_dir)
            make_scene(scene_dir)
        path = scene_dir / "agent_a"
    layout = detect_layout(path)[0]
    flags = {k: getattr(args, k, None) for k in ("undistort", "interpolate_poses")}
    if any(v for v in flags.values()) and layout != "tum":
        raise ValueError(f"--undistort/--interpolate-poses apply to TUM sequences only, not {path}")
    profile = profile_for_layout(layout)
    loader_kw = dict(profile.loader)
    loader_kw.update({k: bool(v) for k, v in flags.items() if v is not None and layout == "tum"})
    args.profile = profile
    msg = f"profile: {profile.name} ({profile.description}); loader {loader_kw or 'defaults'}; mapper {profile.mapper or 'defaults'}"
    log.info("%s", msg)
    print(msg, flush=True)
    return load_dataset(path, downscale=args.downscale, max_frames=args.max_frames, **loader_kw)


def config_from_args(args: argparse.Namespace, **extra):
    """MapperConfig from --config, --set and the shortcut flags (flags win)."""
    from gausslite.mapping.config import load_config

    profile = getattr(args, "profile", None)
    return load_config(
        args.config, args.overrides, defaults=dict(profile.mapper) if profile is not None else None,
        iters_per_frame=args.iters, seeds_per_frame=args.seeds_per_frame, max_gaussians=args.max_gaussians,
        backend=args.backend, seed=args.seed, **extra,
    )


def _handler(args: argparse.Namespace) -> int:
    from gausslite.pipeline import run_mapping

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ds = resolve_dataset(args, out)
    try:
        cfg = config_from_args(args, mode=args.mode)
    except (ValueError, FileNotFoundError) as e:  # pydantic's ValidationError is a ValueError
        log.error("invalid mapper configuration: %s", e)
        return 2
    if args.task_id is None and cfg.mode == "gausslite":
        if ds.annotations is None or not ds.annotations.tasks:
            log.error("mode gausslite needs --task-id and a tasks.json next to %s", ds.path)
            return 2
        args.task_id = ds.annotations.tasks[0].id
        log.info("no --task-id given: using the first task, %s", args.task_id)
    log.info("mapping %s (%d frames, %dx%d) mode=%s task=%s", ds.path, len(ds),
             ds.intrinsics.width, ds.intrinsics.height, cfg.mode, args.task_id)
    _, metrics = run_mapping(ds, cfg, task_id=args.task_id, stride=args.stride, out_dir=out,
                             progress=not args.no_progress)
    brief = {k: v for k, v in metrics.items() if k != "per_frame"}
    print(json.dumps(brief, indent=2))
    return 0


def register(sub) -> None:
    p = sub.add_parser("map", help="map a posed RGB-D sequence and evaluate it",
                       description="Map a sequence with known poses; writes map.ply, metrics.json and PNGs.")
    add_mapping_args(p)
    p.add_argument("--mode", choices=["uniform", "gausslite"], default="uniform")
    p.add_argument("--out", required=True, type=Path, help="output folder")
    p.set_defaults(func=_handler)
