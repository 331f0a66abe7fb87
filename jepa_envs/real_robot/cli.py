"""``jepa-robot-bridge``: serve a robot (default subcommand), benchmark the bridge, and operator commands.

    jepa-robot-bridge --backend sim --task PushT                 # simulated robot on tcp://127.0.0.1:5555
    jepa-robot-bridge --backend arx5 --config deploy/robot/arx5_cabinet.toml
    jepa-robot-bridge bench                                      # loopback latency, three 128x128 cameras
    jepa-robot-bridge estop | clear-estop | home | status | shutdown [--operator tcp://host:5556]
    jepa-robot-bridge confirm success|failure [--operator ...]

The policy side runs elsewhere: ``jepa-policy robot --address tcp://robot-pc:5555 --checkpoint ckpt.pt``.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import threading
import tomllib
from pathlib import Path

from jepa_envs.real_robot.safety import SafetyConfig

SUBCOMMANDS = ("serve", "bench", "estop", "clear-estop", "confirm", "home", "status", "shutdown")
DEFAULT_OPERATOR = "tcp://127.0.0.1:5556"


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="jepa-robot-bridge", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command")
    serve = sub.add_parser("serve", help="run the robot bridge (default)")
    serve.add_argument("--backend", choices=("sim", "arx5"), default="sim")
    serve.add_argument("--task", help="sim: any jepa_envs simulation task (PushT, Square, ...)")
    serve.add_argument("--config", help="arx5: set-up TOML (deploy/robot/arx5_cabinet.toml); sim: optional "
                                        "TOML with a [safety] table")
    serve.add_argument("--bind", help="control socket (default tcp://127.0.0.1:5555, arx5: from config)")
    serve.add_argument("--operator-bind", help=f"operator socket (default {DEFAULT_OPERATOR})")
    serve.add_argument("--image-size", type=int)
    serve.add_argument("--record-dir", help="write per-episode HDF5 + JSON manifests here")
    serve.add_argument("--chunk-budget", type=int, help="override the task's action-chunk budget")
    serve.add_argument("--realtime", action="store_true", help="sim: pace actions at the task's control rate")
    serve.add_argument("--success-source", choices=("sim", "operator"), default="sim",
                       help="sim: take success from the simulator or rehearse operator confirmation")
    serve.add_argument("--camera-replicas", type=int, default=1,
                       help="sim: repeat each camera N times on the wire (payload benchmarks)")
    serve.add_argument("--on-violation", choices=("refuse", "clip"), help="override safety.on_violation")
    serve.add_argument("--no-prompt", action="store_true", help="never prompt on stdin for confirmation")
    serve.add_argument("-v", "--verbose", action="store_true")

    bench = sub.add_parser("bench", help="round-trip latency over loopback vs the sim env in-process")
    bench.add_argument("--task", default="PushT")
    bench.add_argument("--image-size", type=int, default=128)
    bench.add_argument("--cameras", type=int, default=3, help="camera streams on the wire (replicas)")
    bench.add_argument("--steps", type=int, default=300)
    bench.add_argument("--chunks", type=int, default=40)
    bench.add_argument("--max-seconds", type=float, default=120.0)
    bench.add_argument("--json", help="also write the numbers to this file")

    for name, text in (("estop", "latch the emergency stop (takes effect mid-chunk)"),
                       ("clear-estop", "release the emergency stop"), ("home", "drive the robot home"),
                       ("status", "print the bridge status"), ("shutdown", "stop the bridge")):
        cmd = sub.add_parser(name, help=text)
        cmd.add_argument("--operator", default=DEFAULT_OPERATOR)
    confirm = sub.add_parser("confirm", help="confirm the episode outcome")
    confirm.add_argument("outcome", choices=("success", "failure"))
    confirm.add_argument("--operator", default=DEFAULT_OPERATOR)
    return parser


def _safety_from_toml(path: str | None) -> SafetyConfig:
    if not path:
        return SafetyConfig()
    with Path(path).open("rb") as f:
        return SafetyConfig.model_validate(tomllib.load(f).get("safety", {}))


def _prompt_operator(operator_address: str):
    """Ask on stdin for the outcome of an episode whose chunk budget is spent; answer via the operator API."""
    from jepa_envs.real_robot.bridge import OperatorClient

    def ask(summary: dict) -> None:
        def run() -> None:
            answer = ""
            while answer not in ("y", "n"):
                answer = input(f"\nEpisode {summary['episode_id']} ({summary['task']}, {summary['chunks']} chunks) "
                               "ended. Success? [y/n] ").strip().lower()[:1]
            with OperatorClient(operator_address) as op:
                op.confirm(answer == "y")
        threading.Thread(target=run, name="operator-prompt", daemon=True).start()
    return ask


def serve(args) -> int:
    from jepa_envs.real_robot.bridge import BridgeConfig, RobotBridge

    if args.backend == "arx5":
        if not args.config:
            raise SystemExit("--backend arx5 needs --config FILE (see deploy/robot/arx5_cabinet.toml)")
        from jepa_envs.real_robot.backends.arx5 import ARX5Backend, load_arx5_config
        setup = load_arx5_config(args.config)
        safety = setup.safety
        backend = ARX5Backend(setup, image_size=args.image_size)
        config = BridgeConfig(args.bind or setup.control_address, args.operator_bind or setup.operator_address,
                              args.record_dir or setup.record_dir, args.chunk_budget)
    else:
        if not args.task:
            raise SystemExit("--backend sim needs --task NAME (e.g. PushT)")
        import jepa_envs  # noqa: F401  (registers the tasks)
        from jepa_envs.real_robot.backends.sim import SimBackend
        safety = _safety_from_toml(args.config)
        backend = SimBackend(args.task, image_size=args.image_size, success_source=args.success_source,
                             realtime=args.realtime, camera_replicas=args.camera_replicas)
        config = BridgeConfig(args.bind or "tcp://127.0.0.1:5555", args.operator_bind or DEFAULT_OPERATOR,
                              args.record_dir, args.chunk_budget)
    if args.on_violation:
        safety = safety.model_copy(update={"on_violation": args.on_violation})
    prompt = None
    if not args.no_prompt and backend.success_source == "operator" and sys.stdin.isatty():
        prompt = _prompt_operator(config.operator_address.replace("0.0.0.0", "127.0.0.1"))
    bridge = RobotBridge(backend, safety, config, on_confirmation_needed=prompt)
    bridge.bind()
    print(f"robot bridge v{_version()} serving {backend.task_spec.name} ({type(backend).__name__}) on "
          f"{bridge.control_endpoint}, operator socket {bridge.operator_endpoint}", flush=True)
    try:
        bridge.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        backend.close()
    return 0


def _version() -> int:
    from jepa_envs.real_robot.protocol import PROTOCOL_VERSION
    return PROTOCOL_VERSION


def operator(args) -> int:
    from jepa_envs.real_robot.bridge import OperatorClient

    with OperatorClient(args.operator) as op:
        try:
            result = _operator_call(op, args)
        except (RuntimeError, TimeoutError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 1
    print(json.dumps(result, indent=2, default=str))
    return 0


def _operator_call(op, args) -> dict:
    if args.command == "shutdown":
        op.shutdown()
        return {"shutdown": True}
    calls = {"estop": op.estop, "clear-estop": op.clear_estop, "home": op.home, "status": op.status,
             "confirm": lambda: op.confirm(args.outcome == "success")}
    return calls[args.command]()


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``jepa-robot-bridge``; without a subcommand it serves."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in SUBCOMMANDS + ("-h", "--help"):
        argv = ["serve", *argv]
    args = _parser().parse_args(argv)
    if args.command == "serve":
        logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                            format="%(asctime)s %(levelname)s %(name)s: %(message)s")
        from jepa_envs.real_robot.backends.base import BackendUnavailable
        try:
            return serve(args)
        except BackendUnavailable as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    if args.command == "bench":
        from jepa_envs.real_robot.bench import run_bench
        return run_bench(args)
    return operator(args)


if __name__ == "__main__":
    sys.exit(main())
