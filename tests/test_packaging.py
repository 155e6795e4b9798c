"""The project installs from a built wheel and runs a shipped scenario from an
unrelated directory: scenarios, models and tables come from package data or the
cache, never from the source tree."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def run(command, **kwargs):
    result = subprocess.run(command, capture_output=True, text=True, **kwargs)
    assert result.returncode == 0, f"{command}:\n{result.stdout}\n{result.stderr}"
    return result


@pytest.mark.slow  # builds the wheel, installs it and compiles its kernels afresh
@pytest.mark.skipif(not (REPO / "pyproject.toml").exists(), reason="needs the source tree")
def test_wheel_installs_and_runs_a_scenario_from_anywhere(tmp_path):
    source, dist, site, elsewhere = (tmp_path / name for name in
                                     ("source", "dist", "site", "elsewhere"))
    elsewhere.mkdir()
    # A copy, so the build leaves nothing in the checkout.
    shutil.copytree(REPO, source, ignore=shutil.ignore_patterns(
        ".venv", ".git", "build", "*.egg-info", "__pycache__", "out", "docs"))
    # No build isolation: setuptools and wheel come with the test extra, so no download.
    run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
         "-w", str(dist), str(source)], cwd=tmp_path)
    wheel, = dist.glob("maglev_haptics-*.whl")
    run([sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(site),
         str(wheel)])
    env = {**os.environ, "PYTHONPATH": str(site), "MPLBACKEND": "Agg"}
    where = run([sys.executable, "-c", "import maglev_haptics; print(maglev_haptics.__file__)"],
                cwd=elsewhere, env=env).stdout
    assert Path(where.strip()).is_relative_to(site)
    run([str(site / "bin" / "maglev"), "run", "levitate", "--duration", "0.3", "--no-meshcat",
         "--out", "out"], cwd=elsewhere, env=env)
    summary = json.loads((elsewhere / "out" / "summary.json").read_text())
    assert summary["duration_s"] == pytest.approx(0.3)
    assert summary["max_coil_current_a"] > 0.1  # it levitated: the coils carried current
