"""Benchmarks of ``jepa-policy serve``: the round-trip overhead over in-process decisions, decisions/s with several
clients, batched and not, and what a hostile peer costs the others (``jepa-policy bench serve [--hostile]``).

Each runs real ``jepa-policy serve`` processes (a checkpoint of random weights unless one is given) and talks to
them with websockets, as a robot does.
"""
from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import torch
import websockets
from tqdm import tqdm
from websockets.sync.client import connect

from jepa_policy.bench import _random_checkpoint
from jepa_policy.policy import Policy
from jepa_policy.serve import MAX_REQUEST_BYTES, pack, unpack


def _start_server(checkpoint: str, threads: int, *flags: str, cwd: str | None = None):
    """A ``jepa-policy serve`` process on a free port (run from ``cwd``: another checkout's code, to compare);
    returns once it accepts websockets."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen([sys.executable, "-m", "jepa_policy.cli", "serve", "--checkpoint", checkpoint,
                             "--port", str(port), "--threads", str(threads), *flags], cwd=cwd,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 60
    while True:
        try:
            with connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None):
                return proc, port
        except OSError:
            if time.monotonic() > deadline or proc.poll() is not None:
                raise RuntimeError(f"jepa-policy serve did not start: {proc.stderr.read().decode()[-1500:]}")
            time.sleep(0.2)


def bench_serve(task: str = "PushT", preset: str = "cpu", checkpoint: str | None = None, iters: int = 200,
                seconds: float = 5.0, clients=(1, 4, 16), threads: int = 1, hostile: bool = False,
                progress: bool = False) -> dict:
    """``jepa-policy serve`` beside in-process decisions, in one run: round-trip overhead at batch 1 (the same
    history decided in-process and over the websocket, alternately), then decisions/s with several clients,
    cross-client batching on (``--max-batch 16``) and off (``--max-batch 1``); with ``hostile``, also
    ``bench_serve_hostile`` and ``bench_serve_peers``. ``progress``: a bar of the phases on stderr."""
    torch.set_num_threads(threads)
    bar = tqdm(total=1 + 2 * len(clients) + 2 * hostile, desc="bench serve", unit="phase", disable=not progress)
    tmp = tempfile.mkdtemp(prefix="jepa-bench-serve-")
    checkpoint = checkpoint or _random_checkpoint(task, preset, Path(tmp) / "random.pt")
    policy = Policy.from_checkpoint(checkpoint)
    spec = policy.spec
    rng = np.random.default_rng(0)

    def history():
        return [{**{k: rng.integers(0, 256, (spec.image_size, spec.image_size, 3), dtype=np.uint8)
                    for k in spec.image_keys},
                 **{k: rng.uniform(-1, 1, d).astype(np.float32) for k, d in spec.lowdim}}
                for _ in range(policy.obs_steps)]

    def request(frames) -> bytes:
        return pack({k: np.stack([f[k] for f in frames]) for k in frames[0]})

    def start_server(max_batch: int):
        return _start_server(checkpoint, threads, "--max-batch", str(max_batch), "--max-queue", "1024")

    result = {"task": spec.name, "preset": preset, "torch_threads": threads, "cores": os.cpu_count(),
              "load_average_before": os.getloadavg()[0]}
    proc, port = start_server(16)
    try:
        local_ms, remote_ms = [], []
        with connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None) as ws:
            unpack(ws.recv())
            for i in range(iters + 20):
                frames = history()
                body = request(frames)
                t0 = time.perf_counter()
                policy.decide_from(frames)
                t1 = time.perf_counter()
                ws.send(body)
                reply = unpack(ws.recv())
                t2 = time.perf_counter()
                if i >= 20:   # warm-up first
                    local_ms.append((t1 - t0) * 1e3)
                    remote_ms.append((t2 - t1) * 1e3)
                assert reply["actions"].shape[0] == policy.n_action_steps
        bar.update()
        local, remote = np.array(local_ms), np.array(remote_ms)
        result["overhead"] = {"in_process_p50_ms": float(np.percentile(local, 50)),
                              "in_process_p99_ms": float(np.percentile(local, 99)),
                              "served_p50_ms": float(np.percentile(remote, 50)),
                              "served_p99_ms": float(np.percentile(remote, 99)),
                              "overhead_p50_ms": float(np.percentile(remote - local, 50)),
                              "overhead_p99_ms": float(np.percentile(remote - local, 99))}
        proc.terminate()
        proc.wait(timeout=30)
        result["concurrency"] = {}
        for max_batch in (16, 1):
            proc, port = start_server(max_batch)
            for n in clients:
                counts, latencies = [0] * n, [[] for _ in range(n)]
                bodies = [request(history()) for _ in range(8)]
                stop = time.perf_counter() + seconds
                barrier = threading.Barrier(n)

                def client(i):
                    with connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None) as c:
                        unpack(c.recv())
                        barrier.wait()
                        while time.perf_counter() < stop:
                            t = time.perf_counter()
                            c.send(bodies[counts[i] % len(bodies)])
                            reply = c.recv()
                            if isinstance(reply, str):
                                raise RuntimeError(reply)
                            latencies[i].append((time.perf_counter() - t) * 1e3)
                            counts[i] += 1
                workers = [threading.Thread(target=client, args=(i,)) for i in range(n)]
                start = time.perf_counter()
                for w in workers:
                    w.start()
                for w in workers:
                    w.join()
                elapsed = time.perf_counter() - start
                lat = np.concatenate([np.array(x) for x in latencies])
                result["concurrency"][f"batch{max_batch}_clients{n}"] = {
                    "decisions_per_s": sum(counts) / elapsed, "p50_ms": float(np.percentile(lat, 50)),
                    "p99_ms": float(np.percentile(lat, 99))}
                bar.update()
            proc.terminate()
            proc.wait(timeout=30)
        if hostile:
            result["hostile"] = bench_serve_hostile(checkpoint, request(history()), seconds=seconds, threads=threads)
            bar.update()
            result["peers"] = bench_serve_peers(checkpoint, request(history()), seconds=seconds, threads=threads)
            bar.update()
    finally:
        bar.close()
        if proc.poll() is None:
            proc.kill()
        shutil.rmtree(tmp, ignore_errors=True)
    result["load_average_after"] = os.getloadavg()[0]
    return result


def _memory_mib(pid: int) -> dict:
    fields = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines() if ":" in line)
    return {k: int(fields[k].split()[0]) / 1024 for k in ("VmRSS", "VmHWM")}


def _tiny_arrays_frame(body: bytes, n: int = 190_000, nested: bool = False) -> bytes:
    """A request with ``n`` one-byte arrays (8 MiB for 190,000): in one list, or in lists of 60 (each list short)."""
    tiny = {b"__ndarray__": True, b"data": b"x", b"dtype": "|u1", b"shape": [1]}
    return pack({**unpack(body), "extra": [[tiny] * 60] * (n // 60) if nested else [tiny] * n})


def bench_serve_hostile(checkpoint: str, body: bytes, seconds: float = 5.0, threads: int = 1, flooders: int = 8,
                        cwd: str | None = None) -> dict:
    """What a hostile peer costs the others, each phase on a fresh server: one robot's round trips (``body``, a
    good request) alone and beside a client sending 8 MiB frames of 190,000 tiny arrays (one list; lists of 60);
    then the server's peak memory when ``flooders`` clients each send one 63 MiB frame, and one just under the
    8 MiB limit (a valid request whose array has the wrong shape)."""
    result: dict = {"latency": {}, "memory": {}}
    frames = {"alone": None, "tiny_arrays_list": _tiny_arrays_frame(body),
              "tiny_arrays_nested": _tiny_arrays_frame(body, nested=True)}
    for name, frame in frames.items():
        proc, port = _start_server(checkpoint, threads, cwd=cwd)
        try:
            robot = connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None)
            unpack(robot.recv())
            stop, answered = threading.Event(), []

            def attack():
                with connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None) as ws:
                    ws.recv()
                    while not stop.is_set():
                        t = time.perf_counter()
                        ws.send(frame)
                        ws.recv()
                        answered.append((time.perf_counter() - t) * 1e3)
            attacker = threading.Thread(target=attack) if frame is not None else None
            if attacker is not None:
                attacker.start()
                time.sleep(0.5)
            latencies, end = [], time.perf_counter() + seconds
            while time.perf_counter() < end:
                t = time.perf_counter()
                robot.send(body)
                if isinstance(robot.recv(), str):
                    raise RuntimeError("the good request was refused")
                latencies.append((time.perf_counter() - t) * 1e3)
            stop.set()
            if attacker is not None:
                attacker.join()
            robot.close()
            lat = np.array(latencies)
            result["latency"][name] = {
                "robot_p50_ms": float(np.percentile(lat, 50)), "robot_p99_ms": float(np.percentile(lat, 99)),
                "robot_max_ms": float(lat.max()), "robot_requests": len(lat), "frame_bytes": len(frame or body),
                "hostile_answer_ms": float(np.median(answered)) if answered else None}
        finally:
            proc.kill()
            proc.wait(timeout=30)
    big = pack({"top_image": np.zeros(63 * 2**20, np.uint8)})
    under = pack({**unpack(body), "extra": np.zeros(MAX_REQUEST_BYTES - 4096, np.uint8)})
    for name, frame in (("63MiB", big), ("just_under_limit", under)):
        proc, port = _start_server(checkpoint, threads, cwd=cwd)
        try:
            with connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None) as ws:   # warm: one decision
                ws.recv()
                ws.send(body)
                ws.recv()
            before = _memory_mib(proc.pid)["VmRSS"]
            barrier, done, peak = threading.Barrier(flooders), threading.Event(), [before]

            def sample():   # VmHWM keeps the checkpoint load's peak: sample VmRSS instead
                while not done.is_set():
                    peak[0] = max(peak[0], _memory_mib(proc.pid)["VmRSS"])
                    time.sleep(0.002)
            sampler = threading.Thread(target=sample)
            sampler.start()

            def flood():
                try:
                    with connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None, open_timeout=30) as ws:
                        ws.recv()
                        barrier.wait()
                        ws.send(frame)
                        ws.recv(timeout=60)
                except (OSError, websockets.WebSocketException):
                    pass   # refused or closed by the server: what this phase measures is its memory
            workers = [threading.Thread(target=flood) for _ in range(flooders)]
            for w in workers:
                w.start()
            for w in workers:
                w.join()
            done.set()
            sampler.join()
            result["memory"][name] = {"frame_bytes": len(frame), "clients": flooders, "rss_before_mib": before,
                                      "peak_rss_mib": peak[0], "peak_growth_mib": peak[0] - before}
        finally:
            proc.kill()
            proc.wait(timeout=30)
    return result


STRING_LIST_FRAMES = {   # a list of strings or bytes where a low-dim array goes (numpy would size them)
    "65,536-char str + 4,000 str": ["x" * 65536] + ["y"] * 4000,
    "4 MB bytes + 4,000 bytes": [b"x" * 4_000_000] + [b"y"] * 4000,
    "8 MB str + 4,000 str": ["x" * (8 * 2**20 - 70_000)] + ["y"] * 4000,
}


def _robot_latencies(port: int, body: bytes, seconds: float) -> np.ndarray:
    """A good robot's round trips for ``seconds``; a connection the server dropped (it stalled past the
    keep-alive) ends the series with an infinite latency."""
    latencies, end = [], time.perf_counter() + seconds
    try:
        with connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None, open_timeout=60) as robot:
            unpack(robot.recv())
            while time.perf_counter() < end:
                t = time.perf_counter()
                robot.send(body)
                if isinstance(robot.recv(timeout=60), str):
                    raise RuntimeError("the good request was refused")
                latencies.append((time.perf_counter() - t) * 1e3)
    except (OSError, TimeoutError, websockets.WebSocketException):
        latencies.append(float("inf"))
    return np.array(latencies)


def bench_serve_peers(checkpoint: str, body: bytes, seconds: float = 5.0, threads: int = 1,
                      cwd: str | None = None, junk_clients: int = 3, frames: tuple[str, ...] | None = None) -> dict:
    """What one hostile peer's kind of frame costs, on a fresh server each: for each string-list frame, the
    server's peak memory growth and the answer time of the frame sent once, then another robot's round trips
    (``body``) alone and while the frame is sent in a loop (paced by the server); and the robot's round trips
    beside ``junk_clients`` clients that reconnect after every refused frame. ``cwd``: run another checkout's
    server (the code before a change, side by side)."""
    result: dict = {"frames": {}, "reconnecting": {}}
    good = unpack(body)
    key = next(k for k, v in good.items() if getattr(v, "dtype", None) == np.float32)   # a low-dim key
    for name, value in STRING_LIST_FRAMES.items():
        if frames is not None and name not in frames:
            continue
        frame = pack({**good, key: value})
        proc, port = _start_server(checkpoint, threads, cwd=cwd)
        try:
            quiet = _robot_latencies(port, body, seconds / 2)
            before = _memory_mib(proc.pid)["VmRSS"]
            peak, done = [before], threading.Event()

            def sample():
                while not done.is_set():
                    try:
                        peak[0] = max(peak[0], _memory_mib(proc.pid)["VmRSS"])
                    except (OSError, KeyError):   # the server died (MemoryError killed it, or the OOM killer)
                        return
                    time.sleep(0.001)
            sampler = threading.Thread(target=sample)
            sampler.start()
            answer_ms, answered = None, "no answer"
            try:
                with connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None, open_timeout=30) as ws:
                    ws.recv()
                    t = time.perf_counter()
                    ws.send(frame)
                    reply = ws.recv(timeout=120)
                    answer_ms = (time.perf_counter() - t) * 1e3
                    answered = reply if isinstance(reply, str) else "actions"
            except (OSError, TimeoutError, websockets.WebSocketException) as exc:
                answered = f"{type(exc).__name__}"
            done.set()
            sampler.join()
            stop = threading.Event()

            def attack():
                while not stop.is_set():
                    try:
                        with connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None) as ws:
                            ws.recv()
                            while not stop.is_set():
                                ws.send(frame)
                                ws.recv(timeout=60)
                    except (OSError, TimeoutError, websockets.WebSocketException):
                        time.sleep(0.01)
            attacker = threading.Thread(target=attack)
            attacker.start()
            loaded = _robot_latencies(port, body, seconds) if proc.poll() is None else np.array([np.inf])
            stop.set()
            attacker.join()
            result["frames"][name] = {
                "frame_bytes": len(frame), "peak_growth_mib": peak[0] - before, "answer_ms": answer_ms,
                "answer": answered[:120], "server_alive": proc.poll() is None,
                "robot_quiet_max_ms": float(quiet.max()), "robot_loaded_max_ms": float(loaded.max()),
                "robot_quiet_p50_ms": float(np.median(quiet)), "robot_loaded_p50_ms": float(np.median(loaded))}
        finally:
            proc.kill()
            proc.wait(timeout=30)
    proc, port = _start_server(checkpoint, threads, cwd=cwd)
    try:
        alone = _robot_latencies(port, body, seconds)
        stop, frames_sent = threading.Event(), [0]

        def reconnecting():
            while not stop.is_set():
                try:
                    with connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None) as ws:
                        ws.recv()
                        ws.send(b"\xc1" * 64)
                        ws.recv(timeout=30)
                        frames_sent[0] += 1
                except (OSError, TimeoutError, websockets.WebSocketException):
                    pass   # refused (429) or closed: try again at once, as a hostile client does
        junk = [threading.Thread(target=reconnecting) for _ in range(junk_clients)]
        for t in junk:
            t.start()
        time.sleep(0.5)
        loaded = _robot_latencies(port, body, seconds)
        stop.set()
        for t in junk:
            t.join()
        result["reconnecting"] = {"clients": junk_clients, "junk_frames_answered": frames_sent[0],
                                  "robot_alone_p50_ms": float(np.median(alone)),
                                  "robot_loaded_p50_ms": float(np.median(loaded)),
                                  "p50_ratio": float(np.median(loaded) / np.median(alone))}
    finally:
        proc.kill()
        proc.wait(timeout=30)
    return result


def format_serve_peers(result: dict) -> str:
    lines = [f"{'frame (one hostile peer)':<28}{'MiB':>6}{'peak +MiB':>11}{'answer ms':>11}"
             f"{'robot max quiet/loaded ms':>27}  answer"]
    for name, r in result["frames"].items():
        answer = "-" if r["answer_ms"] is None else f"{r['answer_ms']:.0f}"
        lines.append(f"{name:<28}{r['frame_bytes'] / 2**20:>6.2f}{r['peak_growth_mib']:>11.0f}{answer:>11}"
                     f"{r['robot_quiet_max_ms']:>14.1f} / {r['robot_loaded_max_ms']:<10.1f}  {r['answer'][:60]}")
    r = result["reconnecting"]
    lines.append(f"{r['clients']} clients reconnecting after each refused frame "
                 f"({r['junk_frames_answered']} answered): "
                 f"another robot's p50 {r['robot_alone_p50_ms']:.2f} ms alone, {r['robot_loaded_p50_ms']:.2f} ms "
                 f"beside them (x{r['p50_ratio']:.2f})")
    return "\n".join(lines)


def format_serve(result: dict) -> str:
    o = result["overhead"]
    lines = [f"jepa-policy serve vs in-process, {result['task']} ({result['preset']}), torch threads "
             f"{result['torch_threads']}, {result['cores']} cores, load {result['load_average_before']:.2f} -> "
             f"{result['load_average_after']:.2f}",
             f"{'batch 1':<22}{'p50 ms':>9}{'p99 ms':>9}",
             f"{'in-process decision':<22}{o['in_process_p50_ms']:>9.2f}{o['in_process_p99_ms']:>9.2f}",
             f"{'served (round trip)':<22}{o['served_p50_ms']:>9.2f}{o['served_p99_ms']:>9.2f}",
             f"{'overhead (paired)':<22}{o['overhead_p50_ms']:>9.2f}{o['overhead_p99_ms']:>9.2f}",
             f"{'clients':<10}{'batched dec/s':>15}{'p50/p99 ms':>16}{'unbatched dec/s':>18}{'p50/p99 ms':>16}"
             f"{'gain':>7}"]
    c = result["concurrency"]
    for n in sorted({int(k.split("clients")[1]) for k in c}):
        b, u = c[f"batch16_clients{n}"], c[f"batch1_clients{n}"]
        lines.append(f"{n:<10}{b['decisions_per_s']:>15.1f}{b['p50_ms']:>8.1f}/{b['p99_ms']:<7.1f}"
                     f"{u['decisions_per_s']:>18.1f}{u['p50_ms']:>8.1f}/{u['p99_ms']:<7.1f}"
                     f"{b['decisions_per_s'] / u['decisions_per_s']:>7.2f}")
    if "hostile" in result:
        lines.append(format_serve_hostile(result["hostile"]))
    if "peers" in result:
        lines.append(format_serve_peers(result["peers"]))
    return "\n".join(lines)


def format_serve_hostile(result: dict) -> str:
    lines = [f"{'another robot beside':<34}{'frame MiB':>10}{'p50 ms':>9}{'p99 ms':>9}{'max ms':>9}"
             f"{'hostile answered ms':>21}"]
    for name, r in result["latency"].items():
        hostile = "-" if r["hostile_answer_ms"] is None else f"{r['hostile_answer_ms']:.1f}"
        lines.append(f"{name:<34}{r['frame_bytes'] / 2**20:>10.2f}{r['robot_p50_ms']:>9.2f}{r['robot_p99_ms']:>9.2f}"
                     f"{r['robot_max_ms']:>9.1f}{hostile:>21}")
    lines.append(f"{'clients x frame':<34}{'RSS before MiB':>16}{'peak MiB':>10}{'peak growth MiB':>17}")
    for name, r in result["memory"].items():
        lines.append(f"{str(r['clients']) + ' x ' + name:<34}{r['rss_before_mib']:>16.0f}{r['peak_rss_mib']:>10.0f}"
                     f"{r['peak_growth_mib']:>17.0f}")
    return "\n".join(lines)
