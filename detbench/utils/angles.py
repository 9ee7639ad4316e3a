"""Exact wrapping of huge angles into [-pi, pi).

`x - 2 pi * floor((x + pi) / 2 pi)` in float64 is accurate for the angles a detector sees,
but for |x| beyond ~1e5 rad the float64 value of 2 pi is not exact enough (its error grows
with the number of turns: at 1e30 rad the result is pure noise, and the usual formula gives
0). `wrap_exact` reduces such a value against pi held to 1200 bits in integer arithmetic
(Machin's formula), so every finite float64 wraps to the correctly rounded angle.
`fix_huge(values, wrapped)` applies it to the few elements of an array that need it.
"""
from __future__ import annotations

import functools
import math

import numpy as np

__all__ = ["HUGE_ANGLE", "wrap_exact", "fix_huge"]

HUGE_ANGLE = 65536.0  # radians; below this the float64 formula is within ~1e-11 rad of the exact wrap
_BITS = 1200  # fixed-point bits of pi: float64 reaches 2**1024, and 53 bits of the result must survive


@functools.lru_cache(maxsize=1)
def _two_pi_fixed() -> int:
    """floor(2 pi * 2**_BITS), from Machin's formula pi = 16 atan(1/5) - 4 atan(1/239)."""
    guard = 16
    one = 1 << (_BITS + guard)

    def atan_inv(n: int) -> int:
        total, term, k, n2 = 0, one // n, 1, n * n
        while term:
            total += term // k if k % 4 == 1 else -(term // k)
            term //= n2
            k += 2
        return total

    return (2 * (16 * atan_inv(5) - 4 * atan_inv(239))) >> guard


def wrap_exact(x: float) -> float:
    """`x` radians wrapped into [-pi, pi) exactly (NaN and inf give NaN)."""
    x = float(x)
    if not math.isfinite(x):
        return math.nan
    num, den = x.as_integer_ratio()  # den is a power of two
    period = _two_pi_fixed()
    scaled = (num << _BITS) // den  # x * 2**_BITS, exact when den <= 2**_BITS (always for |x| >= 1)
    r = (scaled + period // 2) % period - period // 2
    out = r / (1 << _BITS)
    return out if out < math.pi else out - 2 * math.pi


def fix_huge(values: np.ndarray, wrapped: np.ndarray) -> np.ndarray:
    """`wrapped` (the float formula's result for `values`) with the elements where |value| >= HUGE_ANGLE
    replaced by their exact wrap (float64 values)."""
    values = np.asarray(values)
    huge = np.abs(values) >= HUGE_ANGLE
    if not huge.any():
        return wrapped
    wrapped = np.array(wrapped, copy=True)
    wrapped[huge] = [wrap_exact(v) for v in values[huge].astype(np.float64)]
    return wrapped
