"""The lean ingest check (ingest/validation.py) accepts only what the pydantic models accept and reads it the
same way; everything else goes to pydantic, which words every error."""
import json

import numpy as np
import pytest
from pydantic import TypeAdapter, ValidationError

from monitor_service.encoding import decode_body, pack
from monitor_service.ingest.validation import plain_records
from monitor_service.schemas import BatchIn, DecisionIn

Z = np.arange(1, 5, dtype=np.float32)
BATCH = TypeAdapter(BatchIn)
DECISION = {"kind": "decision", "task": "T", "episode": "e-1", "step": 8, "horizon": 4, "z_hat": Z,
            "z_now": Z * 2, "scores": {"stac": 0.5, "rnd": 2}, "robot": "arm1", "checkpoint": "ck/1",
            "held_out": True, "group": "seed0"}
VALID = [
    DECISION,
    {"kind": "decision", "task": "T", "episode": "e", "step": 0, "scores": {"stac": 0.0}},
    {"kind": "decision", "task": "T", "episode": "e", "step": 0, "horizon": 1, "z_hat": Z, "z_now": None},
    {"kind": "target", "episode": "e", "step": 12, "z": Z},
    {"kind": "outcome", "episode": "e", "success": False, "held_out": True, "group": "g", "length": 300},
    {"kind": "outcome", "episode": "e", "success": True},
]
# each is valid only in a form the lean check leaves to pydantic (None: pydantic accepts it), or refused by
# pydantic with an error at this location saying this
UNUSUAL = [
    ({**DECISION, "step": 8.0}, None),                           # an integral float: pydantic converts it
    ({k: v for k, v in DECISION.items() if k != "kind"}, None),   # kind inferred from the fields
    ({**DECISION, "step": -1}, ("decision.step", "greater than or equal to 0")),
    ({**DECISION, "step": True}, ("decision.step", "valid integer")),
    ({**DECISION, "horizon": None}, ("decision", "z_hat and horizon go together")),
    ({**DECISION, "z_hat": None, "z_now": None, "horizon": None, "scores": {}}, ("decision", "carries z_hat")),
    ({**DECISION, "z_hat": np.array([1.0, np.nan], dtype=np.float32)}, ("decision.z_hat", "NaN or inf at index 1")),
    ({**DECISION, "z_hat": np.zeros(0, dtype=np.float32)}, ("decision.z_hat", "non-empty 1-D vector")),
    ({**DECISION, "z_hat": [1.0, True]}, ("decision.z_hat", "list of numbers")),
    ({**DECISION, "z_hat": [1e39]}, ("decision.z_hat", "overflows float32")),
    ({**DECISION, "scores": {"stac": float("nan")}}, ("decision.scores", "'stac' is nan")),
    ({**DECISION, "scores": {"stac": -0.1}}, ("decision.scores", "non-negative")),
    ({**DECISION, "scores": {"nmse": 0.1}}, ("decision.scores", "'nmse' is computed by the service")),
    ({**DECISION, "scores": {"bad name": 0.1}}, ("decision.scores.bad name.[key]", "should match pattern")),
    ({**DECISION, "task": "a b"}, ("decision.task", "should match pattern")),
    ({**DECISION, "task": "x" * 129}, ("decision.task", "at most 128 characters")),
    ({**DECISION, "held_out": 1}, ("decision.held_out", "valid boolean")),
    ({**DECISION, "extra": 1}, ("decision.extra", "Extra inputs are not permitted")),
    ({**DECISION, "checkpoint": "c" * 257}, ("decision.checkpoint", "at most 256 characters")),
    ({"kind": "target", "episode": "e", "step": 12}, ("target.z", "Field required")),
    ({"kind": "outcome", "episode": "e", "success": "yes"}, ("outcome.success", "valid boolean")),
    ({"kind": "outcome", "episode": "e", "success": True, "length": 0}, ("outcome.length", "greater than or equal")),
    ({"kind": "vote", "episode": "e"}, ("", "a record is a decision, target or outcome")),
]


def _fields(rec) -> dict:
    names = [n for n in DecisionIn.model_fields if hasattr(rec, n)] if hasattr(rec, "task") else \
        [n for n in ("kind", "episode", "step", "z", "success", "held_out", "group", "length") if hasattr(rec, n)]
    return {n: getattr(rec, n).tolist() if isinstance(getattr(rec, n), np.ndarray) else getattr(rec, n)
            for n in names}


@pytest.mark.parametrize("binary", [True, False])
def test_valid_records_read_as_pydantic_reads_them(binary):
    as_lists = [{k: v.tolist() if isinstance(v, np.ndarray) else v for k, v in r.items()} for r in VALID]
    body = pack({"records": VALID}) if binary else json.dumps({"records": as_lists}).encode()
    decoded = decode_body(body, "application/x-msgpack" if binary else "application/json")
    lean, models = plain_records(decoded, None), BATCH.validate_python(decoded).records
    assert lean is not None and len(lean) == len(models)
    for ours, theirs in zip(lean, models):
        assert _fields(ours) == _fields(theirs)
        for name in ("z_hat", "z_now", "z"):
            if isinstance(getattr(theirs, name, None), np.ndarray):
                assert getattr(ours, name).dtype == getattr(theirs, name).dtype == np.dtype("<f4")


@pytest.mark.parametrize("record, refusal", UNUSUAL, ids=range(len(UNUSUAL)))
def test_anything_else_is_left_to_pydantic(record, refusal):
    """The lean check declines; pydantic then accepts the record, or refuses it with the one error the client gets
    (this test passed whatever pydantic did until each row said which)."""
    decoded = decode_body(pack({"records": [VALID[3], record]}), "application/x-msgpack")
    assert plain_records(decoded, None) is None
    if refusal is None:
        assert len(BATCH.validate_python(decoded).records) == 2
        return
    with pytest.raises(ValidationError) as refused:
        BATCH.validate_python(decoded)
    where, says = refusal
    errors = refused.value.errors()
    assert len(errors) == 1 and ".".join(map(str, errors[0]["loc"])) == ".".join(filter(None, ("records.1", where)))
    assert says in errors[0]["msg"]


def test_single_record_routes_take_their_own_kind_only():
    target = {"episode": "e", "step": 3, "z": Z}
    assert plain_records(target, "target")[0].kind == "target"   # kind left out on its own route
    assert plain_records({**target, "kind": "target"}, "decision") is None
    assert plain_records({"records": [VALID[3]]}, "target") is None
    assert plain_records({"records": [VALID[3]], "extra": 1}, None) is None
