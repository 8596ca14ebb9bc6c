"""Trust load benchmark: a valid robot's ack latency while other clients try to hold or exhaust the fusion server.

    python -m bench.trust_load                      # 45 s; --seconds, --stalled, --bad-rate, --gaussians

Starts a real fusion server process (``python -m gausslite_services.fusion_server``, SQLite store in ``--work``, 16
handler threads, per-robot tokens stored as salted PBKDF2 records, the costly kind for a wrong token) and, at once:

* ``--stalled`` upload streams (16) from ``--stalled-robots`` misbehaving robots with valid tokens: each sends an
  ``UploadSubset`` header and one chunk, then nothing; when the server ends it, the stream is opened again. The
  server's ``fusion.stream_idle_s`` (``--idle-s``; the server's default when not given) ends a stalled stream with
  DEADLINE_EXCEEDED, its upload-stream caps refuse the ones beyond them with RESOURCE_EXHAUSTED, and a new upload
  that finds every slot taken evicts one (ABORTED);
* ``--bad-rate`` calls per second (50) carrying wrong tokens (``GetStats``, each a fresh random token);
* one valid robot that pushes its ROI subset (``--gaussians`` 2,000 Gaussians, the size of an agent's share, a
  new map version every push) back to back, ``--pause-s`` apart, and times each ``UploadSubset`` call from its
  start to the ack; a refused attempt (any status but OK) is counted and sent again.

Reports the valid robot's ack latency p50/p95/p99/max (goal: p99 ≤ 250 ms, and no refused push), how many stalled
streams the deadline ended, how many were refused and how many evicted, what the wrong-token calls got, and the
server's peak RSS.
Writes ``bench/results/trust_load.json`` (``--out``) and the table beside it (``.md``). Exit code 1 when the goal
is missed. The figure depends on the machine's load: run it alone.
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
import subprocess
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results"
ACK_P99_GOAL_MS = 250.0


def parse_args(argv=None) -> argparse.Namespace:
    """Command-line options (``--help``)."""
    p = argparse.ArgumentParser(prog="python -m bench.trust_load", description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=45.0, help="measured time (default 45)")
    p.add_argument("--stalled", type=int, default=16, help="stalled upload streams kept open (default 16)")
    p.add_argument("--stalled-robots", type=int, default=1,
                   help="robot identities the stalled streams come from, round robin (default 1)")
    p.add_argument("--bad-rate", type=float, default=50.0, help="wrong-token calls per second (default 50)")
    p.add_argument("--gaussians", type=int, default=2000, help="Gaussians in the valid robot's subset")
    p.add_argument("--pause-s", type=float, default=0.05, help="pause between the valid robot's pushes")
    p.add_argument("--idle-s", type=float, default=None, help="the server's fusion.stream_idle_s (default: its own)")
    p.add_argument("--workers", type=int, default=16, help="the server's handler threads")
    p.add_argument("--token-scheme", default="pbkdf2", choices=("pbkdf2", "sha256"),
                   help="how the token file stores the tokens (default pbkdf2: a wrong token costs derivations)")
    p.add_argument("--work", default=str(REPO / "runs" / "trust_load"), help="scratch folder (store, token file, log)")
    p.add_argument("--out", default=str(RESULTS / "trust_load.json"))
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p.parse_args(argv)


def random_subset(n: int, seed: int):
    """A random ``GaussianArrays`` of ``n`` Gaussians (seeded), the stand-in for a robot's ROI subset."""
    # lazy: the wire codec loads only once the benchmark runs, not at --help
    from gausslite.wire.codec import GaussianArrays

    r = np.random.default_rng(seed)
    return GaussianArrays(means=r.uniform(-2, 2, (n, 3)), quats=r.normal(size=(n, 4)),
                          log_scales=r.uniform(-5, -3, (n, 3)), opacity_logits=r.normal(size=n),
                          colors=r.uniform(0, 1, (n, 3)), kappa=r.integers(0, 100, n), active=r.random(n) < 0.5)


def percentiles(values_ms: List[float]) -> Dict[str, Optional[float]]:
    """p50/p95/p99/max of ``values_ms`` (ms; None when empty)."""
    if not values_ms:
        return {"p50": None, "p95": None, "p99": None, "max": None}
    a = np.asarray(values_ms, float)
    return {"p50": float(np.percentile(a, 50)), "p95": float(np.percentile(a, 95)),
            "p99": float(np.percentile(a, 99)), "max": float(a.max())}


def proc_status_mb(pid: int, key: str) -> Optional[float]:
    """``key`` (``VmRSS``, ``VmHWM``) of process ``pid`` from ``/proc/<pid>/status``, in MB; None when unreadable."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None


def start_server(work: Path, tokens_file: Path, workers: int, idle_s: Optional[float],
                 settings: Optional[dict] = None) -> tuple:
    """A fusion server process with per-robot tokens and the ``fusion`` ``settings`` given (plus ``stream_idle_s``
    when ``idle_s`` is set); returns (Popen, address). Raises RuntimeError when it does not come up within 60 s (its
    log is ``work/fusion.log``)."""
    cfg = work / "fusion.json"
    cfg.write_text(json.dumps({**(settings or {}), **({} if idle_s is None else {"stream_idle_s": idle_s})}))
    port_file = work / "port"
    port_file.unlink(missing_ok=True)
    env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"}
    log = open(work / "fusion.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "gausslite_services.fusion_server", "--port", "0", "--port-file",
                             str(port_file), "--data-dir", str(work / "data"), "--agent-tokens", str(tokens_file),
                             "--max-workers", str(workers), "--config", str(cfg), "--log-level", "WARNING"],
                            cwd=str(REPO), env=env, stdout=log, stderr=subprocess.STDOUT)
    log.close()
    deadline = time.monotonic() + 60
    while not port_file.exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            raise RuntimeError(f"the fusion server did not start; see {work / 'fusion.log'}")
        time.sleep(0.05)
    return proc, f"127.0.0.1:{int(port_file.read_text())}"


def stop_server(proc: subprocess.Popen, timeout_s: float = 20.0) -> None:
    """Stop a server process from :func:`start_server`: SIGTERM, then SIGKILL if it has not exited in
    ``timeout_s`` seconds; returns once it has exited."""
    proc.terminate()
    try:
        proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


@dataclass
class _Load:
    """What the load threads and the valid robot record while the benchmark runs; ``lock`` guards what the threads
    share, ``stop`` ends them."""

    stop: threading.Event = field(default_factory=threading.Event)
    lock: threading.Lock = field(default_factory=threading.Lock)
    stalled_codes: Counter = field(default_factory=Counter)
    stalled_durations: List[float] = field(default_factory=list)
    bad_codes: Counter = field(default_factory=Counter)
    acks_ms: List[float] = field(default_factory=list)
    ack_times: List[float] = field(default_factory=list)  # seconds since the robot's first push, per ack
    valid_errors: List[str] = field(default_factory=list)


def _fresh_store_and_tokens(args: argparse.Namespace) -> tuple:
    """An empty store and a new token file in ``--work``; returns (work folder, token file, the stalled robots' ids,
    token per robot)."""
    from gausslite_services.common import auth

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    import shutil

    shutil.rmtree(work / "data", ignore_errors=True)  # a fresh store: map versions start at 1
    tokens_file = work / "fusion_tokens.json"
    tokens_file.unlink(missing_ok=True)
    stalled_ids = [f"stalled-{i}" for i in range(max(1, args.stalled_robots))]
    tok = {a: auth.issue_token(tokens_file, a, scheme=args.token_scheme) for a in ["valid", *stalled_ids]}
    return work, tokens_file, stalled_ids, tok


def _open_sessions(address: str, tok: Dict[str, str], agents: List[str]) -> None:
    """Open a session for each of ``agents`` once the server serves."""
    from gausslite.camera import Intrinsics
    from gausslite_services.fusion_server.client import FusionClient

    intr = Intrinsics(300.0, 300.0, 159.5, 119.5, 320, 240)
    for a in agents:
        with FusionClient(address, token=tok[a], timeout_s=30) as c:
            c.wait_ready(60)
            c.open_session(a, "find the chair", intr)


def _stalled_stream(address: str, agent: str, chunks: list, metadata: tuple, seconds: float, load: _Load) -> None:
    """One stalled upload of ``agent``: a header and one chunk, then nothing; opened again when the server ends it,
    until ``load.stop``."""
    import grpc

    from gausslite_rpc import fusion_pb2, fusion_pb2_grpc

    stop = load.stop
    ch = grpc.insecure_channel(address)  # a connection of its own, as a separate client would have
    st = fusion_pb2_grpc.FusionStub(ch)
    while not stop.is_set():
        def requests():
            yield fusion_pb2.UploadSubsetRequest(header=fusion_pb2.UploadHeader(
                agent_id=agent, map_version=1, n_chunks=len(chunks), full_map_gaussians=400))
            yield fusion_pb2.UploadSubsetRequest(chunk=chunks[0])
            stop.wait()  # then nothing until the benchmark ends

        t0 = time.monotonic()
        try:
            st.UploadSubset(requests(), timeout=seconds + 120, metadata=metadata)
            code = "OK"
        except grpc.RpcError as e:
            code = e.code().name
        with load.lock:
            load.stalled_codes[code] += 1
            if code == "DEADLINE_EXCEEDED":
                load.stalled_durations.append(time.monotonic() - t0)
        if code != "DEADLINE_EXCEEDED":
            stop.wait(0.5)  # refused: try again a little later
    ch.close()


def _wrong_tokens(stub, bad_rate: float, load: _Load) -> None:
    """``GetStats`` calls with a fresh random token, ``bad_rate`` per second until ``load.stop``; counts their
    status codes."""
    import grpc

    from gausslite_rpc import fusion_pb2

    stop = load.stop
    period = 1.0 / bad_rate
    nxt = time.monotonic()
    pending = []
    while not stop.is_set():
        bad = (("authorization", f"Bearer {secrets.token_urlsafe(32)}"),)
        pending.append(stub.GetStats.future(fusion_pb2.StatsRequest(), timeout=10, metadata=bad))
        done = [f for f in pending if f.done()]
        for f in done:
            pending.remove(f)
            with load.lock:
                load.bad_codes[f.code().name] += 1
        nxt += period
        stop.wait(max(0.0, nxt - time.monotonic()))
    for f in pending:
        try:
            f.result(timeout=10)
            code = "OK"
        except grpc.RpcError as e:
            code = e.code().name
        except grpc.FutureTimeoutError:
            code = "NO_ANSWER"
        load.bad_codes[code] += 1


def _start_load(args: argparse.Namespace, address: str, stub, stalled_ids: List[str], md: dict,
                load: _Load) -> List[threading.Thread]:
    """Start the stalled streams and the wrong-token calls; returns their threads after they have run for 1 s."""
    from gausslite.wire.codec import encode_subset

    stalled_chunks = {a: encode_subset(random_subset(400, 7), a, 1, max_chunk_bytes=4096) for a in stalled_ids}
    threads = []
    for i in range(args.stalled):
        agent = stalled_ids[i % len(stalled_ids)]
        threads.append(threading.Thread(target=_stalled_stream, daemon=True,
                                        args=(address, agent, stalled_chunks[agent], md[agent], args.seconds, load)))
    if args.bad_rate > 0:
        threads.append(threading.Thread(target=_wrong_tokens, args=(stub, args.bad_rate, load), daemon=True))
    for t in threads:
        t.start()
    time.sleep(1.0)  # the stalled streams are open and the wrong tokens flowing before the robot pushes
    return threads


def _push_valid(args: argparse.Namespace, stub, metadata: tuple, load: _Load) -> None:
    """The valid robot: push its subset back to back for ``--seconds``, timing each ack (a refused push is counted
    and sent again)."""
    import grpc

    from gausslite.wire.codec import encode_subset
    from gausslite_rpc import fusion_pb2

    sub = random_subset(args.gaussians, 1)
    version = 0
    t_start = time.monotonic()
    t_end = t_start + args.seconds
    bar = None
    if not args.no_progress:
        from tqdm import tqdm

        bar = tqdm(total=int(args.seconds), desc="bench.trust_load", unit="s")
    failed_last = False
    while time.monotonic() < t_end:
        if not failed_last:  # a refused push is sent again (same version), as the agent's pusher does
            version += 1
        chunks = encode_subset(sub, "valid", version)
        msgs = [fusion_pb2.UploadSubsetRequest(header=fusion_pb2.UploadHeader(
            agent_id="valid", map_version=version, n_chunks=len(chunks), full_map_gaussians=50_000))]
        msgs += [fusion_pb2.UploadSubsetRequest(chunk=c) for c in chunks]
        t0 = time.perf_counter()
        try:
            ack = stub.UploadSubset(iter(msgs), timeout=30, metadata=metadata)
            dt = (time.perf_counter() - t0) * 1000.0
            failed_last = not ack.complete
            if ack.complete:
                load.acks_ms.append(dt)
                load.ack_times.append(time.monotonic() - t_start)
            else:
                load.valid_errors.append(f"v{version}: incomplete ack")
        except grpc.RpcError as e:
            failed_last = True
            load.valid_errors.append(f"v{version}: {e.code().name}: {e.details()}")
        if bar is not None:
            bar.n = min(int(args.seconds), int(args.seconds - (t_end - time.monotonic())))
            bar.refresh()
        time.sleep(args.pause_s)
    if bar is not None:
        bar.close()


def _health(address: str, token: str) -> str:
    """``SERVING`` when the server answers a readiness check within 5 s, else the error."""
    from gausslite_services.fusion_server.client import FusionClient

    health = None
    with FusionClient(address, token=token, timeout_s=10) as c:
        try:
            c.wait_ready(5)
            health = "SERVING"
        except Exception as e:  # noqa: BLE001 - recorded, not raised
            health = f"{type(e).__name__}: {e}"
    return health


def _results(args: argparse.Namespace, load: _Load, n_stalled_robots: int, rss_start: Optional[float],
             rss_peak: Optional[float], health: str) -> dict:
    """The benchmark's results (the JSON) from what ``load`` recorded, with the goals met or missed."""
    acks_ms, valid_errors, stalled_codes = load.acks_ms, load.valid_errors, load.stalled_codes
    lat = percentiles(acks_ms)
    idle = args.idle_s
    if idle is None:
        from gausslite.config import FusionSettings

        idle = FusionSettings().stream_idle_s
    goals = {f"ack p99 <= {ACK_P99_GOAL_MS:g} ms": lat["p99"] is not None and lat["p99"] <= ACK_P99_GOAL_MS,
             "no refused push": not valid_errors, "health SERVING after": health == "SERVING"}
    return {"seconds": args.seconds, "stalled_streams": args.stalled, "stalled_robots": n_stalled_robots,
            "bad_rate_per_s": args.bad_rate, "gaussians": args.gaussians, "workers": args.workers,
            "token_scheme": args.token_scheme, "stream_idle_s": idle,
            "pushes": len(acks_ms) + len(valid_errors), "acks": len(acks_ms),
            "ack_ms": lat, "valid_errors": valid_errors[:20],
            "slowest_acks": [{"t_s": round(load.ack_times[i], 2), "ms": round(acks_ms[i], 1)}
                             for i in sorted(np.argsort(acks_ms)[::-1][:10].tolist())],
            "stalled_ended_by_deadline": int(stalled_codes.get("DEADLINE_EXCEEDED", 0)),
            "stalled_refused": int(stalled_codes.get("RESOURCE_EXHAUSTED", 0)),
            "stalled_evicted": int(stalled_codes.get("ABORTED", 0)),
            "stalled_codes": dict(stalled_codes),
            "stalled_s_median": float(np.median(load.stalled_durations)) if load.stalled_durations else None,
            "bad_calls": int(sum(load.bad_codes.values())), "bad_codes": dict(load.bad_codes),
            "rss_mb_start": rss_start, "rss_mb_peak": rss_peak, "health_after": health, "goals": goals}


def run(args: argparse.Namespace) -> dict:
    """Run the benchmark (module docstring) and return its results."""
    import grpc

    from gausslite_rpc import fusion_pb2_grpc

    work, tokens_file, stalled_ids, tok = _fresh_store_and_tokens(args)
    proc, address = start_server(work, tokens_file, args.workers, args.idle_s)
    md = {a: (("authorization", f"Bearer {t}"),) for a, t in tok.items()}
    load = _Load()
    rss_start = None
    try:
        _open_sessions(address, tok, ["valid", *stalled_ids])
        rss_start = proc_status_mb(proc.pid, "VmRSS")
        channel = grpc.insecure_channel(address)
        stub = fusion_pb2_grpc.FusionStub(channel)
        threads = _start_load(args, address, stub, stalled_ids, md, load)
        _push_valid(args, stub, md["valid"], load)
        rss_peak = proc_status_mb(proc.pid, "VmHWM")
        load.stop.set()
        for t in threads:
            t.join(30)
        health = _health(address, tok["valid"])
        channel.close()
    finally:
        load.stop.set()
        stop_server(proc)
    return _results(args, load, len(stalled_ids), rss_start, rss_peak, health)


def table(res: dict) -> str:
    """The results as a Markdown table."""
    f = lambda v: "n/a" if v is None else f"{v:.1f}"  # noqa: E731
    a = res["ack_ms"]
    rows = [("valid robot: pushes acknowledged", f"{res['acks']} of {res['pushes']} attempts ({res['gaussians']} Gaussians)"),
            ("ack latency p50 / p95 / p99 / max (ms)", f"{f(a['p50'])} / {f(a['p95'])} / {f(a['p99'])} / {f(a['max'])}"),
            ("stalled streams ended by the deadline", f"{res['stalled_ended_by_deadline']} (after {f(res['stalled_s_median'])} s "
                                                      f"median; stream_idle_s {res['stream_idle_s']:g})"),
            ("stalled streams refused (RESOURCE_EXHAUSTED)", str(res["stalled_refused"])),
            ("stalled streams evicted for another upload (ABORTED)", str(res.get("stalled_evicted", 0))),
            ("wrong-token calls", f"{res['bad_calls']}: " + ", ".join(f"{k} {v}" for k, v in sorted(res["bad_codes"].items()))),
            ("server RSS start / peak (MB)", f"{f(res['rss_mb_start'])} / {f(res['rss_mb_peak'])}"),
            ("health after", str(res["health_after"]))]
    rows += [(f"goal: {k}", "met" if v else "MISSED") for k, v in res["goals"].items()]
    return "\n".join(["| quantity | value |", "|---|---|"] + [f"| {k} | {v} |" for k, v in rows])


def main(argv=None) -> int:
    """``python -m bench.trust_load``: run, print the table, write the JSON and Markdown. Returns 1 when a goal
    is missed."""
    from bench._results import write_results

    args = parse_args(argv)
    res = run(args)
    details = (f": {res['seconds']:g} s, {res['stalled_streams']} stalled streams from {res['stalled_robots']} "
               f"robot(s), {res['bad_rate_per_s']:g} wrong-token calls/s, {res['workers']} handler threads, "
               f"{res['token_scheme']} token records")
    write_results(Path(args.out), "trust_load", argv, details, table(res), res)
    return 0 if all(res["goals"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
