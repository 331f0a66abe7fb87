"""Parameter counts of a model of the family, total and per part, next to the paper's (Sec. 4.2, Table 5).

``jepa-policy describe --task ToolHang --arm jepa --json`` prints ``describe("ToolHang", "jepa")``.
Models are built on the meta device, so describing the full 44 M-parameter network allocates no weights.
"""
from __future__ import annotations

import torch

from jepa_policy.config import ModelConfig
from jepa_policy.model import build_model

# The paper's Tool Hang counts in millions (Sec. 4.2 "Compared Methods", Table 5).
PAPER_TOOLHANG_M: dict[str, dict[str, float]] = {
    "jepa": {"total": 43.96, "encoder": 22.90, "shared_stack_with_conditioning": 20.27, "future_branch": 0.79},
    "mip": {"total": 43.2, "encoder": 22.90, "shared_stack_with_conditioning": 20.27},
    "dual_independent": {"total": 48.38, "encoder": 22.90, "conditioning": 1.40, "action_stack": 18.93,
                         "future_stack": 4.75},
    "dual_cross": {"total": 53.73, "encoder": 22.90, "conditioning": 1.40, "action_stack": 18.93,
                   "future_stack": 4.75, "cross_block": 5.35},
    "diffusion": {"total": 42.6},
}
for _arm in ("backcut", "fwdcut", "sigreg", "lambda_a0"):      # same network as jepa, different routing or loss
    PAPER_TOOLHANG_M[_arm] = dict(PAPER_TOOLHANG_M["jepa"])

# Which top-level parameters make up each reported part.
_PARTS: dict[str, dict[str, tuple[str, ...]]] = {
    "shared": {
        "encoder": ("encoder",),
        "conditioning": ("memory",),
        "shared_stack": ("trunk", "action_embed", "action_pos", "action_head"),
        "future_branch": ("future_embed", "future_type", "future_pos", "future_head"),
    },
    "dual": {
        "encoder": ("encoder",),
        "conditioning": ("memory",),
        "action_stack": ("action_stack", "action_embed", "action_pos", "action_head"),
        "future_stack": ("future_stack", "future_type", "future_pos"),
        "future_io": ("future_embed", "future_head"),
        "cross_block": ("cross_blocks",),
    },
    "diffusion": {
        "encoder": ("encoder",),
        "denoiser": ("denoiser",),
    },
}


def count_parts(model: torch.nn.Module, family: str) -> dict[str, int]:
    """Per-part parameter counts; every parameter must belong to exactly one part."""
    groups = _PARTS[family]
    counts = {name: 0 for name in groups}
    for pname, p in model.named_parameters():
        top = pname.split(".", 1)[0]
        owner = [name for name, prefixes in groups.items() if top in prefixes]
        if len(owner) != 1:
            raise RuntimeError(f"parameter {pname!r} belongs to {owner or 'no'} part(s) of family {family!r}; "
                               "update jepa_policy.describe._PARTS")
        counts[owner[0]] += p.numel()
    return {k: v for k, v in counts.items() if v}


def describe(task, arm: str = "jepa", **overrides) -> dict:
    """Total and per-part parameter counts of ``ModelConfig.for_task(task, arm, **overrides)``.

    On Tool Hang with no overrides the paper's counts (millions) and the relative error are included.
    """

    cfg = ModelConfig.for_task(task, arm=arm, **overrides)
    with torch.device("meta"):
        model = build_model(cfg)
    family = "diffusion" if arm == "diffusion" else ("dual" if cfg.is_dual else "shared")
    parts = count_parts(model, family)
    if family == "shared":
        parts["shared_stack_with_conditioning"] = parts["conditioning"] + parts["shared_stack"]
    total = sum(p.numel() for p in model.parameters())
    task_name = task if isinstance(task, str) else task.name
    report = {"task": task_name, "arm": arm, "total": total, "parts": parts, "config": cfg.to_dict()}
    if task_name in ("ToolHang", "JEPA/ToolHang-v0") and not overrides:
        paper = PAPER_TOOLHANG_M[arm]
        report["paper_m"] = paper
        report["relative_error"] = {
            k: round((total if k == "total" else parts[k]) / (v * 1e6) - 1.0, 5) for k, v in paper.items()}
    return report
