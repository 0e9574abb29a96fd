"""A minimal viser client for the tests: speaks viser's wire format, keeps the scene.

Server -> client frames (viser 1.1): 8 bytes decompressed length, 8 bytes compressed
length (little endian), a zstd-compressed msgpack ``{"messages": [...]}``, then raw
binary buffers (unused by the twin's primitives). Each message is a dict with a
``type`` (the message class name) and its fields.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from typing import Any

import msgspec
import websockets
import zstandard
from websockets.asyncio.client import ClientConnection
from websockets.typing import Origin, Subprotocol


@dataclass
class SceneNode:
    kind: str
    props: dict[str, Any]
    wxyz: tuple[float, ...] | None = None
    position: tuple[float, ...] | None = None
    visible: bool | None = None
    orientations: list[tuple[float, tuple[float, ...]]] = field(default_factory=list)


@dataclass
class ViserScene:
    """The scene as a client sees it: nodes by name, updated by every frame."""

    nodes: dict[str, SceneNode] = field(default_factory=dict)
    replay_done: bool = False
    frames: int = 0

    def apply(self, frame: bytes) -> None:
        raw_len = int.from_bytes(frame[:8], "little")
        packed_len = int.from_bytes(frame[8:16], "little")
        inner = zstandard.ZstdDecompressor().decompress(
            frame[16 : 16 + packed_len], max_output_size=raw_len
        )
        self.frames += 1
        now = time.monotonic()
        for message in msgspec.msgpack.decode(inner)["messages"]:
            kind, name = message["type"], message.get("name")
            if kind == "ReplayDoneMessage":
                self.replay_done = True
            elif kind == "RemoveSceneNodeMessage":
                self.nodes.pop(name, None)
            elif kind == "SetOrientationMessage" and name in self.nodes:
                node = self.nodes[name]
                node.wxyz = tuple(message["wxyz"])
                node.orientations.append((now, node.wxyz))
            elif kind == "SetPositionMessage" and name in self.nodes:
                self.nodes[name].position = tuple(message["position"])
            elif kind == "SetSceneNodeVisibilityMessage" and name in self.nodes:
                self.nodes[name].visible = message["visible"]
            elif kind == "SceneNodeUpdateMessage" and name in self.nodes:
                self.nodes[name].props.update(message["updates"])
            elif kind.endswith("Message") and isinstance(message.get("props"), dict) and name:
                self.nodes[name] = SceneNode(kind.removesuffix("Message"), dict(message["props"]))


def angle_of(wxyz: tuple[float, ...]) -> float:
    """Inverse of ``servotune.twin.model.disc_wxyz``: the turn about the disc axis."""
    w, _, y, _ = wxyz
    return 2 * math.atan2(-y, w)


def same_angle(a: float, b: float, tolerance: float) -> bool:
    difference = (a - b + math.pi) % (2 * math.pi) - math.pi
    return abs(difference) <= tolerance


@contextlib.asynccontextmanager
async def viser_session(
    url: str, version: str, origin: str | None, headers: dict[str, str] | None = None
) -> AsyncIterator[tuple[ViserScene, ClientConnection]]:
    """Connect like viser's browser client (subprotocol ``viser-v<version>``; ``origin``
    None: a script's handshake, without one) and keep a ``ViserScene`` up to date in
    the background."""
    scene = ViserScene()
    async with websockets.connect(
        url,
        subprotocols=[Subprotocol(f"viser-v{version}")],
        origin=Origin(origin) if origin is not None else None,
        additional_headers=headers,
        max_size=None,
        compression=None,
    ) as connection:

        async def receive() -> None:
            async for frame in connection:
                assert isinstance(frame, bytes)
                scene.apply(frame)

        task = asyncio.create_task(receive())
        try:
            yield scene, connection
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, websockets.ConnectionClosed):
                await task


async def until(condition: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        await asyncio.sleep(0.05)
