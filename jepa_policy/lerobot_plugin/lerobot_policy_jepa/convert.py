"""A checkpoint of ours as a LeRobot policy folder: ``lerobot-eval --policy.path=OUT`` then runs it.

    python -m lerobot_policy_jepa.convert runs/jepa/checkpoints/latest.pt OUT

OUT holds what LeRobot's ``save_pretrained`` writes (config.json, model.safetensors) and the two processor
files; the weights are the checkpoint's EMA weights, the ones ``Policy.from_checkpoint`` acts with. (The other
way needs no converter: ``Policy.from_checkpoint`` reads a folder LeRobot wrote.)
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from lerobot.configs.types import FeatureType, PolicyFeature

from jepa_policy.checkpoint import load_checkpoint, load_model
from jepa_policy.config import ModelConfig
from jepa_policy.lerobot_format import lerobot_features, lerobot_fields
from jepa_envs.tasks.spec import get_task_spec
from lerobot_policy_jepa.configuration_jepa import JEPAConfig
from lerobot_policy_jepa.modeling_jepa import JEPAPolicy
from lerobot_policy_jepa.processor_jepa import make_jepa_pre_post_processors


def to_lerobot(checkpoint: str | Path, out: str | Path, device: str = "cpu") -> JEPAPolicy:
    """Write ``checkpoint`` (a ``jepa-policy train`` .pt) as a LeRobot ``jepa`` policy folder ``out``."""
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise FileExistsError(f"{out} is not empty; pass a new folder")
    ckpt = load_checkpoint(checkpoint)
    cfg = ModelConfig.from_dict(ckpt["model_config"])
    spec = get_task_spec(ckpt["task"])
    features = {key: PolicyFeature(type=FeatureType[kind], shape=shape)
                for key, (kind, shape) in lerobot_features(spec, cfg.image_size).items()}
    config = JEPAConfig(device=device, n_action_steps=spec.n_action_steps, **lerobot_fields(cfg, spec.name),
                        input_features={k: f for k, f in features.items() if f.type is not FeatureType.ACTION},
                        output_features={k: f for k, f in features.items() if f.type is FeatureType.ACTION})
    policy = JEPAPolicy(config)
    policy.model.load_state_dict(load_model(ckpt, ema=True).state_dict())
    policy.save_pretrained(out)
    for pipeline in make_jepa_pre_post_processors(config):
        pipeline.save_pretrained(out)
    return policy


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m lerobot_policy_jepa.convert", description=__doc__.split("\n")[0])
    parser.add_argument("checkpoint", help="a `jepa-policy train` checkpoint (.pt)")
    parser.add_argument("out", help="the LeRobot policy folder to write (new or empty)")
    parser.add_argument("--device", default="cpu", help="the device LeRobot loads the policy onto")
    args = parser.parse_args(argv)
    policy = to_lerobot(args.checkpoint, args.out, args.device)
    print(json.dumps({"out": args.out, "task": policy.config.task, "arm": policy.config.arm,
                      "tensors": len(policy.model.state_dict())}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
