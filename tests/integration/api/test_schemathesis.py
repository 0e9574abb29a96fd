"""The API keeps its contract: schemathesis against the live OpenAPI of a demo-like app.

The app runs in-process (ASGI) with the demo's simulators (two SLAP2 modules on a pty,
a Z1100 chip with three motors on a pty, the EP7047 slave), so the OpenAPI it serves
states each axis' command and parameter bodies from its descriptor. For every
operation hypothesis generates a bounded number of requests, schema-valid ones and
schema-invalid ones, and every response must be:

- no server error: no 500 ever; a device or line that misbehaves answers 502, 503 or
  504, which are documented (the simulated lines of a loaded machine do misbehave);
- a documented status code, with a body that conforms to the documented schema and
  content type;
- for a schema-valid request: accepted, or refused for a reason the schema cannot
  state (404 no such resource, 409 refused by the device or busy). A 422 for a
  schema-valid body means the schema lies about what the server accepts;
- for a schema-invalid request: rejected (4xx).

Bounded: ``MAX_EXAMPLES`` per operation and mode, derandomized, so the whole run takes
well under a minute on a loaded 2-core machine.
"""

from __future__ import annotations

import contextlib
import dataclasses
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

schemathesis = pytest.importorskip("schemathesis")

import requests  # noqa: E402
import uvicorn  # noqa: E402
from hypothesis import HealthCheck, Phase, given, settings  # noqa: E402
from hypothesis.errors import Unsatisfiable  # noqa: E402
from schemathesis.specs.openapi import checks as openapi_checks  # noqa: E402

from servotune.api.app import AppConfig, create_app  # noqa: E402
from servotune.auth.security import SecurityConfig  # noqa: E402
from servotune.config import LinkSpec  # noqa: E402
from servotune.devices.ep7047.entry import demo_slave as ep7047_demo_slave  # noqa: E402
from servotune.devices.slap2.entry import demo_line as slap2_demo_line  # noqa: E402
from servotune.devices.z1100.entry import demo_line as z1100_demo_line  # noqa: E402
from tests.support.auth import TEST_PASSWORD_COST  # noqa: E402
from tests.support.servers import bound_socket  # noqa: E402

MAX_EXAMPLES = 2

# Operations not generated at all, each with its reason.
EXCLUDED: dict[str, str] = {
    # Each call moves the axis for 2-8 s (staircase, fit, verification moves): a
    # bounded run cannot afford them, and the test_autotune*.py modules cover them (the body
    # that once gave a 500 there: test_identify_with_the_body_schemathesis_found_a_500_with).
    "POST /api/axes/{axis_id}/autotune/identify": "slow: moves the axis for seconds",
    "POST /api/axes/{axis_id}/autotune/accept": "slow: two recorded tests per call",
}

# Operations whose schema-valid requests may be refused with 422 for a reason the
# schema cannot state; every other check still runs on them.
VALID_MAY_BE_422: dict[str, str] = {
    # The templated operations take the union of every device's bodies: a body of one
    # device sent to an axis of another is 422. The concrete per-axis operations
    # (/api/axes/<axis>/commands and /params) state each body exactly and are checked.
    "POST /api/axes/{axis_id}/commands": "union of the devices' bodies",
    "PATCH /api/axes/{axis_id}/params": "union of the devices' bodies",
    # The console grammar is the device's own (Z1100 command names, EP7047 object
    # addresses); a line it cannot parse is 422 naming `line`. Control characters are
    # excluded by the schema's pattern.
    "POST /api/axes/{axis_id}/console": "the device's console grammar",
    # Bench and import requests are checked against the axis' own limits and the run
    # format (kind-dependent distances, the stored limits, the export's meta): state
    # the schema cannot carry. Their request models belong to the bench.
    "POST /api/axes/{axis_id}/bench/runs": "checked against the axis' stored limits",
    "POST /api/axes/{axis_id}/bench/runs/import": "meta must be a run export",
}


def no_internal_error(ctx: Any, response: Any, case: Any) -> None:
    """No 5xx but the documented device answers: 502 (the device broke its protocol),
    503 (link down), 504 (no answer) say the device or its line failed, and the
    simulated lines of a loaded test machine do produce them. A 500 (or any other 5xx)
    is a bug of the server."""
    status = response.status_code
    assert status < 500 or status in (502, 503, 504), f"server error {status}: {response.text}"


def positive_unless_constraint(ctx: Any, response: Any, case: Any) -> Any:
    """``positive_data_acceptance``, except a 422 for a descriptor constraint across
    parameters (``lower <= upper`` against the device's current values): JSON Schema
    cannot compare two fields, so the params schema only lists them in its
    description."""
    if response.status_code == 422 and "must not exceed" in response.text:
        return None
    return openapi_checks.positive_data_acceptance(ctx, response, case)


def _can_be_invalid(operation: dict[str, Any]) -> bool:
    """Whether a schema-invalid request exists: a body, or a parameter with more than
    "any string" (a bare string path parameter accepts everything)."""
    if "requestBody" in operation:
        return True
    for parameter in operation.get("parameters", []):
        schema = parameter.get("schema", {})
        if set(schema) - {"type", "title", "description"} or schema.get("type") != "string":
            return True
    return False


CHECKS = [
    no_internal_error,
    openapi_checks.status_code_conformance,
    openapi_checks.content_type_conformance,
    openapi_checks.response_schema_conformance,
    openapi_checks.response_headers_conformance,
]


def _first_axis(
    start: Callable[[], contextlib.AbstractContextManager[list[LinkSpec]]],
) -> Callable[[], contextlib.AbstractContextManager[list[LinkSpec]]]:
    """The demo's simulator, but only its first axis polled: one axis per device family
    keeps the run bounded and still covers every descriptor."""

    @contextlib.contextmanager
    def started() -> Iterator[list[LinkSpec]]:
        with start() as specs:
            yield [dataclasses.replace(s, addresses=s.addresses[:1]) for s in specs]

    return started


@dataclasses.dataclass
class Demo:
    base_url: str
    app: Any


@contextlib.contextmanager
def demo_server(data_dir: Path, security: SecurityConfig | None = None) -> Iterator[Demo]:
    """A demo-like app (a SLAP2 module and a Z1100 motor on ptys, the EP7047 slave; the
    simulators in their own processes as in the demo), served by uvicorn on a free port
    in a thread; yields its base URL and the app."""
    config = AppConfig(
        data_dir=data_dir,
        simulators=[
            _first_axis(lambda: slap2_demo_line(data_dir / "sim")),
            _first_axis(lambda: z1100_demo_line(data_dir / "sim")),
            lambda: ep7047_demo_slave(data_dir / "sim"),
        ],
        web_dir=data_dir / "no-web",
        security=security or SecurityConfig(),
        # Users created by the fuzzer are hashed at the tests' cost (tests/support/auth.py).
        password_cost=TEST_PASSWORD_COST,
    )
    sock = bound_socket()
    port = sock.getsockname()[1]
    app = create_app(config)
    server = uvicorn.Server(
        uvicorn.Config(
            app,
            host="127.0.0.1",
            port=port,
            log_level="warning",
            timeout_graceful_shutdown=5,
            proxy_headers=False,  # as `servotune serve`
        )
    )
    thread = threading.Thread(
        target=server.run, kwargs={"sockets": [sock]}, name="schemathesis-demo-server"
    )
    thread.start()
    try:
        deadline = time.monotonic() + 30
        while not server.started:
            assert thread.is_alive() and time.monotonic() < deadline, "server did not start"
            time.sleep(0.05)
        yield Demo(f"http://127.0.0.1:{port}", app)
    finally:
        server.should_exit = True
        thread.join(120)


def _run(
    operation: Any,
    mode: Any,
    checks: list[Callable[..., Any]],
    base_url: str,
    headers: dict[str, str],
) -> None:
    strategy = operation.as_strategy(generation_mode=mode)

    @given(case=strategy)
    @settings(
        max_examples=MAX_EXAMPLES,
        deadline=None,
        derandomize=True,
        database=None,
        # No shrinking: the devices change state, so a failing request would not
        # fail the same way again; report what was found.
        phases=[Phase.explicit, Phase.generate],
        suppress_health_check=list(HealthCheck),
    )
    def check(case: Any) -> None:
        case.call_and_validate(base_url=base_url, headers=headers, checks=checks, timeout=30)

    check()


def _contract(base_url: str, raw: dict[str, Any], headers: dict[str, str]) -> None:
    """Every operation of ``raw`` in both modes with ``headers``; fails with every
    failure found."""
    from schemathesis import GenerationMode

    failures: list[str] = []
    operations = 0
    timings: list[tuple[float, str]] = []
    schema = schemathesis.openapi.from_dict(raw)
    for result in schema.get_all_operations():
        operation = result.ok()
        label = f"{operation.method.upper()} {operation.path}"
        if label in EXCLUDED:
            continue
        operations += 1
        positive = [*CHECKS]
        if label not in VALID_MAY_BE_422:
            positive.append(positive_unless_constraint)
        modes = [(GenerationMode.POSITIVE, positive)]
        if _can_be_invalid(raw["paths"][operation.path][operation.method.lower()]):
            negative = [*CHECKS, openapi_checks.negative_data_rejection]
            modes.append((GenerationMode.NEGATIVE, negative))
        for mode, checks in modes:
            started = time.monotonic()
            try:
                _run(operation, mode, checks, base_url, headers)
            except Unsatisfiable:
                pass  # no request of this mode exists for the operation
            except (Exception, BaseExceptionGroup) as exc:  # collect all, then fail
                failures.append(f"{label} ({mode.value}): {exc}")
            timings.append((time.monotonic() - started, f"{label} {mode.value}"))
    timings.sort(reverse=True)
    print(f"{operations} operations in {sum(t for t, _ in timings):.1f} s; slowest:")
    for seconds, what in timings[:5]:
        print(f"  {seconds:6.2f} s  {what}")
    # Every route of the demo is in the schema, the per-axis ones included.
    assert operations >= 25
    assert not failures, "\n\n".join(failures)


@pytest.mark.slow
def test_live_openapi_contract(tmp_path: Path) -> None:
    with demo_server(tmp_path) as demo:
        raw = requests.get(f"{demo.base_url}/openapi.json", timeout=60).json()
        # As the web client does: the CSRF token from the session probe on every call.
        session = requests.get(f"{demo.base_url}/api/auth/session", timeout=60).json()
        _contract(demo.base_url, raw, {"X-CSRF-Token": session["csrf_token"]})


@pytest.mark.slow
def test_live_openapi_contract_as_an_operator_in_exposed_mode(tmp_path: Path) -> None:
    """The same contract where a lab runs it: exposed mode (behind a TLS proxy on
    127.0.0.1), as an operator with an API token. What an operator may not do answers
    403, which every route documents; nothing answers 500."""
    from servotune.auth.security import AUTH_DB
    from servotune.auth.store import AuthStore
    from tests.support.auth import make_accounts

    make_accounts(tmp_path)
    store = AuthStore(tmp_path / AUTH_DB)
    try:
        token, _ = store.create_token("olga", "schemathesis", "operator")
    finally:
        store.close()
    security = SecurityConfig(mode="exposed", proxy=["127.0.0.1"], public_hosts=["127.0.0.1"])
    with demo_server(tmp_path, security) as demo:
        # An exposed server does not serve its schema: the app's own, built in-process.
        assert requests.get(f"{demo.base_url}/openapi.json", timeout=60).status_code == 404
        raw = demo.app.openapi()
        _contract(demo.base_url, raw, {"Authorization": f"Bearer {token}"})
