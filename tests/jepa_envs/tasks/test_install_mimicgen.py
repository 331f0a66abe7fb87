"""`jepa-envs install-mimicgen DIR`: refuses what is not a MimicGen clone or an impostor package, and (where local
clones are present) installs them into a fresh environment in which the D1 tasks build and step."""
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from jepa_envs.cli import main
from jepa_envs.tasks.install_mimicgen import InstallError, install

ROOT = Path(__file__).resolve().parents[2]


def _clone_of(env_var: str, *names: str) -> Path | None:
    """A local clone named by ``env_var`` or sitting beside this checkout."""
    candidates = [os.environ.get(env_var)] + [str(ROOT.parent / n) for n in names]
    return next((Path(c) for c in candidates if c and (Path(c) / "setup.py").is_file()), None)


MIMICGEN_CLONE = _clone_of("JEPA_MIMICGEN_CLONE", "mimicgen")
TASK_ZOO_CLONE = _clone_of("JEPA_TASK_ZOO_CLONE", "robosuite-task-zoo")


def _fake_clone(root: Path, name: str = "mimicgen", with_tasks: bool = True) -> Path:
    root.mkdir(parents=True)
    (root / "setup.py").write_text(f'from setuptools import setup\nsetup(name="{name}")\n')
    if with_tasks:
        (root / "mimicgen" / "envs" / "robosuite").mkdir(parents=True)
        (root / "mimicgen" / "envs" / "robosuite" / "coffee.py").write_text("")
    return root


def test_what_is_not_a_mimicgen_clone_is_refused_with_the_clone_command(tmp_path, capsys):
    cases = [
        (tmp_path / "absent", "is not a directory; clone it with: git clone https://github.com/NVlabs/mimicgen"),
        (_fake_clone(tmp_path / "zoo", name="robosuite_task_zoo", with_tasks=False),
         "is not a clone of https://github.com/NVlabs/mimicgen (no setup.py naming 'mimicgen')"),
        (_fake_clone(tmp_path / "partial", with_tasks=False),
         "lacks mimicgen/envs/robosuite/coffee.py: an incomplete clone"),
    ]
    for path, message in cases:
        assert main(["install-mimicgen", str(path)]) == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err


def test_the_unrelated_pypi_mimicgen_is_named_and_nothing_is_installed(tmp_path, monkeypatch):
    impostor = tmp_path / "site"
    (impostor / "mimicgen").mkdir(parents=True)
    (impostor / "mimicgen" / "__init__.py").write_text("")   # a 'mimicgen' without MimicGen's task modules
    monkeypatch.setenv("PYTHONPATH", str(impostor))
    logged = []
    with pytest.raises(InstallError, match=r"not NVlabs' MimicGen is installed .*pip uninstall -y mimicgen"):
        install(_fake_clone(tmp_path / "clone"), python=sys.executable, log=logged.append)
    assert not any("pip install" in line for line in logged)


@pytest.mark.skipif(MIMICGEN_CLONE is None or TASK_ZOO_CLONE is None,
                    reason="no local clones of MimicGen and robosuite-task-zoo (set JEPA_MIMICGEN_CLONE and "
                           "JEPA_TASK_ZOO_CLONE, or clone them beside this checkout)")
def test_local_clones_install_into_a_fresh_environment_where_the_four_tasks_run(tmp_path):
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(venv)], check=True)
    python = str(venv / "bin" / "python")
    assert subprocess.run([python, "-c", "import mimicgen.envs"], capture_output=True, cwd=tmp_path).returncode != 0
    out = subprocess.run([python, "-m", "jepa_envs.cli", "install-mimicgen", str(MIMICGEN_CLONE),
                          "--task-zoo", str(TASK_ZOO_CLONE)], capture_output=True, text=True, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert "importable: CoffeePreparation, ThreePieceAssembly, Kitchen, HammerCleanup" in out.stdout
    assert f"keep {MIMICGEN_CLONE.resolve()}" in out.stdout
    script = textwrap.dedent("""
        import gymnasium as gym, jepa_envs
        for task in ("CoffeePreparation", "Kitchen", "ThreePieceAssembly", "HammerCleanup"):
            env = gym.make(f"JEPA/{task}-v0", image_size=32)
            obs, _ = env.reset(seed=0)
            obs, *_ = env.step(env.unwrapped.hold_action())
            assert obs["agentview_image"].shape == (32, 32, 3), task
            env.close()
        print("four tasks ran")
    """)
    ran = subprocess.run([python, "-c", script], capture_output=True, text=True, cwd=tmp_path,
                         env={**os.environ, "MUJOCO_GL": "osmesa"})
    assert "four tasks ran" in ran.stdout, ran.stderr[-2000:]
