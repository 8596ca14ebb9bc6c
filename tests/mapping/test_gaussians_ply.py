"""GaussianMap PLY export/import: 3DGS layout, lossless round trip, foreign files, errors."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from gausslite.gaussians import PLY_KAPPA_MAX, SH_C0, GaussianMap


def random_map(n: int, seed: int = 0) -> GaussianMap:
    g = torch.Generator().manual_seed(seed)
    return GaussianMap(
        means=torch.randn(n, 3, generator=g),
        quats=torch.randn(n, 4, generator=g),
        log_scales=torch.randn(n, 3, generator=g) - 3.0,
        opacity_logits=torch.randn(n, generator=g),
        colors=torch.rand(n, 3, generator=g),
        active=torch.rand(n, generator=g) > 0.5,
        kappa=torch.randint(0, 1000, (n,), generator=g),
    )

STD_ORDER = (
    ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"]
    + [f"scale_{i}" for i in range(3)]
    + [f"rot_{i}" for i in range(4)]
)


def _assert_bit_exact(a: GaussianMap, b: GaussianMap) -> None:
    for name in ("means", "quats", "log_scales", "opacity_logits", "colors"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype == torch.float32
        assert torch.equal(x.view(torch.int32), y.view(torch.int32)), name  # bit-exact incl. -0.0
    assert torch.equal(a.active, b.active) and torch.equal(a.kappa, b.kappa)
    assert b.kappa.dtype == torch.int64 and b.active.dtype == torch.bool


def test_round_trip_bit_exact(tmp_path):
    m = random_map(257, seed=5)
    # awkward colours: tiny, negative zero, out of [0, 1], extremes
    m.colors[:4] = torch.tensor([[1e-9, -0.0, 1.0], [0.0, 1.5, -0.2], [0.3333333, 7e-4, 0.9999999], [0.5, 0.25, 0.75]])
    m.kappa[0] = PLY_KAPPA_MAX
    path = tmp_path / "map.ply"
    m.save_ply(path)
    back = GaussianMap.load_ply(path)
    _assert_bit_exact(m, back)


def test_layout_matches_3dgs(tmp_path):
    m = random_map(10)
    path = tmp_path / "map.ply"
    m.save_ply(path)
    with open(path, "rb") as fh:
        header = fh.read(200).decode("ascii", errors="replace")
    assert header.startswith("ply\nformat binary_little_endian 1.0\n")
    ply = PlyData.read(str(path))
    props = ply["vertex"].properties
    names = [p.name for p in props]
    assert names[: len(STD_ORDER)] == STD_ORDER
    assert names[len(STD_ORDER):] == ["kappa", "active", "rgb_0", "rgb_1", "rgb_2"]
    types = {p.name: p.val_dtype for p in props}
    assert all(types[n] in ("f4", "<f4") for n in STD_ORDER)
    assert types["kappa"] in ("u4", "<u4") and types["active"] in ("u1", "|u1", "<u1")
    v = ply["vertex"].data
    np.testing.assert_allclose(v["f_dc_1"], (m.colors[:, 1].numpy() - 0.5) / SH_C0, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(v["opacity"], m.opacity_logits.numpy())
    np.testing.assert_array_equal(v["rot_0"], m.quats[:, 0].numpy())
    np.testing.assert_array_equal(v["scale_2"], m.log_scales[:, 2].numpy())
    np.testing.assert_array_equal(v["nx"], 0)
    # standard-only writer output (no exact colours) still close
    m.save_ply(tmp_path / "std.ply", exact_colors=False)
    names2 = [p.name for p in PlyData.read(str(tmp_path / "std.ply"))["vertex"].properties]
    assert names2 == STD_ORDER + ["kappa", "active"]
    back = GaussianMap.load_ply(tmp_path / "std.ply")
    assert torch.allclose(back.colors, m.colors, atol=1e-6)
    assert torch.equal(back.kappa, m.kappa)


def _write_foreign(path, n, drop=(), rest=True):
    rng = np.random.default_rng(0)
    names = [p for p in STD_ORDER if p not in drop] + ([f"f_rest_{i}" for i in range(45)] if rest else [])
    arr = np.zeros(n, dtype=[(p, "<f4") for p in names])
    for p in names:
        arr[p] = rng.standard_normal(n).astype(np.float32)
    PlyData([PlyElement.describe(arr, "vertex")], text=False, byte_order="<").write(str(path))
    return arr


def test_load_standard_3dgs_ply_without_task_fields(tmp_path, caplog):
    path = tmp_path / "inria.ply"
    arr = _write_foreign(path, 20)
    with caplog.at_level(logging.DEBUG, logger="gausslite.gaussians"):
        m = GaussianMap.load_ply(path)
    assert any("f_rest" in r.message for r in caplog.records)
    assert len(m) == 20 and not m.active.any() and (m.kappa == 0).all()
    np.testing.assert_array_equal(m.means[:, 1].numpy(), arr["y"])
    np.testing.assert_allclose(m.colors[:, 0].numpy(), arr["f_dc_0"] * SH_C0 + 0.5, rtol=1e-6)
    np.testing.assert_array_equal(m.quats[:, 3].numpy(), arr["rot_3"])


def test_load_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        GaussianMap.load_ply(tmp_path / "nope.ply")
    bad = tmp_path / "bad.ply"
    _write_foreign(bad, 3, drop=("opacity", "rot_2"), rest=False)
    with pytest.raises(ValueError, match=r"lacks required 3DGS properties \['opacity', 'rot_2'\]"):
        GaussianMap.load_ply(bad)
    junk = tmp_path / "junk.ply"
    junk.write_bytes(b"not a ply at all")
    with pytest.raises(ValueError, match="not a readable PLY"):
        GaussianMap.load_ply(junk)
    noverts = tmp_path / "faces.ply"
    PlyData([PlyElement.describe(np.zeros(2, dtype=[("a", "u1")]), "face")]).write(str(noverts))
    with pytest.raises(ValueError, match="no 'vertex' element"):
        GaussianMap.load_ply(noverts)


def test_save_rejects_negative_kappa_and_saturates(tmp_path, caplog):
    m = random_map(3)
    m.kappa[1] = -1
    with pytest.raises(ValueError, match="kappa"):
        m.save_ply(tmp_path / "neg.ply")
    m.kappa[1] = 2**40
    with caplog.at_level(logging.WARNING, logger="gausslite.gaussians"):
        m.save_ply(tmp_path / "big.ply")
    assert any("saturated" in r.message for r in caplog.records)
    assert GaussianMap.load_ply(tmp_path / "big.ply").kappa[1] == PLY_KAPPA_MAX


def test_empty_map_round_trip(tmp_path):
    GaussianMap.empty().save_ply(tmp_path / "e.ply")
    assert len(GaussianMap.load_ply(tmp_path / "e.ply")) == 0


def test_edited_f_dc_wins_over_stale_exact_colours(tmp_path):
    m = random_map(4)
    path = tmp_path / "m.ply"
    m.save_ply(path)
    ply = PlyData.read(str(path))
    ply["vertex"].data["f_dc_0"] += 1.0  # e.g. recoloured in a viewer that kept unknown props
    ply.write(str(tmp_path / "edited.ply"))
    back = GaussianMap.load_ply(tmp_path / "edited.ply")
    assert torch.allclose(back.colors[:, 0], m.colors[:, 0] + SH_C0, atol=1e-5)
