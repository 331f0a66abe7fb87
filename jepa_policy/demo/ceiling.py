"""The imitation ceiling of a PushT demonstration file: behaviour cloning with perfect perception.

A 3 x 512 MLP sees the true state of the two newest steps (agent position, block position, cos and sin of the
block angle; standardised) and regresses the same 16-action chunk as the image policies (8 executed, the same
window padding as ``dataset.window_indices``). Trained by MSE on [-1, 1] actions and rolled out in the
environment the demonstrations were recorded in, it separates what the demonstrations teach from what the image
encoder and the training budget let a policy learn of it (docs/training.md, "The ceiling re-measured").
``jepa-demo ceiling --dataset FILE`` runs it.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from torch import nn

import jepa_envs  # noqa: F401  (registers the environments)
from jepa_envs.datasets.hdf5 import demo_names, open_hdf5
from jepa_envs.tasks.spec import get_task_spec
from jepa_policy.dataset import window_indices

TASK = "PushT"
STATE_DIM = 5      # PushT state: agent x, y, block x, y, block angle (rad), as jepa_envs/tasks/pusht.py records it


def state_features(states: np.ndarray) -> np.ndarray:
    """(..., 5) PushT states -> (..., 6): agent x, y, block x, y, cos and sin of the angle (no wrap-around)."""
    states = np.asarray(states, dtype=np.float64)
    if states.shape[-1] != STATE_DIM:
        raise ValueError(f"PushT states have {STATE_DIM} values (agent x, y, block x, y, angle); got shape "
                         f"{states.shape}")
    angle = states[..., 4:5]
    return np.concatenate([states[..., :4], np.cos(angle), np.sin(angle)], axis=-1)


def read_state_demos(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """(states (N, 5), actions (N, 2), episode_ends, env_args) of a PushT demonstration file, without its images."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"demonstration file {path} does not exist; write one with "
                                "`jepa-envs make-demos PushT --out FILE`")
    with open_hdf5(path) as f:
        if "data" not in f or "env_args" not in f["data"].attrs:
            raise ValueError(f"{path} is not a demonstration file (no data group with env_args; robomimic layout)")
        env_args = json.loads(f["data"].attrs["env_args"])
        if env_args.get("env_name") != TASK:
            raise ValueError(f"the state ceiling is defined for the embedded PushT task (its states are the agent "
                             f"and block poses); {path} holds {env_args.get('env_name')!r} demonstrations")
        names = demo_names(f["data"])
        if not names:
            raise ValueError(f"{path} holds no demo_N groups")
        states = [f["data"][k]["states"][:] for k in names]
        actions = [f["data"][k]["actions"][:] for k in names]
    ends = np.cumsum([len(a) for a in actions])
    return np.concatenate(states), np.concatenate(actions).astype(np.float32), ends, env_args


class StatePolicy(nn.Module):
    """The MLP with its input standardisation and [-1, 1] action scaling as buffers. ``featurize`` turns a batch of
    state histories into features of ``state_dim`` per step (PushT's: the block angle as cos and sin; the pick
    job's true states are features as they are)."""

    def __init__(self, obs_steps: int, horizon: int, action_dim: int, width: int = 512,
                 state_dim: int = STATE_DIM + 1, featurize=state_features):
        super().__init__()
        self.obs_steps, self.horizon, self.action_dim = obs_steps, horizon, action_dim
        self.featurize = featurize
        d_in = obs_steps * state_dim
        self.net = nn.Sequential(nn.Linear(d_in, width), nn.ReLU(), nn.Linear(width, width), nn.ReLU(),
                                 nn.Linear(width, width), nn.ReLU(), nn.Linear(width, horizon * action_dim))
        self.register_buffer("x_mean", torch.zeros(d_in))
        self.register_buffer("x_std", torch.ones(d_in))
        self.register_buffer("a_low", -torch.ones(action_dim))
        self.register_buffer("a_high", torch.ones(action_dim))

    def features(self, state_history: np.ndarray) -> torch.Tensor:
        """(B, obs_steps, d) states -> standardised (B, obs_steps * state_dim) inputs."""
        x = torch.as_tensor(self.featurize(state_history).reshape(len(state_history), -1), dtype=torch.float32)
        return (x - self.x_mean) / self.x_std

    def scale(self, actions: torch.Tensor) -> torch.Tensor:
        return (actions - self.a_low) / (self.a_high - self.a_low) * 2 - 1

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Standardised inputs -> (B, horizon, action_dim) chunk in [-1, 1] units."""
        return self.net(x).view(-1, self.horizon, self.action_dim)

    @torch.no_grad()
    def act(self, state_history: np.ndarray) -> np.ndarray:
        """(obs_steps, d) states, oldest first -> (horizon, action_dim) actions in env units."""
        chunk = self(self.features(state_history[None]))[0]
        return ((chunk + 1) / 2 * (self.a_high - self.a_low) + self.a_low).numpy()


def train_state_policy(path: str | Path, steps: int = 4000, batch_size: int = 256, lr: float = 1e-3,
                       warmup: int = 200, seed: int = 0) -> tuple[StatePolicy, dict]:
    """Fit the MLP on every window of the file. Returns (policy, {"first_step_mse": mean of the last 500 steps'
    first-action MSE in [-1, 1] units, "windows": count, "env_args": the file's})."""
    if steps < 1 or batch_size < 1 or lr <= 0 or not 0 <= warmup <= steps:
        raise ValueError(f"need steps >= 1, batch_size >= 1, lr > 0 and 0 <= warmup <= steps; got {steps}, "
                         f"{batch_size}, {lr}, {warmup}")
    spec = get_task_spec(TASK)
    states, actions, ends, env_args = read_state_demos(path)
    idx = window_indices(ends, spec.obs_steps, spec.horizon, future_k=0)
    torch.manual_seed(seed)
    policy = StatePolicy(spec.obs_steps, spec.horizon, actions.shape[1])
    raw = state_features(states[idx.obs]).reshape(len(idx.obs), -1)
    policy.x_mean.copy_(torch.as_tensor(raw.mean(0), dtype=torch.float32))
    policy.x_std.copy_(torch.as_tensor(raw.std(0) + 1e-6, dtype=torch.float32))
    policy.a_low.copy_(torch.as_tensor(actions.min(0)))
    policy.a_high.copy_(torch.as_tensor(np.maximum(actions.max(0), actions.min(0) + 1e-6)))
    x = policy.features(states[idx.obs])
    y = policy.scale(torch.as_tensor(actions[idx.action]))
    opt = torch.optim.AdamW(policy.parameters(), lr=lr, weight_decay=1e-6)
    schedule = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda i: min(1.0, (i + 1) / max(warmup, 1)) * 0.5 * (1 + math.cos(math.pi * i / steps)))
    gen = torch.Generator().manual_seed(seed)
    first = []
    policy.train()
    for i in range(steps):
        b = torch.randint(0, len(x), (batch_size,), generator=gen)
        pred = policy(x[b])
        loss = ((pred - y[b]) ** 2).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        schedule.step()
        if i >= steps - 500:
            first.append(float(((pred.detach()[:, 0] - y[b][:, 0]) ** 2).mean()))
    policy.eval()
    return policy, {"first_step_mse": float(np.mean(first)), "windows": int(len(x)), "env_args": env_args}


def evaluate_state_policy(policy: StatePolicy, env_args: dict, episodes: int, seed: int,
                          n_action_steps: int | None = None) -> dict:
    """Seeded rollouts (episode i from seed + i) in the recorded environment, re-planning every
    ``n_action_steps`` (the task's 8 by default). Returns success rate, mean best coverage and mean length."""
    spec = get_task_spec(TASK)
    n_exec = n_action_steps or spec.n_action_steps
    if episodes < 1 or not 1 <= n_exec <= policy.horizon:
        raise ValueError(f"need episodes >= 1 and 1 <= n_action_steps <= {policy.horizon}; got {episodes}, {n_exec}")
    kwargs = dict(env_args.get("env_kwargs", {}))
    kwargs["image_size"] = 16   # the policy never looks at the frame; the smallest render keeps rollouts cheap
    env = gym.make(spec.env_id, **kwargs)
    successes, best, lengths = [], [], []
    try:
        for e in range(episodes):
            env.reset(seed=seed + e)
            history = [env.unwrapped.get_state()] * policy.obs_steps
            plan, k, done, cover, t, info = None, 0, False, 0.0, 0, {}
            while not done:
                if plan is None or k >= n_exec:
                    plan, k = policy.act(np.stack(history[-policy.obs_steps:])), 0
                _, reward, terminated, truncated, info = env.step(plan[k])
                k, t = k + 1, t + 1
                cover = max(cover, float(reward))
                history.append(env.unwrapped.get_state())
                done = terminated or truncated
            successes.append(bool(info["is_success"]))
            best.append(cover)
            lengths.append(t)
    finally:
        env.close()
    return {"episodes": episodes, "seed": seed, "success_rate": float(np.mean(successes)),
            "mean_max_reward": float(np.mean(best)), "mean_length": float(np.mean(lengths))}


def state_ceiling(path: str | Path, seed: int = 0, episodes: int = 200, eval_seed: int = 200_000,
                  steps: int = 4000) -> dict:
    """Train on ``path`` and roll out: the numbers of one row of docs/training.md's ceiling table."""
    policy, fit = train_state_policy(path, steps=steps, warmup=min(200, steps), seed=seed)
    report = evaluate_state_policy(policy, fit["env_args"], episodes, eval_seed)
    return {"dataset": str(path), "train_seed": seed, "steps": steps, "windows": fit["windows"],
            "first_step_mse": fit["first_step_mse"], **report}
