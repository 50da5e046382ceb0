"""Schemathesis drives every documented operation, as an operator and as a labeller, with
generated requests (a bounded number per operation, a fixed seed): no answer is a 5xx, and
every answer conforms to the OpenAPI document (status codes, content types, headers, bodies);
a method an operation does not take is a 405 naming the ones it does."""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
import schemathesis
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, settings
from schemathesis import checks
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
TOKENS: dict[str, str] = {}


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
    case.call_and_validate(headers={"Authorization": f"Bearer {TOKENS[role]}"}, checks=CHECKS)


@schema.parametrize()
@BOUNDED
def test_every_operation_as_an_operator(case: schemathesis.Case) -> None:
    call_as("operator", case)


@schema.parametrize()
@BOUNDED
def test_every_operation_as_a_labeller(case: schemathesis.Case) -> None:
    call_as("labeller", case)
