"""A fake rig: a client of the lab's bus with a rig's credentials that speaks the rig
agent's protocol (manifest, presence, clock answers, snapshot, command answers, and
telemetry at a chosen rate) without a device behind it. Used by the flood test
(tests/integration/bus/test_faults.py, in a process of its own) and scripts/perf_bus_lab.py.

    python -m tests.support.fake_rig --url nats://... --credentials rig-b.cred --rig rig-b \\
        --axes 1 --samples-per-s 5000 --batch 1 --seconds 20

A sample's ``position`` channel is the wall clock when it was made and ``velocity`` a
per-axis sequence number, so a viewer can measure latency and count missing samples.
On exit it prints one JSON line: what it published.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import secrets
import sys
import time
from pathlib import Path
from typing import Any

import nats

from servotune import __version__
from servotune.bus import subjects
from servotune.bus.messages import ACK_HEADER, RemoteAxisInfo, RemoteLinkInfo, RigManifest
from servotune.devices.slap2.descriptor import slap2_descriptor
from servotune.schema import AxisInfo, LinkInfo

# The fake link's status, as a rig's link publishes it.
LINK_STATUS = {
    "type": "link_status",
    "link": "line",
    "state": "connected",
    "message": "",
    "rate_hz": 30.0,
    "wire_limit_hz": 100.0,
    "errors": 0,
}


class FakeRig:
    """The rig agent's side of the protocol, without a device behind it."""

    def __init__(
        self,
        name: str,
        axes: int,
        *,
        url: str,
        user: str,
        password: str,
        samples_per_s: float = 120.0,
        batch: int = 4,
    ) -> None:
        self.name = name
        self.axes = [f"ax-{i}" for i in range(axes)]
        self.url, self.user, self.password = url, user, password
        self.samples_per_s = samples_per_s  # per axis
        self.batch = batch
        self.nc: Any = None
        self.published = 0
        self.samples = 0
        self.bytes = 0
        self.instance = secrets.token_hex(8)
        self._t0 = time.monotonic()
        self._seq = dict.fromkeys(self.axes, 0)

    def now(self) -> float:
        return time.monotonic() - self._t0

    def clock_headers(self) -> dict[str, str]:
        return {subjects.RIG_NOW_HEADER: f"{self.now():.6f}", subjects.RIG_ID_HEADER: self.instance}

    def manifest(self) -> bytes:
        descriptor = slap2_descriptor(512)
        link = LinkInfo(id="line", device="slap2", path="/dev/fake", baud=115200)
        axes = [
            RemoteAxisInfo(
                info=AxisInfo(id=a, device="slap2", link="line", address=i, name=a),
                descriptor=descriptor,
            )
            for i, a in enumerate(self.axes)
        ]
        manifest = RigManifest(
            rig=self.name, server_version=__version__, links=[RemoteLinkInfo(info=link, axes=axes)]
        )
        return manifest.model_dump_json().encode()

    async def start(self) -> None:
        self.nc = await nats.connect(
            self.url,
            user=self.user,
            password=self.password,
            inbox_prefix=subjects.inbox_prefix(self.name),
            max_reconnect_attempts=-1,
            reconnect_time_wait=0.5,
        )
        root = f"{subjects.PREFIX}.{self.name}"
        await self.nc.subscribe(subjects.rig_cmd(self.name, "snapshot"), cb=self._snapshot)
        await self.nc.subscribe(subjects.rig_cmd(self.name, subjects.CLOCK), cb=self._clock)
        await self.nc.subscribe(subjects.rig_cmd(self.name, "keepalive"), cb=self._ignore)
        await self.nc.subscribe(f"{root}.*.*.cmd.*", cb=self._answer)
        await self.nc.jetstream().publish(subjects.manifest(self.name), self.manifest())

    async def _ignore(self, msg: Any) -> None:
        return None

    async def _clock(self, msg: Any) -> None:
        await self.nc.publish(msg.reply, b"", headers=self.clock_headers())

    async def _snapshot(self, msg: Any) -> None:
        messages = [json.dumps(LINK_STATUS)] + [
            json.dumps({"type": "params", "axis": a, "values": {"kp": 100}, "source": "read"})
            for a in self.axes
        ]
        await msg.respond(json.dumps(messages).encode())

    async def _answer(self, msg: Any) -> None:
        if not msg.subject.endswith(f".{subjects.STOP}") and not msg.subject.endswith("params"):
            await self.nc.publish(msg.reply, b"", headers={ACK_HEADER: "1"})
        await msg.respond(json.dumps({"ok": True, "result": {"values": {"kp": 100}}}).encode())

    async def presence(self) -> None:
        link = LINK_STATUS
        while True:
            body = json.dumps({"rig": self.name, "period_s": 0.5, "sent_wall_s": time.time()})
            await self.nc.publish(
                subjects.presence(self.name), body.encode(), headers=self.clock_headers()
            )
            await self.nc.publish(subjects.events(self.name), json.dumps(link).encode())
            await asyncio.sleep(0.5)

    def batch_body(self, axis: str) -> bytes:
        """One batch of ``self.batch`` samples, made over the last moments."""
        n = self.batch
        now_r, now_w = self.now(), time.time()
        spacing = 1.0 / self.samples_per_s
        seq = self._seq[axis]
        self._seq[axis] = seq + n
        ages = [spacing * (n - 1 - k) for k in range(n)]
        return json.dumps(
            {
                "type": "telemetry",
                "axis": axis,
                "t": [round(now_r - age, 6) for age in ages],
                "channels": {
                    "position": [now_w - age for age in ages],
                    "velocity": [float(seq + k) for k in range(n)],
                    "following_error": [0.0] * n,
                },
                "flags": {},
            }
        ).encode()

    async def telemetry(self) -> None:
        """``samples_per_s`` per axis in batches of ``batch``; a process that falls
        behind catches up in bursts (the rate is kept on average)."""
        period = self.batch / self.samples_per_s
        started = time.monotonic()
        batches = 0
        while True:
            due = int((time.monotonic() - started) / period) + 1
            while batches < due:
                for axis in self.axes:
                    body = self.batch_body(axis)
                    await self.nc.publish(
                        subjects.telemetry(self.name, "line", axis),
                        body,
                        headers={subjects.RIG_NOW_HEADER: f"{self.now():.6f}"},
                    )
                    self.published += 1
                    self.samples += self.batch
                    self.bytes += len(body)
                batches += 1
            await asyncio.sleep(max(0.0, started + batches * period - time.monotonic()))


async def _main(args: argparse.Namespace) -> None:
    user, password = Path(args.credentials).read_text().splitlines()[:2]
    rig = FakeRig(
        args.rig,
        args.axes,
        url=args.url,
        user=user,
        password=password,
        samples_per_s=args.samples_per_s,
        batch=args.batch,
    )
    await rig.start()
    tasks = [asyncio.create_task(rig.presence())]
    await asyncio.sleep(args.quiet_s)
    started = time.monotonic()
    tasks.append(asyncio.create_task(rig.telemetry()))
    await asyncio.sleep(args.seconds)
    elapsed = time.monotonic() - started
    for task in tasks:
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    await rig.nc.flush()
    print(
        json.dumps(
            {
                "published": rig.published,
                "samples": rig.samples,
                "bytes": rig.bytes,
                "seconds": elapsed,
                "samples_per_s": rig.samples / elapsed,
            }
        ),
        flush=True,
    )
    await rig.nc.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--url", required=True)
    parser.add_argument("--credentials", required=True)
    parser.add_argument("--rig", required=True)
    parser.add_argument("--axes", type=int, default=1)
    parser.add_argument("--samples-per-s", type=float, default=5000.0, help="per axis")
    parser.add_argument("--batch", type=int, default=1, help="samples per telemetry message")
    parser.add_argument("--quiet-s", type=float, default=0.0, help="presence only, first")
    parser.add_argument("--seconds", type=float, default=10.0)
    asyncio.run(_main(parser.parse_args()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
