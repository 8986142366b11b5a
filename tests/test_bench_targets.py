"""``scripts/bench.py``'s summary of the issue-6 targets, worked by hand (the script itself
runs the registrations; only its arithmetic is tested here)."""

import importlib.util
import json
from pathlib import Path

import pytest

_PATH = Path(__file__).resolve().parents[1] / "scripts" / "bench.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_script", _PATH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _results(wall=25.4, error=0.0102, equivalents=45.6, nricp_wall=8.5, paper_error=0.281, paper_equivalents=637.0):
    return {"ours, default": {"wall_s": wall, "error": error, "full_grid_equivalents": equivalents},
            "trimesh nricp_amberg": {"wall_s": nricp_wall, "error": 0.238},
            "ours, --preset paper": {"wall_s": 300.0, "error": paper_error,
                                        "full_grid_equivalents": paper_equivalents}}


def test_targets_by_hand(bench):
    t = bench.targets(_results())
    assert t["wall_time"]["ratio"] == pytest.approx(25.4 / 8.5) and not t["wall_time"]["met"]
    assert t["evaluations"]["factor"] == pytest.approx(637.0 / 45.6) and t["evaluations"]["met"]
    # exactly at the bounds: a third of NRICP's time, ten times fewer evaluations
    t = bench.targets(_results(wall=3.0, nricp_wall=9.0, equivalents=64.0, paper_equivalents=640.0))
    assert t["wall_time"]["met"] and t["evaluations"]["met"]
    t = bench.targets(_results(wall=3.01, nricp_wall=9.0, equivalents=64.1, paper_equivalents=640.0))
    assert not t["wall_time"]["met"] and not t["evaluations"]["met"]


def test_a_higher_error_than_the_paper_meets_no_target(bench):
    t = bench.targets(_results(wall=1.0, error=0.3, equivalents=10.0))
    assert t["wall_time"]["ratio"] < bench.TIME_RATIO and not t["wall_time"]["met"]
    assert t["evaluations"]["factor"] > bench.EVALUATION_FACTOR and not t["evaluations"]["met"]


def test_targets_whose_methods_did_not_run_are_left_out(bench):
    full = _results(wall=2.0)
    assert set(bench.targets(full)) == {"wall_time", "evaluations"}
    no_paper = {k: v for k, v in full.items() if k != "ours, --preset paper"}
    assert set(bench.targets(no_paper)) == {"wall_time"} and bench.targets(no_paper)["wall_time"]["met"]
    no_nricp = {k: v for k, v in full.items() if k != "trimesh nricp_amberg"}
    assert set(bench.targets(no_nricp)) == {"evaluations"}
    assert bench.targets({"trimesh nricp_amberg": full["trimesh nricp_amberg"]}) == {}
    line = bench.target_line("p", bench.targets(full), full)
    assert line.startswith("- issue-6 targets, p: wall time 0.24x") and line.count("**met**") == 2
    assert bench.target_line("p", {}, {}) is None
    # with options set, the line says the run is not of the default settings
    assert bench.target_line("p", bench.targets(full), full, {"grid": 48}).endswith(
        "; ours ran with --set grid=48, not the default settings")


def test_the_other_settings_ratios_are_reported_not_judged(bench):
    """``--preset fast`` and ``--preset fastest`` get the same wall-time ratio, for comparison, in
    ``"settings"`` and at the end of the line; the targets stay the default's."""
    full = _results()
    full["ours, --preset fastest"] = {"wall_s": 4.25, "error": 0.0109, "full_grid_equivalents": 4.4}
    t = bench.targets(full)
    assert t["settings"] == {"--preset fastest": {"ratio": pytest.approx(0.5), "error": 0.0109}}
    assert not t["wall_time"]["met"] and t["wall_time"]["ratio"] == pytest.approx(25.4 / 8.5)
    line = bench.target_line("p", t, full)
    assert line.endswith("; the other settings: --preset fastest 0.50x at error 0.0109")
    no_nricp = {k: v for k, v in full.items() if k != "trimesh nricp_amberg"}
    assert "settings" not in bench.targets(no_nricp)
    # a run of the other settings without the default still gets its line
    alone = {k: full[k] for k in ("trimesh nricp_amberg", "ours, --preset fastest")}
    assert set(bench.targets(alone)) == {"settings"}
    assert bench.target_line("p", bench.targets(alone), alone) == (
        "- issue-6 targets, p: the default did not run; the other settings: --preset fastest 0.50x at error 0.0109")
    lines = []
    bench.add_targets({}, "p", alone, lines)
    assert lines == [bench.target_line("p", bench.targets(alone), alone)]


def test_targets_only_reads_a_saved_run(bench, tmp_path, monkeypatch, capsys):
    """``--targets-only``: nothing runs; the targets of the saved run are printed and added to
    ``bench.json`` and ``bench.md``, once however often it is asked."""
    rows = [{"pair": "p", "method": m, **r} for m, r in _results().items()]
    (tmp_path / "bench.json").write_text(json.dumps({"results": rows}))
    (tmp_path / "bench.md").write_text("| table |\n|---|\n")
    monkeypatch.setattr("sys.argv", ["bench.py", "--targets-only", "--out", str(tmp_path)])
    for _ in range(2):
        assert bench.main() == 0
    printed = capsys.readouterr().out
    assert printed.count("- issue-6 targets, p: wall time 2.99x NRICP's (at most 0.33x): **not met**") == 2
    md = (tmp_path / "bench.md").read_text().splitlines()
    assert md[:2] == ["| table |", "|---|"] and md[2] == "" and len(md) == 4 and md[3] == printed.splitlines()[0]
    saved = json.loads((tmp_path / "bench.json").read_text())["targets"]["p"]
    assert saved["evaluations"]["met"] and not saved["wall_time"]["met"]
    monkeypatch.setattr("sys.argv", ["bench.py", "--targets-only", "--out", str(tmp_path / "none")])
    assert bench.main() == 2 and "bench.json is missing" in capsys.readouterr().err
