"""One rule for tests that need a real component (the shared datasets, PostgreSQL, headless Chromium,
docker-compose, kubernetes-validate): when it is missing they skip on a user's machine and fail under CI
(``CI=true``), where ``.ci/run`` provides every one of them."""

from __future__ import annotations

import os

import pytest


def under_ci() -> bool:
    """True when the environment says CI (``CI`` is 1, true or yes)."""
    return os.environ.get("CI", "").lower() in ("1", "true", "yes")


def missing(msg: str, ci_hint: str = "", user_hint: str = "") -> None:
    """A required component is missing: ``pytest.fail`` under CI (``msg (required under CI=true<ci_hint>)``),
    else ``pytest.skip`` (``msg<user_hint>``). Never returns."""
    if under_ci():
        pytest.fail(f"{msg} (required under CI=true{ci_hint})")
    pytest.skip(msg + user_hint)
