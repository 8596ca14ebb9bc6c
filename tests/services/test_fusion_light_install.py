"""The fusion server on the light install (``pyproject.toml``'s core dependencies and the ``fusion`` extra, without
torch, Warp, onnxruntime or anything else only the ``mapper`` extra brings; ``docs/fusion-and-deploy.md``, "A light
fusion-server install").

A subprocess first installs an import hook that refuses every module of an installed distribution outside the light
set (the dependency closure of the core and ``fusion`` requirements, read from ``pyproject.toml``), then imports the
server, serves it in process and runs a robot's round trip: uploads, keyframes, ``Fuse`` vote and concat, download.
``Fuse(refine=true)`` and a ``for_agent`` ROI guard over ROI keyframes must end FAILED_PRECONDITION naming the
``mapper`` extra, the startup log and the metrics must say which fuse modes the server runs, and ``gausslite sim``
must name the extra it needs.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from importlib import metadata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
OWN = {"gausslite", "gausslite_rpc", "gausslite_services", "bench", "tests"}

#: first lines of a child process: refuse the top-level modules named by argv[1] (comma-separated), as if their
#: distributions were not installed
_HOOK = textwrap.dedent('''
    import sys
    BLOCKED = set(sys.argv[1].split(","))
    AT_START = set(sys.modules)  # the interpreter's start-up (site's .pth hooks), before the hook

    class LightInstall:
        """Refuses the modules of every distribution outside the light install, as if they were not installed."""

        def find_spec(self, name, path=None, target=None):
            if name.partition(".")[0] in BLOCKED:
                raise ModuleNotFoundError(f"No module named {name!r} (not in the light install)", name=name)
            return None

    sys.meta_path.insert(0, LightInstall())
''')

_CHILD = _HOOK + textwrap.dedent('''
    import io, json, logging, socket, tempfile, urllib.request
    import numpy as np

    log_lines = io.StringIO()
    logging.basicConfig(level=logging.INFO, stream=log_lines, format="%(name)s: %(message)s")

    from gausslite.camera import Intrinsics
    from gausslite.datasets.base import Frame
    from gausslite.fusion.vote import voxel_vote
    from gausslite.wire.codec import GaussianArrays, assemble, encode_subset
    from gausslite_services.common.errors import FailedPrecondition
    from gausslite_services.common.server import ServerOptions
    from gausslite_services.fusion_server.client import FusionClient
    from gausslite_services.fusion_server.server import serve

    H, W = 24, 32
    K = Intrinsics(30.0, 30.0, (W - 1) / 2, (H - 1) / 2, W, H)

    def subset(n, offset, seed):
        r = np.random.default_rng(seed)
        return GaussianArrays(means=r.uniform(0, 1, (n, 3)) + offset, quats=r.normal(size=(n, 4)),
                              log_scales=r.uniform(-5, -3, (n, 3)), opacity_logits=r.normal(size=n),
                              colors=r.uniform(0, 1, (n, 3)), kappa=r.integers(0, 100, n), active=r.random(n) < 0.5)

    def frame(i):
        rgb = np.random.default_rng(i).uniform(0, 255, (H, W, 3)).astype(np.uint8)
        return Frame(i, i / 30.0, rgb, np.full((H, W), 1.5, np.float32), np.eye(4), K)

    def refused(fn):
        try:
            fn()
        except FailedPrecondition as e:
            return e.details()
        return None

    with socket.socket() as s:  # a free loopback port for the metrics endpoint
        s.bind(("127.0.0.1", 0))
        metrics_port = s.getsockname()[1]
    out = {}
    srv = serve(ServerOptions(port=0, max_workers=8, metrics_port=metrics_port), data_dir=tempfile.mkdtemp())
    try:
        a, b = subset(600, 0.0, 1), subset(400, 0.5, 2)
        with FusionClient(f"127.0.0.1:{srv.port}", timeout_s=20) as c:
            c.wait_ready(10)
            c.open_session("robot-a", "find the cup", K)
            c.open_session("robot-b", "find the desk", K)
            out["complete"] = [c.upload_subset("robot-a", 1, a, full_map_gaussians=6000).complete,
                               c.upload_subset("robot-b", 1, b, full_map_gaussians=4000).complete]
            roi = np.zeros((H, W), bool)
            roi[5:15, 8:20] = True
            out["keyframes"] = c.upload_keyframes("robot-a", [frame(0), frame(1)], rois=[roi, roi])
            maps = {"robot-a": assemble(encode_subset(a, "robot-a", 1))[0],
                    "robot-b": assemble(encode_subset(b, "robot-b", 1))[0]}
            r = c.fuse("vote", voxel_size=0.1, contest_radius=0)
            expected, report = voxel_vote(maps, 0.1)
            out["vote"] = [r.n_gaussians, len(expected), bool(c.download_fused(r.fused_version).equals(expected)),
                           r.kept == dict(report.kept)]
            out["concat"] = c.fuse("concat").n_gaussians
            out["for_agent_without_roi"] = c.fuse("vote", for_agent="robot-b").n_gaussians
            out["refine"] = refused(lambda: c.fuse("vote", refine=True, refine_iters=2))
            out["for_agent_over_roi"] = refused(lambda: c.fuse("vote", for_agent="robot-a"))
        with urllib.request.urlopen(f"http://127.0.0.1:{metrics_port}/metrics", timeout=10) as resp:
            out["metrics"] = [l for l in resp.read().decode().splitlines()
                              if l.startswith("gausslite_fusion_fuse_mode_available{")]
    finally:
        srv.stop(0.5)
    from gausslite.cli import main
    out["sim_rc"] = main(["sim", "--out", tempfile.mkdtemp()])
    out["log"] = log_lines.getvalue()
    out["loaded_blocked"] = sorted({m.partition(".")[0] for m in set(sys.modules) - AT_START} & BLOCKED)
    print("RESULT " + json.dumps(out))
''')


def _pyproject() -> dict:
    try:
        import tomllib
    except ImportError:  # Python 3.10
        tomllib = pytest.importorskip("tomli")
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))


def _closure(requirements) -> set:
    """Canonical names of the installed distributions ``requirements`` pull in, dependencies followed recursively
    (markers evaluated here, extras followed); the project itself is named by ``pyproject.toml``, not followed."""
    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name

    seen, todo, out = set(), [Requirement(r) for r in requirements], set()
    while todo:
        req = todo.pop()
        name = canonicalize_name(req.name)
        key = (name, frozenset(req.extras))
        if key in seen or name == "gausslite":
            continue
        seen.add(key)
        try:
            dist = metadata.distribution(name)
        except metadata.PackageNotFoundError:
            continue
        out.add(name)
        for line in dist.requires or []:
            dep = Requirement(line)
            if dep.marker is None or any(dep.marker.evaluate({"extra": e}) for e in (sorted(req.extras) or [""])):
                todo.append(dep)
    return out


def light_install_blocks(more=()) -> tuple:
    """(modules to refuse, light distributions): the top-level modules installed here whose distributions all lie
    outside the light install (core + ``fusion`` extra, + the requirements ``more``), and that install's
    distributions."""
    from packaging.utils import canonicalize_name

    project = _pyproject()["project"]
    light = _closure(project["dependencies"] + project["optional-dependencies"]["fusion"] + list(more))
    blocked = sorted(mod for mod, dists in metadata.packages_distributions().items()
                     if mod.isidentifier() and mod not in OWN and mod not in sys.stdlib_module_names
                     and not any(canonicalize_name(d) in light | {"gausslite"} for d in dists))
    return blocked, light


def test_the_light_set_leaves_out_the_mapper_dependencies():
    blocked, light = light_install_blocks()
    for heavy in ("torch", "warp", "onnxruntime", "scipy", "matplotlib", "viser", "rosbags", "plyfile"):
        assert heavy in blocked, heavy
    for needed in ("numpy", "grpc", "google", "zstandard", "cv2", "yaml", "pydantic", "prometheus_client", "psycopg"):
        assert needed not in blocked, needed
    assert {"torch", "warp-lang", "onnxruntime"}.isdisjoint(light)


def test_fusion_server_serves_vote_and_refuses_refine_without_the_mapper_extra(tmp_path):
    blocked, _ = light_install_blocks()
    proc = subprocess.run([sys.executable, "-c", _CHILD, ",".join(blocked)], cwd=str(ROOT), capture_output=True,
                          text=True, timeout=240, env={**os.environ, "PYTHONPATH": str(ROOT), "TMPDIR": str(tmp_path)})
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    assert proc.returncode == 0 and lines, proc.stdout[-3000:] + proc.stderr[-3000:]
    out = json.loads(lines[-1][len("RESULT "):])
    assert out["loaded_blocked"] == []
    assert out["complete"] == [True, True] and out["keyframes"] == 2
    n, n_expected, same, kept_same = out["vote"]
    assert n == n_expected and 0 < n < 1000 and same and kept_same
    assert out["concat"] == 1000
    assert out["for_agent_without_roi"] >= 400  # robot-b's whole subset and the others' rows: no ROI views, no render
    for key in ("refine", "for_agent_over_roi"):
        assert out[key] is not None, f"{key} was not refused with FAILED_PRECONDITION"
        assert "'mapper' extra" in out[key] and "gausslite[mapper]" in out[key] and "torch" in out[key], out[key]
    assert "rejected Fuse from" in out["log"] and "FAILED_PRECONDITION: refine=true:" in out["log"]
    assert "fuse modes available: vote, concat; unavailable: for_agent (" in out["log"]
    assert "; refine (the joint refinement" in out["log"]
    assert sorted(out["metrics"]) == ['gausslite_fusion_fuse_mode_available{mode="concat"} 1.0',
                                      'gausslite_fusion_fuse_mode_available{mode="for_agent"} 0.0',
                                      'gausslite_fusion_fuse_mode_available{mode="refine"} 0.0',
                                      'gausslite_fusion_fuse_mode_available{mode="vote"} 1.0']
    assert out["sim_rc"] == 2
    assert "gausslite sim: error: this command needs" in proc.stderr and "'mapper' extra" in proc.stderr, proc.stderr[-2000:]


def test_the_full_install_runs_every_fuse_mode(tmp_path):
    """The same server on the full install (this environment) announces every mode."""
    from gausslite_services.common.server import ServerOptions
    from gausslite_services.fusion_server.server import serve

    srv = serve(ServerOptions(port=0, max_workers=4), data_dir=str(tmp_path / "data"))
    try:
        assert srv.servicer.fuse_modes() == {"vote": None, "concat": None, "for_agent": None, "refine": None}
        assert srv.servicer.describe_fuse_modes() == "fuse modes available: vote, concat, for_agent, refine"
    finally:
        srv.stop(0.5)


@pytest.mark.parametrize("feature, module", [("refine", "gausslite.fusion.refine"), ("roi_guard", "gausslite.sharing")])
def test_each_feature_names_the_modules_its_code_imports(feature, module):
    """With every other module of the feature's extra refused, the feature's code imports; refusing one of its own
    modules stops it (the list :data:`gausslite.core.extras.FEATURES` checks before a Fuse starts is complete)."""
    from gausslite.core.extras import EXTRA_MODULES, FEATURES

    f = FEATURES[feature]
    assert set(f.modules) <= set(EXTRA_MODULES[f.extra])
    # the light install plus the feature's distributions (with their own dependencies)
    others, _ = light_install_blocks(EXTRA_MODULES[f.extra][m] for m in f.modules)
    assert not set(f.modules) & set(others)

    def run(refuse):
        return subprocess.run([sys.executable, "-c", _HOOK + f"import {module}", ",".join(refuse)], cwd=str(ROOT),
                              capture_output=True, text=True, timeout=240, env={**os.environ, "PYTHONPATH": str(ROOT)})

    ok = run(others)
    assert ok.returncode == 0, ok.stderr[-2000:]
    stopped = run(others + [f.modules[0]])
    assert stopped.returncode != 0 and f"No module named '{f.modules[0]}" in stopped.stderr, stopped.stderr[-2000:]
