"""``gausslite export bag --dataset PATH --out BAG``: write any supported dataset as a ROS bag.

Default output: rosbag2 with MCAP storage (a new folder). Topics, frames and stamps are described in
:mod:`gausslite.ros.export`; the bag reads back with ``--dataset BAG`` giving the same images, depths,
intrinsics and poses.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

log = logging.getLogger("gausslite.export_bag")


#: one line for the command listing of ``gausslite export``
HELP = "a dataset as a ROS bag: rosbag2 MCAP (or SQLite3 / ROS 1)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Add the options of ``gausslite export bag`` to ``p`` and make :func:`handle` its handler."""
    # lazy: the command line starts without loading the library
    from gausslite.cli.cmd_map import add_bag_args, add_depth_camera_args

    p.description = __doc__.split("\n\n")[0]
    p.add_argument("--dataset", required=True, type=Path, help="dataset folder or bag (any supported layout)")
    p.add_argument("--out", required=True, type=Path, help="output bag (a new folder; a .bag file with --storage ros1)")
    p.add_argument("--storage", choices=["mcap", "sqlite3", "ros1"], default="mcap")
    p.add_argument("--depth-encoding", choices=["32FC1", "16UC1"], default="32FC1",
                   help="32FC1: metres, exact; 16UC1: millimetres, rounded")
    p.add_argument("--downscale", type=float, default=1.0, help="image downscale factor (intrinsics scale too)")
    p.add_argument("--max-frames", type=int, default=None, help="export at most N frames")
    p.add_argument("--stride", type=int, default=1, help="export every k-th frame")
    p.add_argument("--undistort", action=argparse.BooleanOptionalAction, default=None,
                   help="TUM only: undistort before export (on by default: the hand-held profile, as in `map`)")
    p.add_argument("--interpolate-poses", action=argparse.BooleanOptionalAction, default=None,
                   help="TUM only: interpolate ground-truth poses (on by default, as in `map`)")
    add_bag_args(p)
    add_depth_camera_args(p)
    p.set_defaults(func=handle)


def handle(args: argparse.Namespace) -> int:
    """Run ``gausslite export bag``: print the bag's summary (JSON). Returns the exit code: 0, or 2 when the
    dataset does not load or the bag cannot be written (e.g. ``--out`` exists)."""
    # lazy: the command line starts without loading the library
    from tqdm import tqdm

    from gausslite.cli.cmd_map import dataset_kwargs
    from gausslite.datasets import load_dataset
    from gausslite.ros.export import export_bag

    try:
        ds = load_dataset(args.dataset, downscale=args.downscale, max_frames=args.max_frames, stride=args.stride,
                          **dataset_kwargs(args, args.dataset))
    except (ValueError, FileNotFoundError) as e:
        log.error("cannot load the dataset: %s", e)
        return 2
    bar = tqdm(total=len(ds), desc="export bag", unit="frame")
    try:
        summary = export_bag(ds, args.out, storage=args.storage, depth_encoding=args.depth_encoding,
                             progress=lambda i, n: bar.update(1))
    except (ValueError, FileExistsError) as e:
        log.error("cannot export: %s", e)
        return 2
    finally:
        bar.close()
    print(json.dumps(summary, indent=2))
    return 0
