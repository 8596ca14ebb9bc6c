"""Render the synthetic scene for both agents and write it in the Replica / NICE-SLAM layout.

Output of :func:`make_scene` (``DIR`` = ``out_dir``)::

    DIR/cam_params.json            {"camera": {"w", "h", "fx", "fy", "cx", "cy", "scale": 6553.5}}
    DIR/objects.json               gausslite-objects/1, up_axis "+z"
    DIR/tasks.json                 gausslite-tasks/1
    DIR/scene.json                 summary: seed, sizes, frames, generator version, ROI fractions (and, for the
                                   walk or with sensor noise, the frame rate, path lengths and sensor model)
    DIR/agent_a/traj.txt           one row-major 4x4 camera-to-world pose per line
    DIR/agent_a/results/frame000000.jpg   colour (JPEG quality 97)
    DIR/agent_a/results/depth000000.png   uint16 depth, metres = value / 6553.5
    DIR/agent_b/...                likewise

Everything written is a deterministic function of the arguments ``(seed, width, height, frames, trajectory,
sensor_noise, fps)``.
"""

from __future__ import annotations

import json
import logging
import os
import pickle
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable, Dict, Optional, Sequence, Union

import cv2
import numpy as np
from tqdm import tqdm

from gausslite.camera import Intrinsics, backproject
from gausslite.synthetic.raycast import render
from gausslite.synthetic.scene import GENERATOR_VERSION, build_default_scene
from gausslite.synthetic.sensor import (
    SensorErrorModel, exposure_track, render_with_errors, sensor_intrinsics, sensor_model,
)
from gausslite.synthetic.trajectories import AGENTS, WALK_FPS, make_trajectories

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


def _write_agent(out: Path, agent: str, poses: np.ndarray, scene, intr: Intrinsics, by_id: dict,
                 advance: Callable[[int], object], noise: Optional[SensorErrorModel],
                 rng: Optional[np.random.Generator], fps: float):
    """Render and write one agent's frames and ``traj.txt``, calling ``advance(1)`` after each frame; returns ``(roi
    fraction sum, frames with ROI)``, each task id -> float / int, over the written depth."""
    res_dir = out / agent / "results"
    res_dir.mkdir(parents=True, exist_ok=True)
    for stale in list(res_dir.glob("frame??????.jpg")) + list(res_dir.glob("depth??????.png")):
        stale.unlink()
    np.savetxt(out / agent / "traj.txt", poses.reshape(len(poses), 16), fmt="%.18e")
    if noise is not None:
        gain, offset = exposure_track(rng, len(poses), fps, noise)
    roi_sum = {t.id: 0.0 for t in scene.tasks}
    roi_hit = {t.id: 0 for t in scene.tasks}
    for i, c2w in enumerate(poses):
        if noise is None:
            r = render(scene, intr, c2w)
        else:
            r = render_with_errors(scene, intr, poses, i, fps, noise, rng, gain[i], float(offset[i]))
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
            roi_sum[t.id] += frac
            roi_hit[t.id] += int(frac > 0)
        advance(1)
    return roi_sum, roi_hit


#: pixels per robot (frames x width x height) from which :func:`make_scene` renders each robot in a process of its own
#: (the default sim's scene, 2 x 31 frames at 320x240 on 2 cores: 4.0 s against 5.9 s with a thread per robot, whose
#: NumPy work holds the GIL for much of a render); smaller scenes render in threads, cheaper than a process's start
PROCESS_PIXELS = 1_000_000


def _render_agent(job: tuple, advance: Callable[[int], object]) -> tuple:
    """Render and write one robot's frames (:func:`_write_agent`) from the arguments of :func:`make_scene`: the scene
    and trajectories are rebuilt from the seed, and the robot's noise stream is its own (seeded by the seed and the
    robot's index), so the files are the same in a thread or a process. ``advance(1)`` after each frame."""
    out, agent, seed, frames, trajectory, intr, sensor_noise, fps = job
    scene = build_default_scene(seed)
    noise = sensor_model(sensor_noise)
    by_id = {o["id"]: o for o in scene.objects_json()["objects"]}
    rng = np.random.default_rng([seed, AGENTS.index(agent), 1729]) if noise is not None else None
    poses = make_trajectories(frames, seed, trajectory, fps=fps)[agent]
    return _write_agent(Path(out), agent, poses, scene, intr, by_id, advance, noise, rng, fps)


def _render_in_processes(jobs: list, bar) -> list:
    """:func:`_render_agent` for each job in a Python process of its own (``python -m gausslite.synthetic.writer``,
    the job pickled on its stdin): a fresh interpreter, so the caller's threads, native thread pools and ``__main__``
    never reach it. Each process prints a line per frame (the bar advances) and then its result.

    Raises:
        RuntimeError: a process failed (its exit code and the end of its stderr).
    """
    procs = [subprocess.Popen([sys.executable, "-m", "gausslite.synthetic.writer"], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE) for _ in jobs]
    results: list = [None] * len(jobs)
    errors: list = [b""] * len(jobs)

    def follow(k: int) -> None:
        p = procs[k]
        p.stdin.write(pickle.dumps(jobs[k]))
        p.stdin.close()
        for line in p.stdout:
            if line.startswith(b"result "):
                results[k] = json.loads(line[7:])
            else:
                bar.update(1)
        errors[k] = p.stderr.read()
        p.wait()

    try:
        with ThreadPoolExecutor(max_workers=len(procs)) as pool:
            list(pool.map(follow, range(len(procs))))
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    for job, p, r, err in zip(jobs, procs, results, errors):
        if p.returncode != 0 or r is None:
            tail = err.decode(errors="replace").strip().splitlines()[-5:]
            raise RuntimeError(f"rendering {job[1]} failed (exit {p.returncode}): " + " | ".join(tail))
    return [tuple(r) for r in results]


def _worker_main() -> None:
    """A rendering process of :func:`_render_in_processes`: one job from stdin, a line per frame, then the result."""
    job = pickle.load(sys.stdin.buffer)

    def advance(_n: int) -> None:
        sys.stdout.write("frame\n")
        sys.stdout.flush()

    roi_sum, roi_hit = _render_agent(job, advance)
    sys.stdout.write("result " + json.dumps([roi_sum, roi_hit]) + "\n")
    sys.stdout.flush()


def _scene_json(seed: int, intr: Intrinsics, frames: int, trajectory: str, scene, roi_fraction: dict,
                roi_nonempty: dict, noise: Optional[SensorErrorModel], sensor_noise: str, fps: float,
                trajs: Dict[str, np.ndarray]) -> dict:
    """``scene.json``'s content; the walk and the sensor model add ``fps``, ``sensor_noise`` (with the model's
    parameters) and each agent's path length, the default scenes' content is unchanged."""
    doc = {
        "format": "gausslite-synthetic-scene/1",
        "generator_version": GENERATOR_VERSION,
        "seed": int(seed), "width": intr.width, "height": intr.height, "frames_per_agent": int(frames),
        "trajectory": trajectory,
        "agents": list(roi_fraction), "depth_scale": DEPTH_SCALE, "jpeg_quality": JPEG_QUALITY,
        "num_objects": len(scene.objects),
        "objects": [{"id": o.id, "label": o.label} for o in scene.objects],
        "tasks": {t.id: t.text for t in scene.tasks},
        "roi_fraction_mean": roi_fraction,
        "roi_nonempty_frame_fraction": roi_nonempty,
    }
    if trajectory in ("walk", "scan_walk") or noise is not None:
        lengths = {a: round(float(np.linalg.norm(np.diff(p[:, :3, 3], axis=0), axis=1).sum()), 4)
                   for a, p in trajs.items()}
        doc.update({"fps": float(fps), "path_length_m": lengths,
                    "mean_speed_m_s": {a: round(v * fps / max(int(frames) - 1, 1), 4) for a, v in lengths.items()},
                    "sensor_noise": sensor_noise, "sensor_model": noise.to_json() if noise is not None else None})
    return doc


def make_scene(out_dir: Union[str, Path], seed: int = 0, width: int = 320, height: int = 240,
               frames: int = 30, progress: bool = True, trajectory: str = "arcs", sensor_noise: str = "none",
               fps: float = WALK_FPS, agents: Sequence[str] = AGENTS) -> Dict:
    """Generate, render and write the default synthetic two-robot scene.

    Args:
        out_dir: output folder (created; previously written frames there are replaced).
        seed: scene / trajectory / sensor-noise seed; equal arguments give byte-identical files.
        width, height: image size in pixels (>= 16 x 12).
        frames: frames per agent (>= 2).
        progress: show a tqdm progress bar over the rendered frames.
        trajectory: ``"arcs"`` (the default two-robot arcs), ``"circle"`` (both robots once around
            the room: the long-mission scene, e.g. ``frames=600`` mapped with stride 2) or ``"walk"`` (a 7 m
            hand-held walk, two loops in front of the desk: :func:`gausslite.synthetic.make_trajectories`;
            ``frames=525`` at 30 fps walks at 0.40 m/s) or ``"scan_walk"`` (the same walk looking around as it goes,
            turning at TUM fr1/rpy's median rate of about 52 degrees/s).
        sensor_noise: ``"none"`` (exact renders, the default), ``"realistic"`` (Kinect-like depth noise and holes,
            motion blur, rolling shutter, exposure changes and colour noise: :mod:`gausslite.synthetic.sensor`) or
            ``"tum"`` (the Kinect v1 of TUM RGB-D fr1 as measured: its field of view, disparity-quantised and
            correlated depth noise, its holes, colour-depth misregistration and delay, and its exposure changes,
            blur and rolling shutter: :data:`gausslite.synthetic.sensor.TUM_FR1`).
        fps: frame rate of the sequence (frames per second): the walk's clock and the sensor model's (exposure and
            readout times). The Replica loader replays at 30 fps unless told otherwise (``fps=`` of
            :class:`gausslite.datasets.replica.ReplicaDataset`).
        agents: the robots whose frames are rendered and written (a subset of ``AGENTS``, in any order; the others'
            folders are not written). A single-robot benchmark renders half the frames with ``("agent_a",)``; the
            scene, its objects, tasks and each robot's trajectory are the same whichever robots are written.

    Returns:
        Summary dict: ``out_dir``, ``cam_params``, ``objects``, ``tasks``, ``scene_json`` (paths as
        str), ``agents`` (name -> ``{"dir", "traj", "frames"}``), ``tasks_text`` (task id -> text),
        ``roi_fraction`` (agent -> task id -> mean fraction of pixels in the task's ROI mask),
        ``roi_nonempty`` (agent -> task id -> fraction of frames whose ROI mask is non-empty),
        ``num_objects`` and ``seconds`` (wall time; the only non-deterministic entry, not written).

    Raises:
        ValueError: invalid size, frame count, trajectory, sensor noise name, frame rate or robot name (or none).
    """
    t0 = time.perf_counter()
    if int(frames) < 2:
        raise ValueError(f"frames must be >= 2, got {frames}")
    agents = tuple(dict.fromkeys(agents))
    if not agents or any(a not in AGENTS for a in agents):
        raise ValueError(f"agents must name one or more of {', '.join(AGENTS)}, got {list(agents)}")
    noise = sensor_model(sensor_noise)
    intr = default_intrinsics(width, height) if noise is None else sensor_intrinsics(noise, width, height)
    out = Path(out_dir)
    scene = build_default_scene(seed)
    trajs = make_trajectories(frames, seed, trajectory, fps=fps)
    out.mkdir(parents=True, exist_ok=True)
    objects_json = scene.objects_json()
    tasks_json = scene.tasks_json()

    _dump_json(out / "cam_params.json", {"camera": {
        "w": intr.width, "h": intr.height, "fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy,
        "scale": DEPTH_SCALE}})
    _dump_json(out / "objects.json", objects_json)
    _dump_json(out / "tasks.json", tasks_json)

    roi_sum, roi_hit, agents_out = {}, {}, {}
    bar = tqdm(total=len(agents) * int(frames), desc="make-scene", unit="frame", disable=not progress)
    jobs = [(str(out), agent, int(seed), int(frames), trajectory, intr, sensor_noise, float(fps)) for agent in agents]
    workers = min(len(agents), os.cpu_count() or 1)
    try:
        if workers > 1 and sys.executable and int(frames) * intr.width * intr.height >= PROCESS_PIXELS:
            results = _render_in_processes(jobs, bar)
        else:
            # one thread per robot for a small scene: a process's start-up would cost more than its render
            with ThreadPoolExecutor(max_workers=workers) as pool:
                results = list(pool.map(lambda job: _render_agent(job, bar.update), jobs))
        for agent, (roi_sum[agent], roi_hit[agent]) in zip(agents, results):
            agents_out[agent] = {"dir": str(out / agent), "traj": str(out / agent / "traj.txt"),
                                 "frames": int(frames)}
    finally:
        bar.close()

    roi_fraction = {a: {k: round(v / frames, 6) for k, v in d.items()} for a, d in roi_sum.items()}
    roi_nonempty = {a: {k: round(v / frames, 6) for k, v in d.items()} for a, d in roi_hit.items()}
    _dump_json(out / "scene.json", _scene_json(seed, intr, frames, trajectory, scene, roi_fraction, roi_nonempty,
                                               noise, sensor_noise, fps, trajs))
    secs = time.perf_counter() - t0
    log.info("wrote synthetic scene (seed %d, %dx%d, %d frames/agent, %s, sensor noise %s) to %s in %.1f s",
             seed, intr.width, intr.height, frames, trajectory, sensor_noise, out, secs)
    return {
        "out_dir": str(out), "cam_params": str(out / "cam_params.json"), "objects": str(out / "objects.json"),
        "tasks": str(out / "tasks.json"), "scene_json": str(out / "scene.json"), "agents": agents_out,
        "tasks_text": {t.id: t.text for t in scene.tasks}, "roi_fraction": roi_fraction,
        "roi_nonempty": roi_nonempty, "num_objects": len(scene.objects), "seconds": secs,
    }


def agent_dirs(out_dir: Union[str, Path]) -> Sequence[Path]:
    """The per-agent sequence folders that :func:`make_scene` writes under ``out_dir``."""
    return [Path(out_dir) / a for a in AGENTS]


if __name__ == "__main__":
    _worker_main()
