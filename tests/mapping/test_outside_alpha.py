"""Transparency penalty outside the ROI (gausslite.mapping.loss.outside_alpha; MapperConfig.roi_outside_alpha), used
by the share fine-tune so a subset draws its ROI and nothing beside it (docs/sharing.md)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gausslite.mapping.loss import outside_alpha


def test_outside_alpha_is_the_mean_alpha_outside_the_grown_roi():
    alpha = torch.zeros(10, 10)
    alpha[:, 5:] = 1.0
    roi = torch.zeros(10, 10, dtype=torch.bool)
    roi[:, 5:] = True
    assert float(outside_alpha(alpha, roi, 0)) == 0.0
    alpha2 = torch.full((10, 10), 0.5, requires_grad=True)
    v = outside_alpha(alpha2, roi, 1)  # columns 0..3 are outside (column 4 is the margin)
    assert float(v.detach()) == pytest.approx(0.5)
    v.backward()
    g = alpha2.grad
    assert (g[:, :4] > 0).all() and (g[:, 4:] == 0).all()
    full = torch.ones(10, 10, dtype=torch.bool)
    z = outside_alpha(alpha2, full, 2)
    assert float(z.detach()) == 0.0 and z.requires_grad
    with pytest.raises(ValueError):
        outside_alpha(alpha, roi[:5], 1)
    with pytest.raises(ValueError):
        outside_alpha(alpha, roi, -1)
