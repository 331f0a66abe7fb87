"""MimicGen D1 tasks (CoffeePreparation, Kitchen, ThreePieceAssembly, HammerCleanup) behind our interface.

MimicGen's task classes live in its source package (github.com/NVlabs/mimicgen), which registers them in
robosuite's env registry when imported; it is not on PyPI (the PyPI package named ``mimicgen`` is unrelated).
Kitchen and HammerCleanup also need robosuite-task-zoo. When they are missing, building an env raises
:class:`MimicGenNotInstalled` naming what to install and how. Once importable, the envs are built exactly like
the robomimic tasks (same settings as MimicGen's image datasets), see :mod:`jepa_envs.tasks.robomimic_env`.
"""
from __future__ import annotations

import importlib

import numpy as np

from jepa_envs.tasks.robomimic_env import RobomimicEnv, robomimic_env_args
from jepa_envs.tasks.spec import TaskSpec, get_task_spec

NEEDS_TASK_ZOO = ("Kitchen_D1", "HammerCleanup_D1")
TASK_MODULES = {
    "CoffeePreparation_D1": "mimicgen.envs.robosuite.coffee",
    "Kitchen_D1": "mimicgen.envs.robosuite.kitchen",
    "ThreePieceAssembly_D1": "mimicgen.envs.robosuite.three_piece_assembly",
    "HammerCleanup_D1": "mimicgen.envs.robosuite.hammer_cleanup",
}
# robosuite-task-zoo's Kitchen fails under numpy 2.4 ("setting an array element with a sequence")
KITCHEN_MAX_NUMPY = (2, 4)

INSTALL_MIMICGEN = "git clone https://github.com/NVlabs/mimicgen && jepa-envs install-mimicgen mimicgen"
INSTALL_WITH_TASK_ZOO = ("git clone https://github.com/NVlabs/mimicgen && git clone "
                         "https://github.com/ARISE-Initiative/robosuite-task-zoo && "
                         "jepa-envs install-mimicgen mimicgen --task-zoo robosuite-task-zoo")


class MimicGenNotInstalled(ImportError):
    """MimicGen (or robosuite-task-zoo) source packages are not importable."""


def _message(spec: TaskSpec, what: str, reason: str) -> str:
    steps = INSTALL_WITH_TASK_ZOO if spec.source_task in NEEDS_TASK_ZOO else INSTALL_MIMICGEN
    return (f"{spec.env_id} needs {what} ({reason}). MimicGen's task classes are not on PyPI, and the PyPI "
            f"package named 'mimicgen' is unrelated: do not pip install mimicgen. Install from local clones "
            f"(editable, so that the XML assets are found; keep the clones where they are): " + steps +
            ". Details: docs/envs_simulation.md")


def require_mimicgen(spec: TaskSpec) -> None:
    """Import the MimicGen module defining the task (robosuite-task-zoo first where needed); defining the
    class registers it in robosuite's env registry. Raises MimicGenNotInstalled naming the fix."""
    if spec.source_task in NEEDS_TASK_ZOO:
        try:
            importlib.import_module("robosuite_task_zoo")
        except ImportError as e:
            raise MimicGenNotInstalled(_message(spec, "robosuite-task-zoo",
                                                f"import robosuite_task_zoo failed: {e}")) from e
    if spec.source_task == "Kitchen_D1" and tuple(int(p) for p in np.__version__.split(".")[:2]) >= KITCHEN_MAX_NUMPY:
        raise RuntimeError(f"{spec.env_id}: robosuite-task-zoo's Kitchen crashes with numpy {np.__version__}; "
                           "install numpy<2.4 (pip install 'numpy<2.4')")
    try:
        importlib.import_module("mimicgen")
    except ImportError as e:
        raise MimicGenNotInstalled(_message(spec, "the MimicGen source package", f"import mimicgen failed: {e}")) from e
    try:
        # importing the module directly also registers tasks that `import mimicgen` skipped because
        # robosuite-task-zoo was missing at that time
        importlib.import_module(TASK_MODULES[spec.source_task])
    except ImportError as e:
        raise MimicGenNotInstalled(_message(
            spec, f"the MimicGen task class {spec.source_task}",
            f"the importable 'mimicgen' has no {TASK_MODULES[spec.source_task]} ({e}); is it the unrelated "
            "PyPI package?")) from e
    from robosuite.environments.base import REGISTERED_ENVS

    if spec.source_task not in REGISTERED_ENVS:
        raise MimicGenNotInstalled(_message(spec, f"the MimicGen task class {spec.source_task}",
                                            "its module did not register it in robosuite"))


class MimicGenEnv(RobomimicEnv):
    """A MimicGen D1 task; arguments as :class:`jepa_envs.tasks.robomimic_env.RobomimicEnv`."""

    SUITES = ("mimicgen",)

    def __init__(self, task: str = "CoffeePreparation", **kwargs):
        spec = get_task_spec(task)
        if spec.suite not in self.SUITES:
            raise ValueError(f"MimicGenEnv serves MimicGen tasks; {spec.name} is a {spec.suite} task")
        require_mimicgen(spec)
        super().__init__(task=task, **kwargs)

    @classmethod
    def default_env_args(cls, spec: TaskSpec) -> dict:
        """MimicGen's D1 image datasets: robomimic's settings with one Panda."""
        return robomimic_env_args(spec.source_task, spec.cameras, spec.image_size, task_kwargs={"robots": ["Panda"]})
