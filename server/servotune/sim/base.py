"""The contract between a simulated serial device and whatever carries its bytes.

A simulated device is a sans-IO state machine driven by *simulation time*: it never
reads a clock, sleeps or touches a file descriptor. The carrier (``PtySimulator`` for a
real pseudo-terminal, or a test that feeds bytes directly) decides when each byte has
arrived and when the bytes the device transmits leave the wire. Given the same
sequence of ``advance_to`` / ``receive`` calls a device must produce the same output.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable


@runtime_checkable
class SimDevice(Protocol):
    """A simulated device on one serial line (one or several modules behind it)."""

    def advance_to(self, t_s: float) -> bytes:
        """Run firmware and physics up to absolute simulation time ``t_s`` (seconds).

        Returns bytes the device transmits on its own during that interval (for example
        a power-on banner), in transmission order. A ``t_s`` earlier than the time
        already reached is ignored: time never runs backwards.
        """
        ...

    def receive(self, byte: int) -> bytes:
        """One host byte (0..255) has completely arrived at the current simulation time.

        Returns every byte the device transmits in response (echo, reply, or nothing),
        in transmission order. The carrier is responsible for the time those bytes take
        on the wire.
        """
        ...


@runtime_checkable
class PowerCyclable(Protocol):
    """A device whose supply can be switched off and on again (optional capability)."""

    def power_cycle(self, address: int | None = None) -> None:
        """Reset one module (``address``) or the whole line (``None``) as at power-on."""
        ...
