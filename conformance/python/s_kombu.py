"""Scenarios driven by kombu over its pyamqp transport (py-amqp), the way
Celery uses a broker, plus py-amqp directly for what kombu hides."""

import json
import socket
import threading
import time
import uuid

import amqp
import amqp.exceptions as ax
from kombu import Connection, Consumer, Exchange, Producer, Queue, binding

from harness import HANG, Failure, scenario, wait_until

LIB = "kombu"


def s(name):
    return scenario(LIB, name)


def kurl(t):
    return "pyamqp" + t.url[len("amqp"):] if t.url.startswith("amqp") else t.url


def kconn(t, **kw):
    c = Connection(kurl(t), connect_timeout=10, **kw)
    c.ensure_connection(max_retries=1)
    t.defer(c.release)
    return c


def raw(t, **kw):
    c = amqp.Connection(host=f"{t.host}:{t.port}", userid=kw.pop("userid", t.user), password=kw.pop("password", t.password),
                        virtual_host=kw.pop("virtual_host", t.vhost), connect_timeout=10, **kw)
    c.connect()
    t.defer(lambda: c.collect() if not c.connected else c.close())
    return c


def drain_until(conn, pred, timeout=HANG):
    deadline = time.monotonic() + timeout
    while not pred() and time.monotonic() < deadline:
        try:
            conn.drain_events(timeout=0.05)
        except socket.timeout:
            pass
    if not pred():
        raise Failure(f"condition not reached within {timeout}s")


def tidy(t, queues=(), exchanges=()):
    def cleanup():
        c = raw(t)
        ch = c.channel()
        for q in queues:
            ch.queue_delete(q)
        for e in exchanges:
            ch.exchange_delete(e)
        c.close()

    t.defer(cleanup)


@s("connection.pyamqp_transport")
def _(t):
    c = kconn(t)
    t.eq("transport", c.transport.driver_type, "amqp")
    t.eq("connected", c.connected, True)
    ch = c.default_channel
    q = Queue("", exclusive=True, channel=ch)
    q.declare()
    t.eq("server-named", q.name.startswith("amq.gen-"), True)


@s("pyamqp.login_methods")
def _(t):
    for method in ["AMQPLAIN", "PLAIN"]:
        c = raw(t, login_method=method)
        ch = c.channel()
        name, count, consumers = ch.queue_declare("", exclusive=True)
        t.eq(f"{method} login works", [count, consumers], [0, 0])
        c.close()


@s("pyamqp.refusals")
def _(t):
    for label, kw, code, cls in [
        ("bad password", {"password": "wrong"}, 403, ax.AccessRefused),
        ("unknown vhost", {"virtual_host": "no-such-vhost"}, 530, ax.NotAllowed),
        ("bad password AMQPLAIN", {"password": "wrong", "login_method": "AMQPLAIN"}, 403, ax.AccessRefused),
    ]:
        try:
            c = amqp.Connection(host=f"{t.host}:{t.port}", userid=t.user, password=kw.get("password", t.password),
                                virtual_host=kw.get("virtual_host", t.vhost), login_method=kw.get("login_method"), connect_timeout=10)
            c.connect()
            c.close()
        except ax.AMQPError as e:
            t.eq(label, [e.code, type(e).__name__], [code, cls.__name__])
            continue
        except (OSError, ConnectionError) as e:
            raise Failure(f"{label}: socket closed without connection.close: {e!r}")
        raise Failure(f"{label}: connection succeeded")


@s("pyamqp.channel_errors")
def _(t):
    c = raw(t)
    cases = [
        ("passive missing queue", lambda ch: ch.queue_declare(t.n("kombu-missing"), passive=True), ax.NotFound),
        ("bind missing exchange", lambda ch: ch.queue_bind(ch.queue_declare("", exclusive=True)[0], t.n("nope"), "k"), ax.NotFound),
        ("declare amq.* exchange", lambda ch: ch.exchange_declare("amq." + t.n("x"), "direct"), ax.AccessRefused),
        ("tx.commit without select", lambda ch: ch.tx_commit(), ax.PreconditionFailed),
    ]
    for label, fn, cls in cases:
        ch = c.channel()
        try:
            fn(ch)
        except ax.AMQPError as e:
            t.eq(label, [e.code, type(e).__name__], [cls.code, cls.__name__])
            continue
        raise Failure(f"{label}: no error")


@s("producer_consumer_json")
def _(t):
    c = kconn(t)
    ex = Exchange(t.n("kombu-direct"), type="direct", auto_delete=True)
    q = Queue(t.n("kombu-q"), exchange=ex, routing_key="r", exclusive=True)
    producer = Producer(c.default_channel, serializer="json")
    got = []

    def on_message(body, message):
        got.append((body, message.content_type, message.delivery_info["routing_key"], message.headers))
        message.ack()

    with Consumer(c, queues=[q], callbacks=[on_message], accept=["json"]):
        for i in range(5):
            producer.publish({"n": i, "s": "ü"}, exchange=ex, routing_key="r", declare=[q], headers={"i": i})
        drain_until(c, lambda: len(got) == 5)
    t.eq("messages", got, [({"n": i, "s": "ü"}, "application/json", "r", {"i": i}) for i in range(5)])


@s("simple_queue")
def _(t):
    c = kconn(t)
    name = t.n("kombu-simple")
    tidy(t, queues=[name])
    sq = c.SimpleQueue(name)
    for i in range(3):
        sq.put({"i": i})
    wait_until(lambda: sq.qsize() == 3, what="qsize 3")
    t.eq("qsize", sq.qsize(), 3)
    m = sq.get(block=True, timeout=5)
    t.eq("first", m.payload, {"i": 0})
    m.ack()
    m = sq.get(block=True, timeout=5)
    m.requeue()
    rest = []
    for _ in range(2):
        m = sq.get(block=True, timeout=5)
        rest.append([m.payload["i"], m.delivery_info["redelivered"]])
        m.ack()
    t.eq("requeued one redelivered", sorted(rest), [[1, True], [2, False]])
    try:
        sq.get(block=False)
        raise Failure("queue should be empty")
    except sq.Empty:
        t.obs("empty", True)
    sq.close()


@s("queue_arguments")
def _(t):
    c = kconn(t)
    ch = c.default_channel
    q = Queue(t.n("kombu-args"), exclusive=True, message_ttl=30.0, expires=60.0, max_length=2, max_priority=4, channel=ch)
    q.declare()
    q2 = Queue(t.n("kombu-args"), exclusive=True, message_ttl=30.0, expires=60.0, max_length=2, max_priority=4, channel=ch)
    q2.declare()
    t.obs("equivalent redeclare ok", True)
    producer = Producer(ch, serializer="json")
    for i in range(4):
        producer.publish(i, routing_key=q.name, priority=i % 3)
    got = []
    while True:
        m = q.get(no_ack=True)
        if m is None:
            break
        got.append(m.payload)
    t.eq("max-length drops from the head, which is the highest priority", got, [0, 3])


@s("topic_bindings")
def _(t):
    c = kconn(t)
    ex = Exchange(t.n("kombu-topic"), type="topic", auto_delete=True)
    q = Queue(t.n("kombu-multi"), exclusive=True, bindings=[binding(ex, routing_key="a.*"), binding(ex, routing_key="*.z")])
    ch = c.default_channel
    q(ch).declare()
    producer = Producer(ch, serializer="json")
    for key in ["a.b", "b.z", "a.z", "c.c"]:
        producer.publish(key, exchange=ex, routing_key=key)
    time.sleep(0.2)
    got = []
    bq = q(ch)
    while True:
        m = bq.get(no_ack=True)
        if m is None:
            break
        got.append(m.payload)
    t.eq("routed once each", got, ["a.b", "b.z", "a.z"])


@s("confirm_publish_transport_option")
def _(t):
    c = kconn(t, transport_options={"confirm_publish": True})
    q = Queue(t.n("kombu-confirm"), exclusive=True)
    producer = Producer(c.default_channel, serializer="json")
    for i in range(50):
        producer.publish(i, routing_key=q.name, declare=[q])
    name, count, _ = c.default_channel.queue_declare(q.name, passive=True)
    t.eq("all confirmed and queued", count, 50)


@s("pyamqp.recover_qos_flow")
def _(t):
    c = raw(t)
    ch = c.channel()
    q, _, _ = ch.queue_declare("", exclusive=True)
    for i in range(3):
        ch.basic_publish(amqp.Message(str(i)), routing_key=q)
    ch.basic_qos(0, 1, False)
    got = []
    ch.basic_consume(q, callback=lambda m: got.append((m.body, m.delivery_info["redelivered"], m.delivery_tag)))
    drain_until(c, lambda: len(got) == 1)
    try:
        c.drain_events(timeout=0.3)
    except socket.timeout:
        pass
    t.eq("prefetch 1", len(got), 1)
    ch.basic_recover(requeue=True)
    drain_until(c, lambda: len(got) == 2)
    t.eq("recovered", got, [("0", False, 1), ("0", True, 2)])
    ch.basic_ack(2)
    drain_until(c, lambda: len(got) == 3)
    t.eq("next", got[2], ("1", False, 3))


def _celery_task_message(task, args, task_id, reply_to, retries=0):
    headers = {
        "lang": "py", "task": task, "id": task_id, "shadow": None, "eta": None, "expires": None, "group": None,
        "group_index": None, "retries": retries, "timelimit": [None, None], "root_id": task_id, "parent_id": None,
        "argsrepr": repr(args), "kwargsrepr": "{}", "origin": "gen1@conformance", "ignore_result": False,
    }
    body = [args, {}, {"callbacks": None, "errbacks": None, "chain": None, "chord": None}]
    return body, headers


@s("load.celery_worker_pool")
def _(t):
    """Celery's protocol 2 over kombu: a direct `celery` exchange and queue,
    4 workers with prefetch 4 and late acks, results to the client's
    reply_to queue by correlation_id (the rpc:// backend), one task that
    fails once and is retried by republishing with retries+1."""
    exname, qname = t.n("celery"), t.n("celery")
    tidy(t, queues=[qname], exchanges=[exname])
    ex = Exchange(exname, type="direct", durable=True)
    task_q = Queue(qname, exchange=ex, routing_key=qname, durable=True)
    client = kconn(t)
    reply_q = Queue(t.n("celery-reply-") + uuid.uuid4().hex[:6], exclusive=True, auto_delete=True)
    results = {}
    lock = threading.Lock()
    stop = threading.Event()
    errors = []
    per_worker = [0] * 4
    ready = []

    def worker(idx):
        try:
            with Connection(kurl(t), connect_timeout=10) as wc:
                ch = wc.channel()
                wprod = Producer(ch, serializer="json")

                def on_task(body, message):
                    args, kwargs, embed = body
                    h = message.headers
                    if h["task"] == "tasks.flaky" and h["retries"] == 0:
                        b2, h2 = _celery_task_message(h["task"], args, h["id"], message.properties["reply_to"], retries=1)
                        wprod.publish(b2, exchange=ex, routing_key=qname, headers=h2, correlation_id=h["id"],
                                      reply_to=message.properties["reply_to"], delivery_mode=2)
                        message.ack()
                        return
                    result = sum(args)
                    wprod.publish({"status": "SUCCESS", "result": result, "task_id": h["id"], "retries": h["retries"]},
                                  routing_key=message.properties["reply_to"], correlation_id=message.properties["correlation_id"])
                    per_worker[idx] += 1
                    message.ack()

                with Consumer(ch, queues=[task_q], callbacks=[on_task], accept=["json"], prefetch_count=4):
                    ready.append(idx)
                    while not stop.is_set():
                        try:
                            wc.drain_events(timeout=0.1)
                        except socket.timeout:
                            pass
        except Exception as e:  # noqa
            errors.append(repr(e))

    threads = [threading.Thread(target=worker, args=(i,), daemon=True) for i in range(4)]
    for th in threads:
        th.start()
    try:
        ch = client.default_channel
        wait_until(lambda: len(ready) == 4 or errors, timeout=10, what="4 workers consuming")
        reply_q(ch).declare()
        producer = Producer(ch, serializer="json")
        N = 120
        ids = []
        for i in range(N):
            tid = str(uuid.uuid4())
            ids.append(tid)
            task = "tasks.flaky" if i % 40 == 0 else "tasks.add"
            body, headers = _celery_task_message(task, [i, 1], tid, reply_q.name)
            producer.publish(body, exchange=ex, routing_key=qname, declare=[task_q], headers=headers, correlation_id=tid,
                             reply_to=reply_q.name, delivery_mode=2, priority=0, content_encoding="utf-8")

        def on_result(body, message):
            with lock:
                results[message.properties["correlation_id"]] = body
            message.ack()

        with Consumer(client, queues=[reply_q], callbacks=[on_result], accept=["json"]):
            drain_until(client, lambda: len(results) >= N, timeout=30)
    finally:
        stop.set()
        for th in threads:
            th.join(5)
    t.eq("worker errors", errors, [])
    t.eq("every task answered correctly", all(results[tid]["result"] == i + 1 for i, tid in enumerate(ids)), True)
    t.eq("flaky tasks retried once", sorted(r["retries"] for r in results.values() if r["retries"]), [1, 1, 1])
    t.check(all(n > 0 for n in per_worker), f"every worker ran tasks: {per_worker}")


@s("load.celery_pidbox_broadcast")
def _(t):
    """Celery remote control: a fanout pidbox exchange, one auto-delete queue
    per worker with x-message-ttl and x-expires, replies on a direct exchange."""
    pidbox = Exchange(t.n("celery.pidbox"), type="fanout", durable=False, auto_delete=True)
    reply_ex = Exchange(t.n("reply.celery.pidbox"), type="direct", durable=False, auto_delete=True)
    c = kconn(t)
    ch = c.default_channel
    workers = []
    for i in range(3):
        q = Queue(f"{t.n('worker')}{i}.celery.pidbox", exchange=pidbox, auto_delete=True, durable=False,
                  queue_arguments={"x-message-ttl": 300000, "x-expires": 10000})
        q(ch).declare()
        workers.append(q)
    ticket = str(uuid.uuid4())
    reply_q = Queue(t.n("reply-") + ticket[:8], exchange=reply_ex, routing_key=ticket, auto_delete=True, durable=False,
                    queue_arguments={"x-message-ttl": 300000, "x-expires": 10000})
    reply_q(ch).declare()
    producer = Producer(ch, serializer="json")
    producer.publish({"method": "ping", "arguments": {}, "destination": None, "ticket": ticket, "reply_to": {"exchange": reply_ex.name, "routing_key": ticket}},
                     exchange=pidbox, routing_key="", declare=[pidbox])
    time.sleep(0.2)
    for i, q in enumerate(workers):
        m = q(ch).get(no_ack=True)
        t.check(m is not None, f"worker {i} got no broadcast")
        producer.publish({f"worker{i}@host": {"ok": "pong"}}, exchange=reply_ex, routing_key=m.payload["reply_to"]["routing_key"], ticket=ticket)
    time.sleep(0.2)
    replies = []
    while True:
        m = reply_q(ch).get(no_ack=True)
        if m is None:
            break
        replies.append(m.payload)
    t.eq("pong from each worker", sorted(list(r)[0] for r in replies), ["worker0@host", "worker1@host", "worker2@host"])


@s("load.celery_events_topic")
def _(t):
    ev = Exchange(t.n("celeryev"), type="topic", durable=True, auto_delete=False)
    tidy(t, exchanges=[ev.name])
    c = kconn(t)
    ch = c.default_channel
    mon = Queue(t.n("celeryev.") + uuid.uuid4().hex[:6], exchange=ev, routing_key="#", auto_delete=True, durable=False,
                queue_arguments={"x-message-ttl": 5000, "x-expires": 60000})
    only_workers = Queue(t.n("celeryev-w.") + uuid.uuid4().hex[:6], exchange=ev, routing_key="worker.#", auto_delete=True, durable=False)
    mon(ch).declare()
    only_workers(ch).declare()
    producer = Producer(ch, serializer="json")
    for key in ["worker.online", "task.sent", "worker.heartbeat", "task.succeeded", "worker.offline"]:
        producer.publish({"type": key.replace(".", "-"), "timestamp": 1.0}, exchange=ev, routing_key=key, delivery_mode=1)
    time.sleep(0.2)

    def collect(q):
        out = []
        while True:
            m = q(ch).get(no_ack=True)
            if m is None:
                return out
            out.append(m.payload["type"])

    t.eq("monitor sees all", collect(mon), ["worker-online", "task-sent", "worker-heartbeat", "task-succeeded", "worker-offline"])
    t.eq("worker events only", collect(only_workers), ["worker-online", "worker-heartbeat", "worker-offline"])
