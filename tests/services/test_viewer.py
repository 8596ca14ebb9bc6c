"""Viewer and splat formats: map → splat arrays, ``.splat`` / ``.spz`` round trips, ``gausslite export``
and ``gausslite view``, the live fusion feed (in-process fusion server), and headless Chromium
screenshots of the viser page (see tests/_browser.py; artifacts in tests/artifacts/)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gausslite.camera import Intrinsics
from gausslite.datasets.base import Frame
from gausslite.viewer.export import (export_map, from_splat_bytes, load_map, read_splat, read_spz,
                                     write_map, write_splat, write_spz)
from gausslite.viewer.splats import covariances, kappa_colors, sigmoid, splat_arrays
from gausslite.wire.codec import GaussianArrays
from tests._waits import STARTUP_S

REPO = Path(__file__).resolve().parents[2]


def shell_map(n: int = 4000, seed: int = 0, radius: float = 1.0) -> GaussianArrays:
    """n Gaussians on a sphere shell (colour = direction), active on the upper half, κ in [0, 200)."""
    r = np.random.default_rng(seed)
    d = r.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return GaussianArrays(means=(d * radius).astype(np.float32), quats=r.normal(size=(n, 4)).astype(np.float32),
                          log_scales=np.log(r.uniform(0.02, 0.06, (n, 3))).astype(np.float32),
                          opacity_logits=r.uniform(1.0, 4.0, n).astype(np.float32),
                          colors=(0.5 + 0.5 * d).astype(np.float32), kappa=r.integers(0, 200, n),
                          active=d[:, 2] > 0)


# ---------------------------------------------------------------- conversion
def test_covariances_match_scipy_rotation():
    g = shell_map(500)
    cov = covariances(g.quats, g.log_scales)
    q = g.quats.astype(np.float64)
    rot = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()  # scipy: (x, y, z, w)
    s2 = np.exp(2 * g.log_scales.astype(np.float64))
    ref = rot @ (s2[:, :, None] * np.transpose(rot, (0, 2, 1)))
    np.testing.assert_allclose(cov, ref, rtol=1e-4, atol=1e-9)
    assert np.allclose(cov, np.transpose(cov, (0, 2, 1)))
    assert (np.linalg.eigvalsh(cov.astype(np.float64)) > 0).all()


def test_splat_arrays_modes_and_progress():
    g = shell_map(1000)
    calls = []
    s = splat_arrays(g, "rgb", chunk=300, progress=lambda d, t: calls.append((d, t)))
    assert calls == [(300, 1000), (600, 1000), (900, 1000), (1000, 1000)]
    assert s.centers.shape == (1000, 3) and s.covariances.shape == (1000, 3, 3)
    assert s.rgbs.dtype == np.float32 and s.opacities.shape == (1000, 1)
    np.testing.assert_allclose(s.opacities[:, 0], 1 / (1 + np.exp(-g.opacity_logits.astype(np.float64))), rtol=1e-6)
    np.testing.assert_allclose(s.rgbs, g.colors, atol=1e-7)
    k = splat_arrays(g, "kappa").rgbs
    assert not np.allclose(k, s.rgbs)
    lo, hi = np.argmin(g.kappa), np.argmax(g.kappa)
    np.testing.assert_allclose(k[hi], kappa_colors(np.array([1, 1]), 1)[0], atol=1e-6)  # top of the scale
    assert k[lo].sum() < k[hi].sum()  # viridis: dark purple → yellow
    roi = splat_arrays(g, "roi").rgbs
    a = g.active
    np.testing.assert_allclose(roi[a], 0.6 * g.colors[a] + 0.4 * np.float32([1.0, 0.1, 0.1]), atol=1e-6)  # red tint
    assert np.allclose(roi[~a, 0], roi[~a, 1]) and np.allclose(roi[~a, 1], roi[~a, 2])  # grey
    assert roi[~a].max() <= 0.5 + 1e-6  # dim
    with pytest.raises(ValueError, match="colour mode"):
        splat_arrays(g, "depth")
    bad = GaussianArrays(**{**{k: getattr(g, k) for k in GaussianArrays.FIELDS}, "means": g.means.copy()})
    bad.means[3, 1] = np.nan
    with pytest.raises(ValueError, match="1 Gaussian.*non-finite means"):
        splat_arrays(bad)


def test_sigmoid_is_stable():
    x = np.array([-1000, -20, 0, 20, 1000], np.float32)
    y = sigmoid(x)
    assert np.isfinite(y).all() and y[0] == 0 and y[2] == 0.5 and y[-1] == 1


# ---------------------------------------------------------------- formats
def _match(a: GaussianArrays, b: GaussianArrays, tol: float):
    """Pair rows of b with rows of a by nearest position (formats may reorder)."""
    from scipy.spatial import cKDTree

    d, idx = cKDTree(a.means).query(b.means)
    assert d.max() <= tol, d.max()
    assert len(set(idx.tolist())) == len(a)
    return idx


def test_splat_roundtrip(tmp_path):
    g = shell_map(3000, seed=1)
    size = write_splat(tmp_path / "m.splat", g)
    assert size == 32 * len(g) == (tmp_path / "m.splat").stat().st_size
    back = read_splat(tmp_path / "m.splat")
    assert len(back) == len(g)
    idx = _match(g, back, 0.0)  # float32 positions are exact
    np.testing.assert_array_equal(back.means, g.means[idx])
    np.testing.assert_allclose(back.log_scales, g.log_scales[idx], atol=1e-6)
    np.testing.assert_allclose(back.colors, g.colors[idx], atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(sigmoid(back.opacity_logits), sigmoid(g.opacity_logits[idx]), atol=0.5 / 255 + 1e-5)
    qa = g.quats[idx] / np.linalg.norm(g.quats[idx], axis=1, keepdims=True)
    dots = np.abs((back.quats * qa).sum(1))
    assert dots.min() > 0.995, dots.min()  # components quantised to 1/128
    # records are sorted by size × opacity, largest first (what web viewers expect)
    imp = np.exp(g.log_scales[idx].astype(np.float64).sum(1)) * sigmoid(g.opacity_logits[idx])
    assert (np.diff(imp) <= 0).all()
    with pytest.raises(ValueError, match="32-byte"):
        from_splat_bytes(b"\0" * 33)


def test_spz_roundtrip(tmp_path):
    g = shell_map(3000, seed=2)
    size = write_spz(tmp_path / "m.spz", g)
    assert 0 < size < 32 * len(g)  # compressed below .splat
    back = read_spz(tmp_path / "m.spz")
    assert len(back) == len(g)
    idx = _match(g, back, 2.0 ** -12)
    np.testing.assert_allclose(back.means, g.means[idx], atol=2.0 ** -12)
    np.testing.assert_allclose(back.log_scales, g.log_scales[idx], atol=1 / 16 + 1e-6)
    np.testing.assert_allclose(back.colors, g.colors[idx], atol=0.02)
    np.testing.assert_allclose(sigmoid(back.opacity_logits), sigmoid(g.opacity_logits[idx]), atol=0.01)
    qa = g.quats[idx] / np.linalg.norm(g.quats[idx], axis=1, keepdims=True)
    assert np.abs((back.quats * qa).sum(1)).min() > 0.999
    (tmp_path / "bad.spz").write_bytes(b"not an spz file")
    with pytest.raises(ValueError, match="SPZ"):
        read_spz(tmp_path / "bad.spz")


def test_ply_roundtrip_keeps_kappa_and_active(tmp_path):
    g = shell_map(500, seed=3)
    write_map(g, tmp_path / "m.ply")
    back = load_map(tmp_path / "m.ply")
    assert back.equals(g)
    with pytest.raises(ValueError, match="unsupported splat format"):
        export_map(tmp_path / "m.ply", tmp_path / "m.obj")
    with pytest.raises(FileNotFoundError):
        load_map(tmp_path / "missing.ply")


def _cli(*args, timeout=120, **kw):
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-m", "gausslite.cli", *args], capture_output=True, text=True,
                          timeout=timeout, env=env, **kw)


def test_cli_export(tmp_path):
    g = shell_map(800, seed=4)
    write_map(g, tmp_path / "m.ply")
    r = _cli("export", "map", str(tmp_path / "m.ply"), "--out", str(tmp_path / "m.splat"))
    assert r.returncode == 0, r.stderr
    assert "800 Gaussians" in r.stdout and (tmp_path / "m.splat").stat().st_size == 32 * 800
    r = _cli("export", "map", str(tmp_path / "m.splat"), "--out", str(tmp_path / "x.bin"), "--format", "spz")
    assert r.returncode == 0, r.stderr
    assert len(read_spz(tmp_path / "x.bin")) == 800
    r = _cli("export", "map", str(tmp_path / "nope.ply"), "--out", str(tmp_path / "o.splat"))
    assert r.returncode == 2 and "not found" in r.stderr


def test_cli_view_serves_page(tmp_path):
    from gausslite_services.sim import free_port

    write_map(shell_map(2000), tmp_path / "m.ply")
    port = free_port()
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "gausslite.cli", "view", str(tmp_path / "m.ply"), "--port",
                             str(port), "--timeout", "60"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env)
    try:
        lines = []
        for _ in range(40):  # viser prints a banner first
            lines.append(proc.stdout.readline())
            if lines[-1].startswith("showing") or not lines[-1]:
                break
        assert f"showing {tmp_path / 'm.ply'} (2,000 Gaussians) at http://127.0.0.1:{port}/" in lines[-1], \
            "".join(lines) + (proc.stderr.read() if proc.poll() is not None else "")
        # the URL was printed before the map was loaded
        assert any(line.startswith(f"serving http://127.0.0.1:{port}/ (loading ") for line in lines[:-1]), lines
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10) as r:
            assert r.status == 200 and b"<html" in r.read().lower()
    finally:
        proc.terminate()
        proc.wait(30)
    r = _cli("view", "--port", "0")
    assert r.returncode == 2 and "either a map file or --fusion" in r.stderr
    r = _cli("view", str(tmp_path / "missing.ply"), "--port", "0", "--timeout", "1")
    assert r.returncode == 2 and "not found" in r.stderr and "serving" not in r.stdout  # no page for no file
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 2\nend_header\n1 2\n")
    r = _cli("view", str(tmp_path / "bad.ply"), "--port", "0", "--timeout", "1")
    assert r.returncode == 2 and "bad.ply" in r.stderr and "error" in r.stderr, r.stderr


class PageClient:
    """A minimal viser page over the real websocket: connects with the server's protocol, sends the first
    camera message (which is when viser registers a client, as the browser's page does) and decodes
    every message the server sends (zstd-compressed msgpack windows) into ``self.messages``."""

    def __init__(self, port: int):
        import threading

        import msgspec
        import viser
        from websockets.sync.client import connect

        self._msgspec = msgspec
        self.messages: list = []
        self.ws = connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"], open_timeout=10)
        self.ws.send(msgspec.msgpack.encode({
            "type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0], "position": [0.0, 0.0, 3.0], "fov": 1.0,
            "near": 0.01, "far": 100.0, "image_height": 480, "image_width": 640, "look_at": [0.0, 0.0, 0.0],
            "up_direction": [0.0, 0.0, 1.0]}))
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        import zstandard

        dec = zstandard.ZstdDecompressor()
        try:
            for frame in self.ws:
                n, c = int.from_bytes(frame[:8], "little"), int.from_bytes(frame[8:16], "little")
                inner = self._msgspec.msgpack.decode(dec.decompress(frame[16:16 + c], max_output_size=n))
                self.messages.extend(inner["messages"])
        except Exception:  # closed
            pass

    def of_type(self, kind: str) -> list:
        return [m for m in list(self.messages) if m["type"] == kind]

    def notifications(self) -> list:
        """(title, body, loading) of every notification shown or updated on this page, in order."""
        return [(m["props"]["title"], m["props"]["body"], m["props"]["loading"]) for m in list(self.messages)
                if m["type"] in ("NotificationShowMessage", "NotificationUpdateMessage")]

    def gui_updates(self, uuid: str) -> list:
        """The property updates of GUI element ``uuid`` this page received, in order."""
        return [m["updates"] for m in list(self.messages) if m["type"] == "GuiUpdateMessage" and m["uuid"] == uuid]

    def wait_for(self, predicate, timeout_s: float = 10.0) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if predicate():
                return True
            time.sleep(0.02)
        return bool(predicate())

    def close(self) -> None:
        self.ws.close()


def test_load_progress_drives_page_progress_and_notifications():
    """LoadProgress on a real viser server: the progress bar handle goes 0 → 40 → 100 and hides; every
    page (connected before the load or during it) gets a "Loading …" notification that turns into
    "Loaded …"; both the server-side handles and the messages the pages receive say so."""
    from gausslite.viewer.app import LoadProgress, MapViewer

    viewer = MapViewer("127.0.0.1", 0)
    early = late = None
    try:
        early = PageClient(viewer.port)
        assert viewer.wait_for_client(10)
        bar = viewer.progress._impl.uuid
        assert viewer.progress.visible is False
        with LoadProgress(viewer, "sphere", 1000) as prog:
            assert viewer.progress.visible is True and viewer.progress.value == 0.0
            assert list(prog.notes) == list(viewer.server.get_clients())  # the page connected before the load
            note = next(iter(prog.notes.values()))
            assert (note.title, note.body, note.loading) == ("Loading sphere", "1,000 Gaussians", True)
            prog(400, 1000)
            assert viewer.progress.value == 40.0
            late = PageClient(viewer.port)  # a page opened while loading gets the notification too
            assert late.wait_for(lambda: len(prog.notes) == 2), prog.notes
            assert late.wait_for(lambda: ("Loading sphere", "1,000 Gaussians", True) in late.notifications())
            # it was sent the progress bar as it is now: visible at 40 %
            made = [m for m in late.of_type("GuiProgressBarMessage") if m["uuid"] == bar]
            assert made and made[-1]["props"]["visible"] and (
                [u["value"] for u in late.gui_updates(bar) if "value" in u] or [made[-1]["value"]])[-1] == 40.0
            time.sleep(0.12)  # past the 0.1 s GUI throttle
            prog(700, 1000)
            assert viewer.progress.value == 70.0
            prog(1000, 1000)  # the last step is never throttled
            assert viewer.progress.value == 100.0
        assert viewer.progress.visible is False and viewer.progress.value == 100.0
        assert prog.closed and viewer._loading is None
        for note in prog.notes.values():
            assert (note.title, note.loading, note.with_close_button, note.auto_close_seconds) == \
                ("Loaded sphere", False, True, 3.0)
        for page in (early, late):
            assert page.wait_for(lambda: page.notifications()[-1:] == [("Loaded sphere", "1,000 Gaussians", False)])
        # the page saw the bar move (viser sends only the latest of quick successive updates)
        values = [u["value"] for u in early.gui_updates(bar) if "value" in u]
        assert values == sorted(values) and values[-1] == 100.0 and 40.0 in values, values
        assert [u["visible"] for u in early.gui_updates(bar) if "visible" in u] == [True, False]
        # a page that connects after the load gets no stale "Loading" notification
        after = PageClient(viewer.port)
        assert after.wait_for(lambda: len(viewer.server.get_clients()) == 3)
        time.sleep(0.3)
        assert after.notifications() == [] and len(prog.notes) == 2
        after.close()
        # a failed load says so on the page instead of "Loaded"
        with pytest.raises(RuntimeError):
            with LoadProgress(viewer, "broken", 10):
                raise RuntimeError("bad bytes")
        assert early.wait_for(lambda: early.notifications()[-1:] == [("Failed to load broken", "bad bytes", False)])
        assert viewer.progress.visible is False
        # set_map drives the same progress and notification, then the splats reach the page
        n = viewer.set_map(shell_map(3000), label="shell")
        assert n == 3000
        assert early.wait_for(lambda: early.notifications()[-1:] == [("Loaded shell", "3,000 Gaussians", False)])
        assert early.wait_for(lambda: early.of_type("GaussianSplatsMessage"))
    finally:
        for page in (early, late):
            if page is not None:
                page.close()
        viewer.stop()


def _run_view_in_thread(args):
    """``gausslite view ARGS`` in-process on a thread; returns (thread, result dict with "rc")."""
    import threading

    from gausslite.cli import main

    result = {}
    t = threading.Thread(target=lambda: result.update(rc=main(["view", *args])), daemon=True)
    t.start()
    return t, result


def _held_conversion(real_splats, chunk: int, timeout: float = 20):
    """A stand-in for ``splat_arrays`` that converts in chunks of ``chunk`` Gaussians and holds after the
    first one until released: returns (function, event set when it holds, event that releases it)."""
    import threading

    converting, release = threading.Event(), threading.Event()

    def slow_splats(g, mode="rgb", progress=None):
        def prog(done, total):
            progress(done, total)
            if done < total and not converting.is_set():
                converting.set()
                assert release.wait(timeout), "test never released the conversion"
        return real_splats(g, mode, chunk=chunk, progress=prog)

    return slow_splats, converting, release


def test_cli_view_prints_url_before_loading_and_page_sees_progress(tmp_path, monkeypatch, capsys):
    """File mode serves the page and prints its URL first, then loads: a page opened while the file is
    still being read sees "reading …" and the progress bar, then the load notification and the map."""
    import threading

    import gausslite.viewer.app as app
    import gausslite.viewer.export as export
    from gausslite_services.sim import free_port

    write_map(shell_map(2500, seed=5), tmp_path / "m.ply")
    entered, release = threading.Event(), threading.Event()
    real_load = export.load_map

    def slow_load(path):  # a "large" file: reading takes until the test says so
        entered.set()
        assert release.wait(20), "test never released the loader"
        return real_load(path)

    viewers = []

    class SpyViewer(app.MapViewer):
        def __init__(self, *a, **kw):
            super().__init__(*a, **kw)
            viewers.append(self)

    # and converting it, too: stop after the first chunk
    slow_splats, converting, release_conv = _held_conversion(app.splat_arrays, chunk=1000)

    monkeypatch.setattr(export, "load_map", slow_load)
    monkeypatch.setattr(app, "splat_arrays", slow_splats)
    monkeypatch.setattr(app, "MapViewer", SpyViewer)
    port = free_port()
    t, result = _run_view_in_thread([str(tmp_path / "m.ply"), "--port", str(port), "--timeout", "0.5"])
    page = None
    try:
        assert entered.wait(20), "the map was never loaded"
        out = capsys.readouterr().out
        url = f"http://127.0.0.1:{port}/"
        assert f"serving {url} (loading {tmp_path / 'm.ply'}" in out, out
        assert "showing" not in out  # the URL is out while the map is still loading
        with urllib.request.urlopen(url, timeout=10) as r:  # the page is served meanwhile
            assert r.status == 200 and b"<html" in r.read().lower()
        page = PageClient(port)
        viewer = viewers[0]
        assert viewer.wait_for_client(10)
        info, bar = viewer.info._impl.uuid, viewer.progress._impl.uuid
        # the page learns that the file is being read: panel text and the visible progress bar
        def panel_text():
            made = [m["props"]["_markdown"] for m in page.of_type("GuiMarkdownMessage") if m["uuid"] == info]
            return (made + [u["_markdown"] for u in page.gui_updates(info) if "_markdown" in u])[-1:]

        assert page.wait_for(lambda: panel_text() and panel_text()[0].startswith("reading **m.ply** (")), \
            panel_text()
        made = [m for m in page.of_type("GuiProgressBarMessage") if m["uuid"] == bar]
        assert made and made[-1]["props"]["visible"] is True
        release.set()
        assert converting.wait(20)
        # mid-conversion: the page shows the "Loading" notification and the bar at 40 % (1,000 of 2,500)
        assert page.wait_for(lambda: page.notifications()[-1:] == [("Loading m.ply", "2,500 Gaussians", True)]), \
            page.notifications()
        assert page.wait_for(lambda: [u["value"] for u in page.gui_updates(bar) if "value" in u][-1:] == [40.0])
        assert "showing" not in capsys.readouterr().out
        release_conv.set()
        assert page.wait_for(lambda: page.notifications()[-1:] == [("Loaded m.ply", "2,500 Gaussians", False)])
        assert page.wait_for(lambda: page.of_type("GaussianSplatsMessage"))
        t.join(30)
        assert not t.is_alive() and result["rc"] == 0
        out = capsys.readouterr().out
        assert f"showing {tmp_path / 'm.ply'} (2,500 Gaussians) at {url}" in out, out
        assert viewer.n_displayed == 2500
    finally:
        release.set()
        release_conv.set()
        if page is not None:
            page.close()
        t.join(30)


# ---------------------------------------------------------------- live fusion feed
H, W = 24, 32
INTR = Intrinsics(30.0, 30.0, (W - 1) / 2, (H - 1) / 2, W, H)


def _kf(i: int, x: float) -> Frame:
    c2w = np.eye(4)
    c2w[:3, 3] = [x, -3.0 + 0.2 * i, 0.0]
    c2w[:3, :3] = Rotation.from_euler("x", -90, degrees=True).as_matrix()  # look along +y, z up
    return Frame(i, i / 30.0, np.full((H, W, 3), 60 + 20 * i, np.uint8), np.full((H, W), 2.0, np.float32), c2w, INTR)


@pytest.fixture()
def fusion_with_two_agents(tmp_path):
    from gausslite.config import FusionSettings
    from gausslite_services.common.server import ServerOptions
    from gausslite_services.fusion_server.client import FusionClient
    from gausslite_services.fusion_server.server import serve

    # the viewer follows the fused versions: no team map refined in a process of its own beside them
    srv = serve(ServerOptions(port=0, max_workers=8), FusionSettings(team_map={"enabled": False}),
                data_dir=str(tmp_path / "fusion"))
    fc = FusionClient(srv.address, timeout_s=20)
    fc.wait_ready(10)
    for j, agent in enumerate(("robot_a", "robot_b")):
        fc.open_session(agent, f"task {agent}", INTR)
        sub = shell_map(1500, seed=10 + j)
        sub = GaussianArrays(**{**{k: getattr(sub, k) for k in GaussianArrays.FIELDS},
                                "means": sub.means + np.float32([0.8 * (2 * j - 1), 0, 0])})
        fc.upload_subset(agent, 1, sub, full_map_gaussians=6000)
        fc.upload_keyframes(agent, [_kf(i, 0.8 * (2 * j - 1)) for i in range(4)])
    yield srv, fc
    fc.close()
    srv.stop(0)


def test_keyframe_poses_rpc(fusion_with_two_agents):
    import grpc

    _, fc = fusion_with_two_agents
    poses = fc.keyframe_poses()
    assert [(p["agent_id"], p["frame_id"]) for p in poses] == [(a, i) for a in ("robot_a", "robot_b") for i in range(4)]
    np.testing.assert_allclose(poses[5]["c2w"], _kf(1, 0.8).c2w, atol=1e-12)
    assert (poses[0]["fx"], poses[0]["width"], poses[0]["height"]) == (30.0, W, H)
    assert len(fc.keyframe_poses("robot_b")) == 4
    with pytest.raises(grpc.RpcError) as e:
        fc.keyframe_poses("ghost")
    assert e.value.code() == grpc.StatusCode.NOT_FOUND
    with pytest.raises(grpc.RpcError) as e:
        fc.keyframe_poses("bad id!")
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT


def test_fusion_feed_follows_versions(fusion_with_two_agents):
    from gausslite.viewer.app import MapViewer
    from gausslite_services.viewer.feed import FusionFeed

    srv, fc = fusion_with_two_agents
    viewer = MapViewer("127.0.0.1", 0)
    try:
        feed = FusionFeed(viewer, fc, poll_s=0.2)
        assert feed.poll_once() is False and feed.shown_version == 0  # nothing fused yet
        assert "robot_a" in viewer.panel.content and "(none yet)" in viewer.panel.content
        assert sorted(viewer._keyframes) == ["robot_a", "robot_b"]
        assert all(len(v) == 4 for v in viewer._keyframes.values())
        r1 = fc.fuse("concat")
        assert feed.poll_once() is True and feed.shown_version == r1.fused_version == 1
        assert viewer.n_displayed == r1.n_gaussians == 3000
        assert "25.0 %" in viewer.panel.content and "showing v1" in viewer.panel.content
        assert feed.poll_once() is False  # same version: not downloaded again
        viewer.roi_only.value = True  # GUI toggle → redraw with the active subset only
        n_active = int(fc.download_fused(1).active.sum())
        assert viewer.n_displayed == n_active < 3000
        viewer.roi_only.value = False
        r2 = fc.fuse("vote", voxel_size=0.05)
        feed.start()
        deadline = time.monotonic() + 20
        while feed.shown_version != r2.fused_version and time.monotonic() < deadline:
            time.sleep(0.05)
        feed.stop()
        assert feed.shown_version == 2 and viewer.n_displayed == r2.n_gaussians
        assert re.search(r"\| 2 \| vote \|", viewer.panel.content)
        srv.stop(0)  # server gone: the feed reports it and keeps going
        assert feed.poll_once() is False and "UNAVAILABLE" in feed.last_error
    finally:
        viewer.stop()


def test_cli_view_follows_fusion(fusion_with_two_agents):
    from gausslite_services.sim import free_port

    _, fc = fusion_with_two_agents
    r = fc.fuse("concat")
    port = free_port()
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "gausslite.cli", "view", "--fusion", fc.target, "--port", str(port),
                             "--poll", "0.3", "--timeout", "60"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True, env=env)
    try:
        seen = []
        deadline = time.monotonic() + STARTUP_S
        while time.monotonic() < deadline and proc.poll() is None:
            seen.append(proc.stderr.readline())
            if "showing fused version" in seen[-1]:
                break
        assert f"showing fused version 1 ({r.n_gaussians} Gaussians)" in seen[-1], "".join(seen)
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10) as page:
            assert page.status == 200
    finally:
        proc.terminate()
        proc.wait(30)


# ---------------------------------------------------------------- real browser
def test_browser_renders_splats(tmp_path):
    """Headless Chromium opens the viser page: the empty scene, then the map; ≥ 5 % of pixels change."""
    from tests._browser import changed_fraction, headless_chromium, hide_overlays, keep_artifact, require_chromium, \
        wait_for_change, wait_until_still
    from gausslite.viewer.app import MapViewer

    require_chromium()
    viewer = MapViewer("127.0.0.1", 0, up="+z")
    try:
        with headless_chromium() as driver:
            driver.get(viewer.url)
            assert viewer.wait_for_client(30), "the page never connected to the viser server"
            hide_overlays(driver)  # measure the 3D scene, not the GUI panel and its toasts
            empty = wait_until_still(driver)  # the empty scene as drawn
            n = viewer.set_map(shell_map(6000), label="sphere")
            assert n == 6000
            img, frac = wait_for_change(driver, empty, min_fraction=0.05)
            keep_artifact(empty, tmp_path, "viewer_empty.png")
            kept = keep_artifact(img, tmp_path, "viewer_splats.png")
            print(f"changed pixels: {100 * frac:.1f} %")
            assert frac >= 0.05, f"only {100 * frac:.2f} % of pixels changed; see {kept}"
            # colour toggle reaches the browser too: κ colouring repaints the splats
            viewer.color_mode.value = "kappa"
            img_k, frac_k = wait_for_change(driver, img, min_fraction=0.02)
            keep_artifact(img_k, tmp_path, "viewer_kappa.png")
            assert frac_k >= 0.02, f"κ colouring changed only {100 * frac_k:.2f} % of pixels"
            assert changed_fraction(img_k, empty) >= 0.05
    finally:
        viewer.stop()


def test_browser_follows_fusion_server(tmp_path, fusion_with_two_agents):
    """`view --fusion` path in the browser: fused splats plus both agents' trajectories and frusta."""
    from tests._browser import headless_chromium, hide_overlays, keep_artifact, require_chromium, wait_for_change, \
        wait_until_still
    from gausslite.viewer.app import MapViewer
    from gausslite_services.viewer.feed import FusionFeed

    require_chromium()
    _, fc = fusion_with_two_agents
    viewer = MapViewer("127.0.0.1", 0, up="+z")
    try:
        with headless_chromium() as driver:
            driver.get(viewer.url)
            assert viewer.wait_for_client(30)
            hide_overlays(driver)
            empty = wait_until_still(driver)  # the empty scene as drawn
            fc.fuse("vote", voxel_size=0.05)
            feed = FusionFeed(viewer, fc, poll_s=0.5)
            assert feed.poll_once() is True
            # the browser's camera looks at the fused map (regression: viser's position setter moves
            # look_at along, which once aimed the view away from the map)
            init = viewer.server.initial_camera
            for client in viewer.server.get_clients().values():
                np.testing.assert_allclose(client.camera.look_at, init.look_at, atol=1e-6)
                np.testing.assert_allclose(client.camera.position, init.position, atol=1e-6)
            img, frac = wait_for_change(driver, empty, min_fraction=0.05)
            kept = keep_artifact(img, tmp_path, "viewer_fusion.png")
            print(f"changed pixels: {100 * frac:.1f} %")
            assert frac >= 0.05, f"only {100 * frac:.2f} % of pixels changed; see {kept}"
    finally:
        viewer.stop()


def test_browser_opened_during_load_shows_progress(tmp_path, monkeypatch):
    """`gausslite view MAP` as a user sees it: open the printed URL in headless Chromium while the map
    is still loading; the page shows the "Loading" notification and the progress bar, then "Loaded"."""
    from tests._browser import headless_chromium, require_chromium
    from selenium.webdriver.common.by import By

    import gausslite.viewer.app as app
    from gausslite_services.sim import free_port

    require_chromium()
    write_map(shell_map(3000, seed=6), tmp_path / "m.ply")
    # hold the load after the first chunk (50 %)
    slow_splats, converting, release = _held_conversion(app.splat_arrays, chunk=1500, timeout=30)

    monkeypatch.setattr(app, "splat_arrays", slow_splats)
    port = free_port()
    t, result = _run_view_in_thread([str(tmp_path / "m.ply"), "--port", str(port), "--timeout", "1"])
    try:
        assert converting.wait(20)
        with headless_chromium() as driver:
            driver.get(f"http://127.0.0.1:{port}/")

            def page_has(xpath, timeout_s=30.0):
                deadline = time.monotonic() + timeout_s
                while time.monotonic() < deadline:
                    if driver.find_elements(By.XPATH, xpath):
                        return True
                    time.sleep(0.2)
                return False

            assert page_has("//*[contains(text(), 'Loading m.ply')]"), "no loading notification on the page"
            assert page_has("//*[contains(text(), '3,000 Gaussians')]")
            bars = driver.find_elements(By.XPATH, "//*[@role='progressbar']")
            assert bars and any(b.get_attribute("aria-valuenow") == "50" for b in bars), \
                [(b.get_attribute("aria-valuenow"), b.is_displayed()) for b in bars]
            release.set()
            assert page_has("//*[contains(text(), 'Loaded m.ply')]"), "the notification never said Loaded"
            t.join(30)
            assert result.get("rc") == 0
    finally:
        release.set()
        t.join(30)

