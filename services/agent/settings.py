"""The agent process's settings (:class:`AgentSettings`) and where they come from: the ``GAUSSLITE_*`` environment
variables (:data:`ENV`, read through :class:`gausslite.core.environment.EnvironmentSettings`) and the GaussLite YAML
(:func:`settings_from_env`). :mod:`gausslite_services.agent.server` re-exports every name.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from typing import Optional, Tuple

from gausslite.config import load_config
from gausslite.core.environment import EnvironmentSettings
from gausslite.mission import AgentConfig
from gausslite_services.common.auth import read_secret

log = logging.getLogger("gausslite_services.agent.server")  # one logger for the agent service

__all__ = ["AgentSettings", "ENV", "settings_from_env"]


@dataclass
class AgentSettings:
    """Settings of one agent process.

    Attributes:
        agent_id (str): id on the fusion server.
        parser_address (str): parser service ``host:port``; empty → in-process rule parser.
        fusion_address (str): fusion server ``host:port``; empty → no pushes (local mapping only).
        fusion_allow (tuple[str, ...]): other fusion servers a ``StartMission`` may name (``fusion_address`` of the
            request). The agent sends its fusion token and client certificate to the server it pushes to, so it
            never pushes to an address a caller picks: one not configured here is PERMISSION_DENIED
            (``docs/security.md``).
        data_roots (tuple[str, ...]): folders under which a ``StartMission``'s ``dataset_path`` and
            ``annotations_path`` must lie (after following symlinks and ``..``); any other path is PERMISSION_DENIED.
            The configured ``dataset`` and ``annotations_path`` always count as roots (a folder itself, a file its
            folder). Env ``GAUSSLITE_AGENT_DATA_ROOTS`` (comma-separated), CLI ``--data-root``.
        token (str | None): bearer token sent to the parser service, and to the fusion server unless
            a per-agent fusion token is set (the fleet token: team-wide mode).
        fusion_token (str | None): this robot's own token for the fusion server (per-robot identity:
            it may write only ``agent_id``'s data there; ``docs/security.md``).
        fusion_token_file (str | None): file holding that token (a docker secret / mounted Kubernetes
            Secret); read whenever a mission connects, so a rotated token is picked up by the next one.
        root_cert (str | None): PEM file of the CA for TLS to parser/fusion (None: plaintext).
        tls_client_cert (str | None), tls_client_key (str | None): PEM client certificate and key
            presented to the fusion server (mutual TLS; the certificate's CN must be ``agent_id``).
        data_dir (str | None): where finished missions write ``<agent_id>/<mission>/map.ply`` and
            ``summary.json``.
        dataset (str | None), task (str | None), task_id (str | None): auto-start a replay mission at boot.
        annotations_path (str | None): default scene folder with ``objects.json``/``tasks.json`` for
            streamed missions.
        auto_finish (bool): finish an auto-started replay mission (final push) when it is mapped.
        parser_timeout_s (float): deadline of the Parse call, which waits for the parser to become ready: long
            enough for a parser process started beside the agent on a busy robot computer to load.
        shutdown_s (float): on SIGTERM, how long the agent may take to push the final subset of a mission still
            mapping and write its checkpoint before it exits (:meth:`AgentServicer.shutdown`).
        config (AgentConfig): mission/mapper settings.
    """

    agent_id: str = "agent"
    parser_address: str = ""
    fusion_address: str = ""
    fusion_allow: Tuple[str, ...] = ()
    data_roots: Tuple[str, ...] = ()
    token: Optional[str] = None
    fusion_token: Optional[str] = None
    fusion_token_file: Optional[str] = None
    root_cert: Optional[str] = None
    tls_client_cert: Optional[str] = None
    tls_client_key: Optional[str] = None
    data_dir: Optional[str] = None
    dataset: Optional[str] = None
    task: Optional[str] = None
    task_id: Optional[str] = None
    annotations_path: Optional[str] = None
    auto_finish: bool = True
    parser_timeout_s: float = 120.0
    shutdown_s: float = 30.0
    config: AgentConfig = field(default_factory=lambda: AgentConfig())


#: AgentSettings field → the :class:`~gausslite.core.environment.EnvironmentSettings` field (``GAUSSLITE_*`` variable)
#: it falls back to
ENV = {
    "agent_id": "agent_id",  # GAUSSLITE_AGENT_ID
    "parser_address": "parser_addr",  # GAUSSLITE_PARSER_ADDR
    "fusion_address": "fusion_addr",  # GAUSSLITE_FUSION_ADDR
    "fusion_allow": "fusion_allow",  # GAUSSLITE_FUSION_ALLOW
    "data_roots": "agent_data_roots",  # GAUSSLITE_AGENT_DATA_ROOTS
    "data_dir": "data_dir",  # GAUSSLITE_DATA_DIR
    "dataset": "agent_dataset",  # GAUSSLITE_AGENT_DATASET
    "task": "agent_task",  # GAUSSLITE_AGENT_TASK
    "task_id": "agent_task_id",  # GAUSSLITE_AGENT_TASK_ID
    "annotations_path": "agent_annotations",  # GAUSSLITE_AGENT_ANNOTATIONS
    "root_cert": "tls_ca",  # GAUSSLITE_TLS_CA
    "fusion_token": "fusion_token",  # GAUSSLITE_FUSION_TOKEN
    "fusion_token_file": "fusion_token_file",  # GAUSSLITE_FUSION_TOKEN_FILE
    "tls_client_cert": "tls_client_cert",  # GAUSSLITE_TLS_CLIENT_CERT
    "tls_client_key": "tls_client_key",  # GAUSSLITE_TLS_CLIENT_KEY
}


def settings_from_env(config_path: Optional[str], env=None, token: Optional[str] = None) -> AgentSettings:
    """Agent settings from environment variables (:data:`ENV`, read through
    :class:`gausslite.core.environment.EnvironmentSettings`; ``GAUSSLITE_AGENT_SET`` holds ``;``-separated
    ``key=value`` config overrides, ``GAUSSLITE_AGENT_AUTO_FINISH=0`` disables auto finish) and the GaussLite YAML
    file (:func:`gausslite.config.load_config`; the agent takes its ``agent`` and ``mapper`` sections; no file: the
    models' defaults).

    Args:
        config_path: the GaussLite YAML, or None.
        env: the environment (default ``os.environ``).
        token: the fleet token the agent's server requires.
    Raises:
        FileNotFoundError / ValueError / pydantic.ValidationError: bad config; a ``GAUSSLITE_*`` variable that does
            not parse; an unreadable or empty ``GAUSSLITE_FUSION_TOKEN_FILE``, only one of the client certificate
            and key.
    """
    variables = EnvironmentSettings.read(env)
    kw = {k: getattr(variables, v) for k, v in ENV.items()}
    kw = {k: v for k, v in kw.items() if v is not None and v != ()}
    if kw.get("fusion_token_file"):
        read_secret(kw["fusion_token_file"])  # fail at start-up, not at the first push
    if bool(kw.get("tls_client_cert")) != bool(kw.get("tls_client_key")):
        raise ValueError("mutual TLS needs both GAUSSLITE_TLS_CLIENT_CERT and GAUSSLITE_TLS_CLIENT_KEY")
    tree = load_config(config_path, list(variables.agent_set))
    log.info("effective configuration: %s", json.dumps(tree.sections("agent"), sort_keys=True))
    return AgentSettings(**kw, token=token, config=tree.agent, auto_finish=variables.agent_auto_finish)
