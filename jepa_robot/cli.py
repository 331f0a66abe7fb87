"""``jepa-robot-bridge``: serve a robot (default subcommand), check a set-up, dry-run, watch, benchmark.

    jepa-robot-bridge --backend sim --task PushT                 # simulated robot on tcp://127.0.0.1:5555
    jepa-robot-bridge --backend arx5 --config deploy/robot/arx5_cabinet.toml
    jepa-robot-bridge supervise --state-file STATE.json --backend arx5 --config ...   # restarts latched after a crash
    jepa-robot-bridge check deploy/robot/arx5_cabinet.toml      # every length and bound, no hardware touched
    jepa-robot-bridge --backend replay --episode EP.json [--config SETUP.toml]   # dry run of a recording
    jepa-robot-bridge --backend arx5 --config ... --observe-only   # cameras and proprioception, no motion
    jepa-robot-bridge observe --address tcp://robot-pc:5555       # watch what an observe-only bridge serves
    jepa-robot-bridge keys DIR --client policy-pc                  # CurveZMQ keys for a network link
    jepa-robot-bridge bench                                      # loopback latency, three 128x128 cameras
    jepa-robot-bridge bench --load flood,operators,big,aborts    # e-stop latency and aborts under local load
    jepa-robot-bridge estop | clear-estop | home | status | shutdown [--operator tcp://host:5556]
    jepa-robot-bridge confirm success|failure [--operator ...]

The console script answers the operator commands without importing this module (``jepa_robot.operator_cli``); they
also work here. The policy side runs elsewhere: ``jepa-policy robot --address tcp://robot-pc:5555
--checkpoint ckpt.pt``.

One module of about 650 lines on purpose: each command's run sits beside its flags, and every import of the
work is inside the command that does it, so ``--help`` and the operator commands load none of the bridge.
"""
from __future__ import annotations

import argparse
from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as installed_version
import logging
import math
import sys
import time
import tomllib
from pathlib import Path

from jepa_robot.guard import DEFAULT_MAX_RSS_MB, FD_FRACTION, descriptor_limit
from jepa_robot.operator import DEFAULT_OPERATOR
from jepa_robot.operator_cli import OPERATOR_COMMANDS, run_operator_command

SUBCOMMANDS = ("serve", "supervise", "bench", "check", "observe", "keys") + OPERATOR_COMMANDS


def _package_version() -> str:
    """This install's version, for --version."""
    try:
        return installed_version("jepa-policy-toolkit")
    except PackageNotFoundError:
        return "unknown (not installed: pip install -e . in the checkout)"


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="jepa-robot-bridge", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"%(prog)s {_package_version()}")
    sub = parser.add_subparsers(dest="command")
    serve = sub.add_parser("serve", help="run the robot bridge (default)")
    serve.add_argument("--backend", choices=("sim", "arx5", "replay"), default="sim")
    serve.add_argument("--task", help="sim: any jepa_envs simulation task (PushT, Square, ...)")
    serve.add_argument("--config", help="arx5: set-up TOML (deploy/robot/arx5_cabinet.toml); sim: optional "
                                        "TOML with a [safety] table; replay: the set-up whose limits apply")
    serve.add_argument("--episode", help="replay: the episode manifest (.json) a bridge recorded")
    serve.add_argument("--bind", help="control socket (default tcp://127.0.0.1:5555, arx5: from config)")
    serve.add_argument("--operator-bind", help=f"operator socket (default $JEPA_ROBOT_OPERATOR, else "
                                               f"{DEFAULT_OPERATOR}; arx5: from config)")
    serve.add_argument("--image-size", type=int)
    serve.add_argument("--record-dir", help="write per-episode HDF5 + JSON manifests here")
    serve.add_argument("--chunk-budget", type=int, help="override the task's action-chunk budget")
    serve.add_argument("--realtime", action="store_true", help="sim, replay: pace actions at the task's control rate")
    serve.add_argument("--success-source", choices=("sim", "operator"), default="sim",
                       help="sim: take success from the simulator or rehearse operator confirmation")
    serve.add_argument("--camera-replicas", type=int, default=1,
                       help="sim: repeat each camera N times on the wire (payload benchmarks)")
    serve.add_argument("--on-violation", choices=("refuse", "clip"), help="override safety.on_violation")
    serve.add_argument("--observe-only", action="store_true",
                       help="serve cameras and proprioception; refuse every action, reset and homing")
    serve.add_argument("--curve-keys", help="CurveZMQ on the control socket: the folder `keys` wrote")
    serve.add_argument("--insecure-network", action="store_true",
                       help="allow a control socket reachable from the network without CurveZMQ (only on a "
                            "dedicated, isolated robot-policy link)")
    serve.add_argument("--no-prompt", action="store_true", help="never prompt on stdin for confirmation")
    serve.add_argument("--operator-secret", metavar="FILE",
                       help="the operator credential file the bridge creates (mode 600) or reuses (default "
                            "$JEPA_ROBOT_OPERATOR_SECRET, else ~/.config/jepa-robot/operator.secret); clear-estop, "
                            "home, confirm and shutdown need it")
    serve.add_argument("--start-latched", metavar="REASON", help=argparse.SUPPRESS)   # the supervisor's restarts
    serve.add_argument("--state-file", help="keep the e-stop latch here across restarts: a bridge started after "
                                            "a crash (or with the e-stop still latched) starts latched")
    serve.add_argument("--rt-priority", type=int, default=None,
                       help="run the e-stop path (the operator thread and the bridge's ZeroMQ I/O threads) at this "
                            "SCHED_FIFO priority (1-99; needs CAP_SYS_NICE, which the systemd unit grants): the e-stop's bound "
                            "under CPU overload (docs/real_robot.md, 'E-stop and load')")
    serve.add_argument("--max-rss-mb", type=float, default=DEFAULT_MAX_RSS_MB,
                       help="the memory guard: latch the e-stop when the bridge's resident memory passes this many MiB "
                            f"(default {DEFAULT_MAX_RSS_MB:g}; 0: no guard); the systemd unit's MemoryMax is above it "
                            "(docs/real_robot.md, 'Connections and memory')")
    serve.add_argument("-v", "--verbose", action="store_true")

    supervise = sub.add_parser("supervise", help="run `serve` and restart it with the e-stop latched after a crash; "
                                                 "every argument it does not know goes to serve")
    supervise.add_argument("--state-file", required=True,
                           help="where the bridge keeps its e-stop latch and whether it stopped cleanly")
    supervise.add_argument("--restart-delay", type=float, default=1.0,
                           help="seconds before the first restart (doubling, up to 30 s, while it keeps crashing)")

    check = sub.add_parser("check", help="validate a set-up file without touching any hardware")
    check.add_argument("config", help="ARX-5 set-up TOML, or a TOML with a [safety] table for --task")
    check.add_argument("--task", help="a simulation task to check a [safety] table against (builds the sim)")
    check.add_argument("--insecure-network", action="store_true",
                       help="accept a network-reachable control socket without CurveZMQ (as serve would)")
    check.add_argument("--bind", help="--task: the control socket serve would bind (default tcp://127.0.0.1:5555)")
    check.add_argument("--operator-bind", help="--task: the operator socket serve would bind (default "
                                               f"{DEFAULT_OPERATOR})")
    check.add_argument("--curve-keys", help="--task: the CurveZMQ folder serve would use (`keys` wrote it)")

    observe = sub.add_parser("observe", help="watch the observations a bridge serves (observe-only or not)")
    observe.add_argument("--address", default="tcp://127.0.0.1:5555")
    observe.add_argument("--seconds", type=float, default=5.0)
    observe.add_argument("--save", help="write the newest frame of every camera here as PNG")
    observe.add_argument("--timeout", type=float, default=10.0, help="seconds to wait for the bridge")

    keys = sub.add_parser("keys", help="CurveZMQ keys: the bridge's pair (robot computer), a client's pair "
                                       "(policy computer), or authorise a client's public key")
    keys.add_argument("folder", help="the bridge's key folder (robot computer), or with --client-only the "
                                     "folder for the client's pair (policy computer)")
    keys.add_argument("--client", action="append", default=[],
                      help="client name (repeat): its pair is written to --client-dir, its public key authorised")
    keys.add_argument("--client-dir", help="where the clients' pairs go (a folder you move to the policy computer; "
                                           "it must not be inside the bridge's folder)")
    keys.add_argument("--client-only", action="store_true",
                      help="policy computer: write only a client pair (named by --client) into FOLDER")
    keys.add_argument("--authorize", metavar="PUBLIC_KEY", action="append", default=[],
                      help="robot computer: add a client's public key file (<name>.key) to FOLDER/authorized_clients")

    bench = sub.add_parser("bench", help="round-trip latency over loopback vs the sim env in-process")
    bench.add_argument("--task", default="PushT")
    bench.add_argument("--image-size", type=int, default=128)
    bench.add_argument("--cameras", type=int, default=3, help="camera streams on the wire (replicas)")
    bench.add_argument("--steps", type=int, default=300)
    bench.add_argument("--chunks", type=int, default=40)
    bench.add_argument("--max-seconds", type=float, default=120.0)
    bench.add_argument("--estop-runs", type=int, default=10, help="time the e-stop command this many times")
    bench.add_argument("--out", metavar="FILE", help="also write the numbers to this file (JSON)")
    bench.add_argument("--no-progress", action="store_true", help="no progress bar on stderr (for logs)")
    bench.add_argument("--load", metavar="SCENARIOS",
                       help="instead: the bridge under local load, comma-separated from flood, operators, "
                            "operators+flood, big, flood-elsewhere, many-strangers, operator-flood, aborts (e-stop "
                            "latency, controller chunk rate, bridge aborts)")
    bench.add_argument("--trials", type=int, default=20, help="--load: e-stops per scenario")
    bench.add_argument("--window", type=float, default=4.0,
                       help="--load: seconds the controller's chunk rate is counted alone, then under the load")
    bench.add_argument("--abort-runs", type=int, default=30, help="--load aborts: fresh bridges flooded")
    bench.add_argument("--nice", type=int, default=0,
                       help="--load: the bridges' niceness (the systemd unit's -10 needs root; default 0)")
    bench.add_argument("--check-ms", type=float, default=0.0,
                       help="--load held: the safety check slowed by this many milliseconds")
    bench.add_argument("--process-fifo", type=int, default=None,
                       help="--load: every thread of the bridges at this SCHED_FIFO priority (chrt), for comparison")
    bench.add_argument("--rt-priority", type=int, default=None,
                       help="--load: the bridges' e-stop path at this SCHED_FIFO priority (serve --rt-priority)")
    bench.add_argument("--realtime", action="store_true",
                       help="--load: the bridge paces actions at the task's rate, as on the robot (default: as "
                            "fast as the simulator runs, the CPU-bound worst case)")
    bench.add_argument("--flood-seconds", type=float, default=3.0, help="--load aborts: seconds of flood per run")
    return parser


MAX_SETUP_BYTES = 1024 * 1024   # a set-up file is a few KiB; a bigger one is refused before it is parsed


def _read_toml(path: str | None) -> dict:
    """The TOML file at ``path`` ({} for none); SystemExit with one line for anything that is not a readable,
    reasonably sized TOML text (the bridge's ``serve`` exits 2 with it, ``check`` prints it)."""
    if not path:
        return {}
    file = Path(path)
    shown = path if len(path) <= 200 else path[:200] + "..."
    try:
        if not file.is_file():
            raise SystemExit(f"config file {shown} not found")
        if file.stat().st_size > MAX_SETUP_BYTES:
            raise SystemExit(f"config file {shown} has {file.stat().st_size} bytes; a set-up file is a few KiB (at "
                             f"most {MAX_SETUP_BYTES // 1024} KiB are read)")
        with file.open("rb") as f:
            return tomllib.load(f)
    except OSError as exc:   # a name too long, a folder we may not read ...
        raise SystemExit(f"cannot read config file {shown}: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise SystemExit(f"{shown} is not a UTF-8 text file (byte {exc.start}): a set-up file is TOML text") from None
    except tomllib.TOMLDecodeError as exc:
        raise SystemExit(f"{shown} is not valid TOML: {exc}") from None
    except RecursionError:
        raise SystemExit(f"{shown} nests arrays or tables too deeply to be a set-up file (TOML that deep cannot be "
                         "read); write each limit as a flat list of numbers") from None
    except ValueError as exc:   # tomllib's own int(): an integer of more than 4,300 digits
        raise SystemExit(f"{shown} holds a value TOML cannot be read as ({str(exc)[:120]}); write each limit as a "
                         "number of a few digits") from None


def _unknown_tables(raw: dict) -> list[str]:
    """A sim or replay config holds a [safety] table and nothing else: a misspelt one ([saftey], [Safety]) would
    otherwise leave every rule at its default without a word."""
    unknown = sorted(k for k in raw if k != "safety")
    if not unknown:
        return [] if isinstance(raw.get("safety", {}), dict) else ["safety must be a [safety] table, not a value"]
    return [f"unknown top-level table or key {', '.join(repr(k[:40]) for k in unknown)}: a sim or replay config "
            "holds only a [safety] table (an ARX-5 set-up has [[arms]], [[cameras]] and [safety]); check the spelling"]


def _safety_from_toml(path: str | None):
    """The [safety] table of a TOML file (defaults without one); SetupRefused with one line per bad field."""
    from pydantic import ValidationError

    from jepa_robot.safety import SafetyConfig, config_errors
    raw = _read_toml(path)
    problems = _unknown_tables(raw)
    if problems:
        raise SetupRefused("\n".join(problems))
    try:
        return SafetyConfig.model_validate(raw.get("safety", {}))
    except ValidationError as exc:
        raise SetupRefused("\n".join(config_errors(exc))) from None


def _prompt_operator(bridge):
    """Ask on stdin for the outcome of an episode whose chunk budget is spent; answer through the bridge."""
    import threading

    from jepa_robot import protocol as P

    def ask(summary: dict) -> None:
        def run() -> None:
            answer = ""
            while answer not in ("y", "n"):
                answer = input(f"\nEpisode {summary['episode_id']} ({summary['task']}, {summary['chunks']} chunks) "
                               "ended. Success? [y/n] ").strip().lower()[:1]
            bridge.command({"type": P.OP_CONFIRM, "success": answer == "y"})
        threading.Thread(target=run, name="operator-prompt", daemon=True).start()
    return ask


def _curve(folder: str | None) -> dict:
    if not folder:
        return {}
    root = Path(folder)
    secret, authorized = root / "bridge.key_secret", root / "authorized_clients"
    if not secret.is_file() or not authorized.is_dir():
        raise SystemExit(f"{folder} has no bridge.key_secret and authorized_clients/; make them with "
                         f"`jepa-robot-bridge keys {folder}`")
    return {"curve_secret_key": str(secret), "curve_authorized_dir": str(authorized)}


MAX_IMAGE_SIZE = 1024   # --image-size: a camera side in pixels (three 1024x1024 frames are ~9 MiB a step)
EXIT_REFUSED = 2   # serve refused its set-up before touching the robot (the supervisor does not restart it)
EXIT_PORT_BUSY = 3   # a port serve must bind is held by another process (the supervisor retries, latched)


class SetupRefused(Exception):
    """``serve`` cannot start with this set-up; each line of the message is one problem and its fix."""


class PortBusy(Exception):
    """A port ``serve`` must bind is held by another process: perhaps a bridge still stopping, perhaps a process
    squatting it to answer in the bridge's place."""


def serve(args) -> int:
    """Build the backend and the bridge, then serve until an operator shutdown, SIGINT or SIGTERM (exit 0). A
    refused set-up prints one line per problem and exits 2; a crash while serving exits otherwise, and the
    next start with the same ``--state-file`` is latched."""
    import signal

    import zmq
    from pydantic import ValidationError

    from jepa_robot.backends.base import BackendUnavailable
    from jepa_robot.safety import config_errors

    try:
        bridge, backend = _build_bridge(args)
    except PortBusy as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_PORT_BUSY
    except SetupRefused as exc:
        print("\n".join(f"error: {line}" for line in str(exc).splitlines()), file=sys.stderr)
        return EXIT_REFUSED
    except ValidationError as exc:
        print("\n".join(f"error: {line}" for line in config_errors(exc, prefix="")), file=sys.stderr)
        return EXIT_REFUSED
    except (BackendUnavailable, OSError, ValueError, zmq.ZMQError) as exc:
        print(f"error: {str(exc)[:500]}", file=sys.stderr)
        return EXIT_REFUSED
    if not args.no_prompt and backend.success_source == "operator" and sys.stdin.isatty():
        bridge.on_confirmation_needed = _prompt_operator(bridge)
    mode = " (observe-only: no motion)" if bridge.config.observe_only else ""
    if bridge.estop.latched:
        mode += f" (e-stop LATCHED: {bridge.estop.reason})"
    print(f"robot bridge v{_version()} serving {backend.task_spec.name} ({type(backend).__name__}) on "
          f"{bridge.control_endpoint}, operator socket {bridge.operator_endpoint}{mode}", flush=True)
    signal.signal(signal.SIGTERM, lambda *_: bridge.stop())   # systemctl stop: a clean stop, as SIGINT
    try:
        bridge.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        backend.close()
    return 0


def _build_bridge(args):
    """The backend and the bound bridge of ``serve``; SetupRefused (or a pydantic ValidationError) before any
    hardware moves."""
    import zmq

    from jepa_robot.bridge import BridgeConfig, RobotBridge
    from jepa_robot.endpoints import network_bind_problem, operator_bind_problem

    curve = _curve(args.curve_keys)
    if args.image_size is not None and not 1 <= args.image_size <= MAX_IMAGE_SIZE:
        raise SetupRefused(f"--image-size {args.image_size}: give a side in pixels from 1 to {MAX_IMAGE_SIZE} (the "
                           "tasks are trained at 84-256)")
    if not (math.isfinite(args.max_rss_mb) and args.max_rss_mb >= 0):
        raise SetupRefused(f"--max-rss-mb {args.max_rss_mb:g}: give the memory guard's bound in MiB, a finite "
                           "number >= 0 (0: no guard)")

    def config_for(control: str, operator: str, record_dir: str | None, curve: dict) -> BridgeConfig:
        config = BridgeConfig(control, operator, record_dir, args.chunk_budget, args.observe_only,
                              insecure_network=args.insecure_network, state_file=args.state_file,
                              rt_priority=args.rt_priority, start_latched=args.start_latched,
                              operator_secret_file=args.operator_secret,
                              max_rss_mb=args.max_rss_mb if args.max_rss_mb > 0 else None, **curve)
        # refused before any hardware is opened (the bridge checks again before it binds)
        problem = (network_bind_problem(config.control_address, config.curve_secret_key is not None,
                                        config.insecure_network)
                   or operator_bind_problem(config.operator_address, config.curve_secret_key is not None))
        if problem:
            raise SetupRefused(problem)
        return config

    if args.backend == "arx5":
        if not args.config:
            raise SetupRefused("--backend arx5 needs --config FILE (see deploy/robot/arx5_cabinet.toml)")
        from jepa_robot.backends.arx5 import ARX5Backend, load_arx5_config
        setup = load_arx5_config(args.config)
        safety = setup.safety
        curve = curve or ({"curve_secret_key": setup.curve_secret_key,
                           "curve_authorized_dir": setup.curve_authorized_dir} if setup.curve_secret_key else {})
        config = config_for(args.bind or setup.control_address, args.operator_bind or setup.operator_address,
                            args.record_dir or setup.record_dir, curve)
        backend = ARX5Backend(setup, image_size=args.image_size)
    elif args.backend == "replay":
        if not args.episode:
            raise SetupRefused("--backend replay needs --episode MANIFEST.json (an episode a bridge recorded)")
        from jepa_robot.backends.replay import ReplayBackend
        config = config_for(args.bind or "tcp://127.0.0.1:5555", args.operator_bind or _operator_default(),
                            args.record_dir, curve)
        bounds, joints, safety = None, None, _safety_from_toml(None)
        raw = _read_toml(args.config)
        if "arms" in raw:   # the real set-up: its workspace, joint count and safety rules apply to the dry run
            from jepa_robot.backends.arx5 import JOINTS_PER_ARM, arx5_action_bounds, load_arx5_config
            setup = load_arx5_config(args.config)
            bounds, joints, safety = arx5_action_bounds(setup), JOINTS_PER_ARM * len(setup.arms), setup.safety
        elif raw:
            safety = _safety_from_toml(args.config)
        backend = ReplayBackend(args.episode, bounds=bounds, joint_count=joints, realtime=args.realtime)
    else:
        if not args.task:
            raise SetupRefused("--backend sim needs --task NAME (e.g. PushT)")
        import jepa_envs  # noqa: F401  (registers the tasks)
        from jepa_robot.backends.sim import SimBackend
        config = config_for(args.bind or "tcp://127.0.0.1:5555", args.operator_bind or _operator_default(),
                            args.record_dir, curve)
        safety = _safety_from_toml(args.config)
        backend = SimBackend(_known_task(args.task), image_size=args.image_size, success_source=args.success_source,
                             realtime=args.realtime, camera_replicas=args.camera_replicas)
    if args.on_violation:
        safety = safety.model_copy(update={"on_violation": args.on_violation})
    try:
        bridge = RobotBridge(backend, safety, config)
        bridge.bind()
    except (ValueError, zmq.ZMQError) as exc:
        backend.close()
        if isinstance(exc, zmq.ZMQError) and exc.errno == zmq.EADDRINUSE:
            raise PortBusy(f"{str(exc)[:300]}: another process holds a port this bridge binds (a bridge still "
                           "stopping, or a process answering in its place: find it with ss -ltnp)") from None
        raise SetupRefused(str(exc)) from None
    return bridge, backend


def _known_task(name: str) -> str:
    """The task's name, or exit with the list of known tasks (no traceback)."""
    import jepa_envs  # noqa: F401  (registers the tasks)
    from jepa_envs.tasks.spec import get_task_spec
    try:
        return get_task_spec(name).name
    except KeyError as exc:
        raise SystemExit(f"error: {exc.args[0]}") from None


def _operator_default() -> str:
    """The operator socket a sim or replay bridge binds: the address the operator commands use by default."""
    import os

    from jepa_robot.operator_cli import OPERATOR_ENV
    return os.environ.get(OPERATOR_ENV) or DEFAULT_OPERATOR


def _version() -> int:
    from jepa_robot.protocol import PROTOCOL_VERSION
    return PROTOCOL_VERSION


def check(args) -> int:
    """Validate a set-up file: every list length and bound, timing rules, addresses, keys, record folder; no
    hardware."""
    from pydantic import ValidationError

    from jepa_robot.safety import SafetyConfig, config_errors

    raw = _read_toml(args.config)
    errors: list[str] = []
    notes: list[str] = []
    if "arms" in raw or "cameras" in raw:
        from jepa_robot.backends.arx5 import JOINTS_PER_ARM, ARX5Config
        from jepa_envs.tasks.spec import get_task_spec
        try:
            setup = ARX5Config.model_validate(raw)
        except ValidationError as exc:
            errors += config_errors(exc, prefix="")
        else:
            spec = get_task_spec(setup.task)
            notes.append(f"task {spec.name}: {spec.action_dim}-D actions, arms {list(spec.extra['arms'])}, "
                         f"{JOINTS_PER_ARM * len(setup.arms)} joints, cameras {list(spec.cameras)}")
            serials = [c.serial for c in setup.cameras]
            if len(set(serials)) != len(serials):
                errors.append(f"cameras: the same serial is listed twice ({serials})")
            errors += _address_problems(setup.control_address, setup.operator_address, setup.curve_secret_key,
                                        args.insecure_network, notes)
            errors += _record_dir_problems(setup.record_dir)
            notes += _rules_off(setup.safety, joints=True)
            for key in (setup.curve_secret_key, setup.curve_authorized_dir):
                if key is not None and not Path(key).exists():
                    errors.append(f"{key} does not exist; make the keys with `jepa-robot-bridge keys`")
    else:
        if not args.task:
            raise SystemExit("a file without [[arms]] is a [safety] table for a simulation task: add --task NAME")
        task = _known_task(args.task)
        safety, errors = None, _unknown_tables(raw)
        curve = _curve(args.curve_keys).get("curve_secret_key") if args.curve_keys else None
        errors += _address_problems(args.bind or "tcp://127.0.0.1:5555", args.operator_bind or _operator_default(),
                                    curve, args.insecure_network, notes)
        if not errors:
            try:
                safety = SafetyConfig.model_validate(raw.get("safety", {}))
            except ValidationError as exc:
                errors += config_errors(exc)
        if safety is not None:
            from jepa_robot.backends.sim import SimBackend
            backend = SimBackend(task)
            spec = backend.task_spec
            try:
                errors += safety.problems(spec.action_dim, backend.joint_count, spec.control_hz,
                                          action_range=(backend.action_low, backend.action_high))
                notes.append(f"task {spec.name}: {spec.action_dim}-D actions, {backend.joint_count or 'no'} joints")
                notes += _rules_off(safety, joints=backend.joint_count is not None)
            finally:
                backend.close()
    notes += _descriptor_notes()
    for note in notes:
        print(f"ok: {note}")
    for error in errors:
        print(f"error: {error}")
    print(f"{args.config}: " + ("OK, nothing touched" if not errors else f"{len(errors)} problem(s); fix them "
                                                                          "before starting the bridge"))
    return 0 if not errors else 1


def _descriptor_notes() -> list[str]:
    """The descriptor limit a bridge started from this shell would have, and where its connection guard trips."""
    limit = descriptor_limit()
    notes = [f"descriptors: a bridge started here may hold {limit} (RLIMIT_NOFILE); it latches its e-stop at "
             f"{int(FD_FRACTION * limit)} (the connection guard); the systemd unit sets LimitNOFILE=65536"]
    if limit < 4096:
        notes.append(f"WARNING the descriptor limit {limit} is low: about {int(FD_FRACTION * limit)} idle local "
                     "connections latch the e-stop; raise it (ulimit -n 65536, or the unit's LimitNOFILE)")
    return notes


def _rules_off(safety, joints: bool) -> list[str]:
    """The safety rules this set-up leaves off, said aloud (none is off without a line saying so)."""
    notes = []
    if safety.max_step_delta is None:
        notes.append("WARNING safety.max_step_delta is not set: no per-step jump limit")
    if joints and safety.joint_low is None and safety.joint_high is None:
        notes.append("WARNING safety.joint_low/joint_high are not set: joints are not checked")
    return notes


def _address_problems(control: str, operator: str, curve: str | None, insecure_network: bool,
                      notes: list[str]) -> list[str]:
    from jepa_robot.endpoints import is_loopback, network_bind_problem, operator_bind_problem

    problems = []
    for name, address in (("control_address", control), ("operator_address", operator)):
        if not address.startswith(("tcp://", "ipc://", "inproc://")) or (
                address.startswith("tcp://") and not address.rsplit(":", 1)[-1].replace("*", "1").isdigit()):
            problems.append(f"{name} {address!r} is not a ZeroMQ endpoint like tcp://127.0.0.1:5555")
    operator_problem = operator_bind_problem(operator, curve is not None)
    if operator_problem:
        problems.append(f"operator_address: {operator_problem}")
    bind_problem = network_bind_problem(control, curve is not None, insecure_network)
    if bind_problem:
        problems.append(f"control_address: {bind_problem}")
    elif not is_loopback(control) and curve is None:
        notes.append(f"WARNING control_address {control} is reachable from the network without encryption "
                     "(--insecure-network): the session token travels in clear")
    return problems


def _record_dir_problems(record_dir: str) -> list[str]:
    folder = Path(record_dir)
    parent = folder if folder.exists() else next((p for p in folder.parents if p.exists()), Path("."))
    import os
    if not os.access(parent, os.W_OK):
        return [f"record_dir {record_dir}: {parent} is not writable by this user"]
    return []


def observe(args) -> int:
    """Print what a bridge serves (rates, shapes, proprioception) for a while; save the newest frames."""
    import numpy as np

    from jepa_envs.real_robot.proxy import BridgeError, RealRobotEnv

    try:
        env = RealRobotEnv(address=args.address, client_name="observer", timeout_s=args.timeout)
    except (TimeoutError, BridgeError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    try:
        count, start = 0, time.monotonic()
        frames: list[dict] = []
        while time.monotonic() - start < args.seconds:
            frames, info = env.observe()
            count += 1
        elapsed = time.monotonic() - start
        obs = frames[-1]
        print(f"{env.task_spec.name}: {count} observations in {elapsed:.1f}s ({count / elapsed:.1f}/s)")
        for key, value in obs.items():
            summary = f"{value.dtype}{list(value.shape)}"
            if value.dtype != np.uint8:
                summary += " " + np.array2string(value, precision=4, suppress_small=True)
            print(f"  {key}: {summary}")
        if args.save:
            from PIL import Image
            Path(args.save).mkdir(parents=True, exist_ok=True)
            for key in env.task_spec.image_keys:
                Image.fromarray(obs[key]).save(Path(args.save) / f"{key}.png")
            print(f"frames written to {args.save}")
    finally:
        env.close()
    return 0


def keys(args) -> int:
    """CurveZMQ certificates. Robot computer: FOLDER/bridge.key(_secret) and FOLDER/authorized_clients/; each
    client's pair is written to --client-dir (to be moved to its policy computer), never into FOLDER, and only
    its public key is authorised. Policy computer: --client-only writes one client pair. --authorize adds a
    public key a policy computer made."""
    import shutil

    import zmq.auth

    root = Path(args.folder)
    if args.client_only:
        names = args.client or ["policy"]
        root.mkdir(parents=True, exist_ok=True)
        for name in names:
            _, secret = zmq.auth.create_certificates(root, name)
            Path(secret).chmod(0o600)
        print(f"client keys in {root}: keep {', '.join(n + '.key_secret' for n in names)} here; copy "
              f"{', '.join(n + '.key' for n in names)} to the robot computer and authorise it there "
              "(jepa-robot-bridge keys BRIDGE_FOLDER --authorize NAME.key)")
        return 0
    authorized = root / "authorized_clients"
    authorized.mkdir(parents=True, exist_ok=True)
    if not (root / "bridge.key_secret").exists():
        _, secret = zmq.auth.create_certificates(root, "bridge")
        Path(secret).chmod(0o600)
    for public in args.authorize:
        public = Path(public)
        try:
            key, secret = zmq.auth.load_certificate(public)
        except (OSError, ValueError) as exc:
            raise SystemExit(f"error: {public} is not a CurveZMQ public key file ({exc})") from None
        if secret is not None:
            raise SystemExit(f"error: {public} holds a secret key; authorise the client's public '.key' file")
        shutil.copy(public, authorized / public.name)
        print(f"authorised {public.name}; restart the bridge to let it in (the bridge reads the folder at start)")
    if args.client:
        if not args.client_dir:
            raise SystemExit("error: --client needs --client-dir OUT: the clients' secret keys go there, to be "
                             "moved to the policy computer, never into the bridge's folder")
        out = Path(args.client_dir)
        if out.resolve() == root.resolve() or root.resolve() in out.resolve().parents:
            raise SystemExit(f"error: --client-dir {out} is inside the bridge's folder {root}; pick a folder "
                             "outside it (the clients' secret keys must not stay on the robot computer)")
        out.mkdir(parents=True, exist_ok=True)
        for name in args.client:
            public, secret = zmq.auth.create_certificates(out, name)
            Path(secret).chmod(0o600)
            shutil.copy(public, authorized / Path(public).name)
    leftover = sorted(p.name for p in root.glob("*.key_secret") if p.name != "bridge.key_secret")
    print(f"bridge keys in {root}: the robot computer keeps bridge.key_secret and authorized_clients/ "
          f"({len(list(authorized.glob('*.key')))} client(s)); give each policy computer bridge.key"
          + (f"; move {args.client_dir} to the policy computer and delete it here "
             f"(jepa-policy robot --curve-server-key bridge.key --curve-client-key NAME.key_secret)"
             if args.client else ""))
    if leftover:
        print(f"WARNING {root} holds client secret keys {leftover}: move them to their policy computers and delete "
              "them here")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m jepa_robot.cli``; without a subcommand it serves."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in OPERATOR_COMMANDS:
        return run_operator_command(argv)
    if not argv or argv[0] not in SUBCOMMANDS + ("-h", "--help", "--version"):
        argv = ["serve", *argv]
    if argv[0] == "supervise":
        args, serve_args = _parser().parse_known_args(argv)
        from jepa_robot.supervisor import supervise
        return supervise(serve_args, args.state_file, args.restart_delay)
    args = _parser().parse_args(argv)
    if args.command == "serve":
        logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                            format="%(asctime)s %(levelname)s %(name)s: %(message)s")
        try:
            return serve(args)
        except SystemExit as exc:   # a refusal of the set-up helpers (unknown task, bad TOML ...)
            if not isinstance(exc.code, str):
                raise
            print(exc.code if exc.code.startswith("error") else f"error: {exc.code}", file=sys.stderr)
            return EXIT_REFUSED
    if args.command == "check":
        return check(args)
    if args.command == "observe":
        return observe(args)
    if args.command == "keys":
        return keys(args)
    if args.load:
        from jepa_robot.load_bench import run_load_bench
        return run_load_bench(args)
    from jepa_robot.bench import run_bench
    return run_bench(args)


if __name__ == "__main__":
    sys.exit(main())
