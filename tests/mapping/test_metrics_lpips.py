"""LPIPS-Alex with a tiny randomly initialised local state dict (nothing is downloaded)."""

from __future__ import annotations

import pytest
import torch

from gausslite.lpips import ALEX_CHANNELS, ALEX_CONV_SPECS, LPIPS


def random_state_dict(seed: int = 0, naming: str = "torchvision") -> dict:
    g = torch.Generator().manual_seed(seed)
    sd = {}
    for i, (fi, cin, cout, k, _s, _p) in enumerate(ALEX_CONV_SPECS):
        prefix = f"features.{fi}" if naming == "torchvision" else f"net.slice{i + 1}.{fi}"
        sd[f"{prefix}.weight"] = torch.randn(cout, cin, k, k, generator=g) * (2.0 / (cin * k * k)) ** 0.5
        sd[f"{prefix}.bias"] = torch.randn(cout, generator=g) * 0.01
    for k, c in enumerate(ALEX_CHANNELS):
        sd[f"lin{k}.model.1.weight"] = torch.rand(1, c, 1, 1, generator=g) * 0.1
    return sd


def images(seed=0, h=48, w=64):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(h, w, 3, generator=g), torch.rand(h, w, 3, generator=g)


def test_load_from_file_and_basic_properties(tmp_path):
    sd = random_state_dict()
    sd["classifier.1.weight"] = torch.zeros(2, 2)  # torchvision extras are ignored
    path = tmp_path / "lpips_alex.pth"
    torch.save(sd, path)
    model = LPIPS.load(path)
    a, b = images()
    d_same = model(a, a)
    d_diff = model(a, b)
    assert d_same.ndim == 0 and float(d_same) == pytest.approx(0.0, abs=1e-7)
    assert float(d_diff) > 0
    assert float(model(a, b)) == pytest.approx(float(model(b, a)), rel=1e-5)  # symmetric
    near = (a + 0.01).clamp(0, 1)
    assert float(model(a, near)) < float(d_diff)
    batch = model(torch.stack([a, a]), torch.stack([b, a]))
    assert batch.shape == (2,) and float(batch[0]) == pytest.approx(float(d_diff), rel=1e-5)
    assert float(batch[1]) == pytest.approx(0.0, abs=1e-7)
    x = a.clone().requires_grad_(True)
    model(x, b).backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


def test_split_files_and_official_lpips_naming_agree(tmp_path):
    sd_tv = random_state_dict(1, "torchvision")
    sd_lp = random_state_dict(1, "lpips")
    backbone = {k: v for k, v in sd_tv.items() if k.startswith("features.")}
    heads = {k: v for k, v in sd_tv.items() if k.startswith("lin")}
    torch.save(backbone, tmp_path / "alexnet.pth")
    torch.save(heads, tmp_path / "alex.pth")
    m1 = LPIPS.load(tmp_path / "alexnet.pth", tmp_path / "alex.pth")
    m2 = LPIPS.from_state_dict(sd_lp)
    a, b = images(3)
    assert float(m1(a, b)) == pytest.approx(float(m2(a, b)), rel=1e-6)


def test_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="never downloaded"):
        LPIPS.load(tmp_path / "missing.pth")
    sd = random_state_dict()
    del sd["lin3.model.1.weight"]
    torch.save(sd, tmp_path / "partial.pth")
    with pytest.raises(KeyError, match="lin3"):
        LPIPS.load(tmp_path / "partial.pth")
    sd = random_state_dict()
    sd["features.3.weight"] = torch.zeros(192, 64, 3, 3)
    with pytest.raises(ValueError, match=r"conv1.weight: expected shape \(192, 64, 5, 5\)"):
        LPIPS.from_state_dict(sd)
    torch.save([1, 2, 3], tmp_path / "list.pth")
    with pytest.raises(ValueError, match="state dict"):
        LPIPS.load(tmp_path / "list.pth")
    model = LPIPS.from_state_dict(random_state_dict())
    a, b = images()
    with pytest.raises(ValueError, match="matching"):
        model(a, b[:, :-1])
    with pytest.raises(ValueError, match="matching"):
        model(a[..., :2], b[..., :2])
    with pytest.raises(ValueError, match=">= 31"):
        model(a[:30], b[:30])
    assert float(model(a[:31, :31], b[:31, :31])) > 0  # smallest valid size runs
