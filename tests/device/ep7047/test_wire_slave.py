"""The simulated EP7047-1032 for the wire, sans-IO: its process image against the
driver's codec (the independent check), its SDO server, its AL state machine.

The slave's layout comes from its own PDO mapping objects (written from the spec); the
codec's from ``devices.ep7047.codec``. They must agree byte for byte, and a wrong bit or
offset on either side fails here (``test_a_moved_field_is_caught`` proves it can).
"""

from __future__ import annotations

import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from servotune.devices.ep7047 import codec
from servotune.devices.ep7047.codec import Inputs, Outputs, StartType
from servotune.devices.ep7047.sim import coe, process_image
from servotune.devices.ep7047.sim.coe import ImageLayout, ObjectDictionary, SdoServer
from servotune.devices.ep7047.sim.engine import Ep7047Engine
from servotune.devices.ep7047.sim.plant import DEMO_MECHANICS
from servotune.devices.ep7047.sim.slave import demo_slave
from servotune.devices.ep7047.sim.wire import WireSlave
from servotune.devices.ep7047.sim.wire_loop import demo_wire_slave

u16 = st.integers(0, 0xFFFF)
i32 = st.integers(codec.INT32_MIN, codec.INT32_MAX)
i16 = st.integers(codec.INT16_MIN, codec.INT16_MAX)

RX = ImageLayout.of(coe.RXPDO_MAPS, coe.POSITIONING_RX)
TX = ImageLayout.of(coe.TXPDO_MAPS, coe.POSITIONING_TX)


def test_the_spec_sizes() -> None:
    assert (RX.size_bytes, TX.size_bytes) == (22, 24)
    assert (RX.size_bytes, TX.size_bytes) == (codec.OUTPUTS_SIZE, codec.INPUTS_SIZE)
    assert coe.POSITIONING_RX == codec.RXPDO_ASSIGNMENT
    assert coe.POSITIONING_TX == codec.TXPDO_ASSIGNMENT


@given(
    enc=st.integers(0, 0xF),
    stm=st.sampled_from([0, 1, 2, 3, 7, 0x801]),
    pos=st.integers(0, 3),
    counter=i32,
    target=i32,
    velocity=i16,
    start=u16,
    acc=u16,
    dec=u16,
)
def test_outputs_codec_and_slave_agree(
    enc: int, stm: int, pos: int, counter: int, target: int, velocity: int, start: int,
    acc: int, dec: int,
) -> None:  # fmt: skip
    outputs = Outputs(
        enc_control=codec.EncControl(enc),
        set_counter_counts=counter,
        stm_control=codec.StmControl(stm),
        pos_control=codec.PosControl(pos),
        target_position_counts=target,
        velocity_bp=velocity,
        start_type=codec.start_type_of(start),
        acceleration_ms=acc,
        deceleration_ms=dec,
    )
    wire = codec.encode_outputs(outputs)
    # The slave decodes the driver's bytes with its own mapping, into the same outputs.
    assert process_image.outputs_from(RX.unpack(wire)) == outputs
    assert RX.pack(process_image.output_values(outputs)) == wire


@given(
    enc=st.sampled_from([0, 1, 4, 0x100, 0x400, 0x8000, 0x8401]),
    stm=st.integers(0, 0xFF),
    stm_hi=st.sampled_from([0, 0x800, 0x1000, 0x2000, 0x8000]),
    pos=st.integers(0, 0xFF),
    counter=i32,
    latch=i32,
    position=i32,
    velocity=i16,
    drive_time=st.integers(0, 0xFFFF_FFFF),
)
def test_inputs_codec_and_slave_agree(
    enc: int, stm: int, stm_hi: int, pos: int, counter: int, latch: int, position: int,
    velocity: int, drive_time: int,
) -> None:  # fmt: skip
    inputs = Inputs(
        enc_status=codec.EncStatus(enc),
        counter_counts=counter,
        latch_counts=latch,
        stm_status=codec.StmStatus(stm | stm_hi),
        pos_status=codec.PosStatus(pos),
        actual_position_counts=position,
        actual_velocity_bp=velocity,
        actual_drive_time_ms=drive_time,
    )
    # What the slave puts on the wire is what the driver's codec reads.
    assert codec.decode_inputs(TX.pack(process_image.input_values(inputs))) == inputs


def test_a_moved_field_is_caught() -> None:
    """The check can fail: a slave that maps Velocity and Start type the other way round
    (both 16 bit) gives bytes the codec reads differently."""
    name, entries = coe.RXPDO_MAPS[0x1606]
    swapped = list(entries)
    swapped[4], swapped[5] = swapped[5], swapped[4]
    maps = {**coe.RXPDO_MAPS, 0x1606: (name, tuple(swapped))}
    wrong = ImageLayout.of(maps, coe.POSITIONING_RX)
    outputs = Outputs(velocity_bp=3000, start_type=StartType.ABSOLUTE)
    assert wrong.pack(process_image.output_values(outputs)) != codec.encode_outputs(outputs)
    assert codec.decode_outputs(wrong.pack(process_image.output_values(outputs))) != outputs


def test_every_coe_setting_of_the_codec_is_in_the_slave_with_its_size() -> None:
    slave = WireSlave(Ep7047Engine())
    for obj in codec.SDO_OBJECTS:
        entry = slave.od.entries.get((obj.index, obj.subindex))
        assert entry is not None, f"0x{obj.index:04X}:{obj.subindex:02X} {obj.name}"
        assert len(entry.read()) == obj.data_type.size, obj.name
        assert entry.name == obj.name


# --- SDO server ---------------------------------------------------------------------------


def _request(sdo: bytes) -> bytes:
    body = struct.pack("<H", coe.COE_SDO_REQUEST << 12) + sdo
    return struct.pack("<HHBB", len(body), 0, 0, coe.MBX_TYPE_COE | 1 << 4) + body


def _reply(message: bytes) -> tuple[int, bytes]:
    length = struct.unpack_from("<H", message)[0]
    body = message[6 : 6 + length]
    return struct.unpack_from("<H", body)[0] >> 12, body[2:]


def _server() -> SdoServer:
    od = ObjectDictionary()
    od.add(coe.Entry(0x2000, 0, "pad", coe.OCTET_STRING, coe.Access.RW, b"", size=256))
    od.add(coe.Entry(0x3000, 1, "u16", coe.UNSIGNED16, coe.Access.RW, 5, maximum=100))
    return SdoServer(od, mailbox_size=48)


def test_expedited_download_and_upload() -> None:
    server = _server()
    service, sdo = _reply(server.handle(_request(struct.pack("<BHBH2x", 0x2B, 0x3000, 1, 42))))
    assert (service, sdo[0]) == (coe.COE_SDO_RESPONSE, 0x60)
    _, sdo = _reply(server.handle(_request(struct.pack("<BHB4x", 0x40, 0x3000, 1))))
    assert sdo[0] == 0x4B and sdo[4:6] == struct.pack("<H", 42)


def test_an_abort_is_sent_as_an_sdo_request_with_its_code() -> None:
    server = _server()
    service, sdo = _reply(server.handle(_request(struct.pack("<BHBH2x", 0x2B, 0x3000, 1, 101))))
    assert service == coe.COE_SDO_REQUEST  # SOEM reads an abort only with service 2
    assert sdo[0] == 0x80 and struct.unpack_from("<I", sdo, 4)[0] == coe.ABORT_VALUE_HIGH
    _, sdo = _reply(server.handle(_request(struct.pack("<BHB4x", 0x40, 0x4000, 0))))
    assert struct.unpack_from("<I", sdo, 4)[0] == coe.ABORT_NO_OBJECT


def test_segmented_download_then_upload_through_a_small_mailbox() -> None:
    server = _server()  # 48-byte mailbox: 32 bytes in the first message, 39 a segment
    data = bytes(range(200))
    first = 48 - 6 - 10
    initiate = struct.pack("<BHBI", 0x21, 0x2000, 0, len(data)) + data[:first]
    assert _reply(server.handle(_request(initiate)))[1][0] == 0x60
    offset, toggle = first, 0
    while offset < len(data):
        chunk = data[offset : offset + 39]
        offset += len(chunk)
        last = offset >= len(data)
        unused = max(0, 7 - len(chunk))
        command = toggle | unused << 1 | (1 if last else 0)
        _, sdo = _reply(server.handle(_request(bytes([command]) + chunk.ljust(7, b"\0"))))
        assert sdo[0] == 0x20 | toggle
        toggle ^= 0x10
    # Upload: the size and the first part, then segments until the last bit.
    _, sdo = _reply(server.handle(_request(struct.pack("<BHB4x", 0x40, 0x2000, 0))))
    assert sdo[0] == 0x41 and struct.unpack_from("<I", sdo, 4)[0] == len(data)
    received = bytearray(sdo[8:])
    toggle = 0
    while True:
        message = server.handle(_request(bytes([0x60 | toggle]) + bytes(7)))
        length = struct.unpack_from("<H", message)[0]
        _, sdo = _reply(message)
        size = length - 3
        if size == 7:
            size -= (sdo[0] >> 1) & 7
        received += sdo[1 : 1 + size]
        if sdo[0] & 1:
            break
        toggle ^= 0x10
    assert bytes(received) == data


def test_a_wrong_toggle_aborts() -> None:
    server = _server()
    initiate = struct.pack("<BHBI", 0x21, 0x2000, 0, 100) + bytes(32)
    server.handle(_request(initiate))
    _, sdo = _reply(server.handle(_request(bytes([0x10]) + bytes(39))))
    assert sdo[0] == 0x80 and struct.unpack_from("<I", sdo, 4)[0] == coe.ABORT_TOGGLE


# --- AL state machine ---------------------------------------------------------------------


class _Clock:
    def __init__(self) -> None:
        self.ns = 0

    def __call__(self) -> int:
        return self.ns


def _configured(slave: WireSlave, *, mailbox_ok: bool = True) -> None:
    esc = slave.esc
    struct.pack_into(
        "<HHBBBB", esc.memory, 0x0800, 0x1000, 128 if mailbox_ok else 64, 0x26, 0, 1, 0
    )
    struct.pack_into("<HHBBBB", esc.memory, 0x0808, 0x1080, 128, 0x22, 0, 1, 0)


def test_al_transitions_refuse_with_their_codes() -> None:
    slave = WireSlave(Ep7047Engine(), clock_ns=_Clock())
    slave.al_control(0x08)  # INIT -> OP: not a valid jump
    assert (slave.al_state, slave.al_error, slave.al_code) == (0x01, True, 0x0011)
    slave.al_control(0x02)  # not acknowledged: no way up
    assert slave.al_state == 0x01
    _configured(slave, mailbox_ok=False)
    slave.al_control(0x12)  # acknowledge + PRE-OP, but the mailbox is wrong
    assert (slave.al_state, slave.al_code) == (0x01, 0x0016)
    _configured(slave)
    slave.al_control(0x12)
    assert (slave.al_state, slave.al_error) == (0x02, False)
    slave.al_control(0x04)  # SM2/SM3 not configured for the (default) assignment
    assert (slave.al_state, slave.al_code) == (0x02, 0x001D)
    slave.al_control(0x15)  # acknowledged, but state 5 does not exist
    assert slave.al_code == 0x0012  # an unknown state


def test_the_watchdog_puts_the_slave_into_safeop_error_with_safe_outputs() -> None:
    clock = _Clock()
    slave = WireSlave(Ep7047Engine(), clock_ns=clock)
    _configured(slave)
    slave.al_control(0x12)
    out = slave.od.output_layout().size_bytes
    inp = slave.od.input_layout().size_bytes
    struct.pack_into("<HHBBBB", slave.esc.memory, 0x0810, 0x1100, out, 0x64, 0, 1, 0)
    struct.pack_into("<HHBBBB", slave.esc.memory, 0x0818, 0x1180, inp, 0x20, 0, 1, 0)
    slave.al_control(0x04)
    slave.al_control(0x08)
    assert slave.al_state == 0x08
    clock.ns = 99_000_000
    slave.advance(clock.ns)
    assert slave.al_state == 0x08
    clock.ns = 101_000_000
    slave.advance(clock.ns)
    assert (slave.al_state, slave.al_error, slave.al_code) == (0x04, True, 0x001B)
    assert slave.stats.watchdog_trips == 1


@pytest.mark.parametrize("code", [0x1B87_4052])
def test_the_sii_names_the_device_in_string_one(code: int) -> None:
    from servotune.devices.ep7047.sim.sii import Identity, build_sii

    image = build_sii(Identity(product=code))
    assert struct.unpack_from("<I", image, 0x0A * 2)[0] == code
    assert struct.unpack_from("<HH", image, 0x40 * 2) == (
        10,
        struct.unpack_from("<H", image, 0x82)[0],
    )
    count, length = image[0x84], image[0x85]
    assert count >= 1 and image[0x86 : 0x86 + length] == b"EP7047-1032"


def test_the_wire_slave_drives_the_demo_mechanics_which_coast_when_outputs_go_safe() -> None:
    """The slave on the wire runs the demo's drive with its rotor and load: when its
    outputs go safe (Enable off: the watchdog, a pulled cable) at speed, the shaft
    coasts and the counter (an encoder) counts it."""
    assert demo_wire_slave().engine.plant.mechanics is DEMO_MECHANICS
    clock = _Clock()
    slave = WireSlave(demo_slave().engine, clock_ns=clock)
    endless = Outputs(
        stm_control=codec.StmControl.ENABLE,
        pos_control=codec.PosControl.EXECUTE,
        velocity_bp=10_000,
        start_type=StartType.ENDLESS_PLUS,
        acceleration_ms=400,
    )
    slave.engine.run(Outputs(stm_control=codec.StmControl.ENABLE), 4)
    slave.engine.run(endless, 4000)  # 1 s: at top speed (10 turns/s)
    before = slave.record()["actual_counts"]
    clock.ns = 500_000_000
    slave.advance(clock.ns)  # 0.5 s with the slave's safe outputs
    coasted = slave.record()["actual_counts"] - before
    assert 4000 < coasted < 5500, coasted  # ~1.2 turns: the equation of motion's 4760
    assert slave.engine.plant.speed_counts_s == 0.0
