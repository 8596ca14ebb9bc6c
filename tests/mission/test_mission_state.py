"""MissionState is an enum that reads as its bare name (status dicts, JSON and logs stay as they were)."""

import json

from gausslite.mission import MissionState


def test_mission_state_reads_as_its_name():
    s = MissionState.REPLAY_DONE
    assert s == "REPLAY_DONE" and str(s) == "REPLAY_DONE" and f"{s}" == "REPLAY_DONE" and s.lower() == "replay_done"
    assert json.dumps({"state": s}) == '{"state": "REPLAY_DONE"}'
    assert MissionState("FAILED") is MissionState.FAILED
