"""Agent service: a thin gRPC server over :class:`gausslite.mission.AgentRuntime` (paper
Sec. III-E).

``gausslite.v1.Agent``:

* ``StartMission`` — parses the task with the parser service (``parser_address``; empty → the
  in-process rule parser), opens a mission, and either replays ``dataset_path`` or waits for frames; its
  ``T_world_map`` (or the setting ``agent.frame.T_world_map``) puts the mission's poses in the team's world frame
  (``docs/team.md``).
* ``StreamFrames`` — a client stream of posed RGB-D frames (:mod:`gausslite_services.agent.frames` validates
  each: INVALID_ARGUMENT for malformed frames, wrong shapes, NaN poses). With keyframe ingest (default)
  the call never blocks the sender: headers are validated on arrival, keyframe selection keeps the
  newest candidate, and only keyframes are decoded (by the mapping worker).
* ``StartMission`` with a ``mission_id`` whose checkpoint is in ``<data_dir>/<agent_id>/<mission_id>``
  resumes that mission (``docs/live.md``).
* ``GetStatus`` / ``Finish`` — progress; final push + summary (ROI PSNR on its own task when the scene
  has annotations).

Status codes: INVALID_ARGUMENT (bad input), NOT_FOUND (unknown mission), FAILED_PRECONDITION (mission
finished/replaying, no relevance source), UNAVAILABLE (parser unreachable), DEADLINE_EXCEEDED (Finish
did not complete within the client's deadline), PERMISSION_DENIED (a ``StartMission`` naming a fusion server, an
agent id or a path outside what the agent is configured for: ``docs/security.md``). Health, reflection, bounded message sizes, bearer
token and TLS come from :mod:`gausslite_services.common.server`; on shutdown the health service goes
NOT_SERVING, in-flight calls get the grace period and running missions are closed.

The agent's settings and their reading from the environment are :mod:`gausslite_services.agent.settings`' (re-exported
here); the messages made from a mission's status and summary are :mod:`gausslite_services.agent.convert`'s.
"""

from __future__ import annotations

import json
import logging
import os
import re
import sys
import threading
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional

import grpc
from pydantic import ValidationError

from gausslite.datasets.annotations import load_annotations
from gausslite.mission import AgentRuntime, MissionError, MissionState, build_mission, replay_dataset
from gausslite.mission.state import ACTIVE as ACTIVE_STATES
from gausslite.mission.team_frame import parse_T_world_map
from gausslite.parser import TaskParser
from gausslite_rpc import agent_pb2, agent_pb2_grpc, parser_pb2, parser_pb2_grpc
from gausslite_services.agent.convert import status_proto, summary_proto
from gausslite_services.agent.frames import FrameError, decode_frame, validate_frame
from gausslite_services.agent.metrics import agent_registry
# the settings and their reading live in a module of their own; their names import from here as before
from gausslite_services.agent.settings import ENV, AgentSettings, settings_from_env  # noqa: F401
from gausslite_services.common.auth import read_secret
from gausslite_services.common.errors import status_for
from gausslite_services.common.server import (MalformedMessage, RunningServer, ServerOptions, build_server,
                                              run_until_signalled)
from gausslite_services.fusion_server.client import FusionClient
from gausslite_services.parser.server import graph_to_proto

log = logging.getLogger(__name__)

SERVICE_NAME = "gausslite.v1.Agent"
#: Frames of up to ~4K RGB-D (PNG colour + 16-bit depth) fit; larger ones → RESOURCE_EXHAUSTED.
MAX_MESSAGE_BYTES = 64 * 1024 * 1024
MAX_TASK_BYTES = 2048
_MISSION_ID = re.compile(r"[A-Za-z0-9_.-]{1,64}")


def _valid_id(value: str) -> bool:
    """An agent or mission id: 1..64 characters of ``[A-Za-z0-9_.-]``, not only dots (it names a folder of the
    data dir)."""
    return bool(_MISSION_ID.fullmatch(value)) and value.strip(".") != ""


def _check_task_text(task_text: str) -> None:
    """Raises ValueError for an empty or oversized task text or one with a NUL character (the fusion server and
    PostgreSQL refuse it: the mission could never push)."""
    if not task_text.strip():
        raise ValueError("task_text is empty")
    if len(task_text.encode("utf-8")) > MAX_TASK_BYTES:
        raise ValueError(f"task_text longer than {MAX_TASK_BYTES} bytes")
    if "\x00" in task_text:
        raise ValueError("task_text contains a NUL character")


def _abort(context, method: str, code: grpc.StatusCode, message: str) -> None:
    """Log a rejected call and abort it with ``code`` (raises, as ``context.abort`` does)."""
    log.warning("rejected %s from %s: %s: %s", method, context.peer(), code.name, message)
    context.abort(code, message)


class CallerNotAllowed(Exception):
    """A ``StartMission`` asked for what only the agent's configuration decides (PERMISSION_DENIED)."""


def _channel(address: str, root_cert: Optional[str]) -> grpc.Channel:
    opts = [("grpc.max_receive_message_length", 4 * 1024 * 1024)]
    if root_cert:
        return grpc.secure_channel(address, grpc.ssl_channel_credentials(Path(root_cert).read_bytes()), opts)
    return grpc.insecure_channel(address, opts)


def parse_task_remote(address: str, text: str, token: Optional[str] = None, root_cert: Optional[str] = None,
                      timeout_s: float = 30.0):
    """Parse ``text`` with the parser service at ``address`` (waits for it to be ready up to the deadline).

    Returns:
        gausslite_rpc.common_pb2.TaskGraph.
    Raises:
        grpc.RpcError: the parser's error (INVALID_ARGUMENT, UNAVAILABLE, DEADLINE_EXCEEDED...).
    """
    md = (("authorization", f"Bearer {token}"),) if token else None
    with _channel(address, root_cert) as ch:
        return parser_pb2_grpc.ParserStub(ch).Parse(parser_pb2.ParseRequest(task_text=text), timeout=timeout_s,
                                                    metadata=md, wait_for_ready=True)


class AgentServicer(agent_pb2_grpc.AgentServicer):
    """Implements ``gausslite.v1.Agent``; holds the missions of this agent (one runs at a time)."""

    def __init__(self, settings: AgentSettings):
        """Args: settings (AgentSettings)."""
        self.settings = settings
        self.missions: Dict[str, AgentRuntime] = {}
        self.current: Optional[str] = None
        self._lock = threading.Lock()
        self._clients: List[object] = []

    # ------------------------------------------------------------------ helpers
    def _parse(self, text: str):
        s = self.settings
        if s.parser_address:
            return parse_task_remote(s.parser_address, text, s.token, s.root_cert, s.parser_timeout_s)

        return TaskParser().parse(text)

    def _parser_failed(self, context, method: str, e: grpc.RpcError) -> None:
        """Abort ``method`` after the parser service failed: its INVALID_ARGUMENT passes through, anything else is
        UNAVAILABLE; a deadline says how long the agent waited for which parser."""
        code = e.code() if e.code() == grpc.StatusCode.INVALID_ARGUMENT else grpc.StatusCode.UNAVAILABLE
        s = self.settings
        waited = (f" (waited {s.parser_timeout_s:g} s for the parser at {s.parser_address} to become ready and answer)"
                  if e.code() == grpc.StatusCode.DEADLINE_EXCEEDED else "")
        _abort(context, method, code, f"parser service: {e.code().name}: {e.details()}{waited}")

    def _fusion_client(self, address: str):
        if not address:
            return None

        s = self.settings
        try:
            token = s.fusion_token or (read_secret(s.fusion_token_file) if s.fusion_token_file else None) or s.token
            read = lambda path: Path(path).read_bytes() if path else None  # noqa: E731
            c = FusionClient(address, token=token, root_cert=read(s.root_cert), client_cert=read(s.tls_client_cert),
                             client_key=read(s.tls_client_key))
        except (OSError, ValueError) as e:  # a credential file gone or broken since start-up
            log.error("agent %s: fusion credentials unusable: %s", s.agent_id, e)
            raise MissionError(f"fusion credentials unusable: {e}") from None
        self._clients.append(c)
        return c

    def _save(self, rt: AgentRuntime) -> None:
        if not self.settings.data_dir:
            return
        out = Path(self.settings.data_dir) / rt.agent_id / rt.mission_id
        out.mkdir(parents=True, exist_ok=True)
        rt.mapper.gmap.save_ply(out / "map.ply")
        if rt.summary is not None:
            (out / "summary.json").write_text(json.dumps(rt.summary.as_dict(), indent=2))
        log.info("agent %s: mission %s written to %s", rt.agent_id, rt.mission_id, out)

    def _mission(self, mission_id: str, context) -> AgentRuntime:
        with self._lock:
            mid = mission_id or self.current
            rt = self.missions.get(mid) if mid else None
        if rt is None:
            context.abort(grpc.StatusCode.NOT_FOUND,
                          f"unknown mission {mission_id!r}" if mission_id else "no mission has been started")
        return rt

    def start_mission(self, task_text: str, *, task_id: str = "", dataset_path: str = "",
                      annotations_path: str = "", fusion_address: str = "", agent_id: str = "",
                      auto_finish: bool = False, mission_id: str = "", T_world_map=()) -> AgentRuntime:
        """Create and start a mission (used by ``StartMission`` and by the boot-time auto start).

        With a data dir, the mission checkpoints into ``<data_dir>/<agent_id>/<mission_id>/``; a
        ``mission_id`` whose folder holds a checkpoint resumes from it. ``T_world_map``: 16 row-major numbers, this
        mission's map frame in the team's world frame (overrides ``agent.frame.T_world_map``; empty: the setting;
        docs/team.md).

        Raises:
            ValueError: empty/oversized task or one with a NUL character, bad dataset, missing relevance source, unknown task id,
                a ``T_world_map`` that is not 16 numbers of a rigid transform.
            CallerNotAllowed: a ``fusion_address`` or ``agent_id`` other than the configured ones, a
                ``dataset_path`` or ``annotations_path`` outside the data roots (:meth:`_check_caller_choices`).
            MissionError: another mission is still mapping; ``mission_id`` already used in this process;
                the fusion credential files became unreadable.
            FileNotFoundError: dataset/annotations path missing.
            grpc.RpcError: the parser service failed.
        """
        s, cfg = self.settings, self.settings.config
        _check_task_text(task_text)
        if mission_id and not _valid_id(mission_id):
            raise ValueError(f"mission_id {mission_id!r} must be 1..64 characters of [A-Za-z0-9_.-], not only dots")
        if agent_id and not _valid_id(agent_id):
            raise ValueError(f"agent_id {agent_id[:80]!r} must be 1..64 characters of [A-Za-z0-9_.-], not only dots")
        self._check_caller_choices(fusion_address, agent_id, dataset_path, annotations_path)
        T = parse_T_world_map(T_world_map, "T_world_map")  # overrides agent.frame.T_world_map when given
        with self._lock:
            if mission_id and mission_id in self.missions:
                raise MissionError(f"mission {mission_id} already exists in this agent process "
                                   f"({self.missions[mission_id].state.lower()})")
            cur = self.missions.get(self.current) if self.current else None
            if cur is not None and cur.state in ACTIVE_STATES:
                raise MissionError(f"mission {cur.mission_id} is still {cur.state.lower()}; Finish it first")
        dataset = None
        annotations = None
        if dataset_path:
            if not Path(dataset_path).exists():
                raise FileNotFoundError(f"dataset_path not found on the agent: {dataset_path}")
            # the sensor profile's loader options and mapper defaults under whatever the agent's YAML sets
            dataset, cfg, profile = replay_dataset(dataset_path, cfg)
            log.info("agent %s: dataset profile %s (%s); mapper %s", agent_id or s.agent_id, profile.name,
                     profile.description, {k: getattr(cfg.mapper, k) for k in profile.mapper} or "defaults")
            annotations = dataset.annotations
        ann_path = annotations_path or (s.annotations_path if not dataset_path else "")
        if ann_path:
            if not Path(ann_path).exists():
                raise FileNotFoundError(f"annotations_path not found on the agent: {ann_path}")
            annotations = load_annotations(ann_path)
        graph = self._parse(task_text)
        fusion = self._fusion_client(fusion_address or s.fusion_address)
        aid = agent_id or s.agent_id
        mid = mission_id or None
        if mid is None and s.data_dir:
            mid = uuid.uuid4().hex[:12]
        ckpt = Path(s.data_dir) / aid / mid if s.data_dir else None
        rt = build_mission(cfg, task_text, graph, agent_id=aid, annotations=annotations, task_id=task_id or None,
                           fusion=fusion, on_finished=self._save, mission_id=mid, checkpoint_dir=ckpt,
                           T_world_map=T, start=True)
        with self._lock:
            self.missions[rt.mission_id] = rt
            self.current = rt.mission_id
        if dataset is not None:
            rt.replay(dataset)
            if auto_finish:
                threading.Thread(target=self._auto_finish, args=(rt,), daemon=True,
                                 name=f"agent-{rt.agent_id}-autofinish").start()
        log.info("agent %s: mission %s started (%s): %r → targets %s anchors %s", rt.agent_id, rt.mission_id,
                 f"replay of {len(dataset)} frames" if dataset is not None else "streaming", task_text,
                 list(graph.targets), list(graph.anchors))
        return rt

    def _auto_finish(self, rt: AgentRuntime) -> None:
        rt.wait_mapped()
        if rt.state != MissionState.FAILED:
            try:
                rt.finish()
            except Exception as e:
                log.error("agent %s: auto finish failed: %s", rt.agent_id, e)

    def data_roots(self) -> List[str]:
        """The folders a caller's ``dataset_path`` / ``annotations_path`` may name (real paths, symlinks
        resolved): ``AgentSettings.data_roots``, and the configured ``dataset`` and ``annotations_path`` (a folder
        itself, a file its parent folder)."""
        s = self.settings
        roots = [os.path.realpath(r) for r in s.data_roots if r]
        for p in (s.dataset, s.annotations_path):
            if p:
                rp = os.path.realpath(p)
                roots.append(rp if os.path.isdir(rp) or not os.path.exists(rp) else os.path.dirname(rp))
        return roots

    def _check_path(self, what: str, path: str) -> None:
        """Raise CallerNotAllowed unless ``path`` resolves (``os.path.realpath``: symlinks followed, ``..``
        removed) to a data root or a path inside one (:meth:`data_roots`). ValueError for a NUL character."""
        if "\x00" in path:
            raise ValueError(f"{what} contains a NUL character")
        real = os.path.realpath(path)
        for root in self.data_roots():
            if os.path.commonpath([real, root]) == root:
                return
        raise CallerNotAllowed(f"{what} {path[:200]!r} is outside the agent's data roots (GAUSSLITE_AGENT_DATA_ROOTS, "
                               "or the configured dataset / annotations folder)")

    def _check_caller_choices(self, fusion_address: str, agent_id: str, dataset_path: str = "",
                              annotations_path: str = "") -> None:
        """A caller of ``StartMission`` picks neither where the agent's credentials go nor whose they are, nor
        which files of the robot it reads.

        Raises:
            CallerNotAllowed: ``fusion_address`` is neither the configured fusion server nor in
                ``AgentSettings.fusion_allow``; ``agent_id`` differs from the configured one (the identity its fusion
                token and certificate stand for); ``dataset_path`` or ``annotations_path`` lies outside the data
                roots (:meth:`data_roots`).
            ValueError: a path with a NUL character.
        """
        s = self.settings
        if fusion_address and fusion_address != s.fusion_address and fusion_address not in s.fusion_allow:
            raise CallerNotAllowed(f"fusion_address {fusion_address[:200]!r} is not a fusion server this agent is "
                                   "configured for (GAUSSLITE_FUSION_ADDR, or GAUSSLITE_FUSION_ALLOW)")
        if agent_id and agent_id != s.agent_id:
            raise CallerNotAllowed(f"agent_id {agent_id[:80]!r}: this agent is {s.agent_id!r} (its fusion identity "
                                   "is configured, not chosen per mission)")
        if dataset_path:
            self._check_path("dataset_path", dataset_path)
        if annotations_path:
            self._check_path("annotations_path", annotations_path)

    # ------------------------------------------------------------------ RPCs
    def StartMission(self, request, context):  # noqa: N802
        try:
            rt = self.start_mission(request.task_text, task_id=request.task_id, dataset_path=request.dataset_path,
                                    annotations_path=request.annotations_path,
                                    fusion_address=request.fusion_address, agent_id=request.agent_id,
                                    mission_id=request.mission_id, T_world_map=request.T_world_map)
        except CallerNotAllowed as e:
            _abort(context, "StartMission", grpc.StatusCode.PERMISSION_DENIED, str(e))
        except (FileNotFoundError, KeyError) as e:
            _abort(context, "StartMission", grpc.StatusCode.INVALID_ARGUMENT,
                   str(e.args[0] if isinstance(e, KeyError) else e))
        except (MissionError, ValueError) as e:
            _abort(context, "StartMission", status_for(e), str(e))
        except OSError as e:  # a path the agent cannot read (too long, a directory, no permission)
            _abort(context, "StartMission", grpc.StatusCode.INVALID_ARGUMENT,
                   f"cannot read a path of the request: {type(e).__name__}: {str(e)[:300]}")
        except grpc.RpcError as e:
            self._parser_failed(context, "StartMission", e)
        except MalformedMessage:
            raise
        except Exception as e:  # noqa: BLE001 - never crash: INTERNAL with the cause logged
            log.exception("StartMission failed")
            _abort(context, "StartMission", grpc.StatusCode.INTERNAL, f"internal error: {type(e).__name__}: {e}")

        g = rt.graph
        gp = g if hasattr(g, "SerializeToString") else graph_to_proto(g)
        return agent_pb2.StartMissionResponse(mission_id=rt.mission_id, graph=gp, agent_id=rt.agent_id,
                                              replay_frames=rt.replay_frames, resumed=rt.resumed_keyframes > 0,
                                              resumed_keyframes=rt.resumed_keyframes)

    def UpdateTask(self, request, context):  # noqa: N802
        rt = self._mission(request.mission_id, context)
        try:
            _check_task_text(request.task_text)
            graph = self._parse(request.task_text)
            rt.update_task(request.task_text, graph, request.task_id or None)
        except KeyError as e:
            _abort(context, "UpdateTask", grpc.StatusCode.INVALID_ARGUMENT, str(e.args[0]))
        except (MissionError, ValueError) as e:
            _abort(context, "UpdateTask", status_for(e), str(e))
        except grpc.RpcError as e:
            self._parser_failed(context, "UpdateTask", e)

        gp = graph if hasattr(graph, "SerializeToString") else graph_to_proto(graph)
        return agent_pb2.UpdateTaskResponse(mission_id=rt.mission_id, graph=gp)

    def StreamFrames(self, request_iterator, context):  # noqa: N802
        rt: Optional[AgentRuntime] = None
        n = 0
        for msg in request_iterator:
            if rt is None:
                rt = self._mission(msg.mission_id, context)
                if rt.replaying or rt.replay_frames:
                    context.abort(grpc.StatusCode.FAILED_PRECONDITION,
                                  f"mission {rt.mission_id} replays a dataset; it takes no streamed frames")
            elif msg.mission_id and msg.mission_id != rt.mission_id:
                context.abort(grpc.StatusCode.INVALID_ARGUMENT,
                              f"frame {msg.frame_id}: mission_id {msg.mission_id!r} differs from the stream's "
                              f"{rt.mission_id!r}")
            t_arrival = time.perf_counter()
            try:
                # keyframe ingest decodes a frame's images only if it becomes a keyframe (worker thread)
                frame = validate_frame(msg) if rt.config.ingest == "keyframes" else decode_frame(msg)
            except FrameError as e:
                log.warning("agent %s mission %s: rejected frame: %s", rt.agent_id, rt.mission_id, e)
                context.abort(grpc.StatusCode.INVALID_ARGUMENT, str(e))
            try:
                while True:
                    try:
                        rt.submit(frame, timeout=1.0, arrival=t_arrival)  # never blocks with keyframe ingest
                        break
                    except Exception as e:  # queue.Full: re-check that the client is still there
                        if isinstance(e, MissionError):
                            raise
                        if not context.is_active():
                            return agent_pb2.StreamFramesResponse()
            except MissionError as e:
                code = status_for(e)
                log.warning("agent %s: StreamFrames %s: %s", rt.agent_id, code.name, e)
                context.abort(code, str(e))
            n += 1
        if rt is None:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, "empty frame stream")
        st = rt.status()
        return agent_pb2.StreamFramesResponse(mission_id=rt.mission_id, frames_received=n,
                                              frames_mapped=st["frames_mapped"])

    @staticmethod
    def _status_proto(st: dict) -> agent_pb2.MissionStatus:
        return status_proto(st)

    def GetStatus(self, request, context):  # noqa: N802
        return self._status_proto(self._mission(request.mission_id, context).status())

    def Finish(self, request, context):  # noqa: N802
        rt = self._mission(request.mission_id, context)
        remaining = context.time_remaining()
        try:
            s = rt.finish(push=not request.skip_push, evaluate=not request.skip_eval,
                          timeout_s=None if remaining is None else max(0.1, remaining - 0.5))
        except TimeoutError as e:
            context.abort(grpc.StatusCode.DEADLINE_EXCEEDED, f"{e}; call Finish again to keep waiting")
        return summary_proto(s)

    def shutdown(self, timeout_s: float) -> List[str]:
        """What SIGTERM does before the process exits: every mission still mapping stops ingest, maps what it holds,
        pushes its final subset (while the link is up: the pusher's retries are bounded by what is left of
        ``timeout_s``), then writes its checkpoint and map to the data dir, so a robot being shut down loses nothing
        it mapped and a restart with the same mission id resumes. Bounded by ``timeout_s`` overall; never raises.

        Returns:
            the mission ids whose final push the fusion server acknowledged.
        """
        deadline = time.monotonic() + max(0.0, timeout_s)
        pushed = []
        for rt in list(self.missions.values()):
            if rt.state not in ACTIVE_STATES:
                continue
            log.info("agent %s: shutting down mission %s: final push and checkpoint", rt.agent_id, rt.mission_id)
            try:
                summary = rt.finish(push=True, evaluate=False, timeout_s=max(0.1, deadline - time.monotonic()))
            except Exception as e:  # noqa: BLE001 - a shutdown step must not stop the others
                log.error("agent %s: mission %s: final push at shutdown failed: %s", rt.agent_id, rt.mission_id, e)
                continue
            if summary.final_push_ok:
                pushed.append(rt.mission_id)
            try:
                if rt.checkpoint_dir is not None:
                    rt.save_checkpoint()
                self._save(rt)
            except Exception as e:  # noqa: BLE001
                log.error("agent %s: mission %s: checkpoint at shutdown failed: %s", rt.agent_id, rt.mission_id, e)
        return pushed

    def close(self) -> None:
        """Close every mission and fusion client (after the server stopped)."""
        for rt in list(self.missions.values()):
            rt.close()
        for c in self._clients:
            try:
                c.close()
            except Exception:
                pass


@dataclass
class RunningAgent:
    """A started agent server: ``running`` (RunningServer) and its ``servicer``."""

    running: RunningServer
    servicer: AgentServicer

    @property
    def port(self) -> int:
        return self.running.port

    @property
    def address(self) -> str:
        return self.running.address

    def stop(self, grace_s: Optional[float] = None) -> None:
        """Graceful stop: NOT_SERVING, finish in-flight calls (grace), then close the missions."""
        self.running.stop(grace_s)
        self.servicer.close()


def serve(options: ServerOptions, settings: Optional[AgentSettings] = None) -> RunningAgent:
    """Start the agent service (non-blocking); auto-starts a replay mission when ``settings.dataset`` and
    ``settings.task`` are set.

    Args:
        options (ServerOptions): bind address/limits/token/TLS (``max_message_bytes`` capped at
            :data:`MAX_MESSAGE_BYTES`).
        settings (AgentSettings | None): agent id, parser/fusion addresses, config.
    Returns:
        RunningAgent.
    Raises:
        RuntimeError: the address cannot be bound. ValueError / FileNotFoundError / grpc.RpcError: the
            auto-start mission cannot start (the server is stopped again then).
    """
    settings = settings or AgentSettings()
    servicer = AgentServicer(settings)
    opts = ServerOptions(**{**options.__dict__, "max_message_bytes": min(max(options.max_message_bytes, 16 << 20),
                                                                         MAX_MESSAGE_BYTES)})
    running = build_server(opts, lambda srv: agent_pb2_grpc.add_AgentServicer_to_server(servicer, srv),
                           [SERVICE_NAME], agent_registry(servicer))
    agent = RunningAgent(running, servicer)
    if settings.dataset and settings.task:
        try:
            servicer.start_mission(settings.task, task_id=settings.task_id or "", dataset_path=settings.dataset,
                                   auto_finish=settings.auto_finish)
        except BaseException:
            agent.stop(0)
            raise
    return agent


def run(options: ServerOptions, config_path: Optional[str] = None) -> int:
    """Serve until SIGTERM/SIGINT (used by ``gausslite serve agent``). Returns the exit code.

    Agent-specific settings come from the environment (:func:`settings_from_env`; the ``serve agent``
    flags ``--agent-id --parser --fusion --dataset --task --task-id --data-dir`` set those variables).
    """
    try:
        settings = settings_from_env(config_path, token=options.token)
    except ValidationError as e:
        raise ValueError(f"agent config: {e}") from None
    try:
        agent = serve(options, settings)
    except grpc.RpcError as e:
        raise RuntimeError(f"cannot start the mission: parser service {e.code().name}: {e.details()}") from None
    print(f"agent {settings.agent_id} listening on {options.host}:{agent.port}", flush=True)
    try:
        rc = run_until_signalled(agent.running)
        agent.servicer.shutdown(settings.shutdown_s)
    finally:
        agent.servicer.close()
    busy = [t.name for t in threading.enumerate() if t.name.startswith("agent-") and t.is_alive()]
    if busy:
        # a frame still being optimised in a daemon thread: exiting the interpreter normally would tear
        # torch/warp down under it (C++ abort); everything worth keeping is flushed already.
        log.info("exiting with mapping threads still busy: %s", ", ".join(busy))
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(rc)
    return rc
