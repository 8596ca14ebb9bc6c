"""Render the synthetic scene for both agents and write it in the Replica / NICE-SLAM layout.

Output of :func:`make_scene` (``DIR`` = ``out_dir``)::

    DIR/cam_params.json            {"camera": {"w", "h", "fx", "fy", "cx", "cy", "scale": 6553.5}}
    DIR/objects.json               gausslite-objects/1, up_axis "+z"
    DIR/tasks.json                 gausslite-tasks/1
    DIR/scene.json                 summary: seed, sizes, frames, generator version, ROI fractions
    DIR/agent_a/traj.txt           one row-major 4x4 camera-to-world pose per line
    DIR/agent_a/results/frame000000.jpg   colour (JPEG quality 97)
    DIR/agent_a/results/depth000000.png   uint16 depth, metres = value / 6553.5
    DIR/agent_b/...                likewise

Everything written is a deterministic function of ``(seed, width, height, frames)``.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Dict, Sequence, Union

import cv2
import numpy as np
from tqdm import tqdm

from gausslite.camera import Intrinsics, backproject
from gausslite.synthetic.raycast import render
from gausslite.synthetic.scene import GENERATOR_VERSION, build_default_scene
from gausslite.synthetic.trajectories import AGENTS, make_trajectories

log = logging.getLogger(__name__)

#: Depth PNG scale: depth_m = value / DEPTH_SCALE.
DEPTH_SCALE = 6553.5
JPEG_QUALITY = 97


def default_intrinsics(width: int, height: int) -> Intrinsics:
    """90-degree horizontal field of view, like the Replica renders: ``fx = fy = width / 2``,
    principal point at the image centre ``((w - 1) / 2, (h - 1) / 2)`` (pixels).

    Raises:
        ValueError: ``width < 16`` or ``height < 12``.
    """
    if int(width) < 16 or int(height) < 12:
        raise ValueError(f"image too small: {width}x{height} (minimum 16x12)")
    f = float(width) / 2.0
    return Intrinsics(fx=f, fy=f, cx=(width - 1) / 2.0, cy=(height - 1) / 2.0, width=int(width), height=int(height))


def quantize_depth(depth_m: np.ndarray) -> np.ndarray:
    """(H, W) float depth in metres -> (H, W) uint16 PNG values (``round(depth * 6553.5)``).

    Raises:
        ValueError: depth outside [0, 65535 / 6553.5] metres or not finite.
    """
    if not np.all(np.isfinite(depth_m)) or depth_m.min() < 0 or depth_m.max() > 65535 / DEPTH_SCALE:
        raise ValueError("depth out of the uint16 PNG range [0, 10.0] m")
    return np.rint(depth_m * DEPTH_SCALE).astype(np.uint16)


def mask_rule(points: np.ndarray, valid: np.ndarray, obj: dict) -> np.ndarray:
    """Mask of points inside an ``objects.json`` box enlarged by its ``mask_margin_m``.

    Args:
        points: (..., 3) float64 world points (metres).
        valid: (...) bool, points with valid depth (others are never in the mask).
        obj: one ``objects.json`` object entry (``center``, ``size``, ``rotation``, ``mask_margin_m``).

    Returns:
        (...) bool mask.
    """
    R = np.asarray(obj["rotation"], dtype=np.float64)
    c = np.asarray(obj["center"], dtype=np.float64)
    half = 0.5 * np.asarray(obj["size"], dtype=np.float64) + float(obj.get("mask_margin_m", 0.0))
    local = (points - c) @ R
    return valid & np.all(np.abs(local) <= half, axis=-1)


def _dump_json(path: Path, data: dict) -> None:
    path.write_text(json.dumps(data, indent=2) + "\n")


def make_scene(out_dir: Union[str, Path], seed: int = 0, width: int = 320, height: int = 240,
               frames: int = 30, progress: bool = True, trajectory: str = "arcs") -> Dict:
    """Generate, render and write the default synthetic two-robot scene.

    Args:
        out_dir: output folder (created; previously written frames there are replaced).
        seed: scene / trajectory seed; equal arguments give byte-identical files.
        width, height: image size in pixels (>= 16 x 12).
        frames: frames per agent (>= 2).
        progress: show a tqdm progress bar over the rendered frames.
        trajectory: ``"arcs"`` (the default two-robot arcs) or ``"circle"`` (both robots once around
            the room: the long-mission scene, e.g. ``frames=600`` mapped with stride 2).

    Returns:
        Summary dict: ``out_dir``, ``cam_params``, ``objects``, ``tasks``, ``scene_json`` (paths as
        str), ``agents`` (name -> ``{"dir", "traj", "frames"}``), ``tasks_text`` (task id -> text),
        ``roi_fraction`` (agent -> task id -> mean fraction of pixels in the task's ROI mask),
        ``roi_nonempty`` (agent -> task id -> fraction of frames whose ROI mask is non-empty),
        ``num_objects`` and ``seconds`` (wall time; the only non-deterministic entry, not written).

    Raises:
        ValueError: invalid size or frame count.
    """
    t0 = time.perf_counter()
    if int(frames) < 2:
        raise ValueError(f"frames must be >= 2, got {frames}")
    intr = default_intrinsics(width, height)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    scene = build_default_scene(seed)
    trajs = make_trajectories(frames, seed, trajectory)
    objects_json = scene.objects_json()
    tasks_json = scene.tasks_json()
    by_id = {o["id"]: o for o in objects_json["objects"]}

    _dump_json(out / "cam_params.json", {"camera": {
        "w": intr.width, "h": intr.height, "fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy,
        "scale": DEPTH_SCALE}})
    _dump_json(out / "objects.json", objects_json)
    _dump_json(out / "tasks.json", tasks_json)

    roi_sum = {a: {t.id: 0.0 for t in scene.tasks} for a in AGENTS}
    roi_hit = {a: {t.id: 0 for t in scene.tasks} for a in AGENTS}
    agents_out = {}
    bar = tqdm(total=len(AGENTS) * int(frames), desc="make-scene", unit="frame", disable=not progress)
    try:
        for agent in AGENTS:
            res_dir = out / agent / "results"
            res_dir.mkdir(parents=True, exist_ok=True)
            for stale in list(res_dir.glob("frame??????.jpg")) + list(res_dir.glob("depth??????.png")):
                stale.unlink()
            poses = trajs[agent]
            np.savetxt(out / agent / "traj.txt", poses.reshape(len(poses), 16), fmt="%.18e")
            for i, c2w in enumerate(poses):
                r = render(scene, intr, c2w)
                dq = quantize_depth(r.depth)
                if not cv2.imwrite(str(res_dir / f"frame{i:06d}.jpg"), r.rgb[:, :, ::-1],
                                   [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY]):
                    raise OSError(f"could not write {res_dir / f'frame{i:06d}.jpg'}")
                if not cv2.imwrite(str(res_dir / f"depth{i:06d}.png"), dq):
                    raise OSError(f"could not write {res_dir / f'depth{i:06d}.png'}")
                dm = dq.astype(np.float64) / DEPTH_SCALE
                pts = backproject(dm, intr, c2w)
                valid = dm > 0
                masks = {oid: mask_rule(pts, valid, o) for oid, o in by_id.items()}
                for t in scene.tasks:
                    m = np.zeros(dm.shape, dtype=bool)
                    for oid in t.roi_object_ids:
                        m |= masks[oid]
                    frac = float(m.mean())
                    roi_sum[agent][t.id] += frac
                    roi_hit[agent][t.id] += int(frac > 0)
                bar.update(1)
            agents_out[agent] = {"dir": str(out / agent), "traj": str(out / agent / "traj.txt"), "frames": int(frames)}
    finally:
        bar.close()

    roi_fraction = {a: {k: round(v / frames, 6) for k, v in d.items()} for a, d in roi_sum.items()}
    roi_nonempty = {a: {k: round(v / frames, 6) for k, v in d.items()} for a, d in roi_hit.items()}
    _dump_json(out / "scene.json", {
        "format": "gausslite-synthetic-scene/1",
        "generator_version": GENERATOR_VERSION,
        "seed": int(seed), "width": intr.width, "height": intr.height, "frames_per_agent": int(frames),
        "trajectory": trajectory,
        "agents": list(AGENTS), "depth_scale": DEPTH_SCALE, "jpeg_quality": JPEG_QUALITY,
        "num_objects": len(scene.objects),
        "objects": [{"id": o.id, "label": o.label} for o in scene.objects],
        "tasks": {t.id: t.text for t in scene.tasks},
        "roi_fraction_mean": roi_fraction,
        "roi_nonempty_frame_fraction": roi_nonempty,
    })
    secs = time.perf_counter() - t0
    log.info("wrote synthetic scene (seed %d, %dx%d, %d frames/agent) to %s in %.1f s",
             seed, intr.width, intr.height, frames, out, secs)
    return {
        "out_dir": str(out), "cam_params": str(out / "cam_params.json"), "objects": str(out / "objects.json"),
        "tasks": str(out / "tasks.json"), "scene_json": str(out / "scene.json"), "agents": agents_out,
        "tasks_text": {t.id: t.text for t in scene.tasks}, "roi_fraction": roi_fraction,
        "roi_nonempty": roi_nonempty, "num_objects": len(scene.objects), "seconds": secs,
    }


def agent_dirs(out_dir: Union[str, Path]) -> Sequence[Path]:
    """The per-agent sequence folders that :func:`make_scene` writes under ``out_dir``."""
    return [Path(out_dir) / a for a in AGENTS]
