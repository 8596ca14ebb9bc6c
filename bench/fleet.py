"""Fleet benchmark with faults: N replay agents push real ROI subsets and keyframes to R fusion
replicas sharing one PostgreSQL store; one replica is SIGKILLed mid-run and restarted.

    python -m bench.fleet --agents 32 --replicas 2

Loopback only (every server binds 127.0.0.1), bounded in time (``--duration``) and count. Needs a
reachable PostgreSQL: ``--store postgresql://…`` or ``$GAUSSLITE_FUSION_STORE`` or
``$GAUSSLITE_TEST_PG_DSN`` (``.ci/run`` sets the latter up); the run uses a fresh schema and drops it.

Source map (real Gaussians, not random arrays): ``--ply map.ply`` (written by ``gausslite map``),
or — by default — the first ``--map-frames`` frames of the synthetic default scene mapped once with
``--map-iters`` Adam iterations per frame and cached in ``--work`` (``source_map.ply``). Agent i's
subset for map version v is the ``--share`` fraction of that map nearest to a point that moves
with v (the robot's region of interest drifting), its κ scaled per agent and growing with v; the
keyframes are the scene's posed RGB-D frames (downscaled by ``--keyframe-downscale``).

Replay clients are threads of this process, one gRPC channel each, addressing every replica as
``ipv4:127.0.0.1:p1,127.0.0.1:p2`` (round_robin, no retry policy — the same channel options as
:class:`gausslite_services.fusion_server.client.FusionClient`); chunks are pre-encoded per version and sent one
``UploadSubset`` call per ``--chunks-per-call`` chunks; a failed call is resumed from ``GetUploadStatus``
(:func:`gausslite_services.fusion_server.client.resume_upload`). An ack's latency runs from the first send attempt
of its chunks to the ack (retries included).

Measured (``bench/results/fleet.json``): ``acks`` (chunks acknowledged), ``lost`` (acknowledged chunks
of each agent's final version that the store does not hold at the end, plus acknowledged-complete
versions that are not the agent's latest; must be 0), ``ack_latency_ms_p50/p99``,
``gaussians_per_s`` (acknowledged Gaussians per second of run), ``fuse_full_s`` (vote stage of a
``Fuse`` on the restarted replica, whose voted map is empty: a full vote over every agent) and
``fuse_incremental_s`` (vote stage of the next ``Fuse`` after one agent pushed a new version: only
that agent is re-voted; median of three such updates), ``voxel_vote_local_s`` (a one-off
:func:`voxel_vote` of the same subsets in this process, for reference: building the incremental
index costs more than a one-off vote), the whole-``Fuse`` times beside them, each server's ``peak_rss_mb``
(VmHWM), and checks that the fused map equals a local :func:`voxel_vote` of the subsets the agents
sent and that every replica answers ``GetStats`` identically. ``goals`` records the fleet goals
(≥ 32 agents, 0 lost, p99 ack ≤ 250 ms, incremental vote ≤ 0.1 × full); the exit code is 1 when one
is missed or the fused map differs from the local vote (each printed), 0 otherwise.

``--db-outage S`` makes PostgreSQL unreachable for S seconds under the replicas at ``--db-outage-at`` of the
run (before the replica kill): by default the replicas reach the database through a TCP relay of this process
that is cut (connections dropped, new ones refused — what a stopped server looks like to a client, without
stopping a cluster others share); ``--db-stop-cmd`` / ``--db-start-cmd`` stop and start the real server instead
(e.g. ``pg_ctlcluster 15 main stop``). Clients retry UNAVAILABLE and DEADLINE_EXCEEDED with exponential backoff
(0.05 s doubling to 2 s). Added to the results: ``failed_call_codes`` (status codes of the failed calls;
the agents retry the transient ones), ``acks_during_outage``, ``replicas_serving_after_s`` (from the database's
return until every replica answers ``GetStats``), ``replicas_not_restarted`` (same processes) and
``acks_in_2s_after_recovery``; goals: no INTERNAL/UNKNOWN status, no agent error, replicas recovered without a
restart (and ``lost`` = 0 as always).
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional
from urllib.parse import urlsplit, urlunsplit

import grpc
import numpy as np
import torch

from bench._results import write_json
from gausslite.datasets import load_dataset
from gausslite.fusion.vote import voxel_vote
from gausslite.gaussians import GaussianMap
from gausslite.config import load_mapper_config
from gausslite.mapping.mapper import Mapper
from gausslite.synthetic import make_scene
from gausslite.wire.codec import GaussianArrays, QuantConfig, assemble, encode_subset, peek_header
from gausslite_rpc import fusion_pb2, fusion_pb2_grpc
from gausslite_services.fusion_server.client import (FusionClient, channel_options, intrinsics_to_proto,
                                                     keyframe_to_proto, resume_upload)
from tests._relay import TcpRelay

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results"


# ------------------------------------------------------------------------------------ source data
def source_map(args) -> "object":
    """The fleet's source map as GaussianArrays (loaded from --ply, or mapped once and cached)."""
    if args.ply:
        return GaussianArrays.from_any(GaussianMap.load_ply(args.ply))
    work = Path(args.work)
    cache = work / f"source_map_f{args.map_frames}_i{args.map_iters}.ply"
    if cache.is_file():
        return GaussianArrays.from_any(GaussianMap.load_ply(cache))

    ds = load_dataset(scene_dir(args), max_frames=args.map_frames)
    cfg = load_mapper_config(None, [], iters_per_frame=args.map_iters, warmup_iters=min(args.map_iters, 15))
    torch.manual_seed(cfg.seed)
    t0 = time.perf_counter()
    mapper = Mapper(cfg)
    for i in range(len(ds)):
        mapper.map_frame(ds[i], None)
    mapper.finalize()
    print(f"mapped {len(ds)} frames of {ds.path} in {time.perf_counter() - t0:.1f}s: {len(mapper.gmap)} Gaussians",
          flush=True)
    mapper.gmap.save_ply(cache)
    return GaussianArrays.from_any(GaussianMap.load_ply(cache))


def scene_dir(args) -> Path:
    """The posed RGB-D sequence of the keyframes (and of the mapped source map)."""
    if args.dataset:
        return Path(args.dataset)
    d = Path(args.work) / "scene"
    if not (d / "agent_a" / "traj.txt").is_file():
        make_scene(d, frames=max(args.map_frames, 4), progress=False)
    return d / "agent_a"


def keyframes(args) -> list:
    """Posed RGB-D frames, downscaled (``gausslite.datasets.base.Frame``)."""
    ds = load_dataset(scene_dir(args), downscale=args.keyframe_downscale, max_frames=8)
    return [ds[i] for i in range(len(ds))]


def tile_site(src, rooms: int, gap_m: float = 1.0):
    """A site of ``rooms`` copies of the mapped room on a square grid (``gap_m`` apart), so that a
    fleet spreads over more space than one robot's ROI, as on a real site. rooms=1: the map itself."""
    if rooms <= 1:
        return src
    side = int(np.ceil(np.sqrt(rooms)))
    ext = src.means.max(0) - src.means.min(0) + gap_m
    parts = []
    for r in range(rooms):
        p = src.take(np.arange(len(src)))
        p.means[:, 0] += np.float32(ext[0] * (r % side))
        p.means[:, 1] += np.float32(ext[1] * (r // side))
        parts.append(p)
    return GaussianArrays.concat(parts)


class SubsetMaker:
    """Agent i's ROI subset for map version v: the ``share`` of the site map nearest to a point
    drifting ``drift`` metres per version. κ (active-optimisation count) grows towards the ROI
    centre (the robot optimised its task region most): ``round(kappa_peak · exp(-d²/2r²))`` with r
    the subset radius, times a per-agent factor, plus the map's own κ and the version number."""

    def __init__(self, src, n_agents: int, share: float, drift: float, seed: int, kappa_peak: float = 40.0):
        self.src = src
        rng = np.random.default_rng(seed)
        self.k = max(1, int(round(share * len(src))))
        self.centres = src.means[rng.choice(len(src), n_agents, replace=False)].astype(np.float64)
        d = rng.normal(size=(n_agents, 3))
        self.dirs = d / np.linalg.norm(d, axis=1, keepdims=True)
        self.factor = rng.uniform(0.5, 1.5, n_agents)
        self.drift = float(drift)
        self.kappa_peak = float(kappa_peak)

    def __call__(self, i: int, v: int):
        c = self.centres[i] + self.dirs[i] * self.drift * (v - 1)
        d2 = ((self.src.means.astype(np.float64) - c) ** 2).sum(1)
        idx = np.sort(np.argpartition(d2, self.k - 1)[:self.k])
        sub = self.src.take(idx)
        r2 = max(float(d2[idx].max()), 1e-6)
        w = self.kappa_peak * self.factor[i] * np.exp(-d2[idx] / (2 * r2 / 4))
        sub.kappa[:] = sub.kappa + np.round(w).astype(np.int64) + v
        return sub


# ------------------------------------------------------------------------------------ replicas
@dataclass
class Replica:
    """One fusion-server subprocess (restartable on the same port)."""

    name: str
    dsn: str
    work: Path
    port: int = 0
    team_map: bool = False
    proc: Optional[subprocess.Popen] = None
    peak_rss_mb: List[float] = field(default_factory=list)  # per incarnation
    log: Optional[object] = None

    def start(self, timeout_s: float = 60.0) -> None:
        port_file = self.work / f"{self.name}.port"
        if port_file.exists():
            port_file.unlink()
        env = dict(os.environ, PYTHONPATH=str(REPO), OMP_NUM_THREADS="1")
        env.pop("GAUSSLITE_FUSION_STORE", None)
        self.log = open(self.work / f"{self.name}.log", "ab")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "gausslite_services.fusion_server", "--host", "127.0.0.1", "--port", str(self.port),
             "--store", self.dsn, "--port-file", str(port_file), "--max-workers", "48", "--log-level", "WARNING",
             "--data-dir", str(self.work / f"{self.name}-unused"),
             "--set", f"fusion.team_map.enabled={str(self.team_map).lower()}"],
            cwd=str(REPO), env=env, stdout=self.log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + timeout_s
        while not port_file.exists():
            if self.proc.poll() is not None:
                raise RuntimeError(f"replica {self.name} exited {self.proc.returncode}; see {self.log.name}")
            if time.monotonic() > deadline:
                self.kill()
                raise RuntimeError(f"replica {self.name} did not start within {timeout_s:.0f}s")
            time.sleep(0.05)
        self.port = int(port_file.read_text().strip())

    def rss_hwm_mb(self) -> float:
        try:
            for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
        except OSError:
            pass
        return float("nan")

    def kill(self, sig=signal.SIGKILL) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.peak_rss_mb.append(self.rss_hwm_mb())
            self.proc.send_signal(sig)
            self.proc.wait(30)
        if self.log is not None:
            self.log.close()
            self.log = None


# ------------------------------------------------------------------------------------ agents
@dataclass
class AgentLog:
    """What one replay agent sent and had acknowledged."""

    acked: Dict[int, set] = field(default_factory=dict)  # version -> acknowledged chunk indices
    complete: List[int] = field(default_factory=list)  # versions acknowledged complete
    latencies_ms: List[float] = field(default_factory=list)
    gaussians_acked: int = 0
    retries: int = 0
    keyframes: int = 0
    errors: List[str] = field(default_factory=list)
    codes: Dict[str, int] = field(default_factory=dict)  # status codes of failed calls (retried or not)

    def failed(self, e) -> None:
        """Count a failed call's status code."""
        name = e.code().name if hasattr(e, "code") else type(e).__name__
        self.codes[name] = self.codes.get(name, 0) + 1


RETRYABLE_CODES = ("UNAVAILABLE", "DEADLINE_EXCEEDED")


def backoff(attempt: int, first_s: float = 0.05, max_s: float = 2.0) -> float:
    """Delay before retry ``attempt`` (1, 2, ...): ``first_s`` doubling up to ``max_s`` seconds."""
    return min(max_s, first_s * 2 ** (attempt - 1))


def push_version(stub, grpc, fusion_pb2, aid: str, v: int, chunks: List[bytes], counts: List[int],
                 full: int, per_call: int, log: AgentLog, timeout_s: float, give_up: float) -> bool:
    """Upload one version, resuming from GetUploadStatus after failures (:func:`resume_upload`, at most ``per_call``
    chunks per call), retried with :func:`backoff` until ``give_up`` (monotonic s). True when complete."""
    header = fusion_pb2.UploadHeader(agent_id=aid, map_version=v, n_chunks=len(chunks), full_map_gaussians=full)
    first_sent: Dict[int, float] = {}
    acked = log.acked.setdefault(v, set())
    attempts = 0  # consecutive failed calls: exponential backoff (a database outage lasts seconds)

    def sending(batch: List[int]) -> None:
        now = time.monotonic()
        for i in batch:
            first_sent.setdefault(i, now)

    def acknowledged(batch: List[int], ack) -> None:
        nonlocal attempts
        t = time.monotonic()
        attempts = 0
        stored = set(ack.stored)
        for i in batch:
            if i in stored and i not in acked:
                acked.add(i)
                log.gaussians_acked += counts[i]
                log.latencies_ms.append(1000.0 * (t - first_sent[i]))

    while time.monotonic() < give_up:
        try:
            if resume_upload(stub, header, chunks, timeout_s=timeout_s, batch_bytes=None, chunks_per_call=per_call,
                             on_send=sending, on_ack=acknowledged).complete:
                log.complete.append(v)
                return True
        except grpc.RpcError as e:
            log.failed(e)
            if e.code().name not in RETRYABLE_CODES:
                log.errors.append(f"v{v}: {e.code().name}: {e.details()}")
                return False
            log.retries += 1
            attempts += 1
            time.sleep(backoff(attempts))
    log.errors.append(f"v{v}: gave up")
    return False


def agent_main(i: int, target: str, make, args, frames: list, stop: threading.Event, log: AgentLog,
               barrier: threading.Barrier) -> None:
    aid = f"robot-{i:02d}"
    ch = grpc.insecure_channel(target, channel_options())
    stub = fusion_pb2_grpc.FusionStub(ch)
    try:
        stub.OpenSession(fusion_pb2.OpenSessionRequest(agent_id=aid, task_text=f"inspect zone {i}",
                                                       intrinsics=intrinsics_to_proto(frames[0].intrinsics)),
                         timeout=30, wait_for_ready=True)
        barrier.wait(120)
        rng = np.random.default_rng(i)
        time.sleep(rng.uniform(0, args.interval))  # agents start out of phase
        v = 0
        full = len(make.src)
        while not stop.is_set():
            v += 1
            t_next = time.monotonic() + args.interval
            chunks = encode_subset(make(i, v), aid, v, chunk_gaussians=args.chunk_gaussians, quant=QuantConfig())
            counts = [peek_header(c).count for c in chunks]
            if not push_version(stub, grpc, fusion_pb2, aid, v, chunks, counts, full, args.chunks_per_call, log,
                                10.0, time.monotonic() + 60):
                break
            if args.keyframe_every and v % args.keyframe_every == 0:
                f = frames[(v // args.keyframe_every + i) % len(frames)]
                msg = keyframe_to_proto(aid, f)
                msg.frame_id = v
                give_up, attempt = time.monotonic() + 60, 0
                while True:
                    try:
                        stub.UploadKeyframes(iter([msg]), timeout=10)
                        log.keyframes += 1
                        break
                    except grpc.RpcError as e:
                        log.failed(e)
                        if e.code().name not in RETRYABLE_CODES or time.monotonic() > give_up:
                            raise
                        log.retries += 1
                        attempt += 1
                        time.sleep(backoff(attempt))
            stop.wait(max(0.0, t_next - time.monotonic()))
    except Exception as e:  # noqa: BLE001 - reported in the results
        log.errors.append(f"{type(e).__name__}: {e}")
    finally:
        ch.close()


# ------------------------------------------------------------------------------------ database outage
class DbOutage:
    """Makes the PostgreSQL store unreachable for the replicas and brings it back: cuts a TCP relay of this
    process that the replicas connect through (:class:`tests._relay.TcpRelay`; the default, safe on a
    shared cluster), or runs ``stop_cmd`` / ``start_cmd`` (e.g. ``pg_ctlcluster 15 main stop|start``)."""

    def __init__(self, store_dsn: str, stop_cmd: Optional[str] = None, start_cmd: Optional[str] = None):
        self.stop_cmd, self.start_cmd = stop_cmd, start_cmd
        self.relay = None
        if not (stop_cmd and start_cmd):
            u = urlsplit(store_dsn)
            self.relay = TcpRelay((u.hostname or "127.0.0.1", u.port or 5432))
        self.mode = "relay cut" if self.relay is not None else f"{stop_cmd!r} / {start_cmd!r}"

    def dsn(self, dsn: str) -> str:
        """``dsn`` as the replicas use it (through the relay, if any)."""
        if self.relay is None:
            return dsn

        u = urlsplit(dsn)
        auth = u.netloc.rpartition("@")[0]
        return urlunsplit(u._replace(netloc=(auth + "@" if auth else "") + f"127.0.0.1:{self.relay.port}"))

    def begin(self) -> None:
        """The database goes away. Raises subprocess.CalledProcessError when the stop command fails."""
        if self.relay is not None:
            self.relay.cut()
        else:
            subprocess.run(self.stop_cmd, shell=True, check=True)

    def end(self) -> None:
        """The database comes back. Raises subprocess.CalledProcessError when the start command fails."""
        if self.relay is not None:
            self.relay.restore()
        else:
            subprocess.run(self.start_cmd, shell=True, check=True)

    def close(self) -> None:
        """Stop relaying (the relay mode); the command mode leaves the database as ``end`` left it."""
        if self.relay is not None:
            self.relay.cut()


def wait_serving(reps: List["Replica"], timeout_s: float) -> Optional[float]:
    """Seconds until every replica answers ``GetStats`` (which reads the store), or None after ``timeout_s``."""
    t0 = time.monotonic()
    chans = [grpc.insecure_channel(f"127.0.0.1:{r.port}") for r in reps]
    try:
        todo = list(range(len(reps)))
        while todo:
            for k in list(todo):
                try:
                    fusion_pb2_grpc.FusionStub(chans[k]).GetStats(fusion_pb2.StatsRequest(), timeout=5)
                    todo.remove(k)
                except grpc.RpcError:
                    pass
            if todo:
                if time.monotonic() - t0 > timeout_s:
                    return None
                time.sleep(0.1)
        return time.monotonic() - t0
    finally:
        for ch in chans:
            ch.close()


# ------------------------------------------------------------------------------------ main
def parse_args(argv=None):
    p = argparse.ArgumentParser(prog="python -m bench.fleet", description=__doc__.split("\n\n")[0])
    p.add_argument("--agents", type=int, default=32)
    p.add_argument("--replicas", type=int, default=2)
    p.add_argument("--duration", type=float, default=40.0, help="seconds of pushing (bounded run)")
    p.add_argument("--kill-at", type=float, default=0.5, help="fraction of --duration when a replica is SIGKILLed "
                   "(after the database outage, if any)")
    p.add_argument("--db-outage", type=float, default=0.0, metavar="S",
                   help="make PostgreSQL unreachable for S seconds under the replicas (0 = no outage); --duration "
                        "grows to cover it")
    p.add_argument("--db-outage-at", type=float, default=0.25, help="fraction of --duration when the outage starts")
    p.add_argument("--db-stop-cmd", default=None,
                   help="shell command stopping PostgreSQL for the outage, e.g. 'pg_ctlcluster 15 main stop' (with "
                        "--db-start-cmd); default: the replicas reach the database through a TCP relay of this "
                        "process that the bench cuts (connections dropped, new ones refused), so a shared cluster "
                        "keeps serving its other users")
    p.add_argument("--db-start-cmd", default=None, help="shell command starting PostgreSQL again after the outage")
    p.add_argument("--interval", type=float, default=2.0, help="seconds between an agent's map versions")
    p.add_argument("--keyframe-every", type=int, default=2, help="a keyframe every k versions (0 = none)")
    p.add_argument("--team-map", action="store_true",
                   help="keep the replicas' team map refined while the fleet pushes (off: the bench measures ingest "
                        "and Fuse; the team map's refinement would compete for the cores, and its vote shares the "
                        "replica's incremental vote, so a Fuse after it finds nothing left to re-vote)")
    p.add_argument("--rooms", type=int, default=1, help="copies of the mapped room making up the site (1 = one room)")
    p.add_argument("--share", type=float, default=0.04, help="fraction of the site map in one agent's subset")
    p.add_argument("--drift", type=float, default=0.05, help="metres the ROI centre moves per version")
    p.add_argument("--chunk-gaussians", type=int, default=1000)
    p.add_argument("--chunks-per-call", type=int, default=1)
    p.add_argument("--store", default=os.environ.get("GAUSSLITE_FUSION_STORE") or os.environ.get("GAUSSLITE_TEST_PG_DSN"),
                   help="postgresql:// DSN (env GAUSSLITE_FUSION_STORE or GAUSSLITE_TEST_PG_DSN)")
    p.add_argument("--ply", default=None, help="source map PLY (from `gausslite map`); default: map the synthetic scene")
    p.add_argument("--dataset", default=None, help="posed RGB-D sequence for mapping and keyframes (default: synthetic)")
    p.add_argument("--map-frames", type=int, default=6)
    p.add_argument("--map-iters", type=int, default=6)
    p.add_argument("--keyframe-downscale", type=float, default=4.0)
    p.add_argument("--work", default=str(REPO / "runs" / "fleet"), help="scratch folder (scene, cached map, logs)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=str(RESULTS / "fleet.json"))
    return p.parse_args(argv)


def _usage_error(args) -> Optional[str]:
    """Why the arguments are unusable (no PostgreSQL DSN, fewer than 2 replicas, ...), or None."""
    if not args.store or not args.store.startswith(("postgresql://", "postgres://")):
        return ("bench.fleet: needs a PostgreSQL DSN: --store postgresql://user:pw@127.0.0.1:5432/db "
                "(or $GAUSSLITE_FUSION_STORE / $GAUSSLITE_TEST_PG_DSN)")
    if args.agents < 1 or args.replicas < 2:
        return "bench.fleet: needs --agents >= 1 and --replicas >= 2"
    if bool(args.db_stop_cmd) != bool(args.db_start_cmd):
        return "bench.fleet: --db-stop-cmd and --db-start-cmd go together"
    return None


def _site(args) -> tuple:
    """The site map, the keyframes, the source map's size and the agents' :class:`SubsetMaker` (printed)."""
    src = source_map(args)
    frames = keyframes(args)
    n_map = len(src)
    src = tile_site(src, args.rooms)
    make = SubsetMaker(src, args.agents, args.share, args.drift, args.seed)
    print(f"source map: {n_map} Gaussians, site of {args.rooms} room(s): {len(src)}; {args.agents} agents x "
          f"{make.k} Gaussians per subset", flush=True)
    return src, frames, n_map, make


def _acks_so_far(logs: List[AgentLog]) -> int:
    """Chunks acknowledged to every agent so far."""
    return sum(len(x) for lg in logs for x in lg.acked.values())


def _start_agents(args, target: str, make, frames: list, logs: List[AgentLog]) -> tuple:
    """Start the replay agents; returns (their stop event, their threads) once every one has opened its session."""
    stop = threading.Event()
    barrier = threading.Barrier(args.agents + 1)
    threads = [threading.Thread(target=agent_main, args=(i, target, make, args, frames, stop, logs[i], barrier),
                                daemon=True) for i in range(args.agents)]
    for t in threads:
        t.start()
    barrier.wait(300)
    return stop, threads


def _db_outage(args, outage: DbOutage, reps: List[Replica], logs: List[AgentLog], t0: float) -> dict:
    """At ``--db-outage-at`` of the run, the database goes away for ``--db-outage`` seconds; returns the outage's
    figures (acks during it, replicas' recovery, acks in the 2 s after)."""
    time.sleep(max(0.0, t0 + args.duration * args.db_outage_at - time.monotonic()))
    pids = [r.proc.pid for r in reps]
    acks_before = _acks_so_far(logs)
    outage.begin()
    t_cut = time.monotonic()
    print(f"database unreachable ({outage.mode}) at {t_cut - t0:.1f}s for {args.db_outage:.0f}s", flush=True)
    time.sleep(args.db_outage)
    outage.end()
    t_back = time.monotonic()
    acks_during = _acks_so_far(logs) - acks_before
    recovered = wait_serving(reps, 120.0)
    acks_mark = _acks_so_far(logs)
    time.sleep(2.0)
    out_res = {"db_outage_s": round(t_back - t_cut, 2), "db_outage_mode": outage.mode,
               "db_outage_at_s": round(t_cut - t0, 2), "acks_during_outage": int(acks_during),
               "replicas_serving_after_s": None if recovered is None else round(recovered, 2),
               "replicas_not_restarted": [r.proc.pid for r in reps] == pids
                                         and all(r.proc.poll() is None for r in reps),
               "acks_in_2s_after_recovery": int(_acks_so_far(logs) - acks_mark)}
    print(f"database back at {t_back - t0:.1f}s; replicas serving after "
          f"{out_res['replicas_serving_after_s']}s", flush=True)
    return out_res


def _kill_and_restart(args, reps: List[Replica], t0: float) -> tuple:
    """At ``--kill-at`` of the run, SIGKILL the last replica and start it again; returns (it, restart seconds)."""
    time.sleep(max(0.0, t0 + args.duration * args.kill_at - time.monotonic()))
    victim = reps[-1]
    victim.kill()
    t_kill = time.monotonic()
    victim.start()
    restart_s = time.monotonic() - t_kill
    print(f"SIGKILLed {victim.name} at {t_kill - t0:.1f}s; restarted on port {victim.port} in {restart_s:.1f}s",
          flush=True)
    return victim, restart_s


def _verify_stored(args, reps: List[Replica], logs: List[AgentLog], make) -> tuple:
    """Chunks acknowledged but not stored (``lost``), and each agent's final subset exactly as it sent it."""
    lost = 0
    sent_subsets = {}
    with FusionClient(f"127.0.0.1:{reps[0].port}", timeout_s=30) as c0:
        stats = c0.stats()
        for i, lg in enumerate(logs):
            aid = f"robot-{i:02d}"
            if not lg.complete:
                lost += sum(len(s) for s in lg.acked.values())
                continue
            vf = max(lg.complete)
            st = c0.upload_status(aid, vf)
            lost += len(lg.acked.get(vf, set()) - set(st.stored))
            if stats["agents"].get(aid, {}).get("latest_map_version") != vf:
                lost += len(lg.acked.get(vf, set()))
            # the subset exactly as the agent sent it (same deterministic encoding)
            sent_subsets[aid] = assemble(encode_subset(make(i, vf), aid, vf, chunk_gaussians=args.chunk_gaussians,
                                                       quant=QuantConfig()))[0]
    return lost, sent_subsets


def _fuse_on(rep: Replica) -> tuple:
    """A ``vote`` Fuse on ``rep``: (its result, its seconds end to end)."""
    with FusionClient(f"127.0.0.1:{rep.port}", timeout_s=60) as c:
        t = time.monotonic()
        res = c.fuse("vote", timeout_s=600)
        return res, time.monotonic() - t


def _fuse_stage(args, reps: List[Replica], victim: Replica, logs: List[AgentLog], make, src, target: str,
                sent_subsets: dict) -> tuple:
    """Full votes, then three one-agent updates each followed by an incremental vote, the fused map downloaded
    from another replica and a local :func:`voxel_vote` of what was sent; returns (fulls, incs, fused, local,
    local vote seconds)."""
    # full votes: each replica's first Fuse (no voted map yet: every agent is voted)
    fulls = [_fuse_on(victim), _fuse_on(reps[0])]
    # incremental: after one agent's update, the next Fuse on the same replica re-votes that agent
    incs = []
    for upd in (len(logs) - 1, len(logs) // 2, 0):
        aid = f"robot-{upd:02d}"
        v_new = max(logs[upd].complete or [0]) + 1
        sub = make(upd, v_new)
        with FusionClient(target, timeout_s=30) as c:
            c.upload_subset(aid, v_new, sub, full_map_gaussians=len(src), chunk_gaussians=args.chunk_gaussians,
                            quant=QuantConfig())
        sent_subsets[aid] = assemble(encode_subset(sub, aid, v_new, chunk_gaussians=args.chunk_gaussians,
                                                   quant=QuantConfig()))[0]
        incs.append(_fuse_on(victim))
    inc_res = incs[-1][0]
    with FusionClient(f"127.0.0.1:{reps[0].port}", timeout_s=60) as c:  # download from another replica
        fused = c.download_fused(inc_res.fused_version)
    local, _ = voxel_vote(sent_subsets, float(inc_res.voxel_size), contest_radius=int(inc_res.contest_radius))
    local_s = []
    for _ in range(3):
        t = time.perf_counter()
        voxel_vote(sent_subsets, float(inc_res.voxel_size), contest_radius=int(inc_res.contest_radius))
        local_s.append(time.perf_counter() - t)
    return fulls, incs, fused, local, local_s


@dataclass
class _Measured:
    """What one fleet run measured, before it is summarised into the results."""

    run_s: float
    lost: int
    same_stats: bool
    victim: Replica
    restart_s: float
    fulls: list
    incs: list
    fused: object
    local: object
    local_s: List[float]
    out_res: dict


def _run_fleet(args, reps: List[Replica], outage: Optional[DbOutage], logs: List[AgentLog], make, src,
               frames: list) -> _Measured:
    """Start the replicas and agents, run the outage (if any) and the replica kill, stop the agents, verify the
    store, fuse, and stop the replicas (SIGTERM)."""
    for r in reps:
        r.start()
    target = "ipv4:" + ",".join(f"127.0.0.1:{r.port}" for r in reps)
    stop, threads = _start_agents(args, target, make, frames, logs)
    t0 = time.monotonic()
    print(f"{args.agents} agents pushing to {args.replicas} replicas for {args.duration:.0f}s", flush=True)
    out_res = _db_outage(args, outage, reps, logs, t0) if outage is not None else {}
    victim, restart_s = _kill_and_restart(args, reps, t0)
    time.sleep(max(0.0, args.duration - (time.monotonic() - t0)))
    stop.set()
    for t in threads:
        t.join(120)
    run_s = time.monotonic() - t0

    # ---- verification: everything acknowledged is stored, replicas agree
    lost, sent_subsets = _verify_stored(args, reps, logs, make)
    stubs = []
    for r in reps:
        ch = grpc.insecure_channel(f"127.0.0.1:{r.port}")
        stubs.append((ch, fusion_pb2_grpc.FusionStub(ch)))
    same_stats = len({s.GetStats(fusion_pb2.StatsRequest(), timeout=30).SerializeToString(deterministic=True)
                      for _, s in stubs}) == 1

    # ---- fusion: full vote on the restarted replica (empty voted map), then one agent's update
    fulls, incs, fused, local, local_s = _fuse_stage(args, reps, victim, logs, make, src, target, sent_subsets)
    for ch, _ in stubs:
        ch.close()
    for r in reps:
        r.kill(signal.SIGTERM)
    return _Measured(run_s, lost, same_stats, victim, restart_s, fulls, incs, fused, local, local_s, out_res)


def _results(args, logs: List[AgentLog], reps: List[Replica], outage: Optional[DbOutage], n_map: int, src, make,
             m: _Measured) -> dict:
    """The results JSON of a run: acks, losses, latencies, vote times, checks, settings and goals."""
    fulls, incs, inc_res = m.fulls, m.incs, m.incs[-1][0]
    lat = np.array([x for lg in logs for x in lg.latencies_ms]) if any(lg.latencies_ms for lg in logs) \
        else np.array([float("nan")])
    acks = int(sum(len(s) for lg in logs for s in lg.acked.values()))
    res = {
        "agents": args.agents, "replicas": args.replicas, "duration_s": round(m.run_s, 2),
        "acks": acks, "lost": int(m.lost),
        "ack_latency_ms_p50": round(float(np.percentile(lat, 50)), 2),
        "ack_latency_ms_p99": round(float(np.percentile(lat, 99)), 2),
        "ack_latency_ms_max": round(float(lat.max()), 2),
        "gaussians_per_s": round(sum(lg.gaussians_acked for lg in logs) / m.run_s, 1),
        "versions_complete": int(sum(len(lg.complete) for lg in logs)),
        "keyframes": int(sum(lg.keyframes for lg in logs)),
        "client_retries": int(sum(lg.retries for lg in logs)),
        "agent_errors": [e for lg in logs for e in lg.errors][:20],
        "failed_call_codes": {k: sum(lg.codes.get(k, 0) for lg in logs)
                              for k in sorted({c for lg in logs for c in lg.codes})},
        "fuse_full_s": round(float(np.median([r.vote_seconds for r, _ in fulls])), 4),
        "fuse_incremental_s": round(float(np.median([r.vote_seconds for r, _ in incs])), 4),
        "fuse_full_s_each": [round(float(r.vote_seconds), 4) for r, _ in fulls],
        "fuse_incremental_s_each": [round(float(r.vote_seconds), 4) for r, _ in incs],
        "fuse_full_agents_revoted": [int(r.agents_revoted) for r, _ in fulls],
        "fuse_incremental_agents_revoted": [int(r.agents_revoted) for r, _ in incs],
        "fuse_incremental_was_incremental": all(bool(r.incremental) for r, _ in incs),
        "fuse_full_total_s": round(float(np.median([r.seconds for r, _ in fulls])), 4),
        "fuse_incremental_total_s": round(float(np.median([r.seconds for r, _ in incs])), 4),
        "fuse_full_rpc_s": round(float(np.median([t for _, t in fulls])), 4),
        "fuse_incremental_rpc_s": round(float(np.median([t for _, t in incs])), 4),
        "voxel_vote_local_s": round(float(np.median(m.local_s)), 4),
        "fused_gaussians": int(inc_res.n_gaussians),
        "fused_equals_local_vote": bool(m.fused.equals(m.local)),
        "replicas_agree_getstats": bool(m.same_stats),
        "killed_replica": m.victim.name, "restart_s": round(m.restart_s, 2),
        "peak_rss_mb": {r.name: round(max(r.peak_rss_mb), 1) for r in reps},
        "peak_rss_mb_per_incarnation": {r.name: [round(x, 1) for x in r.peak_rss_mb] for r in reps},
        "source_gaussians": n_map, "site_gaussians": len(src), "rooms": args.rooms, "subset_gaussians": make.k,
        "source": (args.ply or f"synthetic scene, {args.map_frames} frames x {args.map_iters} iters")
                  + f", site of {args.rooms} room copies",
        "chunks_per_call": args.chunks_per_call, "team_map": bool(args.team_map),
        "interval_s": args.interval, "chunk_gaussians": args.chunk_gaussians,
        "machine": f"{os.cpu_count()} CPUs, shared with other jobs (load average "
                   f"{', '.join(f'{x:.1f}' for x in os.getloadavg())} at the end)",
    }
    res["incremental_over_full"] = round(res["fuse_incremental_s"] / max(res["fuse_full_s"], 1e-9), 4)
    res["incremental_over_local_voxel_vote"] = round(res["fuse_incremental_s"] / max(res["voxel_vote_local_s"],
                                                                                       1e-9), 4)
    res.update(m.out_res)
    res["goals"] = {
        "agents>=32": res["agents"] >= 32, "lost==0": res["lost"] == 0,
        "p99<=250ms": res["ack_latency_ms_p99"] <= 250.0,
        "incremental<=0.1*full": res["fuse_incremental_s"] <= 0.1 * res["fuse_full_s"],
    }
    if outage is not None:
        codes = res["failed_call_codes"]
        res["goals"].update({
            "db_outage:no_INTERNAL_or_UNKNOWN": not (codes.get("INTERNAL") or codes.get("UNKNOWN")),
            "db_outage:no_agent_errors": not res["agent_errors"],
            "db_outage:replicas_recovered_without_restart": bool(
                res["replicas_serving_after_s"] is not None and res["replicas_not_restarted"]
                and res["acks_in_2s_after_recovery"] > 0),
        })
    return res


def _write_and_print(args, res: dict, argv=None) -> None:
    """Write ``res`` to ``--out`` (with the run's provenance, :func:`bench._results.write_json`) and print its
    headline figures."""
    out = write_json(Path(args.out), res, "fleet", argv)
    keys = ["agents", "replicas", "acks", "lost", "ack_latency_ms_p50", "ack_latency_ms_p99", "gaussians_per_s",
            "fuse_full_s", "fuse_incremental_s", "voxel_vote_local_s", "incremental_over_full", "fuse_full_rpc_s", "fuse_incremental_rpc_s", "peak_rss_mb",
            "fused_equals_local_vote", "replicas_agree_getstats", "failed_call_codes"]
    keys += [k for k in ("db_outage_s", "db_outage_mode", "acks_during_outage", "replicas_serving_after_s",
                         "replicas_not_restarted", "acks_in_2s_after_recovery") if k in res]
    keys += ["goals"]
    w = max(len(k) for k in keys)
    print("\n".join(f"{k:<{w}}  {res[k]}" for k in keys))
    print(f"wrote {out}")


def main(argv=None) -> int:
    """Run the fleet benchmark (options: ``--help``) and write its JSON to ``--out``. Returns 0 when
    every goal is met (:func:`exit_code`), 1 when one is missed (each printed to stderr; the JSON is
    written anyway), 2 on unusable arguments (no PostgreSQL DSN, fewer than 2 replicas)."""
    args = parse_args(argv)
    error = _usage_error(args)
    if error:
        print(error, file=sys.stderr)
        return 2
    if args.db_outage > 0:  # room for the outage, the recovery and the replica kill after it
        args.duration = max(args.duration, args.duration * args.db_outage_at + args.db_outage + 20.0)
    # lazy: heavy optional dependency, loaded only on this path
    import psycopg

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    src, frames, n_map, make = _site(args)

    schema = f"fleet_{uuid.uuid4().hex[:10]}"
    with psycopg.connect(args.store, autocommit=True) as conn:
        conn.execute(f"CREATE SCHEMA {schema}")
    dsn = args.store + ("&" if "?" in args.store else "?") + f"options=-csearch_path%3D{schema}"
    outage = DbOutage(args.store, args.db_stop_cmd, args.db_start_cmd) if args.db_outage > 0 else None
    rep_dsn = outage.dsn(dsn) if outage is not None else dsn
    reps = [Replica(f"replica{r}", rep_dsn, work, team_map=args.team_map) for r in range(args.replicas)]
    logs = [AgentLog() for _ in range(args.agents)]
    res: dict = {}
    try:
        res = _results(args, logs, reps, outage, n_map, src, make,
                       _run_fleet(args, reps, outage, logs, make, src, frames))
    finally:
        for r in reps:
            r.kill()
        if outage is not None:
            outage.close()
        with psycopg.connect(args.store, autocommit=True) as conn:
            conn.execute(f"DROP SCHEMA IF EXISTS {schema} CASCADE")
    _write_and_print(args, res, argv)
    return exit_code(res)


def missed_goals(res: dict) -> List[str]:
    """The names of the goals in ``res["goals"]`` that were missed (every one when there are none:
    an unevaluated run meets nothing), plus ``fused_equals_local_vote`` when the fused map differs
    from a local vote of what the agents sent (a correctness failure rather than a goal)."""
    goals = res.get("goals") or {"goals evaluated": False}
    missed = [name for name, met in goals.items() if not met]
    if not res.get("fused_equals_local_vote", False):
        missed.append("fused_equals_local_vote")
    return missed


def exit_code(res: dict) -> int:
    """The bench's exit code for results ``res``: 0 when :func:`missed_goals` is empty, else 1 after
    printing each missed goal to stderr (``main`` writes the JSON before, either way)."""
    missed = missed_goals(res)
    for name in missed:
        print(f"bench.fleet: goal missed: {name}", file=sys.stderr)
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
