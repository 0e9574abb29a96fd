"""A frequency-response run of the bench on the SLAP2 firmware simulator, in simulated
time (no pty, no host load: deterministic), with host stalls injected at chosen
exchanges.

What the bench and the driver do, step by step: one ``ma`` per changed target and one
``rp`` after it, each exchange 5-9 ms (a 19200-baud wire and a host's jitter; the
module acts on the CR), stamped as the driver stamps them: the latch estimate (an
upper bound: the end of the CR's echo less a character) and the time the CR was
written (a lower bound), whose difference is the latch span the driver records.

A **host stall** (``Stalls``) is an exchange whose callback the host runs late: either
after the CR was written (the module acted on time, the echo and the reply were
processed ``stall`` late: the stamp is late by the stall and the span says so), or
before it (the CR itself leaves late: the stamp is right). Which exchanges stall and
for how long comes from a seeded generator: the same seed, the same run.

The run's ``setpoint`` column is what the capture records when it can trust its
profile (the firmware's setpoint at the sample's stamp, as the reconstruction from the
same stamps gives it) or, with ``setpoint_from_pe``, ``rp + pe`` (the firmware's setpoint
at the sample's true latch: what the capture falls back to when its checks fail).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from servotune.devices.slap2.injection import TrapezoidInput
from servotune.devices.slap2.profile import TICK_S
from servotune.devices.slap2.sim.module import Slap2Module
from servotune.sim.physics import DcMotorParams
from servotune.tuning import frfrun
from servotune.tuning.frf import tone_fit

# the span of a latch estimate on a quiet host: the CR's transmission and the
# callback's latency (measured on the pty: 0.5-0.9 ms)
QUIET_SPAN_S = 0.0007


@dataclass(frozen=True, slots=True)
class Stalls:
    """One exchange in ``every`` (on average) stalls for ``seconds[0]..seconds[1]``;
    ``after_cr`` is the share of stalls that hit after the CR was written (the harmful
    kind: a late stamp)."""

    every: int
    seconds: tuple[float, float]
    after_cr: float = 0.7
    seed: int = 0


@dataclass(slots=True)
class ScriptedRun:
    """A run as the bench stores it (``frfrun.analyse``'s arguments) and the truth."""

    t_s: list[float]
    position: list[float]
    setpoint: list[float]
    sent: list[list[float]]
    spans_s: list[float]
    t0_s: float
    excitation: frfrun.Excitation
    gains: tuple[int, int, int]
    params: DcMotorParams
    stalled_samples: int = 0
    stalled_commands: int = 0
    late_by_s: list[float] = field(default_factory=list)

    def analyse(self, **kwargs: Any) -> dict[str, Any]:
        return frfrun.analyse(
            self.t_s,
            self.position,
            self.setpoint,
            self.sent,
            self.t0_s,
            self.excitation,
            model=TrapezoidInput(65535, 65535),
            sample_spans_s=self.spans_s,
            **kwargs,
        )


class TickClock:
    """Advances a simulated SLAP2 module to host time ``t_s``: one control tick every
    ``TICK_S`` from t = 0, as the firmware runs beside a polling host."""

    def __init__(self, module: Slap2Module) -> None:
        self._module = module
        self._ticks = 0

    def run_until(self, t_s: float) -> None:
        due = math.floor(t_s / TICK_S)
        self._module.run_ticks(due - self._ticks)
        self._ticks = due


def _send(module: Slap2Module, line: str) -> None:
    for byte in line.encode() + b"\r":
        module.receive(byte)


def scripted_run(
    params: DcMotorParams,
    gains: tuple[int, int, int],
    *,
    seed: int = 1,
    amplitude: float = 200.0,
    low_hz: float = 1.0,
    high_hz: float = 10.0,
    duration_s: float = 6.0,
    transaction_s: tuple[float, float] = (0.005, 0.009),
    stalls: Stalls | None = None,
    setpoint_from_pe: bool = False,
    y0: int = 0,
) -> ScriptedRun:
    """The bench's closed-loop run (see the module docstring)."""
    rng = np.random.default_rng(seed)
    stall_rng = np.random.default_rng(None if stalls is None else 1000 + stalls.seed)
    module = Slap2Module(0, params=params)
    kp, ki, kd = gains
    for line in (f"kp{kp}", f"ki{ki}", f"kd{kd}", "sv65535", "sa65535", "pm", f"ma{y0}"):
        _send(module, line)
    run_until = TickClock(module).run_until

    run_until(0.5)  # at rest at y0
    module.take_output()
    excitation = frfrun.design(float(module.setpoint), amplitude, low_hz, high_hz)
    t0 = t = 0.5
    out = ScriptedRun([], [], [], [], [], t0, excitation, gains, params)

    def stall() -> tuple[float, bool]:
        """(seconds, after the CR) of this exchange's stall; (0, False) for none."""
        if stalls is None or stall_rng.uniform() >= 1.0 / stalls.every:
            return 0.0, False
        return float(stall_rng.uniform(*stalls.seconds)), bool(
            stall_rng.uniform() < stalls.after_cr
        )

    last: int | None = None
    while t < t0 + duration_s:
        target = excitation.target(t - t0)
        if target != last:
            pause, late = stall()
            if pause and not late:
                t += pause  # the CR leaves late: the stamp is right
            run_until(t)
            _send(module, f"ma{target}")
            module.take_output()
            stamp = t + (pause if late else 0.0)
            # [acknowledged, target, latched, span]: acknowledged after the reply
            out.sent.append(
                [stamp + 0.0013, float(target), stamp, QUIET_SPAN_S + (pause if late else 0.0)]
            )
            out.stalled_commands += bool(late and pause)
            last = target
            t = stamp + float(rng.uniform(*transaction_s))
        pause, late = stall()
        if pause and not late:
            t += pause
        run_until(t)
        position, setpoint = float(module.position), float(module.setpoint)
        module.take_output()
        stamp = t + (pause if late else 0.0)
        out.t_s.append(stamp)
        out.position.append(position)
        out.spans_s.append(QUIET_SPAN_S + (pause if late else 0.0))
        out.late_by_s.append(stamp - t)
        out.stalled_samples += bool(late and pause)
        if setpoint_from_pe:
            out.setpoint.append(setpoint)
        else:
            out.setpoint.append(math.nan)  # filled from the stamps below
        t = stamp + float(rng.uniform(*transaction_s))
    if not setpoint_from_pe:
        # the capture's reconstruction from the same stamps: the rebuilt input
        tick_t, u = frfrun.rebuild_input(
            out.sent, t0, excitation.y0, TrapezoidInput(65535, 65535), t - t0 + 0.01
        )
        out.setpoint = [float(v) for v in np.interp(np.asarray(out.t_s) - t0, tick_t, u)]
    return out


def simulator_response(
    params: DcMotorParams, gains: tuple[int, int, int], excitation: frfrun.Excitation
) -> np.ndarray:
    """The simulated module's own closed loop at the excitation's tones: the multisine
    sent as ``ma`` at every tick (no wire, no host), its position against its own
    setpoint at every tick, fitted tone by tone over 6 periods after one. What a bench
    run of a module without friction must read (it leads the ZOH model of
    ``tuning.loops`` by one tick: the simulator's convention, docs/frequency-response.md)."""
    module = Slap2Module(0, params=params)
    kp, ki, kd = gains
    for line in (f"kp{kp}", f"ki{ki}", f"kd{kd}", "sv65535", "sa65535", "pm", "ma0"):
        _send(module, line)
    module.run_ticks(600)
    module.take_output()
    shifted = frfrun.Excitation.from_dict(excitation.to_dict() | {"y0": float(module.setpoint)})
    n = round(7 * excitation.period_s / TICK_S)
    t = np.arange(1, n + 1) * TICK_S
    position = np.empty(n)
    setpoint = np.empty(n)
    last: int | None = None
    for k in range(n):
        target = shifted.target(k * TICK_S)
        if target != last:
            _send(module, f"ma{target}")
            module.take_output()
            last = target
        module.run_ticks(1)
        position[k], setpoint[k] = module.position, module.setpoint
    analysed = t >= excitation.period_s
    tones = np.asarray(excitation.tones_hz)
    t_ref = float(t[analysed].mean())
    y = tone_fit(t[analysed], position[analysed], tones, t_ref).amplitude
    u = tone_fit(t[analysed], setpoint[analysed], tones, t_ref).amplitude
    return np.asarray(y / u)
