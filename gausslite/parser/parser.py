"""``TaskParser``: the parser facade used by the CLI and the parser service (paper Sec. III-B).

The configuration picks a backend (``rules`` — default, offline; ``openai``; ``onnx``). LLM answers
that are malformed, invalid, hallucinated, time out or error fall back to the rule parser, with a
warning and ``backend = "rules(fallback from <name>)"``. Results are cached in an LRU keyed by the
normalised task text (:func:`gausslite.parser.rules.normalize_text`); fallback results are not cached
so that a transient LLM failure is retried next time.
"""

from __future__ import annotations

import json
import logging
import threading
from collections import OrderedDict
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Dict, Mapping, Optional, Union

import yaml

from .graph import TaskGraph
from .llm import (
    BackendUnavailableError,
    LLMBackend,
    LLMBackendError,
    LLMOutputError,
    OnnxGenAIBackend,
    OnnxGenAIConfig,
    OpenAIChatBackend,
    OpenAIConfig,
)
from .rules import RuleParser, normalize_text

log = logging.getLogger(__name__)

BACKENDS = ("rules", "openai", "onnx")
#: Default bound on the task text, in UTF-8 bytes.
DEFAULT_MAX_TEXT_BYTES = 2048


class InvalidTaskTextError(ValueError):
    """The task text is not acceptable (not a string, longer than the byte limit, or holding a NUL)."""


@dataclass
class ParserConfig:
    """Parser configuration.

    Attributes:
        backend (str): ``"rules"`` (default), ``"openai"`` or ``"onnx"``.
        cache_size (int): LRU entries (0 disables caching).
        max_text_bytes (int): longest accepted task text in UTF-8 bytes.
        openai (OpenAIConfig): settings of the OpenAI-compatible backend.
        onnx (OnnxGenAIConfig): settings of the ONNX Runtime GenAI backend.
    """

    backend: str = "rules"
    cache_size: int = 1024
    max_text_bytes: int = DEFAULT_MAX_TEXT_BYTES
    openai: OpenAIConfig = field(default_factory=OpenAIConfig)
    onnx: OnnxGenAIConfig = field(default_factory=OnnxGenAIConfig)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "ParserConfig":
        """Build from a mapping; an optional top-level ``parser`` key is unwrapped.

        Raises:
            ValueError: unknown keys or unknown backend.
        """
        if "parser" in data and isinstance(data["parser"], Mapping):
            data = data["parser"]
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"unknown parser config key(s): {sorted(unknown)}")

        def sub(klass, value):
            value = dict(value or {})
            bad = set(value) - {f.name for f in fields(klass)}
            if bad:
                raise ValueError(f"unknown {klass.__name__} key(s): {sorted(bad)}")
            return klass(**value)

        cfg = cls(
            backend=str(data.get("backend", "rules")),
            cache_size=int(data.get("cache_size", 1024)),
            max_text_bytes=int(data.get("max_text_bytes", DEFAULT_MAX_TEXT_BYTES)),
            openai=sub(OpenAIConfig, data.get("openai")),
            onnx=sub(OnnxGenAIConfig, data.get("onnx")),
        )
        if cfg.backend not in BACKENDS:
            raise ValueError(f"unknown parser backend {cfg.backend!r}; choose one of {BACKENDS}")
        return cfg

    @classmethod
    def from_file(cls, path: Union[str, Path]) -> "ParserConfig":
        """Load a YAML (``.yaml``/``.yml``) or JSON config file.

        Raises:
            FileNotFoundError: no such file. ValueError: bad content.
        """
        p = Path(path)
        text = p.read_text(encoding="utf-8")
        if p.suffix.lower() in (".yaml", ".yml"):
            data = yaml.safe_load(text) or {}
        else:
            data = json.loads(text)
        if not isinstance(data, Mapping):
            raise ValueError(f"{p}: parser config must be a mapping")
        return cls.from_dict(data)


def make_llm_backend(config: ParserConfig) -> Optional[LLMBackend]:
    """The LLM backend named by ``config.backend`` (``None`` for ``rules``).

    Raises:
        BackendUnavailableError: the backend cannot be constructed (missing package or folder).
        ValueError: unknown backend name.
    """
    if config.backend == "rules":
        return None
    if config.backend == "openai":
        return OpenAIChatBackend(config.openai)
    if config.backend == "onnx":
        return OnnxGenAIBackend(config.onnx)
    raise ValueError(f"unknown parser backend {config.backend!r}; choose one of {BACKENDS}")


def check_task_text(text: Any, max_bytes: int = DEFAULT_MAX_TEXT_BYTES) -> str:
    """Validate a task text and return it.

    Raises:
        InvalidTaskTextError: not a ``str``, longer than ``max_bytes`` UTF-8 bytes (the message
            states the limit), or holding a NUL character (no store can keep it as text).
    """
    if not isinstance(text, str):
        raise InvalidTaskTextError(f"task text must be a string, got {type(text).__name__}")
    n = len(text.encode("utf-8", errors="surrogatepass"))
    if n > max_bytes:
        raise InvalidTaskTextError(f"task text is {n} bytes; the limit is {max_bytes} UTF-8 bytes")
    if "\x00" in text:
        raise InvalidTaskTextError("task text contains a NUL character")
    return text


class TaskParser:
    """Backend selection, LRU cache and fallback to the rule parser. Thread safe."""

    def __init__(self, config: Optional[ParserConfig] = None, llm: Optional[LLMBackend] = None):
        """Args:
            config (ParserConfig | None): defaults to the offline rule parser.
            llm (LLMBackend | None): inject a ready backend instead of building one from ``config``.

        Raises:
            BackendUnavailableError: the configured LLM backend cannot be used.
        """
        self.config = config or ParserConfig()
        self.rules = RuleParser()
        self.llm = llm if llm is not None else make_llm_backend(self.config)
        self._cache: "OrderedDict[str, TaskGraph]" = OrderedDict()
        self._lock = threading.Lock()
        self.hits = 0
        self.misses = 0

    @property
    def backend_name(self) -> str:
        """Name of the primary backend (``rules``, ``openai``, ``onnx``)."""
        return self.llm.name if self.llm is not None else self.rules.name

    def cache_info(self) -> Dict[str, int]:
        """``{"hits", "misses", "size", "maxsize"}``."""
        with self._lock:
            return {"hits": self.hits, "misses": self.misses, "size": len(self._cache),
                    "maxsize": self.config.cache_size}

    def clear_cache(self) -> None:
        """Empty the cache and reset the counters."""
        with self._lock:
            self._cache.clear()
            self.hits = self.misses = 0

    def parse(self, text: str, timeout_s: Optional[float] = None) -> TaskGraph:
        """Parse a task text into a :class:`TaskGraph` (a fresh copy; safe to mutate).

        Args:
            text (str): the task (≤ ``config.max_text_bytes`` UTF-8 bytes). Empty text gives an
                empty graph with a warning.
            timeout_s (float | None): time budget for an LLM backend (e.g. the remaining gRPC
                deadline); the rule parser ignores it.
        Returns:
            TaskGraph
        Raises:
            InvalidTaskTextError: see :func:`check_task_text`.
        """
        check_task_text(text, self.config.max_text_bytes)
        key = normalize_text(text)
        if self.config.cache_size > 0:
            with self._lock:
                hit = self._cache.get(key)
                if hit is not None:
                    self._cache.move_to_end(key)
                    self.hits += 1
                    return hit.copy()
                self.misses += 1
        graph, cacheable = self._parse_uncached(key, timeout_s)
        if cacheable and self.config.cache_size > 0:
            with self._lock:
                self._cache[key] = graph.copy()
                self._cache.move_to_end(key)
                while len(self._cache) > self.config.cache_size:
                    self._cache.popitem(last=False)
        return graph

    def _parse_uncached(self, norm_text: str, timeout_s: Optional[float] = None):
        if self.llm is None or not norm_text:
            return self.rules.parse(norm_text), True
        try:
            return self.llm.parse(norm_text, timeout_s=timeout_s), True
        except (LLMBackendError, LLMOutputError, BackendUnavailableError) as e:
            reason = str(e)
        except Exception as e:  # never let a backend bug take the service down
            log.exception("parser backend %s crashed", self.llm.name)
            reason = f"{type(e).__name__}: {e}"
        log.warning("parser backend %s rejected for %r: %s; using rules", self.llm.name, norm_text, reason)
        g = self.rules.parse(norm_text)
        g.backend = f"rules(fallback from {self.llm.name})"
        g.warnings.insert(0, f"{self.llm.name} backend failed ({reason}); used the rule parser")
        return g, False
