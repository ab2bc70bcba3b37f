"""Inverting a non-decreasing tabulated function, flat stretches included."""

from __future__ import annotations

import numpy as np


def invert_table(wanted, values: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """The smallest x with f(x) = ``wanted``, f the piecewise-linear function through
    (``grid``, ``values``).

    ``np.interp`` needs strictly increasing abscissae; a response is only
    non-decreasing (a pooled flat stretch near black, a clipped top). Taking the first
    table entry at or above the wanted value picks the smallest x of a flat stretch,
    so black is sent as 0, and is exact at both ends.

    Parameters
    ----------
    wanted : array_like, any shape, clipped to [values[0], values[-1]]
    values : ndarray, shape (N,), non-decreasing
    grid : ndarray, shape (N,), increasing

    Returns
    -------
    ndarray of float64, the shape of ``wanted``
    """
    wanted = np.clip(np.asarray(wanted, dtype=np.float64), values[0], values[-1])
    above = np.clip(np.searchsorted(values, wanted, side="left"), 1, values.size - 1)
    below = above - 1
    rise = values[above] - values[below]  # > 0 wherever wanted > values[0]
    short = np.divide(values[above] - wanted, rise, out=np.zeros_like(wanted), where=rise > 0)
    x = grid[above] - short * (grid[above] - grid[below])
    return np.where(wanted <= values[0], grid[0], x)
