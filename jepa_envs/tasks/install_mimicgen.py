"""``jepa-envs install-mimicgen DIR``: install MimicGen (and robosuite-task-zoo) from local clones, the way that works.

MimicGen's task classes are not on PyPI (the PyPI package named ``mimicgen`` is unrelated). Its ``setup.py`` lists
packages its env classes never import (gdown, huggingface_hub, imageio-ffmpeg, chardet: only its dataset tools
use them) and omits one they do (``six``, imported by ``mimicgen.env_interfaces``); robosuite-task-zoo's
``setup.py`` requires mujoco-py, which does not build here and is not used with robosuite 1.4. MimicGen's own
installation guide (docs/introduction/installation.md) recommends mujoco 2.3.2, which robosuite 1.4.1 does not
need; this toolkit measured its four D1 tasks with mujoco 3.3.7 and keeps the project's mujoco.

So: each clone is installed editable (its XML and mesh assets are read from the clone, so the clone must stay
where it is) without its declared dependencies, ``six`` is installed, and the four task modules are imported in
a fresh interpreter to prove the result. Nothing of either project is copied into this one.
"""
from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

TASK_ZOO_TASKS = {"Kitchen": "mimicgen.envs.robosuite.kitchen",
                  "HammerCleanup": "mimicgen.envs.robosuite.hammer_cleanup"}
MIMICGEN_TASKS = {"CoffeePreparation": "mimicgen.envs.robosuite.coffee",
                  "ThreePieceAssembly": "mimicgen.envs.robosuite.three_piece_assembly"}
RUNTIME_DEPENDENCIES = ("six",)   # imported by MimicGen's env classes, not declared by its setup.py


class InstallError(RuntimeError):
    """A clone is not what it should be, or pip failed; the message names the fix."""


def check_clone(path: str | Path, package: str, marker: str, url: str) -> Path:
    """The clone's root, or InstallError saying what is wrong and how to get a proper one."""
    root = Path(path).expanduser().resolve()
    hint = f"clone it with: git clone {url} {path}"
    if not root.is_dir():
        raise InstallError(f"{path} is not a directory; {hint}")
    setup = root / "setup.py"
    if not setup.is_file() or f'name="{package}"' not in setup.read_text(errors="replace").replace("'", '"'):
        raise InstallError(f"{root} is not a clone of {url} (no setup.py naming {package!r}); {hint}")
    if not (root / marker).is_file():
        raise InstallError(f"{root} lacks {marker}: an incomplete clone or checkout; {hint}")
    return root


def _run(cmd: list[str], what: str) -> str:
    # from an empty folder: a clone in the current folder would otherwise import as a namespace package
    with tempfile.TemporaryDirectory() as empty:
        out = subprocess.run(cmd, capture_output=True, text=True, cwd=empty)
    if out.returncode != 0:
        tail = "\n".join((out.stderr or out.stdout).strip().splitlines()[-8:])
        raise InstallError(f"{what} failed (exit {out.returncode}): {' '.join(cmd)}\n{tail}")
    return out.stdout


_PROBE = r"""
import importlib, json, os, sys
os.environ.setdefault("MUJOCO_GL", "osmesa")
result = {}
try:
    import mimicgen
    where = mimicgen.__file__ or list(mimicgen.__path__)[0] + "/__init__.py"
    result["mimicgen_path"] = os.path.dirname(os.path.dirname(os.path.abspath(where)))
except ImportError:
    result["mimicgen_path"] = None
for task, module in json.loads(sys.argv[1]).items():
    try:
        importlib.import_module(module)
        result[task] = "ok"
    except Exception as e:
        result[task] = f"{type(e).__name__}: {e}"
print(json.dumps(result))
"""


def probe(python: str, tasks: dict[str, str]) -> dict:
    """Import each task module in a fresh ``python``: {"mimicgen_path": ..., task: "ok" | the error}."""
    import json

    lines = _run([python, "-c", _PROBE, json.dumps(tasks)], "importing the MimicGen task modules").splitlines()
    return json.loads(next(line for line in reversed(lines) if line.startswith("{")))


def install(mimicgen_dir: str | Path, task_zoo_dir: str | Path | None = None, python: str = sys.executable,
            log=print) -> dict:
    """Install the clones into ``python``'s environment and return what each task's import gave."""
    mimicgen = check_clone(mimicgen_dir, "mimicgen", "mimicgen/envs/robosuite/coffee.py",
                           "https://github.com/NVlabs/mimicgen")
    zoo = None if task_zoo_dir is None else check_clone(
        task_zoo_dir, "robosuite_task_zoo", "robosuite_task_zoo/__init__.py",
        "https://github.com/ARISE-Initiative/robosuite-task-zoo")
    existing = probe(python, {})
    if existing["mimicgen_path"] and Path(existing["mimicgen_path"]).resolve() != mimicgen:
        where = existing["mimicgen_path"]
        if not (Path(where) / "mimicgen" / "envs" / "robosuite" / "coffee.py").is_file():
            raise InstallError(f"a package named mimicgen that is not NVlabs' MimicGen is installed ({where}): the "
                               f"PyPI 'mimicgen' is unrelated. Remove it first: {python} -m pip uninstall -y mimicgen")
        log(f"[install-mimicgen] replacing the MimicGen installed from {where}")
    pip = [python, "-m", "pip", "install", "-q", "--disable-pip-version-check"]
    for root in [mimicgen] + ([zoo] if zoo else []):
        log(f"[install-mimicgen] pip install --no-deps -e {root}")
        _run(pip + ["--no-deps", "-e", str(root)], f"installing {root.name}")
    log(f"[install-mimicgen] pip install {' '.join(RUNTIME_DEPENDENCIES)}  (imported by MimicGen's env classes)")
    _run(pip + list(RUNTIME_DEPENDENCIES), "installing MimicGen's runtime imports")
    tasks = {**MIMICGEN_TASKS, **(TASK_ZOO_TASKS if zoo else {})}
    result = probe(python, tasks)
    failed = {t: why for t, why in result.items() if t in tasks and why != "ok"}
    if failed:
        raise InstallError("installed, but these task modules do not import: "
                           + "; ".join(f"{t}: {why}" for t, why in failed.items()))
    log(f"[install-mimicgen] importable: {', '.join(tasks)}"
        + ("" if zoo else "; Kitchen and HammerCleanup also need --task-zoo DIR (a robosuite-task-zoo clone)"))
    log(f"[install-mimicgen] editable installs: keep {mimicgen}" + (f" and {zoo}" if zoo else "")
        + " where they are (the assets are read from there); after moving a clone, run this command again")
    return result


def add_arguments(p) -> None:
    p.add_argument("mimicgen_dir", metavar="DIR", help="a local clone of https://github.com/NVlabs/mimicgen")
    p.add_argument("--task-zoo", metavar="DIR", default=None,
                   help="a local clone of https://github.com/ARISE-Initiative/robosuite-task-zoo (Kitchen, "
                        "HammerCleanup)")
    p.add_argument("--python", default=sys.executable, help="the interpreter whose environment to install into")


def main(args) -> int:
    try:
        install(args.mimicgen_dir, args.task_zoo, python=args.python)
    except InstallError as exc:
        print(f"jepa-envs install-mimicgen: {exc}", file=sys.stderr)
        return 2
    return 0
