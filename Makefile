# The README's two commands: `make demo` (the main job on the embedded PushT task) and `make test`.
# Each does all set-up itself (scripts/setup.sh is idempotent).
# The tests render with OSMesa (deterministic, no renderer probe); elsewhere jepa_envs measures and picks the
# fastest backend that renders identical frames (jepa_envs/tasks/render.py), unless MUJOCO_GL is set.
test: export MUJOCO_GL ?= osmesa
test: export PYOPENGL_PLATFORM ?= osmesa
PYTHON ?= python3

.PHONY: setup demo test bench interop
setup:
	bash scripts/setup.sh

demo: setup
	jepa-demo $(ARGS)

# Two test processes (pytest-xdist), each taking whole files, so a module's fixtures are built once: 1,570 tests in
# 653 s instead of 1,257 s one after another on this 2-core machine (most tests wait on servers, sockets and
# renders; run alone they take as long). At most 4 processes on larger machines. ARGS="-n 0" runs them serially.
test: setup
	$(PYTHON) -m pytest -q -n auto --maxprocesses 4 --dist loadfile $(ARGS)

bench: setup
	jepa-envs bench
	jepa-policy bench latency --task ToolHang --arms mip,jepa,diffusion
	jepa-monitor bench

# our LeRobot and openpi integrations against the real libraries, each in a venv of its own (large, once)
interop: setup
	bash scripts/interop.sh
