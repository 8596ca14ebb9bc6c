"""The team map the fusion server keeps refined in the background (fusion.team_map): made once subsets and keyframes
are in, served at once by Fuse(team_map) with its version, age and whether it is current, re-made when a subset
changes; uploads, downloads and other Fuse calls go on while it refines (in a process of its own), and a read during
a refinement gets the last complete version; a stopping server kills the refinement's process."""

from __future__ import annotations

import os
import time

import grpc
import numpy as np
import pytest

from gausslite.config import FusionSettings
from tests._waits import STARTUP_S, WORK_S
from tests.services.test_fusion_server import INTR, frame, rand_subset, start

from gausslite_services.fusion_server.client import FusionClient

pytestmark = pytest.mark.integration


def _plane_subset(seed: int, off: float):
    g = rand_subset(300, 0.0, seed)
    g.means[:, 0] = g.means[:, 0] * 0.8 + off
    g.means[:, 1] = g.means[:, 1] * 0.6 - 0.3
    g.means[:, 2] = 1.5
    return g


def _wait(pred, timeout_s=60.0):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        out = pred()
        if out:
            return out
        time.sleep(0.05)
    raise AssertionError("timed out")


def _served(c):
    try:
        return c.fuse(team_map=True)
    except grpc.RpcError as e:
        assert e.code() == grpc.StatusCode.NOT_FOUND, e
        return None


def _config(**team_map):
    return FusionSettings(team_map={"enabled": True, "settle_s": 0.05, "min_interval_s": 0.0, "refine_iters": 30,
                                    **team_map}, refine_validation={"per_view_iters": 0})


def _fill(c, agents=("r1", "r2")):
    for i, a in enumerate(agents):
        c.open_session(a, "find the cup", INTR)
        assert c.upload_subset(a, 1, _plane_subset(3 + i, -0.3 + 0.3 * i), full_map_gaussians=3000).complete
        c.upload_keyframes(a, [frame(10 * i + k, 0.05 * k) for k in range(3)])


def test_the_team_map_is_refined_in_the_background_and_served_with_its_version_and_age(tmp_path):
    srv = start(tmp_path, config=_config())
    try:
        with FusionClient(f"127.0.0.1:{srv.port}", timeout_s=20) as c:
            with pytest.raises(grpc.RpcError) as e:
                c.fuse(team_map=True)
            assert e.value.code() == grpc.StatusCode.NOT_FOUND
            _fill(c)
            first = _wait(lambda: (lambda r: r if r and r.map_versions == {"r1": 1, "r2": 1}
                                   and r.keyframes_seen == 6 else None)(_served(c)))
            assert first.team_map and first.refined and first.team_map_current and first.age_s >= 0
            assert first.keyframes_used == 6 and first.method == "vote"
            rec = first.refine_record
            assert rec["train_views"] + rec["heldout_views"] == 6 and 0 < rec["iters_run"] <= 30
            assert rec["best_loss"] <= rec["vote_loss"]
            fused = c.download_fused(first.fused_version)
            assert len(fused) == first.n_gaussians > 0 and np.isfinite(fused.means).all()
            # Fuse results of clients do not evict it (own retention), and it ages
            for _ in range(3):
                c.fuse("vote")
            again = c.fuse(team_map=True)
            assert again.fused_version == first.fused_version and again.age_s >= first.age_s
            # a new subset version: the served map says it is no longer current until the next one is made
            assert c.upload_subset("r1", 2, _plane_subset(7, -0.25), full_map_gaussians=3000).complete
            stale = c.fuse(team_map=True)
            if stale.fused_version == first.fused_version:
                assert not stale.team_map_current
            second = _wait(lambda: (lambda r: r if r and r.map_versions["r1"] == 2 else None)(_served(c)))
            assert second.fused_version > first.fused_version and second.team_map_current
        # the refresher counts a run once its map is stored and the Fuse lock released: a client can see the map first
        assert _wait(lambda: srv.servicer.team_map.runs >= 2) and srv.servicer.team_map.last_error == ""
    finally:
        srv.stop(0.5)


def test_uploads_reads_and_fuse_calls_go_on_while_the_team_map_refines(tmp_path):
    srv = start(tmp_path, config=_config(settle_s=0.0))
    try:
        with FusionClient(f"127.0.0.1:{srv.port}", timeout_s=20) as c:
            _fill(c, ("r1",))
            tm = srv.servicer.team_map
            # the team map of everything r1 sent (a loaded machine may make one before its last keyframe is in)
            first = _wait(lambda: (r := _served(c)) is not None and r.team_map_current and r, 120)
            # then a long refinement (many iterations, no early stop) to act during
            tm.settings = tm.settings.model_copy(update={"refine_iters": 20000})
            srv.servicer._engine.refine_options["patience"] = 10 ** 6
            _fill(c, ("r2",))  # a second robot: a new refinement starts
            assert _wait(lambda: tm.busy.is_set(), 30)
            child = _wait(lambda: tm.worker.pid, 30)  # the refinement runs in a process of its own
            assert child != os.getpid()
            t0 = time.monotonic()
            assert c.upload_subset("r2", 2, _plane_subset(9, 0.1), full_map_gaussians=3000).complete
            assert c.upload_keyframes("r2", [frame(40)]) == 1
            served = c.fuse(team_map=True)  # the last complete version, at once
            got = c.download_fused(served.fused_version)
            vote = c.fuse("vote")
            elapsed = time.monotonic() - t0
            assert tm.busy.is_set(), "the refinement ended before the calls: nothing was shown"
            assert served.fused_version == first.fused_version and not served.team_map_current
            assert len(got) == served.n_gaussians and vote.map_versions == {"r1": 1, "r2": 2}
            assert elapsed < 30
    finally:
        srv.stop(0.5)
    assert not srv.servicer.team_map._thread.is_alive()  # the stop ended the refinement
    assert tm.worker.pid is None  # and killed its process
    with pytest.raises(ProcessLookupError):
        os.kill(child, 0)


def test_a_fuse_with_refinement_goes_ahead_of_the_team_maps_refinement(tmp_path):
    srv = start(tmp_path, config=_config(settle_s=0.0))
    try:
        with FusionClient(f"127.0.0.1:{srv.port}", timeout_s=WORK_S) as c:
            tm = srv.servicer.team_map
            # a team-map refinement that would run for a long time (many iterations, no early stop)
            tm.settings = tm.settings.model_copy(update={"refine_iters": 20000})
            srv.servicer._engine.refine_options["patience"] = 10 ** 6
            _fill(c)
            assert _wait(lambda: tm.busy.is_set() and tm.worker.pid, STARTUP_S)
            starts = tm.worker.starts
            tm.settings = tm.settings.model_copy(update={"refine_iters": 5})  # what it runs when it starts again
            r = c.fuse("vote", refine=True, refine_iters=5)  # one joint refinement at a time: this one goes first
            assert r.refined and r.refine_record["iters_run"] <= 5 and r.map_versions == {"r1": 1, "r2": 1}
            assert tm.gave_way == 1 and tm.last_error == ""
            # the team map is made again after the Fuse, in a new process, from the same subsets and views
            again = _wait(lambda: (r := _served(c)) is not None and r.team_map_current and r, WORK_S)
            assert again.map_versions == {"r1": 1, "r2": 1} and again.refine_record["iters_run"] <= 5
            assert tm.worker.starts == starts + 1
    finally:
        srv.stop(0.5)


def test_a_server_without_a_team_map_says_so(tmp_path):
    srv = start(tmp_path, config=FusionSettings(team_map={"enabled": False}))
    try:
        with FusionClient(f"127.0.0.1:{srv.port}", timeout_s=20) as c:
            with pytest.raises(grpc.RpcError) as e:
                c.fuse(team_map=True)
            assert e.value.code() == grpc.StatusCode.FAILED_PRECONDITION and "team_map" in e.value.details()
    finally:
        srv.stop(0.5)


def test_the_store_locks_by_name_one_team_map_refinement_at_a_time(tmp_path):
    from gausslite_services.fusion_server.store import open_store

    a, b = open_store(str(tmp_path / "db")), open_store(str(tmp_path / "db"))
    try:
        with a.fuse_lock(lambda: False, name="team_map"):
            with b.fuse_lock(lambda: False, name="fuse"):  # other names are independent
                pass
            with pytest.raises(InterruptedError):
                with b.fuse_lock(lambda: True, poll_s=0.01, name="team_map"):
                    pass
        with pytest.raises(KeyError):
            with a.fuse_lock(lambda: False, name="nope"):
                pass
    finally:
        a.close()
        b.close()
