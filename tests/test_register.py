"""Synthetic recovery with known answers, monotone energy, untouched inputs, real data."""

import numpy as np
import pytest

import morphmodes_vol as mm
from morphmodes_vol.primitives import affine, bend, capsule, icosphere
from morphmodes_vol.register import ground_truth_error


def lumpy_ellipsoid():
    V, F = icosphere(2)
    V = V * [1.0, 0.65, 0.45]
    r = 1.0 + 0.2 * np.sin(3 * V[:, 0] + 0.5) * np.cos(2 * V[:, 1]) + 0.15 * V[:, 2] + 0.1 * V[:, 0]
    return V * r[:, None], F


def flat_capsule():
    V, F = capsule(height=1.0, radius=0.25, count=(16, 16))
    return V * [1.0, 0.6, 1.0], F


def test_ground_truth_error_by_hand():
    truth = np.array([[0.0, 0, 0], [3, 4, 0], [0, 0, 0], [0, 0, 0]])  # diagonal 5
    reg = truth + [[1.0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0]]
    assert ground_truth_error(reg, truth) == pytest.approx(0.25 / 5)
    with pytest.raises(ValueError):
        ground_truth_error(reg[:3], truth)


def test_recovers_known_affine_map():
    V, F = lumpy_ellipsoid()
    th = np.deg2rad(12)
    R = np.array([[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0], [0, 0, 1]])
    A = R @ np.diag([1.1, 0.95, 1.05])
    A[0, 2] += 0.05
    target = affine(V, A, [0.08, -0.05, 0.03])
    result = mm.register((V, F), (target, F), grid=24, ground_truth=target)
    assert result.metrics["identity_error"] > 0.05
    assert result.metrics["ground_truth_error"] < 0.01  # below 1% of the diagonal


def test_recovers_smooth_bend_and_energy_never_increases():
    V, F = flat_capsule()
    target = bend(V * [1, 1, 1.1], np.deg2rad(60))
    V_in, F_in, T_in = V.copy(), F.copy(), target.copy()
    # Algorithm 1 alone (the warped pass's result has its own history)
    result = mm.register((V, F), (target, F), grid=24, modes=10, ground_truth=target, warped_pass=False)
    m = result.metrics
    assert m["ground_truth_error"] <= m["identity_error"] / 3
    assert m["final_sdf_rms"] < 0.2 * m["initial_sdf_rms"]
    # accepted steps never increase E (the quadrature is set once, by the target)
    steps = np.diff(np.asarray(result.history.energy))
    assert steps.size > 10 and np.all(steps <= 0)
    assert len(result.history.stage_starts) == result.modes == 10
    # inputs untouched
    np.testing.assert_array_equal(V, V_in)
    np.testing.assert_array_equal(F, F_in)
    np.testing.assert_array_equal(target, T_in)
    # result in the original frame, same order and faces
    assert result.vertices.shape == V.shape
    np.testing.assert_array_equal(result.faces, F)
    # correspondence: barycentric points on the target lie close to the registered vertices
    p = np.einsum("kc,kcd->kd", result.correspondence_barycentrics, target[F[result.correspondence_faces]])
    assert np.linalg.norm(p - result.vertices, axis=1).mean() < 0.02 * np.linalg.norm(np.ptp(target, 0))


def test_result_is_in_the_original_frame_whatever_the_units():
    V, F = lumpy_ellipsoid()
    target = V * 1.1 + [0.05, 0, 0]
    small = mm.register((V, F), (target, F), grid=16, modes=2)
    big = mm.register((V * 1000 + 5e5, F), (target * 1000 + 5e5, F), grid=16, modes=2)
    np.testing.assert_allclose(big.vertices, small.vertices * 1000 + 5e5, rtol=0, atol=1e-6 * 1000)
    # the dense map does not suffer from float32 searches at large coordinates
    np.testing.assert_array_equal(big.correspondence_faces, small.correspondence_faces)
    np.testing.assert_allclose(big.correspondence_barycentrics, small.correspondence_barycentrics, atol=1e-6)


def test_same_seed_same_result():
    V, F = flat_capsule()
    target = V * [1.1, 1, 1]
    a = mm.register((V, F), (target, F), grid=16, modes=3)
    b = mm.register((V, F), (target, F), grid=16, modes=3)
    np.testing.assert_array_equal(a.vertices, b.vertices)


def test_one_call_and_object_agree_and_options_are_checked():
    V, F = flat_capsule()
    opts = mm.RegistrationOptions(grid=16, modes=2)
    reg = mm.Registration((V, F), (V * 1.05, F), opts)
    r1 = reg.run()
    r2 = mm.register((V, F), (V * 1.05, F), opts)
    np.testing.assert_array_equal(r1.vertices, r2.vertices)
    with pytest.raises(mm.OptionError):
        mm.register((V, F), (V, F), grid=16, modes=10**6)
    with pytest.raises(mm.OptionError, match="exceeds the source"):
        mm.register((V, F), (V, F), grid=16, modes=len(V) + 1)
    with pytest.raises(mm.OptionError):
        mm.register((V, F), (V, F), not_an_option=3)


@pytest.mark.parametrize("optimizer", ["paper", "lm"])
def test_iteration_caps_and_stage_bookkeeping(optimizer):
    V, F = flat_capsule()
    target = bend(V, np.deg2rad(40))
    caps = dict(max_iterations_per_stage=5, lm_iterations_per_stage=5, lm_stall_decrease=0.0,
                warped_pass=False)  # one run: its bookkeeping
    r = mm.register((V, F), (target, F), grid=16, modes=6, max_iterations=10, optimizer=optimizer,
                    stall_start=1e-9, stall_end=1e-9, initialization="none", **caps)
    h = r.history
    assert r.status == "max_iterations"
    assert r.modes == 2 and r.T.shape == (2, 3, 4)  # no empty third mode
    assert h.stage_starts == [0, 5] and h.stage_ends == ["iteration_cap", "iteration_cap"]
    assert len(h.step_rms) == 10 and h.modes == [1] * 5 + [2] * 5
    assert len(h.stage_seconds) == 2 and sum(h.stage_evaluations) + 1 == h.evaluations
    r = mm.register((V, F), (target, F), grid=16, modes=2, max_iterations_per_stage=3,
                    lm_iterations_per_stage=3, lm_stall_decrease=0.0, optimizer=optimizer,
                    stall_start=1e-9, stall_end=1e-9, initialization="none", warped_pass=False)
    assert r.status == "stage_cap" and r.modes == 2


def test_last_stage_has_its_own_step_cap():
    """``lm_final_iterations``: one step per stage, then up to 4 in the last (all taken: the
    stall tests are off); ``None`` keeps the last stage at ``lm_iterations_per_stage``."""
    V, F = flat_capsule()
    target = bend(V, np.deg2rad(40))
    common = dict(grid=16, modes=3, lm_iterations_per_stage=1, lm_stall_decrease=0.0,
                  stall_start=1e-12, stall_end=1e-12, initialization="none", warped_pass=False)
    r = mm.register((V, F), (target, F), lm_final_iterations=4, **common)
    assert r.history.stage_starts == [0, 1, 2] and r.history.modes == [1, 2, 3, 3, 3, 3]
    assert r.history.stage_ends == ["iteration_cap"] * 3 and r.status == "stage_cap"
    r = mm.register((V, F), (target, F), **common)
    assert r.history.modes == [1, 2, 3]
    with pytest.raises(mm.OptionError, match="lm_final_iterations"):
        mm.RegistrationOptions(lm_final_iterations=0)


def test_paper_plain_gradient_step_also_descends():
    V, F = flat_capsule()
    target = V * [1.1, 1.0, 1.05]
    r = mm.register((V, F), (target, F), grid=16, modes=3, optimizer="paper", quadrature="full",
                    preconditioner="none", ground_truth=target)
    assert r.history.energy[-1] < 0.5 * r.history.energy[0]
    assert np.all(np.diff(r.history.energy) <= 0)


def test_stl_soup_source_does_not_tear(tmp_path):
    import trimesh

    V, F = flat_capsule()
    path = tmp_path / "src.stl"
    trimesh.Trimesh(V, F, process=False).export(path)
    Vs, Fs = mm.load_mesh(path)
    assert len(Vs) == 3 * len(F)  # STL: a soup
    target = bend(V, np.deg2rad(40))
    r = mm.register(path, (target, F), grid=16, modes=6)
    key = np.round(Vs, 6)
    _, inverse = np.unique(key, axis=0, return_inverse=True)
    # copies of one input vertex end up at the same place
    spread = max(np.ptp(r.vertices[inverse.ravel() == k], axis=0).max() for k in range(inverse.max() + 1))
    assert spread < 1e-9


@pytest.mark.realdata
@pytest.mark.slow
def test_lion_reference_onto_lion_01_halves_the_error(data_dir):
    src = data_dir / "lion-poses" / "lion-reference.obj"
    tgt = data_dir / "lion-poses" / "lion-01.obj"
    result = mm.register(src, tgt, ground_truth=tgt)
    assert result.metrics["ground_truth_error"] < 0.5 * result.metrics["identity_error"]


@pytest.mark.realdata
@pytest.mark.slow
def test_lion_reference_onto_lion_05_large_turn_is_registered(data_dir):
    """The pose the paper's start gets wrong (the lion rears up, turning by ~70 degrees): the
    default's initial alignment and two starts bring it below a third of the identity error
    (measured 0.098 against 0.39; 0.31 from the rest pose alone; 0.08-0.13 from alignments
    turned by 2 degrees, scripts/start_sensitivity.py)."""
    src = data_dir / "lion-poses" / "lion-reference.obj"
    tgt = data_dir / "lion-poses" / "lion-05.obj"
    result = mm.register(src, tgt, ground_truth=tgt)
    # a start of the initialization (0.011; 0.017 without), not the rest pose, before the
    # hops: the aligned one or, when that is a rotated start, the unrotated one
    # (docs/decisions/0010-no-orientation-prior.md)
    assert result.metrics["warped_pass"]["kept_before_hops"].removeprefix("warped: ") in ("aligned", "unrotated")
    assert result.metrics["ground_truth_error"] < result.metrics["identity_error"] / 3
