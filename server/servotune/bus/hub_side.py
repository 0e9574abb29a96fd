"""The central hub on the bus (``servotune hub --bus URL``): finds the lab's rigs, feeds
their ``RemoteLink``s, keeps its session alive on every rig, and collects their runs.

* Rigs come from the rigs stream (last manifest per rig) at start-up (a rig that was
  ever on the bus is listed, offline until its presence says otherwise), and at run
  time from the manifests rigs publish when they join: a new rig's links are
  registered live (``Hub.add_running_link``, ``ControlManager.add_link``) and every
  web client gets a new ``hello``, so its navigation lists the rig at once.
* Connections, one per kind of request (``BusPort``), each its own NATS user with
  its own permissions (``accounts``): ``view`` (subscriptions, snapshots, parameter
  reads: may not publish any command), ``operate`` (commands, parameter writes,
  console, the JetStream API) and ``stop`` (STOP, STOP all, keep-alives).
* Presence: the hub listens to the rigs' presence messages (every 0.5 s per rig);
  ``offline_after_s`` (1.5 s) of silence shows the rig offline, and a "gone" presence
  (a rig stopping cleanly) at once.
* Keep-alive: every ``keepalive_period_s`` (100 ms) on the STOP connection, to every
  rig, with this hub's session id; the rig's dead-man stops what this session moved
  when they stop coming (hub killed, lab network or leaf link cut).
* Runs: a durable pull consumer on ``SERVOTUNE_RUNS`` writes every run into the hub's
  SQLite store with the rig's name; acknowledged after the write, so a run published
  while the hub was down is delivered when it is back (JetStream replay). A run
  already stored (redelivery) is acknowledged and skipped.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import secrets

from nats.aio.client import Client
from nats.aio.msg import Msg
from nats.errors import Error as NatsError
from nats.errors import TimeoutError as NatsTimeoutError
from nats.js.api import ConsumerConfig, StorageType, StreamConfig
from nats.js.errors import Error as JetStreamError
from nats.js.errors import NotFoundError
from pydantic import ValidationError

from servotune.bus import subjects
from servotune.bus.connection import BusSettings, connect_bus, role_settings
from servotune.bus.leaf import ensure_sources
from servotune.bus.messages import KeepAlive, RigManifest, RunRecord
from servotune.bus.remote import BusPort, RemoteLink, hub_id
from servotune.bus.tasks import BackgroundTasks
from servotune.control import ControlManager
from servotune.hub import Hub
from servotune.storage import Storage, StorageError

logger = logging.getLogger(__name__)

RUNS_DUPLICATE_WINDOW_S = 24 * 3600.0


async def ensure_bus_state(nc: Client) -> None:
    """Create the rigs, presence and runs streams if they are missing (the hub's job)."""
    js = nc.jetstream()
    for config in (
        StreamConfig(
            name=subjects.RIGS_STREAM,
            subjects=[subjects.RIGS_SUBJECTS],
            max_msgs_per_subject=1,
            storage=StorageType.FILE,
        ),
        StreamConfig(
            name=subjects.PRESENCE_STREAM,
            subjects=[subjects.PRESENCE_SUBJECTS],
            max_msgs_per_subject=1,
            max_age=subjects.PRESENCE_TTL_S,
            storage=StorageType.MEMORY,
        ),
        StreamConfig(
            name=subjects.RUNS_STREAM,
            subjects=[subjects.RUNS_SUBJECTS],
            storage=StorageType.FILE,
            duplicate_window=RUNS_DUPLICATE_WINDOW_S,
        ),
    ):
        assert config.name is not None
        try:
            await js.stream_info(config.name)
        except NotFoundError:
            await js.add_stream(config=config)


async def last_values(nc: Client, stream: str) -> dict[str, bytes]:
    """The last message of every subject of a one-message-per-subject stream."""
    js = nc.jetstream()
    info = await js.stream_info(stream, subjects_filter=">")
    found = {}
    for subject in sorted((info.state.subjects or {}).keys()):
        with contextlib.suppress(NotFoundError):
            msg = await js.get_last_msg(stream, subject)
            if msg.data is not None:
                found[subject.split(".")[2]] = msg.data
    return found


class HubBus:
    """The hub's side of the bus; lives for the app's lifespan."""

    def __init__(self, settings: BusSettings) -> None:
        if settings.hub is None:
            raise ValueError("a hub needs a name on the bus")
        self.name = subjects.check_token("--hub-name", settings.hub)
        self._settings = settings
        self._session = secrets.token_hex(16)
        self._nc: Client | None = None
        self._view_nc: Client | None = None
        self._stop_nc: Client | None = None
        self._port: BusPort | None = None
        self._hub: Hub | None = None
        self._control: ControlManager | None = None
        self._storage: Storage | None = None
        # Rigs are added by the manifest callback and at start: one at a time.
        self._adding = asyncio.Lock()
        # Rigs heard (presence) but not known: their manifest is being asked for.
        self._asking: set[str] = set()
        # Leaf rigs (their own JetStream domain) whose streams the lab's source.
        self._sourced: set[str] = set()
        self.links: dict[tuple[str, str], RemoteLink] = {}
        self._rigs: dict[str, list[RemoteLink]] = {}
        self._tasks = BackgroundTasks(logger)
        self.runs_stored = 0

    async def prepare(self, hub: Hub, storage: Storage) -> None:
        """Connect, create what is missing, and register every known rig's links."""
        self._hub, self._storage = hub, storage
        base = f"hub-{self.name}"
        self._nc = await connect_bus(role_settings(self._settings, "operate"), name=base)
        self._view_nc = await connect_bus(
            role_settings(self._settings, "view"), name=f"{base}-view"
        )
        self._stop_nc = await connect_bus(
            role_settings(self._settings, "stop"), name=f"{base}-stop"
        )
        await ensure_bus_state(self._nc)
        self._port = BusPort(
            self._nc,
            self._stop_nc,
            self._session,
            self.name,
            self._settings.request_timeout_s,
            self._settings.stop_timeout_s,
            view_nc=self._view_nc,
        )
        for manifest in await self._manifests():
            self._add_rig(manifest)

    async def _manifests(self) -> list[RigManifest]:
        assert self._view_nc is not None
        found = []
        for rig, data in (await last_values(self._view_nc, subjects.RIGS_STREAM)).items():
            try:
                found.append(RigManifest.model_validate_json(data))
            except ValidationError as exc:
                logger.error("rig %s: manifest not understood (%s); not listed", rig, exc)
        return found

    def _new_links(self, manifest: RigManifest) -> list[RemoteLink]:
        """RemoteLinks for the links of ``manifest`` the hub does not have yet."""
        assert self._hub is not None and self._port is not None
        links = []
        for info in manifest.links:
            key = (manifest.rig, info.info.id)
            known = self.links.get(key)
            if known is not None:
                if {a.local_id for a in known.remote_axes} != {a.info.id for a in info.axes}:
                    self._hub.on_event(
                        "warning",
                        None,
                        f"rig {manifest.rig}: the axes of link {info.info.id} changed; "
                        "restart the hub to list them",
                    )
                continue
            link = RemoteLink(
                manifest.rig,
                info,
                self._port,
                self._hub,
                self._settings.offline_after_s,
                self._hub.broadcast_model,
            )
            self.links[key] = link
            self._rigs.setdefault(manifest.rig, []).append(link)
            links.append(link)
        return links

    def _add_rig(self, manifest: RigManifest) -> None:
        """Before the hub starts: its links are registered with the others."""
        assert self._hub is not None
        self._rigs.setdefault(manifest.rig, [])
        for link in self._new_links(manifest):
            self._hub.add_link(link)

    async def _add_rig_live(self, manifest: RigManifest) -> None:
        """While the hub runs: a rig that joined (or a known rig's new link) is listed
        at once, locked by the hub's control lock like the others, and announced."""
        assert self._hub is not None and self._control is not None
        await self._source_leaf(manifest)
        async with self._adding:
            added = self._new_links(manifest)
            for link in added:
                await self._hub.add_running_link(link)
                self._control.add_link(link.id)
            if added:
                axes = sum(len(link.remote_axes) for link in added)
                logger.info("rig %s joined: %d link(s), %d axes", manifest.rig, len(added), axes)
                self._hub.on_event(
                    "info", None, f"rig {manifest.rig} joined the lab: {axes} axes listed"
                )

    async def _source_leaf(self, manifest: RigManifest) -> None:
        """A rig on its own leaf node: the lab's streams source its manifest and runs
        from its JetStream domain (``bus.leaf``); retried on the next presence."""
        if manifest.domain is None or manifest.rig in self._sourced or self._nc is None:
            return
        try:
            if await ensure_sources(self._nc, manifest.rig, manifest.domain):
                logger.info("rig %s: its streams sourced from its domain", manifest.rig)
            self._sourced.add(manifest.rig)
        except (NatsError, JetStreamError) as exc:
            logger.warning("rig %s: its streams not sourced yet (%s)", manifest.rig, exc)

    async def _ask_manifest(self, rig: str) -> None:
        """A rig heard but not known (a leaf rig whose manifest the lab's stream has not
        got, or one that joined unseen): ask it for its manifest."""
        assert self._view_nc is not None
        try:
            msg = await self._view_nc.request(
                subjects.rig_cmd(rig, "manifest"), b"{}", timeout=self._settings.request_timeout_s
            )
            manifest = RigManifest.model_validate_json(msg.data)
            if manifest.rig == rig:
                await self._add_rig_live(manifest)
        except (NatsError, ValidationError) as exc:
            logger.info("rig %s: manifest not got (%s); asked again on its next presence", rig, exc)
        finally:
            self._asking.discard(rig)

    async def start(self, control: ControlManager) -> None:
        """Listen to the rigs, keep the session alive, collect the runs."""
        assert self._view_nc is not None
        self._control = control
        nc = self._view_nc
        # One subscription to everything, dispatched here: nats-server 2.9 does not
        # carry a subscription with a wildcard in the rig's token (``...v1.*.presence``)
        # across a leaf link whose user may publish only ``servotune.v1.<rig>.>``
        # (checked: such a subscription hears nothing from a leaf rig; ``v1.>`` does).
        await nc.subscribe(f"{subjects.PREFIX}.>", cb=self._on_bus)
        await nc.flush()
        # A rig that registered between ``prepare`` and the subscription above (and
        # the leaf rigs' sources, which a lab's server keeps but a new hub checks).
        for manifest in await self._manifests():
            await self._add_rig_live(manifest)
        # Rigs already present: their last presence (younger than its age limit) counts.
        present = await last_values(nc, subjects.PRESENCE_STREAM)
        for rig, links in self._rigs.items():
            if rig in present and present[rig] != b"{}":
                for link in links:
                    link.on_presence()
        self._tasks.spawn(self._keepalive(), "bus: keep-alive")
        self._tasks.spawn(self._collect_runs(), "bus: runs")

    async def stop(self) -> None:
        if self._port is not None:
            self._port.closing = True
        await self._tasks.cancel_all()
        for nc in (self._nc, self._view_nc, self._stop_nc):
            if nc is not None:
                # A connection already cut (network down) fails its last flush.
                with contextlib.suppress(NatsError, TimeoutError, OSError):
                    await nc.close()

    # --- what the rigs publish --------------------------------------------------------

    async def _on_bus(self, msg: Msg) -> None:
        tokens = msg.subject.split(".")
        last = tokens[-1]
        if len(tokens) == 6 and last == "telemetry":
            await self._on_telemetry(msg)
        elif len(tokens) == 4 and last == "events":
            await self._on_events(msg)
        elif len(tokens) == 4 and last == "presence":
            await self._on_presence(msg)
        elif len(tokens) == 4 and last == "manifest":
            await self._on_manifest(msg)
        # Anything else (commands, keep-alives, runs) is not for the hub's view.

    async def _on_telemetry(self, msg: Msg) -> None:
        tokens = msg.subject.split(".")
        link = self.links.get((tokens[2], tokens[3]))
        if link is None:
            return
        rig_now = None
        if msg.headers and "St-Rig-Now" in msg.headers:
            with contextlib.suppress(ValueError):
                rig_now = float(msg.headers["St-Rig-Now"])
        try:
            link.on_telemetry(msg.data, rig_now)
        except ValidationError as exc:
            logger.warning("telemetry of %s not understood: %s", msg.subject, exc)

    async def _on_events(self, msg: Msg) -> None:
        rig = msg.subject.split(".")[2]
        links = self._rigs.get(rig)
        if not links:
            return
        try:
            message = json.loads(msg.data)
        except ValueError:
            return
        if not isinstance(message, dict):
            return
        if message.get("type") == "link_status":
            target = self.links.get((rig, str(message.get("link"))))
            if target is not None and target.present():
                target.on_message(message)
            return
        for link in links:
            if not link.present():
                continue
            if message.get("axis") is None:
                link.on_message(message)  # a rig-wide event: shown once
                return
            if any(a.local_id == message.get("axis") for a in link.remote_axes):
                link.on_message(message)
                return

    async def _on_presence(self, msg: Msg) -> None:
        rig = msg.subject.split(".")[2]
        gone = bool(msg.headers and msg.headers.get(subjects.GONE_HEADER))
        unknown = rig not in self._rigs and rig not in self._asking
        if unknown and not gone and self._control is not None and subjects.check_token_ok(rig):
            self._asking.add(rig)
            self._tasks.spawn(self._ask_manifest(rig), f"bus: manifest of {rig}")
        rig_now: float | None = None
        if msg.headers and "St-Rig-Mono" in msg.headers:
            with contextlib.suppress(ValueError):
                rig_now = float(msg.headers["St-Rig-Mono"])
        for link in self._rigs.get(rig, []):
            if gone:
                link.on_gone()
            else:
                link.on_presence(rig_now)

    async def _on_manifest(self, msg: Msg) -> None:
        rig = msg.subject.split(".")[2]
        try:
            manifest = RigManifest.model_validate_json(msg.data)
        except ValidationError as exc:
            logger.error("rig %s: manifest not understood (%s); not listed", rig, exc)
            return
        if manifest.rig != rig:
            logger.error("a manifest of rig %s on %s's subject: ignored", manifest.rig, rig)
            return
        await self._add_rig_live(manifest)

    # --- the session's keep-alive -----------------------------------------------------

    async def _keepalive(self) -> None:
        assert self._stop_nc is not None
        body = KeepAlive(session=self._session, hub=self.name).model_dump_json().encode()
        while True:
            for rig, links in list(self._rigs.items()):
                if any(link.present() for link in links):
                    with contextlib.suppress(NatsError):
                        await self._stop_nc.publish(subjects.rig_cmd(rig, "keepalive"), body)
            await asyncio.sleep(self._settings.keepalive_period_s)

    # --- runs -------------------------------------------------------------------------

    async def _collect_runs(self) -> None:
        assert self._nc is not None
        js = self._nc.jetstream()
        durable = f"hub-{self.name}-runs"
        subscription = await js.pull_subscribe(
            subjects.RUNS_SUBJECTS,
            durable=durable,
            stream=subjects.RUNS_STREAM,
            config=ConsumerConfig(ack_wait=30.0, max_ack_pending=64),
        )
        while True:
            try:
                messages = await subscription.fetch(8, timeout=1.0)
            except (NatsTimeoutError, TimeoutError):
                continue  # nothing new (nats-py raises asyncio's TimeoutError here)
            except (NatsError, JetStreamError) as exc:
                logger.info("runs not fetched (%s): retrying", exc)
                await asyncio.sleep(1.0)
                continue
            for msg in messages:
                try:
                    record = RunRecord.model_validate_json(msg.data)
                except ValidationError as exc:
                    logger.error("a run on the bus is not understood (%s): dropped", exc)
                    await msg.term()
                    continue
                try:
                    await asyncio.to_thread(self._store_run, record)
                except StorageError as exc:
                    logger.error("run %s not stored (%s): redelivered later", record.run, exc)
                    await msg.nak(delay=5.0)
                    continue
                await msg.ack()

    def _store_run(self, record: RunRecord) -> None:
        """Write one rig's run into the hub's store, under the hub's id of its axis
        (worker thread). A run already there (a redelivery) is left as it is."""
        assert self._storage is not None and self._hub is not None
        run = dict(record.run)
        run_id = str(run.pop("id"))
        if self._storage.get_run_meta(run_id) is not None:
            return
        axis_id = hub_id(record.rig, str(run.pop("axis_id", "")))
        try:
            axis_key = self._hub.entry(axis_id).storage_key
        except KeyError:
            axis_key = f"{record.rig}/{record.axis_key}"
        created_s = float(run.pop("created_s", 0.0) or 0.0)  # type: ignore[arg-type]
        status = str(run.pop("status", "complete"))
        run.pop("baseline", None)
        meta = {**run, "rig": record.rig, "rig_axis_key": record.axis_key}
        self._storage.create_run(run_id, axis_key, axis_id, created_s, meta)
        if record.samples:
            self._storage.append_samples(run_id, 0, record.samples)
        self._storage.finish_run(run_id, status, meta)
        self.runs_stored += 1
