"""The 3D twin: state rules, and viser's protocol through the dashboard's proxy."""

from __future__ import annotations

import asyncio
import contextlib
import math
from pathlib import Path

import pytest
import viser
import websockets

from servotune.devices.slap2.descriptor import slap2_descriptor
from servotune.devices.z1100.descriptor import z1100_descriptor
from servotune.twin.model import Rail, angle_rad, classify, disc_wxyz, node_slot
from servotune.twin.scene import MIN_TURN_RAD
from tests.support.servers import demo_server
from tests.support.twin_client import angle_of, same_angle, until, viser_session

SLAP2 = slap2_descriptor(512)
Z1100 = z1100_descriptor(2048)


def test_state_priority_stale_then_fault_then_motion() -> None:
    assert SLAP2.twin is not None and Z1100.twin is not None
    live = {"link_state": "connected", "health": "ok", "sample_age_s": 0.1}
    moving_in_oc = {"move": True, "inpos": False, "oc": True}
    state = classify(SLAP2, SLAP2.twin, moving_in_oc, **live)  # type: ignore[arg-type]
    assert (state.kind, state.text) == ("fault", "oc")
    state = classify(SLAP2, SLAP2.twin, {"move": True, "inpos": True}, **live)  # type: ignore[arg-type]
    assert state.kind == "moving"
    state = classify(SLAP2, SLAP2.twin, {"inpos": True}, **live)  # type: ignore[arg-type]
    assert state.kind == "in_position"
    assert classify(Z1100, Z1100.twin, {"stall": True}, **live).text == "stall"  # type: ignore[arg-type]
    # A fault on a link that is down is not shown as live: stale wins, in grey.
    down = classify(
        SLAP2, SLAP2.twin, moving_in_oc, link_state="reconnecting", health="ok", sample_age_s=0.1
    )
    assert (down.kind, down.text) == ("stale", "STALE — link reconnecting")
    old = classify(
        SLAP2, SLAP2.twin, {"inpos": True}, link_state="connected", health="ok", sample_age_s=3.0
    )
    assert old.kind == "stale" and "3 s" in old.text
    assert down.colour != state.colour


def test_angle_convention_and_rail() -> None:
    assert angle_rad(512, 2048) == pytest.approx(math.pi / 2)
    # A quarter turn positive: the mark (at +z) goes to -x, counter-clockwise seen from -y.
    w, x, y, z = disc_wxyz(math.pi / 2)
    mark = (0.0, 0.0, 1.0)
    # Rotate the mark by the quaternion (v' = q v q*), written out for a y-axis turn.
    rotated_x = (w * w - y * y) * mark[0] + 2 * w * y * mark[2]
    assert rotated_x == pytest.approx(-1.0) and x == z == 0.0
    assert angle_of(disc_wxyz(1.0)) == pytest.approx(1.0)

    rail = Rail(2048, [None, None])
    rail.observe(0, [False, False])
    assert rail.switch_place(0, 2) == 0.0 and rail.switch_place(1, 2) == 1.0
    assert not rail.switch_known(0)
    rail.observe(-3000, [True, False])  # E1 seen on at -3000 counts: learned
    assert rail.switch_known(0) and rail.place(-3000) == rail.switch_place(0, 2)
    assert 0.0 < rail.place(-3000) < rail.place(0) < 1.0


async def raw_handshake(port: int, host: str, origin: str | None) -> str:
    """Open a websocket to /twin by hand (any Host header) and return the status line."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    lines = [
        "GET /twin HTTP/1.1",
        f"Host: {host}",
        "Upgrade: websocket",
        "Connection: Upgrade",
        "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==",
        "Sec-WebSocket-Version: 13",
        f"Sec-WebSocket-Protocol: viser-v{viser.__version__}",
    ]
    if origin is not None:
        lines.append(f"Origin: {origin}")
    writer.write(("\r\n".join(lines) + "\r\n\r\n").encode())
    await writer.drain()
    status = (await asyncio.wait_for(reader.readline(), 10)).decode().strip()
    writer.close()
    with contextlib.suppress(ConnectionError):
        await writer.wait_closed()
    return status


@pytest.mark.slow
async def test_proxy_shows_every_demo_axis_and_the_disc_follows_a_move(tmp_path: Path) -> None:
    async with demo_server(tmp_path) as demo:
        axes = [a["id"] for a in (await demo.client.get("/api/axes")).json()]
        assert len(axes) == 6
        page = await demo.client.get("/twin/")
        assert page.status_code == 200 and "Viser" in page.text
        redirect = await demo.client.get("/twin/axis/demo-slap2-0")
        assert redirect.status_code == 307
        assert redirect.headers["location"].startswith("/twin/?initialCameraPosition=")
        assert (await demo.client.get("/twin/axis/nope")).status_code == 404

        async with viser_session(demo.ws_url, viser.__version__, demo.base_url) as (scene, conn):
            assert conn.subprotocol == f"viser-v{viser.__version__}"
            await until(lambda: scene.replay_done, 20, "viser's scene replay")
            for axis_id in axes:
                root = f"/axes/{node_slot(axis_id)}"
                assert scene.nodes[f"{root}/rotor/disc"].kind == "Cylinder", axis_id
                assert scene.nodes[f"{root}/label"].kind == "Label", axis_id
            for axis_id in ("demo-slap2-0", "demo-slap2-1", "demo-ep7047-1"):
                assert f"/axes/{axis_id}/stage/carriage" in scene.nodes, "switches: a stage"
            assert "/axes/demo-z1100-x/stage/carriage" not in scene.nodes
            assert scene.nodes["/axes/demo-slap2-0/label"].props["text"] == "SLAP2 #0 unloaded"

            # A slow move of 0.375 rev (768 of 2048 counts) on SLAP2 #0.
            axis = "/api/axes/demo-slap2-0"
            rotor = scene.nodes["/axes/demo-slap2-0/rotor"]

            def rotor_angle() -> float:
                # No orientation message yet: the node is at its initial pose (angle 0).
                return angle_of(rotor.wxyz) if rotor.wxyz is not None else 0.0

            async def first_state() -> float:
                while True:
                    response = await demo.client.get(f"{axis}/state")
                    if response.status_code == 200:
                        return float(response.json()["position"])
                    await asyncio.sleep(0.1)

            start = await asyncio.wait_for(first_state(), 30)
            assert (await demo.client.patch(f"{axis}/params", json={"velocity": 30})).is_success
            for command in (
                {"command": "position_mode"},
                {"command": "move_relative", "distance": 768},
            ):
                response = await demo.client.post(f"{axis}/commands", json=command)
                assert response.status_code == 200, response.text
            seen_from = len(rotor.orientations)

            async def settled() -> float:
                # In position only after the move was seen: right after the command the
                # state may still be a sample from before it (a loaded host polls late),
                # at rest where the move starts (this read 0 instead of 768 under load).
                started = False
                while True:
                    state = (await demo.client.get(f"{axis}/state")).json()
                    moving = bool(state["flags"]["move"])
                    started = started or moving or abs(float(state["position"]) - start) > 10
                    if started and state["flags"]["inpos"] and not moving:
                        return float(state["position"])
                    await asyncio.sleep(0.1)

            end = await asyncio.wait_for(settled(), 60)
            assert end - start == pytest.approx(768, abs=20)
            final = angle_rad(end, 2048)
            await until(
                lambda: same_angle(rotor_angle(), final, MIN_TURN_RAD + 0.01),
                5,
                "the disc at the final position",
            )
            during = [angle_of(q) for _, q in rotor.orientations[seen_from:]]
            first, last = angle_rad(start, 2048), final
            between = [
                a
                for a in during
                if not same_angle(a, first, 0.05) and not same_angle(a, last, 0.05)
            ]
            # The move lasts about 2.7 s (velocity 30 sv = 281 counts/s): the disc
            # shows it on the way, not only at the end.
            assert len(between) >= 3, during


@pytest.mark.slow
async def test_proxy_refuses_foreign_origin_and_host(tmp_path: Path) -> None:
    async with demo_server(tmp_path) as demo:
        port = int(demo.base_url.rsplit(":", 1)[1])
        own = f"127.0.0.1:{port}"
        assert " 101 " in await raw_handshake(port, own, f"http://{own}")
        assert " 403 " in await raw_handshake(port, own, "http://evil.example")
        assert " 403 " in await raw_handshake(port, own, None)
        assert " 403 " in await raw_handshake(
            port, f"evil.example:{port}", f"http://evil.example:{port}"
        )
        page = await demo.client.get("/twin/", headers={"Host": "evil.example"})
        assert page.status_code == 403
        with pytest.raises(websockets.InvalidStatus):
            async with viser_session(demo.ws_url, viser.__version__, "http://evil.example"):
                pass


async def test_scene_lights_a_switch_and_greys_out_when_stale() -> None:
    """AxisScene on a real viser server, watched by a protocol client on viser's port."""
    from servotune.link.base import Sample
    from servotune.twin.model import COLOURS, SWITCH_OFF, SWITCH_ON
    from servotune.twin.scene import AxisInput, AxisScene

    assert SLAP2.twin is not None
    server = await asyncio.to_thread(viser.ViserServer, "127.0.0.1", 0, verbose=False)
    try:
        axis = AxisScene(server, "/axes/a", 0.0, "A", SLAP2, SLAP2.twin)
        url = f"ws://127.0.0.1:{server.get_port()}"
        async with viser_session(url, viser.__version__, "http://127.0.0.1") as (scene, _):
            await until(lambda: scene.replay_done, 20, "the replay")
            switch = scene.nodes["/axes/a/stage/switch0"]
            disc = scene.nodes["/axes/a/rotor/disc"]
            on_e1 = Sample(0.0, {"position": -100.0, "setpoint": -90.0}, {"limit1": True})
            with server.atomic():
                axis.apply(AxisInput(on_e1, 0.1, "connected", "ok", 1), 0.0)
            await until(lambda: switch.props["color"] == list(SWITCH_ON), 10, "E1 lit")
            assert disc.props["color"] == list(COLOURS["idle"])
            # The link drops: same sample, but stale — grey, switch unlit, no ghost.
            with server.atomic():
                axis.apply(AxisInput(on_e1, 0.1, "reconnecting", "ok", 1), 0.1)
            await until(lambda: disc.props["color"] == list(COLOURS["stale"]), 10, "grey")
            await until(lambda: switch.props["color"] == list(SWITCH_OFF), 10, "E1 unlit")
            assert scene.nodes["/axes/a/state"].props["text"] == "STALE — link reconnecting"
            assert scene.nodes["/axes/a/setpoint"].visible is False
    finally:
        await asyncio.to_thread(server.stop)
