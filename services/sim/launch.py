"""The simulation's agents and processes: which dataset and task each agent gets (:func:`plan_agents`), the
service commands mirroring ``deploy/docker-compose.yml`` (:func:`service_commands`), the child processes
(:class:`ProcessGroup`), their health (:func:`wait_healthy`) and the gRPC clients of a run (:func:`connect_clients`).
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Dict, List, Optional

from gausslite.config import GaussLiteConfig
from gausslite.datasets import detect_layout, load_dataset
from gausslite.datasets.annotations import load_annotations
from gausslite.mission.config import AgentConfig
from gausslite.team import AgentPlan
from gausslite_services.agent.client import AgentClient
from gausslite_services.cli.cmd_health import check_health
from gausslite_services.fusion_server.client import FusionClient

log = logging.getLogger("gausslite_services.sim")  # one logger for the whole simulation

REPO = Path(__file__).resolve().parents[2]
AGENT_NAMES = ("agent_a", "agent_b")


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that is free on ``host`` right now (bind to port 0, read it, close)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def plan_agents(dataset: str, cfg: GaussLiteConfig, task_ids: Optional[List[str]] = None) -> List[AgentPlan]:
    """The two agents' datasets and tasks.

    Synthetic default scene (``dataset`` holds ``agent_a``/``agent_b``): each agent its own trajectory.
    Other datasets: both agents traverse the same frames. Tasks: ``task_ids`` or the config's
    ``sim.tasks`` pair for the scene (``synthetic`` / ``room0``), else the first two tasks of tasks.json.

    Raises:
        ValueError: the scene has no annotations or fewer than two tasks. KeyError: unknown task id.
    """
    root = Path(dataset)
    split = all((root / n).is_dir() for n in AGENT_NAMES)
    paths = [str(root / n) for n in AGENT_NAMES] if split else [str(root)] * 2
    ann = load_annotations(paths[0])
    if ann is None or len(ann.tasks) < 1:
        raise ValueError(f"{dataset}: the simulation needs objects.json/tasks.json with tasks")
    known = [t.id for t in ann.tasks]

    tasks_cfg = cfg.sim.tasks
    if not task_ids:
        for key in ("synthetic", "room0"):
            pair = tasks_cfg.get(key) or []
            if len(pair) == 2 and all(t in known for t in pair):
                task_ids = list(pair)
                break
    if not task_ids:
        if len(known) < 2:
            raise ValueError(f"{dataset}: need two tasks, tasks.json has {known}")
        task_ids = known[:2]
    if len(task_ids) != 2:
        raise ValueError(f"need exactly two task ids, got {task_ids}")
    return [AgentPlan(name, path, tid, ann.task_by_id(tid).text)
            for name, path, tid in zip(AGENT_NAMES, paths, task_ids)]


def check_bags(plans: List[AgentPlan], agent_cfg: AgentConfig) -> None:
    """Open every ROS bag the agents will replay, so a bad bag fails with its one clear error before any
    process starts (``BagError`` lists the bag's topics and TF frames). ``agent_cfg``: the typed
    :class:`gausslite.mission.config.AgentConfig` (max_frames, bag options)."""
    for path in sorted({p.dataset for p in plans}):
        if detect_layout(path)[0] == "bag":
            ds = load_dataset(path, max_frames=agent_cfg.max_frames, bag=agent_cfg.bag)
            ds.close()


class ProcessGroup:
    """Child processes started by the simulation; :meth:`stop_all` terminates every one of them
    (SIGTERM, wait ``grace_s``, then SIGKILL). Only processes started here are touched."""

    def __init__(self, log_dir: Path):
        self.log_dir = log_dir
        self.procs: Dict[str, subprocess.Popen] = {}
        self._files = []

    def start(self, name: str, argv: List[str], env: Dict[str, str]) -> subprocess.Popen:
        """Start ``argv`` with ``env`` added to the environment; output goes to ``logs/<name>.log``."""
        self.log_dir.mkdir(parents=True, exist_ok=True)
        f = open(self.log_dir / f"{name}.log", "w")
        self._files.append(f)
        full_env = {**os.environ, **env, "PYTHONUNBUFFERED": "1"}
        full_env["PYTHONPATH"] = os.pathsep.join([str(REPO)] + [p for p in [os.environ.get("PYTHONPATH")] if p])
        p = subprocess.Popen(argv, stdout=f, stderr=subprocess.STDOUT, env=full_env, cwd=str(REPO),
                             start_new_session=True)
        self.procs[name] = p
        log.info("started %s (pid %d): %s", name, p.pid, " ".join(argv[2:]))
        return p

    def check_alive(self) -> None:
        """Raise RuntimeError naming a child that exited early (with the tail of its log)."""
        for name, p in self.procs.items():
            rc = p.poll()
            if rc is not None:
                tail = (self.log_dir / f"{name}.log").read_text(errors="replace")[-1500:]
                raise RuntimeError(f"{name} exited with code {rc}; log tail:\n{tail}")

    def stop_all(self, grace_s: float = 10.0) -> None:
        """Terminate all children (idempotent)."""
        for name, p in self.procs.items():
            if p.poll() is None:
                try:
                    p.send_signal(signal.SIGTERM)
                except ProcessLookupError:
                    pass
        deadline = time.monotonic() + grace_s
        for name, p in self.procs.items():
            try:
                p.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("%s (pid %d) did not stop in %.0f s: killing", name, p.pid, grace_s)
                p.kill()
                p.wait(5)
        for f in self._files:
            f.close()
        self._files.clear()


def _cli(*args: str) -> List[str]:
    return [sys.executable, "-m", "gausslite.cli", *args]


def service_commands(config_path: Path, plans: List[AgentPlan], ports: Dict[str, int], data_dir: Path,
                     host: str = "127.0.0.1") -> Dict[str, tuple]:
    """``name → (argv, env)`` of the four services, mirroring the compose file's commands/environment."""
    parser_addr, fusion_addr = f"{host}:{ports['parser']}", f"{host}:{ports['fusion_server']}"
    cmds = {
        "parser": (_cli("serve", "parser", "--host", host, "--port", str(ports["parser"])), {}),
        "fusion_server": ([sys.executable, "-m", "gausslite_services.fusion_server", "--host", host,
                           "--port", str(ports["fusion_server"]), "--config", str(config_path)],
                          {"GAUSSLITE_DATA_DIR": str(data_dir / "fusion")}),
    }
    for p in plans:
        env = {"GAUSSLITE_AGENT_ID": p.name, "GAUSSLITE_PARSER_ADDR": parser_addr,
               "GAUSSLITE_FUSION_ADDR": fusion_addr, "GAUSSLITE_AGENT_DATASET": p.dataset,
               "GAUSSLITE_AGENT_TASK": p.task, "GAUSSLITE_AGENT_TASK_ID": p.task_id,
               "GAUSSLITE_DATA_DIR": str(data_dir / "agents")}
        cmds[p.name] = (_cli("serve", "agent", "--host", host, "--port", str(ports[p.name]),
                             "--config", str(config_path)), env)
    return cmds


def wait_healthy(target: str, service: str, timeout_s: float, group: Optional[ProcessGroup] = None) -> None:
    """Poll the health service of ``target`` until ``service`` is SERVING.

    Raises:
        TimeoutError: not SERVING in time. RuntimeError: a child process died meanwhile.
    """
    deadline = time.monotonic() + timeout_s
    status = "?"
    while time.monotonic() < deadline:
        if group is not None:
            group.check_alive()
        status = check_health(target, service, timeout_s=1.0)
        if status == "SERVING":
            return
        time.sleep(0.2)
    raise TimeoutError(f"{service} at {target} not healthy after {timeout_s:.0f} s (last: {status})")


def start_services(out: Path, config_path: Path, plans: List[AgentPlan], group: ProcessGroup,
                   token: Optional[str]) -> Dict[str, str]:
    """Start the parser, the fusion server and the agents in ``group`` on free loopback ports, each waited for
    until its health service reports SERVING (120 s, agents 180 s).

    Returns:
        service name → ``host:port``.
    Raises:
        TimeoutError: a service not healthy in time. RuntimeError: a process died.
    """
    ports = {n: free_port() for n in ("parser", "fusion_server", *AGENT_NAMES)}
    addrs = {n: f"127.0.0.1:{p}" for n, p in ports.items()}
    cmds = service_commands(config_path, plans, ports, out / "data")
    tok = {"GAUSSLITE_TOKEN": token} if token else {}
    for name in ("parser", "fusion_server"):
        group.start(name, cmds[name][0], {**cmds[name][1], **tok})
    wait_healthy(addrs["parser"], "gausslite.v1.Parser", 120, group)
    wait_healthy(addrs["fusion_server"], "gausslite.v1.Fusion", 120, group)
    for p in plans:
        group.start(p.name, cmds[p.name][0], {**cmds[p.name][1], **tok})
    for p in plans:
        wait_healthy(addrs[p.name], "gausslite.v1.Agent", 180, group)
    return addrs


def connect_clients(addrs: Dict[str, str], plans: List[AgentPlan], token: Optional[str],
                    fusion_token: Optional[str], clients: list):
    """Clients of the fusion server (waited for until ready, 60 s) and of each agent (``addrs``: service name →
    ``host:port``; each plan's ``address`` is set). Every client is appended to ``clients`` as soon as it exists,
    so the caller closes it whatever fails next.

    Returns:
        ``(fusion, agents)``: the ``FusionClient`` and agent id → ``AgentClient``.
    """
    for p in plans:
        p.address = addrs[p.name]
    fusion = FusionClient(addrs["fusion_server"], token=fusion_token or token, timeout_s=120.0)
    clients.append(fusion)
    fusion.wait_ready(60)
    agents = {p.name: AgentClient(p.address, token=token) for p in plans}
    clients.extend(agents.values())
    return fusion, agents


def close_all(clients: list, group: ProcessGroup, previous_sigterm) -> None:
    """Close the gRPC clients (errors ignored), stop the started processes and restore the SIGTERM handler."""
    for c in clients:
        try:
            c.close()
        except Exception:
            pass
    group.stop_all()
    if previous_sigterm is not None:
        signal.signal(signal.SIGTERM, previous_sigterm)


def main_thread() -> bool:
    """Whether the caller runs on the interpreter's main thread (where signal handlers may be installed)."""
    return threading.current_thread() is threading.main_thread()


def raise_interrupt(signum, frame):
    """A signal handler (SIGTERM) that stops the simulation as Ctrl-C does. Raises: KeyboardInterrupt."""
    raise KeyboardInterrupt(f"signal {signum}")
