"""Eigenbasis: hand-computed Laplacian/mass values, Eq. (4) identities, implicit LBS (Eq. 5-6)."""

import numpy as np
import pytest

from morphmodes_vol.eigenbasis import (
    LBSBasis,
    cotangent_laplacian,
    from_paper_z,
    lumped_mass,
    skinning_eigenmodes,
    to_paper_z,
)
from morphmodes_vol.eigenbasis import mesh_skinning_weights
from morphmodes_vol.errors import MeshValidationError, OptionError
from morphmodes_vol.primitives import capsule, icosphere


def test_cotangent_laplacian_right_isoceles_triangle():
    # Right angle at vertex 0, 45 degrees at 1 and 2: cot 90 = 0, cot 45 = 1.
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    F = np.array([[0, 1, 2]])
    L = cotangent_laplacian(V, F).toarray()
    # edge (0,1) is opposite vertex 2 (45 deg): weight cot/2 = 0.5; edge (1,2) opposite the right angle: 0
    expected = np.array([[1.0, -0.5, -0.5], [-0.5, 0.5, 0.0], [-0.5, 0.0, 0.5]])
    np.testing.assert_allclose(L, expected, atol=1e-12)


def test_lumped_mass_sums_to_area():
    V, F = icosphere(2)
    import trimesh

    area = trimesh.Trimesh(V, F, process=False).area
    for kind in ("voronoi", "barycentric"):
        M = lumped_mass(V, F, kind)
        assert M.diagonal().min() > 0
        assert M.diagonal().sum() == pytest.approx(area, rel=1e-10)
    V3 = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    F3 = np.array([[0, 2, 1]])
    with pytest.raises(OptionError, match="voronoi"):
        lumped_mass(V3, F3, "nope")


@pytest.mark.parametrize("mesh", [icosphere(2), capsule(count=(14, 14)), icosphere(4)])
def test_eigenmodes_identities(mesh):
    V, F = mesh
    W, lam = skinning_eigenmodes(V, F, 8)
    M = lumped_mass(V, F)
    L = cotangent_laplacian(V, F)
    np.testing.assert_allclose(W.T @ (M @ W), np.eye(8), atol=1e-8)
    np.testing.assert_allclose(W[:, 0], W[0, 0], rtol=1e-12)  # mode 0 constant
    assert np.all(np.diff(lam) >= -1e-10) and lam[0] == 0 and lam.min() >= 0
    # they solve Eq. (4): L W = M W Lambda (relative residual)
    R = L @ W - (M @ W) * lam
    assert np.abs(R).max() <= 1e-6 * max(1.0, np.abs(L @ W).max())


def test_eigenmodes_sparse_and_dense_paths_agree():
    V, F = icosphere(3)  # 642 vertices: sparse path
    W, lam = skinning_eigenmodes(V, F, 4)
    import importlib

    mod = importlib.import_module("morphmodes_vol.eigenbasis.skinning_eigenmodes")
    se = mod.skinning_eigenmodes

    old = mod._DENSE_LIMIT
    mod._DENSE_LIMIT = 10**9
    try:
        Wd, lamd = se(V, F, 4)
    finally:
        mod._DENSE_LIMIT = old
    np.testing.assert_allclose(lam, lamd, rtol=1e-6, atol=1e-9)
    # mode 0 identical; modes 1-3 span a degenerate (l=1) eigenspace on the sphere: compare spans
    M = lumped_mass(V, F)
    P = W[:, 1:4].T @ (M @ Wd[:, 1:4])
    np.testing.assert_allclose(np.abs(np.linalg.svd(P)[1]), 1.0, atol=1e-6)


def test_eigenmodes_disconnected_components():
    V1, F1 = icosphere(2)
    V = np.vstack([V1, V1 + [3.0, 0, 0]])
    F = np.vstack([F1, F1 + len(V1)])
    W, lam = skinning_eigenmodes(V, F, 4)
    M = lumped_mass(V, F)
    np.testing.assert_allclose(W.T @ (M @ W), np.eye(4), atol=1e-8)
    np.testing.assert_allclose(W[:, 0], W[0, 0])
    assert lam[1] < 1e-6  # the second zero eigenvalue: per-component constant


def test_eigenmodes_reject_bad_mode_count():
    V, F = icosphere(1)
    with pytest.raises(ValueError):
        skinning_eigenmodes(V, F, 0)
    with pytest.raises(ValueError):
        skinning_eigenmodes(V, F, len(V) + 1)


def test_one_mode_reproduces_any_affine_map(rng):
    V, F = capsule(count=(10, 10))
    W, _ = skinning_eigenmodes(V, F, 3)
    basis = LBSBasis(V, W)
    A = np.eye(3) + 0.3 * rng.standard_normal((3, 3))
    t = rng.standard_normal(3)
    # x = x0 + w0 * T0 [x0 1] = A x0 + t  <=>  T0 = ([A - I, t]) / w0
    T = np.zeros((1, 3, 4))
    T[0, :, :3] = (A - np.eye(3)) / W[0, 0]
    T[0, :, 3] = t / W[0, 0]
    np.testing.assert_allclose(basis.deform(T), V @ A.T + t, atol=1e-12)


def test_implicit_lbs_matches_explicit_eq5(rng):
    V, F = icosphere(1)
    W, _ = skinning_eigenmodes(V, F, 5)
    basis = LBSBasis(V, W)
    T = rng.standard_normal((5, 3, 4))
    B = basis.matrix(5)
    assert B.shape == (3 * len(V), 60)
    z = to_paper_z(T)
    np.testing.assert_allclose(from_paper_z(z), T)
    np.testing.assert_allclose((B @ z).reshape(-1, 3), basis.displacement(T), atol=1e-12)
    G = rng.standard_normal(V.shape)
    np.testing.assert_allclose(to_paper_z(basis.pullback(G, 5)), B.T @ G.ravel(), atol=1e-10)
    # Gram blocks are the diagonal 12x12 blocks of B^T B (per coordinate)
    BtB = (B.T @ B).toarray()
    gram = basis.gram_blocks(5)
    for j in range(5):
        block = BtB[12 * j : 12 * j + 12, 12 * j : 12 * j + 12]
        np.testing.assert_allclose(block, np.kron(gram[j], np.eye(3)), atol=1e-10)


def _lumpy(subdivisions):
    V, F = icosphere(subdivisions)
    V = V * [1.0, 0.65, 0.45]
    return V * (1 + 0.2 * np.sin(3 * V[:, 0] + 0.5) * np.cos(2 * V[:, 1]))[:, None], F


def test_sparse_solver_is_seed_independent_for_simple_eigenvalues():
    V, F = _lumpy(3)  # 642 vertices: the sparse shift-invert path
    W0, lam0 = skinning_eigenmodes(V, F, 6, seed=0)
    W1, lam1 = skinning_eigenmodes(V, F, 6, seed=7)
    assert np.all(np.diff(lam0) > 1e-3 * lam0[-1])  # no repeated eigenvalue on this shape
    assert lam0[1] > 0  # connected: a single zero eigenvalue, computed, not imposed
    np.testing.assert_allclose(lam0, lam1, rtol=1e-8)
    np.testing.assert_allclose(W0, W1, atol=1e-7)


def test_mesh_weights_weld_a_triangle_soup():
    V, F = icosphere(2)
    soup = V[F].reshape(-1, 3)
    Fs = np.arange(len(soup)).reshape(-1, 3)
    W_soup, lam_soup = mesh_skinning_weights(soup, Fs, 5)
    W, lam = skinning_eigenmodes(V, F, 5)
    np.testing.assert_allclose(lam_soup, lam, rtol=1e-8, atol=1e-10)
    # copies of one vertex get identical weights: compare each soup vertex with the first
    # copy of the same mesh vertex
    idx = F.ravel()
    first = {}
    for k, v in enumerate(idx):
        first.setdefault(v, k)
    same = np.array([first[v] for v in idx])
    np.testing.assert_array_equal(W_soup, W_soup[same])


def test_mesh_weights_unreferenced_vertex_and_degenerate_face():
    V, F = icosphere(2)
    extra = np.vstack([V, [[1.01, 0.0, 0.0]]])  # unreferenced, next to vertex argmax x
    Fdeg = np.vstack([F, [[0, 1, 1]], [[0, 0, 0]]])  # repeated corners: zero area
    W, lam = mesh_skinning_weights(extra, Fdeg, 4)
    W_ref, lam_ref = skinning_eigenmodes(V, F, 4)
    np.testing.assert_allclose(lam, lam_ref, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(W[-1], W[np.argmax(V[:, 0])])
    with pytest.raises(MeshValidationError, match="usable vertices"):
        mesh_skinning_weights(V, F[:1], 4)
