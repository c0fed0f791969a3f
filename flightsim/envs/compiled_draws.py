"""numpy ``Generator.standard_normal`` and ``Generator.random`` draws in compiled code, bit for bit.

The batched lidar draws some 11,000 numbers per vehicle and step (a range noise per return, a
dropout draw per ray) from each env's own generator, and they must be the numbers the single env
draws, in its order. Through numpy that is about 70 µs per vehicle (5,000 normals and 5,760
uniforms); here about 31 µs: the same algorithms (PCG64's XSL-RR step and output, numpy's
256-strip ziggurat for normals, 53-bit doubles) run in compiled code on the generator's live state,
which they advance exactly as numpy would, with the normal's random sign applied without a branch.
Not under the generator's lock: the caller's thread must own the generators while it draws.

Only numpy's ``PCG64`` (what ``np.random.default_rng`` and gymnasium's ``np_random`` use) with
its state laid out as native 128-bit integers is covered; :func:`state_address` returns None for
anything else, and callers then draw through numpy. tests/flightsim/test_compiled_draws.py holds
the draws and the generator states afterwards to numpy's.
"""

from __future__ import annotations

import ctypes
import math
import sys

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic
from numba.np.random._constants import (
    fi_double,
    ki_double,
    wi_double,
    ziggurat_nor_inv_r,
    ziggurat_nor_r,
)

_MULT_HI = np.uint64(2549297995355413924)  # PCG64's 128-bit LCG multiplier
_MULT_LO = np.uint64(4865540595714422341)
_KI, _WI, _FI = ki_double.copy(), wi_double.copy(), fi_double.copy()  # numpy's ziggurat tables
_TO_DOUBLE = 1.0 / 9007199254740992.0  # 2**-53
_M64 = (1 << 64) - 1


def state_address(rng: np.random.Generator) -> int | None:
    """Where ``rng``'s PCG64 state (state and increment, 128 bits each) lives, or None when it is
    not a PCG64 whose memory holds them as this module reads them (checked against ``.state``).

    The address is valid while ``rng`` lives: keep a reference to it.
    """
    bit_generator = rng.bit_generator
    if type(bit_generator) is not np.random.PCG64:
        return None
    address = ctypes.c_void_p.from_address(bit_generator.ctypes.state_address).value
    # numpy keeps the 128-bit words inside the PCG64 object itself: read nothing that is not there
    start, size = id(bit_generator), sys.getsizeof(bit_generator)
    if address is None or not start <= address <= start + size - 32:
        return None
    words = (ctypes.c_uint64 * 4).from_address(address)
    state = bit_generator.state["state"]
    expected = (state["state"] & _M64, state["state"] >> 64, state["inc"] & _M64, state["inc"] >> 64)
    return address if tuple(words) == expected else None


@intrinsic
def state_words(typingctx, address):  # pragma: no cover - compiled
    """The generator state at ``address`` (:func:`state_address`) as a pointer to its four 64-bit
    words: lo, hi of the state, lo, hi of the increment. Load them, draw, store ``lo, hi`` back."""
    sig = types.CPointer(types.uint64)(types.int64)

    def codegen(context, builder, signature, args):
        return builder.inttoptr(args[0], ir.PointerType(ir.IntType(64)))

    return sig, codegen


@intrinsic
def _mulhi(typingctx, a, b):  # pragma: no cover - compiled
    """The high 64 bits of the 128-bit product of two uint64."""
    sig = types.uint64(types.uint64, types.uint64)

    def codegen(context, builder, signature, args):
        wide = ir.IntType(128)
        product = builder.mul(builder.zext(args[0], wide), builder.zext(args[1], wide))
        return builder.trunc(builder.lshr(product, ir.Constant(wide, 64)), ir.IntType(64))

    return sig, codegen


@njit(cache=True, inline="always")
def _next64(lo, hi, inc_lo, inc_hi):  # pragma: no cover - compiled
    """One PCG64 step: ``state = state · mult + inc`` (mod 2**128), then the XSL-RR output of the
    new state. Returns the new state (lo, hi) and the output."""
    new_lo = lo * _MULT_LO
    new_hi = hi * _MULT_LO + lo * _MULT_HI + _mulhi(lo, _MULT_LO)
    sum_lo = new_lo + inc_lo
    new_hi = new_hi + inc_hi + (np.uint64(1) if sum_lo < new_lo else np.uint64(0))
    x = new_hi ^ sum_lo
    rot = new_hi >> np.uint64(58)
    return sum_lo, new_hi, (x >> rot) | (x << ((np.uint64(64) - rot) & np.uint64(63)))


@njit(cache=True, inline="always")
def _double(bits):  # pragma: no cover - compiled
    """numpy's ``next_double``: the top 53 bits as a double in [0, 1)."""
    return np.float64(bits >> np.uint64(11)) * _TO_DOUBLE


@njit(cache=True, inline="always")
def standard_normal(lo, hi, inc_lo, inc_hi):  # pragma: no cover - compiled
    """numpy's ``random_standard_normal`` on the state ``(lo, hi, inc_lo, inc_hi)``: returns the
    new state's ``lo, hi`` and the draw."""
    ki, wi, fi = _KI, _WI, _FI
    while True:
        lo, hi, r = _next64(lo, hi, inc_lo, inc_hi)
        idx = np.int64(r & np.uint64(0xFF))
        r = r >> np.uint64(8)
        rabs = (r >> np.uint64(1)) & np.uint64(0x000FFFFFFFFFFFFF)
        # the sign as a factor of exactly ±1, not a branch: a coin toss would mispredict half the time
        x = np.float64(rabs) * wi[idx] * (1.0 - 2.0 * np.float64(r & np.uint64(1)))
        if rabs < ki[idx]:
            return lo, hi, x  # 99.3 % of the time
        if idx == 0:  # the tail
            while True:
                lo, hi, r1 = _next64(lo, hi, inc_lo, inc_hi)
                xx = -ziggurat_nor_inv_r * math.log1p(-_double(r1))
                lo, hi, r2 = _next64(lo, hi, inc_lo, inc_hi)
                yy = -math.log1p(-_double(r2))
                if yy + yy > xx * xx:
                    tail = ziggurat_nor_r + xx
                    return lo, hi, -tail if (rabs >> np.uint64(8)) & np.uint64(1) else tail
        lo, hi, r1 = _next64(lo, hi, inc_lo, inc_hi)
        if (fi[idx - 1] - fi[idx]) * _double(r1) + fi[idx] < math.exp(-0.5 * x * x):
            return lo, hi, x


@njit(cache=True, inline="always")
def uniform(lo, hi, inc_lo, inc_hi):  # pragma: no cover - compiled
    """numpy's ``next_double`` (``Generator.random``): the new state's ``lo, hi`` and the draw."""
    lo, hi, r = _next64(lo, hi, inc_lo, inc_hi)
    return lo, hi, _double(r)


@njit(cache=True)
def draw(addresses, n_normal, normals, normal_offsets, uniforms):  # pragma: no cover - compiled
    """For each generator ``v``: ``standard_normal(n_normal[v])`` into
    ``normals[normal_offsets[v]:]``, then ``random(uniforms[v].shape)`` into ``uniforms[v]``, and
    its state advanced as numpy's own draws advance it.

    :param addresses: ``(N,)`` int64, from :func:`state_address`
    :param n_normal: ``(N,)`` int64 normals to draw from each (0: none)
    :param normals: float64, room for them all
    :param normal_offsets: ``(N,)`` int64, where each one's normals go
    :param uniforms: ``(N, ...)`` float64, C-contiguous; a ``(N, 0, ...)`` array draws none
    """
    for v in range(addresses.shape[0]):
        words = state_words(addresses[v])
        lo, hi, inc_lo, inc_hi = words[0], words[1], words[2], words[3]
        base = normal_offsets[v]
        for k in range(n_normal[v]):
            lo, hi, normals[base + k] = standard_normal(lo, hi, inc_lo, inc_hi)
        flat = uniforms[v].reshape(-1)
        for k in range(flat.shape[0]):
            lo, hi, flat[k] = uniform(lo, hi, inc_lo, inc_hi)
        words[0], words[1] = lo, hi
