"""Hypothesis fuzzing of the wire codec (docs/wire-format.md): hostile bytes raise only WireError
subclasses, valid subsets and deltas round-trip within the documented precision.

    python -m bench.wire_fuzz --examples 100000

Splits ``--examples`` over the properties (``tests/_fuzz.py``), prints a table (examples, failures, seconds per
property) and writes ``bench/results/wire_fuzz.json``.  ``tests/wire/test_wire_fuzz.py`` runs the same
properties with a few dozen examples each in the normal suite.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Optional, Sequence

from bench._results import write_json
from tests._fuzz import properties

RESULTS = Path(__file__).resolve().parent / "results"


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run every property; exit code 1 when one fails."""
    ap = argparse.ArgumentParser(prog="python -m bench.wire_fuzz", description=__doc__.splitlines()[0])
    ap.add_argument("--examples", type=int, default=100_000, help="total examples over all properties")
    ap.add_argument("--out", type=Path, default=RESULTS / "wire_fuzz.json")
    args = ap.parse_args(argv)
    props = properties()
    # the round trips are ~10x costlier than the hostile-input properties
    weights = {k: (0.25 if "round_trip" in k else 1.0) for k in props}
    total_w = sum(weights.values())
    rows = []
    for name, make in props.items():
        k = max(1, int(round(args.examples * weights[name] / total_w)))
        t0 = time.perf_counter()
        err = ""
        try:
            make(k)()
        except Exception as e:  # hypothesis re-raises the minimal failing example
            err = f"{type(e).__name__}: {e}"[:500]
        rows.append({"property": name, "examples": k, "seconds": time.perf_counter() - t0, "failure": err})
        print(f"{name:<18} {k:>8} examples {rows[-1]['seconds']:>8.1f} s  {'FAIL ' + err if err else 'ok'}",
              flush=True)
    total = sum(r["examples"] for r in rows)
    print(f"total {total} examples, {sum(1 for r in rows if r['failure'])} failing properties")
    write_json(args.out, {"total_examples": total, "rows": rows}, "wire_fuzz", argv)
    return 1 if any(r["failure"] for r in rows) else 0


if __name__ == "__main__":
    raise SystemExit(main())
