"""LIBERO-10 tasks MokaMoka and MugMug behind our Gymnasium interface (LIBERO's OffScreenRenderEnv on robosuite).

Same conventions as the robomimic tasks: ``agentview_image`` / ``robot0_eye_in_hand_image`` the right way up,
float32 proprioception, absolute (10-D) or LIBERO's native delta (7-D) OSC_POSE actions. Resets start from
LIBERO's fixed initial states of the task (50 per task), chosen by the seed or by
``options={"init_state_id": i}`` (the fixtures, which LIBERO's states leave out, placed by a seed of ``i``: the
same id is the same scene), followed by the few still steps LIBERO's own evaluation takes to let objects
settle. Default image size 84 (the paper's); pass ``image_size=128`` for LIBERO-native frames.
"""
from __future__ import annotations

import os

from jepa_envs.tasks.libero_setup import check_assets, ensure_libero_config
from jepa_envs.tasks.robosuite_common import (CONSTRUCTION_SEED, RobosuiteTaskEnv, check_action_mode, global_numpy_seed,
                                              set_control_delta)
from jepa_envs.tasks.spec import get_task_spec

BENCHMARK = "libero_10"
SETTLE_STEPS = 5  # still steps after loading an initial state, as in LIBERO's evaluation (lifelong/metric.py)
FIXTURE_SEED = 20_240_000  # + init_state_id: where the fixtures stand in that initial state


class LiberoEnv(RobosuiteTaskEnv):
    """MokaMoka / MugMug from LIBERO-10.

    Args:
        task: "MokaMoka" or "MugMug" (or their gym ids).
        image_size: camera resolution (84 default; LIBERO's datasets are 128).
        render_mode: None or "rgb_array".
        action_mode: "abs" (paper convention) or "delta" (LIBERO's native OSC_POSE deltas).
        hard_reset: robosuite's reset mode; the initial state is loaded after the reset either way.
    """

    def __init__(self, task: str = "MokaMoka", image_size: int | None = None, render_mode: str | None = None,
                 action_mode: str = "abs", hard_reset: bool = False):
        spec = get_task_spec(task)
        if spec.suite != "libero":
            raise ValueError(f"LiberoEnv serves LIBERO tasks; {spec.name} is a {spec.suite} task")
        spec = spec.with_image_size(image_size or spec.image_size)
        check_action_mode(action_mode)
        ensure_libero_config()  # before the first libero import: it would otherwise ask a question on stdin
        check_assets()
        from libero.libero import benchmark, get_libero_path
        from libero.libero.envs import OffScreenRenderEnv

        suite = benchmark.get_benchmark_dict()[BENCHMARK]()
        names = [t.name for t in suite.tasks]
        if spec.source_task not in names:
            raise KeyError(f"{spec.source_task} is not a {BENCHMARK} task of this LIBERO install")
        index = names.index(spec.source_task)
        task_info = suite.get_task(index)
        self.bddl_file = os.path.join(get_libero_path("bddl_files"), task_info.problem_folder, task_info.bddl_file)
        self.init_states = suite.get_task_init_states(index)
        with global_numpy_seed(CONSTRUCTION_SEED):   # the same scene in every process (robosuite_common)
            self.libero_env = OffScreenRenderEnv(
                bddl_file_name=self.bddl_file, camera_names=list(spec.cameras), camera_heights=spec.image_size,
                camera_widths=spec.image_size, ignore_done=True, hard_reset=hard_reset)
        self.language_instruction = self.libero_env.language_instruction
        backend = self.libero_env.env  # the robosuite env inside LIBERO's wrapper
        set_control_delta(backend, action_mode == "delta")
        super().__init__(spec, backend, render_mode=render_mode, action_mode=action_mode,
                         success_fn=self.libero_env.check_success)

    def _backend_reset(self, options: dict | None) -> dict:
        init_id = (options or {}).get("init_state_id")
        if init_id is None:
            init_id = int(self.np_random.integers(len(self.init_states)))
        if not 0 <= int(init_id) < len(self.init_states):
            raise ValueError(f"init_state_id must be in [0, {len(self.init_states)}), got {init_id}")
        self.init_state_id = int(init_id)
        # LIBERO's stored initial states hold the movable objects (qpos), not the fixtures (the stove is a fixed
        # body placed by the reset's sampler into model.body_pos): seed that placement by the initial state's id,
        # so the same id is the same scene every time.
        with global_numpy_seed(FIXTURE_SEED + self.init_state_id):
            self.libero_env.reset()
        raw = self.libero_env.set_init_state(self.init_states[self.init_state_id])
        if SETTLE_STEPS:
            rendering = self.render_images
            self.set_render_images(False)  # nobody sees the settling frames: do not render them
            hold = self.to_native(self.hold_action(gripper=-1.0))
            for _ in range(SETTLE_STEPS):
                self.backend.step(hold)
            self.set_render_images(rendering)
            self.backend._update_observables(force=True)
            raw = self.backend._get_observations()
        return raw

    def close(self):
        if getattr(self, "backend", None) is not None:
            self._make_gl_current()
            self.libero_env.close()
            self.backend = None
