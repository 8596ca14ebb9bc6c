"""A fusion link that comes and goes: a real fusion-server process is stopped mid-mission and started
again on the same port and data dir after ``GAUSSLITE_TEST_OUTAGE_S`` seconds (default 3). The agent
keeps mapping, holds only the newest subset (bounded backlog, reported by ``GetStatus``), pushes it when
the link returns, and the subset the server stores at the end is exactly the agent's final one."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from gausslite.datasets import load_dataset
from gausslite.parser import TaskParser
from gausslite.synthetic import make_scene
from gausslite.config import load_config
from gausslite.mission import AgentRuntime
from gausslite_services.agent.server import AgentServicer
from gausslite_services.fusion_server.client import FusionClient
from tests._waits import STARTUP_S, WORK_S, wait_for_start, wait_until

REPO = Path(__file__).resolve().parents[2]
OUTAGE_S = float(os.environ.get("GAUSSLITE_TEST_OUTAGE_S", "3"))
CFG = ["agent.ingest=every_frame", "agent.push.every=2", "agent.upload_keyframe_every=1", "agent.push.backoff_s=0.1",
       "agent.push.max_backoff_s=0.5", "agent.upload_backlog_max=3", "agent.push.final_timeout_s=60",
       "mapper.iters_per_frame=3", "mapper.warmup_iters=1", "mapper.seeding.seeds_per_frame=200",
       "agent.refine_views.crop=false", "agent.refine_views.budget_ratio=null",  # whole keyframes, all counted
       "agent.share.worker=thread"]  # no share worker process: the link, not the worker, is what comes and goes


def _start_fusion(data_dir: Path, port_file: Path, port: int = 0) -> tuple[subprocess.Popen, int]:
    if port_file.exists():
        port_file.unlink()
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    log = data_dir.parent / f"{port_file.name}.log"
    with open(log, "ab") as out:
        # no team map (tests/services/test_team_map.py): no refinement process beside the uploads
        proc = subprocess.Popen([sys.executable, "-m", "gausslite_services.fusion_server", "--port", str(port),
                                 "--data-dir", str(data_dir), "--port-file", str(port_file),
                                 "--set", "fusion.team_map.enabled=false"], cwd=str(REPO), env=env,
                                stdout=out, stderr=subprocess.STDOUT)
    wait_for_start(proc, lambda: port_file.exists() and port_file.read_text().strip(),
                   f"the fusion server's port file {port_file}", log)
    return proc, int(port_file.read_text().strip())


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)



def test_link_outage_mid_mission(tmp_path):
    scene = tmp_path / "scene"
    make_scene(scene, seed=0, width=64, height=48, frames=12, progress=False, agents=("agent_a",))
    ds = load_dataset(scene / "agent_a")
    text = ds.annotations.task_by_id("synth-pick-object").text
    data, port_file = tmp_path / "fusion", tmp_path / "port"
    proc, port = _start_fusion(data, port_file)
    client = FusionClient(f"127.0.0.1:{port}", timeout_s=3)
    rt = AgentRuntime("robot1", text, TaskParser().parse(text), load_config(None, CFG).agent,
                      annotations=ds.annotations, fusion=client)
    try:
        for i in range(4):
            rt.submit(ds[i])
        assert rt.wait_mapped(STARTUP_S)
        assert wait_until(lambda: rt.status()["last_pushed_version"] >= 2, STARTUP_S), \
            f"no push acknowledged within {STARTUP_S:.0f} s: {rt.last_error}"
        acked_before = rt.status()["last_pushed_version"]

        _stop(proc)  # the link drops
        t_down = time.monotonic()
        for i in range(4, len(ds)):  # the agent keeps mapping
            rt.submit(ds[i])
        assert rt.wait_mapped(STARTUP_S)
        assert wait_until(lambda: rt.pusher.push_failures > 0 and rt.status()["link_down_s"] > 0, STARTUP_S), \
            f"no failed push within {STARTUP_S:.0f} s of the link dropping"
        st = rt.status()
        assert st["frames_mapped"] == len(ds) == 12
        assert st["last_pushed_version"] == acked_before  # nothing acknowledged while the link is down
        assert st["newest_map_version"] == 6 > acked_before  # 12 frames, a snapshot every 2
        assert 1 <= st["push_backlog"] <= 2  # only the newest subset is held, not one per version
        assert 1 <= st["keyframes_backlog"] <= 3  # bounded by agent.upload_backlog_max
        msg = AgentServicer._status_proto(st)  # what GetStatus sends
        assert msg.push_backlog == st["push_backlog"] and msg.newest_map_version == 6
        assert msg.last_pushed_version == acked_before and msg.link_down_s > 0

        time.sleep(max(0.0, OUTAGE_S - (time.monotonic() - t_down)))
        proc, port2 = _start_fusion(data, port_file, port)  # the link returns
        assert port2 == port
        # the held subset goes out without any new frame or Finish
        assert wait_until(lambda: rt.status()["last_pushed_version"] == 6, STARTUP_S), \
            f"the held subset not acknowledged within {STARTUP_S:.0f} s of the link returning: {rt.last_error}"
        st = rt.status()
        assert st["push_backlog"] == 0 and st["link_down_s"] == 0.0 and st["keyframes_backlog"] == 0

        s = rt.finish(timeout_s=WORK_S, evaluate=False)
        assert s.final_push_ok, rt.last_error
        version, subset, _ = rt.acknowledged_subset()
        with FusionClient(f"127.0.0.1:{port}", timeout_s=10) as c:
            stats = c.stats()["agents"]["robot1"]
            assert stats["latest_map_version"] == version == s.status["last_pushed_version"]
            assert stats["has_complete_subset"]
            fused = c.fuse("concat")  # concat keeps the rows verbatim: the stored subset itself
            stored = c.download_fused(fused.fused_version)
        assert len(stored) == len(subset) == s.n_shared > 0
        assert stored.equals(subset)
    finally:
        rt.close()
        client.close()
        _stop(proc)
