"""Rule-parser latency benchmark (paper Sec. III-B: parsing happens once per task; target p99 < 5 ms).

Run: ``.venv/bin/python -m bench.parser [--repeats N]``. Parses every shared phrasing (and the
dataset ``tasks.json`` texts) ``N`` times with the uncached rule parser and with the cached
``TaskParser``, prints a table of p50/p95/p99/max in milliseconds and writes
``bench/results/parser.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

from bench._results import write_json
from gausslite.parser import RuleParser, TaskParser

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("GAUSSLITE_SHARED", REPO.parent / "shared"))


def load_texts() -> list:
    """Task texts from ``$GAUSSLITE_SHARED/tasks/phrasings.jsonl`` and the dataset ``tasks.json`` files.

    Raises:
        FileNotFoundError: the shared phrasings file is missing.
    """
    lines = (SHARED / "tasks" / "phrasings.jsonl").read_text().splitlines()
    texts = [json.loads(x)["text"] for x in lines if x.strip()]
    for f in sorted((SHARED / "datasets").glob("*/tasks.json")):
        texts += [t["text"] for t in json.loads(f.read_text())["tasks"]]
    return texts


def _stats(samples: list) -> dict:
    s = sorted(samples)
    pick = lambda q: s[min(len(s) - 1, int(round(q * (len(s) - 1))))]  # noqa: E731
    return {"n": len(s), "mean_ms": statistics.fmean(s) * 1e3, "p50_ms": pick(0.50) * 1e3,
            "p95_ms": pick(0.95) * 1e3, "p99_ms": pick(0.99) * 1e3, "max_ms": s[-1] * 1e3}


def run(repeats: int = 50, argv=None) -> dict:
    """Measure and return the results dict (also written to ``bench/results/parser.json``, with the provenance of
    the command line ``argv``)."""
    texts = load_texts()
    rules = RuleParser()
    cached = TaskParser()
    for t in texts:  # warm-up (imports, regex compilation)
        rules.parse(t)
    rows = {}
    samples = []
    for _ in range(repeats):
        for t in texts:
            t0 = time.perf_counter()
            rules.parse(t)
            samples.append(time.perf_counter() - t0)
    rows["rules (uncached)"] = _stats(samples)
    samples = []
    for _ in range(repeats):
        for t in texts:
            t0 = time.perf_counter()
            cached.parse(t)
            samples.append(time.perf_counter() - t0)
    rows["TaskParser (LRU cache)"] = _stats(samples)
    result = {"texts": len(texts), "repeats": repeats, "python": platform.python_version(),
              "machine": platform.machine(), "cpu_count": os.cpu_count(), "budget_p99_ms": 5.0, "rows": rows}
    write_json(REPO / "bench" / "results" / "parser.json", result, "parser", argv)
    return result


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="rule-parser latency benchmark")
    ap.add_argument("--repeats", type=int, default=50)
    args = ap.parse_args(argv)
    res = run(args.repeats, argv)
    print(f"{res['texts']} texts x {res['repeats']} repeats (python {res['python']}, {res['cpu_count']} cpus)")
    print(f"{'backend':<24}{'n':>7}{'mean':>9}{'p50':>9}{'p95':>9}{'p99':>9}{'max':>9}  (ms)")
    for name, r in res["rows"].items():
        print(f"{name:<24}{r['n']:>7}{r['mean_ms']:>9.3f}{r['p50_ms']:>9.3f}{r['p95_ms']:>9.3f}"
              f"{r['p99_ms']:>9.3f}{r['max_ms']:>9.3f}")
    ok = all(r["p99_ms"] < res["budget_p99_ms"] for r in res["rows"].values())
    print("p99 within 5 ms budget:", ok)
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
