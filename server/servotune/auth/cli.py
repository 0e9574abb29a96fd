"""``servotune users ...`` and ``servotune tokens ...``, and the serve/demo security options.

The first admin is made here, never by a first-come web form. Passwords are read
with getpass (twice) or, for scripts and containers, one line from stdin
(``--password-stdin``); never from the command line, where ``ps`` and the shell
history would show them. A token is printed once, when it is made.

Changes take effect at once for REST calls of a running server (it reads the same
``auth.db``); the server also re-checks open websockets every few seconds and closes
those whose session or token is gone (``servotune.auth.install``).
"""

from __future__ import annotations

import argparse
import getpass
import sys
import time
from pathlib import Path

from servotune.auth.audit import ANONYMOUS_RETENTION_DAYS
from servotune.auth.passwords import WeakPasswordError, check_password_rule, hash_password
from servotune.auth.permissions import ADMIN, ROLE_ORDER, UnknownRoleError
from servotune.auth.security import AUTH_DB, SecurityConfig
from servotune.auth.store import TOKEN_DEFAULT_DAYS, AccountError, AuthStore


def add_security_arguments(parser: argparse.ArgumentParser) -> None:
    """The exposed-mode options of ``serve`` and ``demo``."""
    group = parser.add_argument_group("remote access (exposed mode)")
    group.add_argument("--tls-cert", type=Path, default=None, help="PEM certificate (TLS)")
    group.add_argument("--tls-key", type=Path, default=None, help="PEM private key (TLS)")
    group.add_argument(
        "--proxy",
        action="append",
        default=[],
        metavar="ADDR",
        help="address, network or name of the TLS reverse proxy in front; forwarded "
        "headers are trusted from it only (repeatable)",
    )
    group.add_argument(
        "--public-host",
        action="append",
        default=[],
        metavar="NAME",
        help="host name the dashboard is reached by (Host header allowlist; repeatable)",
    )
    group.add_argument(
        "--audit-anonymous-days",
        type=_positive_days,
        default=ANONYMOUS_RETENTION_DAYS,
        metavar="DAYS",
        help="days the audit log keeps the rows of anonymous callers: refused requests "
        f"and failed logins (default {ANONYMOUS_RETENTION_DAYS:g}); other rows are kept",
    )
    group.add_argument(
        "--mode",
        choices=("auto", "local", "exposed"),
        default="auto",
        help="auto (default): exposed when bound to a non-loopback address or given "
        "TLS or a proxy; local: no login, on 0.0.0.0 only with --loopback-published (a "
        "container whose port is published on the host's loopback); exposed: login even "
        "on 127.0.0.1",
    )


def _positive_days(text: str) -> float:
    try:
        days = float(text)
    except ValueError:
        days = 0.0
    if not days > 0:
        raise argparse.ArgumentTypeError(f"days must be a number above 0 (got {text!r})")
    return days


def security_config_from_args(args: argparse.Namespace, host: str) -> SecurityConfig:
    return SecurityConfig(
        mode=None if args.mode == "auto" else args.mode,
        host=host,
        tls_cert=args.tls_cert,
        tls_key=args.tls_key,
        proxy=list(args.proxy),
        public_hosts=list(args.public_host),
        audit_anonymous_days=args.audit_anonymous_days,
    )


def _read_password(args: argparse.Namespace) -> str:
    if args.password_stdin:
        password = sys.stdin.readline().rstrip("\r\n")
    else:
        password = getpass.getpass("password: ")
        if getpass.getpass("again: ") != password:
            raise AccountError("the two passwords differ")
    check_password_rule(password)
    return password


def account_data_dir(args: argparse.Namespace) -> Path:
    """The data directory a ``users``/``tokens`` command works on.

    ``--data-dir`` may stand before the action (``users --data-dir D add ...``) or after
    it (``users add ... --data-dir D``), as the recipes print it; given twice it must
    name the same directory.
    """
    from servotune.storage import default_data_dir

    before: Path | None = args.data_dir
    after: Path | None = getattr(args, "action_data_dir", None)
    if before is not None and after is not None and before != after:
        raise AccountError(f"--data-dir given twice: {before} and {after}")
    return after or before or default_data_dir()


def _store(args: argparse.Namespace, command: str) -> AuthStore:
    try:
        data_dir = account_data_dir(args)
    except AccountError as exc:
        print(f"servotune {command}: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    return AuthStore(data_dir / AUTH_DB)


def _when(t_s: float | None) -> str:
    return time.strftime("%Y-%m-%d %H:%M", time.localtime(t_s)) if t_s else "-"


def cmd_users(args: argparse.Namespace) -> int:
    from servotune.auth.audit import AuditLog

    store = _store(args, "users")
    audit = AuditLog(store.path)
    try:
        action = args.users_command
        if action == "list":
            for user in store.list_users():
                print(f"{user.name:24} {user.role:9} since {_when(user.created_s)}")
            return 0
        if action == "add":
            password = _read_password(args)
            store.add_user(args.name, args.role, hash_password(password))
            detail = "first admin" if store.count_users() == 1 else ""
            audit.record(
                who="cli",
                action="user add",
                after={"name": args.name, "role": args.role},
                detail=detail,
            )
            print(f"user {args.name} ({args.role}) added")
            return 0
        if action == "remove":
            gone = store.get_user(args.name)
            if gone is not None and gone.role == ADMIN and store.count_admins() <= 1:
                raise AccountError("the last admin cannot be removed")
            store.remove_user(args.name)
            audit.record(who="cli", action="user remove", before={"name": args.name})
            print(f"user {args.name} removed (sessions and tokens with it)")
            return 0
        if action == "passwd":
            if store.get_user(args.name) is None:
                raise AccountError(f"no user {args.name!r}")
            store.set_password_hash(args.name, hash_password(_read_password(args)))
            audit.record(who="cli", action="password change", detail=f"user {args.name}")
            print(f"password of {args.name} changed; their sessions ended")
            return 0
        if action == "role":
            changed = store.get_user(args.name)
            if changed is None:
                raise AccountError(f"no user {args.name!r}")
            if changed.role == ADMIN and args.role != ADMIN and store.count_admins() <= 1:
                raise AccountError("the last admin cannot lose the admin role")
            store.set_role(args.name, args.role)
            audit.record(
                who="cli",
                action="user change",
                before={"name": args.name, "role": changed.role},
                after={"name": args.name, "role": args.role},
            )
            print(f"{args.name} is now {args.role}; their sessions ended")
            return 0
        raise AssertionError(action)
    except (AccountError, UnknownRoleError, WeakPasswordError) as exc:
        print(f"servotune users {args.users_command}: {exc}", file=sys.stderr)
        return 2
    finally:
        audit.close()
        store.close()


def cmd_tokens(args: argparse.Namespace) -> int:
    from servotune.auth.audit import AuditLog

    store = _store(args, "tokens")
    audit = AuditLog(store.path)
    try:
        action = args.tokens_command
        if action == "list":
            for token in store.list_tokens(args.user):
                print(
                    f"{token.id}  {token.user:16} {token.role:9} {token.name:24} "
                    f"expires {_when(token.expires_s)}  last used {_when(token.last_used_s)}"
                )
            return 0
        if action == "create":
            user = store.get_user(args.user)
            if user is None:
                raise AccountError(f"no user {args.user!r}")
            secret, token = store.create_token(
                args.user, args.name, args.role or user.role, args.days
            )
            audit.record(
                who="cli",
                action="token create",
                after={"id": token.id, "user": token.user, "name": token.name, "role": token.role},
            )
            print(
                f"token {token.id} for {token.user} ({token.role}), "
                f"expires {_when(token.expires_s)}"
            )
            print("It is shown this once; send it as 'Authorization: Bearer <token>':")
            print(secret)
            return 0
        if action == "revoke":
            token = store.revoke_token(args.id)
            audit.record(
                who="cli", action="token revoke", before={"id": token.id, "user": token.user}
            )
            print(f"token {token.id} ({token.name}) revoked")
            return 0
        raise AssertionError(action)
    except (AccountError, UnknownRoleError) as exc:
        print(f"servotune tokens {args.tokens_command}: {exc}", file=sys.stderr)
        return 2
    finally:
        audit.close()
        store.close()


_DATA_DIR_HELP = (
    "the server's data directory, where auth.db lives (default: as for 'serve'; the "
    "demo's is <default>/demo, the hub's <default>/hub)"
)


def _action_data_dir(parser: argparse.ArgumentParser) -> None:
    # Its own dest: an action's default would otherwise overwrite a --data-dir given
    # before the action (argparse sets a subparser's defaults on the shared namespace).
    parser.add_argument(
        "--data-dir", dest="action_data_dir", type=Path, default=None, help=_DATA_DIR_HELP
    )


def add_account_commands(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Register ``users`` and ``tokens`` on the main parser's subcommands."""
    users = sub.add_parser("users", help="accounts for exposed mode (login)")
    users.add_argument("--data-dir", type=Path, default=None, help=_DATA_DIR_HELP)
    users_sub = users.add_subparsers(dest="users_command", required=True)
    _action_data_dir(users_sub.add_parser("list", help="list accounts"))
    for name, text in (("add", "create an account"), ("passwd", "set a new password")):
        p = users_sub.add_parser(name, help=text)
        p.add_argument("name")
        if name == "add":
            p.add_argument("--role", choices=ROLE_ORDER, required=True)
        p.add_argument("--password-stdin", action="store_true", help="read one line from stdin")
        _action_data_dir(p)
    remove = users_sub.add_parser("remove", help="delete an account, its sessions and tokens")
    remove.add_argument("name")
    _action_data_dir(remove)
    role = users_sub.add_parser("role", help="change an account's role")
    role.add_argument("name")
    role.add_argument("role", choices=ROLE_ORDER)
    _action_data_dir(role)
    users.set_defaults(func=cmd_users)

    tokens = sub.add_parser("tokens", help="API tokens for scripts (Authorization: Bearer)")
    tokens.add_argument("--data-dir", type=Path, default=None, help=_DATA_DIR_HELP)
    tokens_sub = tokens.add_subparsers(dest="tokens_command", required=True)
    listing = tokens_sub.add_parser("list", help="list tokens (never their secrets)")
    _action_data_dir(listing)
    listing.add_argument("--user", default=None)
    create = tokens_sub.add_parser("create", help="make a token; printed once")
    create.add_argument("user")
    create.add_argument("name", help="what the token is for, e.g. 'nightly-bench'")
    create.add_argument("--role", choices=ROLE_ORDER, default=None, help="at most the user's")
    create.add_argument("--days", type=int, default=TOKEN_DEFAULT_DAYS)
    _action_data_dir(create)
    revoke = tokens_sub.add_parser("revoke", help="delete a token")
    revoke.add_argument("id")
    _action_data_dir(revoke)
    tokens.set_defaults(func=cmd_tokens)
