"""Who is calling: caller identity for the GaussLite gRPC services (see ``docs/security.md``).

Credentials a caller may present, and the :class:`Principal` each one yields:

* **Fleet token** (``authorization: Bearer <token>``, ``--token`` / ``GAUSSLITE_TOKEN``): one secret
  shared by the whole team. Alone on a server it is the *team-wide mode*: its holder may read and
  write every agent's data (the behaviour before per-robot identities existed). Next to per-robot
  credentials it authenticates a team member that may read and fuse but write no agent's data
  (unless ``fleet_writes`` is set, for a migration).
* **Per-agent token** (same metadata): looked up in an :class:`AgentTokens` file that stores only
  hashes (``agent_id → sha256:… | pbkdf2_sha256$…``); it authenticates that agent, which may write
  only its own data. The file is re-read when its stat signature (mtime, size, inode) changes and on
  :meth:`Authenticator.reload` (SIGHUP); a token removed from it is refused from the next call on.
* **Client certificate** (mTLS; the server's TLS client CA, :mod:`gausslite_services.common.server`): the
  subject CN is the agent id.

:class:`Authenticator` turns a call's metadata and TLS auth context into a :class:`Principal`
(raising :class:`AuthError` with ``UNAUTHENTICATED``); :meth:`Principal.check_write` raises
``PERMISSION_DENIED`` for a write to another agent's data. Nothing here is specific to one service;
the fusion server decides which of its RPCs are writes.

Token files (JSON or YAML)::

    agents:
      robot-1: sha256:9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08
      robot-2:                         # several records: old and new token during a rotation
        - sha256:...
        - pbkdf2_sha256$200000$<salt b64>$<hash b64>

Command line: ``gausslite tokens {issue,revoke,hash,provision}`` (:func:`issue_token`,
:func:`revoke_token`, :func:`hash_token`, :func:`provision`). Hashing, secret files, token files and their
administration are :mod:`gausslite_services.common.tokens`' (re-exported here).
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import os
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Iterable, List, Mapping, Optional, Sequence, Tuple

import grpc

# tokens at rest and on disk live in a module of their own; their names import from here as before
from gausslite_services.common.tokens import (AGENT_ID_RE, MAX_TOKEN_CHARS, PBKDF2_ITERATIONS,  # noqa: F401
                                              TOKEN_RE, check_token, hash_token, issue_token, new_token,
                                              parse_token_records, provision, read_secret, read_token_file,
                                              revoke_token, verify_token, write_secret, write_token_file)

log = logging.getLogger(__name__)


class AuthError(Exception):
    """A call is refused: ``code`` (``UNAUTHENTICATED`` or ``PERMISSION_DENIED``) and ``message``."""

    def __init__(self, code: grpc.StatusCode, message: str):
        super().__init__(message)
        self.code = code
        self.message = message


@dataclass(frozen=True)
class Principal:
    """An authenticated caller.

    Attributes:
        agent_id (str | None): the agent this caller is; None for a team member bound to no agent.
        via (str): how it authenticated: ``"agent-token"``, ``"mtls"``, ``"fleet-token"`` or
            ``"open"`` (the server requires no credentials).
        may_write_any (bool): may write every agent's data (team-wide mode, open servers).
    """

    agent_id: Optional[str]
    via: str
    may_write_any: bool = False

    def describe(self) -> str:
        """A short description for log lines, e.g. ``agent 'robot-1' (agent-token)``."""
        who = f"agent {self.agent_id!r}" if self.agent_id else "team member"
        return f"{who} ({self.via})"

    def may_write(self, agent_id: str) -> bool:
        """True when this caller may write ``agent_id``'s data."""
        return self.may_write_any or (self.agent_id is not None and self.agent_id == agent_id)

    def check_write(self, agent_id: str) -> None:
        """Raise unless this caller may write ``agent_id``'s data.

        Raises:
            AuthError: ``PERMISSION_DENIED`` naming the caller and the agent.
        """
        if not self.may_write(agent_id):
            raise AuthError(grpc.StatusCode.PERMISSION_DENIED,
                            f"{self.describe()} may not write the data of agent {agent_id!r}")


OPEN = Principal(None, "open", True)


def _signature(path: Path) -> Optional[tuple]:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_mtime_ns, st.st_size, st.st_ino, st.st_dev)


class AgentTokens:
    """Per-agent token hashes from a file, re-read when it changes.

    Before every lookup the file's stat signature (mtime, size, inode) is compared with the loaded
    one; a change re-reads it. A file that became unreadable or invalid *fails closed*: no per-agent
    token is accepted (error logged) until it is valid again. :meth:`reload` re-reads unconditionally
    (the servers call it on SIGHUP).

    Args:
        path: the token file (:func:`read_token_file`).
        watch (bool): compare the stat signature before lookups (False: only :meth:`reload` re-reads).
    Raises:
        OSError / ValueError: the file cannot be read or is invalid at construction.
    """

    def __init__(self, path: str | os.PathLike, *, watch: bool = True):
        self.path = Path(path)
        self.watch = bool(watch)
        self._lock = threading.Lock()
        sig = _signature(self.path)
        self._records = read_token_file(self.path)
        self._sig = sig
        self._error: Optional[str] = None
        self._by_sha = self._index(self._records)
        self._verified: Dict[str, str] = {}  # sha256(token) -> agent, for pbkdf2 records
        log.info("per-agent tokens: %d agent(s) from %s", len(self._records), self.path)

    @staticmethod
    def _index(records: Mapping[str, Tuple[str, ...]]) -> Dict[str, str]:
        return {r[len("sha256:"):]: a for a, rs in records.items() for r in rs if r.startswith("sha256:")}

    def agents(self) -> List[str]:
        """Agent ids that currently hold a token (empty while the file is invalid)."""
        self._maybe_reload()
        return sorted(self._records) if self._error is None else []

    def reload(self, force: bool = True) -> bool:
        """Re-read the file (``force=False``: only when its stat signature changed).

        Returns:
            bool: the file was (re-)read successfully. A failure is logged and leaves the store
            failing closed; it never raises.
        """
        with self._lock:
            sig = _signature(self.path)
            if not force and sig == self._sig:
                return False
            self._sig = sig
            try:
                records = read_token_file(self.path)
            except (OSError, ValueError) as e:
                msg = f"{type(e).__name__}: {e}"
                if msg != self._error:
                    log.error("token file %s unusable, refusing every per-agent token until fixed: %s",
                              self.path, msg)
                self._error = msg
                self._records, self._by_sha, self._verified = {}, {}, {}
                return False
            revoked = sorted(set(self._records) - set(records))
            self._records, self._by_sha, self._verified = records, self._index(records), {}
            if self._error is not None:
                log.info("token file %s usable again", self.path)
            self._error = None
            log.info("per-agent tokens reloaded from %s: %d agent(s)%s", self.path, len(records),
                     f", revoked {', '.join(revoked)}" if revoked else "")
            return True

    def _maybe_reload(self) -> None:
        if self.watch and _signature(self.path) != self._sig:
            self.reload(force=False)

    def identify(self, token: str, cheap_only: bool = False) -> Optional[str]:
        """The agent id whose record matches ``token``, or None.

        sha256 records are one dictionary lookup; pbkdf2 records cost one key derivation each for a
        token not seen before (matches are remembered until the next reload). ``cheap_only``: no key derivation
        (a token not seen before matches no pbkdf2 record).
        """
        self._maybe_reload()
        digest = hashlib.sha256(token.encode("utf-8")).hexdigest()
        by_sha, verified, records = self._by_sha, self._verified, self._records
        agent = by_sha.get(digest) or verified.get(digest)
        if agent is not None or cheap_only:
            return agent
        for a, recs in records.items():
            for r in recs:
                if r.startswith("pbkdf2_sha256$") and verify_token(token, r):
                    if records is self._records:
                        self._verified[digest] = a
                    return a
        return None


# ---------------------------------------------------------------------------------------------- authenticator
def bearer_token(metadata: Optional[Iterable[Tuple[str, object]]]) -> Optional[str]:
    """The token of the call's ``authorization: Bearer <token>`` metadata, or None when absent.

    Raises:
        AuthError: ``UNAUTHENTICATED`` for a malformed value or a repeated ``authorization`` key.
    """
    found = None
    for key, val in metadata or ():
        if key.lower() != "authorization":
            continue
        if found is not None:
            raise AuthError(grpc.StatusCode.UNAUTHENTICATED, "more than one 'authorization' metadata entry")
        found = val if isinstance(val, str) else bytes(val).decode("utf-8", "replace")
    if found is None:
        return None
    scheme, _, token = found.partition(" ")
    if scheme != "Bearer" or not TOKEN_RE.match(token):
        raise AuthError(grpc.StatusCode.UNAUTHENTICATED,
                        "malformed authorization metadata: expected 'Bearer <token>'")
    return token


def certificate_cn(auth_context: Optional[Mapping[str, Sequence[bytes]]]) -> Optional[str]:
    """The verified client certificate's subject CN from a gRPC auth context, or None without one."""
    names = (auth_context or {}).get("x509_common_name") or ()
    if not names:
        return None
    v = names[0]
    return v.decode("utf-8", "replace") if isinstance(v, (bytes, bytearray)) else str(v)


class Authenticator:
    """Maps a call's credentials to a :class:`Principal` (see the module docstring).

    Args:
        fleet_token (str | None): the team-wide bearer token.
        agent_tokens (AgentTokens | None): per-agent token hashes.
        mtls (bool): the server verifies client certificates; their CN names the agent.
        fleet_writes (bool | None): the fleet token may write every agent's data. None (default):
            only when it is the server's sole credential (team-wide mode).
    Raises:
        ValueError: an empty or malformed fleet token.
    """

    def __init__(self, fleet_token: Optional[str] = None, agent_tokens: Optional[AgentTokens] = None,
                 mtls: bool = False, fleet_writes: Optional[bool] = None):
        if fleet_token is not None:
            try:
                check_token(fleet_token)
            except ValueError as e:
                raise ValueError(f"fleet token: {e}") from None
        self._fleet = fleet_token.encode("ascii") if fleet_token else None
        self.agent_tokens = agent_tokens
        self.mtls = bool(mtls)
        per_agent = agent_tokens is not None or self.mtls
        self.fleet_writes = (not per_agent) if fleet_writes is None else bool(fleet_writes)

    @property
    def enabled(self) -> bool:
        """False when the server takes no credentials at all (every caller is :data:`OPEN`)."""
        return self._fleet is not None or self.agent_tokens is not None or self.mtls

    def describe(self) -> str:
        """The configured credential kinds, for the startup log line."""
        kinds = []
        if self._fleet is not None:
            kinds.append("fleet token" + (" (team-wide writes)" if self.fleet_writes else " (read/fuse only)"))
        if self.agent_tokens is not None:
            kinds.append(f"per-agent tokens from {self.agent_tokens.path}")
        if self.mtls:
            kinds.append("client certificates (CN = agent id)")
        return ", ".join(kinds) or "no credentials required"

    def reload(self) -> None:
        """Re-read the per-agent token file now (SIGHUP); never raises."""
        if self.agent_tokens is not None:
            self.agent_tokens.reload(force=True)

    def identify(self, metadata=None, auth_context=None, cheap_only: bool = False) -> Principal:
        """Authenticate one call.

        Args:
            metadata: the call's invocation metadata (key, value) pairs.
            auth_context (dict | None): the call's ``context.auth_context()``.
            cheap_only (bool): no key derivation for a token not verified before (a peer over its failure budget,
                :class:`gausslite_services.common.server.FailureLimiter`).
        Returns:
            Principal: the caller.
        Raises:
            AuthError: ``UNAUTHENTICATED``: no credential although one is required, a malformed or
                unknown (or revoked) token, a token and a client certificate naming different agents, or (with
                per-agent tokens) a client certificate of an agent absent from the token file (revoked).
        """
        if not self.enabled:
            return OPEN
        token = bearer_token(metadata)
        cert_agent = None
        if self.mtls:
            cn = certificate_cn(auth_context)
            if cn is None:
                raise AuthError(grpc.StatusCode.UNAUTHENTICATED, "no verified client certificate")
            cert_agent = cn if AGENT_ID_RE.match(cn) else None
        token_principal = None
        if token is not None:
            if self._fleet is not None and hmac.compare_digest(token.encode("ascii"), self._fleet):
                token_principal = Principal(None, "fleet-token", self.fleet_writes)
            else:
                agent = self.agent_tokens.identify(token, cheap_only) if self.agent_tokens is not None else None
                if agent is None:
                    raise AuthError(grpc.StatusCode.UNAUTHENTICATED, "invalid or revoked bearer token")
                token_principal = Principal(agent, "agent-token")
        if self.mtls:
            if cert_agent is not None and token_principal is not None \
                    and token_principal.agent_id not in (None, cert_agent):
                raise AuthError(grpc.StatusCode.UNAUTHENTICATED,
                                f"the bearer token names agent {token_principal.agent_id!r}, the client "
                                f"certificate {cert_agent!r}")
            if cert_agent is not None:
                # with per-agent tokens the token file is the roster: an agent revoked there (absent from it) is
                # refused with its certificate too, so a revocation holds for either credential
                if self.agent_tokens is not None and cert_agent not in self.agent_tokens.agents():
                    raise AuthError(grpc.StatusCode.UNAUTHENTICATED,
                                    f"agent {cert_agent!r} is revoked (not in the token file); its client "
                                    "certificate is refused too")
                return Principal(cert_agent, "mtls")
            if token_principal is not None:
                return token_principal
            return Principal(None, "mtls")  # a certificate whose CN is no agent id: team member
        if token_principal is None:
            raise AuthError(grpc.StatusCode.UNAUTHENTICATED, "missing 'authorization: Bearer <token>' metadata")
        return token_principal

    def identify_context(self, context, cheap_only: bool = False) -> Principal:
        """:meth:`identify` for a gRPC servicer ``context``. Raises AuthError."""
        if not self.enabled:
            return OPEN
        return self.identify(context.invocation_metadata(), context.auth_context(), cheap_only)


__all__ = ["AGENT_ID_RE", "AuthError", "Principal", "OPEN", "hash_token", "verify_token", "new_token",
           "parse_token_records", "read_token_file", "write_token_file", "AgentTokens", "bearer_token",
           "certificate_cn", "Authenticator", "issue_token", "revoke_token", "read_secret", "write_secret",
           "provision"]
