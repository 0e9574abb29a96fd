"""EP7047-1032 process image and CoE codec: byte-exact against the spec's PDO tables."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from servotune.devices.ep7047 import codec
from servotune.devices.ep7047.codec import (
    CodecError,
    DataType,
    DriveState,
    EncControl,
    EncStatus,
    Inputs,
    Outputs,
    PosControl,
    PosStatus,
    StartType,
    StmControl,
    StmStatus,
)

# --- outputs ------------------------------------------------------------------------------


def test_outputs_layout_matches_spec_table() -> None:
    outputs = Outputs(
        enc_control=EncControl.SET_COUNTER,
        set_counter_counts=-2,
        stm_control=StmControl.ENABLE | StmControl.DIGITAL_OUTPUT_1,
        pos_control=PosControl.EXECUTE | PosControl.EMERGENCY_STOP,
        target_position_counts=200000,
        velocity_bp=-1500,
        start_type=StartType.ABSOLUTE_CHANGE,
        acceleration_ms=1000,
        deceleration_ms=2000,
    )
    expected = bytes.fromhex(
        "0400"  # 0-1 ENC control: 0x7000:03 Set counter = bit 2
        "feffffff"  # 2-5 0x7000:11 set counter value -2
        "0108"  # 6-7 STM control: bit 0 Enable, bit 11 digital output 1
        "0300"  # 8-9 POS control: bit 0 Execute, bit 1 Emergency stop
        "400d0300"  # 10-13 target 200000 = 0x00030D40
        "24fa"  # 14-15 velocity -1500 (INT16)
        "0110"  # 16-17 start type 0x1001
        "e803"  # 18-19 acceleration 1000
        "d007"  # 20-21 deceleration 2000
    )
    assert codec.encode_outputs(outputs) == expected
    assert codec.decode_outputs(expected) == outputs
    assert len(expected) == codec.OUTPUTS_SIZE == 22


def test_manual_first_command_bytes() -> None:
    """The manual's t1: Execute, target 200000, velocity 2000, ABSOLUTE, acc/dec 1000."""
    outputs = Outputs(
        stm_control=StmControl.ENABLE,
        pos_control=PosControl.EXECUTE,
        target_position_counts=200000,
        velocity_bp=2000,
        start_type=StartType.ABSOLUTE,
        acceleration_ms=1000,
        deceleration_ms=1000,
    )
    data = codec.encode_outputs(outputs)
    assert data[8:10] == b"\x01\x00"
    assert data[10:14] == (200000).to_bytes(4, "little")
    assert data[14:16] == b"\xd0\x07"
    assert data[16:18] == b"\x01\x00"
    assert data[18:22] == b"\xe8\x03\xe8\x03"


def test_unknown_start_type_survives_decoding_as_a_number() -> None:
    data = bytearray(22)
    data[16:18] = (0x0007).to_bytes(2, "little")
    outputs = codec.decode_outputs(bytes(data))
    assert outputs.start_type == 7
    assert not isinstance(outputs.start_type, StartType)
    known = codec.decode_outputs(bytes(16) + b"\x05\x04" + bytes(4))
    assert known.start_type is StartType.MODULO_CURRENT


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("target_position_counts", 1 << 31),
        ("target_position_counts", -(1 << 31) - 1),
        ("velocity_bp", 32768),
        ("start_type", 0x10000),
        ("acceleration_ms", -1),
        ("deceleration_ms", 65536),
        ("set_counter_counts", 1 << 32),
    ],
)
def test_encode_outputs_refuses_values_that_do_not_fit(field: str, value: int) -> None:
    with pytest.raises(CodecError, match="must be between"):
        codec.encode_outputs(Outputs(**{field: value}))


@pytest.mark.parametrize("size", [0, 21, 23])
def test_decode_refuses_wrong_lengths(size: int) -> None:
    with pytest.raises(CodecError, match="22 bytes"):
        codec.decode_outputs(bytes(size))
    with pytest.raises(CodecError, match="24 bytes"):
        codec.decode_inputs(bytes(size + 2))


# --- inputs -------------------------------------------------------------------------------


def test_inputs_layout_matches_spec_table() -> None:
    data = bytes.fromhex(
        "0084"  # 0-1 ENC status: bit 10 input C, bit 15 TxPDO toggle
        "a0860100"  # 2-5 counter 100000
        "9cffffff"  # 6-9 latch -100
        "1308"  # 10-11 STM: ready to enable, ready, moving positive, digital input 1
        "a3"  # 12 POS: busy, in-target, accelerate, ready to execute
        "00"  # 13 (gap)
        "50e1fbff"  # 14-17 actual position -270000 (0xFFFBE150)
        "c0e0"  # 18-19 actual velocity -8000 (0xE0C0)
        "e8030000"  # 20-23 actual drive time 1000 ms
    )
    inputs = codec.decode_inputs(data)
    assert inputs.enc_status == EncStatus.INPUT_C | EncStatus.TXPDO_TOGGLE
    assert inputs.counter_counts == 100000
    assert inputs.latch_counts == -100
    assert inputs.stm_status == (
        StmStatus.READY_TO_ENABLE
        | StmStatus.READY
        | StmStatus.MOVING_POSITIVE
        | StmStatus.DIGITAL_INPUT_1
    )
    assert inputs.pos_status == (
        PosStatus.BUSY | PosStatus.IN_TARGET | PosStatus.ACCELERATE | PosStatus.READY_TO_EXECUTE
    )
    assert inputs.busy and inputs.in_target and not inputs.warning and not inputs.error
    assert inputs.actual_position_counts == -270000  # two's complement, not 0xFFFBE150
    assert inputs.actual_velocity_bp == -8000
    assert inputs.actual_drive_time_ms == 1000
    assert codec.encode_inputs(inputs) == data
    assert len(data) == codec.INPUTS_SIZE == 24


@pytest.mark.parametrize(
    ("flag", "byte_offset", "bit"),
    [
        (PosStatus.BUSY, 12, 0),
        (PosStatus.IN_TARGET, 12, 1),
        (PosStatus.WARNING, 12, 2),
        (PosStatus.ERROR, 12, 3),
        (PosStatus.CALIBRATED, 12, 4),
        (PosStatus.ACCELERATE, 12, 5),
        (PosStatus.DECELERATE, 12, 6),
        (PosStatus.READY_TO_EXECUTE, 12, 7),
    ],
)
def test_each_pos_status_bit_is_where_the_spec_puts_it(
    flag: PosStatus, byte_offset: int, bit: int
) -> None:
    data = codec.encode_inputs(Inputs(pos_status=flag))
    expected = bytearray(24)
    expected[byte_offset] = 1 << bit
    assert data == bytes(expected)


@pytest.mark.parametrize(
    ("flag", "bit"),
    [
        (StmStatus.MOTOR_STALL, 7),
        (StmStatus.DIGITAL_INPUT_1, 11),
        (StmStatus.DIGITAL_INPUT_2, 12),
        (StmStatus.SYNC_ERROR, 13),
        (StmStatus.TXPDO_TOGGLE, 15),
    ],
)
def test_stm_status_bits(flag: StmStatus, bit: int) -> None:
    data = codec.encode_inputs(Inputs(stm_status=flag))
    assert int.from_bytes(data[10:12], "little") == 1 << bit


def test_control_bits_positions() -> None:
    assert int(StmControl.ENABLE) == 1 and int(StmControl.RESET) == 2
    assert int(StmControl.REDUCE_TORQUE) == 4 and int(StmControl.DIGITAL_OUTPUT_1) == 1 << 11
    assert int(PosControl.EXECUTE) == 1 and int(PosControl.EMERGENCY_STOP) == 2


# --- round trips ---------------------------------------------------------------------------

int32 = st.integers(codec.INT32_MIN, codec.INT32_MAX)
uint16 = st.integers(0, codec.UINT16_MAX)

outputs_strategy = st.builds(
    Outputs,
    enc_control=uint16.map(EncControl),
    set_counter_counts=int32,
    stm_control=uint16.map(StmControl),
    pos_control=uint16.map(PosControl),
    target_position_counts=int32,
    velocity_bp=st.integers(codec.INT16_MIN, codec.INT16_MAX),
    start_type=st.one_of(st.sampled_from(StartType), uint16.map(codec.start_type_of)),
    acceleration_ms=uint16,
    deceleration_ms=uint16,
)
inputs_strategy = st.builds(
    Inputs,
    enc_status=uint16.map(EncStatus),
    counter_counts=int32,
    latch_counts=int32,
    stm_status=uint16.map(StmStatus),
    pos_status=uint16.map(PosStatus),
    actual_position_counts=int32,
    actual_velocity_bp=st.integers(codec.INT16_MIN, codec.INT16_MAX),
    actual_drive_time_ms=st.integers(0, codec.UINT32_MAX),
)


@given(outputs_strategy)
def test_outputs_round_trip(outputs: Outputs) -> None:
    data = codec.encode_outputs(outputs)
    assert len(data) == 22
    assert codec.decode_outputs(data) == outputs


@given(inputs_strategy)
def test_inputs_round_trip(inputs: Inputs) -> None:
    data = codec.encode_inputs(inputs)
    assert len(data) == 24
    assert codec.decode_inputs(data) == inputs


@given(st.binary(min_size=22, max_size=22))
def test_any_22_bytes_decode_and_encode_back_unchanged(data: bytes) -> None:
    assert codec.encode_outputs(codec.decode_outputs(data)) == data


@given(st.binary(min_size=24, max_size=24))
def test_any_24_bytes_decode_and_encode_back_unchanged(data: bytes) -> None:
    assert codec.encode_inputs(codec.decode_inputs(data)) == data


@given(st.integers(-(1 << 40), 1 << 40))
def test_wrap_int32_is_what_a_32_bit_counter_shows(value: int) -> None:
    wrapped = codec.wrap_int32(value)
    assert codec.INT32_MIN <= wrapped <= codec.INT32_MAX
    assert (wrapped - value) % (1 << 32) == 0


# --- CoE ------------------------------------------------------------------------------------


def test_identity() -> None:
    assert codec.VENDOR_ID == 0x2
    assert codec.PRODUCT_CODE == 0x1B874052
    assert codec.RXPDO_ASSIGNMENT == (0x1601, 0x1602, 0x1606)
    assert codec.TXPDO_ASSIGNMENT == (0x1A01, 0x1A03, 0x1A07)


def test_sdo_addresses_named_by_the_manual() -> None:
    assert (codec.CALIBRATION_POSITION.index, codec.CALIBRATION_POSITION.subindex) == (
        0x8020,
        0x08,
    )
    assert codec.CALIBRATION_VELOCITY_TOWARDS_CAM.subindex == 0x09
    assert codec.CALIBRATION_VELOCITY_OFF_CAM.subindex == 0x0A
    assert codec.IN_TARGET_TIMEOUT.subindex == 0x0C
    assert codec.MODULO_FACTOR.subindex == 0x0E
    assert codec.MODULO_TOLERANCE_WINDOW.subindex == 0x0F
    assert (codec.DEFAULT_START_TYPE.index, codec.DEFAULT_START_TYPE.subindex) == (0x8021, 1)
    assert codec.INVERT_CALIBRATION_CAM_SEARCH.subindex == 0x13
    assert codec.INVERT_SYNC_IMPULSE_SEARCH.subindex == 0x14
    assert (codec.DRIVE_STATE.index, codec.DRIVE_STATE.subindex) == (0x9020, 0x03)
    assert [d.subindex for d in (codec.DIAG_COMMAND_REJECTED, codec.DIAG_COMMAND_ABORTED)] == [
        1,
        2,
    ]
    assert codec.DIAG_TARGET_OVERRUN.subindex == 3


def test_sdo_table_has_no_duplicate_addresses() -> None:
    addresses = [(o.index, o.subindex) for o in codec.SDO_OBJECTS]
    assert len(addresses) == len(set(addresses))
    assert all(o.index in (0x8020, 0x8021) for o in codec.POS_SETTINGS_SDO.values())
    assert not any(o.writable for o in codec.SDO_OBJECTS if o.index in (0x9020, 0xA020, 0x1018))


def test_sdo_values_encode_little_endian_and_check_range() -> None:
    assert codec.encode_sdo(codec.MODULO_FACTOR, 3600) == b"\x10\x0e\x00\x00"
    assert codec.encode_sdo(codec.CALIBRATION_POSITION, -1) == b"\xff\xff\xff\xff"
    assert codec.encode_sdo(codec.INVERT_SYNC_IMPULSE_SEARCH, 1) == b"\x01"
    assert codec.decode_sdo(codec.VELOCITY_MIN, b"\x9c\xff") == -100
    with pytest.raises(CodecError):
        codec.encode_sdo(codec.TARGET_WINDOW, 70000)
    with pytest.raises(CodecError):
        codec.encode_sdo(codec.INVERT_CALIBRATION_CAM_SEARCH, 2)
    with pytest.raises(CodecError):
        codec.decode_sdo(codec.MODULO_FACTOR, b"\x00\x00")


@given(st.sampled_from(codec.SDO_OBJECTS), st.data())
def test_sdo_round_trip(obj: codec.SdoObject, data: st.DataObject) -> None:
    value = data.draw(st.integers(obj.data_type.minimum, obj.data_type.maximum))
    payload = codec.encode_sdo(obj, value)
    assert len(payload) == obj.data_type.size
    assert codec.decode_sdo(obj, payload) == value


def test_settings_writes_cover_every_setting_in_range() -> None:
    settings = codec.PosSettings(modulo_factor_counts=3600, invert_sync_impulse_search=True)
    writes = dict(codec.settings_writes(settings))
    assert writes[codec.MODULO_FACTOR] == 3600
    assert writes[codec.INVERT_SYNC_IMPULSE_SEARCH] == 1
    assert writes[codec.DEFAULT_START_TYPE] == StartType.ABSOLUTE
    assert len(writes) == 19
    with pytest.raises(CodecError, match="Target window"):
        codec.settings_writes(codec.PosSettings(target_window_counts=-1))


def test_state_ids_are_the_manuals() -> None:
    assert DriveState.PRE_TARGET == 0x1000
    assert DriveState.CALI_LEAVE_CAM == 0x0121
    assert DriveState.UNDEFINED == 0xFFFF
    assert DataType.BIT2.maximum == 3


# --- fast paths (the cycle thread and the simulator call these every frame) ---------------

_MEMOISED = [
    (codec.enc_control_of, EncControl),
    (codec.stm_control_of, StmControl),
    (codec.pos_control_of, PosControl),
    (codec.enc_status_of, EncStatus),
    (codec.stm_status_of, StmStatus),
    (codec.pos_status_of, PosStatus),
]


@pytest.mark.parametrize(("memoised", "flag"), _MEMOISED, ids=[f.__name__ for _, f in _MEMOISED])
def test_memoised_flag_words_are_the_plain_members(
    memoised: object, flag: type[EncControl]
) -> None:
    """Every combination of the low 10 bits, every single bit and all 16 (the exhaustive
    run over 65536 values takes seconds per type)."""
    of = memoised
    assert callable(of)
    values = [*range(1 << 10), *(1 << bit for bit in range(16)), codec.UINT16_MAX]
    for value in values:
        member = of(value)
        plain = flag(value)
        assert type(member) is flag
        assert member == plain == value
        assert member.name == plain.name
        assert of(value) is member  # the second call is the cached member


def test_memoised_start_type_is_the_plain_lookup_for_every_code() -> None:
    for code in [*range(codec.UINT16_MAX + 1), codec.UINT16_MAX + 1]:
        try:
            expected: StartType | int = StartType(code)
        except ValueError:
            expected = code
        found = codec.start_type_of(code)
        assert found == expected
        assert type(found) is type(expected)


@given(uint16)
def test_status_and_control_properties_are_the_flag_tests(value: int) -> None:
    inputs = Inputs(pos_status=PosStatus(value))
    assert inputs.busy is bool(PosStatus(value) & PosStatus.BUSY)
    assert inputs.in_target is bool(PosStatus(value) & PosStatus.IN_TARGET)
    assert inputs.warning is bool(PosStatus(value) & PosStatus.WARNING)
    assert inputs.error is bool(PosStatus(value) & PosStatus.ERROR)
    outputs = Outputs(stm_control=StmControl(value), pos_control=PosControl(value))
    assert outputs.enable is bool(StmControl(value) & StmControl.ENABLE)
    assert outputs.execute is bool(PosControl(value) & PosControl.EXECUTE)
    assert outputs.emergency_stop is bool(PosControl(value) & PosControl.EMERGENCY_STOP)


_OUTPUT_RANGES = {
    "enc_control": (0, codec.UINT16_MAX),
    "set_counter_counts": (codec.INT32_MIN, codec.INT32_MAX),
    "stm_control": (0, codec.UINT16_MAX),
    "pos_control": (0, codec.UINT16_MAX),
    "target_position_counts": (codec.INT32_MIN, codec.INT32_MAX),
    "velocity_bp": (codec.INT16_MIN, codec.INT16_MAX),
    "start_type": (0, codec.UINT16_MAX),
    "acceleration_ms": (0, codec.UINT16_MAX),
    "deceleration_ms": (0, codec.UINT16_MAX),
}
_INPUT_RANGES = {
    "enc_status": (0, codec.UINT16_MAX),
    "counter_counts": (codec.INT32_MIN, codec.INT32_MAX),
    "latch_counts": (codec.INT32_MIN, codec.INT32_MAX),
    "stm_status": (0, codec.UINT16_MAX),
    "pos_status": (0, codec.UINT16_MAX),
    "actual_position_counts": (codec.INT32_MIN, codec.INT32_MAX),
    "actual_velocity_bp": (codec.INT16_MIN, codec.INT16_MAX),
    "actual_drive_time_ms": (0, codec.UINT32_MAX),
}


@given(st.sampled_from(sorted(_OUTPUT_RANGES)), st.integers(-(1 << 33), 1 << 33))
def test_encode_outputs_packs_exactly_the_values_in_range(field: str, value: int) -> None:
    """Packing first must accept and refuse exactly what the field checks do."""
    minimum, maximum = _OUTPUT_RANGES[field]
    outputs = Outputs(**{field: value})
    if minimum <= value <= maximum:
        assert codec.decode_outputs(codec.encode_outputs(outputs)) == outputs
    else:
        with pytest.raises(CodecError, match="must be between"):
            codec.encode_outputs(outputs)


@given(st.sampled_from(sorted(_INPUT_RANGES)), st.integers(-(1 << 33), 1 << 33))
def test_encode_inputs_packs_exactly_the_values_in_range(field: str, value: int) -> None:
    minimum, maximum = _INPUT_RANGES[field]
    inputs = Inputs(**{field: value})
    if minimum <= value <= maximum:
        assert codec.decode_inputs(codec.encode_inputs(inputs)) == inputs
    else:
        with pytest.raises(CodecError, match="must be between"):
            codec.encode_inputs(inputs)


def test_a_field_that_is_not_an_integer_is_a_codec_error() -> None:
    with pytest.raises(CodecError, match="do not fit"):
        codec.encode_outputs(Outputs(target_position_counts=1.5))  # type: ignore[arg-type]
    with pytest.raises(CodecError, match="do not fit"):
        codec.encode_inputs(Inputs(actual_velocity_bp=2.5))  # type: ignore[arg-type]
