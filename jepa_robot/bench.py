"""``jepa-robot-bridge bench``: what the bridge costs over loopback compared with the sim env in-process.

A bridge serving a simulation task runs in a child process (two processes, as on the robot); the proxy env
times ``step`` (one action) and ``step_chunk`` (8 actions) round trips. The same backend is timed in-process
for the reference. Images: ``--cameras`` streams of ``--image-size`` pixels (default three 128x128, the real
robot's payload, Sec. 4.8). Run time is bounded by ``--max-seconds``.

It also times the operator's e-stop command from process start to exit, side by side: the console script's
import-light path (``jepa_robot.operator_cli``) and the full command line (``jepa_robot.cli``, which imports
numpy, gymnasium and the safety models), ``--estop-runs`` times each, interleaved, against the bench bridge.
"""
from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np
from tqdm import tqdm

import jepa_envs  # noqa: F401  (registers the simulation tasks the sim backend builds)
from jepa_robot.backends.sim import SimBackend
from jepa_robot.operator import OperatorClient
from jepa_envs.real_robot.proxy import RealRobotEnv


def percentiles_ms(samples_s: list[float]) -> dict:
    """p50 / p99 / mean in milliseconds."""
    x = np.asarray(samples_s, np.float64) * 1e3
    return {"n": int(x.size), "p50_ms": float(np.percentile(x, 50)), "p99_ms": float(np.percentile(x, 99)),
            "mean_ms": float(x.mean())}


def bench_actions(backend, count: int) -> np.ndarray:
    """A smooth in-bounds absolute action path (identity rotation for arm tasks) so no safety rule fires."""
    low, high = backend.action_low, backend.action_high
    t = np.arange(count)[:, None]
    actions = low + (high - low) * (0.5 + 0.2 * np.sin(t / 15.0 + np.arange(low.size)))
    for start in backend.rotation6d_starts:
        actions[:, start:start + 6] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0]
    return actions


def _time_in_process(backend, actions: np.ndarray, steps: int, chunks: int, n: int, deadline: float,
                     tick=lambda: None):
    step_s, chunk_s = [], []
    backend.reset(seed=0)
    for i in range(steps):
        if time.monotonic() > deadline:
            break
        t0 = time.perf_counter()
        result = backend.apply(actions[i % len(actions)])
        step_s.append(time.perf_counter() - t0)
        tick()
        if result.terminated or result.truncated:
            backend.reset(seed=i)
    backend.reset(seed=0)
    for c in range(chunks):
        if time.monotonic() > deadline:
            break
        t0 = time.perf_counter()
        done = False
        for j in range(n):
            result = backend.apply(actions[(c * n + j) % len(actions)])
            done = done or result.terminated or result.truncated
        chunk_s.append(time.perf_counter() - t0)
        tick()
        if done:
            backend.reset(seed=c)
    return step_s, chunk_s


def _time_bridge(env, actions: np.ndarray, steps: int, chunks: int, n: int, deadline: float, tick=lambda: None):
    step_s, chunk_s = [], []
    env.reset(seed=0)
    for i in range(steps):
        if time.monotonic() > deadline:
            break
        t0 = time.perf_counter()
        _, _, terminated, truncated, _ = env.step(actions[i % len(actions)])
        step_s.append(time.perf_counter() - t0)
        tick()
        if terminated or truncated:
            env.reset(seed=i)
    env.reset(seed=0)
    for c in range(chunks):
        if time.monotonic() > deadline:
            break
        chunk = np.stack([actions[(c * n + j) % len(actions)] for j in range(n)])
        t0 = time.perf_counter()
        _, _, terminated, truncated, _ = env.step_chunk(chunk)
        chunk_s.append(time.perf_counter() - t0)
        tick()
        if terminated or truncated:
            env.reset(seed=c)
    return step_s, chunk_s


def time_estop_commands(operator: str, runs: int, tick=lambda: None) -> dict:
    """Process start to exit of ``estop`` through each entry point, interleaved (same load for both)."""
    commands = {"operator_cli": [sys.executable, "-m", "jepa_robot.operator_cli", "estop", "--operator", operator],
                "full_cli": [sys.executable, "-m", "jepa_robot.cli", "estop", "--operator", operator],
                "bare_python": [sys.executable, "-c", "pass"]}
    samples: dict[str, list[float]] = {name: [] for name in commands}
    for _ in range(runs):
        for name, command in commands.items():
            t0 = time.perf_counter()
            subprocess.run(command, check=True, capture_output=True)
            samples[name].append(time.perf_counter() - t0)
        tick()
    out = {"runs": runs}
    for name, values in samples.items():
        x = np.asarray(values, np.float64) * 1e3
        out[name] = {"p50_ms": float(np.median(x)) if x.size else None,
                     "p90_ms": float(np.percentile(x, 90)) if x.size else None}
    return out


def run_bench(args) -> int:
    """Run the benchmark described in the module docstring and print its numbers."""
    deadline = time.monotonic() + args.max_seconds
    # steps and chunks in process and over the bridge, then the e-stop commands (a phase cut short by its
    # deadline leaves the bar short)
    bar = tqdm(total=2 * (args.steps + args.chunks) + args.estop_runs, desc="robot bench", unit="op",
               disable=args.no_progress, file=sys.stderr)
    backend = SimBackend(args.task, image_size=args.image_size, camera_replicas=args.cameras)
    try:
        n = backend.task_spec.n_action_steps
        actions = bench_actions(backend, 256)
        obs, _ = backend.reset(seed=0)
        payload = sum(v.nbytes for v in obs.values())
        in_step, in_chunk = _time_in_process(backend, actions, args.steps, args.chunks, n,
                                             time.monotonic() + args.max_seconds / 3, bar.update)
    finally:
        backend.close()
    server = subprocess.Popen(
        [sys.executable, "-m", "jepa_robot.cli", "serve", "--backend", "sim", "--task", args.task,
         "--image-size", str(args.image_size), "--camera-replicas", str(args.cameras), "--chunk-budget",
         "1000000", "--bind", "tcp://127.0.0.1:*", "--operator-bind", "tcp://127.0.0.1:*", "--no-prompt"],
        stdout=subprocess.PIPE, text=True)
    try:
        banner = server.stdout.readline()
        if " on " not in banner:
            raise RuntimeError(f"the bench bridge did not start (said {banner!r})")
        control = banner.split(" on ")[1].split(",")[0].strip()
        operator = banner.rsplit("operator socket ", 1)[1].strip()
        env = RealRobotEnv(task=args.task, address=control, client_name="bench")
        try:
            br_step, br_chunk = _time_bridge(env, actions, args.steps, args.chunks, n, deadline, bar.update)
        finally:
            env.close()
        estop = time_estop_commands(operator, args.estop_runs, bar.update)
        with OperatorClient(operator) as op:
            op.clear_estop()
            status = op.status()
            op.shutdown()
        server.wait(timeout=30)
    finally:
        bar.close()
        if server.poll() is None:
            server.kill()
            server.wait()
    result = {
        "task": args.task, "cameras": args.cameras, "image_size": args.image_size,
        "obs_payload_bytes": int(payload), "actions_per_chunk": n,
        "in_process": {"step": percentiles_ms(in_step), "chunk": percentiles_ms(in_chunk)},
        "bridge": {"step": percentiles_ms(br_step), "chunk": percentiles_ms(br_chunk)},
        "bridge_frame_to_chunk": status["frame_to_chunk_latency_all"],
        "estop_command": estop,
    }
    for level in ("step", "chunk"):
        result[f"overhead_{level}_p50_ms"] = (result["bridge"][level]["p50_ms"]
                                              - result["in_process"][level]["p50_ms"])
        result[f"overhead_{level}_p99_ms"] = (result["bridge"][level]["p99_ms"]
                                              - result["in_process"][level]["p99_ms"])
    print(f"task {args.task}: {args.cameras} camera(s) of {args.image_size}x{args.image_size}, "
          f"{payload / 1024:.1f} KiB per observation")
    print(f"{'':>22}{'p50 ms':>10}{'p99 ms':>10}{'n':>7}")
    for where in ("in_process", "bridge"):
        for level in ("step", "chunk"):
            r = result[where][level]
            print(f"{where + ' ' + level:>22}{r['p50_ms']:>10.3f}{r['p99_ms']:>10.3f}{r['n']:>7}")
    print(f"overhead per step  p50 {result['overhead_step_p50_ms']:.3f} ms, p99 {result['overhead_step_p99_ms']:.3f} ms")
    print(f"overhead per chunk p50 {result['overhead_chunk_p50_ms']:.3f} ms, p99 "
          f"{result['overhead_chunk_p99_ms']:.3f} ms ({n} actions, one round trip)")
    f2c = result["bridge_frame_to_chunk"]
    if f2c["count"]:
        print(f"bridge-side frame-to-chunk latency (no policy, steady state): median {f2c['median_ms']:.3f} ms, "
              f"p95 {f2c['p95_ms']:.3f} ms over {f2c['count']} chunks")
    if estop["runs"]:
        light, full = estop["operator_cli"], estop["full_cli"]
        print(f"`jepa-robot-bridge estop`, process start to exit over {estop['runs']} runs (median, p90): "
              f"operator entry point {light['p50_ms']:.0f} / {light['p90_ms']:.0f} ms, full command line "
              f"{full['p50_ms']:.0f} / {full['p90_ms']:.0f} ms (x{full['p50_ms'] / light['p50_ms']:.1f}); "
              f"bare python {estop['bare_python']['p50_ms']:.0f} ms")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=2)
    return 0
