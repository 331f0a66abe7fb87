"""LIBERO-10 tasks: gymnasium compliance, spaces, seeded initial states, image orientation, config handling."""
import os
import subprocess
import sys

import mujoco
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

pytest.importorskip("robosuite", reason="robosuite is part of the [sim] extra")
from jepa_envs.tasks import libero_setup  # noqa: E402

try:
    libero_setup.libero_benchmark_root()
    libero_setup.check_assets()
except libero_setup.LiberoSetupError as exc:  # pragma: no cover - depends on the install
    pytest.skip(f"LIBERO not installed or not set up ({exc})", allow_module_level=True)

import jepa_envs  # noqa: E402,F401
from jepa_envs.tasks import abs_actions, rotations  # noqa: E402
from jepa_envs.tasks.libero_env import LiberoEnv  # noqa: E402
from jepa_envs.tasks.robosuite_common import upright  # noqa: E402

SIZE = 64


@pytest.fixture(scope="module")
def moka():
    env = LiberoEnv("MokaMoka", image_size=SIZE)
    yield env
    env.close()


def test_mokamoka_passes_check_env(moka):
    check_env(moka, skip_render_check=True)


def test_mugmug_passes_check_env_with_default_size():
    import gymnasium as gym

    env = gym.make("JEPA/MugMug-v0")
    try:
        base = env.unwrapped
        assert base.task_spec.image_size == 84 and base.task_spec.max_episode_steps == 300
        assert "white mug on the left plate" in base.language_instruction
        check_env(base, skip_render_check=True)
        obs, _ = env.reset(seed=0)
        assert obs["agentview_image"].shape == (84, 84, 3)
    finally:
        env.close()


def test_spaces_and_success_flag(moka):
    spec = moka.task_spec
    assert set(moka.observation_space.spaces) == {"agentview_image", "robot0_eye_in_hand_image",
                                                 "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos"}
    assert moka.action_space.shape == (10,) and spec.horizon == 16
    obs, info = moka.reset(seed=0)
    assert moka.observation_space.contains(obs)
    assert obs["agentview_image"].shape == (SIZE, SIZE, 3) and obs["agentview_image"].dtype == np.uint8
    assert obs["robot0_eef_pos"].dtype == np.float32
    assert type(info["is_success"]) is bool and info["is_success"] is False
    *_, terminated, truncated, info = moka.step(moka.hold_action())
    assert type(info["is_success"]) is bool and terminated is False and truncated is False


def test_resets_use_libero_initial_states(moka):
    assert moka.init_states.shape[0] == 50
    a, _ = moka.reset(seed=5)
    first = moka.init_state_id
    b, _ = moka.reset(seed=5)
    assert moka.init_state_id == first
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])
    ids = set()
    for seed in range(6):
        moka.reset(seed=seed)
        ids.add(moka.init_state_id)
    assert len(ids) > 1
    moka.reset(options={"init_state_id": 3})
    assert moka.init_state_id == 3
    # the objects start where LIBERO's initial state puts them (the robot settles for a few steps first)
    state = moka.backend.sim.get_state().flatten()
    np.testing.assert_allclose(state[1 + 9:1 + 9 + 7], moka.init_states[3][1 + 9:1 + 9 + 7], atol=5e-3)
    with pytest.raises(ValueError, match="init_state_id"):
        moka.reset(options={"init_state_id": 50})


def _body_pixels(env, camera):
    """Which body each pixel of our (upright) view shows, from MuJoCo's segmentation pass (raw, bottom row
    first, like robosuite's RGB frames)."""
    sim, model = env.backend.sim, env.backend.sim.model
    ctx = sim._render_context_offscreen
    env._make_gl_current()
    ctx.render(SIZE, SIZE, camera_id=model.camera_name2id(camera), segmentation=True)
    rgb = np.empty((SIZE, SIZE, 3), dtype=np.uint8)
    mujoco.mjr_readPixels(rgb, None, mujoco.MjrRect(0, 0, SIZE, SIZE), ctx.con)
    seg = rgb[..., 0].astype(np.int64) + 256 * rgb[..., 1].astype(np.int64) + 65536 * rgb[..., 2].astype(np.int64)
    body_of_seg = np.full(ctx.scn.ngeom + 1, -1)
    for i in range(ctx.scn.ngeom):
        geom = ctx.scn.geoms[i]
        if geom.segid != -1 and geom.objtype == mujoco.mjtObj.mjOBJ_GEOM:
            body_of_seg[geom.segid + 1] = model.geom_bodyid[geom.objid]
    seg[seg > ctx.scn.ngeom] = 0
    return upright(body_of_seg[seg][..., None])[..., 0]


def test_agentview_shows_the_cameras_true_view(moka):
    """Objects appear where the camera's pose and field of view project them: right way up and not mirrored."""
    obs, _ = moka.reset(seed=0)
    sim, model = moka.backend.sim, moka.backend.sim.model
    cam = model.camera_name2id("agentview")
    focal = (SIZE / 2) / np.tan(np.deg2rad(model.cam_fovy[cam]) / 2)
    cam_pos, cam_mat = sim.data.cam_xpos[cam], sim.data.cam_xmat[cam].reshape(3, 3)
    bodies = _body_pixels(moka, "agentview")
    rows = {}
    for name in ("moka_pot_1_main", "moka_pot_2_main", "robot0_base"):
        body = model.body_name2id(name)
        p = cam_mat.T @ (sim.data.xpos[body] - cam_pos)  # camera frame: x right, y up, looking along -z
        expected = np.array([SIZE / 2 - focal * p[1] / -p[2], SIZE / 2 + focal * p[0] / -p[2]])
        family = [b for b in range(model.nbody) if b == body or model.body_parentid[b] == body]
        r, c = np.nonzero(np.isin(bodies, family))
        assert len(r) > 10, f"{name} not visible"
        np.testing.assert_allclose([r.mean(), c.mean()], expected, atol=4.0, err_msg=name)
        rows[name] = r.mean()
    # the robot stands behind the table: upper part of the image; the pots on the table below it
    assert rows["robot0_base"] < SIZE / 2 < rows["moka_pot_2_main"]
    # the RGB frame went through the same transform: the wooden table fills the lower half, which is brighter
    gray = obs["agentview_image"].astype(float).mean(axis=2)
    assert gray[SIZE // 2:].mean() > gray[: SIZE // 8].mean()


def test_absolute_action_sets_the_controller_goal(moka):
    moka.reset(seed=1)
    moka.set_render_images(False)
    try:
        assert moka.backend.robots[0].controller.use_delta is False
        pos, mats = moka.controller_pose()
        target_m = mats @ rotations.axis_angle_to_matrix(np.array([0.2, 0.0, 0.1]))
        action = abs_actions.pose_to_abs(pos + [0.03, 0.02, 0.04], target_m, np.array([1.0]))
        moka.step(action)
        goal_p, goal_m = moka.controller_goal()
        np.testing.assert_allclose(goal_p, pos + [0.03, 0.02, 0.04], atol=1e-9)
        np.testing.assert_allclose(goal_m, target_m, atol=1e-6)
    finally:
        moka.set_render_images(True)


def test_libero_config_is_written_and_import_never_prompts(tmp_path):
    """With an empty config dir and no stdin, importing our LIBERO backend writes the config and does not ask."""
    env = {**os.environ, "LIBERO_CONFIG_PATH": str(tmp_path / "cfg"), "MUJOCO_GL": "osmesa"}
    code = ("import jepa_envs.tasks.libero_env as m; from jepa_envs.tasks.libero_setup import ensure_libero_config; "
            "ensure_libero_config(); import libero.libero as l; print(l.get_libero_path('bddl_files'))")
    out = subprocess.run([sys.executable, "-c", code], env=env, stdin=subprocess.DEVNULL, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "Do you want" not in out.stdout
    assert (tmp_path / "cfg" / "config.yaml").is_file()
    assert out.stdout.strip().splitlines()[-1] == str(libero_setup.libero_benchmark_root() / "bddl_files")


def test_stale_config_is_rewritten(tmp_path, monkeypatch):
    monkeypatch.setenv("LIBERO_CONFIG_PATH", str(tmp_path))
    (tmp_path / "config.yaml").write_text("bddl_files: /nonexistent\n")
    path = libero_setup.ensure_libero_config()
    import yaml

    cfg = yaml.safe_load(path.read_text())
    assert set(cfg) == set(libero_setup.CONFIG_KEYS)
    assert os.path.isdir(cfg["bddl_files"]) and os.path.isdir(cfg["init_states"])


def test_setup_links_assets_idempotently(capsys):
    assert libero_setup.main([]) == 0
    assert libero_setup.main([]) == 0
    assets = libero_setup.check_assets()
    assert (assets / "scenes").is_dir()
    assert "LIBERO_CONFIG_PATH" in capsys.readouterr().out


def test_same_initial_state_id_is_the_same_scene(moka):
    """The stove (a fixture: a fixed body placed at reset, absent from LIBERO's stored states) stands where it
    stood the last time this id was loaded, whatever came between; other ids may place it elsewhere."""
    stove = moka.backend.sim.model.body_name2id(moka.libero_env.env.fixtures_dict["flat_stove_1"].root_body)
    scenes = []
    for init_id in (7, 3, 7, 7):
        obs, _ = moka.reset(options={"init_state_id": init_id})
        scenes.append((moka.backend.sim.model.body_pos[stove].copy(), moka.backend.sim.model.body_quat[stove].copy(),
                       obs["agentview_image"].copy()))
    for later in (scenes[2], scenes[3]):
        np.testing.assert_array_equal(later[0], scenes[0][0])
        np.testing.assert_array_equal(later[1], scenes[0][1])
        np.testing.assert_array_equal(later[2], scenes[0][2])
    # numpy's global stream is the caller's: a reset neither consumes nor reseeds it
    np.random.seed(123)
    expected = np.random.random(3)
    np.random.seed(123)
    moka.reset(options={"init_state_id": 5})
    np.testing.assert_array_equal(np.random.random(3), expected)
