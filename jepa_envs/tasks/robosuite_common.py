"""Shared plumbing for the robosuite-based backends (robomimic tasks, MimicGen, LIBERO).

One class, ``RobosuiteTaskEnv``, turns a built robosuite env into our interface: observation mapping (images
the right way up, float32 proprioception), absolute or delta actions (paper Sec. 4.1), reproducible seeded
resets, the success flag, and switching camera rendering off for real (disabled camera observables are never
rendered by robosuite).
"""
from __future__ import annotations

import copy
from contextlib import contextmanager
from typing import Any, Callable

from jepa_envs.tasks.render import use_renderer

# The user's MUJOCO_GL, else the measured fastest backend with identical frames (jepa_envs/tasks/render.py); this must
# precede the first mujoco/robosuite import.
use_renderer()

import mujoco
import numpy as np
from gymnasium import spaces

from jepa_envs.tasks import abs_actions, rotations
from jepa_envs.tasks.base import JEPAEnv
from jepa_envs.tasks.outcomes import OutcomeTracker, pick_object
from jepa_envs.tasks.spec import TaskSpec

ACTION_MODES = ("abs", "delta")
# numpy's global RNG is seeded with this while robosuite builds an env: its object models draw their sizes,
# masses and frictions from it (Transport's hammer, Lift's cube), so the same task is the same scene in every
# process (reset seeds then vary the placements).
CONSTRUCTION_SEED = 0
NATIVE_DIM_PER_ARM = abs_actions.NATIVE_DIM_PER_ARM
# Declared bounds of the absolute action: positions in metres (world frame, generous box around every task's
# workspace), 6-D rotation entries are unit-vector components, gripper -1 (open) .. 1 (closed).
ABS_POS_BOUND = 2.0

# robosuite's OSC_POSE defaults as stored in the robomimic v1.5 image datasets' env_args (robosuite 1.4.1).
OSC_POSE = {
    "type": "OSC_POSE",
    "input_max": 1,
    "input_min": -1,
    "output_max": [0.05, 0.05, 0.05, 0.5, 0.5, 0.5],
    "output_min": [-0.05, -0.05, -0.05, -0.5, -0.5, -0.5],
    "kp": 150,
    "damping": 1,
    "impedance_mode": "fixed",
    "kp_limits": [0, 300],
    "damping_limits": [0, 10],
    "position_limits": None,
    "orientation_limits": None,
    "uncouple_pos_ori": True,
    "control_delta": True,
    "interpolation": None,
    "ramp_ratio": 0.2,
}


def check_action_mode(action_mode: str) -> str:
    if action_mode not in ACTION_MODES:
        raise ValueError(f"action_mode must be one of {ACTION_MODES}, got {action_mode!r}")
    return action_mode


def osc_pose_config(control_delta: bool) -> dict:
    """robomimic's OSC_POSE controller config; ``control_delta=False`` is the absolute-pose variant."""
    return {**OSC_POSE, "control_delta": bool(control_delta)}


def set_control_delta(backend: Any, control_delta: bool) -> None:
    """Switch every arm's OSC controller between delta and absolute input, now and after future resets.

    robosuite rebuilds controllers from ``robot.controller_config`` on reset, so both the config and the
    live controller are changed.
    """
    for robot in backend.robots:
        if robot.controller_config.get("type") != "OSC_POSE":
            raise ValueError(f"absolute actions need an OSC_POSE controller, robot has "
                             f"{robot.controller_config.get('type')!r}; build the env with controller OSC_POSE")
        robot.controller_config["control_delta"] = bool(control_delta)
        if robot.controller is not None:
            robot.controller.use_delta = bool(control_delta)


@contextmanager
def global_numpy_seed(seed: int):
    """robosuite's and LIBERO's placement samplers draw from numpy's global RNG: seed it for one block, then
    restore it, so the caller's random stream is untouched."""
    state = np.random.get_state()
    np.random.seed(seed)
    try:
        yield
    finally:
        np.random.set_state(state)


def localize_model_xml(xml: str) -> str:
    """A recorded MJCF model with its asset paths pointed at this machine's robosuite (datasets store the
    absolute paths of the machine that recorded them, e.g. /home/me/robosuite/robosuite/models/assets/...)."""
    import os
    import re

    import robosuite

    local = os.path.dirname(robosuite.__file__)

    def repoint(match: re.Match) -> str:
        path = match.group(2)
        marker = "/robosuite/models/assets/"
        if marker in path and not os.path.exists(path):
            path = os.path.join(local, "models", "assets", path.split(marker, 1)[1])
        return f'{match.group(1)}"{path}"'

    return re.sub(r'(\bfile=)"([^"]*)"', repoint, xml)


def upright(image: np.ndarray) -> np.ndarray:
    """The right-way-up view of a frame robosuite 1.4 rendered OpenGL-style (bottom row first).

    Only the rows are flipped, as robomimic does. Turning by 180 degrees (rows and columns, as some LIBERO
    consumers do) would also mirror left and right; ``tests/jepa_envs/tasks/test_libero.py`` checks against the
    camera geometry that this flip gives the camera's true view for LIBERO too. Works on (..., H, W, C) stacks.
    """
    return np.ascontiguousarray(image[..., ::-1, :, :])


class RobosuiteTaskEnv(JEPAEnv):
    """Our interface around a built robosuite env (``self.backend``).

    Subclasses build the backend and pass it in, and may override ``_backend_reset`` (returns robosuite's
    observation dict); ``success_fn`` returns the task's success (default ``backend._check_success()``).
    """

    def __init__(
        self,
        spec: TaskSpec,
        backend: Any,
        *,
        render_mode: str | None = None,
        action_mode: str = "abs",
        success_fn: Callable[[], bool] | None = None,
        reflections: bool = True,
    ):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        super().__init__(spec, render_mode=render_mode)
        self.backend = backend
        # MuJoCo's reflection pass (the table's mirror-like finish) renders the scene a second time; software
        # renderers spend most of a frame on it. Off: 4.5x faster frames that differ by 0.2-0.5 of 255 per pixel
        # on average (docs/envs_simulation.md, "Rendering speed"); on: robomimic's frames.
        self.reflections = bool(reflections)
        self.action_mode = check_action_mode(action_mode)
        self.num_arms = spec.num_arms
        # our camera name -> the backend's observation key of that camera
        self._camera_keys = {c: f"{c}_image" for c in spec.cameras}
        self._success_fn = success_fn or backend._check_success
        # the pick tasks (Lift, Can) name each failure from the simulator state: info["failure_kind"] (outcomes.py)
        self._outcome = OutcomeTracker(backend) if pick_object(backend) is not None else None
        self.action_space = self._make_action_space()
        self._resumed_cameras: set[str] = set()
        # Observations are read at the END of each control step (``step``: a forced update), as robomimic's datasets
        # are rendered from recorded states (its ``step`` returns robosuite's clock-sampled ones instead), so a
        # recorded state re-renders to the frame seen live (render-dataset). robosuite's own clock samples
        # observables early in a step; the cameras are made to never sample on it, so each is still rendered once
        # per step.
        for key in self._camera_keys.values():
            backend.modify_observable(observable_name=key, attribute="sampling_rate", modifier=1e-9)

    # ---- spaces and actions -------------------------------------------------------------------------
    def _make_action_space(self) -> spaces.Box:
        if self.action_mode == "delta":
            return spaces.Box(-1.0, 1.0, shape=(NATIVE_DIM_PER_ARM * self.num_arms,), dtype=np.float32)
        per_arm_low = np.array([-ABS_POS_BOUND] * 3 + [-1.0] * 6 + [-1.0], dtype=np.float32)
        return spaces.Box(np.tile(per_arm_low, self.num_arms), np.tile(-per_arm_low, self.num_arms),
                          dtype=np.float32)

    def to_native(self, action: np.ndarray) -> np.ndarray:
        """Our action -> the backend's controller input (7 per arm).

        Every action in the space is accepted: an arm whose 6-D rotation defines no rotation (a zero first
        column, or parallel columns, e.g. the all-zeros action) holds its end effector's current orientation
        (its position and gripper are taken as given)."""
        action = np.asarray(action, dtype=np.float64)
        if action.shape != self.action_space.shape:
            raise ValueError(f"{self.task_spec.name}: action must have shape {self.action_space.shape} "
                             f"({self.action_mode} mode), got {action.shape}")
        if self.action_mode == "delta":
            return action
        arms = abs_actions.split_arms(action, self.num_arms, abs_actions.ABS_DIM_PER_ARM, "absolute").copy()
        held = rotations.rot6d_is_degenerate(arms[:, 3:9])
        if held.any():
            _, mats = self.controller_pose()
            arms[held, 3:9] = rotations.matrix_to_rot6d(mats[held])
        return abs_actions.abs_to_native(arms.reshape(-1), self.num_arms)

    def controller_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Per arm, the current pose in the frame of the OSC controller: positions (n, 3), matrices (n, 3, 3).

        Read from a scratch copy of the simulation state, so asking changes nothing: the controller's own
        ``update(force=True)`` would run ``mj_forward`` on the live data and leave its caches set, which moves
        the following steps by ~1e-15 that grows to ~1e-8 m within an episode. The copy gives the same numbers
        (the controller reads the same end-effector site after the same forward kinematics).
        """
        sim = self.backend.sim
        model = sim.model._model
        scratch = copy.copy(sim.data._data)   # MjData copies are deep
        mujoco.mj_kinematics(model, scratch)
        pos, mats = [], []
        for robot in self.backend.robots:
            site = sim.model.site_name2id(robot.controller.eef_name)
            pos.append(np.array(scratch.site_xpos[site]))
            mats.append(np.array(scratch.site_xmat[site]).reshape(3, 3))
        return np.stack(pos), np.stack(mats)

    def controller_goal(self) -> tuple[np.ndarray, np.ndarray]:
        """Per arm, the goal pose the OSC controllers currently track: positions (n, 3), matrices (n, 3, 3)."""
        robots = self.backend.robots
        return (np.stack([np.array(r.controller.goal_pos) for r in robots]),
                np.stack([np.array(r.controller.goal_ori) for r in robots]))

    def hold_action(self, gripper: float = -1.0) -> np.ndarray:
        """The action in our convention that keeps every arm where it is (gripper open by default)."""
        if self.action_mode == "delta":
            act = np.zeros(self.action_space.shape, dtype=np.float32)
            act[NATIVE_DIM_PER_ARM - 1::NATIVE_DIM_PER_ARM] = gripper
            return act
        pos, mats = self.controller_pose()
        return abs_actions.pose_to_abs(pos, mats, np.full(self.num_arms, gripper)).astype(np.float32)

    def native_zero_action(self) -> np.ndarray:
        """The backend's own action that holds the arms still: zeros in delta mode, the current pose in
        absolute mode (robosuite's OSC input, 7 per arm). For comparing raw stepping with ours."""
        return self.to_native(self.hold_action(gripper=0.0))

    # ---- observations -------------------------------------------------------------------------------
    def _set_camera_observables(self, enabled: bool) -> None:
        observables = self.backend._observables
        # Proprioception is never switched off and samples at the same rate as the cameras: its sampling
        # phase is the one the cameras would have had if they had stayed on.
        ref = observables[self.task_spec.lowdim_keys[0]]
        for key in self._camera_keys.values():
            self.backend.modify_observable(observable_name=key, attribute="enabled", modifier=enabled)
            self.backend.modify_observable(observable_name=key, attribute="active", modifier=enabled)
            if enabled:
                # Re-enabling resets robosuite's sampling clock and leaves a zero image; resume in phase with
                # the reference so that on-demand frames equal always-on frames.
                cam = observables[key]
                cam._time_since_last_sample = ref._time_since_last_sample
                cam._sampled = ref._sampled
        self._resumed_cameras = set(self._camera_keys.values()) if enabled else set()

    def set_render_images(self, enabled: bool) -> None:
        """Really stop (or restart) camera rendering in robosuite; images are zeros while it is off."""
        enabled = bool(enabled)
        if enabled != self.render_images:
            self._set_camera_observables(enabled)
        super().set_render_images(enabled)

    def _observation(self, raw: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        for key in self._resumed_cameras:
            # robosuite's clock skipped this period's sample (the image is still the zero placeholder; a real
            # render is never all black): render the current state now
            if not np.any(raw[key]):
                cam = self.backend._observables[key]
                cam.update(0.0, {}, force=True)
                raw[key] = cam.obs
        self._resumed_cameras = set()
        if self.render_images:
            obs = {f"{c}_image": upright(raw[key]) for c, key in self._camera_keys.items()}
        else:
            obs = self.blank_images()
        for key, dim in self.task_spec.lowdim:
            value = np.asarray(raw[key], dtype=np.float32).reshape(-1)
            if value.shape != (dim,):
                raise RuntimeError(f"backend observation {key!r} has {value.size} values, task spec expects {dim}")
            obs[key] = value
        return obs

    # ---- gymnasium API ------------------------------------------------------------------------------
    def _backend_reset(self, options: dict | None) -> dict[str, np.ndarray]:
        """robosuite's reset; ``options`` may restore a recorded episode's start as robomimic's ``reset_to``
        does: ``model`` (the MJCF XML a dataset stored, ``demo.attrs["model_file"]``) and ``state`` (MuJoCo's
        flattened state, ``states[0]``)."""
        raw = self.backend.reset()
        options = options or {}
        if "model" in options:
            self.backend.reset_from_xml_string(localize_model_xml(options["model"]))
            self.backend.sim.reset()
            self._make_gl_current()
        if "state" in options:
            self.set_sim_state(options["state"])
        if "model" in options or "state" in options:
            raw = self.backend._get_observations(force_update=True)
        return raw

    def set_sim_state(self, state) -> None:
        """Put the simulator in a recorded flattened MuJoCo state (no step is taken)."""
        state = np.asarray(state, dtype=np.float64)
        expected = self.backend.sim.get_state().flatten().shape
        if state.shape != expected:
            raise ValueError(f"a {self.task_spec.name} state has {expected[0]} values, got {state.shape}; the "
                             "recording comes from another env (check its env_args / model)")
        self.backend.sim.set_state_from_flattened(state)
        self.backend.sim.forward()

    def observe_now(self) -> dict[str, np.ndarray]:
        """The observation of the simulator's current state, cameras rendered now (robomimic's get_observation)."""
        self._make_gl_current()
        return self._observation(self.backend._get_observations(force_update=True))

    def _clear_gripper_commands(self) -> None:
        # A soft reset (hard_reset=False) keeps the gripper models, whose incremental command would otherwise
        # carry over from the previous episode and make seeded episodes depend on history.
        for robot in self.backend.robots:
            grippers = robot.gripper.values() if isinstance(robot.gripper, dict) else [robot.gripper]
            for gripper in grippers:
                gripper.current_action = np.zeros(gripper.dof)

    def _make_gl_current(self) -> None:
        # robosuite's offscreen renderer draws into whichever GL context is current, and building or closing
        # another env switches it: with several envs in one process (tests, SyncVectorEnv) images would come
        # from the wrong context. Claim ours before anything renders.
        ctx = getattr(self.backend.sim, "_render_context_offscreen", None)
        if ctx is not None:
            ctx.gl_ctx.make_current()
            ctx.scn.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = int(self.reflections)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._make_gl_current()
        episode_seed = int(self.np_random.integers(0, 2**31 - 1))
        self._clear_gripper_commands()
        with global_numpy_seed(episode_seed):
            raw = self._backend_reset(options)
        info = {"is_success": bool(self._success_fn())}
        if self._outcome is not None:
            self._outcome.reset()
            info["failure_kind"] = self._outcome.update(info["is_success"])
        return self._observation(raw), info

    def step(self, action):
        if self.render_images:
            self._make_gl_current()
        native = self.to_native(action)
        self.backend.step(native)
        # MuJoCo's step leaves positions (xpos, sites) computed for the state before its integration: forward to
        # the final state, then read every observation, the success and the reward from it (see __init__).
        # robosuite's own step computed its reward before that forward, from the old positions: on the step that
        # succeeds it could still be 0 while success is read as True (an episode's max reward 0 on a success)
        self.backend.sim.forward()
        raw = self.backend._get_observations(force_update=True)
        success = bool(self._success_fn())
        reward = self.backend.reward(native)
        info = {"is_success": success}
        if self._outcome is not None:
            info["failure_kind"] = self._outcome.update(success)
        # robosuite runs with ignore_done; the episode ends on success, the time limit is the TimeLimit wrapper's.
        return self._observation(raw), float(reward), success, False, info

    def render(self):
        """All cameras side by side at the task's image size (rendered now, even while images are off)."""
        if self.render_mode != "rgb_array":
            return None
        s = self.task_spec.image_size
        self._make_gl_current()
        frames = [upright(self.backend.sim.render(camera_name=c, width=s, height=s))
                  for c in self.task_spec.cameras]
        return np.concatenate(frames, axis=1)

    def close(self):
        if getattr(self, "backend", None) is not None:
            # freeing the renderer deletes GL objects in the *current* context: make it ours, not a neighbour's
            self._make_gl_current()
            self.backend.close()
            self.backend = None
