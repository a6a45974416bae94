"""Generated tests against the OpenAPI schema (schemathesis 4): every operation, positive and negative
data, with the write token, on SQLite and PostgreSQL: no 5xx, no response that violates the schema."""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from typing import Any

import pytest
import schemathesis
from hypothesis import HealthCheck, settings
from schemathesis.specs.openapi.checks import positive_data_acceptance

from driftlab.api.app import create_app
from tests.api.helpers import AUTH, TOKEN, Seeded

#: generated examples per operation and database (schemathesis adds its coverage-phase cases on top)
MAX_EXAMPLES = 5

calls: Counter[str] = Counter()
operations: dict[str, set[str]] = {}


@pytest.fixture
def api_schema(seeded: Seeded, request: pytest.FixtureRequest) -> Iterator[schemathesis.BaseSchema]:
    """The OpenAPI schema loaded from the app on a seeded database (jobs only queued, not run)."""
    # schemathesis' lazy loader reads node._nodeid, which pytest 9 no longer sets: give it one
    if not hasattr(request.node, "_nodeid"):
        request.node._nodeid = request.node.nodeid
    app = create_app(seeded.url, TOKEN, run_jobs=False)
    yield schemathesis.openapi.from_asgi("/openapi.json", app)
    # after the generated run on this database: every operation ran, a few hundred cases in all
    dialect = app.state.driftlab.store.dialect
    ran = operations.get(dialect, set())
    print(f"\nschemathesis on {dialect}: {calls[dialect]} cases over {len(ran)} operations")
    assert len(ran) == 27, sorted(ran)  # 25 + GET /live/snapshot + DELETE /machines/{machine_id}/online
    assert calls[dialect] >= 300, calls[dialect]


schema = schemathesis.pytest.from_fixture("api_schema")


def valid_requests_pass_request_validation(ctx: Any, response: Any, case: schemathesis.Case) -> bool | None:
    """A schema-valid request is never refused by request validation (the schema and the validators agree).

    This replaces schemathesis' positive_data_acceptance, which also counts as a failure the 422 of a
    semantic check the schema cannot express (an end before a start, a cursor that is not ours, a
    model document whose terms do not match its inputs). Those problems carry no ``errors`` list.
    """
    meta = case.meta
    if meta is None or not meta.generation.mode.is_positive or response.status_code != 422:
        return None
    body = response.json()
    if "errors" in body:
        raise AssertionError(f"schema-valid request refused by request validation: {body['detail']}")
    return None


@schema.parametrize()
@settings(max_examples=MAX_EXAMPLES, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
def test_api_conforms_to_its_schema(case: schemathesis.Case, seeded: Seeded) -> None:
    dialect = "sqlite" if seeded.url.startswith("sqlite") else "postgresql"
    calls[dialect] += 1
    operations.setdefault(dialect, set()).add(case.operation.label)
    case.call_and_validate(
        headers=AUTH,
        excluded_checks=[positive_data_acceptance],
        additional_checks=[valid_requests_pass_request_validation],
    )
