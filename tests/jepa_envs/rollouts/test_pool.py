"""EnvPool: the same observations whatever the number of worker processes, frozen ended episodes, clear errors,
and workers started from a plain script (no ``if __name__ == "__main__"`` guard)."""
import re
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from jepa_envs.rollouts.pool import EnvPool, WorkerFailure

KW = {"image_size": 32}


def _trajectory(workers: int, steps: int = 12):
    rng = np.random.default_rng(0)
    with EnvPool("JEPA/PushT-v0", 3, workers=workers, env_kwargs=KW, max_steps=8) as pool:
        obs, _ = pool.reset([5, 6, 7], active=[True, True, False])
        out = [obs]
        for t in range(steps):
            pool.set_render_images(t % 2 == 0)
            out.append(pool.step(rng.uniform(100, 400, size=(3, 2)).astype(np.float32)))
        return out


def test_same_observations_for_zero_one_and_two_workers_and_ended_envs_stay_frozen():
    runs = {w: _trajectory(w) for w in (0, 1, 2)}
    for w in (1, 2):
        for a, b in zip(runs[0], runs[w]):
            flat_a = a if isinstance(a, dict) else a[0]
            flat_b = b if isinstance(b, dict) else b[0]
            for key in flat_a:
                np.testing.assert_array_equal(flat_a[key], flat_b[key])
    steps = runs[0][1:]
    truncated = np.array([s[3] for s in steps])
    assert truncated[7].tolist() == [True, True, False]        # max_steps 8 ends the two live episodes
    for s in steps[8:]:                                         # then they are frozen: no reward, no flags
        assert s[1].tolist() == [0.0, 0.0, 0.0] and not s[2].any() and not s[3].any()
        np.testing.assert_array_equal(s[0]["agent_pos"], steps[7][0]["agent_pos"])
    np.testing.assert_array_equal(steps[0][0]["agent_pos"][2], runs[0][0]["agent_pos"][2])   # the spare never moved


def test_bad_calls_and_dead_workers_are_named():
    with pytest.raises(ValueError, match="workers must be >= 0"):
        EnvPool("JEPA/PushT-v0", 2, workers=-1)
    with EnvPool("JEPA/PushT-v0", 2, workers=1, env_kwargs=KW, timeout_s=5) as pool:
        with pytest.raises(ValueError, match=r"one seed per environment \(2\)"):
            pool.reset([1])
        pool.reset([1, 2])
        pool.inject(0, "crash", 7)
        with pytest.raises(WorkerFailure, match=r"rollout worker 0 failed: process ended \(exit code 7\)"):
            pool.step(np.zeros((2, 2), np.float32))
        pool.restart(0, "test")
        pool.reset([1, 2])
        assert pool.describe()["restarts"][0]["reason"] == "test"
    with pytest.raises(RuntimeError, match="closed"):
        pool.reset([1, 2])


def test_workers_start_from_a_script_without_a_main_guard(tmp_path):
    script = tmp_path / "plain_script.py"
    script.write_text(textwrap.dedent("""
        import numpy as np
        from jepa_envs.rollouts.pool import EnvPool
        print("top level ran")
        with EnvPool("JEPA/PushT-v0", 2, workers=2, env_kwargs={"image_size": 32}) as pool:
            obs, _ = pool.reset([0, 1])
            pool.step(np.zeros((2, 2), np.float32))
        print("pool ok", obs["agent_pos"].shape)
    """))
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.count("top level ran") == 1 and "pool ok (2, 2)" in out.stdout   # not re-run in the workers


def test_a_hung_worker_is_found_in_the_limit_derived_from_the_task_not_300_s(monkeypatch):
    monkeypatch.delenv("JEPA_POOL_TIMEOUT_S", raising=False)
    with EnvPool("JEPA/PushT-v0", 2, workers=1, env_kwargs=KW, timeout_floor_s=2.0) as pool:
        limit = pool.describe()["step_timeout_s"][0]
        step_s = pool._workers[0].seconds["step"]          # measured by the worker when it started
        assert limit == max(2.0, 30.0 * 2 * step_s) and limit < 10   # PushT: milliseconds per step
        pool.reset([1, 2])
        pool.step(np.zeros((2, 2), np.float32))
        pool.inject(0, "hang", 60.0)
        started = time.monotonic()
        with pytest.raises(WorkerFailure,
                           match=r"no answer within .*hung; 30 x its 2 env\(s\) x .*JEPA_POOL_TIMEOUT_S"):
            pool.step(np.zeros((2, 2), np.float32))
        waited = time.monotonic() - started
        assert limit * 0.9 <= waited < limit + 5, (waited, limit)   # the derived limit, not 300 s
        pool.restart(0, "hung")
        pool.reset([1, 2])


def test_the_fixed_limit_from_timeout_s_or_the_environment(monkeypatch):
    monkeypatch.setenv("JEPA_POOL_TIMEOUT_S", "1.5")
    with EnvPool("JEPA/PushT-v0", 1, workers=1, env_kwargs=KW) as pool:
        assert pool.describe()["step_timeout_s"] == [1.5]
        pool.reset([0])
        pool.inject(0, "hang", 3.0)                      # past the limit, and over soon after (close waits for it)
        started = time.monotonic()
        with pytest.raises(WorkerFailure,
                           match=r"within 1.5s \(hung; the fixed limit \(timeout_s / JEPA_POOL_TIMEOUT_S"):
            pool.step(np.zeros((1, 2), np.float32))
        assert time.monotonic() - started < 6
    with EnvPool("JEPA/PushT-v0", 1, workers=0, env_kwargs=KW, timeout_s=7) as pool:   # the argument wins
        assert pool.timeout_s == 7.0


@pytest.mark.parametrize("value", ["abc", "0", "-5", "nan", "inf", "10s"])
def test_a_bad_JEPA_POOL_TIMEOUT_S_is_refused_in_one_line_before_any_worker_starts(monkeypatch, value):
    monkeypatch.setenv("JEPA_POOL_TIMEOUT_S", value)
    with pytest.raises(ValueError, match=rf"^JEPA_POOL_TIMEOUT_S='{re.escape(value)}' is not a number of seconds > 0; "
                                         r"set it .* or unset it to derive the limit from the task$"):
        EnvPool("JEPA/PushT-v0", 1, workers=1, env_kwargs=KW)
    monkeypatch.delenv("JEPA_POOL_TIMEOUT_S")
    with pytest.raises(ValueError, match="timeout_s must be a finite number of seconds > 0"):
        EnvPool("JEPA/PushT-v0", 1, workers=1, env_kwargs=KW, timeout_s=float("nan"))
