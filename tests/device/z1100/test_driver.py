"""The Z1100 driver against the simulated chip on a real pseudo-terminal."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import pytest

from servotune.devices.z1100.codec import Command
from servotune.devices.z1100.sim.chip import Z1100Chip
from servotune.devices.z1100.sim.demo import Z1100_LOADS_KG_M2, write_demo_flash
from servotune.link.base import DeviceRefusedError, InvalidArgumentError
from servotune.sim.pty import PtySimulator
from tests.support.servers import use_csrf_token
from tests.support.sim_lines import Z1100_BAUD, chip_line
from tests.support.waiting import wait_for


async def test_three_axes_stream_and_read_flash_parameters(tmp_path: Path) -> None:
    async with chip_line(tmp_path) as line:
        assert [a.id for a in line.link.axes] == ["chip-x", "chip-y", "chip-z"]
        assert line.sink.params["chip-y"]["kabh_k"] == 128
        assert line.sink.params["chip-x"]["vmax"] == 100_000
        await wait_for(lambda: all(len(line.samples(i)) > 5 for i in range(3)), 5, "samples")
        # The line carried the polls: a share of its time, never more than all of it.
        busy = line.link.wire_busy
        assert busy is not None and 0 < busy <= 1


async def test_kabh_overwrites_kabd_and_both_are_read_back(tmp_path: Path) -> None:
    async with chip_line(tmp_path) as line:
        readback = await line.axis(0).write_params({"kabh_k": 40})
        assert readback["kabh_k"] == 40
        # The chip copied KABH into KABD (manual): the driver reports it.
        assert (readback["kabd_k"], readback["kabd_a"], readback["kabd_b"]) == (40, 16, 8)
        readback = await line.axis(0).write_params({"kabh_k": 50, "kabd_k": 20})
        assert (readback["kabh_k"], readback["kabd_k"]) == (50, 20)


async def test_move_and_refusals_while_moving(tmp_path: Path) -> None:
    async with chip_line(tmp_path) as line:
        axis = line.axis(0)
        await axis.command("go_to_target", {"target": 60_000})
        with pytest.raises(DeviceRefusedError, match="moving"):
            await axis.write_params({"vmax": 50_000})
        with pytest.raises(DeviceRefusedError, match="moving"):
            await axis.command("go_to_target", {"target": 0})
        await wait_for(
            lambda: (
                abs((line.samples(0)[-1] or 0) - 60_000) < 20
                and not line.sink.samples["chip-x"][-1].flags["running"]
            ),
            5,
            "the move to end at the target",
        )
        # Standing still again: Vmax may change.
        assert (await axis.write_params({"vmax": 50_000}))["vmax"] == 50_000


async def test_chip_reset_is_detected(tmp_path: Path) -> None:
    async with chip_line(tmp_path, flash=False) as line:
        await line.axis(1).write_params({"kabh_k": 30, "vmax": 20_000, "acc": 100_000})
        line.sim.power_cycle()  # blank flash: RAM parameters read 0 afterwards
        await wait_for(
            lambda: line.sink.health.get("chip-y", ("", ""))[0] == "reset", 5, "reset flag"
        )
        assert "reads 0" in line.sink.health["chip-y"][1]


async def test_a_zero_after_an_unanswered_fence_is_no_reset(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A reset witness that reads 0 is confirmed only on a line back in step: while the
    fence goes unanswered (a starved chip or host), a late reply may still be on its
    way, so no reset is flagged; once the fence is answered the same zeros are."""
    async with chip_line(tmp_path, flash=False) as line:
        await line.axis(1).write_params({"kabh_k": 30, "vmax": 20_000, "acc": 100_000})

        async def unanswered_fence(channel: object) -> bool:
            return False

        monkeypatch.setattr(line.link, "_resync", unanswered_fence)
        line.sim.power_cycle()  # the witnesses read 0 from now on
        await asyncio.sleep(3 * line.link.config.verify_period_s * 3)
        assert all(health != "reset" for health, _ in line.sink.health.values())
        monkeypatch.undo()
        await wait_for(
            lambda: line.sink.health.get("chip-y", ("", ""))[0] == "reset", 5, "reset flag"
        )


async def test_reset_with_flashed_parameters_is_detected_by_the_job(tmp_path: Path) -> None:
    async with chip_line(tmp_path) as line:  # flash holds good parameters
        await line.axis(0).command("go_to_target", {"target": 3000})
        await wait_for(
            lambda: (
                not line.sink.samples["chip-x"][-1].flags["running"]
                and abs((line.samples(0)[-1] or 0) - 3000) < 50
            ),
            5,
            "the move",
        )
        line.sim.power_cycle()  # parameters come back from flash, the job does not
        await wait_for(
            lambda: line.sink.health.get("chip-x", ("", ""))[0] == "reset", 5, "reset flag"
        )
        assert "job" in line.sink.health["chip-x"][1]


async def test_noise_reply_and_console(tmp_path: Path) -> None:
    async with chip_line(tmp_path) as line:
        errors = line.link.errors
        line.sim.inject_garbage(bytes([0x08, 0, 0, 0, 0, 0xF8]))  # a valid-looking reply
        sent, reply = await line.axis(2).console("GetKABH")
        assert sent == "GetKABH[motor 3]"
        assert reply[-1] == "= Gains(k=128, a=64, b=8)"
        assert line.link.errors >= errors
        with pytest.raises(InvalidArgumentError, match="K A B"):
            await line.axis(2).console("SetKABH 1 2")


async def test_a_reply_with_a_corrupt_code_byte_is_not_taken(tmp_path: Path) -> None:
    """Pinned rule: a reply whose code byte was corrupted on the wire (its
    checksum no longer adds up) is rejected and the request asked again, never taken
    for the refusal its bits would spell ("forbidden while motor 1 is moving")."""
    async with chip_line(tmp_path) as line:
        retries = line.link.counters["retries"]
        line.sim.call(
            lambda: line.chip.inject_corrupt_codes(1, mask=0x10, command=Command.SET_VMAX)
        )
        readback = await line.axis(0).write_params({"vmax": 50_000})
        assert readback["vmax"] == 50_000
        assert line.link.counters["retries"] >= retries + 1
        assert not any("moving" in message for _, _, message in line.sink.events)


async def test_a_chip_that_stops_answering_is_not_shown_connected(tmp_path: Path) -> None:
    """A chip that answers nothing at all (power lost, cable cut) left its
    link ``connected`` at 0 Hz for 11 s (three failed poll cycles of fence timeouts);
    the silence rule (``link.engine``) shows ``error`` once 3 requests in a row over
    1 s went unanswered, and ``connected`` again with the next good poll. A host that
    stalls while the chip answers is no silence: it sent nothing and missed nothing."""
    async with chip_line(tmp_path) as line:
        # The event loop (the driver) stalls 1.5 s while the chip, in its own thread,
        # answers: its reply waits in the pty, nothing is unanswered.
        stalled = asyncio.Event()

        def stall() -> None:
            time.sleep(1.5)
            stalled.set()

        asyncio.get_running_loop().call_soon(stall)
        await stalled.wait()
        await asyncio.sleep(1.2)  # a status tick after the stall
        assert "error" not in [state for state, _ in line.sink.states], line.sink.states
        assert not any("no answer" in message for _, _, message in line.sink.events)

        line.sim.set_silent(True)
        silent_at = time.monotonic()
        await wait_for(lambda: line.link.state == "error", 5, "the link in error")
        shown_s = time.monotonic() - silent_at
        state, message = line.sink.states[-1]
        assert state == "error" and message.startswith("no answer from the device for"), message
        assert any(
            level == "error" and "no answer from the device" in text
            for level, _, text in line.sink.events
        )
        print(f"silent chip shown in error after {shown_s:.2f} s")
        await asyncio.sleep(2.0)
        assert line.link.state == "error"  # for as long as it lasts

        line.sim.set_silent(False)
        await wait_for(lambda: line.link.state == "connected", 10, "connected again")
        count = len(line.sink.samples["chip-x"])
        await wait_for(lambda: len(line.sink.samples["chip-x"]) > count + 5, 5, "samples again")


async def test_the_rate_never_exceeds_the_wire_limit_after_a_capture(tmp_path: Path) -> None:
    """After a capture the link's rate counted the capture's dense samples
    of the last 2 s against the normal poll set's wire limit: "131 % of wire". The
    rate restarts with the poll set, so it never reads above the limit."""
    async with chip_line(tmp_path) as line:
        link = line.link
        ratios: list[float] = []
        async with link.capture(0, "test"):
            for _ in range(20):
                await asyncio.sleep(0.05)
                ratios.append(link.achieved_rate_hz() / link.wire_limit_hz())
        for _ in range(50):
            await asyncio.sleep(0.05)
            ratios.append(link.achieved_rate_hz() / link.wire_limit_hz())
        assert max(ratios) <= 1.0, [round(r, 2) for r in ratios]
        assert max(ratios[20:]) > 0.3  # the normal polls did run meanwhile


async def test_stall_is_flagged(tmp_path: Path) -> None:
    async with chip_line(tmp_path) as line:
        await line.axis(0).write_params({"limit": 200})
        line.sim._call(lambda: line.chip.jam(0))
        await line.axis(0).command("go_to_target", {"target": 40_000})
        await wait_for(lambda: line.sink.samples["chip-x"][-1].flags["stall"], 5, "the stall flag")
        assert any("stall" in message for _, _, message in line.sink.events)


async def test_api_refuses_while_moving_before_sending(tmp_path: Path) -> None:
    """PATCH Vmax while the motor moves: 409 with the chip's rule, nothing sent."""
    import httpx

    from servotune.api.app import AppConfig, create_app
    from servotune.config import LinkSpec

    path = tmp_path / "flash.json"
    write_demo_flash(path)
    chip = Z1100Chip.with_loads(Z1100_LOADS_KG_M2, flash_path=path, jumper_baud=Z1100_BAUD)
    with PtySimulator(chip, baud=Z1100_BAUD) as sim:
        spec = LinkSpec("z1100", sim.path, "chip", Z1100_BAUD, [0, 1, 2])
        app = create_app(AppConfig(links=[spec], data_dir=tmp_path / "data"))
        async with app.router.lifespan_context(app):
            hub = app.state.hub
            await wait_for(lambda: hub.link_status("chip").state == "connected", 5, "link")
            transport = httpx.ASGITransport(app=app)
            async with httpx.AsyncClient(
                transport=transport, base_url="http://localhost"
            ) as client:
                await use_csrf_token(client)
                url = "/api/axes/chip-y"
                response = await client.post(
                    f"{url}/commands", json={"command": "go_to_target", "target": 80_000}
                )
                assert response.status_code == 200, response.text
                await wait_for(
                    lambda: (
                        hub.entry("chip-y").latest is not None
                        and bool(hub.entry("chip-y").latest.flags["running"])
                    ),
                    5,
                    "running",
                )
                vmax_before = chip.parameters(1).vmax_counts_s
                response = await client.patch(f"{url}/params", json={"vmax": 1234})
                assert response.status_code == 409
                assert "moving" in response.json()["detail"]
                assert chip.parameters(1).vmax_counts_s == vmax_before
                response = await client.patch(f"{url}/params", json={"kabh_k": 300})
                assert response.status_code == 422
                assert "0..255" in response.json()["detail"]
