"""``nmse_persistence`` is the service's own column (NMSE of z_now against the realized target, the paper's
control): a task registering it as a named signal, or a robot sending a score under that name, was accepted and
stored, and then the calibration read the service's column instead of the sent scores (409 'record held-out
labelled rollouts first' on a task full of them). The name is now refused up front, like nmse and nmse_ratio."""
import numpy as np
from monitor_testkit import DIM, make_settings, post_batch, register_task

from monitor_service.cli import main as monitor_main


def test_nmse_persistence_cannot_be_registered_or_sent_as_a_named_score(client, robot, admin, tmp_path, capsys):
    register_task(client, "Push")
    r = client.put("/v1/tasks/Push", json={"signals": ["stac", "nmse_persistence"]}, headers=admin)
    assert r.status_code == 422 and "nmse_persistence is the service's own signal" in r.json()["detail"]
    tasks = {t["name"]: t for t in client.get("/v1/tasks", headers=admin).json()}
    assert tasks["Push"]["signals"] == []   # nothing half-registered
    url = ["--database-url", make_settings(tmp_path).database_url]
    assert monitor_main(url + ["tasks", "add", "Push", "--signals", "nmse_persistence"]) == 2
    assert "nmse_persistence is the service's own signal" in capsys.readouterr().err
    rec = {"kind": "decision", "task": "Push", "episode": "e1", "step": 0, "horizon": 4,
           "z_hat": np.zeros(DIM).tolist(), "scores": {"nmse_persistence": 0.5}}
    r = post_batch(client, robot, [rec])
    assert r.status_code == 422, r.text
    assert "score 'nmse_persistence' is computed by the service from z_now" in r.json()["detail"]
    assert client.get("/v1/episodes/e1", headers=admin).status_code == 404   # nothing refused was written


def test_calibrating_nmse_persistence_names_the_control_not_a_registration(client, admin):
    register_task(client, "Lift")
    r = client.post("/v1/calibrations", json={"task": "Lift", "signals": ["nmse_persistence"], "n_bootstrap": 100,
                                              "n_permutation": 100}, headers=admin)
    assert r.status_code == 404 and "nmse_persistence is the persistence control" in r.json()["detail"]
    assert "register it" not in r.json()["detail"]   # registering it is refused: the old hint led nowhere
