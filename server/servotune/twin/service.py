"""The twin's lifecycle: one viser server per dashboard process, fed from the hub.

Threads and loops (why it cannot slow the links): viser runs its own websocket
server on a daemon thread with its own asyncio loop. The app's loop runs one small
task (``_tick``) every ``TICK_PERIOD_S``: it reads each axis' latest sample
(``AxisEntry.latest``, the hub's latest-value slot), its link state and health into a
snapshot — a few attribute reads, no viser call — and hands the snapshot over in a
single slot guarded by a lock. A callback scheduled on viser's loop takes the newest
snapshot and applies it to the scene inside one ``atomic()`` block; when viser falls
behind, snapshots are overwritten, never queued. Starting (import of viser, binding
the port) and stopping (joining viser's thread) run in a worker thread.

Security: viser has no authentication and no Origin check. It binds 127.0.0.1 on a
port the OS picks (``port=0``; viser silently takes the next port when one is busy,
so the port is read back with ``get_port()``) and is reached only through the
dashboard's proxy (``servotune.api.twin_routes``), which proves itself with a random
secret in the ``X-Servotune-Twin`` header of its handshake. viser's websocket handler
runs its connect callbacks before it sends or reads a single message, so the last one
(``_admit``) closes every other connection (1008) before a scene frame leaves: a local
user who finds the port gets nothing. The HTTP side of the port serves only viser's
own client files (the pip package's), which hold no data.

viser can publish its port on the internet (``ShareUrlRequest`` from any client forks
a tunnel process to viser's share service). servotune never wants that: the handlers
are removed and ``request_share_url`` is replaced on the server (``_refuse_share``),
beside the proxy's allowlist of client messages that drops the request first.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import logging
import secrets
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from servotune.hub.hub import Hub
from servotune.link.base import Sample
from servotune.twin.model import node_slot

if TYPE_CHECKING:
    import viser

    from servotune.twin.scene import AxisInput, AxisScene, CameraView

logger = logging.getLogger(__name__)

TICK_PERIOD_S = 1 / 30
# The header that carries the proxy's secret to viser (see the module doc).
SECRET_HEADER = "X-Servotune-Twin"


@dataclass(slots=True)
class TwinStats:
    """Work done on viser's thread, for the measurements in docs/twin.md."""

    applied: int = 0
    apply_cpu_s: float = 0.0  # applying snapshots to the scene (viser's thread)
    snapshot_cpu_s: float = 0.0  # building snapshots (the app's loop)
    viser_thread_cpu_s: float = 0.0  # all CPU of viser's loop thread, at the last apply


class Twin:
    """The 3D twin of every axis. Build with ``await Twin.start(hub)``."""

    def __init__(self, hub: Hub, period_s: float = TICK_PERIOD_S) -> None:
        self._hub = hub
        self._period_s = period_s
        self._server: viser.ViserServer | None = None
        self._scenes: dict[str, AxisScene] = {}
        self._views: dict[str, CameraView] = {}
        self._rig_view: CameraView | None = None
        self._task: asyncio.Task[None] | None = None
        self._lock = threading.Lock()
        self._pending: dict[str, AxisInput] | None = None
        self._scheduled = False
        self._refresh = False
        self._viewers = 0
        self._seen: dict[str, tuple[Sample | None, float, int]] = {}
        self.stats = TwinStats()
        self.client_page: Path = Path()
        self.version = ""
        # The proxy's proof to viser; never leaves this process.
        self.secret = secrets.token_urlsafe(32)
        self.refused_connections = 0
        self.share_requests_refused = 0

    # --- lifecycle ----------------------------------------------------------------------

    @classmethod
    async def start(cls, hub: Hub, period_s: float = TICK_PERIOD_S) -> Twin:
        """Start viser (in a worker thread: importing it and binding take a while),
        build the scene of every axis whose descriptor has a ``twin`` part, and start
        feeding it."""
        twin = cls(hub, period_s)
        await asyncio.to_thread(twin._build)
        twin._task = asyncio.create_task(twin._tick(), name="twin ticker")
        return twin

    async def stop(self) -> None:
        """Stop feeding and stop viser (its thread is joined in a worker thread)."""
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        server, self._server = self._server, None
        if server is not None:
            await asyncio.to_thread(server.stop)

    def _build(self) -> None:
        import viser

        from servotune.twin import scene as twin_scene

        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
        self._lock_down(server)
        self.version = viser.__version__
        self.client_page = Path(viser.__file__).resolve().parent / "client" / "build" / "index.html"
        server.gui.configure_theme(show_logo=False, show_share_button=False)
        # The panel (connection, scene tree) starts folded: the picture is the point.
        server.gui.main_panel.minimize()
        server.scene.set_up_direction("+z")
        server.scene.world_axes.visible = False
        x = 0.0
        previous_link: str | None = None
        stage_anywhere = False
        for info in self._hub.axes_info():
            descriptor = self._hub.descriptor(info.id)
            if descriptor.twin is None:
                continue
            if previous_link is not None and info.link != previous_link:
                x += twin_scene.LINK_GAP
            previous_link = info.link
            axis_scene = twin_scene.AxisScene(
                server,
                f"/axes/{node_slot(info.id)}",
                x,
                info.name,
                descriptor,
                descriptor.twin,
            )
            self._scenes[info.id] = axis_scene
            self._views[info.id] = twin_scene.camera_for_span(x, x, axis_scene.has_stage)
            stage_anywhere = stage_anywhere or axis_scene.has_stage
            x += twin_scene.AXIS_PITCH
        last_x = max(x - twin_scene.AXIS_PITCH, 0.0)
        server.scene.add_grid(
            "/floor",
            width=last_x + 2.0,
            height=2.0,
            cell_size=0.25,
            position=(last_x / 2, 0.0, -0.8),
        )
        self._rig_view = twin_scene.camera_for_span(0.0, last_x, stage_anywhere)
        server.initial_camera.position = self._rig_view.position
        server.initial_camera.look_at = self._rig_view.look_at
        server.initial_camera.up = (0.0, 0.0, 1.0)
        self._server = server

    def _lock_down(self, server: viser.ViserServer) -> None:
        """No share tunnel, and nobody but the proxy on viser's port (module doc)."""
        from viser import _messages

        websock = server._websock_server
        for message in (_messages.ShareUrlRequest, _messages.ShareUrlDisconnect):
            if message in websock._incoming_handlers:
                websock.unregister_handler(message)
        # Instance attributes shadow the methods for every caller, viser's own included.
        server.request_share_url = self._refuse_share  # type: ignore[method-assign]
        server.disconnect_share_url = lambda: None  # type: ignore[method-assign]

        async def admit(connection: object) -> None:
            live = websock._live_connections.get(getattr(connection, "client_id", -1))
            if live is None:
                return
            presented = live.request.headers.get(SECRET_HEADER, "") if live.request else ""
            if not hmac.compare_digest(presented.encode(), self.secret.encode()):
                self.refused_connections += 1
                logger.warning("twin: a connection to viser's port without the proxy's secret")
                await live.close(1008, "connect through the dashboard")

        # Registered after viser's own callbacks: runs last, before any message flows.
        websock.on_client_connect(admit)

    def _refuse_share(self, verbose: bool = True) -> None:
        """viser's ``request_share_url``, refused: servotune never publishes the twin."""
        del verbose
        self.share_requests_refused += 1
        logger.warning("twin: a share URL was requested and refused")

    # --- what the proxy and the routes need ---------------------------------------------

    @property
    def port(self) -> int:
        """viser's port on 127.0.0.1 (read back: viser may not take the one asked for)."""
        assert self._server is not None, "twin not started"
        return self._server.get_port()

    @property
    def subprotocol(self) -> str:
        """The websocket subprotocol viser's client offers: the exact viser version."""
        return f"viser-v{self.version}"

    @property
    def axes(self) -> list[str]:
        return list(self._scenes)

    def node_root(self, axis_id: str) -> str:
        """Scene-tree path of an axis' group (KeyError if the axis is not drawn)."""
        return self._scenes[axis_id].root

    def rig_view(self) -> CameraView:
        assert self._rig_view is not None, "twin not started"
        return self._rig_view

    def axis_view(self, axis_id: str) -> CameraView:
        """The camera of an axis' own 3D view (KeyError if the axis is not drawn)."""
        return self._views[axis_id]

    def viewer_opened(self) -> None:
        """A browser connected through the proxy: send it the current state."""
        self._viewers += 1
        self._refresh = True

    def viewer_closed(self) -> None:
        self._viewers = max(0, self._viewers - 1)

    # --- feeding ------------------------------------------------------------------------

    async def _tick(self) -> None:
        from servotune.twin.scene import AxisInput

        while True:
            await asyncio.sleep(self._period_s)
            if self._viewers == 0:
                # Nobody looks: build nothing. The next viewer gets a full refresh.
                continue
            started = time.thread_time()
            now = time.monotonic()
            snapshot: dict[str, AxisInput] = {}
            for axis_id in self._scenes:
                entry = self._hub.entry(axis_id)
                sample = entry.latest
                last, seen_at, serial = self._seen.get(axis_id, (None, now, 0))
                if sample is not last:
                    seen_at, serial = now, serial + 1
                    self._seen[axis_id] = (sample, seen_at, serial)
                snapshot[axis_id] = AxisInput(
                    sample=sample,
                    sample_age_s=None if sample is None else now - seen_at,
                    link_state=self._hub.link_status(entry.link.id).state,
                    health=entry.health,
                    serial=serial,
                )
            self._hand_over(snapshot)
            self.stats.snapshot_cpu_s += time.thread_time() - started

    def _hand_over(self, snapshot: dict[str, AxisInput]) -> None:
        server = self._server
        if server is None:
            return
        with self._lock:
            self._pending = snapshot
            if self._scheduled:
                return
            self._scheduled = True
        try:
            server.get_event_loop().call_soon_threadsafe(self._apply_pending)
        except RuntimeError:
            # viser's loop is closed (shutting down): nothing to draw any more.
            with self._lock:
                self._scheduled = False

    def _apply_pending(self) -> None:
        """On viser's loop: apply the newest snapshot in one atomic block."""
        with self._lock:
            self._scheduled = False
            snapshot, self._pending = self._pending, None
            refresh, self._refresh = self._refresh, False
        server = self._server
        if snapshot is None or server is None:
            return
        started = time.thread_time()
        now = time.monotonic()
        try:
            with server.atomic():
                for axis_id, data in snapshot.items():
                    axis_scene = self._scenes[axis_id]
                    if refresh:
                        axis_scene.invalidate()
                    axis_scene.apply(data, now)
        except Exception:
            # A scene bug must be visible in the log, and must not stop the feed.
            logger.exception("twin update failed")
        self.stats.applied += 1
        finished = time.thread_time()
        self.stats.apply_cpu_s += finished - started
        self.stats.viser_thread_cpu_s = finished
