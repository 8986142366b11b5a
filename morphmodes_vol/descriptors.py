"""Intrinsic surface descriptors for the warped rest field: the heat kernel signature.

Eq. (2) sees only where the two surfaces are, not which part of one lies on which part of the
other: a curled body can slide along itself, and a limb can land on the wrong limb, at a low
SDF energy. The heat kernel signature (Sun, Ovsjanikov and Guibas, "A concise and provably
informative multi-scale signature based on heat diffusion", SGP 2009),

    HKS(x, t) = sum_i exp(-lambda_i t) phi_i(x)^2,

with ``(lambda_i, phi_i)`` the eigenpairs of Eq. (4) (the cotangent Laplacian and the lumped
mass, as the skinning eigenmodes are computed), is intrinsic: it does not change when the
surface bends without stretching, so at corresponding points of two poses it is nearly
equal (docs/method.md, "The stages of a registration"). Each mesh is scaled to unit area first
and each time's signature is divided by the heat trace ``sum_i exp(-lambda_i t)``, so the
descriptor is invariant to a similarity of the mesh.

:func:`heat_kernel_signature` computes it at the vertices; :func:`surface_descriptor_grid`
extends a target's descriptors off its surface (each grid node takes the value at its
closest surface point) so that they can be sampled trilinearly, as the target SDF is.
"""

from __future__ import annotations

import logging

import numpy as np

from .eigenbasis.mesh_weights import mesh_skinning_weights
from .errors import OptionError
from .mesh import validate_mesh
from .sdf import Grid, closest_points

log = logging.getLogger(__name__)

__all__ = ["HKS_TIMES", "heat_kernel_signature", "surface_descriptor_grid"]

#: Diffusion times of the signature on a unit-area surface: from about the size of a paw or
#: an ear (``sqrt(t)`` of 0.045 of a unit area) to the size of a limb or the head (0.45)
HKS_TIMES = tuple(np.geomspace(0.002, 0.2, 4))


def heat_kernel_signature(V, F, times=HKS_TIMES, eigenpairs: int = 100, seed: int = 0) -> np.ndarray:
    """The log of the heat kernel signature at the vertices (module docstring).

    Parameters
    ----------
    V : (n, 3) float
    F : (f, 3) int
    times : sequence of float
        Diffusion times on the mesh scaled to unit area (positive).
    eigenpairs : int
        Eigenpairs of Eq. (4) in the sum (at most ``n``); the smallest time's terms decay as
        ``exp(-lambda t)``: 100 leave ``exp(-2.5)`` of the last term at ``t = 0.002``.
    seed : int
        Seed of the eigensolver's start vector.

    Returns
    -------
    (n, len(times)) float64
        ``log(HKS(x, t) / sum_i exp(-lambda_i t))``, vertex by time.

    Raises
    ------
    MeshValidationError
        When fewer than ``eigenpairs`` vertices are usable (see
        :func:`~morphmodes_vol.eigenbasis.mesh_skinning_weights`).

    Examples
    --------
    >>> import trimesh
    >>> s = trimesh.creation.icosphere(3)
    >>> D = heat_kernel_signature(s.vertices, s.faces, eigenpairs=49)  # whole multiplets: l <= 6
    >>> D.shape, bool(np.ptp(D, axis=0).max() < 0.05)  # a sphere: the same everywhere
    ((642, 4), True)
    """
    V, F = validate_mesh(V, F, "heat_kernel_signature input")
    times = np.asarray(times, dtype=np.float64).ravel()
    if times.size == 0 or not np.all(times > 0) or not np.all(np.isfinite(times)):
        raise OptionError(f"times must be positive and finite, got {times}")
    k = min(int(eigenpairs), V.shape[0])
    if k < 1:
        raise OptionError(f"eigenpairs must be a positive integer, got {eigenpairs!r}")
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1).sum()
    # on the unit-area mesh, cleaned as the source's eigenbasis is (welded seams, degenerate
    # triangles and unreferenced vertices): Eq. (4)'s eigenvectors, W^T M W = I
    phi, lam = mesh_skinning_weights(V / np.sqrt(area), F, k, seed=seed)
    decay = np.exp(-np.outer(lam, times))  # (k, t)
    hks = (phi ** 2) @ decay / decay.sum(axis=0)
    return np.log(np.maximum(hks, np.finfo(float).tiny))


def surface_descriptor_grid(V, F, D, grid: Grid) -> np.ndarray:
    """Per-vertex descriptors ``D (n, c)`` of the mesh ``(V, F)`` carried to the nodes of
    ``grid``: each node takes the barycentric mix of ``D`` at its closest surface point.

    Returns
    -------
    (nx, ny, nz, c) float64
        For :func:`~morphmodes_vol.sdf.grid.trilinear_sample`.
    """
    V, F = validate_mesh(V, F, "surface_descriptor_grid input")
    D = np.asarray(D, dtype=np.float64)
    if D.ndim != 2 or D.shape[0] != V.shape[0]:
        raise OptionError(f"descriptors must be (n, c) with n = {V.shape[0]} vertices, got {D.shape}")
    cp = closest_points(V, F, grid.points())
    values = np.einsum("pc,pcj->pj", cp.barycentrics, D[F[cp.faces]])
    return values.reshape(*grid.shape, D.shape[1])
