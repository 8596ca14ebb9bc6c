"""Camera trajectories of the two robots (``agent_a``, ``agent_b``) in the default room: smooth arcs, a circle
around the room, and a hand-held walk with loops."""

from __future__ import annotations

from typing import Dict, Optional

import numpy as np

#: Agent names, in output order.
AGENTS = ("agent_a", "agent_b")


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """Camera-to-world pose of a camera at ``eye`` looking at ``target``.

    Args:
        eye, target: (3,) world points (metres).
        up: (3,) world up direction; the image's y axis (down) points against it.

    Returns:
        (4, 4) float64 c2w with OpenCV camera axes (x right, y down, z forward).

    Raises:
        ValueError: ``eye == target`` or the viewing direction is parallel to ``up``.
    """
    eye = np.asarray(eye, dtype=np.float64)
    fwd = np.asarray(target, dtype=np.float64) - eye
    nf = np.linalg.norm(fwd)
    if nf < 1e-9:
        raise ValueError("look_at: eye and target coincide")
    fwd /= nf
    right = np.cross(fwd, up)
    nr = np.linalg.norm(right)
    if nr < 1e-6:
        raise ValueError("look_at: viewing direction parallel to up")
    right /= nr
    down = np.cross(fwd, right)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = right, down, fwd, eye
    return T


#: Trajectory kinds of :func:`make_trajectories`.
TRAJECTORIES = ("arcs", "circle", "walk", "scan_walk")
#: the walk's path length (metres) and the frame rate its timing assumes (frames per second; the Replica loader's
#: default clock, which replays the synthetic scene): ``frames=525`` walks it at 0.40 m/s
WALK_PATH_M = 7.0
WALK_FPS = 30.0
#: desk-top centre of the default scene (world, metres) and the desk's long axis, the walk's main view target
_DESK_TOP = np.array([-0.2, 0.55, 0.78])
_DESK_AXIS = np.array([np.cos(np.deg2rad(8.0)), np.sin(np.deg2rad(8.0)), 0.0])
#: the walk's stride (metres per step): the lateral sway repeats every two steps, the vertical bob every step
_STEP_M = 0.7


def _circle_trajectories(n_frames: int, ph: np.ndarray) -> Dict[str, np.ndarray]:
    """Both robots circle the desk once on an ellipse through the room (the long mission of ``bench.long_mission``).

    ``agent_a`` goes counter-clockwise at about 1.4 m height, ``agent_b`` clockwise at about 1.2 m,
    half a lap apart. Both look at the desk with a slow sideways sweep of the look-at point, so the
    walls, the door, the chairs and the shelves pass through the view on every lap.
    """
    s = np.linspace(0.0, 1.0, int(n_frames), endpoint=False)
    centre = np.array([-0.1, 0.4])
    semi = np.array([2.2, 1.45])
    desk = np.array([-0.2, 0.55, 0.7])
    out: Dict[str, np.ndarray] = {}
    for name, sign, start, h0, phase in (("agent_a", 1.0, 200.0, 1.40, ph[0]), ("agent_b", -1.0, 20.0, 1.20, ph[1])):
        ang = np.deg2rad(start + phase + sign * 360.0 * s)
        eye = np.stack([centre[0] + semi[0] * np.cos(ang), centre[1] + semi[1] * np.sin(ang),
                        h0 + 0.08 * np.sin(6 * np.pi * s)], axis=1)
        tangent = np.stack([-np.sin(ang), np.cos(ang), 0 * ang], axis=1) * sign
        sweep = 0.9 * np.sin(2 * np.pi * 3.0 * s)[:, None]
        tgt = desk[None, :] + sweep * tangent + np.stack([0 * s, 0 * s, 0.15 * np.cos(4 * np.pi * s)], axis=1)
        out[name] = np.stack([look_at(e, t) for e, t in zip(eye, tgt)])
    return out


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _walk_progress(n_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Arc-length fraction ``u`` (n,) in [0, 1] of each frame of a walk that starts and ends at rest (speed ramps
    up over the first 6 % of the time and down over the last 6 %), and the gait envelope (n,) in [0, 1] (0 at rest)."""
    tau = np.linspace(0.0, 1.0, int(n_frames))
    env = _smoothstep(tau / 0.06) * _smoothstep((1.0 - tau) / 0.06)
    dense = np.linspace(0.0, 1.0, 4001)
    speed = _smoothstep(dense / 0.06) * _smoothstep((1.0 - dense) / 0.06)
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]))])
    return np.interp(tau, dense, cum / cum[-1]), env


def _walk_centre_line(u: np.ndarray, sign: float, theta0: float) -> np.ndarray:
    """Points (n, 2) at arc-length fractions ``u`` of two laps of a loop in front of the desk, walked in direction
    ``sign`` from the angle ``theta0`` (rad) and scaled to :data:`WALK_PATH_M` (the sway adds under 1 %). The second
    lap is wider by up to 12 % (the loops differ), both return to the start."""
    th = np.linspace(0.0, 1.0, 8001)
    ang = theta0 + sign * 4.0 * np.pi * th
    grow = 1.0 + 0.12 * np.sin(np.pi * th) ** 2
    pts = np.stack([0.78 * grow * np.cos(ang), 0.36 * grow * np.sin(ang)], axis=1)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    scale = (WALK_PATH_M - 0.05) / cum[-1]
    th_u = np.interp(u, cum / cum[-1], th)
    ang = theta0 + sign * 4.0 * np.pi * th_u
    grow = 1.0 + 0.12 * np.sin(np.pi * th_u) ** 2
    return np.array([-0.15, -1.05]) + scale * np.stack([0.78 * grow * np.cos(ang), 0.36 * grow * np.sin(ang)], axis=1)


def _walk_targets(u: np.ndarray, glances: tuple, sweep: tuple) -> np.ndarray:
    """Look-at points (n, 3): the desk top, swept along the desk (lap 1: ``sweep[0]`` m at 3 sweeps per lap; lap 2:
    ``sweep[1]`` m at 2 per lap, 5 cm lower), with short glances ``(u centre, weight, (3,) point)`` elsewhere."""
    lap2 = _smoothstep((u - 0.45) / 0.1)[:, None]
    t1 = _DESK_TOP + (sweep[0] * np.sin(2 * np.pi * 6.0 * u))[:, None] * _DESK_AXIS
    t2 = _DESK_TOP + (sweep[1] * np.sin(2 * np.pi * 4.0 * u + 1.0))[:, None] * _DESK_AXIS - [0.0, 0.0, 0.05]
    tgt = (1.0 - lap2) * t1 + lap2 * t2
    for centre, weight, point in glances:
        w = (weight * np.exp(-0.5 * ((u - centre) / 0.03) ** 2))[:, None]
        tgt = (1.0 - w) * tgt + w * np.asarray(point, np.float64)
    return tgt


def _hand_jitter(rng: np.random.Generator, n_frames: int, fps: float, dist: np.ndarray, env: np.ndarray) -> np.ndarray:
    """Hand-held rotation jitter (n, 3) rad about the camera's x (pitch), y (yaw) and z (roll) axes: tremor (white
    noise low-passed with a 0.1 s Gaussian, RMS 0.8 / 1.0 / 0.6 degrees) plus the gait's pitch nod at the step
    frequency (0.5 degrees) and roll at half of it (0.7 degrees), the gait terms scaled by ``env``."""
    from scipy.ndimage import gaussian_filter1d  # noqa: PLC0415 - SciPy is not in the light install

    tremor = gaussian_filter1d(rng.standard_normal((int(n_frames), 3)), sigma=max(0.1 * fps, 0.5), axis=0, mode="wrap")
    tremor /= np.maximum(tremor.std(axis=0), 1e-12)
    tremor *= np.deg2rad([0.8, 1.0, 0.6])
    ph = rng.uniform(0.0, 2.0 * np.pi, size=2)
    gait = np.stack([np.deg2rad(0.5) * np.sin(2 * np.pi * dist / _STEP_M + ph[0]), 0.0 * dist,
                     np.deg2rad(0.7) * np.sin(np.pi * dist / _STEP_M + ph[1])], axis=1)
    return tremor + env[:, None] * gait


#: the look-around of ``kind="scan_walk"``: per camera axis (pitch, yaw, roll) the amplitude (degrees) and the
#: frequency (Hz) of its sweep, chosen so that the walk turns at TUM fr1/rpy's median rate (about 52 degrees/s)
SCAN_SWEEPS = ((12.0, 0.45), (18.0, 0.35), (12.0, 0.55))


def _scan(rng: np.random.Generator, n_frames: int, fps: float, env: np.ndarray) -> np.ndarray:
    """Look-around rotation (n, 3) rad about the camera's x, y and z axes: one sweep per axis of
    :data:`SCAN_SWEEPS`, each a sinusoid with a random phase whose frequency wanders by +-20 % (so the sweeps never
    lock into one pattern), scaled by the gait envelope ``env`` (the camera starts and ends at rest)."""
    t = np.arange(int(n_frames)) / fps
    out = np.zeros((int(n_frames), 3))
    for axis, (amp_deg, hz) in enumerate(SCAN_SWEEPS):
        wander = 1.0 + 0.2 * np.sin(2 * np.pi * t / 7.3 + rng.uniform(0.0, 2.0 * np.pi))
        phase = 2 * np.pi * np.cumsum(hz * wander) / fps + rng.uniform(0.0, 2.0 * np.pi)
        out[:, axis] = np.deg2rad(amp_deg) * np.sin(phase)
    return env[:, None] * out


def _walk_trajectories(n_frames: int, rng: np.random.Generator, fps: float,
                       scan: Optional[np.random.Generator] = None) -> Dict[str, np.ndarray]:
    """Both robots' hand-held walks (see :func:`make_trajectories`, ``kind="walk"``; with ``scan``, the generator of
    the look-around's phases, ``"scan_walk"``: the same walk, looking around)."""
    from scipy.spatial.transform import Rotation  # noqa: PLC0415 - SciPy is not in the light install

    u, env = _walk_progress(n_frames)
    dist = u * WALK_PATH_M
    out: Dict[str, np.ndarray] = {}
    specs = (("agent_a", 1.0, -90.0, (1.38, 0.07), ((0.30, 0.6, (0.9, 2.3, 0.7)), (0.78, 0.55, (-2.6, 1.3, 1.0))),
              (0.25, 0.45)),
             ("agent_b", -1.0, 90.0, (1.25, -0.06), ((0.22, 0.55, (2.2, 1.55, 0.6)), (0.70, 0.5, (1.3, 2.4, 1.1))),
              (0.35, 0.3)))
    for name, sign, start, (h0, dh), glances, sweep in specs:
        xy = _walk_centre_line(u, sign, np.deg2rad(start + rng.uniform(-10.0, 10.0)))
        tang = np.gradient(xy, axis=0)
        tang /= np.maximum(np.linalg.norm(tang, axis=1, keepdims=True), 1e-12)
        side = np.stack([-tang[:, 1], tang[:, 0]], axis=1)
        xy = xy + (env * 0.02 * np.sin(np.pi * dist / _STEP_M))[:, None] * side
        z = h0 + dh * np.cos(2 * np.pi * u) + env * 0.012 * np.sin(2 * np.pi * dist / _STEP_M)
        eye = np.concatenate([xy, z[:, None]], axis=1)
        base = np.stack([look_at(e, t) for e, t in zip(eye, _walk_targets(u, glances, sweep))])
        jit = Rotation.from_rotvec(_hand_jitter(rng, n_frames, fps, dist, env)).as_matrix()
        base[:, :3, :3] = base[:, :3, :3] @ jit
        if scan is not None:
            base[:, :3, :3] = base[:, :3, :3] @ Rotation.from_rotvec(_scan(scan, n_frames, fps, env)).as_matrix()
        out[name] = base
    return out


def make_trajectories(n_frames: int, seed: int = 0, kind: str = "arcs", fps: float = WALK_FPS) -> Dict[str, np.ndarray]:
    """Two smooth arcs around the desk, seen from the side opposite the door.

    ``agent_a`` sweeps the left-front quadrant at about 1.45 m height; ``agent_b`` sweeps the
    right-front quadrant in the opposite direction at about 1.25 m, with a different bob and
    look-at drift. Both keep the desk, the chair closest to it, the door and the trash can in view.
    The seed shifts the arcs' phases by a few degrees.

    ``kind="circle"`` instead sends both robots once around the desk on an ellipse through the
    room (a long mission that revisits every side; see :func:`_circle_trajectories`).

    ``kind="walk"``: a hand-held walk of :data:`WALK_PATH_M` (7 m) per robot: two laps of a loop in the open
    floor in front of the desk (about 1.6 m x 0.8 m, the second lap up to 12 % wider and about 0.14 m lower), starting
    and stopping at rest at the same place; ``agent_a`` walks counter-clockwise from the far side at 1.31-1.45 m,
    ``agent_b`` clockwise from the desk side at 1.19-1.31 m. Gait: 0.7 m steps, +-2 cm lateral sway, +-1.2 cm
    vertical bob. The camera looks at the desk top most of the time, swept along the desk (a different sweep on each
    lap, so the two laps see the task region with different headings), with two short glances per robot at the
    door, the shelf or the far chair, plus hand-held rotation jitter (about 1 degree RMS tremor and the gait's nod and
    roll; :func:`_hand_jitter`). Its timing assumes ``fps`` frames per second: the mean speed is
    ``7 m * fps / n_frames`` (0.40 m/s for 525 frames at 30 fps).

    ``kind="scan_walk"``: the same walk (the same positions for a seed), looking around as it goes: a sweep about
    each camera axis (:data:`SCAN_SWEEPS`, random phases) turns it at about TUM fr1/rpy's median rate, 52 degrees/s
    at 30 fps (the walk: 17), so that the sensor effects that grow with the motion act as hard as on TUM.

    Args:
        n_frames: frames per agent (>= 2).
        seed: integer seed.
        kind: ``"arcs"`` (default), ``"circle"``, ``"walk"`` or ``"scan_walk"``.
        fps: frames per second of the walk's clock (its jitter's time scale); the other kinds ignore it.

    Returns:
        ``{"agent_a": (n_frames, 4, 4), "agent_b": (n_frames, 4, 4)}`` float64 c2w poses (metres).

    Raises:
        ValueError: ``n_frames < 2``, an unknown ``kind`` or ``fps <= 0``.
    """
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    if int(n_frames) < 2:
        raise ValueError(f"need at least 2 frames per agent, got {n_frames}")
    if kind not in TRAJECTORIES:
        raise ValueError(f"unknown trajectory kind {kind!r}; expected one of {TRAJECTORIES}")
    rng = np.random.default_rng(int(seed) + 7777)
    ph = rng.uniform(-3.0, 3.0, size=2)
    if kind == "circle":
        return _circle_trajectories(n_frames, ph)
    if kind in ("walk", "scan_walk"):
        scan = np.random.default_rng(int(seed) + 8888) if kind == "scan_walk" else None
        return _walk_trajectories(n_frames, rng, float(fps), scan)
    s = np.linspace(0.0, 1.0, int(n_frames))
    centre = np.array([0.25, 1.0, 0.0])
    out: Dict[str, np.ndarray] = {}

    # agent_a: left-front arc, moving counter-clockwise
    ang = np.deg2rad(205.0 + ph[0] + 45.0 * s)
    rad = 2.55 + 0.15 * np.sin(2 * np.pi * s)
    h = 1.45 + 0.12 * np.sin(np.pi * s * 1.5)
    eye = np.stack([centre[0] + rad * np.cos(ang), centre[1] + rad * np.sin(ang), h], axis=1)
    tgt = np.stack([0.35 + 0.25 * np.sin(np.pi * s), 1.05 + 0.15 * np.cos(np.pi * s), 0.55 + 0.1 * s], axis=1)
    out["agent_a"] = np.stack([look_at(e, t) for e, t in zip(eye, tgt)])

    # agent_b: right-front arc, moving clockwise, lower
    ang = np.deg2rad(335.0 + ph[1] - 45.0 * s)
    rad = 2.35 - 0.12 * np.sin(np.pi * s)
    h = 1.25 + 0.1 * np.cos(2 * np.pi * s)
    eye = np.stack([centre[0] + rad * np.cos(ang), centre[1] + rad * np.sin(ang), h], axis=1)
    tgt = np.stack([0.1 - 0.2 * s, 1.15 + 0.1 * np.sin(2 * np.pi * s), 0.6 - 0.05 * np.cos(np.pi * s)], axis=1)
    out["agent_b"] = np.stack([look_at(e, t) for e, t in zip(eye, tgt)])
    return out
