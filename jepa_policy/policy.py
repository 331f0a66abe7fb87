"""The acting runtime (LeRobot-style): observation history, action queue, decision metadata.

The paper's schedule (Sec. 4.1, "Timing"): at a decision step t the policy predicts H actions from the frames
t-obs_steps+1 .. t, executes the first ``n_action_steps`` (8) of them, then decides again. Each decision also
predicts z_hat for the frame t+k (Sec. 3.6); once that frame arrives, ``encode_future`` gives the realized
latent E_rgb(o_{t+k}) so a robot loop or the evaluator can score e_fc = NMSE(z_hat, z_real).

Observations are single env observations (``<camera>_image`` uint8 (S,S,3) and low-dim float32 (D,)) or a
batch of them with a leading env axis (vector envs, all stepping in lockstep).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

from jepa_envs.tasks.spec import TaskSpec, get_task_spec
from jepa_envs.tasks.wrappers import frames_to_render
from jepa_policy.checkpoint import load_checkpoint, load_model
from jepa_policy.detectors import EmbeddingDetectors, detector_path, load_detectors, stac
from jepa_policy.evaluate import env_kwargs_for


@dataclass
class Decision:
    """One replanning event: what was predicted at step t and when its future target arrives."""

    step: int                 # t: episode step of the newest observation frame used
    k: int                    # future horizon in env steps
    actions: np.ndarray       # (H, A) or (B, H, A), unnormalised
    z_hat: np.ndarray | None  # (D,) or (B, D): predicted E_rgb(o_{t+k}); None for arms without a future head
    # per-decision failure scores known at the decision (jepa_policy/detectors.py): "stac" always (NaN at an
    # episode's first decision), "rnd", "pca_kmeans", "mahalanobis" with fitted detectors; float or (B,)
    scores: dict = field(default_factory=dict)
    embedding: np.ndarray | None = None   # c_t (width,) or (B, width); None for arms without one

    @property
    def target_step(self) -> int:
        return self.step + self.k


class Policy:
    """Acts with a trained model (EMA weights when loaded from a checkpoint); ``detectors`` (fitted after the
    policy, ``jepa-policy fit-detectors``) add the embedding scores to every decision."""

    def __init__(self, model: torch.nn.Module, spec: TaskSpec, device: str | torch.device = "cpu",
                 detectors: EmbeddingDetectors | None = None):
        self.device = torch.device(device)
        self.model = model.to(self.device).eval()
        self.spec = spec
        self.detectors = detectors
        # the policy's own action scaling to [-1, 1]: STAC compares chunks in these units
        fields = getattr(getattr(model, "normalizer", None), "fields", {})
        self._action_affine = ((fields["action"].scale.cpu().numpy().astype(np.float64),
                                fields["action"].offset.cpu().numpy().astype(np.float64))
                               if "action" in fields else None)
        self.env_args: dict | None = None   # the dataset's env_args, so evaluation rebuilds the same env
        self.checkpoint_step: int | None = None
        # history length, chunk length and future horizon k are the MODEL's (a checkpoint trained with
        # --model '{"future_k": 8}' is scored against o_{t+8}, not the task spec's t+4); the spec gives the cadence
        cfg = self.model.cfg
        self.obs_steps, self.n_action_steps, self.k = int(cfg.obs_steps), spec.n_action_steps, int(cfg.future_k)
        if not 1 <= self.n_action_steps <= cfg.horizon:
            raise ValueError(f"n_action_steps={self.n_action_steps} must be in [1, horizon={cfg.horizon}]")
        self.reset()

    @classmethod
    def from_checkpoint(cls, path: str | Path, device: str | torch.device = "cpu", ema: bool = True,
                        detectors: bool | None = None) -> "Policy":
        """Load a ``jepa-policy train`` checkpoint; acts with the EMA weights unless ``ema=False``.

        ``detectors``: None loads the fitted detectors beside the checkpoint when that file exists (a file that
        exists but is refused raises), True requires them, False loads none."""
        ckpt = load_checkpoint(path, map_location="cpu")
        model = load_model(ckpt, ema=ema)
        spec = get_task_spec(ckpt["task"]).with_image_size(ckpt["image_size"])
        fitted = None
        if detectors or (detectors is None and detector_path(path).is_file()):
            fitted = load_detectors(detector_path(path), checkpoint=path)
        policy = cls(model, spec, device, detectors=fitted)
        policy.checkpoint_step = int(ckpt["step"])
        policy.env_args = ckpt.get("env_args")
        return policy

    @property
    def image_size(self) -> int:
        """The camera image size in pixels this policy acts on: its checkpoint's. Environments follow it
        (``make_env``, evaluation, ``jepa-policy robot``); ``act`` refuses frames of another size."""
        return self.spec.image_size

    def make_env(self, **kwargs) -> gym.Env:
        """``gym.make`` of the policy's task as it was trained: its image size and its demonstrations' env
        settings (``kwargs`` override them)."""
        return gym.make(self.spec.env_id, **{**env_kwargs_for(self.spec, self.env_args), **kwargs})

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget the history and the queued actions; call at the start of every episode."""
        self._history: deque = deque(maxlen=self.obs_steps)
        self._queue: deque = deque()
        self.t = -1                       # episode step of the newest observation seen
        self.last_decision: Decision | None = None
        self._batched: bool | None = None
        self._previous_chunk: tuple[int, np.ndarray] | None = None   # (step, normalised actions) for STAC

    def images_needed(self, step: int) -> bool:
        """Whether the frame of episode step ``step`` is used: the history of a decision or its future target.

        Decisions happen at multiples of ``n_action_steps``; a render-on-demand loop renders only these frames
        (the schedule of ``jepa_envs.tasks.wrappers.RenderOnDemand``). Arms without a future head need no t+k frames.
        """
        future_k = self.k if self.model.cfg.has_future_token else 0
        return frames_to_render(step, self.n_action_steps, self.obs_steps, future_k)

    # ------------------------------------------------------------------ public acting API
    def act(self, obs: dict) -> np.ndarray:
        """Consume one observation and return the action to execute now ((A,) or (B, A))."""
        self._push(obs)
        if not self._queue:
            decision = self._decide(want_future=True)
            for i in range(self.n_action_steps):
                self._queue.append(decision.actions[..., i, :])
        return self._queue.popleft()

    def predict(self, obs: dict, want_future: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """Consume one observation and return (action chunk (H, A), z_hat for frame t+k) without queueing."""
        self._push(obs)
        decision = self._decide(want_future=want_future)
        return decision.actions, decision.z_hat

    def decide_from(self, frames: list[dict], want_future: bool = True) -> Decision:
        """Decide from an explicit history: the newest observations, oldest first, one per env step.

        For loops that do not feed every frame through ``act`` (the asynchronous executor observes only when
        it replans). Replaces the history and the queue; fewer frames than ``obs_steps`` are padded with the
        first, as at an episode's start.
        """
        if not frames:
            raise ValueError("decide_from needs at least one observation")
        self.reset()
        for frame in frames[-self.obs_steps:]:
            self._push(frame)
        return self._decide(want_future=want_future)

    @torch.inference_mode()
    def encode_future(self, obs: dict) -> np.ndarray:
        """Realized future latent z = E_rgb(o) of an observation ((D,) or (B, D)); needs only its images."""
        batched = self._is_batched(obs)
        images = {}
        for key in self.spec.image_keys:
            arr = self._image(obs, key)
            # a copy: env observations may be read-only views, which torch must not alias
            images[key] = torch.from_numpy(np.array(arr if batched else arr[None], dtype=np.uint8)).to(self.device)
        z = self.model.encode_future(images).float().cpu().numpy()
        return z if batched else z[0]

    # ------------------------------------------------------------------ internals
    def _is_batched(self, obs: dict) -> bool:
        key = self.spec.image_keys[0]
        if key not in obs:
            raise KeyError(f"observation lacks {key!r}; it has {sorted(obs)}")
        ndim = np.asarray(obs[key]).ndim
        if ndim not in (3, 4):
            raise ValueError(f"{key} must be (S,S,3) or (B,S,S,3) uint8, got shape {np.asarray(obs[key]).shape}")
        return ndim == 4

    def _image(self, obs: dict, key: str) -> np.ndarray:
        """Camera ``key`` of an observation, refused with the fix when it is not of the policy's image size."""
        arr = np.asarray(obs[key])
        size = self.spec.image_size
        if arr.shape[-3:-1] != (size, size):
            raise ValueError(
                f"{key} is {arr.shape[-3]}x{arr.shape[-2]} px but this policy acts on {size}x{size} px (its "
                f"checkpoint's image size); make the env at the policy's size: policy.make_env() or "
                f"gym.make({self.spec.env_id!r}, image_size={size}); a robot bridge: jepa-robot-bridge serve ... "
                f"--image-size {size}")
        return arr

    def _push(self, obs: dict) -> None:
        batched = self._is_batched(obs)
        if self._batched is not None and batched != self._batched:
            raise ValueError("mixing batched and unbatched observations in one episode; call reset() first")
        frame = {}
        for key in (*self.spec.image_keys, *self.spec.lowdim_keys):
            if key not in obs:
                raise KeyError(f"observation lacks {key!r}; the task {self.spec.name} needs "
                               f"{list(self.spec.image_keys) + list(self.spec.lowdim_keys)}")
            arr = self._image(obs, key) if key in self.spec.image_keys else np.asarray(obs[key])
            frame[key] = arr if batched else arr[None]
        self._batched = batched     # only once the frame was accepted: a refused one leaves no trace
        if not self._history:  # pad the start of the episode by repeating the first frame, as in training
            self._history.extend([frame] * (self.obs_steps - 1))
        self._history.append(frame)
        self.t += 1

    @torch.inference_mode()
    def _decide(self, want_future: bool) -> Decision:
        actions, z, c = decide_frames(self.model, self.spec, list(self._history), self.device, want_future)
        scores = self._scores(actions, c)
        if not self._batched:
            actions, z = actions[0], (None if z is None else z[0])
            c = None if c is None else c[0]
            scores = {name: float(v[0]) for name, v in scores.items()}
        self.last_decision = Decision(step=self.t, k=self.k, actions=actions, z_hat=z, scores=scores, embedding=c)
        return self.last_decision

    def normalised_actions(self, actions: np.ndarray) -> np.ndarray | None:
        """Action chunks in the policy's own [-1, 1] units (STAC's), or None when the model has no action scaling."""
        if self._action_affine is None:
            return None
        scale, offset = self._action_affine
        return actions * scale + offset

    def _scores(self, actions: np.ndarray, c: np.ndarray | None) -> dict[str, np.ndarray]:
        """The decision-time failure scores of a batch of chunks (B, H, A) and embeddings (B, width)."""
        scores = {}
        chunk = self.normalised_actions(actions)
        if chunk is not None:
            previous = self._previous_chunk
            scores["stac"] = (stac(chunk, None, 0) if previous is None or previous[1].shape != chunk.shape
                              else stac(chunk, previous[1], self.t - previous[0]))
            self._previous_chunk = (self.t, chunk)
        if self.detectors is not None and c is not None:
            scores.update(self.detectors.score(c))
        return scores


@torch.inference_mode()
def predict_frames(model: torch.nn.Module, spec: TaskSpec, frames: list[dict], device: torch.device,
                   want_future: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """One forward pass over a history: ``frames`` oldest first, each key batched (B, ...); returns the
    unnormalised action chunks (B, H, A) and z_hat (B, D) (None for arms without a future head). Shared by the
    acting runtime and the policy server, which stacks several clients' histories into one batch."""
    actions, z_hat, _ = decide_frames(model, spec, frames, device, want_future)
    return actions, z_hat


@torch.inference_mode()
def decide_frames(model: torch.nn.Module, spec: TaskSpec, frames: list[dict], device: torch.device,
                  want_future: bool = True) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """``predict_frames`` and the newest frame's fused embedding c_t (B, width) of the same pass (None for arms
    without one, e.g. the diffusion arm)."""
    obs = {}
    for key in spec.image_keys:
        stacked = np.stack([f[key] for f in frames], axis=1)
        obs[key] = torch.from_numpy(np.ascontiguousarray(stacked, dtype=np.uint8)).to(device)
    for key in spec.lowdim_keys:
        stacked = np.stack([f[key] for f in frames], axis=1).astype(np.float32)
        obs[key] = torch.from_numpy(stacked).to(device)
    if hasattr(model, "predict_embedded"):
        actions, z_hat, c = model.predict_embedded(obs, want_future=want_future)
    else:
        (actions, z_hat), c = model.predict(obs, want_future=want_future), None
    return (actions.float().cpu().numpy(), None if z_hat is None else z_hat.float().cpu().numpy(),
            None if c is None else c.cpu().numpy())
