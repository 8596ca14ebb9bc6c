"""``gausslite map``: single-agent mapping of a posed RGB-D sequence (or the synthetic default)."""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING, Optional

if TYPE_CHECKING:  # the command line starts without loading the library
    from gausslite.mapping.config import MapperConfig
    from gausslite.pipeline import TimeBudget

log = logging.getLogger("gausslite.map")

#: ``gausslite map``'s default total time budget, minutes: a 250-frame 640x480 sequence without poses (odometry
#: included) maps and scores in about this long on a 2-core CPU (docs/mapper.md, "Running it")
DEFAULT_TIME_BUDGET_MIN = 4.0
#: ``--time-budget`` values that turn the budget off (the fixed schedule: every frame, ``iters_per_frame`` iterations)
NO_BUDGET = ("none", "off")


def add_mapping_args(p: argparse.ArgumentParser) -> None:
    """Arguments shared by ``map`` and ``ablate``: dataset selection and config overrides."""
    p.add_argument("--dataset", type=Path, default=None,
                   help="sequence folder (Replica/TUM/7-Scenes layout, or a camera folder: camera.yaml, rgb/, "
                        "depth/) or ROS bag (rosbag2 folder, .mcap, .db3, .bag; a RealSense .bag); default: generate "
                        "the synthetic scene")
    p.add_argument("--downscale", type=float, default=1.0, help="image downscale factor (intrinsics scale too)")
    p.add_argument("--max-frames", type=int, default=None, help="use only the first N frames")
    p.add_argument("--stride", type=int, default=1, help="map every k-th frame; the others are held-out views")
    p.add_argument("--task-id", default=None, help="task id from the dataset's tasks.json (ROI + metrics)")
    p.add_argument("--annotations", default="auto", metavar="auto|beside|shipped|FOLDER",
                   help="scene annotations (objects.json, tasks.json): auto (default: the files beside the data, "
                        "else the set GaussLite ships for TUM fr1/rpy and Replica room0), beside, shipped, or a "
                        "folder holding them (docs/annotations.md)")
    p.add_argument("--config", type=Path, default=None, help="YAML mapper config")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config field, e.g. --set iters_per_frame=60 --set lr.means=1e-4")
    p.add_argument("--iters", type=int, default=None, help="Adam iterations per mapped frame")
    p.add_argument("--seeds-per-frame", dest="seeds_per_frame", type=int, default=None,
                   help="new Gaussians per mapped frame at most (mapper.seeding.seeds_per_frame)")
    p.add_argument("--max-gaussians", type=int, default=None, help="global Gaussian budget")
    p.add_argument("--backend", default=None, choices=["auto", "warp", "torch", "gsplat"])
    p.add_argument("--seed", type=int, default=None, help="random seed")
    p.add_argument("--undistort", action=argparse.BooleanOptionalAction, default=None,
                   help="TUM only: undistort with the Freiburg coefficients (onto the alpha=0 optimal pinhole "
                        "camera); on by default for TUM (hand-held profile), --no-undistort to opt out")
    p.add_argument("--interpolate-poses", action=argparse.BooleanOptionalAction, default=None,
                   help="TUM only: interpolate ground-truth poses at the colour timestamps; on by default for "
                        "TUM, --no-interpolate-poses to opt out")
    p.add_argument("--align-depth-time", action=argparse.BooleanOptionalAction, default=None,
                   help="TUM only: re-project each depth image from the pose at its own timestamp to the colour "
                        "frame's (the Kinect streams are not synchronised); on by default for TUM, "
                        "--no-align-depth-time to opt out")
    p.add_argument("--pose-source", dest="pose_source", choices=["auto", "given", "odometry"], default="auto",
                   help="camera poses: given (the dataset's own), odometry (estimated with Open3D's RGB-D odometry, "
                        "docs/mapper.md#poses-from-odometry) or auto (default: given when the dataset has poses, else "
                        "odometry)")
    p.add_argument("--no-progress", action="store_true")
    add_bag_args(p)
    add_depth_camera_args(p)


#: ``--flag`` → BagOptions field
BAG_FLAGS = {
    "--rgb-topic": ("rgb_topic", str, "colour Image/CompressedImage topic (default: the bag's only colour topic)"),
    "--depth-topic": ("depth_topic", str, "depth Image/CompressedImage topic (default: the only depth topic)"),
    "--camera-info-topic": ("camera_info_topic", str, "colour CameraInfo topic (default: the one in the colour frame)"),
    "--depth-camera-info-topic": ("depth_camera_info_topic", str,
                                  "CameraInfo of an unregistered depth camera (depth is then registered to colour)"),
    "--pose-topic": ("pose_topic", str, "PoseStamped/Odometry topic for poses (default: TF)"),
    "--pose-child-frame": ("pose_child_frame", str, "frame whose pose a PoseStamped topic gives (default: the camera frame)"),
    "--world-frame": ("world_frame", str, "world frame (default: map, else odom, else the TF root)"),
    "--camera-frame": ("camera_frame", str, "camera optical frame (default: the colour image's frame_id)"),
    "--max-depth-dt": ("max_depth_dt", float, "colour/depth association tolerance, seconds (default 0.02)"),
    "--max-pose-dt": ("max_pose_dt", float, "pose tolerance at image stamps, seconds (default 0.05)"),
}


def add_bag_args(p: argparse.ArgumentParser) -> None:
    """ROS bag options (``BagOptions``): used when ``--dataset`` is a bag."""
    g = p.add_argument_group("ROS bag input (rosbag2 folder, .mcap, .db3 or ROS 1 .bag as --dataset)")
    for flag, (dest, typ, help_) in BAG_FLAGS.items():
        g.add_argument(flag, dest=dest, type=typ, default=None, help=help_)
    g.add_argument("--no-bag-undistort", dest="bag_undistort", action="store_false", default=True,
                   help="do not undistort bag images whose CameraInfo has distortion")


def add_depth_camera_args(p: argparse.ArgumentParser) -> None:
    """Unregistered depth for folder datasets: depth intrinsics + depth→colour extrinsic."""
    g = p.add_argument_group("unregistered depth (folder datasets)")
    g.add_argument("--color-intrinsics", default=None, metavar="FX,FY,CX,CY",
                   help="override the colour intrinsics (TUM, 7-Scenes), e.g. 525,525,320,240 for 7-Scenes")
    g.add_argument("--depth-intrinsics", default=None, metavar="FX,FY,CX,CY[,W,H]",
                   help="depth files are not registered: their intrinsics (7-Scenes: 585,585,320,240)")
    g.add_argument("--depth-extrinsic", default=None, metavar="TX,TY,TZ,QX,QY,QZ,QW",
                   help="pose of the depth optical frame in the colour optical frame (m, quaternion xyzw); default identity")


def _numbers(text: str, flag: str) -> list:
    try:
        return [float(v) for v in str(text).replace(" ", ",").split(",") if v.strip()]
    except ValueError:
        raise ValueError(f"{flag} must be comma-separated numbers, got {text!r}") from None


def bag_options_from_args(args: argparse.Namespace) -> dict:
    """The BagOptions fields given on the command line (only those set)."""
    out = {dest: getattr(args, dest) for dest, _t, _h in BAG_FLAGS.values() if getattr(args, dest, None) is not None}
    if getattr(args, "bag_undistort", True) is False:
        out["undistort"] = False
    return out


def dataset_kwargs(args: argparse.Namespace, path: Path) -> dict:
    """Loader keyword arguments from the dataset's sensor profile (:mod:`gausslite.mapping.profiles`,
    stored in ``args.profile`` for :func:`config_from_args`) and the dataset flags, checked against
    the dataset layout. Flags win over the profile (``--no-undistort`` …).

    Raises:
        ValueError: a flag that does not apply to this layout, or malformed numbers.
    """
    # lazy: the command line starts without loading the library
    from gausslite.datasets import detect_layout
    from gausslite.datasets.registration import parse_depth_camera
    from gausslite.mapping.profiles import profile_for_layout

    kind = detect_layout(path)[0]
    flags = {k: getattr(args, k, None) for k in ("undistort", "interpolate_poses", "align_depth_time")}
    if any(v for v in flags.values()) and kind != "tum":
        raise ValueError(f"--undistort/--interpolate-poses/--align-depth-time apply to TUM sequences only, not {path}")
    profile = profile_for_layout(kind)
    args.profile = profile  # read by config_from_args
    kw: dict = dict(profile.loader)
    kw.update({k: bool(v) for k, v in flags.items() if v is not None and kind == "tum"})
    bag = bag_options_from_args(args)
    if bag and kind != "bag":
        raise ValueError(f"bag options ({', '.join('--' + k.replace('_', '-') for k in sorted(bag))}) apply to ROS "
                         f"bags only, not the {kind} dataset {path}")
    if bag:
        kw["bag"] = bag
    ci, di, de = (getattr(args, k, None) for k in ("color_intrinsics", "depth_intrinsics", "depth_extrinsic"))
    if (ci or di or de) and kind not in ("tum", "7scenes", "replica"):
        raise ValueError(f"--color-intrinsics/--depth-intrinsics/--depth-extrinsic apply to folder datasets; a bag "
                         f"takes them from its CameraInfo topics and TF ({path})")
    if ci:
        if kind == "replica":
            raise ValueError("--color-intrinsics: Replica intrinsics come from cam_params.json")
        vals = _numbers(ci, "--color-intrinsics")
        if len(vals) != 4:
            raise ValueError(f"--color-intrinsics needs fx,fy,cx,cy, got {ci!r}")
        kw["intrinsics"] = vals
    if de and not di:
        raise ValueError("--depth-extrinsic needs --depth-intrinsics")
    if di:
        dvals = _numbers(di, "--depth-intrinsics")
        size = None
        if len(dvals) == 4:  # same size as the colour images
            # lazy: the command line starts without loading the library
            from gausslite.datasets import load_dataset

            probe = load_dataset(path, max_frames=1, **{k: v for k, v in kw.items() if k != "bag"})
            size = (probe.native_intrinsics.width, probe.native_intrinsics.height)
        kw["depth_camera"] = parse_depth_camera(dvals, _numbers(de, "--depth-extrinsic") if de else None, size)
    return kw


def resolve_dataset(args: argparse.Namespace, out: Path):
    """Load ``--dataset``, or generate the synthetic default scene into ``out/scene`` (agent_a).

    The dataset's layout picks a sensor profile (see :func:`dataset_kwargs`); the chosen profile is
    logged and printed.
    """
    # lazy: the command line starts without loading the library
    from gausslite.datasets import load_dataset

    path = args.dataset
    if path is None:
        # lazy: the command line starts without loading the library
        from gausslite.synthetic import make_scene

        scene_dir = out / "scene"
        if not (scene_dir / "agent_a" / "traj.txt").exists():
            log.info("no --dataset: generating the synthetic default scene in %s", scene_dir)
            make_scene(scene_dir)
        path = scene_dir / "agent_a"
    kw = dataset_kwargs(args, path)
    profile = args.profile
    source = getattr(args, "pose_source", "auto")
    if source == "odometry" and kw.get("align_depth_time") and args.align_depth_time is None:
        kw["align_depth_time"] = False  # it re-projects depth with the ground truth: not for estimated poses
    msg = (f"profile: {profile.name} ({profile.description}); loader "
           f"{ {k: v for k, v in kw.items() if k != 'bag'} or 'defaults'}; mapper {profile.mapper or 'defaults'}")
    log.info("%s", msg)
    print(msg, flush=True)
    ds = load_dataset(path, downscale=args.downscale, max_frames=args.max_frames, pose_source=source,
                      progress=not getattr(args, "no_progress", False), annotations=args.annotations, **kw)
    used = "odometry" if hasattr(ds, "reference_poses") else "given"
    if used == "odometry":
        t_track = time.perf_counter()
        ds.track()  # before mapping: a frame that cannot be read, or Open3D missing a library, fails here
        args.odometry_s = time.perf_counter() - t_track  # recorded in metrics.json by ``map``
    print(f"poses: {used}" + (" (the dataset has none)" if used == "odometry" and source == "auto" else ""),
          flush=True)
    if used == "odometry" and not profile.mapper.get("pose", {}).get("refine"):
        # lazy: the command line starts without loading the library
        from dataclasses import replace

        from gausslite.mapping.config import deep_merge

        # estimated poses are refined with the map, from the estimate (the rendered profile's exact poses are not)
        args.profile = replace(profile, mapper=deep_merge(profile.mapper, {"pose": {"refine": True}}))
    return ds


def write_trajectory(ds, out: Path) -> Path:
    """Write the poses the map was made with as ``out/trajectory.tum`` (TUM format: ``timestamp tx ty tz qx qy qz
    qw``, camera-to-world, metres), leaving out the frames the odometry lost. Returns the file."""
    # lazy: the command line starts without loading the library
    import numpy as np

    from gausslite.datasets.trajectory import write_tum_trajectory

    ok = np.asarray(getattr(ds, "pose_ok", np.ones(len(ds), dtype=bool)), dtype=bool)
    stamps = np.asarray(getattr(ds, "timestamps", None) if hasattr(ds, "timestamps")
                        else [ds[i].timestamp for i in range(len(ds))], dtype=np.float64)
    source = "odometry" if hasattr(ds, "reference_poses") else "given"
    return write_tum_trajectory(out / "trajectory.tum", stamps[ok], np.asarray(ds.poses)[ok],
                                comment=f"gausslite map: the poses it mapped with ({source}) of {ds.path}")


def config_from_args(args: argparse.Namespace, **extra) -> MapperConfig:
    """MapperConfig from --config (a mapper-only YAML: :func:`gausslite.config.load_mapper_config`), --set and the
    shortcut flags (flags win), over the dataset's sensor profile (``args.profile``)."""
    # lazy: the command line starts without loading the library
    from gausslite.config import load_mapper_config

    profile = getattr(args, "profile", None)
    return load_mapper_config(
        args.config, args.overrides, defaults=dict(profile.mapper) if profile is not None else None,
        iters_per_frame=args.iters, seeding={"seeds_per_frame": args.seeds_per_frame},
        budget={"max_gaussians": args.max_gaussians}, backend=args.backend, seed=args.seed, **extra,
    )


#: what task-conditioned mapping of one's own recording needs (``docs/ros.md``, "Task-conditioned mapping of your bag")
TASK_HELP = ("task-conditioned mapping needs a task: --task \"pick up the cup\" (its words, grounded in an objects.json of "
             "labelled 3D boxes in the poses' world frame, in the dataset's folder or its parent, or by the ONNX "
             "detector and segmenter of --onnx-detector, --onnx-vocab and --onnx-segmenter), or --mode gausslite "
             "--task-id ID of a tasks.json beside the objects.json (docs/ros.md)")


def warn_uniform(task_id) -> None:
    """Log that ``gausslite map`` maps uniformly (mode ``uniform``): with no task at all, or with a task that then only
    scores the map."""
    if task_id is None:
        log.warning("no task given: mapping uniformly (every region alike); %s", TASK_HELP)
    else:
        log.warning("mode uniform: task %s only scores the map (ROI metrics), it does not steer the mapping; "
                    "add --mode gausslite to map for it", task_id)


def ground_task(args: argparse.Namespace, ds):
    """The relevance function ``frame -> (H, W) bool`` of ``--task`` text, grounded as the agent grounds it
    (:func:`gausslite.mission.relevance.build_relevance`): the task parser's graph, then the attention front-end with
    the dataset's annotations (``objects.json``) when it has them, else with the ONNX detector and segmenter of
    ``--onnx-detector/--onnx-vocab/--onnx-segmenter``. Prints which it used.

    Raises:
        ValueError: the task cannot be grounded (no annotations and no ONNX models; models that do not load).
    """
    # lazy: the command line starts without loading the library
    from gausslite.mission.config import AgentConfig, OnnxRelevanceConfig
    from gausslite.mission.relevance import build_relevance
    from gausslite.parser import TaskParser

    onnx = OnnxRelevanceConfig(detector_path=args.onnx_detector, vocab_path=args.onnx_vocab,
                               segmenter_path=args.onnx_segmenter)
    ann = ds.annotations if ds.annotations is not None and ds.annotations.objects else None
    if ann is not None:
        backend, what = "annotation", f"the scene annotations ({ann.objects_path})"
    elif any((args.onnx_detector, args.onnx_vocab, args.onnx_segmenter)):
        backend, what = "onnx", f"the ONNX detector {args.onnx_detector} and segmenter {args.onnx_segmenter}"
    else:
        raise ValueError(f"cannot ground the task {args.task!r}: {ds.path} has no objects.json (scene annotations; "
                         f"--annotations FOLDER, docs/annotations.md) and no ONNX models are configured "
                         f"(--onnx-detector, --onnx-vocab, --onnx-segmenter; docs/perception.md)")
    graph = TaskParser().parse(args.task)
    cfg = AgentConfig(relevance="attention", relevance_backend=backend, onnx=onnx)
    fn, _ = build_relevance(cfg, graph, ann)
    print(f"task: {args.task!r} grounded with {what}; targets {list(graph.targets)}, anchors {list(graph.anchors)}",
          flush=True)
    return fn


def parse_time_budget(text: str):
    """``--time-budget``'s value: minutes (a float > 0), or ``"none"`` for ``none``/``off`` (the fixed schedule).

    Raises:
        argparse.ArgumentTypeError: anything else.
    """
    if str(text).strip().lower() in NO_BUDGET:
        return "none"
    try:
        minutes = float(text)
    except ValueError:
        minutes = float("nan")
    if not minutes > 0 or minutes == float("inf"):
        raise argparse.ArgumentTypeError(f"--time-budget takes minutes > 0 or 'none', got {text!r}")
    return minutes


def parse_withhold(text: str) -> int:
    """``--withhold``'s value: an integer ≥ 2.

    Raises:
        argparse.ArgumentTypeError: anything else.
    """
    try:
        k = int(text)
    except ValueError:
        k = 0
    if k < 2:
        raise argparse.ArgumentTypeError(f"--withhold takes an integer >= 2 (every k-th frame), got {text!r}")
    return k


def time_budget_from_args(args: argparse.Namespace, cfg: MapperConfig, spent_s: float) -> Optional[TimeBudget]:
    """The total time budget of ``gausslite map`` (:class:`gausslite.pipeline.TimeBudget`), or None for the fixed
    schedule, with the live agent's keyframe rule and resolution governor (the defaults of ``AgentConfig``:
    ``keyframe_*``, ``agent.resolution``; the work model of ``cfg.work_cost``; with ``cfg.detail`` the task region's
    own level too, :meth:`~gausslite.mission.config.ResolutionConfig.governor`).

    The budget is ``--time-budget`` minutes, by default :data:`DEFAULT_TIME_BUDGET_MIN`; the fixed schedule is
    ``--time-budget none``, or, when ``--time-budget`` is not given, an iteration count or keyframe budget set by
    ``--iters``, ``--config`` or ``--set`` (``iters_per_frame``, ``keyframe_budget_s``).

    Args:
        args: the parsed arguments (``time_budget``: minutes, ``"none"`` for the fixed schedule, or None/absent when
            not given).
        cfg: the mapper config. spent_s: seconds the command spent before mapping (loading, odometry).
    Raises:
        ValueError: ``--time-budget`` with ``mapper.keyframe_budget_s`` set (two budgets).
    """
    # lazy: the command line starts without loading the library
    from gausslite.mapping.keyframes import KeyframeRule
    from gausslite.mission.config import AgentConfig
    from gausslite.pipeline import TimeBudget

    given = getattr(args, "time_budget", None)
    if given == "none":
        return None
    fixed = {"iters_per_frame", "keyframe_budget_s"} & cfg.model_fields_set
    if given is None and fixed:
        log.info("fixed schedule (%s set): every frame mapped at its size; --time-budget MIN fits a budget instead",
                 " and ".join(sorted(fixed)))
        return None
    if cfg.keyframe_budget_s is not None:
        raise ValueError("--time-budget and mapper.keyframe_budget_s both set a budget: give one (the total budget "
                         "sets each keyframe's)")
    minutes = DEFAULT_TIME_BUDGET_MIN if given is None else float(given)
    agent = AgentConfig()
    governor = agent.resolution.governor(cfg)  # the task region's level too, under mapper.detail
    rule = KeyframeRule(agent.keyframe_translation_m, agent.keyframe_rotation_deg, agent.keyframe_max_interval_s)
    return TimeBudget(60.0 * minutes, max(0.0, spent_s), rule, governor)


def _handler(args: argparse.Namespace) -> int:
    t_start = time.perf_counter()  # the time budget counts from here: loading and odometry are part of it
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    try:
        ds = resolve_dataset(args, out)
    except (ValueError, FileNotFoundError, RuntimeError) as e:  # bad dataset / bag: one clear error, no traceback
        log.error("cannot load the dataset: %s", e)
        return 2
    if args.mode is None:
        args.mode = "gausslite" if args.task else "uniform"
    try:
        cfg = config_from_args(args, mode=args.mode)
    except (ValueError, FileNotFoundError) as e:  # pydantic's ValidationError is a ValueError
        log.error("invalid mapper configuration: %s", e)
        return 2
    relevance = None
    if args.task:
        try:
            relevance = ground_task(args, ds)
        except ValueError as e:  # RelevanceUnavailable, an unparsable task: one line
            log.error("%s", e)
            return 2
    elif cfg.mode == "uniform":
        warn_uniform(args.task_id)
    if args.task_id is None and cfg.mode == "gausslite" and relevance is None:
        if ds.annotations is None or not ds.annotations.tasks:
            log.error("mode gausslite needs --task-id and a tasks.json next to %s", ds.path)
            return 2
        args.task_id = ds.annotations.tasks[0].id
        log.info("no --task-id given: using the first task, %s", args.task_id)
    # lazy: the command line starts without loading the library
    from gausslite.pipeline import run_mapping  # torch + warp: imported once the inputs are valid

    try:
        budget = time_budget_from_args(args, cfg, time.perf_counter() - t_start)
    except ValueError as e:
        log.error("%s", e)
        return 2
    log.info("mapping %s (%d frames, %dx%d) mode=%s task=%s", ds.path, len(ds),
             ds.intrinsics.width, ds.intrinsics.height, cfg.mode, args.task_id)
    print(f"schedule: time budget {budget.total_s / 60:g} min ({budget.spent_s:.0f} s spent loading), keyframes and "
          f"resolution as the live agent picks them" if budget is not None else
          f"schedule: fixed, {cfg.iters_per_frame} iterations on every frame at its size (no time budget)", flush=True)
    _, metrics = run_mapping(ds, cfg, task_id=args.task_id, relevance_fn=relevance, stride=args.stride, out_dir=out,
                             progress=not args.no_progress, withhold_every=args.withhold, time_budget=budget)
    if getattr(args, "odometry_s", None) is not None:  # the tracking before mapping (part of a time budget)
        metrics["odometry_s"] = args.odometry_s
        (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    brief = {k: v for k, v in metrics.items() if k != "per_frame"}
    if "time_budget" in brief:
        brief["time_budget"] = {k: v for k, v in brief["time_budget"].items() if k != "keyframe_ids"}
    print(json.dumps(brief, indent=2))
    print(f"trajectory: {write_trajectory(ds, out)}", flush=True)
    return 0


def register(sub) -> None:
    p = sub.add_parser("map", help="map an RGB-D sequence and evaluate it",
                       description="Map an RGB-D sequence, with its poses or poses from odometry; writes map.ply, "
                                   "metrics.json, trajectory.tum and PNGs.")
    add_mapping_args(p)
    p.add_argument("--mode", choices=["uniform", "gausslite"], default=None,
                   help="uniform (the default without --task: every region alike, a warning says so) or gausslite "
                        "(task-conditioned, the default with --task: needs --task, or --task-id or a tasks.json beside "
                        "the dataset, with objects.json)")
    g = p.add_argument_group("task text (grounded as the agent grounds it: the task parser, then the attention "
                             "front-end with the dataset's objects.json, else the ONNX models below)")
    g.add_argument("--task", default=None, help='what the map is for, e.g. "pick up the cup"')
    g.add_argument("--onnx-detector", default=None, metavar="PATH", help="Grounding-DINO-style detector .onnx")
    g.add_argument("--onnx-vocab", default=None, metavar="PATH", help="the detector's vocab.txt")
    g.add_argument("--onnx-segmenter", default=None, metavar="PATH", help="FastSAM / YOLOv8-seg segmenter .onnx")
    p.add_argument("--time-budget", dest="time_budget", type=parse_time_budget, default=None, metavar="MIN",
                   help=f"total time budget in minutes, loading, odometry and scoring included (default "
                        f"{DEFAULT_TIME_BUDGET_MIN:g}): keyframes and the mapping resolution are picked as the live "
                        f"agent picks them and each keyframe gets its share, at most iters_per_frame iterations' "
                        f"worth; 'none' maps every frame with iters_per_frame iterations at its size (the fixed "
                        f"schedule, also the default when --iters, iters_per_frame or keyframe_budget_s is set)")
    p.add_argument("--withhold", type=parse_withhold, default=None, metavar="K",
                   help="withhold every K-th frame (from frame K/2) from the mapper and score it as a held-out view "
                        "(heldout_* in metrics.json)")
    p.add_argument("--out", required=True, type=Path, help="output folder")
    p.set_defaults(func=_handler)
