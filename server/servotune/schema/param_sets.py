"""Named parameter sets of an axis (``.../param-sets``)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

# A parameter set's name is a path segment of its URL: no "/", no leading or trailing
# space, and at least one character that is neither a dot nor a space, so "." and ".."
# (which a browser folds away when it normalises the URL) and " " can never be saved.
# Letters, digits, "_", spaces inside and . , + ( ) # - are allowed ("#" is sent as %23).
SET_NAME_PATTERN = r"^(?:[\w.,+()#-][\w .,+()#-]*)?[\w,+()#-](?:[\w .,+()#-]*[\w.,+()#-])?$"
SET_NAME_MAX = 60


class SaveSetRequest(BaseModel):
    """``POST .../param-sets``: the set's name (see ``SET_NAME_PATTERN``) and a note."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(min_length=1, max_length=SET_NAME_MAX, pattern=SET_NAME_PATTERN)
    note: str = Field(default="", max_length=200)


class SavedSet(BaseModel):
    """``POST .../param-sets``: the name saved and the values read from the device."""

    name: str
    params: dict[str, int]


class ParamSet(BaseModel):
    """A named set of parameter values as read from the device when it was saved."""

    name: str
    created_s: float = Field(description="unix seconds")
    device: str
    params: dict[str, int]
    note: str


class ParamSetComparison(BaseModel):
    """``device`` (read now) against the set; ``differing`` names the parameters whose
    values differ (the UI adds its own unsaved values as the third column)."""

    name: str
    device: dict[str, int]
    saved: dict[str, int]
    differing: list[str]
