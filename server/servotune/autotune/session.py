"""The auto-tune's API-facing state: the identify request and the per-axis session."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Final

from servotune.autotune.proposal import Proposal
from servotune.link.base import InvalidArgumentError
from servotune.schema import AutoTuneRequest, AutoTuneState

HISTORY_LENGTH: Final = 20  # decisions a session keeps (the runs keep theirs for good)


class IdentifyRequest(AutoTuneRequest):
    """``schema.AutoTuneRequest`` with the travel checks every device shares."""

    def checked_distance(
        self, bench_max_distance_counts: int, min_distance: int, default_distance: int
    ) -> int:
        """The test distance, after the travel checks every device shares: within the
        user's bench limit, long enough to identify (``min_distance``), and no further
        than ``max_distance_counts``. Raises InvalidArgumentError naming the field."""
        if self.max_distance_counts > bench_max_distance_counts:
            raise InvalidArgumentError(
                "max_distance_counts",
                f"max_distance_counts {self.max_distance_counts} exceeds your bench limit "
                f"of ±{bench_max_distance_counts} counts",
            )
        if self.max_distance_counts < min_distance:
            raise InvalidArgumentError(
                "max_distance_counts",
                f"max_distance_counts {self.max_distance_counts} is too small to identify "
                f"the axis: at least {min_distance} counts",
            )
        distance = self.distance or min(default_distance, self.max_distance_counts // 2)
        if distance > self.max_distance_counts:
            raise InvalidArgumentError(
                "distance",
                f"distance {distance} exceeds your limit max_distance_counts of "
                f"±{self.max_distance_counts}",
            )
        return distance


@dataclass(slots=True)
class Session:
    axis_id: str
    state: AutoTuneState = "idle"
    message: str = ""
    request: IdentifyRequest | None = None
    identification_run_id: str | None = None
    proposal: Proposal | None = None
    proposal_dict: dict[str, Any] | None = None
    model: dict[str, Any] | None = None
    device_settings: dict[str, int] = field(default_factory=dict)
    result: dict[str, Any] | None = None
    updated_s: float = 0.0
    # what the user chose for the current proposal (``autotune.recommend``), and the
    # decisions on this axis' earlier proposals since the server started, newest last
    decision: dict[str, Any] | None = None
    history: list[dict[str, Any]] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {
            "axis": self.axis_id,
            "state": self.state,
            "message": self.message,
            "request": self.request.model_dump() if self.request else None,
            "identification_run_id": self.identification_run_id,
            "model": self.model,
            "proposal": self.proposal_dict,
            "result": self.result,
            "decision": self.decision,
            "history": list(self.history),
            "updated_s": self.updated_s,
        }

    def reset(self, request: IdentifyRequest) -> None:
        """A new identification starts: forget the last proposal and result."""
        self.request = request
        self.proposal = self.proposal_dict = self.result = self.model = None
        self.identification_run_id = None
        self.decision = None

    def decide(self, decision: dict[str, Any]) -> None:
        """Record the user's choice for the current proposal (and in the history)."""
        self.decision = decision
        self.history = [*self.history, decision][-HISTORY_LENGTH:]

    def set(self, state: AutoTuneState, message: str) -> None:
        self.state = state
        self.message = message
        self.updated_s = time.time()
