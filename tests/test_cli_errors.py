"""Every console script answers a bad invocation with a non-zero exit, no traceback, and a line naming the fix.

One table for all five programs: a missing, truncated, foreign or crafted file, an unknown task, an impossible
number, a service that is not there. Each row runs the program's own ``main`` (in this process, which is what
the console script calls; ``jepa-robot-bridge`` hands non-operator commands to ``jepa_robot.cli``),
and a few run as real console scripts in a subprocess.
"""
from __future__ import annotations

import contextlib
import io
import os
import subprocess
import sys

import pytest
import torch

from jepa_envs.cli import main as envs_main
from jepa_robot.cli import main as bridge_main
from jepa_policy.checkpoint import FORMAT
from jepa_policy.cli import main as policy_main
from jepa_policy.demo.cli import main as demo_main
from monitor_service.cli import main as monitor_main

PROGRAMS = {"jepa-envs": envs_main, "jepa-policy": policy_main, "jepa-demo": demo_main,
            "jepa-monitor": monitor_main, "jepa-robot-bridge": bridge_main}


class _RunsCode:
    def __reduce__(self):
        return (os.system, ("true",))


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    root = tmp_path_factory.mktemp("bad")
    (root / "junk.hdf5").write_bytes(b"this is not HDF5")
    (root / "garbage.pt").write_bytes(b"hello world")
    good = root / "good.pt"
    torch.save({"format": FORMAT, "step": 1, "weights": torch.zeros(1000)}, good)
    (root / "truncated.pt").write_bytes(good.read_bytes()[:600])
    torch.save({"format": FORMAT, "ema": _RunsCode()}, root / "crafted.pt")
    (root / "bad.toml").write_text("this is = not [toml")
    (root / "safety.toml").write_text("[safety]\n")
    (root / "notjson.json").write_text("{")
    assert monitor_main(["--database-url", f"sqlite:///{root / 'm.db'}", "db", "upgrade"]) == 0   # an existing DB
    return root


# (program, argv, a piece of the one-line answer that names the problem or the fix)
BAD_INVOCATIONS = [
    ("jepa-envs", ["make-demos", "Nope", "--episodes", "1", "--out", "{d}/x.hdf5"], "known tasks"),
    ("jepa-envs", ["make-demos", "PushT", "--episodes", "0", "--out", "{d}/x.hdf5"], "--episodes must be >= 1"),
    ("jepa-envs", ["bench", "--task", "Nope"], "known tasks"),
    ("jepa-envs", ["install-mimicgen", "{d}/no-clone"], "clone it with"),
    ("jepa-envs", ["info", "Nope"], "known tasks"),
    ("jepa-policy", ["eval", "--checkpoint", "{d}/missing.pt"], "does not exist"),
    ("jepa-policy", ["eval", "--checkpoint", "{d}/garbage.pt"], "not a readable checkpoint"),
    ("jepa-policy", ["eval", "--checkpoint", "{d}/truncated.pt"], "not a readable checkpoint"),
    ("jepa-policy", ["eval", "--checkpoint", "{d}/crafted.pt"], "could run code"),
    ("jepa-policy", ["audit", "--checkpoint", "{d}/garbage.pt", "--dataset", "{d}/junk.hdf5"], "not a readable"),
    ("jepa-policy", ["protocols", "{d}/no-run"], "does not exist"),
    ("jepa-policy", ["protocols", "{d}/crafted.pt"], "could run code"),
    ("jepa-policy", ["train", "--task", "Nope"], "known tasks"),
    ("jepa-policy", ["train", "--task", "PushT", "--dataset", "{d}/missing.hdf5"], "make one with"),
    ("jepa-policy", ["train", "--task", "PushT", "--preset", "quick", "--dataset", "{d}/junk.hdf5"],
     "not a readable HDF5 file"),
    ("jepa-policy", ["train", "--task", "PushT", "--preset", "nope"], "choose one of"),
    ("jepa-policy", ["train", "--config", "{d}/missing.json"], "does not exist"),
    ("jepa-policy", ["describe", "--task", "Nope"], "known tasks"),
    ("jepa-policy", ["bench", "latency", "--task", "Nope"], "known tasks"),
    ("jepa-policy", ["robot", "--checkpoint", "{d}/missing.pt"], "train one with"),
    ("jepa-policy", ["robot", "--checkpoint", "{d}/crafted.pt", "--no-wait"], "could run code"),
    ("jepa-policy", ["serve", "--checkpoint", "{d}/missing.pt"], "train one with"),
    ("jepa-policy", ["serve", "--checkpoint", "{d}/crafted.pt"], "could run code"),
    ("jepa-policy", ["serve", "--checkpoint", "{d}/good.pt", "--host", "0.0.0.0"], "pass --api-key KEY"),
    ("jepa-envs", ["lerobot", "import", "{d}/no-root", "{d}/x.hdf5", "--task", "PushT"], "no-root does not exist"),
    ("jepa-envs", ["lerobot", "export", "{d}/junk.hdf5", "{d}/out"], "not a readable HDF5 file"),
    ("jepa-envs", ["render-dataset", "{d}/junk.hdf5", "{d}/out.hdf5"], "not a readable HDF5 file"),
    ("jepa-demo", ["ceiling", "--dataset", "{d}/missing.hdf5"], "make-demos"),
    ("jepa-demo", ["ceiling", "--dataset", "{d}/junk.hdf5"], "not a readable HDF5 file"),
    ("jepa-demo", ["--steps", "0"], "positive number"),
    ("jepa-monitor", ["--database-url", "nope://x", "db", "upgrade"], "use sqlite:///path.db"),
    ("jepa-monitor", ["--database-url", "sqlite:///{d}/m.db", "db", "restore", "{d}/junk.hdf5"],
     "not an SQLite database"),
    ("jepa-monitor", ["--database-url", "sqlite:///{d}/m.db", "calibrate", "--task", "Nope"], "register it"),
    ("jepa-monitor", ["--database-url", "sqlite://", "db", "current"], "give a file: sqlite:///"),
    ("jepa-monitor", ["--database-url", "sqlite:///", "db", "upgrade"], "give a file: sqlite:///"),
    ("jepa-monitor", ["--database-url", "sqlite:///:memory:", "serve", "--port", "0"], "give a file: sqlite:///"),
    ("jepa-monitor", ["--database-url", "", "db", "current"], "--database-url is empty; give sqlite:///"),
    ("jepa-monitor", ["--database-url", "", "serve", "--create"], "--database-url is empty; give sqlite:///"),
    ("jepa-monitor", ["--database-url", "sqlite:///{d}/m.db", "db", "backup", "{d}/nofolder/b.db"],
     "does not exist; create it (mkdir -p"),
    ("jepa-monitor", ["--database-url", "sqlite:///{d}/m.db", "db", "backup", "{d}"], "is a folder; give a file"),
    ("jepa-robot-bridge", ["serve", "--backend", "sim", "--task", "Nope"], "known tasks"),
    ("jepa-robot-bridge", ["serve", "--backend", "arx5"], "needs --config"),
    ("jepa-robot-bridge", ["serve", "--backend", "replay", "--episode", "{d}/missing.json"], "not found"),
    ("jepa-robot-bridge", ["serve", "--backend", "sim", "--task", "PushT", "--bind", "tcp://0.0.0.0:5999"],
     "--insecure-network"),
    ("jepa-robot-bridge", ["check", "{d}/missing.toml"], "not found"),
    ("jepa-robot-bridge", ["check", "{d}/bad.toml"], "not valid TOML"),
    ("jepa-robot-bridge", ["check", "{d}/safety.toml", "--task", "Nope"], "known tasks"),
    ("jepa-robot-bridge", ["observe", "--address", "tcp://127.0.0.1:9", "--seconds", "0.1", "--timeout", "0.5"],
     "did not answer"),
    ("jepa-robot-bridge", ["status", "--operator", "tcp://127.0.0.1:9", "--timeout", "0.3"], "no robot bridge"),
]


@pytest.mark.parametrize("program, argv, fix", BAD_INVOCATIONS,
                         ids=[f"{p} {' '.join(a)[:60]}" for p, a, _ in BAD_INVOCATIONS])
def test_bad_invocation_gets_one_line_naming_the_fix(program, argv, fix, files):
    argv = [a.format(d=files) for a in argv]
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = PROGRAMS[program](argv)
        except SystemExit as exc:   # argparse and the launchers exit with a message; never an exception
            code = exc.code if isinstance(exc.code, int) else 1
            if isinstance(exc.code, str):
                err.write(exc.code)
    text = out.getvalue() + err.getvalue()
    assert code not in (0, None), f"{program} {argv} succeeded:\n{text}"
    assert "Traceback" not in text
    assert fix in text, f"{program} {argv} did not name the fix ({fix!r}):\n{text}"


@pytest.mark.parametrize("argv", [
    ["jepa-policy", "eval", "--checkpoint", "{d}/truncated.pt"],
    ["jepa-demo", "ceiling", "--dataset", "{d}/missing.hdf5"],
    ["jepa-robot-bridge", "check", "{d}/safety.toml", "--task", "Nope"],
])
def test_console_scripts_exit_without_a_traceback(argv, files):
    bindir = os.path.dirname(sys.executable)
    script = os.path.join(bindir, argv[0])
    command = [script] if os.path.exists(script) else [argv[0]]
    out = subprocess.run(command + [a.format(d=files) for a in argv[1:]], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode != 0 and "Traceback" not in out.stderr + out.stdout
    assert len((out.stderr.strip() or out.stdout.strip()).splitlines()) == 1, out.stderr


@pytest.mark.parametrize("argv", [
    ["--database-url", "", "db", "upgrade"],             # used to fall back to ./jepa_monitor.db and create it
    ["--database-url", "sqlite://", "db", "upgrade"],
    ["--database-url", "sqlite:///:memory:", "serve", "--create", "--port", "0"],
])
def test_a_refused_database_url_creates_nothing(argv, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("JEPA_MONITOR_DATABASE_URL", raising=False)
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        assert monitor_main(argv) == 2
    assert len(err.getvalue().strip().splitlines()) == 1 and "Traceback" not in err.getvalue()
    assert list(tmp_path.iterdir()) == []
