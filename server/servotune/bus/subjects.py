"""Subject names, key-value buckets and the runs stream: the bus' address space, v1.

Every subject starts with ``servotune.v1.<rig>``; the version token lets a later
schema live beside this one. Rig, link and axis ids become subject tokens, so they may
use only letters, digits, ``-`` and ``_`` (a ``.`` would split a token, ``*``/``>`` are
wildcards): ``check_token`` refuses anything else at start-up, naming the field.
"""

from __future__ import annotations

import re

PREFIX = "servotune.v1"
# Last-value state: a rig's manifest (links, axes, descriptors: kept, so the hub lists
# a rig that is offline) and its presence (an age limit: older than that it is gone, so
# a hub starting later never sees a dead rig as present). Each is a stream with one
# message per subject and an age limit: exactly what a JetStream key-value bucket is
# underneath, on subjects inside the rig's own subtree. Why not the KV API: a KV bucket
# lives on ``$KV.<bucket>.*``, and nats-server 2.9 denies ``$KV.>`` and ``$JS.API.>``
# across a leaf node unless the system account is shared with the rig (docs/lab.md).
RIGS_STREAM = "SERVOTUNE_RIGS"
RIGS_SUBJECTS = f"{PREFIX}.*.manifest"
PRESENCE_STREAM = "SERVOTUNE_PRESENCE"
PRESENCE_SUBJECTS = f"{PREFIX}.*.presence"
PRESENCE_TTL_S = 2.0
# Recorded runs: one JetStream stream, one subject per rig, kept by the bus server.
RUNS_STREAM = "SERVOTUNE_RUNS"
RUNS_SUBJECTS = f"{PREFIX}.*.runs"
# Header of a presence message that says the rig left (a clean stop).
GONE_HEADER = "St-Gone"
# Headers of a rig's presence and clock answers: its clock (its server's ``Hub.now()``,
# the clock of its telemetry) and the id of its agent's run (a new one: a new clock).
RIG_NOW_HEADER = "St-Rig-Now"
RIG_ID_HEADER = "St-Rig-Id"

_TOKEN = re.compile(r"[A-Za-z0-9_-]{1,64}")
# Verbs that are not descriptor commands (a descriptor command name is a verb too).
WRITE_PARAMS = "write_params"
READ_PARAMS = "read_params"
CONSOLE = "console"
BENCH_START = "bench_start"
BENCH_RUNS = "bench_runs"
STOP = "stop"
# Rig-wide: the rig answers its clock (``bus.clock``), on its STOP connection.
CLOCK = "clock"
# Auto-tune from the hub (``bus.autotune``): long requests, run by the rig's AutoTuner.
AUTOTUNE_IDENTIFY = "autotune_identify"
AUTOTUNE_ACCEPT = "autotune_accept"
AUTOTUNE_REVERT = "autotune_revert"
AUTOTUNE_KEEP = "autotune_keep"
AUTOTUNE_VERBS = (AUTOTUNE_IDENTIFY, AUTOTUNE_ACCEPT, AUTOTUNE_REVERT, AUTOTUNE_KEEP)
RESERVED_VERBS = (WRITE_PARAMS, READ_PARAMS, CONSOLE, BENCH_START, BENCH_RUNS, *AUTOTUNE_VERBS)
# Verbs that only read: the hub sends them on its view connection (``accounts``).
READ_VERBS = (READ_PARAMS, BENCH_RUNS)


def check_token(field: str, value: str) -> str:
    """``value`` if it is a valid subject token, else ValueError naming ``field``."""
    if not _TOKEN.fullmatch(value):
        raise ValueError(
            f"{field} must be 1..64 letters, digits, '-' or '_' to be a NATS subject "
            f"token, got {value!r}"
        )
    return value


def check_token_ok(value: str) -> bool:
    return _TOKEN.fullmatch(value) is not None


def axis_root(rig: str, link: str, axis: str) -> str:
    return f"{PREFIX}.{rig}.{link}.{axis}"


def telemetry(rig: str, link: str, axis: str) -> str:
    return f"{axis_root(rig, link, axis)}.telemetry"


def axis_cmd(rig: str, link: str, axis: str, verb: str) -> str:
    return f"{axis_root(rig, link, axis)}.cmd.{verb}"


def rig_cmd(rig: str, verb: str) -> str:
    """Rig-wide requests: ``stop_all``, ``keepalive`` (hub session lease)."""
    return f"{PREFIX}.{rig}.cmd.{verb}"


def manifest(rig: str) -> str:
    return f"{PREFIX}.{rig}.manifest"


def presence(rig: str) -> str:
    return f"{PREFIX}.{rig}.presence"


def events(rig: str) -> str:
    """Status changes, parameters read back and events of every axis of the rig."""
    return f"{PREFIX}.{rig}.events"


def runs(rig: str) -> str:
    """A rig's finished runs (JetStream; ``Nats-Msg-Id`` is ``<rig>/<run id>``)."""
    return f"{PREFIX}.{rig}.runs"


def inbox_prefix(rig: str) -> str:
    """A rig's own reply inbox, so its permissions need not cover everyone's replies."""
    return f"_INBOX_{rig}"
