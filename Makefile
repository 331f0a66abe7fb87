# The README's two commands: `make demo` (the main job on the embedded PushT task) and `make test`.
# Each does all set-up itself (scripts/setup.sh is idempotent).
export MUJOCO_GL ?= osmesa
export PYOPENGL_PLATFORM ?= osmesa
PYTHON ?= python3

.PHONY: setup demo test bench
setup:
	bash scripts/setup.sh

demo: setup
	jepa-demo $(ARGS)

test: setup
	$(PYTHON) -m pytest -q $(ARGS)

bench: setup
	jepa-envs bench
	jepa-policy bench latency --task ToolHang --arms mip,jepa,diffusion
	jepa-monitor bench
