"""Smooth camera trajectories of the two robots (``agent_a``, ``agent_b``) in the default room."""

from __future__ import annotations

from typing import Dict

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
TRAJECTORIES = ("arcs", "circle")


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


def make_trajectories(n_frames: int, seed: int = 0, kind: str = "arcs") -> Dict[str, np.ndarray]:
    """Two smooth arcs around the desk, seen from the side opposite the door.

    ``agent_a`` sweeps the left-front quadrant at about 1.45 m height; ``agent_b`` sweeps the
    right-front quadrant in the opposite direction at about 1.25 m, with a different bob and
    look-at drift. Both keep the desk, the chair closest to it, the door and the trash can in view.
    The seed shifts the arcs' phases by a few degrees.

    ``kind="circle"`` instead sends both robots once around the desk on an ellipse through the
    room (a long mission that revisits every side; see :func:`_circle_trajectories`).

    Args:
        n_frames: frames per agent (>= 2).
        seed: integer seed.
        kind: ``"arcs"`` (default) or ``"circle"``.

    Returns:
        ``{"agent_a": (n_frames, 4, 4), "agent_b": (n_frames, 4, 4)}`` float64 c2w poses (metres).

    Raises:
        ValueError: ``n_frames < 2`` or an unknown ``kind``.
    """
    if int(n_frames) < 2:
        raise ValueError(f"need at least 2 frames per agent, got {n_frames}")
    if kind not in TRAJECTORIES:
        raise ValueError(f"unknown trajectory kind {kind!r}; expected one of {TRAJECTORIES}")
    rng = np.random.default_rng(int(seed) + 7777)
    ph = rng.uniform(-3.0, 3.0, size=2)
    if kind == "circle":
        return _circle_trajectories(n_frames, ph)
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
