"""The simulation's team runner (:class:`ServiceTeam`): the services as processes on loopback (or already running
ones, attached), the robots' missions followed and finished over gRPC. It is the
:class:`gausslite.team.harness.TeamRunner` that :func:`gausslite.team.harness.run_team` drives for ``gausslite sim``.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Dict, List, Optional

import grpc

from gausslite.mission.scoring import MissionSummaryData
from gausslite.team import AgentPlan
from gausslite_services.sim.launch import ProcessGroup, close_all, connect_clients, start_services
from gausslite_services.sim.summary import status_from_proto, summary_from_proto


class ServiceTeam:
    """A team whose robots are agent services, beside a parser and a fusion server.

    Started (:meth:`start`) it launches the four services as processes in ``group`` on free loopback ports, each
    waited for until healthy (:func:`~gausslite_services.sim.launch.start_services`), or, with ``attach``, connects to
    running ones, and opens a client of the fusion server (:attr:`fusion`) and of each agent (:attr:`agents`). The
    agents start their missions themselves (their dataset and task come with their environment).

    Args:
        out: the simulation's output folder (the services' data under ``out/data``).
        config_path: the configuration file the services read (``--config``).
        plans: the robots. group: the child processes (their logs in ``out/logs``).
        token: bearer token of the services; fusion_token: this client's own token for the fusion server (default
            ``token``).
        attach: service name (``parser``, ``fusion_server``, each agent) → ``host:port`` of running services, or None
            to start them.
    """

    def __init__(self, out: Path, config_path: Path, plans: List[AgentPlan], group: ProcessGroup,
                 token: Optional[str] = None, fusion_token: Optional[str] = None,
                 attach: Optional[Dict[str, str]] = None) -> None:
        self.out, self.config_path, self.plans, self.group = out, config_path, plans, group
        self.token, self.fusion_token, self.attach = token, fusion_token, attach
        self.fusion = None
        self.agents: Dict[str, object] = {}
        self._clients: list = []

    def start(self) -> None:
        """Start (or attach to) the services and connect; idempotent. Raises TimeoutError (a service not healthy in
        time) and RuntimeError (a process died)."""
        if self.fusion is not None:
            return
        addrs = (start_services(self.out, self.config_path, self.plans, self.group, self.token)
                 if self.attach is None else dict(self.attach))
        self.fusion, self.agents = connect_clients(addrs, self.plans, self.token, self.fusion_token, self._clients)

    def progress(self) -> Dict[str, Optional[dict]]:
        """Agent id → its mission's status (``state`` a :class:`~gausslite.mission.state.MissionState`), None for an
        attached agent that has no mission yet (``NOT_FOUND``).

        Raises:
            RuntimeError: a started process exited. grpc.RpcError: a status call failed otherwise.
        """
        self.group.check_alive()
        out: Dict[str, Optional[dict]] = {}
        for name, client in self.agents.items():
            try:
                out[name] = status_from_proto(client.status())
            except grpc.RpcError as e:
                if e.code() != grpc.StatusCode.NOT_FOUND:
                    raise
                out[name] = None
        return out

    def finish(self, timeout_s: Optional[float]) -> Dict[str, MissionSummaryData]:
        """Each agent's ``Finish`` (its final push), one after the other, all within ``timeout_s`` (None: 600 s; each
        call has at least 10 s); agent id → its summary (:func:`~gausslite_services.sim.summary.summary_from_proto`).
        Raises grpc.RpcError (``DEADLINE_EXCEEDED`` past the bound)."""
        deadline = time.monotonic() + (600.0 if timeout_s is None else timeout_s)
        return {n: summary_from_proto(c.finish(timeout_s=max(10.0, deadline - time.monotonic())))
                for n, c in self.agents.items()}

    def close(self, previous_sigterm=None) -> None:
        """Close the clients, stop the started processes and restore ``previous_sigterm`` (when given) as the SIGTERM
        handler; idempotent."""
        close_all(self._clients, self.group, previous_sigterm)
        self._clients.clear()
