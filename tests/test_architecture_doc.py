"""docs/architecture.md cannot go stale: its folder map lists every package folder and only those,
its layer lists hold every module of each package exactly once and every import inside a package points down
them, and every module, class, function or attribute it names in backticks is defined where the page says
(in a file named beside it, or, where the sentence names no file, somewhere in the project).

Nothing is imported: modules are read with ``ast``, as tests/test_architecture.py reads the import graph.
"""
from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest
from test_architecture import PACKAGES, import_edges, project_modules

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "architecture.md"
# names the page uses that are not ours (the standard library's), checked to stay few
EXTERNAL = {"ast", "os.execv"}
PACKAGE_NAME = re.compile(r"\b(?:%s)(?:\.\w+)+" % "|".join(PACKAGES))
PATH = re.compile(r"^[\w/.-]*\w\.py$")
NAME = re.compile(r"^[A-Za-z_]\w*(?:\.[A-Za-z_]\w*)?$")


# ----------------------------------------------------------------------------- reading the page

def code_block(text: str, heading: str) -> str:
    """The first fenced block after ``heading``."""
    after = text[text.index(heading):]
    return after.split("```", 2)[1].split("\n", 1)[1]


def parse_layers(block: str) -> dict[str, dict[str, int]]:
    """{package: {module (relative): level}} from the numbered lines of the layer block (a level's text may run
    over several lines, braces too)."""
    layers: dict[str, dict[str, int]] = {}
    seen: list[tuple[str, str]] = []
    package, level, body = None, None, []

    def close_level() -> None:
        for name in expand(" ".join(body)):
            seen.append((package, name))
            layers[package][name] = level

    for line in block.splitlines():
        if not line.strip():
            continue
        numbered = re.match(r"\s+(\d+)\s+(.*)$", line)
        if not line[0].isspace() or numbered:
            if level is not None:
                close_level()
            if not line[0].isspace():
                package, level, body = line.strip(), None, []
                layers[package] = {}
            else:
                level, body = int(numbered.group(1)), [numbered.group(2)]
        elif level is None:
            raise AssertionError(f"layer line without a level: {line!r}")
        else:
            body.append(line)
    if level is not None:
        close_level()
    duplicates = sorted({f"{p}.{n}" for p, n in seen if seen.count((p, n)) > 1})
    assert not duplicates, f"architecture.md lists these modules twice: {duplicates}"
    return layers


def expand(body: str) -> list[str]:
    """``a, b.{c, d (comment)}`` -> [a, b.c, b.d]."""
    while "(" in body:                       # comments, innermost first
        body = re.sub(r"\([^()]*\)", "", body)
    names = []
    for item in re.findall(r"[\w.]+\{[^}]*\}|[\w.]+", body):
        if "{" in item:
            prefix, inner = item.split("{")
            names += [prefix + part.strip() for part in inner.rstrip("}").split(",") if part.strip()]
        else:
            names.append(item)
    return names


def segments(text: str) -> list[str]:
    """Sentences' scopes for backticked names: table rows and list items (joined), split at ';'."""
    units, current = [], []
    for line in text.splitlines():
        starts_unit = not line.strip() or line.startswith(("|", "#", "```")) or re.match(r"\d+\. |\* |- ", line)
        if starts_unit and current:
            units.append(" ".join(current))
            current = []
        if line.strip():
            current.append(line)
    units.append(" ".join(current))
    return [part for unit in units for part in unit.split(";")]


# ----------------------------------------------------------------------------- reading the code

def definitions(path: Path) -> set[str]:
    """Names a file defines: top-level functions, classes and assignments; ``Class.member`` and ``member`` for
    methods, class attributes and ``self.x`` attributes."""
    tree = ast.parse(path.read_text())
    names: set[str] = set()

    def targets(node) -> list[str]:
        out = []
        for t in getattr(node, "targets", [getattr(node, "target", None)]):
            if isinstance(t, ast.Name):
                out.append(t.id)
            elif isinstance(t, ast.Attribute) and isinstance(t.value, ast.Name) and t.value.id == "self":
                out.append(t.attr)
            elif isinstance(t, ast.Tuple):
                out += [e.id for e in t.elts if isinstance(e, ast.Name)]
                out += [e.attr for e in t.elts if isinstance(e, ast.Attribute)]
        return out

    members: dict[str, set[str]] = {}
    bases: dict[str, list[str]] = {}
    for top in tree.body:
        if isinstance(top, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(top.name)
        elif isinstance(top, (ast.Assign, ast.AnnAssign)):
            names.update(targets(top))
        if isinstance(top, ast.ClassDef):
            for node in ast.walk(top):
                member = []
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node in top.body:
                    member = [node.name]
                elif isinstance(node, (ast.Assign, ast.AnnAssign)):
                    member = targets(node)
                members.setdefault(top.name, set()).update(member)
            bases[top.name] = [b.id for b in top.bases if isinstance(b, ast.Name)]

    def inherited(cls: str, seen: frozenset = frozenset()) -> set[str]:
        """A class's members with those of its bases defined in the same file."""
        return members.get(cls, set()).union(*(inherited(b, seen | {cls}) for b in bases.get(cls, [])
                                                if b in members and b not in seen))

    for cls in members:
        for m in inherited(cls):
            names.update({m, f"{cls}.{m}"})
    return names


@pytest.fixture(scope="module")
def modules() -> dict[str, Path]:
    return project_modules(ROOT)


@pytest.fixture(scope="module")
def text() -> str:
    return DOC.read_text()


# ----------------------------------------------------------------------------- the page against the code

def test_the_folder_map_lists_every_package_folder(text):
    listed = {m.group(1).rstrip("/") for m in re.finditer(r"^([\w/]+/)\s", code_block(text, "## Folder map"),
                                                           re.MULTILINE)}
    folders = {str(p.parent.relative_to(ROOT)) for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")
               if "__pycache__" not in p.parts}
    assert not folders - listed, f"package folders missing from the folder map: {sorted(folders - listed)}"
    gone = sorted(f for f in listed if not (ROOT / f).is_dir())
    assert not gone, f"the folder map lists folders that do not exist: {gone}"


def test_the_layer_lists_hold_every_module_once(text, modules):
    layers = parse_layers(code_block(text, "## Layers inside each package"))
    assert set(layers) == set(PACKAGES)
    listed = {f"{p}.{m}" for p, ms in layers.items() for m in ms}
    actual = {m for m, path in modules.items() if path.name != "__init__.py"}
    assert not actual - listed, ("modules missing from architecture.md's layer lists (add each at a level above "
                                 f"every module of its package it imports): {sorted(actual - listed)}")
    assert not listed - actual, f"architecture.md lists modules that do not exist: {sorted(listed - actual)}"


def test_imports_inside_a_package_point_down_the_documented_layers(text, modules):
    layers = parse_layers(code_block(text, "## Layers inside each package"))
    level = {f"{p}.{m}": lvl for p, ms in layers.items() for m, lvl in ms.items()}
    edges = import_edges(ROOT)
    inits = {m for m, path in modules.items() if path.name == "__init__.py"}
    imports: dict[str, set[str]] = {}
    for e in edges:
        imports.setdefault(e.source, set()).add(e.target)

    def through_inits(target: str, seen: frozenset = frozenset()) -> set[str]:
        """A package's ``__init__`` stands for the modules it re-exports."""
        if target not in inits:
            return {target}
        return {m for t in imports.get(target, ()) - seen for m in through_inits(t, seen | {target})}

    upward = []
    for e in edges:
        if e.source in inits or e.source.split(".")[0] != e.target.split(".")[0]:
            continue
        for target in through_inits(e.target):
            if target in level and e.source in level and level[target] >= level[e.source]:
                upward.append(f"{e.source} (level {level[e.source]}) imports {target} (level {level[target]}), "
                              f"line {e.line}")
    assert not upward, "imports that do not point down architecture.md's layers:\n" + "\n".join(sorted(set(upward)))


def test_every_backticked_name_is_defined_where_the_page_says(text, modules):
    by_path = {str(p.relative_to(ROOT)): p for p in modules.values()}
    defined = {path: definitions(p) for path, p in by_path.items()}
    anywhere = set().union(*defined.values())
    file_names = {p.name for p in modules.values()}
    problems = []
    for segment in segments(text):
        tokens = re.findall(r"`([^`]+)`", segment)
        paths = [t for t in tokens if PATH.match(t)]
        for token in tokens:
            for dotted in PACKAGE_NAME.findall(token):          # jepa_policy.model, monitor_service.scoring.nmse
                module = next((dotted[:i] for i in range(len(dotted), 0, -1)
                               if dotted[:i] in modules and (i == len(dotted) or dotted[i] == ".")), None)
                rest = dotted[len(module) + 1:] if module else None
                if module is None or (rest and rest not in definitions(modules[module])
                                      and f"{module}.{rest}" not in modules):
                    problems.append(f"{dotted}: no such module or name")
            if PATH.match(token):
                if "/" in token and token not in by_path and not (ROOT / token).exists():
                    problems.append(f"{token}: no such file")
                elif "/" not in token and token not in file_names:
                    problems.append(f"{token}: no project file has this name")
            elif NAME.match(token) and not token.startswith("__") and not PACKAGE_NAME.fullmatch(token) \
                    and token not in EXTERNAL and token.split(".")[0] not in PACKAGES:
                places = [p for p in paths if p in defined]
                if places and not any(token in defined[p] for p in places):
                    problems.append(f"{token}: not defined in {', '.join(places)} (the files its sentence names)")
                elif not places and token not in anywhere:
                    problems.append(f"{token}: defined nowhere in the project")
    assert not problems, "architecture.md names what the code does not have:\n" + "\n".join(problems)


# ----------------------------------------------------------------------------- the checkers themselves

def test_expand_reads_braces_and_comments():
    assert expand("a, b.{c, d (a comment, with a comma)}, e (f)") == ["a", "b.c", "b.d", "e"]


def test_the_checker_catches_a_misplaced_name(tmp_path):
    (tmp_path / "m.py").write_text("class A:\n    def f(self):\n        self.x = 1\n\ndef g():\n    pass\n")
    names = definitions(tmp_path / "m.py")
    assert {"A", "A.f", "f", "A.x", "x", "g"} <= names and "h" not in names
    (tmp_path / "n.py").write_text("class Base:\n    def f(self):\n        pass\n\nclass Child(Base):\n    pass\n")
    assert "Child.f" in definitions(tmp_path / "n.py")
    assert segments("| row | `a.py` `f`; `b.py` `g` |\n1. step one\n   goes on `h`\n") == [
        "| row | `a.py` `f`", " `b.py` `g` |", "1. step one    goes on `h`", ]


def test_layers_parse_levels_and_continuations():
    block = "pkg\n  0  a, b.{c, d,\n     e (x, y)}, g\n  1  f (uses a)\nother\n  0  h\n"
    assert parse_layers(block) == {"pkg": {"a": 0, "b.c": 0, "b.d": 0, "b.e": 0, "g": 0, "f": 1}, "other": {"h": 0}}
