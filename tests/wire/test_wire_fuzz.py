"""Fast variant of ``bench.wire_fuzz`` (≈ 200 hypothesis examples over every property of ``tests/_fuzz.py``);
the bench runs the same properties with ≥ 100k examples."""

from __future__ import annotations

import pytest

from tests._fuzz import properties

PROPS = properties()


@pytest.mark.parametrize("name", sorted(PROPS))
def test_wire_fuzz_property(name):
    PROPS[name](40 if "round_trip" not in name else 15)()
