"""Small dense linear algebra for the filters and the template search: compiled (numba) helpers on float64 arrays.

One matrix at a time (``n`` up to a few dozen), without LAPACK's per-call overhead; callers loop over the batch.
Every function writes into caller-provided buffers and allocates at most ``O(n)`` scratch. Oracle:
``tests/test_linalg.py`` (against :mod:`numpy.linalg`).

Example:
    >>> import numpy as np
    >>> from torchevtrack.linalg import cholesky, cholesky_solve
    >>> A, L, x = np.array([[4.0, 2.0], [2.0, 3.0]]), np.empty((2, 2)), np.empty(2)
    >>> cholesky(A, L)
    True
    >>> cholesky_solve(L, np.array([2.0, 1.0]), x)
    >>> x.round(6).tolist()
    [0.5, 0.0]
"""

from __future__ import annotations

import numpy as np

from torchevtrack.kernels import kernel

__all__ = ["cholesky", "cholesky_inverse", "cholesky_solve", "lu_solve", "eigh"]


@kernel
def cholesky(A, L):
    """Lower Cholesky factor ``L`` of the symmetric part of ``A`` ``(n, n)`` (float64); False if ``A`` is not
    positive definite."""
    n = A.shape[0]
    for j in range(n):
        s = 0.5 * (A[j, j] + A[j, j])
        for m in range(j):
            s -= L[j, m] * L[j, m]
        if not s > 0.0:
            return False
        d = np.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, n):
            s = 0.5 * (A[i, j] + A[j, i])
            for m in range(j):
                s -= L[i, m] * L[j, m]
            L[i, j] = s / d
            L[j, i] = 0.0
    return True


@kernel
def cholesky_inverse(L, out):
    """``out = (L L^T)^-1`` (symmetric) from the lower Cholesky factor ``L`` ``(n, n)``."""
    n = L.shape[0]
    Li = np.zeros((n, n))
    for j in range(n):  # Li = L^-1, lower triangular, column by column
        Li[j, j] = 1.0 / L[j, j]
        for i in range(j + 1, n):
            s = 0.0
            for m in range(j, i):
                s -= L[i, m] * Li[m, j]
            Li[i, j] = s / L[i, i]
    for i in range(n):  # out = Li^T Li
        for j in range(i + 1):
            s = 0.0
            for m in range(i, n):
                s += Li[m, i] * Li[m, j]
            out[i, j] = s
            out[j, i] = s


@kernel
def cholesky_solve(L, b, out):
    """``out = (L L^T)^-1 b`` for the lower Cholesky factor ``L`` ``(n, n)`` and ``b`` ``(n,)``."""
    n = L.shape[0]
    y = np.empty(n)
    for i in range(n):
        s = b[i]
        for m in range(i):
            s -= L[i, m] * y[m]
        y[i] = s / L[i, i]
    for i in range(n - 1, -1, -1):
        s = y[i]
        for m in range(i + 1, n):
            s -= L[m, i] * out[m]
        out[i] = s / L[i, i]


@kernel
def lu_solve(A, Bm, out):
    """``out = A^-1 Bm`` for ``A`` ``(n, n)`` and ``Bm`` ``(n, m)`` by Gaussian elimination with partial pivoting
    (LAPACK ``getrf`` / ``getrs``, as :func:`torch.linalg.solve`); False if ``A`` is singular."""
    n, m = Bm.shape
    a = A.copy()
    for i in range(n):
        for j in range(m):
            out[i, j] = Bm[i, j]
    for k in range(n):
        p = k
        for i in range(k + 1, n):
            if abs(a[i, k]) > abs(a[p, k]):
                p = i
        if a[p, k] == 0.0:
            return False
        if p != k:
            for j in range(n):
                a[k, j], a[p, j] = a[p, j], a[k, j]
            for j in range(m):
                out[k, j], out[p, j] = out[p, j], out[k, j]
        for i in range(k + 1, n):
            f = a[i, k] / a[k, k]
            for j in range(k + 1, n):
                a[i, j] -= f * a[k, j]
            for j in range(m):
                out[i, j] -= f * out[k, j]
    for i in range(n - 1, -1, -1):
        for j in range(m):
            s = out[i, j]
            for q in range(i + 1, n):
                s -= a[i, q] * out[q, j]
            out[i, j] = s / a[i, i]
    return True


@kernel
def eigh(a, d, v):
    """Eigen-decomposition of the symmetric ``a`` ``(n, n)`` float64 (overwritten) by cyclic Jacobi rotations, until
    the off-diagonal part is below float64 rounding of the diagonal.

    Outputs: ``d`` ``(n,)`` the eigenvalues (unsorted) and ``v`` ``(n, n)`` the unit eigenvectors as columns
    (``a_in v[:, i] = d[i] v[:, i]``). Accurate to rounding like :func:`numpy.linalg.eigh`, without a LAPACK call.
    """
    n = a.shape[0]
    v[:] = 0.0
    for i in range(n):
        v[i, i] = 1.0
    for _ in range(50):
        off = scale = 0.0
        for i in range(n):
            scale += a[i, i] * a[i, i]
            for j in range(i + 1, n):
                off += a[i, j] * a[i, j]
        if off <= 1e-32 * (scale + 2.0 * off) or off == 0.0:
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = a[p, q]
                if apq == 0.0:
                    continue
                theta = (a[q, q] - a[p, p]) / (2.0 * apq)
                t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + np.sqrt(theta * theta + 1.0))
                c = 1.0 / np.sqrt(t * t + 1.0)
                sn = t * c
                for k in range(n):  # columns p, q of a and v
                    akp, akq = a[k, p], a[k, q]
                    a[k, p], a[k, q] = c * akp - sn * akq, sn * akp + c * akq
                    vkp, vkq = v[k, p], v[k, q]
                    v[k, p], v[k, q] = c * vkp - sn * vkq, sn * vkp + c * vkq
                for k in range(n):  # rows p, q of a
                    apk, aqk = a[p, k], a[q, k]
                    a[p, k], a[q, k] = c * apk - sn * aqk, sn * apk + c * aqk
    for i in range(n):
        d[i] = a[i, i]
