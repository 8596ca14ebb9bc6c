"""The states of a mission (``AgentRuntime.state``; the ``MissionState`` of ``proto/gausslite_rpc/agent.proto``)."""

from __future__ import annotations

from enum import Enum

__all__ = ["MissionState", "ACCEPTS_TASK", "ACTIVE"]


class MissionState(str, Enum):
    """State of a mission. String-valued: ``MissionState.MAPPING == "MAPPING"``, and ``str()``, f-strings and JSON
    give the bare name, so status dicts and logs read as before.

    ``MAPPING`` → (replays: ``REPLAY_DONE`` when the last frame is in) → ``FINISHING`` (final pass and push) →
    ``FINISHED``; ``FAILED`` from any state when the mapping worker dies.
    """

    MAPPING = "MAPPING"
    REPLAY_DONE = "REPLAY_DONE"
    FINISHING = "FINISHING"
    FINISHED = "FINISHED"
    FAILED = "FAILED"

    __str__ = str.__str__
    __format__ = str.__format__


#: states in which a mission takes a new task (``UpdateTask``)
ACCEPTS_TASK = frozenset({MissionState.MAPPING, MissionState.REPLAY_DONE})
#: states of a mission that still runs (a new one must wait for its ``Finish``)
ACTIVE = frozenset({MissionState.MAPPING, MissionState.REPLAY_DONE, MissionState.FINISHING})
