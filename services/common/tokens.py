"""Tokens at rest and on disk for the GaussLite gRPC services (``docs/security.md``): their hashes
(:func:`hash_token`, :func:`verify_token`, :func:`new_token`), secret files (:func:`read_secret`,
:func:`write_secret`), token files (:func:`parse_token_records`, :func:`read_token_file`, :func:`write_token_file`)
and their administration (:func:`issue_token`, :func:`revoke_token`, :func:`provision`; ``gausslite tokens``).
:mod:`gausslite_services.common.auth`, which identifies callers by them, re-exports every name.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import os
import re
import secrets
from pathlib import Path
from typing import Dict, Mapping, Optional, Sequence, Tuple

import yaml

__all__ = ["AGENT_ID_RE", "MAX_TOKEN_CHARS", "PBKDF2_ITERATIONS", "TOKEN_RE", "check_token", "hash_token",
           "verify_token", "new_token", "read_secret", "write_secret", "parse_token_records", "read_token_file",
           "write_token_file", "issue_token", "revoke_token", "provision"]

#: Agent ids: 1..64 characters of ``[A-Za-z0-9_.-]`` (the fusion server's rule).
AGENT_ID_RE = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")
#: Longest bearer token accepted (characters).
MAX_TOKEN_CHARS = 512
PBKDF2_ITERATIONS = 200_000
_SHA256_RE = re.compile(r"^sha256:([0-9a-f]{64})$")
_PBKDF2_RE = re.compile(r"^pbkdf2_sha256\$(\d{1,8})\$([A-Za-z0-9+/=_-]{8,128})\$([A-Za-z0-9+/=_-]{40,128})$")
#: a bearer token: printable ASCII, no leading or trailing space
TOKEN_RE = re.compile(r"^[\x21-\x7e](?:[\x20-\x7e]{0,%d}[\x21-\x7e])?$" % (MAX_TOKEN_CHARS - 2))


# ---------------------------------------------------------------------------------------------- hashing
def hash_token(token: str, scheme: str = "sha256", iterations: int = PBKDF2_ITERATIONS) -> str:
    """The at-rest record of ``token``.

    ``sha256`` suits generated tokens (:func:`new_token`: 256 random bits, so a fast hash loses
    nothing); ``pbkdf2`` (salted PBKDF2-HMAC-SHA256) suits tokens a person chose.

    Args:
        token (str): the token (1..512 printable ASCII characters, no leading/trailing space).
        scheme (str): ``"sha256"`` or ``"pbkdf2"``.
        iterations (int): PBKDF2 iterations (>= 10000).
    Returns:
        str: ``sha256:<hex>`` or ``pbkdf2_sha256$<iterations>$<salt>$<hash>`` (URL-safe base64).
    Raises:
        ValueError: malformed token, unknown scheme, too few iterations.
    """
    check_token(token)
    if scheme == "sha256":
        return "sha256:" + hashlib.sha256(token.encode("ascii")).hexdigest()
    if scheme == "pbkdf2":
        if int(iterations) < 10_000:
            raise ValueError(f"pbkdf2 needs >= 10000 iterations, got {iterations}")
        salt = secrets.token_bytes(16)
        dk = hashlib.pbkdf2_hmac("sha256", token.encode("ascii"), salt, int(iterations))
        b64 = lambda b: base64.urlsafe_b64encode(b).decode("ascii").rstrip("=")  # noqa: E731
        return f"pbkdf2_sha256${int(iterations)}${b64(salt)}${b64(dk)}"
    raise ValueError(f"unknown hash scheme {scheme!r}; use 'sha256' or 'pbkdf2'")


def verify_token(token: str, record: str) -> bool:
    """True when ``token`` matches the at-rest ``record`` (constant-time comparison).

    Raises:
        ValueError: ``record`` is not a ``sha256:`` or ``pbkdf2_sha256$`` record.
    """
    m = _SHA256_RE.match(record)
    if m:
        return hmac.compare_digest(hashlib.sha256(token.encode("utf-8")).hexdigest(), m.group(1))
    m = _PBKDF2_RE.match(record)
    if m:
        unb64 = lambda s: base64.urlsafe_b64decode(s + "=" * (-len(s) % 4))  # noqa: E731
        dk = hashlib.pbkdf2_hmac("sha256", token.encode("utf-8"), unb64(m.group(2)), int(m.group(1)))
        return hmac.compare_digest(dk, unb64(m.group(3)))
    raise ValueError("token record must be 'sha256:<64 hex>' or 'pbkdf2_sha256$<iterations>$<salt>$<hash>'")


def new_token() -> str:
    """A fresh random token (256 bits, 64 hex digits). Hex, not URL-safe base64: a base64 token starts with ``-``
    one time in 64, and a command line (``gausslite tokens hash --token T``) then reads it as an option."""
    return secrets.token_hex(32)


def check_token(token: str) -> None:
    """Raise ValueError unless ``token`` is 1..:data:`MAX_TOKEN_CHARS` printable ASCII characters without leading or
    trailing spaces (the form of every bearer token)."""
    if not isinstance(token, str) or not TOKEN_RE.match(token):
        raise ValueError(f"a token must be 1..{MAX_TOKEN_CHARS} printable ASCII characters, "
                         "without leading or trailing spaces")


def read_secret(path: str | os.PathLike) -> str:
    """A token from a secret file (a docker secret, a mounted Kubernetes Secret key), surrounding
    whitespace stripped.

    Raises:
        FileNotFoundError / OSError: unreadable file. ValueError: empty or not a valid token.
    """
    text = Path(path).read_text(encoding="utf-8", errors="replace").strip()
    if not text:
        raise ValueError(f"token file {path} is empty")
    try:
        check_token(text)
    except ValueError as e:
        raise ValueError(f"token file {path}: {e}") from None
    return text


# ---------------------------------------------------------------------------------------------- token file
def parse_token_records(data: object, source: str = "token file") -> Dict[str, Tuple[str, ...]]:
    """Validate the parsed contents of a token file.

    Args:
        data: the parsed document: ``{"agents": {agent_id: record | [record, ...]}}``.
        source (str): named in error messages.
    Returns:
        dict: agent id → its records (a revoked agent is simply absent).
    Raises:
        ValueError: not that shape, a bad agent id, a malformed record, or one sha256 record under two
            agents.
    """
    if not isinstance(data, dict) or set(data) - {"agents"}:
        raise ValueError(f"{source}: expected a mapping with one key 'agents' (agent id -> token hash)")
    agents = data.get("agents") or {}
    if not isinstance(agents, dict):
        raise ValueError(f"{source}: 'agents' must map agent ids to token hashes")
    out: Dict[str, Tuple[str, ...]] = {}
    owner: Dict[str, str] = {}
    for agent, recs in agents.items():
        if not isinstance(agent, str) or not AGENT_ID_RE.match(agent):
            raise ValueError(f"{source}: invalid agent id {str(agent)[:80]!r}: need 1..64 characters of [A-Za-z0-9_.-]")
        recs = [recs] if isinstance(recs, str) else recs
        if not isinstance(recs, list) or not recs or not all(isinstance(r, str) for r in recs):
            raise ValueError(f"{source}: agent {agent!r}: expected a token hash or a non-empty list of them")
        for r in recs:
            if not (_SHA256_RE.match(r) or _PBKDF2_RE.match(r)):
                raise ValueError(f"{source}: agent {agent!r}: malformed token hash {r[:24]!r}... (expected "
                                 "'sha256:<64 hex>' or 'pbkdf2_sha256$<iterations>$<salt>$<hash>')")
            if r.startswith("sha256:"):
                if owner.setdefault(r, agent) != agent:
                    raise ValueError(f"{source}: agents {owner[r]!r} and {agent!r} share one token")
        out[agent] = tuple(recs)
    return out


def read_token_file(path: str | os.PathLike) -> Dict[str, Tuple[str, ...]]:
    """Read and validate a token file (JSON, or YAML when the name ends in .yaml/.yml).

    Raises:
        OSError: unreadable file. ValueError: unparsable or invalid contents (:func:`parse_token_records`).
    """
    p = Path(path)
    text = p.read_text(encoding="utf-8")
    try:
        if p.suffix.lower() in (".yaml", ".yml"):
            data = yaml.safe_load(text)
        else:
            data = json.loads(text)
    except Exception as e:  # noqa: BLE001 - any parser error is a file error
        raise ValueError(f"cannot parse token file {p}: {type(e).__name__}: {e}") from None
    return parse_token_records({} if data is None else data, str(p))


def write_token_file(path: str | os.PathLike, records: Mapping[str, Sequence[str]]) -> None:
    """Atomically write a token file (JSON or YAML by suffix, mode 0600).

    Raises:
        ValueError: invalid records (:func:`parse_token_records`). OSError: unwritable directory.
    """
    p = Path(path)
    doc = {"agents": {a: (list(r) if len(r) > 1 else r[0]) for a, r in sorted(records.items())}}
    parse_token_records(doc, str(p))
    if p.suffix.lower() in (".yaml", ".yml"):
        text = yaml.safe_dump(doc, sort_keys=True)
    else:
        text = json.dumps(doc, indent=2, sort_keys=True) + "\n"
    tmp = p.with_name(f".{p.name}.tmp{os.getpid()}")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, p)


# ---------------------------------------------------------------------------------------------- provisioning
def _load_or_empty(path: Path) -> Dict[str, Tuple[str, ...]]:
    return read_token_file(path) if path.exists() else {}


def issue_token(tokens_file: str | os.PathLike, agent_id: str, *, keep_old: bool = False,
                scheme: str = "sha256") -> str:
    """Make a new random token for ``agent_id`` and store its hash in ``tokens_file`` (created when
    missing).

    Args:
        tokens_file: the server's token file.
        agent_id (str): 1..64 characters of ``[A-Za-z0-9_.-]``.
        keep_old (bool): keep the agent's earlier records (token rotation: both work until the old
            one is revoked with :func:`revoke_token` ``keep_newest=True``).
        scheme (str): :func:`hash_token` scheme.
    Returns:
        str: the new token (give it to the robot; it is not stored).
    Raises:
        ValueError: bad agent id or an invalid existing file. OSError: unwritable file.
    """
    if not isinstance(agent_id, str) or not AGENT_ID_RE.match(agent_id):
        raise ValueError(f"invalid agent id {agent_id!r}: need 1..64 characters of [A-Za-z0-9_.-]")
    path = Path(tokens_file)
    records = _load_or_empty(path)
    token = new_token()
    old = records.get(agent_id, ()) if keep_old else ()
    records[agent_id] = tuple(old) + (hash_token(token, scheme),)
    write_token_file(path, records)
    return token


def revoke_token(tokens_file: str | os.PathLike, agent_id: str, *, keep_newest: bool = False) -> bool:
    """Remove ``agent_id``'s records from ``tokens_file`` (``keep_newest``: all but the last one).

    Returns:
        bool: something was removed.
    Raises:
        ValueError: invalid file. OSError: unreadable or unwritable file.
    """
    path = Path(tokens_file)
    records = read_token_file(path)
    if agent_id not in records:
        return False
    if keep_newest and len(records[agent_id]) > 1:
        records[agent_id] = records[agent_id][-1:]
    elif keep_newest:
        return False
    else:
        del records[agent_id]
    write_token_file(path, records)
    return True


def write_secret(path: str | os.PathLike, text: str) -> None:
    """Write a secret (a token) to ``path`` with mode 0600, newline-terminated.

    Raises:
        OSError: unwritable path.
    """
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w", encoding="ascii") as f:
        f.write(text + "\n")


def provision(directory: str | os.PathLike, agent_ids: Sequence[str], *, tokens_name: str = "fusion_tokens.json",
              force: bool = False) -> Dict[str, Optional[Path]]:
    """One token per agent in ``directory/<agent>.token`` (mode 0600) and their hashes in
    ``directory/<tokens_name>`` (the server's token file): what docker secrets or a Kubernetes Secret
    are made from.

    Args:
        directory: created when missing.
        agent_ids: the agents (1..64 characters of ``[A-Za-z0-9_.-]`` each).
        tokens_name (str): file name of the token file (``.json``, ``.yaml`` or ``.yml``).
        force (bool): replace existing token files (their old tokens stop working).
    Returns:
        dict: agent id → path of its new token file, or None when an existing one was kept.
    Raises:
        ValueError: a bad agent id or an invalid existing token file. OSError: unwritable directory.
    """
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    tokens_file = out / tokens_name
    done: Dict[str, Optional[Path]] = {}
    for agent in agent_ids:
        token_path = out / f"{agent}.token"
        known = tokens_file.exists() and agent in read_token_file(tokens_file)
        if token_path.exists() and known and not force:
            done[agent] = None
            continue
        token = issue_token(tokens_file, agent)
        write_secret(token_path, token)
        done[agent] = token_path
    return done
