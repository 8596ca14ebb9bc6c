"""``gausslite annotate``: a sequence's ``objects.json`` and ``tasks.json`` from a labels file of one click per object
(:mod:`gausslite.datasets.labelling`; ``docs/annotations.md``)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(subparsers) -> None:
    """Add the ``annotate`` subcommand to ``subparsers``."""
    p = subparsers.add_parser(
        "annotate", help="label a sequence's objects as 3D boxes from one click each (objects.json, tasks.json)",
        description="Write objects.json and tasks.json for an RGB-D sequence with poses from a labels file "
                    "(gausslite-labels/1: one pixel per object in one frame, its kind, the tasks). The boxes come "
                    "from the frames' depth fused at their poses: the cluster above the supporting plane for an "
                    "object, the connected patch of the plane for a surface.")
    p.add_argument("--dataset", required=True, help="the sequence folder (TUM, Replica, 7-Scenes, a camera folder)")
    p.add_argument("--labels", required=True,
                   help="a labels file, or the name of a set GaussLite ships (tum_fr1_rpy, replica_room0)")
    p.add_argument("--out", required=True, help="folder to write objects.json and tasks.json into")
    p.set_defaults(func=_handle)


def _handle(args: argparse.Namespace) -> int:
    # lazy: the command line starts without loading the library
    from gausslite.datasets import load_dataset
    from gausslite.datasets.labelling import SHIPPED, SHIPPED_DIR, label_scene, write_annotations

    labels = SHIPPED_DIR / args.labels / "labels.json" if args.labels in SHIPPED else Path(args.labels)
    try:
        ds = load_dataset(args.dataset, annotations="beside", progress=False)
        objects_json, tasks_json = label_scene(ds, labels)
        paths = write_annotations(args.out, objects_json, tasks_json)
    except (KeyError, ValueError, OSError) as e:
        print(f"gausslite annotate: error: {e}", file=sys.stderr)
        return 2
    for o in objects_json["objects"]:
        size = " x ".join(f"{v:.2f}" for v in o["size"])
        print(f"{o['id']:>3}  {o['label']:<16} {size} m")
    print(f"wrote {paths[0]} and {paths[1]}")
    return 0
