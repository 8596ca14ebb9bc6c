"""Parser service: a thin gRPC server over :class:`gausslite.parser.TaskParser` (paper Sec. III-B).

``gausslite.v1.Parser/Parse``: INVALID_ARGUMENT for empty or oversized task text (the limit is in
the message), the remaining client deadline bounds LLM backends, the standard health service and
reflection are on, optional bearer token and TLS come from :mod:`gausslite_services.common`.
"""

from __future__ import annotations

import logging
from typing import Optional

import grpc

from gausslite.parser import InvalidTaskTextError, ParserConfig, TaskGraph, TaskParser
from gausslite_rpc import common_pb2, parser_pb2_grpc
from gausslite_services.common.server import RunningServer, ServerOptions, build_server, run_until_signalled
from gausslite_services.parser.metrics import MeteredParser, ParserMetrics

log = logging.getLogger(__name__)

SERVICE_NAME = "gausslite.v1.Parser"
#: The parser's messages are tiny; bound them well below gRPC's 4 MiB default.
MAX_MESSAGE_BYTES = 64 * 1024


def graph_to_proto(graph: TaskGraph) -> common_pb2.TaskGraph:
    """Convert a library :class:`TaskGraph` to the wire message."""
    return common_pb2.TaskGraph(
        targets=graph.targets,
        anchors=graph.anchors,
        relations=[common_pb2.Relation(predicate=r.predicate, target=r.target, anchor=r.anchor)
                   for r in graph.relations],
        unsupported=graph.unsupported,
        backend=graph.backend,
        warnings=graph.warnings,
    )


class ParserServicer(parser_pb2_grpc.ParserServicer):
    """Implements ``gausslite.v1.Parser``."""

    def __init__(self, parser: TaskParser):
        """Args: parser (TaskParser): shared, thread-safe parser."""
        self.parser = parser

    def Parse(self, request, context):  # noqa: N802 - gRPC method name
        text = request.task_text
        limit = self.parser.config.max_text_bytes
        if not text.strip():
            context.abort(grpc.StatusCode.INVALID_ARGUMENT,
                          f"task_text is empty; send 1..{limit} UTF-8 bytes of task text")
        remaining = context.time_remaining()
        budget = None
        if remaining is not None:
            # keep a margin so that a fallback answer still reaches the client before its deadline
            budget = max(0.01, remaining - max(0.1, 0.2 * remaining))
        try:
            graph = self.parser.parse(text, timeout_s=budget)
        except InvalidTaskTextError as e:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, str(e))
        if not context.is_active():  # deadline passed or client cancelled meanwhile
            log.info("Parse finished after the client went away (deadline/cancel)")
        return graph_to_proto(graph)


def serve(options: ServerOptions, config: Optional[ParserConfig] = None,
          parser: Optional[TaskParser] = None) -> RunningServer:
    """Start the parser service (non-blocking).

    Args:
        options (ServerOptions): bind address/limits/token/TLS; ``max_message_bytes`` is capped at
            :data:`MAX_MESSAGE_BYTES`.
        config (ParserConfig | None): parser backend configuration (default: offline rules).
        parser (TaskParser | None): a ready parser (overrides ``config``; used by tests/embedding).
    Returns:
        RunningServer: ``.port`` is the bound port; ``.stop()`` shuts it down gracefully.
    Raises:
        gausslite.parser.BackendUnavailableError: the configured LLM backend cannot be used.
        RuntimeError: the address cannot be bound.
    """
    parser = parser or TaskParser(config or ParserConfig())
    servicer = MeteredParser(ParserServicer(parser), ParserMetrics())
    opts = ServerOptions(**{**options.__dict__, "max_message_bytes": min(options.max_message_bytes, MAX_MESSAGE_BYTES)})
    running = build_server(opts, lambda srv: parser_pb2_grpc.add_ParserServicer_to_server(servicer, srv),
                           [SERVICE_NAME], servicer.metrics.registry)
    log.info("parser backend: %s", parser.backend_name)
    return running


def run(options: ServerOptions, config_path: Optional[str] = None) -> int:
    """Serve until SIGTERM/SIGINT (used by ``gausslite serve parser``). Returns the exit code."""
    config = ParserConfig.from_file(config_path) if config_path else ParserConfig()
    running = serve(options, config)
    print(f"parser listening on {options.host}:{running.port}", flush=True)
    return run_until_signalled(running)
