"""ARX-5 backend: one or two ARX-5 arms through the public arx5-sdk and Intel RealSense cameras.

Written against the arx5-sdk python bindings (``arx5_interface``: ``Arx5CartesianController(model,
interface)``, ``EEFState(pose_6d, gripper_pos)``, ``set_eef_cmd``, ``get_eef_state``, ``get_joint_state``,
``get_timestamp``, ``reset_to_home``, ``get_robot_config``) and ``pyrealsense2``. Both are imported only when
this backend is built; when they are missing the error names what to install (docs/real_robot.md).

Action convention (Sec. 4.1): per arm ``[x, y, z, r6 (6-D rotation), gripper]`` in the arm's base frame,
gripper 0 = closed, 1 = open; arms ordered as ``task_spec.extra["arms"]``. The SDK's controller interpolates
each 10 Hz target at its own 500 Hz; each camera streams at the 30 Hz driver rate on its own thread and the
newest frame is taken at the end of each control period (the bridge calls ``observe`` then).
"""
from __future__ import annotations

import importlib
import threading
import time
import tomllib
from pathlib import Path

import numpy as np
from PIL import Image
from pydantic import BaseModel, ConfigDict, field_validator, model_validator
from scipy.spatial.transform import Rotation

from jepa_robot.backends.base import BackendUnavailable, RobotBackend, StepResult
from jepa_robot.safety import SafetyConfig
from jepa_envs.tasks.rotations import matrix_to_rot6d, rot6d_to_matrix
from jepa_envs.tasks.spec import get_task_spec

ARX5_INSTALL_HINT = (
    "the ARX-5 backend needs the arx5-sdk python bindings (module `arx5_interface`, built from "
    "https://github.com/real-stanford/arx5-sdk: conda env + cmake + make, then put its python/ folder on "
    "PYTHONPATH and lib/<arch> on LD_LIBRARY_PATH) and Intel RealSense (`pip install pyrealsense2`); "
    "see docs/real_robot.md, 'ARX-5 install'"
)


def import_hardware_sdks():
    """Import (arx5_interface, pyrealsense2) or raise BackendUnavailable naming what to install."""
    modules = []
    for name in ("arx5_interface", "pyrealsense2"):
        try:
            modules.append(importlib.import_module(name))
        except ImportError as exc:
            raise BackendUnavailable(f"cannot import {name!r} ({exc}); {ARX5_INSTALL_HINT}") from exc
    return tuple(modules)


JOINTS_PER_ARM = 6   # X5 and L5 arms: six revolute joints (the gripper is not a joint here)
# no X5/L5 joint turns a full turn either way: a configured joint limit beyond this never fires
JOINT_RANGE_RAD = (-2 * np.pi, 2 * np.pi)


class ArmConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str            # "left" | "right", matches task_spec.extra["arms"]
    interface: str       # CAN interface, e.g. "can0"
    model: str = "X5"    # arx5-sdk robot model name ("X5", "L5")


class CameraConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str            # one of the task's cameras: base, left_wrist, right_wrist
    serial: str          # RealSense serial number (`rs-enumerate-devices -s`)
    width: int = 640
    height: int = 480
    fps: int = 30        # the 30 Hz driver rate of Sec. 4.8


class ARX5Config(BaseModel):
    """The robot computer's set-up file (TOML), e.g. deploy/robot/arx5_cabinet.toml."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)   # a NaN bound would switch its check off
    task: str
    arms: list[ArmConfig]
    cameras: list[CameraConfig]
    workspace_low: list[float]    # x, y, z lower bound (m) of every arm's end effector, arm base frame
    workspace_high: list[float]
    control_address: str = "tcp://127.0.0.1:5555"   # loopback unless set: docs/real_robot.md, "Network security"
    operator_address: str = "tcp://127.0.0.1:5556"
    record_dir: str = "robot_episodes"
    safety: SafetyConfig = SafetyConfig()
    curve_secret_key: str | None = None       # CurveZMQ on the control socket (jepa-robot-bridge keys)
    curve_authorized_dir: str | None = None

    @field_validator("workspace_low", "workspace_high")
    @classmethod
    def _three(cls, v: list[float]) -> list[float]:
        if len(v) != 3:
            raise ValueError("workspace bounds are [x, y, z] in metres")
        return v

    @model_validator(mode="after")
    def _matches_task(self) -> "ARX5Config":
        try:
            spec = get_task_spec(self.task)
        except KeyError as exc:   # pydantic reports ValueErrors as the field's problem, not KeyErrors
            raise ValueError(exc.args[0]) from None
        if spec.suite != "real":
            raise ValueError(f"task {self.task!r} is not a real-robot task; use one of Cabinet, CupStack, "
                             "CupUpright, PlateGrape, PenInsert")
        want_arms = list(spec.extra["arms"])
        if sorted(a.name for a in self.arms) != sorted(want_arms):
            raise ValueError(f"task {spec.name} uses arms {want_arms}; the config lists "
                             f"{[a.name for a in self.arms]}")
        missing = set(spec.cameras) - {c.name for c in self.cameras}
        if missing:
            raise ValueError(f"task {spec.name} needs cameras {list(spec.cameras)}; add {sorted(missing)}")
        if any(lo >= hi for lo, hi in zip(self.workspace_low, self.workspace_high)):
            raise ValueError("workspace_low must be below workspace_high on x, y and z")
        problems = self.safety.problems(spec.action_dim, JOINTS_PER_ARM * len(self.arms), spec.control_hz,
                                        action_range=arx5_action_bounds(self), joint_range=JOINT_RANGE_RAD)
        if problems:
            raise ValueError("\n".join(problems))   # one line each (safety.config_errors)
        if (self.curve_secret_key is None) != (self.curve_authorized_dir is None):
            raise ValueError("CurveZMQ needs both curve_secret_key and curve_authorized_dir (or neither)")
        return self


def load_arx5_config(path: str | Path) -> ARX5Config:
    """Read and validate an ARX-5 set-up TOML file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"ARX-5 config {path} not found; start from deploy/robot/arx5_cabinet.toml")
    with path.open("rb") as f:
        return ARX5Config.model_validate(tomllib.load(f))


def arx5_action_bounds(config: ARX5Config) -> tuple[np.ndarray, np.ndarray]:
    """Per-dimension action bounds of a set-up: the workspace box, r6 in [-1, 1], gripper in [0, 1], per arm."""
    arms = len(get_task_spec(config.task).extra["arms"])
    low = np.concatenate([config.workspace_low, -np.ones(6), [0.0]])
    high = np.concatenate([config.workspace_high, np.ones(6), [1.0]])
    return np.tile(low, arms), np.tile(high, arms)


def pose6d_to_action(pose_6d: np.ndarray, gripper01: float) -> np.ndarray:
    """SDK pose (x, y, z, roll, pitch, yaw) + gripper in [0, 1] -> the 10-D absolute action of one arm."""
    matrix = Rotation.from_euler("xyz", pose_6d[3:6]).as_matrix()
    return np.concatenate([pose_6d[:3], matrix_to_rot6d(matrix), [gripper01]])


def action_to_pose6d(action10: np.ndarray) -> tuple[np.ndarray, float]:
    """The 10-D absolute action of one arm -> SDK pose (x, y, z, roll, pitch, yaw) and gripper in [0, 1]."""
    rpy = Rotation.from_matrix(rot6d_to_matrix(action10[3:9])).as_euler("xyz")
    return np.concatenate([action10[:3], rpy]), float(action10[9])


class _CameraStream:
    """One RealSense colour stream read by its own thread at the 30 Hz driver rate; keeps the newest frame."""

    def __init__(self, rs, camera: CameraConfig):
        self.name = camera.name
        rs_config = rs.config()
        rs_config.enable_device(camera.serial)
        rs_config.enable_stream(rs.stream.color, camera.width, camera.height, rs.format.rgb8, camera.fps)
        self._pipeline = rs.pipeline()
        self._pipeline.start(rs_config)
        self._frame = np.asanyarray(self._pipeline.wait_for_frames().get_color_frame().get_data()).copy()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._error: Exception | None = None
        self._thread = threading.Thread(target=self._run, name=f"realsense-{camera.name}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                frame = np.asanyarray(self._pipeline.wait_for_frames().get_color_frame().get_data()).copy()
                with self._lock:
                    self._frame = frame
        except RuntimeError as exc:   # pyrealsense2 raises RuntimeError when a camera drops out
            self._error = exc

    def latest(self) -> np.ndarray:
        if self._error is not None:
            raise RuntimeError(f"camera {self.name!r} stopped streaming: {self._error}; check its USB link")
        with self._lock:
            return self._frame

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        self._pipeline.stop()


class ARX5Backend(RobotBackend):
    """Drives the ARX-5 arms and reads the RealSense cameras of one task set-up."""

    success_source = "operator"
    realtime = True

    def __init__(self, config: ARX5Config, image_size: int | None = None):
        arx5, rs = import_hardware_sdks()
        spec = get_task_spec(config.task)
        self.task_spec = spec.with_image_size(image_size) if image_size else spec
        self.config = config
        self._arx5 = arx5
        self._arm_names = list(spec.extra["arms"])
        by_name = {a.name: a for a in config.arms}
        self._controllers = [arx5.Arx5CartesianController(by_name[n].model, by_name[n].interface)
                             for n in self._arm_names]
        self._gripper_width = [c.get_robot_config().gripper_width for c in self._controllers]
        self._streams = [_CameraStream(rs, cam) for cam in config.cameras if cam.name in spec.cameras]
        self._low, self._high = arx5_action_bounds(config)
        self._render = True
        self._period = 1.0 / spec.control_hz

    @property
    def action_low(self) -> np.ndarray:
        return self._low

    @property
    def action_high(self) -> np.ndarray:
        return self._high

    def _images(self) -> dict[str, np.ndarray]:
        size = self.task_spec.image_size
        if not self._render:
            return {k: np.zeros((size, size, 3), np.uint8) for k in self.task_spec.image_keys}
        # Sec. 4.8: policies receive every view resized to 128x128
        return {f"{s.name}_image": np.asarray(Image.fromarray(s.latest()).resize((size, size), Image.BILINEAR))
                for s in self._streams}

    def observe(self) -> dict[str, np.ndarray]:
        obs = self._images()
        for i, controller in enumerate(self._controllers):
            state = controller.get_eef_state()
            pose = np.asarray(state.pose_6d(), np.float64)
            quat = Rotation.from_euler("xyz", pose[3:6]).as_quat()  # (x, y, z, w) like robosuite
            half = float(state.gripper_pos) / 2.0
            obs[f"robot{i}_eef_pos"] = pose[:3].astype(np.float32)
            obs[f"robot{i}_eef_quat"] = quat.astype(np.float32)
            obs[f"robot{i}_gripper_qpos"] = np.array([half, -half], np.float32)
        return obs

    def current_action(self) -> np.ndarray:
        parts = []
        for controller, width in zip(self._controllers, self._gripper_width):
            state = controller.get_eef_state()
            parts.append(pose6d_to_action(np.asarray(state.pose_6d(), np.float64), state.gripper_pos / width))
        return np.concatenate(parts)

    def joint_positions(self) -> np.ndarray:
        return np.concatenate([np.asarray(c.get_joint_state().pos(), np.float64)[:JOINTS_PER_ARM]
                               for c in self._controllers])

    @property
    def joint_count(self) -> int:
        return JOINTS_PER_ARM * len(self._controllers)

    def _command(self, action: np.ndarray, lead_s: float) -> None:
        for i, (controller, width) in enumerate(zip(self._controllers, self._gripper_width)):
            pose, gripper01 = action_to_pose6d(action[10 * i:10 * i + 10])
            cmd = self._arx5.EEFState(pose, gripper01 * width)
            # the SDK interpolates to the target over lead_s, so motion is smooth at its 500 Hz
            cmd.timestamp = controller.get_timestamp() + lead_s
            controller.set_eef_cmd(cmd)

    def apply(self, action: np.ndarray) -> StepResult:
        self._command(action, self._period)
        return StepResult(obs=None)   # the bridge observes at the end of the control period

    def hold(self) -> None:
        self._command(self.current_action(), 0.0)

    def emergency_stop(self) -> None:
        """The e-stop thread's hold, concurrent with the loop's calls: arx5-sdk's controllers guard their command
        and state with their own mutexes, so a hold set here wins over a target set just before it, and the
        bridge sends the loop's next command only after checking the latch."""
        self.hold()

    def home(self) -> None:
        for controller in self._controllers:
            controller.reset_to_home()

    def reset(self, seed: int | None = None) -> tuple[dict[str, np.ndarray], dict]:
        """Home both arms; the operator resets the scene before the client's first chunk."""
        self.home()
        time.sleep(0.5)   # let the arms settle before the first decision frame
        return self.observe(), {"homed": True}

    def set_render_images(self, enabled: bool) -> None:
        self._render = bool(enabled)

    def close(self) -> None:
        """Hold the arms where they are (homing is explicit) and stop the camera streams."""
        self.hold()
        for stream in self._streams:
            stream.stop()
        self._streams.clear()
