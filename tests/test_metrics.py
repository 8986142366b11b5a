"""Metrics (morphmodes_vol.metrics): hand-computed cases and identities on generated meshes."""

import numpy as np
import pytest
import trimesh

from morphmodes_vol import metrics
from morphmodes_vol.primitives import icosphere


def unit_square(z=0.0, size=1.0):
    V = np.array([[0, 0, z], [size, 0, z], [size, size, z], [0, size, z]], dtype=float)
    F = np.array([[0, 1, 2], [0, 2, 3]])
    return V, F


def test_ground_truth_error_is_reexported_and_by_hand():
    import morphmodes_vol as mm
    from morphmodes_vol.register import ground_truth_error

    assert mm.ground_truth_error is metrics.ground_truth_error is ground_truth_error
    truth = np.array([[0.0, 0, 0], [3, 4, 0]])  # diagonal 5
    assert metrics.ground_truth_error(truth + [[0, 0, 1], [0, 2, 0]], truth) == pytest.approx(1.5 / 5)
    np.testing.assert_allclose(metrics.vertex_errors(truth + [[0, 0, 1], [0, 2, 0]], truth), [0.2, 0.4])


def test_surface_distance_parallel_squares_by_hand():
    V, F = unit_square()
    W, _ = unit_square(z=0.3)
    d = metrics.surface_distance(W, F, V, F)  # every vertex 0.3 from the other plane
    assert d["surface_mean"] == pytest.approx(0.3 / np.sqrt(2), abs=1e-6)
    assert d["surface_hausdorff"] == pytest.approx(0.3 / np.sqrt(2), abs=1e-6)


def test_surface_distance_is_symmetric_mean_of_one_sided_means():
    V, F = unit_square()  # target
    S, _ = unit_square(size=0.5)  # source: a quarter of it, in its plane
    d = metrics.surface_distance(S, F, V, F)
    # source -> target: 0 everywhere; target corners -> source: 0, 0.5, 0.5, sqrt(0.5)
    one_sided = (0 + 0.5 + 0.5 + np.sqrt(0.5)) / 4
    assert d["surface_mean"] == pytest.approx(0.5 * one_sided / np.sqrt(2), abs=1e-6)
    assert d["surface_hausdorff"] == pytest.approx(np.sqrt(0.5) / np.sqrt(2), abs=1e-6)


def test_sdf_residual_of_concentric_spheres():
    V, F = icosphere(4)
    Q = np.array([[2.0, 0, 0], [0, 3.0, 0], [0, 0, -2.5], [0.2, 0.1, 0.0]])
    g = np.linalg.norm(Q, axis=1) - 1.2  # sphere of radius 1.2, negative inside
    # f is the unit sphere's distance: f - g = 0.2 everywhere (up to the mesh's chord error)
    assert metrics.sdf_residual(V, F, Q, g) == pytest.approx(0.2, abs=5e-3)
    assert metrics.sdf_residual(V, F, Q, np.linalg.norm(Q, axis=1) - 1.0) < 5e-3


def test_areas_and_volume_by_hand():
    box = trimesh.creation.box(extents=(1, 2, 3))
    assert metrics.signed_volume(box.vertices, box.faces) == pytest.approx(6.0)
    assert metrics.signed_volume(box.vertices, box.faces[:, ::-1]) == pytest.approx(-6.0)
    assert metrics.signed_volume(box.vertices + [3.0, -2.0, 5.0], box.faces) == pytest.approx(6.0)  # any origin
    assert metrics.triangle_areas(box.vertices, box.faces).sum() == pytest.approx(2 * (2 + 3 + 6))


def test_best_affine_fit_recovers_affine_map(rng):
    X0 = rng.standard_normal((30, 3))
    A = rng.standard_normal((3, 3))
    t = rng.standard_normal(3)
    A_fit, t_fit = metrics.best_affine_fit(X0, X0 @ A.T + t)
    np.testing.assert_allclose(A_fit, A, atol=1e-10)
    np.testing.assert_allclose(t_fit, t, atol=1e-10)


def test_degeneracy_of_affine_maps_counts_nothing(sphere):
    V, F = sphere
    assert metrics.degeneracy(V, V, F) == {"collapsed_fraction": 0.0, "flipped_fraction": 0.0, "volume_ratio": pytest.approx(1.0)}
    # a reflection with stretch: normals follow the cofactor, so no flip; volume scales by det
    A = np.diag([-1.0, 2.0, 1.0])
    d = metrics.degeneracy(V, V @ A.T + [1, 2, 3], F)
    assert d["collapsed_fraction"] == 0 and d["flipped_fraction"] == 0
    assert d["volume_ratio"] == pytest.approx(-2.0)


def test_degeneracy_edge_collapse_and_pushed_through_vertex():
    V, F = icosphere(1)  # 42 vertices, 80 faces; vertex 0 has valence 5
    ring = np.unique(F[np.any(F == 0, axis=1)])
    a = int(ring[ring != 0][0])
    X = V.copy()
    X[0] = V[a]  # collapse the edge (0, a): the 2 triangles sharing it have zero area
    d = metrics.degeneracy(V, X, F)
    assert d["collapsed_fraction"] == pytest.approx(2 / 80)
    assert d["flipped_fraction"] == 0


def test_degeneracy_vertex_dragged_across_its_fan_flips_two_triangles():
    # 3x3 grid in the plane z = 0, every square split through the centre vertex 4: its fan
    # has 8 triangles, whose opposite edges are the halves of the outer square's sides
    V = np.array([[x, y, 0.0] for y in range(3) for x in range(3)])
    ring = [0, 1, 2, 5, 8, 7, 6, 3]
    F = np.array([[4, ring[k], ring[(k + 1) % 8]] for k in range(8)])
    X = V.copy()
    X[4] = [2.5, 1.0, 0.0]  # crosses the line x = 2: the 2 triangles on that side flip
    d = metrics.degeneracy(V, X, F)
    assert d["flipped_fraction"] == pytest.approx(2 / 8)
    assert d["collapsed_fraction"] == 0
    assert np.isnan(d["volume_ratio"])  # a flat mesh encloses no volume


def test_shape_metrics_keys_and_identity(sphere):
    V, F = sphere
    m = metrics.shape_metrics(V, V, F, V, F, truth=V)
    assert m["ground_truth_error"] == 0
    assert m["surface_mean"] < 1e-6 and m["surface_hausdorff"] < 1e-6
    assert set(m) == {"surface_mean", "surface_hausdorff", "collapsed_fraction", "flipped_fraction",
                      "volume_ratio", "ground_truth_error"}
