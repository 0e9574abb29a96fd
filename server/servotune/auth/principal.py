"""Who is asking: the principal of a request or websocket, and the permission names."""

from __future__ import annotations

from dataclasses import dataclass

VIEW = "view"
STOP = "stop"
CONTROL = "control"
MOVE = "move"
TUNE = "tune"
BENCH = "bench"
AUTOTUNE = "autotune"
PARAM_SETS = "param_sets"
CONSOLE = "console"
PERSIST = "persist"
LIMITS = "limits"
FORCE_CONTROL = "force_control"
USERS = "users"
AUDIT_ALL = "audit_all"

ALL_PERMISSIONS: frozenset[str] = frozenset(
    {
        VIEW,
        STOP,
        CONTROL,
        MOVE,
        TUNE,
        BENCH,
        AUTOTUNE,
        PARAM_SETS,
        CONSOLE,
        PERSIST,
        LIMITS,
        FORCE_CONTROL,
        USERS,
        AUDIT_ALL,
    }
)


@dataclass(frozen=True)
class Principal:
    """The authenticated caller: user name, role, and the permissions the role grants."""

    user: str
    role: str
    permissions: frozenset[str]
    session_id: str | None = None
    via: str = "local"


LOCAL_PRINCIPAL = Principal(user="local", role="admin", permissions=ALL_PERMISSIONS)
