"""MimicGen D1 tasks: the clear error when MimicGen is missing, and (where it is installed) the envs themselves."""
import importlib.util
import os
import subprocess
import sys
import textwrap

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("robosuite", reason="robosuite is part of the [sim] extra")

import jepa_envs  # noqa: E402,F401
from jepa_envs.tasks.mimicgen_env import MimicGenEnv, MimicGenNotInstalled  # noqa: E402

MIMICGEN_IMPORTABLE = importlib.util.find_spec("mimicgen") is not None and \
    importlib.util.find_spec("robosuite_task_zoo") is not None
needs_mimicgen = pytest.mark.skipif(
    not MIMICGEN_IMPORTABLE,
    reason="MimicGen and robosuite-task-zoo source packages not installed (optional; docs/envs_simulation.md)")


def test_missing_mimicgen_names_what_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "mimicgen", None)  # `import mimicgen` now fails as if it were absent
    with pytest.raises(MimicGenNotInstalled) as err:
        gym.make("JEPA/CoffeePreparation-v0")
    msg = str(err.value)
    assert "JEPA/CoffeePreparation-v0" in msg
    assert "git clone https://github.com/NVlabs/mimicgen && jepa-envs install-mimicgen mimicgen." in msg
    assert "do not pip install mimicgen" in msg
    assert "robosuite-task-zoo" not in msg


def test_missing_task_zoo_is_named_for_kitchen(monkeypatch):
    monkeypatch.setitem(sys.modules, "robosuite_task_zoo", None)
    with pytest.raises(MimicGenNotInstalled) as err:
        gym.make("JEPA/Kitchen-v0")
    msg = str(err.value)
    assert "git clone https://github.com/ARISE-Initiative/robosuite-task-zoo && " \
           "jepa-envs install-mimicgen mimicgen --task-zoo robosuite-task-zoo" in msg
    assert "NVlabs/mimicgen" in msg


def test_unrelated_mimicgen_package_is_detected():
    """A module named mimicgen without MimicGen's tasks (like the unrelated PyPI package) is refused clearly.
    Run in a fresh interpreter, where no real MimicGen module is cached yet."""
    code = textwrap.dedent("""
        import sys, types
        sys.modules["mimicgen"] = types.ModuleType("mimicgen")  # importable, but not MimicGen
        from jepa_envs.tasks.mimicgen_env import MimicGenEnv, MimicGenNotInstalled
        try:
            MimicGenEnv("ThreePieceAssembly")
        except MimicGenNotInstalled as e:
            print("REFUSED:", e)
    """)
    out = subprocess.run([sys.executable, "-c", code], env={**os.environ, "MUJOCO_GL": "osmesa"},
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "REFUSED:" in out.stdout and "unrelated PyPI package" in out.stdout


def test_wrong_suite_is_refused():
    with pytest.raises(ValueError, match="MimicGen tasks"):
        MimicGenEnv("Square")


@needs_mimicgen
def test_coffee_preparation_passes_check_env():
    from gymnasium.utils.env_checker import check_env

    env = MimicGenEnv("CoffeePreparation", image_size=32)
    try:
        check_env(env, skip_render_check=True)
        b = env.backend
        assert b.control_freq == 20 and b.reward_shaping is False and b.ignore_done is True
        assert b.robots[0].controller.use_delta is False
    finally:
        env.close()


@needs_mimicgen
@pytest.mark.parametrize("task", ["Kitchen", "ThreePieceAssembly", "HammerCleanup"])
def test_mimicgen_tasks_build_and_step(task):
    env = gym.make(f"JEPA/{task}-v0", image_size=32)
    try:
        base = env.unwrapped
        assert base.task_spec.max_episode_steps == {"Kitchen": 800, "ThreePieceAssembly": 500,
                                                     "HammerCleanup": 500}[task]
        obs, info = env.reset(seed=0)
        assert base.observation_space.contains(obs) and obs["agentview_image"].any()
        assert type(info["is_success"]) is bool
        again, _ = env.reset(seed=0)
        np.testing.assert_array_equal(again["agentview_image"], obs["agentview_image"])
        obs, _, terminated, _, info = env.step(base.hold_action())
        assert base.observation_space.contains(obs)
        assert info["is_success"] is False and terminated is False
    finally:
        env.close()
