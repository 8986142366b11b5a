"""Baselines (morphmodes_vol.baselines) and the initial_modes option, on generated meshes."""

import numpy as np
import pytest

import morphmodes_vol as mm
from morphmodes_vol.baselines import fixed_subspace, full_space_sdf, nricp, prepare_pair, rigid_icp
from morphmodes_vol.baselines.full_space import DirichletSDFEnergy
from morphmodes_vol.errors import OptionError
from morphmodes_vol.primitives import affine, capsule

OPTS = mm.RegistrationOptions(grid=16)
METRIC_KEYS = {"final_sdf_rms", "surface_mean", "surface_hausdorff", "collapsed_fraction",
               "flipped_fraction", "volume_ratio", "identity_error", "ground_truth_error"}


def rotation_x(degrees):
    a = np.deg2rad(degrees)
    return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])


def test_rigid_icp_recovers_a_small_rigid_motion(lumpy_sphere):
    V, F = lumpy_sphere
    target = affine(V, rotation_x(8), [0.03, -0.02, 0.01])
    V_in = V.copy()
    r = rigid_icp((V, F), (target, F), ground_truth=target, options=OPTS)
    assert r.method == "ricp" and r.vertices.shape == V.shape
    np.testing.assert_array_equal(r.faces, F)
    np.testing.assert_array_equal(V, V_in)  # input untouched
    assert r.metrics["identity_error"] > 0.02
    assert r.metrics["ground_truth_error"] < 1e-3
    assert METRIC_KEYS <= set(r.metrics)
    R = r.info["matrix"][:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)  # rigid, no scale
    assert np.linalg.det(R) > 0  # no reflection


def test_nricp_alone_and_after_rigid_icp_reduce_the_error():
    V, F = capsule(count=(10, 10))
    target = affine(V, np.diag([1.15, 1.0, 0.9]), [0.02, 0, 0])
    for rigid_first, name in ((False, "nricp"), (True, "ricp+nricp")):
        r = nricp((V, F), (target, F), rigid_first=rigid_first, ground_truth=target, options=OPTS)
        assert r.method == name and r.vertices.shape == V.shape
        assert r.metrics["ground_truth_error"] < 0.5 * r.metrics["identity_error"]
        assert ("matrix" in r.info) == rigid_first


def test_dirichlet_energy_by_hand(small_capsule):
    V, F = small_capsule
    pair = prepare_pair((V, F), (V * 1.1, F), OPTS)
    energy = DirichletSDFEnergy(pair, weight=2.0)
    e, g = energy.dirichlet(pair.X0 + [0.1, -0.2, 0.3])  # translations are in L's null space
    assert abs(e) < 1e-12 and np.abs(g).max() < 1e-10
    rng = np.random.default_rng(0)
    U = rng.standard_normal(pair.X0.shape) * 1e-2
    e, g = energy.dirichlet(pair.X0 + U)
    assert e == pytest.approx(0.5 * 2.0 * np.sum(U * (energy.L @ U)))
    np.testing.assert_allclose(g, 2.0 * (energy.L @ U))
    assert e > 0  # L is positive semidefinite and U is not constant


def test_full_space_descends_and_the_dirichlet_term_stiffens(small_capsule):
    V, F = small_capsule
    target = affine(V, np.diag([1.1, 0.95, 1.05]), [0.02, 0, 0])
    opts = OPTS.replace(max_iterations=15)
    pair = prepare_pair((V, F), (target, F), opts)
    free = full_space_sdf(None, None, options=opts, ground_truth=target, pair=pair)
    stiff = full_space_sdf(None, None, dirichlet=10.0, options=opts, ground_truth=target, pair=pair)
    assert free.method == "full" and stiff.method == "full+dirichlet"
    assert np.all(np.diff(free.info["energy"]) <= 0)  # Armijo: never increases
    assert free.info["final_energy"] < free.info["initial_energy"]
    X0 = pair.X0

    def dirichlet_of(r):
        U = pair.normalization.apply(r.vertices) - X0
        return float(np.sum(U * (DirichletSDFEnergy(pair, 1.0).L @ U)))

    assert dirichlet_of(stiff) < dirichlet_of(free)
    with pytest.raises(OptionError):
        full_space_sdf(None, None, dirichlet=-1.0, options=opts, pair=pair)


def test_fixed_subspace_is_one_stage_with_all_modes(small_capsule):
    V, F = small_capsule
    target = affine(V, np.diag([1.1, 0.95, 1.05]), [0.02, 0, 0])
    opts = OPTS.replace(max_iterations=6)
    r = fixed_subspace((V, F), (target, F), 3, options=opts, ground_truth=target)
    assert r.modes == 3 and len(r.history.stage_ends) == 1
    assert set(r.history.modes) == {3}
    # with one mode, the fixed subspace is the adaptive scheme's first stage
    one = fixed_subspace((V, F), (target, F), 1, options=opts)
    ref = mm.register((V, F), (target, F), opts.replace(modes=1, max_iterations_per_stage=6))
    np.testing.assert_array_equal(one.vertices, ref.vertices)


def test_initial_modes_option(small_capsule):
    with pytest.raises(OptionError):
        mm.RegistrationOptions(modes=3, initial_modes=4)
    with pytest.raises(OptionError):
        mm.RegistrationOptions(initial_modes=0)
    V, F = small_capsule
    r = mm.register((V, F), (V * 1.05, F), OPTS.replace(modes=4, initial_modes=2, max_iterations_per_stage=3))
    assert r.history.modes[0] == 2 and len(r.history.stage_ends) == 3
    # the coefficients at the end of each stage: one more mode each, the last is the result
    shapes = [T.shape for T in r.history.stage_coefficients]
    assert shapes == [(2, 3, 4), (3, 3, 4), (4, 3, 4)]
    np.testing.assert_array_equal(r.history.stage_coefficients[-1], r.T)


@pytest.mark.realdata
@pytest.mark.slow
def test_ricp_nricp_on_a_lion_pose(data_dir):
    src = data_dir / "lion-poses" / "lion-reference.obj"
    tgt = data_dir / "lion-poses" / "lion-01.obj"
    r = nricp(src, tgt, rigid_first=True, ground_truth=tgt, options=mm.RegistrationOptions(grid=16))
    m = r.metrics
    assert m["ground_truth_error"] < 0.75 * m["identity_error"]
    assert m["surface_mean"] < 0.05 and 0 < m["volume_ratio"] < 2
