"""The EtherCAT transport: the master and slave protocols the EP7047-1032 driver uses
(pysoem's names), their errors, the state-machine values and the pysoem adapter.

This is the EtherCAT counterpart of ``transports/base.py``'s byte channel: the driver
(``servotune.devices.ep7047.link``, which re-exports every public name here) talks to a
master through it, and the simulators (``servotune.devices.ep7047.sim.slave``,
``devices.ep7047.sim.process``) implement it, so they import this module and no driver code.
pysoem is imported lazily, only for real hardware.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Final, Protocol, runtime_checkable

# --- EtherCAT state machine values (the same numbers as pysoem's constants) ---------------

NONE_STATE: Final = 0x00
INIT_STATE: Final = 0x01
PREOP_STATE: Final = 0x02
BOOT_STATE: Final = 0x03
SAFEOP_STATE: Final = 0x04
OP_STATE: Final = 0x08
STATE_ACK: Final = 0x10  # written: acknowledge an error indication
STATE_ERROR: Final = 0x10  # read: the slave has an error indication (see AL status)

_STATE_NAMES = {
    NONE_STATE: "NONE",
    INIT_STATE: "INIT",
    PREOP_STATE: "PRE-OP",
    BOOT_STATE: "BOOT",
    SAFEOP_STATE: "SAFE-OP",
    OP_STATE: "OP",
}
# AL status codes (ETG.1000.6) a user is likely to meet with this slave.
AL_STATUS_TEXTS: Final[Mapping[int, str]] = {
    0x0000: "no error",
    0x0011: "invalid requested state change",
    0x0012: "unknown requested state",
    0x0016: "invalid mailbox configuration",
    0x001A: "synchronization error",
    0x001B: "sync manager watchdog",
    0x001D: "invalid output configuration",
    0x001E: "invalid input configuration",
    0x001F: "invalid watchdog configuration",
}

# SDO abort codes (ETG.1000.6) worth a word in a message.
SDO_ABORT_TEXTS: Final[Mapping[int, str]] = {
    0x05040000: "SDO protocol timed out",
    0x06010000: "unsupported access to an object",
    0x06010002: "attempt to write a read only object",
    0x06020000: "the object does not exist in the object dictionary",
    0x06070010: "data type does not match, length of service parameter does not match",
    0x06090011: "subindex does not exist",
    0x06090030: "value range of parameter exceeded",
    0x06090031: "value of parameter written too high",
    0x06090032: "value of parameter written too low",
    0x08000000: "general error",
    0x08000020: "data cannot be transferred or stored to the application",
    0x08000022: "data cannot be transferred because of the present device state",
}


def state_name(state: int) -> str:
    """``SAFE-OP + ERROR`` for 0x14 and so on."""
    name = _STATE_NAMES.get(state & 0x0F, f"0x{state & 0x0F:02X}")
    return f"{name} + ERROR" if state & STATE_ERROR else name


def al_status_text(code: int) -> str:
    return f"AL status 0x{code:04X} ({AL_STATUS_TEXTS.get(code, 'see ETG.1000.6')})"


# --- the library seam ---------------------------------------------------------------------


class EthercatError(Exception):
    """Base of what an :class:`EthercatMaster` raises."""


class EthercatUnavailableError(EthercatError):
    """EtherCAT cannot be used at all here: pysoem missing, no raw sockets, no such NIC.

    The message says exactly what is wrong and how to fix it.
    """


class EthercatSdoError(EthercatError):
    """The slave aborted an SDO transfer (it answered, with an abort code)."""

    def __init__(self, index: int, subindex: int, abort_code: int, desc: str = "") -> None:
        text = desc or SDO_ABORT_TEXTS.get(abort_code, "see ETG.1000.6")
        super().__init__(f"SDO abort 0x{abort_code:08X} at 0x{index:04X}:{subindex:02X}: {text}")
        self.index = index
        self.subindex = subindex
        self.abort_code = abort_code
        self.desc = text


class EthercatMailboxError(EthercatError):
    """An SDO transfer got no (valid) answer: mailbox error, timeout, working counter 0."""


class EthercatSlave(Protocol):
    """One slave as the master found it (pysoem's ``CdefSlave`` names)."""

    @property
    def man(self) -> int:
        """Vendor id from the slave's SII (EEPROM)."""
        ...

    @property
    def id(self) -> int:
        """Product code from the SII."""
        ...

    @property
    def rev(self) -> int:
        """Revision number from the SII."""
        ...

    @property
    def name(self) -> str: ...

    @property
    def state(self) -> int:
        """The state last read (``read_state``/``state_check``) or set to be requested."""
        ...

    @state.setter
    def state(self, value: int) -> None: ...

    @property
    def al_status(self) -> int:
        """The AL status code of the last state read."""
        ...

    @property
    def input(self) -> bytes:
        """This slave's input process data as of the last ``receive_processdata``."""
        ...

    @property
    def output(self) -> bytes: ...

    @output.setter
    def output(self, value: bytes) -> None:
        """Output process data, sent with the next ``send_processdata``."""
        ...

    def sdo_read(self, index: int, subindex: int, size: int = 0) -> bytes:
        """Upload one CoE entry; raises EthercatSdoError / EthercatMailboxError."""
        ...

    def sdo_write(self, index: int, subindex: int, data: bytes) -> None:
        """Download one CoE entry; raises EthercatSdoError / EthercatMailboxError."""
        ...

    def write_state(self) -> int:
        """Request ``state`` at this slave."""
        ...

    def state_check(self, expected_state: int, timeout: int = 2000) -> int:
        """Wait up to ``timeout`` us for ``expected_state``; returns the state found."""
        ...


class EthercatMaster(Protocol):
    """The EtherCAT master the driver needs (pysoem's ``Master`` names)."""

    def open(self, ifname: str) -> None:
        """Open the network interface; EthercatUnavailableError when impossible."""
        ...

    def config_init(self) -> int:
        """Enumerate the slaves (they end in PRE-OP); returns how many were found."""
        ...

    @property
    def slaves(self) -> Sequence[EthercatSlave]: ...

    def config_map(self) -> int:
        """Map every slave's PDOs into the process image (slaves go to SAFE-OP)."""
        ...

    def send_processdata(self) -> int: ...

    def receive_processdata(self, timeout: int = 2000) -> int:
        """Wait up to ``timeout`` us for the frame; returns the working counter."""
        ...

    def read_state(self) -> int:
        """Read every slave's AL state (into ``slave.state``); returns the lowest."""
        ...

    def write_state(self) -> int:
        """Request ``state`` at every slave."""
        ...

    def state_check(self, expected_state: int, timeout: int = 50000) -> int: ...

    @property
    def state(self) -> int: ...

    @state.setter
    def state(self, value: int) -> None: ...

    @property
    def expected_wkc(self) -> int: ...

    def close(self) -> None: ...


@runtime_checkable
class PacedMaster(Protocol):
    """A master whose process data runs on a cycle of its own (``ethercat_cycle``):
    ``receive_processdata`` waits for that cycle, so the driver's loop does not sleep,
    and the slave's watchdog is judged by the cycle's exchanges (``last_good_t``: the
    send time of its last good one), not by the driver's thread."""

    paced: bool
    priority_granted: bool
    priority_text: str

    @property
    def cycle_lost(self) -> int:
        """Exchanges of the cycle without the expected working counter, so far."""
        ...

    def last_good_t(self) -> float | None: ...

    def shutdown(self) -> None: ...


class SlaveCalls(Protocol):
    """What a master in another process offers for one slave (by bus position)."""

    def slave_sdo_read(self, position: int, index: int, subindex: int, size: int) -> bytes: ...

    def slave_sdo_write(self, position: int, index: int, subindex: int, data: bytes) -> None: ...

    def slave_write_state(self, position: int, state: int) -> int: ...

    def slave_state_check(self, position: int, expected_state: int, timeout: int) -> int: ...


class RemoteSlave:
    """An :class:`EthercatSlave` whose master runs in another process: identity, the
    state and AL status as last reported, the process data as last exchanged, and the
    slave's calls forwarded to ``calls`` (the proxy master)."""

    def __init__(self, calls: SlaveCalls, position: int, info: Sequence[Any]) -> None:
        self._calls = calls
        self.position = position
        man, id_, rev, name, state, al_status = info
        self._man, self._id, self._rev, self._name = int(man), int(id_), int(rev), str(name)
        self._state, self._al_status = int(state), int(al_status)
        self._output = b""
        self._input = b""
        self.output_size: int | None = None

    @property
    def man(self) -> int:
        return self._man

    @property
    def id(self) -> int:
        return self._id

    @property
    def rev(self) -> int:
        return self._rev

    @property
    def name(self) -> str:
        return self._name

    @property
    def state(self) -> int:
        return self._state

    @state.setter
    def state(self, value: int) -> None:
        self._state = value

    @property
    def al_status(self) -> int:
        return self._al_status

    def reported(self, state: int, al_status: int) -> None:
        """The state and AL status the remote master read last."""
        self._state, self._al_status = state, al_status

    @property
    def input(self) -> bytes:
        return self._input

    @input.setter
    def input(self, value: bytes) -> None:
        self._input = value

    @property
    def output(self) -> bytes:
        return self._output

    @output.setter
    def output(self, value: bytes) -> None:
        if self.output_size is None:
            raise ValueError("the process data is not mapped (config_map)")
        if len(value) != self.output_size:
            raise ValueError(f"outputs are {self.output_size} bytes, got {len(value)}")
        self._output = bytes(value)

    def mapped(self, output_size: int, inputs: bytes) -> None:
        """config_map: the image's sizes (outputs zero) and the first inputs."""
        self.output_size = output_size
        self._output = bytes(output_size)
        self._input = bytes(inputs)

    def sdo_read(self, index: int, subindex: int, size: int = 0) -> bytes:
        return self._calls.slave_sdo_read(self.position, index, subindex, size)

    def sdo_write(self, index: int, subindex: int, data: bytes) -> None:
        self._calls.slave_sdo_write(self.position, index, subindex, bytes(data))

    def write_state(self) -> int:
        return self._calls.slave_write_state(self.position, self._state)

    def state_check(self, expected_state: int, timeout: int = 2000) -> int:
        return self._calls.slave_state_check(self.position, expected_state, timeout)


# --- pysoem adapter ---------------------------------------------------------------------

PYSOEM_MISSING: Final = (
    "pysoem is not installed, so servotune cannot talk EtherCAT: install it with "
    "`pip install 'servotune[ethercat]'` and restart servotune"
)
RAW_SOCKET_FIX: Final = (
    "run `sudo setcap cap_net_raw,cap_net_admin+ep $(readlink -f .venv/bin/python)` and "
    "restart servotune, or run servotune as root"
)
CAP_NET_RAW: Final = 13


def _effective_capabilities() -> int:
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("CapEff:"):
                return int(line.split()[1], 16)
    return 0


def raw_socket_problem(
    ifname: str,
    *,
    euid: int | None = None,
    cap_eff: int | None = None,
    net_dir: Path = Path("/sys/class/net"),
) -> str | None:
    """Why this process cannot open ``ifname`` for EtherCAT, or None if it looks fine.

    Linux only (elsewhere None): the interface must exist and raw sockets need root or
    CAP_NET_RAW. The arguments other than ``ifname`` are for tests.
    """
    if not sys.platform.startswith("linux"):
        return None
    if not (net_dir / ifname).exists():
        known = sorted(p.name for p in net_dir.iterdir()) if net_dir.is_dir() else []
        return (
            f"there is no network interface {ifname!r} on this machine (found: "
            f"{', '.join(known) or 'none'}; `ip link` lists them): use the NIC the "
            "EP7047 is plugged into"
        )
    euid = os.geteuid() if euid is None else euid
    caps = _effective_capabilities() if cap_eff is None else cap_eff
    if euid != 0 and not (caps >> CAP_NET_RAW) & 1:
        return (
            f"raw sockets are not permitted for this process (not root, no CAP_NET_RAW), "
            f"and EtherCAT on {ifname} needs them: {RAW_SOCKET_FIX}"
        )
    return None


class _PysoemSlave:
    """EthercatSlave over a ``pysoem.CdefSlave``: maps pysoem's exceptions to the seam's."""

    def __init__(self, slave: Any, pysoem: Any) -> None:
        self._slave = slave
        self._pysoem = pysoem

    @property
    def man(self) -> int:
        return int(self._slave.man)

    @property
    def id(self) -> int:
        return int(self._slave.id)

    @property
    def rev(self) -> int:
        return int(self._slave.rev)

    @property
    def name(self) -> str:
        return str(self._slave.name)

    @property
    def state(self) -> int:
        return int(self._slave.state)

    @state.setter
    def state(self, value: int) -> None:
        self._slave.state = value

    @property
    def al_status(self) -> int:
        return int(self._slave.al_status)

    @property
    def input(self) -> bytes:
        return bytes(self._slave.input)

    @property
    def output(self) -> bytes:
        return bytes(self._slave.output)

    @output.setter
    def output(self, value: bytes) -> None:
        self._slave.output = value

    def _translate(self, exc: Exception, index: int, subindex: int) -> EthercatError:
        if isinstance(exc, self._pysoem.SdoError):
            return EthercatSdoError(index, subindex, int(exc.abort_code), str(exc.desc))
        return EthercatMailboxError(
            f"no valid answer to SDO 0x{index:04X}:{subindex:02X}: {type(exc).__name__} "
            f"{getattr(exc, 'desc', '') or getattr(exc, 'message', '') or exc}"
        )

    def sdo_read(self, index: int, subindex: int, size: int = 0) -> bytes:
        try:
            return bytes(self._slave.sdo_read(index, subindex, size))
        except (
            self._pysoem.SdoError,
            self._pysoem.WkcError,
            self._pysoem.MailboxError,
            self._pysoem.PacketError,
        ) as exc:
            raise self._translate(exc, index, subindex) from exc

    def sdo_write(self, index: int, subindex: int, data: bytes) -> None:
        try:
            self._slave.sdo_write(index, subindex, data)
        except (
            self._pysoem.SdoError,
            self._pysoem.WkcError,
            self._pysoem.MailboxError,
            self._pysoem.PacketError,
        ) as exc:
            raise self._translate(exc, index, subindex) from exc

    def write_state(self) -> int:
        return int(self._slave.write_state())

    def state_check(self, expected_state: int, timeout: int = 2000) -> int:
        return int(self._slave.state_check(expected_state, timeout))


class PysoemMaster:
    """:class:`EthercatMaster` over a real ``pysoem.Master``.

    Constructing it raises :class:`EthercatUnavailableError` when pysoem is not installed;
    ``open`` raises it when the interface is missing or raw sockets are not permitted,
    each with the fix in the message.

    SDO transfers time out after ``sdo_timeout_us`` (50 ms; SOEM's default is 700 ms):
    they run between two exchanges, and a slave that does not answer must not hold the
    process data back past the 100 ms watchdog.
    """

    def __init__(self, sdo_timeout_us: int = 50_000) -> None:
        try:
            import pysoem  # optional dependency: servotune[ethercat]
        except ImportError as exc:
            raise EthercatUnavailableError(PYSOEM_MISSING) from exc
        self._pysoem: Any = pysoem
        self._master: Any = pysoem.Master()
        self._master.sdo_read_timeout = sdo_timeout_us
        self._master.sdo_write_timeout = sdo_timeout_us
        self._slaves: list[_PysoemSlave] = []

    def open(self, ifname: str) -> None:
        problem = raw_socket_problem(ifname)
        if problem is not None:
            raise EthercatUnavailableError(problem)
        try:
            self._master.open(ifname)
        except ConnectionError as exc:
            raise EthercatUnavailableError(
                f"could not open {ifname} for EtherCAT ({exc}): is it the right NIC, and may "
                f"this process use raw sockets? {RAW_SOCKET_FIX}"
            ) from exc

    def config_init(self) -> int:
        found = int(self._master.config_init())
        self._slaves = [_PysoemSlave(s, self._pysoem) for s in (self._master.slaves or [])]
        return found

    @property
    def slaves(self) -> Sequence[EthercatSlave]:
        return self._slaves

    def config_map(self) -> int:
        try:
            return int(self._master.config_map())
        except self._pysoem.ConfigMapError as exc:
            details = "; ".join(str(getattr(e, "desc", e)) for e in getattr(exc, "error_list", []))
            raise EthercatMailboxError(f"mapping the process data failed: {details}") from exc

    def send_processdata(self) -> int:
        return int(self._master.send_processdata())

    def receive_processdata(self, timeout: int = 2000) -> int:
        return int(self._master.receive_processdata(timeout))

    def read_state(self) -> int:
        return int(self._master.read_state())

    def write_state(self) -> int:
        return int(self._master.write_state())

    def state_check(self, expected_state: int, timeout: int = 50000) -> int:
        return int(self._master.state_check(expected_state, timeout))

    @property
    def state(self) -> int:
        return int(self._master.state)

    @state.setter
    def state(self, value: int) -> None:
        self._master.state = value

    @property
    def expected_wkc(self) -> int:
        return int(self._master.expected_wkc)

    def close(self) -> None:
        self._master.close()
