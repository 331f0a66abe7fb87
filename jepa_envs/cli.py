"""``jepa-envs``: make expert demonstrations, list and describe tasks, benchmark the env layer.

Subcommands are registered with :func:`subcommand`; add one by decorating a ``run(args)`` function and giving
it an ``add_arguments(parser)`` function (see ``make-demos`` below).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from dataclasses import asdict, dataclass
from importlib.metadata import PackageNotFoundError, version
from typing import Callable

from jepa_envs.tasks import install_mimicgen
from jepa_envs.errors import USER_ERRORS, user_error
from jepa_envs.tasks.spec import all_task_specs, backend_available, get_task_spec

@dataclass(frozen=True)
class Subcommand:
    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


SUBCOMMANDS: dict[str, Subcommand] = {}


def subcommand(name: str, help: str, add_arguments: Callable[[argparse.ArgumentParser], None] = lambda p: None):
    """Register ``run(args) -> exit code`` as ``jepa-envs <name>``."""
    def register(run: Callable[[argparse.Namespace], int]):
        SUBCOMMANDS[name] = Subcommand(name, help, add_arguments, run)
        return run
    return register


def _spec_or_exit(task: str):
    try:
        return get_task_spec(task)
    except KeyError as exc:
        raise SystemExit(f"error: {exc.args[0]}") from exc


# -- make-demos -----------------------------------------------------------------------------------------------

ROBOSUITE_EXPERT_TASKS = ("Lift", "Can")   # jepa_envs.tasks.robosuite_expert.EXPERTS (imported only when used)
EXPERT_TASKS = ("PushT", "PushTStandard", *ROBOSUITE_EXPERT_TASKS)


def _make_demos_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("task", help="task name: PushT, PushTStandard (gym-pusht's task), Lift or Can (robomimic's, on "
                                "robosuite)")
    p.add_argument("--episodes", type=int, required=True, help="number of successful demonstrations")
    p.add_argument("--out", required=True, help="output HDF5 file (robomimic layout)")
    p.add_argument("--seed", type=int, default=0, help="first episode seed (episodes use seed, seed+1, ...)")
    p.add_argument("--image-size", type=int, default=None, help="camera image size (default: the task's)")
    p.add_argument("--difficulty", default=None,
                   help="PushT difficulty preset: easy (default), medium, hard, full (not for PushTStandard)")
    p.add_argument("--finish-threshold", type=float, default=None,
                   help="PushT only: coverage at which each demonstration ends, between the task's success threshold "
                        "and 1 (default: the threshold itself; jepa-demo uses 0.9 on easy: demos that finish with a "
                        "margin teach a policy to clear the threshold, see docs/training.md)")
    p.add_argument("--no-images", action="store_true",
                   help="Lift and Can only: render no camera (about ten times faster) and write states, actions and "
                        "low-dim observations; `jepa-envs render-dataset` renders the frames later")
    p.add_argument("--no-reflections", action="store_true",
                   help="Lift and Can only: draw the table without its reflection (software rendering 4.5x faster; "
                        "recorded in the file, so evaluation and render-dataset draw the same frames)")
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                   help="processes that record episodes (default: one per core; the file is the same for any number)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr (for logs)")


@subcommand("make-demos", "write scripted-expert demonstrations to HDF5 (PushT, PushTStandard, Lift, Can)",
            _make_demos_args)
def make_demos(args: argparse.Namespace) -> int:
    spec = _spec_or_exit(args.task)
    if spec.name not in EXPERT_TASKS:
        raise SystemExit(
            f"error: no scripted expert exists for {spec.name} ({spec.suite}); there are experts for "
            f"{', '.join(EXPERT_TASKS)}. Bring your own "
            f"data: download the public {spec.suite} demonstrations (or record your own) as HDF5 in the "
            "robomimic layout data/demo_N/{obs/<camera>_image, obs/<low-dim keys>, actions, states} with "
            "data.attrs['env_args']; convert delta actions with `jepa-envs convert-abs-actions IN OUT`; then "
            f"`jepa-policy train --task {spec.name} --dataset OUT` (docs/envs_simulation.md)")
    if args.episodes < 1:
        raise SystemExit(f"error: --episodes must be >= 1, got {args.episodes}")
    if args.workers < 1:
        raise SystemExit(f"error: --workers must be >= 1, got {args.workers}")
    robosuite = spec.name in ROBOSUITE_EXPERT_TASKS
    if robosuite and (args.difficulty is not None or args.finish_threshold is not None):
        raise SystemExit(f"error: --difficulty and --finish-threshold are PushT's options; {spec.name}'s expert "
                         "ends each demonstration when the task's own success check has held for a few steps")
    if args.no_reflections and not robosuite:
        raise SystemExit(f"error: --no-reflections is for the robosuite tasks ({', '.join(ROBOSUITE_EXPERT_TASKS)}); "
                         f"{spec.name} draws no reflection")
    if args.no_images and not robosuite:
        raise SystemExit(f"error: --no-images is for the robosuite tasks ({', '.join(ROBOSUITE_EXPERT_TASKS)}); "
                         f"{spec.name} renders its frames in about a millisecond")
    from jepa_envs.datasets.hdf5 import write_dataset

    t0 = time.perf_counter()
    try:
        if robosuite:
            from jepa_envs.tasks.robosuite_expert import generate_demos as generate_robosuite_demos

            episodes, env_args = generate_robosuite_demos(spec.name, args.episodes, seed=args.seed,
                                                          image_size=args.image_size, images=not args.no_images,
                                                          workers=args.workers, progress=not args.no_progress,
                                                          reflections=not args.no_reflections)
        else:
            from jepa_envs.tasks.pusht_expert import generate_demos

            options = {} if args.difficulty is None else {"difficulty": args.difficulty}
            episodes, env_args = generate_demos(args.episodes, seed=args.seed, image_size=args.image_size,
                                                task=spec.name, workers=args.workers, progress=not args.no_progress,
                                                finish_threshold=args.finish_threshold, **options)
    except (ValueError, TypeError) as exc:  # an option out of range or not of this task: say which and stop
        raise SystemExit(f"error: {exc}") from None
    seconds = time.perf_counter() - t0
    write_dataset(args.out, episodes, env_args)
    lengths = [len(ep["actions"]) for ep in episodes]
    attempts = env_args["expert"]["attempts"]
    print(f"wrote {len(episodes)} demos ({sum(lengths)} steps, expert success {len(episodes)}/{attempts}) to "
          f"{args.out} in {time.perf_counter() - t0:.1f} s")
    if robosuite:
        print(f"episode length mean {sum(lengths) / len(lengths):.1f}, median {statistics.median(lengths):.1f} steps; "
              f"{attempts} attempts recorded in {seconds:.1f} s with {args.workers} worker(s): "
              f"{seconds / attempts:.2f} s per attempt, {60 * attempts / seconds:.1f} attempts/min")
    return 0


# -- list / info ----------------------------------------------------------------------------------------------

@subcommand("list", "tasks and whether their backend can be imported here")
def list_tasks(args: argparse.Namespace) -> int:
    print(f"{'task':<20}{'gym id':<30}{'suite':<11}backend")
    for spec in all_task_specs():
        ok, why = backend_available(spec.suite)
        print(f"{spec.name:<20}{spec.env_id:<30}{spec.suite:<11}{'available' if ok else 'unavailable: ' + why}")
    return 0


def _info_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("task", help="task name or gym id")


@subcommand("info", "the task spec of one task as JSON", _info_args)
def info(args: argparse.Namespace) -> int:
    spec = _spec_or_exit(args.task)
    data = asdict(spec)
    data["backend_available"] = backend_available(spec.suite)[0]
    print(json.dumps(data, indent=2))
    return 0


# -- bench ----------------------------------------------------------------------------------------------------

def _bench_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--tasks", nargs="+", default=None, help="tasks to measure (default: every buildable task)")
    p.add_argument("--steps", type=int, default=1000, help="most env steps per arm of each comparison")
    p.add_argument("--seconds", type=float, default=3.0, help="time budget of each comparison")
    p.add_argument("--renderers", action="store_true",
                   help="instead: ms per 84 px frame of every OpenGL backend (osmesa, EGL) and Mesa thread count, "
                        "whether its frames are identical, and the one in use")
    p.add_argument("--frames", type=int, default=20, help="frames per backend (--renderers)")
    p.add_argument("--gym-pusht", metavar="PYTHON",
                   help="instead: our PushTStandard's steps/s beside gym-pusht's own env, run by this interpreter "
                        "(a venv with gym-pusht 0.1.8; `make interop` builds .cache/interop/gym_pusht)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr (for logs)")


@subcommand("bench", "steps/s raw backend vs our interface, and render-every-step vs render-on-demand", _bench_args)
def bench(args: argparse.Namespace) -> int:
    if args.renderers:
        from jepa_envs.tasks.render import bench_renderers

        bench_renderers(frames=args.frames, progress=not args.no_progress)
        return 0
    if args.gym_pusht:
        from jepa_envs.bench import run_bench_gym_pusht

        run_bench_gym_pusht(args.gym_pusht, args.steps, args.seconds if args.seconds != 3.0 else 10.0,
                            progress=not args.no_progress)
        return 0
    from jepa_envs.bench import run_bench

    run_bench(args.tasks, args.steps, args.seconds, progress=not args.no_progress)
    return 0


@subcommand("install-mimicgen", "install MimicGen (and robosuite-task-zoo) from local clones, editable, with the "
                                "imports its env classes need, and prove the four D1 tasks import",
            install_mimicgen.add_arguments)
def install_mimicgen_cmd(args: argparse.Namespace) -> int:
    return install_mimicgen.main(args)


def _convert_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("input", help="robomimic / MimicGen HDF5 file with delta actions and states")
    p.add_argument("output", help="where to write the copy with absolute actions")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr (for logs)")


@subcommand("convert-abs-actions", "delta -> absolute actions (position, 6-D rotation, gripper) by state replay",
            _convert_args)
def convert_abs_actions(args: argparse.Namespace) -> int:
    # the converter replays states in robosuite: imported only when this subcommand runs
    from jepa_envs.datasets.convert_abs_actions import convert_abs_actions as convert

    try:
        out = convert(args.input, args.output, progress=not args.no_progress)
    except (FileNotFoundError, KeyError, ValueError) as e:
        raise SystemExit(f"error: {e}") from None
    print(f"wrote {out} (actions: absolute position + 6-D rotation + gripper; originals in actions_delta)")
    return 0


# -- LeRobotDataset v3.0 -------------------------------------------------------------------------------------

def _lerobot_args(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="action", required=True)
    e = sub.add_parser("export", help="a demos (or rollouts) HDF5 file -> a LeRobotDataset v3.0 folder")
    e.add_argument("src", help="robomimic-layout HDF5 (jepa-envs make-demos, jepa-envs lerobot import ...)")
    e.add_argument("out", help="new folder for the dataset (must not exist or be empty)")
    e.add_argument("--task", help="task name (default: the file's env_name)")
    e.add_argument("--fps", type=int, help="frame rate (default: the rate the file was recorded at, else the task's "
                                           "control rate; another rate than the recorded one is refused)")
    e.add_argument("--codec", default="lossless", choices=("lossless", "av1", "h264"),
                   help="video codec: lossless H.264 RGB (default; bit-identical frames), av1 (LeRobot's "
                        "default, lossy), h264 (yuv420p, lossy)")
    e.add_argument("--instruction", help="task string of every episode without its own (default: from the task)")
    e.add_argument("--encoder-timeout", type=float, default=60.0, metavar="S",
                   help="seconds a video encoder may go without taking a frame or handing back a packet before "
                        "the export stops as stalled, naming the episode (default 60)")
    i = sub.add_parser("import", help="a LeRobotDataset v3.0 folder -> an HDF5 file the loader and trainer read")
    i.add_argument("src", help="the dataset's root folder (the one holding meta/info.json)")
    i.add_argument("out", help="HDF5 file to write")
    i.add_argument("--task", help="our task the data is for (its spec names the keys; default: the task the dataset "
                                  "names, as our exports do in robot_type jepa/<task>)")
    i.add_argument("--map", action="append", default=[], metavar="LEROBOT_KEY=SPEC_KEY",
                   help="feature -> spec key, e.g. observation.images.front=agentview_image, "
                        "observation.state=robot0_eef_pos,robot0_eef_quat,robot0_gripper_qpos (repeat)")
    i.add_argument("--fps", type=int, help="accept a dataset recorded at this rate when it differs from the task's "
                                           "(it must be the dataset's own rate; its timestamps are checked)")
    i.add_argument("--overwrite", action="store_true", help="replace OUT when it exists (refused otherwise)")
    b = sub.add_parser("bench", help="export and import frames/s and peak memory beside an h5py read of the same "
                                     "frames, each phase in a fresh process")
    b.add_argument("src", help="a demos HDF5 file (e.g. the main job's demo_out/default/data/*.hdf5)")
    b.add_argument("--codec", default="lossless", choices=("lossless", "av1", "h264"))
    for command in (e, i, b):
        command.add_argument("--no-progress", action="store_true", help="no progress bar on stderr (for logs)")


@subcommand("lerobot", "LeRobotDataset v3.0: export our demos, import a LeRobot dataset", _lerobot_args)
def lerobot(args: argparse.Namespace) -> int:
    from jepa_envs.datasets import lerobot as lr

    if args.action == "bench":
        result = lr.bench_lerobot(args.src, args.codec, progress=not args.no_progress)
        print(f"LeRobot v3.0 export/import of {result['src']} ({result['codec']}), load {result['load_average']:.2f}; "
              f"HDF5 {result['hdf5_mib']:.1f} MiB, LeRobot folder {result['dataset_mib']:.1f} MiB")
        for name, row in result["phases"].items():
            print(f"  {name:<10} {row['frames']:>7} frames {row['seconds']:>7.1f} s "
                  f"{row['frames_per_s']:>8.0f} frames/s peak RSS {row['peak_rss_mib']:>6.0f} MiB")
        return 0
    t0 = time.perf_counter()
    if args.action == "export":
        summary = lr.export_lerobot(args.src, args.out, task=args.task, fps=args.fps, codec=args.codec,
                                    instruction=args.instruction, encoder_timeout_s=args.encoder_timeout,
                                    progress=not args.no_progress)
    else:
        summary = lr.import_lerobot(args.src, args.out, args.task, args.map, fps=args.fps, overwrite=args.overwrite,
                                    progress=not args.no_progress)
        for key, what in summary["unmapped"].items():
            print(f"jepa-envs lerobot import: note: feature {key!r} ({what}) was not imported: no key of task "
                  f"{summary['task']} takes it; to bring it in as one of the task's keys, pass "
                  f"--map {key}=SPEC_KEY (jepa-envs info {summary['task']} lists them)", file=sys.stderr)
    seconds = time.perf_counter() - t0
    print(json.dumps({**summary, "seconds": round(seconds, 2),
                      "frames_per_s": round(summary["frames"] / max(seconds, 1e-9), 1)}))
    return 0


# -- raw states -> images ----------------------------------------------------------------------------------------

def _render_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("src", help="raw HDF5: states and actions only (robomimic/MimicGen env_args or robosuite's "
                               "own demonstration format)")
    p.add_argument("out", help="HDF5 file with image observations the loader reads")
    p.add_argument("--task", help="our task (default: from the file's env name)")
    p.add_argument("--cameras", nargs="+", default=(), help="cameras to render (default: the task's)")
    p.add_argument("--size", type=int, help="image size (default: the task's, 84)")
    p.add_argument("--reflections", choices=("on", "off"), default=None,
                   help="draw the table's reflection (robomimic's frames) or not (4.5x faster; recorded in the "
                        "output); default: the source's own setting, else on")
    p.add_argument("--replay", action="store_true",
                   help="then replay the written actions open-loop in the task's gym env from each recorded start")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr (for logs)")


@subcommand("render-dataset", "render a raw dataset's recorded states into image observations (robomimic's "
                              "dataset_states_to_obs), with each episode's replay drift", _render_args)
def render_dataset_cmd(args: argparse.Namespace) -> int:
    from jepa_envs.datasets.render_dataset import render_dataset, replay_in_env

    t0 = time.perf_counter()
    report = render_dataset(args.src, args.out, task=args.task, cameras=tuple(args.cameras), size=args.size,
                            progress=not args.no_progress,
                            reflections=None if args.reflections is None else args.reflections == "on")
    report["seconds"] = round(time.perf_counter() - t0, 1)
    if args.replay:
        report["replay_in_env"] = replay_in_env(args.out, report["task"])
    print(json.dumps(report))
    return 0


def _version() -> str:
    """This install's version, for --version."""
    try:
        return version("jepa-policy-toolkit")
    except PackageNotFoundError:
        return "unknown (not installed: pip install -e . in the checkout)"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="jepa-envs", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)
    for cmd in SUBCOMMANDS.values():
        p = sub.add_parser(cmd.name, help=cmd.help)
        cmd.add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return SUBCOMMANDS[args.command].run(args)
    except USER_ERRORS as exc:
        return user_error(f"jepa-envs {args.command}", exc)


if __name__ == "__main__":
    sys.exit(main())
