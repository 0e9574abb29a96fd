"""The documented error answers of the REST routes (``responses=`` of every route).

Every 4xx/5xx body is an ``ErrorBody``; which codes a route can answer follows from
what it does: any route with a body or path parameters can answer 422; a route that
talks to a device can answer 409 (refused), 502 (protocol error), 503 (link down,
nothing sent) and 504 (no answer).
"""

from __future__ import annotations

from typing import Any

from servotune.schema import ErrorBody

DESCRIPTIONS: dict[int, str] = {
    401: "not logged in (exposed mode): log in or send a bearer token",
    403: "refused: the role lacks the permission, or a Host / Origin / CSRF check failed",
    404: "no such axis, link, run or parameter set (detail names it)",
    409: "refused: by the device, or the axis/run is busy (reason in detail)",
    413: "request body too large",
    422: "bad input: detail names the field and the allowed range; nothing was sent",
    423: "locked: another browser tab controls this axis (detail names the holder)",
    429: "too many failed logins, or too many at once: wait (Retry-After) and try again",
    502: "the device answered something its protocol does not allow",
    503: "link down or storage unavailable: nothing was sent",
    504: "the device did not answer in time",
}

# The device path: every route that sends something to a device or reads from one.
DEVICE_CODES = (404, 409, 422, 423, 502, 503, 504)


def errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    """``responses=`` for these status codes, each with the ``ErrorBody`` model."""
    return {code: {"model": ErrorBody, "description": DESCRIPTIONS[code]} for code in codes}


DEVICE_ERRORS = errors(*DEVICE_CODES)
NOT_FOUND = errors(404, 422)


def json_errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    """Like ``errors`` for a route whose success is not JSON (a CSV download): the
    error bodies are still JSON ``ErrorBody``."""
    ref = {"$ref": "#/components/schemas/ErrorBody"}
    return {
        code: {"description": DESCRIPTIONS[code], "content": {"application/json": {"schema": ref}}}
        for code in codes
    }
