"""schemathesis against the API's own OpenAPI schema, on real data (the mapper's own
processing path filled Redis), with a bounded budget: no 5xx, every response (status,
content type, body, headers) as the schema says, and the token enforced where the
schema says it is required."""

from __future__ import annotations

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from pydantic import SecretStr
from test_api import filled  # noqa: F401  (the fixture)

from services.api.main import create_app

TOKEN = "schema-test-token"


@pytest.fixture()
def api_schema(filled):  # noqa: F811
    s, _ = filled
    app = create_app(s.model_copy(update={"api_token": SecretStr(TOKEN)}))
    return schemathesis.openapi.from_asgi("/openapi.json", app)


def test_api_conforms_to_its_schema(api_schema):
    # Operation by operation through hypothesis directly: schemathesis's pytest plugin
    # does not run under pytest 9.
    ops = [r.ok() for r in api_schema.get_all_operations()]
    assert {op.path for op in ops} >= {"/agents", "/agents/{agent}/pose", "/maps/{map_id}/points"}
    failed = []
    for op in ops:

        @settings(max_examples=30, deadline=None, database=None,
                  suppress_health_check=list(HealthCheck))  # fmt: skip
        @given(case=op.as_strategy())
        def check(case):
            case.call_and_validate(headers={"Authorization": f"Bearer {TOKEN}"})

        try:
            check()
        except (Exception, BaseExceptionGroup) as e:  # every operation runs; all are reported
            failed.append(f"{op.method.upper()} {op.path}: {e}")
    assert not failed, "\n\n".join(failed)
