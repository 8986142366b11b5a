"""Numerical faults injected into the energy: never accepted, the run rolls back to its last
good state and still writes valid outputs; and determinism."""

import json

import numpy as np
import pytest
import trimesh

import morphmodes_vol as mm
from morphmodes_vol.energy import EnergyEvaluation
from morphmodes_vol.primitives import bend, capsule, icosphere

# both optimizers, 10 steps per stage, on the full grid (so accepted energies compare), one
# run from the rest pose (the initialization's second start is tested in test_initialize.py,
# the warped pass after the runs in test_warped_field.py)
OPTS = mm.RegistrationOptions(grid=12, modes=3, max_iterations=30, stall_start=1e-9, stall_end=1e-9,
                              max_iterations_per_stage=10, lm_iterations_per_stage=10,
                              lm_stall_decrease=0.0, quadrature="full", initialization="none",
                              warped_pass=False)


class FaultyEnergy:
    """Wraps an SDFEnergy; evaluations whose 1-based number is in ``bad`` return a NaN (or
    infinite) energy or gradient."""

    def __init__(self, inner, bad, what="energy", value=float("nan")):
        self.inner, self.bad, self.what, self.value = inner, bad, what, value
        self.calls = 0

    def __getattr__(self, name):  # evaluations, seconds
        return getattr(self.inner, name)

    def evaluate(self, X):
        ev = self.inner.evaluate(X)
        self.calls += 1
        if self.calls not in self.bad:
            return ev
        if self.what == "energy":
            return EnergyEvaluation(self.value, ev.gradient, ev.residual)
        grad = ev.gradient.copy()
        grad[0, 0] = self.value
        return EnergyEvaluation(ev.energy, grad, ev.residual)


@pytest.fixture(scope="module", params=["paper", "lm"])
def reg(request):
    V, F = capsule(count=(8, 8))
    V = V * [1.0, 0.6, 1.0]
    return mm.Registration((V, F), (bend(V, np.deg2rad(40)), F), OPTS.replace(optimizer=request.param))


@pytest.fixture(scope="module")
def clean(reg):
    return reg.run()


def faulty_run(reg, monkeypatch, bad, **kwargs):
    inner = type(reg).energy
    monkeypatch.setattr(type(reg), "energy", lambda self: FaultyEnergy(inner(self), bad, **kwargs))
    return reg.run()


def strict_json(path):
    def refuse(constant):
        raise ValueError(f"non-standard JSON constant {constant}")

    return json.loads(path.read_text(), parse_constant=refuse)


@pytest.mark.parametrize("what, value", [("energy", np.nan), ("energy", np.inf), ("gradient", np.nan)])
def test_persistent_fault_rolls_back_to_the_last_good_state(reg, clean, monkeypatch, tmp_path, what, value):
    k = 15  # every evaluation after the 15th is broken
    r = faulty_run(reg, monkeypatch, range(k + 1, 10**6), what=what, value=value)
    assert r.status == "rolled_back" and r.history.stage_ends[-1] == "fault"
    # the accepted steps are the clean run's, up to the fault
    got = np.asarray(r.history.energy)
    assert 2 <= len(got) < len(clean.history.energy) and np.isfinite(got).all()
    np.testing.assert_array_equal(got, clean.history.energy[: len(got)])
    # the result is that last good state
    last = reg.energy().evaluate(reg.normalization.apply(r.vertices))
    assert last.energy == pytest.approx(got[-1], rel=1e-9)
    assert r.metrics["final_energy"] == got[-1]
    # ... and is written as a complete, valid output folder
    paths = mm.write_outputs(r, tmp_path / "out")
    report = strict_json(paths["report"])
    assert report["status"] == "rolled_back" and report["history"]["stage_ends"][-1] == "fault"
    mesh = trimesh.load(paths["mesh"], process=False, force="mesh")
    np.testing.assert_allclose(mesh.vertices, r.vertices, rtol=1e-6, atol=1e-6)


def test_transient_nan_is_skipped_by_backtracking(reg, clean, monkeypatch):
    r = faulty_run(reg, monkeypatch, {6, 7, 20})
    assert r.status != "rolled_back" and "fault" not in r.history.stage_ends
    e = np.asarray(r.history.energy)
    assert np.isfinite(e).all() and np.all(np.diff(e) <= 0)
    assert e[-1] < 0.5 * e[0]


def test_non_finite_rest_pose_returns_the_source_and_valid_outputs(reg, monkeypatch, tmp_path):
    r = faulty_run(reg, monkeypatch, range(1, 10**6))
    assert r.status == "rolled_back" and r.evaluations == 1
    np.testing.assert_allclose(r.vertices, reg.source_vertices, rtol=0, atol=1e-12)
    assert r.modes == 1 and not r.T.any()
    report = strict_json(mm.write_outputs(r, tmp_path / "out")["report"])
    assert report["metrics"]["initial_energy"] is None and report["status"] == "rolled_back"


def test_optimizer_never_hands_non_finite_vertices_to_the_sdf(reg, monkeypatch):
    seen = []
    inner = type(reg).energy

    class Spy(FaultyEnergy):
        def evaluate(self, X):
            seen.append(bool(np.isfinite(X).all()))
            return super().evaluate(X)

    monkeypatch.setattr(type(reg), "energy", lambda self: Spy(inner(self), range(10, 10**6), "gradient"))
    r = reg.run()
    assert r.status == "rolled_back" and all(seen)


def test_same_inputs_and_seed_give_identical_outputs(tmp_path):
    V, F = icosphere(3)  # 642 vertices: the sparse eigensolver with its seeded start vector
    V = V * [1.0, 0.7, 0.5]
    target = V * [1.1, 1.0, 0.95] + [0.02, 0, 0]
    opts = mm.RegistrationOptions(grid=12, modes=3, max_iterations=12, seed=7)
    outs = [mm.write_outputs(mm.register((V, F), (target, F), opts), tmp_path / f"run{i}") for i in range(2)]
    a, b = outs
    assert a["mesh"].read_bytes() == b["mesh"].read_bytes()
    for key in ("state", "correspondence"):
        with np.load(a[key]) as x, np.load(b[key]) as y:
            assert sorted(x.files) == sorted(y.files)
            for name in x.files:
                if name != "stage_seconds":
                    np.testing.assert_array_equal(x[name], y[name])
    ra, rb = strict_json(a["report"]), strict_json(b["report"])
    for r in (ra, rb):
        r.pop("timings")
        r["history"].pop("stage_seconds")
    assert ra == rb


def test_cli_rolled_back_run_exits_0_with_complete_outputs(tmp_path, monkeypatch, capsys):
    from morphmodes_vol.cli import main

    V, F = capsule(count=(8, 8))
    src, tgt = tmp_path / "s.obj", tmp_path / "t.obj"
    trimesh.Trimesh(V, F, process=False).export(src)
    trimesh.Trimesh(V * 1.1, F, process=False).export(tgt)
    inner = mm.Registration.energy
    monkeypatch.setattr(mm.Registration, "energy", lambda self: FaultyEnergy(inner(self), range(5, 10**6)))
    out = tmp_path / "out"
    assert main(["register", str(src), str(tgt), "-o", str(out), "--grid", "12", "--modes", "2", "-q",
                 "--set", "warped_pass=false"]) == 0
    printed = capsys.readouterr().out
    assert "status: rolled_back" in printed and "last good state" in printed
    assert strict_json(out / "report.json")["status"] == "rolled_back"
    assert sorted(p.name for p in out.iterdir()) == ["correspondence.npz", "registered.obj", "report.json", "state.npz"]
