"""JEPA Policy in LeRobot's formats: the fields of the ``jepa`` policy type, the features a task gives it, its
statistics, batches and observations turned into ours, and a checkpoint LeRobot saved read back as one of ours.

The LeRobot plugin (``jepa_policy/lerobot_plugin``, the distribution ``lerobot_policy_jepa``) registers a policy
type ``jepa`` whose configuration carries the task name, the shapes and the model fields of ``ModelConfig`` under
the same names (LeRobot's ``n_obs_steps`` is our ``obs_steps``). A directory LeRobot wrote with
``save_pretrained`` (``config.json`` and ``model.safetensors``: the plugin's weights are our network's under
``model.``) loads here without LeRobot: ``load_checkpoint`` hands such a directory to ``read_lerobot_checkpoint``,
so ``Policy.from_checkpoint``, ``jepa-policy serve`` and ``jepa-policy eval`` run it as they run a ``.pt`` file.
LeRobot trains without our EMA: the weights it saved are the ones both runtimes act with.

Pixels: LeRobot hands images over as float32 in [0, 1] (its loaders and ``preprocess_observation`` divide uint8
frames by 255); ``uint8_frames`` multiplies back and rounds, which gives every one of the 256 levels back exactly,
so the network sees the bytes our runtime sees.
"""
from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file

from jepa_envs.datasets.lerobot.format import image_features
from jepa_envs.tasks.spec import TaskSpec, get_task_spec
from jepa_policy.config import ModelConfig

POLICY_TYPE = "jepa"
WEIGHTS_PREFIX = "model."        # the plugin's policy holds our network as ``self.model``
STATE = "observation.state"      # our low-dim keys, concatenated in the task's order (as our dataset export)
ACTION = "action"
# ModelConfig fields the LeRobot configuration carries under the same name
MODEL_FIELDS = ("arm", "horizon", "future_k", "width", "layers", "heads", "ffn_mult", "time_emb_dim",
                "encoder_width", "dropout", "crop_ratio", "image_norm", "tau", "lambda_a", "lambda_z_mode", "rho",
                "lambda_z_min", "lambda_z_max", "lambda_z", "sigreg_weight", "sigreg_slices", "dual_future_layers",
                "dual_future_width")


def lerobot_features(spec: TaskSpec, image_size: int | None = None) -> dict[str, tuple[str, tuple[int, ...]]]:
    """{LeRobot feature: (its FeatureType name, shape)} that the policy of a task takes and gives: cameras as
    LeRobot's channel-first float images, the low-dim keys as one ``observation.state``, the action."""
    size = int(image_size or spec.image_size)
    features = {key: ("VISUAL", (3, size, size)) for key in image_features(spec)}
    if spec.lowdim:
        features[STATE] = ("STATE", (spec.lowdim_dim,))
    features[ACTION] = ("ACTION", (spec.action_dim,))
    return features


def check_features(spec: TaskSpec, given: dict[str, tuple[str, tuple[int, ...]]]) -> int:
    """The image size of LeRobot features that fit ``spec``; a ValueError naming every mismatch and the fix.
    ``observation.environment_state`` (an ENV feature: the simulator state our exports carry) is no input of the
    policy and is passed over."""
    given = {key: value for key, value in given.items() if value[0] != "ENV"}
    sizes = {shape[-1] for kind, shape in given.values() if kind == "VISUAL"}
    size = sizes.pop() if len(sizes) == 1 else spec.image_size
    want = lerobot_features(spec, size)
    problems = [f"{key} {kind} {list(shape)} is missing" for key, (kind, shape) in want.items() if key not in given]
    problems += [f"{key} is {given[key][0]} {list(given[key][1])}, the task needs {kind} {list(shape)}"
                 for key, (kind, shape) in want.items() if key in given and (given[key][0], tuple(given[key][1]))
                 != (kind, shape)]
    problems += [f"{key} is not a feature of the task" for key in given if key not in want]
    if problems:
        raise ValueError(f"the jepa policy of task {spec.name} cannot take these features: {'; '.join(problems)}. "
                         f"Its features are {', '.join(f'{k} {list(s)}' for k, (_, s) in want.items())}; pass "
                         "--policy.task=<the task of your data> (jepa-envs list), or map the dataset's keys with "
                         "--rename_map")
    return size


def model_config(fields: dict, image_size: int) -> tuple[TaskSpec, ModelConfig]:
    """The task spec (at ``image_size``) and our ModelConfig of a LeRobot ``jepa`` configuration (a config.json
    dict or the fields of the plugin's configuration)."""
    try:
        spec = get_task_spec(fields["task"]).with_image_size(int(image_size))
    except KeyError as exc:
        raise ValueError(f"the jepa policy's task {fields.get('task')!r} is not a task of this toolkit ({exc}); "
                         "pass --policy.task=<one of `jepa-envs list`>") from None
    if fields["arm"] == "diffusion":
        raise ValueError("arm='diffusion' is Diffusion Policy: in LeRobot run its own --policy.type=diffusion; the "
                         "jepa type trains the two-step arms (jepa, mip, ...)")
    values = {name: fields[name] for name in MODEL_FIELDS if name != "arm"}
    cfg = ModelConfig.for_task(spec, fields["arm"], image_size=int(image_size), obs_steps=int(fields["n_obs_steps"]),
                               **values)
    return spec, cfg


def lerobot_fields(cfg: ModelConfig, task: str) -> dict:
    """The LeRobot configuration fields of one of our models (the inverse of ``model_config``)."""
    return {"task": task, "n_obs_steps": cfg.obs_steps, **{name: getattr(cfg, name) for name in MODEL_FIELDS}}


def is_lerobot_checkpoint(path: str | Path) -> bool:
    """A directory LeRobot's ``save_pretrained`` wrote (``config.json`` beside ``model.safetensors``)."""
    path = Path(path)
    return path.is_dir() and (path / "config.json").is_file() and (path / "model.safetensors").is_file()


def read_lerobot_checkpoint(path: str | Path) -> dict:
    """The payload of ``checkpoint.load_checkpoint`` (less its format tag and EMA weights) from a
    ``pretrained_model`` directory of the LeRobot ``jepa`` policy."""
    path = Path(path)
    if not is_lerobot_checkpoint(path):
        raise FileNotFoundError(f"{path} is not a LeRobot checkpoint directory (config.json and model.safetensors); "
                                "pass a `.../checkpoints/<step>/pretrained_model` folder that lerobot-train wrote")
    config = json.loads((path / "config.json").read_text())
    if config.get("type") != POLICY_TYPE:
        raise ValueError(f"{path} holds a LeRobot {config.get('type')!r} policy; only the {POLICY_TYPE!r} type "
                         "(lerobot_policy_jepa) is JEPA Policy")
    given = {key: (ft["type"], tuple(ft["shape"])) for key, ft in
             {**config["input_features"], **config["output_features"]}.items()}
    spec, cfg = model_config(config, check_features(get_task_spec(config["task"]), given))
    weights = load_file(path / "model.safetensors")
    foreign = sorted(k for k in weights if not k.startswith(WEIGHTS_PREFIX))
    if foreign:
        raise ValueError(f"{path}/model.safetensors has tensors outside {WEIGHTS_PREFIX!r} ({foreign[:3]}); it was "
                         "not written by the jepa policy")
    state = {key[len(WEIGHTS_PREFIX):]: value for key, value in weights.items()}
    step_file = path.parent / "training_state" / "training_step.json"
    step = json.loads(step_file.read_text())["step"] if step_file.is_file() else 0
    return {"step": int(step), "model_config": cfg.to_dict(), "task": spec.name, "image_size": spec.image_size,
            "env_args": None, "model": state, "lerobot_config": config}


def uint8_frames(x: torch.Tensor) -> torch.Tensor:
    """LeRobot's images (..., 3, h, w) float in [0, 1] (or uint8) -> ours, uint8 (..., h, w, 3)."""
    if x.dtype != torch.uint8:
        x = x.mul(255.0).round_().clamp_(0, 255).to(torch.uint8)
    return x.movedim(-3, -1).contiguous()


def split_state(state, spec: TaskSpec) -> dict:
    """``observation.state`` (..., D) -> {low-dim key: (..., d)} in the task's order."""
    if state.shape[-1] != spec.lowdim_dim:
        raise ValueError(f"{STATE} has {state.shape[-1]} values, task {spec.name} concatenates {spec.lowdim_dim} "
                         f"({', '.join(f'{k} {d}' for k, d in spec.lowdim)})")
    out, start = {}, 0
    for key, dim in spec.lowdim:
        out[key] = state[..., start:start + dim]
        start += dim
    return out


def _feature(batch: Mapping, key: str, where: str):
    if key not in batch:
        raise KeyError(f"{where} lacks {key!r} (it has {sorted(k for k in batch if not k.endswith('_is_pad'))}); "
                       "the jepa policy reads its task's LeRobot features (--rename_map maps other names)")
    return batch[key]


def model_batch(batch: Mapping, spec: TaskSpec, obs_steps: int, with_future: bool) -> dict:
    """A LeRobot training batch (observations at delta indices -obs_steps+1 .. 0 and, ``with_future``, +k;
    actions 0 .. H-1) in the layout of ``PolicyModel.compute_loss``."""
    frames = obs_steps + int(with_future)
    obs, future = {}, {}
    for lerobot_key, key in image_features(spec).items():
        x = _feature(batch, lerobot_key, "the training batch")
        if x.dim() != 5 or x.shape[1] != frames:
            raise ValueError(f"{lerobot_key} must be (B, {frames}, 3, h, w): {obs_steps} history frame(s)"
                             f"{' and the future frame' if with_future else ''}; got {tuple(x.shape)}")
        x = uint8_frames(x)
        obs[key] = x[:, :obs_steps]
        if with_future:
            future[key] = x[:, obs_steps]
    if spec.lowdim:
        obs.update(split_state(_feature(batch, STATE, "the training batch")[:, :obs_steps].float(), spec))
    out = {"obs": obs, "action": _feature(batch, ACTION, "the training batch")}
    if with_future:
        out["future_obs"] = future
    return out


def observation(batch: Mapping, spec: TaskSpec) -> dict[str, np.ndarray]:
    """One env step of a LeRobot policy's input (batched, after its preprocessor) as our runtime's observation:
    ``<camera>_image`` uint8 (B, h, w, 3), low-dim float32 (B, d)."""
    obs, size = {}, spec.image_size
    for lerobot_key, key in image_features(spec).items():
        x = _feature(batch, lerobot_key, "the observation")
        if tuple(x.shape[-2:]) != (size, size):
            raise ValueError(f"{lerobot_key} is {x.shape[-2]}x{x.shape[-1]} px but this jepa policy acts on "
                             f"{size}x{size} px, the size it was trained at; give it frames of that size (gym-pusht "
                             "renders 96 px: train at 96 px, e.g. `jepa-policy train --image-size 96`, then convert)")
        obs[key] = uint8_frames(x).cpu().numpy()
    if spec.lowdim:
        state = _feature(batch, STATE, "the observation").float().cpu().numpy()
        obs.update(split_state(state, spec))
    return obs


def _array(value) -> np.ndarray:
    return np.asarray(value.cpu() if torch.is_tensor(value) else value, dtype=np.float64).reshape(-1)


def normalizer_stats(stats: Mapping, spec: TaskSpec) -> dict:
    """LeRobot's dataset statistics (``meta/stats.json``) in the format of ``set_normalizer_stats``: min/max of the
    action and of each low-dim key, per-channel pixel mean/std of each camera."""
    need = {ACTION: ("min", "max"), **({STATE: ("min", "max")} if spec.lowdim else {}),
            **{key: ("mean", "std") for key in image_features(spec)}}
    missing = [f"{key}.{stat}" for key, names in need.items() for stat in names if stat not in stats.get(key, {})]
    if missing:
        raise ValueError(f"the dataset's statistics lack {', '.join(missing)}; recompute meta/stats.json with "
                         "LeRobot (its aggregate_stats) or jepa-envs lerobot export")
    out = {ACTION: {"min": _array(stats[ACTION]["min"]), "max": _array(stats[ACTION]["max"])}}
    if spec.lowdim:
        lo, hi = split_state(_array(stats[STATE]["min"]), spec), split_state(_array(stats[STATE]["max"]), spec)
        out.update({key: {"min": lo[key], "max": hi[key]} for key in lo})
    for lerobot_key, key in image_features(spec).items():
        out[key] = {"mean": _array(stats[lerobot_key]["mean"]), "std": _array(stats[lerobot_key]["std"])}
    return out
