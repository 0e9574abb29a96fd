"""The central hub on the bus (``servotune hub --bus URL``): finds the lab's rigs, feeds
their ``RemoteLink``s, keeps its session alive on every rig, and collects their runs.

* Rigs come from the rigs stream (last manifest per rig) at start-up (a rig that was
  ever on the bus is listed, offline until its presence says otherwise), and at run
  time from the manifests rigs publish when they join: a new rig's links are
  registered live (``Hub.add_running_link``, ``ControlLock.add_link``) and every
  web client gets a new ``hello``, so its navigation lists the rig at once.
* Connections, one per kind of traffic, each its own NATS user with its own
  permissions (``accounts``): ``view`` (telemetry and events, one subscription per
  rig, snapshots, parameter reads: may not publish any command), ``operate``
  (commands, parameter writes, console, the JetStream API) and ``stop`` (STOP, the
  keep-alives, the rigs' presence and clock probes), the last in a thread of its own
  (``bus.lane``): nothing the other two carry can delay it.
* The hub subscribes to nothing it sends requests to (no ``servotune.v1.>``), so a
  request nobody answers is refused at once by nats-server (no-responders).
* Identity from the subject: telemetry, events, presence, manifests and runs are
  attributed to the rig (and axis) of the subject nats-server let the rig publish
  on; a message that names another is refused and logged (stored manifests too,
  when the hub starts).
* Telemetry passes ``bus.gate``: per rig at most ``rig_telemetry_bytes_per_s`` (its
  oldest shed first), nothing older than ``remote.LIVE_MAX_AGE_S``, and the hub's
  loop never spends more than half its time on it.
* Runs: a durable pull consumer on ``SERVOTUNE_RUNS`` writes every run into the hub's
  SQLite store with the rig's name; acknowledged after the write (which removes it
  from the work-queue stream, ``bus.streams``), so a run published while the hub was
  down is delivered when it is back (JetStream replay). A run already stored
  (redelivery) is acknowledged and skipped.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from collections.abc import Awaitable, Callable

from nats.aio.client import Client
from nats.aio.msg import Msg
from nats.errors import Error as NatsError
from nats.errors import TimeoutError as NatsTimeoutError
from nats.js.api import ConsumerConfig
from nats.js.errors import Error as JetStreamError
from nats.js.errors import NotFoundError
from pydantic import ValidationError

from servotune.bus import subjects
from servotune.bus.connection import BusSettings, connect_bus, role_settings
from servotune.bus.gate import PUMP_PERIOD_S, TelemetryGate
from servotune.bus.lane import SafetyLane
from servotune.bus.leaf import ensure_sources
from servotune.bus.messages import RigManifest, RunRecord
from servotune.bus.remote import LIVE_MAX_AGE_S, BusPort, RemoteLink, hub_id
from servotune.bus.replies import ReplyMux
from servotune.bus.streams import ensure_bus_state
from servotune.bus.tasks import BackgroundTasks
from servotune.hub.control_lock import ControlLock
from servotune.hub.hub import Hub
from servotune.storage import Storage, StorageError

logger = logging.getLogger(__name__)

__all__ = ["HubBus", "ensure_bus_state", "last_values"]

# A rig's telemetry waiting in nats-py for the hub's callback, at most (a last resort:
# ``bus.gate`` sheds long before); beyond, nats-py drops that rig's newest.
RIG_PENDING_BYTES = 16 << 20


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
        self._nc: Client | None = None
        self._view_nc: Client | None = None
        self.lane = SafetyLane(settings, self.name, self._on_unknown_rig)
        self._port: BusPort | None = None
        self._hub: Hub | None = None
        self._control: ControlLock | None = None
        self._storage: Storage | None = None
        # Rigs are added by the manifest callback and at start: one at a time.
        self._adding = asyncio.Lock()
        # Rigs heard (presence) but not known: their manifest is being asked for.
        self._asking: set[str] = set()
        # Leaf rigs (their own JetStream domain) whose streams the lab's source.
        self._sourced: set[str] = set()
        # Rigs whose telemetry and events the view connection subscribes to.
        self._subscribed: set[str] = set()
        self.links: dict[tuple[str, str], RemoteLink] = {}
        self._rigs: dict[str, list[RemoteLink]] = {}
        self._tasks = BackgroundTasks(logger)
        self.gate: TelemetryGate[tuple[RemoteLink, str, bytes]] = TelemetryGate(
            settings.rig_telemetry_bytes_per_s,
            max_wait_s=LIVE_MAX_AGE_S,
            on_shed=self._shed,
        )
        self.runs_stored = 0
        self.runs_refused = 0

    async def prepare(self, hub: Hub, storage: Storage) -> None:
        """Connect, create what is missing, and register every known rig's links."""
        self._hub, self._storage = hub, storage
        base = f"hub-{self.name}"
        self._nc = await connect_bus(
            role_settings(self._settings, "operate"), name=base, on_reconnect=self._reconnected
        )
        self._view_nc = await connect_bus(
            role_settings(self._settings, "view"), name=f"{base}-view"
        )
        await self.lane.start()
        self._tasks.spawn(self._turns(), "bus: the hub's loop turns")
        await ensure_bus_state(self._nc)
        mux = ReplyMux(self._nc)
        await mux.start()
        self._port = BusPort(
            self._nc,
            self._view_nc,
            self.lane,
            mux,
            self.name,
            self._settings.request_timeout_s,
            self._settings.stop_timeout_s,
            start_within_s=self._settings.command_start_within_s,
        )
        for manifest in await self._manifests():
            self._add_rig(manifest)

    async def _turns(self) -> None:
        """Tell the safety lane this loop turns: its keep-alives say the hub can act."""
        while True:
            self.lane.main_turned()
            await asyncio.sleep(self._settings.keepalive_period_s)

    async def _reconnected(self) -> None:
        """The lab's server is back: it may have restarted and lost the presence
        stream (memory) or more; create what is missing."""
        if self._nc is None:
            return
        try:
            await ensure_bus_state(self._nc)
        except (NatsError, JetStreamError, TimeoutError) as exc:
            logger.warning("bus: streams not checked after the reconnect (%s)", exc)

    async def _manifests(self) -> list[RigManifest]:
        """The rigs stream's manifests, each checked against its subject's rig."""
        assert self._view_nc is not None
        found = []
        for rig, data in (await last_values(self._view_nc, subjects.RIGS_STREAM)).items():
            try:
                manifest = RigManifest.model_validate_json(data)
            except ValidationError as exc:
                logger.error("rig %s: manifest not understood (%s); not listed", rig, exc)
                continue
            if manifest.rig != rig:
                logger.error(
                    "the stored manifest on rig %s's subject names rig %s: refused, not listed",
                    rig,
                    manifest.rig,
                )
                continue
            found.append(manifest)
        return found

    def _new_links(self, manifest: RigManifest) -> list[RemoteLink]:
        """RemoteLinks for the links of ``manifest`` the hub does not have yet."""
        assert self._hub is not None and self._port is not None
        live = self.lane.list_rig(manifest.rig)
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
                manifest.rig, info, self._port, self._hub, live, self._hub.broadcast_model
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
            await self._subscribe_rig(manifest.rig)
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

    def _on_unknown_rig(self, rig: str) -> None:
        """The lane heard a rig the hub does not list (a leaf rig whose manifest the
        lab's stream has not got, or one that joined unseen): ask for its manifest."""
        if rig in self._rigs or rig in self._asking or self._control is None:
            return
        self._asking.add(rig)
        self._tasks.spawn(self._ask_manifest(rig), f"bus: manifest of {rig}")

    async def _ask_manifest(self, rig: str) -> None:
        assert self._view_nc is not None
        try:
            msg = await self._view_nc.request(
                subjects.rig_cmd(rig, "manifest"), b"{}", timeout=self._settings.request_timeout_s
            )
            manifest = RigManifest.model_validate_json(msg.data)
            if manifest.rig == rig:
                await self._add_rig_live(manifest)
            else:
                logger.error(
                    "rig %s answered with a manifest of rig %s: refused", rig, manifest.rig
                )
        except (NatsError, TimeoutError, ValidationError) as exc:
            logger.info("rig %s: manifest not got (%s); asked again on its next presence", rig, exc)
        finally:
            self._asking.discard(rig)

    async def start(self, control: ControlLock) -> None:
        """Listen to the rigs, collect the runs (the lane keeps the session alive)."""
        assert self._view_nc is not None
        self._control = control
        # Manifests of every rig (the rig token a wildcard: nats-server 2.9.10 carries
        # it across a leaf link, tests/integration/bus/test_leaf.py); telemetry and
        # events per rig.
        await self._view_nc.subscribe(subjects.RIGS_SUBJECTS, cb=self._on_manifest)
        for rig in list(self._rigs):
            await self._subscribe_rig(rig)
        await self._view_nc.flush()
        # A rig that registered between ``prepare`` and the subscription above (and
        # the leaf rigs' sources, which a lab's server keeps but a new hub checks).
        for manifest in await self._manifests():
            await self._add_rig_live(manifest)
        self._tasks.spawn(self._pump(), "bus: telemetry pump")
        self._tasks.spawn(self._collect_runs(), "bus: runs")

    async def _subscribe_rig(self, rig: str) -> None:
        """The rig's telemetry and events, on subscriptions of their own: one rig's
        backlog in nats-py is that rig's alone."""
        if rig in self._subscribed or self._view_nc is None:
            return
        self._subscribed.add(rig)
        root = f"{subjects.PREFIX}.{rig}"
        await self._view_nc.subscribe(
            f"{root}.*.*.telemetry",
            cb=self._telemetry_of(rig),
            pending_bytes_limit=RIG_PENDING_BYTES,
        )
        await self._view_nc.subscribe(subjects.events(rig), cb=self._events_of(rig))

    async def stop(self) -> None:
        if self._port is not None:
            self._port.closing = True
        await self._tasks.cancel_all()
        await self.lane.stop()
        for nc in (self._nc, self._view_nc):
            if nc is not None:
                # A connection already cut (network down) fails its last flush.
                with contextlib.suppress(NatsError, TimeoutError, OSError):
                    await nc.close()

    # --- what the rigs publish --------------------------------------------------------

    def _telemetry_of(self, rig: str) -> Callable[[Msg], Awaitable[None]]:
        async def on_telemetry(msg: Msg) -> None:
            tokens = msg.subject.split(".")
            link = self.links.get((rig, tokens[3])) if len(tokens) == 6 else None
            if link is not None:
                self.gate.offer(rig, (link, tokens[4], msg.data), len(msg.data))

        return on_telemetry

    @staticmethod
    def _shed(item: tuple[RemoteLink, str, bytes]) -> None:
        item[0].batches_shed += 1

    async def _pump(self) -> None:
        """The gate's batches into the links, every ``PUMP_PERIOD_S``."""
        while True:
            await asyncio.sleep(PUMP_PERIOD_S)
            self.gate.take(self._deliver)

    @staticmethod
    def _deliver(rig: str, item: tuple[RemoteLink, str, bytes]) -> None:
        link, axis, data = item
        try:
            link.on_telemetry(axis, data)
        except ValidationError as exc:
            logger.warning("telemetry of rig %s not understood: %s", rig, exc)

    def _events_of(self, rig: str) -> Callable[[Msg], Awaitable[None]]:
        async def on_events(msg: Msg) -> None:
            self._on_events(rig, msg)

        return on_events

    def _on_events(self, rig: str, msg: Msg) -> None:
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

    async def _on_manifest(self, msg: Msg) -> None:
        rig = msg.subject.split(".")[2]
        try:
            manifest = RigManifest.model_validate_json(msg.data)
        except ValidationError as exc:
            logger.error("rig %s: manifest not understood (%s); not listed", rig, exc)
            return
        if manifest.rig != rig:
            logger.error("a manifest of rig %s on rig %s's subject: refused", manifest.rig, rig)
            return
        await self._add_rig_live(manifest)

    # --- runs -------------------------------------------------------------------------

    async def _collect_runs(self) -> None:
        assert self._nc is not None
        js = self._nc.jetstream()
        durable = f"hub-{self.name}-runs"
        subscription = None
        while True:
            if subscription is None:
                try:
                    subscription = await js.pull_subscribe(
                        subjects.RUNS_SUBJECTS,
                        durable=durable,
                        stream=subjects.RUNS_STREAM,
                        config=ConsumerConfig(ack_wait=30.0, max_ack_pending=64),
                    )
                except (NatsError, JetStreamError, TimeoutError) as exc:
                    logger.info("runs consumer not ready (%s): retrying", exc)
                    await asyncio.sleep(1.0)
                    continue
            try:
                messages = await subscription.fetch(8, timeout=1.0)
            except (NatsTimeoutError, TimeoutError):
                continue  # nothing new (nats-py raises asyncio's TimeoutError here)
            except NotFoundError:
                # The lab's server lost the stream or the consumer (a new store): the
                # stream is created again on reconnect, the consumer here.
                subscription = None
                await asyncio.sleep(1.0)
                continue
            except (NatsError, JetStreamError) as exc:
                logger.info("runs not fetched (%s): retrying", exc)
                await asyncio.sleep(1.0)
                continue
            for msg in messages:
                await self._take_run(msg)

    async def _take_run(self, msg: Msg) -> None:
        """One run of the stream: stored under the rig of its subject, then
        acknowledged; one that names another rig is refused (terminated) and logged."""
        rig = msg.subject.split(".")[2]
        try:
            record = RunRecord.model_validate_json(msg.data)
        except ValidationError as exc:
            logger.error("a run on the bus is not understood (%s): dropped", exc)
            await msg.term()
            return
        if record.rig != rig:
            self.runs_refused += 1
            logger.error(
                "a run on rig %s's subject names rig %s: refused, not stored (run %s)",
                rig,
                record.rig,
                record.run.get("id"),
            )
            await msg.term()
            return
        try:
            await asyncio.to_thread(self._store_run, record)
        except StorageError as exc:
            logger.error("run %s not stored (%s): redelivered later", record.run, exc)
            await msg.nak(delay=5.0)
            return
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
