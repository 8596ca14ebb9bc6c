"""Typed client errors (gausslite_services.common.errors): one class per status code, still grpc.RpcError."""

from __future__ import annotations

import grpc
import pytest

from gausslite_services.common.errors import (FailedPrecondition, NotFound, RpcStatusError, Unavailable,
                                              raises_typed_errors, typed_error)


class _Raw(grpc.RpcError):
    def __init__(self, code, details):
        self._c, self._d = code, details

    def code(self):
        return self._c

    def details(self):
        return self._d


def test_each_status_has_its_class_and_keeps_code_and_details():
    e = typed_error(_Raw(grpc.StatusCode.FAILED_PRECONDITION, "no base"), "upload_chunks")
    assert isinstance(e, FailedPrecondition) and isinstance(e, grpc.RpcError)
    assert e.code() == grpc.StatusCode.FAILED_PRECONDITION and e.details() == "no base"
    assert "upload_chunks" in str(e) and "FAILED_PRECONDITION" in str(e)
    assert type(typed_error(_Raw(grpc.StatusCode.DATA_LOSS, "x"))) is RpcStatusError  # no class of its own
    assert typed_error(e) is e


def test_decorated_clients_raise_typed_errors_from_calls_and_streams():
    @raises_typed_errors
    class Client:
        def call(self, code):
            raise _Raw(code, "boom")

        def stream(self):
            yield 1
            raise _Raw(grpc.StatusCode.UNAVAILABLE, "gone")

        def _private(self):
            raise _Raw(grpc.StatusCode.NOT_FOUND, "raw")

    c = Client()
    with pytest.raises(NotFound) as ei:
        c.call(grpc.StatusCode.NOT_FOUND)
    assert ei.value.method == "call"
    with pytest.raises(Unavailable):
        list(c.stream())
    with pytest.raises(_Raw):  # private helpers are left alone
        c._private()


def test_fusion_client_maps_a_server_status_to_its_class(tmp_path):
    from gausslite_services.fusion_server.client import FusionClient
    from gausslite_services.fusion_server.server import FusionConfig, serve
    from gausslite_services.common.server import ServerOptions

    srv = serve(ServerOptions(host="127.0.0.1", port=0), FusionConfig(data_dir=str(tmp_path)))
    try:
        c = FusionClient(srv.address, timeout_s=10.0)
        c.wait_ready(30)
        with pytest.raises(FailedPrecondition):  # nothing uploaded yet
            c.fuse("vote")
        with pytest.raises(NotFound):
            c.download_fused(7)
        c.close()
    finally:
        srv.stop(0)
