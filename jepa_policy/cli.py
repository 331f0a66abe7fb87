"""``jepa-policy``: train, eval, describe, bench latency, bench train, audit, protocols, robot."""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from jepa_policy.train import TrainConfig


def _add_train_args(parser: argparse.ArgumentParser) -> None:
    """One flag per TrainConfig field (CleanRL style); unset flags keep the preset's value."""
    parser.add_argument("--config", help="JSON file of TrainConfig fields (e.g. a run's train_config.json)")
    parser.add_argument("--preset", default="paper", help="preset of configs/<task>.json (paper, cpu, quick)")
    for f in dataclasses.fields(TrainConfig):
        flag = "--" + f.name.replace("_", "-")
        default = getattr(TrainConfig(), f.name)
        if isinstance(default, bool):
            parser.add_argument(flag, dest=f.name, action=argparse.BooleanOptionalAction, default=None)
        elif isinstance(default, dict):
            parser.add_argument(flag, dest=f.name, type=json.loads, default=None,
                                help="JSON object of ModelConfig overrides")
        else:
            parser.add_argument(flag, dest=f.name, type=type(default), default=None, help=f"default {default!r}")


def _train_config(args) -> TrainConfig:
    from jepa_policy.train import load_config

    overrides = {f.name: getattr(args, f.name) for f in dataclasses.fields(TrainConfig)
                 if getattr(args, f.name) is not None}
    if args.config:
        data = json.loads(Path(args.config).read_text())
        return TrainConfig.from_dict({**data, **overrides})
    task = overrides.pop("task", "PushT")
    return load_config(task, args.preset, **overrides)


def cmd_train(args) -> int:
    from jepa_policy.train import train

    cfg = _train_config(args)
    result = train(cfg)
    print(json.dumps({"checkpoint": result["checkpoint"], "step": result["step"], "eval_curve": result["curve"]}))
    return 0


def cmd_eval(args) -> int:
    from jepa_policy.evaluate import evaluate
    from jepa_policy.policy import Policy

    policy = Policy.from_checkpoint(args.checkpoint, device=args.device, ema=not args.no_ema)
    report = evaluate(policy, episodes=args.episodes, seed=args.seed, num_envs=args.num_envs,
                      max_steps=args.max_steps, video_dir=args.video, out=args.out)
    summary = {k: v for k, v in report.items() if k != "records"}
    print(json.dumps(summary))
    return 0


def cmd_describe(args) -> int:
    from jepa_policy.describe import describe

    report = describe(args.task, arm=args.arm)
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
                           seed=args.seed)
    print(json.dumps(result, indent=2) if args.json else format_latency(result))
    return 0


def cmd_bench_train(args) -> int:
    from jepa_policy.bench import bench_train, format_train

    result = bench_train(args.task, preset=args.preset, arm=args.arm, steps=args.steps, warmup=args.warmup,
                         device=args.device, batch_size=args.batch_size)
    print(json.dumps(result, indent=2) if args.json else format_train(result))
    return 0


def cmd_protocols(args) -> int:
    from jepa_policy.evaluate import reporting_protocols

    path = Path(args.curve)
    if path.suffix == ".pt":
        from jepa_policy.checkpoint import load_checkpoint
        curve = load_checkpoint(path)["eval_curve"]
    else:
        curve = json.loads(path.read_text())
    print(json.dumps(reporting_protocols(curve)))
    return 0


def cmd_audit(args) -> int:
    from jepa_envs.data import load_dataset
    from jepa_policy.audit import audit_checkpoint
    from jepa_policy.policy import Policy

    policy = Policy.from_checkpoint(args.checkpoint, device=args.device)
    demos = load_dataset(args.dataset, task=policy.spec.name, image_size=policy.spec.image_size)
    print(json.dumps(audit_checkpoint(policy, demos, samples=args.samples, seed=args.seed)))
    return 0


def cmd_robot(args) -> int:
    from jepa_policy.robot import run_checkpoint_on_bridge

    summary = run_checkpoint_on_bridge(args.checkpoint, args.address, args.episodes, seed=args.seed,
                                       device=args.device, method=args.method, wait=not args.no_wait)
    print(json.dumps(summary, indent=2, default=str))
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=2, default=str))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="jepa-policy", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("train", help="train a policy (torchrun for several GPUs / nodes)")
    _add_train_args(p)
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("eval", help="seeded rollouts of a checkpoint: success rate and per-decision NMSE")
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--episodes", type=int, default=40)
    p.add_argument("--seed", type=int, default=100_000)
    p.add_argument("--num-envs", type=int, default=4)
    p.add_argument("--max-steps", type=int, default=None, help="episode step limit (default: the task's)")
    p.add_argument("--video", default=None, help="directory for one GIF per episode")
    p.add_argument("--out", default=None, help="JSONL file of per-episode records")
    p.add_argument("--device", default="cpu")
    p.add_argument("--no-ema", action="store_true", help="act with the raw instead of the EMA weights")
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("describe", help="parameter counts of an arm, total and per part")
    p.add_argument("--task", default="ToolHang")
    p.add_argument("--arm", default="jepa")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_describe)

    bench = sub.add_parser("bench", help="latency and training-throughput benchmarks")
    bsub = bench.add_subparsers(dest="bench", required=True)
    p = bsub.add_parser("latency", help="decision latency at batch 1, arms interleaved in one process")
    p.add_argument("--task", default="ToolHang")
    p.add_argument("--arms", default="mip,jepa,diffusion")
    p.add_argument("--warmup", type=int, default=30)
    p.add_argument("--iters", type=int, default=300)
    p.add_argument("--dp-steps", default="100,16", help="DDPM sampler lengths timed for the diffusion arm")
    p.add_argument("--device", default="auto")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_bench_latency)
    p = bsub.add_parser("train", help="training samples/s and peak memory on synthetic batches")
    p.add_argument("--task", default="ToolHang")
    p.add_argument("--preset", default="paper")
    p.add_argument("--arm", default="jepa")
    p.add_argument("--steps", type=int, default=3)
    p.add_argument("--warmup", type=int, default=1)
    p.add_argument("--batch-size", type=int, default=None, help="default: the preset's")
    p.add_argument("--device", default="auto")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_bench_train)

    p = sub.add_parser("audit", help="collapse audit (Sec. 4.9): effective rank, top share, TE32 of latents")
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--dataset", required=True)
    p.add_argument("--samples", type=int, default=4096)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu")
    p.set_defaults(func=cmd_audit)

    p = sub.add_parser("protocols", help="Table 6 reporting protocols from eval_curve.json or a checkpoint")
    p.add_argument("curve")
    p.set_defaults(func=cmd_protocols)

    p = sub.add_parser("robot", help="run a checkpoint for N episodes on a robot bridge (jepa-robot-bridge)")
    p.add_argument("--address", default="tcp://127.0.0.1:5555", help="the bridge's control socket")
    p.add_argument("--checkpoint", required=True, help="a `jepa-policy train` checkpoint")
    p.add_argument("--episodes", type=int, default=10, help="episodes to run")
    p.add_argument("--seed", type=int, default=0, help="seed of the first episode")
    p.add_argument("--device", default="cpu", help="torch device of the policy")
    p.add_argument("--method", default="JEPA Policy", help="recorded in every episode's manifest")
    p.add_argument("--no-wait", action="store_true", help="do not wait for Enter before each episode")
    p.add_argument("--json", help="also write the summary to this file")
    p.set_defaults(func=cmd_robot)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
