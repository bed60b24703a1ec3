"""torchevtrack.linalg against numpy.linalg (LAPACK) on symmetric matrices of mixed signs and scales."""

import numpy as np
import pytest

from torchevtrack import linalg


def _symmetric(rng, n):
    Q = rng.normal(size=(n, n)) * 10.0 ** rng.uniform(-3, 6, size=(1, n))
    S = Q @ Q.T * rng.choice([-1.0, 1.0]) + np.diag(rng.normal(size=n))
    return (S + S.T) / 2


@pytest.mark.parametrize("n", [4, 6, 12])
def test_eigh_matches_lapack(n):
    rng = np.random.default_rng(n)
    for _ in range(100):
        S = _symmetric(rng, n)
        ref = np.linalg.eigvalsh(S)
        d, V = np.empty(n), np.empty((n, n))
        linalg.eigh(S.copy(), d, V)
        scale = np.abs(ref).max()
        np.testing.assert_allclose(np.sort(d), ref, rtol=0, atol=1e-13 * scale)
        np.testing.assert_allclose(V.T @ V, np.eye(n), rtol=0, atol=1e-12)
        np.testing.assert_allclose(S @ V, V * d, rtol=0, atol=1e-12 * scale)


def test_cholesky_inverse_and_solve_match_lapack():
    rng = np.random.default_rng(1)
    for n in (3, 6, 12):
        for _ in range(50):
            Q = rng.normal(size=(n, n)) * 10.0 ** rng.uniform(-2, 2)
            A = Q @ Q.T + 0.1 * np.abs(Q).max() ** 2 * np.eye(n)
            L, x, inv = np.empty((n, n)), np.empty(n), np.empty((n, n))
            assert linalg.cholesky(A, L)
            np.testing.assert_allclose(L, np.linalg.cholesky(A), rtol=1e-10, atol=1e-12 * np.sqrt(np.abs(A).max()))
            b = rng.normal(size=n)
            linalg.cholesky_solve(L, b, x)
            np.testing.assert_allclose(x, np.linalg.solve(A, b), rtol=1e-8, atol=1e-12 * np.abs(x).max())
            linalg.cholesky_inverse(L, inv)
            np.testing.assert_allclose(inv, np.linalg.inv(A), rtol=1e-7, atol=1e-10 * np.abs(inv).max())


def test_cholesky_rejects_indefinite():
    L = np.empty((2, 2))
    assert not linalg.cholesky(np.array([[1.0, 2.0], [2.0, 1.0]]), L)


def test_lu_solve_matches_lapack_and_flags_singular():
    rng = np.random.default_rng(2)
    for n in (3, 6, 13):
        A, B = rng.normal(size=(n, n)), rng.normal(size=(n, 4))
        out = np.empty((n, 4))
        assert linalg.lu_solve(A, B, out)
        np.testing.assert_allclose(out, np.linalg.solve(A, B), rtol=1e-8, atol=1e-10)
    assert not linalg.lu_solve(np.zeros((3, 3)), np.ones((3, 1)), np.empty((3, 1)))
