"""Every `jepa-monitor` command line of the documentation parses with the CLI's own parser, so documented flags
and real ones cannot drift apart (docs/monitor.md's bench synopsis once listed three flags the CLI refused)."""
import shlex
from pathlib import Path

import pytest

from monitor_service.cli import build_parser

ROOT = Path(__file__).resolve().parents[2]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md")), *sorted((ROOT / "deploy").rglob("*.md"))]
# placeholders the documents write in capitals, and a value of the type the CLI expects there
PLACEHOLDERS = {"ID": "3", "KEY": "k", "H": "127.0.0.1", "P": "8765", "K": "k"}
SHELL = {"|", "||", "&", "&&", ";", ">", ">>", "<", "2>&1"}


def command_lines(text: str) -> list[tuple[int, str]]:
    """(line number, command) for every line that starts with `jepa-monitor` (after indentation or a `$ `
    prompt), joined with its backslash continuations."""
    out, lines = [], text.splitlines()
    i = 0
    while i < len(lines):
        stripped = lines[i].strip().removeprefix("$ ")
        if stripped.startswith("jepa-monitor ") or stripped == "jepa-monitor":
            start, command = i + 1, stripped
            while command.endswith("\\") and i + 1 < len(lines):
                i += 1
                command = command[:-1] + " " + lines[i].strip()
            out.append((start, command))
        i += 1
    return out


def argv_of(command: str) -> list[str]:
    lexer = shlex.shlex(command, posix=True, punctuation_chars=True)
    lexer.whitespace_split = True
    lexer.commenters = "#"
    argv = []
    for token in lexer:
        if token in SHELL or set(token) <= set("|&;<>"):
            break
        argv.append(PLACEHOLDERS.get(token, token))
    return argv[1:]


DOCUMENTED = [(doc, n, cmd) for doc in DOCS for n, cmd in command_lines(doc.read_text())]


def test_the_documentation_shows_every_subcommand():
    shown = {build_parser().parse_args(argv_of(cmd)).command for _, _, cmd in DOCUMENTED}
    subcommands = set(build_parser()._subparsers._group_actions[0].choices)
    assert subcommands <= shown, f"documented nowhere: {subcommands - shown}"


@pytest.mark.parametrize("doc, line, command", DOCUMENTED,
                         ids=[f"{d.relative_to(ROOT)}:{n}" for d, n, _ in DOCUMENTED])
def test_documented_command_line_parses(doc, line, command, capsys):
    try:
        build_parser().parse_args(argv_of(command))
    except SystemExit:
        pytest.fail(f"{doc.relative_to(ROOT)}:{line}: `{command}` is refused by the CLI: "
                    f"{capsys.readouterr().err.strip().splitlines()[-1]}")


def test_the_checker_catches_a_flag_the_cli_does_not_have():
    bad = command_lines("text\n    jepa-monitor bench --n 4000 --batch 16,64   # old synopsis\n")
    assert bad == [(2, "jepa-monitor bench --n 4000 --batch 16,64   # old synopsis")]
    with pytest.raises(SystemExit):
        build_parser().parse_args(argv_of(bad[0][1]))
