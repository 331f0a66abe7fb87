"""No configuration value switches a safety rule off: ``check`` and ``serve`` refuse each one
with a one-line reason naming the field, before any hardware moves.

A NaN compares false with everything (``jump > nan`` never fires), an infinite deadline never expires, and a
workspace bound beyond the backend's own range bounds nothing; all of these used to pass ``check``.
"""
from __future__ import annotations

import pytest

from jepa_robot.cli import EXIT_REFUSED
from jepa_robot.cli import main as bridge_main

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
    ("heartbeat_interval_s = 0.5", "heartbeat_interval_s (0.5s) must be at most half the link timeout"),
    # values so small the bridge cannot keep them: pings every nanosecond wedged its loop
    ("heartbeat_interval_s = 1e-9", "safety.heartbeat_interval_s: must be at least 0.001 seconds"),
    ("link_timeout_s = 1e-8", "safety.link_timeout_s: must be at least 0.005 seconds"),
    ("command_deadline_s = 1e-7", "safety.command_deadline_s: must be at least 0.01 seconds"),
    ("link_timeout_s = 0.01\ncommand_deadline_s = 0.05", "must be at least one control period"),
    ("link_timeout_s = 0.01\nheartbeat_interval_s = 0.006", "must be at most half of link_timeout_s"),
    # huge finite limits switch a rule off as surely as NaN (F5)
    ("max_step_delta = 1e300", "max_step_delta is at or beyond the action range's width"),
    ("max_step_delta = 99999999999999999999", "max_step_delta is at or beyond the action range's width"),
    ("max_step_delta = [1e300, 5.0]", "max_step_delta is at or beyond the action range's width at indices [0]"),
    ("action_high = [100.0, 100.0]\nmax_step_delta = 100.0", "at or beyond the action range's width"),
    # a number is a number: TOML true is not 1.0, "inf" is not a number (F6)
    ("command_deadline_s = true", "safety.command_deadline_s: must be a number, not bool"),
    ('command_deadline_s = "inf"', "safety.command_deadline_s: must be a number, not str"),
    ("max_step_delta = [true, 5.0]", "safety.max_step_delta: must be a number, not bool"),
    ("link_timeout_s = nan", "safety.link_timeout_s: Input should be a finite number"),
    ("link_timeout_s = inf", "safety.link_timeout_s: Input should be a finite number"),
    ("link_timeout_s = 3.0", "must be below command_deadline_s"),
    ("action_low = [-1.7e308, -1.7e308]", "safety.action_low leaves the backend's own action range"),
    ("action_high = [1.7e308, 1.7e308]", "safety.action_high leaves the backend's own action range"),
    ("action_low = [nan, 0.0]", "safety.action_low: Input should be a finite number"),
    ("joint_low = [nan]", "safety.joint_low: Input should be a finite number"),
    ('on_violation = "ignore"', "safety.on_violation: Input should be 'refuse' or 'clip'"),
]


# whole files: a misspelt table leaves every rule at its default (F6)
BAD_FILES = [
    ("[saftey]\nmax_step_delta = 5.0\n", "unknown top-level table or key 'saftey'"),
    ("[Safety]\nmax_step_delta = 5.0\n", "unknown top-level table or key 'Safety'"),
    ('safety = "off"\n', "safety must be a [safety] table"),
]


@pytest.mark.parametrize("line, reason", SWITCHES_OFF, ids=[line for line, _ in SWITCHES_OFF])
def test_check_and_serve_refuse_every_value_that_switches_safety_off(tmp_path, capsys, line, reason, text=None):
    setup = tmp_path / "safety.toml"
    setup.write_text(text or f"[safety]\n{line}\n")
    assert bridge_main(["check", str(setup), "--task", "PushT"]) == 1
    errors = [row for row in capsys.readouterr().out.splitlines() if row.startswith("error:")]
    assert len(errors) == 1 and reason in errors[0], errors
    assert bridge_main(["serve", "--backend", "sim", "--task", "PushT", "--config", str(setup), "--bind",
                        "tcp://127.0.0.1:*", "--operator-bind", "tcp://127.0.0.1:*", "--no-prompt"]) == EXIT_REFUSED
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and reason in err[0], err


@pytest.mark.parametrize("text, reason", BAD_FILES, ids=[t.split("\n")[0] for t, _ in BAD_FILES])
def test_check_and_serve_refuse_a_misspelt_table(tmp_path, capsys, text, reason):
    test_check_and_serve_refuse_every_value_that_switches_safety_off(tmp_path, capsys, None, reason, text)


def test_arx5_joint_limits_outside_the_arms_range_are_refused(tmp_path, capsys):
    """+-1e308 joint limits are finite but bound nothing (F5)."""
    from pathlib import Path
    text = Path(__file__).resolve().parents[2].joinpath("deploy/robot/arx5_cabinet.toml").read_text()
    assert "joint_low = [-3.0," in text
    text = text.replace("joint_low = [-3.0,", "joint_low = [-1e308,")
    text = text.replace('control_address = "tcp://0.0.0.0:5555"', 'control_address = "tcp://127.0.0.1:5555"')
    setup = tmp_path / "arx5.toml"
    setup.write_text("\n".join(row for row in text.splitlines() if not row.startswith("curve_")))
    assert bridge_main(["check", str(setup)]) == 1
    errors = [row for row in capsys.readouterr().out.splitlines() if row.startswith("error:")]
    assert any("safety.joint_low leaves the robot's joint range" in e and "joints [0]" in e for e in errors), errors


def test_check_says_which_rules_are_off(tmp_path, capsys):
    """A rule left out on purpose (no jump limit) is allowed, and said aloud."""
    setup = tmp_path / "safety.toml"
    setup.write_text("[safety]\ncommand_deadline_s = 30.0\n")
    assert bridge_main(["check", str(setup), "--task", "PushT"]) == 0
    assert "WARNING safety.max_step_delta is not set: no per-step jump limit" in capsys.readouterr().out


UNREADABLE = {
    "nested arrays": "[safety]\nmax_step_delta = " + "[" * 5000 + "]" * 5000 + "\n",
    "nested tables": "[safety]\nx = " + "{a=" * 3000 + "1" + "}" * 3000 + "\n",
    "a 5,000-digit integer": "[safety]\nmax_step_delta = " + "9" * 5000 + "\n",
}


@pytest.mark.parametrize("name", list(UNREADABLE))
def test_a_file_no_reader_can_take_is_one_line_everywhere(tmp_path, name):
    """Deeply nested TOML (a RecursionError inside tomllib) and an integer beyond Python's 4,300-digit limit: check
    printed a traceback, serve exited 1 with 2,995 lines of one, and supervise retried it forever (17,976 lines in
    60 s). Now: check one line (exit 1), serve one line (exit 2), supervise exit 2 without a restart."""
    import subprocess
    import sys
    setup = tmp_path / "setup.toml"
    setup.write_text(UNREADABLE[name])
    bridge = [sys.executable, "-m", "jepa_robot.cli"]
    out = subprocess.run([*bridge, "check", str(setup), "--task", "PushT"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 1 and "Traceback" not in out.stderr + out.stdout, out
    assert len((out.stdout + out.stderr).strip().splitlines()) == 1, out
    for command in (["serve"], ["supervise", "--state-file", str(tmp_path / "state.json")]):
        out = subprocess.run([*bridge, *command, "--backend", "sim", "--task", "PushT", "--config", str(setup),
                              "--no-prompt"], capture_output=True, text=True, timeout=120)
        lines = out.stderr.strip().splitlines()
        assert out.returncode == EXIT_REFUSED and "Traceback" not in out.stderr, out
        assert len(lines) == (1 if command == ["serve"] else 2) and "restart" not in out.stderr, lines


SETUP_REFUSALS = {   # serve's arguments (after --no-prompt), what its one error line must say
    "an image side of 100,000 px (a 27.9 GiB array)": (["--backend", "sim", "--task", "PushT", "--image-size",
                                                         "100000"], "--image-size 100000: give a side"),
    "--max-rss-mb nan (the guard silently off)": (["--backend", "sim", "--task", "PushT", "--max-rss-mb", "nan"],
                                                  "--max-rss-mb nan: give"),
    "--max-rss-mb -1": (["--backend", "sim", "--task", "PushT", "--max-rss-mb", "-1"], "--max-rss-mb -1: give"),
    "--max-rss-mb inf": (["--backend", "sim", "--task", "PushT", "--max-rss-mb", "inf"], "--max-rss-mb inf: give"),
    "a replay manifest nested 200,000 deep": (["--backend", "replay", "--episode", "{deep}"], "nested too deeply"),
}


@pytest.mark.parametrize("name", list(SETUP_REFUSALS))
def test_set_up_values_that_crashed_serve_are_one_line(tmp_path, capsys, name):
    """Each of these made serve exit 1 with a traceback (a RecursionError, numpy's _ArrayMemoryError) or start with
    the memory guard off; now one line, exit 2, before any backend is built."""
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 200_000)
    args, says = SETUP_REFUSALS[name]
    code = bridge_main(["serve", "--no-prompt", "--state-file", str(tmp_path / "state.json"),
                        *[a.replace("{deep}", str(deep)) for a in args]])
    err = capsys.readouterr().err
    assert code == EXIT_REFUSED and len(err.strip().splitlines()) == 1 and says in err, err


def test_thousands_of_unknown_keys_give_a_bounded_answer(tmp_path, capsys):
    """A [safety] table of 20,000 unknown keys printed 20,000 error lines; now the first 10 and a count."""
    setup = tmp_path / "safety.toml"
    setup.write_text("[safety]\n" + "".join(f"k{i} = 1\n" for i in range(20_000)))
    code = bridge_main(["serve", "--no-prompt", "--backend", "sim", "--task", "PushT", "--config", str(setup)])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == EXIT_REFUSED and len(lines) == 11 and "and 19990 more" in lines[-1], lines[:3] + lines[-2:]


def test_a_state_file_no_parser_can_read_starts_latched(tmp_path):
    """A state file nested 200,000 deep raised RecursionError at every start (a crash loop under supervise); it is
    unreadable, so the bridge starts latched, as documented."""
    from jepa_robot.estop import EStop
    for content in ("[" * 200_000, "{" * 5_000 + "}" * 5_000, "x" * 100_000, b"\xff\xfe"):
        state = tmp_path / "state.json"
        state.write_bytes(content if isinstance(content, bytes) else content.encode())
        estop = EStop(lambda: None, str(state))
        assert estop.restore() is not None and estop.latched, content[:20]
