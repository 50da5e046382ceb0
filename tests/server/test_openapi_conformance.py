"""Schemathesis drives every documented operation, as an operator and as a labeller, with
generated requests (a bounded number per operation, a fixed seed): no answer is a 5xx, and
every answer conforms to the OpenAPI document (status codes, content types, headers, bodies);
a method an operation does not take is a 405 naming the ones it does. Requests valid by the
document alone, as an operator, are never refused for their shape (400, or a 422 but for the
few rules the document states in words)."""

from __future__ import annotations

import json
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
import schemathesis
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, settings
from schemathesis import GenerationMode, checks
from server_helpers import OPERATOR_TOKEN, new_labeller, running_run_with_queries

from labelqueue import make_engine, session_factory
from server.app import create_app
from server.settings import Settings

CHECKS = [
    checks.not_a_server_error,
    checks.status_code_conformance,
    checks.content_type_conformance,
    checks.response_headers_conformance,
    checks.response_schema_conformance,
    checks.unsupported_method,
]
BOUNDED = settings(
    max_examples=12,
    derandomize=True,  # a fixed seed: the same requests on every run
    deadline=None,
    suppress_health_check=list(HealthCheck),
)
# The schema is read from the app when the module is collected; the database behind it is
# migrated and seeded by the module's fixture before the first request.
DATA = Path(tempfile.mkdtemp(prefix="sepoa-conformance-")) / "data"
APP = create_app(
    Settings(
        database_url=f"sqlite:///{DATA / 'queue.db'}",
        data_dir=DATA,
        operator_token=OPERATOR_TOKEN,
        secret_key="conformance-secret-key-0123",
    )
)
# An external run's clip upload takes raw bytes of these types, as application/octet-stream.
for media_type in ("video/mp4", "video/webm", "application/x-npy"):
    schemathesis.serializer.alias(media_type, "application/octet-stream")
schema = schemathesis.openapi.from_asgi("/openapi.json", APP)
valid_only = schemathesis.openapi.from_asgi("/openapi.json", APP)
valid_only.config.generation.update(modes=[GenerationMode.POSITIVE])
TOKENS: dict[str, str] = {}
RESPONSE_TIMEOUT_S = 60
"""these tests check what comes back, not how fast: a rendered PNG or an export took longer
than schemathesis's 10 s default on a 2-core host running the suite beside other work"""


@pytest.fixture(scope="module", autouse=True)
def seeded_app() -> Iterator[None]:
    """The app started (migrated database), a labeller, and a run with two rendered queries."""
    try:
        with TestClient(APP) as client:
            TOKENS["operator"] = OPERATOR_TOKEN
            TOKENS["labeller"] = new_labeller(client, "fuzzed-labeller")
            engine = make_engine(APP.state.settings.database_url)
            with session_factory(engine)() as session:
                running_run_with_queries(client, session, APP.state.settings, n=2)
            engine.dispose()
            yield
    finally:
        shutil.rmtree(DATA.parent, ignore_errors=True)


def call_as(role: str, case: schemathesis.Case) -> None:
    case.call_and_validate(headers={"Authorization": f"Bearer {TOKENS[role]}"}, checks=CHECKS,
                           timeout=RESPONSE_TIMEOUT_S)


@schema.parametrize()
@BOUNDED
def test_every_operation_as_an_operator(case: schemathesis.Case) -> None:
    call_as("operator", case)


@schema.parametrize()
@BOUNDED
def test_every_operation_as_a_labeller(case: schemathesis.Case) -> None:
    call_as("labeller", case)


# The refusals of a request valid by the document that the document states in words: a value
# rule of a config field (its range, a rule between fields: `CONFIG_RULES`), a dataset that is
# not in the server's folder, calibration bins out of order, an uploaded clip's bytes that are no
# video (or frame array) the server decodes, or none at all, an external pair naming a clip
# never uploaded, an invite's entry test that does not fit its run's practice pairs, an answers
# feed's cursor the run never gave, a NUL character in an external pair's meta.
STATED_IN_WORDS = ("config", "teacher_params", "params")


def stated_in_words(detail: object) -> bool:
    if isinstance(detail, str):
        return (detail == "bins: the edges must increase" or detail.startswith("the clip ")
                or detail.startswith("the body is empty") or detail.startswith("cursor ")
                or detail.endswith("is no clip uploaded to this run"))
    if not isinstance(detail, list) or len(detail) != 1:
        return False
    loc, message = detail[0].get("loc", []), detail[0].get("msg", "")
    if loc[:2] == ["body", "dataset"]:
        return message.startswith("no dataset ")
    if loc[:2] == ["body", "entry_pass"]:
        return message.startswith("entry_pass ")
    if loc[-1:] == ["meta"] and loc[:2] == ["body", "pairs"]:
        return "holds a NUL character" in message
    return (len(loc) == 3 and loc[1] in STATED_IN_WORDS
            and "unknown config field" not in message and " takes " not in message)


@valid_only.parametrize()
@settings(BOUNDED, max_examples=6)
def test_a_valid_request_is_not_refused_for_its_shape(case: schemathesis.Case) -> None:
    response = case.call(headers={"Authorization": f"Bearer {OPERATOR_TOKEN}"},
                         timeout=RESPONSE_TIMEOUT_S)
    if response.status_code in (400, 422):
        detail = json.loads(response.text).get("detail")
        assert stated_in_words(detail), (case.operation.label, case.body, case.query,
                                         response.status_code, detail)
