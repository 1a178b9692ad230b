"""Float64 arithmetic that gives the same bits on every x86 CPU: products, norms and transcendental functions built
from numpy's elementwise add, subtract, multiply, divide, sqrt, rint, floor and ldexp only.

Those elementwise operations are correctly rounded IEEE 754 operations whatever SIMD kernel numpy dispatches to, and
numpy applies them one ufunc at a time (no fused multiply-add). What is not exact across CPUs, and what this module
replaces in the stages that write data: matrix products and dot products (``@``, ``np.dot``, ``np.einsum``,
``np.linalg``: OpenBLAS and numpy pick kernels by CPU, which sum in another order or fuse multiply-adds), and
``np.sin``/``np.exp``/``np.power`` (numpy's AVX-512 kernels are accurate to a few units in the last place, not
correctly rounded, and differ from the AVX2 ones). Every sum here runs left to right over the last axis.
"""
from __future__ import annotations

import math

import numpy as np

# pi/2 in three parts (fdlibm's Cody-Waite split): k * _PIO2_1 is exact for |k| < 2**20
_PIO2_1, _PIO2_2, _PIO2_3 = 1.57079632673412561417e+00, 6.07710050630396597660e-11, 2.02226624871116645580e-21
_LN2_HI, _LN2_LO = 6.93147180369123816490e-01, 1.90821492927058770002e-10
# Taylor coefficients from exact integer factorials (one correctly rounded division each)
_SIN = [(-1) ** k / math.factorial(2 * k + 1) for k in range(10)]  # of x, x^3, x^5, ...
_COS = [(-1) ** k / math.factorial(2 * k) for k in range(10)]  # of 1, x^2, x^4, ...
_EXP = [1 / math.factorial(k) for k in range(16)]


def _f64(x) -> np.ndarray:
    return np.asarray(x, dtype=np.float64)


def dot(a, b) -> np.ndarray:
    """Sum over the last axis of ``a * b`` (broadcast), left to right."""
    a, b = np.broadcast_arrays(_f64(a), _f64(b))
    out = a[..., 0] * b[..., 0]
    for j in range(1, a.shape[-1]):
        out = out + a[..., j] * b[..., j]
    return out


def matmul(a, b) -> np.ndarray:
    """``a @ b`` for ``a`` of shape (..., k) and ``b`` of shape (k,) or (k, m): the sum over j of a's column j
    times b's row j, left to right."""
    a, b = _f64(a), _f64(b)
    if b.ndim == 1:
        out = a[..., 0] * b[0]
        for j in range(1, b.shape[0]):
            out = out + a[..., j] * b[j]
        return out
    out = a[..., 0, None] * b[0]
    for j in range(1, b.shape[0]):
        out = out + a[..., j, None] * b[j]
    return out


def norm(x, keepdims: bool = False) -> np.ndarray:
    """Euclidean norm over the last axis."""
    n = np.sqrt(dot(x, x))
    return n[..., None] if keepdims else n


def normalize(x) -> np.ndarray:
    """`x` divided by its norm over the last axis."""
    x = _f64(x)
    return x / norm(x, keepdims=True)


def cross(a, b) -> np.ndarray:
    """Cross product over the last axis (3-vectors)."""
    a, b = np.broadcast_arrays(_f64(a), _f64(b))
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1], a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def rigid_inverse(T) -> np.ndarray:
    """Inverse of a 4x4 rigid transform (rotation and translation): [R^T, -R^T t]."""
    T = _f64(T)
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -matmul(T[:3, :3].T, T[:3, 3])
    return out


def _poly(coeffs: list, x: np.ndarray) -> np.ndarray:
    """sum_k coeffs[k] * x**k by Horner's rule."""
    out = np.full_like(x, coeffs[-1])
    for c in reversed(coeffs[:-1]):
        out = out * x + c
    return out


def _quadrant(x) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x = k pi/2 + r with |r| <= pi/4: (sin r, cos r, k mod 4), by Taylor series in r (error below 1e-15 for
    |x| < 1e5, the range the renderer's textures use)."""
    x = _f64(x)
    k = np.rint(x * (2.0 / np.pi))
    r = ((x - k * _PIO2_1) - k * _PIO2_2) - k * _PIO2_3
    r2 = r * r
    return r * _poly(_SIN, r2), _poly(_COS, r2), np.mod(k, 4.0)


def sin(x) -> np.ndarray:
    """sin(x) from the quadrant of x and the sine or cosine of the remainder."""
    s, c, q = _quadrant(x)
    return np.where(q == 0, s, np.where(q == 1, c, np.where(q == 2, -s, -c)))


def cos(x) -> np.ndarray:
    """cos(x) from the quadrant of x and the cosine or sine of the remainder."""
    s, c, q = _quadrant(x)
    return np.where(q == 0, c, np.where(q == 1, -s, np.where(q == 2, -c, s)))


def exp(x) -> np.ndarray:
    """exp(x): x = k ln 2 + r with |r| <= ln(2)/2, Taylor series of exp(r), scaled by 2**k (0 below -745, inf
    above 709.8)."""
    x = np.clip(_f64(x), -746.0, 710.0)
    k = np.rint(x * (1.0 / _LN2_HI))
    r = (x - k * _LN2_HI) - k * _LN2_LO
    return np.ldexp(_poly(_EXP, r), k.astype(np.int64))


def log(x) -> np.ndarray:
    """Natural log of x > 0: x = m 2**e with m in [sqrt(1/2), sqrt(2)), log(m) = 2 atanh((m - 1) / (m + 1)) by its
    series."""
    m, e = np.frexp(_f64(x))
    small = m < np.sqrt(0.5)
    m = np.where(small, m * 2.0, m)
    e = np.where(small, e - 1, e).astype(np.float64)
    s = (m - 1.0) / (m + 1.0)
    s2 = s * s
    series = 2.0 * s * _poly([1.0 / (2 * k + 1) for k in range(14)], s2)
    return (e * _LN2_LO + series) + e * _LN2_HI


def power(x, y: float) -> np.ndarray:
    """x ** y for x >= 0 (0 ** y = 0 for y > 0)."""
    x = _f64(x)
    pos = x > 0
    return np.where(pos, exp(y * log(np.where(pos, x, 1.0))), 0.0)
