"""Scripted experts for robomimic's Lift and Can (``JEPA/Lift-v0``, ``JEPA/Can-v0``) and the demonstrations they
record.

The expert reads the object's true pose from the simulator (the policy later sees only images and
proprioception) and drives the env through its public action: the absolute grip-site pose, ``[position (3),
6-D rotation (6), gripper (1)]``, which the env hands to robosuite's OSC_POSE controller with absolute input.
That controller takes its goal as given, so a far goal would be a jump: the expert moves a *commanded* pose
toward its current waypoint at a bounded speed, and a waypoint counts as reached once the grip site is within
its tolerance. The gripper points down; its yaw is aligned to the cube's faces for Lift (the open fingers clear
the 4.2 cm cube by a few millimetres a side, too little for a corner first), and free for Can's round can.

Each task is a short script of phases (approach, descend, close, lift; Can also carries, lowers, opens and
retreats). Every phase reads the live object pose, and a grasp that missed or slipped sends the expert back to
the approach, so a bump costs time rather than the episode. Success is robosuite's own ``_check_success()``.

What varies per episode, drawn from a numpy Generator seeded per attempt (``generate_demos``): the object's
placement (robosuite's own placement sampler, seeded by the episode seed through ``env.reset(seed=...)``), a
random via point on every long move, the speeds, approach and grasp heights, pauses before and after the grasp,
Can's yaw, lift and carry heights and its drop point in the target compartment, and how many steps the
recording goes on once success holds.
"""
from __future__ import annotations

import collections
import contextlib
import math
import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from typing import Callable, Iterator

import gymnasium as gym
import numpy as np
from tqdm import tqdm

from jepa_envs.tasks import abs_actions, rotations
from jepa_envs.tasks.robomimic_env import robomimic_env_args
from jepa_envs.tasks.robosuite_common import RobosuiteTaskEnv
from jepa_envs.tasks.spec import TaskSpec, get_task_spec

EXPERT_TASKS = ("Lift", "Can")
# The grip site pointing straight down with the fingers closing along world y: robosuite's own default
# orientation for OSC without orientation input, and about the Panda's pose after a reset.
TOP_DOWN = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
GRIPPER_OPEN, GRIPPER_CLOSED = -1.0, 1.0
TURN_SPEED = 0.08           # radians per step the commanded orientation turns at most
SETTLE_STEPS = 20           # steps a reached command waits for the arm before its waypoint is given up on
MISSED_GRASP_OPENING = 0.01  # finger gap (m) below which a closed gripper holds nothing
# PickPlace's bins: floors' top at z = 0.82, walls up to z = 0.90 (robosuite's bins_arena.xml)
BIN_FLOOR_Z, BIN_WALL_TOP_Z = 0.82, 0.90
CAN_HALF_HEIGHT = 0.04     # robosuite's can mesh: 8 cm tall, 2.5 cm in radius, about its body origin


def top_down(yaw: float) -> np.ndarray:
    """The downward grip-site orientation turned by ``yaw`` about world z; the fingers close along
    ``(-sin yaw, cos yaw, 0)``."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ TOP_DOWN


def face_aligned_yaw(object_matrix: np.ndarray) -> float:
    """The yaw in [-pi/4, pi/4) that closes the fingers square onto a box's vertical faces (the turn from the
    reset pose is at most 45 degrees)."""
    yaw = math.atan2(object_matrix[1, 0], object_matrix[0, 0])
    return (yaw + math.pi / 4) % (math.pi / 2) - math.pi / 4


@dataclass(frozen=True)
class Waypoint:
    """A grip-site target the commanded pose moves to in a straight line."""

    position: np.ndarray
    yaw: float
    gripper: float          # -1 open, +1 closed
    speed: float            # metres per control step the command moves
    tolerance: float = 0.01  # how close the grip site must come before the next waypoint
    pause: int = 0          # steps held once reached


class RobosuiteExpert:
    """Moves a commanded grip-site pose through the waypoints of its task's phases; ``act(env)`` once per step.

    A subclass names its phases in ``PHASES`` and gives each a method ``_<phase>(base) -> list[Waypoint]``
    planned from the live simulator state when the phase starts; ``_lost(base)`` says whether the object
    slipped out of the plan, which restarts it at ``PHASES[0]``."""

    PHASES: tuple[str, ...] = ()
    TASK = ""

    def __init__(self, seed=None):
        self.rng = np.random.default_rng(seed)
        # steps the recording goes on after success is reached and held (the policy learns to finish)
        self.finish_steps = int(self.rng.integers(5, 11))
        self.retries = 0
        self._phase = -1
        self._queue: list[Waypoint] = []

    def reset(self, env) -> None:
        """Start a new episode from the env's state just after its reset."""
        base = self._base(env)
        pos, mats = base.controller_pose()
        self.cmd_pos, self.cmd_rot = pos[0].copy(), mats[0].copy()
        self.retries = 0
        self._phase = -1
        self._queue = []

    def _base(self, env) -> RobosuiteTaskEnv:
        base = env.unwrapped
        if not isinstance(base, RobosuiteTaskEnv) or base.task_spec.name != self.TASK:
            raise TypeError(f"{type(self).__name__} drives JEPA/{self.TASK}-v0, got {base.task_spec.name}")
        if base.action_mode != "abs":
            raise ValueError(f"{type(self).__name__} acts in absolute mode; make the env with action_mode='abs'")
        return base

    @property
    def phase(self) -> str:
        return self.PHASES[self._phase] if self._phase >= 0 else "start"

    def act(self, env) -> np.ndarray:
        """The next absolute action (float32, 10) for the env's current state.

        A waypoint ends ``pause`` steps after the grip site comes within its tolerance, or ``SETTLE_STEPS`` steps
        after the command reached it if the grip site does not come (the arm sags near the edge of its reach, or
        the object is in the way)."""
        base = self._base(env)
        if self._phase >= 0 and self._lost(base):
            self.retries += 1
            self._phase, self._queue = -1, []
        while not self._queue:
            self._phase = (self._phase + 1) % len(self.PHASES)
            self._queue = getattr(self, f"_{self.phase}")(base)
            self._waited = self._held = 0
        waypoint = self._queue[0]
        if self._move_command(waypoint):
            self._waited += 1
            if self._held or np.linalg.norm(self._grip_pos(base) - waypoint.position) <= waypoint.tolerance:
                self._held += 1
            if self._held > waypoint.pause or (not self._held and self._waited > SETTLE_STEPS):
                self._queue.pop(0)
                self._waited = self._held = 0
        return abs_actions.pose_to_abs(self.cmd_pos[None], self.cmd_rot[None],
                                       np.array([waypoint.gripper])).astype(np.float32)

    def _move_command(self, waypoint: Waypoint) -> bool:
        """Move the commanded pose one step toward ``waypoint``; whether it is there."""
        delta = waypoint.position - self.cmd_pos
        dist = float(np.linalg.norm(delta))
        self.cmd_pos = (np.array(waypoint.position, dtype=np.float64) if dist <= waypoint.speed
                        else self.cmd_pos + delta * (waypoint.speed / dist))
        target = top_down(waypoint.yaw)
        turn = rotations.matrix_to_axis_angle(self.cmd_rot.T @ target)
        angle = float(np.linalg.norm(turn))
        self.cmd_rot = (target if angle <= TURN_SPEED
                        else self.cmd_rot @ rotations.axis_angle_to_matrix(turn * (TURN_SPEED / angle)))
        return dist <= waypoint.speed and angle <= TURN_SPEED

    # ---- what the phases share ------------------------------------------------------------------------
    def _grip_pos(self, base) -> np.ndarray:
        return base.controller_pose()[0][0]

    def _finger_gap(self, base) -> float:
        robot = base.backend.robots[0]
        left, right = base.backend.sim.data.qpos[robot._ref_gripper_joint_pos_indexes]
        return float(left - right)

    def _uniform(self, low: float, high: float) -> float:
        return float(self.rng.uniform(low, high))

    def _via(self, start: np.ndarray, end: np.ndarray, spread: float, lift: float, min_z: float) -> np.ndarray:
        """A random point near the middle of a move: the paths differ from episode to episode."""
        mid = (start + end) / 2 + np.array([self._uniform(-spread, spread), self._uniform(-spread, spread),
                                            self._uniform(0.0, lift)])
        mid[2] = max(mid[2], min_z)
        return mid

    def _regrasp(self) -> list[Waypoint]:
        """After a grasp that holds nothing: open and rise; the approach that follows re-reads the object."""
        self.retries += 1
        self._phase = -1
        up = self.cmd_pos + np.array([0.0, 0.0, 0.06])
        return [Waypoint(self.cmd_pos.copy(), self.yaw, GRIPPER_OPEN, 0.01, tolerance=1.0, pause=6),
                Waypoint(up, self.yaw, GRIPPER_OPEN, 0.012, tolerance=0.02)]

    def _lost(self, base) -> bool:
        return False


class LiftExpert(RobosuiteExpert):
    """Lift: above the cube, down to it with the fingers square to its faces, close, lift."""

    TASK = "Lift"
    PHASES = ("approach", "descend", "close", "lift")

    def _cube(self, base) -> tuple[np.ndarray, np.ndarray]:
        sim, body = base.backend.sim, base.backend.cube_body_id
        return np.array(sim.data.body_xpos[body]), np.array(sim.data.body_xmat[body]).reshape(3, 3)

    def _approach(self, base) -> list[Waypoint]:
        cube, mat = self._cube(base)
        self.yaw = face_aligned_yaw(mat)
        start = self._grip_pos(base)
        above = cube + np.array([0.0, 0.0, self._uniform(0.05, 0.10)])
        speed = self._uniform(0.012, 0.022)
        via = self._via(start, above, spread=0.04, lift=0.04, min_z=above[2])
        return [Waypoint(via, self.yaw, GRIPPER_OPEN, speed, tolerance=0.03),
                Waypoint(above, self.yaw, GRIPPER_OPEN, speed, tolerance=0.006, pause=int(self.rng.integers(0, 4)))]

    def _descend(self, base) -> list[Waypoint]:
        cube, _ = self._cube(base)
        # the finger pads reach about 2 cm below the grip site; the cube's centre is about 2.1 cm above the table
        grasp = cube + np.array([0.0, 0.0, self._uniform(0.004, 0.012)])
        return [Waypoint(grasp, self.yaw, GRIPPER_OPEN, self._uniform(0.006, 0.012), tolerance=0.006,
                         pause=int(self.rng.integers(0, 3)))]

    def _close(self, base) -> list[Waypoint]:
        return [Waypoint(self.cmd_pos.copy(), self.yaw, GRIPPER_CLOSED, 0.01, tolerance=1.0,
                         pause=int(self.rng.integers(8, 14)))]

    def _lift(self, base) -> list[Waypoint]:
        if self._finger_gap(base) < MISSED_GRASP_OPENING:
            return self._regrasp()
        top = self.cmd_pos + np.array([self._uniform(-0.02, 0.02), self._uniform(-0.02, 0.02),
                                       self._uniform(0.08, 0.16)])
        # held until the recording stops
        return [Waypoint(top, self.yaw, GRIPPER_CLOSED, self._uniform(0.008, 0.016), tolerance=0.01, pause=10**6)]

    def _lost(self, base) -> bool:
        if self.phase != "lift":
            return False
        cube, _ = self._cube(base)
        return bool(np.linalg.norm(cube - self._grip_pos(base)) > 0.05)


class CanExpert(RobosuiteExpert):
    """Can: grasp the can in the left bin, carry it over the right bin, lower it into its compartment (robosuite's
    ``target_bin_placements``), open, retreat (success needs the grip site clear of the can)."""

    TASK = "Can"
    PHASES = ("approach", "descend", "close", "lift", "carry", "lower", "release", "retreat")

    def _can(self, base) -> np.ndarray:
        backend = base.backend
        return np.array(backend.sim.data.body_xpos[backend.obj_body_id[backend.obj_to_use]])

    def _target(self, base) -> np.ndarray:
        backend = base.backend
        return np.array(backend.target_bin_placements[backend.object_id])

    def _approach(self, base) -> list[Waypoint]:
        self.yaw = self._uniform(-0.35, 0.35)
        self.carry_z = self._uniform(1.02, 1.08)
        can = self._can(base)
        start = self._grip_pos(base)
        speed = self._uniform(0.012, 0.022)
        path = []
        if start[2] < BIN_WALL_TOP_Z + 0.06:   # a retry from inside a bin: straight up first
            path.append(Waypoint(np.array([start[0], start[1], self.carry_z]), self.yaw, GRIPPER_OPEN, speed,
                                 tolerance=0.03))
            start = path[-1].position
        above = can + np.array([0.0, 0.0, CAN_HALF_HEIGHT + self._uniform(0.04, 0.08)])
        via = self._via(start, above, spread=0.04, lift=0.04, min_z=above[2])
        return path + [Waypoint(via, self.yaw, GRIPPER_OPEN, speed, tolerance=0.03),
                       Waypoint(above, self.yaw, GRIPPER_OPEN, speed, tolerance=0.008,
                                pause=int(self.rng.integers(0, 4)))]

    def _descend(self, base) -> list[Waypoint]:
        # the palm meets the can's top when the grip site is about 4 mm above the can's origin: grasp higher
        self.grasp_offset = self._uniform(0.012, 0.028)
        grasp = self._can(base) + np.array([0.0, 0.0, self.grasp_offset])
        return [Waypoint(grasp, self.yaw, GRIPPER_OPEN, self._uniform(0.006, 0.012), tolerance=0.006,
                         pause=int(self.rng.integers(0, 3)))]

    def _close(self, base) -> list[Waypoint]:
        return [Waypoint(self.cmd_pos.copy(), self.yaw, GRIPPER_CLOSED, 0.01, tolerance=1.0,
                         pause=int(self.rng.integers(8, 14)))]

    def _lift(self, base) -> list[Waypoint]:
        if self._finger_gap(base) < MISSED_GRASP_OPENING:
            return self._regrasp()
        up = np.array([self.cmd_pos[0], self.cmd_pos[1], self.carry_z])
        return [Waypoint(up, self.yaw, GRIPPER_CLOSED, self._uniform(0.01, 0.018), tolerance=0.03)]

    def _carry(self, base) -> list[Waypoint]:
        # in the corner of the compartment nearest the robot, clear of the divider and the near wall: the
        # compartment's centre lies at the edge of the Panda's reach, where the arm sags 3 cm short of its goal
        target = self._target(base)
        self.drop_xy = target[:2] + np.array([self._uniform(-0.065, -0.025), self._uniform(-0.07, -0.03)])
        over = np.array([*self.drop_xy, self.carry_z])
        speed = self._uniform(0.012, 0.02)
        via = self._via(self.cmd_pos, over, spread=0.05, lift=0.03, min_z=self.carry_z)
        return [Waypoint(via, self.yaw, GRIPPER_CLOSED, speed, tolerance=0.04),
                Waypoint(over, self.yaw, GRIPPER_CLOSED, speed, tolerance=0.025, pause=int(self.rng.integers(0, 3)))]

    def _lower(self, base) -> list[Waypoint]:
        # the can's bottom 3-6 cm above the compartment's floor
        z = BIN_FLOOR_Z + CAN_HALF_HEIGHT + self.grasp_offset + self._uniform(0.03, 0.06)
        return [Waypoint(np.array([*self.drop_xy, z]), self.yaw, GRIPPER_CLOSED, self._uniform(0.008, 0.014),
                         tolerance=0.02)]

    def _release(self, base) -> list[Waypoint]:
        return [Waypoint(self.cmd_pos.copy(), self.yaw, GRIPPER_OPEN, 0.01, tolerance=1.0,
                         pause=int(self.rng.integers(4, 9)))]

    def _retreat(self, base) -> list[Waypoint]:
        up = self.cmd_pos + np.array([0.0, 0.0, self._uniform(0.08, 0.14)])
        return [Waypoint(up, self.yaw, GRIPPER_OPEN, self._uniform(0.01, 0.016), tolerance=0.02, pause=10**6)]

    def _lost(self, base) -> bool:
        if self.phase not in ("lift", "carry", "lower"):
            return False
        return bool(np.linalg.norm(self._can(base) - self._grip_pos(base)) > 0.06)


EXPERTS = {"Lift": LiftExpert, "Can": CanExpert}


def expert_for(task: str, seed=None) -> RobosuiteExpert:
    """The scripted expert of ``task`` (Lift or Can), its random draws seeded by ``seed``."""
    if task not in EXPERTS:
        raise ValueError(f"no scripted robosuite expert for {task!r}; there are experts for {', '.join(EXPERTS)}")
    return EXPERTS[task](seed=seed)


def collect_episode(env, seed: int, expert: RobosuiteExpert, images: bool = True) -> dict:
    """Run ``expert`` for one episode from ``env.reset(seed=seed)``.

    The recording stops ``expert.finish_steps`` steps after success is reached and held, or at the time limit.
    Returns ``obs`` (every key of the observation; without the camera frames when ``images`` is False: none is
    rendered then), ``actions``, ``states`` (MuJoCo's flattened state before each action, as robomimic stores
    them), ``rewards``, ``dones``, ``success`` (the task's ``_check_success()`` at the last step) and ``seed``.
    """
    base = env.unwrapped
    base.set_render_images(images)
    obs, info = env.reset(seed=seed)
    expert.reset(env)
    keys = [k for k in obs if images or k not in base.task_spec.image_keys]
    frames: dict[str, list] = {k: [] for k in keys}
    actions, states, rewards, dones = [], [], [], []
    held = 0
    for _ in range(base.task_spec.max_episode_steps):
        for k in keys:
            frames[k].append(obs[k])
        states.append(base.backend.sim.get_state().flatten())
        action = expert.act(env)
        obs, reward, terminated, truncated, info = env.step(action)
        actions.append(action)
        rewards.append(reward)
        dones.append(terminated or truncated)
        held = held + 1 if info["is_success"] else 0
        if held >= expert.finish_steps or truncated:
            break
    dones[-1] = True
    return {
        "obs": {k: np.stack(v) for k, v in frames.items()},
        "actions": np.asarray(actions, dtype=np.float32),
        "states": np.asarray(states, dtype=np.float64),
        "rewards": np.asarray(rewards, dtype=np.float32),
        "dones": np.asarray(dones, dtype=np.uint8),
        "success": bool(info["is_success"]),
        "seed": seed,
        "attrs": {"seed": seed, "expert_retries": expert.retries},
    }


class EpisodeRecorder:
    """One env of ``task`` (building one takes seconds) recording attempts one after another. Attempt ``a`` of a
    run seeded ``seed`` resets the env with seed ``seed + a`` and seeds the expert with ``[seed, a]``; a seeded
    reset does not depend on the episodes before it, so which process records an attempt does not matter."""

    def __init__(self, task: str, image_size: int | None = None, images: bool = True, reflections: bool = True):
        self.task, self.images = task, images
        self.env = gym.make(get_task_spec(task).env_id, image_size=image_size, reflections=reflections)

    def __call__(self, seed: int, attempt: int) -> dict:
        return collect_episode(self.env, seed + attempt, expert_for(self.task, seed=[seed, attempt]), self.images)

    def close(self) -> None:
        self.env.close()


_WORKER: dict[str, EpisodeRecorder] = {}


def _start_worker(task: str, image_size: int | None, images: bool, render_threads: int,
                  reflections: bool = True) -> None:
    # Mesa's llvmpipe starts one render thread per core in every process; the workers share the cores, so each
    # gets its share unless the user chose (as the rollout pool does; its frames are the same for any count)
    os.environ.setdefault("LP_NUM_THREADS", str(render_threads))
    _WORKER["recorder"] = EpisodeRecorder(task, image_size, images, reflections)


def _record_in_worker(seed: int, attempt: int) -> dict:
    return _WORKER["recorder"](seed, attempt)


def _in_order(pool: ProcessPoolExecutor, seed: int, max_attempts: int, depth: int,
              missing: Callable[[], int]) -> Iterator[dict]:
    """Attempts 0, 1, ... recorded by ``pool``, yielded in order. At most ``depth`` are in flight and never more
    than ``missing()`` episodes, so while the expert succeeds no attempt is recorded only to be thrown away (an
    episode takes seconds to tens of seconds, and a pool's shutdown waits for the ones running)."""
    pending: collections.deque = collections.deque()
    attempt = 0
    while True:
        while attempt < max_attempts and len(pending) < min(depth, missing()):
            pending.append(pool.submit(_record_in_worker, seed, attempt))
            attempt += 1
        if not pending:
            return
        yield pending.popleft().result()


def demo_env_args(spec: TaskSpec, image_size: int) -> dict:
    """robomimic's env_args of the task (absolute OSC_POSE input: the recorded actions are absolute poses)."""
    return robomimic_env_args(spec.source_task, spec.cameras, image_size, control_delta=False)


def generate_demos(task: str, num_episodes: int, seed: int = 0, image_size: int | None = None, images: bool = True,
                   only_successes: bool = True, max_attempts_factor: int = 2, workers: int = 1,
                   progress: bool = False, reflections: bool = True) -> tuple[list[dict], dict]:
    """``num_episodes`` scripted-expert demos of Lift or Can on seeds seed, seed+1, ...; returns (episodes,
    env_args) for ``jepa_envs.datasets.hdf5.write_dataset``.

    With ``only_successes`` failed attempts are dropped (and counted) and further seeds are tried, up to
    ``max_attempts_factor * num_episodes`` in all. ``workers > 1`` records in that many processes, one env each;
    the episodes are the same as with one. ``images=False`` renders no camera (about ten times faster): the
    episodes hold states, actions and low-dim observations only, and ``jepa-envs render-dataset`` renders their
    frames later; the expert reads the simulator, so its actions are the same either way. ``env_args`` are
    robomimic's for the task with the expert's record under ``"expert"``: seed, attempts, successes and the seeds
    of the failed attempts. ``reflections=False`` renders without the table's reflection (4.5x faster software
    frames, docs/envs_simulation.md); the setting is recorded in ``env_args["render"]``, so the env a policy is
    evaluated in (and render-dataset) draws the same frames.
    """
    spec = get_task_spec(task)
    if task not in EXPERTS:
        raise ValueError(f"no scripted robosuite expert for {task!r}; there are experts for {', '.join(EXPERTS)}")
    if num_episodes < 1:
        raise ValueError(f"num_episodes must be >= 1, got {num_episodes}")
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    size = int(image_size or spec.image_size)
    if size < 8:
        raise ValueError(f"image_size must be >= 8 pixels, got {size}")
    max_attempts = max_attempts_factor * num_episodes
    episodes, attempts, failed = [], 0, []
    with contextlib.ExitStack() as stack:
        if workers == 1:
            recorder = EpisodeRecorder(task, size, images, reflections)
            stack.callback(recorder.close)
            results = (recorder(seed, a) for a in range(max_attempts))
        else:
            pool = stack.enter_context(ProcessPoolExecutor(
                workers, mp_context=multiprocessing.get_context("spawn"), initializer=_start_worker,
                initargs=(task, size, images, max(1, (os.cpu_count() or 1) // workers), reflections)))
            stack.callback(pool.shutdown, cancel_futures=True)
            results = _in_order(pool, seed, max_attempts, 2 * workers, lambda: num_episodes - len(episodes))
        bar = stack.enter_context(tqdm(total=num_episodes, desc=f"{task} demos", unit="demo", disable=not progress))
        for ep in results:
            attempts += 1
            if not ep["success"]:
                failed.append(ep["seed"])
            if ep["success"] or not only_successes:
                episodes.append(ep)
                bar.update()
            if len(episodes) == num_episodes:
                break
    if len(episodes) < num_episodes:
        raise RuntimeError(f"the {task} expert succeeded in only {attempts - len(failed)} of {attempts} attempts "
                           f"(failed seeds {failed[:20]}); ask for fewer episodes or pass only_successes=False")
    env_args = demo_env_args(spec, size)
    if not reflections:
        env_args["render"] = {"reflections": False}
    env_args["expert"] = {"seed": seed, "attempts": attempts, "successes": attempts - len(failed),
                          "failed_seeds": failed, "images": images}
    return episodes, env_args
