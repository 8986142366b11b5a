"""The switch of ``.ci/run``: without the real meshes, a test that needs them skips with its
reason, or fails under ``MORPHMODES_REQUIRE_DATA=1``."""

import os
import shutil
import subprocess
import sys
from pathlib import Path


def _run_needing_data(tmp_path, require: bool) -> subprocess.CompletedProcess:
    shutil.copy(Path(__file__).with_name("conftest.py"), tmp_path / "conftest.py")
    (tmp_path / "test_needs_data.py").write_text("def test_needs_data(data_dir):\n    assert data_dir.is_dir()\n")
    env = dict(os.environ, MORPHMODES_DATA=str(tmp_path / "absent"))
    env.pop("MORPHMODES_REQUIRE_DATA", None)
    if require:
        env["MORPHMODES_REQUIRE_DATA"] = "1"
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider", "-c", os.devnull,
                           str(tmp_path)], env=env, capture_output=True, text=True, cwd=tmp_path)


def test_without_the_data_a_realdata_test_skips_with_its_reason(tmp_path):
    run = _run_needing_data(tmp_path, require=False)
    assert run.returncode == 0, run.stdout
    assert "1 skipped" in run.stdout and "real meshes not found" in run.stdout


def test_without_the_data_a_realdata_test_fails_when_the_data_is_required(tmp_path):
    run = _run_needing_data(tmp_path, require=True)
    assert run.returncode == 1, run.stdout
    assert "1 error" in run.stdout and "MORPHMODES_REQUIRE_DATA=1" in run.stdout
