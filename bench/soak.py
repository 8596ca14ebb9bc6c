"""Soak benchmark: one agent streaming the synthetic circle for a long time, pushing to a fusion server.

    python -m bench.soak --minutes 60          # default 10; --sample-s 60 between samples

Starts a real fusion server (``python -m gausslite_services.fusion_server``, SQLite store in ``--work``) and a real
agent (``gausslite serve agent`` with the default settings, keyframe ingest, ``mapper.keyframe_budget_s`` =
``--budget``, checkpoints in its data dir, pushes to the fusion server), opens a streaming mission and sends the
synthetic scene's circle trajectory (``make_scene(trajectory="circle")``, ``--frames`` frames of
``--width`` x ``--height``, generated once and cached in ``--work``) in a loop at ``--fps`` (30 Hz) for
``--minutes``. Every ``--sample-s`` seconds it records:

* ``rss_mb_agent`` / ``rss_mb_fusion``: resident memory of each server process and its children (the agent's
  share worker), MB (the goal's figure); beside it ``pss_mb_*`` (shared library pages split between the
  processes, the tree's true footprint), ``anon_mb_*`` (heap and tensors: what a leak grows) and ``procs_*``
  (each process's RSS and anonymous memory, to tell the mapping process from the share worker);
* ``disk_mb_agent`` (checkpoints, pushed-version file) / ``disk_mb_fusion`` (SQLite store: subsets, keyframes), MB,
  and ``disk_tmp_mb_*``: atomic-write temporaries in flight at the sample (a checkpoint being replaced), apart;
* ``accept_p99_ms``: the agent's accept latency p99 over its last 1800 frames (``GetStatus``
  ``accept_latency_ms_p99_recent``), and ``keyframe_latency_s_p95`` (arrival → mapped, whole mission);
* map size (``n_gaussians``, ``n_active``), the subset the fusion server holds, frames, pushes, failures.

Goals (exit code 1 when one is missed): RSS and on-disk bytes of both processes grow by at most 5 % over the
last half of the run (the largest sample of the last half against the sample at its start), accept p99 ≤ 20 ms
in every sample, no error (stream error, failed push, rejected frame), and the mission finished. Writes
``bench/results/soak.json``, ``soak.md`` (the table) and ``soak.png`` (the curves).

The mission's end (:mod:`bench._missions`): ``mission`` in the JSON holds its ``end_state``, ``error``,
``frames_failed`` and ``corrections_rejected`` from the status Finish returned; a mission that failed (its state
``FAILED``, or frames that failed to map; sampling stops when the agent reports ``FAILED``) is
marked † below the table and misses the goal ``mission finished``, which exits 1 unless ``--allow-failed``.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Dict, List, Optional

from bench._missions import FAILED_MARK, add_allow_failed, describe, exit_code, failed, mission_outcome
from bench._results import write_results
from gausslite.datasets import load_dataset
from gausslite.synthetic import make_scene
from gausslite_rpc import agent_pb2
from gausslite_services.agent.client import AgentClient
from gausslite_services.agent.frames import encode_frame
from gausslite_services.fusion_server.client import FusionClient
from gausslite_services.sim import free_port

import grpc
import numpy as np

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results"
GROWTH_LIMIT = 0.05
ACCEPT_P99_LIMIT_MS = 20.0


def parse_args(argv=None) -> argparse.Namespace:
    """Command-line options (``--help``)."""
    p = argparse.ArgumentParser(prog="python -m bench.soak", description=__doc__.split("\n\n")[0])
    p.add_argument("--minutes", type=float, default=10.0, help="streaming time (default 10)")
    p.add_argument("--sample-s", type=float, default=60.0, help="seconds between samples (default 60)")
    p.add_argument("--fps", type=float, default=30.0)
    p.add_argument("--frames", type=int, default=300, help="frames of one circle (the loop's length)")
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--budget", type=float, default=1.0, help="mapper.keyframe_budget_s of the agent")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="more agent config overrides (agent.push.every=10, mapper.stored_keyframes_max=300, ...)")
    p.add_argument("--work", default=str(REPO / "runs" / "soak"), help="scratch folder (scene, data dirs, logs)")
    p.add_argument("--out", default=str(RESULTS / "soak.json"))
    add_allow_failed(p)
    return p.parse_args(argv)


# ------------------------------------------------------------------------------------ measurements
def process_tree(pid: int) -> List[int]:
    """``pid`` and all its descendants (from ``/proc/*/stat``), parents first."""
    children: Dict[int, List[int]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(d.name))
    out, todo = [], [pid]
    while todo:
        p = todo.pop(0)
        out.append(p)
        todo += sorted(children.get(p, []))
    return out


def _kb_fields(path: Path, keys: tuple) -> Dict[str, float]:
    """``key: value kB`` lines of a ``/proc`` file → {key: MB} for ``keys`` (missing keys are absent)."""
    out = {}
    for line in path.read_text().splitlines():
        k, _, v = line.partition(":")
        if k in keys:
            out[k] = int(v.split()[0]) / 1024.0
    return out


def tree_memory_mb(pid: int) -> dict:
    """Memory of process ``pid`` and its descendants, MB: ``rss`` (sum of VmRSS: shared library pages count once per
    process), ``pss`` (proportional set size: shared pages split between the processes that map them, so the tree's
    true footprint), ``anon`` (sum of RssAnon: heap and tensors, what a leak grows) and ``procs`` (per process:
    pid, short command, rss, anon). Zeros when the process is gone."""
    tot = {"rss": 0.0, "pss": 0.0, "anon": 0.0, "procs": []}
    for p in process_tree(pid):
        try:
            st = _kb_fields(Path(f"/proc/{p}/status"), ("VmRSS", "RssAnon"))
            pss = _kb_fields(Path(f"/proc/{p}/smaps_rollup"), ("Pss",)).get("Pss", 0.0)
            cmd = Path(f"/proc/{p}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        rss, anon = st.get("VmRSS", 0.0), st.get("RssAnon", 0.0)
        tot["rss"] += rss
        tot["pss"] += pss
        tot["anon"] += anon
        short = " ".join(c.decode(errors="replace") for c in cmd[:3] if c)[-60:]
        tot["procs"].append({"pid": p, "cmd": short, "rss": round(rss, 1), "anon": round(anon, 1)})
    return tot


def dir_mb(path: Path) -> tuple[float, float]:
    """MB of the files under ``path`` (recursively): (settled files, atomic-write temporaries in flight). The agent
    writes a checkpoint through ``.<name>.<pid>.tmp`` and renames it (``gausslite.mission.runtime``): a sample taken
    during that write sees the old and the new checkpoint at once, which is not growth."""
    n = tmp = 0
    for root, _, files in os.walk(path):
        for f in files:
            try:
                size = os.stat(os.path.join(root, f)).st_size
            except OSError:
                continue
            if f.startswith(".") and f.endswith(".tmp"):
                tmp += size
            else:
                n += size
    return n / 2**20, tmp / 2**20


def _disk(name: str, path: Path) -> dict:
    """``disk_mb_<name>`` (settled files) and ``disk_tmp_mb_<name>`` (temporaries in flight) of :func:`dir_mb`."""
    settled, tmp = dir_mb(path)
    return {f"disk_mb_{name}": round(settled, 2), f"disk_tmp_mb_{name}": round(tmp, 2)}


def _memory(name: str, pid: int) -> dict:
    """``rss_mb_<name>``, ``pss_mb_<name>``, ``anon_mb_<name>`` and ``procs_<name>`` of :func:`tree_memory_mb`."""
    m = tree_memory_mb(pid)
    return {f"rss_mb_{name}": round(m["rss"], 1), f"pss_mb_{name}": round(m["pss"], 1),
            f"anon_mb_{name}": round(m["anon"], 1), f"procs_{name}": m["procs"]}


def growth_last_half(samples: List[dict], key: str) -> Optional[float]:
    """Relative growth of ``key`` over the last half of the run: (largest sample at or after the midpoint −
    the sample at the midpoint) / the sample at the midpoint; None with fewer than 2 samples there."""
    if not samples:
        return None
    mid = samples[-1]["t_s"] / 2.0
    half = [s[key] for s in samples if s["t_s"] >= mid]
    if len(half) < 2 or half[0] <= 0:
        return None
    return (max(half) - half[0]) / half[0]


def trend_last_half(samples: List[dict], key: str) -> Optional[float]:
    """Least-squares slope of ``key`` over the last half of the run, as a fraction of its median there per 30
    minutes: a leak shows as a steady positive trend, a transient peak (which :func:`growth_last_half` counts) does
    not. None with fewer than 3 samples there."""
    if not samples:
        return None
    mid = samples[-1]["t_s"] / 2.0
    half = [(s["t_s"], s[key]) for s in samples if s["t_s"] >= mid]
    if len(half) < 3:
        return None
    t, y = np.array(half, float).T
    med = float(np.median(y))
    return None if med <= 0 else float(np.polyfit(t, y, 1)[0]) * 1800.0 / med


# ------------------------------------------------------------------------------------ processes
def _start(cmd: List[str], env: dict, log_path: Path) -> subprocess.Popen:
    log = open(log_path, "ab")
    try:
        return subprocess.Popen(cmd, cwd=str(REPO), env=env, stdout=log, stderr=subprocess.STDOUT,
                                start_new_session=True)
    finally:
        log.close()


def _stop(proc: Optional[subprocess.Popen]) -> None:
    if proc is None or proc.poll() is not None:
        return
    os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(30)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)


def _scene(args, work: Path):
    """The circle's frames and the scene folder (annotations)."""
    d = work / f"scene_circle_{args.frames}_{args.width}x{args.height}"
    if not (d / "agent_a" / "traj.txt").is_file():
        print(f"rendering the circle scene ({args.frames} frames) into {d} ...", flush=True)
        make_scene(d, seed=0, width=args.width, height=args.height, frames=args.frames, progress=False,
                   trajectory="circle", agents=("agent_a",))
    ds = load_dataset(d / "agent_a")
    return [ds[i] for i in range(len(ds))], d / "agent_a", ds.annotations


def _wait_for_port(fusion: subprocess.Popen, port_file: Path, log_path: Path) -> str:
    """The fusion server's address once it has written its port (RuntimeError when it has not within 60 s)."""
    deadline = time.monotonic() + 60
    while not (port_file.exists() and port_file.read_text().strip()):
        if fusion.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"the fusion server did not start; see {log_path}")
        time.sleep(0.05)
    return f"127.0.0.1:{int(port_file.read_text())}"


def _start_agent(args, env: dict, agent_port: int, fusion_addr: str, agent_dir: Path, scene: Path,
                 log_path: Path) -> subprocess.Popen:
    """The agent process (the default settings, ``--budget`` and ``--set`` overrides), pushing to
    ``fusion_addr``."""
    overrides = [f"mapper.keyframe_budget_s={args.budget}", "agent.downscale=1"] + list(args.set)
    return _start([sys.executable, "-m", "gausslite.cli", "serve", "agent", "--host", "127.0.0.1", "--port",
                   str(agent_port), "--config", str(REPO / "deploy" / "gausslite.yaml")],
                  dict(env, GAUSSLITE_AGENT_ID="soak", GAUSSLITE_FUSION_ADDR=fusion_addr,
                       GAUSSLITE_DATA_DIR=str(agent_dir), GAUSSLITE_AGENT_SET=";".join(overrides),
                       GAUSSLITE_AGENT_DATA_ROOTS=str(scene)),
                  log_path)


def _paced(encoded: list, period: float, stop: threading.Event, sent: dict):
    """The encoded frames in a loop, one every ``period`` seconds until ``stop``; records in ``sent`` how many were
    sent and the largest lateness."""
    t0 = time.perf_counter()
    k = 0
    while not stop.is_set():
        due = t0 + k * period
        now = time.perf_counter()
        if due > now:
            time.sleep(due - now)
        sent["late_ms_max"] = max(sent["late_ms_max"], 1e3 * (time.perf_counter() - due))
        msg = encoded[k % len(encoded)]
        msg.frame_id = k
        msg.timestamp = k * period
        sent["n"] = k + 1
        k += 1
        yield msg


def _stream(c: AgentClient, messages, total_s: float, errors: List[str]) -> None:
    """Stream ``messages`` to the agent; a stream error goes to ``errors``."""
    try:
        c.stream_messages(messages, timeout_s=total_s + 600)
    except grpc.RpcError as e:
        errors.append(f"StreamFrames: {e.code().name}: {e.details()}")


def _sample_loop(args, c: AgentClient, fc: FusionClient, mission_id: str, agent: subprocess.Popen,
                 fusion: subprocess.Popen, agent_dir: Path, fusion_dir: Path, t_start: float, total_s: float,
                 sent: dict, samples: List[dict], errors: List[str]) -> None:
    """A sample every ``--sample-s`` seconds into ``samples`` (and printed) until ``total_s`` or a failed
    mission."""
    k = 0
    while True:
        k += 1
        t_next = t_start + k * args.sample_s
        end = min(t_next, t_start + total_s)
        time.sleep(max(0.0, end - time.monotonic()))
        st = c.status(mission_id)
        try:
            held = fc.stats()["agents"].get("soak", {})
        except grpc.RpcError as e:
            errors.append(f"GetStats: {e.code().name}: {e.details()}")
            held = {}
        s = {"t_s": round(time.monotonic() - t_start, 1),
             **_memory("agent", agent.pid), **_memory("fusion", fusion.pid),
             **_disk("agent", agent_dir), **_disk("fusion", fusion_dir),
             "accept_p99_ms": round(float(st.accept_latency_ms_p99_recent), 3),
             "keyframe_latency_s_p95": round(float(st.keyframe_latency_s_p95), 3),
             "n_gaussians": int(st.n_gaussians), "n_active": int(st.n_active),
             "fusion_subset_gaussians": int(held.get("gaussians_received", 0)),
             "fusion_keyframes": int(held.get("keyframes", 0)),
             "frames_sent": sent["n"], "frames_received": int(st.frames_received),
             "frames_keyframed": int(st.frames_keyframed), "pushes": int(st.pushes),
             "push_failures": int(st.push_failures), "frames_rejected": int(st.frames_rejected),
             "checkpoints": int(st.checkpoints), "state": agent_state_name(st.state)}
        samples.append(s)
        print(" ".join(f"{k2}={v}" for k2, v in s.items() if not k2.startswith("procs_")), flush=True)
        if st.state == agent_pb2.MISSION_STATE_FAILED:  # recorded from Finish's status (_mission)
            break
        if time.monotonic() - t_start >= total_s - 1e-3:
            break


def _mission(args, c: AgentClient, fc: FusionClient, frames: list, scene: Path, ann, agent: subprocess.Popen,
             fusion: subprocess.Popen, agent_dir: Path, fusion_dir: Path, samples: List[dict],
             errors: List[str]) -> dict:
    """Start the mission, stream the circle for ``--minutes`` while sampling, finish it and check both processes;
    returns what the sender recorded (``n``, ``late_ms_max``) and ``"mission"``, how the mission ended
    (:func:`bench._missions.mission_outcome` of Finish's status)."""
    c.wait_ready(180)
    task = ann.tasks[0].text
    m = c.start_mission(task, annotations_path=str(scene))
    encoded = [encode_frame(f, m.mission_id, color_format=".jpg") for f in frames]
    period = 1.0 / args.fps
    total_s = args.minutes * 60.0
    stop = threading.Event()
    sent = {"n": 0, "late_ms_max": 0.0}
    th = threading.Thread(target=lambda: _stream(c, _paced(encoded, period, stop, sent), total_s, errors),
                          name="soak-stream", daemon=True)
    t_start = time.monotonic()
    th.start()
    print(f"streaming {len(frames)}-frame circle at {args.fps:.0f} Hz for {args.minutes:g} min; "
          f"a sample every {args.sample_s:g} s", flush=True)
    _sample_loop(args, c, fc, m.mission_id, agent, fusion, agent_dir, fusion_dir, t_start, total_s, sent, samples,
                 errors)
    stop.set()
    th.join(120)
    fin = c.finish(m.mission_id, skip_push=True, skip_eval=True, timeout_s=600).status
    sent["mission"] = mission_outcome(fin)
    if fin.push_failures:
        errors.append(f"{fin.push_failures} failed push attempts (last: {fin.last_error})")
    if fin.frames_rejected:
        errors.append(f"{fin.frames_rejected} rejected frames")
    for p, name in ((agent, "agent"), (fusion, "fusion")):
        if p.poll() is not None:
            errors.append(f"the {name} process exited ({p.returncode})")
    return sent


def _results(args, samples: List[dict], errors: List[str], sent: Optional[dict]) -> dict:
    """The results dict: settings, samples, errors, growth and trend over the last half, goals."""
    res = {"minutes": args.minutes, "sample_s": args.sample_s, "fps": args.fps,
           "scene": f"synthetic circle, {args.frames} frames of {args.width}x{args.height}, looped",
           "budget_s": args.budget, "overrides": list(args.set), "frames_sent": samples[-1]["frames_sent"] if samples
           else 0, "sender_late_ms_max": round(sent["late_ms_max"], 1) if samples else None,
           "errors": errors, "mission": (sent or {}).get("mission") or {"end_state": "UNKNOWN", "error": ""},
           "samples": samples,
           "machine": f"{os.cpu_count()} CPUs, load average {', '.join(f'{x:.1f}' for x in os.getloadavg())}"}
    res["growth_last_half"] = {k: (None if (g := growth_last_half(samples, k)) is None else round(g, 4))
                               for k in ("rss_mb_agent", "rss_mb_fusion", "disk_mb_agent", "disk_mb_fusion")}
    res["trend_last_half_per_30min"] = {k: (None if (g := trend_last_half(samples, k)) is None else round(g, 4))
                                        for k in ("rss_mb_agent", "rss_mb_fusion", "disk_mb_agent", "disk_mb_fusion")}
    res["accept_p99_ms_max"] = max((s["accept_p99_ms"] for s in samples), default=None)
    res["goals"] = {
        **{f"{k} growth<=5%": g is not None and g <= GROWTH_LIMIT for k, g in res["growth_last_half"].items()},
        "accept p99<=20ms": res["accept_p99_ms_max"] is not None and res["accept_p99_ms_max"] <= ACCEPT_P99_LIMIT_MS,
        "no errors": not errors,
        "mission finished": not failed(res["mission"]),
    }
    return res


def run(args) -> dict:
    """Run the soak (see the module docstring); returns the results dict (``samples``, ``goals``, ...)."""
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    frames, scene, ann = _scene(args, work)
    tag = time.strftime("%Y%m%d-%H%M%S")
    fusion_dir, agent_dir = work / f"fusion-{tag}", work / f"agent-{tag}"
    env = dict(os.environ, PYTHONPATH=str(REPO), PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1")
    for k in ("GAUSSLITE_FUSION_STORE", "GAUSSLITE_DATA_DIR"):
        env.pop(k, None)
    port_file = work / f"fusion-{tag}.port"
    fusion = agent = None
    samples: List[dict] = []
    errors: List[str] = []
    try:
        fusion = _start([sys.executable, "-m", "gausslite_services.fusion_server", "--host", "127.0.0.1", "--port", "0",
                         "--data-dir", str(fusion_dir), "--port-file", str(port_file), "--log-level", "WARNING"],
                        env, work / f"fusion-{tag}.log")
        fusion_addr = _wait_for_port(fusion, port_file, work / f"fusion-{tag}.log")
        agent_port = free_port()
        agent = _start_agent(args, env, agent_port, fusion_addr, agent_dir, scene, work / f"agent-{tag}.log")
        with AgentClient(f"127.0.0.1:{agent_port}") as c, FusionClient(fusion_addr, timeout_s=30) as fc:
            sent = _mission(args, c, fc, frames, scene, ann, agent, fusion, agent_dir, fusion_dir, samples, errors)
    finally:
        _stop(agent)
        _stop(fusion)
    return _results(args, samples, errors, sent)


def agent_state_name(state: int) -> str:
    """``MissionState`` number → its short name (``MAPPING``)."""
    return agent_pb2.MissionState.Name(state).replace("MISSION_STATE_", "")


# ------------------------------------------------------------------------------------ output
def table(res: dict) -> str:
    """Markdown table of the samples, then the growth figures and goals."""
    cols = [("t_s", "t (s)"), ("rss_mb_agent", "agent RSS MB"), ("anon_mb_agent", "agent anon MB"),
            ("rss_mb_fusion", "fusion RSS MB"),
            ("disk_mb_agent", "agent disk MB"), ("disk_mb_fusion", "fusion disk MB"),
            ("accept_p99_ms", "accept p99 ms"), ("keyframe_latency_s_p95", "keyframe p95 s"),
            ("n_gaussians", "Gaussians"), ("fusion_subset_gaussians", "fused subset"),
            ("frames_keyframed", "keyframes"), ("pushes", "pushes")]
    lines = ["| " + " | ".join(h for _, h in cols) + " |", "|" + "---|" * len(cols)]
    for s in res["samples"]:
        lines.append("| " + " | ".join(str(s.get(k, "–")) for k, _ in cols) + " |")
    g = res["growth_last_half"]
    lines += ["", "Growth over the last half: " + ", ".join(
        f"{k} {'n/a' if v is None else f'{100 * v:+.1f} %'}" for k, v in g.items()),
        "Trend over the last half (least-squares slope, per 30 minutes): " + ", ".join(
            f"{k} {'n/a' if v is None else f'{100 * v:+.1f} %'}"
            for k, v in (res.get("trend_last_half_per_30min") or {}).items()),
        f"Accept p99 (last 1800 frames), largest sample: {res['accept_p99_ms_max']} ms",
        f"Errors: {res['errors'] or 'none'}",
        *_mission_line(res),
        "Goals: " + ", ".join(f"{k} {'met' if v else 'MISSED'}" for k, v in res["goals"].items())]
    return "\n".join(lines)


def _mission_line(res: dict) -> list:
    """The table's line on how the mission ended (none for a result written before it was recorded)."""
    m = res.get("mission")
    if not m:
        return []
    return [f"{FAILED_MARK} Mission failed: {describe(m)}" if failed(m) else f"Mission: {m['end_state']}"]


def plot(res: dict, path: Path) -> None:
    """PNG of RSS, disk, accept p99 and map size against time."""
    # lazy: heavy optional dependency, loaded only on this path
    import matplotlib

    matplotlib.use("Agg")
    # lazy: heavy optional dependency, loaded only on this path
    import matplotlib.pyplot as plt

    s = res["samples"]
    t = [x["t_s"] / 60.0 for x in s]
    fig, ax = plt.subplots(2, 2, figsize=(11, 7), sharex=True)
    for key, label in (("rss_mb_agent", "agent"), ("rss_mb_fusion", "fusion")):
        ax[0, 0].plot(t, [x[key] for x in s], marker="o", label=label)
        if all(f"anon_mb_{label}" in x for x in s):
            ax[0, 0].plot(t, [x[f"anon_mb_{label}"] for x in s], ls="--", label=f"{label}, anonymous")
    ax[0, 0].set_ylabel("RSS (MB)")
    for key, label in (("disk_mb_agent", "agent (checkpoints)"), ("disk_mb_fusion", "fusion (store)")):
        ax[0, 1].plot(t, [x[key] for x in s], marker="o", label=label)
    ax[0, 1].set_ylabel("on disk (MB)")
    ax[1, 0].plot(t, [x["accept_p99_ms"] for x in s], marker="o", label="accept p99 (ms)")
    ax[1, 0].axhline(ACCEPT_P99_LIMIT_MS, color="r", ls="--", lw=1, label="goal")
    ax[1, 0].plot(t, [1e3 * x["keyframe_latency_s_p95"] / 100 for x in s], marker="x",
                  label="keyframe latency p95 (s × 10)")
    ax[1, 0].set_ylabel("latency")
    ax[1, 1].plot(t, [x["n_gaussians"] for x in s], marker="o", label="agent map")
    ax[1, 1].plot(t, [x["fusion_subset_gaussians"] for x in s], marker="o", label="subset on the fusion server")
    ax[1, 1].set_ylabel("Gaussians")
    for a in ax.flat:
        a.legend(fontsize=8)
        a.grid(alpha=0.3)
    for a in ax[1]:
        a.set_xlabel("minutes")
    fig.suptitle(f"bench.soak: {res['minutes']:g} min at {res['fps']:g} Hz ({res['scene']})", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv=None) -> int:
    """Run the soak and write JSON, Markdown and PNG next to ``--out``. Returns 0 when every goal is met (the goal
    ``mission finished`` waived by ``--allow-failed``), 1 otherwise (each missed goal printed to stderr), 2 on
    unusable arguments."""
    args = parse_args(argv)
    if args.minutes <= 0 or args.sample_s <= 0 or args.fps <= 0:
        print("bench.soak: --minutes, --sample-s and --fps must be > 0", file=sys.stderr)
        return 2

    res = run(args)
    out = Path(args.out)
    write_results(out, "soak", argv, f": {len(res['samples'])} samples", table(res), res)
    if res["samples"]:
        plot(res, out.with_suffix(".png"))
        print(f"wrote {out}, {out.with_suffix('.md')}, {out.with_suffix('.png')}")
    missed = [k for k, v in res["goals"].items() if not v and k != "mission finished"]
    for k in missed:
        print(f"bench.soak: goal missed: {k}", file=sys.stderr)
    return 1 if exit_code([res["mission"]], args.allow_failed, "bench.soak") or missed else 0


if __name__ == "__main__":
    sys.exit(main())
