"""Whether the tests run in a git checkout (the benches' ``--against COMMIT`` needs one: a copy without ``.git`` runs
their quick test against this tree alone)."""

from __future__ import annotations

import subprocess


def has_git() -> bool:
    """True when ``git rev-parse HEAD`` succeeds here."""
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, timeout=30).returncode == 0
    except (OSError, subprocess.SubprocessError):
        return False
