"""The OpenAPI document tells the truth: schemathesis generates requests (valid and invalid) for every operation
from the document alone and checks that the server never answers 5xx and that every answer (status, content
type, body, headers) is the one documented. Each caller uses the key a client of that route would hold."""
import pathlib
import tempfile

import pytest

schemathesis = pytest.importorskip("schemathesis")
from hypothesis import HealthCheck, settings  # noqa: E402
from monitor_testkit import ADMIN, make_settings  # noqa: E402

from monitor_service.app import create_app  # noqa: E402
from monitor_service.auth import create_key  # noqa: E402
from monitor_service.encoding import pack  # noqa: E402

ROBOT, OPERATOR = "robot-secret-for-schemathesis", "operator-secret-for-schemathesis"
EXAMPLES = 20   # per operation: bounded and derandomized (the same requests every run), about 20 s here


def _fits_msgpack(value):
    """msgpack has no integers beyond 64 bits: generated out-of-range ones travel as floats."""
    if isinstance(value, dict):
        return {k: _fits_msgpack(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_fits_msgpack(v) for v in value]
    if isinstance(value, int) and not isinstance(value, bool) and not -2**63 <= value < 2**64:
        return float(value)
    return value


@schemathesis.serializer("application/x-msgpack")
def to_msgpack(ctx, value):
    return pack(_fits_msgpack(value))


def _app():
    app = create_app(make_settings(pathlib.Path(tempfile.mkdtemp(prefix="openapi-"))))
    with app.state.sessionmaker() as s:
        create_key(s, "schemathesis-robot", "robot", "0", key=ROBOT)
        create_key(s, "schemathesis-operator", "operator", key=OPERATOR)
        s.commit()
    return app


APP = _app()
# the SSE stream never ends by design; it is documented (text/event-stream) and tested in test_api.py
schema = schemathesis.openapi.from_asgi("/openapi.json", APP).exclude(path="/v1/alerts/stream")


def _key(case) -> str:
    if case.path in ("/v1/decisions", "/v1/targets", "/v1/outcomes", "/v1/batch"):
        return ROBOT
    if case.method.upper() == "GET" and not case.path.startswith("/v1/keys"):
        return OPERATOR
    return ADMIN


@schema.parametrize()
@settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
def test_every_operation_answers_as_documented(case):
    case.call_and_validate(headers={"X-API-Key": _key(case)})


def test_document_declares_errors_timestamps_and_latents():
    doc = APP.openapi()
    error = {"$ref": "#/components/schemas/Error"}
    decisions = doc["paths"]["/v1/decisions"]["post"]
    for code in ("400", "401", "403", "404", "409", "413", "422"):
        assert decisions["responses"][code]["content"]["application/json"]["schema"] == error
    decision = doc["components"]["schemas"]["DecisionIn"]
    latent = next(t for t in decision["properties"]["z_hat"]["anyOf"] if t.get("type") == "array")
    assert latent["minItems"] == 1
    # latents with their horizon, or named scores alone: the document says so
    assert [alt["required"] for alt in decision["anyOf"]] == [["z_hat", "horizon"], ["scores"]]
    assert set(decisions["requestBody"]["content"]) == {"application/json", "application/x-msgpack"}
    assert "text/plain" in doc["paths"]["/metrics"]["get"]["responses"]["200"]["content"]
    assert "HTTPValidationError" not in doc["components"]["schemas"]
