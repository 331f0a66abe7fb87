"""Runs inside the gym-pusht venv (scripts/interop.sh): replays given actions in gym-pusht 0.1.8 itself, or in our
standard PushT on this venv's pymunk 6, and records every step.

    python interop_pusht_peer.py gym-pusht IN.npz OUT.npz
    python interop_pusht_peer.py ours IN.npz OUT.npz
    python interop_pusht_peer.py bench gym-pusht|ours OBS_TYPE STEPS    # steps/s of random actions
    python interop_pusht_peer.py sizes                                  # other frame sizes, both envs here

IN.npz: ``seeds`` (S,), ``actions`` (S, T, 2) float32, optionally ``reset_states`` (S, 5) (each episode starts with
``reset(options={"reset_to_state": ...})`` instead of the seeded draw) and ``render_steps`` (frames of ``render()``
to keep, for the first ``render_episodes`` episodes). OUT.npz: per episode and step (reset = step 0) the state
(agent x, y, block x, y, block angle as simulated), the observation's pixels and agent_pos, the keypoints, coverage,
reward, terminated, is_success, n_contacts and vel_agent, and the kept ``render()`` frames.

gym-pusht mode imports nothing of this project; ours mode imports only ``jepa_envs`` from the repository.
"""
import json
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np


def make(kind: str, obs_type: str = "pixels_agent_pos"):
    if kind == "gym-pusht":
        import gym_pusht  # noqa: F401  (registers gym_pusht/PushT-v0)

        env = gym.make("gym_pusht/PushT-v0", obs_type=obs_type, render_mode="rgb_array")
        return env, lambda: env.unwrapped._get_coverage(), lambda: env.unwrapped.get_keypoints(
            env.unwrapped._block_shapes)
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    import jepa_envs  # noqa: F401

    env = gym.make("JEPA/PushTStandard-v0", obs_type=obs_type, render_mode="rgb_array")
    from jepa_envs.tasks.pusht_standard import coverage

    return env, lambda: coverage(env.unwrapped.backend.block_pose), lambda: env.unwrapped.keypoints()


def replay(kind: str, src: str, out: str) -> None:
    data = np.load(src)
    seeds, actions = data["seeds"], data["actions"]
    resets = data["reset_states"] if "reset_states" in data else None
    render_steps = [int(t) for t in data["render_steps"]] if "render_steps" in data else []
    render_episodes = int(data["render_episodes"]) if "render_episodes" in data else 0
    env, get_coverage, get_keypoints = make(kind)
    n, steps = actions.shape[:2]
    rec = {"state": np.zeros((n, steps + 1, 5)), "pixels": None, "agent_pos": np.zeros((n, steps + 1, 2)),
           "keypoints": np.zeros((n, steps + 1, 16)), "coverage": np.zeros((n, steps + 1)),
           "reward": np.zeros((n, steps + 1)), "terminated": np.zeros((n, steps + 1), bool),
           "is_success": np.zeros((n, steps + 1), bool), "n_contacts": np.zeros((n, steps + 1), np.int64),
           "vel_agent": np.zeros((n, steps + 1, 2))}
    renders = []
    t0 = time.perf_counter()
    for i, seed in enumerate(seeds):
        options = None if resets is None else {"reset_to_state": resets[i]}
        obs, info = env.reset(seed=int(seed), options=options)
        for t in range(steps + 1):
            if t > 0:
                obs, reward, terminated, _, info = env.step(actions[i, t - 1])
                rec["reward"][i, t], rec["terminated"][i, t] = reward, terminated
            if rec["pixels"] is None:
                rec["pixels"] = np.zeros((n, steps + 1, *obs["pixels"].shape), np.uint8)
            rec["pixels"][i, t] = obs["pixels"]
            rec["agent_pos"][i, t] = obs["agent_pos"]
            rec["state"][i, t] = [*info["pos_agent"], *info["block_pose"]]
            rec["keypoints"][i, t] = np.asarray(get_keypoints()).reshape(-1)
            rec["coverage"][i, t] = get_coverage()
            rec["is_success"][i, t] = info["is_success"]
            rec["n_contacts"][i, t] = info["n_contacts"]
            rec["vel_agent"][i, t] = info["vel_agent"]
            if i < render_episodes and t in render_steps:
                renders.append(env.render())
    seconds = time.perf_counter() - t0
    np.savez_compressed(out, renders=np.array(renders, np.uint8), **rec)
    import pymunk

    print(json.dumps({"kind": kind, "episodes": int(n), "steps": int(steps), "seconds": round(seconds, 2),
                      "pymunk": pymunk.version}))


def bench(kind: str, obs_type: str, steps: str) -> None:
    """Wall and CPU time of ``steps`` env steps with uniform random actions (resets when an episode ends)."""
    env, _, _ = make(kind, obs_type)
    actions = np.random.default_rng(0).uniform(0, 512, (int(steps), 2)).astype(np.float32)
    env.reset(seed=0)
    for a in actions[:20]:   # warm caches
        env.step(a)
    wall, cpu = time.perf_counter(), time.process_time()
    for a in actions:
        _, _, terminated, truncated, _ = env.step(a)
        if terminated or truncated:
            env.reset()
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    print(json.dumps({"kind": kind, "obs_type": obs_type, "steps": int(steps), "wall_s": wall, "cpu_s": cpu}))


SIZES = ((680, 680, 96, 96), (384, 256, 96, 96), (200, 300, 128, 96), (96, 96, 64, 64))


def sizes() -> None:
    """gym-pusht's other ``visualization_width/height`` and ``observation_width/height``: both envs (ours on this
    venv's pymunk) reset with seed 3 and take the same 5 actions; per size, how many ``pixels`` observations and
    ``render()`` frames are identical."""
    import gym_pusht  # noqa: F401

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    import jepa_envs  # noqa: F401

    actions = np.array([[100, 400], [300, 200], [450, 60], [256, 256], [20, 500]], np.float32)
    rows = []
    for vw, vh, ow, oh in SIZES:
        kw = dict(obs_type="pixels_agent_pos", render_mode="rgb_array", visualization_width=vw,
                  visualization_height=vh, observation_width=ow, observation_height=oh)
        frames = []
        for env_id in ("gym_pusht/PushT-v0", "JEPA/PushTStandard-v0"):
            env = gym.make(env_id, **kw)
            obs, _ = env.reset(seed=3)
            got = [(obs["pixels"].copy(), env.render().copy())]
            for a in actions:
                obs, *_ = env.step(a)
                got.append((obs["pixels"].copy(), env.render().copy()))
            env.close()
            frames.append(got)
        rows.append({"visualization": [vw, vh], "observation": [ow, oh], "frames": len(frames[0]),
                     "render_shape": list(frames[1][0][1].shape), "pixels_shape": list(frames[1][0][0].shape),
                     "pixels_equal": sum(np.array_equal(a[0], b[0]) for a, b in zip(*frames)),
                     "render_equal": sum(np.array_equal(a[1], b[1]) for a, b in zip(*frames))})
    print(json.dumps(rows))


if __name__ == "__main__":
    if sys.argv[1] == "sizes":
        sizes()
    elif sys.argv[1] == "bench":
        bench(*sys.argv[2:5])
    else:
        replay(*sys.argv[1:4])
