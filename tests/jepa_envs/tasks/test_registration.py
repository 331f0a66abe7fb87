"""What gym.make accepts for every JEPA/* id: render modes that work, a clear refusal for those that do not."""
import pickle

import gymnasium as gym
import numpy as np
import pytest

import jepa_envs  # noqa: F401

ALL_IDS = sorted(i for i in gym.registry if i.startswith("JEPA/"))


@pytest.mark.parametrize("env_id", ALL_IDS)
def test_human_render_mode_is_refused_at_make_naming_the_modes_that_work(env_id):
    # refused before any backend is imported or built, so this holds whatever extras are installed
    with pytest.raises(ValueError, match=r"render_mode='human' is not supported.*'rgb_array'.*None"):
        gym.make(env_id, render_mode="human")


def test_rgb_array_renders_and_the_spec_pickles_for_spawned_workers():
    env = gym.make("JEPA/PushT-v0", render_mode="rgb_array", image_size=64)
    try:
        env.reset(seed=0)
        frame = env.render()
        assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[-1] == 3
    finally:
        env.close()
    spec = pickle.loads(pickle.dumps(gym.spec("JEPA/PushT-v0")))
    assert spec.id == "JEPA/PushT-v0"
    assert gym.make(spec).unwrapped.task_spec.name == "PushT"
