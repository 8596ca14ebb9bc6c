"""gRPC statuses come from the library's exception types (gausslite_services.common.errors.status_for), never from
message text: the same message under another type gets another status."""

import grpc
import pytest
from gausslite_rpc import common_pb2

from gausslite.errors import CapacityExceeded, ImageSizeError, RelevanceUnavailable
from gausslite.fusion.uploads import MissingDeltaBase, RebuiltTooLarge, SupersededVersion
from gausslite.mission import AgentConfig, FrameSizeMismatch, MissionError, PreconditionFailed
from gausslite.mission.relevance import build_relevance
from gausslite.wire import DeltaMismatch, LimitExceeded
from gausslite_services.common.convert import intrinsics_from_proto
from gausslite_services.common.errors import status_for


def test_status_by_type():
    assert status_for(FrameSizeMismatch("frame 3: image size 64x48 differs")) == grpc.StatusCode.INVALID_ARGUMENT
    assert status_for(ImageSizeError("x")) == grpc.StatusCode.INVALID_ARGUMENT
    assert status_for(MissionError("mission m is finished")) == grpc.StatusCode.FAILED_PRECONDITION
    assert status_for(RelevanceUnavailable("x")) == grpc.StatusCode.FAILED_PRECONDITION
    assert status_for(PreconditionFailed("x")) == grpc.StatusCode.FAILED_PRECONDITION
    assert status_for(ValueError("x")) == grpc.StatusCode.INVALID_ARGUMENT
    assert status_for(RuntimeError("x")) == grpc.StatusCode.INTERNAL
    assert status_for(RuntimeError("x"), grpc.StatusCode.UNAVAILABLE) == grpc.StatusCode.UNAVAILABLE


def test_message_text_does_not_decide():
    # the words the servers used to look for, under other types
    assert status_for(MissionError("image size 64x48 differs")) == grpc.StatusCode.FAILED_PRECONDITION
    text = "relevance map shape (4, 4) != depth shape (2, 2)"
    assert status_for(ValueError(text)) == grpc.StatusCode.INVALID_ARGUMENT


def test_library_raises_the_typed_errors():
    with pytest.raises(ImageSizeError):
        intrinsics_from_proto(common_pb2.Intrinsics(fx=100, fy=100, cx=32, cy=24, width=0, height=48))
    with pytest.raises(RelevanceUnavailable):
        build_relevance(AgentConfig(relevance="gt"), graph=None, annotations=None, task_id=None)
    e = FrameSizeMismatch("frame 1")
    assert isinstance(e, MissionError) and isinstance(e, ValueError)


def test_upload_refusals_keep_their_statuses():
    # gausslite.fusion.uploads raises these; the fusion server answers with status_for
    assert status_for(SupersededVersion("x")) == grpc.StatusCode.FAILED_PRECONDITION
    assert status_for(MissingDeltaBase("x")) == grpc.StatusCode.FAILED_PRECONDITION
    assert status_for(DeltaMismatch("x")) == grpc.StatusCode.INVALID_ARGUMENT
    assert status_for(RebuiltTooLarge("x")) == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert status_for(CapacityExceeded("x")) == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert status_for(LimitExceeded("x")) == grpc.StatusCode.INVALID_ARGUMENT  # unchanged: a wire error
    assert isinstance(MissingDeltaBase("x"), PreconditionFailed)  # the mission's fallback to a full upload
