"""SLAP2 codec: replies, numbers, status words, unit conversions (manual examples)."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from servotune.devices.slap2 import codec

positions = st.integers(min_value=-codec.POSITION_LIMIT, max_value=codec.POSITION_LIMIT)


@given(positions, st.booleans())
def test_numbers_round_trip_in_decimal_and_hex(value: int, hex_mode: bool) -> None:
    text = codec.format_int(value, hex_mode=hex_mode)
    assert codec.parse_int(text) == value
    reply = codec.parse_reply(text)
    assert reply.kind is codec.ReplyKind.NUMBER
    assert reply.value == value


def test_hex_reply_forms() -> None:
    assert codec.parse_int("0x3E8") == 1000
    assert codec.parse_int("0x3e8") == 1000
    assert codec.parse_int("-0x3E8") == -1000
    # 32-bit two's complement, in case a firmware prints negatives that way.
    assert codec.parse_int("0xFFFFFC18") == -1000


@pytest.mark.parametrize("text", ["", "abc", "0x", "12a", "--5", "0xZZ"])
def test_garbage_is_not_a_number(text: str) -> None:
    with pytest.raises(codec.CodecError):
        codec.parse_int(text)


def test_reply_kinds() -> None:
    assert codec.parse_reply("").kind is codec.ReplyKind.EMPTY
    assert codec.parse_reply("-1UC").kind is codec.ReplyKind.REFUSED
    assert codec.parse_reply(" 42 ").value == 42
    text = codec.parse_reply("SLAP2 SW2205 HW2209 SN1234")
    assert text.kind is codec.ReplyKind.TEXT
    assert text.text.startswith("SLAP2")


@given(st.integers(min_value=0, max_value=511))
def test_rss_bits_round_trip(value: int) -> None:
    flags = codec.decode_rss(value)
    assert codec.encode_bits(flags, codec.RssBit) == value


def test_rss_bit_meaning_matches_manual() -> None:
    flags = codec.decode_rss(0b1_0010_1000)  # pm, inpos, uc
    assert flags["pm"] and flags["inpos"] and flags["uc"]
    assert not flags["move"] and not flags["oc"] and not flags["vm"]
    assert codec.decode_ss(1 << 5)["deccel"]
    assert codec.decode_syscon(1 << 5)["ucon"]
    assert codec.decode_syscon(1 << 4)["hex"]


def test_manual_unit_examples() -> None:
    # Manual, sv: 512 lines, 2500 rpm -> 9115.7 -> 9116.
    assert codec.rpm_to_sv(2500, 512) == 9116
    assert codec.sv_to_rpm(9116, 512) == pytest.approx(2500, abs=0.1)
    # Manual, sa: 512 lines, 5000 rpm/min -> 71.21 -> 71.
    assert codec.rpm_per_min_to_sa(5000, 512) == 71
    # Manual, sipt: 50 -> ~42 ms, 100 -> ~84 ms.
    assert codec.ticks_to_ms(50) == pytest.approx(42.075)
    assert codec.ms_to_ticks(84) == 100


@given(st.binary(max_size=200))
def test_line_decoder_never_raises_and_keeps_printables(data: bytes) -> None:
    decoder = codec.LineDecoder()
    lines = decoder.feed(data)
    assert len(lines) == data.count(b"\r")
    for line in lines:
        assert all(31 < ord(c) < 127 for c in line)


@given(
    st.lists(st.text(alphabet="0123456789abcdefx -", max_size=12), max_size=5), st.integers(1, 7)
)
def test_line_decoder_is_chunking_independent(lines: list[str], chunk: int) -> None:
    data = "".join(f"{line}\r\n" for line in lines).encode()
    whole = codec.LineDecoder().feed(data)
    decoder = codec.LineDecoder()
    pieces: list[str] = []
    for start in range(0, len(data), chunk):
        pieces.extend(decoder.feed(data[start : start + chunk]))
    assert pieces == whole == lines


def test_builders_check_ranges_and_format_without_spaces() -> None:
    assert [c.text for c in codec.make_set_gains(40, 40, 80)] == ["kp40", "ki40", "kd80"]
    assert codec.make_move_absolute(-10000).text == "ma-10000"
    assert codec.make_pwm(-255).text == "spwm-255"
    with pytest.raises(codec.CodecError, match="kp must be between 0 and 32767"):
        codec.make_set_gains(40000, 0, 0)
    with pytest.raises(codec.CodecError, match="pwm"):
        codec.make_pwm(256)
    with pytest.raises(codec.CodecError, match="mode"):
        codec.make_calibrate(6)


def test_console_lines_are_normalised() -> None:
    assert codec.normalise_line(" sv 1000 ") == "sv1000"
    with pytest.raises(codec.CodecError):
        codec.normalise_line("   ")
    with pytest.raises(codec.CodecError):
        codec.normalise_line("rp\x18")
