"""Paper Table 2 (§4.3): with the true F, S_n^-1 = F T_n^-1 (eq. 13 with S = T F^-1)
cancels bounces: its coefficient of A^m is 0 for 2 <= m <= n, and S_n^-1 S = I + O(A^{n+1}).

T is built from a known A: S = (I - A)^-1, T = S F, with A = c N for the nilpotent
shift N (so powers A^m sit on distinct superdiagonals and each coefficient is read off
exactly: coef(A^m) = entry (0, m) / c^m). The expected values are Table 2 as printed.
"""

import numpy as np
import pytest

import bigT

from inverse_helpers import dense

TABLE2_S_INV = [  # rows n = 0..7, columns m = 0..7 (I, A, ..., A^7)
    [1, 0, 0, 0, 0, 0, 0, 0],
    [1, -1, -1, -1, -1, -1, -1, -1],
    [1, -1, 0, 1, 2, 3, 4, 5],
    [1, -1, 0, 0, -1, -3, -6, -10],
    [1, -1, 0, 0, 0, 1, 4, 10],
    [1, -1, 0, 0, 0, 0, -1, -5],
    [1, -1, 0, 0, 0, 0, 0, 1],
    [1, -1, 0, 0, 0, 0, 0, 0],
]
TABLE2_S_INV_S = [
    [1, 1, 1, 1, 1, 1, 1, 1],
    [1, 0, -1, -2, -3, -4, -5, -6],
    [1, 0, 0, 1, 3, 6, 10, 15],
    [1, 0, 0, 0, -1, -4, -10, -20],
    [1, 0, 0, 0, 0, 1, 5, 15],
    [1, 0, 0, 0, 0, 0, -1, -6],
    [1, 0, 0, 0, 0, 0, 0, 1],
    [1, 0, 0, 0, 0, 0, 0, 0],
]

N_PIX = 12
C = 0.5


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("table2")
    A = C * np.eye(N_PIX, k=1)
    S = np.linalg.inv(np.eye(N_PIX) - A)
    f = 1.5 + 0.25 * np.arange(N_PIX) / N_PIX
    T = S @ np.diag(f)
    from inverse_helpers import store

    return tmp, store(tmp, T, tile_size=4), S, f


def coefficients(Smat):
    return np.array([Smat[0, m] / C**m for m in range(8)])


@pytest.mark.parametrize("n", range(8))
def test_table2_rows(scene, n):
    tmp, T, S, f = scene
    out = tmp / f"X{n}.zarr"
    bigT.stratified_inverse(T, out, terms=n, prune=0, first_bounce=f, progress=False)
    S_inv_n = np.diag(f) @ dense(out)                       # S_n^-1 = F T_n^-1
    np.testing.assert_allclose(coefficients(S_inv_n), TABLE2_S_INV[n], atol=1e-9)
    np.testing.assert_allclose(coefficients(S_inv_n @ S), TABLE2_S_INV_S[n], atol=1e-9)
    # eq. 27: S_n^-1 S = I + O(A^{n+1}): every superdiagonal 1..n of S_n^-1 S - I is 0
    E = S_inv_n @ S - np.eye(N_PIX)
    for m in range(0, min(n, N_PIX - 1) + 1):
        np.testing.assert_allclose(np.diagonal(E, m), 0, atol=1e-9)
