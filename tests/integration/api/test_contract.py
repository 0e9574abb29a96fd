"""The API's contract without a device: descriptor defaults and constraints, the live
OpenAPI's per-device bodies, request models that refuse what the server would refuse,
and 405 answers with a correct ``Allow`` header."""

from __future__ import annotations

from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import pytest

from servotune.api.app import AppConfig, create_app
from servotune.descriptor import DeviceDescriptor
from servotune.devices.ep7047.descriptor import ep7047_descriptor
from servotune.devices.slap2.descriptor import slap2_descriptor
from servotune.devices.z1100.descriptor import z1100_descriptor
from servotune.hub.state import UnknownAxisError
from servotune.link.base import InvalidArgumentError
from servotune.link.validation import validate_command, validate_params
from servotune.schema import AxisInfo
from tests.support.servers import local_client, use_csrf_token

EP7047 = ep7047_descriptor(speed_range_steps_s=2000, counts_per_rev=4096)
SLAP2 = slap2_descriptor(512)
Z1100 = z1100_descriptor(2048)


def refused(call: Any) -> InvalidArgumentError:
    with pytest.raises(InvalidArgumentError) as caught:
        call()
    return caught.value


# --- command arguments: defaults and required ------------------------------------------


def test_omitted_arguments_take_the_descriptor_default() -> None:
    checked = validate_command(EP7047, "execute_move", {"target": 1000})
    move = EP7047.command("execute_move")
    defaults = {a.name: a.default for a in move.arguments if a.name != "target"}
    assert defaults["acceleration_ms"] == 500  # what the descriptor promises
    assert checked == {"target": 1000, **defaults}


def test_a_required_argument_must_be_given() -> None:
    error = refused(lambda: validate_command(EP7047, "execute_move", {"velocity": 100}))
    assert error.field == "target"
    assert refused(lambda: validate_command(SLAP2, "move_absolute", {})).field == "position"
    assert refused(lambda: validate_command(Z1100, "go_to_target", {})).field == "target"


def test_integral_floats_are_integers_others_are_refused() -> None:
    checked = validate_command(SLAP2, "move_relative", {"distance": 381.0})
    assert checked == {"distance": 381} and type(checked["distance"]) is int
    for bad in (381.5, float("nan"), float("inf"), True, "381"):
        assert refused(lambda b=bad: validate_command(SLAP2, "move_relative", {"distance": b}))
    assert refused(lambda: validate_params(SLAP2, {"kp": 1.5})).field == "kp"


# --- parameters: choices and constraints across fields ----------------------------------


def test_cross_field_constraint_against_the_current_values() -> None:
    current = {"velocity_min_bp": 50, "velocity_max_bp": 100}
    error = refused(lambda: validate_params(EP7047, {"velocity_min_bp": 5000}, current))
    assert error.field == "velocity_min_bp"
    assert "velocity_max_bp (100)" in str(error)
    # Lowering the maximum below the current minimum names the maximum.
    current = {"velocity_min_bp": 500, "velocity_max_bp": 10000}
    error = refused(lambda: validate_params(EP7047, {"velocity_max_bp": 100}, current))
    assert error.field == "velocity_max_bp"
    # Both written together, consistent: fine, whatever the device had.
    both = {"velocity_min_bp": 5000, "velocity_max_bp": 6000}
    assert validate_params(EP7047, both, {"velocity_min_bp": 0, "velocity_max_bp": 1}) == both
    # Both written together, inconsistent: refused without any current values.
    bad = {"velocity_min_bp": 5000, "velocity_max_bp": 100}
    assert refused(lambda: validate_params(EP7047, bad)).field == "velocity_min_bp"


def test_enumerated_parameter_accepts_only_its_codes() -> None:
    parameter = EP7047.parameter("default_start_type")
    assert parameter.choices and 0x1001 not in {c.value for c in parameter.choices}
    assert validate_params(EP7047, {"default_start_type": 1}) == {"default_start_type": 1}
    error = refused(lambda: validate_params(EP7047, {"default_start_type": 28415}))
    assert error.field == "default_start_type"


def test_every_device_names_its_stop_effect() -> None:
    # STOP is the shortest safe stop: the servos hold under power (cat. 2),
    # the stepper ramps and drops Enable (cat. 1); cutting power is a command of its own.
    assert SLAP2.stop.motor_powered is True and "holds" in SLAP2.stop.summary
    assert SLAP2.stop.category == 2 and "spwm 0" in (SLAP2.stop.loop_failed or "")
    assert SLAP2.stop.gentler == ["jog_stop", "hold"] and SLAP2.command("hold").group == "stop"
    assert Z1100.stop.motor_powered is True and Z1100.stop.gentler == ["decelerate"]
    assert EP7047.stop.motor_powered is False and EP7047.stop.category == 1
    for descriptor in (SLAP2, Z1100, EP7047):
        for name in descriptor.stop.gentler:
            descriptor.command(name)  # exists
        assert descriptor.stop.power_off_command is not None
        assert descriptor.command(descriptor.stop.power_off_command).group == "stop"
        for constraint in descriptor.constraints:
            descriptor.parameter(constraint.lower), descriptor.parameter(constraint.upper)


# --- HTTP: an app with a stub hub (nothing behind it) -------------------------------------


@dataclass
class StubHub:
    """Enough of a Hub for the schema and for requests refused before the handler."""

    axes: dict[str, DeviceDescriptor] = field(default_factory=dict)

    def axes_info(self) -> list[AxisInfo]:
        return [
            AxisInfo(id=a, device=d.device, link="l", address=0, name=a)
            for a, d in self.axes.items()
        ]

    def descriptor(self, axis_id: str) -> DeviceDescriptor:
        try:
            return self.axes[axis_id]
        except KeyError:
            raise UnknownAxisError(axis_id) from None

    def entry(self, axis_id: str) -> Any:
        raise UnknownAxisError(axis_id)


@pytest.fixture
async def client(tmp_path: Path) -> AsyncIterator[httpx.AsyncClient]:
    """The app without its lifespan (no storage, no links): only what is refused or
    answered before a handler reaches the hub."""
    app = create_app(AppConfig(data_dir=tmp_path, web_dir=tmp_path / "no-web"))
    app.state.hub = StubHub({"s": SLAP2, "e": EP7047})
    app.state.storage = None  # resolved as a dependency, never used by these requests
    # The accounts database and the CSRF secret are opened by the lifespan, which this
    # app does not run: open them here.
    app.state.security.open()
    try:
        async with local_client(app) as client:
            await use_csrf_token(client)
            yield client
    finally:
        await app.state.security.close()


async def test_live_openapi_states_each_axis_body(client: httpx.AsyncClient) -> None:
    schema = (await client.get("/openapi.json")).json()
    body = schema["paths"]["/api/axes/e/commands"]["post"]["requestBody"]["content"]
    variants = body["application/json"]["schema"]["anyOf"]
    move = next(v for v in variants if v["properties"]["command"]["const"] == "execute_move")
    assert move["required"] == ["command", "target"]
    assert move["properties"]["acceleration_ms"]["default"] == 500
    assert move["additionalProperties"] is False
    params = schema["paths"]["/api/axes/s/params"]["patch"]["requestBody"]["content"]
    kp = params["application/json"]["schema"]["properties"]["kp"]
    assert (kp["type"], kp["minimum"], kp["maximum"]) == ("integer", 0, 32767)
    assert "get" in schema["paths"]["/api/axes/s/params"]
    # The templated operation takes every device's commands.
    templated = schema["paths"]["/api/axes/{axis_id}/commands"]["post"]["requestBody"]
    names = {
        v["properties"]["command"]["const"]
        for v in templated["content"]["application/json"]["schema"]["anyOf"]
    }
    assert {"hold", "execute_move"} <= names
    # Every operation documents 422 where it takes input, and its error body.
    for path, item in schema["paths"].items():
        for method, operation in item.items():
            if "{" in path or "requestBody" in operation:
                assert "422" in operation["responses"], (method, path)


@pytest.mark.parametrize(
    "line", ["rp\rsv0", "rp\n", "se\x18", "\x0b", "a\x7fb", "", "   ", "x" * 65]
)
async def test_console_line_with_control_characters_is_422_naming_line(
    client: httpx.AsyncClient, line: str
) -> None:
    response = await client.post("/api/axes/s/console", json={"line": line})
    assert response.status_code == 422, response.text
    assert response.json()["field"] == "line"


@pytest.mark.parametrize("name", [".", "..", " ", " a", "a ", "a/b", "", "x" * 61])
async def test_parameter_set_names_that_could_not_be_opened_are_422(
    client: httpx.AsyncClient, name: str
) -> None:
    response = await client.post("/api/axes/s/param-sets", json={"name": name})
    assert response.status_code == 422, response.text
    assert response.json()["field"] == "name"


async def test_unknown_fields_and_bodies_that_are_not_json_are_422(
    client: httpx.AsyncClient,
) -> None:
    response = await client.post("/api/axes/s/console", json={"line": "rp", "echo": True})
    assert (response.status_code, response.json()["field"]) == (422, "echo")
    response = await client.post(
        "/api/axes/s/param-sets", json={"name": "a", "note": "", "colour": "red"}
    )
    assert (response.status_code, response.json()["field"]) == (422, "colour")
    response = await client.post(
        "/api/axes/s/commands", content=b"\xff\x00{", headers={"content-type": "application/json"}
    )
    assert response.status_code == 422


async def test_405_lists_every_method_of_the_path(client: httpx.AsyncClient) -> None:
    response = await client.put("/api/axes/s/params", json={})
    assert response.status_code == 405
    assert set(response.headers["allow"].split(", ")) == {"GET", "PATCH"}
    response = await client.options("/api/axes/s/param-sets/x")
    assert response.status_code == 405
    assert set(response.headers["allow"].split(", ")) == {"DELETE"}
    response = await client.delete("/api/stop")
    assert (response.status_code, response.headers["allow"]) == (405, "POST")
    assert response.json()["detail"]
