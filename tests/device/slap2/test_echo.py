"""EchoExchange as a sans-IO handler, driven here as the channel drives it (start, feed
after every arrival, expire at the deadline) against a module that echoes every byte
and answers after CR: any split of the incoming bytes gives the same outcome; a wrong
byte (garbage, a late echo of an earlier command) or a missing echo stops it there with
nothing more sent; bytes after the reply stay received; the chained read follows only
when nothing else came and it is allowed."""

from __future__ import annotations

from dataclasses import dataclass, field

from hypothesis import given
from hypothesis import strategies as st

from servotune.devices.slap2.echo import EchoExchange, EchoResult, ReadByte

CR = 0x0D
CHAR_S = 0.15
REPLY_S = 0.5

texts = st.binary(min_size=0, max_size=8).map(lambda b: bytes(0x61 + x % 26 for x in b))
replies = st.binary(min_size=0, max_size=12).map(lambda b: bytes(0x30 + x % 10 for x in b))


@dataclass
class Wire:
    """The channel's side: what the handler sent, when, and what is received."""

    handler: EchoExchange
    received: bytearray = field(default_factory=bytearray)
    sent: bytearray = field(default_factory=bytearray)
    sent_at: list[float] = field(default_factory=list)

    def out(self, data: bytes, now_s: float) -> None:
        self.sent += data
        self.sent_at += [now_s] * len(data)

    def start(self, now_s: float) -> None:
        self.out(self.handler.start(now_s), now_s)
        if not self.handler.done:
            self.out(self.handler.feed(self.received, now_s), now_s)

    def arrive(self, data: bytes, now_s: float) -> None:
        self.received += data
        if not self.handler.done:
            self.out(self.handler.feed(self.received, now_s), now_s)


class Module:
    """Echoes each byte it was sent; after CR sends ``reply`` CR, then ``trailing``."""

    def __init__(self, reply: bytes, trailing: bytes = b"", mute_at: int | None = None) -> None:
        self.reply, self.trailing, self.mute_at = reply, trailing, mute_at
        self.taken = 0
        self.pending = bytearray()

    def hear(self, sent: bytes) -> None:
        for byte in sent[self.taken :]:
            if self.taken == self.mute_at:
                return
            self.taken += 1
            self.pending.append(byte)
            if byte == CR:
                self.pending += self.reply + b"\r" + self.trailing


def run(
    wire: Wire, module: Module, sizes: list[int], *, t0: float = 100.0, step_s: float = 0.001
) -> list[float]:
    """Deliver what the module has to say in pieces of ``sizes`` (cycled); returns the
    arrival time of every delivered byte."""
    now = t0
    wire.start(now)
    arrivals: list[float] = []
    i = 0
    while not wire.handler.done:
        module.hear(bytes(wire.sent))
        if not module.pending:
            deadline = wire.handler.deadline_s
            assert deadline is not None
            wire.out(wire.handler.expire(deadline), deadline)
            break
        now += step_s
        size = min(sizes[i % len(sizes)], len(module.pending))
        i += 1
        piece = bytes(module.pending[:size])
        del module.pending[:size]
        arrivals += [now] * len(piece)
        wire.arrive(piece, now)
    module.hear(bytes(wire.sent))
    return arrivals


def exchange(payload: bytes, **kwargs: object) -> EchoExchange:
    return EchoExchange(
        payload,
        terminator=CR,
        first_timeout_s=CHAR_S,
        char_timeout_s=CHAR_S,
        first_reply_timeout_s=REPLY_S,
        **kwargs,  # type: ignore[arg-type]
    )


@given(texts, replies, texts, st.lists(st.integers(1, 20), min_size=1, max_size=8))
def test_any_split_gives_the_echo_the_reply_and_leaves_the_rest(
    text: bytes, reply: bytes, trailing: bytes, sizes: list[int]
) -> None:
    payload = text + b"\r"
    wire, module = Wire(exchange(payload)), Module(reply, trailing)
    arrivals = run(wire, module, sizes)
    done = wire.handler.outcome()
    assert bytes(wire.sent) == payload  # each byte once, in order
    assert done.echo == EchoResult(len(payload), None)
    assert done.reply == reply + b"\r"
    assert wire.handler.follow_up() is None
    # what came after the reply stays; the rest of the last piece was not taken
    assert bytes(wire.received) + bytes(module.pending) == trailing
    # stamped when the last echo byte / the terminator arrived
    assert done.t_echo_s == arrivals[len(payload) - 1]
    assert done.t_reply_s == arrivals[len(payload) + len(reply)]
    # the last payload byte left after the previous echo came, before its own
    assert done.t_sent_s == wire.sent_at[-1]
    assert done.t_sent_s is not None and done.t_sent_s <= done.t_echo_s


@given(
    texts,
    st.integers(0, 8),
    st.integers(0, 255),
    st.binary(max_size=4),
    st.lists(st.integers(1, 5), min_size=1, max_size=4),
)
def test_a_wrong_echo_stops_it_there(
    text: bytes, at: int, garbage: int, after: bytes, sizes: list[int]
) -> None:
    payload = text + b"\r"
    at = at % len(payload)
    if garbage == payload[at]:
        garbage ^= 0x80
    wire = Wire(exchange(payload))
    wire.start(100.0)
    now = 100.0
    while len(wire.sent) <= at:  # echo what was sent, up to byte ``at``
        now += 0.001
        assert not wire.handler.done
        wire.arrive(bytes(wire.sent[-1:]), now)
    sent_before = bytes(wire.sent)
    data = bytes([garbage]) + after
    for i in range(0, len(data), sizes[0]):
        wire.arrive(data[i : i + sizes[0]], now + 0.001)
    assert wire.handler.done
    assert wire.handler.outcome().echo == EchoResult(at, garbage)
    assert wire.handler.outcome().reply is None
    assert bytes(wire.sent) == sent_before == payload[: at + 1]  # nothing more sent
    assert bytes(wire.received) == after


@given(texts, st.sampled_from([b"\x18", b"se0\r", b"\r"]))
def test_a_late_echo_of_an_earlier_command_is_a_wrong_echo(text: bytes, late: bytes) -> None:
    """Bytes already received before it starts (a late Ctrl-X echo, a late echo of
    ``se0``) are compared with the first echo: a mismatch, the rest left received."""
    payload = b"r" + text + b"\r"
    wire = Wire(exchange(payload))
    wire.received += late
    wire.start(100.0)
    assert wire.handler.done
    assert wire.handler.outcome().echo == EchoResult(0, late[0])
    assert bytes(wire.sent) == payload[:1]
    assert bytes(wire.received) == late[1:]


@given(texts, st.integers(0, 8), replies)
def test_a_missing_echo_times_out_where_it_stopped(text: bytes, mute_at: int, reply: bytes) -> None:
    payload = text + b"\r"
    mute_at %= len(payload)
    wire = Wire(exchange(payload))
    run(wire, Module(reply, mute_at=mute_at), [1])
    done = wire.handler.outcome()
    assert done.echo == EchoResult(mute_at, None) and done.reply is None
    assert bytes(wire.sent) == payload[: mute_at + 1]


@given(texts, replies)
def test_deadlines_per_phase(text: bytes, reply: bytes) -> None:
    """A character's gap during the echo, the reply's first-byte timeout after the last
    echo, the character gap again once the reply has begun."""
    payload = text + b"\r"
    wire = Wire(exchange(payload))
    wire.start(100.0)
    assert wire.handler.deadline_s == 100.0 + CHAR_S
    now = 100.0
    for _ in payload:
        now += 0.01
        wire.arrive(bytes(wire.sent[-1:]), now)
    assert wire.handler.deadline_s == now + REPLY_S
    if reply:
        wire.arrive(reply[:1], now + 0.2)
        assert wire.handler.deadline_s == now + 0.2 + CHAR_S
        wire.arrive(reply[1:], now + 0.3)
        assert not wire.handler.done
        assert wire.handler.deadline_s == now + 0.3 + CHAR_S
    wire.arrive(b"\r", now + 0.4)
    assert wire.handler.done and wire.handler.outcome().reply == reply + b"\r"


@given(replies, st.binary(max_size=3), st.booleans())
def test_the_chained_read_follows_only_when_nothing_else_came_and_it_may(
    reply: bytes, trailing: bytes, may: bool
) -> None:
    asked: list[bool] = []

    def may_chain() -> bool:
        asked.append(may)
        return may

    wire = Wire(exchange(b"rp\r", then=b"pe\r", may_chain=may_chain))
    run(wire, Module(reply, trailing), [64])
    follow = wire.handler.follow_up()
    if trailing or not may:
        assert follow is None
    else:
        assert follow is not None and follow.payload == b"pe\r" and not follow.started
        assert follow.first_timeout_s == CHAR_S and follow.first_reply_timeout_s == REPLY_S
        assert wire.handler.chained is follow
    assert asked == ([] if trailing else [may])


@given(st.binary(max_size=4), st.lists(st.integers(1, 4), min_size=1, max_size=3))
def test_read_until_without_a_payload(data: bytes, sizes: list[int]) -> None:
    handler = EchoExchange(terminator=CR, first_timeout_s=1.0, char_timeout_s=CHAR_S)
    wire = Wire(handler)
    wire.start(100.0)
    assert bytes(wire.sent) == b"" and handler.deadline_s == 101.0
    line = data.replace(b"\r", b"") + b"\r"
    stream = line + b"tail"
    i = 0
    while not handler.done:
        size = sizes[i % len(sizes)]
        wire.arrive(stream[:size], 100.1 + i)
        stream = stream[size:]
        i += 1
    assert handler.reply == line and handler.echo == EchoResult(0, None)
    assert bytes(wire.received) + stream == b"tail"


def test_read_byte_takes_one_byte_and_leaves_the_rest() -> None:
    handler = ReadByte(0.1)
    assert handler.start(5.0) == b"" and handler.deadline_s == 5.1
    received = bytearray()
    handler.feed(received, 5.01)
    assert not handler.done
    received += b"ab"
    handler.feed(received, 5.02)
    assert handler.done and handler.byte == ord("a") and received == b"b"
    timed_out = ReadByte(0.1)
    timed_out.start(5.0)
    timed_out.expire(5.1)
    assert timed_out.done and timed_out.byte is None
