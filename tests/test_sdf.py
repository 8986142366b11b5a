"""SDF: hand-computed closest points, trilinear identities, grid SDF of a sphere vs analytic."""

import numpy as np
import pytest

from morphmodes_vol.errors import OptionError
from morphmodes_vol.options import RegistrationOptions
from morphmodes_vol.primitives import icosphere
from morphmodes_vol.sdf.source import resolve_sign
from morphmodes_vol.sdf import (
    DenseTargetSDF,
    Grid,
    closest_point_barycentrics,
    closest_points,
    inside,
    signed_distance,
    trilinear_sample,
)

A, B, C = np.array([0.0, 0, 0]), np.array([1.0, 0, 0]), np.array([0.0, 1, 0])


@pytest.mark.parametrize(
    "p, expected",
    [
        ([0.2, 0.3, 0.7], [0.5, 0.2, 0.3]),  # above the interior
        ([-1.0, -1.0, 0.5], [1, 0, 0]),  # vertex region A
        ([2.0, -0.5, 0.0], [0, 1, 0]),  # vertex region B
        ([-0.3, 2.0, 0.1], [0, 0, 1]),  # vertex region C
        ([0.5, -1.0, 0.0], [0.5, 0.5, 0]),  # edge AB
        ([-1.0, 0.25, 0.0], [0.75, 0, 0.25]),  # edge AC
        ([1.0, 1.0, 0.0], [0, 0.5, 0.5]),  # edge BC
    ],
)
def test_closest_point_regions_by_hand(p, expected):
    b = closest_point_barycentrics(np.array([p]), A[None], B[None], C[None])
    np.testing.assert_allclose(b[0], expected, atol=1e-12)


def test_closest_point_is_closest_among_samples(rng):
    P = rng.standard_normal((200, 3))
    tri = rng.standard_normal((200, 3, 3))
    b = closest_point_barycentrics(P, tri[:, 0], tri[:, 1], tri[:, 2])
    assert np.all(b >= -1e-12) and np.allclose(b.sum(1), 1)
    best = np.linalg.norm(P - np.einsum("kc,kcd->kd", b, tri), axis=1)
    # compare with a dense sampling of each triangle
    u, v = np.meshgrid(np.linspace(0, 1, 41), np.linspace(0, 1, 41))
    keep = (u + v) <= 1
    S = np.stack([1 - u[keep] - v[keep], u[keep], v[keep]], 1)  # (s, 3)
    pts = np.einsum("sc,kcd->ksd", S, tri)
    sampled = np.linalg.norm(pts - P[:, None], axis=2).min(1)
    assert np.all(best <= sampled + 1e-12)


def test_trilinear_reproduces_linear_field_exactly(rng):
    grid = Grid.covering([-1, -0.5, 0], [1, 0.5, 2], 9)
    a, c = rng.standard_normal(3), 0.7
    vals = (grid.points() @ a + c).reshape(grid.shape)
    P = grid.origin + rng.random((500, 3)) * (np.array(grid.shape) - 1) * grid.spacing
    np.testing.assert_allclose(trilinear_sample(vals, grid, P), P @ a + c, atol=1e-12)
    # at the nodes it returns the node values
    np.testing.assert_allclose(trilinear_sample(vals, grid, grid.points()), vals.ravel(), atol=1e-12)


def test_grid_covering_shape_and_spacing():
    g = Grid.covering([0, 0, 0], [2, 1, 0.5], 5, padding=0.0)
    assert g.spacing == pytest.approx(0.5)
    assert g.shape == (5, 3, 2)
    assert g.points().shape == (30, 3)
    with pytest.raises(ValueError):
        Grid.covering([0, 0, 0], [1, 1, 1], 1)


@pytest.mark.parametrize("sign", ["raycast", "winding"])
def test_grid_sdf_of_sphere_matches_analytic(sign):
    V, F = icosphere(4)  # max chord error of the polyhedral sphere is ~3e-3
    grid = Grid.covering([-1.5] * 3, [1.5] * 3, 24)
    sdf = DenseTargetSDF.from_mesh(V, F, grid, sign=sign)
    P = np.random.default_rng(1).uniform(-1.4, 1.4, (2000, 3))
    exact = np.linalg.norm(P, axis=1) - 1.0
    err = np.abs(sdf.sample(P) - exact)
    # trilinear interpolation of |x| - 1: error within a grid spacing (and tiny away from 0)
    assert err.max() < grid.spacing
    assert np.median(err) < 0.1 * grid.spacing


def test_signed_distance_sign_and_normal():
    V, F = icosphere(3)
    Q = np.array([[0.1, 0.2, -0.1], [0.0, 0.0, 2.0], [1.5, 0.0, 0.0]])
    q = signed_distance(V, F, Q)
    assert q.value[0] < 0 and q.value[1] > 0
    np.testing.assert_allclose(q.value[1:], [1.0, 0.5], atol=5e-3)
    np.testing.assert_allclose(q.normal[1], [0, 0, 1], atol=1e-2)  # outward
    np.testing.assert_allclose(q.normal[2], [1, 0, 0], atol=1e-2)
    cp = closest_points(V, F, Q)
    np.testing.assert_allclose(
        cp.points, np.einsum("kc,kcd->kd", cp.barycentrics, V[F[cp.faces]]), atol=1e-14
    )
    assert inside(V, F, Q, "winding").tolist() == [True, False, False]
    with pytest.raises(ValueError):
        inside(V, F, Q, "parity")


def test_unsigned_distance_of_an_open_cap_by_hand():
    # the upper half of a sphere: no inside; the distance is the same seen from either side
    # and whichever way its triangles turn, and its gradient points away from the surface
    V, F = icosphere(3)
    cap = F[V[F].mean(axis=1)[:, 2] > 0]
    Q = np.array([[0.0, 0, 0.5], [0.0, 0, 1.5], [0.0, 0, -1.0]])
    for faces in (cap, cap[:, ::-1]):
        q = signed_distance(V, faces, Q, sign="unsigned")
        np.testing.assert_allclose(q.value, [0.5, 0.5, np.sqrt(2)], atol=5e-3)  # the last to the rim
        np.testing.assert_allclose(q.normal[:2], [[0, 0, -1], [0, 0, 1]], atol=0.1)  # facets
    assert resolve_sign(cap, "unsigned") == "unsigned"
    with pytest.raises(ValueError, match="inside test"):
        inside(V, cap, Q, "unsigned")
    # a source may be matched unsigned; a target's field is always signed
    assert RegistrationOptions(source_sign="unsigned").source_sign == "unsigned"
    with pytest.raises(OptionError, match="target_sign"):
        RegistrationOptions(target_sign="unsigned")
