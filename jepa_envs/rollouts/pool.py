"""A persistent pool of env-only worker processes for rollouts at scale (the model stays in the parent).

``EnvPool(env_id, num_envs, workers=N)`` starts N worker processes (spawn) once; each hosts a fixed share of the
``num_envs`` environments and keeps them across evaluations. The parent sends one batch of actions, the workers
step their environments in parallel and send back observations; the policy then acts on all of them as one
batch. ``workers=0`` hosts the environments in this process with the same code (the sequential path), so
results are identical whatever N: every environment runs its own seeded episode and the policy always sees
batches of ``num_envs`` rows in the same order.

An environment whose episode ended is frozen (not stepped, no frames rendered) until the next reset, and
rendering is per environment on demand (``set_render_images``), so only the frames a policy and its monitor
use are made. A worker that dies or does not answer in time raises ``WorkerFailure`` naming it;
``restart(worker)`` replaces it (the caller reruns what was lost; ``jepa_policy.evaluate`` reruns the round
and says so in its report). Nothing is dropped silently.

"In time" is derived from the task: each worker times one reset and one rendered step of its first env when it
starts, and a command may take TIMEOUT_MARGIN times (its environments x the slowest time per env measured so
far for that kind of command), never less than ``timeout_floor_s``. ``timeout_s`` (or the environment variable
JEPA_POOL_TIMEOUT_S, which reaches ``jepa-policy eval``, ``train`` and ``bench``) sets one fixed limit instead.
"""
from __future__ import annotations

import contextlib
import math
import multiprocessing as mp
import os
import sys
import time
import traceback
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np

import jepa_envs  # noqa: F401  (registers the JEPA/* ids)

TIMEOUT_MARGIN = 30.0      # a command may take this many times its measured duration (load bursts) before it hangs
TIMEOUT_FLOOR_S = 30.0     # ... and never less than this
TIMEOUT_ENV = "JEPA_POOL_TIMEOUT_S"


def _seconds_from_env(text: str) -> float:
    """JEPA_POOL_TIMEOUT_S as seconds, refused in one line naming the variable when it is not a finite number > 0."""
    try:
        seconds = float(text)
    except ValueError:
        seconds = math.nan
    if not (math.isfinite(seconds) and seconds > 0):
        raise ValueError(f"{TIMEOUT_ENV}={text!r} is not a number of seconds > 0; set it to the seconds a rollout "
                         f"worker may take per command (e.g. {TIMEOUT_ENV}=600) or unset it to derive the limit "
                         f"from the task")
    return seconds


class WorkerFailure(RuntimeError):
    """Pool workers died or hung: ``failures`` maps each one's index to the reason (``worker``/``reason``: the
    first). The pool can ``restart`` them."""

    def __init__(self, failures: dict[int, str] | int, reason: str = ""):
        self.failures = dict(failures) if isinstance(failures, dict) else {int(failures): reason}
        self.worker, self.reason = next(iter(self.failures.items()))
        super().__init__("; ".join(f"rollout worker {w} failed: {r}" for w, r in self.failures.items()))


def available_cores() -> int:
    """The cores this process may run on (affinity, cgroup-limited containers included where visible)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:   # not Linux
        return max(1, os.cpu_count() or 1)


# ----------------------------------------------------------------------------- what runs next to the envs

class _EnvHost:
    """A few environments of one task, stepped one after the other; ended ones are frozen until reset."""

    def __init__(self, env_id: str, count: int, env_kwargs: dict, max_steps: int | None):
        extra = {"max_episode_steps": max_steps} if max_steps else {}
        self.envs = [gym.make(env_id, **env_kwargs, **extra) for _ in range(count)]
        self.last: list[tuple] = [None] * count
        self.done = [True] * count

    def probe(self) -> dict[str, float]:
        """Seconds of one reset and one rendered step of the first environment (what the pool's time limits are
        derived from); the pool resets every environment before stepping it, so this leaves no trace."""
        env = self.envs[0]
        t0 = time.perf_counter()
        env.reset(seed=0)
        t1 = time.perf_counter()
        env.step(env.unwrapped.hold_action())
        return {"reset": t1 - t0, "step": time.perf_counter() - t1}

    def reset(self, payload: tuple[list, list[bool], list[bool] | None]) -> list[tuple]:
        seeds, active, render = payload
        if render is not None:
            self.set_render_images(render)
        out = []
        for i, (env, seed) in enumerate(zip(self.envs, seeds)):
            obs, info = env.reset(seed=seed)
            info = _plain_info(info)
            self.done[i] = not active[i]   # a spare keeps the batch's shape; it is never stepped
            self.last[i] = (obs, 0.0, False, False, info)
            out.append((obs, info))
        return out

    def step(self, payload: tuple[list[np.ndarray], list[bool] | None]) -> list[tuple]:
        actions, render = payload
        if render is not None:
            self.set_render_images(render)
        out = []
        for i, (env, action) in enumerate(zip(self.envs, actions)):
            if self.done[i]:   # frozen: the episode is over; the same observation, nothing rendered
                obs, _, _, _, info = self.last[i]
                out.append((obs, 0.0, False, False, info))
                continue
            obs, reward, terminated, truncated, info = env.step(action)
            self.done[i] = bool(terminated or truncated)
            self.last[i] = (obs, float(reward), bool(terminated), bool(truncated), _plain_info(info))
            out.append(self.last[i])
        return out

    def set_render_images(self, flags: list[bool]) -> None:
        for env, flag in zip(self.envs, flags):
            env.unwrapped.set_render_images(bool(flag))

    def call(self, name: str, args: tuple) -> list[Any]:
        return [getattr(env.unwrapped, name)(*args) for env in self.envs]

    def close(self) -> None:
        for env in self.envs:
            env.close()


def _renderer_in_use() -> str:
    """The OpenGL backend this process's MuJoCo envs render with, or "none" (PushT rasterises without it)."""
    return os.environ.get("MUJOCO_GL", "none") if "mujoco" in sys.modules else "none"


def _plain_info(info: dict) -> dict:
    """The scalar entries of an env's info (what crosses the process boundary and gets batched)."""
    return {k: v for k, v in info.items() if isinstance(v, (bool, int, float, np.bool_, np.integer, np.floating))}


def _worker_main(conn, env_id: str, count: int, env_kwargs: dict, max_steps: int | None,
                 render_threads: int) -> None:
    host = None
    # Mesa's llvmpipe (behind both osmesa and EGL on a CPU) starts one thread per core in every process; the
    # workers share the cores, so each gets its share unless the user chose (read when the first context is made).
    os.environ.setdefault("LP_NUM_THREADS", str(render_threads))
    try:
        host = _EnvHost(env_id, count, env_kwargs, max_steps)
        conn.send(("ok", (os.getpid(), _renderer_in_use(), host.probe())))
        while True:
            command, payload = conn.recv()
            if command == "close":
                break
            try:
                if command == "reset":
                    result = host.reset(payload)
                elif command == "step":
                    result = host.step(payload)
                elif command == "call":
                    result = host.call(*payload)
                elif command == "crash":   # fault injection for the tests: die as a segfault would
                    os._exit(int(payload))
                elif command == "hang":    # fault injection for the tests: stop answering
                    time.sleep(float(payload))
                    result = None
                else:
                    raise ValueError(f"unknown pool command {command!r}")
                conn.send(("ok", result))
            except Exception:
                conn.send(("error", traceback.format_exc()))
    except (EOFError, KeyboardInterrupt):
        pass
    except Exception:
        try:
            conn.send(("error", traceback.format_exc()))
        except (BrokenPipeError, OSError):
            pass
    finally:
        if host is not None:
            host.close()
        conn.close()


@contextlib.contextmanager
def _main_module_hidden():
    """Start workers without re-running the caller's script in them: a worker needs only this module, and
    spawn would otherwise import ``__main__`` again, which fails in a script without an
    ``if __name__ == "__main__":`` guard (and repeats whatever work its top level does)."""
    main = sys.modules.get("__main__")
    saved = {name: main.__dict__[name] for name in ("__file__", "__spec__")
             if main is not None and name in main.__dict__}
    try:
        if main is not None:
            main.__dict__.pop("__file__", None)
            main.__spec__ = None
        yield
    finally:
        if main is not None:
            main.__dict__.update(saved)
            if "__spec__" not in saved:
                main.__dict__.pop("__spec__", None)


@dataclass
class _Worker:
    index: int
    envs: list[int]                     # which of the pool's environments it hosts
    process: Any = None
    conn: Any = None
    pid: int | None = None
    seconds: dict[str, float] = field(default_factory=dict)   # slowest measured seconds per env, per command


@dataclass
class PoolEvent:
    """A restart: which worker, why, when."""

    worker: int
    reason: str
    time: float = field(default_factory=time.time)


class EnvPool:
    """``num_envs`` environments of one task over ``workers`` processes (0: in this process)."""

    def __init__(self, env_id: str, num_envs: int, workers: int | None = None, env_kwargs: dict | None = None,
                 max_steps: int | None = None, timeout_s: float | None = None, start_timeout_s: float = 600.0,
                 timeout_floor_s: float = TIMEOUT_FLOOR_S):
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        workers = available_cores() if workers is None else int(workers)
        if workers < 0:
            raise ValueError(f"workers must be >= 0 (0: in this process), got {workers}")
        self.env_id, self.num_envs = env_id, int(num_envs)
        self.workers = min(workers, self.num_envs)
        self.env_kwargs, self.max_steps = dict(env_kwargs or {}), max_steps
        if timeout_s is None and os.environ.get(TIMEOUT_ENV, "").strip():
            timeout_s = _seconds_from_env(os.environ[TIMEOUT_ENV])
        elif timeout_s is not None and not (math.isfinite(timeout_s) and timeout_s > 0):
            raise ValueError(f"the pool's timeout_s must be a finite number of seconds > 0, got {timeout_s}")
        self.timeout_s = None if timeout_s is None else float(timeout_s)   # None: derived per command
        self.start_timeout_s, self.timeout_floor_s = float(start_timeout_s), float(timeout_floor_s)
        self.events: list[PoolEvent] = []
        self._render = [True] * self.num_envs
        self._render_changed = True   # render flags travel with the next reset or step (no extra round trip)
        self._closed = False
        self.renderer = "none"
        if self.workers == 0:
            self._host = _EnvHost(env_id, self.num_envs, self.env_kwargs, max_steps)
            self.renderer = _renderer_in_use()
            self._workers: list[_Worker] = []
        else:
            self._host = None
            shares = np.array_split(np.arange(self.num_envs), self.workers)
            self._workers = [_Worker(i, [int(j) for j in share]) for i, share in enumerate(shares)]
            self._ctx = mp.get_context("spawn")   # fork would copy the parent's threads and GL state
            for worker in self._workers:
                self._start(worker)
            for worker in self._workers:
                self._await_start(worker)

    # ------------------------------------------------------------------ processes
    def _start(self, worker: _Worker) -> None:
        parent, child = self._ctx.Pipe()
        worker.process = self._ctx.Process(
            target=_worker_main, args=(child, self.env_id, len(worker.envs), self.env_kwargs, self.max_steps,
                                      max(1, available_cores() // self.workers)),
            name=f"rollout-worker-{worker.index}", daemon=True)
        with _main_module_hidden():
            worker.process.start()
        child.close()
        worker.conn = parent

    def _await_start(self, worker: _Worker) -> None:
        status, payload = self._receive(worker, self.start_timeout_s)
        if status != "ok":
            self._kill(worker)
            raise RuntimeError(f"rollout worker {worker.index} could not build {self.env_id}:\n{payload}")
        worker.pid, self.renderer, worker.seconds = payload
        worker.seconds["call"] = worker.seconds["reset"]

    def command_timeout(self, worker: _Worker, command: str) -> tuple[float, str]:
        """The limit for ``command`` on ``worker`` and how it was set (for the hung worker's message)."""
        if self.timeout_s is not None:
            return self.timeout_s, f"the fixed limit (timeout_s / {TIMEOUT_ENV})"
        per_env = worker.seconds[command]
        derived = TIMEOUT_MARGIN * per_env * len(worker.envs)
        return max(self.timeout_floor_s, derived), (
            f"{TIMEOUT_MARGIN:g} x its {len(worker.envs)} env(s) x {per_env:.3g}s, the slowest {command} measured, at "
            f"least {self.timeout_floor_s:g}s; set {TIMEOUT_ENV} to fix another limit")

    def _kill(self, worker: _Worker) -> None:
        if worker.process is not None and worker.process.is_alive():
            worker.process.kill()
        if worker.process is not None:
            worker.process.join(timeout=10)
        if worker.conn is not None:
            worker.conn.close()

    def restart(self, index: int, reason: str = "") -> None:
        """Replace worker ``index`` with a fresh process (its environments are rebuilt; reset them next)."""
        worker = self._workers[index]
        self._kill(worker)
        self.events.append(PoolEvent(index, reason or "restarted"))
        self._start(worker)
        self._await_start(worker)
        self._render_changed = True

    def _receive(self, worker: _Worker, timeout_s: float, how: str = "the start limit"):
        try:
            if not worker.conn.poll(timeout_s):
                raise WorkerFailure(worker.index, f"no answer within {timeout_s:.3g}s (hung; {how})")
            return worker.conn.recv()
        except (EOFError, BrokenPipeError, ConnectionResetError, OSError) as exc:
            raise WorkerFailure(worker.index, f"process ended (exit code {self._exit_code(worker)}): "
                                              f"{type(exc).__name__}") from None

    @staticmethod
    def _exit_code(worker: _Worker):
        """The exit code of a worker whose pipe closed (it may take a moment to be reaped)."""
        if worker.process is None:
            return None
        worker.process.join(timeout=5)
        return worker.process.exitcode

    def _broadcast(self, command: str, payloads: list) -> list:
        """Send each worker its payload, then collect the answers in env order. Every worker that was sent a
        command is heard from (or found dead) before anything is raised, so no stale answer is left in a pipe."""
        if self._closed:
            raise RuntimeError("this EnvPool is closed; make a new one")
        if self._host is not None:   # in this process: the same host code, one share
            method = {"reset": self._host.reset, "step": self._host.step}
            return method[command](payloads[0]) or []
        failures: dict[int, str] = {}
        sent = []
        for worker, payload in zip(self._workers, payloads):
            try:
                worker.conn.send((command, payload))
                sent.append(worker)
            except (BrokenPipeError, OSError):
                failures[worker.index] = f"process ended (exit code {self._exit_code(worker)}): its pipe is closed"
        answers, errors = {}, []
        started = time.perf_counter()
        for worker in sent:
            try:
                status, payload = self._receive(worker, *self.command_timeout(worker, command))
            except WorkerFailure as exc:
                failures[worker.index] = exc.reason
                continue
            per_env = (time.perf_counter() - started) / len(worker.envs)
            worker.seconds[command] = max(worker.seconds[command], per_env)
            if status != "ok":
                errors.append(f"rollout worker {worker.index} failed on {command!r}:\n{payload}")
            answers[worker.index] = payload
        if failures:
            raise WorkerFailure(failures)
        if errors:
            raise RuntimeError("\n".join(errors))
        return [row for worker in self._workers for row in (answers[worker.index] or [])]

    def _split(self, values: list) -> list[list]:
        if self._host is not None:
            return [list(values)]
        return [[values[j] for j in worker.envs] for worker in self._workers]

    # ------------------------------------------------------------------ vector-env interface
    def _render_flags(self) -> list | None:
        flags, self._render_changed = (self._render if self._render_changed else None), False
        return flags

    def reset(self, seeds: list[int | None], active: list[bool] | None = None) -> tuple[dict, dict]:
        """Reset every environment with its seed; ``active`` False: a spare (reset, then frozen)."""
        if len(seeds) != self.num_envs:
            raise ValueError(f"reset needs one seed per environment ({self.num_envs}), got {len(seeds)}")
        active = [True] * self.num_envs if active is None else [bool(a) for a in active]
        render = self._render_flags()
        shares = [(s, a, None if render is None else r)
                  for s, a, r in zip(self._split(list(seeds)), self._split(active), self._split(render or active))]
        results = self._broadcast("reset", shares)
        return _stack([r[0] for r in results]), _stack_info([r[1] for r in results])

    def step(self, actions) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray, dict]:
        actions = np.asarray(actions)
        if actions.shape[0] != self.num_envs:
            raise ValueError(f"step needs one action per environment ({self.num_envs}), got {actions.shape[0]}")
        render = self._render_flags()
        shares = [(a, None if render is None else r)
                  for a, r in zip(self._split(list(actions)), self._split(render or [True] * self.num_envs))]
        results = self._broadcast("step", shares)
        obs = _stack([r[0] for r in results])
        reward = np.array([r[1] for r in results], np.float64)
        terminated = np.array([r[2] for r in results], bool)
        truncated = np.array([r[3] for r in results], bool)
        return obs, reward, terminated, truncated, _stack_info([r[4] for r in results])

    def set_render_images(self, flags) -> None:
        """Render camera images (True) or skip them (False) from the next step on, per environment or one flag
        for all."""
        flags = [bool(flags)] * self.num_envs if np.ndim(flags) == 0 else [bool(f) for f in flags]
        if flags != self._render:
            self._render, self._render_changed = flags, True

    def call(self, name: str, *args) -> list:
        """Call a method of every environment's ``unwrapped`` env; one result per environment."""
        if self._host is not None:
            return self._host.call(name, args)
        return self._broadcast("call", [(name, args)] * len(self._workers))

    def inject(self, worker: int, command: str, payload) -> None:
        """Fault injection (tests): ``crash`` (exit code) or ``hang`` (seconds) in one worker."""
        self._workers[worker].conn.send((command, payload))

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._host is not None:
            self._host.close()
        for worker in self._workers:
            try:
                worker.conn.send(("close", None))
            except (BrokenPipeError, OSError):
                pass
        for worker in self._workers:
            if worker.process is not None:
                worker.process.join(timeout=10)
            self._kill(worker)

    def __enter__(self) -> "EnvPool":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def describe(self) -> dict:
        return {"env_id": self.env_id, "num_envs": self.num_envs, "workers": self.workers, "renderer": self.renderer,
                "pids": [w.pid for w in self._workers], "restarts": [e.__dict__ for e in self.events],
                "step_s": [w.seconds.get("step") for w in self._workers],
                "step_timeout_s": [self.command_timeout(w, "step")[0] for w in self._workers]}


def _stack(observations: list[dict]) -> dict:
    return {key: np.stack([o[key] for o in observations]) for key in observations[0]}


def _stack_info(infos: list[dict]) -> dict:
    keys = set().union(*infos) if infos else set()
    return {key: np.array([info.get(key, False) for info in infos]) for key in sorted(keys)}
