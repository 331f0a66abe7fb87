"""The code passes the linter configured in pyproject.toml ([tool.ruff]: pycodestyle and pyflakes at 120 columns),
when ruff is installed (scripts/setup.sh installs it with the dev extra)."""
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.skipif(shutil.which("ruff") is None, reason="ruff is not installed (pip install -e '.[dev]')")
def test_ruff_finds_nothing():
    done = subprocess.run(["ruff", "check", "--output-format", "concise", "."], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-2000:]


@pytest.mark.skipif(shutil.which("ruff") is None, reason="ruff is not installed (pip install -e '.[dev]')")
def test_the_linter_reads_the_projects_configuration(tmp_path):
    """A 121-column line is refused and a 120-column one is not: the check above runs with pyproject's settings."""
    (tmp_path / "pyproject.toml").write_text((ROOT / "pyproject.toml").read_text())
    (tmp_path / "ok.py").write_text("x = " + "1" * 116 + "\n")
    (tmp_path / "long.py").write_text("x = " + "1" * 117 + "\n")
    done = subprocess.run(["ruff", "check", "--output-format", "concise", "."], cwd=tmp_path, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 1 and "long.py:1:121: E501" in done.stdout and "ok.py" not in done.stdout
