"""Seeded rollouts, success rate, per-decision future-consistency error, and the reporting protocols.

Per decision t the policy predicts z_hat for frame t+k; when that frame arrives the same encoder gives
z_real = E_rgb(o_{t+k}) and the record stores e_fc = d_NMSE(z_hat, z_real) (paper Sec. 3.6). A decision whose
episode ends before t+k has no valid target and is recorded with ``nmse: null``. The record also stores the
persistence baseline d_NMSE(z_t, z_real), the present latent E_rgb(o_t) taken as the prediction (a control of
Sec. 4.10; ``jepa-monitor study`` and the monitor's calibration compare the two).
"""
from __future__ import annotations

import contextlib
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch.distributed as dist

import jepa_envs  # noqa: F401  (registers the JEPA/* ids)
from jepa_envs.datasets.hdf5 import DemoWriter
from jepa_envs.rollouts.pool import EnvPool, WorkerFailure
from jepa_envs.tasks.faults import FAULTED_ENV, FAULTS
from jepa_envs.tasks.outcomes import failure_kind_name
from jepa_policy.detectors import whitened_error
from monitor_service.scoring import nmse_rows


@dataclass
class DecisionEvent:
    """What the per-decision hook receives: once at prediction time, once when the target is realized."""

    kind: str                   # "prediction" (z_real, nmse are None) or "realized"
    episode: int
    seed: int
    step: int                   # decision step t
    target_step: int            # t + k
    z_hat: np.ndarray
    z_real: np.ndarray | None = None
    nmse: float | None = None
    z_now: np.ndarray | None = None   # E_rgb(o_t) at the decision (the persistence baseline's prediction)


def reporting_protocols(curve: list[dict]) -> dict:
    """The four summaries of Table 6 from a curve of periodic evaluations [{"step", "success_rate"}, ...]."""
    if not curve:
        raise ValueError("empty evaluation curve; train with eval_every > 0 to record one")
    rates = [float(p["success_rate"]) for p in sorted(curve, key=lambda p: p["step"])]
    return {
        "best": max(rates),
        "mean_last5": float(np.mean(rates[-5:])),
        "mean_all": float(np.mean(rates)),
        "last": rates[-1],
        "evaluations": len(rates),
    }


RESIDUAL_FOLDS = 5   # cross-fitting without a calibration split: an episode's fold is its seed modulo this


def _scored_pairs(records: list[dict]) -> tuple[list[dict], np.ndarray, np.ndarray]:
    """The decisions with both scores, their log NMSE (y) and log persistence NMSE (x)."""
    pairs = [d for r in records for d in r["decisions"]
             if d.get("nmse") is not None and d.get("nmse_persistence") is not None]
    y = np.log(np.maximum([d["nmse"] for d in pairs], 1e-12)) if pairs else np.zeros(0)
    x = np.log(np.maximum([d["nmse_persistence"] for d in pairs], 1e-12)) if pairs else np.zeros(0)
    return pairs, y, x


def residual_line(records: list[dict]) -> dict | None:
    """Sec. 4.10's control line fitted on ``records`` (a calibration split): log NMSE = intercept + slope x log
    persistence NMSE (the magnitude of latent change) over their scored decisions; None below 3 of them."""
    pairs, y, x = _scored_pairs(records)
    if len(pairs) < 3:
        return None
    slope, intercept = np.polyfit(x, y, 1)
    scored = {id(d) for d in pairs}
    return {"intercept": float(intercept), "slope": float(slope), "decisions": len(pairs),
            "episodes": sum(any(id(d) in scored for d in r["decisions"]) for r in records)}


def _apply_line(records: list[dict], line: dict) -> None:
    pairs, y, x = _scored_pairs(records)
    for d, yi, xi in zip(pairs, y, x):
        d["nmse_residualised"] = float(yi - line["intercept"] - line["slope"] * xi)


def residualise_records(records: list[dict], calibration: list[dict] | dict | None = None,
                        folds: int = RESIDUAL_FOLDS) -> dict | None:
    """Sec. 4.10's control: each scored decision gets ``nmse_residualised``, its log NMSE minus a line of log NMSE
    on log persistence NMSE that was never fitted on its own episode. Returns how (None: nothing to fit).

    ``calibration``: the records of a calibration split (other seeds, e.g. ``jepa-policy eval --out`` of a
    held-out block) or a line already fitted on one (``residual_line``). The line comes from there only, so an
    episode's value depends on its own decisions and the calibration split, never on which other episodes
    this run holds. Without one the run is cross-fitted: episode seed s is in fold s % ``folds`` and gets the
    line fitted on the run's other folds (a fold whose complement has fewer than 3 scored decisions gets none);
    its value then still moves with the episodes of the other folds.
    """
    if calibration is not None:
        line = calibration if isinstance(calibration, dict) else residual_line(calibration)
        if isinstance(line, dict) and not {"intercept", "slope"} <= set(line):
            raise ValueError("a calibration line needs 'intercept' and 'slope' (residual_line of a calibration "
                             "split's records); a cross-fitted report's residualised_fit is not one")
        if line is None:
            raise ValueError("the calibration split has fewer than 3 decisions with both NMSE and persistence "
                             "NMSE; evaluate more held-out episodes for it")
        _apply_line(records, line)
        return {**line, "how": "fitted on the calibration split, applied to every episode of this run",
                "what": "log NMSE = intercept + slope * log NMSE(z_t, z_{t+k}); nmse_residualised is the rest"}
    if folds < 2:
        raise ValueError(f"cross-fitting needs folds >= 2, got {folds}")
    by_fold: dict[int, list[dict]] = {}
    for r in records:
        by_fold.setdefault(int(r["seed"]) % folds, []).append(r)
    lines = {}
    for fold, held in sorted(by_fold.items()):
        line = residual_line([r for f, part in by_fold.items() if f != fold for r in part])
        if line is not None:
            _apply_line(held, line)
        lines[fold] = line
    if all(line is None for line in lines.values()):
        return None
    return {"how": f"cross-fitted: episode seed s in fold s % {folds}, residualised on the line of the other folds",
            "folds": {str(f): line for f, line in lines.items()},
            "what": "log NMSE = intercept + slope * log NMSE(z_t, z_{t+k}); nmse_residualised is the rest"}


def env_kwargs_for(spec, env_args: dict | None) -> dict:
    """Constructor kwargs that rebuild the environment the demonstrations were recorded in.

    PushT stores its own constructor options under ``env_kwargs``; the robosuite backends take the dataset's
    ``env_args`` whole. The image size is always the policy's.
    """
    kwargs = {}
    if env_args:
        if spec.suite == "embedded":
            kwargs.update(env_args.get("env_kwargs", {}))
        elif spec.suite in ("robomimic", "mimicgen"):
            kwargs["env_args"] = env_args
    kwargs["image_size"] = spec.image_size
    return kwargs


def pool_env(policy, fault: dict | None = None) -> tuple[str, dict]:
    """The env id and constructor kwargs a rollout pool of ``policy`` builds; with ``fault`` ({"name": one of
    ``jepa_envs.tasks.faults.FAULTS``, "onset": step or [low, high], the fault's own options}) the task's env
    wrapped in that fault."""
    spec = policy.spec
    kwargs = env_kwargs_for(spec, getattr(policy, "env_args", None))
    if not fault:
        return spec.env_id, kwargs
    options = dict(fault)
    name = options.pop("name", None)
    if name not in FAULTS:
        raise ValueError(f"unknown fault {name!r}; choose one of {sorted(FAULTS)}")
    return FAULTED_ENV, {**kwargs, "base": spec.env_id, "fault": name, "fault_kwargs": options}


def make_pool(policy, num_envs: int, workers: int | None = 0, max_steps: int | None = None,
              timeout_s: float | None = None, fault: dict | None = None) -> EnvPool:
    """A persistent rollout pool for ``policy``'s task (its image size, its demonstrations' env settings);
    pass it to ``evaluate`` again and again. ``workers=None``: one worker per available core; 0: in-process.
    ``fault``: every env wrapped in that fault (``pool_env``). ``timeout_s``: the hung-worker limit; None derives
    it from the task's measured reset/step time, or takes JEPA_POOL_TIMEOUT_S (``EnvPool``)."""
    env_id, env_kwargs = pool_env(policy, fault)
    return EnvPool(env_id, num_envs, workers=workers, env_kwargs=env_kwargs, max_steps=max_steps,
                   timeout_s=timeout_s)


def evaluate(policy, episodes: int, seed: int, num_envs: int = 4, max_steps: int | None = None,
             video_dir: str | Path | None = None, on_decision: Callable[[DecisionEvent], None] | None = None,
             keep_latents: bool = False, out: str | Path | None = None, pool: EnvPool | None = None,
             workers: int | None = 0, max_reruns: int = 2, shard: tuple[int, int] | None = None,
             save_rollouts: str | Path | None = None, residual_calibration: list[dict] | dict | None = None,
             fault: dict | None = None, tags: dict | None = None) -> dict:
    """Run ``episodes`` rollouts with seeds seed, seed+1, ... in rounds of ``num_envs`` lockstep environments.

    The environments live in ``pool`` (a persistent ``EnvPool`` from ``make_pool``, reused across calls; its
    size sets the round) or in a pool made for this call with ``workers`` processes (0: in this process; None:
    one per core). The policy acts on each round's observations as one batch, so results are the same whatever
    the number of workers. A worker that dies or hangs is restarted and its round rerun (at most ``max_reruns``
    times); the report lists each rerun. Per-decision events (``on_decision``) are delivered once their round
    has completed, so a rerun never delivers an event twice. Only the frames the policy uses are rendered
    (``policy.images_needed``) unless videos are written. Returns the report (success rate, mean NMSE,
    per-episode records); ``out`` also writes the records as JSONL; ``tags``: fields added to every record;
    ``keep_latents``: each scored decision also holds its z_hat, z_now and z_real (lists: what a robot sends the
    monitor).

    Across machines (torchrun): ``shard=(rank, world)``, by default that of an initialised torch.distributed
    process group, gives rank r the rounds r, r + world, ...; every rank's records are gathered, so every rank
    returns the whole report (``out`` is written by rank 0) and it equals the one-process report. Each rank runs
    its own pool and delivers ``on_decision`` events of its own episodes. Without a process group, an explicit
    ``shard`` runs and reports that shard's episodes only.

    ``residual_calibration``: the records (or the line, ``residual_line``) of a calibration split that each
    decision's ``nmse_residualised`` is taken against; without it the run's episodes are cross-fitted
    (``residualise_records``).

    ``save_rollouts``: also write every episode (all frames rendered, actions, rewards, its seed and outcome as
    ``success``) as a robomimic-layout HDF5 file, e.g. for ``jepa-envs lerobot export`` (its ``next.success``).

    ``fault``: every episode runs under that fault (``pool_env``; a given ``pool`` must have been made with it);
    each record then names it and its onset step (``fault``, ``fault_onset``). Every decision record carries the
    policy's decision-time failure scores (``scores``: STAC, and the embedding scores when the policy has
    fitted detectors; ``jepa_policy/detectors.py``), and ``nmse_white`` beside ``nmse`` when the detectors
    hold the future-error scale.
    """
    if episodes < 1 or num_envs < 1:
        raise ValueError(f"need episodes >= 1 and num_envs >= 1, got {episodes}, {num_envs}")
    spec = policy.spec
    own_pool = pool is None
    if own_pool:
        pool = make_pool(policy, min(num_envs, episodes), workers=workers, max_steps=max_steps, fault=fault)
    else:
        wanted_id, wanted = pool_env(policy, fault)
        if pool.env_id != wanted_id or pool.env_kwargs != wanted:
            raise ValueError(f"the pool runs {pool.env_id} with {pool.env_kwargs}, the policy acts on {wanted_id} "
                             f"with {wanted}; make a pool for it (jepa_policy.evaluate.make_pool)")
    n = pool.num_envs
    rank, world = shard if shard is not None else _process_group()
    if not 0 <= rank < world:
        raise ValueError(f"shard must be (rank, world) with 0 <= rank < world, got {(rank, world)}")
    records, reruns = [], []
    with contextlib.ExitStack() as stack:
        if own_pool:
            stack.callback(pool.close)
        writer = None if save_rollouts is None else stack.enter_context(DemoWriter(save_rollouts, {
            **(getattr(policy, "env_args", None) or {}), "env_name": spec.name,
            "rollouts": {"seed": seed, "checkpoint_step": policy.checkpoint_step}}))
        for first in list(range(0, episodes, n))[rank::world]:
            ids = list(range(first, min(first + n, episodes)))
            for attempt in range(max_reruns + 1):
                events: list[DecisionEvent] = []
                steps: list | None = [] if writer is not None else None
                try:
                    records += _run_round(pool, policy, ids, seed, video_dir,
                                          events.append if on_decision else None, keep_latents, steps,
                                          None if not fault else fault["name"])
                    for episode in steps or []:
                        writer.add(episode)
                    break
                except WorkerFailure as exc:
                    if attempt == max_reruns:
                        raise RuntimeError(f"{exc}; the round of episodes {ids[0]}-{ids[-1]} failed "
                                           f"{max_reruns + 1} times, giving up") from exc
                    print(f"[evaluate] {exc}; restarting it and rerunning episodes {ids[0]}-{ids[-1]}",
                          file=sys.stderr, flush=True)
                    for worker, reason in exc.failures.items():
                        reruns.append({"episodes": ids, "worker": worker, "reason": reason})
                        pool.restart(worker, reason)
            for event in events:
                on_decision(event)
    shares = {rank: [r["episode"] for r in records]}
    if world > 1 and dist.is_available() and dist.is_initialized():
        gathered = [None] * world
        dist.all_gather_object(gathered, (rank, records, reruns))
        records = sorted((r for _, part, _ in gathered for r in part), key=lambda r: r["episode"])
        reruns = [x for _, _, part in gathered for x in part]
        shares = {k: [r["episode"] for r in part] for k, part, _ in gathered}
    valid = [d["nmse"] for r in records for d in r["decisions"] if d["nmse"] is not None]
    fit = residualise_records(records, residual_calibration)
    report = {
        "task": spec.name,
        "episodes": episodes,
        "seed": seed,
        "success_rate": float(np.mean([r["success"] for r in records])),
        "mean_length": float(np.mean([r["length"] for r in records])),
        "mean_max_reward": float(np.mean([r["max_reward"] for r in records])),  # PushT: best coverage
        "mean_nmse": float(np.mean(valid)) if valid else None,
        "mean_nmse_persistence": float(np.mean(
            [d["nmse_persistence"] for r in records for d in r["decisions"] if d.get("nmse_persistence") is not None]
        )) if valid else None,
        "residualised_fit": fit,
        "workers": pool.workers,
        "renderer": pool.renderer,
        "reruns": reruns,
        "ranks": world,
        "episodes_by_rank": shares,
        "records": records,
    }
    for r in records:   # e.g. the arm and checkpoint, so that records of several checkpoints never pool
        r.update(tags or {})
    if out and rank == 0:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        with open(out, "w") as f:
            for r in records:
                f.write(json.dumps(r) + "\n")
    return report


def _process_group() -> tuple[int, int]:
    """(rank, world size) of an initialised torch.distributed process group, else (0, 1)."""
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def _scores_of(decision, j: int) -> dict:
    """Env ``j``'s decision-time scores of a batched decision (NaN, e.g. STAC at the first decision, as None)."""
    return {name: (float(v[j]) if np.isfinite(v[j]) else None) for name, v in decision.scores.items()}


def _run_round(envs, policy, ids, seed, video_dir, on_decision, keep_latents, steps: list | None = None,
               fault: str | None = None) -> list[dict]:
    """One round of lockstep episodes; ``steps`` (a list) receives each episode's frames, actions, rewards and
    outcome, every frame rendered; ``fault``: the name of the fault the pool's envs run under."""
    n = envs.num_envs
    seeds = [seed + i for i in ids] + [seed + ids[-1] + 1 + j for j in range(n - len(ids))]  # spares
    live = np.array([j < len(ids) for j in range(n)])
    success, length = np.zeros(n, bool), np.zeros(n, int)
    max_reward = np.full(n, -np.inf)
    decisions = [[] for _ in range(n)]
    pending: list = []          # (decision, z_now) pairs whose target frame has not arrived
    frames = [[] for _ in range(n)]
    want_video = video_dir is not None
    keep = steps is not None
    kept = [{"obs": [], "actions": [], "rewards": []} for _ in range(n)]

    policy.reset()
    envs.set_render_images(True)
    obs, reset_info = envs.reset(seeds, active=list(live))   # spares keep the batch's shape and are never stepped
    # the kind of failure each episode would be if it ended now, for tasks that name them (Lift, Can: outcomes.py)
    failure_kind = np.asarray(reset_info["failure_kind"], int) if "failure_kind" in reset_info else None
    future_scale = getattr(getattr(policy, "detectors", None), "future_scale", None)
    while live.any():
        if want_video:
            for j in np.flatnonzero(live):
                frames[j].append(np.concatenate([obs[key][j] for key in policy.spec.image_keys], axis=1))
        before = policy.last_decision
        action = policy.act(obs)
        if keep:
            for j in np.flatnonzero(live):
                kept[j]["obs"].append({k: np.array(v[j]) for k, v in obs.items()})
                kept[j]["actions"].append(np.array(action[j], np.float32))
        decision = policy.last_decision
        if decision is not before and decision.z_hat is not None:
            z_now = policy.encode_future(obs)
            pending.append((decision, z_now))
            if on_decision:
                for j in np.flatnonzero(live):
                    on_decision(DecisionEvent("prediction", ids[j], seeds[j], decision.step,
                                              decision.target_step, decision.z_hat[j], z_now=z_now[j]))
        elif decision is not before:
            for j in np.flatnonzero(live):
                decisions[j].append({"step": decision.step, "target_step": decision.target_step, "nmse": None,
                                     "scores": _scores_of(decision, j)})
        envs.set_render_images(want_video or keep or policy.images_needed(policy.t + 1))
        obs, reward, terminated, truncated, infos = envs.step(action)
        t_new = policy.t + 1
        length += live
        max_reward = np.where(live, np.maximum(max_reward, reward), max_reward)
        if keep:
            for j in np.flatnonzero(live):
                kept[j]["rewards"].append(float(reward[j]))
        if "is_success" in infos:
            success |= live & np.asarray(infos["is_success"], bool)
        if failure_kind is not None and "failure_kind" in infos:
            failure_kind = np.where(live, np.asarray(infos["failure_kind"], int), failure_kind)
        due = [p for p in pending if p[0].target_step == t_new]
        pending = [p for p in pending if p[0].target_step != t_new]
        if due:
            z_real = policy.encode_future(obs)
            for d, z_now in due:
                err, err_persistence = nmse_rows(d.z_hat, z_real), nmse_rows(z_now, z_real)
                white = None if future_scale is None else whitened_error(d.z_hat, z_real, future_scale)
                for j in np.flatnonzero(live):
                    rec = {"step": d.step, "target_step": d.target_step, "nmse": float(err[j]),
                           "nmse_persistence": float(err_persistence[j]), "scores": _scores_of(d, j)}
                    if white is not None:
                        rec["nmse_white"] = float(white[j])
                    if keep_latents:
                        rec.update(z_hat=d.z_hat[j].tolist(), z_now=z_now[j].tolist(), z_real=z_real[j].tolist())
                    decisions[j].append(rec)
                    if on_decision:
                        on_decision(DecisionEvent("realized", ids[j], seeds[j], d.step, d.target_step,
                                                  d.z_hat[j], z_real[j], float(err[j])))
        ended = live & (np.asarray(terminated) | np.asarray(truncated))
        for j in np.flatnonzero(ended):  # decisions still waiting for a frame that never comes
            for d, _ in pending:
                decisions[j].append({"step": d.step, "target_step": d.target_step, "nmse": None,
                                     "scores": _scores_of(d, j)})
        live &= ~ended

    records = []
    for j, episode in enumerate(ids):
        records.append({"episode": episode, "seed": seeds[j], "success": bool(success[j]),
                        "length": int(length[j]), "max_reward": float(max_reward[j]), "decisions": sorted(decisions[j], key=lambda d: d["step"])})
        if fault is not None:
            records[-1].update(fault=fault, fault_onset=int(reset_info["fault_onset"][j]))
        if failure_kind is not None:
            records[-1]["failure_kind"] = None if success[j] else failure_kind_name(failure_kind[j])
        if keep:
            ep = kept[j]
            steps.append({"obs": {k: np.stack([o[k] for o in ep["obs"]]) for k in ep["obs"][0]},
                          "actions": np.stack(ep["actions"]), "rewards": np.asarray(ep["rewards"], np.float32),
                          "dones": np.eye(1, len(ep["actions"]), len(ep["actions"]) - 1, dtype=np.uint8)[0],
                          "attrs": {"success": bool(success[j]), "seed": int(seeds[j]), "episode": int(episode)}})
        if want_video and frames[j]:
            import imageio.v2 as imageio
            Path(video_dir).mkdir(parents=True, exist_ok=True)
            imageio.mimsave(Path(video_dir) / f"episode_{episode:04d}_seed{seeds[j]}.gif", frames[j], duration=0.1)
    return records
