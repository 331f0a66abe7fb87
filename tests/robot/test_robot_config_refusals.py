"""No configuration value switches a safety rule off (issue 35, part 4): ``check`` and ``serve`` refuse each one
with a one-line reason naming the field, before any hardware moves.

A NaN compares false with everything (``jump > nan`` never fires), an infinite deadline never expires, and a
workspace bound beyond the backend's own range bounds nothing; all of these used to pass ``check``.
"""
from __future__ import annotations

import pytest

from jepa_envs.real_robot.cli import EXIT_REFUSED
from jepa_envs.real_robot.cli import main as bridge_main

# (one line of a sim [safety] table, what the one-line reason must say)
SWITCHES_OFF = [
    ("max_step_delta = nan", "safety.max_step_delta: Input should be a finite number"),
    ("max_step_delta = inf", "safety.max_step_delta: Input should be a finite number"),
    ("max_step_delta = [60.0, nan]", "safety.max_step_delta: Input should be a finite number"),
    ("max_step_delta = 0.0", "max_step_delta must be > 0"),
    ("command_deadline_s = nan", "safety.command_deadline_s: Input should be a finite number"),
    ("command_deadline_s = inf", "safety.command_deadline_s: Input should be a finite number"),
    ("command_deadline_s = 0.0", "the command watchdog cannot be switched off"),
    ("command_deadline_s = 1e9", "the command watchdog cannot be switched off"),
    ("link_grace_s = nan", "safety.link_grace_s: Input should be a finite number"),
    ("link_grace_s = inf", "safety.link_grace_s: Input should be a finite number"),
    ("heartbeat_interval_s = nan", "safety.heartbeat_interval_s: Input should be a finite number"),
    ("heartbeat_interval_s = 0.0", "safety.heartbeat_interval_s: must be > 0"),
    ("heartbeat_interval_s = 0.5", "heartbeat_interval_s (0.5s) must be below the link timeout"),
    ("link_timeout_s = nan", "safety.link_timeout_s: Input should be a finite number"),
    ("link_timeout_s = inf", "safety.link_timeout_s: Input should be a finite number"),
    ("link_timeout_s = 3.0", "must be below command_deadline_s"),
    ("action_low = [-1.7e308, -1.7e308]", "safety.action_low leaves the backend's own action range"),
    ("action_high = [1.7e308, 1.7e308]", "safety.action_high leaves the backend's own action range"),
    ("action_low = [nan, 0.0]", "safety.action_low: Input should be a finite number"),
    ("joint_low = [nan]", "safety.joint_low: Input should be a finite number"),
    ('on_violation = "ignore"', "safety.on_violation: Input should be 'refuse' or 'clip'"),
]


@pytest.mark.parametrize("line, reason", SWITCHES_OFF, ids=[line for line, _ in SWITCHES_OFF])
def test_check_and_serve_refuse_every_value_that_switches_safety_off(tmp_path, capsys, line, reason):
    setup = tmp_path / "safety.toml"
    setup.write_text(f"[safety]\n{line}\n")
    assert bridge_main(["check", str(setup), "--task", "PushT"]) == 1
    errors = [row for row in capsys.readouterr().out.splitlines() if row.startswith("error:")]
    assert len(errors) == 1 and reason in errors[0], errors
    assert bridge_main(["serve", "--backend", "sim", "--task", "PushT", "--config", str(setup), "--bind",
                        "tcp://127.0.0.1:*", "--operator-bind", "tcp://127.0.0.1:*", "--no-prompt"]) == EXIT_REFUSED
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and reason in err[0], err


def test_check_says_which_rules_are_off(tmp_path, capsys):
    """A rule left out on purpose (no jump limit) is allowed, and said aloud."""
    setup = tmp_path / "safety.toml"
    setup.write_text("[safety]\ncommand_deadline_s = 30.0\n")
    assert bridge_main(["check", str(setup), "--task", "PushT"]) == 0
    assert "WARNING safety.max_step_delta is not set: no per-step jump limit" in capsys.readouterr().out
