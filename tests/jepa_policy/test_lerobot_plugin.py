"""JEPA Policy as a LeRobot policy type (jepa_policy/lerobot_format.py, jepa_policy/lerobot_plugin).

In our env, without LeRobot: the plugin is named and laid out as LeRobot 0.4.4 finds plugins; LeRobot's float
frames come back as the env's bytes; a LeRobot training batch gives the two-step loss our WindowDataset's batch
gives; LeRobot's statistics fit our normalisers; a LeRobot policy folder loads into ``Policy`` and acts as the
network it holds. In LeRobot's venv (`make interop` builds it; skipped without it): a checkpoint of ours converted
by the plugin acts bit-equal in LeRobot's runtime and ours. (scripts/interop_lerobot_policy.py runs lerobot-train,
lerobot-eval and 1,000 observations.)"""
from __future__ import annotations

import ast
import json
import subprocess
import tomllib
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from jepa_envs.tasks.spec import get_task_spec
from jepa_policy.checkpoint import FORMAT, EMA_PREFIX
from jepa_policy.config import ModelConfig
from jepa_policy.dataset import WindowDataset, normalizer_stats as our_stats
from jepa_policy.lerobot_format import (lerobot_features, lerobot_fields, model_batch, model_config,
                                        normalizer_stats, observation, read_lerobot_checkpoint, uint8_frames)
from jepa_policy.model import build_model
from jepa_policy.policy import Policy

ROOT = Path(__file__).resolve().parents[2]
PLUGIN = ROOT / "jepa_policy" / "lerobot_plugin"
LEROBOT_PYTHON = ROOT / ".cache" / "interop" / "lerobot" / "bin" / "python"
SIZE = 32
SMALL = {"width": 32, "layers": 1, "heads": 2, "encoder_width": 8, "time_emb_dim": 16, "dropout": 0.0,
         "image_norm": "dataset"}


def _spec():
    return get_task_spec("PushTStandard").with_image_size(SIZE)


def _episode(n: int = 24, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    return {"top_image": rng.integers(0, 256, (n, SIZE, SIZE, 3), dtype=np.uint8),
            "agent_pos": rng.uniform(0, 512, (n, 2)), "action": rng.uniform(0, 512, (n, 2)).astype(np.float32)}


def _model(ep: dict, arm: str = "jepa"):
    cfg = ModelConfig.for_task(_spec(), arm, image_size=SIZE, **SMALL)
    torch.manual_seed(0)
    model = build_model(cfg)
    model.set_normalizer_stats(our_stats(ep["action"], ep, ["agent_pos"], ["top_image"]))
    return model


def _lerobot_folder(model, path: Path) -> Path:
    """What LeRobot's save_pretrained writes for the plugin's policy: config.json and model.safetensors."""
    path.mkdir(parents=True)
    features = {k: {"type": kind, "shape": list(shape)} for k, (kind, shape) in
                lerobot_features(_spec(), SIZE).items()}
    config = {"type": "jepa", **lerobot_fields(model.cfg, "PushTStandard"),
              "input_features": {k: v for k, v in features.items() if k != "action"},
              "output_features": {"action": features["action"]}}
    path.joinpath("config.json").write_text(json.dumps(config))
    save_file({"model." + k: v.contiguous() for k, v in model.state_dict().items()}, path / "model.safetensors")
    return path


def test_the_plugin_is_named_and_laid_out_as_lerobot_finds_plugins():
    """LeRobot 0.4.4 imports each installed distribution whose Name starts with lerobot_policy_ under that very
    name, then finds <Name>Policy in modeling_* and make_<type>_pre_post_processors in processor_* beside the
    configuration_* module of the registered <Name>Config (lerobot/policies/factory.py)."""
    name = tomllib.loads((PLUGIN / "pyproject.toml").read_text())["project"]["name"]
    assert name.startswith("lerobot_policy_") and (PLUGIN / name / "__init__.py").is_file()

    def defined(module: str) -> set[str]:
        tree = ast.parse((PLUGIN / name / f"{module}.py").read_text())
        return {n.name for n in tree.body if isinstance(n, (ast.ClassDef, ast.FunctionDef))}

    assert "JEPAConfig" in defined("configuration_jepa")
    assert "JEPAPolicy" in defined("modeling_jepa")
    assert "make_jepa_pre_post_processors" in defined("processor_jepa")
    assert '@PreTrainedConfig.register_subclass("jepa")' in (PLUGIN / name / "configuration_jepa.py").read_text()


def test_lerobot_float_frames_come_back_as_the_env_bytes():
    """All 256 levels, divided by 255 as LeRobot's loaders and preprocess_observation do, round back exactly."""
    frames = torch.arange(256, dtype=torch.uint8).view(1, 16, 16).expand(3, 16, 16).contiguous()
    assert torch.equal(uint8_frames(frames.float() / 255), frames.movedim(0, -1))
    assert torch.equal(uint8_frames(frames), frames.movedim(0, -1))


def test_a_lerobot_batch_gives_the_loss_our_window_batch_gives():
    """LeRobot's loader clamps delta indices at an episode's ends (frames -1, 0 and +k; actions 0 .. H-1), as our
    WindowDataset pads; converted, its batch is the same batch to the model, so the loss is the same number."""
    ep, spec = _episode(), _spec()
    model = _model(ep).train()
    windows = WindowDataset({"top_image": ep["top_image"], "agent_pos": ep["agent_pos"].astype(np.float32)},
                            ep["action"], np.array([len(ep["action"])]), spec.image_keys, spec.lowdim_keys,
                            2, spec.horizon, spec.future_k)
    idx = [0, 5, 20, 23]
    ours = windows[idx]
    n = len(ep["action"])
    obs_rows = [[min(max(t + d, 0), n - 1) for d in (-1, 0, spec.future_k)] for t in idx]
    act_rows = [[min(t + d, n - 1) for d in range(spec.horizon)] for t in idx]
    lerobot = {"observation.image": torch.from_numpy(ep["top_image"][obs_rows]).movedim(-1, -3).float() / 255,
               "observation.state": torch.from_numpy(ep["agent_pos"][obs_rows].astype(np.float32)),
               "action": torch.from_numpy(ep["action"][act_rows])}
    converted = model_batch(lerobot, spec, obs_steps=2, with_future=True)
    losses = []
    for batch in (ours, converted):
        loss, _ = model.compute_loss(batch, torch.Generator().manual_seed(3))
        losses.append(loss.item())
    assert losses[0] == losses[1]
    with pytest.raises(ValueError, match=r"observation.image must be \(B, 3, 3, h, w\)"):
        model_batch({**lerobot, "observation.image": lerobot["observation.image"][:, :2]}, spec, 2, True)


def test_lerobot_statistics_fit_our_normalisers_and_a_missing_one_is_named():
    spec = _spec()
    stats = {"action": {"min": np.array([1.0, 2.0]), "max": np.array([500.0, 510.0])},
             "observation.state": {"min": np.array([3.0, 4.0]), "max": np.array([400.0, 410.0])},
             "observation.image": {"mean": np.full((3, 1, 1), 0.9), "std": np.full((3, 1, 1), 0.1)}}
    ours = normalizer_stats(stats, spec)
    assert ours["agent_pos"]["max"].tolist() == [400.0, 410.0] and ours["top_image"]["mean"].shape == (3,)
    model = _model(_episode())
    model.set_normalizer_stats(ours)
    assert model.normalizer.normalize("action", torch.tensor([[1.0, 510.0]])).tolist() == [[-1.0, 1.0]]
    with pytest.raises(ValueError, match=r"observation.image.std"):
        normalizer_stats({**stats, "observation.image": {"mean": stats["observation.image"]["mean"]}}, spec)


def test_a_lerobot_policy_folder_acts_in_our_runtime_as_its_network(tmp_path):
    """``Policy.from_checkpoint`` reads the folder (no LeRobot here): decisions equal the network's own, the
    step comes from LeRobot's training_state, and LeRobot's batched observation converts to the same action."""
    ep = _episode()
    model = _model(ep).eval()
    folder = _lerobot_folder(model, tmp_path / "checkpoints" / "000010" / "pretrained_model")
    (folder.parent / "training_state").mkdir()
    (folder.parent / "training_state" / "training_step.json").write_text('{"step": 10}')
    policy = Policy.from_checkpoint(folder, detectors=False)
    direct = Policy(model, _spec())
    assert policy.checkpoint_step == 10 and policy.model.cfg == model.cfg
    for t in range(12):
        obs = {"top_image": ep["top_image"][t], "agent_pos": ep["agent_pos"][t]}
        assert np.array_equal(policy.act(obs), direct.act(obs))
        assert np.array_equal(policy.last_decision.z_hat, direct.last_decision.z_hat)
    lerobot_obs = {"observation.image": torch.from_numpy(ep["top_image"][:1]).movedim(-1, -3).float() / 255,
                   "observation.state": torch.from_numpy(ep["agent_pos"][:1]).float()}
    converted = observation(lerobot_obs, _spec())
    assert np.array_equal(converted["top_image"], ep["top_image"][:1])
    assert np.array_equal(converted["agent_pos"], ep["agent_pos"][:1].astype(np.float32))
    with pytest.raises(ValueError, match=r"observation.image is 96x96 px but this jepa policy acts on 32x32 px"):
        observation({**lerobot_obs, "observation.image": torch.zeros(1, 3, 96, 96)}, _spec())


def test_a_folder_of_another_policy_or_task_is_refused_with_the_fix(tmp_path):
    model = _model(_episode())
    folder = _lerobot_folder(model, tmp_path / "act")
    config = json.loads((folder / "config.json").read_text())
    folder.joinpath("config.json").write_text(json.dumps({**config, "type": "act"}))
    with pytest.raises(ValueError, match="'act' policy"):
        read_lerobot_checkpoint(folder)
    folder.joinpath("config.json").write_text(json.dumps({**config, "task": "Lift"}))
    with pytest.raises(ValueError, match=r"task Lift .*agentview VISUAL .* is missing.*--policy.task"):
        read_lerobot_checkpoint(folder)
    with pytest.raises(ValueError, match="--policy.type=diffusion"):
        model_config({**config, "arm": "diffusion"}, SIZE)


@pytest.mark.slow      # 20-45 s here, most of it LeRobot's own imports
@pytest.mark.timeout(300)
@pytest.mark.skipif(not LEROBOT_PYTHON.exists(), reason="LeRobot's venv is not built (make interop)")
def test_ours_converted_acts_bit_equal_in_lerobots_runtime(tmp_path):
    """The plugin's converter writes a LeRobot folder from a checkpoint of ours; LeRobot's own factory, processors
    and select_action (scripts/interop_lerobot_policy_peer.py) act on 40 observations of two episodes exactly
    as our Policy does on the .pt, and z_hat too."""
    ep = _episode(n=40, seed=1)
    model = _model(ep)
    pt = tmp_path / "ours.pt"
    torch.save({"format": FORMAT, "step": 7, "model_config": model.cfg.to_dict(), "task": "PushTStandard",
                "image_size": SIZE, "env_args": None,
                "ema": {EMA_PREFIX + k: v for k, v in model.state_dict().items()}}, pt)
    obs = tmp_path / "obs.npz"
    np.savez(obs, pixels=ep["top_image"], agent_pos=ep["agent_pos"], episode_starts=np.array([0, 25]))
    # one process (LeRobot imports in seconds): the converter, then LeRobot's runtime on the folder it wrote
    script = ("import sys; sys.path.insert(0, sys.argv[1]); from lerobot_policy_jepa.convert import to_lerobot; "
              "import interop_lerobot_policy_peer as peer; to_lerobot(sys.argv[2], sys.argv[3]); "
              "peer.act(sys.argv[3], sys.argv[4], sys.argv[5])")
    subprocess.run([str(LEROBOT_PYTHON), "-c", script, str(ROOT / "scripts"), str(pt), str(tmp_path / "lr"), str(obs),
                    str(tmp_path / "theirs.npz")], check=True, capture_output=True)
    theirs = np.load(tmp_path / "theirs.npz")
    policy, actions, z_hats = Policy.from_checkpoint(pt, detectors=False), [], []
    for t in range(40):
        if t in (0, 25):
            policy.reset()
        before = policy.last_decision
        actions.append(policy.act({"top_image": ep["top_image"][t], "agent_pos": ep["agent_pos"][t]}))
        if policy.last_decision is not before:
            z_hats.append(policy.last_decision.z_hat)
    assert np.array_equal(np.stack(actions), theirs["actions"])
    assert np.array_equal(np.stack(z_hats), theirs["z_hat"])
    assert len(theirs["nmse"]) > 0       # the plugin paired z_hat with the realized latent of frame t+k
