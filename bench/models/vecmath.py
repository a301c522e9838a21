"""exp and log written in plain float arithmetic, so that LLVM vectorises loops that call them.

numba has no vector math library here (no SVML): a loop calling ``math.exp`` runs one lane at a time. These
versions use range reduction through the float64 bit pattern (an int64 ↔ float64 bitcast intrinsic) and
polynomials, about 1 ulp of the libm results (tested against numpy), and inline into the caller's loop.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, cast

from llvmlite import ir
from numba import types
from numba.extending import intrinsic

from bench.models.jit import njit

LN2_HI = 6.93147180369123816490e-01  # fdlibm split of ln 2: k·LN2_HI is exact for |k| < 2^11
LN2_LO = 1.90821492927058770002e-10
LOG2E = 1.4426950408889634
SQRT2 = 1.4142135623730951
EXP_MAX = 709.0
EXP_MIN = -708.0
SHIFT = 6755399441055744.0  # 1.5·2^52: adding it rounds to an integer, kept in the low mantissa bits
SHIFT_BITS = 0x4338000000000000  # its bit pattern


# An intrinsic is written as numba's typing hook (typing context, argument types) -> (signature, codegen) and
# called in jitted code with the values alone; the casts below give the checker that second, callable form.
Codegen = Callable[[object, Any, object, Sequence[Any]], Any]


@intrinsic
def _as_int_ir(typingctx: object, x: object) -> tuple[object, Codegen] | None:
    """Bit pattern of a float64 as int64."""
    if not isinstance(x, types.Float):
        return None

    def codegen(context: object, builder: Any, signature: object, args: Sequence[Any]) -> Any:
        return builder.bitcast(args[0], ir.IntType(64))

    return types.int64(types.float64), codegen


@intrinsic
def _as_float_ir(typingctx: object, i: object) -> tuple[object, Codegen] | None:
    """float64 with the bit pattern of an int64."""
    if not isinstance(i, types.Integer):
        return None

    def codegen(context: object, builder: Any, signature: object, args: Sequence[Any]) -> Any:
        return builder.bitcast(args[0], ir.DoubleType())

    return types.float64(types.int64), codegen


_as_int = cast(Callable[[float], int], _as_int_ir)
_as_float = cast(Callable[[int], float], _as_float_ir)


@njit(cache=True, inline="always", error_model="numpy")
def vexp(x: float) -> float:
    """e^x for x in [−708, 709] (clamped outside, NaN → e^709); within 2 ulp of libm.

    Rounding to the nearest multiple of ln 2 by the 1.5·2^52 shifter (no float↔int conversions; the
    integer is read from the sum's low mantissa bits) and the Taylor polynomial to r^13 in Estrin's form
    (depth 4 instead of Horner's 13 dependent multiply-adds, so the loops calling it are not latency-bound).
    """
    x = x if x < EXP_MAX else EXP_MAX  # comparisons map NaN to the bound: the bit tricks never see NaN
    x = x if x > EXP_MIN else EXP_MIN
    t = x * LOG2E + SHIFT  # round(x/ln 2) in the low mantissa bits of t
    k = t - SHIFT
    r = (x - k * LN2_HI) - k * LN2_LO  # |r| ≤ ln2/2
    r2 = r * r
    r4 = r2 * r2
    b0 = (1.0 + r) + r2 * (0.5 + r * (1.0 / 6.0))
    b1 = (1.0 / 24.0 + r * (1.0 / 120.0)) + r2 * (1.0 / 720.0 + r * (1.0 / 5040.0))
    b2 = (1.0 / 40320.0 + r * (1.0 / 362880.0)) + r2 * (1.0 / 3628800.0 + r * (1.0 / 39916800.0))
    b3 = 1.0 / 479001600.0 + r * (1.0 / 6227020800.0)
    p = (b0 + r4 * b1) + (r4 * r4) * (b2 + r4 * b3)
    return p * _as_float((_as_int(t) - SHIFT_BITS + 1023) << 52)


@njit(cache=True, inline="always", error_model="numpy")
def vlog(x: float) -> float:
    """ln x for positive normal x (other inputs give a finite or non-finite value of no meaning)."""
    bits = _as_int(x)
    e = float((bits >> 52) - 1023)
    m = _as_float((bits & 0x000FFFFFFFFFFFFF) | 0x3FF0000000000000)  # mantissa in [1, 2)
    if m > SQRT2:
        m *= 0.5
        e += 1.0
    s = (m - 1.0) / (m + 1.0)  # |s| ≤ 0.172: ln m = 2 atanh s
    z = s * s
    p = 2.0 / 21.0
    p = p * z + 2.0 / 19.0
    p = p * z + 2.0 / 17.0
    p = p * z + 2.0 / 15.0
    p = p * z + 2.0 / 13.0
    p = p * z + 2.0 / 11.0
    p = p * z + 2.0 / 9.0
    p = p * z + 2.0 / 7.0
    p = p * z + 2.0 / 5.0
    p = p * z + 2.0 / 3.0
    p = p * z + 2.0
    return e * LN2_HI + (s * p + e * LN2_LO)

