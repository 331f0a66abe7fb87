"""Shared fixtures: small real data made by the project's own generators."""
from __future__ import annotations

import os

import pytest


@pytest.fixture(scope="session", autouse=True)
def operator_secret(tmp_path_factory):
    """The robot bridges of the suite (in-process and the subprocesses it starts, which inherit the environment)
    and their operators share one credential file in a temporary folder, never the user's own."""
    path = tmp_path_factory.mktemp("operator") / "operator.secret"
    before = os.environ.get("JEPA_ROBOT_OPERATOR_SECRET")
    os.environ["JEPA_ROBOT_OPERATOR_SECRET"] = str(path)
    yield path
    if before is None:
        os.environ.pop("JEPA_ROBOT_OPERATOR_SECRET", None)
    else:
        os.environ["JEPA_ROBOT_OPERATOR_SECRET"] = before


@pytest.fixture(scope="session")
def pusht_demo_file(tmp_path_factory):
    """A robomimic-layout HDF5 file with 4 PushT expert demos at 84x84 (made by jepa_envs' own expert)."""
    from jepa_envs.datasets.hdf5 import write_dataset
    from jepa_envs.tasks.pusht_expert import generate_demos

    episodes, env_args = generate_demos(4, seed=100)
    path = tmp_path_factory.mktemp("pusht_demos") / "pusht_4.hdf5"
    write_dataset(path, episodes, env_args)
    return path


@pytest.fixture(scope="module")
def one_thread():
    """One intra-op thread: on a shared 2-core machine more threads oversubscribe the cores and run slower."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
