"""LLM task-parsing backends (paper Sec. III-B: few-shot prompted Phi-3-mini).

Two backends produce the same JSON task graph:

* :class:`OnnxGenAIBackend` — a local instruction-tuned model (e.g. Phi-3-mini) through ONNX Runtime
  GenAI (``onnxruntime_genai``, imported lazily) from a user-supplied model folder.
* :class:`OpenAIChatBackend` — any OpenAI-compatible ``/chat/completions`` endpoint, over the
  standard library's ``urllib`` (no extra dependency), with ``response_format`` = JSON schema.

Both are prompted few-shot with :data:`SYSTEM_PROMPT`, :data:`FEW_SHOT` and
:data:`TASK_GRAPH_SCHEMA`. Their raw text goes through :func:`graph_from_llm_text`, which parses,
validates (schema, predicates, relation endpoints) and grounds every phrase in the task text; any
problem raises :class:`LLMOutputError` so that :class:`gausslite.parser.parser.TaskParser` falls
back to the rule parser. Transport problems raise :class:`LLMBackendError`.

No gRPC here.
"""

from __future__ import annotations

import abc
import json
import os
import re
import socket
import threading
import time
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional

from .graph import PREDICATES, Relation, TaskGraph
from .rules import DETERMINERS, is_grounded, singularize_phrase, text_vocabulary


class LLMBackendError(RuntimeError):
    """The LLM could not be reached or failed (HTTP error, timeout, runtime error)."""


class LLMOutputError(ValueError):
    """The LLM answered, but the answer is malformed, invalid or not grounded in the task text."""


class BackendUnavailableError(RuntimeError):
    """A configured backend cannot be used at all (package not installed, model folder missing)."""


# --------------------------------------------------------------------------------------------
# Prompt and schema
# --------------------------------------------------------------------------------------------

TASK_GRAPH_SCHEMA: Dict[str, Any] = {
    "type": "object",
    "additionalProperties": False,
    "required": ["targets", "anchors", "relations", "unsupported"],
    "properties": {
        "targets": {"type": "array", "items": {"type": "string"}},
        "anchors": {"type": "array", "items": {"type": "string"}},
        "relations": {
            "type": "array",
            "items": {
                "type": "object",
                "additionalProperties": False,
                "required": ["predicate", "target", "anchor"],
                "properties": {
                    "predicate": {"type": "string", "enum": list(PREDICATES)},
                    "target": {"type": "string"},
                    "anchor": {"type": "string"},
                },
            },
        },
        "unsupported": {"type": "array", "items": {"type": "string"}},
    },
}

SYSTEM_PROMPT = (
    "You turn a robot task into an object-relation graph. Answer with one JSON object only, matching "
    "this JSON schema:\n" + json.dumps(TASK_GRAPH_SCHEMA) + "\n"
    "Rules: targets are what the task is about (objects to pick, find, map, avoid, reach); anchors are "
    "spatial reference objects that only constrain where a target is; a phrase is never both. Phrases "
    "are lower case, singular, without determiners or quantifiers, keeping compound nouns and colour or "
    "material adjectives, and use only words from the task. Predicates: 'near' (near, next to, beside, "
    "by, closest to, nearest, around, close to, at) and 'on' (on, on top of, sitting on, lying on, "
    "resting on, from, off). Other spatial words (under, inside, in, behind, left of, right of, above, "
    "below, between) give no relation: still extract target and anchor and list the word in "
    "'unsupported'. 'X/Y', 'X and Y', 'X or Y' give one entry per noun. Scope words (scene, room, "
    "area) are not objects."
)

FEW_SHOT: List[Dict[str, Any]] = [
    {"text": "Prepare to pick up the object on the desk",
     "graph": {"targets": ["object"], "anchors": ["desk"],
               "relations": [{"predicate": "on", "target": "object", "anchor": "desk"}], "unsupported": []}},
    {"text": "Identify the chair closest to the table",
     "graph": {"targets": ["chair"], "anchors": ["table"],
               "relations": [{"predicate": "near", "target": "chair", "anchor": "table"}], "unsupported": []}},
    {"text": "Locate all obstacles in the scene and find a path to the door",
     "graph": {"targets": ["obstacle", "door"], "anchors": [], "relations": [], "unsupported": []}},
    {"text": "Avoid the trash cans/dirt",
     "graph": {"targets": ["trash can", "dirt"], "anchors": [], "relations": [], "unsupported": []}},
    {"text": "Pick up the toy under the couch",
     "graph": {"targets": ["toy"], "anchors": ["couch"], "relations": [], "unsupported": ["under"]}},
]


def build_messages(task_text: str) -> List[Dict[str, str]]:
    """Chat messages: system prompt, few-shot user/assistant pairs, then the task.

    Args:
        task_text (str): the task.
    Returns:
        list[dict]: OpenAI-style ``{"role", "content"}`` messages.
    """
    msgs = [{"role": "system", "content": SYSTEM_PROMPT}]
    for ex in FEW_SHOT:
        msgs.append({"role": "user", "content": ex["text"]})
        msgs.append({"role": "assistant", "content": json.dumps(ex["graph"])})
    msgs.append({"role": "user", "content": task_text})
    return msgs


# --------------------------------------------------------------------------------------------
# Output parsing, validation, grounding
# --------------------------------------------------------------------------------------------

_FENCE_RE = re.compile(r"```(?:json)?\s*(.*?)```", re.S)


def _extract_json_object(text: str) -> Any:
    """The first JSON object in ``text`` (code fences and surrounding chatter tolerated)."""
    m = _FENCE_RE.search(text)
    if m:
        text = m.group(1)
    start = text.find("{")
    if start < 0:
        raise LLMOutputError("no JSON object in the LLM output")
    try:
        obj, _ = json.JSONDecoder().raw_decode(text[start:])
    except json.JSONDecodeError as e:
        raise LLMOutputError(f"malformed JSON in the LLM output: {e.msg}") from e
    return obj


def _norm_phrase(p: str) -> str:
    words = re.sub(r"[^a-z0-9/' -]+", " ", p.lower()).split()
    while words and words[0] in DETERMINERS:
        words = words[1:]
    return " ".join(singularize_phrase(words))


def _str_list(obj: Dict[str, Any], key: str) -> List[str]:
    val = obj.get(key, [])
    if not isinstance(val, list) or not all(isinstance(x, str) for x in val):
        raise LLMOutputError(f"'{key}' must be a list of strings")
    return val


def graph_from_llm_text(raw: str, task_text: str, backend: str) -> TaskGraph:
    """Parse, validate and ground an LLM answer.

    Args:
        raw (str): the model's text output.
        task_text (str): the task the model was asked about (for grounding).
        backend (str): backend name stored in the returned graph.
    Returns:
        TaskGraph: normalised (lower case, singular head, no determiners).
    Raises:
        LLMOutputError: not JSON; schema violation (missing ``targets``/``anchors``/``relations``,
            wrong types, unknown keys); predicate not in ``{near, on}``; relation endpoint not among
            the targets/anchors; no target; a phrase whose words do not occur in the normalised task
            text (allowing singularisation) — a hallucination.
    """
    obj = _extract_json_object(raw)
    if not isinstance(obj, dict):
        raise LLMOutputError("LLM output is not a JSON object")
    extra = set(obj) - set(TASK_GRAPH_SCHEMA["properties"])
    if extra:
        raise LLMOutputError(f"unexpected key(s) in LLM output: {sorted(extra)}")
    for key in ("targets", "anchors", "relations"):
        if key not in obj:
            raise LLMOutputError(f"LLM output lacks '{key}'")
    targets = [_norm_phrase(p) for p in _str_list(obj, "targets")]
    anchors = [_norm_phrase(p) for p in _str_list(obj, "anchors")]
    unsupported = [u.strip().lower() for u in _str_list(obj, "unsupported")]
    rels_raw = obj["relations"]
    if not isinstance(rels_raw, list):
        raise LLMOutputError("'relations' must be a list")
    relations: List[Relation] = []
    for r in rels_raw:
        if not isinstance(r, dict) or set(r) != {"predicate", "target", "anchor"} or not all(
            isinstance(v, str) for v in r.values()
        ):
            raise LLMOutputError(f"malformed relation {r!r}")
        pred = r["predicate"].strip().lower()
        if pred not in PREDICATES:
            raise LLMOutputError(f"predicate {r['predicate']!r} not in {list(PREDICATES)}")
        relations.append(Relation(pred, _norm_phrase(r["target"]), _norm_phrase(r["anchor"])))
    targets = list(dict.fromkeys(t for t in targets if t))
    anchors = list(dict.fromkeys(a for a in anchors if a))
    if not targets:
        raise LLMOutputError("LLM output has no target")
    vocab = text_vocabulary(task_text)
    for p in targets + anchors + unsupported:
        if not is_grounded(p, vocab):
            raise LLMOutputError(f"phrase {p!r} is not grounded in the task text (hallucination)")
    graph = TaskGraph(targets, anchors, list(dict.fromkeys(relations)), list(dict.fromkeys(unsupported)),
                      backend=backend)
    errs = graph.validate()
    if errs:
        raise LLMOutputError("invalid task graph from LLM: " + "; ".join(errs))
    return graph


# --------------------------------------------------------------------------------------------
# Backends
# --------------------------------------------------------------------------------------------


class LLMBackend(abc.ABC):
    """Base class: subclasses implement :meth:`complete`; :meth:`parse` validates the answer."""

    name = "llm"

    @abc.abstractmethod
    def complete(self, messages: List[Dict[str, str]], timeout_s: Optional[float] = None) -> str:
        """Return the model's raw text answer to ``messages``.

        Raises:
            LLMBackendError: transport/runtime failure or timeout.
        """

    def parse(self, task_text: str, timeout_s: Optional[float] = None) -> TaskGraph:
        """Few-shot prompt the model and return the validated graph.

        Raises:
            LLMBackendError: see :meth:`complete`.
            LLMOutputError: see :func:`graph_from_llm_text`.
        """
        raw = self.complete(build_messages(task_text), timeout_s=timeout_s)
        return graph_from_llm_text(raw, task_text, self.name)


@dataclass
class OpenAIConfig:
    """Settings of an OpenAI-compatible chat-completions endpoint.

    Attributes:
        base_url (str): e.g. ``http://127.0.0.1:8000/v1``; ``/chat/completions`` is appended.
        model (str): model name sent in the request.
        api_key (str | None): sent as ``Authorization: Bearer``; when ``None`` the environment
            variable named by ``api_key_env`` is used if set.
        api_key_env (str): default ``OPENAI_API_KEY``.
        timeout_s (float): per-request timeout in seconds.
        json_schema (bool): send ``response_format={"type": "json_schema", ...}``; if the server
            rejects it with HTTP 400 the request is retried once without it.
        max_tokens (int): completion budget.
    """

    base_url: str = "http://127.0.0.1:8000/v1"
    model: str = "phi-3-mini"
    api_key: Optional[str] = None
    api_key_env: str = "OPENAI_API_KEY"
    timeout_s: float = 10.0
    json_schema: bool = True
    max_tokens: int = 512


class OpenAIChatBackend(LLMBackend):
    """Backend over any OpenAI-compatible ``POST {base_url}/chat/completions`` (urllib only)."""

    name = "openai"

    def __init__(self, config: OpenAIConfig):
        """Args: config (OpenAIConfig). Raises: BackendUnavailableError: no base URL or model."""
        if not config.base_url or not config.model:
            raise BackendUnavailableError("openai backend needs 'base_url' and 'model'")
        self.config = config

    def _post(self, body: Dict[str, Any], timeout: float) -> Dict[str, Any]:
        url = self.config.base_url.rstrip("/") + "/chat/completions"
        headers = {"Content-Type": "application/json", "Accept": "application/json"}
        key = self.config.api_key or os.environ.get(self.config.api_key_env or "", "")
        if key:
            headers["Authorization"] = f"Bearer {key}"
        req = urllib.request.Request(url, data=json.dumps(body).encode("utf-8"), headers=headers, method="POST")
        with urllib.request.urlopen(req, timeout=timeout) as resp:
            payload = resp.read()
        try:
            return json.loads(payload.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            raise LLMOutputError(f"endpoint returned a non-JSON body: {e}") from e

    def complete(self, messages: List[Dict[str, str]], timeout_s: Optional[float] = None) -> str:
        """POST the chat request and return ``choices[0].message.content``.

        Raises:
            LLMBackendError: HTTP error status, connection failure or timeout.
            LLMOutputError: the response body is not a chat-completion object.
        """
        timeout = self.config.timeout_s if timeout_s is None else max(0.01, min(timeout_s, self.config.timeout_s))
        body: Dict[str, Any] = {
            "model": self.config.model,
            "messages": messages,
            "temperature": 0,
            "max_tokens": self.config.max_tokens,
        }
        if self.config.json_schema:
            body["response_format"] = {
                "type": "json_schema",
                "json_schema": {"name": "task_graph", "schema": TASK_GRAPH_SCHEMA, "strict": True},
            }
        try:
            try:
                data = self._post(body, timeout)
            except urllib.error.HTTPError as e:
                if e.code == 400 and "response_format" in body:
                    body.pop("response_format")
                    data = self._post(body, timeout)
                else:
                    raise
        except urllib.error.HTTPError as e:
            raise LLMBackendError(f"HTTP {e.code} from {self.config.base_url}") from e
        except (socket.timeout, TimeoutError) as e:
            raise LLMBackendError(f"timed out after {timeout:.2f} s waiting for {self.config.base_url}") from e
        except urllib.error.URLError as e:
            if isinstance(e.reason, (socket.timeout, TimeoutError)):
                raise LLMBackendError(f"timed out after {timeout:.2f} s waiting for {self.config.base_url}") from e
            raise LLMBackendError(f"cannot reach {self.config.base_url}: {e.reason}") from e
        except (OSError, ValueError) as e:
            if isinstance(e, LLMOutputError):
                raise
            raise LLMBackendError(f"request to {self.config.base_url} failed: {e}") from e
        try:
            content = data["choices"][0]["message"]["content"]
        except (KeyError, IndexError, TypeError) as e:
            raise LLMOutputError("endpoint answer has no choices[0].message.content") from e
        if not isinstance(content, str):
            raise LLMOutputError("choices[0].message.content is not a string")
        return content


@dataclass
class OnnxGenAIConfig:
    """Settings of the local ONNX Runtime GenAI backend.

    Attributes:
        model_dir (str): folder with ``genai_config.json`` and the ONNX model (e.g. Phi-3-mini int4).
        max_length (int): maximum total sequence length (prompt + answer) in tokens.
        execution_provider (str | None): e.g. ``"cuda"``; ``None`` follows the model's config.
        use_guidance (bool): constrain decoding to :data:`TASK_GRAPH_SCHEMA` when the installed
            onnxruntime-genai supports ``GeneratorParams.set_guidance``.
    """

    model_dir: str = ""
    max_length: int = 2048
    execution_provider: Optional[str] = None
    use_guidance: bool = True


def _phi3_prompt(messages: List[Dict[str, str]]) -> str:
    parts = [f"<|{m['role']}|>\n{m['content']}<|end|>\n" for m in messages]
    return "".join(parts) + "<|assistant|>\n"


class OnnxGenAIBackend(LLMBackend):
    """Local model through ONNX Runtime GenAI (``onnxruntime_genai``), greedy decoding.

    The package is imported and the folder checked at construction; the model itself is loaded on
    the first call (thread safe; calls are serialised because one generator runs at a time).
    """

    name = "onnx"

    def __init__(self, config: OnnxGenAIConfig):
        """Args: config (OnnxGenAIConfig).

        Raises:
            BackendUnavailableError: ``onnxruntime_genai`` is not installed, or ``model_dir`` is not
                a folder containing ``genai_config.json``.
        """
        try:
            # lazy: heavy optional dependency, loaded only on this path
            import onnxruntime_genai as og  # noqa: PLC0415 - optional dependency, imported lazily
        except ImportError as e:
            raise BackendUnavailableError(
                "the 'onnx' parser backend needs the onnxruntime-genai package "
                "(pip install onnxruntime-genai); it is not installed"
            ) from e
        folder = Path(config.model_dir).expanduser() if config.model_dir else None
        if folder is None or not folder.is_dir():
            raise BackendUnavailableError(f"ONNX GenAI model folder not found: {config.model_dir!r}")
        if not (folder / "genai_config.json").is_file():
            raise BackendUnavailableError(
                f"{folder} is not an ONNX Runtime GenAI model folder (no genai_config.json)"
            )
        self._og = og
        self.config = config
        self.folder = folder
        self._lock = threading.Lock()
        self._model = None
        self._tokenizer = None

    def _load(self) -> None:
        og = self._og
        cfg = og.Config(str(self.folder))
        if self.config.execution_provider:
            cfg.clear_providers()
            if self.config.execution_provider != "cpu":
                cfg.append_provider(self.config.execution_provider)
        self._model = og.Model(cfg)
        self._tokenizer = og.Tokenizer(self._model)

    def _prompt(self, messages: List[Dict[str, str]]) -> str:
        tok = self._tokenizer
        if hasattr(tok, "apply_chat_template"):
            try:
                return tok.apply_chat_template(messages=json.dumps(messages), add_generation_prompt=True)
            except Exception:  # model without a chat template: fall back to Phi-3's format
                pass
        return _phi3_prompt(messages)

    def complete(self, messages: List[Dict[str, str]], timeout_s: Optional[float] = None) -> str:
        """Greedy-decode an answer with ``og.Generator`` (append_tokens / generate_next_token).

        ``timeout_s`` is checked between tokens.

        Raises:
            LLMBackendError: model loading or generation failed, or the timeout passed.
        """
        og = self._og
        t0 = time.monotonic()
        with self._lock:
            try:
                if self._model is None:
                    self._load()
                prompt = self._prompt(messages)
                input_tokens = self._tokenizer.encode(prompt)
                params = og.GeneratorParams(self._model)
                params.set_search_options(max_length=self.config.max_length, do_sample=False)
                if self.config.use_guidance and hasattr(params, "set_guidance"):
                    params.set_guidance("json_schema", json.dumps(TASK_GRAPH_SCHEMA))
                generator = og.Generator(self._model, params)
                generator.append_tokens(input_tokens)
                stream = self._tokenizer.create_stream()
                out: List[str] = []
                while not generator.is_done():
                    if timeout_s is not None and time.monotonic() - t0 > timeout_s:
                        raise LLMBackendError(f"onnx generation exceeded {timeout_s:.2f} s")
                    generator.generate_next_token()
                    out.append(stream.decode(generator.get_next_tokens()[0]))
                return "".join(out)
            except LLMBackendError:
                raise
            except Exception as e:  # onnxruntime_genai raises plain RuntimeError/OSError
                raise LLMBackendError(f"onnx generation failed: {e}") from e
