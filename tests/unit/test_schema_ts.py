"""The generated TypeScript of the wire schema: every model of ``servotune.schema`` is
rendered, a REST request's defaulted field is optional, a response's fields are all
sent, and the checked-in ``web/src/schema.gen.ts`` is current."""

from __future__ import annotations

import inspect

from pydantic import BaseModel

from servotune import schema, schema_ts
from tests.support.paths import REPO

# Models of the schema that are not bodies the web client reads or sends: the command
# request is free-form (its fields come from the descriptor).
NOT_RENDERED = {"CommandRequest"}


def test_every_schema_model_is_rendered() -> None:
    rendered = {
        m.__name__ for m in [*schema_ts.MODELS, *schema_ts.REST_RESPONSES, *schema_ts.REST_REQUESTS]
    }
    declared = {
        name
        for name, value in vars(schema).items()
        if inspect.isclass(value)
        and issubclass(value, BaseModel)
        and value.__module__ == schema.__name__
    }
    assert declared - NOT_RENDERED - rendered == set()


def test_request_defaults_are_optional_and_responses_are_complete() -> None:
    text = schema_ts.render()
    request = text.split("export interface BenchTestRequest {", 1)[1].split("}", 1)[0]
    assert "  kind: BenchKind;" in request  # required: no default
    assert "  distance?: number;" in request
    response = text.split("export interface BenchLimits {", 1)[1].split("}", 1)[0]
    assert "  min_position_counts: number | null;" in response
    assert "?" not in response


def test_shapes_of_rest_bodies() -> None:
    assert schema_ts.ts_type(tuple[int | float, int | float]) == "[number, number]"
    assert schema_ts.ts_type(dict[str, int | float | None]) == "Record<string, number | null>"


def test_checked_in_file_is_current() -> None:
    path = REPO / "web" / "src" / "schema.gen.ts"
    assert schema_ts.main(["--check", str(path)]) == 0
