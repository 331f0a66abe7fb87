"""JEPA/PushT-v0: the embedded 2-D pushing task (the CPU default of the toolkit).

A round agent pushes a T-shaped block to a fixed goal pose on a 512 x 512 table simulated with pymunk.

Units (all documented contract):
- world coordinates are table units in [0, 512], x to the right, y DOWN (image convention, so the camera is a
  plain scaling of the world: pixel = world * S / 512);
- action: float32 (2,), the ABSOLUTE target position of the agent in world units. A PD controller
  (acceleration = kp * (target - pos) - kv * vel) moves the agent toward it over 10 physics substeps of 10 ms,
  so one control step is 0.1 s (10 Hz);
- observation: ``top_image`` uint8 (S, S, 3) top-down camera with the goal pose drawn in green, and
  ``agent_pos`` float32 (2,) agent position in world units;
- state (for HDF5 ``states`` and exact replays): float64 (5,) = agent x, agent y, block x, block y, block angle
  (rad); the block position is the centroid of the T;
- reward: coverage = area(block T intersect goal T) / area(goal T), in [0, 1];
- terminated when coverage >= the success threshold; ``info["is_success"]`` and ``info["coverage"]`` on every
  step.

The block has no inertia that survives a step (``space.damping = 0``): it only moves while the agent pushes it
(quasi-static pushing, as in diffusion_policy's PushT), which is what makes the task learnable from images.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

import numpy as np
import pymunk
from gymnasium import spaces
from PIL import Image, ImageDraw

from jepa_envs.tasks.base import JEPAEnv
from jepa_envs.tasks.spec import get_task_spec

WORLD_SIZE = 512.0
AGENT_RADIUS = 15.0
SIM_DT = 0.01
SUBSTEPS = 10              # 10 x 10 ms = one 10 Hz control step
KP, KV = 100.0, 20.0       # PD gains of the agent controller (critically damped, settles in ~0.5 s)
GOAL_POSE = (256.0, 256.0, math.pi / 4)
_T_SCALE, _T_LENGTH = 36.0, 4.0

COLORS = {
    "background": (240, 240, 235),
    "goal": (140, 220, 140),
    "block": (110, 125, 145),
    "agent": (60, 100, 220),
}


def _t_parts() -> tuple[np.ndarray, np.ndarray]:
    """The T as two disjoint rectangles (bar, stem) in the block frame, centred on the T's centroid."""
    s, half = _T_SCALE, _T_SCALE * _T_LENGTH / 2
    bar = np.array([(-half, 0.0), (half, 0.0), (half, s), (-half, s)])
    stem = np.array([(-s / 2, s), (s / 2, s), (s / 2, _T_LENGTH * s), (-s / 2, _T_LENGTH * s)])
    area_bar, area_stem = 2 * half * s, s * (_T_LENGTH - 1) * s
    centroid_y = (area_bar * s / 2 + area_stem * (s + _T_LENGTH * s) / 2) / (area_bar + area_stem)
    offset = np.array([0.0, centroid_y])
    return bar - offset, stem - offset


T_PARTS = _t_parts()
T_AREA = _T_SCALE * _T_LENGTH * _T_SCALE + _T_SCALE * (_T_LENGTH - 1) * _T_SCALE
T_OUTLINE = np.array([  # the T's boundary as one closed polygon (vertex order around the outline)
    T_PARTS[0][0], T_PARTS[0][1], T_PARTS[0][2], T_PARTS[1][1], T_PARTS[1][2], T_PARTS[1][3], T_PARTS[1][0],
    T_PARTS[0][3],
])
T_RADIUS = float(np.max(np.linalg.norm(T_OUTLINE, axis=1)))  # circumradius around the centroid


def transform(points: np.ndarray, pose) -> np.ndarray:
    """Block-frame points (N, 2) to world coordinates for a pose (x, y, angle)."""
    x, y, a = pose
    c, s = math.cos(a), math.sin(a)
    return points @ np.array([[c, s], [-s, c]]) + np.array([x, y])


def _part_vertices(pose) -> list[list[tuple[float, float]]]:
    """World vertices of the T's two rectangles at ``pose``, as plain floats (hot path: no numpy)."""
    x, y, a = pose
    c, s = math.cos(a), math.sin(a)
    return [[(x + px * c - py * s, y + px * s + py * c) for px, py in part.tolist()] for part in T_PARTS]


def _clip_edges(poly: list[tuple[float, float]]) -> list[tuple[float, float, float, float]]:
    """Edges (ax, ay, dx, dy) of a convex polygon, oriented so that "inside" is on the left."""
    area2 = sum(poly[i - 1][0] * poly[i][1] - poly[i][0] * poly[i - 1][1] for i in range(len(poly)))
    pts = poly if area2 > 0 else poly[::-1]
    return [(pts[i - 1][0], pts[i - 1][1], pts[i][0] - pts[i - 1][0], pts[i][1] - pts[i - 1][1])
            for i in range(len(pts))]


def _clipped_area(subject: list[tuple[float, float]], edges) -> float:
    """Area of convex ``subject`` inside the convex polygon given by ``edges`` (Sutherland-Hodgman)."""
    out = subject
    for ax, ay, dx, dy in edges:
        inp, out = out, []
        if not inp:
            return 0.0
        px, py = inp[-1]
        sp = dx * (py - ay) - dy * (px - ax)
        for qx, qy in inp:
            sq = dx * (qy - ay) - dy * (qx - ax)
            if sq >= 0:
                if sp < 0:
                    f = sp / (sp - sq)
                    out.append((px + f * (qx - px), py + f * (qy - py)))
                out.append((qx, qy))
            elif sp >= 0:
                f = sp / (sp - sq)
                out.append((px + f * (qx - px), py + f * (qy - py)))
            px, py, sp = qx, qy, sq
    return abs(0.5 * sum(out[i - 1][0] * out[i][1] - out[i][0] * out[i - 1][1] for i in range(len(out))))


def coverage(block_pose, goal_pose=GOAL_POSE) -> float:
    """Fraction of the goal T covered by the block T: area(block & goal) / area(goal), exact.

    Both T's are unions of two disjoint convex rectangles, so the intersection area is the sum of the four
    convex-convex intersections.
    """
    if math.hypot(block_pose[0] - goal_pose[0], block_pose[1] - goal_pose[1]) >= 2 * T_RADIUS:
        return 0.0
    goal_edges = (_GOAL_EDGES if tuple(goal_pose) == GOAL_POSE
                  else [_clip_edges(p) for p in _part_vertices(goal_pose)])
    inter = sum(_clipped_area(b, g) for b in _part_vertices(block_pose) for g in goal_edges)
    return min(1.0, inter / T_AREA)


_GOAL_EDGES = [_clip_edges(p) for p in _part_vertices(GOAL_POSE)]


def clip_regions(parts) -> list:
    """Convex polygons (vertex lists) in the half-plane form ``overlap_area`` clips with; precompute it for a
    polygon used often (a goal)."""
    return [_clip_edges(p) for p in parts]


def overlap_area(parts, regions) -> float:
    """Area of the union of disjoint convex ``parts`` (vertex lists) inside the union of disjoint convex
    ``regions`` (from ``clip_regions``): the sum of the pairwise convex intersections, exact."""
    return sum(_clipped_area(p, r) for p in parts for r in regions)


def wrap_angle(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


@dataclass(frozen=True)
class PushTDifficulty:
    """How hard an episode is. Initial block pose = goal pose moved by a distance drawn from ``offset_range``
    (world units, uniform direction) and turned by an angle whose magnitude is drawn from
    ``rotation_range_deg`` (random sign). Resets are re-drawn until the initial coverage is at most
    ``max_initial_coverage``, so success always needs the block to be pushed and turned.
    """

    offset_range: tuple[float, float] = (30.0, 70.0)
    rotation_range_deg: tuple[float, float] = (15.0, 40.0)
    success_threshold: float = 0.8
    max_initial_coverage: float = 0.5

    def __post_init__(self):
        lo, hi = self.offset_range
        if not 0 <= lo <= hi <= 200:
            raise ValueError(f"offset_range must satisfy 0 <= low <= high <= 200 world units, got {self.offset_range}")
        lo, hi = self.rotation_range_deg
        if not 0 <= lo <= hi <= 180:
            raise ValueError(f"rotation_range_deg must satisfy 0 <= low <= high <= 180, got {self.rotation_range_deg}")
        if not 0 < self.success_threshold <= 1:
            raise ValueError(f"success_threshold must be in (0, 1], got {self.success_threshold}")
        if not 0 <= self.max_initial_coverage < self.success_threshold:
            raise ValueError("max_initial_coverage must be in [0, success_threshold) so that doing nothing never "
                             f"succeeds; got {self.max_initial_coverage} with threshold {self.success_threshold}")


DIFFICULTIES = {
    # default: learnable by a small image policy in minutes on CPU, still a real push-and-turn task
    "easy": PushTDifficulty(),
    "medium": PushTDifficulty(offset_range=(40.0, 90.0), rotation_range_deg=(15.0, 45.0), success_threshold=0.85,
                              max_initial_coverage=0.6),
    "hard": PushTDifficulty(offset_range=(60.0, 140.0), rotation_range_deg=(30.0, 90.0), success_threshold=0.9,
                            max_initial_coverage=0.6),
    # close to diffusion_policy's PushT: anywhere on the table, any angle, 95% coverage
    "full": PushTDifficulty(offset_range=(80.0, 200.0), rotation_range_deg=(0.0, 180.0), success_threshold=0.95,
                            max_initial_coverage=0.6),
}


def make_difficulty(difficulty: str | PushTDifficulty = "easy", **overrides) -> PushTDifficulty:
    """A preset by name ("easy" default, "medium", "hard", "full") with optional field overrides."""
    if isinstance(difficulty, PushTDifficulty):
        base = difficulty
    elif difficulty in DIFFICULTIES:
        base = DIFFICULTIES[difficulty]
    else:
        raise ValueError(f"unknown PushT difficulty {difficulty!r}; use one of {sorted(DIFFICULTIES)} "
                         "or a PushTDifficulty instance")
    known = {f.name for f in fields(PushTDifficulty)}
    unknown = set(overrides) - known
    if unknown:
        raise TypeError(f"unknown PushT option(s) {sorted(unknown)}; valid options: difficulty, {sorted(known)}")
    return PushTDifficulty(**{**asdict(base), **{k: (tuple(v) if isinstance(v, list) else v)
                                                 for k, v in overrides.items() if v is not None}})


class PushTSim:
    """The raw backend: pymunk simulation of agent + T block, with a Pillow renderer. No gym layers."""

    def __init__(self):
        self.space = pymunk.Space()
        self.space.gravity = (0.0, 0.0)
        self.space.damping = 0.0  # quasi-static: velocities do not survive between steps
        walls = [((5, 5), (5, 507)), ((5, 507), (507, 507)), ((507, 507), (507, 5)), ((507, 5), (5, 5))]
        for a, b in walls:
            seg = pymunk.Segment(self.space.static_body, a, b, 2.0)
            seg.friction = 1.0
            self.space.add(seg)
        self.agent = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
        agent_shape = pymunk.Circle(self.agent, AGENT_RADIUS)
        agent_shape.friction = 1.0
        self.space.add(self.agent, agent_shape)
        self.block = pymunk.Body()  # mass and moment come from the shapes' density (total mass 1)
        self.space.add(self.block)
        for part in T_PARTS:
            shape = pymunk.Poly(self.block, [tuple(v) for v in part])
            shape.friction = 1.0
            shape.density = 1.0 / T_AREA
            self.space.add(shape)
        bodies = list(self.space.bodies)
        self._body_index = (bodies.index(self.agent), bodies.index(self.block))
        self.kp, self.kv = KP, KV   # the agent's PD gains (a degraded actuator lowers them: jepa_envs.tasks.faults)

    # -- state -------------------------------------------------------------------------------------------
    def set_state(self, state) -> None:
        ax, ay, bx, by, angle = (float(v) for v in state)
        self.agent.position = (ax, ay)
        self.agent.velocity = (0.0, 0.0)
        self.block.position = (bx, by)
        self.block.angle = angle
        self.block.velocity = (0.0, 0.0)
        self.block.angular_velocity = 0.0
        self.space.reindex_shapes_for_body(self.block)
        self.space.reindex_shapes_for_body(self.agent)

    def get_state(self) -> np.ndarray:
        return np.array([*self.agent.position, *self.block.position, self.block.angle], dtype=np.float64)

    @property
    def block_pose(self) -> tuple[float, float, float]:
        return (*self.block.position, self.block.angle)

    def snapshot(self) -> tuple:
        """Positions and velocities of both bodies (for ``restore``; cheaper than ``clone``)."""
        a, b = self.agent, self.block
        return (a.position, a.velocity, b.position, b.angle, b.velocity, b.angular_velocity)

    def restore(self, snap: tuple) -> None:
        a, b = self.agent, self.block
        a.position, a.velocity, b.position, b.angle, b.velocity, b.angular_velocity = snap
        self.space.reindex_shapes_for_body(a)
        self.space.reindex_shapes_for_body(b)

    def clone(self) -> "PushTSim":
        """An independent copy (pymunk ``Space.copy``) for planning by simulation."""
        new = PushTSim.__new__(PushTSim)
        new.space = self.space.copy()
        new._body_index = self._body_index
        new.kp, new.kv = self.kp, self.kv
        bodies = list(new.space.bodies)
        new.agent, new.block = bodies[self._body_index[0]], bodies[self._body_index[1]]
        return new

    # -- dynamics ------------------------------------------------------------------------------------------
    def step(self, target) -> None:
        """One 10 Hz control step toward the absolute agent target (world units)."""
        tx, ty = float(target[0]), float(target[1])
        agent, space, kp, kv = self.agent, self.space, self.kp, self.kv
        for _ in range(SUBSTEPS):
            (px, py), (vx, vy) = agent.position, agent.velocity
            vx += (kp * (tx - px) - kv * vx) * SIM_DT
            vy += (kp * (ty - py) - kv * vy) * SIM_DT
            agent.velocity = (vx, vy)
            space.step(SIM_DT)

    # -- rendering -----------------------------------------------------------------------------------------
    def render(self, size: int, supersample: int = 2) -> np.ndarray:
        """Top-down RGB image (size, size, 3) uint8: goal T, block T, agent. Pure Pillow, no display."""
        big = size * supersample
        scale = big / WORLD_SIZE
        img = Image.new("RGB", (big, big), COLORS["background"])
        draw = ImageDraw.Draw(img)
        for pose, color in ((GOAL_POSE, COLORS["goal"]), (self.block_pose, COLORS["block"])):
            for part in _part_vertices(pose):
                draw.polygon([(x * scale, y * scale) for x, y in part], fill=color)
        (ax, ay), r = self.agent.position, AGENT_RADIUS
        draw.ellipse([(ax - r) * scale, (ay - r) * scale, (ax + r) * scale, (ay + r) * scale], fill=COLORS["agent"])
        if supersample > 1:
            img = img.reduce(supersample)
        return np.asarray(img, dtype=np.uint8)

    def free(self) -> None:
        """Remove every body and shape and drop the Space (pymunk Spaces alive at exit can segfault)."""
        if self.space is None:
            return
        self.space.remove(*self.space.shapes)
        self.space.remove(*[b for b in self.space.bodies])
        self.space = None
        self.agent = self.block = None


class PushTEnv(JEPAEnv):
    """Gymnasium env for JEPA/PushT-v0. See the module docstring for units, reward and termination.

    Options (constructor kwargs): ``difficulty`` ("easy" default, "medium", "hard", "full" or a PushTDifficulty) and
    overrides of its fields: ``offset_range``, ``rotation_range_deg``, ``success_threshold``,
    ``max_initial_coverage``. ``render_size`` sets the size of ``render()`` frames (default 256).
    ``reset(options={"state": s})`` starts from an exact 5-D state.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}
    plain_background = True   # its frames' background is one colour, COLORS["background"] (BackgroundTint reads it)

    def __init__(self, task: str = "PushT", image_size: int | None = None, render_mode: str | None = None,
                 difficulty: str | PushTDifficulty = "easy", render_size: int = 256, **options):
        spec = get_task_spec(task)
        if spec.name != "PushT":
            raise ValueError(f"PushTEnv builds the embedded PushT task, not {task!r} (the standard PushT is "
                             "jepa_envs.tasks.pusht_standard.PushTStandardEnv)")
        if image_size is not None:
            if int(image_size) < 8:
                raise ValueError(f"image_size must be >= 8 pixels, got {image_size}")
            spec = spec.with_image_size(int(image_size))
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        super().__init__(spec, render_mode=render_mode)
        self.difficulty = make_difficulty(difficulty, **options)
        self.render_size = int(render_size)
        self.action_space = spaces.Box(0.0, WORLD_SIZE, shape=(2,), dtype=np.float32)
        self.backend = PushTSim()
        self._coverage, self._pose = 0.0, GOAL_POSE

    # -- contract used by the benchmark and the expert -------------------------------------------------------
    def hold_action(self) -> np.ndarray:
        """The action (our convention) that holds the agent still: its current position."""
        return np.asarray(self.backend.agent.position, dtype=np.float32)

    def native_zero_action(self) -> np.ndarray:
        """The raw-backend action that holds the agent still (the same target, as the backend takes it)."""
        return np.asarray(self.backend.agent.position, dtype=np.float64)

    def get_state(self) -> np.ndarray:
        return self.backend.get_state()

    @property
    def success_threshold(self) -> float:
        return self.difficulty.success_threshold

    # -- gym API ---------------------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if self.backend.space is None:
            raise RuntimeError("PushTEnv was closed; make a new env")
        # a fresh space per episode: pymunk keeps contact caches that would make equal seeds diverge
        self.backend.free()
        self.backend = PushTSim()
        if options and "state" in options:
            state = np.asarray(options["state"], dtype=np.float64)
            if state.shape != (5,):
                raise ValueError("options['state'] must have shape (5,) (agent xy, block xy, angle), "
                                 f"got {state.shape}")
        else:
            state = self._sample_initial_state()
        self.backend.set_state(state)
        self._update_coverage()
        return self._observation(), self._info()

    def _sample_initial_state(self) -> np.ndarray:
        d, rng = self.difficulty, self.np_random
        gx, gy, ga = GOAL_POSE
        for _ in range(1000):
            r = rng.uniform(*d.offset_range)
            phi = rng.uniform(-math.pi, math.pi)
            rot = math.radians(rng.uniform(*d.rotation_range_deg)) * rng.choice([-1.0, 1.0])
            block = (gx + r * math.cos(phi), gy + r * math.sin(phi), ga + rot)
            if not (T_RADIUS + 10 <= block[0] <= WORLD_SIZE - T_RADIUS - 10
                    and T_RADIUS + 10 <= block[1] <= WORLD_SIZE - T_RADIUS - 10):
                continue
            if coverage(block) > d.max_initial_coverage:
                continue
            agent = rng.uniform(40.0, WORLD_SIZE - 40.0, size=2)
            if point_t_distance(agent, block) < AGENT_RADIUS + 15:
                continue
            return np.array([agent[0], agent[1], *block], dtype=np.float64)
        raise RuntimeError(f"could not sample an initial PushT state for difficulty {d}; widen its ranges")

    def step(self, action):
        action = np.asarray(action, dtype=np.float64)
        if action.size != 2 or not (math.isfinite(action.flat[0]) and math.isfinite(action.flat[1])):
            raise ValueError(f"PushT action must be 2 finite numbers (absolute agent target), got {action!r}")
        x, y = float(action.flat[0]), float(action.flat[1])
        self.backend.step((min(max(x, 0.0), WORLD_SIZE), min(max(y, 0.0), WORLD_SIZE)))
        self._update_coverage()
        success = self._coverage >= self.difficulty.success_threshold
        return self._observation(), self._coverage, success, False, self._info()

    def _update_coverage(self) -> None:
        self._pose = self.backend.block_pose
        self._coverage = coverage(self._pose)

    def _observation(self) -> dict:
        size = self.task_spec.image_size
        image = self.backend.render(size) if self.render_images else np.zeros((size, size, 3), dtype=np.uint8)
        return {"top_image": image, "agent_pos": np.array(self.backend.agent.position, dtype=np.float32)}

    def _info(self) -> dict:
        return {"is_success": self._coverage >= self.difficulty.success_threshold,
                "coverage": self._coverage, "block_pose": np.array(self._pose)}

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        return self.backend.render(self.render_size)

    def close(self):
        self.backend.free()
        super().close()


# the T's two rectangles as (x0, y0, x1, y1) in the block frame, as plain floats for point_t_distance
_T_BOXES = tuple((float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
                 for lo, hi in ((part.min(axis=0), part.max(axis=0)) for part in T_PARTS))


def point_t_distance(point, pose) -> float:
    """Distance from a world point to the T at ``pose`` (0 inside)."""
    return point_boxes_distance(point, pose, _T_BOXES)


def point_boxes_distance(point, pose, boxes) -> float:
    """Distance from a world point to a union of body-frame boxes (x0, y0, x1, y1) at ``pose`` (0 inside).

    Scalar float arithmetic: the expert calls this tens of thousands of times per demonstration, where numpy's
    per-call overhead on 2-vectors dominated. ``np.hypot`` is kept where both gaps are non-zero, so results are
    bit-identical to the vectorised form (hypot(g, 0) is exactly |g|)."""
    x, y, a = pose
    c, s = math.cos(a), math.sin(a)
    dx, dy = float(point[0]) - x, float(point[1]) - y
    lx, ly = c * dx + s * dy, -s * dx + c * dy  # inverse of ``transform``
    best = math.inf
    for x0, y0, x1, y1 in boxes:
        gx, gy = max(x0 - lx, lx - x1, 0.0), max(y0 - ly, ly - y1, 0.0)
        best = min(best, gx if gy == 0.0 else gy if gx == 0.0 else float(np.hypot(gx, gy)))
    return best
