"""Skinning eigenmodes: generalized eigenvectors of the cotangent Laplacian (Eq. 4)."""

from __future__ import annotations

import logging

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..blas import single_threaded_blas
from ..errors import MeshValidationError, OptionError
from ..mesh import validate_mesh
from .cotangent_laplacian import cotangent_laplacian
from .lumped_mass import lumped_mass

__all__ = ["skinning_eigenmodes"]

log = logging.getLogger(__name__)

# Below this many vertices a dense generalized eigensolver is faster and always succeeds.
_DENSE_LIMIT = 600


def skinning_eigenmodes(V, F, modes: int, seed: int = 0, coupling=None) -> tuple[np.ndarray, np.ndarray]:
    """The ``modes`` smallest solutions of ``L W = M W Lambda`` (Eq. 4).

    ``L`` is the positive semidefinite cotangent Laplacian and ``M`` the lumped Voronoi mass
    matrix of the mesh. Solved by sparse shift-invert Lanczos (``scipy.sparse.linalg.eigsh``
    with a small negative shift, so ``L - sigma M`` is positive definite), or densely for
    small meshes.

    The result is normalized so that it is deterministic and usable as skinning weights:
    column 0 is exactly the constant ``1 / sqrt(sum(M))``; every column is M-orthonormalized
    against the previous ones (``W^T M W = I``; this matters only for repeated eigenvalues,
    e.g. disconnected components); each column's entry of largest magnitude is positive.

    Parameters
    ----------
    V : (n, 3) float
    F : (f, 3) int
    modes : int
        Number of eigenmodes, ``1 <= modes <= n``.
    seed : int
        Seed of the Lanczos start vector.
    coupling : (n, n) sparse matrix, optional
        A positive semidefinite stiffness added to ``L`` (the join of a mesh's components,
        :func:`~morphmodes_vol.eigenbasis.component_coupling.component_coupling`).

    Returns
    -------
    W : (n, modes) float64
        Skinning weights, one mode per column, ``W^T M W = I``.
    eigenvalues : (modes,) float64
        Ascending and non-negative (round-off below zero is clipped).

    Examples
    --------
    >>> import trimesh
    >>> s = trimesh.creation.icosphere(2)
    >>> W, lam = skinning_eigenmodes(s.vertices, s.faces, 4)
    >>> W.shape, bool(lam[0] < 1e-8)
    ((162, 4), True)
    """
    V, F = validate_mesh(V, F, "skinning_eigenmodes input")
    n = V.shape[0]
    if not (isinstance(modes, (int, np.integer)) and 1 <= modes <= n):
        raise OptionError(f"modes={modes!r}: expected an integer in [1, {n}] for {n} vertices")
    L = cotangent_laplacian(V, F)
    if coupling is not None:
        L = (L + coupling).tocsc()
    M = lumped_mass(V, F)
    mass = M.diagonal()
    if not np.all(np.isfinite(L.data)) or np.any(mass <= 0) or not np.all(np.isfinite(mass)):
        raise MeshValidationError(
            "the source mesh has degenerate triangles or unreferenced vertices "
            "(zero or non-finite mass / cotangent weights); mesh_skinning_weights cleans them"
        )

    # BLAS on one thread: within a repeated eigenvalue's space (a symmetric mesh) the
    # eigenvectors depend on the last bits of its sums, so on more threads they changed with
    # the thread count (morphmodes_vol.blas)
    with single_threaded_blas():
        if n <= _DENSE_LIMIT or modes >= n - 1:
            lam, W = scipy.linalg.eigh(L.toarray(), np.diag(mass), subset_by_index=[0, modes - 1])
        else:
            scale = float(np.mean(L.diagonal()) / np.mean(mass))
            sigma = -1e-6 * scale
            rng = np.random.default_rng(seed)
            v0 = rng.standard_normal(n)
            lam, W = spla.eigsh(L, k=modes, M=M, sigma=sigma, which="LM", v0=v0)
        order = np.argsort(lam)
        lam, W = lam[order], W[:, order]
        W = _normalize(W, mass)
    lam = np.maximum(lam, 0.0)
    lam[0] = 0.0
    log.debug("skinning eigenmodes: n=%d modes=%d largest eigenvalue %.4g", n, modes, lam[-1])
    return W, lam


def _normalize(W: np.ndarray, mass: np.ndarray) -> np.ndarray:
    """Constant first column, M-orthonormal columns, deterministic signs."""
    W = np.array(W, dtype=np.float64, copy=True)
    W[:, 0] = 1.0 / np.sqrt(mass.sum())
    for j in range(W.shape[1]):
        w = W[:, j]
        for _ in range(2):  # twice is enough (Kahan/Parlett "twice is enough")
            coeffs = W[:, :j].T @ (mass * w)
            w = w - W[:, :j] @ coeffs
        w = w / np.sqrt(np.dot(w, mass * w))
        k = np.argmax(np.abs(w))
        W[:, j] = w if w[k] >= 0 else -w
    return W
