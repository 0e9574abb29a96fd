"""The lab's nats-server accounts: who may publish and subscribe what (NATS does the
enforcing; servotune writes the configuration from the subjects it uses).

``servotune bus-accounts --rig rig-1 --rig rig-2 --viewer guest --out DIR`` writes
``DIR/accounts.conf`` (include it in nats-server's configuration) and one credentials
file per user, ``DIR/<user>.cred`` (user name, password; mode 0600), for
``--bus-credentials``. Passwords are random, written to those files only, never printed.

* a rig publishes only its own subtree ``servotune.v1.<rig>.>`` (telemetry, events,
  manifest, presence, runs; the JetStream streams capture those subjects, so a rig
  needs no JetStream API at all) and may answer requests; it subscribes only to its
  commands and to its own reply inbox (``_INBOX_<rig>``);
* the hub is three users, one per connection (``connection.role_settings``):
  ``<hub>`` sends commands to every rig and uses the JetStream API (it creates the
  streams and its durable consumer); ``<hub>-view`` reads everything under
  ``servotune.v1`` and may request only reads (parameters, snapshots, last values),
  so a hub viewer's path cannot command a rig even with a bug in the hub;
  ``<hub>-stop`` sends STOP and the session's keep-alives, nothing else;
* a viewer (a script that watches, a wall display) publishes nothing at all and
  subscribes to telemetry and events: a handmade command is refused by nats-server.
"""

from __future__ import annotations

import os
import secrets
from dataclasses import dataclass
from pathlib import Path

from servotune.bus import subjects

ACCOUNT = "LAB"


@dataclass(frozen=True, slots=True)
class Permissions:
    publish_allow: tuple[str, ...] = ()
    publish_deny: tuple[str, ...] = ()
    subscribe_allow: tuple[str, ...] = ()
    allow_responses: bool = False

    def to_conf(self) -> str:
        """nats-server configuration syntax of these permissions."""
        publish = []
        if self.publish_allow:
            publish.append(f"allow: {_list(self.publish_allow)}")
        if self.publish_deny:
            publish.append(f"deny: {_list(self.publish_deny)}")
        parts = [f"publish: {{ {', '.join(publish)} }}"]
        parts.append(f"subscribe: {{ allow: {_list(self.subscribe_allow)} }}")
        if self.allow_responses:
            parts.append("allow_responses: true")
        return "{ " + ", ".join(parts) + " }"


def _list(items: tuple[str, ...]) -> str:
    return "[" + ", ".join(f'"{item}"' for item in items) + "]"


def rig_permissions(rig: str, *, leaf: bool = False) -> Permissions:
    """``leaf``: the rig's nats-server is a leaf node in JetStream domain ``<rig>``; the
    lab's stream sources the rig's runs through it (``bus.leaf``), which needs the
    lab's domain-API requests into the leaf and the leaf's answers and deliveries."""
    subjects.check_token("rig", rig)
    root = f"{subjects.PREFIX}.{rig}"
    publish: tuple[str, ...] = (f"{root}.>",)
    subscribe: tuple[str, ...] = (
        f"{root}.*.*.cmd.*",
        f"{root}.cmd.*",
        f"{subjects.inbox_prefix(rig)}.>",
    )
    if leaf:
        # ``allow_responses`` does not cover replies across a leaf link (nats-server
        # 2.9: the hub's requests time out), so the leaf may publish to reply inboxes.
        publish += ("$JSC.>", "$JS.S.>", "_INBOX.>")
        subscribe += (f"$JS.{rig}.API.>", "$JS.FC.>")
    return Permissions(publish_allow=publish, subscribe_allow=subscribe, allow_responses=True)


def hub_permissions() -> Permissions:
    """The hub's operating user: commands to every rig (STOP aside), the JetStream API
    (it creates the streams, reads them, and runs its durable consumer of the runs)."""
    prefix = subjects.PREFIX
    return Permissions(
        publish_allow=(f"{prefix}.*.*.*.cmd.*", f"{prefix}.*.cmd.*", "$JS.API.>", "$JS.ACK.>"),
        publish_deny=(f"{prefix}.*.*.*.cmd.{subjects.STOP}",),
        subscribe_allow=("_INBOX.>",),
    )


def hub_view_permissions() -> Permissions:
    """The hub's viewing user (its ``view`` connection): every rig's telemetry, events,
    presence and manifest; the only requests it may send are reads (parameters, a
    rig's snapshot, the last values of the rigs and presence streams). Not a single
    command: what a hub viewer does goes through this connection or nowhere."""
    prefix = subjects.PREFIX
    return Permissions(
        publish_allow=(
            *(f"{prefix}.*.*.*.cmd.{verb}" for verb in subjects.READ_VERBS),
            f"{prefix}.*.cmd.snapshot",
            f"{prefix}.*.cmd.manifest",
            f"$JS.API.STREAM.INFO.{subjects.RIGS_STREAM}",
            f"$JS.API.STREAM.INFO.{subjects.PRESENCE_STREAM}",
            f"$JS.API.STREAM.MSG.GET.{subjects.RIGS_STREAM}",
            f"$JS.API.STREAM.MSG.GET.{subjects.PRESENCE_STREAM}",
        ),
        subscribe_allow=(f"{prefix}.>", "_INBOX.>"),
    )


def hub_stop_permissions() -> Permissions:
    """The hub's STOP user (its ``stop`` connection): STOP one axis, STOP a rig, and
    the session's keep-alives; nothing else."""
    prefix = subjects.PREFIX
    return Permissions(
        publish_allow=(
            f"{prefix}.*.*.*.cmd.{subjects.STOP}",
            f"{prefix}.*.cmd.stop_all",
            f"{prefix}.*.cmd.keepalive",
        ),
        subscribe_allow=("_INBOX.>",),
    )


def viewer_permissions() -> Permissions:
    prefix = subjects.PREFIX
    return Permissions(
        publish_deny=(">",),
        subscribe_allow=(f"{prefix}.*.*.*.telemetry", f"{prefix}.*.events"),
    )


@dataclass(frozen=True, slots=True)
class Account:
    user: str
    password: str
    permissions: Permissions


def lab_accounts(
    hub: str, rigs: list[str], viewers: list[str], *, leaf: bool = False
) -> list[Account]:
    """A random password for every user (``secrets``), with its permissions."""
    subjects.check_token("hub", hub)
    accounts = [
        Account(hub, secrets.token_urlsafe(24), hub_permissions()),
        Account(f"{hub}-view", secrets.token_urlsafe(24), hub_view_permissions()),
        Account(f"{hub}-stop", secrets.token_urlsafe(24), hub_stop_permissions()),
    ]
    accounts += [
        Account(rig, secrets.token_urlsafe(24), rig_permissions(rig, leaf=leaf)) for rig in rigs
    ]
    accounts += [
        Account(subjects.check_token("viewer", v), secrets.token_urlsafe(24), viewer_permissions())
        for v in viewers
    ]
    names = [a.user for a in accounts]
    if len(set(names)) != len(names):
        raise ValueError("user names must be distinct (hub, rigs and viewers)")
    return accounts


def accounts_conf(accounts: list[Account]) -> str:
    """The ``accounts`` block: one account with JetStream, every user in it."""
    users = ",\n".join(
        f'    {{ user: "{a.user}", password: "{a.password}", '
        f"permissions: {a.permissions.to_conf()} }}"
        for a in accounts
    )
    return (
        "# Written by `servotune bus-accounts`: users and permissions of the lab's bus.\n"
        f"accounts {{\n  {ACCOUNT} {{\n    jetstream: enabled\n    users = [\n{users}\n    ]\n"
        "  }\n}\n"
    )


def write_private(path: Path, text: str) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as handle:
        handle.write(text)
    path.chmod(0o600)


def write_lab_accounts(directory: Path, accounts: list[Account]) -> list[Path]:
    """``accounts.conf`` and ``<user>.cred`` per user in ``directory`` (all 0600)."""
    directory.mkdir(parents=True, exist_ok=True)
    written = [directory / "accounts.conf"]
    write_private(written[0], accounts_conf(accounts))
    for account in accounts:
        path = directory / f"{account.user}.cred"
        write_private(path, f"{account.user}\n{account.password}\n")
        written.append(path)
    return written
