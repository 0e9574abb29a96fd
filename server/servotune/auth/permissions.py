"""Roles as bundles of permission names, and which actions count as dangerous.

A role is only a name for a set of permissions; the server checks permissions, never
role names, so a future role (say "student") is one more line here. STOP is in every
role: stopping is the safe direction and anyone logged in may stop any axis.
"""

from __future__ import annotations

from servotune.auth.principal import (
    ALL_PERMISSIONS,
    AUDIT_ALL,
    AUTOTUNE,
    BENCH,
    CONSOLE,
    CONTROL,
    FORCE_CONTROL,
    LIMITS,
    MOVE,
    PARAM_SETS,
    PERSIST,
    STOP,
    TUNE,
    USERS,
    VIEW,
)

VIEWER = "viewer"
OPERATOR = "operator"
ADMIN = "admin"

_VIEWER_PERMISSIONS = frozenset({VIEW, STOP})
_OPERATOR_PERMISSIONS = _VIEWER_PERMISSIONS | {
    CONTROL,
    MOVE,
    TUNE,
    BENCH,
    AUTOTUNE,
    PARAM_SETS,
    CONSOLE,
}
_ADMIN_PERMISSIONS = _OPERATOR_PERMISSIONS | {PERSIST, LIMITS, FORCE_CONTROL, USERS, AUDIT_ALL}
assert _ADMIN_PERMISSIONS == ALL_PERMISSIONS

ROLES: dict[str, frozenset[str]] = {
    VIEWER: _VIEWER_PERMISSIONS,
    OPERATOR: _OPERATOR_PERMISSIONS,
    ADMIN: _ADMIN_PERMISSIONS,
}
ROLE_ORDER = (VIEWER, OPERATOR, ADMIN)

# Permissions whose use needs a password typed in the last REAUTH_AFTER_S seconds
# (session logins only; an API token was created under such a check already).
DANGEROUS = frozenset({USERS, PERSIST, LIMITS, FORCE_CONTROL})
REAUTH_AFTER_S = 300.0

# Permissions that change an axis: the control helper's per-axis lock applies to them.
LOCKED = frozenset({MOVE, TUNE, BENCH, AUTOTUNE, PARAM_SETS, CONSOLE, PERSIST})


class UnknownRoleError(ValueError):
    """A role name that is not one of ROLES."""


def permissions_of(role: str) -> frozenset[str]:
    """The permissions of ``role``; raises UnknownRoleError naming the valid roles."""
    try:
        return ROLES[role]
    except KeyError:
        raise UnknownRoleError(
            f"role must be one of {', '.join(ROLE_ORDER)}, got {role!r}"
        ) from None


def role_at_most(role: str, ceiling: str) -> bool:
    """True when ``role`` grants nothing ``ceiling`` does not (token role ≤ user role)."""
    return permissions_of(role) <= permissions_of(ceiling)
