"""The auto-tune's API-facing state: the identify request and the per-axis session."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Final, Literal

from pydantic import BaseModel, Field

from servotune.autotune.proposal import Proposal, Response
from servotune.link.base import InvalidArgumentError
from servotune.tuning.plants import OUTPUT_FULL_SCALE
from servotune.tuning.targets import DEFAULT_PRESET, Preset

TestKind = Literal["position_step", "move"]
SessionState = Literal["idle", "identifying", "proposed", "kept", "verifying", "verified", "failed"]
DEFAULT_TEST_DISTANCE: Final = 1000
HISTORY_LENGTH: Final = 20  # decisions a session keeps (the runs keep theirs for good)


class IdentifyRequest(BaseModel):
    """``POST /api/axes/{id}/autotune/identify``: the user's limits and the goal."""

    max_pwm: int = Field(
        ge=1, le=OUTPUT_FULL_SCALE, description="largest open-loop PWM (-255..255)"
    )
    max_distance_counts: int = Field(
        ge=1,
        le=1 << 24,
        description="no test travels further than this from where it starts (counts)",
    )
    response: Response = Field(
        default="no_overshoot", description="no_overshoot (<= 1 %) or fast (<= 10 %)"
    )
    test: TestKind = Field(
        default="position_step",
        description="the test the gains are tuned for: position_step (sv/sa at maximum) "
        "or move (the axis' own sv/sa)",
    )
    direction: Literal[1, -1] = Field(
        default=1, description="1: identify and test towards positive counts, -1: negative"
    )
    margins: Preset = Field(
        default=DEFAULT_PRESET,
        description="the margin target the gains are designed to: stiff (PM 40 deg / GM 6 dB), "
        "medium (45 deg / 8 dB) or soft (60 deg / 12 dB)",
    )
    distance: int | None = Field(
        default=None,
        ge=1,
        le=1 << 24,
        description="distance of the baseline and verification tests, counts "
        f"(default: {DEFAULT_TEST_DISTANCE} or half of max_distance_counts if smaller)",
    )

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
    state: SessionState = "idle"
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

    def set(self, state: SessionState, message: str) -> None:
        self.state = state
        self.message = message
        self.updated_s = time.time()
