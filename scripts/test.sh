#!/usr/bin/env bash
# The README's test command: set-up (idempotent), then the whole test suite, spread over the machine's cores with
# pytest-xdist (GAUSSLITE_TEST_WORKERS: a number of workers, or 0 to run in this process; tests/conftest.py keeps
# the tests that must not run side by side in one worker).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/python -m pytest -q -n "${GAUSSLITE_TEST_WORKERS:-auto}" --dist loadgroup "$@"
