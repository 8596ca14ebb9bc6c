#!/usr/bin/env bash
# The README's test command: set-up (idempotent), then the whole test suite, spread with pytest-xdist over one worker
# per core and one more (much of an integration test's time is spent waiting on the processes it starts);
# GAUSSLITE_TEST_WORKERS sets the number (0: run in this process). Tests that must not run side by side take a lock
# file instead of a worker of their own (the doc pages that serve on the pages' fixed ports, the one export of the
# tiny models: tests/docs/test_doc_blocks.py, tests/conftest.py).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
# The suite starts many Python processes (services, CLI calls) and three workers that each import every test
# module: keep the bytecode they compile (in __pycache__/, ignored by git) even where the environment says not to
# write it (PYTHONDONTWRITEBYTECODE, common in container images); without it each process compiles what it imports.
unset PYTHONDONTWRITEBYTECODE
# --dist worksteal: a worker that runs out of tests takes queued ones from the others (the long integration tests
# are collected first, tests/conftest.py), so the workers finish together.
exec .venv/bin/python -m pytest -q -n "${GAUSSLITE_TEST_WORKERS:-$(( $(nproc) + 1 ))}" --dist worksteal "$@"
