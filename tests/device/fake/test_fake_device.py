"""Adding a device (docs/architecture.md): a device that lives in this one folder and is
registered by one line, ``default_registry().with_devices(ENTRY)``, is listed, polled and
commanded through the REST API, the websocket and the web page, with no other file of
servotune changed. The fake servo runs on a real pseudo-terminal."""

from __future__ import annotations

import ast
import asyncio
import contextlib
import json
import os
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import httpx
import pytest
import uvicorn
import websockets
from hypothesis import given
from hypothesis import strategies as st
from playwright.async_api import async_playwright, expect
from websockets.typing import Origin

from servotune.api.app import WEB_DIST, AppConfig, create_app
from servotune.config import ConfigError, LinkSpec, parse_link_spec
from servotune.devices import default_registry
from servotune.hub.control_client import ControlSettings
from servotune.registry import Registry
from servotune.sim.pty import PtySimulator
from tests.support.servers import bound_socket

from . import codec
from .entry import ENTRY
from .sim import FakeServo

T = TypeVar("T")
HERE = Path(__file__).parent
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
ARTIFACTS = Path(os.environ.get("SERVOTUNE_ARTIFACTS", HERE.parents[2] / "artifacts"))


def registry() -> Registry:
    return default_registry().with_devices(ENTRY)  # the one line that adds the device


async def until(condition: Callable[[], Any], what: str, timeout_s: float = 10.0) -> None:
    """Wait until ``condition()`` is true (an await on the server, never a fixed sleep)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    while not condition():
        if loop.time() > deadline:
            pytest.fail(f"timed out waiting for {what}")
        await asyncio.sleep(0.02)


@contextlib.contextmanager
def fake_servo() -> Iterator[tuple[PtySimulator, Callable[[Callable[[FakeServo], T]], T]]]:
    """The simulated fake servo on a pty, and a way to read it on its own thread."""
    servo = FakeServo()
    with PtySimulator(servo, baud=ENTRY.link_rules.default_baud or 9600) as simulator:

        def read(what: Callable[[FakeServo], T]) -> T:
            return simulator.call(lambda: what(servo))

        yield simulator, read


@contextlib.asynccontextmanager
async def serving(spec: LinkSpec, data_dir: Path) -> AsyncIterator[tuple[str, httpx.AsyncClient]]:
    """The app (the factory's injected registry) on a free local port."""
    config = AppConfig(
        links=[spec],
        data_dir=data_dir,
        web_dir=WEB_DIST,
        devices=registry(),
        twin=False,
        control=ControlSettings(lease_s=10.0),  # a loaded browser heartbeats slowly
    )
    sock = bound_socket()
    port = sock.getsockname()[1]
    server = uvicorn.Server(
        uvicorn.Config(
            create_app(config), host="127.0.0.1", port=port, log_level="warning", lifespan="on"
        )
    )
    task = asyncio.create_task(server.serve(sockets=[sock]))
    try:
        await until(lambda: server.started, "the server to start")
        base = f"http://127.0.0.1:{port}"
        async with httpx.AsyncClient(base_url=base, timeout=10) as client:
            session = await client.get("/api/auth/session")
            client.headers["X-CSRF-Token"] = session.json()["csrf_token"]
            yield base, client
    finally:
        server.should_exit = True
        await task


async def position(client: httpx.AsyncClient, axis: str) -> float | None:
    response = await client.get(f"/api/axes/{axis}/state")
    return response.json()["channels"]["position"] if response.status_code == 200 else None


async def test_a_device_in_one_folder_is_listed_polled_and_commanded(tmp_path: Path) -> None:
    with fake_servo() as (simulator, read):
        spec = parse_link_spec(f"fake:{simulator.path}?name=fk", registry())
        async with serving(spec, tmp_path) as (base, client):
            # Listed.
            axes = (await client.get("/api/axes")).json()
            assert axes == [
                {"id": "fk-0", "device": "fake", "link": "fk", "address": 0, "name": "Fake servo"}
            ]
            descriptor = (await client.get("/api/axes/fk-0/descriptor")).json()
            assert descriptor["title"] == "Fake servo (test)"
            assert [p["name"] for p in descriptor["parameters"]] == ["speed"]

            async with websockets.connect(
                base.replace("http", "ws") + "/ws", origin=Origin(base)
            ) as ws:
                hello = json.loads(await asyncio.wait_for(ws.recv(), 10))
                assert hello["type"] == "hello"
                assert [(a["id"], a["device"]) for a in hello["axes"]] == [("fk-0", "fake")]

                # Polled: its telemetry streams, and follows the device.
                positions: list[float] = []
                while len(positions) < 5:
                    message = json.loads(await asyncio.wait_for(ws.recv(), 10))
                    if message["type"] == "telemetry" and message["axis"] == "fk-0":
                        assert set(message["flags"]) == {"moving"}
                        positions += message["channels"]["position"]
                assert positions[-1] == 0

                # Commanded: a move reaches the simulator; the position follows, on the
                # websocket as on REST.
                response = await client.post(
                    "/api/axes/fk-0/commands", json={"command": "move_absolute", "position": 500}
                )
                assert response.status_code == 200, response.text
                assert response.json()["sent"] == ["M500"]
                assert read(lambda s: s.target) == 500
                seen_500 = False
                while not seen_500:
                    message = json.loads(await asyncio.wait_for(ws.recv(), 10))
                    if message["type"] == "telemetry" and message["axis"] == "fk-0":
                        seen_500 = 500 in message["channels"]["position"]
            assert await position(client, "fk-0") == 500

            # Validation from the descriptor: 422 naming the field, nothing sent.
            lines_before = read(lambda s: len(s.lines_seen))
            response = await client.patch("/api/axes/fk-0/params", json={"speed": 0})
            assert response.status_code == 422 and response.json()["field"] == "speed"
            assert not [x for x in read(lambda s: s.lines_seen[lines_before:]) if x[:1] == "V"]
            response = await client.patch("/api/axes/fk-0/params", json={"speed": 5000})
            assert response.status_code == 200, response.text
            assert response.json() == {"speed": 5000} and read(lambda s: s.speed) == 5000

            # The console: a raw line the descriptor's rules know.
            response = await client.post("/api/axes/fk-0/console", json={"line": "Q"})
            assert response.status_code == 200, response.text
            assert response.json()["reply"] == ["V5000"]

            # STOP goes out and the shaft stays where it stopped, short of the target.
            await client.post(
                "/api/axes/fk-0/commands", json={"command": "move_absolute", "position": 900_000}
            )
            await until(lambda: read(lambda s: s.position) > 1000, "the long move to start")
            lines_before = read(lambda s: len(s.lines_seen))
            response = await client.post("/api/stop")
            assert response.status_code == 200 and response.json()["failed"] == []
            assert "S" in read(lambda s: s.lines_seen[lines_before:])
            stopped_at = read(lambda s: s.target)
            assert 1000 < stopped_at < 900_000
            await until(lambda: not read(lambda s: s.moving), "the shaft to stand")
            status = (await client.get("/api/links/fk/status")).json()
            assert status["state"] == "connected"


@pytest.mark.browser
async def test_the_web_page_renders_and_commands_the_fake_device(tmp_path: Path) -> None:
    assert (WEB_DIST / "index.html").exists(), "build the web bundle (scripts/test.sh does)"
    with fake_servo() as (simulator, read):
        spec = parse_link_spec(f"fake:{simulator.path}?name=fk", registry())
        async with serving(spec, tmp_path) as (base, _), async_playwright() as playwright:
            browser = await playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            try:
                page = await browser.new_page(viewport={"width": 1280, "height": 900})
                errors: list[str] = []
                page.on("pageerror", lambda exc: errors.append(str(exc)))
                await page.goto(base)
                # The axis is listed; its page is the descriptor's fields.
                await page.get_by_test_id("axis-link-fk-0").click()
                await expect(page.get_by_test_id("param-speed-input")).to_be_visible()
                await expect(page.get_by_test_id("readout-position")).to_be_visible()
                await expect(page.get_by_test_id("flag-moving")).to_be_attached()
                await expect(page.get_by_test_id("plot-position")).to_be_visible()
                # Polled: the readout shows the device's position.
                await expect(page.get_by_test_id("readout-position")).to_contain_text("0")
                # Commanded from the page: the move reaches the simulated device.
                await page.get_by_test_id("cmd-move_absolute-position").fill("800")
                await page.get_by_test_id("cmd-move_absolute").click()
                await until(lambda: read(lambda s: s.target) == 800, "the move from the page")
                await expect(page.get_by_test_id("readout-position")).to_contain_text(
                    "800", timeout=10_000
                )
                # STOP is always there and reaches the device.
                stop = page.get_by_test_id("stop-all")
                await expect(stop).to_be_visible()
                sent = read(lambda s: len(s.lines_seen))
                await stop.click()
                await until(lambda: "S" in read(lambda s: s.lines_seen[sent:]), "STOP's S")
                ARTIFACTS.mkdir(parents=True, exist_ok=True)
                await page.screenshot(path=str(ARTIFACTS / "fake-device.png"), full_page=True)
                # Its test bench opens too (a device without bench tests has no kinds).
                await page.get_by_test_id("bench-toggle").click()
                await expect(page.get_by_test_id("bench-runs")).to_be_attached()
                await page.screenshot(path=str(ARTIFACTS / "fake-device-bench.png"))
                assert not errors, f"JavaScript errors: {errors}"
            finally:
                await browser.close()


def test_without_its_registry_line_the_device_is_refused() -> None:
    with pytest.raises(ConfigError, match="slap2, z1100, ep7047"):
        parse_link_spec("fake:/dev/null", default_registry())


@given(
    st.integers(-codec.POSITION_LIMIT, codec.POSITION_LIMIT),
    st.booleans(),
    st.integers(*codec.SPEED_RANGE),
    st.binary(max_size=20).filter(lambda b: b"\n" not in b),
)
def test_codec_round_trips_and_resynchronises(
    counts: int, moving: bool, speed: int, garbage: bytes
) -> None:
    replies: list[codec.Reply] = [
        codec.Position(counts, moving),
        codec.Speed(speed),
        codec.Ok(),
        codec.Refused(),
    ]
    wire = b"".join(codec.encode_reply(r) for r in replies)
    decoder = codec.LineDecoder()
    # Garbage before a line is dropped with that line; the next LF resynchronises.
    out = decoder.feed(garbage + b"\n" + wire[:3]) + decoder.feed(wire[3:])
    assert out[-4:] == replies
    assert decoder.dropped + len(out) == 5
    assert codec.make_move(counts) == f"M{counts}\n".encode()
    with pytest.raises(ValueError, match="speed"):
        codec.make_set_speed(codec.SPEED_RANGE[1] + 1)


def _servotune_imports(path: Path) -> set[str]:
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
    return {name for name in found if name.split(".")[0] == "servotune"}


def device_rule_violations(files: dict[str, Path]) -> list[str]:
    """The layer rules of a device folder (tests/unit/test_layers.py): it imports no device
    and only generic servotune modules; only its entry names the registry's contract;
    its simulator imports only the generic simulator helpers."""
    wrong = []
    for name, path in files.items():
        for module in _servotune_imports(path):
            if module.startswith("servotune.devices") and not (
                name == "test_fake_device" and module == "servotune.devices"
            ):
                wrong.append(f"{name} imports {module}")
            if module == "servotune.registry" and name not in ("entry", "test_fake_device"):
                wrong.append(f"{name} imports {module}")
            if name == "sim" and not module.startswith("servotune.sim"):
                wrong.append(f"{name} imports {module}")
    return wrong


def test_the_folder_imports_only_generic_servotune(tmp_path: Path) -> None:
    files = {path.stem: path for path in HERE.glob("*.py")}
    assert {"codec", "sim", "link", "descriptor", "entry"} <= set(files)
    assert device_rule_violations(files) == []
    # The check's own check: an injected device import is found.
    bad = tmp_path / "link.py"
    bad.write_text("from servotune.devices.z1100.codec import Gains\n", encoding="utf-8")
    assert device_rule_violations({"link": bad}) == ["link imports servotune.devices.z1100.codec"]
