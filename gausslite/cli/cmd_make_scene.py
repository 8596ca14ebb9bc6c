"""``gausslite make-scene``: render the procedural two-robot synthetic scene to a folder."""

from __future__ import annotations

import argparse
import json
import logging

log = logging.getLogger(__name__)

#: ``gausslite.synthetic.SENSOR_NOISE``, named here so that the command line starts without loading the library
SENSOR_NOISE_NAMES = ("none", "realistic", "tum", "tum-clean", "tum-exposure", "tum-blur", "tum-misregistration",
                      "tum-depth-noise", "tum-depth-holes")


def _handler(args: argparse.Namespace) -> int:
    """Run :func:`gausslite.synthetic.make_scene` with the parsed arguments; returns the exit code
    (0 = written, 2 = invalid arguments, 1 = I/O error)."""
    # lazy: the command line starts without loading the library
    from gausslite.synthetic import make_scene

    try:
        summary = make_scene(args.out, seed=args.seed, width=args.width, height=args.height,
                             frames=args.frames, progress=not args.quiet, trajectory=args.trajectory,
                             sensor_noise=args.sensor_noise, fps=args.fps, agents=args.agents)
    except ValueError as e:
        log.error("make-scene: %s", e)
        return 2
    except OSError as e:
        log.error("make-scene: cannot write %s: %s", args.out, e)
        return 1
    print(json.dumps({"out_dir": summary["out_dir"], "seconds": round(summary["seconds"], 2),
                      "roi_fraction": summary["roi_fraction"]}, indent=2))
    return 0


def register(subparsers) -> None:
    """Add the ``make-scene`` subcommand to ``subparsers`` (an argparse sub-parsers action)."""
    p = subparsers.add_parser(
        "make-scene", help="render the synthetic two-robot scene (Replica layout + objects/tasks)",
        description="Render the procedural synthetic room from two robot trajectories and write "
                    "DIR/agent_{a,b}/results/frame*.jpg + depth*.png, traj.txt, cam_params.json, "
                    "objects.json, tasks.json and scene.json.")
    p.add_argument("--out", required=True, help="output folder DIR")
    p.add_argument("--seed", type=int, default=0, help="scene seed (default 0)")
    p.add_argument("--width", type=int, default=320, help="image width in pixels (default 320)")
    p.add_argument("--height", type=int, default=240, help="image height in pixels (default 240)")
    p.add_argument("--frames", type=int, default=30, help="frames per agent (default 30)")
    p.add_argument("--trajectory", choices=["arcs", "circle", "walk", "scan_walk"], default="arcs",
                   help="arcs: two arcs in front of the desk (default); circle: both robots once around the "
                        "room, for long missions (e.g. --frames 600, mapped with --stride 2); walk: a 7 m hand-held "
                        "walk, two loops in front of the desk (--frames 525 at 30 fps = 0.40 m/s); scan_walk: the "
                        "same walk looking around as it goes (about 52 degrees/s, as TUM fr1/rpy)")
    p.add_argument("--sensor-noise", dest="sensor_noise", choices=SENSOR_NOISE_NAMES, default="none",
                   help="none: exact renders (default); realistic: Kinect-like depth noise and holes, motion blur, "
                        "rolling shutter, exposure changes and colour noise; tum: the Kinect v1 of TUM RGB-D fr1 as "
                        "measured (its field of view, disparity-quantised depth, holes, colour-depth misregistration "
                        "and delay, exposure, blur and rolling shutter; seeded by --seed); tum-<fault>: one group of "
                        "tum's faults alone on its camera (exposure, blur, misregistration, depth-noise, depth-holes; "
                        "tum-clean: none)")
    p.add_argument("--fps", type=float, default=30.0,
                   help="frame rate of the sequence: the walk's clock and the sensor model's (default 30, the "
                        "rate the Replica loader replays it at)")
    p.add_argument("--agents", nargs="+", choices=["agent_a", "agent_b"], default=["agent_a", "agent_b"],
                   metavar="AGENT", help="the robots whose frames are written (default both: agent_a agent_b; "
                   "one robot renders half the frames)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_handler)
