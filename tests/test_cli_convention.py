"""One command-line convention across the five console scripts (docs/architecture.md, STYLE.md).

``--help`` of every console script imports nothing heavy (no torch, no simulator, no renderer probe, no database
layer), so it answers at once on a fresh install.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

# console script -> the module whose main() it runs
SCRIPTS = {
    "jepa-envs": "jepa_envs.cli",
    "jepa-policy": "jepa_policy.cli",
    "jepa-monitor": "monitor_service.cli",
    "jepa-robot-bridge": "jepa_robot.cli",   # operator_cli hands --help to it (os.execv)
}
HEAVY = ("torch", "mujoco", "robosuite", "jepa_envs.tasks.render", "sqlalchemy", "fastapi", "h5py", "scipy",
         "matplotlib")


def _modules_after_help(module: str, tmp_path) -> set[str]:
    """The modules a fresh interpreter holds after ``main(["--help"])`` of ``module`` (an empty cache folder: no
    measured renderer choice to read)."""
    code = (f"import json, sys\nfrom {module} import main\n"
            "try:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
            "sys.stderr.write(json.dumps(sorted(sys.modules)))\n")
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    env["XDG_CACHE_HOME"] = str(tmp_path)
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "usage:" in done.stdout
    return set(json.loads(done.stderr.strip().splitlines()[-1]))


@pytest.mark.parametrize("script", sorted(SCRIPTS))
def test_help_imports_nothing_heavy(script, tmp_path):
    loaded = _modules_after_help(SCRIPTS[script], tmp_path)
    assert [m for m in HEAVY if m in loaded] == []
