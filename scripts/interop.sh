#!/usr/bin/env bash
# `make interop`: check our LeRobot and openpi integrations against the real libraries users run, each in a venv
# of its own (their pins clash with ours), then run the checks (scripts/interop*.py) and print one summary table
# (scripts/interop_summary.py). Idempotent: a second run only checks.
#
#   LeRobot 0.4.4 (the newest release for Python 3.11, LeRobotDataset v3.0) pins torch < 2.11; it is installed
#   with --no-deps beside torch 2.13.0 and torchvision 0.28.0 from PyPI (its dataset code imports torchvision,
#   whose PyPI wheel needs PyPI's CUDA build of torch: about 4 GB, downloaded once into .cache/interop), the
#   torchcodec that decodes its videos (it loads Debian's FFmpeg libraries) and the modules its dataset code
#   imports; JEPA Policy's LeRobot plugin goes there too (scripts/interop_lerobot_policy.py runs lerobot-train and
#   lerobot-eval with it). openpi-client needs numpy < 2: its own small venv. gym-pusht 0.1.8 (the standard Push-T) pins
#   pymunk < 7 (ours is 7.x): its own venv; scripts/interop_pusht.py checks our standard PushT against it step for
#   step and writes docs/pusht_parity.md. robomimic 0.3.0 (its EnvRobosuite, dataset_states_to_obs.py and replay,
#   the oracle for our Lift, Can and Square) imports torchvision through its dataset script: its own venv, with
#   --no-deps beside robosuite 1.4.1 and mujoco 3.3.7 as ours, the CUDA torch from PyPI again (pip's cache keeps the
#   download) and robomimic's own next-day fix of its mujoco_py import (commit 8df6e8e, in every later release);
#   scripts/interop_robomimic.py writes docs/robomimic_parity.md.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=.cache/interop
mkdir -p "$ROOT"
SUDO=""
[ "$(id -u)" = 0 ] || SUDO="sudo"
# pip's machine-wide configuration points at a CPU-only torch file and caps versions; these venvs use PyPI's
PIPX=(env PIP_FIND_LINKS= PIP_CONFIG_FILE=/dev/null)

if ! dpkg -s ffmpeg >/dev/null 2>&1; then
  echo "[interop] Debian's ffmpeg (torchcodec loads its libraries)"
  $SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq ffmpeg >/dev/null
fi

LEROBOT=$ROOT/lerobot
if ! "$LEROBOT/bin/python" -c "import lerobot.datasets.lerobot_dataset, torchcodec" 2>/dev/null; then
  echo "[interop] LeRobot venv ($LEROBOT; the CUDA torch download is large)"
  python3.11 -m venv "$LEROBOT"
  "${PIPX[@]}" "$LEROBOT/bin/pip" install -q --disable-pip-version-check \
    "torch==2.13.0" "torchvision==0.28.0" "torchcodec==0.13.0"
  "${PIPX[@]}" "$LEROBOT/bin/pip" install -q --disable-pip-version-check --no-deps "lerobot==0.4.4"
  "${PIPX[@]}" "$LEROBOT/bin/pip" install -q --disable-pip-version-check "datasets>=4.0,<5" \
    "huggingface-hub>=0.34.2,<0.36" pandas pyarrow "av>=15,<16" jsonlines "packaging>=24.2,<26" "draccus==0.10.0" \
    "deepdiff>=7.0.1,<9" "termcolor>=2.4" accelerate einops
fi
# The LeRobot plugin of JEPA Policy (jepa_policy/lerobot_plugin): this project without its dependencies, the
# modules `import jepa_policy.policy` needs, what lerobot-train / lerobot-eval import beyond the dataset code
# (diffusers, pyserial), and gym-pusht 0.1.8 for `lerobot-eval --env.type=pusht` (its pymunk < 7, gymnasium 1.x
# and opencv clash with nothing LeRobot pins)
if ! "$LEROBOT/bin/python" -c "import lerobot_policy_jepa, lerobot.scripts.lerobot_train, gym_pusht" 2>/dev/null; then
  echo "[interop] JEPA Policy's LeRobot plugin and gym-pusht in $LEROBOT"
  "${PIPX[@]}" "$LEROBOT/bin/pip" install -q --disable-pip-version-check "gym-pusht==0.1.8" \
    "diffusers>=0.27.2,<0.36" "pyserial>=3.5,<4" "imageio[ffmpeg]>=2.34" scikit-learn h5py tqdm
  "${PIPX[@]}" "$LEROBOT/bin/pip" install -q --disable-pip-version-check --no-deps -e . -e jepa_policy/lerobot_plugin
fi

OPENPI=$ROOT/openpi
if ! "$OPENPI/bin/python" -c "import openpi_client.websocket_client_policy" 2>/dev/null; then
  echo "[interop] openpi-client venv ($OPENPI)"
  python3.11 -m venv "$OPENPI"
  # its PyPI release imports typing_extensions without declaring it
  "${PIPX[@]}" "$OPENPI/bin/pip" install -q --disable-pip-version-check "openpi-client==0.1.2" typing_extensions
fi

GYM_PUSHT=$ROOT/gym_pusht
if ! "$GYM_PUSHT/bin/python" -c "import gym_pusht, PIL" 2>/dev/null; then
  echo "[interop] gym-pusht venv ($GYM_PUSHT)"
  python3.11 -m venv "$GYM_PUSHT"
  # pillow: our PushT replays there too, on pymunk 6 (a control that tells pymunk versions from us)
  "${PIPX[@]}" "$GYM_PUSHT/bin/pip" install -q --disable-pip-version-check "gym-pusht==0.1.8" pillow
fi

ROBOMIMIC=$ROOT/robomimic
if ! "$ROBOMIMIC/bin/python" -c "import robomimic.scripts.dataset_states_to_obs, robomimic.envs.env_robosuite, \
    robomimic.macros_private, robosuite.macros_private" 2>/dev/null; then
  echo "[interop] robomimic 0.3.0 venv ($ROBOMIMIC)"
  python3.11 -m venv "$ROBOMIMIC"
  # what its env, file and dataset-script code import (its file utils load its models, which import torchvision)
  "${PIPX[@]}" "$ROBOMIMIC/bin/pip" install -q --disable-pip-version-check "torch==2.13.0" "torchvision==0.28.0" \
    "numpy==2.3.5" "robosuite==1.4.1" "mujoco==3.3.7" "numba==0.68.1" "scipy==1.17.1" "h5py==3.16.0" termcolor tqdm \
    matplotlib egl_probe
  "${PIPX[@]}" "$ROBOMIMIC/bin/pip" install -q --disable-pip-version-check --no-deps "robomimic==0.3.0"
  # 0.3.0 imports mujoco_py, which robosuite 1.4 no longer uses and which does not build here: robomimic's own fix
  SITE=$("$ROBOMIMIC/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
  if grep -q "^import mujoco_py" "$SITE/robomimic/envs/env_robosuite.py"; then
    patch -s -p1 -d "$SITE" < scripts/interop_robomimic_8df6e8e.patch
  fi
  # both packages' private settings files (without them every import warns; robosuite's script asks on stdin)
  [ -f "$SITE/robosuite/macros_private.py" ] || "$ROBOMIMIC/bin/python" -m robosuite.scripts.setup_macros >/dev/null 2>&1
  [ -f "$SITE/robomimic/macros_private.py" ] || "$ROBOMIMIC/bin/python" -m robomimic.scripts.setup_macros >/dev/null
fi

# Each part runs through `part`, which keeps its output in interop_out/parts/NAME.log and writes its exit status, wall
# time and the load before and after to interop_out/parts/NAME.json with this run's id; each part's script writes its
# own result with the id too, and scripts/interop_summary.py prints one table of this run's parts (a part with no
# result of this run is a FAIL, never an earlier run's pass).
OUT=interop_out
export PYTHONUNBUFFERED=1 INTEROP_RUN_ID
INTEROP_RUN_ID="$(date -u +%Y%m%dT%H%M%SZ)-$$"
mkdir -p "$OUT/parts"
LOAD_START=$(cut -d' ' -f1-3 /proc/loadavg)
STARTED=$SECONDS
part() {
  local name=$1 start=$SECONDS load rc
  shift
  load=$(cut -d' ' -f1-3 /proc/loadavg)
  echo "[interop] $name: $*"
  set +e
  "$@" 2>&1 | tee "$OUT/parts/$name.log"
  rc=${PIPESTATUS[0]}
  set -e
  printf '{"part": "%s", "run_id": "%s", "exit": %d, "seconds": %d, "load_before": "%s", "load_after": "%s"}\n' \
    "$name" "$INTEROP_RUN_ID" "$rc" $((SECONDS - start)) "$load" "$(cut -d' ' -f1-3 /proc/loadavg)" \
    > "$OUT/parts/$name.json"
}
part lerobot-data python3 scripts/interop.py --only lerobot --lerobot-python "$LEROBOT/bin/python" \
  --openpi-python "$OPENPI/bin/python" --out "$OUT"
part lerobot-plugin python3 scripts/interop_lerobot_policy.py --lerobot-venv "$LEROBOT" --work "$OUT/lerobot_policy"
part openpi python3 scripts/interop.py --only openpi --lerobot-python "$LEROBOT/bin/python" \
  --openpi-python "$OPENPI/bin/python" --out "$OUT"
part gym-pusht python3 scripts/interop_pusht.py --gym-pusht-python "$GYM_PUSHT/bin/python" \
  --table docs/pusht_parity.md --out "$OUT"
part robomimic python3 scripts/interop_robomimic.py --robomimic-python "$ROBOMIMIC/bin/python" \
  --table docs/robomimic_parity.md --out "$OUT"
python3 scripts/interop_summary.py --run-id "$INTEROP_RUN_ID" --seconds $((SECONDS - STARTED)) --load "$LOAD_START" \
  --out "$OUT"
