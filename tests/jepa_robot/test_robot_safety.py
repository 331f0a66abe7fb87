import numpy as np
import pytest
from pydantic import ValidationError

from jepa_robot.safety import (ActionGuard, InvalidAction, SafetyConfig, joint_limit_violation,
                                         validate_action, validate_chunk)

LOW, HIGH = np.zeros(3), np.ones(3)


def test_invalid_actions_refused_with_reason():
    with pytest.raises(InvalidAction, match="NaN or infinite entries at indices \\[1\\]"):
        validate_action([0.1, np.nan, 0.2], 3)
    with pytest.raises(InvalidAction, match="NaN or infinite"):
        validate_action([0.1, np.inf, 0.2], 3)
    with pytest.raises(InvalidAction, match=r"shape \(2,\).*needs \(3,\)"):
        validate_action([0.1, 0.2], 3)
    with pytest.raises(InvalidAction, match="numeric"):
        validate_action(["a", "b", "c"], 3)
    with pytest.raises(InvalidAction, match=r"\(N, 3\)"):
        validate_chunk(np.zeros((4, 2)), 3)
    with pytest.raises(InvalidAction, match="NaN"):
        validate_chunk([[0, 0, 0], [0, np.nan, 0]], 3)


def test_degenerate_rotation_refused():
    good = np.r_[0, 0, 0, 1, 0, 0, 0, 1, 0, 1.0]
    assert np.array_equal(validate_action(good, 10, [3]), good)
    parallel = np.r_[0, 0, 0, 1, 0, 0, 2, 0, 0, 1.0]
    with pytest.raises(InvalidAction, match="degenerate"):
        validate_action(parallel, 10, [3])
    with pytest.raises(InvalidAction, match="degenerate"):
        validate_action(np.zeros(10), 10, [3])


def test_bounds_refuse_and_clip():
    refuse = ActionGuard(SafetyConfig(), LOW, HIGH)
    v = refuse.check(np.array([0.5, 1.5, -0.1]), None)
    assert v.refused and "indices [1, 2]" in v.violations[0]
    assert refuse.check(np.array([0.5, 0.5, 0.5]), None).violations == []
    clip = ActionGuard(SafetyConfig(on_violation="clip"), LOW, HIGH)
    v = clip.check(np.array([0.5, 1.5, -0.1]), None)
    assert not v.refused and v.clipped and np.array_equal(v.action, [0.5, 1.0, 0.0])
    assert v.report() == {"refused": False, "clipped": True, "violations": v.violations}


def test_configured_workspace_overrides_backend_bounds():
    guard = ActionGuard(SafetyConfig(action_low=[0.2] * 3, action_high=[0.8] * 3), LOW, HIGH)
    assert guard.check(np.array([0.1, 0.5, 0.5]), None).refused
    with pytest.raises(ValueError, match="need 3 entries"):
        ActionGuard(SafetyConfig(action_low=[0.0] * 2, action_high=[1.0] * 2), LOW, HIGH)
    with pytest.raises(ValueError, match="<= action_high"):
        ActionGuard(SafetyConfig(action_low=[1.0] * 3, action_high=[0.0] * 3), LOW, HIGH)


def test_jump_limit_refuse_and_clip():
    prev = np.array([0.5, 0.5, 0.5])
    refuse = ActionGuard(SafetyConfig(max_step_delta=0.1), LOW, HIGH)
    assert not refuse.check(np.array([0.55, 0.45, 0.5]), prev).violations
    v = refuse.check(np.array([0.8, 0.5, 0.5]), prev)
    assert v.refused and "jump" in v.violations[0] and "[0]" in v.violations[0]
    assert not refuse.check(np.array([0.8, 0.5, 0.5]), None).refused  # first action: no reference yet
    clip = ActionGuard(SafetyConfig(max_step_delta=[0.1, 0.1, 0.1], on_violation="clip"), LOW, HIGH)
    v = clip.check(np.array([0.8, 0.2, 0.5]), prev)
    np.testing.assert_allclose(v.action, [0.6, 0.4, 0.5])
    with pytest.raises(ValueError, match="max_step_delta must be > 0"):
        ActionGuard(SafetyConfig(max_step_delta=0.0), LOW, HIGH)


def test_joint_limits():
    assert joint_limit_violation(np.array([0.0, 1.0]), np.array([-1, -1]), np.array([1, 1])) is None
    msg = joint_limit_violation(np.array([0.0, 1.5, -2.0]), np.full(3, -1.0), np.full(3, 1.0))
    assert "joints [1, 2]" in msg
    guard = ActionGuard(SafetyConfig(joint_low=[-1.0, -1.0], joint_high=[1.0, 1.0]), LOW, HIGH)
    assert guard.joint_violation(None) is None  # backends without joints
    assert "joints [0]" in guard.joint_violation(np.array([1.2, 0.0]))


def test_config_validation():
    with pytest.raises(ValidationError, match="command_deadline_s"):
        SafetyConfig(command_deadline_s=0)
    with pytest.raises(ValidationError, match="on_violation"):
        SafetyConfig(on_violation="ignore")
    with pytest.raises(ValidationError, match="extra"):
        SafetyConfig(max_jump=1.0)
    cfg = SafetyConfig()
    assert cfg.resolved_link_timeout(10.0) == pytest.approx(0.1)  # one control period
    assert cfg.resolved_heartbeat(10.0) == pytest.approx(0.025)
