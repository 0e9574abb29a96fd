"""Every stop of an axis, and the watch that nothing is left oscillating after it.

The hub's one way to stop an axis (``StopService.stop``), whoever asks: the STOP button
(``kind="stop"``), every other stop (``"controlled"``: a hand-over, the dead-man, the
end or abort of a bench run or an auto-tune step), and the explicit power-off
(``"power_off"``, category 0). Decisions (docs/control.md, "Stops"):

* Before a STOP or a controlled stop, the last ``JUDGE_S`` of telemetry are judged
  (``servotune.hub.loopcheck``): where the position loop is *not working* (oscillating,
  its error running away, the current limit held) the device's loop-free brake goes
  out instead (``StopModes.brake``: SLAP2 spwm 0, else power off) - a loop that does
  not work must not be trusted to brake or hold. Without evidence either way the
  device's own stop goes out.
* After a stop that leaves the axis held by its loop (``action == "hold"``) the axis is
  watched until it is at rest (``hub.loopcheck.at_rest``), at most ``WATCH_S``: if the loop
  oscillates, runs away or holds the current limit meanwhile, or the axis is not at
  rest by then, it gets the brake and an error event says why.
* A watch whose telemetry stops for ``WATCH_SILENT_S`` (a link down, a device that
  stopped answering its polls) says so in a warning event: the hold is *not verified*.
  Nothing is sent on no evidence (a brake or a power-off would drop a vertical axis that
  may well be holding). The watch goes on until telemetry returns and then judges the
  samples after the gap afresh, as after the stop itself: at rest is told (an info
  event), a loop that does not work gets the brake. It never ends silently without a
  verdict; only a new change of the axis or the hub's stop ends it.
* A brake (``action == "brake"``) is switched off (``StopModes.power_off``) once the
  axis is at rest, at the latest after ``BRAKE_MAX_S``; the event says whether it was
  seen at rest or switched off on the time limit.
* A new change of the axis (any command, write, console line) ends its watch: what
  the user does next is theirs (``cancel_watch``).

Sample times are the drivers' own; the watch compares them with each other only (the
samples after the stop are those newer than the newest one at the stop), so an
injected hub clock does not confuse it. ``hub.state`` owns one of these, so nothing
here knows the hub.

``StopDelivery`` is STOP all and the delivery of a STOP that could not be sent at once
(kept pending until the axis is back, ``PENDING_STOP_MAX_S``); it reads and keeps the
hub's axis records and asks the hub's state through ``StopTarget``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import deque
from collections.abc import Awaitable, Callable, Coroutine, Mapping
from dataclasses import dataclass, field
from typing import Any, Final, Literal, Protocol, runtime_checkable

from servotune.descriptor import DeviceDescriptor, LoopSignals
from servotune.hub import loopcheck
from servotune.hub.records import AxisEntry
from servotune.link.base import (
    AxisDriver,
    DeviceRefusedError,
    DriverError,
    LinkDownError,
    Sample,
    StopModes,
    StopOutcome,
    UnjudgedStop,
)
from servotune.schema import EventLevel, LinkStatus

logger = logging.getLogger(__name__)

# Telemetry kept per axis: the judgement before a stop looks at the last JUDGE_S.
HISTORY_S: Final = 4.0
JUDGE_S: Final = 1.5
# After a stop that holds, the axis must be at rest within WATCH_S.
WATCH_S: Final = 3.0
# A brake is switched off once the shaft stands, at the latest after BRAKE_MAX_S.
BRAKE_MAX_S: Final = 2.0
# How often the watch looks at the samples.
WATCH_PERIOD_S: Final = 0.02
# A watch without a new sample for this long says the hold is not verified (as long as
# the hub's own horizon for an axis that sent no sample, ``hub.state.AXIS_SILENT_S``:
# a short hold-up of a busy host is not an outage).
WATCH_SILENT_S: Final = 3.0
# After a bench run or an auto-tune step the axis is watched this long for a loop that
# does not work (enough for four swings of the slowest limit cycle seen, ~3 Hz).
SETTLE_WATCH_S: Final = 1.5
# Telemetry too sparse to judge the loop by then (a starved host, a hole in it): the
# check waits this much longer for evidence before it treats the loop as not working.
SETTLE_EVIDENCE_S: Final = 3.5

StopKind = Literal["stop", "controlled", "power_off"]


@dataclass(eq=False, slots=True)
class _Axis:
    driver: AxisDriver
    loop: LoopSignals | None
    power_off_command: str | None
    history: deque[Sample] = field(default_factory=deque)
    arrived: float = 0.0  # the service's clock when the newest sample came
    watch: asyncio.Task[None] | None = None
    # Stops of this axis so far, and the outcome of its watches (tests, benchmark).
    watches: int = 0
    escalations: int = 0
    # The running watch has had no telemetry for WATCH_SILENT_S: its hold is not verified.
    unverified: bool = False


class StopService:
    """Stops of every axis of one hub (see the module docstring)."""

    def __init__(
        self,
        on_event: Callable[[EventLevel, str | None, str], None],
        *,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], Awaitable[None]] = asyncio.sleep,
    ) -> None:
        self._on_event = on_event
        self._clock = clock
        # The watches' pause between two looks (tests inject one that moves their clock).
        self._sleep = sleep
        self._axes: dict[str, _Axis] = {}

    # --- what the hub feeds in ----------------------------------------------------------

    def add_axis(self, axis_id: str, driver: AxisDriver, descriptor: DeviceDescriptor) -> None:
        self._axes[axis_id] = _Axis(driver, descriptor.loop, descriptor.stop.power_off_command)

    def on_sample(self, axis_id: str, sample: Sample) -> None:
        """Keep the last ``HISTORY_S`` of an axis with a loop to judge (cheap: called
        for every sample)."""
        ax = self._axes.get(axis_id)
        if ax is None or ax.loop is None:
            return
        history = ax.history
        history.append(sample)
        ax.arrived = self._clock()
        while history and sample.t - history[0].t > HISTORY_S:
            history.popleft()

    def verdict(self, axis_id: str, *, window_s: float = JUDGE_S) -> loopcheck.LoopVerdict:
        """The loop check on the axis' last ``window_s`` of telemetry, judged now (how
        long ago the newest sample came counts against the evidence)."""
        ax = self._axes[axis_id]
        if ax.loop is None or not ax.history:
            return loopcheck.NO_EVIDENCE
        newest = ax.history[-1].t
        age_s = max(0.0, self._clock() - ax.arrived)
        return loopcheck.judge(ax.history, ax.loop, since=newest - window_s, age_s=age_s)

    def watching(self, axis_id: str) -> bool:
        ax = self._axes.get(axis_id)
        return ax is not None and ax.watch is not None and not ax.watch.done()

    def unverified(self, axis_id: str) -> bool:
        """The axis' watch after a stop has had no telemetry for ``WATCH_SILENT_S`` and
        waits for it: whether the axis rests and holds is not known."""
        ax = self._axes.get(axis_id)
        return ax is not None and ax.unverified and self.watching(axis_id)

    def cancel_watch(self, axis_id: str) -> None:
        """A new change of the axis: what follows is the user's (see the module doc)."""
        ax = self._axes.get(axis_id)
        if ax is not None and ax.watch is not None and ax.watch is not asyncio.current_task():
            ax.watch.cancel()
            ax.watch = None

    async def close(self) -> None:
        for ax in self._axes.values():
            if ax.watch is not None:
                ax.watch.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await ax.watch
                ax.watch = None

    # --- stopping -------------------------------------------------------------------------

    async def stop(self, axis_id: str, kind: StopKind, reason: str) -> StopOutcome | None:
        """Stop the axis (see the module docstring); returns what went out and what the
        axis does now (None: the driver does not say, e.g. a rig's axis, which its rig
        watches). Raises the driver's error when nothing could be sent (the caller
        keeps a STOP pending then); the watch reports its own outcome as events."""
        ax = self._axes[axis_id]
        self.cancel_watch(axis_id)
        driver = ax.driver
        if not isinstance(driver, StopModes):
            # A driver that stops by itself (a rig's axis: the rig judges and watches
            # it): its STOP, or the power-off command of its descriptor.
            if kind == "power_off" and ax.power_off_command:
                await driver.command(ax.power_off_command, {})
                return None
            return await driver.stop()
        modes = driver
        verdict = self.verdict(axis_id) if kind != "power_off" else loopcheck.NO_EVIDENCE
        outcome: StopOutcome | None
        if kind == "power_off":
            outcome = await modes.power_off()
        elif verdict.working is False:
            outcome = await modes.brake()
            self._on_event(
                "error",
                axis_id,
                f"{reason}: the loop is not working ({verdict.reason}): not trusted to "
                f"brake or hold: {_describe(outcome)}",
            )
        elif kind == "controlled":
            outcome = await modes.controlled_stop()
        elif verdict.sparse and isinstance(driver, UnjudgedStop):
            outcome = await driver.unjudged_stop()
            self._on_event("warning", axis_id, f"{reason}: {verdict.reason}: {_describe(outcome)}")
        else:
            outcome = await driver.stop()
        if outcome is not None:
            self.follow(axis_id, outcome, reason)
        return outcome

    def follow(self, axis_id: str, outcome: StopOutcome, reason: str) -> None:
        """Watch the axis after ``outcome`` (a stop that went out some other way, e.g. a
        stop-group command of the descriptor): see the module docstring."""
        ax = self._axes.get(axis_id)
        if ax is None or ax.loop is None:
            return
        self.cancel_watch(axis_id)
        if outcome.action == "hold":
            job = self._watch_hold(axis_id, ax, reason)
        elif outcome.action == "brake":
            job = self._watch_brake(axis_id, ax, reason)
        else:
            return
        ax.watches += 1
        ax.watch = asyncio.get_running_loop().create_task(job, name=f"stop watch of {axis_id}")

    # --- after a run --------------------------------------------------------------------

    async def settle_check(
        self,
        axis_id: str,
        *,
        gains_now: Mapping[str, int],
        restore: Mapping[str, int],
        reason: str,
        watch_s: float = SETTLE_WATCH_S,
    ) -> Settled | None:
        """After a bench run or an auto-tune step: nothing the product started may be
        left oscillating. Watches the axis until it is at rest, at most ``watch_s`` of
        its telemetry (unpowered and still counts as at rest too). Returns None only on
        evidence: at rest in telemetry dense enough to judge the loop, a loop judged
        working (``hub.loopcheck``), or the loop off.

        If the loop is not working, brings the axis to rest without the loop (the brake,
        then power off at rest), writes ``restore`` (the gains in force before the run,
        or the last verified ones) where they differ from ``gains_now``, and holds with
        them, watched like any hold; with no other gains to go back to (the ones in
        force oscillate) it is left unpowered. Says it in an error event.

        If the telemetry stays too sparse (or absent) to judge, even ``SETTLE_EVIDENCE_S``
        longer, the loop is not verified and is treated as not working, except that the
        axis holds again in the end: brought to rest without the loop, ``restore`` written
        where it differs, held (watched) - with the gains in force before the run, which
        nothing showed to oscillate. Says it in a warning event. Returns what it found
        (``Settled.found``) and did."""
        ax = self._axes.get(axis_id)
        if ax is None or ax.loop is None or not isinstance(ax.driver, StopModes):
            return None
        mark = self._start_mark(ax)
        deadline = self._clock() + watch_s + SETTLE_EVIDENCE_S
        verdict: loopcheck.LoopVerdict | None = None  # None: no sample since the run
        while self._clock() < deadline:
            await self._sleep(WATCH_PERIOD_S * 5)
            after = [s for s in ax.history if s.t > mark]
            if not after:
                continue
            age_s = max(0.0, self._clock() - ax.arrived)
            verdict = loopcheck.judge(after, ax.loop, since=after[0].t, age_s=age_s)
            if verdict.working is False:
                break
            if verdict.sparse:
                continue  # holes in the telemetry hide a swing as well as rest
            if loopcheck.at_rest(after, ax.loop, since=after[0].t):
                return None  # at rest and holding: nothing oscillates
            if after[-1].t - after[0].t >= watch_s and (
                verdict.working or verdict == loopcheck.NO_EVIDENCE
            ):
                return None  # a loop judged working, or the loop off: none to oscillate
        if verdict is not None and verdict.working is False:
            return await self._left_oscillating(ax, axis_id, verdict, gains_now, restore, reason)
        if verdict is not None and (verdict.working or verdict == loopcheck.NO_EVIDENCE):
            return None
        why = verdict.reason if verdict is not None else "no telemetry came after it"
        return await self._unverified(ax, axis_id, why, gains_now, restore, reason)

    async def _left_oscillating(
        self,
        ax: _Axis,
        axis_id: str,
        verdict: loopcheck.LoopVerdict,
        gains_now: Mapping[str, int],
        restore: Mapping[str, int],
        reason: str,
    ) -> Settled:
        done, restored = await self._to_rest_and_restore(ax, axis_id, gains_now, restore)
        holds = restored is not None
        if holds:
            await self._hold_again(ax, axis_id, reason, done)
        else:
            done.append("no other gains to restore (the ones in force oscillate): left unpowered")
        message = f"{reason}: left the axis oscillating ({verdict.reason}); " + "; ".join(done)
        self._on_event("error", axis_id, message)
        return Settled(verdict.reason, message, restored, holds)

    async def _unverified(
        self,
        ax: _Axis,
        axis_id: str,
        why: str,
        gains_now: Mapping[str, int],
        restore: Mapping[str, int],
        reason: str,
    ) -> Settled:
        done, restored = await self._to_rest_and_restore(ax, axis_id, gains_now, restore)
        await self._hold_again(ax, axis_id, reason, done)
        message = (
            f"{reason}: could not verify that the loop works after it ({why}); treated as "
            "not working: " + "; ".join(done)
        )
        self._on_event("warning", axis_id, message)
        return Settled(why, message, restored, True, found="unverified")

    async def _to_rest_and_restore(
        self, ax: _Axis, axis_id: str, gains_now: Mapping[str, int], restore: Mapping[str, int]
    ) -> tuple[list[str], dict[str, int] | None]:
        """The brake, power off at rest, ``restore`` written where it differs from
        ``gains_now``: what was done (words) and the gains written (None: none)."""
        assert isinstance(ax.driver, StopModes)
        modes = ax.driver
        self.cancel_watch(axis_id)
        outcome = await modes.brake()
        if outcome.action == "brake":
            await self._rest(ax, BRAKE_MAX_S)
            await modes.power_off()
        done = [f"brought to rest ({', '.join(outcome.sent)}, then unpowered)"]
        if not {k: v for k, v in restore.items() if gains_now.get(k) != v}:
            return done, None
        await ax.driver.write_params(dict(restore))
        done.append("gains " + " ".join(f"{k} {v}" for k, v in restore.items()) + " restored")
        return done, dict(restore)

    async def _hold_again(self, ax: _Axis, axis_id: str, reason: str, done: list[str]) -> None:
        assert isinstance(ax.driver, StopModes)
        held = await ax.driver.hold_here()
        done.append("holding under power")
        self.follow(axis_id, held, reason)

    async def _rest(self, ax: _Axis, timeout_s: float) -> str:
        """Wait until the axis is seen at rest, ``timeout_s`` at most: "" when it was,
        else why not (for the event that follows)."""
        assert ax.loop is not None
        mark = self._start_mark(ax)
        deadline = self._clock() + timeout_s
        seen = False
        while self._clock() < deadline:
            await self._sleep(WATCH_PERIOD_S)
            after = [s for s in ax.history if s.t > mark]
            seen = seen or bool(after)
            if after and loopcheck.at_rest(after, ax.loop, since=after[0].t):
                return ""
        if not seen:
            return f"no telemetry in {timeout_s:g} s: not seen at rest"
        return f"not seen at rest within {timeout_s:g} s"

    # --- watches ------------------------------------------------------------------------

    def _start_mark(self, ax: _Axis) -> float:
        """Samples newer than this came after the stop went out."""
        return ax.history[-1].t if ax.history else -float("inf")

    async def _watch_hold(self, axis_id: str, ax: _Axis, reason: str) -> None:
        ax.unverified = False
        try:
            why = await self._hold_verdict(axis_id, ax, reason)
        finally:
            ax.unverified = False
        if not why:
            return
        ax.escalations += 1
        modes = ax.driver if isinstance(ax.driver, StopModes) else None
        try:
            outcome = await modes.brake() if modes is not None else await ax.driver.stop()
        except DriverError as exc:
            self._on_event(
                "error", axis_id, f"{reason}: the hold failed ({why}); brake not sent: {exc}"
            )
            return
        self._on_event(
            "error",
            axis_id,
            f"{reason}: the loop does not hold the axis after the stop ({why}): "
            f"{_describe(outcome)}",
        )
        if outcome is not None and outcome.action == "brake":
            await self._watch_brake(axis_id, ax, reason)

    async def _hold_verdict(self, axis_id: str, ax: _Axis, reason: str) -> str:
        """Watch a hold until a verdict: "" at rest, else why the loop does not hold.
        Telemetry that stops for ``WATCH_SILENT_S`` is told (not verified) and waited
        for; the samples after such a gap are judged afresh (module docstring)."""
        assert ax.loop is not None
        mark = self._start_mark(ax)
        started = self._clock()
        gap_s: float | None = None  # the last gap told, how long (the service's clock)
        silent_since = started
        while True:
            await self._sleep(WATCH_PERIOD_S)
            heard = max(started, ax.arrived)
            silent_s = self._clock() - heard
            if silent_s >= WATCH_SILENT_S:
                if not ax.unverified:
                    silent_since = heard
                    ax.unverified = True
                    mark = max(mark, self._start_mark(ax))
                    self._on_event(
                        "warning",
                        axis_id,
                        f"{reason}: no telemetry for {silent_s:.0f} s after the stop: the "
                        "hold is not verified (nothing sent on no evidence); the axis is "
                        "judged again when its telemetry returns",
                    )
                continue
            if ax.unverified:
                # Telemetry is back: what came after the gap is judged afresh.
                ax.unverified = False
                gap_s = heard - silent_since
            after = [s for s in ax.history if s.t > mark]
            if not after:
                continue
            verdict = loopcheck.judge(after, ax.loop, since=after[0].t)
            if verdict.working is False:
                return verdict.reason
            if loopcheck.at_rest(after, ax.loop, since=after[0].t):
                if gap_s is not None:
                    self._on_event(
                        "info",
                        axis_id,
                        f"{reason}: telemetry back after {gap_s:.1f} s without: the axis "
                        "is at rest and holding",
                    )
                return ""
            if after[-1].t - after[0].t >= WATCH_S:
                since = "its telemetry returned" if gap_s is not None else "the stop"
                return f"not at rest {WATCH_S:g} s after {since}"

    async def _watch_brake(self, axis_id: str, ax: _Axis, reason: str) -> None:
        assert ax.loop is not None
        not_rested = await self._rest(ax, BRAKE_MAX_S)
        modes = ax.driver if isinstance(ax.driver, StopModes) else None
        try:
            if modes is not None:
                await modes.power_off()
        except DriverError as exc:
            self._on_event(
                "error", axis_id, f"{reason}: the brake could not be switched off: {exc}"
            )
            return
        if not_rested:
            self._on_event(
                "warning",
                axis_id,
                f"{reason}: motor unpowered after {BRAKE_MAX_S:g} s of brake ({not_rested})",
            )
        else:
            self._on_event("info", axis_id, f"{reason}: at rest, motor unpowered")


@dataclass(frozen=True, slots=True)
class Settled:
    """What ``settle_check`` found and did when a loop the product set going was not
    working after it (``found`` "oscillating"), or could not be verified to work
    (``found`` "unverified": the telemetry too sparse to tell): ``reason`` (the loop
    check's words), what was done (``message``, a sentence for the run's quality and
    the event log), the gains written back (``restored``, None: none) and whether the
    axis holds under power at the end."""

    reason: str
    message: str
    restored: dict[str, int] | None
    holds: bool
    found: Literal["oscillating", "unverified"] = "oscillating"

    def as_dict(self) -> dict[str, object]:
        return {
            "reason": self.reason,
            "message": self.message,
            "restored": self.restored,
            "holds": self.holds,
        }


def gains_of(descriptor: DeviceDescriptor, values: Mapping[str, int]) -> dict[str, int]:
    """The gains among ``values`` (an axis' device values): its parameters of a group
    named "gains..." (SLAP2 kp ki kd; Z1100 KABH and KABD)."""
    names = [p.name for p in descriptor.parameters if p.group.startswith("gains")]
    return {name: values[name] for name in names if name in values}


def _describe(outcome: StopOutcome | None) -> str:
    if outcome is None:
        return "STOP sent"
    return f"{', '.join(outcome.sent)}: {outcome.message}" if outcome.sent else outcome.message


# --- a STOP that could not be sent at once, and STOP all --------------------------------

# A STOP that could not be sent is sent again once the link and axis are back; while the
# link is connected it is tried this many times before the user is told to press again.
STOP_RETRIES_CONNECTED = 10
# A STOP acts on the motion the user saw when pressing it, never on motion started
# after it: a pending STOP is dropped by any command that reached the axis since, by a
# STOP that reached it since (the dead-man's, a hand-over's), and after this long. A
# STOP delivered 30 s late would cut whatever whoever stands at the machine started
# meanwhile (a network cut that ends late delivers it late); after 10 s the
# user is told it was not sent, and checks the axis.
PENDING_STOP_MAX_S: Final = 10.0


class StopOvertakenError(DeviceRefusedError):
    """A STOP not sent because the axis was commanded or stopped after it was pressed."""


@runtime_checkable
class PressTimedStop(Protocol):
    """A driver whose STOP carries when it was pressed, so that the far end (a rig,
    ``servotune.bus``) can refuse it if its axis was commanded since
    (``StopOvertakenError``). ``pressed_at``: the hub's clock."""

    async def stop_pressed(self, pressed_at: float) -> None: ...


class StopTarget(Protocol):
    """What ``StopDelivery`` asks of the hub's state (``HubState``)."""

    def entries(self) -> list[AxisEntry]: ...

    def entry(self, axis_id: str) -> AxisEntry: ...

    def link_status(self, link_id: str) -> LinkStatus: ...

    def on_event(self, level: EventLevel, axis_id: str | None, message: str) -> None: ...

    def show_status(self, entry: AxisEntry) -> None:
        """Send every client the axis' status."""
        ...

    def spawn(self, coro: Coroutine[Any, Any, None], name: str) -> asyncio.Task[None]:
        """Run ``coro`` as a task the hub keeps, cancels at its stop and reports if it fails."""
        ...


class StopDelivery:
    """STOP all, and a STOP that could not reach its axis: kept pending (on the axis'
    record), sent the moment its link and axis are back, dropped - and told - when the
    axis was commanded or stopped since or after ``PENDING_STOP_MAX_S``."""

    def __init__(
        self, target: StopTarget, stops: StopService, *, clock: Callable[[], float]
    ) -> None:
        self._target = target
        self._stops = stops
        self._clock = clock

    async def stop_all(self) -> list[str]:
        """STOP every axis at once; returns the ids of axes whose stop failed."""
        target = self._target
        entries = target.entries()
        pressed_at = self._clock()
        for entry in entries:
            entry.operated = True
            entry.stopped("STOP was pressed")
        results = await asyncio.gather(
            *(self.send_stop(e, pressed_at) for e in entries), return_exceptions=True
        )
        failed = []
        for entry, result in zip(entries, results, strict=True):
            if isinstance(result, StopOvertakenError):
                target.on_event("info", entry.info.id, f"STOP not sent: {result}")
            elif isinstance(result, BaseException):
                failed.append(entry.info.id)
                if isinstance(result, Exception):
                    self.schedule(entry, result, pressed_at)
                else:
                    raise result
            else:
                self.note_stopped(entry)
                said = f": {', '.join(result.sent)}: {result.message}" if result else ""
                target.on_event("warning", entry.info.id, f"STOP{said}")
        for entry in entries:
            target.show_status(entry)
        return failed

    async def send_stop(self, entry: AxisEntry, pressed_at: float) -> StopOutcome | None:
        """The axis' STOP: a driver that can (a rig's axis, whose rig judges the stop)
        is told when it was pressed; every other goes through the stop service (the
        shortest safe stop, watched to rest)."""
        driver = entry.driver
        if isinstance(driver, PressTimedStop):
            self._stops.cancel_watch(entry.info.id)
            await driver.stop_pressed(pressed_at)
            return None
        return await self._stops.stop(entry.info.id, "stop", "STOP")

    def schedule(self, entry: AxisEntry, error: Exception, pressed_at: float) -> None:
        """A STOP pressed at ``pressed_at`` failed: say why and what happens next."""
        link_state = self._target.link_status(entry.link.id).state
        self.pend(entry, pressed_at)
        if isinstance(error, LinkDownError) or link_state != "connected":
            plan = (
                f"link {entry.link.id} is {link_state}: the STOP will be sent the moment "
                f"the link and the axis are back, unless the axis is commanded or stopped "
                f"before, and not after {PENDING_STOP_MAX_S:g} s"
            )
        else:
            plan = "the STOP is being sent again now"
        self._target.on_event("error", entry.info.id, f"STOP not delivered: {error}; {plan}")
        if link_state == "connected":
            self.ensure_task(entry)

    def pend(self, entry: AxisEntry, pressed_at: float | None = None) -> None:
        """Keep a STOP that could not reach the axis, pressed at ``pressed_at`` (now if
        None), for the axis' return (the control lock's dead-man uses this too)."""
        entry.stop_on_reconnect = True
        entry.stop_pressed_at = self._clock() if pressed_at is None else pressed_at
        entry.stop_pressed_wall = time.time() - (self._clock() - entry.stop_pressed_at)

    def note_stopped(self, entry: AxisEntry) -> None:
        """A STOP reached the axis (any: a user's, STOP all, the dead-man's, a
        hand-over's): a STOP pressed before it has nothing left to stop."""
        entry.stopped_at = self._clock()
        if entry.stop_on_reconnect:
            self._drop(entry, "the axis was stopped since")

    def note_commanded(self, entry: AxisEntry, what: str) -> None:
        """A command reached the axis: a STOP pressed before it must not act on the
        motion it may have started."""
        entry.commanded_at = self._clock()
        if entry.stop_on_reconnect:
            self._drop(entry, f"the axis was commanded since ({what})")

    def overtaken(self, entry: AxisEntry, pressed_at: float) -> str | None:
        """Why a STOP pressed at ``pressed_at`` (this hub's clock) must not be sent any
        more (the axis was commanded or stopped since), or None: send it."""
        axis_id = entry.info.id
        if entry.commanded_at > pressed_at:
            ago = self._clock() - entry.commanded_at
            return (
                f"{axis_id} was commanded {ago:.1f} s ago, "
                f"{entry.commanded_at - pressed_at:.1f} s after this STOP was pressed"
            )
        if entry.stopped_at > pressed_at:
            ago = self._clock() - entry.stopped_at
            return f"{axis_id} was already stopped {ago:.1f} s ago, after this STOP was pressed"
        return None

    def tick(self, entry: AxisEntry) -> None:
        """The status tick: expire the axis' pending STOP, or deliver it if the axis is
        back (its link may have come back without a change of its health)."""
        pending = entry.stop_on_reconnect and not self.expire(entry)
        if pending and entry.health != "offline":
            self.ensure_task(entry)

    def _pressed_text(self, entry: AxisEntry) -> str:
        pressed = entry.stop_pressed_at if entry.stop_pressed_at is not None else self._clock()
        wall = time.strftime("%H:%M:%S", time.localtime(entry.stop_pressed_wall))
        return f"pressed at {wall}, {self._clock() - pressed:.1f} s ago"

    def _drop(self, entry: AxisEntry, why: str) -> None:
        self._target.on_event(
            "info", entry.info.id, f"STOP ({self._pressed_text(entry)}) not sent: {why}"
        )
        self._cancel(entry)

    def expire(self, entry: AxisEntry) -> bool:
        """Drop a pending STOP older than PENDING_STOP_MAX_S (told); True if it was."""
        if entry.stop_pressed_at is None:
            self.pend(entry)  # set by someone who did not say when: from now
        assert entry.stop_pressed_at is not None
        if self._clock() - entry.stop_pressed_at <= PENDING_STOP_MAX_S:
            return False
        self._target.on_event(
            "error",
            entry.info.id,
            f"STOP ({self._pressed_text(entry)}) was never delivered and is no longer "
            f"pending (after {PENDING_STOP_MAX_S:g} s it could stop motion started later): "
            "check the axis and press STOP again if it moves",
        )
        self._cancel(entry)
        return True

    def _cancel(self, entry: AxisEntry) -> None:
        entry.stop_on_reconnect = False
        entry.stop_pressed_at = None
        task, entry.stop_task = entry.stop_task, None
        if task is not None and task is not asyncio.current_task():
            task.cancel()

    def ensure_task(self, entry: AxisEntry) -> None:
        """Deliver the axis' pending STOP in a task of its own (one at a time)."""
        if entry.stop_task is not None and not entry.stop_task.done():
            return
        entry.stop_task = self._target.spawn(
            self._deliver(entry), f"delivering a STOP to {entry.info.id}"
        )

    async def _deliver(self, entry: AxisEntry) -> None:
        """Send the pending STOP as soon as the link is connected and the axis online;
        retried while the link stays connected, until it is on the wire. A link that
        goes down again keeps the STOP pending for its next return. Dropped, and
        told, when it expires or is overtaken (``PENDING_STOP_MAX_S``)."""
        target = self._target
        tries = 0
        while entry.stop_on_reconnect:
            if self.expire(entry):
                return
            link_state = target.link_status(entry.link.id).state
            if link_state != "connected" or entry.health == "offline":
                # Health turns ok while the link still probes its other axes.
                await asyncio.sleep(0.05)
                continue
            pressed_at = entry.stop_pressed_at
            assert pressed_at is not None
            why = self.overtaken(entry, pressed_at)
            if why is not None:
                self._drop(entry, why)
                return
            try:
                await self.send_stop(entry, pressed_at)
            except StopOvertakenError as exc:
                # The far end (a rig) knows its axis better: commanded or stopped since.
                self._drop(entry, str(exc))
                return
            except LinkDownError:
                await asyncio.sleep(0.05)
                continue
            except DriverError as exc:
                tries += 1
                if tries >= STOP_RETRIES_CONNECTED:
                    entry.stop_on_reconnect = False
                    target.on_event(
                        "error",
                        entry.info.id,
                        f"STOP could not be delivered after {tries} tries: {exc} — "
                        "check the axis and press STOP again",
                    )
                    return
                await asyncio.sleep(0.1)
                continue
            pressed = self._pressed_text(entry)
            entry.stop_on_reconnect = False
            entry.stop_pressed_at = None
            entry.stopped_at = self._clock()
            target.on_event(
                "warning", entry.info.id, f"STOP sent ({pressed}; it could not go out before)"
            )
            target.show_status(entry)
            return
