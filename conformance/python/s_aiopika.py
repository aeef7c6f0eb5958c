"""Scenarios driven by aio-pika (asyncio, on aiormq/pamqp)."""

import asyncio
import datetime
import decimal

import aio_pika
import aiormq.exceptions as ae
from aio_pika.patterns import RPC, Master

from harness import Failure, scenario


async def settled(pred, timeout=10.0):
    """Waits until pred() holds, then a little longer, so that what would
    break it (one delivery too many) has had time to arrive."""
    deadline = asyncio.get_running_loop().time() + timeout
    while not pred():
        if asyncio.get_running_loop().time() > deadline:
            raise Failure(f"timed out after {timeout}s")
        await asyncio.sleep(0.02)
    await asyncio.sleep(0.2)


LIB = "aio-pika"


def s(name):
    return scenario(LIB, name)


CODES = {
    ae.ChannelAccessRefused: 403,
    ae.ChannelNotFoundEntity: 404,
    ae.ChannelLockedResource: 405,
    ae.ChannelPreconditionFailed: 406,
}


async def connect(t, url=None, **kw):
    conn = await aio_pika.connect(url or t.url, **kw)
    t.defer(conn.close)
    return conn


async def channel_error(t, label, coro, code):
    try:
        await coro
    except ae.ChannelClosed as e:
        got = next((c for cls, c in CODES.items() if isinstance(e, cls)), type(e).__name__)
        t.eq(label, got, code)
        return
    raise Failure(f"{label}: expected channel error {code}, call succeeded")


async def drain(queue, n, timeout=5.0, ack=True):
    out = []
    async with queue.iterator(timeout=timeout) as it:
        async for msg in it:
            out.append(msg)
            if ack:
                await msg.ack()
            if len(out) >= n:
                break
    return out


async def close_conn(conn):
    await conn.close()


@s("connection.open_and_closed_state")
async def _(t):
    conn = await aio_pika.connect(t.url)
    ch = await conn.channel()
    q = await ch.declare_queue("", exclusive=True)
    t.eq("server-named", q.name.startswith("amq.gen-"), True)
    await conn.close()
    t.eq("closed", conn.is_closed, True)


@s("connection.bad_password")
async def _(t):
    try:
        conn = await aio_pika.connect(t.url_with(password="wrong"))
        await conn.close()
    except (ae.AMQPConnectionError, ConnectionError) as e:
        t.obs("refused", True)
        t.check("ACCESS_REFUSED" in repr(e) or "403" in repr(e) or isinstance(e, (ae.ProbableAuthenticationError, ae.AuthenticationError)), f"unexpected {e!r}")
        return
    raise Failure("connected with a bad password")


@s("connection.heartbeat")
async def _(t):
    conn = await connect(t, t.url_with(query="heartbeat=1"))
    await asyncio.sleep(3.5)
    t.eq("open after idle", conn.is_closed, False)
    ch = await conn.channel()
    await ch.declare_queue("", exclusive=True)


@s("exchange.declare_bind_publish")
async def _(t):
    conn = await connect(t)
    ch = await conn.channel()
    ex = await ch.declare_exchange(t.n("aio-direct"), aio_pika.ExchangeType.DIRECT, auto_delete=True)
    q = await ch.declare_queue("", exclusive=True)
    await q.bind(ex, routing_key="blue")
    await q.bind(ex, routing_key="green")
    for key in ["blue", "red", "green"]:
        await ex.publish(aio_pika.Message(body=key.encode()), routing_key=key)
    got = await drain(q, 2)
    t.eq("routed", [m.body.decode() for m in got], ["blue", "green"])
    await q.unbind(ex, routing_key="blue")
    await ex.publish(aio_pika.Message(body=b"blue2"), routing_key="blue")
    await ex.publish(aio_pika.Message(body=b"green2"), routing_key="green")
    got = await drain(q, 1)
    t.eq("after unbind", [m.body.decode() for m in got], ["green2"])


@s("queue.errors")
async def _(t):
    conn = await connect(t)
    ch = await conn.channel()
    await channel_error(t, "passive missing", ch.declare_queue(t.n("aio-missing"), passive=True), 404)
    ch = await conn.channel()
    await channel_error(t, "amq. name", ch.declare_queue("amq.aio-" + t.n("x")), 403)
    ch = await conn.channel()
    name = t.n("aio-excl")
    await ch.declare_queue(name, exclusive=True)
    other = await connect(t)
    och = await other.channel()
    await channel_error(t, "exclusive elsewhere", och.declare_queue(name), 405)
    ch = await conn.channel()
    await channel_error(t, "inequivalent", ch.declare_queue(name, exclusive=True, arguments={"x-max-length": 1}), 406)


@s("message.process_requeue_on_exception")
async def _(t):
    conn = await connect(t)
    ch = await conn.channel()
    q = await ch.declare_queue("", exclusive=True)
    await ch.default_exchange.publish(aio_pika.Message(body=b"job"), routing_key=q.name)
    seen = []
    async with q.iterator(timeout=5) as it:
        async for msg in it:
            seen.append(msg.redelivered)
            try:
                async with msg.process(requeue=True):
                    if len(seen) == 1:
                        raise RuntimeError("worker failed")
            except RuntimeError:
                pass
            if len(seen) == 2:
                break
    t.eq("redelivered after failure", seen, [False, True])
    await asyncio.sleep(0.1)
    t.eq("acked", (await ch.declare_queue(q.name, passive=True)).declaration_result.message_count, 0)


@s("get.fail_false_and_counts")
async def _(t):
    conn = await connect(t)
    ch = await conn.channel()
    q = await ch.declare_queue("", exclusive=True)
    t.eq("empty", await q.get(fail=False), None)
    for i in range(3):
        await ch.default_exchange.publish(aio_pika.Message(body=str(i).encode()), routing_key=q.name)
    m = await q.get(no_ack=False, timeout=5)
    t.eq("get", [m.body, m.message_count, m.delivery_tag, m.redelivered], [b"0", 2, 1, False])
    await m.reject(requeue=True)
    m = await q.get(no_ack=True)
    t.eq("requeued", [m.body, m.redelivered], [b"0", True])


@s("confirm.mandatory_delivery_error")
async def _(t):
    conn = await connect(t)
    ch = await conn.channel(publisher_confirms=True, on_return_raises=True)
    try:
        await ch.default_exchange.publish(aio_pika.Message(body=b"lost"), routing_key=t.n("aio-nobody"), mandatory=True)
    except ae.DeliveryError as e:
        frame = getattr(e, "frame", None)
        t.eq("returned", [getattr(frame, "reply_code", None), getattr(frame, "reply_text", None), e.message.body], [312, "NO_ROUTE", b"lost"])
        return
    raise Failure("no DeliveryError for a mandatory unroutable publish")


@s("confirm.nack_reject_publish")
async def _(t):
    conn = await connect(t)
    ch = await conn.channel(publisher_confirms=True)
    q = await ch.declare_queue("", exclusive=True, arguments={"x-max-length": 1, "x-overflow": "reject-publish"})
    r1 = await ch.default_exchange.publish(aio_pika.Message(body=b"1"), routing_key=q.name)
    try:
        await ch.default_exchange.publish(aio_pika.Message(body=b"2"), routing_key=q.name)
        raise Failure("second publish was not nacked")
    except ae.DeliveryError as e:
        t.obs("nacked", type(e.frame).__name__ if e.frame is not None else None)
    t.eq("first acked", type(r1).__name__, "Ack")


@s("tx.transaction_context")
async def _(t):
    conn = await connect(t)
    ch = await conn.channel(publisher_confirms=False)
    q = await ch.declare_queue("", exclusive=True)
    tx = ch.transaction()
    await tx.select()
    await ch.default_exchange.publish(aio_pika.Message(body=b"rollback"), routing_key=q.name)
    await tx.rollback()
    await ch.default_exchange.publish(aio_pika.Message(body=b"commit"), routing_key=q.name)
    await tx.commit()
    got = await drain(q, 1)
    t.eq("committed", [m.body for m in got], [b"commit"])


@s("properties.typed_headers")
async def _(t):
    conn = await connect(t)
    ch = await conn.channel()
    q = await ch.declare_queue("", exclusive=True)
    headers = {
        "int": 123,
        "neg": -5,
        "big": 2**45,
        "float": 1.25,
        "bool": False,
        "str": "ünïcode",
        "dec": decimal.Decimal("1.50"),
        "dt": datetime.datetime(2023, 5, 6, 7, 8, 9, tzinfo=datetime.timezone.utc),
        "list": [1, "a", None],
        "dict": {"k": {"n": 2}},
        "none": None,
    }
    msg = aio_pika.Message(
        body=b"{}",
        headers=headers,
        content_type="application/json",
        correlation_id="cid",
        reply_to="rt",
        message_id="mid",
        priority=2,
        delivery_mode=aio_pika.DeliveryMode.PERSISTENT,
        type="kind",
        app_id="aio",
        expiration=60,
        timestamp=datetime.datetime(2023, 1, 1, tzinfo=datetime.timezone.utc),
    )
    await ch.default_exchange.publish(msg, routing_key=q.name)
    (m,) = await drain(q, 1)
    t.eq("headers", m.headers, headers)
    t.eq(
        "properties",
        [m.content_type, m.correlation_id, m.reply_to, m.message_id, m.priority, int(m.delivery_mode), m.type, m.app_id, m.expiration, m.timestamp],
        ["application/json", "cid", "rt", "mid", 2, 2, "kind", "aio", 60.0, datetime.datetime(2023, 1, 1, tzinfo=datetime.timezone.utc)],
    )


@s("consume.prefetch_and_cancel")
async def _(t):
    conn = await connect(t)
    ch = await conn.channel()
    await ch.set_qos(prefetch_count=2)
    q = await ch.declare_queue("", exclusive=True)
    for i in range(4):
        await ch.default_exchange.publish(aio_pika.Message(body=str(i).encode()), routing_key=q.name)
    got = []
    tag = await q.consume(lambda m: got.append(m))
    # Two arrive, then no more while they are unacknowledged.
    await settled(lambda: len(got) >= 2)
    t.eq("prefetch 2", len(got), 2)
    await got[1].ack(multiple=True)
    await settled(lambda: len(got) >= 4)
    t.eq("two more", len(got), 4)
    await q.cancel(tag)
    await asyncio.sleep(0.1)
    t.eq("unacked stay with channel", (await ch.declare_queue(q.name, passive=True)).declaration_result.message_count, 0)


@s("load.rpc_pattern")
async def _(t):
    conn = await connect(t)
    ch = await conn.channel()
    rpc = await RPC.create(ch)

    async def multiply(*, x, y):
        return x * y

    await rpc.register(t.n("aio-multiply"), multiply, auto_delete=True)
    results = await asyncio.gather(*(rpc.proxy.__getattr__(t.n("aio-multiply"))(x=i, y=3) for i in range(30)))
    t.eq("results", results, [i * 3 for i in range(30)])
    await rpc.close()


@s("load.master_worker_pattern")
async def _(t):
    conn = await connect(t)
    ch = await conn.channel()
    await ch.set_qos(prefetch_count=5)
    master = Master(ch)
    done = []

    async def worker(*, n):
        done.append(n)

    await master.create_worker(t.n("aio-tasks"), worker, auto_delete=True)
    for i in range(100):
        await master.proxy.__getattr__(t.n("aio-tasks"))(n=i)
    for _ in range(250):
        if len(done) >= 100:
            break
        await asyncio.sleep(0.02)
    t.eq("all tasks ran once", sorted(done), list(range(100)))


@s("load.robust_connection_many_channels")
async def _(t):
    conn = await aio_pika.connect_robust(t.url)
    t.defer(conn.close)
    chans = [await conn.channel() for _ in range(50)]
    q = await chans[0].declare_queue("", exclusive=True)
    await asyncio.gather(*(c.default_exchange.publish(aio_pika.Message(body=str(i).encode()), routing_key=q.name) for i, c in enumerate(chans)))
    got = await drain(q, 50)
    t.eq("all channels delivered", sorted(int(m.body) for m in got), list(range(50)))
