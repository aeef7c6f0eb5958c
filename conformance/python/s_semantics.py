"""RabbitMQ's semantics driven by pika (issue 30): the `semantics` suite
(lib/semantics.py) loads semantics/definitions.json into a RabbitMQ 3.10
node and a Leveret, runs these scenarios against both with the broker's
management API (`t.http`) for what an operator does meanwhile, and
compares what the client observed.

Covered: policies from the definitions file (pattern, priority, apply-to
queues and exchanges, `queue-mode` accepted), arguments against policies,
live policy changes (a queue shortened at once, its head dropped or
dead-lettered; a cleared policy lets it grow), operator policies (the
stricter value), single active consumer hand-over on cancel, channel
close and a killed connection (with the consumers' `active` state as
listed), consumer priorities with credit, argument equivalence both ways
(queues from the definitions and the API redeclared by the client, a
client's queue put again through the API), and every argument and policy
key RabbitMQ refuses.

Names carry the run's prefix; the definitions' policies match name
suffixes (`….pol-maxlen2`) so they apply whatever the prefix. Reply
texts are recorded as RabbitMQ's constant and the argument they name:
the rest of RabbitMQ's text spells Erlang types.
"""

import base64
import json
import os
import re
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.parse
import urllib.request

import pika
import pika.exceptions as pe

from harness import HANG, Failure, reply_name, scenario, wait_until
from s_pika import connect, pump, settle

LIB = "semantics"


def s(name):
    return scenario(LIB, "pika." + name)


# helpers -----------------------------------------------------------------


def http(t, method, path, body=None):
    """(status, parsed JSON or None) of a management API call as guest."""
    auth = base64.b64encode(f"{t.user}:{t.password}".encode()).decode()
    request = urllib.request.Request(
        t.http + path,
        method=method,
        data=None if body is None else json.dumps(body).encode(),
        headers={"Authorization": f"Basic {auth}", "Content-Type": "application/json"},
    )
    try:
        with urllib.request.urlopen(request, timeout=30) as answer:
            text = answer.read()
            return answer.status, json.loads(text) if text else None
    except urllib.error.HTTPError as e:
        text = e.read()
        try:
            return e.code, json.loads(text) if text else None
        except ValueError:
            return e.code, None


def quoted(name):
    return urllib.parse.quote(name, safe="")


def set_policy(t, name, pattern, definition, kind="policies", apply_to="queues", priority=0):
    """PUT a policy (kind `policies` or `operator-policies`), removed at the end."""
    status, _ = http(t, "PUT", f"/api/{kind}/%2F/{quoted(name)}",
                     {"pattern": pattern, "definition": definition, "apply-to": apply_to, "priority": priority})
    t.defer(http, t, "DELETE", f"/api/{kind}/%2F/{quoted(name)}")
    return status


def own_pattern(t, stem):
    """A pattern matching this run's names that start with `stem`."""
    return "^" + re.escape(t.n(stem))


def listing(t, what, name, until=None, keys=("policy", "operator_policy", "effective_policy_definition")):
    """The listed `keys` of queue or exchange `name`, once it is listed
    with them (RabbitMQ lists a queue's policy from its statistics, which
    the suite's node emits every 100 ms) and `until(listed)` holds."""
    found = {}

    def listed():
        status, body = http(t, "GET", f"/api/{what}/%2F/{quoted(name)}")
        if status != 200 or not body or "policy" not in body:
            return False
        # RabbitMQ lists "no policy" as "", null or an empty list depending
        # on the field; an operator reads each as none.
        found.clear()
        found.update({k: (body.get(k) if body.get(k) not in ("", None, [], {}) else None) for k in keys})
        return until is None or until(found)

    wait_until(listed, what=f"{name} in /api/{what}")
    return dict(found)


def count(ch, q):
    return ch.queue_declare(q, passive=True).method.message_count


def settled_count(ch, q, want):
    """The queue's count once it is `want`, or what it is after the hang
    limit (a live change reaches RabbitMQ's queue processes a moment after
    the API call returns)."""
    deadline = time.monotonic() + HANG
    while True:
        n = count(ch, q)
        if n == want or time.monotonic() > deadline:
            return n
        time.sleep(0.02)


def publish(ch, q, bodies, exchange=""):
    for body in bodies:
        ch.basic_publish(exchange, q, str(body).encode(), properties=pika.BasicProperties(delivery_mode=2))


def get_bodies(ch, q):
    out = []
    while True:
        m, p, b = ch.basic_get(q, auto_ack=True)
        if m is None:
            return out
        out.append(b.decode())


def refusal(e):
    """[code, RabbitMQ's constant, the first argument or key the text names]."""
    text = e.reply_text if isinstance(e.reply_text, str) else e.reply_text.decode()
    named = re.search(r"'(x-[a-z-]+)'|(x-[a-z-]+)", text)
    return [e.reply_code, reply_name(text), (named.group(1) or named.group(2)) if named else None]


def declare_outcome(conn, q, **kw):
    """'ok' or the refusal of declaring `q` on a channel of its own."""
    ch = conn.channel()
    try:
        ch.queue_declare(q, **kw)
    except (pe.ChannelClosedByBroker, pe.ConnectionClosedByBroker) as e:
        return refusal(e)
    ch.close()
    return "ok"


def tidy_queues(t, names):
    def cleanup():
        c = pika.BlockingConnection(pika.URLParameters(t.url))
        try:
            ch = c.channel()
            for q in names:
                ch.queue_delete(q)
        finally:
            c.close()

    t.defer(cleanup)


# policies from the definitions file --------------------------------------


@s("policy.from_definitions")
def _(t):
    """The definitions' policies apply by pattern and priority; queue-mode
    is accepted (and does nothing in Leveret); listings name them."""
    conn = connect(t)
    ch = conn.channel()
    ch.confirm_delivery()
    names = {stem: t.n(stem) for stem in ("x.pol-maxlen2", "x.pol-prio", "x.pol-prio-high", "x.pol-lazy", "x.pol-none")}
    tidy_queues(t, names.values())
    for q in names.values():
        ch.queue_declare(q)
        publish(ch, q, range(1, 7))
    for stem, q in names.items():
        t.obs(f"{stem} ready", count(ch, q))
        t.obs(f"{stem} listed", listing(t, "queues", q))
    t.eq("maxlen2 kept the newest", get_bodies(ch, names["x.pol-maxlen2"]), ["5", "6"])
    t.eq("the higher priority policy applies", count(ch, names["x.pol-prio-high"]), 1)


@s("policy.ttl_from_definitions_beats_a_longer_argument")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    ch.confirm_delivery()
    q = t.n("x.pol-ttl0")
    tidy_queues(t, [q])
    ch.queue_declare(q, arguments={"x-message-ttl": 600000})
    publish(ch, q, ["gone"])
    t.eq("expired at once (policy 0 < argument)", settled_count(ch, q, 0), 0)
    t.obs("listed", listing(t, "queues", q))


@s("policy.alternate_exchange_on_exchanges")
def _(t):
    """A policy that applies to exchanges gives one an alternate exchange."""
    conn = connect(t)
    ch = conn.channel()
    ch.confirm_delivery()
    catch = ch.queue_declare("", exclusive=True).method.queue
    ch.queue_bind(catch, "sem.defs.ae")
    src = t.n("x.pol-ae-src")
    ch.exchange_declare(src, "direct")
    t.defer(lambda: http(t, "DELETE", f"/api/exchanges/%2F/{quoted(src)}"))
    ch.basic_publish(src, "nowhere", b"unroutable")
    wait_until(lambda: count(ch, catch) == 1, what="the alternate exchange's copy")
    t.eq("routed to the policy's alternate exchange", get_bodies(ch, catch), ["unroutable"])
    t.obs("listed", listing(t, "exchanges", src, keys=("policy",)))


@s("policy.arguments_against_policies")
def _(t):
    """A queue's own x-max-length against the definitions' max-length 2:
    the smaller wins (as RabbitMQ combines them)."""
    conn = connect(t)
    ch = conn.channel()
    ch.confirm_delivery()
    shorter, longer = t.n("a.pol-maxlen2"), t.n("b.pol-maxlen2")
    tidy_queues(t, [shorter, longer])
    ch.queue_declare(shorter, arguments={"x-max-length": 1})
    ch.queue_declare(longer, arguments={"x-max-length": 4, "x-overflow": "reject-publish"})
    publish(ch, shorter, range(1, 5))
    t.eq("argument 1 < policy 2", get_bodies(ch, shorter), ["4"])
    nacked = 0
    for i in range(1, 5):
        try:
            ch.basic_publish("", longer, str(i).encode())
        except pe.NackError:
            nacked += 1
    t.eq("policy 2 < argument 4, the argument's reject-publish", [nacked, get_bodies(ch, longer)], [2, ["1", "2"]])


# live policy changes ------------------------------------------------------


@s("policy.live_change_drops_the_head")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    ch.confirm_delivery()
    q = t.n("live.q")
    tidy_queues(t, [q])
    ch.queue_declare(q)
    publish(ch, q, range(1, 7))
    t.eq("status of the new policy", set_policy(t, t.n("live"), own_pattern(t, "live."), {"max-length": 2}) // 100, 2)
    t.eq("shortened at once", settled_count(ch, q, 2), 2)
    t.obs("listed", listing(t, "queues", q, until=lambda found: found["policy"] == t.n("live")))
    status, _ = http(t, "DELETE", f"/api/policies/%2F/{quoted(t.n('live'))}")
    t.eq("status of the clear", status // 100, 2)
    listing(t, "queues", q, until=lambda found: found["policy"] is None)
    publish(ch, q, range(7, 10))
    t.eq("grows again once cleared", get_bodies(ch, q), ["5", "6", "7", "8", "9"])


@s("policy.live_change_dead_letters_the_head")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    ch.confirm_delivery()
    q, dlx, dead = t.n("livedl.q"), t.n("livedl-x"), t.n("livedl-dead")
    tidy_queues(t, [q, dead])
    ch.exchange_declare(dlx, "fanout")
    t.defer(lambda: http(t, "DELETE", f"/api/exchanges/%2F/{quoted(dlx)}"))
    ch.queue_declare(dead)
    ch.queue_bind(dead, dlx)
    ch.queue_declare(q)
    publish(ch, q, range(1, 6))
    set_policy(t, t.n("livedl"), own_pattern(t, "livedl.q"), {"max-length": 1, "dead-letter-exchange": dlx})
    t.eq("dead-lettered at once", settled_count(ch, dead, 4), 4)
    got = []
    while True:
        m, p, b = ch.basic_get(dead, auto_ack=True)
        if m is None:
            break
        death = (p.headers or {}).get("x-death", [{}])[0]
        got.append([b.decode(), death.get("reason"), death.get("queue", "").replace(t.prefix, "~")])
    t.eq("the head, in order, with x-death", got, [[str(i), "maxlen", "~livedl.q"] for i in range(1, 5)])
    t.eq("the queue keeps the newest", get_bodies(ch, q), ["5"])


# operator policies ------------------------------------------------------------


@s("operator_policy.the_stricter_value_wins")
def _(t):
    """The definitions' operator policy max-length 3 against the policy's
    5 and the queues' own arguments."""
    conn = connect(t)
    ch = conn.channel()
    ch.confirm_delivery()
    cases = {"z.op-plain": {}, "z.op-arg2": {"x-max-length": 2}, "z.op-arg10": {"x-max-length": 10}}
    tidy_queues(t, [t.n(stem) for stem in cases])
    for stem, arguments in cases.items():
        q = t.n(stem)
        ch.queue_declare(q, arguments=arguments)
        publish(ch, q, range(1, 9))
        t.obs(f"{stem} ready", count(ch, q))
        t.obs(f"{stem} listed", listing(t, "queues", q))


@s("operator_policy.live_changes")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    ch.confirm_delivery()
    q = t.n("liveop.q")
    tidy_queues(t, [q])
    ch.queue_declare(q)
    publish(ch, q, range(1, 6))
    set_policy(t, t.n("liveop-user"), own_pattern(t, "liveop."), {"max-length": 4})
    t.eq("the policy's 4", settled_count(ch, q, 4), 4)
    set_policy(t, t.n("liveop"), own_pattern(t, "liveop."), {"max-length": 1}, kind="operator-policies")
    t.eq("the operator policy's stricter 1", settled_count(ch, q, 1), 1)
    t.obs("listed", listing(t, "queues", q, until=lambda found: found["operator_policy"] == t.n("liveop")))
    set_policy(t, t.n("liveop"), own_pattern(t, "liveop."), {"max-length": 10}, kind="operator-policies")
    t.obs("listed once raised", listing(t, "queues", q, until=lambda found: found["effective_policy_definition"] != {"max-length": 1}))
    publish(ch, q, range(6, 12))
    t.eq("the policy's 4 again, stricter than 10", get_bodies(ch, q), ["8", "9", "10", "11"])


# single active consumer ------------------------------------------------------


def consumers_listed(t, q):
    """[(tag, active, activity_status)] of the queue's consumers, once two are listed."""
    found = []

    def listed():
        status, body = http(t, "GET", "/api/consumers/%2F")
        mine = [c for c in body or [] if (c.get("queue") or {}).get("name") == q] if status == 200 else []
        found[:] = sorted([c["consumer_tag"], c.get("active"), c.get("activity_status")] for c in mine)
        return len(found) == 2

    wait_until(listed, what="both consumers listed")
    return found


def sac_queue(t, ch, stem):
    q = t.n(stem)
    tidy_queues(t, [q])
    ch.queue_declare(q, arguments={"x-single-active-consumer": True})
    return q


@s("sac.cancel_hands_over")
def _(t):
    """The active consumer cancels holding two unacked: the next one gets
    nothing while they are held (Leveret: by design, so two consumers
    never work on the queue at once; RabbitMQ 3.10.8: until its queue
    runs again), then, once they are acked and the channel closed, the
    rest in order. A publish while they are held is left out: RabbitMQ
    3.10.8 delivers it ahead of the backlog (tests/tests/
    single_active_consumer.rs says more)."""
    conn = connect(t)
    ch = conn.channel()
    q = sac_queue(t, ch, "sac-cancel")
    first = conn.channel()
    first.basic_qos(prefetch_count=2)
    got1 = []
    first.basic_consume(q, lambda c, m, p, b: got1.append([b.decode(), m.delivery_tag]), consumer_tag="first")
    second = conn.channel()
    got2 = []
    second.basic_consume(q, lambda c, m, p, b: got2.append([b.decode(), m.redelivered]), auto_ack=True, consumer_tag="second")
    publish(ch, q, range(1, 7))
    pump(conn, got1, 2)
    settle(conn, 0.2)
    t.eq("the first is active, the second waits", consumers_listed(t, q),
         [["first", True, "single_active"], ["second", False, "waiting"]])
    t.eq("active's share", [b for b, _ in got1], ["1", "2"])
    t.eq("waiting's share", got2, [])
    first.basic_cancel("first")
    settle(conn, 1.0)
    t.obs("the next one's share a second after the cancel", got2)
    for _, tag in got1:
        first.basic_ack(tag)
    first.close()
    pump(conn, got2, 4)
    t.eq("hand-over: the rest, not what the first held", got2, [[str(i), False] for i in range(3, 7)])
    t.eq("nothing left", count(ch, q), 0)


@s("sac.channel_close_hands_over")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = sac_queue(t, ch, "sac-close")
    other = connect(t)
    first = other.channel()
    first.basic_qos(prefetch_count=2)
    got1 = []
    first.basic_consume(q, lambda c, m, p, b: got1.append(b.decode()), consumer_tag="first")
    second = conn.channel()
    got2 = []
    second.basic_consume(q, lambda c, m, p, b: got2.append([b.decode(), m.redelivered]), auto_ack=True, consumer_tag="second")
    publish(ch, q, range(1, 7))
    pump(other, got1, 2)
    settle(conn, 0.2)
    t.eq("waiting's share", got2, [])
    first.close()
    pump(conn, got2, 6)
    t.eq("hand-over: the unacked first, redelivered, then the rest", got2,
         [["1", True], ["2", True]] + [[str(i), False] for i in range(3, 7)])


CHILD = r"""
import sys, pika
conn = pika.BlockingConnection(pika.URLParameters(sys.argv[1]))
ch = conn.channel()
ch.basic_qos(prefetch_count=2)
got = []
def cb(c, m, p, b):
    got.append(b)
    if len(got) == 2:
        print("held 2", flush=True)
ch.basic_consume(sys.argv[2], cb, consumer_tag="doomed")
print("consuming", flush=True)
ch.start_consuming()
"""


@s("sac.killed_connection_hands_over")
def _(t):
    """The active consumer's process is killed (SIGKILL: its socket just
    goes): the waiting consumer takes over, the unacked first."""
    conn = connect(t)
    ch = conn.channel()
    q = sac_queue(t, ch, "sac-kill")
    child = subprocess.Popen([sys.executable, "-c", CHILD, t.url, q], stdout=subprocess.PIPE, text=True)
    t.defer(lambda: child.poll() is None and child.kill())
    t.eq("child", child.stdout.readline().strip(), "consuming")
    second = conn.channel()
    got2 = []
    second.basic_consume(q, lambda c, m, p, b: got2.append([b.decode(), m.redelivered]), auto_ack=True, consumer_tag="survivor")
    t.eq("the killed one was active", consumers_listed(t, q),
         [["doomed", True, "single_active"], ["survivor", False, "waiting"]])
    publish(ch, q, range(1, 7))
    t.eq("child", child.stdout.readline().strip(), "held 2")
    settle(conn, 0.2)
    t.eq("waiting's share while the first lives", got2, [])
    os.kill(child.pid, signal.SIGKILL)
    child.wait()
    pump(conn, got2, 6)
    t.eq("hand-over: the unacked first, redelivered, then the rest", got2,
         [["1", True], ["2", True]] + [[str(i), False] for i in range(3, 7)])


@s("sac.from_definitions")
def _(t):
    """The definitions' SAC queue: one consumer gets all."""
    conn = connect(t)
    ch = conn.channel()
    q = "sem.defs.sac"
    ch.queue_purge(q)
    got = {"a": [], "b": []}
    for tag in got:
        conn.channel().basic_consume(q, lambda c, m, p, b, tag=tag: got[tag].append(b.decode()), auto_ack=True,
                                     consumer_tag=t.n(tag))
    publish(ch, q, range(1, 11))
    pump(conn, got["a"], 10)
    settle(conn, 0.2)
    t.eq("10/0", [len(got["a"]), len(got["b"])], [10, 0])


# consumer priorities --------------------------------------------------------


@s("consumer_priority.served_while_it_has_credit")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    got = {"low": [], "high": []}
    chans = {}
    for name, priority, prefetch in (("low", 1, 10), ("high", 5, 2)):
        c = conn.channel()
        c.basic_qos(prefetch_count=prefetch)
        c.basic_consume(q, lambda c_, m, p, b, name=name: got[name].append([b.decode(), m.delivery_tag]),
                        arguments={"x-priority": priority})
        chans[name] = c
    publish(ch, q, range(1, 5))
    pump(conn, got["low"], 2)
    settle(conn, 0.2)
    bodies = lambda name: [b for b, _ in got[name]]
    t.eq("high while it has credit, then low", [bodies("high"), bodies("low")], [["1", "2"], ["3", "4"]])
    chans["high"].basic_ack(got["high"][0][1])
    settle(conn, 0.2)
    publish(ch, q, [5])
    pump(conn, got["high"], 3)
    settle(conn, 0.2)
    t.eq("credit back: high again", [bodies("high"), bodies("low")], [["1", "2", "5"], ["3", "4"]])


# argument equivalence ---------------------------------------------------------


@s("equivalence.definitions_queue_redeclared")
def _(t):
    """Queues the definitions made (JSON numbers) redeclared by pika
    (small ints go as 32-bit): equal values are equivalent, others not."""
    conn = connect(t)
    same = {"x-message-ttl": 60000, "x-expires": 86400000, "x-max-length": 10, "x-max-length-bytes": 1048576,
            "x-max-priority": 5, "x-overflow": "reject-publish",
            "x-dead-letter-exchange": "sem.defs.dlx", "x-dead-letter-routing-key": "dead"}
    t.obs("identical", declare_outcome(conn, "sem.defs.args", durable=True, arguments=same))
    t.obs("passive", declare_outcome(conn, "sem.defs.args", passive=True))
    for key, value in (("x-message-ttl", 60001), ("x-max-priority", 6), ("x-max-length", 11),
                       ("x-overflow", "drop-head"), ("x-dead-letter-routing-key", "other")):
        t.obs(f"{key}={value}", declare_outcome(conn, "sem.defs.args", durable=True, arguments={**same, key: value}))
    without = {k: v for k, v in same.items() if k != "x-max-priority"}
    t.obs("x-max-priority left out", declare_outcome(conn, "sem.defs.args", durable=True, arguments=without))
    t.obs("sac true", declare_outcome(conn, "sem.defs.sac", durable=True, arguments={"x-single-active-consumer": True}))
    t.obs("sac false", declare_outcome(conn, "sem.defs.sac", durable=True, arguments={"x-single-active-consumer": False}))
    t.obs("lazy", declare_outcome(conn, "sem.defs.lazy", durable=True, arguments={"x-queue-mode": "lazy"}))
    t.obs("lazy left out", declare_outcome(conn, "sem.defs.lazy", durable=True))


@s("equivalence.client_and_api_each_way")
def _(t):
    """A queue pika declared, put again through the API with the same
    arguments as JSON numbers and with another value; a queue the API
    made, redeclared by pika."""
    conn = connect(t)
    ch = conn.channel()
    by_client, by_api = t.n("eq.client"), t.n("eq.api")
    tidy_queues(t, [by_client, by_api])
    args = {"x-message-ttl": 1000, "x-max-length": 7, "x-max-priority": 3}
    ch.queue_declare(by_client, durable=True, arguments=args)
    put = lambda q, a: http(t, "PUT", f"/api/queues/%2F/{quoted(q)}", {"durable": True, "auto_delete": False, "arguments": a})[0]
    t.obs("API, same arguments", put(by_client, args) // 100)
    t.obs("API, another ttl", put(by_client, {**args, "x-message-ttl": 2000}) // 100)
    t.obs("API creates", put(by_api, args) // 100)
    t.obs("client, same", declare_outcome(conn, by_api, durable=True, arguments=args))
    t.obs("client, 64-bit ttl", declare_outcome(conn, by_api, durable=True, arguments={**args, "x-message-ttl": 1000}))
    t.obs("client, another max-length", declare_outcome(conn, by_api, durable=True, arguments={**args, "x-max-length": 8}))


# refused arguments and policy keys ---------------------------------------------


REFUSED_QUEUE_ARGUMENTS = [
    ("x-delivery-limit on a classic queue", {"x-delivery-limit": 5}),
    ("x-max-age on a classic queue", {"x-max-age": "1D"}),
    ("x-stream-max-segment-size-bytes on a classic queue", {"x-stream-max-segment-size-bytes": 1000}),
    ("x-quorum-initial-group-size on a classic queue", {"x-quorum-initial-group-size": 3}),
    ("x-max-in-memory-length on a classic queue", {"x-max-in-memory-length": 10}),
    ("x-max-in-memory-bytes on a classic queue", {"x-max-in-memory-bytes": 10}),
    ("x-dead-letter-strategy on a classic queue", {"x-dead-letter-strategy": "at-least-once"}),
    ("x-queue-mode unknown", {"x-queue-mode": "speedy"}),
    ("x-queue-mode lazy (accepted)", {"x-queue-mode": "lazy"}),
    ("x-queue-version 2 (accepted)", {"x-queue-version": 2}),
    ("x-queue-version 3", {"x-queue-version": 3}),
    ("x-overflow unknown", {"x-overflow": "drop-tail"}),
    ("x-max-priority 256", {"x-max-priority": 256}),
    ("x-max-priority -1", {"x-max-priority": -1}),
    ("x-max-priority as text", {"x-max-priority": "5"}),
    ("x-message-ttl -1", {"x-message-ttl": -1}),
    ("x-message-ttl as text", {"x-message-ttl": "100"}),
    ("x-expires 0", {"x-expires": 0}),
    ("x-max-length -1", {"x-max-length": -1}),
    ("x-max-length-bytes -1", {"x-max-length-bytes": -1}),
    ("x-single-active-consumer as text", {"x-single-active-consumer": "yes"}),
    ("x-dead-letter-routing-key without an exchange", {"x-dead-letter-routing-key": "k"}),
    ("x-dead-letter-exchange as a number", {"x-dead-letter-exchange": 5}),
]


@s("refused.queue_arguments")
def _(t):
    conn = connect(t)
    created = []
    tidy_queues(t, created)
    for i, (label, arguments) in enumerate(REFUSED_QUEUE_ARGUMENTS):
        q = t.n(f"refused.{i}")
        outcome = declare_outcome(conn, q, arguments=arguments)
        if outcome == "ok":
            created.append(q)
        t.obs(label, outcome)


@s("refused.consumer_arguments")
def _(t):
    conn = connect(t)
    ch = conn.channel()
    q = ch.queue_declare("", exclusive=True).method.queue
    for label, arguments in (("x-priority as text", {"x-priority": "high"}),
                             ("x-cancel-on-ha-failover (accepted)", {"x-cancel-on-ha-failover": True})):
        c = conn.channel()
        try:
            c.basic_consume(q, lambda *a: None, arguments=arguments)
            t.obs(label, "ok")
            c.close()
        except pe.ChannelClosedByBroker as e:
            t.obs(label, refusal(e))


REFUSED_POLICIES = [
    ("policies", "max-priority", {"max-priority": 5}),
    ("policies", "an unknown key", {"colour": "red"}),
    ("policies", "message-ttl as text", {"message-ttl": "abc"}),
    ("policies", "max-length -1", {"max-length": -1}),
    ("policies", "overflow unknown", {"overflow": "drop-tail"}),
    ("policies", "expires 0", {"expires": 0}),
    ("policies", "queue-mode lazy (accepted)", {"queue-mode": "lazy"}),
    ("policies", "queue-mode unknown", {"queue-mode": "speedy"}),
    ("policies", "an empty definition", {}),
    ("operator-policies", "dead-letter-exchange in an operator policy", {"dead-letter-exchange": "x"}),
    ("operator-policies", "overflow in an operator policy", {"overflow": "drop-head"}),
    ("operator-policies", "max-length (accepted)", {"max-length": 3}),
]


@s("refused.policy_keys")
def _(t):
    """Policies and operator policies with keys RabbitMQ refuses, by the
    API's status class (the texts are each broker's own)."""
    for i, (kind, label, definition) in enumerate(REFUSED_POLICIES):
        status = set_policy(t, t.n(f"refused-{i}"), own_pattern(t, f"refused-{i}."), definition, kind=kind)
        t.obs(label, status // 100)
