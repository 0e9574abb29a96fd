"""Z1100 codec: packets, checksums, command table, data words, decoders, range errors."""

from __future__ import annotations

import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from servotune.devices.z1100 import codec
from servotune.devices.z1100.codec import Command, ReplyCode

axes = st.integers(min_value=0, max_value=2)
gains = st.integers(min_value=0, max_value=255)
positive32 = st.integers(min_value=0, max_value=2**31 - 1)
int32 = st.integers(min_value=-(2**31), max_value=2**31 - 1)
bytes_ = st.integers(min_value=0, max_value=255)
words = st.integers(min_value=0, max_value=2**32 - 1)
requests = st.builds(codec.Request, bytes_, words)
replies = st.builds(codec.Reply, st.builds(ReplyCode, bytes_), words)
axis_sets = st.frozensets(axes)


def checksum_by_hand(*values: int) -> int:
    """The manual's formula, written out independently of the codec."""
    return (0x00 - sum(values)) & 0xFF


# --- packets and checksums ---------------------------------------------------------


@given(requests)
def test_every_request_round_trips(request: codec.Request) -> None:
    packet = codec.encode_request(request)
    assert len(packet) == 7 and packet[0] == 0x5A
    assert codec.decode_request(packet) == request


@given(replies)
def test_every_reply_round_trips(reply: codec.Reply) -> None:
    packet = codec.encode_reply(reply)
    assert len(packet) == 6
    assert sum(packet) & 0xFF == 0
    assert codec.decode_reply(packet) == reply


@given(bytes_, words)
def test_request_checksum_follows_the_manual_formula(command: int, data: int) -> None:
    d3, d2, d1, d0 = data >> 24, (data >> 16) & 0xFF, (data >> 8) & 0xFF, data & 0xFF
    packet = codec.Request(command, data).encode()
    assert packet == bytes(
        (0x5A, command, d3, d2, d1, d0, checksum_by_hand(command, d3, d2, d1, d0))
    )


@pytest.mark.parametrize(
    ("request_", "expected"),
    [
        # GetKABH motor 1..3: CS = -(0x80), -(0x81), -(0x82)
        (codec.make_get_kab(0), "5a 80 00 00 00 00 80"),
        (codec.make_get_kab(1), "5a 81 00 00 00 00 7f"),
        (codec.make_get_kab(2), "5a 82 00 00 00 00 7e"),
        (codec.make_get(Command.GET_VMAX, 0), "5a 88 00 00 00 00 78"),
        (codec.make_get(Command.GET_ACC, 2), "5a 8e 00 00 00 00 72"),
        # SetKABH motor 3, K=0x20 A=0x10 B=0x08: 0x02+0x20+0x10+0x08 = 0x3A -> 0xC6
        (codec.make_set_kab(2, 0x20, 0x10, 0x08), "5a 02 00 20 10 08 c6"),
        # SetTarget motor 1 = -1: 0x2C + 4 * 0xFF = 0x428 -> 0xD8
        (codec.make_set_target(0, -1), "5a 2c ff ff ff ff d8"),
        # SetVmax motor 2 = 100000 = 0x000186A0: 0x09+0x01+0x86+0xA0 = 0x130 -> 0xD0
        (codec.make_set_vmax(1, 100_000), "5a 09 00 01 86 a0 d0"),
        (codec.make_start([0, 2], positive=[2]), "5a 30 00 00 00 45 8b"),
        (codec.make_get(Command.GET_SWITCH, 1), "5a c5 00 00 00 00 3b"),
    ],
)
def test_request_vectors(request_: codec.Request, expected: str) -> None:
    assert request_.encode().hex(" ") == expected
    # and the vector itself satisfies the formula, computed by hand
    packet = bytes.fromhex(expected)
    assert packet[6] == checksum_by_hand(*packet[1:6])


def test_reply_vector() -> None:
    # stall flag, data 0x12345678: 0x80+0x12+0x34+0x56+0x78 = 0x194 -> CS 0x6C
    packet = codec.Reply(ReplyCode.STALL, 0x1234_5678).encode()
    assert packet.hex(" ") == "80 12 34 56 78 6c"
    assert checksum_by_hand(*packet[:5]) == packet[5]


# The manual prints these example packets (GetKABH, GetVmax, GetAcc, GetStm, GetLimit).
MANUAL_EXAMPLES = [
    "5a 80 00 00 00 00 c0",
    "5a 81 00 00 00 00 c0",
    "5a 82 00 00 00 00 c0",
    "5a 88 00 00 00 00 bc",
    "5a 8c 00 00 00 00 bc",
    "5a 90 00 00 00 00 bc",
    "5a 9c 00 00 00 00 bc",
]


@pytest.mark.parametrize("example", MANUAL_EXAMPLES)
def test_the_manuals_example_checksums_are_wrong(example: str) -> None:
    """Errata: the printed checksums do not change with the command byte, so they
    cannot all satisfy the formula - none of them does. The formula wins."""
    packet = bytes.fromhex(example)
    assert packet[6] != checksum_by_hand(*packet[1:6])
    with pytest.raises(codec.CodecError, match="checksum"):
        codec.decode_request(packet)
    fixed = codec.Request(packet[1]).encode()
    assert fixed[:6] == packet[:6] and fixed[6] == checksum_by_hand(packet[1])


def test_decode_rejects_wrong_length_header_and_sum() -> None:
    with pytest.raises(codec.CodecError, match="7 bytes"):
        codec.decode_request(b"\x5a\x80\x00")
    with pytest.raises(codec.CodecError, match="starts with 0x5A"):
        codec.decode_request(bytes.fromhex("a5 80 00 00 00 00 80"))
    with pytest.raises(codec.CodecError, match="6 bytes"):
        codec.decode_reply(b"\x00" * 7)
    with pytest.raises(codec.CodecError, match="checksum"):
        codec.decode_reply(bytes.fromhex("00 00 00 00 01 00"))


@given(replies, st.integers(min_value=1, max_value=255))
def test_a_reply_with_a_corrupt_code_byte_is_rejected(reply: codec.Reply, flip: int) -> None:
    """Pinned rule: the code byte is covered by the checksum. A flipped bit
    there would turn an OK into a refusal ("forbidden while moving"), a stall or a
    checksum complaint: such a reply is no reply, for both decoders."""
    packet = bytearray(reply.encode())
    packet[0] ^= flip
    with pytest.raises(codec.CodecError, match="checksum"):
        codec.decode_reply(bytes(packet))
    decoder = codec.ReplyDecoder()
    assert decoder.feed(bytes(packet)) == []
    assert decoder.discarded == 1 and decoder.pending == 5


# --- command table -----------------------------------------------------------------


def test_get_is_set_or_0x80_for_every_pair() -> None:
    pairs = {
        Command.SET_KABH: Command.GET_KABH,
        Command.SET_KABD: Command.GET_KABD,
        Command.SET_VMAX: Command.GET_VMAX,
        Command.SET_ACC: Command.GET_ACC,
        Command.SET_STM: Command.GET_STM,
        Command.SET_HVM: Command.GET_HVM,
        Command.SET_HAC: Command.GET_HAC,
        Command.SET_LIMIT: Command.GET_LIMIT,
        Command.SET_CAB: Command.GET_CAB,
        Command.SET_JOB: Command.GET_JOB,
        Command.SET_BUSY: Command.GET_BUSY,
        Command.SET_TARGET: Command.GET_TARGET,
        Command.SET_START: Command.GET_START,
        Command.SET_STOP: Command.GET_STOP,
        Command.SET_ESTOP: Command.GET_ESTOP,
    }
    for set_, get in pairs.items():
        assert get == set_ | 0x80
        assert codec.getter_of(set_) is get
    for lone in (Command.SET_CLR, Command.SET_ZERO, Command.SET_BAUD, Command.SET_FLASH):
        assert codec.getter_of(lone) is None
    with pytest.raises(codec.CodecError, match="not a Set"):
        codec.getter_of(Command.GET_VMAX)


def test_per_axis_bytes_resolve_to_command_and_axis() -> None:
    assert codec.resolve(0x0A) == (Command.SET_VMAX, 2)
    assert codec.resolve(0xBD) == (Command.GET_ENCODER, 1)
    assert codec.resolve(0x30) == (Command.SET_START, None)
    assert codec.resolve(0x42) == (Command.SET_ZERO, 2)
    known = [b for b in range(256) if codec.resolve(b) is not None]
    per_axis = sum(1 for info in codec.COMMANDS.values() if info.per_axis)
    assert len(known) == 3 * per_axis + (len(codec.COMMANDS) - per_axis)
    # axis offset 3, offsets on whole-chip commands, holes: unknown
    for unknown in (0x03, 0x1F, 0x31, 0x3D, 0x45, 0x49, 0xB1, 0xC3, 0xC7, 0xC8, 0xFF):
        assert codec.resolve(unknown) is None, hex(unknown)


def test_get_switch_errata_byte_is_not_get_error() -> None:
    # The manual lists GetSwitch at 0xC0..0xC2 (GetError's bytes); decided: 0xC4.
    assert Command.GET_SWITCH == codec.GET_SWITCH_BYTE == 0xC4
    assert codec.resolve(0xC0) == (Command.GET_ERROR, 0)
    assert codec.resolve(0xC6) == (Command.GET_SWITCH, 2)


def test_request_knows_its_command_and_axis() -> None:
    request = codec.make_set_acc(1, 500)
    assert request.command is Command.SET_ACC and request.axis == 1
    assert codec.Request(0x03).command is None and codec.Request(0x03).axis is None
    assert codec.make_clr().axis is None


# --- builders: round trips and data layouts -------------------------------------------


@given(axes, gains, gains, gains, st.booleans())
def test_kab_round_trip(axis: int, k: int, a: int, b: int, moving: bool) -> None:
    request = codec.make_set_kab(axis, k, a, b, moving=moving)
    assert codec.decode_request(request.encode()) == request
    assert request.command is (Command.SET_KABH if moving else Command.SET_KABD)
    assert request.axis == axis
    assert request.data >> 24 == 0
    assert codec.unpack_kab(request.data) == codec.Gains(k, a, b)
    assert codec.decode_get(Command.GET_KABD, request.data) == codec.Gains(k, a, b)


@given(axes, positive32, positive32, positive32, positive32)
def test_speed_and_acceleration_round_trip(
    axis: int, vmax: int, acc: int, hvm: int, hac: int
) -> None:
    for request, command, value in (
        (codec.make_set_vmax(axis, vmax), Command.SET_VMAX, vmax),
        (codec.make_set_acc(axis, acc), Command.SET_ACC, acc),
        (codec.make_set_hvm(axis, hvm), Command.SET_HVM, hvm),
        (codec.make_set_hac(axis, hac), Command.SET_HAC, hac),
    ):
        assert codec.decode_request(request.encode()) == request
        assert (request.command, request.axis, request.data) == (command, axis, value)


@given(axes, int32)
def test_target_is_twos_complement(axis: int, target: int) -> None:
    request = codec.make_set_target(axis, target)
    assert codec.decode_request(request.encode()) == request
    assert codec.unpack_int32(request.data) == target
    assert codec.decode_get(Command.GET_TARGET, request.data) == target


@given(axes, st.integers(min_value=0, max_value=16383))
def test_limit_is_d1_d0(axis: int, limit: int) -> None:
    request = codec.make_set_limit(axis, limit)
    assert codec.decode_request(request.encode()) == request
    assert request.data >> 16 == 0  # D3 and D2 stay 0: ErrMax = D1:D0 (errata)
    assert codec.unpack_limit(request.data) == limit


@given(st.integers(min_value=-32768, max_value=32767))
def test_error_is_signed_16_bit(error: int) -> None:
    data = codec.pack_error(error)
    assert data <= 0xFFFF
    assert codec.unpack_error(data) == error
    assert codec.decode_get(Command.GET_ERROR, data) == error


def test_error_sign_examples() -> None:
    assert codec.unpack_error(0xFFFF) == -1
    assert codec.unpack_error(0x8000) == -32768
    assert codec.unpack_error(0x7FFF) == 32767
    assert codec.unpack_error(0x00FF_0005) == 5  # D3:D2 ignored


@given(axis_sets, axis_sets)
def test_start_bits_round_trip(running: frozenset[int], positive: frozenset[int]) -> None:
    request = codec.make_start(running, positive=positive)
    assert codec.decode_request(request.encode()) == request
    assert request.data & 0x88 == 0  # bits 3 and 7 unused
    assert codec.unpack_start(request.data) == codec.StartStatus(running, positive)


@given(axis_sets, axis_sets)
def test_stop_bits_round_trip(by_command: frozenset[int], stalled: frozenset[int]) -> None:
    status = codec.StopStatus(by_command, stalled)
    assert codec.unpack_stop(codec.pack_stop(status)) == status
    assert codec.decode_get(Command.GET_ESTOP, codec.pack_stop(status)) == status


def test_start_and_stop_bit_layout_per_errata() -> None:
    # bit k and bit k+4 belong to motor k+1
    assert codec.make_start([0, 2], positive=[2]).data == 0b0100_0101
    assert codec.unpack_stop(0b0010_0001) == codec.StopStatus(frozenset({0}), frozenset({1}))
    assert codec.make_stop([1]).data == 0b010
    assert codec.make_estop([0, 1, 2]).data == 0b111


@given(axes, st.sampled_from(list(codec.Cab)), st.sampled_from(list(codec.Job)), st.booleans())
def test_byte_fields_round_trip(axis: int, cab: codec.Cab, job: codec.Job, busy: bool) -> None:
    for request in (
        codec.make_set_cab(axis, cab),
        codec.make_set_job(axis, job),
        codec.make_set_busy(axis, busy),
        codec.make_set_stm(axis, 1 + axis),
        codec.make_zero(axis),
    ):
        assert codec.decode_request(request.encode()) == request
        assert request.axis == axis
    assert codec.decode_get(Command.GET_CAB, int(cab)) == cab
    assert codec.decode_get(Command.GET_JOB, int(job)) is job
    assert codec.decode_get(Command.GET_BUSY, int(busy)) is busy
    assert codec.decode_get(Command.GET_JOB, 7) == 7  # an undefined job survives


@pytest.mark.parametrize("baud", codec.BAUD_RATES)
def test_whole_chip_commands(baud: int) -> None:
    for request, command in (
        (codec.make_set_baud(baud), Command.SET_BAUD),
        (codec.make_clr(), Command.SET_CLR),
        (codec.make_flash(), Command.SET_FLASH),
        (codec.make_get(Command.GET_START), Command.GET_START),
    ):
        assert codec.decode_request(request.encode()) == request
        assert (request.command, request.axis) == (command, None)
    assert codec.make_set_baud(baud).data == baud


def test_sampling_time_units() -> None:
    assert codec.sample_time_s(1) == pytest.approx(32e-6)
    assert codec.sample_time_s(255) == pytest.approx(8.16e-3)
    assert codec.stm_for(1e-3) == 31
    with pytest.raises(codec.CodecError, match="Stm"):
        codec.stm_for(10e-3)


# --- range errors -------------------------------------------------------------------


@pytest.mark.parametrize(
    ("build", "message"),
    [
        (lambda: codec.make_set_kab(0, 256, 0, 0), "K must be between 0 and 255, got 256"),
        (lambda: codec.make_set_kab(0, 1, -1, 0), "A must be between 0 and 255, got -1"),
        (lambda: codec.make_set_kab(0, 1, 1, 300), "B must be between 0 and 255, got 300"),
        (lambda: codec.make_set_kab(3, 1, 1, 1), r"axis must be between 0 and 2 \(motor 1..3\)"),
        (lambda: codec.make_set_vmax(0, -1), r"Vmax \(counts/s\) must be between 0 and 2147483647"),
        (lambda: codec.make_set_acc(1, 2**31), r"Acc \(counts/s\^2\) must be between"),
        (lambda: codec.make_set_hvm(1, -5), "Hvm"),
        (lambda: codec.make_set_hac(1, 2**32), "Hac"),
        (lambda: codec.make_set_limit(0, 16384), "error limit must be between 0 and 16383"),
        (lambda: codec.make_set_stm(0, 0), "Stm must be between 1 and 255, got 0"),
        (lambda: codec.make_set_target(0, 2**31), "target"),
        (lambda: codec.make_set_cab(0, codec.Cab(8)), "Cab must be between 0 and 7"),
        (lambda: codec.make_set_job(0, 4), "job must be between 0 and 3"),  # type: ignore[arg-type]
        (lambda: codec.make_start([3]), "axis"),
        (lambda: codec.make_set_baud(115200), "baud must be one of 1200, 2400"),
        (lambda: codec.make_get(Command.GET_VMAX), "GetVmax needs an axis"),
        (lambda: codec.make_get(Command.GET_START, 0), "GetStart is for the whole chip"),
        (lambda: codec.make_get(Command.SET_VMAX, 0), "SetVmax is not a Get"),
        (lambda: codec.Request(256), "command byte must be between 0 and 255"),
        (lambda: codec.Reply(ReplyCode.OK, 2**32), "data must be between"),
        (lambda: codec.pack_error(40000), "position error"),
    ],
)
def test_range_errors_name_the_field_and_range(build: object, message: str) -> None:
    with pytest.raises(codec.CodecError, match=message):
        build()  # type: ignore[operator]


def test_range_errors_are_value_errors() -> None:
    with pytest.raises(ValueError):
        codec.make_set_limit(0, -1)


# --- reply codes --------------------------------------------------------------------


def test_error_messages_name_the_motor() -> None:
    assert codec.error_message(ReplyCode.MOVING_2) == "forbidden while motor 2 is moving"
    assert codec.error_message(codec.moving_flag(2)) == "forbidden while motor 3 is moving"
    both = codec.error_message(ReplyCode.CHECKSUM | ReplyCode.MOVING_1)
    assert both == "checksum wrong; forbidden while motor 1 is moving"
    assert "100 ms" in (codec.error_message(ReplyCode.TIMEOUT) or "")
    assert "unknown command" in (codec.error_message(0x02) or "")
    assert codec.error_message(ReplyCode.OK) is None
    # bit 7 is a flag, not a rejection
    assert codec.error_message(ReplyCode.STALL) is None
    assert "GetStop" in (codec.stall_message(0x80) or "")
    assert codec.stall_message(0x7F) is None


def test_reply_executed_and_stall() -> None:
    assert codec.Reply(ReplyCode.OK).executed
    stalled = codec.Reply(ReplyCode.STALL, 5)
    assert stalled.executed and stalled.stall
    refused = codec.Reply(ReplyCode.MOVING_3 | ReplyCode.STALL)
    assert not refused.executed
    assert refused.error_message() == "forbidden while motor 3 is moving"


# --- reply decoder: sliding window ------------------------------------------------------


def _chunks(data: bytes, size: int) -> list[bytes]:
    return [data[i : i + size] for i in range(0, len(data), size)]


@given(st.lists(replies, max_size=6), st.integers(min_value=1, max_value=8))
def test_reply_decoder_is_chunking_independent(items: list[codec.Reply], size: int) -> None:
    data = b"".join(r.encode() for r in items)
    decoder = codec.ReplyDecoder()
    decoded = [r for chunk in _chunks(data, size) for r in decoder.feed(chunk)]
    assert decoded == items
    assert decoder.pending == 0 and decoder.discarded == 0


@given(st.binary(min_size=1, max_size=20), st.lists(replies, min_size=1, max_size=4))
def test_reply_decoder_resynchronises_after_garbage(
    garbage: bytes, items: list[codec.Reply]
) -> None:
    data = garbage + b"".join(r.encode() for r in items)
    # Only meaningful when no window starting inside the garbage sums to 0 by chance
    # (probability 1/256 each); that ambiguity is documented and tested below.
    assume(all(sum(data[i : i + 6]) & 0xFF for i in range(len(garbage))))
    decoder = codec.ReplyDecoder()
    assert decoder.feed(data) == items
    assert decoder.discarded == len(garbage)


def test_reply_decoder_ambiguities_are_real() -> None:
    decoder = codec.ReplyDecoder()
    # six zero bytes are a valid reply: code 0, data 0
    assert decoder.feed(bytes(6)) == [codec.Reply(ReplyCode.OK, 0)]
    # a garbage byte equal to a reply's checksum makes a checksum-valid window that
    # straddles garbage and reply: a wrong reply is accepted
    real = codec.Reply(ReplyCode.OK, 0x0102_0304)
    packet = real.encode()
    wrong = codec.ReplyDecoder().feed(packet[5:6] + packet)
    assert wrong and wrong[0] != real
    # which is why the host clears the decoder before every request
    decoder.feed(b"\x13\x37")
    assert decoder.clear() == b"\x13\x37" and decoder.pending == 0


@given(st.binary(max_size=64))
def test_reply_decoder_never_raises(data: bytes) -> None:
    decoder = codec.ReplyDecoder()
    decoded = decoder.feed(data)
    assert decoder.pending < 6
    assert 6 * len(decoded) + decoder.discarded + decoder.pending == len(data)


# --- request decoder (chip side) --------------------------------------------------------


@given(
    st.binary(max_size=12).map(lambda b: b.replace(b"\x5a", b"")),
    st.lists(requests, min_size=1, max_size=4),
    st.integers(min_value=1, max_value=9),
)
def test_request_decoder_skips_garbage_between_packets(
    garbage: bytes, items: list[codec.Request], size: int
) -> None:
    data = garbage + b"".join(garbage + r.encode() for r in items)
    decoder = codec.RequestDecoder()
    decoded = [e for chunk in _chunks(data, size) for e in decoder.feed(chunk)]
    assert decoded == items
    assert decoder.pending == 0


def test_request_decoder_reports_bad_checksum_and_consumes_the_packet() -> None:
    good = codec.make_get_kab(0).encode()
    bad = good[:6] + bytes([good[6] ^ 0xFF])
    decoder = codec.RequestDecoder()
    events = decoder.feed(bad + good)
    assert events == [codec.BadRequest(bad), codec.make_get_kab(0)]


def test_request_decoder_partial_packet_and_clear() -> None:
    decoder = codec.RequestDecoder()
    assert decoder.feed(b"\x00\x5a\x80\x00") == []
    assert decoder.pending == 3
    assert decoder.clear() == b"\x5a\x80\x00"  # what the 100 ms timeout discards
    assert decoder.feed(codec.make_clr().encode()) == [codec.make_clr()]


def test_a_stray_header_byte_swallows_part_of_the_next_packet() -> None:
    """Documented behaviour of the chip: a garbage 0x5A starts a packet, so the next
    real packet is misframed: one bad-checksum event, and the real command is lost
    (its leftover byte is not a header, so it is skipped)."""
    decoder = codec.RequestDecoder()
    events = decoder.feed(b"\x5a" + codec.make_get_kab(0).encode())
    assert len(events) == 1 and isinstance(events[0], codec.BadRequest)
    assert decoder.pending == 0


# --- the fence (resynchronisation; decision in the codec) ----------------------------


def test_the_fence_byte_is_unknown_to_the_chip() -> None:
    fence = codec.make_fence()
    assert codec.resolve(fence.command_byte) is None
    assert fence.command is None and fence.axis is None
    assert codec.decode_request(fence.encode()) == fence


@pytest.mark.parametrize(
    ("code", "expected"),
    [
        (ReplyCode.UNKNOWN_COMMAND, True),
        (ReplyCode.UNKNOWN_COMMAND | ReplyCode.STALL, True),  # bit 7 rides on anything
        (ReplyCode.OK, False),
        (ReplyCode.STALL, False),
        (ReplyCode.UNKNOWN_COMMAND | ReplyCode.CHECKSUM, False),
        (ReplyCode.UNKNOWN_COMMAND | ReplyCode.MOVING_2, False),
        (ReplyCode.MOVING_1, False),
        (ReplyCode.TIMEOUT, False),
    ],
)
def test_is_fence_reply(code: ReplyCode, expected: bool) -> None:
    for data in (0, 0x12345678):
        assert codec.is_fence_reply(codec.Reply(code, data)) is expected


def test_no_reply_to_a_known_request_looks_like_a_fence_reply() -> None:
    """What a chip can answer to a known command never carries bit 1 alone: the codes
    a known request earns are OK, its rejections 0, 2, 3, 4..6 and the stall bit."""
    possible = [ReplyCode.OK, ReplyCode.CHECKSUM, ReplyCode.TIMEOUT, ReplyCode.COMMUNICATION]
    possible += [codec.moving_flag(axis) for axis in range(codec.AXES)]
    for code in possible:
        for stall in (ReplyCode.OK, ReplyCode.STALL):
            assert not codec.is_fence_reply(codec.Reply(code | stall))
