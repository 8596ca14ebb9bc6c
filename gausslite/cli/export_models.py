"""``gausslite export models``: write the ONNX detector, its vocab.txt and the ONNX segmenter that an agent's
``relevance_backend: onnx`` loads (docs/perception.md).

Detector: a Grounding DINO checkpoint folder (``config.json``, ``model.safetensors`` or ``pytorch_model.bin``,
``vocab.txt``) or a hub id (``IDEA-Research/grounding-dino-tiny``) that is in the local Hugging Face cache; with
``--allow-download`` a hub id may be fetched. Segmenter: an ultralytics ``.pt`` (FastSAM-s.pt, yolov8s-seg.pt;
must exist locally) or a model ``.yaml`` (random weights; for timing). Writes ``OUT/detector.onnx``,
``OUT/vocab.txt``, ``OUT/segmenter.onnx`` and ``OUT/agent-onnx.yaml`` (the agent settings that use them).
Exit code 2 with the list of needed files when a source is incomplete or not available offline.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


#: one line for the command listing of ``gausslite export``
HELP = "Grounding DINO / YOLOv8-seg (FastSAM) as the ONNX files the agent loads"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Add the options of ``gausslite export models`` to ``p`` (a parser made with
    ``formatter_class=argparse.RawDescriptionHelpFormatter``) and make :func:`handle` its handler."""
    p.description = __doc__
    p.add_argument("--detector", default=None, help="Grounding DINO checkpoint folder or hub id")
    p.add_argument("--segmenter", default=None, help="ultralytics .pt or .yaml (YOLOv8-seg, FastSAM)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--det-size", type=int, nargs=2, default=[800, 800], metavar=("H", "W"),
                   help="detector input size, pixels (default 800 800)")
    p.add_argument("--seg-imgsz", type=int, nargs="+", default=[640], metavar="S",
                   help="segmenter input: S (square) or H W (default 640; ultralytics rounds up to multiples of 32)")
    p.add_argument("--allow-download", action="store_true",
                   help="let transformers fetch a hub id that is not cached (default: local files only)")
    p.set_defaults(func=handle)


def handle(args: argparse.Namespace) -> int:
    """Run ``gausslite export models``. Returns the exit code: 0, or 2 with the reason on stderr (no source given,
    a bad ``--seg-imgsz``, model files missing or not available offline, the export packages not installed)."""
    # lazy: the command line starts without loading the library
    from gausslite.attention.export import MissingModelFiles, export_models

    if args.detector is None and args.segmenter is None:
        print("gausslite export models: give --detector and/or --segmenter", file=sys.stderr)
        return 2
    if len(args.seg_imgsz) not in (1, 2):
        print("gausslite export models: --seg-imgsz takes S or H W", file=sys.stderr)
        return 2
    seg_imgsz = args.seg_imgsz[0] if len(args.seg_imgsz) == 1 else tuple(args.seg_imgsz)
    try:
        res = export_models(args.out, detector=args.detector, segmenter=args.segmenter,
                            det_size=tuple(args.det_size), seg_imgsz=seg_imgsz,
                            local_files_only=not args.allow_download)
    except MissingModelFiles as e:
        print(f"gausslite export models: {e}", file=sys.stderr)
        print("gausslite export models: needed files:", file=sys.stderr)
        for n in e.needed:
            print(f"  {n}", file=sys.stderr)
        return 2
    except ImportError as e:
        print(f"gausslite export models: {e} (bash scripts/setup.sh installs transformers, onnxscript and ultralytics)",
              file=sys.stderr)
        return 2
    except ValueError as e:
        print(f"gausslite export models: {e}", file=sys.stderr)
        return 2
    yaml_path = Path(args.out) / "agent-onnx.yaml"
    yaml_path.write_text(res.agent_yaml())
    for name, p in (("detector", res.detector), ("vocab", res.vocab), ("segmenter", res.segmenter)):
        if p is not None:
            print(f"{name}: {p}")
    print(f"agent settings: {yaml_path}")
    print(res.agent_yaml(), end="")
    return 0
