"""Scripted expert for JEPA/PushT-v0 (both variants): push planning by simulation over a fixed grid of candidate
pushes.

Every time its queue of targets runs out the expert plans one *push*. Candidates form a fixed grid: every edge
of the T's outline, three contact points per edge, three push directions around the inward normal and two push
lengths (scaled to the remaining error). Each candidate is a smooth path of absolute agent targets (straight to
the push start when clear, else around the block on a safe circle, then the push) and is simulated on a copy of
the pymunk space (``Space.copy``, rewound per candidate); the expert executes the one that brings the block
closest to the goal pose (or reaches success) at the smallest number of steps. A fixed grid makes the choice a
near-deterministic function of the state, which is what makes the demos imitable; the seeded jitter of the grid
and of the speeds per push makes them vary. What it needs to know of a variant's T (outline, distance, coverage)
is a ``TGeometry``; the simulator it plans on (``PushTSim`` or ``StandardPushTSim``) picks it.
"""
from __future__ import annotations

import contextlib
import itertools
import math
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np
from tqdm import tqdm

from jepa_envs.tasks import pusht_standard as standard
from jepa_envs.tasks.pusht import (AGENT_RADIUS, GOAL_POSE, T_OUTLINE, T_RADIUS, WORLD_SIZE, PushTEnv, PushTSim,
                                   coverage, point_boxes_distance, point_t_distance, transform, wrap_angle)
from jepa_envs.tasks.pusht_standard import PushTStandardEnv, StandardPushTSim
from jepa_envs.tasks.pusht_variants import make_pusht

ANGLE_WEIGHT = 60.0  # world units per radian in the pose cost (about the T's radius of gyration)


def pose_cost(pose, goal=GOAL_POSE) -> float:
    """Distance of a block pose to the goal: translation + ANGLE_WEIGHT * |angle error| (world units)."""
    return math.hypot(pose[0] - goal[0], pose[1] - goal[1]) + ANGLE_WEIGHT * abs(wrap_angle(pose[2] - goal[2]))


@dataclass(frozen=True)
class TGeometry:
    """What the planner knows of a variant's T, in the frame its block pose is given in."""

    starts: np.ndarray                 # outline edges: start points, end points, outward unit normals, lengths
    ends: np.ndarray
    normals: np.ndarray
    lengths: np.ndarray
    radius: float                      # circumradius about the centroid
    centroid: np.ndarray | None        # None: the pose is the centroid's
    distance: Callable                 # (world point, pose) -> distance to the T
    coverage: Callable                 # pose -> coverage of the goal

    def centre(self, pose) -> np.ndarray:
        """The T's centroid in world coordinates."""
        return np.array(pose[:2]) if self.centroid is None else transform(self.centroid[None], pose)[0]


def _geometry(outline: np.ndarray, radius: float, centroid, distance, cover) -> TGeometry:
    starts = outline
    ends = np.roll(outline, -1, axis=0)
    d = ends - starts
    normals = np.stack([d[:, 1], -d[:, 0]], axis=1) / np.linalg.norm(d, axis=1, keepdims=True)
    for i in range(len(normals)):
        mid = (starts[i] + ends[i]) / 2
        if distance(mid + normals[i], (0.0, 0.0, 0.0)) == 0.0:
            normals[i] = -normals[i]
    return TGeometry(starts, ends, normals, np.linalg.norm(ends - starts, axis=1), radius, centroid, distance, cover)


EMBEDDED = _geometry(T_OUTLINE, T_RADIUS, None, point_t_distance, coverage)
STANDARD = _geometry(standard.T_OUTLINE, standard.T_RADIUS, standard.T_CENTROID,
                     lambda point, pose: point_boxes_distance(point, pose, standard.T_BOXES), standard.coverage)


def geometry_of(sim) -> TGeometry:
    """The T the simulator ``sim`` simulates."""
    return STANDARD if isinstance(sim, StandardPushTSim) else EMBEDDED


@dataclass
class ExpertConfig:
    contact_points: tuple[float, ...] = (0.25, 0.5, 0.75)  # positions along each outline edge
    push_angles_deg: tuple[float, ...] = (-25.0, 0.0, 25.0)  # push direction relative to the inward normal
    push_lengths: tuple[float, ...] = (0.5, 1.0)  # fractions of the push length allowed by the remaining error
    speed: float = 15.0               # world units per control step while approaching
    push_speed: float = 10.0          # world units per control step while pushing
    standoff: float = 10.0            # gap between agent and block before a push
    hold_steps: int = 2               # targets repeated at the end of a push so the agent catches up
    step_cost: float = 0.5            # world units of pose cost a candidate pays per control step it takes
    jitter: float = 0.05              # seeded shift of the contact points (edge fraction) per push, for variety
    jitter_angle_deg: float = 5.0     # seeded shift of the push directions per push
    speed_jitter: float = 0.2         # seeded relative change of both speeds per push


class PushTExpert:
    """Plans and executes pushes; call ``act(env)`` once per control step."""

    def __init__(self, seed: int | None = None, config: ExpertConfig | None = None):
        self.rng = np.random.default_rng(seed)
        self.config = config or ExpertConfig()
        self._queue: list[np.ndarray] = []

    def reset(self) -> None:
        self._queue = []

    def act(self, env) -> np.ndarray:
        """The next absolute agent target (float32 (2,)) for the env's current state."""
        base = env.unwrapped
        if not isinstance(base, (PushTEnv, PushTStandardEnv)):
            raise TypeError(f"PushTExpert drives JEPA/PushT-v0 (either variant), got {type(base).__name__}")
        if not self._queue:
            self._queue = self.plan(base.backend, base.success_threshold)
        return self._queue.pop(0).astype(np.float32)

    def plan(self, sim: PushTSim | StandardPushTSim, success_threshold: float) -> list[np.ndarray]:
        """Targets of the best simulated push of the grid (re-jittered up to 3 times if none improves)."""
        cfg, rng, geometry = self.config, self.rng, geometry_of(sim)
        current = pose_cost(sim.block_pose)
        best_targets, best_score, best_cost = None, math.inf, math.inf
        trial, start = sim.clone(), sim.snapshot()  # one copy of the space, rewound for every candidate
        try:
            for _ in range(3):
                speeds = (cfg.speed * rng.uniform(1 - cfg.speed_jitter, 1 + cfg.speed_jitter),
                          cfg.push_speed * rng.uniform(1 - cfg.speed_jitter, 1 + cfg.speed_jitter))
                shift = rng.uniform(-cfg.jitter, cfg.jitter), rng.uniform(-cfg.jitter_angle_deg, cfg.jitter_angle_deg)
                for approach, push, clear in self._candidates(sim, geometry, current, speeds, shift):
                    trial.restore(start)
                    if clear:  # the approach cannot touch the block: simulate the push from its start only
                        trial.agent.position = tuple(approach[-1])
                        trial.agent.velocity = (0.0, 0.0)
                        trial.space.reindex_shapes_for_body(trial.agent)
                        cost, used = _simulate(trial, geometry, push, success_threshold)
                        targets = approach + push[:used]
                    else:
                        cost, used = _simulate(trial, geometry, approach + push, success_threshold)
                        targets = (approach + push)[:used]
                    # a small price per step prefers near contacts: shorter, more consistent demonstrations
                    score = cost + cfg.step_cost * len(targets)
                    if score < best_score:
                        best_targets, best_score, best_cost = targets, score, cost
                if best_cost < current - 1.0:
                    break
        finally:
            trial.free()
        return best_targets

    def _candidates(self, sim, geometry: TGeometry, current_cost: float, speeds, shift):
        """(approach targets, push targets, approach verified clear) for every push of the grid."""
        cfg = self.config
        pose = sim.block_pose
        agent = np.asarray(sim.agent.position, dtype=np.float64)
        max_len = float(np.clip(0.8 * current_cost + 5.0, 5.0, 80.0))
        lo, hi = AGENT_RADIUS + 6.0, WORLD_SIZE - AGENT_RADIUS - 6.0
        for edge in range(len(geometry.lengths)):
            normal = geometry.normals[edge]
            for point in cfg.contact_points:
                contact = geometry.starts[edge] + (point + shift[0]) * (geometry.ends[edge] - geometry.starts[edge])
                start_local = contact + normal * (AGENT_RADIUS + cfg.standoff)
                for angle in cfg.push_angles_deg:
                    turn = math.radians(angle + shift[1])
                    c, s = math.cos(turn), math.sin(turn)
                    direction = -np.array([c * normal[0] - s * normal[1], s * normal[0] + c * normal[1]])
                    for length in cfg.push_lengths:
                        end_local = start_local + direction * (cfg.standoff + length * max_len)
                        start, end = transform(np.stack([start_local, end_local]), pose)
                        path = _approach_path(geometry, agent, start, pose)
                        clear = len(path) == 2 or _segment_clear(geometry, path[-2], start, pose, AGENT_RADIUS + 4.0)
                        approach = [np.clip(p, lo, hi) for p in _densify(path, speeds[0])]
                        push = [np.clip(p, lo, hi) for p in _densify([start, end], speeds[1])[1:]]
                        push += [push[-1]] * cfg.hold_steps
                        yield approach, push, clear


def _simulate(trial, geometry: TGeometry, targets: list[np.ndarray], threshold: float) -> tuple[float, int]:
    """Cost after running ``targets`` on ``trial`` (-1 and the steps used when it succeeds)."""
    for i, target in enumerate(targets):
        trial.step(target)
        pose = trial.block_pose
        # the exact coverage is only worth computing near the goal
        if pose_cost(pose) < 30.0 and geometry.coverage(pose) >= threshold:
            return -100.0, i + 1  # success beats any unfinished push, whatever their lengths
    return pose_cost(trial.block_pose), len(targets)


def _segment_clear(geometry: TGeometry, a: np.ndarray, b: np.ndarray, pose, clearance: float) -> bool:
    n = max(2, int(np.linalg.norm(b - a) / 6.0) + 1)
    ax, ay, bx, by = float(a[0]), float(a[1]), float(b[0]), float(b[1])
    return all(geometry.distance((ax + (bx - ax) * f, ay + (by - ay) * f), pose) >= clearance
               for f in np.linspace(0.0, 1.0, n).tolist())


def _approach_path(geometry: TGeometry, agent: np.ndarray, start: np.ndarray, pose) -> list[np.ndarray]:
    """Waypoints from the agent to a push start: straight when clear, else around the block on a safe circle."""
    if _segment_clear(geometry, agent, start, pose, AGENT_RADIUS + 4.0):
        return [agent, start]
    centre = geometry.centre(pose)
    radius = geometry.radius + AGENT_RADIUS + 10.0
    a0 = math.atan2(agent[1] - centre[1], agent[0] - centre[0])
    a1 = math.atan2(start[1] - centre[1], start[0] - centre[0])
    sweep = wrap_angle(a1 - a0)
    arc = [centre + radius * np.array([math.cos(a0 + sweep * f), math.sin(a0 + sweep * f)])
           for f in np.linspace(0.0, 1.0, max(2, int(abs(sweep) / 0.3) + 1))]
    return [agent, *arc, start]


def _densify(waypoints: list[np.ndarray], step: float) -> list[np.ndarray]:
    """Points every ``step`` world units along a polyline, ending exactly on its last waypoint."""
    out = [np.asarray(waypoints[0], dtype=np.float64)]
    carry = 0.0
    for a, b in zip(waypoints[:-1], waypoints[1:]):
        a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
        length = float(np.linalg.norm(b - a))
        pos = step - carry
        while pos <= length:
            out.append(a + (b - a) * (pos / length))
            pos += step
        carry = length - (pos - step)
    if np.linalg.norm(out[-1] - waypoints[-1]) > 1e-9:
        out.append(np.asarray(waypoints[-1], dtype=np.float64))
    return out[1:] if len(out) > 1 else out


def collect_episode(env, seed: int, expert: PushTExpert, max_steps: int | None = None) -> dict:
    """Run the expert for one seeded episode; returns obs/actions/states/rewards/dones and ``success``."""
    base = env.unwrapped
    max_steps = max_steps or base.task_spec.max_episode_steps
    obs, info = env.reset(seed=seed)
    expert.reset()
    frames: dict[str, list] = {k: [] for k in obs}
    actions, states, rewards, dones = [], [], [], []
    success = False
    for _ in range(max_steps):
        for k, v in obs.items():
            frames[k].append(v)
        states.append(base.get_state())
        action = expert.act(env)
        obs, reward, terminated, truncated, info = env.step(action)
        actions.append(action)
        rewards.append(reward)
        success = bool(info["is_success"])
        dones.append(terminated or truncated)
        if terminated or truncated:
            break
    dones[-1] = True
    return {
        "obs": {k: np.stack(v) for k, v in frames.items()},
        "actions": np.asarray(actions, dtype=np.float32),
        "states": np.asarray(states, dtype=np.float64),
        "rewards": np.asarray(rewards, dtype=np.float32),
        "dones": np.asarray(dones, dtype=np.uint8),
        "success": success,
        "seed": seed,
    }


def _expert_episode(seed: int, attempt: int, image_size: int | None, env_options: dict) -> dict:
    """Attempt ``attempt`` of ``generate_demos``: env seed ``seed + attempt``, expert seeded by (seed, attempt)."""
    env = make_pusht(image_size=image_size, **env_options)
    try:
        return collect_episode(env, seed + attempt, PushTExpert(seed=[seed, attempt]))
    finally:
        env.close()


def generate_demos(num_episodes: int, seed: int = 0, image_size: int | None = None, only_successes: bool = True,
                   max_attempts_factor: int = 2, workers: int = 1, progress: bool = False,
                   finish_threshold: float | None = None, task: str = "PushT",
                   **env_options) -> tuple[list[dict], dict]:
    """``num_episodes`` expert demos of ``task`` (PushT or PushTStandard) on seeds seed, seed+1, ...; returns
    (episodes, env_args).

    With ``only_successes`` failed episodes are dropped and further seeds are tried (up to
    ``max_attempts_factor * num_episodes`` in all). ``workers > 1`` plans the episodes in that many processes;
    the result is the same as with one (each attempt is seeded on its own and kept in seed order).
    ``progress`` shows a progress bar of the episodes kept.

    ``finish_threshold`` (at least the task's success threshold, at most 1): the expert keeps pushing until the
    coverage reaches it, and each demonstration ends there instead of at the task's threshold. An expert that
    stops the moment the threshold is crossed teaches a regression policy to bring the block *to about* the
    threshold, so its rollouts end just above or just below it; demonstrations that finish with a margin put the
    imitated end state past it (docs/training.md, "Where the demonstrations end"). The file still records the
    task's own threshold, so evaluation is unchanged.

    ``env_args`` is what ``jepa_envs.datasets.hdf5.write_dataset`` stores.
    """
    if num_episodes < 1:
        raise ValueError(f"num_episodes must be >= 1, got {num_episodes}")
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    env_options = {"task": task, **env_options}
    env = make_pusht(image_size=image_size, **env_options)  # validates the options and gives the effective spec
    if isinstance(env, PushTEnv):   # the effective difficulty fields, so the file alone rebuilds the same env
        env_kwargs = {"image_size": env.task_spec.image_size, **asdict(env.difficulty)}
    else:
        env_kwargs = {"image_size": env.task_spec.image_size,
                      **{k: v for k, v in env_options.items() if k not in ("task", "success_threshold")}}
    threshold, name = env.success_threshold, env.task_spec.name
    env.close()
    if finish_threshold is None:
        finish_threshold = threshold
    elif not threshold <= finish_threshold <= 1.0:
        raise ValueError(f"finish_threshold must lie between the task's success threshold ({threshold}) and 1, "
                         f"got {finish_threshold}; demonstrations that stop short of the threshold are not successes")
    # the collection env ends an episode at the finish threshold; the recorded env_kwargs keep the task's
    env_options = {**env_options, "success_threshold": float(finish_threshold)}
    max_attempts = max_attempts_factor * num_episodes
    episodes, attempts = [], 0
    with contextlib.ExitStack() as stack:
        if workers == 1:
            results = (_expert_episode(seed, a, image_size, env_options) for a in range(max_attempts))
        else:
            pool = stack.enter_context(ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")))
            stack.callback(pool.shutdown, cancel_futures=True)
            results = pool.map(_expert_episode, itertools.repeat(seed), range(max_attempts),
                               itertools.repeat(image_size), itertools.repeat(env_options))
        bar = stack.enter_context(tqdm(total=num_episodes, desc="PushT demos", unit="demo", disable=not progress))
        for ep in results:
            attempts += 1
            if ep["success"] or not only_successes:
                episodes.append(ep)
                bar.update()
            if len(episodes) == num_episodes:
                break
    if len(episodes) < num_episodes:
        raise RuntimeError(f"the PushT expert reached coverage {finish_threshold} in only {len(episodes)} of "
                           f"{attempts} episodes; use an easier difficulty, a lower finish_threshold or "
                           "only_successes=False")
    return episodes, {"env_name": name, "type": "jepa_envs", "env_kwargs": env_kwargs,
                      "expert": {"seed": seed, "attempts": attempts, "finish_threshold": float(finish_threshold)}}
