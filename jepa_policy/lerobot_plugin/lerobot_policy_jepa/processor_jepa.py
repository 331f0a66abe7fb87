"""LeRobot's pre- and post-processors of the ``jepa`` policy: batch dimension and device only.

The network normalises its own actions, low-dim inputs and pixels with statistics stored in its weights (fitted
from LeRobot's dataset statistics when the policy is built), as every checkpoint of ours does: that keeps a
LeRobot checkpoint loadable by our runtime, which has no processors, with bit-equal actions.
"""
from __future__ import annotations

from typing import Any

import torch
from lerobot.processor import (AddBatchDimensionProcessorStep, DeviceProcessorStep, PolicyAction,
                               PolicyProcessorPipeline, RenameObservationsProcessorStep)
from lerobot.processor.converters import policy_action_to_transition, transition_to_policy_action
from lerobot.utils.constants import POLICY_POSTPROCESSOR_DEFAULT_NAME, POLICY_PREPROCESSOR_DEFAULT_NAME

from lerobot_policy_jepa.configuration_jepa import JEPAConfig


Batch = dict[str, Any]


def make_jepa_pre_post_processors(
    config: JEPAConfig, dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[PolicyProcessorPipeline[Batch, Batch], PolicyProcessorPipeline[PolicyAction, PolicyAction]]:
    """(preprocessor, postprocessor); ``dataset_stats`` go to the network itself (``JEPAPolicy``), not here."""
    pre = PolicyProcessorPipeline[Batch, Batch](
        steps=[RenameObservationsProcessorStep(rename_map={}), AddBatchDimensionProcessorStep(),
               DeviceProcessorStep(device=config.device)],
        name=POLICY_PREPROCESSOR_DEFAULT_NAME)
    post = PolicyProcessorPipeline[PolicyAction, PolicyAction](
        steps=[DeviceProcessorStep(device="cpu")], name=POLICY_POSTPROCESSOR_DEFAULT_NAME,
        to_transition=policy_action_to_transition, to_output=transition_to_policy_action)
    return pre, post
