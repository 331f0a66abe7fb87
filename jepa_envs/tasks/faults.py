"""Faults with a known onset: Gymnasium wrappers that change an episode from one env step on, for measuring
runtime failure monitors (which signal notices, how soon after the onset, and which stays quiet when the change is
harmless).

The onset contract, the same for every fault: with onset s, the first s env steps and the frames 0..s are
untouched; the fault acts from the (s+1)-th call to ``step`` on, so frame s+1 (the observation that call returns)
is the first one it can show. ``info["fault"]`` names the fault and ``info["fault_onset"]`` gives s on every reset
and step; ``info["fault_active"]`` says whether it has begun. ``onset`` is a step or a (low, high) range drawn per
episode. Everything random (the onset in a range, the displacement's direction, the noise, the distractors'
places) is drawn from the reset seed, so the same seed gives the same episode; a reset without a seed draws one
from the env's own generator.

One wrapper per fault (``FAULTS`` lists them with their kind):

- physical: ``BlockDisplaced`` (the PushT block moved and turned at the onset);
- dynamics: ``BlockFriction`` (the block's contact friction scaled), ``BlockSlides`` (the table no longer stops
  the block: it slides on after a push; its mass would change nothing in this quasi-static simulation),
  ``WeakActuator`` (the agent's PD gains scaled, halved by default);
- actuation: ``ActionLatency`` (each action executed n steps late), ``ActionNoise`` (Gaussian noise on actions);
- visual: ``Distractors`` (coloured shapes drawn on the camera images), ``ColourShift`` (brightness and per-channel
  gain), ``CameraShift`` (the image translated by a few pixels);
- benign: ``BackgroundTint`` (the table's background recoloured slightly; the objects and the goal untouched)
  and ``SensorNoise`` (Gaussian pixel noise, a few levels of 255), shifts meant not to cause failure (whether
  they do is measured: docs/failure_prediction.md).

Lift and Can (robosuite) have their own physical, dynamics and visual faults, changes of the simulation itself:
``ObjectDisplaced`` (the cube or can moved away at the onset, out of the gripper if it held it),
``GripperSlip`` (the gripper's finger force limit scaled down, so a held object slips) and ``LightDimmed`` (the
scene's lights dimmed: rendered so, not painted on the image). Their model edits are undone at the next reset
(robosuite keeps its model across resets here). The actuation, image and benign faults apply to every task but
``ActionNoise``, whose noise is in PushT's world units; ``faults_for(spec)`` lists a task's faults.

``jepa_envs.tasks.fault_replay`` applies the image faults to recorded frames exactly as to a live episode's.

``gym.make(FAULTED_ID, base="JEPA/PushT-v0", fault="block_displaced", fault_kwargs={...}, **env_kwargs)`` builds
the base env and wraps it (``make_faulted``); the id's module is imported by its name, so rollout workers that
only know the string (``jepa_envs.rollouts.pool``) can build it too.
"""
from __future__ import annotations

import math
import zlib
from collections import deque
from dataclasses import dataclass

import gymnasium as gym
import numpy as np

from jepa_envs.tasks.pusht import AGENT_RADIUS, COLORS, T_RADIUS, WORLD_SIZE, PushTEnv

KINDS = ("physical", "dynamics", "actuation", "visual", "benign")
DEFAULT_ONSET = 30   # env steps: after the third decision of a policy that replans every 8 steps


class FaultWrapper(gym.Wrapper):
    """The onset bookkeeping and the per-episode generator every fault shares; subclasses set ``name`` and
    ``kind`` and override ``begin`` (called once, right before the onset step's action is applied),
    ``action`` (actions from the onset on) and/or ``image`` (camera images of frames after the onset)."""

    name = "fault"
    kind = "physical"
    salt = 0   # separates the generators of different faults under one seed
    suites: tuple[str, ...] | None = None   # the task suites it applies to (None: every task)
    sources: tuple[str, ...] | None = None  # and within them, these backend tasks only (None: all)

    def __init__(self, env: gym.Env, onset: int | tuple[int, int] | list[int] = DEFAULT_ONSET):
        super().__init__(env)
        if isinstance(onset, (tuple, list)):
            lo, hi = (int(v) for v in onset)
            if not 0 <= lo <= hi:
                raise ValueError(f"an onset range needs 0 <= low <= high env steps, got {onset}")
            self.onset_range = (lo, hi)
        else:
            if int(onset) < 0:
                raise ValueError(f"onset must be >= 0 env steps, got {onset}")
            self.onset_range = (int(onset), int(onset))
        self.onset = self.onset_range[0]
        self.t = 0
        self.seed = 0
        self.rng = np.random.default_rng(0)

    @property
    def active(self) -> bool:
        """Whether the fault has begun (the onset step's action was applied)."""
        return self.t > self.onset

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is None:
            seed = int(self.env.unwrapped.np_random.integers(2**31)) if hasattr(self.env.unwrapped, "np_random") \
                else int(np.random.SeedSequence().entropy % 2**31)
        self.seed = int(seed)
        self.rng = np.random.default_rng([int(seed), self.salt, 0x6A6570])
        lo, hi = self.onset_range
        self.onset = int(self.rng.integers(lo, hi + 1))
        self.t = 0
        self.start_episode()
        obs, info = self.env.reset(seed=seed, options=options)
        return obs, self._tag(info)

    def step(self, action):
        if self.t == self.onset:
            self.begin()
        if self.t >= self.onset:
            action = self.action(np.asarray(action))
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.t += 1
        if self.active:
            obs = self._images(obs)
        return obs, reward, terminated, truncated, self._tag(info)

    def _tag(self, info: dict) -> dict:
        info["fault"], info["fault_onset"], info["fault_active"] = self.name, self.onset, self.active
        return info

    def _images(self, obs: dict) -> dict:
        base = self.env.unwrapped
        if not getattr(base, "render_images", True):   # frames nobody looks at stay blank (RenderOnDemand)
            return obs
        keys = base.task_spec.image_keys
        return {k: (self.image(np.asarray(v), k) if k in keys else v) for k, v in obs.items()}

    # what a fault changes; by default nothing
    def start_episode(self) -> None:
        """Per-episode set-up after the generator is seeded, before the env resets."""

    def begin(self) -> None:
        """The onset: change the simulation (physical and dynamics faults)."""

    def action(self, action: np.ndarray) -> np.ndarray:
        return action

    def image(self, image: np.ndarray, key: str) -> np.ndarray:
        return image


def _pusht(env: gym.Env, fault: str) -> PushTEnv:
    base = env.unwrapped
    if not isinstance(base, PushTEnv):
        raise ValueError(f"the {fault} fault changes PushT's simulation and needs JEPA/PushT-v0, not "
                         f"{type(base).__name__}; use an actuation or visual fault on other tasks")
    return base


# ----------------------------------------------------------------------------- physical

class BlockDisplaced(FaultWrapper):
    """The block moved by ``distance`` world units in a random direction and turned by ``turn_deg`` (random sign)
    at the onset, kept on the table and clear of the agent (the direction is redrawn until it is)."""

    name, kind, salt = "block_displaced", "physical", 1
    suites = ("embedded",)

    def __init__(self, env, onset=DEFAULT_ONSET, distance: float = 60.0, turn_deg: float = 40.0):
        super().__init__(env, onset)
        _pusht(env, self.name)
        if distance < 0 or not 0 <= turn_deg <= 180:
            raise ValueError(f"need distance >= 0 and 0 <= turn_deg <= 180, got {distance}, {turn_deg}")
        self.distance, self.turn = float(distance), math.radians(turn_deg)

    def begin(self) -> None:
        sim = self.env.unwrapped.backend
        ax, ay, bx, by, angle = sim.get_state()
        margin = T_RADIUS + 10
        turn = self.turn * self.rng.choice([-1.0, 1.0])
        for _ in range(64):
            phi = self.rng.uniform(-math.pi, math.pi)
            x = min(max(bx + self.distance * math.cos(phi), margin), WORLD_SIZE - margin)
            y = min(max(by + self.distance * math.sin(phi), margin), WORLD_SIZE - margin)
            if math.hypot(x - ax, y - ay) > T_RADIUS + AGENT_RADIUS:
                break
        sim.set_state((ax, ay, x, y, angle + turn))


# ----------------------------------------------------------------------------- dynamics

class BlockFriction(FaultWrapper):
    """The block's contact friction multiplied by ``factor`` (0.1: a slippery block that turns away)."""

    name, kind, salt = "block_friction", "dynamics", 2
    suites = ("embedded",)

    def __init__(self, env, onset=DEFAULT_ONSET, factor: float = 0.1):
        super().__init__(env, onset)
        _pusht(env, self.name)
        if factor < 0:
            raise ValueError(f"friction factor must be >= 0, got {factor}")
        self.factor = float(factor)

    def begin(self) -> None:
        for shape in self.env.unwrapped.backend.block.shapes:
            shape.friction *= self.factor


class BlockSlides(FaultWrapper):
    """The table stops holding the block: a ``keep`` fraction of its velocity survives each second (pymunk's
    damping; 0 in the task, where the block moves only while pushed), so a pushed block slides on. A heavier or
    lighter block would change nothing here: the agent is kinematic and the block quasi-static (measured:
    trajectories equal to 1e-11 with the mass x100), so this is the task's dynamics fault of the block."""

    name, kind, salt = "block_slides", "dynamics", 3
    suites = ("embedded",)

    def __init__(self, env, onset=DEFAULT_ONSET, keep: float = 0.05):
        super().__init__(env, onset)
        _pusht(env, self.name)
        if not 0 < keep < 1:
            raise ValueError(f"keep must lie in (0, 1) (velocity kept per second), got {keep}")
        self.keep = float(keep)

    def begin(self) -> None:
        self.env.unwrapped.backend.space.damping = self.keep


class WeakActuator(FaultWrapper):
    """The agent's PD gains multiplied by ``factor`` (0.5: halved, a degraded actuator that lags its target)."""

    name, kind, salt = "weak_actuator", "dynamics", 4
    suites = ("embedded",)

    def __init__(self, env, onset=DEFAULT_ONSET, factor: float = 0.5):
        super().__init__(env, onset)
        _pusht(env, self.name)
        if factor <= 0:
            raise ValueError(f"gain factor must be > 0, got {factor}")
        self.factor = float(factor)

    def begin(self) -> None:
        sim = self.env.unwrapped.backend
        sim.kp, sim.kv = sim.kp * self.factor, sim.kv * self.factor


# ----------------------------------------------------------------------------- actuation

class ActionLatency(FaultWrapper):
    """Each action from the onset on is executed ``steps`` env steps late: the env receives the action the policy
    gave ``steps`` calls earlier (the first ones after the onset repeat actions from before it)."""

    name, kind, salt = "action_latency", "actuation", 5

    def __init__(self, env, onset=DEFAULT_ONSET, steps: int = 3):
        super().__init__(env, onset)
        if int(steps) < 1:
            raise ValueError(f"latency must be >= 1 env step, got {steps}")
        self.steps = int(steps)
        self.history: deque = deque(maxlen=self.steps + 1)

    def start_episode(self) -> None:
        self.history.clear()

    def step(self, action):
        self.history.append(np.array(action, copy=True))
        return super().step(action)

    def action(self, action: np.ndarray) -> np.ndarray:
        # the history ends with this call's action and holds ``steps`` before it (fewer at an episode's start)
        return self.history[0]


class ActionNoise(FaultWrapper):
    """Gaussian noise of standard deviation ``std`` (in the action's units; PushT: world units) on every action
    from the onset on."""

    name, kind, salt = "action_noise", "actuation", 6
    suites = ("embedded",)   # std in PushT's world units

    def __init__(self, env, onset=DEFAULT_ONSET, std: float = 25.0):
        super().__init__(env, onset)
        if std < 0:
            raise ValueError(f"noise std must be >= 0, got {std}")
        self.std = float(std)

    def action(self, action: np.ndarray) -> np.ndarray:
        noisy = action + self.rng.normal(0.0, self.std, size=np.shape(action))
        space = self.env.action_space
        return np.clip(noisy, space.low, space.high).astype(action.dtype)


# ----------------------------------------------------------------------------- visual

class Distractors(FaultWrapper):
    """``count`` filled shapes (discs and squares, random colours, places and sizes of ``size`` x the image side)
    drawn on every camera image after the onset; where they are is drawn once per episode."""

    name, kind, salt = "distractors", "visual", 7

    def __init__(self, env, onset=DEFAULT_ONSET, count: int = 3, size: float = 0.12):
        super().__init__(env, onset)
        if int(count) < 1 or not 0 < size < 1:
            raise ValueError(f"need count >= 1 and 0 < size < 1, got {count}, {size}")
        self.count, self.size = int(count), float(size)
        self.shapes: list[tuple] = []

    def start_episode(self) -> None:
        self.shapes = [(self.rng.uniform(0.05, 0.95, 2), self.rng.uniform(0.5, 1.0) * self.size,
                        self.rng.integers(0, 256, 3).astype(np.uint8), bool(self.rng.integers(2)))
                       for _ in range(self.count)]

    def image(self, image: np.ndarray, key: str) -> np.ndarray:
        h, w = image.shape[:2]
        out = image.copy()
        yy, xx = np.mgrid[0:h, 0:w]
        for (cx, cy), radius, colour, disc in self.shapes:
            dx, dy = xx - cx * w, yy - cy * h
            r = radius * w
            mask = dx * dx + dy * dy <= r * r if disc else (np.abs(dx) <= r) & (np.abs(dy) <= r)
            out[mask] = colour
        return out


class ColourShift(FaultWrapper):
    """Camera images after the onset scaled by ``brightness`` and per channel by ``gains`` (RGB), clipped."""

    name, kind, salt = "colour_shift", "visual", 8

    def __init__(self, env, onset=DEFAULT_ONSET, brightness: float = 0.7, gains=(1.0, 0.85, 1.15)):
        super().__init__(env, onset)
        gains = np.asarray(gains, dtype=np.float32)
        if brightness <= 0 or gains.shape != (3,) or (gains <= 0).any():
            raise ValueError(f"need brightness > 0 and three positive channel gains, got {brightness}, {gains}")
        self.factor = brightness * gains

    def image(self, image: np.ndarray, key: str) -> np.ndarray:
        return np.clip(image.astype(np.float32) * self.factor, 0, 255).round().astype(np.uint8)


class CameraShift(FaultWrapper):
    """Camera images after the onset translated by ``pixels`` in a random direction of the eight compass
    directions (drawn per episode); the uncovered border repeats the edge."""

    name, kind, salt = "camera_shift", "visual", 9

    def __init__(self, env, onset=DEFAULT_ONSET, pixels: int = 3):
        super().__init__(env, onset)
        if int(pixels) < 1:
            raise ValueError(f"camera shift must be >= 1 pixel, got {pixels}")
        self.pixels = int(pixels)
        self.shift = (0, 0)

    def start_episode(self) -> None:
        directions = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx]
        dy, dx = directions[int(self.rng.integers(len(directions)))]
        self.shift = (dy * self.pixels, dx * self.pixels)

    def image(self, image: np.ndarray, key: str) -> np.ndarray:
        dy, dx = self.shift
        h, w = image.shape[:2]
        rows = np.clip(np.arange(h) - dy, 0, h - 1)
        cols = np.clip(np.arange(w) - dx, 0, w - 1)
        return image[rows][:, cols]


# ----------------------------------------------------------------------------- benign

class BackgroundTint(FaultWrapper):
    """The table's background recoloured by ``tint`` (RGB offsets) after the onset; pixels of the goal, the block
    and the agent keep their colours (PushT renders a plain background colour; on other tasks the whole image
    is offset, which is no longer a background-only change). Meant not to cause failure: the count of alerts it
    raises is the monitor's false alarms under harmless shift."""

    name, kind, salt = "background_tint", "benign", 10

    def __init__(self, env, onset=DEFAULT_ONSET, tint=(-12, -4, 10)):
        super().__init__(env, onset)
        tint = np.asarray(tint, dtype=np.int16)
        if tint.shape != (3,) or (np.abs(tint) > 64).any():
            raise ValueError(f"tint must be three RGB offsets within +-64, got {tint}")
        self.tint = tint
        self.background = np.asarray(COLORS["background"], np.uint8) \
            if getattr(env.unwrapped, "plain_background", False) else None

    def image(self, image: np.ndarray, key: str) -> np.ndarray:
        shifted = np.clip(image.astype(np.int16) + self.tint, 0, 255).astype(np.uint8)
        if self.background is None:
            return shifted
        mask = np.all(image == self.background, axis=-1)
        out = image.copy()
        out[mask] = shifted[mask]
        return out


class SensorNoise(FaultWrapper):
    """Camera images after the onset with independent Gaussian pixel noise of standard deviation ``std`` (of 255),
    rounded and clipped: a noisier sensor, a change of every pixel that leaves the scene as it was. Meant not to
    cause failure. Frame j's noise of camera ``key`` is drawn from a generator of (seed, j, key) alone, not from the
    episode's running generator: the same seed gives the same noise on a frame whichever other frames were rendered
    (``RenderOnDemand`` renders 3 of every 8; a shared stream made its frame 7 differ from an all-frames run).
    ``draw``: which of independent noise sequences of one seed (0, the default, is the sequence above; ``draw = r``
    adds r to the generator's key): the same start state, the same frames up to the onset and a different harmless
    perturbation after it, e.g. to measure how far an episode's first decisions determine its outcome
    (``jepa-monitor ceiling``)."""

    name, kind, salt = "sensor_noise", "benign", 11

    def __init__(self, env, onset=DEFAULT_ONSET, std: float = 4.0, draw: int = 0):
        super().__init__(env, onset)
        if not 0 < float(std) <= 64:
            raise ValueError(f"sensor noise std must be in (0, 64] of 255, got {std}")
        if isinstance(draw, bool) or not isinstance(draw, (int, np.integer)) or not 0 <= int(draw) < 2**31:
            raise ValueError(f"sensor noise draw must be an integer in [0, 2^31), got {draw!r}; e.g. draw=1")
        self.std, self.draw = float(std), int(draw)

    def image(self, image: np.ndarray, key: str) -> np.ndarray:
        extra = [self.draw] if self.draw else []   # draw 0 keeps the key (and the noise) of the records made before
        rng = np.random.default_rng([self.seed, self.salt, self.t, zlib.crc32(key.encode()), *extra])
        noise = rng.normal(0.0, self.std, image.shape)
        return np.clip(np.rint(image.astype(np.float64) + noise), 0, 255).astype(np.uint8)


# ----------------------------------------------------------------------------- Lift and Can (robosuite)

def _pick(env: gym.Env, fault: str):
    """The robosuite environment of a Lift or Can env, with its object's free joint and the x-y box the object
    may be moved within (Lift: the table; Can: the bin it starts in), 5 cm inside the edges."""
    backend = getattr(env.unwrapped, "backend", None)
    kind = type(backend).__name__
    if kind == "Lift":
        half = np.asarray(backend.table_full_size[:2]) / 2 - 0.05
        centre = np.asarray(backend.table_offset[:2])
        joint = backend.cube.joints[0]
    elif kind == "PickPlaceCan":
        half = np.asarray(backend.bin_size[:2]) / 2 - 0.05
        centre = np.asarray(backend.bin1_pos[:2])
        joint = backend.objects[backend.object_id].joints[0]
    else:
        raise ValueError(f"the {fault} fault moves Lift's cube or Can's can and needs JEPA/Lift-v0 or JEPA/Can-v0, "
                         f"not {type(env.unwrapped).__name__}; use an actuation or image fault on other tasks")
    return backend, joint, centre - half, centre + half


class ModelEdit(FaultWrapper):
    """A fault that edits the simulator's model at the onset; the edit is undone before the next episode."""

    def __init__(self, env, onset=DEFAULT_ONSET):
        super().__init__(env, onset)
        self.saved: list[tuple[np.ndarray, np.ndarray]] = []

    def edit(self, array: np.ndarray, value: np.ndarray) -> None:
        """Set ``array`` (a view into the MuJoCo model) to ``value``, remembering what it held."""
        self.saved.append((array, array.copy()))
        array[...] = value

    def start_episode(self) -> None:
        for array, original in reversed(self.saved):
            array[...] = original
        self.saved.clear()


class ObjectDisplaced(FaultWrapper):
    """The cube (Lift) or can (Can) moved ``distance`` metres in a random horizontal direction at the onset, at
    its height and at rest: out of the gripper if it held it (it falls). Kept inside the table (Lift) or the
    start bin (Can)."""

    name, kind, salt = "object_displaced", "physical", 12
    suites, sources = ("robomimic",), ("Lift", "PickPlaceCan")

    def __init__(self, env, onset=(50, 90), distance: float = 0.08):
        super().__init__(env, onset)
        _pick(env, self.name)
        if not 0 < distance <= 0.3:
            raise ValueError(f"distance must lie in (0, 0.3] metres, got {distance}")
        self.distance = float(distance)

    def begin(self) -> None:
        backend, joint, low, high = _pick(self.env, self.name)
        data = backend.sim.data
        qpos = np.array(data.get_joint_qpos(joint), dtype=np.float64)
        phi = self.rng.uniform(-math.pi, math.pi)
        qpos[:2] = np.clip(qpos[:2] + self.distance * np.array([math.cos(phi), math.sin(phi)]), low, high)
        data.set_joint_qpos(joint, qpos)
        data.set_joint_qvel(joint, np.zeros(6))
        backend.sim.forward()


class GripperSlip(ModelEdit):
    """The gripper's finger actuators' force limit multiplied by ``factor`` (0.1: 2 of its 20 N), so a held
    object slips out of the fingers."""

    name, kind, salt = "gripper_slip", "dynamics", 13
    suites = ("robomimic",)

    def __init__(self, env, onset=(50, 90), factor: float = 0.1):
        super().__init__(env, onset)
        if not 0 <= factor < 1:
            raise ValueError(f"force factor must lie in [0, 1), got {factor}")
        self.factor = float(factor)
        self._gripper()

    def _gripper(self):
        backend = getattr(self.env.unwrapped, "backend", None)
        robots = getattr(backend, "robots", None)
        if not robots or getattr(robots[0], "gripper", None) is None:
            raise ValueError(f"the {self.name} fault weakens a robosuite gripper; {type(self.env.unwrapped).__name__} "
                             "has none")
        return backend.sim.model, robots[0].gripper.actuators

    def begin(self) -> None:
        model, actuators = self._gripper()
        for name in actuators:
            i = model.actuator_name2id(name)
            self.edit(model._model.actuator_forcelimited[i:i + 1], np.ones(1))
            self.edit(model._model.actuator_forcerange[i], model._model.actuator_forcerange[i] * self.factor)


class LightDimmed(ModelEdit):
    """The scene's lights (and the renderer's headlight) dimmed to ``factor`` of their diffuse and specular
    strength at the onset: the simulator renders a darker scene, shadows included."""

    name, kind, salt = "light_dimmed", "visual", 14
    suites = ("robomimic",)

    def __init__(self, env, onset=DEFAULT_ONSET, factor: float = 0.35):
        super().__init__(env, onset)
        if not 0 < factor < 1:
            raise ValueError(f"light factor must lie in (0, 1), got {factor}")
        if getattr(getattr(env.unwrapped, "backend", None), "sim", None) is None:
            raise ValueError(f"the {self.name} fault dims a MuJoCo scene; {type(env.unwrapped).__name__} has none")
        self.factor = float(factor)

    def begin(self) -> None:
        m = self.env.unwrapped.backend.sim.model._model
        for array in (m.light_diffuse, m.light_specular, m.light_ambient, m.vis.headlight.diffuse,
                      m.vis.headlight.ambient, m.vis.headlight.specular):
            self.edit(array, array * self.factor)


# ----------------------------------------------------------------------------- registry

@dataclass(frozen=True)
class FaultInfo:
    wrapper: type
    kind: str
    description: str


FAULTS: dict[str, FaultInfo] = {cls.name: FaultInfo(cls, cls.kind, (cls.__doc__ or "").split("\n")[0]) for cls in (
    BlockDisplaced, BlockFriction, BlockSlides, WeakActuator, ActionLatency, ActionNoise, Distractors, ColourShift,
    CameraShift, BackgroundTint, SensorNoise, ObjectDisplaced, GripperSlip, LightDimmed)}
FAULTED_ID = "JEPA/Faulted-v0"
FAULTED_ENV = f"{__name__}:{FAULTED_ID}"   # what gym.make and the rollout pool are given (imports this module)


def faults_for(spec) -> list[str]:
    """The faults that apply to a task (its ``TaskSpec``): what ``--faults all`` runs on it."""
    return sorted(name for name, info in FAULTS.items()
                  if (info.wrapper.suites is None or spec.suite in info.wrapper.suites)
                  and (info.wrapper.sources is None or spec.source_task in info.wrapper.sources))


def wrap_fault(env: gym.Env, fault: str, **kwargs) -> FaultWrapper:
    """``env`` wrapped in the named fault (a key of ``FAULTS``) with its options (``onset`` and the fault's own)."""
    if fault not in FAULTS:
        raise ValueError(f"unknown fault {fault!r}; choose one of {sorted(FAULTS)}")
    try:
        return FAULTS[fault].wrapper(env, **kwargs)
    except TypeError as exc:
        raise ValueError(f"fault {fault!r}: {exc}; its options are onset and those of "
                         f"{FAULTS[fault].wrapper.__name__}") from None


def make_faulted(base: str = "JEPA/PushT-v0", fault: str = "block_displaced", fault_kwargs: dict | None = None,
                 **env_kwargs) -> FaultWrapper:
    """The env ``base`` (made with ``env_kwargs``, its time limit included) wrapped in ``fault``."""
    return wrap_fault(gym.make(base, **env_kwargs), fault, **(fault_kwargs or {}))


if FAULTED_ID not in gym.registry:
    gym.register(id=FAULTED_ID, entry_point=make_faulted, disable_env_checker=True)
