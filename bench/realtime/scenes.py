"""The real-time benchmark's scenes: the built-in ones (:data:`SCENES`) and a user's own sequence
(:func:`dataset_scenes`), where each one's data lives (:func:`scene_path`), how it loads with its sensor profile and
clock (:func:`load_scene`), and its frames decoded into memory for a replay (:class:`Preloaded`)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

from gausslite.datasets import detect_layout, load_dataset
from gausslite.mapping.profiles import profile_for_layout
from gausslite.synthetic import make_scene

REPO = Path(__file__).resolve().parents[2]
SHARED = Path(os.environ.get("GAUSSLITE_SHARED", REPO.parent / "shared"))
RESULTS = REPO / "bench" / "results"

#: bench scenes: dataset, task, resolution, clock, the matched Gaussian cap (a cap uniform reaches at every budget:
#: measured counts below it, docs/realtime.md) and, for the public sequences, the annotations GaussLite ships
#: (``gausslite/datasets/labels``, docs/annotations.md), so that a row reproduces from the dataset and the repository
SCENES = {
    "tum_fr1_rpy": {"kind": "tum", "downscale": 2.0, "task": "tum-find-mouse", "cap": 6000, "annotations": "shipped"},
    "synthetic_circle": {"kind": "synthetic", "frames": 300, "width": 320, "height": 240,
                         "task": "synth-pick-object", "cap": 6000},
    "room0": {"kind": "replica", "downscale": 4.0, "fps": 2.0, "task": "room0-pick-plant", "cap": 6000,
              "annotations": "shipped"},
    "tum_fr1_rpy_cup": {"kind": "tum", "downscale": 2.0, "task": "tum-pick-cup", "cap": 6000, "annotations": "shipped"},
}
MODES = ("uniform", "gausslite")
#: data seconds per keyframe that every budget covers under ``--clock scaled`` (the paper's 0.5 s/frame)
REFERENCE_BUDGET_S = 0.5


def scene_path(name: str, work: Path) -> Path:
    """The dataset folder of a bench scene (the synthetic circle is generated into ``work`` once).

    Raises:
        FileNotFoundError: a shared dataset that is absent (set ``GAUSSLITE_SHARED``).
    """
    spec = SCENES[name]
    if spec["kind"] == "tum":
        p = SHARED / "datasets" / "TUM_rgbd_dataset_freiburg1_rpy"
    elif spec["kind"] == "replica":
        p = SHARED / "datasets" / "Replica_room0"
    else:
        out = work / f"synthetic_circle_{spec['frames']}_{spec['width']}x{spec['height']}"
        if not (out / "agent_a" / "results" / f"depth{spec['frames'] - 1:06d}.png").exists():
            make_scene(out, frames=spec["frames"], width=spec["width"], height=spec["height"], trajectory="circle")
        p = out / "agent_a"
    if not p.exists():
        raise FileNotFoundError(f"{p} not found (set GAUSSLITE_SHARED)")
    return p


def dataset_scenes(path: Path, task_ids: list[str], cap: int, downscale: float = 1.0,
                   fps: Optional[float] = None) -> dict:
    """Bench scenes of a user's own sequence (``--dataset``): one per task id, named after it.

    Args:
        path: a folder the loaders read (:func:`gausslite.datasets.load_dataset`) whose annotations
            (``objects.json`` / ``tasks.json``) name the tasks.
        task_ids: ids in its ``tasks.json``. cap: the matched Gaussian cap. downscale: image downscale factor.
        fps: replay clock of sequences without timestamps (Replica, 7-Scenes).
    Returns:
        ``{task id: scene spec}`` (the layout of :data:`SCENES`, with ``"path"``).
    Raises:
        FileNotFoundError: no such folder. ValueError: no task ids, a sequence without annotations, or a task id
            its ``tasks.json`` lacks.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path} not found")
    if not task_ids:
        raise ValueError("--dataset needs --tasks ID[,ID...]")
    ann = load_dataset(path, max_frames=1).annotations
    if ann is None:
        raise ValueError(f"{path} has no objects.json / tasks.json (docs/mapper.md#scene-annotations)")
    known = [t.id for t in ann.tasks]
    missing = [t for t in task_ids if t not in known]
    if missing:
        raise ValueError(f"tasks {missing} are not in {path}'s tasks.json (known: {known})")
    return {t: {"kind": "dataset", "path": str(path), "task": t, "cap": cap, "downscale": downscale,
                **({"fps": fps} if fps else {})} for t in task_ids}


def load_scene(spec: dict, path: Path):
    """(dataset, sensor profile) of a scene spec with the profile's loader options, the scene's clock and its
    annotations (``spec["annotations"]``: a choice of :func:`gausslite.datasets.load_dataset`, default ``auto``)."""
    layout = detect_layout(path)[0]
    profile = profile_for_layout(layout)
    kw = dict(profile.loader)
    if spec.get("fps") and layout in ("replica", "7scenes"):
        kw["fps"] = spec["fps"]
    return load_dataset(path, downscale=spec.get("downscale", 1.0), annotations=spec.get("annotations", "auto"),
                        **kw), profile


class Preloaded:
    """A dataset's frames decoded into memory: a replay then sends frames as a sensor driver delivers them,
    without the loader's decoding, undistortion and depth registration competing with the mapper."""

    def __init__(self, ds) -> None:
        self.frames = [ds[i] for i in range(len(ds))]
        self.annotations = ds.annotations

    def slice(self, start: int, stop: int) -> "Preloaded":
        """Frames ``[start, stop)`` as a preloaded dataset of their own (no copy of the frames)."""
        out = Preloaded.__new__(Preloaded)
        out.frames, out.annotations = self.frames[start:stop], self.annotations
        return out

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int):
        return self.frames[i]
