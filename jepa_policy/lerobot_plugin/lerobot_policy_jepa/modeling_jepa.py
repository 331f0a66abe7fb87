"""``JEPAPolicy``: JEPA Policy as a LeRobot ``PreTrainedPolicy``, a thin shell around our own code.

The network is ``jepa_policy.model.build_model`` (its weights under ``model.`` in LeRobot's safetensors file);
training is its two-step loss (``compute_loss``) on LeRobot's batches; acting is our runtime itself,
``jepa_policy.policy.Policy``: the same observation history (the first frame repeated at an episode's start), the
same two passes per decision (step 1 from zeros, step 2 from step 1's outputs), the same queue of
``n_action_steps`` actions per chunk. Only the frames change hands, back to the uint8 bytes the env rendered.

What LeRobot's interfaces cannot carry: ``select_action`` returns an action and nothing else, and neither its
processors nor ``lerobot-eval`` pass anything beside it, so the refined z_hat for frame t+k, the decision's
c_t and its failure scores never leave the policy through LeRobot. They stay on it: ``last_decision`` (our
``Decision``: step, k, actions, z_hat, scores, embedding) after every decision, and, as every later
observation arrives, ``future_log`` pairs each z_hat with the realized latent E_rgb(o_{t+k}) of the same
encoder and its NMSE (the monitor's ``nmse_rows``). A loop that drives the policy (LeRobot's record or async
inference, or your own) reads them there and sends them with ``monitor_service.client.MonitorClient``
(``decision`` and ``target``); a checkpoint LeRobot saved also runs in our runtime, whose server and
evaluation stream them to the monitor themselves (``Policy.from_checkpoint`` reads the folder).
"""
from __future__ import annotations

from dataclasses import replace

import torch
from torch import Tensor

from jepa_policy.lerobot_format import model_batch, normalizer_stats, observation
from jepa_policy.model import build_model
from jepa_policy.policy import Decision, Policy
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot_policy_jepa.configuration_jepa import JEPAConfig
from monitor_service.scoring import nmse_rows


class JEPAPolicy(PreTrainedPolicy):
    """``--policy.type=jepa``: trains with our two-step loss, acts with our runtime."""

    config_class = JEPAConfig
    name = "jepa"

    def __init__(self, config: JEPAConfig, dataset_stats: dict | None = None, **kwargs):
        """``dataset_stats``: LeRobot's dataset statistics (``make_policy`` passes them), fitted into the
        network's own normalisers; a loaded checkpoint brings its own in its weights."""
        super().__init__(config)
        self.spec, model_cfg = config.model_config()
        self.spec = replace(self.spec, n_action_steps=int(config.n_action_steps))
        self.model = build_model(model_cfg)
        if dataset_stats is not None:
            self.model.set_normalizer_stats(normalizer_stats(dataset_stats, self.spec))
        self.reset()

    @classmethod
    def from_pretrained(cls, *args, strict: bool = True, **kwargs) -> "JEPAPolicy":
        """LeRobot's loader, strict: a checkpoint missing a tensor of the network is refused, not half-loaded."""
        return super().from_pretrained(*args, strict=strict, **kwargs)

    def get_optim_params(self) -> list[dict]:
        """AdamW groups as our training makes them: matrices decay; biases, norms and positions do not."""
        return self.model.param_groups(self.config.optimizer_weight_decay)

    # ------------------------------------------------------------------ training
    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict]:
        """The two-step loss of a LeRobot batch and its parts (act and future losses, lambda_z) as floats."""
        ours = model_batch(batch, self.spec, self.config.n_obs_steps, with_future=self.config.has_future)
        return self.model.compute_loss(ours)

    # ------------------------------------------------------------------ acting
    def reset(self) -> None:
        """Start an episode: our runtime forgets its history and queue; the future log starts empty."""
        self._runtime: Policy | None = None
        self._pending: list[Decision] = []
        self.future_log: list[dict] = []

    @property
    def runtime(self) -> Policy:
        """Our acting runtime around this network (built at an episode's first observation)."""
        if self._runtime is None:
            self._runtime = Policy(self.model, self.spec, device=self.config.device)
        return self._runtime

    @property
    def last_decision(self) -> Decision | None:
        """The newest decision: its chunk, z_hat for frame step + k (batched (B, D)), scores and c_t."""
        return None if self._runtime is None else self._runtime.last_decision

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """One observation in (batched, after the preprocessor), the action to execute now out, (B, A)."""
        obs = observation(batch, self.spec)
        runtime = self.runtime
        before = runtime.last_decision
        action = runtime.act(obs)
        self._log_future(obs)
        if runtime.last_decision is not before and runtime.last_decision.z_hat is not None:
            self._pending.append(runtime.last_decision)
        return torch.from_numpy(action).to(self._device(batch))

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """One observation in, the whole chunk of a new decision out (B, H, A); the queue is left alone."""
        actions, _ = self.runtime.predict(observation(batch, self.spec))
        return torch.from_numpy(actions).to(self._device(batch))

    def _log_future(self, obs: dict) -> None:
        """Pair every decision whose target frame this observation is with its realized latent."""
        t = self.runtime.t
        due = [d for d in self._pending if d.target_step == t]
        if not due:
            return
        z = self.runtime.encode_future(obs)
        for d in due:
            self._pending.remove(d)
            self.future_log.append({"step": d.step, "target_step": t, "z_hat": d.z_hat, "z": z,
                                    "nmse": nmse_rows(d.z_hat, z)})

    @staticmethod
    def _device(batch: dict) -> torch.device:
        return next((v.device for v in batch.values() if torch.is_tensor(v)), torch.device("cpu"))
