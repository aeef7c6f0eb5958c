"""Stream queue scenarios driven by pika (issue 33): the `streams` suite
(lib/streams.py) runs them against a RabbitMQ 3.10 node and a Leveret and
compares what the client observed.

Where RabbitMQ's output depends on its storage layout (where `last`
starts: the last chunk; which offsets a segment's first record takes;
how much a retention pass removes) a scenario records the invariant that
holds on both brokers instead of the raw value. Reply texts are recorded
whole where RabbitMQ's are plain English, and up to the Erlang term that
ends some of them otherwise.
"""

import datetime
import time

import pika
import pika.exceptions as pe

from harness import HANG, Failure, scenario
from s_pika import connect, settle, tidy

LIB = "streams"
STREAM = {"x-queue-type": "stream"}


def s(name):
    return scenario(LIB, "pika." + name)


# helpers -----------------------------------------------------------------


def refusal(e):
    """[level, code, text] of the broker's close; the text up to an Erlang
    term (`...: {invalid_stream_offset_arg,...}`) when it ends with one."""
    level = "connection" if isinstance(e, pe.ConnectionClosedByBroker) else "channel"
    text = e.reply_text if isinstance(e.reply_text, str) else e.reply_text.decode()
    head, sep, tail = text.rpartition(": ")
    if sep and (tail.startswith(("{", "<<", '"')) or tail in ("invalid_max_age",)):
        text = head
    return [level, e.reply_code, text]


def expect_refusal(t, label, fn, code):
    try:
        fn()
    except (pe.ChannelClosedByBroker, pe.ConnectionClosedByBroker) as e:
        got = refusal(e)
        t.obs(label, got)
        t.check(got[1] == code, f"{label}: expected {code}, got {got}")
        return got
    t.obs(label, "accepted")
    raise Failure(f"{label}: expected refusal {code}, call succeeded")


def stream(t, name, **args):
    """Declare a stream `name` (prefixed) with `args`; deleted at the end."""
    q = t.n(name)
    conn = connect(t)
    ch = conn.channel()
    ch.queue_declare(q, durable=True, arguments={**STREAM, **args})
    tidy(t, queues=[q])
    conn.close()
    return q


class Publisher:
    """A channel in confirm mode: every publish waits for its confirm, so
    each message is its own write on both brokers."""

    def __init__(self, t):
        self.conn = connect(t)
        self.ch = self.conn.channel()
        self.ch.confirm_delivery()

    def send(self, q, bodies, headers=None):
        for body in bodies:
            self.ch.basic_publish("", q, body.encode(), pika.BasicProperties(headers=headers))


class Reader:
    """A consumer with a prefetch on its own connection, recording
    (body, x-stream-offset, delivery tag, redelivered, headers) and the
    properties of each delivery."""

    def __init__(self, t, q, offset=None, prefetch=100, ack=True):
        self.conn = connect(t)
        self.ch = self.conn.channel()
        self.ch.basic_qos(prefetch_count=prefetch)
        self.got = []
        self.properties = []
        self.ack = ack
        args = {} if offset is None else {"x-stream-offset": offset}
        self.tag = self.ch.basic_consume(q, self._on, arguments=args)

    def _on(self, ch, method, props, body):
        headers = dict(props.headers or {})
        self.got.append((body.decode(), headers.get("x-stream-offset"), method.delivery_tag, method.redelivered, headers))
        self.properties.append(props)
        if self.ack:
            ch.basic_ack(method.delivery_tag)

    def until(self, n, timeout=HANG):
        deadline = time.monotonic() + timeout
        while len(self.got) < n and time.monotonic() < deadline:
            self.conn.process_data_events(time_limit=0.05)
        if len(self.got) < n:
            raise Failure(f"expected {n} deliveries, got {len(self.got)}: {[g[0] for g in self.got]}")
        return self

    def until_body(self, body, timeout=HANG):
        deadline = time.monotonic() + timeout
        while body not in self.bodies() and time.monotonic() < deadline:
            self.conn.process_data_events(time_limit=0.05)
        if body not in self.bodies():
            raise Failure(f"never delivered {body}; got {self.bodies()}")
        return self

    def quiet(self, seconds=1.0):
        """Let anything else arrive (what follows asserts nothing more did)."""
        settle(self.conn, seconds)
        return self

    def bodies(self):
        return [g[0] for g in self.got]

    def offsets(self):
        return [g[1] for g in self.got]


def bodies_and_offsets(reader):
    return [[b, o] for b, o, *_ in reader.got]


def names(prefix, n, start=0):
    return [f"{prefix}{i}" for i in range(start, start + n)]


def increasing(xs):
    return all(isinstance(x, int) for x in xs) and all(a < b for a, b in zip(xs, xs[1:]))


def suffix_of(got, sent):
    """True when `got` is a non-empty suffix of `sent`."""
    return bool(got) and got == sent[len(sent) - len(got):]


# declare rules -------------------------------------------------------------


@s("declare.durable_required")
def _(t):
    ch = connect(t).channel()
    expect_refusal(t, "non-durable", lambda: ch.queue_declare(t.n("nd"), durable=False, arguments=STREAM), 406)


@s("declare.exclusive_refused")
def _(t):
    ch = connect(t).channel()
    expect_refusal(t, "exclusive", lambda: ch.queue_declare(t.n("ex"), durable=True, exclusive=True, arguments=STREAM), 406)


@s("declare.auto_delete_refused")
def _(t):
    ch = connect(t).channel()
    expect_refusal(t, "auto-delete", lambda: ch.queue_declare(t.n("ad"), durable=True, auto_delete=True, arguments=STREAM), 406)


@s("declare.server_named_refused")
def _(t):
    ch = connect(t).channel()
    expect_refusal(t, "server-named", lambda: ch.queue_declare("", durable=True, arguments=STREAM), 406)


@s("declare.redeclare_and_inequivalent_type")
def _(t):
    q = stream(t, "re")
    conn = connect(t)
    ch = conn.channel()
    t.eq("redeclare same", ch.queue_declare(q, durable=True, arguments=STREAM).method.queue, q)
    t.eq("passive", ch.queue_declare(q, passive=True).method.queue, q)
    expect_refusal(t, "as classic", lambda: ch.queue_declare(q, durable=True), 406)
    ch = conn.channel()
    expect_refusal(t, "as quorum", lambda: ch.queue_declare(q, durable=True, arguments={"x-queue-type": "quorum"}), 406)


@s("declare.declare_ok_counts")
def _(t):
    """What queue.declare-ok says of a stream with messages and a consumer."""
    q = stream(t, "counts")
    Publisher(t).send(q, names("m", 3))
    reader = Reader(t, q, "first").until(3)
    ok = connect(t).channel().queue_declare(q, passive=True).method
    t.obs("message_count, consumer_count", [ok.message_count, ok.consumer_count])
    t.eq("reader", reader.bodies(), names("m", 3))


@s("declare.arguments_of_other_types_refused")
def _(t):
    conn = connect(t)
    for arg, value in [("x-max-length", 10), ("x-message-ttl", 1000), ("x-max-priority", 5),
                       ("x-dead-letter-exchange", "dlx"), ("x-overflow", "reject-publish"),
                       ("x-expires", 100000), ("x-single-active-consumer", True)]:
        ch = conn.channel()
        expect_refusal(t, arg, lambda: ch.queue_declare(t.n("arg"), durable=True, arguments={**STREAM, arg: value}), 406)


@s("declare.retention_arguments_validated")
def _(t):
    """(RabbitMQ 3.10 answers x-max-age "m", a unit without a number, with 541
    INTERNAL_ERROR: not compared.)"""
    conn = connect(t)
    for arg, value in [("x-max-age", "10x"), ("x-max-age", 10),
                       ("x-max-length-bytes", "big"), ("x-max-length-bytes", -1),
                       ("x-stream-max-segment-size-bytes", "x")]:
        ch = conn.channel()
        expect_refusal(t, f"{arg}={value!r}", lambda: ch.queue_declare(t.n("bad"), durable=True, arguments={**STREAM, arg: value}), 406)
    ch = conn.channel()
    for unit in "YMDhms":
        q = t.n(f"age-{unit}")
        tidy(t, queues=[q])
        t.eq(f"x-max-age 7{unit}", ch.queue_declare(q, durable=True, arguments={**STREAM, "x-max-age": f"7{unit}"}).method.queue, q)


@s("declare.limits_and_cluster_arguments")
def _(t):
    """Out-of-range retention values are refused; RabbitMQ's cluster
    arguments are accepted. (RabbitMQ 3.10 accepts a segment size of 0 and
    then never confirms a publish, and answers x-max-age "-1s" with 541:
    not compared.)"""
    conn = connect(t)
    for arg, value in [("x-stream-max-segment-size-bytes", -1), ("x-stream-max-segment-size-bytes", 3_000_000_001),
                       ("x-max-age", "0s"), ("x-max-age", "10")]:
        ch = conn.channel()
        expect_refusal(t, f"{arg}={value!r}", lambda: ch.queue_declare(t.n("limits"), durable=True, arguments={**STREAM, arg: value}), 406)
    q = stream(t, "cluster", **{"x-initial-cluster-size": 1, "x-queue-leader-locator": "client-local", "x-max-length-bytes": 0})
    Publisher(t).send(q, names("m", 3))
    t.eq("accepted, and a stream", Reader(t, q, "first").until(3).quiet(0.3).bodies(), names("m", 3))


@s("declare.purge_refused")
def _(t):
    q = stream(t, "purge")
    Publisher(t).send(q, names("m", 2))
    ch = connect(t).channel()
    expect_refusal(t, "queue.purge", lambda: ch.queue_purge(q), 540)
    t.eq("still there", Reader(t, q, "first").until(2).bodies(), names("m", 2))


# x-stream-offset -----------------------------------------------------------


def ten(t, name):
    q = stream(t, name)
    pub = Publisher(t)
    pub.send(q, names("m", 10))
    return q, pub


@s("offset.default_is_next")
def _(t):
    q, pub = ten(t, "default")
    reader = Reader(t, q).quiet(0.5)
    pub.send(q, ["n0"])
    t.eq("delivered", bodies_and_offsets(reader.until(1).quiet()), [["n0", 10]])


@s("offset.first")
def _(t):
    q, pub = ten(t, "first")
    reader = Reader(t, q, "first").until(10)
    pub.send(q, ["n0"])
    t.eq("delivered", bodies_and_offsets(reader.until(11).quiet()), [[b, i] for i, b in enumerate(names("m", 10) + ["n0"])])


@s("offset.last")
def _(t):
    """`last` starts at the last chunk (RabbitMQ: the last write's batch):
    whatever it starts with ends at m9, contiguous, then new messages."""
    q, pub = ten(t, "last")
    reader = Reader(t, q, "last").until_body("m9").quiet(0.5)
    old = reader.bodies()
    t.eq("a contiguous tail of the stream ending at the last message", suffix_of(old, names("m", 10)), True)
    t.eq("offsets match positions", reader.offsets() == list(range(10 - len(old), 10)), True)
    pub.send(q, ["n0"])
    t.eq("then", bodies_and_offsets(reader.until(len(old) + 1).quiet())[len(old):], [["n0", 10]])


@s("offset.next")
def _(t):
    q, pub = ten(t, "next")
    reader = Reader(t, q, "next").quiet(0.5)
    t.eq("nothing old", reader.bodies(), [])
    pub.send(q, ["n0", "n1"])
    t.eq("delivered", bodies_and_offsets(reader.until(2).quiet()), [["n0", 10], ["n1", 11]])


@s("offset.absolute")
def _(t):
    q, pub = ten(t, "abs")
    t.eq("from 5", bodies_and_offsets(Reader(t, q, 5).until(5).quiet()), [[f"m{i}", i] for i in range(5, 10)])
    t.eq("from 9", bodies_and_offsets(Reader(t, q, 9).until(1).quiet()), [["m9", 9]])
    t.eq("from 0", Reader(t, q, 0).until(10).quiet().offsets(), list(range(10)))


@s("offset.absolute_below_first")
def _(t):
    q, pub = ten(t, "neg")
    t.eq("from -5", Reader(t, q, -5).until(10).quiet().offsets(), list(range(10)))


@s("offset.absolute_beyond_end")
def _(t):
    """An offset past the end waits for that offset to be written."""
    q, pub = ten(t, "beyond")
    reader = Reader(t, q, 12).quiet(0.5)
    t.eq("nothing yet", reader.bodies(), [])
    pub.send(q, ["n10", "n11"])
    t.eq("still nothing", reader.quiet(0.5).bodies(), [])
    pub.send(q, ["n12", "n13"])
    t.eq("from offset 12", bodies_and_offsets(reader.until(2).quiet()), [["n12", 12], ["n13", 13]])


def next_second():
    """Sleep past the next whole second (AMQP timestamps are seconds) and return it."""
    boundary = int(time.time()) + 1
    time.sleep(boundary - time.time() + 0.3)
    return boundary


@s("offset.timestamp")
def _(t):
    q = stream(t, "ts")
    pub = Publisher(t)
    pub.send(q, names("a", 5))
    boundary = next_second()
    pub.send(q, names("b", 5))
    at = datetime.datetime.fromtimestamp(boundary, tz=datetime.timezone.utc)
    t.eq("from the boundary", bodies_and_offsets(Reader(t, q, at).until(5).quiet()), [[f"b{i}", 5 + i] for i in range(5)])
    old = datetime.datetime(2000, 1, 1, tzinfo=datetime.timezone.utc)
    t.eq("from 2000-01-01", Reader(t, q, old).until(10).quiet().bodies(), names("a", 5) + names("b", 5))
    future = datetime.datetime.fromtimestamp(time.time() + 3600, tz=datetime.timezone.utc)
    reader = Reader(t, q, future).quiet(0.5)
    t.eq("from an hour ahead: nothing old", reader.bodies(), [])
    pub.send(q, ["c0"])
    t.eq("then new messages", bodies_and_offsets(reader.until(1).quiet()), [["c0", 10]])


@s("offset.interval")
def _(t):
    q, pub = ten(t, "interval")
    for spec in ["10m", "1h", "1D", "1M", "1Y"]:
        t.eq(f"from {spec} ago", Reader(t, q, spec).until(10).quiet(0.3).offsets(), list(range(10)))


@s("offset.interval_excludes_older")
def _(t):
    """Messages written 8 s before the others; a 4 s interval (generous
    either side) starts after them."""
    q = stream(t, "interval-old")
    pub = Publisher(t)
    pub.send(q, names("a", 3))
    time.sleep(8)
    pub.send(q, names("b", 3))
    t.eq("from 4s ago", bodies_and_offsets(Reader(t, q, "4s").until(3).quiet()), [[f"b{i}", 3 + i] for i in range(3)])


@s("offset.invalid")
def _(t):
    """Malformed intervals are refused with 406. (RabbitMQ 3.10 answers other
    malformed values, an unknown word, "-1m", a boolean, a table, with 541
    INTERNAL_ERROR, a crash of its consumer setup: not compared.)"""
    q, pub = ten(t, "invalid")
    conn = connect(t)
    for spec in ["10x", "0s", "1.5h"]:
        ch = conn.channel()
        ch.basic_qos(prefetch_count=10)
        expect_refusal(t, f"x-stream-offset {spec!r}", lambda: ch.basic_consume(q, lambda *a: None, arguments={"x-stream-offset": spec}), 406)


@s("offset.header_on_each_delivery")
def _(t):
    q = stream(t, "headers")
    pub = Publisher(t)
    pub.send(q, ["plain"])
    pub.send(q, ["with-headers"], headers={"robot": "r7", "seq": 2})
    reader = Reader(t, q, "first").until(2).quiet()
    t.eq("headers", [g[4] for g in reader.got], [{"x-stream-offset": 0}, {"robot": "r7", "seq": 2, "x-stream-offset": 1}])
    t.eq("delivery tags, redelivered", [[g[2], g[3]] for g in reader.got], [[1, False], [2, False]])


# consumers: prefetch and acks ------------------------------------------------


@s("consume.prefetch_required")
def _(t):
    q = stream(t, "noqos")
    conn = connect(t)
    ch = conn.channel()
    expect_refusal(t, "no basic.qos", lambda: ch.basic_consume(q, lambda *a: None), 406)
    ch = conn.channel()
    ch.basic_qos(prefetch_count=10, global_qos=True)
    expect_refusal(t, "global basic.qos only", lambda: ch.basic_consume(q, lambda *a: None), 406)


@s("consume.manual_ack_required")
def _(t):
    q = stream(t, "autoack")
    ch = connect(t).channel()
    ch.basic_qos(prefetch_count=10)
    expect_refusal(t, "auto-ack", lambda: ch.basic_consume(q, lambda *a: None, auto_ack=True), 540)


@s("consume.get_refused")
def _(t):
    q = stream(t, "get")
    Publisher(t).send(q, ["m0"])
    ch = connect(t).channel()
    expect_refusal(t, "basic.get", lambda: ch.basic_get(q), 540)


@s("consume.nack_and_reject_refused")
def _(t):
    q = stream(t, "nack")
    Publisher(t).send(q, ["m0"])
    for how in ("nack", "reject"):
        reader = Reader(t, q, "first", ack=False).until(1)
        tag = reader.got[0][2]
        call = (lambda: reader.ch.basic_nack(tag)) if how == "nack" else (lambda: reader.ch.basic_reject(tag))
        expect_refusal(t, f"basic.{how}", lambda: (call(), reader.quiet(1.0), reader.ch.basic_qos(prefetch_count=1)), 540)


@s("consume.prefetch_is_credit")
def _(t):
    """Unacked deliveries stop at the prefetch; each ack lets one more in."""
    q, pub = ten(t, "credit")
    reader = Reader(t, q, "first", prefetch=3, ack=False).until(3).quiet()
    t.eq("before acks", reader.bodies(), names("m", 3))
    reader.ch.basic_ack(reader.got[0][2])
    t.eq("after one ack", reader.until(4).quiet().bodies(), names("m", 4))
    reader.ch.basic_ack(reader.got[3][2], multiple=True)
    t.eq("after a multiple ack", reader.until(7).quiet().bodies(), names("m", 7))


@s("consume.acks_never_remove")
def _(t):
    q, pub = ten(t, "keep")
    first = Reader(t, q, "first").until(10).quiet()
    t.eq("first reader", bodies_and_offsets(first), [[b, i] for i, b in enumerate(names("m", 10))])
    first.conn.close()
    second = Reader(t, q, "first").until(10).quiet()
    t.eq("second reader after the first acked all", bodies_and_offsets(second), [[b, i] for i, b in enumerate(names("m", 10))])


@s("consume.readers_at_own_pace")
def _(t):
    """Three readers at different offsets on one stream, one never acking."""
    q, pub = ten(t, "pace")
    fast = Reader(t, q, "first")
    slow = Reader(t, q, "first", prefetch=2, ack=False)
    late = Reader(t, q, 6)
    fast.until(10)
    late.until(4)
    slow.until(2).quiet(0.5)
    pub.send(q, ["n0"])
    t.eq("fast", fast.until(11).quiet().bodies(), names("m", 10) + ["n0"])
    t.eq("late", late.until(5).quiet().bodies(), names("m", 4, 6) + ["n0"])
    t.eq("slow (prefetch 2, no acks)", slow.bodies(), names("m", 2))
    slow.ch.basic_ack(slow.got[1][2], multiple=True)
    t.eq("slow after acking", slow.until(4).quiet().bodies(), names("m", 4))


@s("consume.two_consumers_one_channel")
def _(t):
    q, pub = ten(t, "twoc")
    reader = Reader(t, q, "first")
    got2 = []
    reader.ch.basic_consume(q, lambda ch, m, p, b: (got2.append((b.decode(), m.delivery_tag)), ch.basic_ack(m.delivery_tag)),
                            arguments={"x-stream-offset": 8})
    reader.until(10)
    deadline = time.monotonic() + HANG
    while len(got2) < 2 and time.monotonic() < deadline:
        reader.conn.process_data_events(time_limit=0.05)
    reader.quiet()
    t.eq("from first", reader.bodies(), names("m", 10))
    t.eq("from 8", [b for b, _ in got2], ["m8", "m9"])
    t.eq("one delivery tag sequence for the channel", sorted([g[2] for g in reader.got] + [tag for _, tag in got2]), list(range(1, 13)))


@s("consume.offset_argument_on_classic_queue_refused")
def _(t):
    q = t.n("classic")
    tidy(t, queues=[q])
    ch = connect(t).channel()
    ch.queue_declare(q, durable=True)
    ch.basic_qos(prefetch_count=10)
    expect_refusal(t, "x-stream-offset on a classic queue", lambda: ch.basic_consume(q, lambda *a: None, arguments={"x-stream-offset": "first"}), 406)


@s("consume.priority_refused")
def _(t):
    q = stream(t, "prio")
    ch = connect(t).channel()
    ch.basic_qos(prefetch_count=10)
    expect_refusal(t, "x-priority", lambda: ch.basic_consume(q, lambda *a: None, arguments={"x-priority": 5}), 406)


@s("consume.exclusive_flag")
def _(t):
    """RabbitMQ 3.10 accepts an exclusive consumer on a stream and a second
    consumer beside it."""
    q, pub = ten(t, "excl")
    conn = connect(t)
    first = conn.channel()
    first.basic_qos(prefetch_count=10)
    first.basic_consume(q, lambda ch, m, p, b: ch.basic_ack(m.delivery_tag), exclusive=True, arguments={"x-stream-offset": "first"})
    t.obs("exclusive consumer", "accepted")
    reader = Reader(t, q, "first")
    t.eq("a second consumer beside it", reader.until(10).quiet(0.3).bodies(), names("m", 10))


@s("publish.through_an_exchange_and_in_a_transaction")
def _(t):
    q = stream(t, "routed")
    x = t.n("fan")
    tidy(t, exchanges=[x])
    conn = connect(t)
    ch = conn.channel()
    ch.exchange_declare(x, "fanout")
    ch.queue_bind(q, x)
    ch.confirm_delivery()
    ch.basic_publish(x, "", b"via-exchange", mandatory=True)
    tx = conn.channel()
    tx.tx_select()
    tx.basic_publish("", q, b"in-tx-1")
    tx.basic_publish(x, "", b"in-tx-2")
    tx.tx_commit()
    tx.basic_publish("", q, b"rolled-back")
    tx.tx_rollback()
    reader = Reader(t, q, "first").until(3).quiet()
    t.eq("delivered", bodies_and_offsets(reader), [["via-exchange", 0], ["in-tx-1", 1], ["in-tx-2", 2]])


@s("publish.properties_kept")
def _(t):
    """Every basic property a publisher sets comes back from the stream.
    Scalar header values only: RabbitMQ 3.10 drops a header whose value is
    a table or an array on its way through a stream (Leveret keeps them),
    and closes the connection 541 INTERNAL_ERROR on a decimal one: not
    compared."""
    q = stream(t, "props")
    props = pika.BasicProperties(content_type="application/json", content_encoding="utf-8",
                                 headers={"robot": "r7", "n": 3, "big": 2**40, "neg": -5, "flag": True, "none": None,
                                          "raw": b"\x00\x01", "at": datetime.datetime(2020, 1, 1, tzinfo=datetime.timezone.utc)}, delivery_mode=2, priority=4,
                                 correlation_id="c-1", reply_to="replies", expiration="60000", message_id="m-1",
                                 timestamp=1700000000, type="pose", user_id="guest", app_id="robot-7")
    conn = connect(t)
    ch = conn.channel()
    ch.confirm_delivery()
    ch.basic_publish("", q, b"{}", props)
    p = Reader(t, q, "first").until(1).quiet(0.3).properties[0]
    t.obs("properties", {k: getattr(p, k) for k in ["content_type", "content_encoding", "headers", "delivery_mode", "priority",
                                                     "correlation_id", "reply_to", "expiration", "message_id", "timestamp",
                                                     "type", "user_id", "app_id", "cluster_id"]})


@s("publish.bodies_larger_than_a_segment")
def _(t):
    """Empty, small and 300 KB bodies in a stream of 1000-byte segments."""
    q = stream(t, "large", **{"x-stream-max-segment-size-bytes": 1000})
    big = "".join(chr(65 + i % 26) for i in range(300_000))
    Publisher(t).send(q, ["", "small", big, "after"])
    reader = Reader(t, q, "first").until(4).quiet(0.3)
    t.eq("bodies", [len(b) for b in reader.bodies()], [0, 5, 300_000, 5])
    t.eq("intact", reader.bodies()[2] == big and reader.bodies()[3] == "after", True)
    t.eq("offsets increase", increasing(reader.offsets()), True)


@s("declare.delete_if_empty")
def _(t):
    """queue.delete if-empty on a stream with messages: RabbitMQ 3.10 deletes
    it and says message_count 0."""
    q, pub = ten(t, "ifempty")
    ch = connect(t).channel()
    t.obs("delete-ok message_count", ch.queue_delete(q, if_empty=True).method.message_count)
    expect_refusal(t, "passive declare after", lambda: ch.queue_declare(q, passive=True), 404)


# retention -----------------------------------------------------------------

BODY = "x" * 96


def padded(prefix, n):
    return [f"{prefix}{i:03d}{BODY}" for i in range(n)]


def retained(t, q, sent, last):
    """Read from `first` until `last`; check the invariants of a retention
    pass and return what was kept."""
    reader = Reader(t, q, "first").until_body(last).quiet(0.5)
    kept = reader.bodies()
    t.eq("what remains is a tail of what was sent, ending with the last message", suffix_of(kept, sent), True)
    t.eq("offsets increase", increasing(reader.offsets()), True)
    # Retention may still be removing segments (RabbitMQ's runs apart from
    # the writer): a reader from offset 0 starts at the first offset kept
    # by then, so it reads a tail of what the first reader read.
    zero = Reader(t, q, 0).until_body(last).quiet(0.5)
    t.eq("offset 0 reads a tail of it, at the same offsets", suffix_of(bodies_and_offsets(zero), bodies_and_offsets(reader)), True)
    return kept, reader.offsets()


@s("retention.max_length_bytes")
def _(t):
    """1000-byte segments, at most 3000 bytes, 10000 bytes written one by one:
    the oldest segments go, the first offset moves, the newest stay."""
    q = stream(t, "bytes", **{"x-max-length-bytes": 3000, "x-stream-max-segment-size-bytes": 1000})
    sent = padded("m", 100)
    Publisher(t).send(q, sent)
    kept, offsets = retained(t, q, sent, sent[-1])
    t.eq("the oldest are gone", len(kept) < len(sent), True)
    t.eq("the first offset moved", offsets[0] > 0, True)
    t.eq("at most max-length-bytes plus one segment kept", sum(len(b) for b in kept) <= 3000 + 1000, True)


@s("retention.max_age")
def _(t):
    """x-max-age 2s, 1000-byte segments: 30 messages, 6 s later 30 more
    (rolling segments, where retention is applied): some of the first go,
    every one of the second stays."""
    q = stream(t, "age", **{"x-max-age": "2s", "x-stream-max-segment-size-bytes": 1000})
    old, new = padded("a", 30), padded("b", 30)
    pub = Publisher(t)
    pub.send(q, old)
    time.sleep(6)
    pub.send(q, new)
    kept, offsets = retained(t, q, old + new, new[-1])
    t.eq("some old messages are gone", old[0] not in kept, True)
    t.eq("every new message remains", kept[-len(new):] == new, True)
    t.eq("the first offset moved", offsets[0] > 0, True)


@s("retention.by_policy")
def _(t):
    """The suite's policy (lib/streams.py: max-length-bytes 3000,
    stream-max-segment-size-bytes 1000 on queues named `...policy-retained`)
    retains a stream declared without arguments as the arguments would."""
    q = stream(t, "policy-retained")
    sent = padded("m", 100)
    Publisher(t).send(q, sent)
    kept, offsets = retained(t, q, sent, sent[-1])
    t.eq("the oldest are gone", len(kept) < len(sent), True)
    t.eq("the first offset moved", offsets[0] > 0, True)
    t.eq("at most max-length-bytes plus one segment kept", sum(len(b) for b in kept) <= 3000 + 1000, True)


@s("retention.unlimited_keeps_everything")
def _(t):
    q = stream(t, "all", **{"x-stream-max-segment-size-bytes": 1000})
    sent = padded("m", 50)
    Publisher(t).send(q, sent)
    reader = Reader(t, q, "first").until(50).quiet(0.5)
    t.eq("everything", reader.bodies(), sent)
    t.eq("offsets increase from 0", reader.offsets()[0] == 0 and increasing(reader.offsets()), True)


# errors ----------------------------------------------------------------------


@s("error.consume_missing_stream")
def _(t):
    ch = connect(t).channel()
    ch.basic_qos(prefetch_count=10)
    expect_refusal(t, "consume", lambda: ch.basic_consume(t.n("missing"), lambda *a: None, arguments={"x-stream-offset": "first"}), 404)


@s("error.delete_with_reader")
def _(t):
    """Deleting a stream cancels its readers (consumer_cancel_notify)."""
    q, pub = ten(t, "delete")
    reader = Reader(t, q, "first").until(10)
    cancelled = []
    reader.ch.add_on_cancel_callback(lambda frame: cancelled.append(frame.method.consumer_tag))
    connect(t).channel().queue_delete(q)
    deadline = time.monotonic() + HANG
    while not cancelled and time.monotonic() < deadline:
        reader.conn.process_data_events(time_limit=0.05)
    t.eq("reader cancelled", cancelled == [reader.tag], True)
    ch = connect(t).channel()
    expect_refusal(t, "passive declare after delete", lambda: ch.queue_declare(q, passive=True), 404)

