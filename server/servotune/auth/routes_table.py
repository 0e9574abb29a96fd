"""Which permission every route needs: ONE table, checked on every request.

Keys are ``(method, route path template)`` exactly as FastAPI matched them
(``request.scope["route"].path``), websockets under method ``"WS"``. A route that is
not in this table answers 500 at request time and fails
``tests/integration/auth/test_routes.py``, which walks ``app.routes``: a route added
later without a declared permission cannot slip through.

Special values:
- ``PUBLIC``: no principal needed (the login call, the anonymous session probe).
- ``COMMAND``: the permission depends on the command named in the body
  (see :func:`command_permission`): ``stop``-group commands and aborts need only STOP,
  unless the command may power a motor (SLAP2 ``hold`` sends ``pm``): then MOVE, like
  every other command; ``save_*`` in the persist group needs PERSIST (a re-apply of
  stored settings is TUNE).
- ``CONSOLE_LINE``: the console. The caller needs CONSOLE, and then what the line is
  (see :func:`console_permission`, from the descriptor's console rules): a read needs
  nothing more, a parameter write TUNE, a line that is a descriptor command that
  command's permission (``pg`` is ``save_eeprom``: PERSIST; ``ma`` is a move: MOVE), a
  line that stores or erases settings PERSIST. A line whose effect the descriptor does
  not state is refused (422) and never sent.
"""

from __future__ import annotations

from servotune.auth.principal import (
    AUTOTUNE,
    BENCH,
    CONSOLE,
    LIMITS,
    MOVE,
    PARAM_SETS,
    PERSIST,
    STOP,
    TUNE,
    USERS,
    VIEW,
)
from servotune.descriptor import DeviceDescriptor, UnknownConsoleLineError

PUBLIC = "<public>"
COMMAND = "<command>"
CONSOLE_LINE = "<console line>"

ROUTE_PERMISSIONS: dict[tuple[str, str], str] = {
    # --- the dashboard itself (no bundle built): a static page with no data
    ("GET", "/"): PUBLIC,
    # --- axes, links, telemetry
    ("GET", "/api/axes"): VIEW,
    ("GET", "/api/links"): VIEW,
    ("GET", "/api/links/{link_id}/status"): VIEW,
    ("GET", "/api/axes/{axis_id}/descriptor"): VIEW,
    ("GET", "/api/axes/{axis_id}/params"): VIEW,
    ("PATCH", "/api/axes/{axis_id}/params"): TUNE,
    ("GET", "/api/axes/{axis_id}/state"): VIEW,
    ("POST", "/api/axes/{axis_id}/commands"): COMMAND,
    ("POST", "/api/stop"): STOP,
    ("POST", "/api/axes/{axis_id}/console"): CONSOLE_LINE,
    ("WS", "/ws"): VIEW,
    # --- parameter sets
    ("GET", "/api/axes/{axis_id}/param-sets"): VIEW,
    ("POST", "/api/axes/{axis_id}/param-sets"): PARAM_SETS,
    ("GET", "/api/axes/{axis_id}/param-sets/{name}/compare"): VIEW,
    ("POST", "/api/axes/{axis_id}/param-sets/{name}/restore"): PARAM_SETS,
    ("DELETE", "/api/axes/{axis_id}/param-sets/{name}"): PARAM_SETS,
    # --- test bench
    ("GET", "/api/axes/{axis_id}/bench"): VIEW,
    ("PUT", "/api/axes/{axis_id}/bench/limits"): LIMITS,
    ("POST", "/api/axes/{axis_id}/bench/runs"): BENCH,
    ("GET", "/api/axes/{axis_id}/bench/runs"): VIEW,
    ("POST", "/api/axes/{axis_id}/bench/runs/import"): BENCH,
    ("GET", "/api/bench/runs/{run_id}"): VIEW,
    ("DELETE", "/api/bench/runs/{run_id}"): BENCH,
    ("POST", "/api/bench/runs/{run_id}/baseline"): BENCH,
    ("GET", "/api/bench/runs/{run_id}/samples.csv"): VIEW,
    ("GET", "/api/bench/runs/{run_id}/run.json"): VIEW,
    # --- frequency response and what-if (servotune/api/frf_routes.py)
    ("GET", "/api/bench/runs/{run_id}/frf"): VIEW,
    ("GET", "/api/axes/{axis_id}/whatif"): VIEW,
    # --- auto-tune
    ("GET", "/api/axes/{axis_id}/autotune"): VIEW,
    ("POST", "/api/axes/{axis_id}/autotune/identify"): AUTOTUNE,
    ("POST", "/api/axes/{axis_id}/autotune/accept"): AUTOTUNE,
    ("POST", "/api/axes/{axis_id}/autotune/keep"): AUTOTUNE,
    ("POST", "/api/axes/{axis_id}/autotune/revert"): AUTOTUNE,
    # --- accounts, sessions, tokens, audit (servotune/api/auth_routes.py)
    ("GET", "/api/auth/session"): PUBLIC,
    ("POST", "/api/auth/login"): PUBLIC,
    ("POST", "/api/auth/logout"): VIEW,
    ("POST", "/api/auth/reauth"): VIEW,
    ("POST", "/api/auth/password"): VIEW,
    ("POST", "/api/auth/ws-ticket"): VIEW,
    ("GET", "/api/auth/tokens"): USERS,
    ("POST", "/api/auth/tokens"): USERS,
    ("DELETE", "/api/auth/tokens/{token_id}"): USERS,
    ("GET", "/api/users"): USERS,
    ("POST", "/api/users"): USERS,
    ("PATCH", "/api/users/{name}"): USERS,
    ("DELETE", "/api/users/{name}"): USERS,
    ("GET", "/api/audit"): VIEW,
    ("GET", "/api/audit.csv"): VIEW,
    # --- the live OpenAPI and its interactive page (servotune/api/app.py; local mode
    # only: an exposed server does not serve them)
    ("GET", "/openapi.json"): VIEW,
    ("GET", "/docs"): VIEW,
    # --- storage health (servotune/api/bench_routes.py)
    ("GET", "/api/storage"): VIEW,
    # --- the 3D twin (servotune/api/twin_routes.py)
    ("GET", "/twin"): VIEW,
    ("GET", "/twin/"): VIEW,
    ("GET", "/twin/axis/{axis_id}"): VIEW,
    ("WS", "/twin"): VIEW,
}

# Routes whose mutating call does not need the CSRF token: logging in creates the
# session the token is bound to. It still needs a JSON body and a same-origin browser
# context (see servotune.auth.middleware), which stops a cross-site form from logging
# a victim into the attacker's account.
CSRF_EXEMPT = frozenset({("POST", "/api/auth/login")})


def command_permission(descriptor: DeviceDescriptor, command: str) -> str:
    """The permission a descriptor command needs (unknown names: MOVE, the hub refuses them).

    STOP for the stops (every command of the ``stop`` group: STOP, power off, halt ...)
    and the aborts, which every role may send to any axis, held or not; but a command
    that may power a motor (``powers_motor``) is a change of the axis like a move, even
    in the stop group: MOVE, and the control lock.
    """
    aborts = {c.abort_command for c in descriptor.commands if c.abort_command}
    for spec in descriptor.commands:
        if spec.name != command:
            continue
        if spec.name in aborts or (spec.group == "stop" and not spec.powers_motor):
            return STOP
        if spec.group == "persist":
            return PERSIST if spec.name.startswith("save") else TUNE
        return MOVE
    return MOVE


def console_permission(descriptor: DeviceDescriptor, line: str) -> str:
    """The permission a console line needs besides CONSOLE (see the module doc).

    Raises UnknownConsoleLineError when the descriptor does not state what the line does.
    """
    rule = descriptor.console.rule(line)
    if rule.effect == "read":
        return CONSOLE
    if rule.effect == "write":
        return TUNE
    if rule.effect == "persist":
        return PERSIST
    return command_permission(descriptor, rule.command or "")


__all__ = [
    "COMMAND",
    "CONSOLE_LINE",
    "PUBLIC",
    "ROUTE_PERMISSIONS",
    "UnknownConsoleLineError",
    "command_permission",
    "console_permission",
]
