"""Benchmarks of the policy: decision latency of the arms (Table 5), training throughput / peak memory (Sec. 4.1)
and evaluation rollouts with 1 and N pool workers. The policy server's are in ``jepa_policy/serve/bench.py``.

Latency follows the paper's protocol: batch 1, EMA weights, eager mode, arms interleaved in one process
(each round times every arm once, so drift of the machine hits all arms alike), 30 warm-up and 300 timed calls
per arm, with device synchronisation around each call. Network passes are counted by forward hooks on the
model's top-level parts during one decision, not assumed.
"""
from __future__ import annotations

import contextlib
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn
from tqdm import tqdm

from jepa_envs.rollouts.pool import available_cores
from jepa_envs.tasks.spec import get_task_spec
from jepa_policy.checkpoint import save_eval_snapshot
from jepa_policy.config import ModelConfig
from jepa_policy.detectors import fit_embedding_detectors, stac, whitened_error
from jepa_policy.evaluate import evaluate, make_pool
from jepa_policy.model import build_model
from jepa_policy.policy import Policy
from jepa_policy.train import load_config, resolve_device


def _random_stats(spec) -> dict:
    stats = {"action": {"min": -np.ones(spec.action_dim, np.float32), "max": np.ones(spec.action_dim, np.float32)}}
    for key, dim in spec.lowdim:
        stats[key] = {"min": -np.ones(dim, np.float32), "max": np.ones(dim, np.float32)}
    for key in spec.image_keys:   # the pixel stats of uniform noise, for presets with image_norm "dataset"
        stats[key] = {"mean": np.full(3, 0.5, np.float32), "std": np.full(3, 0.29, np.float32)}
    return stats


def _synthetic_obs(spec, batch: int, steps: int, device, gen: torch.Generator) -> dict:
    s = spec.image_size
    obs = {k: torch.randint(0, 256, (batch, steps, s, s, 3), dtype=torch.uint8, generator=gen).to(device)
           for k in spec.image_keys}
    for key, dim in spec.lowdim:
        obs[key] = (torch.rand(batch, steps, dim, generator=gen) * 2 - 1).to(device)
    return obs


def _random_ema(spec, arm: str, device, **overrides) -> AveragedModel:
    """A randomly initialised model wrapped like training wraps it (its EMA copy is what acts)."""
    model = build_model(ModelConfig.for_task(spec, arm=arm, **overrides)).to(device)
    model.set_normalizer_stats(_random_stats(spec))
    ema = AveragedModel(model, multi_avg_fn=get_ema_multi_avg_fn(0.995), use_buffers=True)
    ema.update_parameters(model)
    return ema


def _ema_model(spec, arm: str, device, **overrides):
    """The EMA copy of a random model, as the benchmark acts with it."""
    return _random_ema(spec, arm, device, **overrides).module.eval()


def count_passes(model: torch.nn.Module, call) -> dict[str, int]:
    """How many times each top-level part of ``model`` runs during ``call()`` (forward hooks)."""
    counts: dict[str, int] = {}
    handles = []
    for name, child in model.named_children():
        def hook(_module, _inputs, _output, name=name):
            counts[name] = counts.get(name, 0) + 1
        handles.append(child.register_forward_hook(hook))
    try:
        call()
    finally:
        for h in handles:
            h.remove()
    return counts


def _sync(device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_calls(calls: dict, warmup: int = 30, iters: int = 300, device=None, progress: bool = False
               ) -> dict[str, dict]:
    """Time each zero-argument callable, interleaved: every round calls each once (Table 5 protocol).

    Returns {label: {mean_ms, p95_ms, median_ms, max_hz}}; runs under ``torch.inference_mode``. ``progress``: a
    bar of the rounds on stderr.
    """
    dev = torch.device(device) if device is not None else torch.device("cpu")
    times = {label: [] for label in calls}
    with torch.inference_mode():
        for i in tqdm(range(warmup + iters), desc="bench latency", unit="round", disable=not progress):
            for label, call in calls.items():
                _sync(dev)
                t0 = time.perf_counter()
                call()
                _sync(dev)
                if i >= warmup:
                    times[label].append((time.perf_counter() - t0) * 1e3)
    rows = {}
    for label, values in times.items():
        t = np.asarray(values)
        rows[label] = {"mean_ms": float(t.mean()), "p95_ms": float(np.percentile(t, 95)),
                       "median_ms": float(np.median(t)), "max_hz": float(1e3 / t.mean())}
    return rows


def _runtime_call(model, obs, want: bool, detectors=None, shift: int = 8):
    """One decision as the acting runtime makes it (``policy.decide_frames``: the pass that also returns c_t, the
    chunk, z_hat and c_t brought to numpy) and, with ``detectors``, every failure score it adds
    (``Policy._scores``): STAC against the previous chunk, the embedding detectors (RND, PCA-kmeans, Mahalanobis)
    and, with a future head, the whitened NMSE of z_hat (against a stand-in for the realized latent)."""
    state = {"previous": None}

    def call():
        actions, z_hat, c = model.predict_embedded(obs, want_future=want)
        chunk = actions.float().cpu().numpy()
        z = None if z_hat is None else z_hat.float().cpu().numpy()
        c = c.cpu().numpy()
        if detectors is None:
            return chunk, z, c
        out = {"stac": stac(chunk, state["previous"], shift)}
        state["previous"] = chunk
        out.update(detectors.score(c))
        if z is not None and detectors.future_scale is not None:
            out["nmse_white"] = whitened_error(z, 0.9 * z, detectors.future_scale)
        return out
    return call


def _bench_detectors(model, spec, dev, seed: int, want: bool):
    """Embedding detectors fitted on this model's own c_t of random inputs (their cost does not depend on
    what they were fitted on, only on the widths: 64 k-means centres, <= 32 PCA directions, the RND nets)."""
    gen = torch.Generator().manual_seed(seed + 1)
    cs, errs = [], []
    with torch.inference_mode():
        while not cs or sum(len(x) for x in cs) < max(2 * 64, cs[0].shape[1] + 2):   # fit_embedding_detectors' need
            obs = _synthetic_obs(spec, 64, spec.obs_steps, dev, gen)
            _a, z, c = model.predict_embedded(obs, want_future=want)
            cs.append(c.double().cpu().numpy())
            if z is not None:
                errs.append(z.double().cpu().numpy() * 0.1)
    c = np.concatenate(cs)
    c = c + 1e-3 * np.random.default_rng(seed).standard_normal(c.shape)   # random weights: keep it full rank
    return fit_embedding_detectors(c, np.concatenate(errs) if errs else None, seed=seed)


def bench_latency(task: str = "ToolHang", arms=("mip", "jepa", "diffusion"), warmup: int = 30, iters: int = 300,
                  dp_steps=(100, 16), device: str = "auto", seed: int = 0, scores: bool = False,
                  preset: str | None = None, progress: bool = False) -> dict:
    """Time one decision (``model.predict`` at batch 1) per arm; the diffusion arm once per sampler length.
    ``scores``: also each arm with an embedding (jepa, mip, ...) as the acting runtime decides (``<label>
    runtime``: the pass that returns c_t, its outputs to numpy) and the same with every failure score it adds
    (``<label> runtime+scores``: STAC, RND, PCA-kmeans, Mahalanobis, whitened NMSE), timed in the same interleaved
    rounds; ``<label>+scores_over_<label>`` is the ratio of the two. ``preset``: the model shapes of that preset of
    configs/<task>.json (e.g. PushT's ``cpu``, the main job's) instead of the paper's. ``progress``: a bar of the
    timed rounds on stderr."""
    if warmup < 0 or iters < 1:
        raise ValueError(f"need warmup >= 0 and iters >= 1, got {warmup}, {iters}")
    spec = get_task_spec(task)
    shapes = {}
    if preset is not None:
        cfg = load_config(spec.name, preset)
        shapes = dict(cfg.model)
        if cfg.image_size:
            spec = spec.with_image_size(cfg.image_size)
    dev = resolve_device(device)
    torch.manual_seed(seed)
    # (label, arm, model, want_future). JEPA's control path skips the future head in its second pass (Table 5);
    # "jepa+monitor" is the monitored path that also returns z_hat.
    variants = []
    for arm in arms:
        if arm == "diffusion":
            for steps in dp_steps:
                model = _ema_model(spec, arm, dev, **{**shapes, "diffusion_infer_steps": int(steps),
                                                      "diffusion_train_steps": max(100, int(steps))})
                variants.append((f"diffusion-{steps}", arm, model, False))
        else:
            model = _ema_model(spec, arm, dev, **shapes)
            variants.append((arm, arm, model, False))
            if arm == "jepa":
                variants.append(("jepa+monitor", arm, model, True))
    gen = torch.Generator().manual_seed(seed)
    obs = _synthetic_obs(spec, 1, spec.obs_steps, dev, gen)

    rows = {}
    for label, arm, model, want in variants:
        with torch.inference_mode():
            passes = count_passes(model, lambda: model.predict(obs, want_future=want))
        rows[label] = {"arm": arm, "want_future": want, "params_m": sum(p.numel() for p in model.parameters()) / 1e6,
                       "passes": passes, "network_passes": max(passes.values())}
    calls = {label: (lambda m=model, w=want: m.predict(obs, want_future=w)) for label, _a, model, want in variants}
    if scores:
        for label, arm, model, want in list(variants):
            if not hasattr(model, "predict_embedded"):
                continue
            detectors = _bench_detectors(model, spec, dev, seed, want)
            calls[f"{label} runtime"] = _runtime_call(model, obs, want)
            calls[f"{label} runtime+scores"] = _runtime_call(model, obs, want, detectors, spec.n_action_steps)
            rows[f"{label} runtime"] = {**rows[label], "scores": False}
            rows[f"{label} runtime+scores"] = {**rows[label], "scores": True}
    for label, row in time_calls(calls, warmup, iters, dev, progress=progress).items():
        rows[label].update(row)
    ratios = {}
    if "jepa" in rows and "mip" in rows:
        ratios["jepa_over_mip"] = rows["jepa"]["mean_ms"] / rows["mip"]["mean_ms"]
    for label in [r for r in rows if r.endswith(" runtime+scores")]:   # the scores' cost on the runtime's decision
        base = label[:-len(" runtime+scores")]
        ratios[f"{base}+scores_over_{base}"] = rows[label]["mean_ms"] / rows[f"{base} runtime"]["mean_ms"]
    for steps in dp_steps:
        if f"diffusion-{steps}" in rows and "jepa" in rows:
            ratios[f"dp{steps}_over_jepa"] = rows[f"diffusion-{steps}"]["mean_ms"] / rows["jepa"]["mean_ms"]
    return {"task": spec.name, "preset": preset or "paper", "device": str(dev), "device_name": _device_name(dev),
            "warmup": warmup,
            "iters": iters, "torch": torch.__version__, "threads": torch.get_num_threads(), "arms": rows,
            "ratios": ratios}


def _device_name(dev) -> str:
    if dev.type == "cuda":
        return torch.cuda.get_device_name(dev)
    import platform
    return platform.processor() or platform.machine()


def format_latency(result: dict) -> str:
    lines = [f"decision latency, {result['task']} ({result.get('preset', 'paper')} shapes), batch 1, EMA weights, "
             f"{result['device']} "
             f"({result['device_name']}), {result['warmup']} warm-up + {result['iters']} timed calls, interleaved",
             f"{'arm':<26}{'params':>9}{'mean ms':>10}{'p95 ms':>10}{'max Hz':>9}  passes"]
    for label, row in result["arms"].items():
        passes = ", ".join(f"{k}x{v}" for k, v in row["passes"].items())
        lines.append(f"{label:<26}{row['params_m']:>8.2f}M{row['mean_ms']:>10.2f}{row['p95_ms']:>10.2f}"
                     f"{row['max_hz']:>9.1f}  {passes}")
    for name, value in result["ratios"].items():
        lines.append(f"{name}: {value:.3f}")
    return "\n".join(lines)


def _peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux reports KiB


def bench_train(task: str = "ToolHang", preset: str = "paper", arm: str = "jepa", steps: int = 3, warmup: int = 1,
                device: str = "auto", batch_size: int | None = None, seed: int = 0, progress: bool = False) -> dict:
    """Training samples/s and peak memory on synthetic batches of the task's shapes under a preset's config.

    Peak memory is ``torch.cuda.max_memory_allocated`` on CUDA and the process's peak RSS on CPU. ``progress``: a
    bar of the steps on stderr.
    """
    if steps < 1 or warmup < 0:
        raise ValueError(f"need steps >= 1 and warmup >= 0, got {steps}, {warmup}")
    cfg = load_config(task, preset, arm=arm)
    spec = get_task_spec(task)
    if cfg.image_size:
        spec = spec.with_image_size(cfg.image_size)
    batch = batch_size or cfg.batch_size
    dev = resolve_device(device)
    torch.manual_seed(seed)
    rss_before = _peak_rss_mib()
    model = build_model(ModelConfig.for_task(spec, arm=arm, **cfg.model)).to(dev)
    model.set_normalizer_stats(_random_stats(spec))
    model.train()
    optimizer = torch.optim.AdamW(model.param_groups(cfg.weight_decay), lr=cfg.lr, betas=(cfg.beta1, cfg.beta2))
    ema = AveragedModel(model, multi_avg_fn=get_ema_multi_avg_fn(cfg.ema_decay), use_buffers=True)
    gen = torch.Generator().manual_seed(seed)
    data = {"obs": _synthetic_obs(spec, batch, spec.obs_steps, dev, gen),
            "future_obs": {k: v[:, -1] for k, v in _synthetic_obs(spec, batch, 1, dev, gen).items()
                           if k in spec.image_keys},
            "action": (torch.rand(batch, spec.horizon, spec.action_dim, generator=gen) * 2 - 1).to(dev)}
    autocast = torch.autocast("cuda", dtype=torch.bfloat16) if dev.type == "cuda" and cfg.bf16 \
        else contextlib.nullcontext()
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats(dev)
    times = []
    for i in tqdm(range(warmup + steps), desc="bench train", unit="step", disable=not progress):
        _sync(dev)
        t0 = time.perf_counter()
        optimizer.zero_grad(set_to_none=True)
        with autocast:
            loss, _ = model.compute_loss(data)
        loss.backward()
        optimizer.step()
        ema.update_parameters(model)
        _sync(dev)
        if i >= warmup:
            times.append(time.perf_counter() - t0)
    step_s = float(np.mean(times))
    result = {"task": spec.name, "preset": preset, "arm": arm, "device": str(dev), "device_name": _device_name(dev),
              "batch_size": batch, "image_size": spec.image_size, "steps": steps,
              "params_m": sum(p.numel() for p in model.parameters()) / 1e6,
              "s_per_step": step_s, "samples_per_s": batch / step_s}
    if dev.type == "cuda":
        result.update(peak_allocated_mib=torch.cuda.max_memory_allocated(dev) / 2**20,
                      peak_reserved_mib=torch.cuda.max_memory_reserved(dev) / 2**20)
    else:
        result.update(peak_rss_mib=_peak_rss_mib(), peak_rss_before_mib=rss_before)
    return result


def format_train(result: dict) -> str:
    mem = (f"peak allocated {result['peak_allocated_mib']:.0f} MiB, reserved {result['peak_reserved_mib']:.0f} MiB"
           if "peak_allocated_mib" in result else
           f"peak RSS {result['peak_rss_mib']:.0f} MiB (before the model: {result['peak_rss_before_mib']:.0f} MiB)")
    return (f"train {result['task']}/{result['arm']} preset={result['preset']} on {result['device']} "
            f"({result['device_name']}): batch {result['batch_size']}, {result['image_size']}px, "
            f"{result['params_m']:.2f} M params, {result['s_per_step']:.3f} s/step, "
            f"{result['samples_per_s']:.1f} samples/s, {mem}")


def rollouts_plan(task: str, size: int, episodes: int, num_envs: int, max_steps: int, repeats: int,
                  pools: list[int]) -> str:
    """What ``bench_rollouts`` is about to run, in one line (it is printed before anything starts)."""
    evaluations = len(pools) * repeats
    steps = evaluations * episodes * max_steps   # a round's spare environments are frozen, not stepped
    return (f"bench rollouts: {task} at {size} px, {evaluations} timed evaluations ({repeats} each with "
            f"{', '.join(map(str, pools))} workers) of {episodes} episodes of <= {max_steps} steps in rounds of "
            f"{num_envs}: up to {steps:,} env steps (the worker pools start first)")


def rollouts_estimate(step_s: float, episodes: int, num_envs: int, max_steps: int, repeats: int,
                      pools: list[int]) -> float:
    """Seconds the timed evaluations take at ``step_s`` per env step (a worker's measured step) if every
    episode runs to ``max_steps``, env time only: 0 and 1 worker step the envs one after the other, N workers
    ``min(N, num_envs)`` at a time."""
    per_eval = episodes * max_steps * step_s
    return repeats * sum(per_eval / max(1, min(n, num_envs)) for n in pools)


def bench_rollouts(task: str = "PushT", workers: int | None = None, episodes: int = 8, num_envs: int = 4,
                   max_steps: int = 60, repeats: int = 2, preset: str = "cpu", image_size: int | None = None,
                   progress: bool = False, checkpoint: str | None = None, seed: int = 0) -> dict:
    """Episodes per minute of full rollouts (env steps and frames in the workers, a JEPA model acting on each
    round's batch in this process) with 1 worker and with ``workers`` workers, interleaved; persistent pools,
    so process start-up is reported apart. A randomly initialised model of the preset's shape acts: the
    throughput of evaluation, not a success rate; or, with ``checkpoint``, that trained policy in the env its
    demonstrations were recorded in (its episodes end when they succeed: the throughput of its evaluation, with
    its success rate). Also checks that both pools give identical records.
    ``progress``: print the plan, the estimated time and a progress bar (episodes) on stderr."""
    torch.set_num_threads(1)   # the policy's share; the workers get the rest of the cores
    workers = available_cores() if workers is None else workers
    if checkpoint:
        policy = Policy.from_checkpoint(checkpoint)
        spec, task = policy.spec, policy.spec.name
        size = spec.image_size
    else:
        spec = get_task_spec(task)
        cfg = load_config(task, preset)
        size = image_size or cfg.image_size or spec.image_size
        spec = spec.with_image_size(size)
        model = _ema_model(spec, "jepa", torch.device("cpu"), **{k: v for k, v in cfg.model.items()
                                                                if k not in ("image_size",)})
        policy = Policy(model, spec)
    counts = sorted({0, 1, workers})
    if progress:
        print(rollouts_plan(task, size, episodes, num_envs, max_steps, repeats, counts), file=sys.stderr, flush=True)
    pools, startup = {}, {}
    for n in counts:
        t0 = time.perf_counter()
        pools[n] = make_pool(policy, num_envs, workers=n, max_steps=max_steps)
        startup[n] = time.perf_counter() - t0
    seconds: dict[int, list[float]] = {n: [] for n in pools}
    records: dict[int, list] = {}
    try:
        step_s = pools[1].describe()["step_s"][0]
        if progress:
            estimate = rollouts_estimate(step_s, episodes, num_envs, max_steps, repeats, counts)
            print(f"pools started in {sum(startup.values()):.1f} s; one {task} step takes {step_s * 1e3:.1f} ms in a "
                  f"worker, so the evaluations take about {estimate / 60:.1f} min of env time (plus the policy's)",
                  file=sys.stderr, flush=True)
        with tqdm(total=len(pools) * repeats * episodes, unit="ep", desc=f"{task} rollouts", disable=not progress,
                  file=sys.stderr) as bar:
            for _ in range(repeats):
                for n, pool in pools.items():
                    bar.set_postfix_str(f"workers={n}")
                    done: set[int] = set()

                    def episode_seen(event, done=done):   # events arrive once a round is complete
                        if event.episode not in done:
                            done.add(event.episode)
                            bar.update(1)
                    t0 = time.perf_counter()
                    report = evaluate(policy, episodes=episodes, seed=seed, pool=pool, on_decision=episode_seen)
                    seconds[n].append(time.perf_counter() - t0)
                    bar.update(episodes - len(done))   # episodes that ended before their first decision's event
                    records[n] = report["records"]
    finally:
        for pool in pools.values():
            pool.close()
    rate = {n: episodes * 60.0 / float(np.median(s)) for n, s in seconds.items()}
    return {"task": task, "image_size": size, "episodes": episodes, "num_envs": num_envs, "max_steps": max_steps,
            "workers": workers, "cores": available_cores(), "episodes_per_min": rate,
            "speedup": rate[workers] / rate[1], "in_process_ratio": rate[0] / rate[1], "startup_s": startup,
            "identical_records": all(r == records[1] for r in records.values()),
            "checkpoint": checkpoint, "seed": seed,
            "successes": sum(r["success"] for r in records[1]),
            "mean_length": float(np.mean([r["length"] for r in records[1]])),
            "renderer": pools[workers].renderer,
            "load_avg": os.getloadavg()[0]}


def format_rollouts(result: dict) -> str:
    w = result["workers"]
    rates = result["episodes_per_min"]
    return (f"{result['task']} rollouts ({result['episodes']} episodes of <= {result['max_steps']} steps, rounds of "
            f"{result['num_envs']}, {result['image_size']} px, renderer {result['renderer']}, "
            f"load {result['load_avg']:.1f} "
            f"on {result['cores']} cores): 1 worker {rates[1]:.1f} episodes/min, {w} workers {rates[w]:.1f} "
            f"episodes/min, speed-up {result['speedup']:.2f}x; in-process (no workers) {rates[0]:.1f} episodes/min; "
            f"pool start-up {result['startup_s'][w]:.1f} s, once; records identical: {result['identical_records']}"
            + (f"; {result['checkpoint']}: {result['successes']}/{result['episodes']} successes, mean length "
               f"{result['mean_length']:.1f} steps" if result.get("checkpoint") else ""))


def _random_checkpoint(task: str, preset: str, path) -> str:
    """A checkpoint of the preset's model with random weights: serving costs the same as a trained one's."""
    cfg = load_config(task, preset)
    spec = get_task_spec(task)
    spec = spec.with_image_size(cfg.image_size or spec.image_size)
    ema = _random_ema(spec, cfg.arm, "cpu", **cfg.model)
    save_eval_snapshot(Path(path), ema=ema, step=0, cfg=cfg, model_cfg=ema.module.cfg, spec=spec)
    return str(path)
