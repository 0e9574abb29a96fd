"""A DriverSink that records everything a link reports."""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Mapping
from dataclasses import dataclass, field

from servotune.link.base import Sample
from servotune.schema import AxisHealth, EventLevel, LinkState


@dataclass
class RecordingSink:
    """A DriverSink that keeps everything a driver reports."""

    samples: dict[str, list[Sample]] = field(default_factory=lambda: defaultdict(list))
    states: list[tuple[LinkState, str]] = field(default_factory=list)
    health: dict[str, tuple[AxisHealth, str]] = field(default_factory=dict)
    health_log: list[tuple[str, AxisHealth, str]] = field(default_factory=list)
    params: dict[str, dict[str, int]] = field(default_factory=lambda: defaultdict(dict))
    events: list[tuple[EventLevel, str | None, str]] = field(default_factory=list)

    def on_sample(self, axis_id: str, sample: Sample) -> None:
        self.samples[axis_id].append(sample)

    def on_link_status(
        self,
        link_id: str,
        state: LinkState,
        message: str,
        rate_hz: float,
        wire_limit_hz: float,
        errors: int,
    ) -> None:
        if not self.states or self.states[-1] != (state, message):
            self.states.append((state, message))

    def on_axis_health(self, axis_id: str, health: AxisHealth, message: str) -> None:
        self.health[axis_id] = (health, message)
        self.health_log.append((axis_id, health, message))

    def on_params(self, axis_id: str, values: Mapping[str, int], source: str) -> None:
        self.params[axis_id].update(values)

    def on_event(self, level: EventLevel, axis_id: str | None, message: str) -> None:
        self.events.append((level, axis_id, message))
