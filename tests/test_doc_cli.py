"""Docs and CLI stay one truth: every command line that README.md, docs/*.md and the two runbooks
show is parsed by the real argument parser of its command (parsed only, never run), and every Python snippet
marked runnable (a fenced block opened with ```python run) runs; every other Python snippet at least compiles.

Command lines are the lines of code blocks (fenced, or indented by four spaces) that start with one of the console
scripts, ``python -m`` of one of their modules or ``torchrun ... -m jepa_policy.cli``, joined with their
backslash continuations. Shell variables are expanded from the ``export`` lines above them in the same document
(the runbooks' set-up blocks), so a runbook's ``jepa-robot-bridge serve $BRIDGE_ARGS`` is checked with the
arguments it really gets. A failure names the document, its line, the command and the parser's own message.

Runnable snippets run as a script in a folder that holds what the documents assume a reader has made by then:
``demos.hdf5`` (PushT demonstrations) and a PushT ``cpu``-preset-sized checkpoint at
``runs/jepa/checkpoints/latest.pt`` (48 px, a few training steps), the README's ``jepa-policy train`` output.
"""
from __future__ import annotations

import argparse
import os
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), ROOT / "deploy" / "RUNBOOK.md",
        ROOT / "deploy" / "robot" / "RUNBOOK.md"]


def _main(module: str):
    def run(argv: list[str]) -> int:
        return __import__(module, fromlist=["main"]).main(argv)
    return run


# console script -> the function that parses its command line (the module ``python -m`` runs is an alias)
CLIS = {
    "jepa-envs": _main("jepa_envs.cli"),
    "jepa-policy": _main("jepa_policy.cli"),
    "jepa-monitor": _main("monitor_service.cli"),
    "jepa-robot-bridge": _main("jepa_robot.cli"),   # what jepa_robot.operator_cli hands everything to
    "jepa-demo": _main("jepa_policy.demo.cli"),
}
MODULES = {"jepa_envs.cli": "jepa-envs", "jepa_policy.cli": "jepa-policy", "monitor_service.cli": "jepa-monitor",
           "jepa_robot.cli": "jepa-robot-bridge", "jepa_robot.operator_cli": "jepa-robot-bridge",
           "jepa_policy.demo.cli": "jepa-demo"}
SHELL = {"|", "||", "&", "&&", ";", ">", ">>", "<", "2>&1", ")", "("}
# placeholders the documents write in capitals where the parser wants a number
NUMBERS = {"ID": "3", "N": "4", "K": "4", "S": "4", "P": "8765"}


@dataclass(frozen=True)
class Command:
    doc: Path
    line: int
    text: str          # as the document shows it (continuations joined)
    cli: str
    argv: tuple[str, ...]

    @property
    def where(self) -> str:
        return f"{self.doc.relative_to(ROOT)}:{self.line}"


def code_lines(text: str) -> list[tuple[int, str, str]]:
    """(line number, line, block info) of every line inside a code block: fenced (info = the opening's info
    string) or indented by four spaces after a blank line (info = "indented")."""
    out, fence, indented, previous_blank = [], None, False, True
    for number, line in enumerate(text.splitlines(), 1):
        stripped = line.strip()
        if fence is not None:
            if stripped.startswith("```"):
                fence = None
            else:
                out.append((number, line, fence))
            continue
        if stripped.startswith("```"):
            fence, indented = stripped[3:].strip(), False
        elif line.startswith("    ") and (indented or previous_blank) and stripped:
            indented = True
            out.append((number, line, "indented"))
        elif stripped:
            indented = False
        previous_blank = not stripped
    return out


ALTERNATIVE = re.compile(r"(?<=[^\s|])\|[^\s\]|]+")   # the "|av1" of "lossless|av1" (no spaces: not a pipe)


def synopsis_as_command(text: str) -> str:
    """A synopsis line as the longest command it allows: optional parts ``[...]`` included, the first of the
    alternatives ``a|b|c`` taken (a ``|`` between spaces stays a shell pipe)."""
    while ALTERNATIVE.search(text):
        text = ALTERNATIVE.sub("", text)
    return text.replace("[", " ").replace("]", " ")


def _split(command: str) -> list[str]:
    lexer = shlex.shlex(command, posix=True, punctuation_chars=True)
    lexer.whitespace_split = True
    lexer.commenters = "#"
    return list(lexer)


def _start(tokens: list[str]) -> tuple[str, list[str]] | None:
    """The console script a token list runs and its arguments, or None when it runs none of ours."""
    while tokens and re.fullmatch(r"[A-Z_][A-Z0-9_]*=.*", tokens[0]):   # VAR=value before the command
        tokens = tokens[1:]
    if not tokens:
        return None
    if tokens[0] in CLIS:
        return tokens[0], tokens[1:]
    if tokens[0] in ("python", "python3", "torchrun") and "-m" in tokens:
        i = tokens.index("-m")
        if i + 1 < len(tokens) and tokens[i + 1] in MODULES:
            return MODULES[tokens[i + 1]], tokens[i + 2:]
    return None


def _expand(token: str, exports: dict[str, str]) -> list[str]:
    """A token with $NAME / ${NAME} replaced from the document's exports; an unquoted lone variable splits."""
    if re.fullmatch(r"\$\{?[A-Za-z_]\w*\}?", token):
        name = token.strip("${}")
        return _split(exports[name]) if name in exports else [token]
    return [re.sub(r"\$\{?([A-Za-z_]\w*)\}?", lambda m: exports.get(m.group(1), m.group(0)), token)]


def documented_commands(doc: Path) -> list[Command]:
    exports = {"PWD": "/tmp/doc", "HOME": "/tmp/home"}
    lines = code_lines(doc.read_text())
    found, i = [], 0
    while i < len(lines):
        number, line, info = lines[i]
        text = line.strip().removeprefix("$ ")
        while text.endswith("\\") and i + 1 < len(lines) and lines[i + 1][0] == lines[i][0] + 1:
            i += 1
            text = text[:-1] + " " + lines[i][1].strip()
        i += 1
        if not info.startswith(("python", "toml", "yaml", "json", "ini")):
            try:
                tokens = _split(synopsis_as_command(text) if _start(text.split()) and "[" in text else text)
            except ValueError:   # unbalanced quotes: a shell would refuse it too, if it is one of ours
                if _start(text.split()) is not None:
                    found.append(Command(doc, number, text, _start(text.split())[0], ("--unbalanced-quotes",)))
                continue
            if tokens[:1] == ["export"] and len(tokens) >= 2 and "=" in tokens[1]:
                name, _, value = tokens[1].partition("=")
                exports[name] = "".join(_expand(value, exports)) if "$" in value else value
                continue
            start = _start(tokens)
            if start is None:
                continue
            cli, args = start
            argv = []
            for token in args:
                if token in SHELL or set(token) <= set("|&;<>()"):
                    break
                argv += [NUMBERS.get(t, t) for t in _expand(token, exports)]
            found.append(Command(doc, number, text, cli, tuple(argv)))
    return found


class Parsed(Exception):
    """Raised from parse_args once the real parser accepted a command line: nothing of the command runs."""


def parse_only(command: Command, monkeypatch, capsys) -> str | None:
    """None when the command's own parser accepts the line, else the parser's message."""
    parse_args, parse_known_args = argparse.ArgumentParser.parse_args, argparse.ArgumentParser.parse_known_args
    state = {"depth": 0, "in_parse_args": False}

    def parse_args_and_stop(self, args=None, namespace=None):
        state["in_parse_args"] = True
        parse_args(self, args, namespace)
        raise Parsed()

    def parse_known_args_and_stop(self, args=None, namespace=None):
        # subparsers call parse_known_args inside the top-level parse: only a top-level call stops the command
        state["depth"] += 1
        try:
            result = parse_known_args(self, args, namespace)
        finally:
            state["depth"] -= 1
        if state["depth"] == 0 and not state["in_parse_args"]:
            raise Parsed()
        return result

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", parse_args_and_stop)
    monkeypatch.setattr(argparse.ArgumentParser, "parse_known_args", parse_known_args_and_stop)
    try:
        CLIS[command.cli](list(command.argv))
    except Parsed:
        return None
    except SystemExit as exc:
        if exc.code in (0, None):   # --help
            return None
        err = capsys.readouterr().err.strip().splitlines()
        return err[-1] if err else f"exit {exc.code}"
    finally:
        monkeypatch.undo()
    return "the command ran instead of parsing: its main() does work before parse_args"


COMMANDS = [c for doc in DOCS for c in documented_commands(doc)]


def inline_commands(doc: Path) -> list[Command]:
    """Commands named in the prose (a `...` span that starts with a console script), e.g. `jepa-policy eval
    --workers N`: references, often without their required arguments, so only their flags are checked."""
    text = doc.read_text()
    prose = re.sub(r"^```.*?^```", lambda m: "\n" * m.group(0).count("\n"), text, flags=re.S | re.M)
    found = []
    for m in re.finditer(r"`([^`]+)`", prose):
        span = " ".join(m.group(1).split())
        start = _start(span.split())
        if start is not None:
            tokens = synopsis_as_command(span).split()
            found.append(Command(doc, prose[:m.start()].count("\n") + 1, span, start[0],
                                 tuple(_start(tokens)[1])))
    return found


INLINE = [c for doc in DOCS for c in inline_commands(doc)]


def parser_of(command: Command, monkeypatch) -> argparse.ArgumentParser:
    """The (sub)parser the command's leading words select, taken from its console script without parsing."""
    captured = []

    def capture(self, args=None, namespace=None):
        captured.append((self, list(args)))   # as main() hands them over (jepa-robot-bridge adds "serve")
        raise Parsed()

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", capture)
    monkeypatch.setattr(argparse.ArgumentParser, "parse_known_args", capture)
    try:
        CLIS[command.cli](list(command.argv))
    except Parsed:
        pass
    finally:
        monkeypatch.undo()
    parser, argv = captured[0]
    for word in argv:
        subparsers = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        if word.startswith("-") or not subparsers or word not in subparsers[0].choices:
            break
        parser = subparsers[0].choices[word]
    return parser


def unknown_flags(command: Command, monkeypatch) -> list[str]:
    parser = parser_of(command, monkeypatch)
    known = {option for action in parser._actions for option in action.option_strings}
    return [flag for flag in (a.split("=")[0] for a in command.argv if a.startswith("--")) if flag not in known]


def test_every_console_script_is_documented_and_found():
    assert {c.cli for c in COMMANDS} == set(CLIS)
    assert len(COMMANDS) > 80, "fewer command lines than the documents show: the extraction broke"


def test_every_subcommand_is_shown(monkeypatch):
    """Each subcommand of each console script appears in a command line or the prose (this replaced
    tests/monitor_service/test_doc_commands.py, which parsed the jepa-monitor lines only)."""
    shown: dict[str, set[str]] = {}
    for c in COMMANDS + INLINE:
        shown.setdefault(c.cli, set()).update(c.argv[:1])
    missing = {}
    for cli in CLIS:
        parser = parser_of(Command(DOCS[0], 0, "", cli, ()), monkeypatch)
        subparsers = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        if subparsers and set(subparsers[0].choices) - shown[cli]:
            missing[cli] = sorted(set(subparsers[0].choices) - shown[cli])
    assert missing == {}, f"subcommands no document shows: {missing}"


@pytest.mark.parametrize("command", COMMANDS, ids=[f"{c.where} {c.cli}" for c in COMMANDS])
def test_documented_command_line_parses(command, monkeypatch, capsys):
    error = parse_only(command, monkeypatch, capsys)
    assert error is None, (f"{command.where}: `{command.text}` is refused by the {command.cli} parser "
                           f"(argv {list(command.argv)}): {error}")


@pytest.mark.parametrize("command", INLINE, ids=[f"{c.where} {c.cli} (prose)" for c in INLINE])
def test_flags_named_in_the_prose_exist(command, monkeypatch):
    assert unknown_flags(command, monkeypatch) == [], (
        f"{command.where}: `{command.text}` names flags the {command.cli} parser does not have")


def test_the_checker_catches_what_a_parser_refuses(monkeypatch, capsys, tmp_path):
    doc = tmp_path / "doc.md"
    doc.write_text("Text.\n\n```bash\nexport ARGS=\"--backend sim --no-such-flag\"\n"
                   "jepa-robot-bridge serve $ARGS --image-size 48   # comment\n"
                   "jepa-policy eval --checkpoint c.pt --episodes many\n"
                   "OMP_NUM_THREADS=1 python -m jepa_policy.cli describe --task PushT | tee out\n"
                   "jepa-envs lerobot export d.hdf5 out/ [--fps 10] [--codec lossless|av1]\n```\n\n"
                   "    jepa-monitor db upgrade\n")
    found = documented_commands(doc)
    assert [(c.line, c.cli, c.argv) for c in found] == [
        (5, "jepa-robot-bridge", ("serve", "--backend", "sim", "--no-such-flag", "--image-size", "48")),
        (6, "jepa-policy", ("eval", "--checkpoint", "c.pt", "--episodes", "many")),
        (7, "jepa-policy", ("describe", "--task", "PushT")),
        (8, "jepa-envs", ("lerobot", "export", "d.hdf5", "out/", "--fps", "10", "--codec", "lossless")),
        (11, "jepa-monitor", ("db", "upgrade"))]
    errors = [parse_only(c, monkeypatch, capsys) for c in found]
    assert "unrecognized arguments: --no-such-flag" in errors[0]
    assert "invalid int value: 'many'" in errors[1]
    assert errors[2:] == [None, None, None]
    doc.write_text("Run `jepa-policy eval --workers N` or `jepa-policy protocols --select --no-flag`.\n")
    prose = inline_commands(doc)
    assert [unknown_flags(c, monkeypatch) for c in prose] == [[], ["--no-flag"]]


# ----------------------------------------------------------------------------- Python snippets

@dataclass(frozen=True)
class Snippet:
    doc: Path
    line: int
    runnable: bool
    code: str

    @property
    def where(self) -> str:
        return f"{self.doc.relative_to(ROOT)}:{self.line}"


def python_snippets(doc: Path) -> list[Snippet]:
    out, fence, body = [], None, []
    for number, line in enumerate(doc.read_text().splitlines(), 1):
        stripped = line.strip()
        if fence is None and stripped.startswith("```python"):
            fence, body = (number, stripped[len("```python"):].split()), []
        elif fence is not None and stripped.startswith("```"):
            out.append(Snippet(doc, fence[0], "run" in fence[1], "\n".join(body) + "\n"))
            fence = None
        elif fence is not None:
            body.append(line)
    return out


SNIPPETS = [s for doc in DOCS for s in python_snippets(doc)]
RUNNABLE = [s for s in SNIPPETS if s.runnable]


@pytest.mark.parametrize("snippet", SNIPPETS, ids=[s.where for s in SNIPPETS])
def test_documented_python_compiles(snippet):
    try:
        compile(snippet.code, snippet.where, "exec")
    except SyntaxError as exc:
        pytest.fail(f"{snippet.where} (+{exc.lineno}): the snippet is not Python: {exc.msg}")


@pytest.fixture(scope="session")
def reader_folder(tmp_path_factory, pusht_demo_file):
    """What a reader has made when the snippets run: demos.hdf5 and the README's PushT checkpoint (48 px, as
    the cpu preset trains; a few steps, since the snippets need a checkpoint, not a good one)."""
    import shutil

    import torch

    from jepa_envs.datasets.hdf5 import load_dataset
    from jepa_policy.train import load_config, train

    folder = tmp_path_factory.mktemp("reader")
    shutil.copyfile(pusht_demo_file, folder / "demos.hdf5")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        demos = load_dataset(folder / "demos.hdf5", task="PushT", image_size=48)
        train(load_config("PushT", "quick", out_dir=str(folder / "runs" / "jepa"), image_size=48, steps=2,
                          warmup_steps=0, batch_size=4), demos)
    finally:
        torch.set_num_threads(threads)
    return folder


def test_the_documents_mark_runnable_snippets():
    assert {s.doc.name for s in RUNNABLE} >= {"training.md", "monitor.md"}


@pytest.mark.timeout(300)
@pytest.mark.parametrize("snippet", RUNNABLE, ids=[s.where for s in RUNNABLE])
def test_runnable_snippet_runs_as_written(snippet, reader_folder, tmp_path):
    script = tmp_path / "snippet.py"
    script.write_text(snippet.code)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, str(script)], cwd=reader_folder, env=env, capture_output=True,
                          text=True, timeout=240)
    assert done.returncode == 0, f"{snippet.where}: the snippet failed:\n{done.stderr[-3000:]}"


def _free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.mark.timeout(300)
def test_the_readme_bridge_and_robot_pair_runs_as_written(reader_folder, tmp_path, capsys):
    """README's simulated bridge line, started as written (on free ports), serves what the README's cpu-preset
    checkpoint acts on, and its `jepa-policy robot` line runs an episode on it (the bridge at its default 84 px
    refused the 48 px checkpoint until the line said --image-size 48)."""
    import json

    from jepa_policy.cli import main as policy_main

    readme = [c for c in COMMANDS if c.doc.name == "README.md"]
    bridge = next(c for c in readme if c.cli == "jepa-robot-bridge" and c.argv[:1] == ("serve",)
                  and "sim" in c.argv)
    robot = next(c for c in readme if c.cli == "jepa-policy" and c.argv[:1] == ("robot",))
    control, operator = f"tcp://127.0.0.1:{_free_port()}", f"tcp://127.0.0.1:{_free_port()}"
    process = subprocess.Popen([sys.executable, "-m", "jepa_robot.cli", *bridge.argv, "--bind", control,
                                "--operator-bind", operator, "--no-prompt", "--record-dir", str(tmp_path / "rec"),
                                "--chunk-budget", "3"],   # a short episode: what is checked is the pairing
                               cwd=reader_folder, env={**os.environ, "OMP_NUM_THREADS": "1"},
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        argv = [a.replace("...", "runs/jepa/checkpoints/latest.pt") for a in robot.argv]
        argv[argv.index("--episodes") + 1] = "1"                      # one of the README's 10 episodes
        summary = tmp_path / "summary.json"
        cwd = os.getcwd()
        os.chdir(reader_folder)
        try:
            code = policy_main([*argv, "--address", control, "--no-wait", "--out", str(summary)])
        finally:
            os.chdir(cwd)
        assert code == 0
        assert "robot: 100%" in capsys.readouterr().err      # its episodes on a bar
        episode = json.loads(summary.read_text())["episodes"][0]
        assert episode["steps"] == 24 and episode["interrupted"] == ""     # 3 chunks of 8 actions
    finally:
        process.terminate()
        _, err = process.communicate(timeout=30)
    assert "Traceback" not in err, err[-2000:]


def test_the_openpi_snippet_says_how_to_install_the_client_make_interop_checks():
    """docs/serving.md's robot loop imports openpi_client, which this project does not install: the page shows the
    install, pinned to the release `make interop` runs the loop with."""
    checked = re.search(r'"openpi-client==([\d.]+)"', (ROOT / "scripts" / "interop.sh").read_text()).group(1)
    text = (ROOT / "docs" / "serving.md").read_text()
    install = [line for _, line, _ in code_lines(text) if "pip install" in line and "openpi-client" in line]
    assert install and all(f"openpi-client=={checked}" in line for line in install), install
    assert text.index("openpi-client==") < text.index("from openpi_client import")   # before the loop needs it
