#!/usr/bin/env python
"""Write the golden wire-format test vectors into ``tests/data/wire`` (docs/wire-format.md §10).

Each vector is one chunk file ``<name>.glwc`` plus an entry in ``vectors.json`` holding the parsed
header, the SHA-256 of the decompressed raw payload and the decoded arrays (float32 values written
as JSON numbers, exact).  ``tests/wire/test_wire_golden.py`` decodes every chunk and compares.  Run this
only when the format version changes (the vectors pin format 3; ``tests/data/wire/v2`` keeps the
format-2 vectors, which decoders still read):

    .venv/bin/python scripts/make_wire_vectors.py
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gausslite.wire.codec import (  # noqa: E402
    FORMAT_VERSION, LOSSLESS, GaussianArrays, QuantConfig, decode_chunk, encode_delta, encode_subset, peek_header,
    raw_payload, spatial_order,
)

OUT = ROOT / "tests" / "data" / "wire"


def _arrays(n: int, seed: int, line: bool = False) -> GaussianArrays:
    rng = np.random.default_rng(seed)
    means = rng.uniform(-1, 1, (n, 3))
    if line:  # smooth rows: previous-row prediction wins for means
        means = np.stack([np.linspace(0.1, 0.4, n), np.linspace(-0.2, 0.0, n), np.full(n, 1.25)], 1)
    return GaussianArrays(
        means=means.astype(np.float32), quats=rng.normal(size=(n, 4)).astype(np.float32),
        log_scales=rng.uniform(-6, -3, (n, 3)).astype(np.float32),
        opacity_logits=rng.normal(0, 2, n).astype(np.float32), colors=rng.uniform(0, 1, (n, 3)).astype(np.float32),
        kappa=rng.integers(0, 400, n), active=rng.random(n) < 0.5)


def _jsonable(a: GaussianArrays) -> dict:
    return {k: np.asarray(getattr(a, k)).astype(float if getattr(a, k).dtype.kind == "f" else int).tolist()
            if getattr(a, k).dtype != bool else getattr(a, k).astype(int).tolist() for k in GaussianArrays.FIELDS}


def main() -> int:
    OUT.mkdir(parents=True, exist_ok=True)
    vectors = []
    line = _arrays(40, 1, line=True)
    cases = [
        ("quantised_predicted", encode_subset(line.take(spatial_order(line.means)), "robot-a", 7)),
        ("quantised_unshuffled", encode_subset(_arrays(6, 2), "robot-a", 8,
                                               quant=QuantConfig(shuffle=False, predict=False))),
        ("lossless", encode_subset(_arrays(3, 3), "robot-b", 1, quant=LOSSLESS)),
        ("two_chunks", encode_subset(_arrays(5, 4), "robot-c", 2, chunk_gaussians=3)),
        ("delta", encode_delta(_arrays(3, 5), [1, 5, 6], [0, 3], "robot-a", 9, 7, 5, kappa_shift=12)),
    ]
    for name, chunks in cases:
        for i, c in enumerate(chunks):
            fname = f"{name}_{i}.glwc"
            (OUT / fname).write_bytes(c)
            h = peek_header(c)
            dc = decode_chunk(c)
            entry = {"file": fname, "header": {k: v for k, v in h.__dict__.items()},
                     "raw_payload_sha256": hashlib.sha256(raw_payload(c)).hexdigest(),
                     "decoded": _jsonable(dc.arrays)}
            if dc.targets is not None:
                entry["targets"] = dc.targets.tolist()
                entry["removed"] = dc.removed.tolist()
            vectors.append(entry)
    (OUT / "vectors.json").write_text(json.dumps({"format_version": FORMAT_VERSION, "vectors": vectors}, indent=1))
    print(f"wrote {len(vectors)} vectors to {OUT}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
