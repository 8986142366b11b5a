"""Pipelines over datasets, on generated primitives: definitions, cached products, resume
after kill -9, failures, executors giving the same numbers."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh

from morphmodes_vol import Registration, RegistrationOptions
from morphmodes_vol.cli import main
from morphmodes_vol.eigenbasis import cotangent_laplacian, lumped_mass
from morphmodes_vol.errors import PipelineError
from morphmodes_vol.mesh import joint_normalization
from morphmodes_vol.pipeline import load_pipeline, run_pipeline
from morphmodes_vol.pipeline.cache import ProductCache, mesh_digest, product_key
from morphmodes_vol.pipeline.task import is_complete
from morphmodes_vol.primitives import bend, capsule
from morphmodes_vol.sdf.source import signed_distance
from morphmodes_vol.stages import SourceEigenbasis, source_eigenbasis, target_field

REPO = Path(__file__).resolve().parents[1]
TINY = "[options]\ngrid = 12\nmodes = 3\nmax_iterations = 40\n"


def _write(path: Path, V, F) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    trimesh.Trimesh(V, F, process=False).export(path)
    return path


@pytest.fixture
def dataset(tmp_path):
    """A source capsule and bent copies of it (same vertex order: ground truth)."""
    V, F = capsule(height=1.0, radius=0.25, count=(8, 8))
    V = V * [1.0, 0.6, 1.0]
    _write(tmp_path / "meshes" / "source.obj", V, F)
    for i, angle in enumerate([0.2, 0.4, 0.6, 0.8, 1.0]):
        _write(tmp_path / "meshes" / f"pose{i}.obj", bend(V, angle), F)
    return tmp_path


def _toml(folder: Path, body: str, name: str = "p.toml") -> Path:
    path = folder / name
    path.write_text(body)
    return path


GLOB = '[pairs]\nsource = "meshes/source.obj"\ntargets = "meshes/pose[0-2].obj"\nground_truth = "target"\n'


# ---- definitions -------------------------------------------------------------------------

def test_pair_expansion_glob_list_all_manifest(dataset):
    p = load_pipeline(_toml(dataset, GLOB + TINY))
    assert [s.name for s in p.pairs] == ["source__pose0", "source__pose1", "source__pose2"]
    assert all(s.ground_truth == s.target for s in p.pairs)
    assert p.pairs[0].options.grid == 12 and p.output == dataset.parent / "out" / "p"
    assert p.cache_dir == p.output / "cache" and p.pairs[1].outdir == p.output / "pairs" / "source__pose1"

    p = load_pipeline(_toml(dataset, '[pairs]\nall = "meshes/pose[01].obj"\n'))
    assert [s.name for s in p.pairs] == ["pose0__pose1", "pose1__pose0"]
    assert all(s.ground_truth is None for s in p.pairs)

    p = load_pipeline(_toml(dataset, '[pairs]\nlist = [["meshes/source.obj", "meshes/pose3.obj"], '
                                      '{source = "meshes/pose3.obj", target = "meshes/source.obj", '
                                      'ground_truth = "meshes/source.obj", name = "back"}]\n'))
    assert [s.name for s in p.pairs] == ["source__pose3", "back"]
    assert p.pairs[1].ground_truth == dataset / "meshes" / "source.obj"

    (dataset / "meshes" / "pairs.csv").write_text("source,target,ground_truth\nsource.obj,pose4.obj,pose4.obj\n"
                                                  "source.obj,pose0.obj,\n")
    p = load_pipeline(_toml(dataset, '[pairs]\nmanifest = "meshes/pairs.csv"\n'))
    assert [(s.source.name, s.target.name, s.ground_truth and s.ground_truth.name) for s in p.pairs] == [
        ("source.obj", "pose4.obj", "pose4.obj"), ("source.obj", "pose0.obj", None)]


def test_sweep_and_data_dir_from_environment(dataset, monkeypatch):
    monkeypatch.setenv("MM_TEST_DATA", str(dataset))
    body = 'data_dir = "${MM_TEST_DATA}/meshes"\n[pairs]\nsource = "source.obj"\ntargets = "pose0.obj"\n' \
           '[sweep]\ngrid = [12, 16]\nmodes = [2, 3]\n'
    (dataset / "elsewhere").mkdir()
    p = load_pipeline(_toml(dataset / "elsewhere", body))
    assert [s.name for s in p.pairs] == ["source__pose0__grid=12__modes=2", "source__pose0__grid=12__modes=3",
                                         "source__pose0__grid=16__modes=2", "source__pose0__grid=16__modes=3"]
    assert [(s.options.grid, s.options.modes) for s in p.pairs] == [(12, 2), (12, 3), (16, 2), (16, 3)]
    assert p.pairs[3].variant == {"grid": 16, "modes": 3}


def test_options_preset_is_a_named_setting_the_other_keys_change(dataset):
    """``[options] preset = "fast"`` starts from ``RegistrationOptions.fast()``; the other keys
    and the sweep change it; without it the defaults; ``"paper"`` and ``"fastest"`` too."""
    import morphmodes_vol as mm

    body = GLOB + '[options]\npreset = "fast"\nmodes = 3\n[sweep]\nwarped_candidates = [false, true]\n'
    p = load_pipeline(_toml(dataset, body))
    assert [s.options for s in p.pairs[:2]] == [mm.RegistrationOptions.fast().replace(modes=3),
                                                mm.RegistrationOptions.fast().replace(modes=3, warped_candidates=True)]
    assert p.pairs[0].options.grid == mm.RegistrationOptions.fast().grid
    assert load_pipeline(_toml(dataset, GLOB)).pairs[0].options == mm.RegistrationOptions()
    paper = load_pipeline(_toml(dataset, GLOB + '[options]\npreset = "paper"\n')).pairs[0].options
    assert paper == mm.RegistrationOptions.paper_faithful()
    fastest = load_pipeline(_toml(dataset, GLOB + '[options]\npreset = "fastest"\n')).pairs[0].options
    assert fastest == mm.RegistrationOptions.fastest()
    with pytest.raises(mm.OptionError, match="preset 'turbo' is unknown"):
        mm.RegistrationOptions.preset("turbo")


@pytest.mark.parametrize("body, key", [
    ('colour = 1\n' + GLOB, "colour"),
    (GLOB + "[options]\ngird = 12\n", "options.gird"),
    (GLOB + "[options]\ngrid = 2\n", "options"),
    (GLOB + '[options]\npreset = "turbo"\n', "options.preset"),
    ('[pairs]\nsource = "meshes/source.obj"\ntargets = "meshes/nothing*.obj"\n', "pairs.targets"),
    ('[pairs]\nall = "meshes/*.obj"\nmanifest = "x.csv"\n', "pairs"),
    ('[pairs]\nsource = "meshes/source.obj"\nall = "meshes/*.obj"\n', "pairs.source"),
    ('[pairs]\nlist = [{source = "a.obj"}]\n', "pairs.list[0].target"),
    (GLOB + "[sweep]\ngrid = 12\n", "sweep.grid"),
    ('data_dir = "${MM_SURELY_UNSET_VAR}"\n' + GLOB, "data_dir"),
    (GLOB + '[outputs]\nformat = "vtk"\n', "outputs.format"),
    (GLOB.replace('"target"', '"meshes/pose0.obj"'), "pairs.ground_truth"),
    (GLOB + '[sweep]\npadding = ["wide"]\n', "sweep"),
    ("[pairs\n", "not valid TOML"),
    ("name = 'x'\n", "pairs"),
])
def test_bad_definitions_name_file_and_key(dataset, body, key):
    path = _toml(dataset, body, "bad.toml")
    with pytest.raises(PipelineError) as info:
        load_pipeline(path)
    assert str(path) in str(info.value) and key in str(info.value)


def test_cli_bad_definition_exit_code_2(dataset, capsys):
    path = _toml(dataset, GLOB + "[options]\ngird = 12\n", "bad.toml")
    assert main(["run", str(path)]) == 2
    err = capsys.readouterr().err
    assert "bad.toml" in err and "options.gird" in err and len(err.strip().splitlines()) == 1


# ---- stage products ----------------------------------------------------------------------

def test_source_eigenbasis_maps_into_any_frame(small_capsule):
    """Eq. (4) in the pair's frame: L W = M W Lambda and W^T M W = I after the rescaling."""
    V, F = small_capsule
    basis = source_eigenbasis(V * 3.0 + 5.0, F, 4)
    frame = joint_normalization(V * 3.0 + 5.0, V * 7.0)
    W, lam = basis.in_frame(frame)
    X = frame.apply(V * 3.0 + 5.0)
    L, M = cotangent_laplacian(X, F), lumped_mass(X, F)
    np.testing.assert_allclose(W.T @ (M @ W), np.eye(4), atol=1e-9)
    residual = L @ W - (M @ W) * lam
    assert np.abs(residual).max() < 1e-7 * np.abs(L @ W).max()


def test_target_field_matches_exact_signed_distance(lumpy_sphere):
    V, F = lumpy_sphere
    field = target_field(V, F, 40, 0.1)
    frame = joint_normalization(V, V * 2.5)         # a pair whose source is larger than the target
    pts = frame.apply(np.concatenate([V * 0.5, V * 1.05, V * 2.0]))   # inside, near, outside the grid
    got = field.sample(pts, frame)
    exact = signed_distance(frame.apply(V), F, pts, sign="winding").value
    spacing_in_frame = field.sdf.grid.spacing * frame.scale / field.frame.scale
    assert np.abs(got - exact).max() < spacing_in_frame
    far = slice(2 * len(V), None)                   # outside the grid: exact values
    np.testing.assert_allclose(got[far], exact[far], atol=1e-9)


def test_injected_eigenbasis_in_the_pair_frame_reproduces_registration(small_capsule):
    V, F = small_capsule
    target = (V * [1.1, 1.0, 1.0], F)
    opts = RegistrationOptions(grid=12, modes=2, max_iterations=30)
    plain = Registration((V, F), target, opts)
    basis = SourceEigenbasis(plain.weights, plain.eigenvalues, plain.normalization)
    injected = Registration((V, F), target, opts, eigenbasis=basis)
    np.testing.assert_array_equal(plain.run().vertices, injected.run().vertices)


def test_cache_keys_follow_content_and_parameters(tmp_path, small_capsule):
    V, F = small_capsule
    d = mesh_digest(V, F)
    assert d != mesh_digest(V * (1 + 1e-12), F) and d != mesh_digest(V, F[:, ::-1])
    assert product_key("eigenbasis", [d], {"modes": 3}) != product_key("eigenbasis", [d], {"modes": 4})
    cache = ProductCache(tmp_path)
    calls = []

    def build():
        calls.append(1)
        return source_eigenbasis(V, F, 3)

    key = product_key("eigenbasis", [d], {"modes": 3, "seed": 0})
    a, hit_a = cache.get_or_build("eigenbasis", key, build, SourceEigenbasis.to_arrays, SourceEigenbasis.from_arrays)
    b, hit_b = cache.get_or_build("eigenbasis", key, build, SourceEigenbasis.to_arrays, SourceEigenbasis.from_arrays)
    assert (hit_a, hit_b, len(calls)) == (False, True, 1)
    np.testing.assert_array_equal(a.weights, b.weights)
    assert b.frame.scale == a.frame.scale


# ---- runs --------------------------------------------------------------------------------

def _states(run) -> list[str]:
    return [r["state"] for r in run.rows]


def test_run_writes_pairs_and_summary_and_resumes(dataset):
    path = _toml(dataset, GLOB + TINY)
    p = load_pipeline(path)
    run = run_pipeline(p, workers=1)
    assert _states(run) == ["ok"] * 3 and run.failed == 0
    for spec in p.pairs:
        assert is_complete(spec, json.loads((spec.outdir / "report.json").read_text())["inputs"]["pipeline"]["key"])
        reg = trimesh.load(spec.outdir / "registered.obj", process=False, force="mesh")
        assert len(reg.vertices) == 66
    rows = run.rows
    # the source's eigenbasis is built once and reused; each target's SDF is built once
    assert [r["eigenbasis_cached"] for r in rows] == [False, True, True]
    assert [r["target_sdf_cached"] for r in rows] == [False, False, False]
    assert all(r["ground_truth_error"] < r["identity_error"] for r in rows)
    try:
        import matplotlib  # noqa: F401
        plots = ["png"]
    except ImportError:
        plots = []
    assert sorted(run.paths) == sorted(["csv", "json", "md"] + plots)
    summary = json.loads(run.paths["json"].read_text())
    assert summary["counts"] == {"ok": 3, "skipped": 0, "failed": 0} and len(summary["pairs"]) == 3
    assert run.paths["md"].read_text().count("\n| source__pose") == 3

    again = run_pipeline(load_pipeline(path), workers=1)
    assert _states(again) == ["skipped"] * 3
    assert [r["ground_truth_error"] for r in again.rows] == [r["ground_truth_error"] for r in rows]

    # an edited target (same file name) and a changed option are never served stale results
    V = trimesh.load(dataset / "meshes" / "pose1.obj", process=False, force="mesh").vertices
    _write(dataset / "meshes" / "pose1.obj", V * 1.01, trimesh.load(dataset / "meshes" / "pose1.obj",
                                                                      process=False, force="mesh").faces)
    third = run_pipeline(load_pipeline(path), workers=1)
    assert _states(third) == ["skipped", "ok", "skipped"] and third.rows[1]["target_sdf_cached"] is False
    path.write_text(GLOB + TINY.replace("max_iterations = 40", "max_iterations = 30"))
    fourth = run_pipeline(load_pipeline(path), workers=1)
    assert _states(fourth) == ["ok"] * 3
    assert all(r["eigenbasis_cached"] and r["target_sdf_cached"] for r in fourth.rows)


def test_failed_pairs_are_recorded_and_the_run_goes_on(dataset, capsys):
    (dataset / "meshes" / "broken.obj").write_text("v 0 0 0\nv 1 0 0\n")
    body = ('[pairs]\nlist = [["meshes/source.obj", "meshes/pose0.obj"], ["meshes/source.obj", "meshes/broken.obj"],'
            ' ["meshes/missing.obj", "meshes/pose0.obj"]]\n' + TINY)
    path = _toml(dataset, body)
    assert main(["run", str(path), "--workers", "1"]) == 1
    captured = capsys.readouterr()
    assert "FAILED" in captured.err and "1 registered" in captured.out
    p = load_pipeline(path)
    rows = json.loads((p.output / "summary.json").read_text())["pairs"]
    assert [r["state"] for r in rows] == ["ok", "failed", "failed"]
    assert "broken.obj" in rows[1]["error"] and "missing.obj: no such file" in rows[2]["error"]
    assert json.loads((p.pairs[1].outdir / "failed.json").read_text())["error"] == rows[1]["error"]
    # the good pair is skipped on a rerun, the failed ones are tried again
    assert main(["run", str(path), "--workers", "1", "-q"]) == 1
    rows = json.loads((p.output / "summary.json").read_text())["pairs"]
    assert [r["state"] for r in rows] == ["skipped", "failed", "failed"]


def _arrays(p):
    return {s.name: np.load(s.outdir / "state.npz")["T"] for s in p.pairs}


def test_same_numbers_from_every_executor(dataset, tmp_path):
    """In-process, a local process pool and Dask (LocalCluster on loopback) run the same tasks."""
    distributed = pytest.importorskip("distributed")
    path = _toml(dataset, GLOB + TINY)
    serial = load_pipeline(path, output=tmp_path / "serial")
    run_pipeline(serial, workers=1)
    pool = load_pipeline(path, output=tmp_path / "pool")
    assert _states(run_pipeline(pool, workers=2)) == ["ok"] * 3
    dask = load_pipeline(path, output=tmp_path / "dask")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False, protocol="tcp", host="127.0.0.1",
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        events = []
        run = run_pipeline(dask, "dask", client=client, on_event=lambda name, text: events.append((name, text)))
    assert _states(run) == ["ok"] * 3
    assert {name for name, _ in events} == {s.name for s in dask.pairs}
    a, b, c = _arrays(serial), _arrays(pool), _arrays(dask)
    for name in a:
        np.testing.assert_array_equal(a[name], b[name])
        np.testing.assert_array_equal(a[name], c[name])


def test_dask_executor_without_dask_says_how_to_install(dataset, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "distributed", None)      # import distributed -> ImportError
    path = _toml(dataset, GLOB + TINY)
    assert main(["run", str(path), "--executor", "dask"]) == 2
    assert "pip install 'dask[distributed]'" in capsys.readouterr().err


def test_kill_9_mid_run_then_resume_completes_every_pair(dataset, tmp_path):
    body = ('[pairs]\nsource = "meshes/source.obj"\ntargets = "meshes/pose*.obj"\nground_truth = "target"\n'
            "[options]\ngrid = 16\nmodes = 3\nmax_iterations = 60\n")
    path = _toml(dataset, body)
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "morphmodes_vol", "run", str(path), "-o", str(out), "--workers", "1", "-q"]
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))

    def run_and_kill(ready) -> None:
        proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 300
        while not ready() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        proc.send_signal(signal.SIGKILL)
        proc.wait()

    # once while the first pair builds its products, once after a pair has been exported
    run_and_kill(lambda: (out / "pairs").is_dir())
    run_and_kill(lambda: len(list(out.glob("pairs/*/report.json"))) >= 1)
    done_before = {p.parent.name for p in out.glob("pairs/*/report.json")}
    p = load_pipeline(path, output=out)
    assert 1 <= len(done_before) < len(p.pairs), "the kill came too late to test anything"
    assert not (out / "summary.json").exists()

    rerun = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert rerun.returncode == 0, rerun.stderr
    rows = json.loads((out / "summary.json").read_text())["pairs"]
    assert {r["pair"] for r in rows if r["state"] == "skipped"} == done_before
    assert all(r["state"] in ("ok", "skipped") for r in rows) and len(rows) == len(p.pairs)
    for spec in p.pairs:
        report = json.loads((spec.outdir / "report.json").read_text())
        assert is_complete(spec, report["inputs"]["pipeline"]["key"])
        state, corr = np.load(spec.outdir / "state.npz"), np.load(spec.outdir / "correspondence.npz")
        assert state["T"].shape == (report["modes"], 3, 4) and corr["faces"].shape == (66,)
        assert len(trimesh.load(spec.outdir / "registered.obj", process=False, force="mesh").vertices) == 66
        assert not list(spec.outdir.glob(".*.tmp"))
    for entry in (out / "cache").glob("*/*.npz"):
        with np.load(entry) as data:
            assert data.files


@pytest.mark.realdata
def test_shipped_definitions_expand_on_the_shared_data(data_dir, monkeypatch):
    monkeypatch.setenv("MORPHMODES_DATA", str(data_dir))
    for name in ("lion_poses", "cat_poses", "lion_grid_study", "lion_poses_quick"):
        p = load_pipeline(REPO / "pipelines" / f"{name}.toml")
        assert len(p.pairs) == 9, name
        assert all(s.source.is_file() and s.ground_truth == s.target and s.target.is_file() for s in p.pairs)
    lion = load_pipeline(REPO / "pipelines" / "lion_poses.toml")
    assert all(s.options == RegistrationOptions() for s in lion.pairs)   # the default settings
    assert [s.target.name for s in lion.pairs] == [f"lion-{i:02d}.obj" for i in range(1, 10)]
    study = load_pipeline(REPO / "pipelines" / "lion_grid_study.toml")
    assert sorted({s.options.grid for s in study.pairs}) == [32, 48, 64]


def test_cached_target_field_uses_the_target_sign_option():
    from morphmodes_vol.primitives import holed_sphere
    from morphmodes_vol.sdf import DenseTargetSDF, Grid
    from morphmodes_vol.stages import target_field

    V, F = holed_sphere(3)
    for sign in ("winding", "raycast"):
        field = target_field(V, F, 20, 0.1, sign)
        Vn = field.frame.apply(V)
        g = field.sdf.grid
        expected = DenseTargetSDF.from_mesh(Vn, field.faces, Grid(g.origin, g.spacing, g.shape), sign=sign)
        np.testing.assert_array_equal(field.sdf.values, expected.values)
    # the two inside tests disagree behind the holes, so the option is not ignored
    assert not np.array_equal(target_field(V, F, 20, 0.1, "winding").sdf.values,
                              target_field(V, F, 20, 0.1, "raycast").sdf.values)
