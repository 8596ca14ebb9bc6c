#!/usr/bin/env python
"""Regenerate the Python gRPC code of ``proto/gausslite_rpc/*.proto`` into ``gausslite_rpc/``.

Usage (from anywhere)::

    .venv/bin/python scripts/gen_proto.py           # regenerate into <repo>/gausslite_rpc/
    .venv/bin/python scripts/gen_proto.py --check   # regenerate into a temp dir; exit 1 when the
                                                    # committed files differ (stale), 0 when current

Runs ``python -m grpc_tools.protoc -I proto --python_out=. --grpc_python_out=. --pyi_out=.
proto/gausslite_rpc/*.proto`` and writes ``gausslite_rpc/__init__.py``.
"""

from __future__ import annotations

import argparse
import difflib
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PROTO_DIR = REPO / "proto"
PACKAGE = "gausslite_rpc"
INIT_TEXT = (
    '"""Generated gRPC/protobuf code of ``proto/gausslite_rpc``. Do not edit: run\n'
    '``python scripts/gen_proto.py``; ``--check`` verifies it is current."""\n'
)


def proto_files() -> list:
    """Sorted ``.proto`` files under ``proto/gausslite_rpc`` (relative to ``proto/``)."""
    return sorted(str(p.relative_to(PROTO_DIR)) for p in (PROTO_DIR / PACKAGE).glob("*.proto"))


def generate(out_dir: Path) -> list:
    """Run protoc into ``out_dir`` (creating ``out_dir/gausslite_rpc``); return generated paths.

    Raises:
        RuntimeError: protoc failed or there are no .proto files.
    """
    files = proto_files()
    if not files:
        raise RuntimeError(f"no .proto files in {PROTO_DIR / PACKAGE}")
    (out_dir / PACKAGE).mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "grpc_tools.protoc", "-I", str(PROTO_DIR), f"--python_out={out_dir}",
           f"--grpc_python_out={out_dir}", f"--pyi_out={out_dir}", *[str(PROTO_DIR / f) for f in files]]
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=str(REPO))
    if res.returncode != 0:
        raise RuntimeError(f"protoc failed ({res.returncode}): {res.stderr.strip()}")
    (out_dir / PACKAGE / "__init__.py").write_text(INIT_TEXT, encoding="utf-8")
    return sorted(p for p in (out_dir / PACKAGE).iterdir() if p.suffix in (".py", ".pyi"))


def _generated_names(folder: Path) -> set:
    if not folder.is_dir():
        return set()
    return {p.name for p in folder.iterdir() if p.suffix in (".py", ".pyi")
            and (p.name == "__init__.py" or p.stem.endswith(("_pb2", "_pb2_grpc")))}


def check() -> int:
    """Return 0 when ``gausslite_rpc/`` matches freshly generated code, 1 otherwise (diff printed)."""
    with tempfile.TemporaryDirectory() as tmp:
        generate(Path(tmp))
        fresh_dir, committed_dir = Path(tmp) / PACKAGE, REPO / PACKAGE
        fresh, committed = _generated_names(fresh_dir), _generated_names(committed_dir)
        problems = []
        for name in sorted(fresh - committed):
            problems.append(f"missing: {PACKAGE}/{name}")
        for name in sorted(committed - fresh):
            problems.append(f"extra (no .proto source): {PACKAGE}/{name}")
        for name in sorted(fresh & committed):
            a = (committed_dir / name).read_text(encoding="utf-8")
            b = (fresh_dir / name).read_text(encoding="utf-8")
            if a != b:
                diff = "".join(difflib.unified_diff(a.splitlines(True), b.splitlines(True),
                                                    f"committed/{name}", f"generated/{name}", n=1))
                problems.append(f"stale: {PACKAGE}/{name}\n{diff[:2000]}")
    if problems:
        print("generated gRPC code is not current; run: python scripts/gen_proto.py", file=sys.stderr)
        for p in problems:
            print("  " + p, file=sys.stderr)
        return 1
    print(f"{PACKAGE}/ is current ({len(fresh)} files)")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="fail (exit 1) when generated code is stale")
    args = ap.parse_args(argv)
    if args.check:
        return check()
    out = generate(REPO)
    print("generated:", ", ".join(str(p.relative_to(REPO)) for p in out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
