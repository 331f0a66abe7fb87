"""Old module names of jepa_envs, kept importable for one release after the package was grouped by concern.

``import jepa_envs.data`` (or ``from jepa_envs import pusht``) still works and gives the module at its new place,
with one DeprecationWarning that names it. The names go away in the next release.
"""
from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

MOVED = {
    "jepa_envs.spec": "jepa_envs.tasks.spec", "jepa_envs.base": "jepa_envs.tasks.base",
    "jepa_envs.entry": "jepa_envs.tasks.entry", "jepa_envs.wrappers": "jepa_envs.tasks.wrappers",
    "jepa_envs.render": "jepa_envs.tasks.render", "jepa_envs.rotations": "jepa_envs.tasks.rotations",
    "jepa_envs.abs_actions": "jepa_envs.tasks.abs_actions", "jepa_envs.pusht": "jepa_envs.tasks.pusht",
    "jepa_envs.pusht_expert": "jepa_envs.tasks.pusht_expert",
    "jepa_envs.robosuite_common": "jepa_envs.tasks.robosuite_common",
    "jepa_envs.robomimic_env": "jepa_envs.tasks.robomimic_env", "jepa_envs.libero_env": "jepa_envs.tasks.libero_env",
    "jepa_envs.libero_setup": "jepa_envs.tasks.libero_setup", "jepa_envs.mimicgen_env": "jepa_envs.tasks.mimicgen_env",
    "jepa_envs.install_mimicgen": "jepa_envs.tasks.install_mimicgen",
    "jepa_envs.data": "jepa_envs.datasets.hdf5", "jepa_envs.lerobot_format": "jepa_envs.datasets.lerobot",
    "jepa_envs.datasets.lerobot_format": "jepa_envs.datasets.lerobot",
    "jepa_envs.render_dataset": "jepa_envs.datasets.render_dataset",
    "jepa_envs.convert_abs_actions": "jepa_envs.datasets.convert_abs_actions",
    "jepa_envs.pool": "jepa_envs.rollouts.pool",
}


class MovedModules(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds an old name and loads it as the module at its new place (the same module object, not a copy)."""

    def find_spec(self, fullname, path=None, target=None):
        return importlib.util.spec_from_loader(fullname, self) if fullname in MOVED else None

    def create_module(self, spec):
        return None

    def exec_module(self, module) -> None:
        new = MOVED[module.__name__]
        warnings.warn(f"{module.__name__} moved to {new}; the old name goes away in the next release",
                      DeprecationWarning, stacklevel=2)
        # the import system returns what sys.modules holds under the old name after this call
        sys.modules[module.__name__] = importlib.import_module(new)


def install() -> None:
    if not any(isinstance(finder, MovedModules) for finder in sys.meta_path):
        sys.meta_path.append(MovedModules())
