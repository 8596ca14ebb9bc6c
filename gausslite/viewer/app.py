"""Browser viewer of Gaussian maps with viser (https://viser.studio): splats, keyframe trajectories,
camera frusta and a GUI panel.

:class:`MapViewer` is a thin presentation layer: it converts maps with
:func:`gausslite.viewer.splats.splat_arrays` and draws what it is handed. It knows nothing of gRPC;
the live fusion feed (``services/viewer``) polls the fusion server and calls :meth:`MapViewer.set_map`,
:meth:`MapViewer.set_keyframes` and :meth:`MapViewer.set_panel`.

Frames: the world frame of the map (metres). Keyframe poses are camera-to-world 4×4 matrices with
OpenCV camera axes (x right, y down, z forward), which is also viser's camera-frustum convention.
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Sequence

import numpy as np
from tqdm import tqdm

from gausslite.core.arrays import GaussianArrays
from gausslite.viewer.splats import COLOR_MODES, scene_bounds, splat_arrays

log = logging.getLogger(__name__)

#: Colours of agents' trajectories and frusta (RGB 0..255), cycled by agent order.
AGENT_COLORS = [(230, 80, 40), (40, 120, 230), (40, 170, 80), (200, 60, 200), (230, 170, 20), (20, 180, 190)]

#: Axis names accepted as ``up`` direction.
UP_AXES = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0), "+z": (0, 0, 1), "-z": (0, 0, -1)}


@dataclass
class KeyframePose:
    """A keyframe camera for display.

    Attributes:
        c2w: (4, 4) float64 camera-to-world pose, OpenCV camera axes, metres.
        fx, fy: focal lengths in pixels; width, height: image size in pixels.
        frame_id: the agent's frame id (ordering of the trajectory).
    """

    c2w: np.ndarray
    fx: float
    fy: float
    width: int
    height: int
    frame_id: int = 0


def rotmat_to_wxyz(r: np.ndarray) -> np.ndarray:
    """(3, 3) rotation matrix → unit quaternion (w, x, y, z), w >= 0 (Shepperd's method)."""
    m = np.asarray(r, np.float64)
    t = np.trace(m)
    if t > 0:
        s = 2.0 * np.sqrt(1.0 + t)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(max(1e-12, 1.0 + m[i, i] - m[j, j] - m[k, k]))
        q = [0.0, 0.0, 0.0, 0.0]
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


class LoadProgress:
    """Progress of a map load, shown on the console (tqdm) and in the browser (GUI progress bar and a
    notification on every client: those connected when the load starts and those that connect while
    it runs, e.g. a page opened from the URL ``gausslite view`` prints before it loads). Use as
    ``with LoadProgress(viewer, "fused v3", n) as p: p(done, total)``.

    Attributes:
        notes: client id → that client's viser ``NotificationHandle`` ("Loading …", then "Loaded …").
        closed: True once the ``with`` block has exited.
    """

    def __init__(self, viewer: "MapViewer", what: str, total: int):
        self.viewer, self.what, self.total = viewer, what, max(int(total), 0)
        self.bar = tqdm(total=self.total, desc=f"loading {what}", unit="G", unit_scale=True, leave=False)
        self._last = 0.0
        self._lock = threading.Lock()
        self.notes: Dict[int, object] = {}
        self.closed = False
        viewer.progress.visible = True
        viewer.progress.value = 0.0
        # Register first, then notify the clients connected now: viser adds a client to get_clients()
        # before it runs the connect callbacks, so each client is caught here or by
        # MapViewer._on_client_connect (or both: add_client is idempotent per client).
        viewer._loading = self
        for client in list(viewer.server.get_clients().values()):
            self.add_client(client)

    def add_client(self, client) -> None:
        """Show the "Loading …" notification on ``client`` (once per client, only while loading)."""
        with self._lock:
            if self.closed or client.client_id in self.notes:
                return
            try:
                self.notes[client.client_id] = client.add_notification(
                    f"Loading {self.what}", f"{self.total:,} Gaussians", loading=True, with_close_button=False)
            except Exception:  # a client that disconnects meanwhile
                pass

    def __call__(self, done: int, total: int) -> None:
        self.bar.update(done - self.bar.n)
        now = time.monotonic()
        if now - self._last > 0.1 or done >= total:
            self._last = now
            self.viewer.progress.value = 100.0 * done / total if total else 100.0

    def __enter__(self) -> "LoadProgress":
        return self

    def __exit__(self, *exc) -> None:
        self.bar.close()
        with self._lock:
            self.closed = True
            notes = list(self.notes.values())
        if self.viewer._loading is self:
            self.viewer._loading = None
        self.viewer.progress.value = 100.0
        self.viewer.progress.visible = False
        failed = exc and exc[0] is not None
        for note in notes:
            try:
                note.title = f"{'Failed to load' if failed else 'Loaded'} {self.what}"
                note.body = str(exc[1]) if failed else f"{self.total:,} Gaussians"
                note.loading = False
                note.with_close_button = True
                note.auto_close_seconds = None if failed else 3.0
            except Exception:
                pass


class MapViewer:
    """A viser server showing one Gaussian map plus agents' keyframe trajectories and frusta.

    Args:
        host: bind address (``127.0.0.1`` loopback; ``0.0.0.0`` to share on the network).
        port: HTTP/websocket port (0 → a free port; see :attr:`port`).
        up: world up axis for the initial camera, one of :data:`UP_AXES` (``"+z"`` for the synthetic
            scene and ROS REP 103 worlds), or ``"auto"`` (from the keyframes' camera axes when known).
        title: text at the top of the GUI panel.
    Raises:
        ValueError: unknown ``up``. OSError: the port cannot be bound.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 8080, *, up: str = "+z", title: str = "GaussLite"):
        # lazy: heavy optional dependency, loaded only on this path
        import viser

        if up != "auto" and up not in UP_AXES:
            raise ValueError(f"up must be 'auto' or one of {sorted(UP_AXES)}, got {up!r}")
        if port == 0:
            port = _free_port(host)
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.up = up
        self._lock = threading.RLock()
        self._map: Optional[GaussianArrays] = None
        self._map_label = ""
        self._keyframes: Dict[str, List[KeyframePose]] = {}
        self._camera_set = False
        self._loading: Optional[LoadProgress] = None  # the load in progress (late clients get its notification)
        self.n_displayed = 0

        gui = self.server.gui
        gui.add_markdown(f"**{title}**")
        self.info = gui.add_markdown("no map loaded")
        self.progress = gui.add_progress_bar(0.0, visible=False, animated=True)
        with gui.add_folder("Display"):
            self.color_mode = gui.add_dropdown("Colour", COLOR_MODES, initial_value="rgb")
            self.roi_only = gui.add_checkbox("ROI (active) only", initial_value=False)
            self.show_traj = gui.add_checkbox("Trajectories", initial_value=True)
            self.show_frusta = gui.add_checkbox("Frusta", initial_value=True)
            self.frustum_scale = gui.add_slider("Frustum size (m)", 0.02, 1.0, 0.01, 0.15)
        self.panel = gui.add_markdown("")
        self.color_mode.on_update(lambda _: self._redraw_map())
        self.roi_only.on_update(lambda _: self._redraw_map())
        self.show_traj.on_update(lambda _: self._redraw_keyframes())
        self.show_frusta.on_update(lambda _: self._redraw_keyframes())
        self.frustum_scale.on_update(lambda _: self._redraw_keyframes())
        self.server.on_client_connect(self._on_client_connect)

    def _on_client_connect(self, client) -> None:
        loading = self._loading
        if loading is not None:
            loading.add_client(client)

    # ------------------------------------------------------------------ properties
    @property
    def port(self) -> int:
        """The bound port."""
        return int(self.server.get_port())

    @property
    def url(self) -> str:
        """``http://host:port/`` of the page."""
        host = self.server.get_host()
        return f"http://{'127.0.0.1' if host in ('0.0.0.0', '') else host}:{self.port}/"

    # ------------------------------------------------------------------ map
    def show_reading(self, label: str, nbytes: Optional[int] = None) -> None:
        """Tell the page a map file is being read (before :meth:`set_map` can show progress): the panel
        says so and the (animated) progress bar appears at 0 %."""
        size = f" ({nbytes / 1e6:,.1f} MB)" if nbytes is not None else ""
        self.info.content = f"reading **{label}**{size} …"
        self.progress.value = 0.0
        self.progress.visible = True

    def set_map(self, gaussians, label: str = "map") -> int:
        """Show ``gaussians`` (replacing the previous map) with the current colour/ROI settings.

        Args:
            gaussians: GaussianArrays, GaussianMap or mapping of arrays.
            label: shown in the panel and the progress notification (e.g. ``"fused v3"``).
        Returns:
            int: splats displayed.
        Raises:
            ValueError: non-finite parameters (see :func:`splat_arrays`).
        """
        with self._lock:
            self._map = GaussianArrays.from_any(gaussians)
            self._map_label = label
            return self._redraw_map()

    def _redraw_map(self) -> int:
        with self._lock:
            g = self._map
            if g is None:
                return 0
            if self.roi_only.value:
                g = g.take(g.active)
            with LoadProgress(self, self._map_label, len(g)) as prog:
                splats = splat_arrays(g, self.color_mode.value, progress=prog)
                if len(splats):
                    self.server.scene.add_gaussian_splats("/map", centers=splats.centers,
                                                          covariances=splats.covariances, rgbs=splats.rgbs,
                                                          opacities=splats.opacities)
                else:
                    self.server.scene.remove_by_name("/map")
            self.n_displayed = len(splats)
            full = self._map
            self.info.content = (f"**{self._map_label}**: {len(full):,} Gaussians, {int(full.active.sum()):,} "
                                 f"active (ROI), κ max {int(full.kappa.max()) if len(full) else 0}; "
                                 f"showing {self.n_displayed:,}")
            if not self._camera_set and len(splats):
                self._set_initial_camera(splats.centers)
            return self.n_displayed

    def _up_vector(self) -> np.ndarray:
        if self.up != "auto":
            return np.asarray(UP_AXES[self.up], np.float64)
        downs = [kf.c2w[:3, 1] for kfs in self._keyframes.values() for kf in kfs]
        if downs:
            v = -np.mean(downs, axis=0)
            if np.linalg.norm(v) > 1e-6:
                return v / np.linalg.norm(v)
        return np.asarray(UP_AXES["+z"], np.float64)

    def _set_initial_camera(self, centers: np.ndarray) -> None:
        """Look at the map's robust centre: from behind the keyframe cameras (their mean centre moved
        back along their mean viewing direction and up) when there are keyframes, else from the side."""
        kf_pos = np.array([kf.c2w[:3, 3] for kfs in self._keyframes.values() for kf in kfs]).reshape(-1, 3)
        centre, radius = scene_bounds(np.concatenate([centers, kf_pos]) if len(kf_pos) else centers)
        up = self._up_vector()
        if len(kf_pos):
            fwd = np.mean([kf.c2w[:3, 2] for kfs in self._keyframes.values() for kf in kfs], axis=0)
            fwd = fwd - up * float(fwd @ up)
            if np.linalg.norm(fwd) < 1e-6:
                fwd = centre - kf_pos.mean(axis=0)
            fwd /= max(np.linalg.norm(fwd), 1e-9)
            eye = kf_pos.mean(axis=0) - 0.6 * radius * fwd + 0.6 * radius * up
        else:
            side = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
            side /= np.linalg.norm(side)
            eye = centre + radius * (1.6 * side + 0.9 * up)
        cam = self.server.initial_camera
        cam.up = tuple(float(x) for x in up)
        cam.look_at = tuple(float(x) for x in centre)
        cam.position = tuple(float(x) for x in eye)
        for client in self.server.get_clients().values():
            # viser's position setter translates look_at along with the camera, so position goes first
            # and look_at after it; the other order aimed the view away from the map whenever the
            # client's camera was not already at `cam.position`.
            client.camera.up_direction = cam.up
            client.camera.position = cam.position
            client.camera.look_at = cam.look_at
        self._camera_set = True

    # ------------------------------------------------------------------ keyframes
    def set_keyframes(self, keyframes: Dict[str, Sequence[KeyframePose]]) -> None:
        """Show each agent's keyframe trajectory (a polyline through the camera centres in frame order)
        and a frustum per keyframe, one colour per agent; replaces what was shown before."""
        with self._lock:
            self._keyframes = {a: sorted(kfs, key=lambda k: k.frame_id) for a, kfs in keyframes.items()}
            self._redraw_keyframes()

    def _redraw_keyframes(self) -> None:
        with self._lock:
            scene = self.server.scene
            scene.remove_by_name("/agents")
            for i, (agent, kfs) in enumerate(sorted(self._keyframes.items())):
                color = AGENT_COLORS[i % len(AGENT_COLORS)]
                base = f"/agents/{_node_name(agent)}"
                pts = np.array([kf.c2w[:3, 3] for kf in kfs], np.float32)
                if self.show_traj.value and len(pts) >= 2:
                    seg = np.stack([pts[:-1], pts[1:]], axis=1)
                    scene.add_line_segments(f"{base}/trajectory", seg, color, thickness=3.0,
                                            thickness_units="screen")
                if self.show_frusta.value:
                    for kf in kfs:
                        fov = 2.0 * np.arctan2(kf.height / 2.0, kf.fy)
                        scene.add_camera_frustum(f"{base}/kf_{kf.frame_id}", fov=float(fov),
                                                 aspect=float(kf.width) / float(kf.height),
                                                 scale=float(self.frustum_scale.value), color=color,
                                                 thickness=2.0, thickness_units="screen",
                                                 wxyz=rotmat_to_wxyz(kf.c2w[:3, :3]),
                                                 position=np.asarray(kf.c2w[:3, 3], np.float64))

    # ------------------------------------------------------------------ panel
    def set_panel(self, markdown: str) -> None:
        """Replace the status panel (Markdown, e.g. a table of agents, shares, bytes and versions)."""
        self.panel.content = markdown

    def wait_for_client(self, timeout_s: float) -> bool:
        """Wait until a browser is connected (True) or ``timeout_s`` passes (False)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.server.get_clients():
                return True
            time.sleep(0.05)
        return False

    def stop(self) -> None:
        """Stop the server."""
        self.server.stop()


def _node_name(text: str) -> str:
    return "".join(c if c.isalnum() or c in "_-." else "_" for c in text) or "_"


def _free_port(host: str) -> int:
    with socket.socket() as s:
        s.bind((host if host not in ("", "0.0.0.0") else "127.0.0.1", 0))
        return int(s.getsockname()[1])


def serve_forever(stop: Optional[Callable[[], bool]] = None, poll_s: float = 0.5) -> None:
    """Block until KeyboardInterrupt (or ``stop()`` returns True)."""
    try:
        while not (stop and stop()):
            time.sleep(poll_s)
    except KeyboardInterrupt:
        pass


__all__ = ["MapViewer", "KeyframePose", "LoadProgress", "rotmat_to_wxyz", "AGENT_COLORS", "UP_AXES",
           "serve_forever"]
