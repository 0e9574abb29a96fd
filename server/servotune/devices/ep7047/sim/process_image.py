"""The simulated EP7047-1032's process image: mapped objects <-> the engine's model.

Independence from the driver's codec: the process image's layout and every CoE
address come from ``devices.ep7047.sim.coe``; the engine's model types (``Inputs``,
``Outputs``, ``PosSettings`` and the flag enums of ``servotune.devices.ep7047.codec``)
are used here only by *name* to translate between mapped objects and the engine
(0x6020:01 is the engine's ``Busy``). Where each object sits on the wire is decided by
the simulator (``coe`` and here), so a wrong bit, offset or size in the codec shows as a
wrong value in the driver. ``devices.ep7047.sim.wire.WireSlave`` packs and unpacks these values.
"""

from __future__ import annotations

from typing import Final

from servotune.devices.ep7047.codec import (
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

# Engine fields by the objects that carry them (names: the engine's model).
OUT_BITS: Final = (
    ((0x7000, 0x01), "enc", EncControl.ENABLE_LATCH_C),
    ((0x7000, 0x02), "enc", EncControl.ENABLE_LATCH_EXTERN_POSITIVE),
    ((0x7000, 0x03), "enc", EncControl.SET_COUNTER),
    ((0x7000, 0x04), "enc", EncControl.ENABLE_LATCH_EXTERN_NEGATIVE),
    ((0x7010, 0x01), "stm", StmControl.ENABLE),
    ((0x7010, 0x02), "stm", StmControl.RESET),
    ((0x7010, 0x03), "stm", StmControl.REDUCE_TORQUE),
    ((0x7010, 0x0C), "stm", StmControl.DIGITAL_OUTPUT_1),
    ((0x7020, 0x01), "pos", PosControl.EXECUTE),
    ((0x7020, 0x02), "pos", PosControl.EMERGENCY_STOP),
)
IN_BITS: Final = (
    ((0x6000, 0x01), "enc", EncStatus.LATCH_C_VALID),
    ((0x6000, 0x02), "enc", EncStatus.LATCH_EXTERN_VALID),
    ((0x6000, 0x03), "enc", EncStatus.SET_COUNTER_DONE),
    ((0x6000, 0x04), "enc", EncStatus.COUNTER_UNDERFLOW),
    ((0x6000, 0x05), "enc", EncStatus.COUNTER_OVERFLOW),
    ((0x6000, 0x08), "enc", EncStatus.EXTRAPOLATION_STALL),
    ((0x6000, 0x09), "enc", EncStatus.INPUT_A),
    ((0x6000, 0x0A), "enc", EncStatus.INPUT_B),
    ((0x6000, 0x0B), "enc", EncStatus.INPUT_C),
    ((0x6000, 0x0D), "enc", EncStatus.EXTERN_LATCH),
    ((0x6000, 0x0E), "enc", EncStatus.SYNC_ERROR),
    ((0x6000, 0x10), "enc", EncStatus.TXPDO_TOGGLE),
    ((0x6010, 0x01), "stm", StmStatus.READY_TO_ENABLE),
    ((0x6010, 0x02), "stm", StmStatus.READY),
    ((0x6010, 0x03), "stm", StmStatus.WARNING),
    ((0x6010, 0x04), "stm", StmStatus.ERROR),
    ((0x6010, 0x05), "stm", StmStatus.MOVING_POSITIVE),
    ((0x6010, 0x06), "stm", StmStatus.MOVING_NEGATIVE),
    ((0x6010, 0x07), "stm", StmStatus.TORQUE_REDUCED),
    ((0x6010, 0x08), "stm", StmStatus.MOTOR_STALL),
    ((0x6010, 0x0C), "stm", StmStatus.DIGITAL_INPUT_1),
    ((0x6010, 0x0D), "stm", StmStatus.DIGITAL_INPUT_2),
    ((0x6010, 0x0E), "stm", StmStatus.SYNC_ERROR),
    ((0x6010, 0x10), "stm", StmStatus.TXPDO_TOGGLE),
    ((0x6020, 0x01), "pos", PosStatus.BUSY),
    ((0x6020, 0x02), "pos", PosStatus.IN_TARGET),
    ((0x6020, 0x03), "pos", PosStatus.WARNING),
    ((0x6020, 0x04), "pos", PosStatus.ERROR),
    ((0x6020, 0x05), "pos", PosStatus.CALIBRATED),
    ((0x6020, 0x06), "pos", PosStatus.ACCELERATE),
    ((0x6020, 0x07), "pos", PosStatus.DECELERATE),
    ((0x6020, 0x08), "pos", PosStatus.READY_TO_EXECUTE),
)
IN_BITS_INT: Final = tuple((key, word, int(bit)) for key, word, bit in IN_BITS)
VALID_START_TYPES: Final = frozenset(int(s) for s in StartType)


def outputs_from(values: dict[tuple[int, int], int]) -> Outputs:
    """The engine's outputs from the values of the mapped RxPDO objects (absent: 0)."""
    words = {"enc": 0, "stm": 0, "pos": 0}
    for key, word, bit in OUT_BITS:
        if values.get(key):
            words[word] |= int(bit)
    start = values.get((0x7020, 0x22), 0)
    return Outputs(
        enc_control=EncControl(words["enc"]),
        set_counter_counts=values.get((0x7000, 0x11), 0),
        stm_control=StmControl(words["stm"]),
        pos_control=PosControl(words["pos"]),
        target_position_counts=values.get((0x7020, 0x11), 0),
        velocity_bp=values.get((0x7020, 0x21), 0),
        start_type=StartType(start) if start in VALID_START_TYPES else start,
        acceleration_ms=values.get((0x7020, 0x23), 0),
        deceleration_ms=values.get((0x7020, 0x24), 0),
    )


def output_values(outputs: Outputs) -> dict[tuple[int, int], int]:
    """The values of the RxPDO objects that carry the engine's ``outputs``."""
    words = {
        "enc": int(outputs.enc_control),
        "stm": int(outputs.stm_control),
        "pos": int(outputs.pos_control),
    }
    values = {key: int(bool(words[word] & int(bit))) for key, word, bit in OUT_BITS}
    values[0x7000, 0x11] = outputs.set_counter_counts
    values[0x7020, 0x11] = outputs.target_position_counts
    values[0x7020, 0x21] = outputs.velocity_bp
    values[0x7020, 0x22] = int(outputs.start_type)
    values[0x7020, 0x23] = outputs.acceleration_ms
    values[0x7020, 0x24] = outputs.deceleration_ms
    return values


def input_values(inputs: Inputs) -> dict[tuple[int, int], int]:
    """The values of the TxPDO objects that carry the engine's ``inputs``."""
    words = {
        "enc": int(inputs.enc_status),
        "stm": int(inputs.stm_status),
        "pos": int(inputs.pos_status),
    }
    values = {key: 1 if words[word] & bit else 0 for key, word, bit in IN_BITS_INT}
    values[0x6000, 0x11] = inputs.counter_counts
    values[0x6000, 0x12] = inputs.latch_counts
    values[0x6020, 0x11] = inputs.actual_position_counts
    values[0x6020, 0x21] = inputs.actual_velocity_bp
    values[0x6020, 0x22] = inputs.actual_drive_time_ms
    return values
