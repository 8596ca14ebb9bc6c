"""Task parsing: free-form task text → object–relation graph (paper Sec. III-B).

Public API::

    from gausslite.parser import TaskParser, ParserConfig, TaskGraph, Relation, parse_task
    TaskParser().parse("Pick up the cup on the desk").to_dict()

The default backend is the offline rule parser (:mod:`gausslite.parser.rules`); LLM backends
(:mod:`gausslite.parser.llm`) are switched on through :class:`ParserConfig`. No gRPC here.
"""

from .graph import PREDICATES, Relation, TaskGraph
from .llm import (
    BackendUnavailableError,
    LLMBackend,
    LLMBackendError,
    LLMOutputError,
    OnnxGenAIBackend,
    OnnxGenAIConfig,
    OpenAIChatBackend,
    OpenAIConfig,
    graph_from_llm_text,
)
from .parser import (
    BACKENDS,
    DEFAULT_MAX_TEXT_BYTES,
    InvalidTaskTextError,
    ParserConfig,
    TaskParser,
    check_task_text,
    make_llm_backend,
)
from .rules import RuleParser, normalize_text, singularize_word

__all__ = [
    "BACKENDS", "DEFAULT_MAX_TEXT_BYTES", "PREDICATES", "BackendUnavailableError", "InvalidTaskTextError",
    "LLMBackend", "LLMBackendError", "LLMOutputError", "OnnxGenAIBackend", "OnnxGenAIConfig",
    "OpenAIChatBackend", "OpenAIConfig", "ParserConfig", "Relation", "RuleParser", "TaskGraph",
    "TaskParser", "check_task_text", "graph_from_llm_text", "make_llm_backend", "normalize_text",
    "parse_task", "singularize_word",
]


def parse_task(text: str) -> TaskGraph:
    """Parse ``text`` with the default offline rule parser (no cache)."""
    return RuleParser().parse(text)
