"""Robot-/operator-side client of ``gausslite.v1.Agent`` (deadlines on every call).

Example::

    from gausslite_services.agent.client import AgentClient
    with AgentClient("127.0.0.1:50061") as c:
        c.wait_ready()
        m = c.start_mission("Prepare to pick up the plant on the side table",
                            annotations_path="/data/scene")            # or dataset_path=... (replay)
        c.stream_frames(m.mission_id, frames)                           # gausslite Frame objects
        summary = c.finish(m.mission_id)                                # final push + ROI PSNR
"""

from __future__ import annotations

import time
from typing import Iterable, Optional

import grpc
import numpy as np
from grpc_health.v1 import health_pb2, health_pb2_grpc

from gausslite_rpc import agent_pb2, agent_pb2_grpc
from gausslite_services.agent.frames import encode_frame
from gausslite_services.common.client_tls import default_client_tls
from gausslite_services.common.errors import raises_typed_errors

SERVICE_NAME = "gausslite.v1.Agent"
CLIENT_MAX_MESSAGE_BYTES = 64 * 1024 * 1024


@raises_typed_errors
class AgentClient:
    """Synchronous client (thread-safe: one channel).

    Args:
        target (str): ``host:port``.
        token (str | None): bearer token.
        root_cert (bytes | None): PEM CA certificate(s) → TLS; None → plaintext.
        client_cert (bytes | None), client_key (bytes | None): PEM client certificate and key, for an agent
            that requires client certificates (mutual TLS). With none of the three TLS arguments: the process
            defaults (:mod:`gausslite_services.common.client_tls`), else plaintext.
        timeout_s (float): deadline of unary calls (seconds); :meth:`finish` and
            :meth:`stream_frames` take their own.
    Raises:
        ValueError: only one of the client certificate and key.
    """

    def __init__(self, target: str, *, token: Optional[str] = None, root_cert: Optional[bytes] = None,
                 timeout_s: float = 30.0, client_cert: Optional[bytes] = None, client_key: Optional[bytes] = None):
        self.target = target
        self.timeout_s = float(timeout_s)
        self._md = (("authorization", f"Bearer {token}"),) if token else None
        if root_cert is None and client_cert is None and client_key is None:
            root_cert, client_cert, client_key = default_client_tls()
        if (client_cert is None) != (client_key is None):
            raise ValueError("mutual TLS needs both the client certificate and its key")
        opts = [("grpc.max_send_message_length", CLIENT_MAX_MESSAGE_BYTES),
                ("grpc.max_receive_message_length", CLIENT_MAX_MESSAGE_BYTES)]
        tls = root_cert is not None or client_cert is not None
        self._channel = (grpc.secure_channel(target, grpc.ssl_channel_credentials(root_cert, client_key, client_cert),
                                             opts) if tls else grpc.insecure_channel(target, opts))
        self.stub = agent_pb2_grpc.AgentStub(self._channel)
        self._health = health_pb2_grpc.HealthStub(self._channel)

    def wait_ready(self, timeout_s: float = 30.0) -> None:
        """Poll the health service until ``gausslite.v1.Agent`` is SERVING.

        Raises:
            TimeoutError: not SERVING within ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        last = "no answer"
        while time.monotonic() < deadline:
            try:
                r = self._health.Check(health_pb2.HealthCheckRequest(service=SERVICE_NAME), timeout=1.0)
                if r.status == health_pb2.HealthCheckResponse.SERVING:
                    return
                last = health_pb2.HealthCheckResponse.ServingStatus.Name(r.status)
            except grpc.RpcError as e:
                last = f"{e.code().name}: {e.details()}"
            time.sleep(0.1)
        raise TimeoutError(f"agent {self.target} not ready after {timeout_s:.1f}s: {last}")

    def start_mission(self, task_text: str, *, task_id: str = "", dataset_path: str = "",
                      annotations_path: str = "", fusion_address: str = "", agent_id: str = "",
                      mission_id: str = "", T_world_map=None,
                      timeout_s: Optional[float] = None) -> agent_pb2.StartMissionResponse:
        """Start a mission; a ``mission_id`` with a checkpoint in the agent's data dir resumes it
        (``response.resumed``). ``T_world_map``: this mission's map frame in the team's world frame, a (4, 4) rigid
        transform (array or nested rows, metres) sent as 16 row-major numbers; None = the agent's setting
        (docs/team.md). Raises grpc.RpcError (INVALID_ARGUMENT, FAILED_PRECONDITION, UNAVAILABLE)."""
        T = [] if T_world_map is None else np.asarray(T_world_map, np.float64).reshape(-1).tolist()
        req = agent_pb2.StartMissionRequest(task_text=task_text, task_id=task_id, dataset_path=dataset_path,
                                            annotations_path=annotations_path, fusion_address=fusion_address,
                                            agent_id=agent_id, mission_id=mission_id, T_world_map=T)
        return self.stub.StartMission(req, timeout=timeout_s or max(self.timeout_s, 60.0), metadata=self._md)

    def stream_frames(self, mission_id: str, frames: Iterable, *, color_format: str = ".png",
                      timeout_s: float = 600.0) -> agent_pb2.StreamFramesResponse:
        """Encode and stream ``frames`` (``gausslite.datasets.Frame``) to a streaming mission.

        Raises:
            grpc.RpcError: INVALID_ARGUMENT (malformed frame), NOT_FOUND, FAILED_PRECONDITION, ...
        """
        msgs = (encode_frame(f, mission_id, color_format=color_format) for f in frames)
        return self.stub.StreamFrames(msgs, timeout=timeout_s, metadata=self._md)

    def stream_messages(self, messages: Iterable[agent_pb2.FrameMsg], timeout_s: float = 600.0):
        """Stream ready-made ``FrameMsg`` messages (e.g. from a robot driver that encodes itself)."""
        return self.stub.StreamFrames(iter(messages), timeout=timeout_s, metadata=self._md)

    def status(self, mission_id: str = "") -> agent_pb2.MissionStatus:
        """Mission progress (empty id: the agent's current mission). Raises grpc.RpcError NOT_FOUND."""
        return self.stub.GetStatus(agent_pb2.MissionRequest(mission_id=mission_id), timeout=self.timeout_s,
                                   metadata=self._md)

    def wait_state(self, states: Iterable[int], mission_id: str = "", timeout_s: float = 600.0,
                   poll_s: float = 0.5, progress=None) -> agent_pb2.MissionStatus:
        """Poll :meth:`status` until its state is in ``states`` (``agent_pb2.MISSION_STATE_*``).

        Args:
            progress: optional callback ``(MissionStatus) -> None`` on every poll.
        Raises:
            TimeoutError: not reached in ``timeout_s``. RuntimeError: the mission FAILED.
        """
        want = set(states)
        deadline = time.monotonic() + timeout_s
        while True:
            st = self.status(mission_id)
            if progress:
                progress(st)
            if st.state in want:
                return st
            if st.state == agent_pb2.MISSION_STATE_FAILED:
                raise RuntimeError(f"agent {st.agent_id} mission {st.mission_id} failed: {st.last_error}")
            if time.monotonic() > deadline:
                raise TimeoutError(f"agent {self.target}: state {agent_pb2.MissionState.Name(st.state)} after "
                                   f"{timeout_s:.0f}s ({st.frames_mapped} frames mapped)")
            time.sleep(poll_s)

    def update_task(self, mission_id: str, task_text: str, task_id: str = "",
                    timeout_s: Optional[float] = None) -> agent_pb2.UpdateTaskResponse:
        """Give a running mission a new task (the map re-targets and keeps what it mapped). Raises grpc.RpcError
        (NOT_FOUND, INVALID_ARGUMENT, FAILED_PRECONDITION, UNAVAILABLE)."""
        req = agent_pb2.UpdateTaskRequest(mission_id=mission_id, task_text=task_text, task_id=task_id)
        return self.stub.UpdateTask(req, timeout=timeout_s or max(self.timeout_s, 60.0), metadata=self._md)

    def finish(self, mission_id: str = "", *, skip_push: bool = False, skip_eval: bool = False,
               timeout_s: float = 600.0) -> agent_pb2.MissionSummary:
        """Final push and summary. Raises grpc.RpcError (NOT_FOUND, DEADLINE_EXCEEDED)."""
        return self.stub.Finish(agent_pb2.FinishRequest(mission_id=mission_id, skip_push=skip_push,
                                                        skip_eval=skip_eval), timeout=timeout_s, metadata=self._md)

    def close(self) -> None:
        """Close the channel."""
        self._channel.close()

    def __enter__(self) -> "AgentClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
