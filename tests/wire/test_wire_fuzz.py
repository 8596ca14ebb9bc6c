"""Every property of ``tests/_fuzz.py`` over ≈ 200 hypothesis examples (the same properties ran 100k examples without
a failure: docs/history.md, "wire_fuzz")."""

from __future__ import annotations

import pytest

from tests._fuzz import properties

PROPS = properties()


@pytest.mark.parametrize("name", sorted(PROPS))
def test_wire_fuzz_property(name):
    PROPS[name](40 if "round_trip" not in name else 15)()
