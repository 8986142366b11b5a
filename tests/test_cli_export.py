"""The command line and the output folder, end to end on generated meshes."""

import json
from pathlib import Path
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from morphmodes_vol.cli import main
from morphmodes_vol.errors import OptionError
from morphmodes_vol.export import atomic_write_bytes
from morphmodes_vol.primitives import capsule


@pytest.fixture
def pair(tmp_path):
    V, F = capsule(height=1.0, radius=0.25, count=(10, 10))
    V = V * [1.0, 0.6, 1.0]
    target = V * [1.1, 1.0, 1.05] + [0.03, 0, 0]
    src, tgt = tmp_path / "src.obj", tmp_path / "tgt.off"
    trimesh.Trimesh(V, F, process=False).export(src)
    trimesh.Trimesh(target, F, process=False).export(tgt)
    return src, tgt, V, F, target


def test_register_writes_complete_outputs(pair, tmp_path, capsys):
    src, tgt, V, F, target = pair
    out = tmp_path / "out"
    code = main(["register", str(src), str(tgt), "-o", str(out), "--grid", "16", "--modes", "3",
                 "--ground-truth", str(tgt), "--quiet"])
    assert code == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == ["correspondence.npz", "registered.obj", "report.json", "state.npz"]
    reg = trimesh.load(out / "registered.obj", process=False, force="mesh")
    assert len(reg.vertices) == len(V)
    np.testing.assert_array_equal(reg.faces, F)
    report = json.loads((out / "report.json").read_text())
    assert report["options"]["grid"] == 16 and report["modes"] == 3
    assert report["metrics"]["ground_truth_error"] < report["metrics"]["identity_error"]
    assert {"preprocess", "target_sdf", "eigenbasis", "optimize"} <= set(report["timings"])
    assert report["versions"]["open3d"] != "not installed"
    # the kept start's history; the report counts the evaluations of every start
    assert 0 < report["history"]["evaluations"] <= report["evaluations"]
    assert report["evaluations"] == sum(s["evaluations"] for s in report["metrics"]["starts"])
    state = np.load(out / "state.npz")
    assert state["W"].shape == (len(V), 3) and state["T"].shape == (3, 3, 4)
    assert state["z"].shape == (36,)
    corr = np.load(out / "correspondence.npz")
    assert corr["faces"].shape == (len(V),) and corr["barycentrics"].shape == (len(V), 3)
    np.testing.assert_allclose(corr["barycentrics"].sum(1), 1.0, atol=1e-9)
    printed = capsys.readouterr().out
    assert "ground-truth error" in printed
    m = report["metrics"]
    assert (f"{report['evaluations']} SDF evaluations + {m['comparison_evaluations']} comparisons, "
            f"the cost of {m['full_grid_equivalents']:.1f} evaluations on the full grid") in printed
    assert not [p for p in out.iterdir() if p.name.endswith(".tmp")]


def test_bad_input_gives_one_line_and_exit_code_2(tmp_path, pair):
    src = pair[0]
    bad = tmp_path / "bad.obj"
    bad.write_text("")
    proc = subprocess.run(
        [sys.executable, "-m", "morphmodes_vol", "register", str(src), str(bad), "-o", str(tmp_path / "o")],
        capture_output=True, text=True,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "bad.obj" in lines[0] and "empty" in lines[0]
    assert not (tmp_path / "o" / "report.json").exists()


def test_progress_is_shown_unless_quiet(pair, tmp_path, capsys):
    src, tgt = pair[0], pair[1]
    main(["register", str(src), str(tgt), "-o", str(tmp_path / "a"), "--grid", "12", "--modes", "2"])
    assert "modes 1/2" in capsys.readouterr().err
    main(["register", str(src), str(tgt), "-o", str(tmp_path / "b"), "--grid", "12", "--modes", "2", "-q"])
    assert capsys.readouterr().err == ""


def test_atomic_write_leaves_old_file_on_failure(tmp_path):
    path = tmp_path / "f.txt"
    atomic_write_bytes(path, b"old")

    with pytest.raises(TypeError):
        atomic_write_bytes(path, object())  # not bytes: fails while writing
    assert path.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["f.txt"]
    assert path.stat().st_mode & 0o044  # readable by others like any file (mkstemp makes 0600)


def test_demo_runs_without_shared_data(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "-o", str(out), "--grid", "16", "--modes", "3", "-q"]) == 0
    report = json.loads((out / "report.json").read_text())
    m = report["metrics"]
    assert m["ground_truth_error"] < m["identity_error"]
    assert (out / "source.ply").exists() and (out / "target.ply").exists()
    printed = capsys.readouterr().out
    assert str(out) in printed and "ground-truth error" in printed


def test_options_from_preset_config_and_set(tmp_path, capsys):
    """``--preset``, then ``--config``, then ``--grid``/``--modes``, then each ``--set``: the
    same table a pipeline's ``[options]`` is (RegistrationOptions.from_table)."""
    from morphmodes_vol.cli import build_parser, options_from_args
    from morphmodes_vol.options import RegistrationOptions as O

    def options(*flags, command="register"):
        files = ["s.obj", "t.obj"] if command == "register" else []
        return options_from_args(build_parser().parse_args([command, *files, "-o", "out", *flags]))

    assert options() == O()
    assert options("--preset", "paper") == O.paper_faithful()
    assert options("--preset", "fast") == O.fast() and O.fast().grid == 48
    assert options("--preset", "fast", "--grid", "64") == O.fast().replace(grid=64)
    assert options("--preset", "fastest", "--set", "warped_hops=1") == O.fastest().replace(warped_hops=1)
    assert options("--set", "quadrature=band", "--set", "warped_pass=false", "--set", "band_cells=1.5") == \
        O(quadrature="band", warped_pass=False, band_cells=1.5)
    assert options("--set", "memory_limit_gb=0").memory_limit_gb is None
    config = tmp_path / "c.toml"
    config.write_text('preset = "fast"\nwarped_hops = 0\n')
    assert options("--config", str(config)) == O.fast().replace(warped_hops=0)
    assert options("--config", str(config), "--preset", "default") == O(warped_hops=0)
    assert options("--config", str(config), "--set", "warped_hops=2").warped_hops == 2
    config.write_text('name = "x"\n[options]\nmodes = 8\n')  # a pipeline definition's table
    assert options("--config", str(config)) == O(modes=8)
    # the demo's own grid and modes unless given
    assert (options(command="demo").grid, options(command="demo").modes) == (48, 12)
    assert options("--grid", "32", command="demo").grid == 32
    with pytest.raises(OptionError, match="unknown option"):
        options("--set", "warp_hops=1")
    with pytest.raises(OptionError, match="KEY=VALUE"):
        options("--set", "grid")
    with pytest.raises(OptionError, match="warped_hops"):
        options("--set", "warped_hops=-1")
    with pytest.raises(OptionError, match="no such config file"):
        options("--config", str(tmp_path / "missing.toml"))
    with pytest.raises(SystemExit):  # argparse: an unknown preset
        options("--preset", "turbo")
    with pytest.raises(SystemExit):
        build_parser().parse_args(["register", "--help"])
    flags = [line for line in capsys.readouterr().out.splitlines() if line.startswith("  -")]
    assert "--preset" in "".join(flags) and len(flags) < 25


def test_progress_lines_name_each_run_once_and_then_every_few_seconds():
    """Off a terminal, a line when a run starts and otherwise every few seconds (here never);
    the runs are labelled."""
    import io

    from morphmodes_vol.cli import ProgressPrinter
    from morphmodes_vol.optimize import ProgressEvent

    stream = io.StringIO()
    printer = ProgressPrinter(stream, interval=1e9)

    def event(start, modes, iteration):
        return ProgressEvent(modes=modes, max_modes=3, iteration=iteration, stage_iteration=0,
                             energy=1.0, step_rms=float("nan"), threshold=1e-3, evaluations=1,
                             elapsed=0.0, start=start)

    for e in [event("rest", 1, 0), event("rest", 1, 1), event("aligned", 1, 0),
              event("aligned", 1, 1), event("rest", 2, 2), event("", 2, 3)]:
        printer(e)
    lines = stream.getvalue().splitlines()
    assert [line[:20] for line in lines] == ["[rest] modes 1/3  it", "[aligned] modes 1/3 ",
                                             "modes 2/3  iter 3  e"]


def _unwritable_folder(tmp_path):
    """A folder where no file can be created: a read-only copy for a normal user, or, for
    root (whom modes do not stop), a read-only system folder; skip when neither refuses."""
    import os
    import tempfile

    ro = tmp_path / "read-only"
    ro.mkdir()
    ro.chmod(0o555)
    for folder in (ro, Path("/sys"), Path("/proc")):
        try:
            fd, name = tempfile.mkstemp(dir=folder)
        except OSError:
            return folder
        os.close(fd)
        os.unlink(name)
    pytest.skip("every folder tried here is writable")


@pytest.mark.parametrize("case", ["existing file", "file on the way", "cannot be written", "overwrites an input"])
@pytest.mark.parametrize("command", ["register", "run", "sdf", "render"])
def test_a_bad_output_path_is_one_line_and_exit_2_before_any_work(pair, tmp_path, capsys, monkeypatch, case,
                                                                   command):
    """Each of the four bad output paths, on each command that writes: one line, exit 2,
    before any input is read (the registration, the SDF and the drawing are never reached)."""
    from morphmodes_vol.register import Registration

    src, tgt, *_ = pair
    a_file = tmp_path / "a_file"
    a_file.write_text("not a folder")
    folder_kind = command in ("register", "run")
    out = {"existing file": a_file if folder_kind else tmp_path,
           "file on the way": a_file / "sub" / ("out" if folder_kind else "out.npz"),
           "cannot be written": _unwritable_folder(tmp_path) / ("out" if folder_kind else "out.npz"),
           "overwrites an input": None}[case]
    expected = {"existing file": "is an existing " + ("file" if folder_kind else "folder"),
                "file on the way": "cannot be created: .* is a file",
                "cannot be written": "cannot be (created|written)",
                "overwrites an input": "would overwrite the input"}[case]
    if command == "register":
        if case == "overwrites an input":  # the source named as the registered mesh would be
            src = src.rename(tmp_path / "registered.obj")
            out = tmp_path
        argv = ["register", str(src), str(tgt), "-o", str(out)]
    elif command == "run":
        if case == "overwrites an input":  # the target pose is the summary a run writes
            tgt = tgt.rename(tmp_path / "summary.csv")
            out = tmp_path
        definition = tmp_path / "p.toml"
        definition.write_text(f'name = "p"\ndata_dir = "{tmp_path}"\n[pairs]\nsource = "{src.name}"\n'
                              f'targets = "{tgt.name}"\n')
        argv = ["run", str(definition), "-o", str(out)]
    elif command == "sdf":
        if case == "overwrites an input":
            tgt = tgt.rename(tmp_path / "target.npz")
            out = tgt
        argv = ["sdf", str(tgt), "-o", str(out)]
    else:
        if case == "overwrites an input":
            out = tmp_path / "src.png"
            src = src.rename(out)
        argv = ["render", str(src), "-o", str(out)]

    def never(*args, **kwargs):
        raise AssertionError("work started before the output path was checked")

    for name in ("as_mesh", "load_mesh"):
        monkeypatch.setattr(f"morphmodes_vol.mesh.{name}", never)
    monkeypatch.setattr(Registration, "__init__", never)
    monkeypatch.setattr("morphmodes_vol.pipeline.run_pipeline", never)
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("morphmodes-vol: error: output")
    import re

    assert re.search(expected, err[0]), err[0]
