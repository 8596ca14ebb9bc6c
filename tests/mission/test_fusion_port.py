"""The gRPC fusion client and the in-memory sink and recording store (gausslite.mission.fakes) all implement
FusionPort: every method the pusher calls exists and accepts the pusher's arguments (positional and keyword) as it
passes them."""

import inspect

import pytest

from gausslite.mission import FusionPort
from gausslite.mission.fakes import RecordingFusion, SinkFusion
from gausslite_services.fusion_server.client import FusionClient

#: how gausslite.mission.pusher.Pusher calls each method (arguments after self)
CALLS = {
    "open_session": (("agent", "task text", object()), {}),
    "upload_chunks": (("agent", 3, [b"chunk"]), {"n_gaussians": 10, "full_map_gaussians": 40}),
    "upload_keyframes": (("agent", []), {"jpeg_quality": 90, "color_format": "png", "rois": []}),
}


def test_the_port_lists_what_the_pusher_calls():
    members = {n for n, v in vars(FusionPort).items() if inspect.isfunction(v) and not n.startswith("_")}
    assert members == set(CALLS)


@pytest.mark.parametrize("impl", [FusionClient, SinkFusion, RecordingFusion])
def test_implementations_conform(impl):
    for name, (args, kwargs) in CALLS.items():
        method = getattr(impl, name, None)
        assert callable(method), f"{impl.__name__} lacks {name}"
        inspect.signature(method).bind(None, *args, **kwargs)  # raises TypeError when the call does not fit


def test_runtime_check_of_an_instance():
    assert isinstance(SinkFusion(), FusionPort) and isinstance(RecordingFusion(), FusionPort)
    assert not isinstance(object(), FusionPort)


def test_a_mismatched_signature_is_caught():
    class Wrong:
        def open_session(self, agent_id):  # too few parameters
            return None

    with pytest.raises(TypeError):
        inspect.signature(Wrong.open_session).bind(None, *CALLS["open_session"][0])
