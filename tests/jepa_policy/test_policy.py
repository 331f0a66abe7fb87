"""Policy runtime: action queue, one encoder pass per decision, decision metadata, EMA checkpoint loading."""
import numpy as np
import pytest
import torch

from jepa_envs.datasets.hdf5 import load_dataset
from jepa_envs.tasks.spec import get_task_spec
from jepa_policy.config import ModelConfig
from jepa_policy.dataset import normalizer_stats
from jepa_policy.checkpoint import load_checkpoint
from jepa_policy.model import build_model
from jepa_policy.policy import Policy
from jepa_policy.train import load_config, train

SPEC = get_task_spec("PushT").with_image_size(32)
TINY = {"width": 32, "layers": 1, "heads": 2, "encoder_width": 8, "time_emb_dim": 16, "dropout": 0.0}


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    m = build_model(ModelConfig.for_task(SPEC, **TINY))
    rng = np.random.default_rng(0)
    m.set_normalizer_stats(normalizer_stats(rng.uniform(0, 512, (50, 2)).astype(np.float32),
                                            {"agent_pos": rng.uniform(0, 512, (50, 2)).astype(np.float32)},
                                            ("agent_pos",)))
    return m


def _obs(rng, batch=None):
    lead = () if batch is None else (batch,)
    return {"top_image": rng.integers(0, 256, lead + (32, 32, 3), dtype=np.uint8),
            "agent_pos": rng.uniform(0, 512, lead + (2,)).astype(np.float32)}


def test_act_executes_eight_actions_per_chunk_with_one_encoder_pass_per_decision(model):
    policy = Policy(model, SPEC)
    calls = []
    handle = model.encoder.register_forward_hook(lambda *_: calls.append(policy.t))
    rng = np.random.default_rng(1)
    decisions, actions = [], []
    try:
        for _ in range(20):
            before = policy.last_decision
            actions.append(policy.act(_obs(rng)))
            if policy.last_decision is not before:
                decisions.append(policy.last_decision)
    finally:
        handle.remove()
    assert [d.step for d in decisions] == [0, 8, 16]
    assert calls == [0, 8, 16]                       # the encoder runs once per decision, never in between
    assert all(a.shape == (2,) for a in actions)
    for d in decisions:
        assert d.actions.shape == (16, 2) and d.z_hat.shape == (model.future_dim,)
        assert d.k == 4 and d.target_step == d.step + 4
        executed = np.stack(actions[d.step:d.step + 8])
        np.testing.assert_array_equal(executed, d.actions[:len(executed)])
    policy.reset()
    policy.act(_obs(rng))
    assert policy.last_decision.step == 0


def test_history_pads_with_the_first_frame_and_matches_a_direct_predict(model):
    rng = np.random.default_rng(2)
    o0, o1 = _obs(rng), _obs(rng)
    policy = Policy(model, SPEC)
    chunk0, z0 = policy.predict(o0)
    chunk1, _ = policy.predict(o1)
    stacked = {k: torch.from_numpy(np.stack([o0[k], o0[k]])[None]) for k in o0}
    ref0, refz = model.predict(stacked)
    np.testing.assert_allclose(chunk0, ref0[0].numpy(), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(z0, refz[0].numpy(), rtol=1e-5, atol=1e-5)
    stacked = {k: torch.from_numpy(np.stack([o0[k], o1[k]])[None]) for k in o0}
    np.testing.assert_allclose(chunk1, model.predict(stacked)[0][0].numpy(), rtol=1e-5, atol=1e-5)
    z = policy.encode_future(o1)
    np.testing.assert_allclose(z, model.encode_future({"top_image": torch.from_numpy(o1["top_image"][None])})[0],
                               rtol=1e-5, atol=1e-6)
    assert z.shape == (model.future_dim,)


def test_batched_observations_act_per_env(model):
    rng = np.random.default_rng(3)
    batch = _obs(rng, batch=3)
    policy = Policy(model, SPEC)
    a = policy.act(batch)
    assert a.shape == (3, 2) and policy.last_decision.z_hat.shape == (3, model.future_dim)
    single = Policy(model, SPEC)
    np.testing.assert_allclose(single.act({k: v[1] for k, v in batch.items()}), a[1], rtol=1e-4, atol=1e-3)
    with pytest.raises(ValueError, match="mixing batched and unbatched"):
        policy.act({k: v[0] for k, v in batch.items()})


def test_bad_observations_name_the_problem(model):
    policy = Policy(model, SPEC)
    with pytest.raises(KeyError, match="agent_pos"):
        policy.act({"top_image": np.zeros((32, 32, 3), np.uint8)})
    with pytest.raises(ValueError, match=r"\(S,S,3\)"):
        policy.act({"top_image": np.zeros((32, 32), np.uint8), "agent_pos": np.zeros(2, np.float32)})


def test_frames_of_another_image_size_are_refused_with_the_fix(model):
    policy = Policy(model, SPEC)
    assert policy.image_size == 32
    rng = np.random.default_rng(2)
    wrong = {"top_image": np.zeros((84, 84, 3), np.uint8), "agent_pos": np.zeros(2, np.float32)}
    fix = (r"top_image is 84x84 px but this policy acts on 32x32 px \(its checkpoint's image size\); make the env "
           r"at the policy's size: policy.make_env\(\) or gym.make\('JEPA/PushT-v0', image_size=32\); a robot "
           r"bridge: jepa-robot-bridge serve ... --image-size 32")
    for call in (policy.act, policy.predict, policy.encode_future):
        with pytest.raises(ValueError, match=fix):
            call(wrong)
    with pytest.raises(ValueError, match="top_image is 48x48 px"):
        policy.act({"top_image": np.zeros((4, 48, 48, 3), np.uint8), "agent_pos": np.zeros((4, 2), np.float32)})
    assert policy.act(_obs(rng)).shape == (2,)      # the refused frames left no trace in the history
    assert policy.last_decision.step == 0


def test_images_needed_covers_every_frame_a_decision_uses(model):
    policy = Policy(model, SPEC)
    needed = {t for t in range(60) if policy.images_needed(t)}
    for d in range(0, 60, 8):
        assert {d - 1, d} - {-1} <= needed                # history frames t-1, t
        if d + 4 < 60:
            assert d + 4 in needed                        # future target t+k
    assert needed == {t for t in range(60) if t % 8 in (0, 7, 4)}  # 3 of every 8 frames are rendered

    # the same schedule as the env-side wrapper
    from jepa_envs.tasks.wrappers import render_schedule
    assert sorted(needed) == render_schedule(60, 8, 2, 4)


def test_arm_without_future_head_needs_no_future_frames():
    mip = Policy(build_model(ModelConfig.for_task(SPEC, arm="mip", **TINY)), SPEC)
    assert {t for t in range(60) if mip.images_needed(t)} == {t for t in range(60) if t % 8 in (0, 7)}


def test_from_checkpoint_acts_with_ema_weights(pusht_demo_file, tmp_path):
    demos = load_dataset(pusht_demo_file, task="PushT", image_size=32)
    result = train(load_config("PushT", "quick", out_dir=str(tmp_path), steps=3, warmup_steps=1), demos)
    ckpt = load_checkpoint(result["checkpoint"])
    policy = Policy.from_checkpoint(result["checkpoint"])
    raw = Policy.from_checkpoint(result["checkpoint"], ema=False)
    w = "action_head.weight"
    assert torch.equal(policy.model.state_dict()[w], ckpt["ema"]["module." + w])
    assert torch.equal(raw.model.state_dict()[w], ckpt["model"][w])
    assert not torch.equal(ckpt["ema"]["module." + w], ckpt["model"][w])
    assert policy.spec.image_size == 32 and policy.checkpoint_step == 3
    assert policy.env_args["env_name"] == "PushT"
    assert not policy.model.training
    env = policy.make_env()                              # the task as trained: the checkpoint's 32 px, not 84
    obs, _ = env.reset(seed=0)
    assert obs["top_image"].shape == (32, 32, 3) and policy.image_size == 32
    assert policy.act(obs).shape == (2,)
    assert policy.make_env(image_size=40).reset(seed=0)[0]["top_image"].shape == (40, 40, 3)   # kwargs override
    with pytest.raises(FileNotFoundError, match="does not exist"):
        Policy.from_checkpoint(tmp_path / "missing.pt")
