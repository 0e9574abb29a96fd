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

Limits (what nats-server 2.9's configuration offers; it has no per-user or per-account
message rates, so one rig's flood is limited by the hub, ``bus.gate``): each user may
connect only the way it must (``allowed_connection_types``: a leaf rig's user only as
a leaf node, every other user only as a client), a rig answers each request at most
twice (taken, outcome: ``allow_responses``), and the lab's account bounds its
JetStream streams and consumers and its subscriptions (``LabLimits``).
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
    # How many answers the user may publish to each request it received (0: none).
    allow_responses: int = 0

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
            parts.append(f"allow_responses: {{ max: {self.allow_responses} }}")
        return "{ " + ", ".join(parts) + " }"


def _list(items: tuple[str, ...]) -> str:
    return "[" + ", ".join(f'"{item}"' for item in items) + "]"


def rig_permissions(rig: str, *, leaf: bool = False) -> Permissions:
    """``leaf``: the rig's nats-server is a leaf node in JetStream domain ``<rig>``; the
    lab's stream sources the rig's runs through it (``bus.leaf``), which needs the
    lab's domain-API requests into the leaf and the leaf's answers and deliveries."""
    subjects.check_token("rig", rig)
    root = f"{subjects.PREFIX}.{rig}"
    # The two literal subjects are inside ``<root>.>`` already: they are there for
    # nats-server's leaf nodes, which pass the hub's subscriptions with a wildcard in
    # the rig's token (``servotune.v1.*.presence``, ``*.manifest``: how the hub finds
    # a rig it does not know yet) to a leaf only if one of its user's publish entries
    # matches them token by token (nats-server 2.9.10, checked in
    # tests/integration/bus/test_leaf.py; without them such a subscription hears no leaf rig).
    publish: tuple[str, ...] = (f"{root}.>", subjects.presence(rig), subjects.manifest(rig))
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
    # Two answers to a command: "taken" before it runs, then its outcome (bus.rig).
    return Permissions(publish_allow=publish, subscribe_allow=subscribe, allow_responses=2)


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
    """The hub's viewing user (its ``view`` connection): every rig's telemetry, events
    and manifest; the only requests it may send are reads (parameters, a rig's
    snapshot, the last values of the rigs and presence streams). Not a single
    command: what a hub viewer does goes through this connection or nowhere. It may
    not subscribe to a command subject either: a subscriber there would answer
    nats-server's "anyone listening?" for a rig that is gone (no-responders)."""
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
        subscribe_allow=(
            f"{prefix}.*.*.*.telemetry",
            f"{prefix}.*.events",
            subjects.RIGS_SUBJECTS,
            "_INBOX.>",
        ),
    )


def hub_stop_permissions() -> Permissions:
    """The hub's STOP user (its ``stop`` connection, the safety lane ``bus.lane``):
    STOP one axis, STOP a rig, the session's keep-alives and the clock probes; it
    hears the rigs' presence. Nothing else."""
    prefix = subjects.PREFIX
    return Permissions(
        publish_allow=(
            f"{prefix}.*.*.*.cmd.{subjects.STOP}",
            f"{prefix}.*.cmd.stop_all",
            f"{prefix}.*.cmd.keepalive",
            f"{prefix}.*.cmd.{subjects.CLOCK}",
        ),
        subscribe_allow=(subjects.PRESENCE_SUBJECTS, "_INBOX.>"),
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
    # "STANDARD" (a client), "LEAFNODE" (a rig's own nats-server), ...
    connection_types: tuple[str, ...] = ("STANDARD",)


@dataclass(frozen=True, slots=True)
class LabLimits:
    """The lab account's limits (``accounts_conf``): JetStream streams and consumers
    (the lab needs 3 streams and the hub's consumer; the rest is headroom for tools)
    and subscriptions (a rig uses about 10, the hub 3 per rig): bounds against a
    client gone wrong, not a share per rig (nats-server 2.9 has none per user)."""

    max_streams: int = 16
    max_consumers: int = 64
    max_subscriptions: int = 10_000

    @classmethod
    def for_lab(cls, rigs: int) -> LabLimits:
        return cls(max_subscriptions=10_000 + 100 * rigs)


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
    rig_connection = ("LEAFNODE",) if leaf else ("STANDARD",)
    accounts += [
        Account(rig, secrets.token_urlsafe(24), rig_permissions(rig, leaf=leaf), rig_connection)
        for rig in rigs
    ]
    accounts += [
        Account(subjects.check_token("viewer", v), secrets.token_urlsafe(24), viewer_permissions())
        for v in viewers
    ]
    names = [a.user for a in accounts]
    if len(set(names)) != len(names):
        raise ValueError("user names must be distinct (hub, rigs and viewers)")
    return accounts


def accounts_conf(accounts: list[Account], limits: LabLimits | None = None) -> str:
    """The ``accounts`` block: one account with JetStream, every user in it."""
    if limits is None:
        rigs = sum(1 for a in accounts if a.permissions.allow_responses)
        limits = LabLimits.for_lab(rigs)
    users = ",\n".join(
        f'    {{ user: "{a.user}", password: "{a.password}", '
        f"allowed_connection_types: {_list(a.connection_types)}, "
        f"permissions: {a.permissions.to_conf()} }}"
        for a in accounts
    )
    return (
        "# Written by `servotune bus-accounts`: users, permissions and limits of the lab's\n"
        "# bus (docs/lab.md). Storage is the server's (jetstream { max_file_store }).\n"
        f"accounts {{\n  {ACCOUNT} {{\n"
        f"    jetstream: {{ max_streams: {limits.max_streams}, "
        f"max_consumers: {limits.max_consumers} }}\n"
        f"    limits: {{ max_subscriptions: {limits.max_subscriptions} }}\n"
        f"    users = [\n{users}\n    ]\n"
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
