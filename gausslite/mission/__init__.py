"""An agent's mission as a library: settings, the mission loop (frames → relevance → mapper), its pusher and what
it shares (paper Sec. III-B to III-E; ``docs/live.md``, ``docs/sharing.md``). No gRPC here: the agent service
(``services/agent``) adapts it to the wire, and any object with the fusion client's methods can receive its
pushes."""

from gausslite.mission.build import build_mission, replay_dataset
from gausslite.mission.config import AgentConfig, OnnxRelevanceConfig
from gausslite.mission.errors import FrameSizeMismatch, MissionError, PreconditionFailed
from gausslite.mission.ports import FusionPort
from gausslite.mission.pusher import Pusher, PushRecord
from gausslite.mission.runtime import AgentRuntime, MissionSummaryData
from gausslite.mission.share import ShareSession, select_shared
from gausslite.mission.state import MissionState

__all__ = ["build_mission", "replay_dataset", "AgentConfig", "OnnxRelevanceConfig", "PreconditionFailed", "AgentRuntime",
           "MissionError", "FrameSizeMismatch", "MissionState", "FusionPort", "MissionSummaryData", "Pusher", "PushRecord",
           "ShareSession", "select_shared"]
