"""Veil response of a −log image to DRR line integrals."""

from __future__ import annotations

import math

import pytest
import torch

from fluoronav.rendering.response import veil_response


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_zero_veil_is_linear_and_a_veil_saturates(dtype: torch.dtype) -> None:
    L = torch.linspace(0.0, 20.0, 41, dtype=dtype).reshape(1, 1, 41).expand(3, 2, 41).reshape(3, 2, 1, 41)
    gain = torch.tensor([1.5, 0.5], dtype=dtype)
    veil = torch.tensor([0.0, 0.2], dtype=dtype)
    y = veil_response(L, gain, veil)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(y[:, 0], 1.5 * L[:, 0], atol=tol * 30, rtol=tol)
    # view 1: by hand at L = 2, and the limit −ln f for a thick object
    assert float(y[0, 1, 0, 4]) == pytest.approx(-math.log(0.8 * math.exp(-1.0) + 0.2), rel=1e-6)
    assert float(y[0, 1, 0, -1]) == pytest.approx(-math.log(0.2), rel=1e-3)
    assert bool((y[0, 1, 0, 1:] > y[0, 1, 0, :-1]).all())  # monotone
    assert y.dtype == dtype and y.shape == L.shape
