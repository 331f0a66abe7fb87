"""Parameter counts of the paper's Tool Hang configuration (Sec. 4.2, Table 5), built on the meta device."""
from __future__ import annotations

import pytest
import torch

from jepa_policy.config import ARMS
from jepa_policy.describe import PAPER_TOOLHANG_M, describe
from jepa_policy.blocks import ResNet18GN

TOLERANCE = 0.02


def test_resnet18_gn_has_the_real_resnet18_size():
    # torchvision's resnet18 has 11,689,512 parameters, 513,000 of them in the 1000-way fc layer we drop;
    # GroupNorm has the same affine parameters as BatchNorm.
    with torch.device("meta"):
        net = ResNet18GN(64)
    assert sum(p.numel() for p in net.parameters()) == 11_689_512 - 513_000


@pytest.mark.parametrize("arm", ARMS)
def test_toolhang_counts_match_the_paper(arm):
    report = describe("ToolHang", arm)
    paper = PAPER_TOOLHANG_M[arm]
    assert report["total"] == pytest.approx(paper["total"] * 1e6, rel=TOLERANCE)
    for part, millions in paper.items():
        if part != "total":
            assert report["parts"][part] == pytest.approx(millions * 1e6, rel=TOLERANCE), part
    assert report["total"] == sum(v for k, v in report["parts"].items() if k != "shared_stack_with_conditioning")
    assert max(abs(e) for e in report["relative_error"].values()) < TOLERANCE


def test_future_branch_is_the_whole_difference_between_jepa_and_mip():
    jepa, mip = describe("ToolHang", "jepa"), describe("ToolHang", "mip")
    assert jepa["total"] - mip["total"] == jepa["parts"]["future_branch"]
    assert "future_branch" not in mip["parts"]
    # Embed_z (1024 -> 384), h_z (384 -> 1024), e_z and p_{H+1}
    assert jepa["parts"]["future_branch"] == (1024 * 384 + 384) + (384 * 1024 + 1024) + 384 + 384


def test_describe_other_tasks_and_overrides():
    square = describe("Square", "jepa")
    assert "paper_m" not in describe("ToolHang", "jepa", width=192)
    assert "paper_m" not in square and square["total"] > 0
    transport = describe("Transport", "jepa")            # four cameras: four ResNets and a 2048-d future target
    assert transport["parts"]["encoder"] > 2 * square["parts"]["encoder"] - 1e6
    assert transport["config"]["cameras"] == ["shouldercamera0", "shouldercamera1", "robot0_eye_in_hand",
                                              "robot1_eye_in_hand"]
    with pytest.raises(ValueError, match="unknown override"):
        describe("ToolHang", "jepa", widht=256)
