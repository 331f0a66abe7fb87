"""Runs inside the LeRobot venv (scripts/interop.sh): LeRobot's own runtime acts with a ``jepa`` policy folder.

    python interop_lerobot_policy_peer.py act POLICY_DIR OBS.npz OUT.npz

The policy is built the way ``lerobot-eval`` builds it (``make_policy`` from the folder's config, LeRobot's
``make_pre_post_processors`` from its processor files, the plugin found by ``register_third_party_plugins``)
and fed OBS.npz's observations one env step at a time through LeRobot's own ``preprocess_observation`` (as
gym-pusht hands them over: ``pixels`` uint8 (96, 96, 3), ``agent_pos`` float64), the preprocessor,
``select_action`` and the postprocessor; ``reset()`` at every episode start. OUT.npz: every action, every
decision's z_hat and step, and the NMSE of each z_hat against the realized latent (the plugin's future log).
"""
import sys
import time

import numpy as np
import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.envs.configs import PushtEnv
from lerobot.envs.utils import preprocess_observation
from lerobot.policies.factory import make_policy, make_pre_post_processors
from lerobot.utils.import_utils import register_third_party_plugins


def act(policy_dir: str, src: str, out: str) -> None:
    register_third_party_plugins()
    cfg = PreTrainedConfig.from_pretrained(policy_dir)
    cfg.pretrained_path = policy_dir
    policy = make_policy(cfg, env_cfg=PushtEnv())
    pre, post = make_pre_post_processors(cfg, pretrained_path=policy_dir)
    data = np.load(src)
    frames, state, starts = data["pixels"], data["agent_pos"], set(data["episode_starts"].tolist())
    actions, z_hats, steps, nmse = [], [], [], []
    start = time.perf_counter()
    for t in range(len(frames)):
        if t in starts:
            nmse += [float(x) for pair in policy.future_log for x in pair["nmse"]]
            policy.reset()
            pre.reset()
            post.reset()
        obs = preprocess_observation({"pixels": frames[t][None], "agent_pos": state[t][None]})
        before = policy.last_decision
        with torch.inference_mode():
            action = post(policy.select_action(pre(obs)))
        actions.append(action.numpy()[0])
        if policy.last_decision is not before:
            steps.append(t)
            if policy.last_decision.z_hat is not None:      # MIP predicts no future latent
                z_hats.append(policy.last_decision.z_hat[0])
    nmse += [float(x) for pair in policy.future_log for x in pair["nmse"]]
    np.savez(out, actions=np.stack(actions), z_hat=np.asarray(z_hats, dtype=np.float32),
             decision_index=np.asarray(steps), nmse=np.asarray(nmse), seconds=time.perf_counter() - start)


if __name__ == "__main__":
    if len(sys.argv) != 5 or sys.argv[1] != "act":
        raise SystemExit(__doc__)
    act(*sys.argv[2:])
