"""The standard Push-T (``JEPA/PushTStandard-v0``, or ``gym.make("JEPA/PushT-v0", variant="standard")``): the task
of gym-pusht 0.1.8, which Diffusion Policy and LeRobot (``lerobot/pusht``, ``diffusion_pusht``) report on, behind
our interface.

Written from the task's published description and from reading gym-pusht's source; ``make interop`` runs
gym-pusht itself beside it (scripts/interop_pusht.py; docs/envs_pusht_and_data.md, "Parity with gym-pusht").

- table 512 x 512 units, y down; walls: four segments of radius 2 along x, y = 5 and 506;
- agent: a kinematic disc of radius 15 driven toward the action (an ABSOLUTE target in table units, not clipped)
  by ``v += (100 * (target - p) - 20 * v) * 0.01`` before each of 10 physics steps of 10 ms (10 Hz control);
- block: a T of scale 30 (bar 120 x 30 with its top edge on the body origin, stem 30 x 90 below it), mass 1,
  moment 3000 (gym-pusht adds the bar's moment about the origin twice) and centre of gravity (0, 45) (the mean of
  the two rectangles' centres, not the area centroid); friction 0 and elasticity 0 everywhere (gym-pusht sets
  ``friction`` on the bodies, which pymunk ignores); ``space.damping = 0``;
- the block's pose is its body origin (the middle of the bar's top edge) and angle; goal (256, 256, pi/4);
- reset, per seed: agent x, y = ``np_random.integers(50, 450)``, block x, y = ``np_random.integers(100, 400)``,
  angle = ``np_random.uniform(-pi, pi)``, then set the legacy way (position, then angle, which turns the block
  about its centre of gravity and so moves its origin) and one physics step; ``reset(options={"reset_to_state":
  s})`` does the same from ``s``; ``reset(options={"state": s})`` starts exactly at ``s`` (our HDF5 ``states``);
- reward ``clip(coverage / 0.95, 0, 1)``, success and termination at coverage > 0.95, 300 steps (gym registry);
- ``obs_type``: ``"jepa"`` (default: ``top_image`` uint8 (S, S, 3) + ``agent_pos`` float32, the toolkit's
  convention), or gym-pusht's ``"state"``, ``"environment_state_agent_pos"``, ``"pixels"``, ``"pixels_agent_pos"``;
- info: ``pos_agent``, ``vel_agent``, ``block_pose``, ``goal_pose``, ``n_contacts``, ``is_success`` and, after a
  step, ``coverage`` (ours also gives ``coverage`` at reset);
- image: white table, goal T light green (144, 238, 144), block filled (143, 163, 184) with a 4-px outline
  (119, 136, 153), agent (65, 105, 225) with a (78, 126, 255) disc of radius 11, walls light grey (211, 211, 211),
  contact marks (231, 76, 60); drawn at 512 px with pygame's rules and shrunk with OpenCV's bilinear resize
  (``jepa_envs.tasks.pusht_raster``), 96 x 96 by default; ``render()`` gives the visualisation frame
  (``visualization_width`` x ``visualization_height``, 680 default) with the last action marked by a red cross.
"""
from __future__ import annotations

import functools
import math

import numpy as np
import pymunk
from gymnasium import spaces
from PIL import Image

from jepa_envs.tasks import pusht_raster as raster
from jepa_envs.tasks.base import JEPAEnv
from jepa_envs.tasks.pusht import KP, KV, SIM_DT, SUBSTEPS, WORLD_SIZE, clip_regions, overlap_area
from jepa_envs.tasks.spec import get_task_spec

AGENT_RADIUS = 15.0
GOAL_POSE = (256.0, 256.0, math.pi / 4)
SUCCESS_THRESHOLD = 0.95
# the T's rectangles in the block's body frame, vertices in gym-pusht's order
BAR = ((-60.0, 30.0), (60.0, 30.0), (60.0, 0.0), (-60.0, 0.0))
STEM = ((-15.0, 30.0), (-15.0, 120.0), (15.0, 120.0), (15.0, 30.0))
T_AREA = 120.0 * 30.0 + 30.0 * 90.0
BLOCK_MASS = 1.0
BLOCK_MOMENT = 2 * pymunk.moment_for_poly(BLOCK_MASS, BAR)
BLOCK_COG = (0.0, 45.0)
WALLS = (((5, 506), (5, 5)), ((5, 5), (506, 5)), ((506, 5), (506, 506)), ((5, 506), (506, 506)))
WALL_RADIUS = 2.0
AGENT_START, BLOCK_START = (256.0, 400.0), (256.0, 300.0)   # where bodies are made, before the reset moves them
CONTACTS_PER_STEP = 1000   # gym-pusht's n_contacts divides the contacts of a step by 1 / dt * control_hz
OBS_TYPES = ("jepa", "state", "environment_state_agent_pos", "pixels", "pixels_agent_pos")
CANVAS = 512               # the scene is drawn at this size, then resized

COLORS = {
    "background": (255, 255, 255),
    "goal": (144, 238, 144),        # pygame's LightGreen
    "block_fill": (143, 163, 184),  # 1.2 x LightSlateGray, rounded (pymunk's debug-draw fill)
    "block_edge": (119, 136, 153),  # LightSlateGray
    "agent": (65, 105, 225),        # RoyalBlue
    "agent_inner": (78, 126, 255),  # 1.2 x RoyalBlue, capped at 255
    "wall": (211, 211, 211),        # LightGray
    "contact": (231, 76, 60),       # pymunk's collision-point colour
    "marker": (255, 0, 0),
}
EDGE_RADIUS = 2     # outlines are drawn as "fat segments" of this radius: a 4-px line, a quad and two end discs
MARKER_SIZE, MARKER_THICKNESS = 8 / 96, 1 / 96   # of the frame's smaller side


def t_parts(pose) -> list[list[tuple[float, float]]]:
    """World vertices of the bar and the stem at ``pose`` = (body origin x, y, angle)."""
    x, y, a = pose
    c, s = math.cos(a), math.sin(a)
    return [[(x + px * c - py * s, y + px * s + py * c) for px, py in part] for part in (BAR, STEM)]


_GOAL_REGIONS = clip_regions(t_parts(GOAL_POSE))


_REACH = max(math.hypot(*v) for v in BAR + STEM)   # farthest point of the T from its body origin


def coverage(block_pose) -> float:
    """area(block T intersect goal T) / area(goal T), exact (each T is two disjoint rectangles)."""
    if math.hypot(block_pose[0] - GOAL_POSE[0], block_pose[1] - GOAL_POSE[1]) >= 2 * _REACH:
        return 0.0
    return overlap_area(t_parts(block_pose), _GOAL_REGIONS) / T_AREA


# the T's rectangles as (x0, y0, x1, y1) boxes and its outline, in the body frame, for the scripted expert
T_BOXES = ((-60.0, 0.0, 60.0, 30.0), (-15.0, 30.0, 15.0, 120.0))
T_OUTLINE = np.array([(-60.0, 0.0), (60.0, 0.0), (60.0, 30.0), (15.0, 30.0), (15.0, 120.0), (-15.0, 120.0),
                      (-15.0, 30.0), (-60.0, 30.0)])
T_CENTROID = np.array([0.0, (120.0 * 30.0 * 15.0 + 30.0 * 90.0 * 75.0) / T_AREA])
T_RADIUS = float(np.max(np.linalg.norm(T_OUTLINE - T_CENTROID, axis=1)))   # circumradius about the centroid


def _goal_pixels() -> list[list[tuple[int, int]]]:
    """The goal T's corners rounded to pixels, computed by pymunk as gym-pusht does (a body at the goal pose)."""
    body = pymunk.Body(1, pymunk.moment_for_box(1, (50, 100)))
    body.position = GOAL_POSE[:2]
    body.angle = GOAL_POSE[2]
    shapes = [pymunk.Poly(body, part) for part in (BAR, STEM)]
    return [[_to_pixel(body.local_to_world(v)) for v in shape.get_vertices()] for shape in shapes]


def _to_pixel(p) -> tuple[int, int]:
    return round(p[0]), round(p[1])


def _outlines(polygons: list[list[tuple[float, float]]], radius: float) -> tuple[tuple, tuple]:
    """The pixels of the closed outlines through each polygon's corners as gym-pusht's debug draw makes each edge
    (a "fat segment"): a line ``round(2 * radius)`` wide, a quad offset by (|dy|, |dx|) scaled to ``radius`` (not
    a true normal: that is how it is drawn) and a disc of radius ``round(radius)`` at each end.
    Returns (line pixels with their polygon, spans with their polygon)."""
    edges, owner, quads, quad_owner, discs, disc_owner = [], [], [], [], [], []
    r = round(radius)
    for k, corners in enumerate(polygons):
        ends = [_to_pixel(c) for c in corners]
        for i in range(len(ends) if len(ends) > 2 else 1):
            (x1, y1), (x2, y2) = ends[i], ends[(i + 1) % len(ends)]
            edges.append((x1, y1, x2, y2))
            owner.append(k)
            ox, oy = abs(y2 - y1), abs(x2 - x1)
            if not (ox or oy):
                continue
            scale = radius / (ox * ox + oy * oy) ** 0.5
            ox, oy = round(ox * scale), round(oy * scale)
            quads.append(([x1 - ox, x1 + ox, x2 + ox, x2 - ox], [y1 - oy, y1 + oy, y2 + oy, y2 - oy]))
            quad_owner.append(k)
            discs += [raster.circle_spans(x1, y1, r), raster.circle_spans(x2, y2, r)]
            disc_owner += [k] * (len(discs[-1][0]) + len(discs[-2][0]))
    rows, cols, line = raster.thick_line_pixels(np.array(edges), round(max(1, radius * 2)), (CANVAS, CANVAS))
    spans, which = raster.polygon_spans(quads)
    return ((rows, cols, np.asarray(owner)[line]),
            raster.concat_spans(spans, *discs), np.concatenate([np.asarray(quad_owner)[which], disc_owner]))


def _filled(polygons: list[list[tuple[float, float]]]) -> tuple[raster.Spans, np.ndarray]:
    """The fills of polygons as gym-pusht draws them (corners rounded to pixels, the first repeated at the end),
    with the polygon of each span."""
    closed = []
    for corners in polygons:
        pixels = [_to_pixel(c) for c in corners]
        closed.append(tuple(zip(*(pixels + pixels[:1]))))
    return raster.polygon_spans(closed)


def _static_layers() -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """The table with the goal drawn (what every frame starts from) and the pixels of the walls (drawn last, over
    the block and the agent)."""
    table = raster.Canvas(np.full((CANVAS, CANVAS, 3), COLORS["background"], dtype=np.uint8))
    table.paint_spans(_filled(_goal_pixels())[0], COLORS["goal"])
    walls = raster.Canvas(np.zeros((CANVAS, CANVAS, 3), dtype=np.uint8))
    (rows, cols, _), spans, _ = _outlines([[a, b] for a, b in WALLS], WALL_RADIUS)
    walls.paint_pixels(rows, cols, (1, 1, 1))
    walls.paint_spans(spans, (1, 1, 1))
    return table.pixels, np.nonzero(walls.pixels[..., 0])


_TABLE, _WALL_PIXELS = _static_layers()


@functools.lru_cache(maxsize=None)
def _blank_canvas(width: int | None, height: int | None) -> raster.Canvas:
    """The table canvas a frame is drawn on: only the pixels a resize to (width, height) reads (all for None)."""
    if width is None:
        return raster.Canvas(_TABLE)
    return raster.Canvas.for_resize(_TABLE, width, height)


class StandardPushTSim:
    """The raw backend: gym-pusht's pymunk scene (built in its order), its PD control and its frames."""

    def __init__(self, damping: float | None = None, block_cog=None, count_contacts: bool = True):
        self.space = space = pymunk.Space()
        space.gravity = (0.0, 0.0)
        space.damping = 0.0 if damping is None else float(damping)
        space.add(*[pymunk.Segment(space.static_body, a, b, WALL_RADIUS) for a, b in WALLS])
        self.agent = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
        self.agent.position = AGENT_START
        space.add(self.agent, pymunk.Circle(self.agent, AGENT_RADIUS))
        self.block = pymunk.Body(BLOCK_MASS, BLOCK_MOMENT)
        self.parts = [pymunk.Poly(self.block, BAR), pymunk.Poly(self.block, STEM)]
        self.block.center_of_gravity = BLOCK_COG
        self.block.angle = 0.0
        self.block.position = BLOCK_START
        space.add(self.block, *self.parts)
        if block_cog is not None:
            self.block.center_of_gravity = tuple(block_cog)
        self.local_vertices = [[tuple(v) for v in part.get_vertices()] for part in self.parts]
        self.count_contacts = count_contacts
        self.contacts = 0   # contact points summed over the substeps of the last step (or of the reset)

    # -- state ---------------------------------------------------------------------------------------------
    def set_state_legacy(self, state) -> None:
        """gym-pusht's reset: agent position, block position, then block angle (turning the block about its
        centre of gravity), then one physics step."""
        s = [float(v) for v in state]
        self.agent.position = (s[0], s[1])
        self.block.position = (s[2], s[3])
        self.block.angle = s[4]
        self.contacts = 0
        self._physics_step()

    def set_state(self, state) -> None:
        """Exactly ``state`` = (agent x, y, block origin x, y, block angle), at rest (angle set before position)."""
        ax, ay, bx, by, angle = (float(v) for v in state)
        self.agent.position = (ax, ay)
        self.agent.velocity = (0.0, 0.0)
        self.block.angle = angle
        self.block.position = (bx, by)
        self.block.velocity = (0.0, 0.0)
        self.block.angular_velocity = 0.0
        self.space.reindex_shapes_for_body(self.block)
        self.space.reindex_shapes_for_body(self.agent)
        self.contacts = 0

    def get_state(self) -> np.ndarray:
        return np.array([*self.agent.position, *self.block.position, self.block.angle], dtype=np.float64)

    @property
    def block_pose(self) -> tuple[float, float, float]:
        return (*self.block.position, self.block.angle)

    def snapshot(self) -> tuple:
        a, b = self.agent, self.block
        return (a.position, a.velocity, b.angle, b.position, b.velocity, b.angular_velocity)

    def restore(self, snap: tuple) -> None:
        a, b = self.agent, self.block
        a.position, a.velocity, b.angle, b.position, b.velocity, b.angular_velocity = snap   # angle first
        self.space.reindex_shapes_for_body(a)
        self.space.reindex_shapes_for_body(b)

    def clone(self) -> "StandardPushTSim":
        """An independent copy for planning by simulation (it does not count contacts)."""
        new = StandardPushTSim.__new__(StandardPushTSim)
        new.space = self.space.copy()
        bodies = list(self.space.bodies)
        copies = list(new.space.bodies)
        new.agent, new.block = copies[bodies.index(self.agent)], copies[bodies.index(self.block)]
        new.parts = list(new.block.shapes)
        new.local_vertices = self.local_vertices
        new.count_contacts, new.contacts = False, 0
        return new

    # -- dynamics --------------------------------------------------------------------------------------------
    def step(self, target) -> None:
        """One 10 Hz control step toward the absolute agent target (table units), 10 substeps of 10 ms."""
        tx, ty = float(target[0]), float(target[1])
        agent = self.agent
        self.contacts = 0
        for _ in range(SUBSTEPS):
            (px, py), (vx, vy) = agent.position, agent.velocity
            agent.velocity = (vx + (KP * (tx - px) - KV * vx) * SIM_DT, vy + (KP * (ty - py) - KV * vy) * SIM_DT)
            self._physics_step()

    def _physics_step(self) -> None:
        self.space.step(SIM_DT)
        if self.count_contacts:
            self.block.each_arbiter(self._add_contacts)   # every colliding pair involves the block

    def _add_contacts(self, arbiter) -> None:
        self.contacts += len(arbiter.contact_point_set.points)

    # -- frames ------------------------------------------------------------------------------------------------
    def draw(self, width: int | None = None, height: int | None = None) -> raster.Canvas:
        """The 512 x 512 scene: goal, block (fill, then outline, bar before stem), agent, walls, contact marks;
        only the pixels a resize to (width, height) reads when they are given."""
        canvas = _blank_canvas(width, height).copy()
        block = self.block
        parts = [[block.local_to_world(v) for v in local] for local in self.local_vertices]
        fills, fill_of = _filled(parts)
        (rows, cols, line_of), edges, edge_of = _outlines(parts, EDGE_RADIUS)
        for k in range(len(parts)):   # the bar filled and outlined, then the stem
            canvas.paint_spans(raster.select_spans(fills, fill_of == k), COLORS["block_fill"])
            on = line_of == k
            canvas.paint_pixels(rows[on], cols[on], COLORS["block_edge"])
            canvas.paint_spans(raster.select_spans(edges, edge_of == k), COLORS["block_edge"])
        cx, cy = _to_pixel(self.agent.position)
        canvas.paint_spans(raster.circle_spans(cx, cy, round(AGENT_RADIUS)), COLORS["agent"])
        canvas.paint_spans(raster.circle_spans(cx, cy, round(AGENT_RADIUS - 4)), COLORS["agent_inner"])
        canvas.paint_pixels(*_WALL_PIXELS, COLORS["wall"])
        for a, b in self.contact_marks():
            raster.aaline(canvas, *_to_pixel(a), *_to_pixel(b), COLORS["contact"])
        return canvas

    def contact_marks(self) -> list[tuple[tuple[float, float], tuple[float, float]]]:
        """The contact marks of the last physics step, in the order pymunk's debug draw makes them: pairs in the
        space's order, each contact from the other shape's point 2 units against the pair's normal to the block's
        point 2 units along it.

        ``each_arbiter`` on the block lists the pairs last first and presents each with the block as its first
        shape; inside chipmunk the block is always the pair's second shape (pairs are ordered by shape type:
        circle, segment, polygon), which fixes the direction."""
        pairs = []

        def add(arbiter):
            points = arbiter.contact_point_set
            nx, ny = points.normal   # from the block (first here) to the other shape
            pairs.append([((bx + 2.0 * nx, by + 2.0 * ny), (ax - 2.0 * nx, ay - 2.0 * ny))
                          for (ax, ay), (bx, by) in ((p.point_a, p.point_b) for p in points.points)])

        self.block.each_arbiter(add)
        return [mark for pair in reversed(pairs) for mark in pair]

    def render(self, width: int, height: int) -> np.ndarray:
        """The observation frame: the scene resized to (height, width, 3) uint8."""
        return self.draw(width, height).resize(width, height)

    def free(self) -> None:
        """Remove every body and shape and drop the Space (pymunk Spaces alive at exit can segfault)."""
        if self.space is None:
            return
        self.space.remove(*self.space.shapes)
        self.space.remove(*self.space.bodies)
        self.space = None
        self.agent = self.block = None


def _marker(frame: np.ndarray, action) -> None:
    """A red cross at the action (the visualisation's marker), in place: two strokes ``MARKER_SIZE`` long drawn as
    OpenCV draws a thick line, every pixel within (thickness + 1) // 2 of the stroke (a capsule)."""
    h, w = frame.shape[:2]
    x, y = (np.asarray(action, dtype=np.float64) / WORLD_SIZE * [h, w]).astype(np.int64)
    half = int(MARKER_SIZE * min(h, w)) // 2
    thickness = max(int(MARKER_THICKNESS * min(h, w)), 1)
    radius = (thickness + 1) // 2 if thickness > 1 else 0
    r0, r1 = max(y - half - radius, 0), min(y + half + radius + 1, h)
    c0, c1 = max(x - half - radius, 0), min(x + half + radius + 1, w)
    if r0 >= r1 or c0 >= c1:
        return
    dy, dx = np.ogrid[r0 - y:r1 - y, c0 - x:c1 - x]
    along_x = np.maximum(np.abs(dx) - half, 0) ** 2 + dy ** 2
    along_y = np.maximum(np.abs(dy) - half, 0) ** 2 + dx ** 2
    frame[r0:r1, c0:c1][np.minimum(along_x, along_y) <= radius ** 2] = COLORS["marker"]


class PushTStandardEnv(JEPAEnv):
    """Gymnasium env of the standard Push-T. See the module docstring for the task; constructor options:

    ``obs_type`` ("jepa" default, "state", "environment_state_agent_pos", "pixels", "pixels_agent_pos");
    gym-pusht's ``observation_width`` / ``observation_height`` (the frame, 96 x 96 default: the scene resized from
    512 px); ``image_size`` (obs_type "jepa" only: ``top_image`` is the frame resized to this square size with
    Pillow's bilinear filter, exactly as ``load_dataset(image_size=...)`` resizes the frames of a 96 px dataset, so
    a policy sees in the env what it was trained on); ``visualization_width`` / ``visualization_height``
    (``render()`` frames, 680 default); gym-pusht's ``block_cog`` and ``damping``; ``success_threshold`` (0.95,
    gym-pusht's; ``make-demos --finish-threshold`` raises it while collecting).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, task: str = "PushTStandard", image_size: int | None = None, render_mode: str | None = None,
                 obs_type: str = "jepa", observation_width: int | None = None, observation_height: int | None = None,
                 visualization_width: int = 680, visualization_height: int = 680, block_cog=None,
                 damping: float | None = None, success_threshold: float = SUCCESS_THRESHOLD, **unknown):
        if unknown:
            raise TypeError(f"unknown option(s) {sorted(unknown)} for the standard PushT; it takes obs_type, "
                            "image_size, observation_width/height, visualization_width/height, render_mode, block_cog, "
                            "damping and success_threshold (difficulty presets belong to the embedded PushT, "
                            "variant='embedded')")
        spec = get_task_spec(task)
        if spec.name != "PushTStandard":
            raise ValueError(f"PushTStandardEnv builds the standard PushT, not {task!r}")
        if obs_type not in OBS_TYPES:
            raise ValueError(f"unknown obs_type {obs_type!r}; use one of {list(OBS_TYPES)}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array' (frames from env.render()), got {render_mode!r}")
        # None is the task's size; 0 is a size like any other, and refused below
        width = spec.image_size if observation_width is None else int(observation_width)
        height = spec.image_size if observation_height is None else int(observation_height)
        for name, value in (("observation_width", width), ("observation_height", height),
                            ("visualization_width", visualization_width),
                            ("visualization_height", visualization_height)):
            if int(value) < 8:
                raise ValueError(f"{name} must be >= 8 pixels, got {value}")
        if obs_type == "jepa":
            if width != height:
                raise ValueError(f"obs_type='jepa' gives square top_image frames; observation_width ({width}) and "
                                 f"observation_height ({height}) must be equal, or use obs_type='pixels_agent_pos'")
            image_size = width if image_size is None else int(image_size)
            if image_size < 8:
                raise ValueError(f"image_size must be >= 8 pixels, got {image_size}")
            spec = spec.with_image_size(image_size)
        elif image_size is not None and (int(image_size), int(image_size)) != (width, height):
            raise ValueError(f"image_size sets obs_type='jepa''s top_image; gym-pusht's obs_type={obs_type!r} takes "
                             "observation_width and observation_height")
        if not 0 < success_threshold <= 1:
            raise ValueError(f"success_threshold must be in (0, 1], got {success_threshold}")
        super().__init__(spec, render_mode=render_mode)
        self.obs_type = obs_type
        self.observation_width, self.observation_height = width, height
        self.visualization_width, self.visualization_height = int(visualization_width), int(visualization_height)
        self.block_cog, self.damping = block_cog, damping
        self._threshold = float(success_threshold)
        self.observation_space = self._space()
        self.action_space = spaces.Box(0.0, WORLD_SIZE, shape=(2,), dtype=np.float32)
        self.backend = StandardPushTSim(damping, block_cog)
        self._coverage, self._last_action = 0.0, None

    def _space(self) -> spaces.Space:
        h, w = self.observation_height, self.observation_width
        pixels = spaces.Box(0, 255, shape=(h, w, 3), dtype=np.uint8)
        agent_pos = spaces.Box(np.zeros(2), np.full(2, WORLD_SIZE), dtype=np.float64)
        if self.obs_type == "jepa":
            return self.observation_space
        if self.obs_type == "state":
            return spaces.Box(np.zeros(5), np.array([WORLD_SIZE] * 4 + [2 * np.pi]), dtype=np.float64)
        if self.obs_type == "environment_state_agent_pos":
            return spaces.Dict({"environment_state": spaces.Box(np.zeros(16), np.full(16, WORLD_SIZE),
                                                                dtype=np.float64), "agent_pos": agent_pos})
        if self.obs_type == "pixels":
            return pixels
        return spaces.Dict({"pixels": pixels, "agent_pos": agent_pos})

    # -- contract used by the benchmark and the expert -------------------------------------------------------
    def hold_action(self) -> np.ndarray:
        """The action that holds the agent still: its current position."""
        return np.asarray(self.backend.agent.position, dtype=np.float32)

    def native_zero_action(self) -> np.ndarray:
        return np.asarray(self.backend.agent.position, dtype=np.float64)

    def get_state(self) -> np.ndarray:
        return self.backend.get_state()

    @property
    def success_threshold(self) -> float:
        return self._threshold

    # -- gym API ---------------------------------------------------------------------------------------------
    def _check_open(self) -> None:
        if self.backend.space is None:
            raise RuntimeError("PushTStandardEnv was closed; make a new env")

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._check_open()
        options = dict(options or {})
        unknown = set(options) - {"reset_to_state", "state"}
        if unknown:
            raise ValueError(f"unknown reset option(s) {sorted(unknown)}; the standard PushT takes 'reset_to_state' "
                             "(gym-pusht's: set the legacy way, then one physics step) or 'state' (exactly this state)")
        # a fresh space per episode, as gym-pusht builds one: equal seeds give bit-identical episodes
        self.backend.free()
        self.backend = StandardPushTSim(self.damping, self.block_cog)
        if options.get("reset_to_state") is not None:
            self.backend.set_state_legacy(self._state_option(options["reset_to_state"], "reset_to_state"))
        elif options.get("state") is not None:
            self.backend.set_state(self._state_option(options["state"], "state"))
        else:
            rng = self.np_random
            self.backend.set_state_legacy([rng.integers(50, 450), rng.integers(50, 450), rng.integers(100, 400),
                                           rng.integers(100, 400), rng.uniform(-np.pi, np.pi)])
        self._coverage = coverage(self.backend.block_pose)
        info = self._info()
        info["is_success"] = False   # gym-pusht never reports success at reset
        return self._observation(), info

    @staticmethod
    def _state_option(value, name: str) -> np.ndarray:
        state = np.asarray(value, dtype=np.float64)
        if state.shape != (5,) or not np.isfinite(state).all():
            raise ValueError(f"options[{name!r}] must be 5 finite numbers (agent x, y, block x, y, block angle), "
                             f"got {value!r}")
        return state

    def step(self, action):
        self._check_open()
        target = np.asarray(action, dtype=np.float64).reshape(-1)
        if target.size != 2 or not np.isfinite(target).all():
            raise ValueError(f"PushT action must be 2 finite numbers (absolute agent target), got {action!r}")
        self._last_action = target
        self.backend.step(target)
        self._coverage = coverage(self.backend.block_pose)
        success = self._coverage > self._threshold
        reward = min(max(self._coverage / self._threshold, 0.0), 1.0)
        info = self._info()
        info["is_success"] = success
        return self._observation(), reward, success, False, info

    def _frame(self) -> np.ndarray:
        if not self.render_images:
            return np.zeros((self.observation_height, self.observation_width, 3), dtype=np.uint8)
        return self.backend.render(self.observation_width, self.observation_height)

    def _top_image(self) -> np.ndarray:
        size = self.task_spec.image_size
        if not self.render_images:
            return np.zeros((size, size, 3), dtype=np.uint8)
        frame = self.backend.render(self.observation_width, self.observation_height)
        if size == self.observation_width:
            return frame
        return np.asarray(Image.fromarray(frame).resize((size, size), Image.BILINEAR))

    def _observation(self):
        sim = self.backend
        if self.obs_type == "jepa":
            return {"top_image": self._top_image(), "agent_pos": np.array(sim.agent.position, dtype=np.float32)}
        if self.obs_type == "state":
            x, y, angle = sim.block_pose
            return np.array([*sim.agent.position, x, y, angle % (2 * np.pi)], dtype=np.float64)
        agent_pos = np.array(sim.agent.position, dtype=np.float64)
        if self.obs_type == "environment_state_agent_pos":
            return {"environment_state": self.keypoints().reshape(-1), "agent_pos": agent_pos}
        if self.obs_type == "pixels":
            return self._frame()
        return {"pixels": self._frame(), "agent_pos": agent_pos}

    def keypoints(self) -> np.ndarray:
        """The T's eight corners (bar, then stem, in pymunk's vertex order) as (8, 2): each body-frame corner
        rotated by the block angle and moved by the block position, as gym-pusht computes them."""
        block = self.backend.block
        (x, y), a = block.position, block.angle
        c, s = math.cos(a), math.sin(a)
        return np.array([(vx * c - vy * s + x, vx * s + vy * c + y)
                         for part in self.backend.local_vertices for vx, vy in part], dtype=np.float64)

    def _info(self) -> dict:
        sim = self.backend
        return {"pos_agent": np.array(sim.agent.position), "vel_agent": np.array(sim.agent.velocity),
                "block_pose": np.array(sim.block_pose), "goal_pose": np.array(GOAL_POSE),
                "n_contacts": int(math.ceil(sim.contacts / CONTACTS_PER_STEP)), "coverage": self._coverage}

    def render(self):
        """The visualisation frame (``visualization_height`` x ``visualization_width``) with the last action
        marked, when ``render_mode="rgb_array"``; None otherwise."""
        if self.render_mode != "rgb_array":
            return None
        self._check_open()
        frame = self.backend.draw().resize(self.visualization_width, self.visualization_height)
        if self._last_action is not None:
            _marker(frame, self._last_action)
        return frame

    def close(self):
        self.backend.free()
        super().close()
