#!/usr/bin/env bash
# `make interop`: check our LeRobot and openpi integrations against the real libraries users run, each in a venv
# of its own (their pins clash with ours), then run scripts/interop.py. Idempotent: a second run only checks.
#
#   LeRobot 0.4.4 (the newest release for Python 3.11, LeRobotDataset v3.0) pins torch < 2.11; it is installed
#   with --no-deps beside torch 2.13.0 and torchvision 0.28.0 from PyPI (its dataset code imports torchvision,
#   whose PyPI wheel needs PyPI's CUDA build of torch: about 4 GB, downloaded once into .cache/interop), the
#   torchcodec that decodes its videos (it loads Debian's FFmpeg libraries) and the modules its dataset code
#   imports; JEPA Policy's LeRobot plugin goes there too (scripts/interop_lerobot_policy.py runs lerobot-train and
#   lerobot-eval with it). openpi-client needs numpy < 2: its own small venv. gym-pusht 0.1.8 (the standard Push-T) pins
#   pymunk < 7 (ours is 7.x): its own venv; scripts/interop_pusht.py checks our standard PushT against it step for
#   step and writes docs/pusht_parity.md.
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

status=0
python3 scripts/interop_pusht.py --gym-pusht-python "$GYM_PUSHT/bin/python" \
  --lerobot-python "$LEROBOT/bin/python" --table docs/pusht_parity.md || status=1
python3 scripts/interop.py --lerobot-python "$LEROBOT/bin/python" --openpi-python "$OPENPI/bin/python" "$@" || status=1
python3 scripts/interop_lerobot_policy.py --lerobot-venv "$LEROBOT" || status=1
exit $status
