"""Eq. (3) and its gradients: analytic = central finite differences, in vertex and subspace
coordinates; a hand-checkable value."""

import numpy as np
import pytest

from morphmodes_vol.eigenbasis import LBSBasis, skinning_eigenmodes
from morphmodes_vol.energy import SDFEnergy
from morphmodes_vol.primitives import icosphere
from morphmodes_vol.sdf import Grid, signed_distance, signed_volume


def _energy_for(V, F, target_V, resolution=11):
    lo = np.minimum(V.min(0), target_V.min(0))
    hi = np.maximum(V.max(0), target_V.max(0))
    grid = Grid.covering(lo, hi, resolution, padding=0.3)
    # shift the grid off any symmetry plane so no point lies on a medial axis
    Q = grid.points() + np.array([0.0123, -0.0071, 0.0047])
    g = signed_distance(target_V, F, Q).value
    return SDFEnergy(F, Q, g, grid.cell_volume)


def test_energy_value_is_weighted_sum_of_squares():
    V, F = icosphere(2)
    E = _energy_for(V, F, V * 1.2)
    ev = E.evaluate(V)
    f = signed_distance(V, F, E.Q).value
    assert ev.energy == pytest.approx(np.sum(E.weights * (f - E.g) ** 2), rel=1e-12)
    # a sphere of radius 1 vs 1.2: every point outside both is off by exactly ~0.2
    far = np.linalg.norm(E.Q, axis=1) > 1.3
    np.testing.assert_allclose(ev.residual[far], 0.2, atol=0.02)
    assert E.evaluations == 1


@pytest.mark.parametrize("sign", ["raycast", "winding"])
def test_a_source_turned_inside_out_does_not_fit_its_mirror_image(sign):
    """A reflection of the vertices maps a closed source onto its mirror image, with the
    source's triangles inside out (a skinning subspace of affine blocks can reach it). The
    mirror image, oriented outward, is fitted exactly by the same vertices with the faces
    reversed; with the source's faces, the inside-out surface must not fit it. Ray parity
    alone cannot tell the two apart (the same field), so the energy's field follows the
    orientation: at nodes inside the target, the residual is twice the distance."""
    V, F = icosphere(2)
    V = V * [1.5, 1.0, 0.7] + [0.3, 0.1, -0.2]
    M = V * [-1.0, 1.0, 1.0]
    assert signed_volume(V, F) > 0 > signed_volume(M, F)
    grid = Grid.covering(M.min(0), M.max(0), 11, padding=0.3)
    Q = grid.points() + np.array([0.0123, -0.0071, 0.0047])
    g = signed_distance(M, F[:, ::-1], Q).value
    ev = SDFEnergy(F, Q, g, grid.cell_volume, sign=sign).evaluate(M)
    assert ev.energy > 0
    inner = g < -0.05
    assert inner.sum() > 20
    np.testing.assert_allclose(ev.residual[inner], -2.0 * g[inner], rtol=1e-9, atol=1e-9)
    assert SDFEnergy(F[:, ::-1], Q, g, grid.cell_volume, sign=sign).evaluate(M).energy < 1e-20
    # without `oriented`, ray parity is blind to the orientation (what the energy used to see)
    np.testing.assert_allclose(signed_distance(M, F, Q).value, g, rtol=0, atol=1e-12)


def test_vertex_gradient_matches_finite_differences(lumpy_sphere, rng):
    V, F = lumpy_sphere
    target = V * [1.15, 0.9, 1.0] + [0.05, 0.0, -0.03]
    E = _energy_for(V, F, target)
    ev = E.evaluate(V)
    h = 1e-6
    for _ in range(6):
        D = rng.standard_normal(V.shape)
        D /= np.linalg.norm(D)
        fd = (E.evaluate(V + h * D).energy - E.evaluate(V - h * D).energy) / (2 * h)
        an = float(np.sum(ev.gradient * D))
        assert an == pytest.approx(fd, rel=2e-3, abs=1e-6 * np.abs(ev.gradient).sum())


def test_unsigned_gradient_matches_finite_differences(rng):
    # an open cap matched by unsigned distances (source_sign="unsigned"): |f| against |g|;
    # an ellipsoid's cap, so that no node lies on the medial axis of a sphere's rim
    V, F = icosphere(3)
    V = V * [1.3, 0.9, 0.8]
    used, cap = np.unique(F[V[F].mean(axis=1)[:, 2] > 0.1], return_inverse=True)
    V, cap = V[used], cap.reshape(-1, 3)
    target = V * [1.15, 0.9, 1.0] + [0.05, 0.0, -0.03]
    grid = Grid.covering(target.min(0), target.max(0), 11, padding=0.3)
    Q = grid.points() + np.array([0.0123, -0.0071, 0.0047])
    g = signed_distance(target, cap[:, ::-1], Q, sign="unsigned").value  # either side: the same
    np.testing.assert_allclose(g, signed_distance(target, cap, Q, sign="unsigned").value, atol=1e-12)
    E = SDFEnergy(cap, Q, g, grid.cell_volume, sign="unsigned")
    ev = E.evaluate(V)
    assert ev.energy > 0 and E.evaluate(target).energy < 1e-20
    h = 1e-7  # a rim's closest-feature switches lie closer together than a closed surface's
    for _ in range(6):
        D = rng.standard_normal(V.shape)
        D /= np.linalg.norm(D)
        fd = (E.evaluate(V + h * D).energy - E.evaluate(V - h * D).energy) / (2 * h)
        an = float(np.sum(ev.gradient * D))
        assert an == pytest.approx(fd, rel=2e-3, abs=1e-6 * np.abs(ev.gradient).sum())


def test_subspace_gradient_matches_finite_differences(lumpy_sphere, rng):
    V, F = lumpy_sphere
    target = V * [0.9, 1.1, 1.05]
    E = _energy_for(V, F, target)
    W, _ = skinning_eigenmodes(V, F, 4)
    basis = LBSBasis(V, W)
    T = 0.01 * rng.standard_normal((4, 3, 4))
    ev = E.evaluate(basis.deform(T))
    grad_T = basis.pullback(ev.gradient, 4)  # B^T dE/dx (Algorithm 1)
    h = 1e-6
    for _ in range(6):
        D = rng.standard_normal(T.shape)
        D /= np.linalg.norm(D)
        fd = (E.evaluate(basis.deform(T + h * D)).energy - E.evaluate(basis.deform(T - h * D)).energy) / (2 * h)
        an = float(np.sum(grad_T * D))
        assert an == pytest.approx(fd, rel=2e-3, abs=1e-6 * np.abs(grad_T).sum())


def test_gradient_is_zero_at_exact_match():
    V, F = icosphere(2)
    E = _energy_for(V, F, V)
    ev = E.evaluate(V)
    assert ev.energy < 1e-20
    assert np.abs(ev.gradient).max() < 1e-10
