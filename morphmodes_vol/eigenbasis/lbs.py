"""The linear-blend-skinning subspace of Eq. (5)-(6), applied implicitly.

With ``m`` modes the coefficients are ``m`` affine blocks ``T_j (3, 4)`` stored as an array
``T (m, 3, 4)``, and the deformed vertices are (Eq. 6)

    x_i = x0_i + sum_j W[i, j] * T_j @ [x0_i, 1]

which is ``x = B z + x0`` with the ``3n x 12m`` matrix ``B`` of Eq. (5), without building
``B``. The paper's vector ``z`` (Eq. 5's column order: mode, homogeneous coordinate,
dimension) is ``T.transpose(0, 2, 1).reshape(-1)``; see :func:`to_paper_z`.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["LBSBasis", "to_paper_z", "from_paper_z"]


def to_paper_z(T: np.ndarray) -> np.ndarray:
    """Blocks ``T (m, 3, 4)`` to the paper's coefficient vector ``z (12m,)`` (Eq. 5-6)."""
    return np.ascontiguousarray(np.asarray(T).transpose(0, 2, 1)).reshape(-1)


def from_paper_z(z: np.ndarray) -> np.ndarray:
    """The paper's ``z (12m,)`` to blocks ``T (m, 3, 4)``."""
    z = np.asarray(z, dtype=np.float64)
    return np.ascontiguousarray(z.reshape(-1, 4, 3).transpose(0, 2, 1))


class LBSBasis:
    """Skinning subspace of a rest mesh: ``x = x0 + B z`` applied without building ``B``.

    Parameters
    ----------
    X0 : (n, 3) float
        Rest vertex positions.
    W : (n, m_max) float
        Skinning weights (columns are modes).

    Examples
    --------
    >>> import numpy as np
    >>> X0 = np.random.default_rng(0).random((10, 3)); W = np.ones((10, 1))
    >>> T = np.zeros((1, 3, 4)); T[0, :, 3] = [1, 0, 0]     # translate by +x
    >>> bool(np.allclose(LBSBasis(X0, W).deform(T), X0 + [1, 0, 0]))
    True
    """

    def __init__(self, X0: np.ndarray, W: np.ndarray):
        self.X0 = np.array(X0, dtype=np.float64, copy=True)
        self.W = np.array(W, dtype=np.float64, copy=True)
        if self.W.ndim != 2 or self.W.shape[0] != self.X0.shape[0]:
            raise ValueError(f"W must have shape ({self.X0.shape[0]}, m), got {self.W.shape}")
        self.Xh = np.hstack([self.X0, np.ones((self.X0.shape[0], 1))])  # [X0 1], (n, 4)
        self._gram: np.ndarray | None = None
        self._skinning: np.ndarray | None = None

    @property
    def max_modes(self) -> int:
        return self.W.shape[1]

    def displacement(self, T: np.ndarray) -> np.ndarray:
        """``B z`` as an ``(n, 3)`` array, for blocks ``T (m, 3, 4)`` with ``m <= m_max``."""
        m = T.shape[0]
        # one (n, m) @ (m, 12) product: every vertex's blended block, then times [x0 1]
        blended = (self.W[:, :m] @ np.asarray(T, dtype=np.float64).reshape(m, 12)).reshape(-1, 3, 4)
        return np.einsum("nab,nb->na", blended, self.Xh)

    def deform(self, T: np.ndarray) -> np.ndarray:
        """Deformed vertices ``x0 + B z`` (Eq. 6), ``(n, 3)``."""
        return self.X0 + self.displacement(T)

    def pullback(self, G: np.ndarray, m: int) -> np.ndarray:
        """``B^T g`` for a per-vertex gradient ``G (n, 3)``: the gradient with respect to the
        first ``m`` blocks, ``(m, 3, 4)``, ``dE/dT_j = G^T diag(w_j) [X0 1]``."""
        # one (m, n) @ (n, 12) product over the outer products g_i [x0_i 1]^T
        outer = (np.asarray(G, dtype=np.float64)[:, :, None] * self.Xh[:, None, :]).reshape(-1, 12)
        return (self.W[:, :m].T @ outer).reshape(m, 3, 4)

    def gram_blocks(self, m: int) -> np.ndarray:
        """Per-mode Gram matrices ``[X0 1]^T diag(w_j)^2 [X0 1]``, ``(m, 4, 4)``.

        ``B_j^T B_j = Gram_j kron I3`` for the 12 columns of mode ``j``; used to precondition
        the gradient step so that translation and linear parts move vertices alike.
        """
        gram = self._gram  # read once: another thread may replace it (the same values)
        if gram is None or gram.shape[0] < m:
            W2 = self.W**2
            gram = self._gram = np.einsum("nj,nk,nl->jkl", W2, self.Xh, self.Xh, optimize=True)
        return gram[:m]

    def skinning_matrix(self, m: int) -> np.ndarray:
        """``C (n, 4m)``, ``C[i, 4 j + b] = W[i, j] [x0_i 1]_b``: each coordinate of the
        displacement is ``C`` times that coordinate's coefficients (Eq. 6), and ``B = C kron
        I3`` (Eq. 5). Read-only: the last one built is kept for the next call."""
        # the optimizer asks for one m many times in a row: the last one is kept (read-only)
        # read once: another thread may replace it with another m's between a test and a return
        C = self._skinning
        if C is None or C.shape[1] != 4 * m:
            n = self.X0.shape[0]
            C = (self.W[:, :m, None] * self.Xh[:, None, :]).reshape(n, 4 * m)
            C.flags.writeable = False
            self._skinning = C
        return C

    def fit(self, X: np.ndarray, m: int, rows: sp.spmatrix | None = None) -> np.ndarray:
        """The blocks ``T (m, 3, 4)`` whose deformation is closest to ``X`` in the least
        squares sense over the first ``m`` modes: ``argmin_T ||S deform(T) - X||^2``, ``S =
        rows`` (default the identity: ``X (n, 3)`` are the vertices' positions). Eq. (6) is
        linear in ``T``, so this is one least-squares solve with ``4m`` unknowns per
        coordinate. ``fit(deform(T), m)`` reproduces ``deform(T)`` (and ``T`` itself when the
        ``n x 4m`` matrix ``W[:, :m] * [X0 1]`` has full column rank).

        Parameters
        ----------
        X : (k, 3) float
            Where the points ``S x`` should be.
        m : int
            Modes to fit, ``1 <= m <= m_max``.
        rows : (k, n) sparse matrix, optional
            Each point a combination of vertices (a row of barycentric coordinates places a
            point on a face).

        Examples
        --------
        >>> X0 = np.random.default_rng(0).random((10, 3)); W = np.ones((10, 1))
        >>> A = np.array([[[0.1, 0, 0, 1], [0, 0, 0, 2], [0, 0, -0.2, 3]]])
        >>> bool(np.allclose(LBSBasis(X0, W).fit(X0 @ (np.eye(3) + A[0, :, :3]).T + A[0, :, 3], 1), A))
        True
        """
        X = np.asarray(X, dtype=np.float64)
        n = self.X0.shape[0]
        k = n if rows is None else rows.shape[0]
        if rows is not None and rows.shape[1] != n:
            raise ValueError(f"rows must have {n} columns (one per vertex), got {rows.shape}")
        if X.shape != (k, 3):
            raise ValueError(f"X must have shape ({k}, 3), got {X.shape}")
        if not 1 <= m <= self.max_modes:
            raise ValueError(f"m must be in [1, {self.max_modes}], got {m}")
        C = self.skinning_matrix(m)  # x - x0 = C T'
        rest = self.X0
        if rows is not None:
            C, rest = rows @ C, rows @ self.X0
        sol, *_ = np.linalg.lstsq(C, X - rest, rcond=None)  # (4m, 3): mode, homogeneous
        return np.ascontiguousarray(sol.reshape(m, 4, 3).transpose(0, 2, 1))

    def matrix(self, m: int) -> sp.csr_matrix:
        """The explicit ``3n x 12m`` matrix ``B`` of Eq. (5) (tests and small meshes only)."""
        return sp.kron(sp.csr_matrix(self.skinning_matrix(m)), sp.identity(3), format="csr")
