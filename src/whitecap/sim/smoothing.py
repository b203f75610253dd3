"""SPH smoothing kernels (Müller et al. 2003), as used by PBF.

poly6 for densities (smooth, never negative), spiky gradient for the
constraint gradients (no vanishing gradient at r → 0, which would let
particles clump). ``h`` is the support radius.
"""


import math

import taichi as ti


class SPHKernel:
    """Support h and the normalisation constants, computed once on the host so
    kernels do not re-evaluate h⁹ per neighbour."""

    def __init__(self, h: float):
        self.h = float(h)
        self.h2 = float(h) ** 2
        self.poly6 = 315.0 / (64.0 * math.pi * h**9)
        self.spiky = -45.0 / (math.pi * h**6)


@ti.func
def poly6(r2: ti.f32, h2: ti.f32, coef: ti.f32) -> ti.f32:
    """W_poly6(r, h) = 315/(64 π h⁹) (h² − r²)³ for r < h;  coef = 315/(64 π h⁹)."""
    w = 0.0
    if r2 < h2:
        d = h2 - r2
        w = coef * d * d * d
    return w


@ti.func
def spiky_grad(r: ti.math.vec3, h: ti.f32, coef: ti.f32) -> ti.math.vec3:
    """∇W_spiky(r, h) = −45/(π h⁶) (h − |r|)² r/|r| for 0 < |r| < h;  coef = −45/(π h⁶)."""
    g = ti.math.vec3(0.0)
    r2 = r.norm_sqr()
    if 0.0 < r2 < h * h:
        inv = ti.rsqrt(r2)  # 1/|r|, saving a division
        d = h - r2 * inv
        g = (coef * d * d * inv) * r
    return g


def poly6_np(r2, h):
    """NumPy twin of :func:`poly6`, for setup-time calibration."""
    import numpy as np

    h2 = h * h
    d = np.clip(h2 - r2, 0.0, None)
    return 315.0 / (64.0 * math.pi * h**9) * d**3


def spiky_grad_np(r, h):
    import numpy as np

    rl = np.linalg.norm(r, axis=-1, keepdims=True)
    d = np.clip(h - rl, 0.0, None)
    with np.errstate(invalid="ignore", divide="ignore"):
        g = np.where(rl > 0, -45.0 / (math.pi * h**6) * d * d / rl * r, 0.0)
    return g


@ti.func
def cubic_spline(r: ti.f32, h: ti.f32) -> ti.f32:
    """The cubic B-spline of support h (SPlisHSPlasH's CubicKernel), q = r/h, σ = 8/(π h³):
    W = σ (6q³ − 6q² + 1) for q ≤ ½, σ 2(1 − q)³ for ½ < q ≤ 1, 0 beyond."""
    q = r / h
    s = 8.0 / (math.pi * h * h * h)
    w = 0.0
    if q <= 0.5:
        w = s * (6.0 * q * q * q - 6.0 * q * q + 1.0)
    elif q <= 1.0:
        w = s * 2.0 * (1.0 - q) ** 3
    return w


@ti.func
def cubic_spline_grad(x: ti.math.vec3, h: ti.f32) -> ti.math.vec3:
    """∇W of :func:`cubic_spline` at offset x: (48/(π h³)) (dW/dq) x̂ / h, with
    dW/dq ∝ q(3q − 2) for q ≤ ½ and −(1 − q)² for ½ < q ≤ 1."""
    g = ti.math.vec3(0.0)
    r = x.norm()
    q = r / h
    if 1e-9 < r and q <= 1.0:
        s = 48.0 / (math.pi * h * h * h)
        d = -(1.0 - q) * (1.0 - q)
        if q <= 0.5:
            d = q * (3.0 * q - 2.0)
        g = (s * d / (r * h)) * x
    return g
