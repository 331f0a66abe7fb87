"""``jepa-policy``: train, eval, fit-detectors, describe, bench (latency, train, serve, rollouts), audit, protocols,
robot, serve.

One module of about 630 lines on purpose: each command's run sits beside its flags and nothing else is in it: every
import of the work is inside the command that does it, so ``--help`` loads none of it."""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import re
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

from jepa_envs.errors import USER_ERRORS, user_error


def _non_negative(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be a whole number >= 0, got {text!r}")
    return value


def _add_train_args(parser: argparse.ArgumentParser) -> None:
    """One flag per TrainConfig field (CleanRL style); unset flags keep the preset's value."""
    from jepa_policy.train import TRAIN_HELP, TrainConfig

    parser.add_argument("--config", help="JSON file of TrainConfig fields (e.g. a run's train_config.json)")
    parser.add_argument("--preset", default="paper", help="preset of configs/<task>.json (paper, cpu, quick)")
    for f in dataclasses.fields(TrainConfig):
        # the run folder is every command's --out; --out-dir stays while docs/training.md still names it
        flags = ("--out", "--out-dir") if f.name == "out_dir" else ("--" + f.name.replace("_", "-"),)
        default = getattr(TrainConfig(), f.name)
        text = f"{TRAIN_HELP[f.name]} (paper default {default!r})"
        if isinstance(default, bool):
            parser.add_argument(*flags, dest=f.name, action=argparse.BooleanOptionalAction, default=None, help=text)
        elif isinstance(default, dict):
            parser.add_argument(*flags, dest=f.name, type=json.loads, default=None, help=TRAIN_HELP[f.name])
        else:
            parser.add_argument(*flags, dest=f.name, type=type(default), default=None, help=text)


def _train_config(args):
    from jepa_policy.train import TrainConfig, load_config

    overrides = {f.name: getattr(args, f.name) for f in dataclasses.fields(TrainConfig)
                 if getattr(args, f.name) is not None}
    if args.config:
        path = Path(args.config)
        if not path.is_file():
            raise FileNotFoundError(f"--config {path} does not exist; pass a run's train_config.json")
        data = json.loads(path.read_text())
        if overrides.get("resume") and "stop_at" not in overrides:
            # a run's train_config.json keeps the stop_at it was launched with; a resume goes on to the end
            data["stop_at"] = 0
        return TrainConfig.from_dict({**data, **overrides})
    task = overrides.pop("task", None)
    if task is None and overrides.get("dataset"):   # a dataset that names its task needs no --task
        from jepa_envs.datasets.lerobot import recorded_task

        task = recorded_task(overrides["dataset"])
        if task is not None:
            print(f"jepa-policy train: task {task}, as the dataset records it (--task overrides it)", file=sys.stderr)
    return load_config(task or "PushT", args.preset, **overrides)


def cmd_train(args) -> int:
    from jepa_policy.train import train

    try:
        cfg = _train_config(args)
    except TypeError as exc:   # an option of the wrong type in --config or --model: the user's to fix
        raise ValueError(str(exc)) from None
    result = train(cfg)
    print(json.dumps({"checkpoint": result["checkpoint"], "step": result["step"], "eval_curve": result["curve"]}))
    return 0


def cmd_eval(args) -> int:
    from jepa_policy.policy import Policy
    from jepa_policy.train import resolve_device

    if args.faults_only and not (args.faults or "").strip():
        raise ValueError("--faults-only needs --faults NAME[;NAME...] (or all)")
    calibration = None
    if args.residual_calibration:
        path = Path(args.residual_calibration)
        if not path.is_file():
            raise FileNotFoundError(f"--residual-calibration {path} does not exist; write one with `jepa-policy eval "
                                    "--out calib.jsonl` on other seeds (e.g. --seed 300000)")
        calibration = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    if args.keep_latents and not args.out:
        raise ValueError("--keep-latents keeps the latents in --out's records; give --out FILE.jsonl")
    policy = Policy.from_checkpoint(args.checkpoint, device=resolve_device(args.device), ema=not args.no_ema)
    if args.faults:
        return _eval_regimes(args, policy, calibration)
    with _episode_bar(args.episodes, "eval", args.no_progress) as bar:
        report = _evaluate_on_bar(bar, policy, None, episodes=args.episodes, seed=args.seed,
                                  num_envs=args.num_envs, max_steps=args.max_steps, video_dir=args.video,
                                  out=args.out, workers=args.workers, save_rollouts=args.save_rollouts,
                                  residual_calibration=calibration, tags=_record_tags(args, policy),
                                  keep_latents=args.keep_latents)
    summary = {k: v for k, v in report.items() if k != "records"}
    from jepa_policy.published import PUBLISHED_TASKS, published_metrics

    if report["task"] in PUBLISHED_TASKS:   # the standard Push-T: its published metrics beside the published figures
        summary["published_metrics"] = published_metrics(report["records"])
    print(json.dumps(summary))
    return 0


def _episode_bar(total: int | None, name: str, off: bool):
    """A tqdm bar of finished episodes on stderr (``off``: --no-progress)."""
    from tqdm import tqdm

    return tqdm(total=total, desc=name, unit="episode", disable=off)


def _evaluate_on_bar(bar, policy, fault: dict | None, **kwargs) -> dict:
    """``evaluate`` on a pool of its own whose rounds move ``bar``."""
    from jepa_policy.evaluate import evaluate, make_pool
    from jepa_policy.progress import EpisodeProgress

    with make_pool(policy, min(kwargs["num_envs"], kwargs["episodes"]), workers=kwargs.pop("workers"),
                   max_steps=kwargs["max_steps"], fault=fault) as pool:
        seen = EpisodeProgress(pool, bar)
        report = evaluate(policy, pool=seen, fault=fault, **kwargs)
        seen.finish()
    return report


def _fault_spec(text: str) -> dict:
    """``NAME`` or ``NAME:key=value,key=value`` (values as JSON, e.g. onset=[20,60]; ``label``, the records'
    regime name, as text) -> {"name", options}."""
    name, _, rest = text.partition(":")
    spec: dict = {"name": name.strip()}
    for item in filter(None, (x.strip() for x in re.split(r",(?![^\[]*\])", rest))):   # not inside [...]
        key, eq, value = item.partition("=")
        if not eq:
            raise ValueError(f"fault option {item!r} needs key=value, e.g. {name}:onset=30")
        if key.strip() == "label":   # the records' regime name, plain text
            label = value.strip()
            if not re.fullmatch(r"[A-Za-z0-9_.:\-]{1,64}", label) or label == "natural":
                raise ValueError(f"fault label {label!r} must be 1-64 letters, digits or _ . : - and not 'natural' "
                                 f"(the records' regime name, a table column), e.g. {name.strip()}:label=tint_faint")
            spec["label"] = label
            continue
        try:
            spec[key.strip()] = json.loads(value)
        except json.JSONDecodeError:
            raise ValueError(f"fault option {key}={value!r} is not a number or JSON list") from None
    return spec


def _record_tags(args, policy) -> dict:
    """What every eval record names: its arm and checkpoint (compare groups records by them, never pooling two)."""
    return {"arm": policy.model.cfg.arm, "checkpoint": str(args.checkpoint)}


def _eval_regimes(args, policy, calibration) -> int:
    """``eval --faults``: the natural episodes and each fault's, one records file (every record tagged with its
    ``regime``, ``arm`` and ``checkpoint``); a fault runs on the first ``--fault-episodes`` seeds of the natural
    block, so each faulted episode has a natural twin up to its onset."""
    import time

    from jepa_envs.tasks.faults import faults_for

    if args.video or args.save_rollouts:
        raise ValueError("--faults writes records only; drop --video / --save-rollouts (or run one fault at a time)")
    names = faults_for(policy.spec) if args.faults.strip() == "all" else \
        [x for x in args.faults.split(";") if x.strip()]
    if not names:
        raise ValueError(f"--faults {args.faults!r} names no fault; give NAME[;NAME...] or all")
    regimes = ([] if args.faults_only else [None]) + [_fault_spec(x) for x in names]
    labels = ["natural" if f is None else str(f.pop("label", f["name"])) for f in regimes]
    if len(set(labels)) < len(labels):
        shared = sorted(x for x in labels if labels.count(x) > 1)
        raise ValueError(f"two regimes would share the records' label {shared}; name one with label=..., e.g. "
                         "background_tint:tint=[-2,0,2],label=tint_faint")
    import gymnasium as gym

    from jepa_policy.evaluate import pool_env
    for fault in regimes:   # every fault's name and options checked before the first rollout, not after hours of them
        if fault is not None:
            env_id, env_kwargs = pool_env(policy, fault)
            gym.make(env_id, **env_kwargs).close()
    records, summary = [], {"checkpoint": str(args.checkpoint), "regimes": {}}
    counts = [args.episodes if fault is None else min(args.fault_episodes, args.episodes) for fault in regimes]
    with _episode_bar(sum(counts), "eval", args.no_progress) as bar:
        for fault, label, episodes in zip(regimes, labels, counts):
            t0 = time.perf_counter()
            report = _evaluate_on_bar(bar, policy, fault, episodes=episodes, seed=args.seed, num_envs=args.num_envs,
                                      max_steps=args.max_steps, workers=args.workers,
                                      residual_calibration=calibration, keep_latents=args.keep_latents,
                                      tags={"regime": label, **_record_tags(args, policy)})
            records += report["records"]
            summary["regimes"][label] = {"episodes": episodes, "success_rate": report["success_rate"],
                                         "seconds": round(time.perf_counter() - t0, 1)}
            bar.write(f"[eval] {label}: {episodes} episodes, success {report['success_rate']:.3f}, "
                      f"{time.perf_counter() - t0:.0f} s", file=sys.stderr)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text("".join(json.dumps(r) + "\n" for r in records))
    print(json.dumps(summary))
    return 0


def cmd_fit_detectors(args) -> int:
    from jepa_envs.datasets.hdf5 import load_dataset
    from jepa_policy.detectors import fit_detectors
    from jepa_policy.policy import Policy
    from jepa_policy.train import resolve_device

    policy = Policy.from_checkpoint(args.checkpoint, device=resolve_device(args.device), detectors=False)
    if not Path(args.dataset).is_file():
        raise FileNotFoundError(f"--dataset {args.dataset} does not exist; pass the demonstrations the checkpoint "
                                "was trained on")
    demos = load_dataset(args.dataset, task=policy.spec.name, image_size=policy.spec.image_size)
    path = fit_detectors(policy, args.checkpoint, demos, samples=args.samples, seed=args.seed, out=args.out,
                         progress=not args.no_progress)
    print(json.dumps({"detectors": str(path), "checkpoint": str(args.checkpoint), "samples": args.samples}))
    return 0


def cmd_describe(args) -> int:
    from jepa_policy.describe import describe

    overrides = {}
    if args.preset:
        from jepa_policy.train import load_config

        cfg = load_config(args.task, args.preset)
        overrides = dict(cfg.model, **({"image_size": cfg.image_size} if cfg.image_size else {}))
    report = describe(args.task, arm=args.arm, **overrides)
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        width = max(len(k) for k in report.get("parts", {})) if report.get("parts") else 10
        print(f"{args.task} / {args.arm}: {report['total'] / 1e6:.2f} M parameters")
        for name, count in report.get("parts", {}).items():
            print(f"  {name:<{width}}  {count / 1e6:8.3f} M")
    return 0


def cmd_bench_latency(args) -> int:
    from jepa_policy.bench import bench_latency, format_latency

    result = bench_latency(args.task, arms=args.arms.split(","), warmup=args.warmup, iters=args.iters,
                           dp_steps=tuple(int(s) for s in args.dp_steps.split(",")), device=args.device,
                           seed=args.seed, scores=args.scores, preset=args.preset, progress=not args.no_progress)
    print(json.dumps(result, indent=2) if args.json else format_latency(result))
    return 0


def cmd_bench_serve(args) -> int:
    from jepa_policy.serve.bench import bench_serve, format_serve

    result = bench_serve(args.task, args.preset, args.checkpoint, iters=args.iters, seconds=args.seconds,
                         clients=tuple(int(c) for c in args.clients.split(",")), threads=args.threads,
                         hostile=args.hostile, progress=not args.no_progress)
    print(json.dumps(result, indent=2) if args.json else format_serve(result))
    return 0


def cmd_bench_rollouts(args) -> int:
    from jepa_policy.bench import bench_rollouts, format_rollouts

    result = bench_rollouts(args.task, workers=args.workers, episodes=args.episodes, num_envs=args.num_envs,
                            max_steps=args.max_steps, repeats=args.repeats, preset=args.preset,
                            progress=not args.no_progress, checkpoint=args.checkpoint, seed=args.seed)
    print(json.dumps(result, default=str) if args.json else format_rollouts(result))
    return 0


def cmd_bench_train(args) -> int:
    from jepa_policy.bench import bench_train, format_train

    result = bench_train(args.task, preset=args.preset, arm=args.arm, steps=args.steps, warmup=args.warmup,
                         device=args.device, batch_size=args.batch_size, progress=not args.no_progress)
    print(json.dumps(result, indent=2) if args.json else format_train(result))
    return 0


def cmd_protocols(args) -> int:
    from jepa_policy.evaluate import reporting_protocols

    path = Path(args.curve)
    if args.select:
        from jepa_policy.selection import select_checkpoint
        from jepa_policy.train import resolve_device

        run_dir = path if path.is_dir() else path.parent
        result = select_checkpoint(run_dir, fresh_seed=args.fresh_seed,
                                   ladder=tuple(int(x) for x in args.ladder.split(",")), num_envs=args.num_envs,
                                   max_steps=args.max_steps, device=resolve_device(args.device),
                                   workers=args.workers, report_seed=args.report_seed,
                                   report_episodes=args.report_episodes, progress=not args.no_progress)
        print(json.dumps(result, indent=2))
        return 0
    if path.is_dir():
        path = path / "eval_curve.json"
    if not path.exists():
        raise FileNotFoundError(f"{path} does not exist; pass a run's eval_curve.json, its folder or a checkpoint")
    if path.suffix == ".pt":
        from jepa_policy.checkpoint import load_checkpoint
        curve = load_checkpoint(path)["eval_curve"]
    else:
        curve = json.loads(path.read_text())
    print(json.dumps(reporting_protocols(curve)))
    return 0


def cmd_audit(args) -> int:
    from jepa_envs.datasets.hdf5 import load_dataset
    from jepa_envs.datasets.lerobot import resolve_dataset
    from jepa_policy.audit import audit_checkpoint, gradient_audit, retrieval_audit, visibility_audit
    from jepa_policy.policy import Policy
    from jepa_policy.train import resolve_device

    kinds = args.kind.split(",")
    unknown = sorted(set(kinds) - {"collapse", "retrieval", "gradients", "visibility"})
    if unknown:
        raise ValueError(f"unknown audit(s) {unknown}; choose from collapse, retrieval, gradients, visibility")
    if args.samples is not None and args.samples < 1:
        raise ValueError(f"--samples must be >= 1 window, got {args.samples}")
    if args.seed < 0:
        raise ValueError(f"--seed must be >= 0, got {args.seed}")
    faults = None
    if args.faults is not None:
        if "visibility" not in kinds:
            raise ValueError("--faults is read by the visibility audit only; add --kind visibility")
        faults = [_fault_spec(x) for x in args.faults.split(";") if x.strip()]
        if not faults:
            raise ValueError(f"--faults {args.faults!r} names no fault; give NAME[:k=v,...][;NAME...], e.g. "
                             "camera_shift;camera_shift:pixels=6,label=camera_6px")
    policy = Policy.from_checkpoint(args.checkpoint, device=resolve_device(args.device))
    demos = load_dataset(resolve_dataset(args.dataset, policy.spec.name), task=policy.spec.name,
                         image_size=policy.spec.image_size)
    report = {"checkpoint": str(args.checkpoint), "dataset": str(args.dataset), "arm": policy.model.cfg.arm}
    progress = not args.no_progress
    if "collapse" in kinds:
        report["collapse"] = audit_checkpoint(policy, demos, samples=args.samples or 4096, seed=args.seed,
                                              progress=progress)
    if "retrieval" in kinds:
        report["retrieval"] = retrieval_audit(policy, demos, samples=args.samples or 4096, pool=args.pool,
                                              seed=args.seed, permutations=args.permutations, progress=progress)
    if "gradients" in kinds:
        report["gradients"] = gradient_audit(policy, demos, batches=args.batches, seed=args.seed, progress=progress)
    if "visibility" in kinds:
        report["visibility"] = visibility_audit(policy, demos, faults=faults, samples=args.samples or 1024,
                                                seed=args.seed, progress=progress)
    print(json.dumps(report, indent=2))
    return 0


def _score_names(text: str | None) -> tuple[str, ...] | None:
    """--monitor-scores: None for all, () for none, else the names."""
    if text in (None, "all"):
        return None
    return () if text == "none" else tuple(x.strip() for x in text.split(",") if x.strip())


def cmd_robot(args) -> int:
    from jepa_envs.real_robot.proxy import BridgeError
    from jepa_policy.robot import run_checkpoint_on_bridge
    from jepa_policy.serve import read_secret
    from jepa_policy.serve.config import MONITOR_KEY_ENV

    try:
        summary = run_checkpoint_on_bridge(args.checkpoint, args.address, args.episodes, seed=args.seed,
                                           device=args.device, method=args.method, wait=not args.no_wait,
                                           asynchronous=args.asynchronous, replan_steps=args.replan_steps,
                                           curve_server_key=args.curve_server_key,
                                           curve_client_key=args.curve_client_key, monitor_url=args.monitor_url,
                                           monitor_key=read_secret("--monitor-key", args.monitor_key,
                                                                   args.monitor_key_file, MONITOR_KEY_ENV),
                                           task_id=args.task_id, robot=args.robot,
                                           monitor_scores=_score_names(args.monitor_scores),
                                           progress=not args.no_progress)
    except (BridgeError, TimeoutError) as exc:   # busy, lost control, no bridge: the message names the fix
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(summary, indent=2, default=str))
    if args.out:
        Path(args.out).write_text(json.dumps(summary, indent=2, default=str))
    return 0


def cmd_serve(args) -> int:
    from jepa_policy.serve import ServeConfig, read_secret, serve_checkpoint
    from jepa_policy.serve.config import API_KEY_ENV, MONITOR_KEY_ENV

    if not Path(args.checkpoint).exists():
        raise FileNotFoundError(f"checkpoint {args.checkpoint} does not exist; train one with `jepa-policy train` (or "
                                "pass the pretrained_model folder lerobot-train wrote for --policy.type=jepa)")
    config = ServeConfig(host=args.host, port=args.port,
                         api_key=read_secret("--api-key", args.api_key, args.api_key_file, API_KEY_ENV),
                         tls_cert=args.tls_cert, tls_key=args.tls_key, tls_client_ca=args.tls_client_ca,
                         max_batch=args.max_batch, max_queue=args.max_queue, max_connections=args.max_connections,
                         monitor_url=args.monitor_url,
                         monitor_key=read_secret("--monitor-key", args.monitor_key, args.monitor_key_file,
                                                 MONITOR_KEY_ENV),
                         task_id=args.task_id, robot=args.robot, monitor_scores=_score_names(args.monitor_scores))
    serve_checkpoint(args.checkpoint, config, device=args.device, threads=args.threads)
    return 0


def _version() -> str:
    """This install's version, for --version."""
    try:
        return version("jepa-policy-toolkit")
    except PackageNotFoundError:
        return "unknown (not installed: pip install -e . in the checkout)"


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The whole command line; given ``argv``, train's flags only when it runs train: they are generated from
    ``TrainConfig``, whose module imports torch, which ``jepa-policy --help`` and every other command need not."""
    parser = argparse.ArgumentParser(prog="jepa-policy", description=__doc__)
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("train", help="train a policy (torchrun for several GPUs / nodes)")
    if argv is None or argv[:1] == ["train"]:
        _add_train_args(p)
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("eval", help="seeded rollouts of a checkpoint: success rate and per-decision NMSE")
    p.add_argument("--checkpoint", required=True,
                   help="a `jepa-policy train` checkpoint (.pt) or a LeRobot jepa policy folder")
    p.add_argument("--episodes", type=int, default=40, help="rollouts (default 40, the paper's)")
    p.add_argument("--seed", type=int, default=100_000, help="seed of the first rollout; episode i uses seed + i")
    p.add_argument("--num-envs", type=int, default=4, help="environments stepped together (the policy's batch)")
    p.add_argument("--workers", type=_non_negative, default=None,
                   help="env-only rollout processes (default: one per available core; 0: step the envs in this "
                        "process, fastest for cheap envs such as PushT); results are identical for any number; a "
                        "worker silent past 30x its measured step time (at least 30 s; JEPA_POOL_TIMEOUT_S=S fixes "
                        "the limit) is restarted and its round rerun")
    p.add_argument("--max-steps", type=int, default=None, help="episode step limit (default: the task's)")
    p.add_argument("--video", default=None, help="directory for one GIF per episode")
    p.add_argument("--out", default=None, help="JSONL file of per-episode records")
    p.add_argument("--keep-latents", action="store_true",
                   help="each scored decision in --out also holds its predicted, current and realized future "
                        "latents (z_hat, z_now, z_real: what a robot sends the monitor; `jepa-monitor replay` "
                        "streams them to a service)")
    p.add_argument("--save-rollouts", default=None, metavar="FILE.hdf5",
                   help="also write every episode (all frames, actions, rewards, outcome) as robomimic-layout HDF5, "
                        "e.g. for `jepa-envs lerobot export` (outcomes become next.success)")
    p.add_argument("--residual-calibration", metavar="RECORDS.jsonl",
                   help="records of a calibration split (`--out` of an eval on other seeds): nmse_residualised is "
                        "taken against the line fitted there (default: cross-fitted over this run's episodes)")
    p.add_argument("--faults", metavar="all|NAME[:k=v,...][;NAME...]",
                   help="also run the episodes under faults with a known onset (jepa_envs/tasks/faults.py), e.g. "
                        "all, or 'block_displaced:onset=30;action_noise:std=40'; --out then holds every regime's "
                        "records, tagged with the fault's name or its label= option (for jepa-monitor compare)")
    p.add_argument("--fault-episodes", type=int, default=100,
                   help="--faults: episodes per fault, on the first seeds of the natural block (default 100)")
    p.add_argument("--faults-only", action="store_true",
                   help="--faults: skip the natural block (when its records exist already, e.g. to add a fault "
                        "to a study: the faulted episodes use the same seeds either way)")
    p.add_argument("--device", default="auto", help="auto (CUDA when present) | cpu | cuda | cuda:N")
    p.add_argument("--no-ema", action="store_true", help="act with the raw instead of the EMA weights")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr (for logs)")
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("fit-detectors", help="fit the embedding failure detectors (RND, PCA-kmeans, Mahalanobis) of "
                                             "a checkpoint on its training set; written beside it")
    p.add_argument("--checkpoint", required=True, help="a `jepa-policy train` checkpoint (.pt)")
    p.add_argument("--dataset", required=True, help="the demonstrations (HDF5) the checkpoint was trained on")
    p.add_argument("--samples", type=int, default=8192, help="training windows embedded (a seeded sample)")
    p.add_argument("--seed", type=int, default=0, help="seed of the sample, k-means and RND")
    p.add_argument("--out", help="where to write (default: <checkpoint stem>.detectors.npz beside it)")
    p.add_argument("--device", default="auto", help="auto | cpu | cuda | cuda:N")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr (for logs)")
    p.set_defaults(func=cmd_fit_detectors)

    p = sub.add_parser("describe", help="parameter counts of an arm, total and per part")
    p.add_argument("--task", default="ToolHang", help="task whose shapes to use")
    p.add_argument("--arm", default="jepa", help="comparison arm (jepa, mip, dual_independent, ...)")
    p.add_argument("--preset", default=None, help="shapes of this preset of configs/<task>.json (default: the paper's)")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.set_defaults(func=cmd_describe)

    bench = sub.add_parser("bench", help="latency and training-throughput benchmarks")
    bsub = bench.add_subparsers(dest="bench", required=True)
    p = bsub.add_parser("latency", help="decision latency at batch 1, arms interleaved in one process")
    p.add_argument("--task", default="ToolHang", help="task whose model shapes to time")
    p.add_argument("--arms", default="mip,jepa,diffusion", help="comma-separated arms, timed interleaved")
    p.add_argument("--warmup", type=int, default=30, help="untimed calls first (paper: 30)")
    p.add_argument("--iters", type=int, default=300, help="timed calls (paper: 300)")
    p.add_argument("--dp-steps", default="100,16", help="DDPM sampler lengths timed for the diffusion arm")
    p.add_argument("--preset", default=None,
                   help="model shapes of this preset of configs/<task>.json (e.g. PushT cpu: the main job's; "
                        "default: the paper's)")
    p.add_argument("--scores", action="store_true",
                   help="also time each arm with every failure score the runtime adds (STAC, RND, PCA-kmeans, "
                        "Mahalanobis, whitened NMSE), interleaved with the same arm without them")
    p.add_argument("--device", default="auto", help="auto | cpu | cuda | cuda:N")
    p.add_argument("--seed", type=int, default=0, help="seed of the random weights and inputs")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr (for logs)")
    p.set_defaults(func=cmd_bench_latency)
    p = bsub.add_parser("train", help="training samples/s and peak memory on synthetic batches")
    p.add_argument("--task", default="ToolHang", help="task whose model shapes to train")
    p.add_argument("--preset", default="paper", help="preset of configs/<task>.json")
    p.add_argument("--arm", default="jepa", help="comparison arm")
    p.add_argument("--steps", type=int, default=3, help="timed steps")
    p.add_argument("--warmup", type=int, default=1, help="untimed steps first")
    p.add_argument("--batch-size", type=int, default=None, help="default: the preset's")
    p.add_argument("--device", default="auto", help="auto | cpu | cuda | cuda:N")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr (for logs)")
    p.set_defaults(func=cmd_bench_train)

    p = bsub.add_parser("serve", help="jepa-policy serve beside in-process decisions: round-trip overhead at batch "
                                      "1, decisions/s with 1, 4 and 16 clients, batched and not")
    p.add_argument("--task", default="PushT", help="task whose model to serve")
    p.add_argument("--preset", default="cpu", help="model of configs/<task>.json (random weights)")
    p.add_argument("--checkpoint", help="serve this checkpoint instead")
    p.add_argument("--iters", type=int, default=200, help="paired round trips at batch 1")
    p.add_argument("--seconds", type=float, default=5.0, help="per concurrency level")
    p.add_argument("--clients", default="1,4,16", help="concurrent clients to measure")
    p.add_argument("--threads", type=int, default=1, help="torch threads of the server and the in-process policy")
    p.add_argument("--hostile", action="store_true",
                   help="also: one robot's latency beside a client sending 8 MiB frames of 190,000 tiny arrays, and "
                        "the server's peak memory under 8 clients sending oversized frames")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr (for logs)")
    p.set_defaults(func=cmd_bench_serve)

    p = bsub.add_parser("rollouts", help="episodes/min of rollouts with 1 and N pool workers, side by side")
    p.add_argument("--task", default="PushT", help="task whose env to roll out (PushT, Square, ToolHang, ...)")
    p.add_argument("--workers", type=int, default=None, help="the N of the comparison (default: the cores)")
    p.add_argument("--episodes", type=int, default=8, help="episodes per timed evaluation")
    p.add_argument("--num-envs", type=int, default=4, help="environments per round (the policy's batch)")
    p.add_argument("--max-steps", type=int, default=60, help="episode step limit")
    p.add_argument("--repeats", type=int, default=2, help="timed evaluations per pool, interleaved")
    p.add_argument("--preset", default="cpu", help="model shapes of this preset")
    p.add_argument("--checkpoint", default=None,
                   help="roll out this trained policy (its task, image size and recorded env) instead of a random "
                        "model: episodes end when they succeed, so the rate is its evaluation's")
    p.add_argument("--seed", type=int, default=0, help="seed of the first episode (episode i: seed + i)")
    # --quiet stays while docs/rollouts.md still names it
    p.add_argument("--no-progress", "--quiet", dest="no_progress", action="store_true",
                   help="no plan, time estimate or progress bar on stderr")
    p.add_argument("--json", action="store_true", help="print JSON instead of a line")
    p.set_defaults(func=cmd_bench_rollouts)

    p = sub.add_parser("audit", help="the paper's audits of a checkpoint: collapse (c_t, E_rgb, z_hat), retrieval, "
                                     "gradient interaction")
    p.add_argument("--checkpoint", required=True, help="a `jepa-policy train` checkpoint (.pt)")
    p.add_argument("--dataset", required=True, help="the demonstrations it was trained on (the sample manifest)")
    p.add_argument("--kind", default="collapse,retrieval,gradients",
                   help="comma-separated: collapse (Sec. 4.9), retrieval (Sec. 4.9), gradients (Sec. 4.5); also "
                        "visibility: how far each image fault moves the NMSE and embedding scores the monitor reads")
    p.add_argument("--faults", default=None, metavar="NAME[:k=v,...][;NAME...]",
                   help="the visibility audit's image faults, as eval --faults names them, e.g. "
                        "'camera_shift;camera_shift:pixels=6,label=camera_6px' (default: every image fault of the "
                        "task at its default options)")
    p.add_argument("--samples", type=int, default=None,
                   help="windows in the fixed manifest (default 4,096, the paper's; the visibility audit: 1,024)")
    p.add_argument("--pool", type=int, default=256, help="retrieval candidates per query (paper: 256)")
    p.add_argument("--permutations", type=int, default=1000, help="label permutations of the retrieval null")
    p.add_argument("--batches", type=int, default=8, help="batches averaged by the gradient audit")
    p.add_argument("--seed", type=int, default=0, help="seed of the manifest, the pools and the batches")
    p.add_argument("--device", default="auto", help="auto | cpu | cuda | cuda:N")
    p.add_argument("--no-progress", action="store_true", help="no progress bars on stderr (for logs)")
    p.set_defaults(func=cmd_audit)

    p = sub.add_parser("protocols", help="Table 6 reporting protocols of a run, or (--select) its leakage-free "
                                         "checkpoint selection on fresh seeds")
    p.add_argument("curve", help="a run folder, its eval_curve.json, or a checkpoint")
    p.add_argument("--select", action="store_true",
                   help="confirm the two best evaluation checkpoints on fresh seeds with a paired bootstrap")
    p.add_argument("--fresh-seed", type=int, default=1_000_000, help="first fresh rollout seed (--select)")
    p.add_argument("--ladder", default="32,64,128", help="fresh episodes per candidate while undecided (--select)")
    p.add_argument("--report-seed", type=int, default=2_000_000,
                   help="first seed of the untouched block the pick's success is reported on (--select)")
    p.add_argument("--report-episodes", type=int, default=None,
                   help="episodes of that block (--select; default: the ladder's last rung)")
    p.add_argument("--num-envs", type=int, default=4, help="environments stepped together (--select)")
    p.add_argument("--workers", type=_non_negative, default=None,
                   help="env-only rollout processes (--select; default: one per available core; 0: in-process)")
    p.add_argument("--max-steps", type=int, default=None, help="episode step limit (--select; default: the task's)")
    p.add_argument("--device", default="auto", help="auto | cpu | cuda | cuda:N (--select)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr (--select; for logs)")
    p.set_defaults(func=cmd_protocols)

    p = sub.add_parser("robot", help="run a checkpoint for N episodes on a robot bridge (jepa-robot-bridge)")
    p.add_argument("--address", default="tcp://127.0.0.1:5555", help="the bridge's control socket")
    p.add_argument("--checkpoint", required=True, help="a `jepa-policy train` checkpoint")
    p.add_argument("--episodes", type=int, default=10, help="episodes to run")
    p.add_argument("--seed", type=int, default=0, help="seed of the first episode")
    p.add_argument("--device", default="cpu", help="torch device of the policy")
    p.add_argument("--method", default="JEPA Policy", help="recorded in every episode's manifest")
    p.add_argument("--no-wait", action="store_true", help="do not wait for Enter before each episode")
    p.add_argument("--async", dest="asynchronous", action="store_true",
                   help="asynchronous execution: infer the next chunk while the current one executes")
    p.add_argument("--replan-steps", type=int, help="--async: replan after this many actions (default n/2)")
    p.add_argument("--curve-server-key", help="CurveZMQ: the bridge's public key file (jepa-robot-bridge keys)")
    p.add_argument("--curve-client-key", help="CurveZMQ: this computer's secret key file")
    p.add_argument("--out", metavar="FILE.json", help="also write the summary (printed as JSON) to this file")
    p.add_argument("--monitor-url", help="report every decision (z_hat, scores), target and outcome to this monitor "
                                         "service, e.g. http://127.0.0.1:8765 (synchronous loop)")
    p.add_argument("--monitor-key", help="a robot key of the monitor; visible in ps: prefer JEPA_POLICY_MONITOR_KEY "
                                         "or --monitor-key-file")
    p.add_argument("--monitor-key-file", help="read the monitor key from this file's first line (chmod 600)")
    p.add_argument("--task-id", help="the monitor's task name (default: the checkpoint's task)")
    p.add_argument("--robot", help="the monitor key's robot name")
    p.add_argument("--monitor-scores", default="all",
                   help="named scores to send: all (default: every finite one the policy computes), none, or a comma "
                        "list, e.g. stac,rnd (the task must register them: jepa-monitor tasks add TASK --signals ...)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr (for logs)")
    p.set_defaults(func=cmd_robot)

    p = sub.add_parser("serve", help="serve a checkpoint over openpi's websocket protocol (openpi-client), with the "
                                     "monitor inside")
    p.add_argument("--checkpoint", required=True,
                   help="a `jepa-policy train` checkpoint, or a LeRobot jepa policy folder")
    p.add_argument("--host", default="127.0.0.1",
                   help="bind address (another than loopback needs an API key or mutual TLS)")
    p.add_argument("--port", type=int, default=8000, help="TCP port (0: a free one)")
    p.add_argument("--api-key", help="clients must send 'Authorization: Api-Key KEY' (openpi-client's api_key); "
                                     "visible in ps: prefer JEPA_POLICY_API_KEY or --api-key-file")
    p.add_argument("--api-key-file", help="read the API key from this file's first line (chmod 600)")
    p.add_argument("--tls-cert", help="serve wss:// with this certificate (PEM)")
    p.add_argument("--tls-key", help="the certificate's private key (PEM)")
    p.add_argument("--tls-client-ca", help="mutual TLS: clients must show a certificate this CA (PEM) signed")
    p.add_argument("--device", default="cpu", help="torch device of the policy")
    p.add_argument("--threads", type=int, help="torch intra-op threads")
    p.add_argument("--max-batch", type=int, default=16, help="requests of several robots batched into one pass")
    p.add_argument("--max-queue", type=int, default=64, help="waiting requests beyond which one is refused")
    p.add_argument("--max-connections", type=int, default=32,
                   help="open connections beyond which a new one is refused (HTTP 503)")
    p.add_argument("--monitor-url", help="the monitor service (jepa-monitor serve), e.g. http://127.0.0.1:8765")
    p.add_argument("--monitor-key", help="a robot key of the monitor service; visible in ps: prefer "
                                         "JEPA_POLICY_MONITOR_KEY or --monitor-key-file")
    p.add_argument("--monitor-key-file", help="read the monitor key from this file's first line (chmod 600)")
    p.add_argument("--task-id", help="the monitor's task name (default: the checkpoint's task)")
    p.add_argument("--robot", help="the monitor key's robot name")
    p.add_argument("--monitor-scores", default="none",
                   help="named failure scores sent with each decision: none (default), all (STAC and, with fitted "
                        "detectors beside the checkpoint, RND, PCA-kmeans, Mahalanobis), or a comma list, e.g. "
                        "stac,rnd (the task must register them: jepa-monitor tasks add TASK --signals ...)")
    p.set_defaults(func=cmd_serve)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser(argv).parse_args(argv)
    try:
        return args.func(args)
    except USER_ERRORS as exc:
        return user_error(f"jepa-policy {args.command}", exc)


if __name__ == "__main__":
    sys.exit(main())
