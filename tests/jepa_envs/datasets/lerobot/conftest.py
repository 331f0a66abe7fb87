"""A small LeRobot v3.0 export of the PushT demos, shared by the LeRobot tests of one module."""
from __future__ import annotations

import pytest

from jepa_envs.datasets.lerobot import export_lerobot


@pytest.fixture(scope="module")
def exported(pusht_demo_file, tmp_path_factory):
    out = tmp_path_factory.mktemp("lerobot") / "pusht"
    summary = export_lerobot(pusht_demo_file, out)
    return out, summary
