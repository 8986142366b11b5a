"""The initialization stage (morphmodes_vol.initialize): hand-computed pieces, identities and
synthetic recovery of known rigid motions."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import morphmodes_vol as mm
from morphmodes_vol.initialize import (RigidSourceField, evaluate, motion_metric, rigid_jacobian,
                                       rodrigues, Similarity, align, candidate_rotations,
                                       icp_align, rotation_angle)
from morphmodes_vol.primitives import bend, capsule
from morphmodes_vol.sdf import Grid, signed_distance


def asymmetric_blob():
    """A tapered, flattened, bent capsule: no proper rotation maps it onto itself."""
    V, F = capsule(height=1.0, radius=0.2, count=(16, 20))
    s = (V[:, 2] - V[:, 2].min()) / np.ptp(V[:, 2])
    V = V * np.c_[1.0 + 0.9 * s, 0.6 + 0 * s, 1.0 + 0 * s]
    return bend(V, 1.2, axis=2, towards=0), F


def test_candidate_rotations_are_the_24_cube_rotations_then_principal_frames():
    R = candidate_rotations()
    assert R.shape == (24, 3, 3)
    assert np.allclose(R[0], np.eye(3))
    assert np.allclose(np.linalg.det(R), 1.0)
    # all distinct
    flat = np.round(R.reshape(24, 9)).astype(int)
    assert len({tuple(r) for r in flat}) == 24
    A = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()
    B = Rotation.from_euler("xyz", [-40, 5, 70], degrees=True).as_matrix()
    R = candidate_rotations(A, B)
    assert R.shape == (28, 3, 3)
    # each principal-frame candidate maps A's axes onto B's, up to sign
    for Rk in R[24:]:
        assert np.allclose(np.abs(Rk @ A), np.abs(B))
        assert np.isclose(np.linalg.det(Rk), 1.0)


def test_rodrigues_and_rotation_angle_match_scipy():
    w = np.array([0.3, -1.1, 0.4])
    assert np.allclose(rodrigues(w), Rotation.from_rotvec(w).as_matrix())
    assert np.isclose(rotation_angle(rodrigues(w)), np.degrees(np.linalg.norm(w)))
    assert np.allclose(rodrigues(np.zeros(3)), np.eye(3))


def test_motion_metric_is_the_mean_squared_vertex_displacement():
    rng = np.random.default_rng(0)
    c, x = rng.random(3), rng.random((5, 3))
    p = rng.standard_normal(7)
    w, t, s = p[:3], p[3:6], p[6]
    dx = np.cross(w, x - c) + s * (x - c) + t
    assert np.isclose(p @ motion_metric(x, c, True) @ p, np.mean(np.sum(dx**2, axis=1)))
    assert np.isclose(p[:6] @ motion_metric(x, c, False) @ p[:6],
                      np.mean(np.sum((dx - s * (x - c)) ** 2, axis=1)))


def test_rigid_source_field_is_the_moved_sources_signed_distance():
    X, F = asymmetric_blob()
    box = Grid.covering(X.min(0), X.max(0), 40, padding=0.6)
    field = RigidSourceField.from_mesh(X, F, box)
    assert field.nodes == box.size
    S = Similarity(rodrigues(np.array([0.3, -0.5, 0.8])), np.array([0.1, 0.0, -0.05]), 1.1)
    Y = S.apply(X)
    rng = np.random.default_rng(2)
    Q = Y.mean(0) + 0.5 * rng.standard_normal((400, 3)) * np.ptp(Y, 0)
    exact = signed_distance(Y, F, Q)
    ev = evaluate(field, S, Q, np.zeros(len(Q)), np.ones(len(Q)))
    P = (Q - S.t) @ S.R / S.scale  # the points in the source's rest frame
    hi = box.origin + box.spacing * (np.asarray(box.shape) - 1)
    near = np.all((P > box.origin + box.spacing) & (P < hi - box.spacing), axis=1)
    assert near.sum() > 300  # most points are inside the field's box
    # trilinear error of a distance field is O(h); normals agree where the field is smooth
    assert np.max(np.abs(ev.value[near] - exact.value[near])) < S.scale * box.spacing
    cos = np.sum(ev.normal[near] * exact.normal[near], axis=1) / np.linalg.norm(ev.normal[near], axis=1)
    assert np.median(cos) > 0.99
    assert np.allclose(ev.residual, ev.value) and np.isclose(ev.energy, ev.value @ ev.value)
    # outside the box the value grows with the distance to it
    far = evaluate(field, Similarity(np.eye(3), np.zeros(3)), np.array([[50.0, 0, 0]]),
                    np.zeros(1), np.ones(1))
    assert far.value[0] > 45.0


@pytest.mark.parametrize("similarity", [False, True])
def test_rigid_jacobian_matches_finite_differences(similarity):
    # a linear field f_0(x) = a.x + b: trilinear interpolation is exact, so is the Jacobian
    grid = Grid.covering([-3.0] * 3, [3.0] * 3, 7)
    a, b = np.array([0.3, -0.7, 0.5]), 0.2
    vals = grid.points() @ a + b
    values = np.concatenate([vals[:, None], np.broadcast_to(a, (grid.size, 3))], axis=1)
    field = RigidSourceField(grid, values.reshape(*grid.shape, 4))
    rng = np.random.default_rng(3)
    Q = rng.uniform(-1, 1, (20, 3))
    g = rng.standard_normal(20)
    w8 = np.ones(20)
    S = Similarity(rodrigues(np.array([0.2, 0.1, -0.3])), np.array([0.1, 0.2, 0.0]), 1.2)
    c = np.array([0.1, -0.2, 0.3])
    ev = evaluate(field, S, Q, g, w8)
    J = rigid_jacobian(ev, Q, c, similarity)
    assert J.shape == (20, 7 if similarity else 6)
    eps = 1e-6
    for k in range(J.shape[1]):
        p = np.zeros(7)
        p[k] = eps
        plus = evaluate(field, S.compose(p[:3], p[3:6], p[6], c), Q, g, w8).residual
        p[k] = -eps
        minus = evaluate(field, S.compose(p[:3], p[3:6], p[6], c), Q, g, w8).residual
        assert np.allclose((plus - minus) / (2 * eps), J[:, k], atol=1e-6)


def test_similarity_compose_applies_the_increment_exactly():
    rng = np.random.default_rng(1)
    X = rng.random((7, 3))
    S = Similarity(rodrigues(np.array([0.1, 0.2, 0.3])), np.array([0.5, 0, 0]), 1.2)
    w, t, s, c = np.array([0, 0.4, 0]), np.array([0, 0, 0.1]), 0.2, np.array([0.3, 0.3, 0.3])
    Y = S.apply(X)
    expected = np.exp(s) * (Y - c) @ rodrigues(w).T + c + t
    assert np.allclose(S.compose(w, t, s, c).apply(X), expected)


def _pair_grid(X, Y, res=28):
    lo, hi = np.minimum(X.min(0), Y.min(0)), np.maximum(X.max(0), Y.max(0))
    grid = Grid.covering(lo, hi, res, 0.1 * np.linalg.norm(hi - lo))
    return grid, grid.points()


def test_align_recovers_a_large_rotation_and_translation():
    X, F = asymmetric_blob()
    R = Rotation.from_rotvec(np.radians(120) * np.array([1, 1, 0]) / np.sqrt(2)).as_matrix()
    t = np.array([0.3, -0.2, 0.1])
    Y = X @ R.T + t
    grid, Q = _pair_grid(X, Y)
    g = signed_distance(Y, F, Q).value
    al = align(X, F, Q, g, grid.cell_volume, kind="rigid", keep=6)
    assert rotation_angle(al.rotation.T @ R) < 10.0
    assert np.sqrt(np.mean(np.sum((al.apply(X) - Y) ** 2, axis=1))) < 0.03 * np.linalg.norm(np.ptp(Y, 0))
    assert al.energy < 0.05 * al.rest_energy
    assert al.candidates == 29 and al.evaluations > al.candidates


def test_align_of_a_translated_copy_is_the_translation_and_similarity_finds_the_scale():
    X, F = asymmetric_blob()
    t = np.array([0.1, 0.05, -0.08])
    grid, Q = _pair_grid(X, X + t)
    g = signed_distance(X + t, F, Q).value
    al = align(X, F, Q, g, grid.cell_volume, kind="rigid", keep=1)
    assert rotation_angle(al.rotation) < 2.0
    assert np.allclose(al.apply(X), X + t, atol=0.01)
    c = X.mean(0)
    Y = 1.25 * (X - c) + c
    grid, Q = _pair_grid(X, Y)
    g = signed_distance(Y, F, Q).value
    sim = align(X, F, Q, g, grid.cell_volume, kind="similarity", keep=1)
    assert sim.scale == pytest.approx(1.25, rel=0.03)
    rigid = align(X, F, Q, g, grid.cell_volume, kind="rigid", keep=1)
    assert rigid.scale == 1.0 and sim.energy < 0.2 * rigid.energy


def test_a_symmetric_shape_keeps_the_unrotated_start():
    """A capsule turned about its axis, or end over end, is the same surface: the rotated
    starts tie with the unrotated one up to the grid's sampling, and the unrotated start is
    kept (its vertex map does not turn the shape) even where a rotated one is lower."""
    from morphmodes_vol.primitives import capsule

    X, F = capsule(count=(12, 16))
    Y = X + [0.05, -0.03, 0.02]
    grid, Q = _pair_grid(X, Y, res=20)
    g = signed_distance(Y, F, Q).value
    al = align(X, F, Q, g, grid.cell_volume, kind="rigid", keep=6)
    assert al.chosen == 0 and al.start_indices() == {"aligned": 0}  # one start, not two
    assert set(al.refined_energies) >= {0} and len(al.refined_energies) == 6
    assert np.allclose(al.apply(X), Y, atol=0.02)


def test_the_lowest_energy_start_wins_when_it_places_the_surface_elsewhere():
    """No prior for the unrotated start: a blob turned by 162 degrees is recovered from a
    rotated start whatever the ratio of the energies; the unrotated start goes on beside
    it, for Algorithm 1's runs to compare."""
    X, F = asymmetric_blob()
    R = Rotation.from_rotvec([0, 0, np.pi * 0.9]).as_matrix()
    Y = X @ R.T
    grid, Q = _pair_grid(X, Y)
    g = signed_distance(Y, F, Q).value
    al = align(X, F, Q, g, grid.cell_volume, kind="rigid", keep=4)
    assert al.chosen != 0 and al.refined_energies[al.chosen] < al.refined_energies[0]
    assert rotation_angle(al.rotation.T @ R) < 10.0
    assert al.start_indices() == {"aligned": al.chosen, "unrotated": 0}


@pytest.mark.parametrize("optimizer", ["paper", "lm"])
def test_registration_with_initialization_recovers_a_turned_target(optimizer):
    X, F = asymmetric_blob()
    R = Rotation.from_rotvec(np.radians(150) * np.array([0, 1, 0])).as_matrix()
    Y = bend(X, 0.4, axis=2, towards=0) @ R.T + [0.2, 0, 0]
    opts = mm.RegistrationOptions(grid=24, modes=3, optimizer=optimizer, max_iterations=200,
                                  quadrature="band" if optimizer == "lm" else "full",
                                  initialization="rigid")
    plain = mm.register((X, F), (Y, F), opts.replace(initialization="none"), ground_truth=Y)
    init = mm.register((X, F), (Y, F), opts.replace(initialization="rigid"), ground_truth=Y)
    assert plain.metrics["ground_truth_error"] > 0.1
    assert init.metrics["ground_truth_error"] < 0.3 * plain.metrics["ground_truth_error"]
    assert init.metrics["init_rotation_deg"] > 100
    assert "initialize" in init.timings


def test_initialization_options_are_checked():
    with pytest.raises(mm.OptionError):
        mm.RegistrationOptions(initialization="pca")
    with pytest.raises(TypeError, match="init_switch"):  # removed: see _chosen
        mm.RegistrationOptions(init_switch=0.6)
    with pytest.raises(mm.OptionError):
        mm.RegistrationOptions(init_candidates=0)
    with pytest.raises(mm.OptionError, match="coarse_starts"):
        mm.RegistrationOptions(coarse_starts=1)
    p = mm.RegistrationOptions.paper_faithful()
    assert p.initialization == "none" and p.optimizer == "paper" and p.quadrature == "full"
    assert not p.coarse_starts


def test_cli_initialization_setting_reaches_the_options_and_the_report(tmp_path, capsys):
    import json

    import trimesh

    from morphmodes_vol.cli import main

    X, F = asymmetric_blob()
    Y = X @ Rotation.from_rotvec([0, 0.6, 0]).as_matrix().T
    src, tgt = tmp_path / "src.obj", tmp_path / "tgt.obj"
    trimesh.Trimesh(X, F, process=False).export(src)
    trimesh.Trimesh(Y, F, process=False).export(tgt)
    code = main(["register", str(src), str(tgt), "-o", str(tmp_path / "out"), "--grid", "16",
                 "--modes", "2", "--set", "initialization=rigid", "-q"])
    assert code == 0
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["options"]["initialization"] == "rigid"
    assert report["metrics"]["init_rotation_deg"] > 20 and "initialize" in report["timings"]
    out = capsys.readouterr().out
    assert "initial alignment: rotation" in out
    assert f"kept: {report['metrics']['start']}" in out


def test_select_start_prefers_the_least_distorted_of_the_runs_that_fit():
    from morphmodes_vol.runs import StartRun, select_start

    a = StartRun("rest", None, 0.0, energy=1e-6, strain=0.5)
    b = StartRun("aligned", None, 0.0, energy=6e-6, strain=0.3)
    assert select_start([a, b], 10.0) is b           # fits within 10x: the less stretched wins
    assert select_start([a, b], 5.0) is a            # fits 6x worse: not eligible
    c = StartRun("aligned", None, 0.0, energy=float("nan"), strain=0.0)
    assert select_start([a, c], 10.0) is a           # a non-finite energy is never chosen


def test_the_starts_are_run_and_reported():
    """The rest pose, the aligned start and, when that turned the source, the unrotated
    alignment: each runs and is reported."""
    X, F = asymmetric_blob()
    Y = bend(X, 0.5, axis=2, towards=0)
    opts = mm.RegistrationOptions(grid=16, modes=2, optimizer="lm", quadrature="band",
                                  initialization="rigid", start_check_modes=99, warped_pass=False)
    reg = mm.Registration((X, F), (Y, F), opts)
    r = reg.run(ground_truth=Y)
    own = list(reg.initial_alignment().start_indices())
    assert own[0] == "aligned" and set(own) <= {"aligned", "unrotated"}
    starts = r.metrics["starts"]
    assert [s["start"] for s in starts] == ["rest", *own]
    assert r.metrics["start"] in ("rest", *own)
    assert r.evaluations == sum(s["evaluations"] for s in starts) > r.history.evaluations
    chosen = next(s for s in starts if s["start"] == r.metrics["start"])
    assert chosen["edge_strain"] == r.metrics["edge_strain"]
    assert "init_rotation_deg" in r.metrics
    one = mm.register((X, F), (Y, F), opts.replace(init_keep_rest=False))
    assert [s["start"] for s in one.metrics["starts"]] == own
    none = mm.register((X, F), (Y, F), opts.replace(initialization="none"))
    assert [s["start"] for s in none.metrics["starts"]] == ["rest"]


def test_source_field_resolution_is_capped_and_still_covers_the_box(monkeypatch):
    import morphmodes_vol.initialize as init

    X, F = asymmetric_blob()
    Q = np.random.default_rng(4).uniform(-1, 1, (50, 3))
    monkeypatch.setattr(init, "FIELD_MAX_RESOLUTION", 20)
    field = init.source_field(X, F, Q, 0.01, X.mean(0), np.zeros(3), 1.0, "raycast")
    assert max(field.grid.shape) == 20
    hi = field.grid.origin + field.grid.spacing * (np.asarray(field.grid.shape) - 1)
    assert np.all(field.grid.origin <= Q.min(0)) and np.all(hi >= Q.max(0))


def test_source_field_queries_only_the_nodes_the_alignment_samples():
    """The alignment's source field queries the nodes within two spacings of the ball the
    starts map the quadrature points into, or of the quadrature box; the grid's corners
    beyond both get the distance to the source's bounding sphere, a lower bound. Every
    point a start samples reads the same values as from the field queried everywhere."""
    import morphmodes_vol.initialize as init

    X, F = asymmetric_blob()
    R = Rotation.from_rotvec([0.3, -0.5, 0.9]).as_matrix()
    Y = X @ R.T + [0.4, -0.1, 0.2]
    grid, Q = _pair_grid(X, Y, res=20)
    cs, ct = X.mean(0), Y.mean(0)
    field = init.source_field(X, F, Q, grid.spacing, cs, ct, 1.0, "raycast")
    full = RigidSourceField.from_mesh(X, F, field.grid)
    assert full.nodes == field.grid.size and field.nodes < 0.8 * field.grid.size
    for rot in candidate_rotations():  # every start about the centroids
        P = (Q - ct) @ rot + cs  # R^T (q - t) with t = ct - R cs
        for a, b in zip(field.sample(P), full.sample(P)):
            np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(field.sample(Q)[0], full.sample(Q)[0])  # the rest pose
    # elsewhere: positive and at most the true distance
    d, true = field.values[..., 0].ravel(), full.values[..., 0].ravel()
    filled = d != true
    assert filled.sum() == field.grid.size - field.nodes
    assert np.all(d[filled] > 0) and np.all(d[filled] <= true[filled] + 1e-12)


def test_align_is_the_same_with_the_source_field_queried_everywhere(monkeypatch):
    import morphmodes_vol.initialize as init

    X, F = asymmetric_blob()
    R = Rotation.from_rotvec(np.radians(120) * np.array([1, 1, 0]) / np.sqrt(2)).as_matrix()
    Y = X @ R.T + [0.3, -0.2, 0.1]
    grid, Q = _pair_grid(X, Y)
    g = signed_distance(Y, F, Q).value
    masked = align(X, F, Q, g, grid.cell_volume, kind="rigid", keep=6)
    everywhere = RigidSourceField.from_mesh.__func__
    monkeypatch.setattr(init.RigidSourceField, "from_mesh",
                        classmethod(lambda cls, X0, F_, grid_, sign="raycast", near=None:
                                    everywhere(cls, X0, F_, grid_, sign)))
    full = align(X, F, Q, g, grid.cell_volume, kind="rigid", keep=6)
    np.testing.assert_array_equal(masked.matrix, full.matrix)
    assert masked.refined_energies == full.refined_energies and masked.evaluations == full.evaluations
    assert masked.field_nodes < full.field_nodes


def test_adaptive_run_stage_by_stage_is_optimize_adaptive():
    """Identity: advancing an AdaptiveRun one stage at a time is the one-call function."""
    from morphmodes_vol.optimize import AdaptiveRun, optimize_adaptive, single_threaded_blas

    X, F = asymmetric_blob()
    Y = bend(X, 0.5, axis=2, towards=0)
    reg = mm.Registration((X, F), (Y, F), mm.RegistrationOptions(grid=16, modes=3, initialization="none"))
    one = optimize_adaptive(reg.energy(), reg.basis, reg.options)
    with single_threaded_blas():
        run = AdaptiveRun(reg.energy(), reg.basis, reg.options)
        stages = []
        while not run.done:
            run.advance()
            stages.append(run.stage)
        out = run.result()
    assert stages == [1, 2, 3]
    np.testing.assert_array_equal(out.T, one.T)
    assert out.history.energy == one.history.energy
    assert out.history.evaluations == one.history.evaluations and out.status == one.status


def test_a_start_stops_early_when_merged_or_outstretched():
    """Hand-made run states: a copy of the other (merged), a stretched fit against a rigid
    one (outstretched), and the energy guard that keeps an unstretched run from winning
    when it does not fit."""
    from types import SimpleNamespace

    from morphmodes_vol.runs import StartRun

    X, F = asymmetric_blob()
    reg = mm.Registration((X, F), (X, F), mm.RegistrationOptions(grid=16, modes=4))
    X0 = reg.X0

    def start(label, V):
        return StartRun(label, None, 0.0, float("nan"), float("nan"), run=SimpleNamespace(vertices=V, stage=4))

    stretched = X0 * [1.0, 1.0, 1.6]  # strain 0.3-0.4 on the blob's edges along z
    near = X0 + 1e-3                   # a translation: unstretched, 1.7e-3 from X0 (RMS)
    # merged: within start_merge_distance; the more stretched one stops
    a, b = start("rest", X0 * 1.001), start("aligned", near)
    assert reg.runner.redundant(a, b) is a and a.stopped == 4 and a.reason == "merged"
    # outstretched: the fit (at the target) is rigid, the other stretched
    a, b = start("rest", stretched), start("aligned", near)
    assert reg.runner.redundant(a, b) is a and a.reason == "outstretched"
    assert np.isfinite(a.energy) and b.stopped is None
    # guard: the unstretched run is far from the target (objective > 10x the stretched one's)
    far = X0 + [0.0, 0.0, 0.3]
    fit = start("rest", X0 + 0.05 * (stretched - X0))
    assert reg.runner.redundant(fit, start("aligned", far)) is None
    # a ratio below start_strain_ratio (about 1.6 here), or the checks off
    mild = (start("rest", X0 * [1.0, 1.0, 1.1]), start("aligned", X0 * [1.0, 1.0, 1.06]))
    assert reg.runner.redundant(*mild) is None
    reg.options = reg.options.replace(start_strain_ratio=float("inf"), start_merge_distance=0.0)
    assert reg.runner.redundant(start("rest", stretched), start("aligned", near)) is None
    assert reg.runner.redundant(start("rest", X0), start("aligned", X0.copy())) is None
    # the choice at start_choice_modes: the least stretched run that fits is kept
    a, b = start("rest", stretched), start("aligned", near)
    assert reg.runner.choose_now([a, b]) is b and a.stopped == 4 and a.reason == "not chosen"
    assert np.isfinite(a.energy) and np.isfinite(b.energy) and b.strain < a.strain
    # ... and the guard: an unstretched run far from the target is not kept
    a, b = start("rest", fit.run.vertices), start("aligned", far)
    assert reg.runner.choose_now([a, b]) is a and b.reason == "not chosen" and a.stopped is None


def test_the_choice_between_starts_made_early_is_the_final_choice_at_that_stage():
    """With ``start_choice_modes=k`` the run kept is the one a registration with ``k``
    modes keeps, and only it goes on to ``modes``. (One stall threshold for every stage:
    the schedule decays over ``modes``, so the two would otherwise end stages apart.)"""
    X, F = asymmetric_blob()
    Y = bend(X, 0.4, axis=2, towards=0) + [0.05, 0.0, 0.0]
    opts = mm.RegistrationOptions(grid=16, modes=5, start_check_modes=99, warped_pass=False,
                                  stall_end=mm.RegistrationOptions().stall_start)
    short = mm.register((X, F), (Y, F), opts.replace(modes=3))
    r = mm.register((X, F), (Y, F), opts.replace(start_choice_modes=3))
    starts = {s["start"]: s for s in r.metrics["starts"]}
    short_starts = {s["start"]: s for s in short.metrics["starts"]}
    kept = short.metrics["start"]
    assert r.metrics["start"] == kept and starts[kept]["stopped_after_modes"] is None
    (other,) = set(starts) - {kept}
    assert starts[other]["stopped_after_modes"] == 3 and starts[other]["stop_reason"] == "not chosen"
    # the stopped run is the 3-mode run, judged by its full-grid objective there
    assert starts[other]["evaluations"] == short_starts[other]["evaluations"]
    np.testing.assert_allclose(starts[other]["energy"], short_starts[other]["energy"], rtol=1e-12)
    assert starts[kept]["evaluations"] > short_starts[kept]["evaluations"]
    assert r.history.modes[-1] == 5
    # at or above modes, the choice is made at the end, as by default
    late = mm.register((X, F), (Y, F), opts.replace(start_choice_modes=5))
    assert all(s["stopped_after_modes"] is None for s in late.metrics["starts"])


def test_two_starts_in_lockstep_stop_one_and_keep_the_other_run_unchanged():
    """A target that is the source translated: both starts reach the same answer, one stops
    as merged; the run that goes on is the same as without early stops."""
    X, F = asymmetric_blob()
    Y = bend(X, 0.4, axis=2, towards=0) + [0.05, 0.0, 0.0]
    opts = mm.RegistrationOptions(grid=16, modes=5, start_check_modes=2, start_merge_distance=0.02,
                                  warped_pass=False)
    events = []
    r = mm.register((X, F), (Y, F), opts, ground_truth=Y, progress=events.append)
    full = mm.register((X, F), (Y, F), opts.replace(start_check_modes=99), ground_truth=Y)
    starts = {s["start"]: s for s in r.metrics["starts"]}
    stopped = [s for s in starts.values() if s["stopped_after_modes"] is not None]
    assert len(stopped) == 1 and stopped[0]["stop_reason"] == "merged"
    assert stopped[0]["stopped_after_modes"] >= 2
    assert {e.start for e in events} == {"rest", "aligned"}
    kept = r.metrics["start"]
    assert starts[kept]["stopped_after_modes"] is None
    full_starts = {s["start"]: s for s in full.metrics["starts"]}
    assert all(s["stopped_after_modes"] is None for s in full_starts.values())
    assert starts[kept]["evaluations"] == full_starts[kept]["evaluations"]
    assert r.evaluations < full.evaluations
    if full.metrics["start"] == kept:
        np.testing.assert_array_equal(r.vertices, full.vertices)


def test_icp_align_is_trimeshs_icp_and_recovers_a_rigid_motion_and_a_scale():
    """Identity: the iteration of ``trimesh.registration.icp`` (closest points from Open3D
    instead of trimesh); known answers: a rigid motion and a similarity of the source."""
    import trimesh
    from trimesh.registration import icp

    X, F = asymmetric_blob()
    R = Rotation.from_rotvec([0.15, -0.25, 0.2]).as_matrix()
    t = np.array([0.05, -0.02, 0.03])
    # a bent copy, turned: the answer is no exact fit, so both must follow the same path
    Y = bend(X, 0.5, axis=2, towards=0) @ R.T + t
    ours = icp_align(X, Y, F)
    ref, _, cost = icp(X, trimesh.Trimesh(Y, F, process=False), max_iterations=100, threshold=1e-10,
                       reflection=False, scale=False, translation=True)
    np.testing.assert_allclose(ours.matrix, ref[:3], atol=2e-4)
    assert ours.cost == pytest.approx(cost, rel=1e-3) and ours.scale == pytest.approx(1.0)
    # known answers
    rigid = icp_align(X, X @ R.T + t, F)
    np.testing.assert_allclose(rigid.matrix, np.c_[R, t], atol=1e-4)
    assert rigid.cost < 1e-9 and rigid.apply(X) == pytest.approx(X @ R.T + t, abs=1e-4)
    # ICP converges linearly: a scale of 1.2 takes about 180 iterations
    similar = icp_align(X, 1.2 * X @ R.T + t, F, scale=True, max_iterations=300)
    assert similar.scale == pytest.approx(1.2, abs=1e-3)
    np.testing.assert_allclose(similar.matrix, np.c_[1.2 * R, t], atol=1e-3)
    with pytest.raises(ValueError, match="X must be"):
        icp_align(X[:2], Y, F)


def test_an_sdf_target_has_the_two_starts():
    """With the target given as an SDF: the rest pose and the SDF alignment."""
    from morphmodes_vol.sdf import DenseTargetSDF, Grid

    X, F = asymmetric_blob()
    Y = bend(X, 0.5, axis=2, towards=0)
    lo, hi = Y.min(0) - 0.3, Y.max(0) + 0.3
    sdf = DenseTargetSDF.from_mesh(Y, F, Grid.covering(lo, hi, 24))
    reg = mm.Registration((X, F), sdf, mm.RegistrationOptions(grid=16, modes=2, warped_pass=False))
    r = reg.run()
    assert [s["start"] for s in r.metrics["starts"]] == ["rest", "aligned"]


def test_coarse_energy_is_eq3_on_every_other_node():
    """Hand check of the coarse pass's objective (full quadrature, no prior): ``(2h)^3`` times
    the sum of squared residuals over every other node, the fine grid's target values
    subsampled."""
    from morphmodes_vol.quadrature import every_other_node

    X, F = asymmetric_blob()
    Y = bend(X, 0.5, axis=2, towards=0)
    reg = mm.Registration((X, F), (Y, F), mm.RegistrationOptions(grid=32, quadrature="full",
                                                                 isometry_weight=0.0))
    grid, idx = every_other_node(reg.quadrature)
    assert grid.cell_volume == pytest.approx(8 * reg.quadrature.cell_volume)
    f = signed_distance(reg.X0, reg.source_sdf_faces, reg.Q[idx]).value
    expected = grid.cell_volume * np.sum((f - reg.g[idx]) ** 2)
    assert reg.coarse_energy().evaluate(reg.X0).energy == pytest.approx(expected, rel=1e-12)


def test_the_coarse_pass_compares_running_starts_on_its_own_grid(monkeypatch):
    """The coarse pass judges its running starts by Eq. (3) on every other node (hand
    checked), a few times cheaper than the fine grid; a run that ends is judged on the fine
    grid, where the final choice is made."""
    from morphmodes_vol.quadrature import every_other_node

    X, F = asymmetric_blob()
    Y = bend(X, 0.5, axis=2, towards=0)
    reg = mm.Registration((X, F), (Y, F), mm.RegistrationOptions(
        grid=48, modes=3, start_choice_modes=2, start_check_modes=99, isometry_weight=0.0,
        warped_pass=False))
    grid, idx = every_other_node(reg.quadrature)
    f = signed_distance(reg.X0, reg.source_sdf_faces, reg.Q[idx]).value
    expected = grid.cell_volume * np.sum((f - reg.g[idx]) ** 2)
    assert reg.coarse_objective(reg.X0) == pytest.approx(expected, rel=1e-12)

    calls = []
    fine, coarse_grid = reg.objective, reg.coarse_objective
    monkeypatch.setattr(reg, "objective", lambda V: (calls.append("fine"), fine(V))[1])
    coarse = lambda V: (calls.append("coarse"), coarse_grid(V))[1]  # noqa: E731
    shifted = reg.start_coefficients(np.hstack([np.eye(3), [[0.02], [0.0], [0.0]]]))
    starts = [("rest", None, reg.options), ("shifted", shifted, reg.options)]
    runs = reg.runner.run(starts, None, reg.coarse_energy, coarse)
    # both judged on the coarse grid after 2 modes (one is not chosen), the kept one on
    # the fine grid when it ends after 3
    assert calls == ["coarse", "coarse", "fine"]
    assert sorted(r.reason or "" for r in runs) == ["", "not chosen"]
    kept = next(r for r in runs if r.stopped is None)
    assert kept.energy == pytest.approx(fine(kept.result.vertices), rel=1e-12)

    # a registration: the two starts judged on the coarse grid after 2 modes, then the
    # coarse pass's kept run on the fine grid when it ends
    calls.clear()
    monkeypatch.setattr(reg, "coarse_objective", coarse)
    starts = reg.run().metrics["starts"]
    assert calls == ["coarse"] * 2 + ["fine"]
    # the report says which grid each start's energy is on, and after how many modes
    assert [(s["energy_grid"], s["energy_after_modes"]) for s in starts if s["stopped_after_modes"]] \
        == [("coarse", 2)]
    assert [(s["energy_grid"], s["energy_after_modes"]) for s in starts if not s["stopped_after_modes"]] \
        == [("fine", 3)]


def test_the_coarse_pass_result_is_kept_by_the_rule_among_starts():
    """With ``coarse_starts``, every start runs on every other node, each run is judged on the
    grid itself, and the run the rule among starts (:func:`_select_start`) picks is the result:
    no run on the grid follows."""
    X, F = asymmetric_blob()
    Y = bend(X, 0.6, axis=2, towards=0) + [0.03, 0.0, 0.0]
    opts = mm.RegistrationOptions(grid=48, modes=3, start_check_modes=99, warped_pass=False)
    reg = mm.Registration((X, F), (Y, F), opts)
    out = reg.run()
    labels = [s["start"] for s in out.metrics["starts"]]
    assert labels == [f"{label} (coarse)" for label in ("rest", *reg.initial_alignment().start_indices())]
    assert all(s["energy_grid"] == "fine" for s in out.metrics["starts"])
    from morphmodes_vol.runs import StartRun, select_start

    kept = select_start([StartRun(s["start"], None, 0.0, s["energy"], s["edge_strain"])
                          for s in out.metrics["starts"]], opts.select_energy_factor)
    assert out.metrics["start"] == kept.label
    # judged on the grid itself, not on the coarse grid it ran on
    assert kept.energy == pytest.approx(reg.objective(reg.normalization.apply(out.vertices)), rel=1e-9)
    # a grid too coarse to halve: one pass
    small = mm.register((X, F), (Y, F), opts.replace(grid=40, initialization="none"))
    assert [s["start"] for s in small.metrics["starts"]] == ["rest"]
    for gone in ("fine_pass", "fine_merge", "icp_start"):
        with pytest.raises(TypeError):
            mm.RegistrationOptions(**{gone: True})


def test_the_fast_setting_is_the_defaults_on_the_band_without_the_other_orientations():
    """``RegistrationOptions.fast()``: the defaults but ``grid``, ``quadrature`` and
    ``warped_candidates``; a registration with it has the coarse runs from the rest pose and
    the initialization's starts, and its warped pass starts from those alone."""
    fast, default = mm.RegistrationOptions.fast(), mm.RegistrationOptions()
    assert fast.grid < default.grid and not fast.warped_candidates
    assert (fast.quadrature, default.quadrature) == ("band", "full")
    assert fast.replace(grid=default.grid, quadrature="full", warped_candidates=True) == default
    X, F = asymmetric_blob()
    Y = bend(X, 0.6, axis=2, towards=0) + [0.03, 0.0, 0.0]
    reg = mm.Registration((X, F), (Y, F), fast.replace(grid=48, modes=3, warped_descriptors=False))
    out = reg.run()
    own = ("rest", *reg.initial_alignment().start_indices())
    runs = [s["start"] for s in out.metrics["starts"]]
    assert runs[:len(own)] == [f"{label} (coarse)" for label in own]
    assert all(not label.startswith(own) or label.endswith(" (coarse)") for label in runs)
    warped = out.metrics["warped_pass"]
    assert set(warped["field_energies"]) | set(warped["pruned"]) == set(own)
    assert out.metrics["final_sdf_rms"] < 0.5 * out.metrics["initial_sdf_rms"]


def test_points_queried_counts_every_query_of_the_source(monkeypatch):
    """``metrics["points_queried"]`` is every point sent to the source mesh's closest-point
    queries (counted here by wrapping the query): the runs' evaluations, the comparisons between runs and the alignment's source field; ``full_grid_equivalents``
    is that over the grid's nodes. With the paper's settings every evaluation is one full
    grid and nothing else queries the source."""
    import trimesh

    import morphmodes_vol.sdf.source as source

    X, F = asymmetric_blob()
    # a target with other vertices, so the count can tell the two meshes apart
    Y, FY = trimesh.remesh.subdivide(bend(X, 0.6, axis=2, towards=0) + [0.03, 0.0, 0.0], F)
    assert len(Y) != len(X)
    counted = []
    query = source.closest_points

    def counting(V, F_, Q, scene=None):
        if len(V) == len(X):
            counted.append(len(Q))
        return query(V, F_, Q, scene=scene)

    monkeypatch.setattr(source, "closest_points", counting)

    reg = mm.Registration((X, F), (Y, FY), mm.RegistrationOptions(grid=48, modes=3))
    nodes = reg.Q.shape[0]
    m = reg.run().metrics
    assert m["points_queried"] == sum(counted) > 0
    assert m["full_grid_equivalents"] == pytest.approx(sum(counted) / nodes)
    # the coarse pass's kept result and the fine run are judged on the full grid at least
    assert m["comparison_evaluations"] >= 2
    assert m["init_field_nodes"] in counted  # the alignment's one query of the source field

    paper = mm.Registration((X, F), (Y, FY), mm.RegistrationOptions.paper_faithful().replace(
        grid=16, modes=2, max_iterations=20))
    counted.clear()
    r = paper.run()
    assert r.metrics["comparison_evaluations"] == 0
    assert r.metrics["points_queried"] == sum(counted) == r.evaluations * paper.Q.shape[0]
    assert r.metrics["full_grid_equivalents"] == r.evaluations
    # its lone run's final energy is already on the full grid
    assert r.metrics["starts"][0]["energy_grid"] == "fine"
    assert r.metrics["starts"][0]["energy"] == r.metrics["final_energy"]


def test_a_lone_run_is_not_judged_on_the_full_grid():
    """One start in one pass: nothing is chosen against it, so no objective is evaluated on
    the full grid; the report keeps the run's own final energy. The run itself is the one a
    judged run makes."""
    X, F = asymmetric_blob()
    Y = bend(X, 0.5, axis=2, towards=0)
    opts = mm.RegistrationOptions(grid=24, modes=3, initialization="none", coarse_starts=False,
                                  warped_pass=False, quadrature="band")
    reg = mm.Registration((X, F), (Y, F), opts)
    r = reg.run()
    assert r.metrics["comparison_evaluations"] == 0
    (start,) = r.metrics["starts"]
    assert start["energy_grid"] == "own" and start["energy_after_modes"] == 3
    assert start["energy"] == r.metrics["final_energy"]

    (judged,) = reg.runner.run([("rest", None, opts)], None)
    np.testing.assert_array_equal(reg.normalization.undo(judged.result.vertices), r.vertices)
    assert judged.energy_grid == "fine"
    assert judged.energy == pytest.approx(reg.objective(judged.result.vertices), rel=1e-12)
