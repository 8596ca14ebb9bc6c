"""How a benchmark records the missions it ran, and what it does when one failed.

The rule, for every benchmark that runs live agent missions (``bench.realtime`` and the benchmarks built on it,
``bench.pose_perturbation --mode live``, ``bench.team``):

- **Every run records how its mission ended** (:func:`mission_outcome`): ``end_state`` (the
  :class:`~gausslite.mission.state.MissionState` name, ``"FINISHED"`` for a mission that ended well), ``error`` (the
  status's ``last_error``, ``""`` when none) and the counters ``frames_failed`` and ``corrections_rejected`` (0 when
  the status has no such field).
- **A mission failed** (:func:`failed`) when it did not end ``FINISHED`` (``FAILED``: it stopped, out of memory or
  disk), or when frames failed (``frames_failed`` > 0: a frame's step raised, e.g. ``"mapping frame 612 failed:
  ..."``, and the mission went on without it). An ``error`` alone is not a failure (``last_error`` also names a
  rejected frame, a frame the odometry lost, a push retried), nor is ``corrections_rejected``: both are recorded.
- **A failed run is kept, never averaged**: it stays in the result's runs with its end state, its error and whatever
  figures it has, is left out of every mean and gain, and is marked :data:`FAILED_MARK` (†) in the tables with a
  footnote (:func:`failed_note`).
- **The benchmark exits 1** when a mission failed (:func:`exit_code`, each failed run printed to stderr), after writing
  its result, unless it was given ``--allow-failed`` (:func:`add_allow_failed`).

A record without ``end_state`` (an offline run, or a result written before this rule) is not a failed one.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any, Iterable, Mapping, Optional, Sequence

__all__ = ["COUNTERS", "END_OK", "FAILED_MARK", "OUTCOME_KEYS", "add_allow_failed", "describe", "exit_code", "failed",
           "failed_note", "failed_runs", "failure_rows", "mission_outcome", "outcome_of", "state_name", "succeeded"]

#: the end state of a mission that ended well
END_OK = "FINISHED"
#: the mark of a failed run in a benchmark's tables
FAILED_MARK = "†"
#: the status counters a run records beside its end state (0 when the status has no such field)
COUNTERS = ("frames_failed", "corrections_rejected")
#: the keys :func:`mission_outcome` gives
OUTCOME_KEYS = ("end_state", "error", *COUNTERS)


def _field(status: Any, key: str, default: Any) -> Any:
    """``status[key]`` of a mapping (``AgentRuntime.status()``), or its attribute ``key`` (a ``MissionStatus``
    message of the agent's gRPC API); ``default`` when it has none."""
    if isinstance(status, Mapping):
        return status.get(key, default)
    return getattr(status, key, default)


def state_name(state: Any) -> str:
    """A mission state as its short name: ``MissionState.FAILED``, ``"FAILED"``, ``"MISSION_STATE_FAILED"`` or the
    gRPC enum number 5 all give ``"FAILED"``; None gives ``"UNKNOWN"``.

    Raises:
        ValueError: a number that is no ``MissionState`` of the agent's gRPC API.
    """
    if state is None:
        return "UNKNOWN"
    if isinstance(state, int) and not isinstance(state, bool):
        from gausslite_rpc import agent_pb2  # lazy: an in-process mission's state needs no gRPC module

        state = agent_pb2.MissionState.Name(state)
    return str(state).removeprefix("MISSION_STATE_")


def mission_outcome(status: Any) -> dict:
    """How a mission ended, from its status after Finish (or after it failed).

    Args:
        status: ``AgentRuntime.status()`` (a dict with ``state``, ``last_error`` and, where the runtime has them,
            ``frames_failed`` / ``corrections_rejected``) or a ``MissionStatus`` message of the agent's gRPC API.
    Returns:
        ``{"end_state": str, "error": str, "frames_failed": int, "corrections_rejected": int}`` (:data:`OUTCOME_KEYS`):
        the state's name (:func:`state_name`), ``last_error`` (``""`` when none) and the two counters (0 when absent).
    """
    return {"end_state": state_name(_field(status, "state", None)),
            "error": str(_field(status, "last_error", "") or ""),
            **{k: int(_field(status, k, 0) or 0) for k in COUNTERS}}


def outcome_of(runtime) -> dict:
    """:func:`mission_outcome` of an in-process mission (a :class:`~gausslite.mission.runtime.AgentRuntime`)."""
    return mission_outcome(runtime.status())


def failed(record: Mapping) -> bool:
    """Whether the run ``record`` (a benchmark's run, or a :func:`mission_outcome`) is a failed mission: its
    ``end_state`` is not ``FINISHED``, or ``frames_failed`` > 0 (a frame whose step raised: its map is partial). An
    ``error`` alone is not a failure: the status's ``last_error`` also names what a mission survives by design (a frame
    the odometry lost, a push retried). A record without ``end_state`` (an offline run, an older result) is not."""
    if "end_state" not in record:
        return False
    return record.get("end_state") != END_OK or int(record.get("frames_failed") or 0) > 0


def failed_runs(runs: Iterable[Mapping]) -> list:
    """The failed runs of ``runs`` (:func:`failed`), in order."""
    return [r for r in runs if failed(r)]


def succeeded(runs: Iterable[Mapping]) -> list:
    """The runs of ``runs`` that are not failed missions (:func:`failed`), in order: the ones a summary averages."""
    return [r for r in runs if not failed(r)]


def failure_rows(runs: Iterable[Mapping], keys: Sequence[str] = ()) -> list[dict]:
    """What a summary keeps of each failed run of ``runs``: its ``keys`` (those it has: ``scene``, ``mode``, ``run``
    ...) and its :data:`OUTCOME_KEYS`."""
    return [{**{k: r[k] for k in keys if k in r}, **{k: r.get(k) for k in OUTCOME_KEYS if k in r}}
            for r in failed_runs(runs)]


def describe(record: Mapping, keys: Sequence[str] = ()) -> str:
    """One line naming a run and how it ended: ``"scene=synthetic_circle mode=gausslite run=0: FAILED (mapping frame
    612 failed: ...), 3 frames failed"`` (``keys``: the fields that name the run, those it has)."""
    name = " ".join(f"{k}={record[k]}" for k in keys if k in record)
    err = f" ({record['error']})" if record.get("error") else ""
    n = int(record.get("frames_failed") or 0)
    return (f"{name}: " if name else "") + f"{record.get('end_state', 'UNKNOWN')}{err}" + (
        f", {n} frames failed" if n else "")


def failed_note(what: str = "run") -> str:
    """The footnote of :data:`FAILED_MARK` in a table (``what``: what the marked cell counts, e.g. ``"run"``)."""
    return (f"{FAILED_MARK} a {what} whose mission failed (end state not FINISHED, or frames that failed to map): kept in the JSON's runs with its end_state and error, left out of every mean and "
            "gain here.")


def add_allow_failed(ap: argparse.ArgumentParser) -> None:
    """Add ``--allow-failed`` to a benchmark's command line."""
    ap.add_argument("--allow-failed", action="store_true",
                    help="exit 0 even when a mission failed (failed runs are recorded with their end_state and "
                         "error, marked in the tables and left out of the figures either way)")


def exit_code(runs: Iterable[Mapping], allow_failed: bool, bench: str, keys: Sequence[str] = (),
              stream: Optional[Any] = None) -> int:
    """The exit code of a benchmark whose result holds ``runs``: 1 when one is a failed mission (:func:`failed`)
    and not ``allow_failed``, else 0. Every failed run is printed to ``stream`` (default stderr), named by its
    ``keys`` (:func:`describe`)."""
    bad = failed_runs(runs)
    out = stream if stream is not None else sys.stderr
    for r in bad:
        print(f"{bench}: failed mission: {describe(r, keys)}", file=out)
    if bad and not allow_failed:
        print(f"{bench}: {len(bad)} failed mission(s), recorded in the result and left out of its figures; "
              "exit 1 (--allow-failed to exit 0)", file=out)
        return 1
    return 0
