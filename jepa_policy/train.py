"""Training loop of JEPA Policy and its comparison arms (paper Sec. 3.3-3.4 objective, Sec. 4.1 protocol).

Read top to bottom like a CleanRL script: the typed ``TrainConfig`` (also the CLI of ``jepa-policy train``),
then the training story (``train``, ``_train_run``: data, model, optimiser, EMA and schedule, resume, the steps,
logs, evaluations, checkpoints, in the order they happen), then the mechanics of each of its steps.

Determinism. The model's own randomness (crop windows, second-step noise) is drawn from torch's global RNG,
which is re-seeded for every shard of every step from (seed, step, shard). A resumed run therefore repeats
the uninterrupted run exactly, and a step split over W DDP ranks x A accumulation shards computes the same
shards whatever W and A are (shard s of a global batch holds its positions s::(W*A)).

One module of about 650 lines on purpose: the training story reads top to bottom in one file, as a CleanRL
script does; the model, the data and the evaluation are modules of their own.
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import random
import shutil
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm

from jepa_envs.datasets.hdf5 import load_dataset
from jepa_envs.datasets.lerobot import resolve_dataset
from jepa_envs.rollouts.pool import available_cores
from jepa_envs.tasks.spec import TaskSpec, get_task_spec
from jepa_policy.audit import gradient_interaction
from jepa_policy.checkpoint import (freeze_backbone, load_checkpoint, load_encoder_weights, save_checkpoint,
                                    save_eval_snapshot, set_rng_state)
from jepa_policy.config import ModelConfig
from jepa_policy.dataset import ResumableBatchSampler, WindowDataset, make_loader, normalizer_stats
from jepa_policy.evaluate import evaluate, make_pool
from jepa_policy.model import build_model
from jepa_policy.policy import Policy
from jepa_policy.progress import bars_disabled

CONFIG_DIR = Path(__file__).parent / "configs"


@dataclass
class TrainConfig:
    """Hyper-parameters of one run. Defaults are the paper's (Sec. 4.1); presets live in ``configs/<task>.json``."""

    task: str = "PushT"
    arm: str = "jepa"                 # jepa | mip | dual_independent | dual_cross | backcut | fwdcut | sigreg | lambda_a0 | diffusion
    dataset: str = ""                 # demonstration file (jepa_envs.datasets.hdf5.load_dataset) or LeRobot v3.0 root
    dataset_map: dict = field(default_factory=dict)   # LeRobot feature -> our key (jepa_envs.datasets.lerobot)
    out_dir: str = "runs/jepa"
    resume: str = ""                  # checkpoint to continue from ("" = fresh run)
    steps: int = 300_000
    stop_at: int = 0                  # stop and checkpoint at this step (time-sliced jobs); 0 = run to ``steps``
    batch_size: int = 256             # global batch over all ranks and accumulation shards
    grad_accum: int = 1               # shards per rank and step (same result as more ranks)
    lr: float = 1e-4
    weight_decay: float = 1e-6        # diffusion_policy / MIP released default for AdamW
    beta1: float = 0.95
    beta2: float = 0.999
    warmup_steps: int = 500
    ema_decay: float = 0.995          # Polyak averaging of the policy weights, used to evaluate and act
    seed: int = 42
    image_size: int = 0               # 0 = the task spec's size
    device: str = "auto"              # auto | cpu | cuda | cuda:N
    bf16: bool = True                 # bf16 autocast, used only on CUDA
    num_workers: int = 0
    log_every: int = 100
    ckpt_every: int = 10_000
    eval_every: int = 10_000          # 0 = no periodic evaluation
    eval_episodes: int = 40
    eval_seed: int = 100_000          # fixed evaluation seed (Sec. 4.1)
    eval_envs: int = 4                # parallel environments of one evaluation
    eval_workers: int = -1            # rollout worker processes per rank (-1 = the cores available; 0 = in-process)
    eval_max_steps: int = 0           # episode step limit of the periodic evaluation; 0 = the task's
    keep_eval_checkpoints: bool = True  # EMA weights at every periodic evaluation (checkpoint selection, protocols)
    grad_every: int = 1000            # gradient interaction of the two losses logged every N steps (0 = never)
    progress: bool = True
    init_candidates: int = 1          # best-of-K start: K initialisations race init_screen_steps (``train``)
    init_screen_steps: int = 0        # steps each candidate trains before the lowest-loss one continues
    model: dict = field(default_factory=dict)  # ModelConfig overrides, e.g. {"image_size": 64}

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "TrainConfig":
        """Build a config from plain data, checking names and types so a typo fails loudly."""
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - set(fields))
        if unknown:
            raise ValueError(f"unknown training option(s) {unknown}; valid options: {sorted(fields)}")
        values = {}
        for name, value in data.items():
            kind = type(getattr(cls(), name))
            if kind is float and isinstance(value, int) and not isinstance(value, bool):
                value = float(value)
            if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
                raise TypeError(f"training option {name!r} must be {kind.__name__}, got {value!r}")
            values[name] = value
        cfg = cls(**values)
        cfg.validate()
        return cfg

    def validate(self) -> None:
        """Reject settings that cannot run, with the fix in the message."""
        spec = get_task_spec(self.task)
        checks = [
            (self.steps >= 1, "steps must be >= 1"),
            (0 <= self.stop_at <= self.steps, "stop_at must be in [0, steps] (0 = run to the end)"),
            (self.batch_size >= 1, "batch_size must be >= 1"),
            (self.grad_accum >= 1 and self.batch_size % self.grad_accum == 0,
             "grad_accum must be >= 1 and divide batch_size"),
            (self.lr > 0, "lr must be > 0"),
            (0.0 <= self.ema_decay < 1.0, "ema_decay must be in [0, 1)"),
            (self.warmup_steps >= 0, "warmup_steps must be >= 0"),
            (self.warmup_steps <= self.steps,
             f"steps ({self.steps}) is below warmup_steps ({self.warmup_steps}) of this preset; pass more --steps or "
             f"--warmup-steps N with N <= steps"),
            (self.log_every >= 1 and self.ckpt_every >= 1, "log_every and ckpt_every must be >= 1"),
            (self.eval_every >= 0 and self.eval_episodes >= 0, "eval_every >= 0 and eval_episodes >= 0"),
            (self.eval_episodes >= 1 or self.keep_eval_checkpoints,
             "eval_episodes 0 (snapshots only) needs keep_eval_checkpoints"),
            (self.eval_max_steps >= 0, "eval_max_steps must be >= 0 (0 = the task's episode length)"),
            (self.eval_workers >= -1, "eval_workers must be >= -1 (-1 = one per core, 0 = in-process)"),
            (self.grad_every >= 0, "grad_every must be >= 0 (0 = no gradient-interaction log)"),
            (self.init_candidates >= 1, "init_candidates must be >= 1 (1 = a single start, no selection)"),
            (self.init_candidates == 1 or 1 <= self.init_screen_steps < self.steps,
             "with init_candidates > 1, init_screen_steps must be in [1, steps)"),
            (self.init_candidates == 1 or self.stop_at == 0 or self.stop_at > self.init_screen_steps,
             "stop_at must be 0 or after init_screen_steps when init_candidates > 1"),
        ]
        for ok, message in checks:
            if not ok:
                raise ValueError(f"invalid training config: {message}")
        ModelConfig.for_task(spec.with_image_size(self.image_size or spec.image_size), arm=self.arm, **self.model)


# What each option does: the --help of ``jepa-policy train`` (every field has a line; tested).
TRAIN_HELP = {
    "task": "task name (PushT, ToolHang, Square, ...; `jepa-envs list`)",
    "arm": "jepa | mip | dual_independent | dual_cross | backcut | fwdcut | sigreg | lambda_a0 | diffusion",
    "dataset": "demonstration file (robomimic/MimicGen/LIBERO HDF5 or `jepa-envs make-demos`), or the root of a "
               "LeRobotDataset v3.0 (the folder holding meta/info.json)",
    "dataset_map": "LeRobot dataset only: JSON object of feature -> our key, e.g. "
                   "'{\"observation.images.front\": \"agentview_image\"}' (jepa-envs lerobot import --map)",
    "out_dir": "run folder: checkpoints, log.jsonl, TensorBoard, train_config.json",
    "resume": "checkpoint to continue from (runs to the schedule's end unless --stop-at is given)",
    "steps": "length of the schedule (cosine decay ends here)",
    "stop_at": "stop and checkpoint at this step (time-sliced jobs); 0 = run to --steps",
    "batch_size": "global batch over all ranks and accumulation shards",
    "grad_accum": "accumulation shards per rank and step (same result as more ranks)",
    "lr": "AdamW learning rate after warm-up",
    "weight_decay": "AdamW weight decay of matrices and kernels",
    "beta1": "AdamW beta1",
    "beta2": "AdamW beta2",
    "warmup_steps": "linear learning-rate warm-up steps",
    "ema_decay": "Polyak averaging of the weights that evaluate and act",
    "seed": "seed of the weights, the batches and the model's noise",
    "image_size": "camera image size in pixels (0 = the task's)",
    "device": "auto (CUDA when present) | cpu | cuda | cuda:N",
    "bf16": "bf16 autocast on CUDA",
    "num_workers": "data-loader worker processes",
    "log_every": "steps between log rows (log.jsonl, TensorBoard)",
    "ckpt_every": "steps between checkpoints (latest.pt)",
    "eval_every": "steps between seeded evaluations (0 = none)",
    "eval_episodes": "rollouts of each periodic evaluation (0: only the EMA snapshot, evaluated later)",
    "eval_seed": "seed of the first evaluation rollout (the same every time)",
    "eval_envs": "environments stepped together in an evaluation",
    "eval_workers": "env-only rollout processes of the evaluations, started once per run (-1 = one per available "
                    "core; 0 = step the envs in the trainer's process, best for cheap envs such as PushT)",
    "eval_max_steps": "episode step limit of the periodic evaluation (0 = the task's)",
    "keep_eval_checkpoints": "keep the EMA weights of every periodic evaluation (for `jepa-policy protocols --select`)",
    "grad_every": "steps between rows of the action/future gradient interaction (Sec. 4.5) in log.jsonl (0 = never)",
    "progress": "progress bar",
    "init_candidates": "best-of-K start: K seeds race --init-screen-steps, the lowest first-step loss continues",
    "init_screen_steps": "steps each best-of-K candidate trains before the choice",
    "model": "JSON object of ModelConfig overrides, e.g. '{\"width\": 64}'",
}


def load_config(task: str, preset: str = "paper", **overrides) -> TrainConfig:
    """The named preset of ``configs/<task>.json`` with keyword overrides applied."""
    path = CONFIG_DIR / f"{get_task_spec(task).name}.json"
    if not path.exists():
        raise FileNotFoundError(f"no config file {path}; available: {sorted(p.stem for p in CONFIG_DIR.glob('*.json'))}")
    data = json.loads(path.read_text())
    extra = sorted(set(data) - {"task", "description", "presets"})
    if extra or "presets" not in data or "task" not in data:
        raise ValueError(f"{path} must hold exactly 'task', 'presets' and optionally 'description'; found {sorted(data)}")
    presets = data["presets"]
    if preset not in presets:
        raise KeyError(f"{path.name} has no preset {preset!r}; choose one of {sorted(presets)}")
    values = {"task": data["task"], **presets[preset], **overrides}
    if "model" in presets[preset] and "model" in overrides:
        values["model"] = {**presets[preset]["model"], **overrides["model"]}
    return TrainConfig.from_dict(values)


# ----------------------------------------------------------------------------- the training story

CANDIDATE_SEED_STRIDE = 10_000  # candidate i of a best-of-K start uses seed + i * this (candidate 0 is the seed)
SELECT_ON = "loss_act_step0"    # best-of-K score: the first-step action loss where the arm has it, else the loss


def candidate_seeds(cfg: TrainConfig) -> list[int]:
    """Seeds of the K starts a best-of-K run races; the first is ``cfg.seed``, so K = 1 is the plain run."""
    return [cfg.seed + CANDIDATE_SEED_STRIDE * i for i in range(cfg.init_candidates)]


def train(cfg: TrainConfig, demos=None) -> dict:
    """Run (or continue) training; returns the final checkpoint path, the step, the eval curve and the logs.

    Launch with ``torchrun --nproc-per-node N -m jepa_policy.cli train ...`` for DistributedDataParallel;
    ``demos`` may be a loaded ``DemoDataset`` (tests), otherwise ``cfg.dataset`` is loaded.

    Best-of-K start (``init_candidates`` = K > 1; not in the paper, a small-budget measure, docs/training.md).
    A narrow image encoder's random initialisation sometimes fits far worse than the others, and it shows
    in the training loss long before the end. K runs that differ only in their seed (``candidate_seeds``) each
    train the first ``init_screen_steps`` steps of the same schedule, in ``out_dir/init_candidates/seed<s>``;
    the one with the lowest mean first-step action loss (``SELECT_ON``; the total loss for arms without it) over
    the last third of those steps continues from its own checkpoint to the end. The selection uses training
    data only, never an evaluation, and the result is exactly the plain run of the chosen seed (resume is
    exact); ``init_selection.json`` and the checkpoint record the seeds, their scores and the choice.
    """
    cfg.validate()
    if cfg.resume or cfg.init_candidates == 1:   # a resumed best-of-K run continues with the seed it chose
        return _train_run(cfg, demos)
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:
        raise ValueError("init_candidates > 1 (best-of-K start) runs in a single process; run it without "
                         "torchrun, or pass --init-candidates 1 and choose the seed yourself")
    demos = _load_demos(cfg) if demos is None else demos
    out, n = Path(cfg.out_dir), cfg.init_screen_steps
    window = max(1, n // 3)
    seeds, scores = candidate_seeds(cfg), []
    for seed in seeds:
        trial = dataclasses.replace(cfg, seed=seed, stop_at=n, init_candidates=1, init_screen_steps=0,
                                    eval_every=0, out_dir=str(out / "init_candidates" / f"seed{seed}"))
        tail = _train_run(trial, demos)["losses"][-window:]
        score_on = SELECT_ON if SELECT_ON in tail[0] else "loss"
        scores.append(float(np.mean([row[score_on] for row in tail])))
    best = int(np.argmin(scores))
    selection = {"seeds": seeds, "scores": scores, "score_on": score_on, "screen_steps": n,
                 "score_steps": [n - window + 1, n], "chosen_seed": seeds[best]}
    chosen_dir = out / "init_candidates" / f"seed{seeds[best]}"
    shutil.copyfile(chosen_dir / "log.jsonl", out / "log.jsonl")   # one learning curve from step 1
    (out / "init_selection.json").write_text(json.dumps(selection, indent=2))
    final = dataclasses.replace(cfg, resume=str(chosen_dir / "checkpoints" / "latest.pt"))
    result = _train_run(final, demos, selection)   # continues with the chosen seed (see ``resume``)
    result["init_selection"] = selection
    return result


def _train_run(cfg: TrainConfig, demos=None, selection: dict | None = None) -> dict:
    """One run from one seed (or from ``cfg.resume``), step by step in the order they happen; how each step
    does its job is in the helpers below."""
    ranks = join_ranks(cfg.device)
    demos = _load_demos(cfg) if demos is None else demos
    data = TrainingData.of(cfg, demos)
    learner = build_learner(cfg, data, ranks)             # seeded: the same initial weights on every rank
    step, curve = 0, []
    if cfg.resume:                                        # weights, optimiser, schedule, RNG: as they were
        cfg, step, curve, selection = resume(cfg, learner, ranks, selection)
    sampler, batches = batch_stream(cfg, data, ranks, step)   # from the batch it would have drawn next
    net = distributed(learner.model, ranks)
    log = RunLog(cfg, step, ranks.is_main)
    evaluation = PeriodicEvaluation(cfg, data, ranks)
    checkpoint = Path(cfg.out_dir) / "checkpoints" / "latest.pt"

    losses, last = [], cfg.stop_at or cfg.steps
    learner.model.train()
    while step < last:
        batch = _to_device(next(batches), ranks.device)
        infos = train_step(net, learner, batch, cfg, step, ranks)   # forward, backward, AdamW, schedule, EMA
        step += 1
        losses.append({k: float(np.mean([i[k] for i in infos])) for k in ("loss", SELECT_ON) if k in infos[0]})
        log.train_row(step, infos, learner.scheduler.get_last_lr()[0])
        if ranks.is_main and cfg.grad_every and step % cfg.grad_every == 0:
            log.gradient_interaction(step, learner.model, _shard(batch, 0, cfg.grad_accum))
        if cfg.eval_every and step % cfg.eval_every == 0:
            evaluation.run(step, learner, curve, log, checkpoint.parent)
        if ranks.is_main and (step % cfg.ckpt_every == 0 or step == last):
            save_checkpoint(checkpoint, **learner.parts(), step=step, cfg=cfg, spec=data.spec, stats=data.stats,
                            curve=curve, sampler_position=sampler_position(sampler, step), env_args=data.env_args,
                            init_selection=selection)

    evaluation.close()
    log.close()
    leave_ranks(ranks)
    return {"checkpoint": str(checkpoint), "step": step, "curve": curve, "history": log.history, "losses": losses,
            "model": learner.model, "ema": learner.ema}


# ----------------------------------------------------------------------------- the mechanics of each step

@dataclass
class Ranks:
    """Where this process stands in a torchrun job; a plain run is rank 0 of 1."""

    world: int
    rank: int
    device: torch.device
    owns_group: bool     # this run started the process group, so it ends it

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def join_ranks(device_name: str) -> Ranks:
    """Rank, world size and device from torchrun's environment; starts the process group when there is none."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank, local_rank = int(os.environ.get("RANK", "0")), int(os.environ.get("LOCAL_RANK", "0"))
    device = resolve_device(device_name, local_rank)
    if device.type == "cuda":
        torch.cuda.set_device(device)  # NCCL collectives run on the current device of each rank
    owns_group = world > 1 and not dist.is_initialized()
    if owns_group:
        dist.init_process_group(backend="nccl" if device.type == "cuda" else "gloo")
    return Ranks(world, rank, device, owns_group)


def leave_ranks(ranks: Ranks) -> None:
    if ranks.world > 1:
        dist.barrier()
    if ranks.owns_group:
        dist.destroy_process_group()


def _load_demos(cfg: TrainConfig):
    if not cfg.dataset:
        raise ValueError("no dataset given; record one with `jepa-envs make-demos PushT --episodes 50 "
                         "--out demos.hdf5` and pass --dataset demos.hdf5")
    path = resolve_dataset(cfg.dataset, cfg.task, [f"{k}={v}" for k, v in cfg.dataset_map.items()])
    return load_dataset(path, task=cfg.task, image_size=cfg.image_size or None)


@dataclass
class TrainingData:
    """The demonstrations as training windows, with the normaliser statistics the model keeps."""

    spec: TaskSpec               # the task at the training image size
    windows: WindowDataset
    stats: dict
    env_args: dict | None        # the dataset's env settings, so evaluation rebuilds the same env

    @classmethod
    def of(cls, cfg: TrainConfig, demos) -> "TrainingData":
        if demos.spec.name != get_task_spec(cfg.task).name:
            raise ValueError(f"dataset is for task {demos.spec.name!r} but the config trains {cfg.task!r}")
        # windows follow the MODEL's sizes (a --model '{"future_k": 8}' override trains against o_{t+8}, not the
        # task spec's t+4), the same values the network is built with in build_learner
        model_cfg = ModelConfig.for_task(demos.spec, arm=cfg.arm, **cfg.model)
        windows = WindowDataset.from_demos(demos, obs_steps=model_cfg.obs_steps, horizon=model_cfg.horizon,
                                           future_k=model_cfg.future_k)
        return cls(demos.spec, windows,
                   normalizer_stats(demos.actions, demos.obs, demos.spec.lowdim_keys, demos.spec.image_keys),
                   getattr(demos, "env_args", None))


@dataclass
class Learner:
    """What an optimisation step changes: the network, its EMA, AdamW and the learning-rate schedule."""

    model: torch.nn.Module
    model_cfg: ModelConfig
    ema: AveragedModel
    optimizer: torch.optim.Optimizer
    scheduler: torch.optim.lr_scheduler.LRScheduler

    def parts(self) -> dict:
        return {"model": self.model, "ema": self.ema, "optimizer": self.optimizer, "scheduler": self.scheduler,
                "model_cfg": self.model_cfg}


def build_learner(cfg: TrainConfig, data: TrainingData, ranks: Ranks) -> Learner:
    """Model, EMA, optimiser and schedule of Sec. 4.1 (AdamW 1e-4, EMA 0.995, cosine with warm-up), from the
    run's seed; a fresh run's image backbone may start from a pretrained file (``encoder_weights``)."""
    seed_everything(cfg.seed)  # identical initial weights on every rank
    model_cfg = ModelConfig.for_task(data.spec, arm=cfg.arm, **cfg.model)
    model = build_model(model_cfg).to(ranks.device)
    if model_cfg.encoder_weights and not cfg.resume:   # a resumed run's weights come from its checkpoint
        tensors, digest = load_encoder_weights(model, model_cfg.encoder_weights, model_cfg.encoder_key_map)
        model_cfg = model_cfg.replace(encoder_weights_sha256=digest)
        if ranks.is_main:
            print(f"image backbone initialised from {model_cfg.encoder_weights} ({tensors} tensors, sha256 "
                  f"{digest[:12]}){'; frozen' if model_cfg.freeze_encoder else ''}", file=sys.stderr, flush=True)
    if model_cfg.freeze_encoder:
        freeze_backbone(model)
    model.set_normalizer_stats(data.stats)
    ema = AveragedModel(model, multi_avg_fn=get_ema_multi_avg_fn(cfg.ema_decay), use_buffers=True)
    optimizer = torch.optim.AdamW(model.param_groups(cfg.weight_decay), lr=cfg.lr, betas=(cfg.beta1, cfg.beta2))
    scheduler = cosine_with_warmup(optimizer, cfg.warmup_steps, cfg.steps)
    return Learner(model, model_cfg, ema, optimizer, scheduler)


def resume(cfg: TrainConfig, learner: Learner, ranks: Ranks, selection: dict | None):
    """Load ``cfg.resume`` into the learner and the RNGs; returns (cfg, step, eval curve, best-of-K selection).

    A best-of-K run continues with the seed it chose: from here that seed drives the batches and the noise."""
    ckpt = load_checkpoint(cfg.resume, map_location=ranks.device)
    step = int(ckpt["step"])
    if cfg.stop_at and cfg.stop_at <= step:
        raise ValueError(f"stop_at {cfg.stop_at} is not after the checkpoint's step {step}; pass "
                         f"--stop-at 0 to train to step {cfg.steps}, or a later --stop-at")
    if cfg.steps < step:
        raise ValueError(f"--steps {cfg.steps} ends before the checkpoint's step {step}; pass --steps {step} or more")
    learner.model.load_state_dict(ckpt["model"])
    learner.ema.load_state_dict(ckpt["ema"])
    learner.optimizer.load_state_dict(ckpt["optimizer"])
    learner.scheduler.load_state_dict(ckpt["scheduler"])
    planned = ckpt["train_config"]
    note = ""
    if (planned["steps"], planned["warmup_steps"]) != (cfg.steps, cfg.warmup_steps):
        lr_before = learner.scheduler.get_last_lr()[0]
        learner.scheduler = schedule_at(learner.optimizer, cfg, step)
        note = (f"; its schedule was planned for {planned['steps']} steps ({planned['warmup_steps']} warm-up): one "
                f"cosine schedule now ends at step {cfg.steps}, as in a run launched with --steps {cfg.steps} "
                f"(lr at step {step}: {lr_before:.3g} -> {learner.scheduler.get_last_lr()[0]:.3g})")
    if ranks.is_main:
        print(f"resuming {cfg.resume} at step {step}: training to step {cfg.stop_at or cfg.steps} of {cfg.steps}"
              f"{note}", file=sys.stderr, flush=True)
    set_rng_state(ckpt["rng"])
    selection = selection or ckpt.get("init_selection")
    if selection:
        cfg = dataclasses.replace(cfg, seed=int(selection["chosen_seed"]))
    return cfg, step, list(ckpt["eval_curve"]), selection


def batch_stream(cfg: TrainConfig, data: TrainingData, ranks: Ranks, step: int):
    """This rank's sampler and its share of the global batches from ``step`` on (``ResumableBatchSampler``)."""
    sampler = ResumableBatchSampler(len(data.windows), cfg.batch_size, cfg.seed, ranks.rank, ranks.world)
    sampler.start_at(step)
    return sampler, iter(make_loader(data.windows, sampler, cfg.num_workers, pin_memory=ranks.device.type == "cuda"))


def sampler_position(sampler: ResumableBatchSampler, step: int) -> dict:
    """Epoch and batches taken after ``step`` steps: where the checkpoint records the sampler stands."""
    epoch, taken = divmod(step, sampler.batches_per_epoch())
    return {"epoch": epoch, "batches_taken": taken}


def distributed(model: torch.nn.Module, ranks: Ranks) -> torch.nn.Module:
    """The network one step calls: DDP around the model on several ranks (model.forward(batch) is
    compute_loss(batch), so DDP wraps it directly), the model itself otherwise."""
    if ranks.world == 1:
        return model
    return torch.nn.parallel.DistributedDataParallel(
        model, device_ids=[ranks.device.index] if ranks.device.type == "cuda" else None)


def train_step(net, learner: Learner, batch, cfg: TrainConfig, step: int, ranks: Ranks) -> list[dict]:
    """One optimisation step over this rank's ``grad_accum`` shards of ``batch``: each shard's noise re-seeded
    from (seed, step, shard), gradients averaged (DDP syncs on the last shard), then AdamW, the schedule and the
    EMA. Returns each shard's loss terms."""
    shards = cfg.grad_accum
    autocast = torch.autocast("cuda", dtype=torch.bfloat16) if ranks.device.type == "cuda" and cfg.bf16 \
        else contextlib.nullcontext()
    learner.optimizer.zero_grad(set_to_none=True)
    infos = []
    for j in range(shards):
        torch.manual_seed(shard_seed(cfg.seed, step, ranks.rank * shards + j))
        sync = contextlib.nullcontext() if (ranks.world == 1 or j == shards - 1) else net.no_sync()
        with sync:
            with autocast:
                loss, info = net(_shard(batch, j, shards))
            (loss / shards).backward()
        infos.append({"loss": float(loss.detach()), **_scalars(info)})
    learner.optimizer.step()
    learner.scheduler.step()
    learner.ema.update_parameters(learner.model)
    return infos


class RunLog:
    """What the main rank writes beside the checkpoints: train_config.json, log.jsonl, TensorBoard and the
    progress bar (``enabled`` False on the other ranks: they write nothing)."""

    def __init__(self, cfg: TrainConfig, step: int, enabled: bool):
        self.cfg, self.enabled, self.history = cfg, enabled, []
        self.t_last, self.samples_since = time.perf_counter(), 0
        if not enabled:
            return
        out = Path(cfg.out_dir)
        out.mkdir(parents=True, exist_ok=True)
        (out / "train_config.json").write_text(json.dumps(cfg.to_dict(), indent=2))
        self.writer = SummaryWriter(str(out / "tensorboard"))
        self.file = open(out / "log.jsonl", "a")
        self.progress = tqdm(total=cfg.steps, initial=step, disable=not cfg.progress or bars_disabled(),
                             desc=f"{cfg.task}/{cfg.arm}")

    def write(self, row: dict) -> None:
        self.file.write(json.dumps(row) + "\n")
        self.file.flush()

    def train_row(self, step: int, infos: list[dict], lr: float) -> None:
        """Every ``log_every`` steps (and the last): the shards' mean of every loss term, lr and samples/s."""
        self.samples_since += self.cfg.batch_size
        if not self.enabled:
            return
        self.progress.update(1)
        if step % self.cfg.log_every and step != self.cfg.steps:
            return
        now = time.perf_counter()
        row = {k: float(np.mean([i[k] for i in infos if k in i])) for k in infos[0]}
        row.update(step=step, lr=lr, samples_per_s=self.samples_since / max(now - self.t_last, 1e-9))
        self.t_last, self.samples_since = now, 0
        for key, value in row.items():
            if key != "step":
                self.writer.add_scalar(f"train/{key}", value, step)
        self.write(row)
        self.progress.set_postfix(loss=f"{row['loss']:.4f}")
        self.history.append(row)

    def gradient_interaction(self, step: int, model, shard) -> None:
        """Sec. 4.5 on this step's first shard, after the update; training's RNG is re-seeded every step and
        no .grad is touched, so the run itself is unchanged."""
        if not hasattr(model, "parameter_groups"):
            return
        row = gradient_interaction(model, shard)
        self.write({"step": step, "gradient_interaction": row})
        self.writer.add_scalar("grad/share", row["gradient_share"], step)
        for name, g in row["groups"].items():
            self.writer.add_scalar(f"grad/{name}/ratio", g["ratio"], step)
            if g["cosine"] is not None:
                self.writer.add_scalar(f"grad/{name}/cosine", g["cosine"], step)

    def evaluation(self, step: int, report: dict) -> None:
        self.writer.add_scalar("eval/success_rate", report["success_rate"], step)
        self.write({"step": step, "eval_success_rate": report["success_rate"], "eval_workers": report["workers"],
                    "eval_reruns": report["reruns"]})

    def close(self) -> None:
        if self.enabled:
            self.progress.close()
            self.writer.close()
            self.file.close()


class PeriodicEvaluation:
    """Seeded rollouts of the EMA weights every ``eval_every`` steps, in one rollout pool per run (and rank)
    started at the first evaluation; every rank runs its share of the rounds and the report (the same on
    every rank) gathers them all."""

    def __init__(self, cfg: TrainConfig, data: TrainingData, ranks: Ranks):
        self.cfg, self.data, self.ranks = cfg, data, ranks
        self.pool = None

    def run(self, step: int, learner: Learner, curve: list, log: RunLog, checkpoints: Path) -> None:
        cfg, ranks = self.cfg, self.ranks
        if cfg.eval_episodes == 0:   # snapshots only: a learning curve measured after training, off the clock
            if ranks.is_main:
                save_eval_snapshot(checkpoints / f"eval_step{step}.pt", ema=learner.ema, step=step, cfg=cfg,
                                   model_cfg=learner.model_cfg, spec=self.data.spec, env_args=self.data.env_args)
            return
        policy = Policy(learner.ema.module, self.data.spec, device=ranks.device)
        policy.env_args = self.data.env_args
        if self.pool is None:
            workers = None if cfg.eval_workers < 0 else cfg.eval_workers
            if workers is None and ranks.world > 1:   # the ranks of one machine share its cores
                workers = max(1, available_cores() // int(os.environ.get("LOCAL_WORLD_SIZE", ranks.world)))
            self.pool = make_pool(policy, min(cfg.eval_envs, cfg.eval_episodes), workers=workers,
                                  max_steps=cfg.eval_max_steps or None)
        report = evaluate(policy, episodes=cfg.eval_episodes, seed=cfg.eval_seed, pool=self.pool)
        if ranks.is_main:
            curve.append({"step": step, "success_rate": report["success_rate"], "mean_nmse": report["mean_nmse"]})
            (Path(cfg.out_dir) / "eval_curve.json").write_text(json.dumps(curve, indent=2))
            if cfg.keep_eval_checkpoints:   # what `jepa-policy protocols --select` confirms on fresh seeds
                save_eval_snapshot(checkpoints / f"eval_step{step}.pt", ema=learner.ema, step=step, cfg=cfg,
                                   model_cfg=learner.model_cfg, spec=self.data.spec, env_args=self.data.env_args)
            log.evaluation(step, report)
        if ranks.world > 1:
            dist.barrier()

    def close(self) -> None:
        if self.pool is not None:
            self.pool.close()


def shard_seed(seed: int, step: int, shard: int) -> int:
    """Seed of the model's randomness for one shard of one step (see the module docstring)."""
    return int(np.random.SeedSequence([seed, step, shard]).generate_state(1)[0])


def cosine_with_warmup(optimizer: torch.optim.Optimizer, warmup_steps: int, total_steps: int):
    """Linear warm-up to the base lr, then cosine decay to zero at ``total_steps``."""
    after = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=max(1, total_steps - warmup_steps))
    if warmup_steps == 0:
        return after
    warm = torch.optim.lr_scheduler.LinearLR(optimizer, start_factor=1.0 / warmup_steps, total_iters=warmup_steps)
    return torch.optim.lr_scheduler.SequentialLR(optimizer, [warm, after], milestones=[warmup_steps])


def schedule_at(optimizer: torch.optim.Optimizer, cfg: TrainConfig, step: int):
    """The schedule of a run launched with ``cfg.steps`` (and ``cfg.warmup_steps``), advanced to ``step``: a
    resume that changes the length continues on it, so the learning rate follows one warm-up and one cosine to
    the new end instead of the old cosine's, which reaches 0 at the old end and climbs back to the peak.
    The steps are replayed, so every later lr equals that of the run launched with this length, bit for bit."""
    for group in optimizer.param_groups:
        group["lr"] = group["initial_lr"]    # the base lr the checkpoint's schedule started from
    scheduler = cosine_with_warmup(optimizer, cfg.warmup_steps, cfg.steps)
    with warnings.catch_warnings():   # replaying the schedule alone is what torch warns about here
        warnings.filterwarnings("ignore", message=r"Detected call of `lr_scheduler\.step\(\)` before")
        for _ in range(step):
            scheduler.step()
    return scheduler


def resolve_device(name: str, local_rank: int = 0) -> torch.device:
    if name == "auto":
        return torch.device(f"cuda:{local_rank}" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise RuntimeError(f"device {name!r} asked for but CUDA is not available; use --device cpu")
    return torch.device(name)


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def _to_device(batch, device):
    if isinstance(batch, dict):
        return {k: _to_device(v, device) for k, v in batch.items()}
    return batch.to(device, non_blocking=True)


def _shard(batch, part: int, parts: int):
    if isinstance(batch, dict):
        return {k: _shard(v, part, parts) for k, v in batch.items()}
    return batch[part::parts]


def _scalars(info: dict) -> dict:
    out = {}
    for key, value in info.items():
        if isinstance(value, torch.Tensor) and value.numel() == 1:
            out[key] = float(value.detach())
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            out[key] = float(value)
    return out
