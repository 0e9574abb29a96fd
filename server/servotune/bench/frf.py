"""The bench's "frequency_response" kind: checks, plans and analysis per device.

* SLAP2 (closed loop, measured): the controller holds the position; the server streams
  a multisine around it as absolute position targets (``ma``, the only way the SLAP2
  takes a position target; it has no streaming or buffered-target command, so every
  target is one command on the wire, and the profile generator runs between them at
  the maximum ``sv``/``sa``, set for the test and restored after it). The targets stay
  inside ``y0 +- amplitude`` and inside the user's travel window.
* SLAP2 open loop (``loop = "open"``, only with ``confirm_open_loop``): the same
  multisine as open-loop PWM (``spwm``, peak ``pwm`` within the bench's ``max_pwm``),
  the controller off; only inside a travel window the user set on both sides, which
  stops it (checked at every PWM sent and every recorded sample); the axis is left
  stopped (``st``, unpowered) where it ends. Gives the plant itself, and with the
  run's gains the loop the PID would close around it.
* Z1100 and others (no way to inject on the wire without leaving the device's own
  profile): the frequency response of the identified plant under the device's exact
  law (``tuning.whatif``), stored as a run like any other and labelled model-based.

Which devices inject is per device: ``tuning.law.DeviceLaw.injection`` (the
SLAP2's ``devices/slap2/injection.py``; None for the Z1100, model-based). The
injection's ``WirePlan`` places tones only where the wire's sample rate resolves them:
the rest of a requested band is listed as ``not_measured_hz`` with the reason. The
planning logic lives here so that the drivers only list the kind.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from servotune.link.base import BenchPlan, DeviceRefusedError, InvalidArgumentError, Sample
from servotune.tuning import frfrun, injection
from servotune.tuning.frf import ComplexArray, FloatArray
from servotune.tuning.frfrun import Excitation
from servotune.tuning.injection import Injection
from servotune.tuning.law import DeviceLaw
from servotune.tuning.plants import OUTPUT_FULL_SCALE
from servotune.tuning.targets import MarginTarget, margin_report, target_for
from servotune.tuning.whatif import loop_for, model_summary, plant_from_identification

KIND = "frequency_response"
LOW_HZ_RANGE = (0.2, 20.0)
HIGH_HZ_MAX = 200.0


def injection_for(law: DeviceLaw | None) -> Injection | None:
    """How the device of ``law`` takes an excitation on its wire; None: its frequency
    response is model-based (or it has no controller law at all: ``law`` None)."""
    return law.injection if law is not None else None


def measured(law: DeviceLaw | None) -> bool:
    """Whether a frequency response of the device of ``law`` is measured (it can inject)."""
    return injection_for(law) is not None


def wire_band(
    inject: Injection, baud: int | None, low_hz: float, high_hz: float
) -> tuple[float, tuple[float, ...], str | None, dict[str, Any] | None]:
    """The band the wire lets ``inject`` measure: (top tone's band edge, the requested
    tones left out, why, the wire plan); the whole band without a baud rate (a link
    that is not a serial line). InvalidArgumentError naming low_hz when the whole band
    lies above what the wire resolves."""
    if baud is None:
        return high_hz, (), None, None
    wire = inject.wire(baud)
    requested = frfrun.design(0.0, 1.0, low_hz, high_hz).tones_hz
    try:
        top, left_out = injection.split(wire, low_hz, high_hz, requested)
    except ValueError as exc:
        raise InvalidArgumentError("low_hz", str(exc)) from None
    if not left_out:
        return high_hz, (), None, wire.to_dict()
    # tones are multiples of low_hz: the highest multiple at or below the wire's top
    high = max(low_hz, low_hz * math.floor(top / low_hz + 1e-9))
    return high, left_out, f"not measured: {wire.reason()}", wire.to_dict()


def check_request(
    device: str,
    inject: Injection | None,
    amplitude: int,
    low_hz: float,
    high_hz: float,
    duration_s: float,
    max_distance_counts: int,
    *,
    loop: str = "closed",
    pwm: int = 0,
    max_pwm: int = OUTPUT_FULL_SCALE,
    confirm_open_loop: bool = False,
    window: tuple[int | None, int | None] = (None, None),
    baud: int | None = None,
) -> None:
    """422 (InvalidArgumentError naming the field and the range) before anything moves.

    Open loop (SLAP2 only): ``pwm`` 1..``max_pwm`` (the bench limit), a travel window
    set on both sides (``window``: the bench's min/max_position_counts) and
    ``confirm_open_loop`` true — the motor runs without position control. A band
    entirely above what the wire at ``baud`` resolves: 422 naming low_hz
    (``wire_band``). ``inject``: the device's (``injection_for``)."""
    if inject is None:
        if loop != "closed":
            raise InvalidArgumentError(
                "loop", f"a {device} frequency response is model-based: loop must be 'closed'"
            )
        if not (0 < low_hz < high_hz <= HIGH_HZ_MAX):
            raise InvalidArgumentError(
                "high_hz", f"need 0 < low_hz < high_hz <= {HIGH_HZ_MAX:g} Hz"
            )
        return
    if loop == "open":
        if inject.open_loop is None:
            raise InvalidArgumentError("loop", f"a {device} cannot be driven open loop")
        if not (1 <= pwm <= max_pwm):
            raise InvalidArgumentError(
                "pwm",
                f"pwm {pwm} must be 1..{max_pwm} (peak of the open-loop PWM, bench limit max_pwm)",
            )
        if window[0] is None or window[1] is None:
            raise InvalidArgumentError(
                "loop",
                "an open-loop frequency response needs a travel window on both sides "
                "(bench limits min_position_counts and max_position_counts): it is what "
                "stops the motor",
            )
        if not confirm_open_loop:
            raise InvalidArgumentError(
                "confirm_open_loop",
                "open loop drives the motor through spwm with the position controller off, "
                "stopped only by the travel window: confirm it (confirm_open_loop: true)",
            )
    elif loop != "closed":
        raise InvalidArgumentError("loop", f"loop {loop!r} must be 'closed' or 'open'")
    elif not (1 <= amplitude <= max_distance_counts):
        raise InvalidArgumentError(
            "amplitude",
            f"amplitude {amplitude} must be 1..{max_distance_counts} counts "
            "(peak, bench limit max_distance_counts)",
        )
    low, high = LOW_HZ_RANGE
    if not (low <= low_hz <= high):
        raise InvalidArgumentError("low_hz", f"low_hz {low_hz:g} must be {low:g}..{high:g} Hz")
    if not (low_hz < high_hz <= HIGH_HZ_MAX):
        raise InvalidArgumentError(
            "high_hz",
            f"high_hz {high_hz:g} must be above low_hz {low_hz:g} and <= {HIGH_HZ_MAX:g} Hz",
        )
    needed = (1 + frfrun.MIN_PERIODS) / low_hz
    if duration_s + 1e-9 < needed:
        raise InvalidArgumentError(
            "duration_s",
            f"duration {duration_s:g} s is too short for low_hz {low_hz:g}: at least "
            f"{needed:g} s (one settling period and {frfrun.MIN_PERIODS} analysed)",
        )
    wire_band(inject, baud, low_hz, high_hz)


def _design(
    inject: Injection,
    baud: int | None,
    y0: float,
    amplitude: float,
    low_hz: float,
    high_hz: float,
    command: tuple[str, str],
) -> Excitation:
    high, left_out, reason, wire = wire_band(inject, baud, low_hz, high_hz)
    excitation = frfrun.design(y0, amplitude, low_hz, high, *command)
    return dataclasses.replace(
        excitation, not_measured_hz=left_out, not_measured_reason=reason, wire=wire
    )


def plan_closed(
    inject: Injection,
    latest: Sample,
    params: Mapping[str, int],
    amplitude: int,
    low_hz: float,
    high_hz: float,
    baud: int | None = None,
) -> tuple[BenchPlan, Excitation]:
    """The plan (hold, the injection's overrides for the test, back to y0 at the end)
    and the signal: targets around the held position, tones up to what the wire at
    ``baud`` resolves (``wire_band``)."""
    if latest.flags.get("move") or latest.flags.get("vm"):
        raise DeviceRefusedError(
            "the axis is moving: a test must start from rest (wait, or press STOP)"
        )
    position = latest.channels.get("position") or 0.0
    if latest.flags.get("pm") and latest.channels.get("setpoint") is not None:
        position = float(latest.channels["setpoint"] or position)
    y0 = float(round(position))
    excitation = _design(inject, baud, y0, amplitude, low_hz, high_hz, inject.closed_loop)
    plan = BenchPlan(
        setup=[] if latest.flags.get("pm") else [("position_mode", {})],
        trigger=[],
        finish=[(inject.closed_loop[0], {inject.closed_loop[1]: round(y0)})],
        response="position",
        y0=y0,
        y_final=y0,
        band=float(params.get("inpos_window", 5)),
        overrides=dict(inject.overrides),
        fault_flags=list(inject.fault_flags),
    )
    return plan, excitation


def plan_open(
    inject: Injection,
    latest: Sample,
    pwm: int,
    low_hz: float,
    high_hz: float,
    baud: int | None = None,
) -> tuple[BenchPlan, Excitation]:
    """Open loop: the multisine as PWM (``spwm``) around 0, from rest; ``st`` at the
    end (the axis is left unpowered where it stands: no return move without the
    controller). The first ``spwm`` leaves position mode."""
    if inject.open_loop is None:
        raise DeviceRefusedError("this device cannot be driven open loop")
    if latest.flags.get("move") or latest.flags.get("vm"):
        raise DeviceRefusedError(
            "the axis is moving: a test must start from rest (wait, or press STOP)"
        )
    position = float(latest.channels.get("position") or 0.0)
    excitation = _design(inject, baud, 0.0, pwm, low_hz, high_hz, inject.open_loop)
    plan = BenchPlan(
        setup=[],
        trigger=[],
        finish=[("stop", {})],
        response="position",
        y0=position,
        y_final=position,
        band=None,
        fault_flags=list(inject.fault_flags),
    )
    return plan, excitation


def model_plan(latest: Sample) -> BenchPlan:
    """A model-based run moves nothing: an empty plan around where the axis stands."""
    position = float(latest.channels.get("position") or 0.0)
    return BenchPlan(
        setup=[],
        trigger=[],
        finish=[],
        response="position",
        y0=position,
        y_final=position,
        band=None,
    )


def model_grid_hz(low_hz: float, period_s: float, count: int = 400) -> np.ndarray[Any, Any]:
    """Where the model's Bode curves are drawn: from below the run's band up to the
    controller's Nyquist frequency, so that both crossovers are on the plot."""
    return np.geomspace(min(low_hz, 1.0), 0.999 * 0.5 / period_s, count)


def analyse_run(
    law: DeviceLaw | None,
    run: Mapping[str, Any],
    identified: Mapping[str, Any] | None,
    preset: str | None = None,
) -> dict[str, Any]:
    """Everything the Bode view shows for one stored run (runs in the compute worker),
    ``law`` the controller law of the run's device (None: it has none).

    ``measured``: from the samples (SLAP2 runs); ``model``: the identified plant under
    the exact law with the run's gains (``identified`` is the auto-tune's model, or the
    one stored with a model-based run); either may be null with a ``*_problem`` reason.
    Both margins are read against the margin target ``preset`` (``tuning.targets``;
    the default for None): ``margins.target``, ``meets_target``, ``warning``.
    """
    target = target_for(preset)
    test = run.get("test") or {}
    device = str(run.get("device", ""))
    low = float(test.get("low_hz") or 1.0)
    high = float(test.get("high_hz") or 40.0)
    out: dict[str, Any] = {
        "run_id": run.get("id"),
        "device": device,
        "model_based": not measured(law),
        "loop": str(test.get("loop") or "closed"),
        "low_hz": low,
        "high_hz": high,
        "measured": None,
        "measured_problem": None,
        "model": None,
        "model_problem": None,
    }
    excitation = run.get("excitation")
    if excitation and run.get("samples"):
        columns: list[str] = list(run["columns"])
        rows = [r for r in run["samples"] if r[columns.index("position")] is not None]
        ip = columns.index("position")
        isp = columns.index("setpoint") if "setpoint" in columns else None
        spans = _sample_spans(excitation, [r[0] for r in rows])
        try:
            inject = injection_for(law)
            if inject is None:
                raise ValueError(f"a {device} run cannot be measured: it takes no injection")
            if test.get("loop") == "open":
                out["measured"] = frfrun.analyse_open(
                    [r[0] for r in rows],
                    [r[ip] for r in rows],
                    excitation.get("sent", []),
                    float(run.get("t0_s") or 0.0),
                    Excitation.from_dict(excitation),
                    _controller(law, run),
                    tick_s=inject.tick_s,
                    sample_spans_s=spans,
                )
            else:
                out["measured"] = frfrun.analyse(
                    [r[0] for r in rows],
                    [r[ip] for r in rows],
                    [r[isp] for r in rows] if isp is not None else None,
                    excitation.get("sent", []),
                    float(run.get("t0_s") or 0.0),
                    Excitation.from_dict(excitation),
                    inject.input_model((run.get("plan") or {}).get("overrides") or {}),
                    sample_spans_s=spans,
                )
        except ValueError as exc:
            out["measured_problem"] = str(exc)
        if out["measured"] is not None:
            out["measured"]["margins"] = out["measured"]["margins"] | measured_target(
                out["measured"]["margins"], target
            )
    elif measured(law):
        out["measured_problem"] = "the run recorded no excitation"
    model = run.get("plant_model") or identified
    try:
        if law is None:
            raise ValueError(f"no controller law for {device}")
        plant = plant_from_identification(law, model)
        loop = loop_for(law, plant, run.get("params") or {})
        summary = model_summary(loop, model_grid_hz(low, loop.period_s))
        summary["margins"] = margin_report(loop.margins(), target)
        out["model"] = summary | {
            "plant": {
                "gain_counts_s_per_unit": plant.gain_counts_s_per_unit,
                "tau_s": plant.tau_s,
                "source": plant.source,
            },
            "law": law.description,
        }
    except (ValueError, KeyError) as exc:
        out["model_problem"] = (
            f"gains not recorded: {exc}" if isinstance(exc, KeyError) else str(exc)
        )
    safe: dict[str, Any] = _json_safe(out)
    return safe


def _sample_spans(excitation: Mapping[str, Any], times: list[float]) -> list[float | None] | None:
    """The latch span of each sample (``excitation["spans"]``: ``[t, span]`` rows the
    bench recorded), matched by time; None for a run recorded without them."""
    recorded = excitation.get("spans")
    if not recorded:
        return None
    by_time = {round(float(t), 6): span for t, span in recorded}
    return [by_time.get(round(float(t), 6)) for t in times]


def measured_target(margins: Mapping[str, Any], target: MarginTarget) -> dict[str, Any]:
    """Measured margins against ``target``: met, not met (with the warning), or unknown
    (None) where a margin is not measurable - never "met" from a margin the run could
    not read."""
    gm, pm = margins.get("gain_margin_db"), margins.get("phase_margin_deg")
    short: list[str] = []
    if pm is not None and pm < target.phase_margin_deg:
        short.append(f"phase margin {pm:.1f} deg is below {target.phase_margin_deg:g} deg")
    if gm is not None and gm < target.gain_margin_db:
        short.append(f"gain margin {gm:.1f} dB is below {target.gain_margin_db:g} dB")
    meets: bool | None = False if short else (True if gm is not None and pm is not None else None)
    warning = (
        f"{'; '.join(short)} (target: {target.preset}, PM {target.phase_margin_deg:g} deg "
        f"/ GM {target.gain_margin_db:g} dB)"
        if short
        else None
    )
    return {"target": target.to_dict(), "meets_target": meets, "warning": warning}


def _controller(
    law: DeviceLaw | None, run: Mapping[str, Any]
) -> Callable[[FloatArray], ComplexArray] | None:
    """The law with the run's gains, as ``frfrun.analyse_open`` closes the loop; None
    when the run did not record its gains (or the law has no error-only controller)."""
    params = run.get("params") or {}
    if law is None:
        return None
    try:
        gains = {name: int(params[name]) for name in law.gain_names}
    except (KeyError, TypeError, ValueError):
        return None

    def controller(frequency_hz: FloatArray) -> ComplexArray:
        response = law.controller_response(frequency_hz, gains)
        if response is None:
            raise ValueError(f"the {law.device} law has no error-only controller to close")
        return response

    return controller


def _json_safe(value: Any) -> Any:
    """NaN and infinities as null (strict JSON)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value
