"""The ``GAUSSLITE_*`` environment variables, read in one place: :class:`EnvironmentSettings` has one typed field per
variable (its name is the field's alias), so the library, the servers, the clients and the command line parse them the
same way (docs/reference.md#environment-variables).

A command-line flag always wins over its variable; the readers (``gausslite_services.common.cli_options``, the agent
server's ``settings_from_env``, ``gausslite view``, ``gausslite health``, ``gausslite sim``) take the field and fall
back from there. An empty variable counts as unset. A value that does not parse (a port that is not an integer, a
yes/no variable that says neither) is a :class:`EnvironmentVariableError` naming the variable, raised when the variables are
read (:meth:`EnvironmentSettings.read`).

This module imports neither gRPC nor torch: the services and the library both read it.
"""

from __future__ import annotations

from typing import Annotated, Mapping, Optional, Tuple

from pydantic import Field, ValidationError, field_validator
from pydantic_settings import BaseSettings, EnvSettingsSource, NoDecode, SettingsConfigDict
from pydantic_settings.sources.utils import parse_env_vars

__all__ = ["EnvironmentSettings", "EnvironmentVariableError", "SERVICES", "LOG_LEVELS"]

#: the servers whose host, port, configuration file and metrics port have variables of their own
#: (``GAUSSLITE_<SERVICE>_HOST`` ...)
SERVICES = ("parser", "fusion", "agent")
#: the names ``GAUSSLITE_LOG_LEVEL`` takes
LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")

Port = Optional[int]
#: a list given as one variable, split on ``,`` (folders, addresses) or ``;`` (``key=value`` overrides)
Listed = Annotated[Tuple[str, ...], NoDecode]


class EnvironmentVariableError(ValueError):
    """A ``GAUSSLITE_*`` variable whose value does not parse; the message names each such variable and its value."""


def _var(name: str, doc: str, default=None, **kw):
    """A field read from the variable ``name`` (its alias), documented by ``doc``."""
    return Field(default, validation_alias=name, description=doc, **kw)


def _split(value, sep: str) -> Tuple[str, ...]:
    """``value`` split on ``sep``, stripped, empty items dropped (a tuple or list passes through)."""
    if value is None:
        return ()
    items = value if isinstance(value, (tuple, list)) else str(value).split(sep)
    return tuple(s.strip() for s in items if str(s).strip())


class EnvironmentSettings(BaseSettings):
    """Every ``GAUSSLITE_*`` environment variable the product reads (module docstring). Read them with
    :meth:`read`; :meth:`service` gives one server's ``GAUSSLITE_<SERVICE>_*`` fields.

    Raises:
        EnvironmentVariableError: from :meth:`read`, a variable that does not parse.
    """

    model_config = SettingsConfigDict(case_sensitive=True, env_ignore_empty=True, extra="ignore", frozen=True)

    # ---- each server (parser, fusion, agent): where it listens, its configuration, its metrics endpoint
    parser_host: Optional[str] = _var("GAUSSLITE_PARSER_HOST", "interface the parser service binds (default 127.0.0.1)")
    parser_port: Port = _var("GAUSSLITE_PARSER_PORT", "port of the parser service (default 50051)", ge=0, le=65535)
    parser_config: Optional[str] = _var("GAUSSLITE_PARSER_CONFIG", "GaussLite YAML of the parser service")
    parser_metrics_port: Port = _var("GAUSSLITE_PARSER_METRICS_PORT",
                                     "Prometheus /metrics port of the parser service (0: off)", ge=0, le=65535)
    fusion_host: Optional[str] = _var("GAUSSLITE_FUSION_HOST", "interface the fusion server binds (default 127.0.0.1)")
    fusion_port: Port = _var("GAUSSLITE_FUSION_PORT", "port of the fusion server (default 50052)", ge=0, le=65535)
    fusion_config: Optional[str] = _var("GAUSSLITE_FUSION_CONFIG", "GaussLite YAML of the fusion server")
    fusion_metrics_port: Port = _var("GAUSSLITE_FUSION_METRICS_PORT",
                                     "Prometheus /metrics port of the fusion server (0: off)", ge=0, le=65535)
    agent_host: Optional[str] = _var("GAUSSLITE_AGENT_HOST", "interface the agent service binds (default 127.0.0.1)")
    agent_port: Port = _var("GAUSSLITE_AGENT_PORT", "port of the agent service (default 50061)", ge=0, le=65535)
    agent_config: Optional[str] = _var("GAUSSLITE_AGENT_CONFIG", "GaussLite YAML of the agent service")
    agent_metrics_port: Port = _var("GAUSSLITE_AGENT_METRICS_PORT",
                                    "Prometheus /metrics port of the agent service (0: off)", ge=0, le=65535)
    metrics_port: Port = _var("GAUSSLITE_METRICS_PORT", "Prometheus /metrics port of a server without a "
                              "GAUSSLITE_<SERVICE>_METRICS_PORT (0: off)", ge=0, le=65535)
    log_level: Optional[str] = _var("GAUSSLITE_LOG_LEVEL", "log level of the servers: DEBUG, INFO, WARNING, ERROR or "
                                    "CRITICAL, any case (default INFO)")
    data_dir: Optional[str] = _var("GAUSSLITE_DATA_DIR", "data folder: the fusion server's SQLite store, an agent's "
                                   "checkpoints and results")
    # ---- credentials a server requires
    token: Optional[str] = _var("GAUSSLITE_TOKEN", "fleet bearer token: servers require it, clients send it when no "
                                "per-agent token is given")
    tls_cert: Optional[str] = _var("GAUSSLITE_TLS_CERT", "PEM certificate of a server (set: TLS)")
    tls_key: Optional[str] = _var("GAUSSLITE_TLS_KEY", "PEM private key of that certificate")
    tls_client_ca: Optional[str] = _var("GAUSSLITE_TLS_CLIENT_CA", "PEM CA a server checks client certificates "
                                        "against (set: mutual TLS)")
    agent_tokens_file: Optional[str] = _var("GAUSSLITE_AGENT_TOKENS_FILE", "the fusion server's per-agent token "
                                            "hashes (JSON; `gausslite tokens` makes it)")
    fleet_token_writes: bool = _var("GAUSSLITE_FLEET_TOKEN_WRITES", "the fusion server lets the fleet token write "
                                    "as any agent while per-agent tokens are in use (1/true/yes; migration)", False)
    # ---- credentials a client presents
    tls_ca: Optional[str] = _var("GAUSSLITE_TLS_CA", "PEM CA a client checks the server's certificate against "
                                 "(set: TLS)")
    tls_client_cert: Optional[str] = _var("GAUSSLITE_TLS_CLIENT_CERT", "PEM certificate a client presents (mutual "
                                          "TLS; with GAUSSLITE_TLS_CLIENT_KEY)")
    tls_client_key: Optional[str] = _var("GAUSSLITE_TLS_CLIENT_KEY", "its PEM private key")
    fusion_token: Optional[str] = _var("GAUSSLITE_FUSION_TOKEN", "bearer token a client sends to the fusion server "
                                       "(a per-agent token; default GAUSSLITE_TOKEN)")
    fusion_token_file: Optional[str] = _var("GAUSSLITE_FUSION_TOKEN_FILE", "file holding that token (a mounted "
                                            "secret), read when GAUSSLITE_FUSION_TOKEN is unset")
    # ---- where the services are
    parser_addr: Optional[str] = _var("GAUSSLITE_PARSER_ADDR", "host:port of the parser service an agent asks "
                                      "(unset: in-process rules)")
    fusion_addr: Optional[str] = _var("GAUSSLITE_FUSION_ADDR", "host:port of the fusion server an agent pushes to "
                                      "and `gausslite view` follows (unset: no pushes)")
    fusion_allow: Listed = _var("GAUSSLITE_FUSION_ALLOW", "further host:port fusion servers a StartMission may "
                                "name, comma-separated", ())
    health_target: Optional[str] = _var("GAUSSLITE_HEALTH_TARGET", "host:port `gausslite health` checks")
    view_port: Port = _var("GAUSSLITE_VIEW_PORT", "port of the viewer's web page (default 8080)", ge=0, le=65535)
    # ---- the agent
    agent_id: Optional[str] = _var("GAUSSLITE_AGENT_ID", "the agent's id on the fusion server")
    agent_data_roots: Listed = _var("GAUSSLITE_AGENT_DATA_ROOTS", "folders a StartMission may read datasets and "
                                    "annotations from, comma-separated", ())
    agent_dataset: Optional[str] = _var("GAUSSLITE_AGENT_DATASET", "dataset of a replay mission the agent starts "
                                        "by itself")
    agent_task: Optional[str] = _var("GAUSSLITE_AGENT_TASK", "task text of that mission")
    agent_task_id: Optional[str] = _var("GAUSSLITE_AGENT_TASK_ID", "its task id in the dataset's tasks.json "
                                        "(ground-truth relevance and scoring)")
    agent_annotations: Optional[str] = _var("GAUSSLITE_AGENT_ANNOTATIONS", "folder of the scene annotations "
                                            "(objects.json) of the agent's missions")
    agent_auto_finish: bool = _var("GAUSSLITE_AGENT_AUTO_FINISH", "finish the self-started replay mission when its "
                                   "frames end (0/false/no: keep it open)", True)
    agent_set: Listed = _var("GAUSSLITE_AGENT_SET", "configuration overrides of the agent, ';'-separated key=value",
                             ())
    # ---- the fusion server
    fusion_store: Optional[str] = _var("GAUSSLITE_FUSION_STORE", "postgresql:// DSN of the fusion server's store "
                                       "(unset: SQLite in the data folder)")
    fusion_port_file: Optional[str] = _var("GAUSSLITE_FUSION_PORT_FILE", "file the fusion server writes its bound "
                                           "port to once serving")
    fusion_set: Listed = _var("GAUSSLITE_FUSION_SET", "configuration overrides of the fusion server, ';'-separated "
                              "key=value", ())

    @field_validator("fusion_allow", "agent_data_roots", mode="before")
    @classmethod
    def _comma_list(cls, v):
        return _split(v, ",")

    @field_validator("agent_set", "fusion_set", mode="before")
    @classmethod
    def _semicolon_list(cls, v):
        return _split(v, ";")

    @field_validator("log_level", mode="before")
    @classmethod
    def _level(cls, v):
        if v is None:
            return v
        if str(v).upper() not in LOG_LEVELS:
            raise ValueError(f"must be one of {', '.join(LOG_LEVELS)}")
        return str(v).upper()

    @classmethod
    def read(cls, env: Optional[Mapping[str, str]] = None) -> "EnvironmentSettings":
        """The variables of ``env`` (default ``os.environ``); names are case-sensitive, empty values count as unset.

        Raises:
            EnvironmentVariableError: a value that does not parse (the message names the variable and its value).
        """
        try:
            if env is None:
                return cls()
            return cls.model_validate(_MappingSource(cls, env)())
        except ValidationError as e:
            raise EnvironmentVariableError(_describe(e)) from None

    def service(self, name: str) -> Tuple[Optional[str], Optional[int], Optional[str], Optional[int]]:
        """``(host, port, config, metrics_port)`` of the server ``name`` (one of :data:`SERVICES`), from its
        ``GAUSSLITE_<SERVICE>_*`` variables (None where unset); the metrics port falls back to
        ``GAUSSLITE_METRICS_PORT``.

        Raises:
            ValueError: an unknown server.
        """
        if name not in SERVICES:
            raise ValueError(f"no GAUSSLITE_<SERVICE>_* variables for {name!r}: one of {', '.join(SERVICES)}")
        metrics = getattr(self, f"{name}_metrics_port")
        return (getattr(self, f"{name}_host"), getattr(self, f"{name}_port"), getattr(self, f"{name}_config"),
                self.metrics_port if metrics is None else metrics)

    @classmethod
    def variables(cls) -> dict:
        """Variable name → field name, for every variable."""
        return {f.validation_alias: name for name, f in cls.model_fields.items()}


class _MappingSource(EnvSettingsSource):
    """The environment settings source over a given mapping instead of ``os.environ`` (same parsing)."""

    def __init__(self, settings_cls, env: Mapping[str, str]) -> None:
        self._env = env
        super().__init__(settings_cls)

    def _load_env_vars(self):
        return parse_env_vars(self._env, self.case_sensitive, self.env_ignore_empty, self.env_parse_none_str)


def _describe(e: ValidationError) -> str:
    """One line per bad variable: ``NAME='value': what is wrong``."""
    parts = []
    for err in e.errors():
        name = ".".join(str(x) for x in err["loc"]) or "environment"
        parts.append(f"{name}={err.get('input')!r}: {err['msg']}")
    return "bad environment variable " + "; ".join(parts)
