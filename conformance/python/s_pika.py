"""Scenarios driven by pika (BlockingConnection), the most used Python client."""

import datetime
import decimal
import re
import threading
import time
import uuid

import pika
import pika.exceptions as pe

from harness import HANG, Failure, reply_name, scenario, wait_until

LIB = "pika"


def s(name):
    return scenario(LIB, name)


# helpers -----------------------------------------------------------------


def params(t, url=None, **kw):
    p = pika.URLParameters(url or t.url)
    p.connection_attempts = 1
    p.socket_timeout = 10
    p.blocked_connection_timeout = 30
    for k, v in kw.items():
        setattr(p, k, v)
    return p


def connect(t, url=None, **kw):
    conn = pika.BlockingConnection(params(t, url, **kw))
    t.defer(close_quiet, conn)
    return conn


def close_quiet(conn):
    try:
        if conn.is_open:
            conn.close()
    except Exception:
        pass


def tidy(t, queues=(), exchanges=()):
    """Delete these at the end of the scenario over a fresh connection."""

    def cleanup():
        c = pika.BlockingConnection(params(t))
        try:
            ch = c.channel()
            for q in queues:
                ch.queue_delete(q)
            for e in exchanges:
                ch.exchange_delete(e)
        finally:
            close_quiet(c)

    t.defer(cleanup)


def channel_error(t, label, fn, code):
    """Run fn, expect the broker to close the channel with `code`."""
    try:
        fn()
    except pe.ChannelClosedByBroker as e:
        t.eq(label, [e.reply_code, reply_name(e.reply_text)], [code, reply_name(e.reply_text)])
        t.check(e.reply_code == code, f"{label}: expected {code}, got {e.reply_code} {e.reply_text}")
        return e
    raise Failure(f"{label}: expected channel error {code}, call succeeded")


def connection_error(t, label, fn, code):
    try:
        fn()
    except pe.ConnectionClosedByBroker as e:
        t.obs(label, [e.reply_code, reply_name(e.reply_text)])
        t.check(e.reply_code == code, f"{label}: expected {code}, got {e.reply_code} {e.reply_text}")
        return e
    raise Failure(f"{label}: expected connection error {code}, call succeeded")


def get_bodies(ch, q, ack=True):
    out = []
    while True:
        m, p, b = ch.basic_get(q, auto_ack=ack)
        if m is None:
            return out
        out.append(b.decode())


def consume_into(ch, q, **kw):
    got = []

    def cb(ch_, method, props, body):
        got.append((method, props, body))

    tag = ch.basic_consume(q, cb, **kw)
    return tag, got


def pump(conn, got, n, timeout=HANG):
    deadline = time.monotonic() + timeout
    while len(got) < n and time.monotonic() < deadline:
        conn.process_data_events(time_limit=0.02)
    if len(got) < n:
        raise Failure(f"expected {n} deliveries, got {len(got)} after {timeout}s")
    return got


def settle(conn, seconds=0.3):
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        conn.process_data_events(time_limit=0.02)


def declare_q(ch, t, name, **kw):
    q = t.n(name)
    ok = ch.queue_declare(q, **kw)
    return q, ok


# negotiation and auth ------------------------------------------------------


@s("connection.plain_and_server_properties")
def _(t):
    conn = connect(t)
    props = conn._impl.server_properties
    caps = props.get("capabilities", {})
    for cap in [
        "publisher_confirms",
        "exchange_exchange_bindings",
        "basic.nack",
        "consumer_cancel_notify",
        "connection.blocked",
        "authentication_failure_close",
        "per_consumer_qos",
    ]:
        t.eq(f"capability {cap}", caps.get(cap), True)
    t.check(isinstance(props.get("product"), (bytes, str)), "server_properties has product")
    t.check(isinstance(props.get("version"), (bytes, str)), "server_properties has version")


@s("connection.tune_frame_max_small")
def _(t):
    conn = connect(t, frame_max=4096)
    t.eq("negotiated frame_max", conn._impl.params.frame_max, 4096)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    body = bytes(range(256)) * 400  # 102400 bytes over 4 KiB frames
    ch.basic_publish("", q, body)
    m, p, b = None, None, None
    wait_until(lambda: ch.queue_declare(q, passive=True).method.message_count == 1, what="message")
    m, p, b = ch.basic_get(q, auto_ack=True)
    t.eq("body intact", b == body, True)


def handshake_refusal(t, url):
    """Connect with bad credentials or vhost; return (code, NAME) of the
    connection.close the broker sent, or fail if it only dropped the socket."""
    try:
        pika.BlockingConnection(params(t, url))
    except pe.ConnectionClosedByBroker as e:
        return [e.reply_code, reply_name(e.reply_text)]
    except pe.AMQPConnectionError as e:
        m = re.search(r"\((\d+)\) '([A-Z_]+)", str(e))
        if m:
            return [int(m.group(1)), m.group(2)]
        raise Failure(f"no connection.close from the broker: {type(e).__name__}: {e}")
    raise Failure("connection succeeded")


@s("connection.bad_password")
def _(t):
    t.eq("refusal", handshake_refusal(t, t.url_with(password="definitely-wrong")), [403, "ACCESS_REFUSED"])


@s("connection.unknown_user")
def _(t):
    t.eq("refusal", handshake_refusal(t, t.url_with(user="no-such-user-x", password="x")), [403, "ACCESS_REFUSED"])


@s("connection.unknown_vhost")
def _(t):
    t.eq("refusal", handshake_refusal(t, t.url_with(vhost="no-such-vhost")), [530, "NOT_ALLOWED"])


@s("connection.heartbeat_keeps_idle_connection")
def _(t):
    conn = connect(t, heartbeat=1)
    t.eq("negotiated heartbeat", conn._impl.params.heartbeat, 1)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    # Idle for 4 heartbeat intervals: pika closes the connection if the broker
    # sends nothing for 2 intervals, so this passes only if heartbeats flow.
    deadline = time.monotonic() + 4
    while time.monotonic() < deadline:
        conn.process_data_events(time_limit=0.2)
    t.eq("connection open", conn.is_open, True)
    ch.basic_publish("", q, b"after idle")
    wait_until(lambda: ch.queue_declare(q, passive=True).method.message_count == 1, what="message")
    t.eq("get", ch.basic_get(q, auto_ack=True)[2], b"after idle")


@s("connection.heartbeat_disabled")
def _(t):
    conn = connect(t, heartbeat=0)
    t.eq("negotiated heartbeat", conn._impl.params.heartbeat, 0)
    ch = conn.channel()
    ch.queue_declare("", exclusive=True)


@s("connection.many_channels")
def _(t):
    conn = connect(t)
    chans = [conn.channel() for _ in range(200)]
    q = chans[0].queue_declare("", exclusive=True).method.queue
    for i, ch in enumerate(chans):
        ch.basic_publish("", q, str(i).encode())
    chans[0].confirm_delivery()
    chans[0].basic_publish("", q, b"end")
    # AMQP orders each channel's publishes, not different channels'
    # (RabbitMQ's "end" sometimes overtook another channel's publish):
    # wait for all 201, then compare them as a set.
    wait_until(lambda: chans[0].queue_declare(q, passive=True).method.message_count == 201,
               what="201 messages")
    bodies = get_bodies(chans[-1], q)
    t.eq("count", len(bodies), 201)
    t.eq("all channels delivered", sorted((b for b in bodies if b != "end"), key=int),
         [str(i) for i in range(200)])
    for ch in chans[1:100]:
        ch.close()
    t.eq("channel 0 still usable", chans[0].queue_declare(q, passive=True).method.message_count, 0)


@s("connection.channel_reopen_after_error")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    channel_error(t, "passive missing", lambda: ch.queue_declare(t.n("missing"), passive=True), 404)
    ch2 = conn.channel()
    t.eq("new channel works", ch2.queue_declare("", exclusive=True).method.message_count, 0)
    t.eq("connection open", conn.is_open, True)


# exchanges -----------------------------------------------------------------


def route_table(t, ch, ex, bindings, publishes, **pubkw):
    """bindings: {queue_suffix: [(key, args)]}; returns {suffix: [bodies]}"""
    queues = {}
    for suffix, binds in bindings.items():
        q = ch.queue_declare("", exclusive=True).method.queue
        queues[suffix] = q
        for key, args in binds:
            ch.queue_bind(q, ex, routing_key=key, arguments=args)
    for key, headers in publishes:
        props = pika.BasicProperties(headers=headers) if headers is not None else None
        ch.basic_publish(ex, key, f"{key}|{headers}".encode() if headers else key.encode(), properties=props)
    ch.confirm_delivery()  # a round trip so everything above is routed
    return {suffix: get_bodies(ch, q) for suffix, q in queues.items()}


@s("exchange.direct_routing")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    ex = t.n("direct")
    tidy(t, exchanges=[ex])
    ch.exchange_declare(ex, "direct")
    got = route_table(t, ch, ex, {"a": [("a", None)], "b": [("b", None), ("a", None)]}, [("a", None), ("b", None), ("c", None)])
    t.eq("routed", got, {"a": ["a"], "b": ["a", "b"]})


@s("exchange.fanout_routing")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    ex = t.n("fanout")
    tidy(t, exchanges=[ex])
    ch.exchange_declare(ex, "fanout")
    got = route_table(t, ch, ex, {"a": [("ignored", None)], "b": [("", None)]}, [("x", None), ("y", None)])
    t.eq("routed", got, {"a": ["x", "y"], "b": ["x", "y"]})


@s("exchange.topic_wildcards")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    ex = t.n("topic")
    tidy(t, exchanges=[ex])
    ch.exchange_declare(ex, "topic")
    binds = {
        "star": [("a.*.c", None)],
        "hash": [("a.#", None)],
        "all": [("#", None)],
        "mid": [("a.#.c", None)],
        "exact": [("a.b.c", None)],
        "lead": [("*.b.*", None)],
        "empty": [("", None)],
    }
    keys = ["a.b.c", "a", "a.c", "a.b.b.c", "x.b.y", "", "a..c", "b.c"]
    got = route_table(t, ch, ex, binds, [(k, None) for k in keys])
    t.eq(
        "routed",
        got,
        {
            "star": ["a.b.c", "a..c"],
            "hash": ["a.b.c", "a", "a.c", "a.b.b.c", "a..c"],
            "all": keys,
            "mid": ["a.b.c", "a.c", "a.b.b.c", "a..c"],
            "exact": ["a.b.c"],
            "lead": ["a.b.c", "x.b.y"],
            "empty": [""],
        },
    )


@s("exchange.headers_all_any")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    ex = t.n("headers")
    tidy(t, exchanges=[ex])
    ch.exchange_declare(ex, "headers")
    binds = {
        "all": [("", {"x-match": "all", "color": "red", "size": 1})],
        "any": [("", {"x-match": "any", "color": "red", "size": 1})],
        "default": [("", {"color": "blue"})],
        "empty": [("", {"x-match": "all"})],
    }
    pubs = [
        ("1", {"color": "red", "size": 1}),
        ("2", {"color": "red", "size": 2}),
        ("3", {"color": "blue"}),
        ("4", {"other": "x"}),
        ("5", {"color": "red", "size": 1, "extra": True}),
    ]
    got = route_table(t, ch, ex, binds, pubs)
    strip = {k: [b.split("|")[0] for b in v] for k, v in got.items()}
    t.eq("routed", strip, {"all": ["1", "5"], "any": ["1", "2", "5"], "default": ["3"], "empty": ["1", "2", "3", "4", "5"]})


@s("exchange.default_exchange")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    ch.basic_publish("", q, b"direct to queue")
    ch.confirm_delivery()
    t.eq("delivered", get_bodies(ch, q), ["direct to queue"])
    channel_error(t, "bind to default exchange", lambda: ch.queue_bind(q, "", routing_key="x"), 403)
    ch = conn.channel()
    channel_error(t, "declare default exchange", lambda: ch.exchange_declare("", "direct"), 403)


@s("exchange.predeclared_amq")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    for name, kind in [("amq.direct", "direct"), ("amq.fanout", "fanout"), ("amq.topic", "topic"), ("amq.headers", "headers"), ("amq.match", "headers")]:
        ch.exchange_declare(name, kind, passive=True)
        t.obs("passive ok", name)
        ch.exchange_declare(name, kind, durable=True)
        t.obs("redeclare same ok", name)
    q = ch.queue_declare("", exclusive=True).method.queue
    ch.queue_bind(q, "amq.topic", routing_key=q + ".#")
    ch.basic_publish("amq.topic", q + ".x", b"via amq.topic")
    ch.confirm_delivery()
    t.eq("delivered", get_bodies(ch, q), ["via amq.topic"])
    channel_error(t, "declare amq.* name", lambda: ch.exchange_declare("amq." + t.n("x"), "direct"), 403)


@s("exchange.redeclare_mismatch")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    ex = t.n("mismatch")
    tidy(t, exchanges=[ex])
    ch.exchange_declare(ex, "direct")
    ch.exchange_declare(ex, "direct")
    channel_error(t, "different type", lambda: ch.exchange_declare(ex, "fanout"), 406)
    ch = conn.channel()
    channel_error(t, "different durable", lambda: ch.exchange_declare(ex, "direct", durable=True), 406)
    ch = conn.channel()
    channel_error(t, "different auto_delete", lambda: ch.exchange_declare(ex, "direct", auto_delete=True), 406)


@s("exchange.passive_missing")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    channel_error(t, "passive missing", lambda: ch.exchange_declare(t.n("nope"), "direct", passive=True), 404)


@s("exchange.unknown_type")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    connection_error(t, "unknown type", lambda: ch.exchange_declare(t.n("weird"), "no-such-type"), 503)


@s("exchange.exchange_to_exchange")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    src, dst = t.n("e2e-src"), t.n("e2e-dst")
    tidy(t, exchanges=[src, dst])
    ch.exchange_declare(src, "topic")
    ch.exchange_declare(dst, "fanout")
    ch.exchange_bind(dst, src, routing_key="k.*")
    q = ch.queue_declare("", exclusive=True).method.queue
    ch.queue_bind(q, dst)
    for k in ["k.1", "z.1", "k.2"]:
        ch.basic_publish(src, k, k.encode())
    ch.confirm_delivery()
    t.eq("through binding", get_bodies(ch, q), ["k.1", "k.2"])
    ch.exchange_unbind(dst, src, routing_key="k.*")
    ch.basic_publish(src, "k.3", b"k.3")
    ch.basic_publish(dst, "", b"direct")
    t.eq("after unbind", get_bodies(ch, q), ["direct"])
    channel_error(t, "bind missing source", lambda: ch.exchange_bind(dst, t.n("nope"), routing_key=""), 404)


@s("exchange.alternate_exchange")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    ae, main = t.n("ae"), t.n("with-ae")
    tidy(t, exchanges=[ae, main])
    ch.exchange_declare(ae, "fanout")
    ch.exchange_declare(main, "direct", arguments={"alternate-exchange": ae})
    qa = ch.queue_declare("", exclusive=True).method.queue
    qm = ch.queue_declare("", exclusive=True).method.queue
    ch.queue_bind(qa, ae)
    ch.queue_bind(qm, main, routing_key="known")
    returned = []
    ch.add_on_return_callback(lambda *a: returned.append(a))
    ch.basic_publish(main, "known", b"k")
    ch.basic_publish(main, "unknown", b"u", mandatory=True)
    ch.confirm_delivery()
    settle(conn, 0.2)
    t.eq("main queue", get_bodies(ch, qm), ["k"])
    t.eq("alternate queue", get_bodies(ch, qa), ["u"])
    t.eq("no return (AE routed it)", len(returned), 0)


@s("exchange.internal_publish_refused")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    ex = t.n("internal")
    tidy(t, exchanges=[ex])
    ch.exchange_declare(ex, "fanout", internal=True)
    ch.confirm_delivery()
    channel_error(t, "publish to internal", lambda: ch.basic_publish(ex, "", b"x"), 403)


@s("exchange.delete_if_unused_and_missing")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    ex = t.n("del")
    tidy(t, exchanges=[ex])
    ch.exchange_declare(ex, "fanout")
    q = ch.queue_declare("", exclusive=True).method.queue
    ch.queue_bind(q, ex)
    channel_error(t, "if_unused with binding", lambda: ch.exchange_delete(ex, if_unused=True), 406)
    ch = conn.channel()
    ch.queue_unbind(q, ex)
    ch.exchange_delete(ex, if_unused=True)
    t.obs("deleted when unused")
    ch.exchange_delete(t.n("never-existed"))
    t.obs("delete of missing exchange ok")
    channel_error(t, "passive after delete", lambda: ch.exchange_declare(ex, "fanout", passive=True), 404)


@s("exchange.auto_delete")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    ex = t.n("autodel")
    tidy(t, exchanges=[ex])
    ch.exchange_declare(ex, "fanout", auto_delete=True)
    q1 = ch.queue_declare("", exclusive=True).method.queue
    q2 = ch.queue_declare("", exclusive=True).method.queue
    ch.queue_bind(q1, ex)
    ch.queue_bind(q2, ex)
    ch.queue_unbind(q1, ex)
    ch.exchange_declare(ex, "fanout", passive=True, auto_delete=True)
    t.obs("still there with one binding")
    ch.queue_unbind(q2, ex)
    channel_error(t, "gone after last unbind", lambda: ch.exchange_declare(ex, "fanout", passive=True), 404)


@s("exchange.bind_errors")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    channel_error(t, "bind to missing exchange", lambda: ch.queue_bind(q, t.n("nope")), 404)
    ch = conn.channel()
    channel_error(t, "bind missing queue", lambda: ch.queue_bind(t.n("noq"), "amq.direct", routing_key="x"), 404)
    ch = conn.channel()
    ch.queue_unbind(q, "amq.direct", routing_key="never-bound")
    t.obs("unbind of missing binding ok")
    ch.queue_bind(q, "amq.direct", routing_key="dup")
    ch.queue_bind(q, "amq.direct", routing_key="dup")
    ch.basic_publish("amq.direct", "dup", b"once")
    ch.confirm_delivery()
    t.eq("duplicate binding delivers once", get_bodies(ch, q), ["once"])


# queues --------------------------------------------------------------------


@s("queue.server_named")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    ok = ch.queue_declare("", exclusive=True)
    t.check(ok.method.queue.startswith("amq.gen-"), f"server name {ok.method.queue}")
    t.eq("declare-ok counts", [ok.method.message_count, ok.method.consumer_count], [0, 0])
    t.obs("name", ok.method.queue)


@s("queue.declare_counts_and_passive")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = t.n("counts")
    tidy(t, queues=[q])
    ch.queue_declare(q)
    for i in range(3):
        ch.basic_publish("", q, b"m")
    ch.confirm_delivery()
    tag, got = consume_into(ch, q)
    pump(conn, got, 3)
    ok = ch.queue_declare(q, passive=True)
    t.eq("passive counts (3 unacked)", [ok.method.message_count, ok.method.consumer_count], [0, 1])
    ch.basic_cancel(tag)
    ch2 = conn.channel()
    ch.close()  # unacked messages go back
    ok = ch2.queue_declare(q, passive=True)
    t.eq("after channel close", [ok.method.message_count, ok.method.consumer_count], [3, 0])
    ok = ch2.queue_declare(q)
    t.eq("redeclare returns counts", [ok.method.message_count, ok.method.consumer_count], [3, 0])
    channel_error(t, "passive missing", lambda: ch2.queue_declare(t.n("missing"), passive=True), 404)


@s("queue.redeclare_mismatch")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = t.n("qmismatch")
    tidy(t, queues=[q])
    ch.queue_declare(q, arguments={"x-message-ttl": 1000})
    channel_error(t, "different ttl", lambda: ch.queue_declare(q, arguments={"x-message-ttl": 2000}), 406)
    ch = conn.channel()
    channel_error(t, "different durable", lambda: ch.queue_declare(q, durable=True, arguments={"x-message-ttl": 1000}), 406)
    ch = conn.channel()
    channel_error(t, "different auto_delete", lambda: ch.queue_declare(q, auto_delete=True, arguments={"x-message-ttl": 1000}), 406)
    ch = conn.channel()
    ok = ch.queue_declare(q, passive=True, arguments={"x-message-ttl": 5})
    t.obs("passive ignores arguments", ok.method.message_count)


@s("queue.reserved_name")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    channel_error(t, "amq. prefix", lambda: ch.queue_declare("amq.mine-" + t.n("q")), 403)


@s("queue.invalid_arguments")
def _(t):
    conn = connect(t)
    for label, args in [
        ("ttl negative", {"x-message-ttl": -1}),
        ("ttl string", {"x-message-ttl": "soon"}),
        ("max-length negative", {"x-max-length": -5}),
        ("expires zero", {"x-expires": 0}),
        ("overflow unknown", {"x-overflow": "explode"}),
        ("max-priority too big", {"x-max-priority": 300}),
    ]:
        ch = conn.channel()
        channel_error(t, label, lambda: ch.queue_declare(t.n("badargs"), arguments=args), 406)
    ch = conn.channel()
    channel_error(t, "passive after refusals", lambda: ch.queue_declare(t.n("badargs"), passive=True), 404)


@s("queue.exclusive_locked")
def _(t):
    c1 = connect(t)
    c2 = connect(t)
    ch1 = c1.channel()
    q = t.n("excl")
    ch1.queue_declare(q, exclusive=True)
    ch2 = c2.channel()
    channel_error(t, "declare from other connection", lambda: ch2.queue_declare(q), 405)
    ch2 = c2.channel()
    channel_error(t, "passive from other connection", lambda: ch2.queue_declare(q, passive=True), 405)
    ch2 = c2.channel()
    channel_error(t, "consume from other connection", lambda: ch2.basic_consume(q, lambda *a: None), 405)
    ch2 = c2.channel()
    channel_error(t, "delete from other connection", lambda: ch2.queue_delete(q), 405)
    ch2 = c2.channel()
    channel_error(t, "get from other connection", lambda: ch2.basic_get(q), 405)
    ch2 = c2.channel()
    ch2.basic_publish("", q, b"publish is allowed")
    ch2.confirm_delivery()
    t.eq("publish from other connection delivered", get_bodies(ch1, q), ["publish is allowed"])
    c1.close()
    wait_until(lambda: _queue_missing(c2, q), what="exclusive queue to go with its connection")
    t.obs("deleted with owner connection")


def _queue_missing(conn, q):
    ch = conn.channel()
    try:
        ch.queue_declare(q, passive=True)
        ch.close()
        return False
    except pe.ChannelClosedByBroker as e:
        return e.reply_code == 404


@s("queue.auto_delete_after_last_consumer")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = t.n("autodelq")
    tidy(t, queues=[q])
    ch.queue_declare(q, auto_delete=True)
    ch.basic_publish("", q, b"x")
    ch.confirm_delivery()
    t.eq("survives without consumers", ch.queue_declare(q, passive=True).method.message_count, 1)
    tag1 = ch.basic_consume(q, lambda *a: None, auto_ack=True)
    tag2 = ch.basic_consume(q, lambda *a: None, auto_ack=True)
    ch.basic_cancel(tag1)
    t.eq("one consumer left", ch.queue_declare(q, passive=True).method.consumer_count, 1)
    ch.basic_cancel(tag2)
    wait_until(lambda: _queue_missing(conn, q), what="auto-delete")
    t.obs("deleted after last cancel")


@s("queue.purge_and_delete_counts")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = t.n("purge")
    tidy(t, queues=[q])
    ch.queue_declare(q)
    for i in range(5):
        ch.basic_publish("", q, b"x")
    ch.confirm_delivery()
    t.eq("purge count", ch.queue_purge(q).method.message_count, 5)
    t.eq("purge again", ch.queue_purge(q).method.message_count, 0)
    for i in range(2):
        ch.basic_publish("", q, b"x")
    channel_error(t, "delete if_empty", lambda: ch.queue_delete(q, if_empty=True), 406)
    ch = conn.channel()
    tag = ch.basic_consume(q, lambda *a: None)
    ch2 = conn.channel()
    channel_error(t, "delete if_unused", lambda: ch2.queue_delete(q, if_unused=True), 406)
    ch.basic_cancel(tag)
    ch.close()
    ch = conn.channel()
    t.eq("delete count", ch.queue_delete(q).method.message_count, 2)
    t.eq("delete missing", ch.queue_delete(q).method.message_count, 0)
    channel_error(t, "purge missing", lambda: ch.queue_purge(q), 404)


@s("queue.message_ttl")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    # A TTL a loaded machine reads the count well within.
    q = ch.queue_declare("", exclusive=True, arguments={"x-message-ttl": 1000}).method.queue
    ch.basic_publish("", q, b"short")
    ch.confirm_delivery()
    t.eq("before ttl", ch.queue_declare(q, passive=True).method.message_count, 1)
    time.sleep(1.5)
    t.eq("get after ttl", ch.basic_get(q, auto_ack=True)[0], None)
    t.eq("count after ttl", ch.queue_declare(q, passive=True).method.message_count, 0)


@s("queue.per_message_expiration")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    ch.basic_publish("", q, b"expires", properties=pika.BasicProperties(expiration="100"))
    ch.basic_publish("", q, b"stays", properties=pika.BasicProperties(expiration="60000"))
    ch.basic_publish("", q, b"forever")
    ch.confirm_delivery()
    time.sleep(0.4)
    m, p, b = ch.basic_get(q, auto_ack=True)
    t.eq("first left", [b, p.expiration], [b"stays", "60000"])
    t.eq("rest", get_bodies(ch, q), ["forever"])
    channel_error(t, "invalid expiration", lambda: (ch.basic_publish("", q, b"x", properties=pika.BasicProperties(expiration="soon")), ch.queue_declare(q, passive=True)), 406)


@s("queue.ttl_lower_of_queue_and_message")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True, arguments={"x-message-ttl": 60000}).method.queue
    ch.basic_publish("", q, b"msg-ttl-wins", properties=pika.BasicProperties(expiration="50"))
    ch.basic_publish("", q, b"queue-ttl")
    ch.confirm_delivery()
    time.sleep(0.3)
    t.eq("remaining", get_bodies(ch, q), ["queue-ttl"])


@s("queue.expires_unused")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = t.n("expires")
    tidy(t, queues=[q])
    # An expiry a loaded machine checks existence well within.
    ch.queue_declare(q, arguments={"x-expires": 1000})
    t.eq("exists", _queue_missing(conn, q), False)
    time.sleep(2.0)
    t.eq("deleted when unused", _queue_missing(conn, q), True)


@s("queue.max_length_drop_head")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True, arguments={"x-max-length": 3}).method.queue
    for i in range(6):
        ch.basic_publish("", q, str(i).encode())
    ch.confirm_delivery()
    t.eq("kept newest", get_bodies(ch, q), ["3", "4", "5"])


@s("queue.max_length_reject_publish")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True, arguments={"x-max-length": 2, "x-overflow": "reject-publish"}).method.queue
    ch.confirm_delivery()
    results = []
    for i in range(4):
        try:
            ch.basic_publish("", q, str(i).encode())
            results.append("ack")
        except pe.NackError:
            results.append("nack")
    t.eq("confirms", results, ["ack", "ack", "nack", "nack"])
    t.eq("kept oldest", get_bodies(ch, q), ["0", "1"])


@s("queue.max_length_bytes")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True, arguments={"x-max-length-bytes": 10}).method.queue
    for body in [b"aaaa", b"bbbb", b"cccc", b"dd"]:
        ch.basic_publish("", q, body)
    ch.confirm_delivery()
    t.eq("within 10 bytes", get_bodies(ch, q), ["bbbb", "cccc", "dd"])


def _xdeath(props):
    d = (props.headers or {}).get("x-death") or []
    out = []
    for e in d:
        out.append({k: (v if k != "time" else "t") for k, v in e.items()})
    return out


@s("queue.dead_letter_rejected")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    dlx = t.n("dlx")
    tidy(t, exchanges=[dlx])
    ch.exchange_declare(dlx, "direct")
    dlq = ch.queue_declare("", exclusive=True).method.queue
    ch.queue_bind(dlq, dlx, routing_key="dead")
    q = ch.queue_declare(t.n("dl-src"), exclusive=True, arguments={"x-dead-letter-exchange": dlx, "x-dead-letter-routing-key": "dead"}).method.queue
    ch.basic_publish("", q, b"bad", properties=pika.BasicProperties(headers={"h": 1}, message_id="m1"))
    ch.confirm_delivery()
    m, p, b = ch.basic_get(q)
    ch.basic_reject(m.delivery_tag, requeue=False)
    m2, p2, b2 = ch.basic_get(q)
    m, p, b = ch.basic_get(q)
    t.eq("source empty", m2, None)
    wait_until(lambda: ch.queue_declare(dlq, passive=True).method.message_count == 1, what="dead letter")
    m, p, b = ch.basic_get(dlq, auto_ack=True)
    t.eq("dead-lettered body", b, b"bad")
    t.eq("dead-letter routing", [m.exchange, m.routing_key], [dlx, "dead"])
    t.eq("message id kept", p.message_id, "m1")
    t.eq("user header kept", p.headers.get("h"), 1)
    xd = _xdeath(p)
    t.eq("x-death", xd, [{"count": 1, "exchange": "", "queue": q, "reason": "rejected", "routing-keys": [q], "time": "t"}])
    t.eq("x-first-death", [p.headers.get("x-first-death-reason"), p.headers.get("x-first-death-queue"), p.headers.get("x-first-death-exchange")], ["rejected", q, ""])


@s("queue.dead_letter_expired_keeps_routing_key")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    dlx = t.n("dlx-exp")
    tidy(t, exchanges=[dlx])
    ch.exchange_declare(dlx, "topic")
    dlq = ch.queue_declare("", exclusive=True).method.queue
    ch.queue_bind(dlq, dlx, routing_key="#")
    src = ch.queue_declare(t.n("dl-exp-src"), exclusive=True, arguments={"x-dead-letter-exchange": dlx, "x-message-ttl": 50}).method.queue
    ch.queue_bind(src, "amq.direct", routing_key="orig.key")
    ch.basic_publish("amq.direct", "orig.key", b"timed out")
    ch.confirm_delivery()
    wait_until(lambda: ch.queue_declare(dlq, passive=True).method.message_count == 1, what="expired dead letter")
    m, p, b = ch.basic_get(dlq, auto_ack=True)
    t.eq("routing key kept", [m.exchange, m.routing_key], [dlx, "orig.key"])
    t.eq("x-death", _xdeath(p), [{"count": 1, "exchange": "amq.direct", "queue": src, "reason": "expired", "routing-keys": ["orig.key"], "time": "t"}])
    t.eq("expiration removed", p.expiration, None)


@s("queue.dead_letter_maxlen_and_nack")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    dlq = ch.queue_declare(t.n("dlq-ml"), exclusive=True).method.queue
    src = ch.queue_declare(t.n("dl-ml-src"), exclusive=True, arguments={"x-dead-letter-exchange": "", "x-dead-letter-routing-key": dlq, "x-max-length": 1}).method.queue
    ch.basic_publish("", src, b"first")
    ch.basic_publish("", src, b"second")
    ch.confirm_delivery()
    wait_until(lambda: ch.queue_declare(dlq, passive=True).method.message_count == 1, what="maxlen dead letter")
    m, p, b = ch.basic_get(dlq, auto_ack=True)
    t.eq("dropped head dead-lettered", [b, _xdeath(p)[0]["reason"]], [b"first", "maxlen"])
    m, p, b = ch.basic_get(src)
    ch.basic_nack(m.delivery_tag, requeue=False)
    wait_until(lambda: ch.queue_declare(dlq, passive=True).method.message_count == 1, what="nack dead letter")
    m, p, b = ch.basic_get(dlq, auto_ack=True)
    t.eq("nacked dead-lettered", [b, _xdeath(p)[0]["reason"]], [b"second", "rejected"])


@s("queue.dead_letter_cycle_count")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    a, b_ = t.n("cyc-a"), t.n("cyc-b")
    ch.queue_declare(a, exclusive=True, arguments={"x-dead-letter-exchange": "", "x-dead-letter-routing-key": b_})
    ch.queue_declare(b_, exclusive=True, arguments={"x-dead-letter-exchange": "", "x-dead-letter-routing-key": a})
    ch.basic_publish("", a, b"ping")
    ch.confirm_delivery()
    for hop, q in enumerate([a, b_, a]):
        wait_until(lambda: ch.queue_declare(q, passive=True).method.message_count == 1, what=f"hop {hop}")
        m, p, body = ch.basic_get(q)
        ch.basic_reject(m.delivery_tag, requeue=False)
    dest = b_
    wait_until(lambda: ch.queue_declare(dest, passive=True).method.message_count == 1, what="final hop")
    m, p, body = ch.basic_get(dest, auto_ack=True)
    xd = sorted(((e["queue"], e["count"], e["reason"]) for e in _xdeath(p)))
    t.eq("x-death counts per queue", xd, sorted([(a, 2, "rejected"), (b_, 1, "rejected")]))
    t.eq("most recent first", _xdeath(p)[0]["queue"], a)


@s("queue.priority")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True, arguments={"x-max-priority": 5}).method.queue
    for body, prio in [("p0", None), ("p3", 3), ("p9", 9), ("p1", 1), ("p3b", 3), ("p5", 5)]:
        ch.basic_publish("", q, body.encode(), properties=pika.BasicProperties(priority=prio))
    ch.confirm_delivery()
    t.eq("priority order", get_bodies(ch, q), ["p9", "p5", "p3", "p3b", "p1", "p0"])


@s("queue.no_priority_is_fifo")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    for body, prio in [("a", 1), ("b", 9), ("c", 5)]:
        ch.basic_publish("", q, body.encode(), properties=pika.BasicProperties(priority=prio))
    ch.confirm_delivery()
    t.eq("fifo order", get_bodies(ch, q), ["a", "b", "c"])


# consumers -----------------------------------------------------------------


@s("consume.basic_ack_and_fields")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    tag, got = consume_into(ch, q, consumer_tag="my-tag")
    t.eq("consumer tag", tag, "my-tag")
    ch.basic_publish("", q, b"one", properties=pika.BasicProperties(content_type="text/plain"))
    ch.basic_publish("", q, b"two")
    pump(conn, got, 2)
    t.eq(
        "deliveries",
        [[m.consumer_tag, m.delivery_tag, m.redelivered, m.exchange, m.routing_key, b] for m, p, b in got],
        [["my-tag", 1, False, "", q, b"one"], ["my-tag", 2, False, "", q, b"two"]],
    )
    t.eq("content type", got[0][1].content_type, "text/plain")
    ch.basic_ack(2, multiple=True)
    ch.basic_cancel(tag)
    t.eq("queue empty after ack", ch.queue_declare(q, passive=True).method.message_count, 0)


@s("consume.server_generated_tag")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    got = []
    ok = []
    impl = ch._impl
    # pika makes its own tag; ask the broker to name it through the raw frame
    # by consuming with an explicit empty tag through the impl.
    from pika import spec

    ev = threading.Event()

    def on_ok(frame):
        ok.append(frame.method.consumer_tag)

    impl._rpc(spec.Basic.Consume(queue=q, consumer_tag="", no_ack=True), on_ok, [spec.Basic.ConsumeOk])
    wait_until(lambda: (conn.process_data_events(0.01) or True) and ok, what="consume-ok")
    t.check(ok[0].startswith("amq.ctag-"), f"generated tag {ok[0]}")
    t.obs("generated tag", ok[0])


@s("consume.duplicate_tag_is_connection_error")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    ch.basic_consume(q, lambda *a: None, consumer_tag="dup")
    from pika import spec

    impl = ch._impl
    impl._rpc(spec.Basic.Consume(queue=q, consumer_tag="dup"), None, [spec.Basic.ConsumeOk])

    def wait_close():
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            conn.process_data_events(time_limit=0.05)

    connection_error(t, "duplicate consumer tag", wait_close, 530)


@s("consume.exclusive_consumer")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = t.n("exclcons")
    tidy(t, queues=[q])
    ch.queue_declare(q)
    ch.basic_consume(q, lambda *a: None, exclusive=True)
    ch2 = conn.channel()
    channel_error(t, "second consumer on exclusive", lambda: ch2.basic_consume(q, lambda *a: None), 403)
    ch3 = conn.channel()
    channel_error(t, "cannot take exclusive with consumers", lambda: _exclusive_over_existing(ch3, conn, q), 403)


def _exclusive_over_existing(ch, conn, q):
    ch.basic_consume(q, lambda *a: None, exclusive=True)


@s("consume.cancel_notification_on_queue_delete")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = t.n("cancelnotify")
    tidy(t, queues=[q])
    ch.queue_declare(q)
    cancelled = []
    ch.add_on_cancel_callback(lambda frame: cancelled.append(frame.method.consumer_tag))
    tag = ch.basic_consume(q, lambda *a: None, consumer_tag="watch")
    other = conn.channel()
    other.queue_delete(q)
    wait_until(lambda: (conn.process_data_events(0.02) or True) and cancelled, what="basic.cancel from broker")
    t.eq("cancelled tag", cancelled, ["watch"])
    t.eq("channel still open", ch.is_open, True)


@s("consume.tag_reusable_after_server_cancel")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    other = conn.channel()
    q = t.n("retag")
    tidy(t, queues=[q])
    ch.queue_declare(q)
    cancelled = []
    ch.add_on_cancel_callback(lambda frame: cancelled.append(frame.method.consumer_tag))
    ch.basic_consume(q, lambda *a: None, auto_ack=True, consumer_tag="t1")
    other.queue_delete(q)
    wait_until(lambda: (conn.process_data_events(0.02) or True) and cancelled, what="basic.cancel from broker")
    ch.queue_declare(q)
    got = []
    ch.basic_consume(q, lambda c, m, p, b: got.append(b), auto_ack=True, consumer_tag="t1")
    t.obs("same tag accepted again", True)
    ch.basic_publish("", q, b"recovered")
    pump(conn, got, 1)
    t.eq("delivered to the re-registered consumer", got, [b"recovered"])


@s("consume.round_robin")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    got = []
    ch.basic_consume(q, lambda c, m, p, b: got.append(("A", b.decode())), auto_ack=True, consumer_tag="A")
    ch.basic_consume(q, lambda c, m, p, b: got.append(("B", b.decode())), auto_ack=True, consumer_tag="B")
    for i in range(6):
        ch.basic_publish("", q, str(i).encode())
    pump(conn, got, 6)
    t.eq("alternating", got, [("A", "0"), ("B", "1"), ("A", "2"), ("B", "3"), ("A", "4"), ("B", "5")])


@s("consume.missing_queue")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    channel_error(t, "consume missing queue", lambda: ch.basic_consume(t.n("nope"), lambda *a: None), 404)


@s("consume.cancel_unknown_tag_ok")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    from pika import spec

    ok = []
    ch._impl._rpc(spec.Basic.Cancel(consumer_tag="never-was"), lambda f: ok.append(f.method.consumer_tag), [spec.Basic.CancelOk])
    wait_until(lambda: (conn.process_data_events(0.01) or True) and ok, what="cancel-ok")
    t.eq("cancel-ok tag", ok, ["never-was"])


@s("consume.cancel_then_unacked_requeued")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    for i in range(3):
        ch.basic_publish("", q, str(i).encode())
    tag, got = consume_into(ch, q)
    pump(conn, got, 3)
    ch.basic_cancel(tag)
    settle(conn, 0.1)
    t.eq("cancel keeps unacked with channel", ch.queue_declare(q, passive=True).method.message_count, 0)
    ch.basic_ack(got[1][0].delivery_tag)
    ch2 = conn.channel()
    ch.close()
    m1 = ch2.basic_get(q, auto_ack=True)
    m2 = ch2.basic_get(q, auto_ack=True)
    t.eq("requeued on close, redelivered", [[m1[2], m1[0].redelivered], [m2[2], m2[0].redelivered]], [[b"0", True], [b"2", True]])


@s("consume.single_active_consumer_close_hands_over")
def _(t):
    """x-single-active-consumer: the first consumer gets everything; when
    its channel closes the next one takes over, its unacked first."""
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True, arguments={"x-single-active-consumer": True}).method.queue
    ch1 = conn.channel()
    ch1.basic_qos(prefetch_count=5)
    got1 = []
    ch1.basic_consume(q, lambda c, m, p, b: got1.append((b.decode(), m.redelivered)), consumer_tag="first")
    ch2 = conn.channel()
    got2 = []
    ch2.basic_consume(q, lambda c, m, p, b: got2.append((b.decode(), m.redelivered)), auto_ack=True, consumer_tag="second")
    for i in range(1, 11):
        ch.basic_publish("", q, str(i).encode())
    pump(conn, got1, 5)
    settle(conn, 0.2)
    t.eq("active consumer's share", got1, [(str(i), False) for i in range(1, 6)])
    t.eq("waiting consumer's share", got2, [])
    ch1.close()
    pump(conn, got2, 10)
    t.eq(
        "hand-over: unacked first, redelivered, then the rest",
        got2,
        [(str(i), True) for i in range(1, 6)] + [(str(i), False) for i in range(6, 11)],
    )


@s("consume.priority_overflow")
def _(t):
    """x-priority: the higher consumer gets messages while it has prefetch
    room, the lower one the overflow."""
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    low_ch = conn.channel()
    low_ch.basic_qos(prefetch_count=10)
    low = []
    low_ch.basic_consume(q, lambda c, m, p, b: low.append(b.decode()), arguments={"x-priority": 1})
    high_ch = conn.channel()
    high_ch.basic_qos(prefetch_count=3)
    high = []
    high_ch.basic_consume(q, lambda c, m, p, b: high.append(b.decode()), arguments={"x-priority": 10})
    for i in range(1, 6):
        ch.basic_publish("", q, str(i).encode())
    pump(conn, high, 3)
    pump(conn, low, 2)
    t.eq("high first", high, ["1", "2", "3"])
    t.eq("low gets the overflow", low, ["4", "5"])
    channel_error(
        t,
        "x-priority must be an integer",
        lambda: conn.channel().basic_consume(q, lambda *a: None, arguments={"x-priority": "high"}),
        406,
    )


@s("queue.other_queue_types_arguments_refused")
def _(t):
    """Arguments of quorum queues and streams are refused on a classic
    queue, naming them; unknown arguments are kept and not compared."""
    conn = connect(t)
    for key, value in [
        ("x-delivery-limit", 5),
        ("x-dead-letter-strategy", "at-most-once"),
        ("x-max-age", "1D"),
        ("x-max-in-memory-length", 3),
        ("x-queue-leader-locator", "balanced"),
        ("x-initial-cluster-size", 3),
    ]:
        ch = conn.channel()
        q = t.n("othertype")
        e = channel_error(t, key, lambda: ch.queue_declare(q, arguments={key: value}), 406)
        t.eq(f"{key} text", e.reply_text, f"PRECONDITION_FAILED - invalid arg '{key}' for queue '{q}' in vhost '/' of queue type rabbit_classic_queue")
    ch = conn.channel()
    q = t.n("unknownarg")
    tidy(t, queues=[q])
    ch.queue_declare(q, arguments={"x-app-owner": "a", "x-message-ttl": 60000})
    ch.queue_declare(q, arguments={"x-app-owner": "b", "x-message-ttl": 60000})
    t.obs("unknown argument not compared")
    e = channel_error(t, "ttl compared", lambda: ch.queue_declare(q, arguments={"x-message-ttl": 1000}), 406)
    t.eq("ttl text", e.reply_text, f"PRECONDITION_FAILED - inequivalent arg 'x-message-ttl' for queue '{q}' in vhost '/': received '1000' but current is '60000'")


@s("consume.no_ack_mode")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    tag, got = consume_into(ch, q, auto_ack=True)
    for i in range(5):
        ch.basic_publish("", q, b"x")
    pump(conn, got, 5)
    ch.basic_cancel(tag)
    ch.close()
    ch = conn.channel()
    t.eq("nothing requeued", ch.queue_declare(q, passive=True).method.message_count, 0)


# prefetch ------------------------------------------------------------------


@s("prefetch.per_consumer")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    ch.basic_qos(prefetch_count=2)
    for i in range(5):
        ch.basic_publish("", q, str(i).encode())
    tag, got = consume_into(ch, q)
    pump(conn, got, 2)
    settle(conn, 0.3)
    t.eq("limited to 2", len(got), 2)
    ch.basic_ack(got[0][0].delivery_tag)
    pump(conn, got, 3)
    settle(conn, 0.2)
    t.eq("one more after ack", len(got), 3)
    ch.basic_ack(got[2][0].delivery_tag, multiple=True)
    pump(conn, got, 5)
    t.eq("order", [b.decode() for _, _, b in got], ["0", "1", "2", "3", "4"])


@s("prefetch.global_shared_across_consumers")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q1 = ch.queue_declare("", exclusive=True).method.queue
    q2 = ch.queue_declare("", exclusive=True).method.queue
    ch.basic_qos(prefetch_count=3, global_qos=True)
    for i in range(4):
        ch.basic_publish("", q1, b"a")
        ch.basic_publish("", q2, b"b")
    got = []
    ch.basic_consume(q1, lambda c, m, p, b: got.append(m))
    ch.basic_consume(q2, lambda c, m, p, b: got.append(m))
    pump(conn, got, 3)
    settle(conn, 0.3)
    t.eq("channel-wide limit", len(got), 3)
    ch.basic_ack(0, multiple=True)
    pump(conn, got, 6)
    settle(conn, 0.2)
    t.eq("three more", len(got), 6)


@s("prefetch.per_consumer_and_global_combined")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    ch.basic_qos(prefetch_count=5, global_qos=True)
    ch.basic_qos(prefetch_count=1, global_qos=False)
    for i in range(6):
        ch.basic_publish("", q, b"m")
    got = []
    ch.basic_consume(q, lambda c, m, p, b: got.append(m))
    ch.basic_consume(q, lambda c, m, p, b: got.append(m))
    pump(conn, got, 2)
    settle(conn, 0.3)
    t.eq("one per consumer", len(got), 2)


@s("prefetch.size_not_implemented")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    connection_error(t, "prefetch_size", lambda: ch.basic_qos(prefetch_size=1024, prefetch_count=1), 540)


@s("prefetch.zero_means_unlimited")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    ch.basic_qos(prefetch_count=1)
    ch.basic_qos(prefetch_count=0)
    for i in range(20):
        ch.basic_publish("", q, b"m")
    tag, got = consume_into(ch, q)
    pump(conn, got, 20)
    t.eq("all delivered", len(got), 20)


# acks, nacks, rejects, recover --------------------------------------------------


def _fill(ch, q, n):
    for i in range(n):
        ch.basic_publish("", q, str(i).encode())
    ch.confirm_delivery() if False else None


@s("ack.multiple")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    _fill(ch, q, 4)
    tag, got = consume_into(ch, q)
    pump(conn, got, 4)
    ch.basic_ack(got[2][0].delivery_tag, multiple=True)
    ch.basic_cancel(tag)
    ch2 = conn.channel()
    ch.close()
    t.eq("only the last requeued", [(b, m.redelivered) for m, p, b in [ch2.basic_get(q, auto_ack=True)]], [(b"3", True)])


@s("ack.nack_requeue_redelivered")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    _fill(ch, q, 3)
    tag, got = consume_into(ch, q)
    pump(conn, got, 3)
    ch.basic_nack(got[0][0].delivery_tag, requeue=True)
    pump(conn, got, 4)
    t.eq("redelivery", [got[3][2], got[3][0].redelivered, got[3][0].delivery_tag], [b"0", True, 4])
    ch.basic_nack(0, multiple=True, requeue=True)
    pump(conn, got, 7)
    t.eq("multiple nack redelivers in order", [(b.decode(), m.redelivered) for m, p, b in got[4:]], [("0", True), ("1", True), ("2", True)])
    ch.basic_ack(0, multiple=True)


@s("ack.reject_requeue_false_drops")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    _fill(ch, q, 2)
    m, p, b = ch.basic_get(q)
    ch.basic_reject(m.delivery_tag, requeue=False)
    m, p, b = ch.basic_get(q)
    ch.basic_reject(m.delivery_tag, requeue=True)
    m, p, b = ch.basic_get(q, auto_ack=True)
    t.eq("only requeued one left", [b, m.redelivered], [b"1", True])
    t.eq("empty", ch.basic_get(q)[0], None)


@s("ack.requeue_keeps_position")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    _fill(ch, q, 5)
    got = [ch.basic_get(q) for _ in range(3)]
    ch.basic_nack(got[1][0].delivery_tag, requeue=True)
    ch.basic_nack(got[0][0].delivery_tag, requeue=True)
    ch.basic_nack(got[2][0].delivery_tag, requeue=True)
    order = [(b.decode(), m.redelivered) for m, p, b in [ch.basic_get(q, auto_ack=True) for _ in range(5)]]
    t.eq("requeued go back to original positions", order, [("0", True), ("1", True), ("2", True), ("3", False), ("4", False)])


@s("ack.recover_requeue")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    _fill(ch, q, 2)
    tag, got = consume_into(ch, q)
    pump(conn, got, 2)
    ch.basic_recover(requeue=True)
    pump(conn, got, 4)
    t.eq("redelivered", [(b.decode(), m.redelivered, m.delivery_tag) for m, p, b in got[2:]], [("0", True, 3), ("1", True, 4)])
    ch.basic_ack(4, multiple=True)


@s("ack.unknown_delivery_tag")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    ch.basic_ack(42)
    channel_error(t, "ack unknown tag", lambda: ch.queue_declare(q, passive=True), 406)
    ch = conn.channel()
    _fill(ch, q, 1)
    m, p, b = ch.basic_get(q)
    ch.basic_ack(m.delivery_tag)
    ch.basic_ack(m.delivery_tag)
    channel_error(t, "double ack", lambda: ch.queue_declare(q, passive=True), 406)
    ch = conn.channel()
    ch.basic_reject(7)
    channel_error(t, "reject unknown tag", lambda: ch.queue_declare(q, passive=True), 406)
    ch = conn.channel()
    ch.basic_nack(9, multiple=True)
    channel_error(t, "nack unknown tag", lambda: ch.queue_declare(q, passive=True), 406)


@s("ack.ack_all_with_zero_multiple")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    _fill(ch, q, 3)
    for _ in range(3):
        ch.basic_get(q)
    ch.basic_ack(0, multiple=True)
    ch2 = conn.channel()
    ch.close()
    t.eq("nothing requeued", ch2.queue_declare(q, passive=True).method.message_count, 0)


# basic.get -----------------------------------------------------------------


@s("get.fields_and_message_count")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    t.eq("empty get", ch.basic_get(q), (None, None, None))
    _fill(ch, q, 3)
    ch.confirm_delivery()
    m, p, b = ch.basic_get(q)
    t.eq("get-ok", [m.delivery_tag, m.redelivered, m.exchange, m.routing_key, m.message_count, b], [1, False, "", q, 2, b"0"])
    m, p, b = ch.basic_get(q, auto_ack=True)
    t.eq("second", [m.delivery_tag, m.message_count, b], [2, 1, b"1"])
    channel_error(t, "get missing queue", lambda: ch.basic_get(t.n("nope")), 404)


# mandatory returns ----------------------------------------------------------


@s("mandatory.return_no_route")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    returned = []
    ch.add_on_return_callback(lambda c, m, p, b: returned.append((m.reply_code, m.reply_text, m.exchange, m.routing_key, p.message_id, b)))
    ch.basic_publish("amq.direct", t.n("nobody"), b"lost", properties=pika.BasicProperties(message_id="r1"), mandatory=True)
    ch.basic_publish("amq.direct", t.n("nobody"), b"silent")
    wait_until(lambda: (conn.process_data_events(0.02) or True) and returned, what="basic.return")
    settle(conn, 0.2)
    t.eq("returns", returned, [(312, "NO_ROUTE", "amq.direct", t.n("nobody"), "r1", b"lost")])


@s("mandatory.return_before_confirm")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    ch.confirm_delivery()
    try:
        ch.basic_publish("", t.n("no-queue"), b"x", mandatory=True)
        raise Failure("no UnroutableError")
    except pe.UnroutableError as e:
        msgs = e.messages
        t.eq("returned", [(m.method.reply_code, m.method.routing_key, m.body) for m in msgs], [(312, t.n("no-queue"), b"x")])
    ch.basic_publish("", t.n("no-queue"), b"not mandatory")
    t.obs("unroutable non-mandatory acked")


@s("mandatory.to_missing_exchange")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    ch.confirm_delivery()
    channel_error(t, "publish to missing exchange", lambda: ch.basic_publish(t.n("noex"), "k", b"x", mandatory=True), 404)


# transactions ---------------------------------------------------------------


@s("tx.commit_and_rollback_publish")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    ch.tx_select()
    ch.basic_publish("", q, b"a")
    ch.basic_publish("", q, b"b")
    t.eq("invisible before commit", ch.queue_declare(q, passive=True).method.message_count, 0)
    ch.tx_commit()
    t.eq("visible after commit", ch.queue_declare(q, passive=True).method.message_count, 2)
    ch.basic_publish("", q, b"c")
    ch.tx_rollback()
    t.eq("rolled back", ch.queue_declare(q, passive=True).method.message_count, 2)
    ch.basic_publish("", q, b"d")
    ch.tx_commit()
    t.eq("order", get_bodies(conn.channel(), q), ["a", "b", "d"])


@s("tx.acks_in_transaction")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    _fill(ch, q, 2)
    ch.tx_select()
    m1 = ch.basic_get(q)[0]
    m2 = ch.basic_get(q)[0]
    ch.basic_ack(m1.delivery_tag)
    ch.tx_rollback()
    ch.basic_ack(m2.delivery_tag)
    ch.tx_commit()
    ch2 = conn.channel()
    ch.close()
    m, p, b = ch2.basic_get(q, auto_ack=True)
    t.eq("rolled-back ack requeued", [b, m.redelivered], [b"0", True])
    t.eq("empty", ch2.basic_get(q)[0], None)


@s("tx.commit_without_select")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    channel_error(t, "commit without select", ch.tx_commit, 406)
    ch = conn.channel()
    channel_error(t, "rollback without select", ch.tx_rollback, 406)


@s("tx.confirm_and_tx_exclusive")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    ch.confirm_delivery()
    channel_error(t, "tx.select on confirm channel", ch.tx_select, 406)
    ch = conn.channel()
    ch.tx_select()
    channel_error(t, "confirm.select on tx channel", ch.confirm_delivery, 406)


@s("tx.mandatory_return_on_commit")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    returned = []
    ch.add_on_return_callback(lambda c, m, p, b: returned.append((m.reply_code, b)))
    ch.tx_select()
    ch.basic_publish("", t.n("no-queue"), b"tx-unroutable", mandatory=True)
    ch.tx_commit()
    settle(conn, 0.3)
    t.eq("returned", returned, [(312, b"tx-unroutable")])


# confirms ------------------------------------------------------------------


@s("confirm.acks_in_order")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    acks = []
    impl = ch._impl
    from pika import spec

    impl.add_callback(lambda f: acks.append(("ack", f.method.delivery_tag, f.method.multiple)), [spec.Basic.Ack], one_shot=False)
    ok = []
    impl._rpc(spec.Confirm.Select(), lambda f: ok.append(1), [spec.Confirm.SelectOk])
    wait_until(lambda: (conn.process_data_events(0.01) or True) and ok, what="select-ok")
    for i in range(20):
        ch.basic_publish("", q, str(i).encode())
    deadline = time.monotonic() + HANG
    while time.monotonic() < deadline and (not acks or acks[-1][1] < 20):
        conn.process_data_events(time_limit=0.02)
    covered = set()
    last = 0
    for kind, tag, multiple in acks:
        t.check(tag > last, f"ack tags increase: {acks}")
        covered.update(range(last + 1, tag + 1) if multiple else [tag])
        last = tag
    t.eq("all 20 confirmed", sorted(covered), list(range(1, 21)))


@s("confirm.nack_not_expected_on_normal_publish")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    ch.confirm_delivery()
    for i in range(50):
        ch.basic_publish("", q, b"x" * i)
    t.eq("all in queue", ch.queue_declare(q, passive=True).method.message_count, 50)


# bodies and properties -------------------------------------------------------


@s("body.empty")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    ch.basic_publish("", q, b"")
    ch.basic_publish("", q, b"", properties=pika.BasicProperties(headers={"k": "v"}))
    tag, got = consume_into(ch, q, auto_ack=True)
    pump(conn, got, 2)
    t.eq("empty bodies", [b for m, p, b in got], [b"", b""])
    t.eq("headers kept", got[1][1].headers, {"k": "v"})


@s("body.large_5mib")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    body = bytes((i * 7) % 251 for i in range(5 * 1024 * 1024))
    ch.confirm_delivery()
    ch.basic_publish("", q, body)
    tag, got = consume_into(ch, q, auto_ack=True)
    pump(conn, got, 1, timeout=30)
    t.eq("length", len(got[0][2]), len(body))
    t.eq("identical", got[0][2] == body, True)
    m, p, b = ch.basic_get(q)
    t.eq("queue now empty", m, None)


@s("body.frame_boundaries")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    fm = conn._impl.params.frame_max
    sizes = [fm - 9, fm - 8, fm - 7, fm, 2 * (fm - 8), 2 * (fm - 8) + 1]
    for n in sizes:
        ch.basic_publish("", q, bytes([n % 256]) * n)
    ch.confirm_delivery()
    got = []
    while True:
        m, p, b = ch.basic_get(q, auto_ack=True)
        if m is None:
            break
        got.append(len(b) if b == bytes([len(b) % 256]) * len(b) else -1)
    t.eq("sizes", got, sizes)


@s("properties.all_basic_properties")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    props = pika.BasicProperties(
        content_type="application/json",
        content_encoding="gzip",
        headers={"a": 1},
        delivery_mode=2,
        priority=7,
        correlation_id="corr-1",
        reply_to="reply.queue",
        expiration="600000",
        message_id="msg-1",
        timestamp=1700000000,
        type="order.created",
        user_id=t.user,
        app_id="conformance",
        cluster_id="",
    )
    ch.basic_publish("", q, b"{}", properties=props)
    ch.confirm_delivery()
    m, p, b = ch.basic_get(q, auto_ack=True)
    fields = ["content_type", "content_encoding", "headers", "delivery_mode", "priority", "correlation_id", "reply_to", "expiration", "message_id", "timestamp", "type", "user_id", "app_id"]
    t.eq("properties", {f: getattr(p, f) for f in fields}, {f: getattr(props, f) for f in fields})


@s("properties.user_id_mismatch")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    ch.confirm_delivery()
    channel_error(t, "user_id of another user", lambda: ch.basic_publish("", q, b"x", properties=pika.BasicProperties(user_id="someone-else")), 406)


@s("properties.header_field_types")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    headers = {
        "str": "text ü",
        "int_small": 7,
        "int_neg": -42,
        "int_big": 2**40,
        "int_min": -(2**63),
        "bool_t": True,
        "bool_f": False,
        "decimal": decimal.Decimal("3.14"),
        "timestamp": datetime.datetime(2024, 1, 2, 3, 4, 5),
        "table": {"nested": {"deep": "yes"}, "n": 1},
        "array": [1, "two", True, {"x": 1}, [3]],
        "bytes": b"\x00\x01\xff",
        "void": None,
        "empty_str": "",
        "empty_table": {},
        "empty_array": [],
    }
    ch.basic_publish("", q, b"h", properties=pika.BasicProperties(headers=headers))
    ch.confirm_delivery()
    m, p, b = ch.basic_get(q, auto_ack=True)
    t.eq("headers round trip", p.headers, headers)


@s("properties.none_set")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    ch.basic_publish("", q, b"bare", properties=pika.BasicProperties())
    ch.confirm_delivery()
    m, p, b = ch.basic_get(q, auto_ack=True)
    fields = ["content_type", "content_encoding", "headers", "delivery_mode", "priority", "correlation_id", "reply_to", "expiration", "message_id", "timestamp", "type", "user_id", "app_id", "cluster_id"]
    t.eq("no properties", {f: getattr(p, f) for f in fields}, {f: None for f in fields})


# realistic loads ------------------------------------------------------------------


@s("load.rpc_reply_to_correlation")
def _(t):
    server_conn = connect(t)
    client_conn = connect(t)
    sch = server_conn.channel()
    rpcq = t.n("rpc")
    sch.queue_declare(rpcq, exclusive=True)
    sch.basic_qos(prefetch_count=4)

    def on_request(c, m, p, b):
        n = int(b)
        c.basic_publish("", p.reply_to, str(n * n).encode(), properties=pika.BasicProperties(correlation_id=p.correlation_id))
        c.basic_ack(m.delivery_tag)

    sch.basic_consume(rpcq, on_request)
    stop = threading.Event()

    def serve():
        while not stop.is_set():
            server_conn.process_data_events(time_limit=0.05)

    th = threading.Thread(target=serve, daemon=True)
    th.start()
    try:
        cch = client_conn.channel()
        replyq = cch.queue_declare("", exclusive=True).method.queue
        answers = {}
        cch.basic_consume(replyq, lambda c, m, p, b: answers.__setitem__(p.correlation_id, int(b)), auto_ack=True)
        for i in range(50):
            cch.basic_publish("", rpcq, str(i).encode(), properties=pika.BasicProperties(reply_to=replyq, correlation_id=f"c{i}"))
        pump(client_conn, answers, 50, timeout=15)
        t.eq("all answered correctly", answers, {f"c{i}": i * i for i in range(50)})
    finally:
        stop.set()
        th.join(2)


@s("load.direct_reply_to")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    rpcq = ch.queue_declare("", exclusive=True).method.queue
    replies = []
    ch.basic_consume("amq.rabbitmq.reply-to", lambda c, m, p, b: replies.append((b, p.correlation_id)), auto_ack=True)
    ch.basic_publish("", rpcq, b"q", properties=pika.BasicProperties(reply_to="amq.rabbitmq.reply-to", correlation_id="x1"))
    m, p, b = None, None, None
    wait_until(lambda: ch.queue_declare(rpcq, passive=True).method.message_count == 1, what="request")
    m, p, b = ch.basic_get(rpcq, auto_ack=True)
    t.check(p.reply_to.startswith("amq.rabbitmq.reply-to."), f"reply_to rewritten: {p.reply_to}")
    server = conn.channel()
    server.basic_publish("", p.reply_to, b"answer", properties=pika.BasicProperties(correlation_id=p.correlation_id))
    pump(conn, replies, 1)
    t.eq("reply", replies, [(b"answer", "x1")])


@s("load.work_queue_competing_consumers")
def _(t):
    q = t.n("work")
    tidy(t, queues=[q])
    producer = connect(t)
    pch = producer.channel()
    pch.queue_declare(q, durable=True)
    pch.confirm_delivery()
    N = 600
    for i in range(N):
        pch.basic_publish("", q, str(i).encode(), properties=pika.BasicProperties(delivery_mode=2))
    results = {}
    lock = threading.Lock()
    errors = []

    def worker(idx):
        try:
            c = pika.BlockingConnection(params(t))
            ch = c.channel()
            ch.basic_qos(prefetch_count=10)
            mine = []

            def cb(c_, m, p, b):
                mine.append(int(b))
                c_.basic_ack(m.delivery_tag)

            ch.basic_consume(q, cb)
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline:
                c.process_data_events(time_limit=0.05)
                with lock:
                    results[idx] = list(mine)
                    if sum(len(v) for v in results.values()) >= N:
                        break
            c.close()
        except Exception as e:  # noqa
            errors.append(repr(e))

    threads = [threading.Thread(target=worker, args=(i,)) for i in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join(30)
    t.eq("worker errors", errors, [])
    allmsgs = sorted(x for v in results.values() for x in v)
    t.eq("each message exactly once", allmsgs == list(range(N)), True)
    t.check(all(len(v) > 0 for v in results.values()) and len(results) == 4, f"every worker got work: {[len(v) for v in results.values()]}")
    t.obs("workers", len(results))


@s("load.fanout_many_queues")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    ex = t.n("fan-many")
    tidy(t, exchanges=[ex])
    ch.exchange_declare(ex, "fanout")
    qs = [ch.queue_declare("", exclusive=True).method.queue for _ in range(30)]
    for q in qs:
        ch.queue_bind(q, ex)
    ch.confirm_delivery()
    for i in range(20):
        ch.basic_publish(ex, "", str(i).encode())
    counts = [ch.queue_declare(q, passive=True).method.message_count for q in qs]
    t.eq("every queue has every message", counts, [20] * 30)
    t.eq("order in one queue", get_bodies(ch, qs[17]), [str(i) for i in range(20)])


@s("load.ordered_10k")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    for i in range(10000):
        ch.basic_publish("", q, str(i).encode())
    tag, got = consume_into(ch, q, auto_ack=True)
    pump(conn, got, 10000, timeout=30)
    t.eq("in order", [int(b) for m, p, b in got] == list(range(10000)), True)
    t.eq("tags", got[-1][0].delivery_tag, 10000)
