"""The ARX-5 backend without hardware: its config, its action conversions and its missing-SDK error."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.spatial.transform import Rotation

from jepa_robot.backends.arx5 import (ARX5Backend, ARX5Config, action_to_pose6d, import_hardware_sdks,
                                               load_arx5_config, pose6d_to_action)
from jepa_robot.backends.base import BackendUnavailable
from jepa_robot.cli import main

EXAMPLE = Path(__file__).resolve().parents[2] / "deploy" / "robot" / "arx5_cabinet.toml"
SDK_PRESENT = importlib.util.find_spec("arx5_interface") is not None and \
    importlib.util.find_spec("pyrealsense2") is not None


@pytest.mark.skipif(SDK_PRESENT, reason="arx5_interface and pyrealsense2 are installed: the missing-SDK path "
                                        "cannot occur on this machine")
def test_missing_sdk_error_names_what_to_install(capsys):
    with pytest.raises(BackendUnavailable, match="arx5-sdk.*pyrealsense2"):
        import_hardware_sdks()
    with pytest.raises(BackendUnavailable, match="arx5_interface"):
        ARX5Backend(load_arx5_config(EXAMPLE))
    assert main(["--backend", "arx5", "--config", str(EXAMPLE)]) == 2
    err = capsys.readouterr().err
    assert "arx5-sdk" in err and "pyrealsense2" in err


def test_example_config_is_valid_for_cabinet():
    config = load_arx5_config(EXAMPLE)
    assert config.task == "Cabinet" and [a.name for a in config.arms] == ["left", "right"]
    assert len(config.safety.max_step_delta) == 20 and len(config.safety.joint_low) == 12
    assert config.safety.resolved_link_timeout(10.0) == pytest.approx(0.1)


def test_config_errors_name_the_fix(tmp_path):
    base = load_arx5_config(EXAMPLE).model_dump()
    with pytest.raises(ValidationError, match="uses arms \\['left', 'right'\\]"):
        ARX5Config.model_validate({**base, "arms": base["arms"][:1]})
    with pytest.raises(ValidationError, match="add \\['right_wrist'\\]"):
        ARX5Config.model_validate({**base, "cameras": base["cameras"][:2]})
    with pytest.raises(ValidationError, match="not a real-robot task"):
        ARX5Config.model_validate({**base, "task": "PushT"})
    with pytest.raises(ValidationError, match="below workspace_high"):
        ARX5Config.model_validate({**base, "workspace_low": [0.6, 0.0, 0.0]})
    with pytest.raises(FileNotFoundError, match="arx5_cabinet.toml"):
        load_arx5_config(tmp_path / "missing.toml")


def test_pose_action_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(20):
        pose = np.r_[rng.uniform(0.1, 0.4, 3), rng.uniform(-1.2, 1.2, 3)]
        action = pose6d_to_action(pose, 0.7)
        assert action.shape == (10,) and action[9] == 0.7
        back, gripper = action_to_pose6d(action)
        np.testing.assert_allclose(back[:3], pose[:3])
        relative = Rotation.from_euler("xyz", back[3:]).inv() * Rotation.from_euler("xyz", pose[3:])
        assert relative.magnitude() < 1e-9 and gripper == 0.7
