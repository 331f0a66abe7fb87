"""Demonstration datasets: robomimic / MimicGen and LIBERO HDF5 files read into ONE in-memory layout.

Layout the policy samples from (:class:`DemoDataset`): every observation key concatenated over episodes
(images uint8 (N, S, S, 3), low-dim float32 (N, D)), actions float32 (N, A) and ``episode_ends`` (E,) int64
cumulative exclusive ends (as diffusion_policy's ReplayBuffer), plus the task spec and the file's env_args.

Files:
- robomimic / MimicGen: ``data/demo_N/{obs/<key>, actions, states, rewards, dones}``, ``data.attrs["env_args"]``
  (JSON with env_name, env_kwargs), ``data.attrs["total"]``, ``demo_N.attrs["num_samples"]``. Images are stored
  upright (robomimic flips robosuite's OpenGL frames when it writes them).
- LIBERO: ``data/demo_N/obs/{agentview_rgb, eye_in_hand_rgb, joint_states, gripper_states, ee_states}``, with
  ``bddl_file_name``, ``env_args`` and ``problem_info`` in ``data.attrs``. LIBERO stores the raw OpenGL frames
  of both cameras; their rows are flipped (``[::-1]``), exactly what our LIBERO env does to its renders
  (``jepa_envs.tasks.robosuite_common.upright``: a 180-degree turn would also mirror left and right),
  ``ee_states`` (position 3 + axis-angle 3) becomes ``robot0_eef_pos`` and ``robot0_eef_quat`` (x, y, z, w)
  and ``gripper_states`` becomes ``robot0_gripper_qpos``.

Actions: files with the task's action dimension are used as they are. Absolute 7-D-per-arm actions
(position, axis-angle, gripper; ``control_delta: false`` in the controller config) are converted to the
paper's 10-D-per-arm convention (position, 6-D rotation, gripper; Sec. 4.1). Delta actions are refused with an
error that says how to convert them.

A load is cached as ``.npy`` files keyed by the file's path, size and mtime (and the requested task and image
size); the second load memory-maps them.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np
from PIL import Image

from jepa_envs.tasks.rotations import axis_angle_to_quat, axis_angle_to_rot6d
from jepa_envs.tasks.spec import TaskSpec, all_task_specs, get_task_spec

CACHE_VERSION = 1
LIBERO_IMAGE_KEYS = {"agentview_rgb": "agentview_image", "eye_in_hand_rgb": "robot0_eye_in_hand_image"}


class DatasetError(ValueError):
    """A dataset file that cannot be used; the message names the file, the place and the fix."""


@dataclass
class DemoDataset:
    """All demonstrations of one file, concatenated over episodes (see the module docstring)."""

    obs: dict[str, np.ndarray]
    actions: np.ndarray
    episode_ends: np.ndarray
    spec: TaskSpec
    env_args: dict
    path: str = ""
    from_cache: bool = False
    demo_names: list[str] = field(default_factory=list)

    def num_episodes(self) -> int:
        return int(len(self.episode_ends))

    def __len__(self) -> int:
        return int(self.episode_ends[-1]) if len(self.episode_ends) else 0

    def episode_slice(self, i: int) -> slice:
        """Steps of episode ``i`` in the concatenated arrays."""
        n = self.num_episodes()
        if not -n <= i < n:
            raise IndexError(f"episode {i} out of range for a dataset of {n} episodes")
        i %= n
        start = int(self.episode_ends[i - 1]) if i > 0 else 0
        return slice(start, int(self.episode_ends[i]))

    def episode(self, i: int) -> dict:
        """``{"obs": {key: (T, ...)}, "actions": (T, A)}`` of episode ``i``."""
        sl = self.episode_slice(i)
        return {"obs": {k: v[sl] for k, v in self.obs.items()}, "actions": self.actions[sl]}


# -- task lookup ----------------------------------------------------------------------------------------------

def _norm(name: str) -> str:
    return re.sub(r"[^a-z0-9]", "", name.lower())


def task_for_env_name(env_name: str) -> TaskSpec | None:
    """Our task for a backend env name ("NutAssemblySquare", "Coffee_Preparation_D1", "JEPA/ToolHang-v0", ...)."""
    key = _norm(env_name)
    for spec in all_task_specs():
        if key in {_norm(spec.name), _norm(spec.env_id), _norm(spec.source_task)}:
            return spec
    return None


def resolve_task(task: str | None, env_args: dict, path) -> TaskSpec:
    """The task a file is for: ``task`` when given, else the one its env_args name; DatasetError otherwise."""
    if task is not None:
        try:
            return get_task_spec(task)
        except KeyError as exc:
            raise DatasetError(exc.args[0]) from None
    found = task_for_env_name(str(env_args.get("env_name", "")))
    if found is None:
        raise DatasetError(f"{path}: env {env_args.get('env_name')!r} is not one of our tasks; pass --task NAME")
    return found


def _known_env_names() -> str:
    return ", ".join(sorted({s.source_task for s in all_task_specs()} | {s.name for s in all_task_specs()}))


# -- writing --------------------------------------------------------------------------------------------------

def demo_names(data: h5py.Group) -> list[str]:
    """The ``demo_N`` groups of a file's ``data`` group, in episode order (N numerically, not as text)."""
    return sorted((k for k in data.keys() if re.fullmatch(r"demo_\d+", k)), key=lambda k: int(k.split("_")[1]))


def write_dataset(path, episodes: list[dict], env_args: dict) -> None:
    """Write episodes as a robomimic-layout HDF5 file (atomically: a temp file renamed into place).

    Each episode dict has ``obs`` (dict of arrays with T rows), ``actions`` (T, A) and optionally ``states``,
    ``rewards`` and ``dones`` (T rows each), and ``attrs`` (JSON-able values stored on its demo group).
    ``env_args`` must contain ``env_name``.
    """
    if not episodes:
        raise ValueError("write_dataset needs at least one episode")
    for i, ep in enumerate(episodes):
        _check_episode(i, ep)
    with DemoWriter(path, env_args) as writer:
        for ep in episodes:
            writer.add(ep)


class DemoWriter:
    """Writes a robomimic-layout HDF5 file one episode at a time (memory bounded by one episode).

    The file appears at ``path`` only when the ``with`` block ends without an error; until then it is a
    temporary file beside it, removed on any error, so a failed write leaves nothing half-written.
    """

    def __init__(self, path, env_args: dict):
        self.path = Path(path)
        if "env_name" not in env_args:
            raise ValueError("env_args must contain 'env_name' (e.g. 'PushT') so readers can find the task")
        try:
            self.env_args_json = json.dumps(env_args)
        except TypeError as exc:
            raise ValueError(f"env_args must be JSON-serialisable: {exc}") from exc
        self.episodes = 0
        self.total = 0

    def __enter__(self) -> "DemoWriter":
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, self.tmp = tempfile.mkstemp(prefix=self.path.name + ".", suffix=".tmp", dir=self.path.parent)
        os.close(fd)
        self.file = h5py.File(self.tmp, "w")
        self.data = self.file.create_group("data")
        return self

    def add(self, ep: dict, name: str | None = None) -> None:
        """Append one episode (the dict ``write_dataset`` takes) as ``data/<name>`` (default: demo_N, N counting
        the episodes written), e.g. the name it had in the file it was read from."""
        _check_episode(self.episodes, ep)
        name = f"demo_{self.episodes}" if name is None else name
        if not re.fullmatch(r"demo_\d+", name) or name in self.data:
            raise ValueError(f"episode name {name!r} must be demo_N and not written before")
        g = self.data.create_group(name)
        n = len(ep["actions"])
        g.attrs["num_samples"] = n
        for key, value in (ep.get("attrs") or {}).items():
            g.attrs[key] = value
        obs = g.create_group("obs")
        for key, value in ep["obs"].items():
            value = np.asarray(value)
            image = value.dtype == np.uint8 and value.ndim == 4
            obs.create_dataset(key, data=value, compression="lzf" if image else None,
                               chunks=(1, *value.shape[1:]) if image else None)
        g.create_dataset("actions", data=np.asarray(ep["actions"]))
        for key in ("states", "rewards", "dones"):
            if ep.get(key) is not None:
                g.create_dataset(key, data=np.asarray(ep[key]))
        self.episodes += 1
        self.total += n

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if exc_type is None:
                if self.episodes == 0:
                    raise ValueError(f"no episode was written to {self.path}; a dataset needs at least one")
                self.data.attrs["total"] = self.total
                self.data.attrs["env_args"] = self.env_args_json
            self.file.close()
            if exc_type is None:
                umask = os.umask(0)
                os.umask(umask)
                os.chmod(self.tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the file the usual permissions
                os.replace(self.tmp, self.path)
        finally:
            if os.path.exists(self.tmp):
                os.remove(self.tmp)


def _check_episode(i: int, ep: dict) -> None:
    if "obs" not in ep or "actions" not in ep:
        raise ValueError(f"episode {i} must have 'obs' and 'actions'; it has {sorted(ep)}")
    actions = np.asarray(ep["actions"])
    if actions.ndim != 2 or len(actions) == 0:
        raise ValueError(f"episode {i}: actions must be a non-empty (T, A) array, got shape {actions.shape}")
    n = len(actions)
    for key, value in [*((f"obs/{k}", v) for k, v in ep["obs"].items()),
                       *((k, ep[k]) for k in ("states", "rewards", "dones") if ep.get(k) is not None)]:
        if len(np.asarray(value)) != n:
            raise ValueError(f"episode {i}: {key} has {len(np.asarray(value))} rows but actions have {n}")


# -- reading --------------------------------------------------------------------------------------------------

def load_dataset(path, task: str | None = None, image_size: int | None = None, cache_dir=None) -> DemoDataset:
    """Load a robomimic / MimicGen / LIBERO HDF5 file into a :class:`DemoDataset`.

    ``task``: our task name or gym id; found from the file's env_args when omitted. ``image_size``: resize
    images to this square size (default: keep the file's). ``cache_dir``: where the ``.npy`` cache lives
    (default ``$JEPA_DATA_CACHE`` or ``~/.cache/jepa_envs/datasets``); ``False`` disables caching.
    Raises :class:`DatasetError` for files that cannot be used.
    """
    path = Path(path).expanduser().resolve()
    if not path.is_file():
        raise DatasetError(f"dataset file {path} does not exist; make one with "
                           "`jepa-envs make-demos PushT --episodes 100 --out FILE` or pass the right path")
    if image_size is not None and int(image_size) < 8:
        raise DatasetError(f"image_size must be >= 8 pixels, got {image_size}")
    cache = _cache_path(path, task, image_size, cache_dir)
    if cache is not None and (cache / "meta.json").is_file():
        return _load_cache(cache, path)
    with open_hdf5(path) as f:
        reader = _Reader(path, f, task, image_size)
        return reader.read(cache)


def open_hdf5(path: str | Path) -> h5py.File:
    """Open an HDF5 file for reading, or raise DatasetError naming a file that is missing or not HDF5."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path} does not exist; pass the path of an HDF5 dataset")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise DatasetError(f"{path} is not a readable HDF5 file ({exc}); re-download or re-create it") from exc


class _Reader:
    """Validates one open file and fills the concatenated arrays (in memory or straight into the cache)."""

    def __init__(self, path: Path, f: h5py.File, task: str | None, image_size: int | None):
        self.path, self.f = path, f
        if "data" not in f or not isinstance(f["data"], h5py.Group):
            raise DatasetError(f"{path}: no 'data' group; expected robomimic/LIBERO layout data/demo_N/...")
        self.data = f["data"]
        self.demos = demo_names(self.data)
        if not self.demos:
            raise DatasetError(f"{path}: 'data' has no demo_N groups; the file holds no demonstrations")
        self.libero = "bddl_file_name" in self.data.attrs or "agentview_rgb" in self._group(self.demos[0], "obs")
        self.env_args = self._env_args()
        self.spec = self._task(task)
        self.image_size = int(image_size) if image_size is not None else None

    # -- metadata --
    def _group(self, demo: str, sub: str) -> h5py.Group:
        g = self.data[demo]
        if sub not in g or not isinstance(g[sub], h5py.Group):
            raise DatasetError(f"{self.path}: data/{demo} has no '{sub}' group; every demo needs {sub}/<key>")
        return g[sub]

    def _env_args(self) -> dict:
        raw = self.data.attrs.get("env_args")
        if raw is None:
            if self.libero:
                return {}
            raise DatasetError(f"{self.path}: data.attrs['env_args'] is missing; robomimic files store the env "
                               "name and kwargs there (write files with jepa_envs.datasets.hdf5.write_dataset)")
        try:
            env_args = json.loads(raw)
        except (TypeError, ValueError) as exc:
            raise DatasetError(f"{self.path}: data.attrs['env_args'] is not valid JSON ({exc})") from exc
        if not isinstance(env_args, dict):
            raise DatasetError(f"{self.path}: data.attrs['env_args'] must be a JSON object, got {type(env_args)}")
        return env_args

    def _file_task(self) -> TaskSpec | None:
        names = []
        if self.libero:
            bddl = self.data.attrs.get("bddl_file_name")
            if bddl is not None:
                names.append(Path(bddl.decode() if isinstance(bddl, bytes) else str(bddl)).stem)
        if self.env_args.get("env_name"):
            names.append(str(self.env_args["env_name"]))
        for name in names:
            spec = task_for_env_name(name)
            if spec is not None:
                return spec
        return None

    def _task(self, task: str | None) -> TaskSpec:
        found = self._file_task()
        if task is not None:
            try:
                spec = get_task_spec(task)
            except KeyError as exc:
                raise DatasetError(f"{self.path}: {exc.args[0]}") from exc
            if found is not None and found.name != spec.name:
                raise DatasetError(f"{self.path}: the file is a {found.name} dataset but task={task!r} was asked "
                                   f"for; pass task={found.name!r} or the right file")
            return spec
        if found is None:
            name = self.env_args.get("env_name", "<none>")
            raise DatasetError(f"{self.path}: unknown env {name!r}; known env names: {_known_env_names()}. "
                               "Pass task=<our task name> to load it as that task")
        return found

    # -- per-demo arrays --
    def _dataset(self, demo: str, group: h5py.Group, key: str, where: str) -> h5py.Dataset:
        if key not in group or not isinstance(group[key], h5py.Dataset):
            have = ", ".join(sorted(group.keys()))
            place = f"data/{demo}/{where}" if where else f"data/{demo}"
            raise DatasetError(f"{self.path}: {place} has no '{key}' (it has: {have}); the task "
                               f"{self.spec.name} needs it; regenerate the file with this key")
        return group[key]

    def _source_keys(self) -> dict[str, str]:
        """Our obs key -> key in the file (LIBERO keys are mapped)."""
        if self.libero:
            inverse = {v: k for k, v in LIBERO_IMAGE_KEYS.items()}
            keys = {k: inverse.get(k, k) for k in self.spec.image_keys}
            keys.update({"robot0_eef_pos": "ee_states", "robot0_eef_quat": "ee_states",
                         "robot0_gripper_qpos": "gripper_states"})
            return keys
        return {k: k for k in (*self.spec.image_keys, *self.spec.lowdim_keys)}

    def _lengths(self) -> list[int]:
        lengths = []
        for demo in self.demos:
            actions = self._dataset(demo, self.data[demo], "actions", "")
            n = actions.shape[0] if actions.ndim == 2 else -1
            if n <= 0:
                raise DatasetError(f"{self.path}: data/{demo}/actions has shape {actions.shape}; expected (T, A) "
                                   "with T >= 1")
            obs = self._group(demo, "obs")
            for src in set(self._source_keys().values()):
                ds = self._dataset(demo, obs, src, "obs")
                if ds.shape[0] != n:
                    raise DatasetError(f"{self.path}: data/{demo}/obs/{src} has {ds.shape[0]} steps but actions "
                                       f"have {n}; every obs key needs one row per action")
            lengths.append(n)
        return lengths

    def _image_size(self) -> int:
        first = self._group(self.demos[0], "obs")[self._source_keys()[self.spec.image_keys[0]]]
        if self.image_size is not None:
            return self.image_size
        return int(first.shape[1])

    def _images(self, demo: str, key: str, size: int) -> np.ndarray:
        src = self._source_keys()[key]
        ds = self._group(demo, "obs")[src]
        if ds.ndim != 4 or ds.shape[-1] != 3 or ds.dtype != np.uint8:
            raise DatasetError(f"{self.path}: data/{demo}/obs/{src} has shape {ds.shape} dtype {ds.dtype}; "
                               "camera images must be uint8 (T, H, W, 3)")
        images = ds[()]
        if self.libero:
            images = images[:, ::-1]  # LIBERO stores OpenGL frames (bottom row first): flip the rows, as upright()
        if images.shape[1:3] != (size, size):
            if self.image_size is None:
                raise DatasetError(f"{self.path}: data/{demo}/obs/{src} is {images.shape[1]}x{images.shape[2]} "
                                   f"but the file's first camera is {size}x{size}; pass image_size=S to resize")
            images = np.stack([np.asarray(Image.fromarray(np.ascontiguousarray(im)).resize(
                (size, size), Image.BILINEAR)) for im in images])
        return images

    def _lowdim(self, demo: str, key: str, dim: int) -> np.ndarray:
        src = self._source_keys()[key]
        ds = self._group(demo, "obs")[src]
        values = np.asarray(ds[()], dtype=np.float64)
        if self.libero and src == "ee_states":
            if values.ndim != 2 or values.shape[1] != 6:
                raise DatasetError(f"{self.path}: data/{demo}/obs/ee_states has shape {values.shape}; LIBERO "
                                   "ee_states must be (T, 6): position 3 + axis-angle 3")
            values = values[:, :3] if key == "robot0_eef_pos" else axis_angle_to_quat(values[:, 3:6])
        if values.ndim == 1:
            values = values[:, None]
        if values.ndim != 2 or values.shape[1] != dim:
            raise DatasetError(f"{self.path}: data/{demo}/obs/{src} has shape {ds.shape}; task {self.spec.name} "
                               f"expects {key} of shape (T, {dim})")
        return values.astype(np.float32)

    def _actions(self, demo: str) -> np.ndarray:
        actions = np.asarray(self.data[demo]["actions"][()], dtype=np.float64)
        want, arms = self.spec.action_dim, max(self.spec.num_arms, 1)
        if actions.shape[1] == want:
            return actions.astype(np.float32)
        if self.spec.num_arms and actions.shape[1] == 7 * arms and want == 10 * arms:
            if self._control_delta():
                raise DatasetError(
                    f"{self.path}: data/{demo}/actions are 7-D delta actions; the policy needs absolute actions "
                    f"({want}-D). Convert the file to absolute actions first (robosuite backend: "
                    "`jepa-envs convert-abs-actions`), then load it")
            per_arm = actions.reshape(len(actions), arms, 7)
            # Sec. 4.1: position 3 + 6-D rotation 6 + gripper 1 per arm
            converted = np.concatenate([per_arm[..., :3], axis_angle_to_rot6d(per_arm[..., 3:6]),
                                        per_arm[..., 6:7]], axis=-1)
            return converted.reshape(len(actions), want).astype(np.float32)
        raise DatasetError(f"{self.path}: data/{demo}/actions has shape {actions.shape}; task {self.spec.name} "
                           f"expects (T, {want}) actions")

    def _control_delta(self) -> bool:
        controller = (self.env_args.get("env_kwargs") or {}).get("controller_configs") or {}
        return bool(controller.get("control_delta", True))  # robosuite's OSC default is delta

    def read(self, cache: Path | None) -> DemoDataset:
        lengths = self._lengths()
        ends = np.cumsum(lengths).astype(np.int64)
        total = int(ends[-1])
        size = self._image_size()
        spec = self.spec.with_image_size(size)
        tmp_dir = None
        if cache is not None:
            cache.parent.mkdir(parents=True, exist_ok=True)
            tmp_dir = Path(tempfile.mkdtemp(prefix=cache.name + ".", dir=cache.parent))
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(tmp_dir, 0o777 & ~umask)  # mkdtemp makes 0700; a shared cache should be readable

        def alloc(name, shape, dtype):
            if tmp_dir is None:
                return np.empty(shape, dtype=dtype)
            return np.lib.format.open_memmap(tmp_dir / f"{name}.npy", mode="w+", dtype=dtype, shape=shape)

        try:
            obs = {k: alloc(f"obs.{k}", (total, size, size, 3), np.uint8) for k in spec.image_keys}
            obs.update({k: alloc(f"obs.{k}", (total, d), np.float32) for k, d in spec.lowdim})
            actions = alloc("actions", (total, spec.action_dim), np.float32)
            start = 0
            for demo, end in zip(self.demos, ends):
                for k in spec.image_keys:
                    obs[k][start:end] = self._images(demo, k, size)
                for k, d in spec.lowdim:
                    obs[k][start:end] = self._lowdim(demo, k, d)
                actions[start:end] = self._actions(demo)
                start = int(end)
            if tmp_dir is not None:
                for arr in (*obs.values(), actions):
                    arr.flush()
                np.save(tmp_dir / "episode_ends.npy", ends)
                meta = {"version": CACHE_VERSION, "task": spec.name, "image_size": size, "env_args": self.env_args,
                        "obs_keys": list(obs), "demo_names": self.demos}
                (tmp_dir / "meta.json").write_text(json.dumps(meta))
                del obs, actions
                try:
                    os.replace(tmp_dir, cache)
                except OSError:  # another process filled the same cache first: use theirs
                    shutil.rmtree(tmp_dir, ignore_errors=True)
                tmp_dir = None
                _remove_stale_entries(cache)
                return _load_cache(cache, self.path, from_cache=False)
            return DemoDataset(obs=obs, actions=actions, episode_ends=ends, spec=spec, env_args=self.env_args,
                               path=str(self.path), demo_names=list(self.demos))
        finally:
            if tmp_dir is not None:
                shutil.rmtree(tmp_dir, ignore_errors=True)


# -- cache ----------------------------------------------------------------------------------------------------

def default_cache_dir() -> Path:
    return Path(os.environ.get("JEPA_DATA_CACHE", Path.home() / ".cache" / "jepa_envs" / "datasets"))


def _cache_path(path: Path, task, image_size, cache_dir) -> Path | None:
    """``<root>/<stem>-<hash of path, task, image size>-<hash of size, mtime>``: one entry per file version."""
    if cache_dir is False:
        return None
    st = path.stat()
    what = hashlib.sha1(json.dumps([CACHE_VERSION, str(path), task, image_size]).encode()).hexdigest()[:12]
    version = hashlib.sha1(json.dumps([st.st_size, st.st_mtime_ns]).encode()).hexdigest()[:12]
    root = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    return root / f"{path.stem}-{what}-{version}"


def _remove_stale_entries(cache: Path) -> None:
    """Drop cached copies of older versions of the same file (same path, task and image size)."""
    prefix = cache.name.rsplit("-", 1)[0] + "-"
    for old in cache.parent.glob(prefix + "*"):
        if old != cache and old.is_dir() and (old / "meta.json").is_file():
            shutil.rmtree(old, ignore_errors=True)


def _load_cache(cache: Path, path: Path, from_cache: bool = True) -> DemoDataset:
    meta = json.loads((cache / "meta.json").read_text())
    spec = get_task_spec(meta["task"]).with_image_size(meta["image_size"])
    obs = {k: np.load(cache / f"obs.{k}.npy", mmap_mode="r") for k in meta["obs_keys"]}
    return DemoDataset(obs=obs, actions=np.load(cache / "actions.npy", mmap_mode="r"),
                       episode_ends=np.load(cache / "episode_ends.npy"), spec=spec, env_args=meta["env_args"],
                       path=str(path), from_cache=from_cache, demo_names=meta["demo_names"])
