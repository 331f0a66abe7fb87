"""robomimic 0.3.0 itself as the oracle of JEPA/Lift-v0: its ``EnvRobosuite`` (in the venv scripts/interop.sh builds:
robomimic's pins clash with ours) sees the states it steps through as our env does, and the goals robosuite sets in
its replay of delta actions are our absolute actions. Skipped until that venv is built (`make interop`, which then
runs the same checks on Lift, Can and Square and on robosuite's human Lift demonstrations:
scripts/interop_robomimic.py).
"""
from pathlib import Path

import gymnasium as gym
import pytest
from script_loader import load_script

pytest.importorskip("robosuite", reason="robosuite is part of the [sim] extra")

import jepa_envs  # noqa: E402,F401  registers the ids
from jepa_envs.datasets.convert_abs_actions import delta_to_abs_by_replay  # noqa: E402
from jepa_envs.tasks.robomimic_env import robomimic_env_args  # noqa: E402
from jepa_envs.tasks.robosuite_common import set_control_delta  # noqa: E402

ROOT = Path(__file__).resolve().parents[3]
ROBOMIMIC_PYTHON = ROOT / ".cache" / "interop" / "robomimic" / "bin" / "python"
pytestmark = [pytest.mark.robosuite,
              pytest.mark.skipif(not ROBOMIMIC_PYTHON.exists(),
                                 reason="robomimic's venv is not built (make interop builds .cache/interop/robomimic)")]


def _interop():
    return load_script("interop_robomimic")


def test_robomimic_sees_our_lift_states_as_we_do_and_its_replay_sets_our_absolute_goals(tmp_path):
    check = _interop()
    env = gym.make("JEPA/Lift-v0", image_size=check.SIZE).unwrapped
    spec = env.task_spec
    keys = (*spec.image_keys, *spec.lowdim_keys)
    try:
        env.reset(seed=3)
        model = env.backend.sim.model.get_xml()
        deltas = check.smooth_deltas(seed=3, steps=4)
        _, theirs = check.peer("replay", str(ROBOMIMIC_PYTHON), tmp_path, "Lift",
                               robomimic_env_args(spec.source_task, spec.cameras, check.SIZE), model,
                               env.backend.sim.get_state().flatten()[None], deltas, spec.cameras)
        states = theirs["states"]   # robomimic's rollout of the delta actions from our state
        env.reset(seed=3, options={"model": model, "state": states[0]})
        ours = []
        for state in states:
            env.set_sim_state(state)
            ours.append(env.observe_now())
        rows = check.compare_obs(check.stack(ours), theirs, "obs", keys)
        assert all(r["ok"] for r in rows.values()), rows
        assert all(rows[k]["equal"] for k in spec.image_keys)   # the same pixels, flipped upright alike
        assert all(rows[k]["float32_of_theirs"] for k in spec.lowdim_keys)   # robosuite's values as float32
        set_control_delta(env.backend, True)   # the conversion reads the goals robosuite's delta controller sets
        absolute = delta_to_abs_by_replay(env.backend, states, deltas)
        actions = check.action_diff(absolute, theirs, deltas)
        assert check.action_ok(actions), actions
        assert actions["later"]["position_max_m"] == 0.0
    finally:
        env.close()
