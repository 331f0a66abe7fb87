"""The import graph keeps its shape (docs/architecture.md): one direction between packages, no circles.

    jepa_envs  <-  jepa_policy  <-  jepa_policy.demo (the main job)
    monitor_service stands alone; anyone may import its client and its scores (``monitor_service.scoring``,
    the one d_NMSE); the main job also starts its server and runs its study of alert rules on the rollouts.
    jepa_robot is the robot bridge, a service: it serves jepa_envs tasks (so it imports jepa_envs) and nothing
    imports it but for its wire: ``jepa_robot.operator`` (the import-light operator client, the protocol
    version, the operator's credential; imports no project module), ``jepa_robot.operator_cli`` (the console
    script: the operator module only) and ``jepa_robot.protocol`` (the messages both ends speak and the
    loopback rule; the operator module only), which the proxy env in jepa_envs and the policy server import.

Every import counts, at module level or inside a function. Imports of project modules inside functions are
allowed only in command-line modules (``cli.py``), where they keep ``--help`` and small commands fast; anywhere
else such an import would only hide a circle, so it must move to the top of the file.
"""
from __future__ import annotations

import ast
import re
import textwrap
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("jepa_envs", "jepa_policy", "monitor_service", "jepa_robot")
# the robot bridge's wire: what the rest of the project may import of it; it imports no project module beyond
ROBOT_WIRE = ("jepa_robot.operator", "jepa_robot.operator_cli", "jepa_robot.protocol")
LAZY_IMPORTS_ALLOWED_IN = ("cli.py",)


@dataclass(frozen=True)
class Edge:
    source: str       # importing module
    target: str       # imported project module
    nested: bool      # inside a function or class body
    line: int


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def project_modules(root: Path, packages=PACKAGES) -> dict[str, Path]:
    return {module_name(p, root): p for pkg in packages for p in sorted((root / pkg).rglob("*.py"))}


def _resolve(name: str, modules: dict[str, Path]) -> str | None:
    """The longest project module that ``name`` names or lies inside (``pkg.mod.func`` -> ``pkg.mod``)."""
    while name:
        if name in modules:
            return name
        name = name.rpartition(".")[0]
    return None


def import_edges(root: Path, packages=PACKAGES) -> list[Edge]:
    """Every import of one project module by another, read with ``ast`` (nothing is imported)."""
    modules = project_modules(root, packages)
    edges = []
    for source, path in modules.items():
        is_package = path.name == "__init__.py"
        tree = ast.parse(path.read_text(), filename=str(path))
        nested_nodes = {id(n) for top in tree.body if not isinstance(top, (ast.Import, ast.ImportFrom))
                        for n in ast.walk(top)}
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = source.split(".") if is_package else source.split(".")[:-1]
                    base = base[: len(base) - (node.level - 1)]
                    module = ".".join(base + ([node.module] if node.module else []))
                else:
                    module = node.module or ""
                # ``from pkg import sub`` imports the submodule pkg.sub when there is one
                names = [f"{module}.{a.name}" if f"{module}.{a.name}" in modules else module for a in node.names]
            else:
                continue
            nested = id(node) in nested_nodes and not _is_type_checking_guard(tree, node)
            for name in names:
                target = _resolve(name, modules)
                if target is None or target == source or source.startswith(target + "."):
                    continue  # not ours, or the module's own parent package (already imported before it runs)
                edges.append(Edge(source, target, nested, node.lineno))
    return edges


def _is_type_checking_guard(tree: ast.Module, node: ast.AST) -> bool:
    return any(isinstance(top, ast.If) and "TYPE_CHECKING" in ast.unparse(top.test) and node in ast.walk(top)
               for top in tree.body)


def circles(edges: list[Edge]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    graph: dict[str, set[str]] = {}
    for e in edges:
        graph.setdefault(e.source, set()).add(e.target)
        graph.setdefault(e.target, set())
    index, low, stack, on_stack, out = {}, {}, [], set(), []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def layer_violations(edges: list[Edge]) -> list[str]:
    """Imports that point up the layers or out of a package that must stand alone."""
    bad = []
    for e in edges:
        src, dst = e.source, e.target
        where = f"{src} imports {dst} (line {e.line})"
        if src in ROBOT_WIRE and dst != "jepa_robot.operator":
            bad.append(f"{where}: the robot's wire imports only jepa_robot.operator (the operator commands must "
                       "start without the heavy stack)")
        elif src.startswith("jepa_robot") and not dst.startswith(("jepa_robot", "jepa_envs")):
            bad.append(f"{where}: the robot bridge imports only itself and the tasks of jepa_envs")
        elif not src.startswith("jepa_robot") and dst.startswith("jepa_robot") and dst not in ROBOT_WIRE:
            bad.append(f"{where}: outside the robot bridge, only its wire ({', '.join(ROBOT_WIRE)}) may be imported")
        elif src.startswith("jepa_envs") and not dst.startswith(("jepa_envs", "jepa_robot")):
            bad.append(f"{where}: jepa_envs imports nothing outside itself but the robot's wire")
        elif src.startswith("monitor_service") and not dst.startswith("monitor_service"):
            bad.append(f"{where}: monitor_service stands alone")
        elif src.startswith("jepa_policy") and not src.startswith("jepa_policy.demo"):
            if dst.startswith("jepa_policy.demo"):
                bad.append(f"{where}: the policy package never imports the main job")
            elif dst.startswith("monitor_service") and dst not in ("monitor_service.client", "monitor_service.scoring"):
                bad.append(f"{where}: only the main job runs the monitor; the policy may use its client and its "
                           "scores (the one d_NMSE)")
        elif src.startswith("jepa_policy.demo") and dst.startswith("monitor_service") and \
                dst not in ("monitor_service.client", "monitor_service.server", "monitor_service.offline.study",
                            "monitor_service.offline.compare", "monitor_service.offline.figures"):
            bad.append(f"{where}: the main job uses the monitor's client, server, study, compare and figures only")
    return bad


def hidden_imports(edges: list[Edge]) -> list[str]:
    return [f"{e.source} line {e.line}: imports {e.target} inside a function; move it to the top of the file"
            for e in edges if e.nested and not e.source.endswith(tuple(n[:-3] for n in LAZY_IMPORTS_ALLOWED_IN))]


# ----------------------------------------------------------------------------- the project itself

@pytest.fixture(scope="module")
def edges() -> list[Edge]:
    return import_edges(ROOT)


def test_no_import_circles(edges):
    assert circles(edges) == []


def test_imports_point_down_the_layers(edges):
    assert layer_violations(edges) == []


def test_no_project_import_hides_inside_a_function(edges):
    assert hidden_imports(edges) == []


# a deployable service (where it starts) and what it must never load: offline studies, benchmarks, plotting
SERVICES = {"monitor_service.app": ("monitor_service.offline", "monitor_service.bench", "monitor_service.floor"),
            "jepa_robot.bridge": ("jepa_robot.bench", "jepa_robot.load_bench")}   # a package: all its modules


def loaded_by(start: str, edges: list[Edge]) -> set[str]:
    """Every project module ``start`` imports, directly or through others."""
    graph: dict[str, set[str]] = {}
    for e in edges:
        graph.setdefault(e.source, set()).add(e.target)
    seen, todo = set(), [start]
    while todo:
        for target in graph.get(todo.pop(), set()) - seen:
            seen.add(target)
            todo.append(target)
    return seen


def service_problems(edges: list[Edge], root: Path = ROOT, services=SERVICES) -> list[str]:
    problems = []
    for start, offline in services.items():
        loaded = loaded_by(start, edges) | {start}
        problems += [f"{start} loads {m}" for m in sorted(loaded)
                     if any(m == o or m.startswith(o + ".") for o in offline)]
        modules = project_modules(root, (start.split(".")[0],))
        for module in sorted(loaded & set(modules)):
            tree = ast.parse(modules[module].read_text())
            names = [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
            names += [n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and not n.level]
            problems += [f"{start} loads {module}, which imports {name}" for name in names
                         if name.split(".")[0] == "matplotlib"]
    return problems


def test_the_deployable_services_load_no_study_benchmark_or_plotting(edges):
    """The monitor's app and the robot bridge import none of the offline studies, benchmarks or figures kept
    beside them (their command lines may, lazily)."""
    assert service_problems(edges) == []


def test_main_job_lives_in_its_own_subpackage():
    top = {p.stem for p in (ROOT / "jepa_policy").glob("*.py")}
    assert not top & {"demo", "report", "ceiling"}
    assert (ROOT / "jepa_policy" / "demo" / "__init__.py").is_file()


# ----------------------------------------------------------------------------- the checker can fail

def _write_package(root: Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text))


def test_checker_finds_a_circle_hidden_in_a_function(tmp_path):
    _write_package(tmp_path, {
        "jepa_policy/__init__.py": "",
        "jepa_policy/train.py": "from jepa_policy.policy import Policy\n",
        "jepa_policy/policy.py": "def load():\n    from jepa_policy.train import load_checkpoint\n",
    })
    found = import_edges(tmp_path, ("jepa_policy",))
    assert circles(found) == [["jepa_policy.policy", "jepa_policy.train"]]
    assert hidden_imports(found) == ["jepa_policy.policy line 2: imports jepa_policy.train inside a function; "
                                     "move it to the top of the file"]


def test_checker_finds_upward_imports(tmp_path):
    _write_package(tmp_path, {
        "jepa_envs/__init__.py": "",
        "jepa_envs/real_robot/__init__.py": "",
        "jepa_envs/real_robot/proxy.py": "from jepa_robot import bridge\n",
        "jepa_robot/__init__.py": "",
        "jepa_robot/bridge.py": "",
        "jepa_robot/protocol.py": "import jepa_envs.real_robot\n",
        "jepa_robot/cli.py": "def run():\n    from jepa_policy.policy import Policy\n",
        "jepa_policy/__init__.py": "",
        "jepa_policy/policy.py": "from jepa_envs import real_robot\n",
        "jepa_policy/train.py": "from jepa_policy.demo import report\nfrom monitor_service import service\n",
        "jepa_policy/demo/__init__.py": "",
        "jepa_policy/demo/report.py": "from monitor_service.client import MonitorClient\n",
        "monitor_service/__init__.py": "",
        "monitor_service/client.py": "",
        "monitor_service/service.py": "import jepa_envs\n",
    })
    found = import_edges(tmp_path)
    bad = layer_violations(found)
    assert any("jepa_robot.cli imports jepa_policy.policy" in b for b in bad)
    assert any("jepa_envs.real_robot.proxy imports jepa_robot.bridge" in b for b in bad)
    assert any("jepa_robot.protocol imports jepa_envs.real_robot" in b for b in bad)
    assert any("jepa_policy.train imports jepa_policy.demo.report" in b for b in bad)
    assert any("jepa_policy.train imports monitor_service.service" in b for b in bad)
    assert any("monitor_service.service imports jepa_envs" in b for b in bad)
    assert len(bad) == 6   # the policy importing envs and the main job importing the client are the allowed shape
    assert hidden_imports(found) == []   # the one nested import sits in a cli.py


def test_checker_finds_a_study_or_plot_a_service_loads(tmp_path):
    _write_package(tmp_path, {
        "monitor_service/__init__.py": "",
        "monitor_service/app.py": "from monitor_service import service\n",
        "monitor_service/service.py": "from monitor_service.offline.study import run_study\n",
        "monitor_service/offline/study.py": "import matplotlib.pyplot as plt\n",
    })
    found = import_edges(tmp_path, ("monitor_service",))
    assert service_problems(found, tmp_path, {"monitor_service.app": ("monitor_service.offline.study",)}) == [
        "monitor_service.app loads monitor_service.offline.study",
        "monitor_service.app loads monitor_service.offline.study, which imports matplotlib.pyplot"]


LONG_MODULE_LINES = 600


def long_modules_without_a_reason(root: Path = ROOT, packages=PACKAGES) -> list[str]:
    """Modules over LONG_MODULE_LINES lines whose docstring does not say why they are one module ("One module
    ... on purpose: <why>")."""
    out = []
    for name, path in project_modules(root, packages).items():
        text = path.read_text()
        if text.count("\n") <= LONG_MODULE_LINES:
            continue
        doc = ast.get_docstring(ast.parse(text)) or ""
        if not re.search(r"One module of about \d+ lines on purpose: \S", doc):
            out.append(f"{name} ({text.count(chr(10))} lines)")
    return out


def test_a_long_module_says_why_it_is_one():
    assert long_modules_without_a_reason() == []


def test_the_long_module_check_catches_a_silent_one(tmp_path):
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    body = "x = 1\n" * (LONG_MODULE_LINES + 1)
    (pkg / "silent.py").write_text('"""A long module."""\n' + body)
    (pkg / "told.py").write_text('"""A long module.\n\nOne module of about 600 lines on purpose: a reason."""\n' + body)
    (pkg / "short.py").write_text('"""Short."""\nx = 1\n')
    assert long_modules_without_a_reason(tmp_path, ("pkg",)) == [f"pkg.silent ({LONG_MODULE_LINES + 2} lines)"]
