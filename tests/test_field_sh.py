"""SH direction encoding: known values on the axes and orthonormality by exact quadrature."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from virus_nerf.field.sh import SH_DIM, sh_encode


def test_values_on_axes():
    y = sh_encode(torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]], dtype=torch.float64))
    assert y.shape == (3, SH_DIM)
    want_z = np.zeros(16)
    # Y_l0 at the pole = sqrt((2l + 1) / (4 pi)); all m != 0 vanish there.
    want_z[[0, 2, 6, 12]] = [0.28209479, 0.48860251, 0.63078313, 0.74635267]
    np.testing.assert_allclose(y[0].numpy(), want_z, atol=1e-8)
    want_x = np.zeros(16)
    want_x[[0, 3, 6, 8, 13, 15]] = [0.28209479, 0.48860251, -0.31539157, 0.54627422, -0.45704580, 0.59004359]
    np.testing.assert_allclose(y[1].numpy(), want_x, atol=1e-8)
    # +y (given unnormalised, length 2): Y_1,-1 = c1, Y_2,2 = -0.546, Y_3,-3 = -0.590, Y_3,-1 = -0.457
    want_y = np.zeros(16)
    want_y[[0, 1, 6, 8, 9, 11]] = [0.28209479, 0.48860251, -0.31539157, -0.54627422, -0.59004359, -0.45704580]
    np.testing.assert_allclose(y[2].numpy(), want_y, atol=1e-8)


def test_orthonormal_on_sphere():
    """Gauss-Legendre in cos(theta) x uniform phi integrates degree <= 6 polynomials exactly."""
    u, wu = np.polynomial.legendre.leggauss(8)
    phi = np.arange(16) * 2 * math.pi / 16
    uu, pp = np.meshgrid(u, phi, indexing="ij")
    s = np.sqrt(1 - uu**2)
    d = np.stack([s * np.cos(pp), s * np.sin(pp), uu], -1).reshape(-1, 3)
    w = (wu[:, None] * np.full(16, 2 * math.pi / 16)[None, :]).reshape(-1)
    y = sh_encode(torch.from_numpy(d)).numpy()  # (M, 16) float64
    gram = (y * w[:, None]).T @ y
    np.testing.assert_allclose(gram, np.eye(16), atol=1e-10)


def test_float32_and_shape_errors():
    y = sh_encode(torch.randn(100, 3))
    assert y.dtype == torch.float32 and y.shape == (100, 16)
    with pytest.raises(ValueError, match="shape"):
        sh_encode(torch.randn(4, 2))
