"""Password hashing with Argon2id (argon2-cffi), and the rule a new password must meet.

Hashing takes tens of milliseconds and much memory on purpose: callers on the event
loop run :func:`hash_password` and :func:`verify_password` in a worker thread.
"""

from __future__ import annotations

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError, VerifyMismatchError

MIN_PASSWORD_LENGTH = 10
MAX_PASSWORD_LENGTH = 1024

# argon2-cffi's defaults are RFC 9106's "second recommended option" (Argon2id,
# t=3, m=64 MiB, p=4), kept as they are.
_HASHER = PasswordHasher()

# Verified against when the user name does not exist, so a login for an unknown name
# costs as long as one for a known name (no user enumeration by timing).
_DUMMY_HASH = _HASHER.hash("servotune-no-such-user")


class WeakPasswordError(ValueError):
    """A password that is too short or too long; the message says the rule."""


def check_password_rule(password: str) -> None:
    """Raise WeakPasswordError unless ``password`` has 10..1024 characters."""
    if not MIN_PASSWORD_LENGTH <= len(password) <= MAX_PASSWORD_LENGTH:
        raise WeakPasswordError(
            f"password must have {MIN_PASSWORD_LENGTH}..{MAX_PASSWORD_LENGTH} characters"
        )


def hash_password(password: str) -> str:
    """The Argon2id hash string (salt and parameters included) of ``password``."""
    return _HASHER.hash(password)


def verify_password(stored_hash: str | None, password: str) -> bool:
    """True when ``password`` matches; ``stored_hash`` None verifies a dummy (same cost)."""
    try:
        return _HASHER.verify(stored_hash or _DUMMY_HASH, password) and stored_hash is not None
    except (VerifyMismatchError, VerificationError, InvalidHashError):
        return False
