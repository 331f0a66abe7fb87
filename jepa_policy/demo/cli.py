"""``jepa-demo``'s command line: the main job on PushT (``demo/job.py``), the pick job on Lift or Can
(``demo/pick.py``) and the imitation-ceiling study (``demo/ceiling.py``). Each is imported inside the command that
runs it, so ``--help`` and ``--version`` load none of them (torch, robosuite: seconds)."""
from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import replace
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

from jepa_envs.errors import USER_ERRORS, user_error

TASK = "PushT"                  # the main job's task
PICK_TASKS = ("Lift", "Can")    # demo/pick.py's


def _version() -> str:
    """This install's version, for --version."""
    try:
        return version("jepa-policy-toolkit")
    except PackageNotFoundError:
        return "unknown (not installed: pip install -e . in the checkout)"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="jepa-demo", description="JEPA Policy end to end: the main job on the "
                                     "embedded PushT task (default), or on robomimic's Lift or Can (--task)")
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="a minute or two: smaller everything, same code path")
    size.add_argument("--full", action="store_true", help="a real study: three seeds per arm, paired comparison")
    parser.add_argument("--task", default=TASK, choices=(TASK, *PICK_TASKS),
                        help="PushT (default: the main job, about 6 minutes) or a robomimic pick task, Lift or Can "
                             "(demonstrations, both arms, the true-state ceiling, 200 evaluation episodes each; "
                             "docs/training.md, 'Lift and Can on a CPU', has its wall times)")
    parser.add_argument("--out", default="demo_out", help="output folder (default: demo_out)")
    parser.add_argument("--fresh", action="store_true", help="recompute demonstrations and checkpoints")
    parser.add_argument("--workers", type=int, default=None,
                        help="env-only rollout processes of the rollouts (PushT default 0: its env step is cheaper "
                             "than a process round trip; Lift and Can default 2; `jepa-policy bench rollouts` "
                             "measures it); results are identical for any number")
    parser.add_argument("--steps", type=int, default=None,
                        help="training steps per arm instead of the preset's (beyond the 15-minute budget: more "
                             "steps, higher success); written to <out>/<mode>-steps<N>")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars on stderr (for logs)")
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="{ceiling}",
                                help="optional: a study on its own instead of the main job")
    p = sub.add_parser("ceiling", help="PushT imitation ceiling of a demo file: a true-state MLP trained and "
                                       "rolled out with the image policies' chunking")
    p.add_argument("--dataset", required=True, help="PushT demonstration file (jepa-envs make-demos)")
    p.add_argument("--seed", type=int, default=0, help="training seed")
    p.add_argument("--episodes", type=int, default=200, help="evaluation rollouts")
    p.add_argument("--eval-seed", type=int, default=200_000, help="seed of the first evaluation rollout")
    p.add_argument("--steps", type=int, default=4000, help="training steps of the state policy")
    p.add_argument("--no-progress", action="store_true", default=argparse.SUPPRESS,
                   help="no progress bars on stderr (for logs)")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.no_progress:   # tqdm's own switch, inherited by the processes the job spawns
        os.environ["TQDM_DISABLE"] = "1"
    if args.command == "ceiling":
        from jepa_policy.demo.ceiling import state_ceiling
        try:
            result = state_ceiling(args.dataset, seed=args.seed, episodes=args.episodes, eval_seed=args.eval_seed,
                                   steps=args.steps)
        except USER_ERRORS as exc:
            return user_error("jepa-demo ceiling", exc)
        print(json.dumps(result))
        return 0
    mode = "quick" if args.quick else "full" if args.full else "default"
    if args.task != TASK:
        if args.full:
            parser.error("--full is the PushT study (three seeds per arm); a pick task runs one seed per arm")
        from jepa_policy.demo.pick import pick_config, run
        try:
            cfg = pick_config(args.task, mode, args.steps)
            if args.workers is not None:
                if args.workers < 0:
                    raise ValueError(f"--workers must be >= 0 (0: in this process), got {args.workers}")
                cfg = replace(cfg, workers=args.workers)
        except ValueError as exc:
            parser.error(str(exc))
        name = args.task + ("-quick" if mode == "quick" else "") + (f"-steps{args.steps}" if args.steps else "")
        try:
            run(cfg, Path(args.out) / name, fresh=args.fresh)
        except USER_ERRORS as exc:
            return user_error("jepa-demo", exc)
        return 0
    from jepa_policy.demo.job import demo_config, run
    try:
        cfg, name = demo_config(mode, args.steps)
        if args.workers is not None:
            if args.workers < 0:
                raise ValueError(f"--workers must be >= 0 (0: in this process), got {args.workers}")
            cfg = replace(cfg, workers=args.workers)
    except ValueError as exc:
        parser.error(str(exc))
    try:
        run(cfg, Path(args.out) / name, fresh=args.fresh)
    except USER_ERRORS as exc:   # e.g. a checkpoint in the output folder that is refused unread
        return user_error("jepa-demo", exc)
    return 0

if __name__ == "__main__":
    sys.exit(main())
