"""numba kernels of :mod:`bigT.compensation.encoding` (imported on first use): the sRGB
curve of :mod:`bigT.colour` in float32 over a flat range [a, b) of an array, ``nogil``
so a thread pool runs ranges in parallel. The constants come from bigT.colour as
arguments, so the curve is defined once."""

from __future__ import annotations

from numba import njit


@njit(nogil=True, cache=True)
def srgb_decode(values, out, a, b, knee, slope, offset, one, gamma):
    """out[a:b] = linear light of the sRGB-encoded values[a:b] (bigT.colour.decode);
    ``one`` is 1 + offset."""
    for i in range(a, b):
        x = values[i]
        out[i] = ((x + offset) / one) ** gamma if x > knee else x / slope


@njit(nogil=True, cache=True)
def srgb_encode(values, out, a, b, knee, slope, offset, one, inv_gamma):
    """out[a:b] = sRGB-encoded values of the linear light values[a:b]
    (bigT.colour.encode); ``one`` is 1 + offset."""
    for i in range(a, b):
        x = values[i]
        out[i] = one * x ** inv_gamma - offset if x > knee else x * slope
