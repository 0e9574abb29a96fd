"""What every device's gain rule shares with the generic auto-tune: the goal the user
picks (``Response``) and the proposal as a session holds it (``Proposal``).

Each device's rule returns its own proposal type (its gains, its model, its test); the
session and the REST routes need only its ``to_dict()`` body, whose shape is
``schema.AutoTuneProposal``. Typing only: the compute worker that imports a gain rule
loads nothing with it that the rule's ``tuning.targets`` does not load already.
"""

from __future__ import annotations

from typing import Any, Protocol

from servotune.schema import AutoTuneGoal

# no_overshoot: at most 1 % overshoot; fast: at most 10 % (each rule's OVERSHOOT_LIMIT_PCT)
Response = AutoTuneGoal


class Proposal(Protocol):
    """A gain rule's proposal: ``to_dict()`` is the body the API and the
    recommendation (``autotune.recommend``) read."""

    def to_dict(self) -> dict[str, Any]: ...
