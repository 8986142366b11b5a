"""The target variants of the robustness study (:mod:`morphmodes_vol.variants`): the same
surface, other triangles, noise, a partial view."""

import numpy as np
import pytest

from morphmodes_vol.metrics import triangle_areas
from morphmodes_vol.primitives import capsule, icosphere
from morphmodes_vol.variants import (VARIANTS, densified, half_view_direction, jittered, noisy, partial_view,
                                     retriangulated, target_variant)


def test_jitter_is_seeded_and_of_the_stated_size():
    V, _ = icosphere(2)
    diagonal = np.linalg.norm(V.max(0) - V.min(0))
    a, b = jittered(V, 1e-3, seed=1), jittered(V, 1e-3, seed=1)
    np.testing.assert_array_equal(a, b)
    assert np.std(a - V) == pytest.approx(1e-3 * diagonal, rel=0.1)
    np.testing.assert_array_equal(jittered(V, 1e-3, seed=0), V)  # copy 0 is the mesh itself


def test_densified_keeps_the_surface_and_splits_each_face_into_16():
    V, F = icosphere(1)
    Vd, Fd = densified(V, F, 16)
    assert len(Fd) == 16 * len(F)
    assert triangle_areas(Vd, Fd).sum() == pytest.approx(triangle_areas(V, F).sum(), rel=1e-12)
    with pytest.raises(ValueError, match="power of 4"):
        densified(V, F, 8)


def test_retriangulated_keeps_about_the_surface_with_a_quarter_of_the_faces():
    V, F = icosphere(4)
    Vr, Fr = retriangulated(V, F, 0.25)
    assert abs(len(Fr) - len(F) / 4) <= 2
    assert np.abs(np.linalg.norm(Vr, axis=1) - 1).max() < 0.02  # still on the unit sphere


def test_noise_moves_vertices_along_their_normals_only():
    V, F = icosphere(3)
    Vn, Fn = noisy(V, F, 1e-2, seed=3)
    np.testing.assert_array_equal(Fn, F)
    d = Vn - V
    radial = np.sum(d * V, axis=1)  # the unit sphere's normal at V is V (nearly, for the mesh)
    assert np.linalg.norm(d - radial[:, None] * V, axis=1).max() < 0.1 * np.abs(radial).max()
    assert np.std(radial) == pytest.approx(1e-2 * np.linalg.norm(V.max(0) - V.min(0)), rel=0.15)


def test_partial_view_keeps_the_faces_that_face_the_view_about_half():
    V, F = capsule(height=2.0, radius=0.3, count=(16, 16))
    d = half_view_direction(V, F)
    Vp, Fp = partial_view(V, F)
    assert 0.35 < triangle_areas(Vp, Fp).sum() / triangle_areas(V, F).sum() < 0.65
    n = np.cross(Vp[Fp[:, 1]] - Vp[Fp[:, 0]], Vp[Fp[:, 2]] - Vp[Fp[:, 0]])
    assert np.all(n @ d > 0) and Fp.max() == len(Vp) - 1
    assert abs(d[2]) < 0.5  # a side view of the capsule (long along z), not from its end


def test_every_variant_and_an_unknown_one():
    V, F = icosphere(2)
    for v in VARIANTS:
        W, G = target_variant(V, F, v)
        assert W.ndim == 2 and G.max() < len(W)
    with pytest.raises(ValueError, match="expected one of"):
        target_variant(V, F, "upside down")
    assert (target_variant(V, F, "no-bridges")[1] == F).all()  # a clean mesh has none
