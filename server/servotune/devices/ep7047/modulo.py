"""The EP7047's modulo positioning rule, shared by the simulator and the driver.

``modulo_travel`` is the arithmetic of a modulo start (MODULO_SHORT/PLUS/MINUS/CURRENT
and their _EXT forms, manual "Positioning interface"): how far and in which direction
the drive moves. The simulator (devices/ep7047/sim/positioning.py) moves by it and the driver
(devices/ep7047/handshakes.py) previews a start with it, so both live on one rule; it
sits beside the codec because it is the device's law, not either side's code.
"""

from __future__ import annotations

from servotune.devices.ep7047.codec import StartType


class ModuloError(ValueError):
    """A modulo start the drive refuses with Error."""


def modulo_travel(
    start_type: StartType,
    start_counts: int,
    target_counts: int,
    modulo_factor_counts: int,
    window_counts: int,
    last_direction: int,
) -> tuple[int, int]:
    """Relative travel of a modulo move, and the direction it was ordered in (+1/-1).

    ``target_counts`` is a modulo position; each whole ``modulo_factor_counts`` in it
    adds a revolution in PLUS/MINUS/CURRENT. A target equal to the current modulo
    position does not move. Non-_EXT types treat a start within ``window_counts`` past
    the target (in the ordered direction) as standing on it, so they move back by that
    little instead of a whole extra turn; _EXT types ignore the window. CURRENT uses
    ``last_direction``. Raises :class:`ModuloError` for a modulo factor <= 0, a negative
    target, or a SHORT target outside [0, modulo factor).

    Decisions (manual silent): the window is closed (a start exactly ``window`` past the
    target is inside); SHORT picks the positive direction on an exact half turn; SHORT
    and SHORT_EXT behave alike, because the shortest way never costs a whole turn.
    """
    m = modulo_factor_counts
    if m <= 0:
        raise ModuloError("modulo factor (0x8020:0E) is not set")
    if target_counts < 0:
        raise ModuloError(f"modulo target {target_counts} is negative")
    revolutions, target_mod = divmod(target_counts, m)
    start_mod = start_counts % m
    base = start_type & ~0x0010  # the _EXT bit
    window = 0 if start_type & 0x0010 else window_counts
    if base == StartType.MODULO_SHORT:
        if revolutions:
            raise ModuloError(f"MODULO_SHORT target {target_counts} is not below {m}")
        ahead = (target_mod - start_mod) % m
        if ahead == 0:
            return 0, last_direction
        return (ahead, 1) if ahead <= m - ahead else (ahead - m, -1)
    if base == StartType.MODULO_PLUS:
        direction = 1
    elif base == StartType.MODULO_MINUS:
        direction = -1
    else:
        direction = last_direction
    # distance still to go in the ordered direction, within one turn
    to_go = ((target_mod - start_mod) * direction) % m
    if to_go and m - to_go <= window:
        to_go -= m  # just past the target: step back instead of a whole turn
    return direction * (to_go + revolutions * m), direction


__all__ = ["ModuloError", "modulo_travel"]
