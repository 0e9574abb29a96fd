"""Requests whose answer comes in two parts, and may come late.

A rig answers a command twice: "taken" (``ACK_HEADER``) before it runs, then the
outcome. nats-py's ``request`` keeps one answer and forgets the request at its timeout;
here one wildcard subscription per connection (``<inbox>.*``) takes every answer, so
the hub can tell "never taken" (it will not run: the rig drops what comes after its
deadline) from "taken, no outcome yet", and hears an outcome that comes after it gave
up (``on_late``: told to the user, e.g. "it DID run"). nats-server's no-responders
status (503) comes the same way: nobody listens, refused at once.
"""

from __future__ import annotations

import asyncio
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field

from nats.aio.client import Client
from nats.aio.msg import Msg

from servotune.bus.messages import ACK_HEADER

NO_RESPONDERS_STATUS = "503"
# Requests given up on, kept to recognise a late outcome (oldest forgotten first).
LATE_KEEP = 256


@dataclass(eq=False, slots=True)
class Call:
    """One request under way: ``taken`` set by the rig's first answer, ``outcome`` by
    its last (or by the no-responders status: ``no_responders``)."""

    token: str
    inbox: str
    verb: str
    taken: asyncio.Event = field(default_factory=asyncio.Event)
    outcome: asyncio.Future[Msg] = field(default_factory=asyncio.Future)
    no_responders: bool = False
    given_up: str | None = None
    given_up_at: float = 0.0
    on_late: Callable[[Call, Msg], None] | None = None


class ReplyMux:
    """Every two-part request of one connection (``start`` once it is connected)."""

    def __init__(self, nc: Client) -> None:
        self._nc = nc
        self._prefix = ""
        self._calls: dict[str, Call] = {}
        self._late: OrderedDict[str, Call] = OrderedDict()
        self._next = 0

    async def start(self) -> None:
        self._prefix = self._nc.new_inbox()
        # nats-py subscribes again by itself after a reconnect.
        await self._nc.subscribe(f"{self._prefix}.*", cb=self._on_reply)

    def open(self, verb: str) -> Call:
        self._next += 1
        token = str(self._next)
        call = Call(token, f"{self._prefix}.{token}", verb)
        self._calls[token] = call
        return call

    async def publish(self, call: Call, subject: str, data: bytes) -> None:
        await self._nc.publish(subject, data, reply=call.inbox)

    def close(self, call: Call) -> None:
        """Done with ``call`` (its outcome arrived)."""
        self._calls.pop(call.token, None)

    def give_up(self, call: Call, why: str, on_late: Callable[[Call, Msg], None]) -> None:
        """The hub answered its user without the outcome (``why``); an outcome that
        comes later goes to ``on_late``."""
        self._calls.pop(call.token, None)
        call.given_up, call.given_up_at, call.on_late = why, time.monotonic(), on_late
        self._late[call.token] = call
        while len(self._late) > LATE_KEEP:
            self._late.popitem(last=False)

    async def _on_reply(self, msg: Msg) -> None:
        token = msg.subject.rsplit(".", 1)[-1]
        headers = msg.headers or {}
        call = self._calls.get(token)
        if call is None:
            late = self._late.get(token)
            if late is not None and not headers.get(ACK_HEADER) and late.on_late is not None:
                del self._late[token]
                late.on_late(late, msg)
            return
        if headers.get("Status") == NO_RESPONDERS_STATUS:
            call.no_responders = True
            if not call.outcome.done():
                call.outcome.set_result(msg)
            return
        if headers.get(ACK_HEADER):
            call.taken.set()
            return
        call.taken.set()
        if not call.outcome.done():
            call.outcome.set_result(msg)
