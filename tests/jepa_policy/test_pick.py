"""The pick job's own parts (jepa_policy/demo/pick.py): its budget's refusals, the true state its ceiling reads,
the action errors of the human-data check against a reference formula, and the success counts of its report."""
from __future__ import annotations

from types import SimpleNamespace

import gymnasium as gym
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import binomtest

pytest.importorskip("robosuite", reason="robosuite is part of the [sim] extra")

from jepa_envs.datasets.hdf5 import write_dataset  # noqa: E402
from jepa_envs.tasks.rotations import matrix_to_rot6d, rot6d_to_matrix  # noqa: E402
from jepa_envs.tasks.robosuite_expert import generate_demos  # noqa: E402
from jepa_envs.tasks.spec import get_task_spec  # noqa: E402
from jepa_policy.demo.pick import PickStates, action_errors, pick_config, rate  # noqa: E402

SIZE = 16


def test_the_budget_refuses_what_it_cannot_run():
    with pytest.raises(ValueError, match="the pick job runs Lift, Can; got 'Square'"):
        pick_config("Square")
    with pytest.raises(ValueError, match="--steps must be a positive number"):
        pick_config("Lift", steps=0)
    full, quick = pick_config("Can"), pick_config("Can", "quick")
    assert full.eval_episodes >= 200 and full.demos == 200 and quick.eval_episodes < full.eval_episodes
    assert pick_config("Lift", steps=123).train_overrides["steps"] == 123


def test_rate_counts_successes_failure_kinds_and_the_wilson_interval():
    records = ([{"success": True, "length": n} for n in (50, 60, 70)]
               + [{"success": False, "length": 400, "failure_kind": "never_grasped"}] * 2
               + [{"success": False, "length": 400, "failure_kind": "dropped"}])
    r = rate(records)
    ci = binomtest(3, 6).proportion_ci(confidence_level=0.95, method="wilson")
    assert (r["successes"], r["episodes"], r["rate"]) == (3, 6, 0.5)
    assert r["ci95"] == pytest.approx([ci.low, ci.high])
    assert r["failure_kinds"] == {"never_grasped": 2, "dropped": 1} and r["median_success_length"] == 60


@pytest.mark.robosuite
def test_the_true_state_is_the_robots_lowdim_and_the_objects_pose():
    env = gym.make("JEPA/Lift-v0", image_size=SIZE)
    env.unwrapped.set_render_images(False)
    try:
        obs, _ = env.reset(seed=3)
        states = PickStates(env)
        x = states.now(obs)
        sim, backend = env.unwrapped.backend.sim, env.unwrapped.backend
        cube = sim.data.body_xpos[backend.cube_body_id].copy()
        assert np.array_equal(x[-7:-4], cube) and np.array_equal(x[-4:], sim.data.body_xquat[backend.cube_body_id])
        assert np.array_equal(x[:3], obs["robot0_eef_pos"])
        obs2, _ = env.reset(seed=4)   # another seed places the cube elsewhere: the state says so
        assert not np.allclose(states.now(obs2)[-7:-4], cube)
    finally:
        env.close()


@pytest.mark.robosuite
def test_action_errors_agree_with_scipy_on_a_known_offset(tmp_path):
    """A stand-in policy that answers each window with the recorded action of its newest frame, moved 1 cm
    along x, turned 10 degrees about z and, on every other step, with the gripper's sign flipped: the errors
    must be exactly those (the rotation read by scipy), and each window must be the frame and its predecessor
    within the episode (the first frame padded), as in training."""
    episodes, env_args = generate_demos("Lift", 2, seed=0, image_size=SIZE, reflections=False)
    path = tmp_path / "lift.hdf5"
    write_dataset(path, episodes, env_args)
    eef = np.concatenate([e["obs"]["robot0_eef_pos"] for e in episodes])
    actions = np.concatenate([e["actions"] for e in episodes]).astype(np.float64)
    starts = np.repeat(np.cumsum([0] + [len(e["actions"]) for e in episodes[:-1]]),
                       [len(e["actions"]) for e in episodes])
    turn = Rotation.from_euler("z", 10, degrees=True).as_matrix()

    def index(frame_eef):
        return int(np.argmin(np.abs(eef - frame_eef).sum(axis=1)))

    def decide_from(frames, want_future):
        assert not want_future and len(frames) == 2
        out = []
        for older, newest in zip(frames[0]["robot0_eef_pos"], frames[1]["robot0_eef_pos"]):
            t = index(newest)
            assert index(older) == max(t - 1, starts[t])
            a = actions[t].copy()
            a[0] += 0.01
            a[3:9] = matrix_to_rot6d(turn @ rot6d_to_matrix(a[3:9]))
            a[9] *= -1 if t % 2 else 1
            out.append(a[None])
        return SimpleNamespace(actions=np.stack(out))

    policy = SimpleNamespace(spec=get_task_spec("Lift").with_image_size(SIZE), obs_steps=2, decide_from=decide_from)
    errors = action_errors(policy, path, batch=16)
    assert errors["steps"] == len(actions) and errors["episodes"] == 2
    assert errors["position_cm"]["median"] == pytest.approx(1.0, abs=1e-6)
    assert errors["orientation_deg"]["median"] == pytest.approx(10.0, abs=1e-4)
    recorded = Rotation.from_matrix(rot6d_to_matrix(actions[:, 3:9]))
    moved = Rotation.from_matrix(turn @ rot6d_to_matrix(actions[:, 3:9]))
    assert np.allclose((recorded.inv() * moved).magnitude(), np.radians(10))
    assert errors["gripper_agreement"] == pytest.approx(np.mean(np.arange(len(actions)) % 2 == 0))


def test_a_finished_training_run_is_reused_and_a_changed_one_is_not(pusht_demo_file, tmp_path, one_thread,
                                                                     capsys):
    """A rerun of the job reuses an arm whose stamped config and data match (its wall time stamped beside them
    once had it retrain every time: a killed and restarted Can job lost 16 minutes of training); a changed
    config trains again."""
    from jepa_policy.demo.pick import train_arm, training_wall_s

    run = tmp_path / "mip"
    overrides = {"steps": 2, "batch_size": 2, "eval_every": 0, "eval_episodes": 0, "ckpt_every": 100, "log_every": 1}
    ckpt = train_arm("PushT", "quick", "mip", 0, pusht_demo_file, run, overrides, fresh=False)
    first = (ckpt.stat().st_mtime_ns, training_wall_s(ckpt))
    assert first[1] > 0
    assert train_arm("PushT", "quick", "mip", 0, pusht_demo_file, run, overrides, fresh=False) == ckpt
    assert "reusing" in capsys.readouterr().out
    assert (ckpt.stat().st_mtime_ns, training_wall_s(ckpt)) == first   # untouched, its wall time kept
    train_arm("PushT", "quick", "mip", 0, pusht_demo_file, run, {**overrides, "steps": 3}, fresh=False)
    assert "reusing" not in capsys.readouterr().out and ckpt.stat().st_mtime_ns != first[0]
