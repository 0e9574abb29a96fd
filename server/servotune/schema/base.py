"""What the schema's modules share: the base of the documented shapes and JSON numbers."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field


class _Shape(BaseModel):
    """A body the server builds as a dict, documented by a model: no field beyond its own."""

    model_config = ConfigDict(extra="forbid")


# Numbers the server computes may be sent as integers: ``int | float`` keeps each as sent.
Number = int | float

FiniteFloat = Annotated[float, Field(strict=True, allow_inf_nan=False)]
"""A JSON number (not a string), never NaN or infinite (JSON has neither)."""
