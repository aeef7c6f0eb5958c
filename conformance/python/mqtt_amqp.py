"""MQTT <-> AMQP checks with real clients (issue 32): Eclipse Paho's Python
client and Mosquitto's mosquitto_pub/mosquitto_sub on the MQTT side, pika
on the AMQP side, through the same broker:

    python mqtt_amqp.py --amqp-port P --mqtt-port M [--v5]

One JSON line per check: {"name", "outcome"}. MQTT 3.1.1 checks (what
RabbitMQ 3.10's rabbitmq_mqtt does too, so lib/mqtt_amqp.py compares them
with it): an MQTT publish seen by an AMQP consumer (exchange, routing key,
delivery mode, the headers, body) at QoS 0 and 1, wildcards both ways, a
topic with a dot, and an AMQP publish with properties seen by MQTT
subscribers at QoS 0 and 1 (topic, payload, QoS, retain). With --v5, MQTT
5.0 property mapping as RabbitMQ 3.13 maps it (3.10 has no MQTT 5.0), run
against Leveret only: content type, correlation data, response topic,
user properties, message expiry, both ways.
"""

import argparse
import json
import subprocess
import threading
import time
import uuid

import paho.mqtt.client as mqtt
import pika
from paho.mqtt.enums import CallbackAPIVersion
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

RUN = uuid.uuid4().hex[:6]


def amqp(port):
    return pika.BlockingConnection(pika.ConnectionParameters(
        "127.0.0.1", port, credentials=pika.PlainCredentials("guest", "guest")))


def bound_queue(ch, key):
    q = ch.queue_declare("", exclusive=True).method.queue
    ch.queue_bind(q, "amq.topic", key)
    return q


def drain(ch, q, want, timeout=10):
    got = []
    deadline = time.monotonic() + timeout
    while len(got) < want and time.monotonic() < deadline:
        method, props, body = ch.basic_get(q, auto_ack=True)
        if method is None:
            time.sleep(0.05)
            continue
        headers = dict(props.headers or {})
        got.append({"exchange": method.exchange, "routing_key": method.routing_key,
                    "delivery_mode": props.delivery_mode, "headers": {k: str(v) for k, v in sorted(headers.items())},
                    "content_type": props.content_type, "correlation_id": props.correlation_id,
                    "reply_to": props.reply_to, "expiration": props.expiration, "body": body.decode()})
    return got


def paho_client(port, version=mqtt.MQTTv311):
    c = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=f"ma-{uuid.uuid4().hex[:8]}", protocol=version)
    c.username_pw_set("guest", "guest")
    connected = threading.Event()
    c.on_connect = lambda *_: connected.set()
    c.connect("127.0.0.1", port)
    c.loop_start()
    connected.wait(10)
    return c


def close(c):
    c.disconnect()
    c.loop_stop()


def mqtt_to_amqp(args):
    """paho publishes QoS 0 and 1 to a/<run>/x; a queue bound `a.<run>.*` sees them."""
    conn = amqp(args.amqp_port)
    ch = conn.channel()
    q = bound_queue(ch, f"a.{RUN}.*")
    c = paho_client(args.mqtt_port)
    for qos in (0, 1):
        c.publish(f"a/{RUN}/q{qos}", f"from mqtt qos {qos}".encode(), qos=qos).wait_for_publish(10)
    got = drain(ch, q, 2)
    close(c)
    conn.close()
    return sorted(got, key=lambda m: m["body"])


def wildcard_bindings(args):
    """AMQP bindings with * and # against MQTT topics with several levels."""
    conn = amqp(args.amqp_port)
    ch = conn.channel()
    star = bound_queue(ch, f"w{RUN}.*.end")
    hash_ = bound_queue(ch, f"w{RUN}.#")
    c = paho_client(args.mqtt_port)
    for topic in (f"w{RUN}/one/end", f"w{RUN}/one/two/end", f"w{RUN}"):
        c.publish(topic, topic.encode(), qos=1).wait_for_publish(10)
    result = {"star": sorted(m["routing_key"] for m in drain(ch, star, 1, 3)),
              "hash": sorted(m["routing_key"] for m in drain(ch, hash_, 3))}
    close(c)
    conn.close()
    return result


def dotted_topic(args):
    """An MQTT topic with a dot in a level: the routing key an AMQP queue sees."""
    conn = amqp(args.amqp_port)
    ch = conn.channel()
    q = bound_queue(ch, f"d{RUN}.#")
    c = paho_client(args.mqtt_port)
    c.publish(f"d{RUN}/v1.2/x", b"dot", qos=1).wait_for_publish(10)
    got = [m["routing_key"] for m in drain(ch, q, 1, 3)]
    close(c)
    conn.close()
    return got


def amqp_to_mqtt(args):
    """pika publishes to amq.topic `s.<run>.x` with properties, transient and
    persistent; paho subscribers on `s/<run>/+` at QoS 0 and 1 report topic,
    payload, QoS and retain."""
    got = {0: [], 1: []}
    subs = []
    for qos in (0, 1):
        c = paho_client(args.mqtt_port)
        done = threading.Event()
        c.on_message = lambda _c, _u, m, qos=qos: got[qos].append([m.topic, m.payload.decode(), m.qos, bool(m.retain)])
        c.on_subscribe = lambda *_, done=done: done.set()
        c.subscribe(f"s/{RUN}/+", qos=qos)
        done.wait(10)
        subs.append(c)
    conn = amqp(args.amqp_port)
    ch = conn.channel()
    for mode in (1, 2):
        ch.basic_publish("amq.topic", f"s.{RUN}.m{mode}", f"delivery mode {mode}".encode(),
                         pika.BasicProperties(delivery_mode=mode, content_type="text/plain",
                                              headers={"h": "v"}, correlation_id="c-1", reply_to="r.t"))
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and (len(got[0]) < 2 or len(got[1]) < 2):
        time.sleep(0.05)
    time.sleep(0.3)
    conn.close()
    for c in subs:
        close(c)
    return {f"subscriber qos {q}": sorted(v) for q, v in got.items()}


def mosquitto_cli(args):
    """mosquitto_sub on `c/<run>/#` gets an AMQP publish; an AMQP queue gets mosquitto_pub's QoS 1 publish."""
    conn = amqp(args.amqp_port)
    ch = conn.channel()
    q = bound_queue(ch, f"c.{RUN}.from-cli")
    base = ["-h", "127.0.0.1", "-p", str(args.mqtt_port), "-u", "guest", "-P", "guest", "-V", "mqttv311"]
    sub = subprocess.Popen(["mosquitto_sub", *base, "-t", f"c/{RUN}/to-cli", "-q", "1", "-C", "1", "-v", "-W", "15"],
                           text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    time.sleep(1.5)
    ch.basic_publish("amq.topic", f"c.{RUN}.to-cli", b"from amqp", pika.BasicProperties(delivery_mode=2))
    out, _ = sub.communicate(timeout=30)
    pub = subprocess.run(["mosquitto_pub", *base, "-t", f"c/{RUN}/from-cli", "-m", "from cli", "-q", "1"],
                         capture_output=True, timeout=30)
    got = drain(ch, q, 1)
    conn.close()
    return {"mosquitto_sub": out.strip(), "mosquitto_pub exit": pub.returncode,
            "amqp got": [(m["routing_key"], m["body"], m["delivery_mode"]) for m in got]}


def v5_properties_both_ways(args):
    """MQTT 5.0 properties -> AMQP properties (paho publishes, pika reads) and
    AMQP -> MQTT 5.0 (pika publishes, paho reads), as RabbitMQ 3.13 maps them."""
    conn = amqp(args.amqp_port)
    ch = conn.channel()
    q = bound_queue(ch, f"p5.{RUN}.in")
    c = paho_client(args.mqtt_port, mqtt.MQTTv5)
    props = Properties(PacketTypes.PUBLISH)
    props.ContentType = "application/json"
    props.CorrelationData = b"corr-42"
    props.ResponseTopic = f"p5/{RUN}/reply"
    props.UserProperty = [("k1", "v1"), ("k2", "v2")]
    c.publish(f"p5/{RUN}/in", b"{}", qos=1, properties=props).wait_for_publish(10)
    inbound = drain(ch, q, 1)
    got = []
    subscribed = threading.Event()
    c.on_subscribe = lambda *_: subscribed.set()

    def on_message(_c, _u, m):
        p = m.properties
        got.append({"topic": m.topic, "payload": m.payload.decode(), "qos": m.qos,
                    "content_type": getattr(p, "ContentType", None),
                    "correlation_data": getattr(p, "CorrelationData", b"").decode() or None,
                    "response_topic": getattr(p, "ResponseTopic", None),
                    "user_properties": sorted(map(list, getattr(p, "UserProperty", [])))})

    c.on_message = on_message
    c.subscribe(f"p5/{RUN}/out", qos=1)
    subscribed.wait(10)
    ch.basic_publish("amq.topic", f"p5.{RUN}.out", b"out", pika.BasicProperties(
        delivery_mode=2, content_type="text/plain", correlation_id="corr-7", reply_to=f"p5.{RUN}.back",
        headers={"a": "b"}))
    deadline = time.monotonic() + 10
    while not got and time.monotonic() < deadline:
        time.sleep(0.05)
    close(c)
    conn.close()
    return {"mqtt to amqp": inbound, "amqp to mqtt": got}


def v5_expiry_both_ways(args):
    """Message Expiry Interval 60 s -> `expiration` "60000"; an AMQP message
    with `expiration` reaches a 5.0 subscriber with the interval left (at
    most 60 s)."""
    conn = amqp(args.amqp_port)
    ch = conn.channel()
    q = bound_queue(ch, f"e5.{RUN}.in")
    c = paho_client(args.mqtt_port, mqtt.MQTTv5)
    props = Properties(PacketTypes.PUBLISH)
    props.MessageExpiryInterval = 60
    c.publish(f"e5/{RUN}/in", b"expires", qos=1, properties=props).wait_for_publish(10)
    inbound = [m["expiration"] for m in drain(ch, q, 1)]
    got = []
    subscribed = threading.Event()
    c.on_subscribe = lambda *_: subscribed.set()
    c.on_message = lambda _c, _u, m: got.append(0 < getattr(m.properties, "MessageExpiryInterval", -1) <= 60)
    c.subscribe(f"e5/{RUN}/out", qos=1)
    subscribed.wait(10)
    ch.basic_publish("amq.topic", f"e5.{RUN}.out", b"out", pika.BasicProperties(delivery_mode=2, expiration="60000"))
    deadline = time.monotonic() + 10
    while not got and time.monotonic() < deadline:
        time.sleep(0.05)
    close(c)
    conn.close()
    return {"mqtt to amqp expiration": inbound, "amqp to mqtt interval in (0, 60]": got}


CHECKS_311 = [
    ("paho 3.1.1 -> pika: QoS 0 and 1 publishes as AMQP messages", mqtt_to_amqp),
    ("paho 3.1.1 -> pika: * and # bindings on multi-level topics", wildcard_bindings),
    ("paho 3.1.1 -> pika: a topic with a dot", dotted_topic),
    ("pika -> paho 3.1.1: delivery modes to QoS 0 and 1 subscribers", amqp_to_mqtt),
    ("pika <-> mosquitto_sub/mosquitto_pub 3.1.1", mosquitto_cli),
]
CHECKS_5 = [
    ("paho 5.0 <-> pika: content type, correlation, response topic, user properties", v5_properties_both_ways),
    ("paho 5.0 <-> pika: message expiry", v5_expiry_both_ways),
]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--amqp-port", type=int, required=True)
    ap.add_argument("--mqtt-port", type=int, required=True)
    ap.add_argument("--v5", action="store_true")
    args = ap.parse_args()
    for name, check in CHECKS_311 + (CHECKS_5 if args.v5 else []):
        try:
            outcome = check(args)
        except Exception as e:  # noqa: BLE001 - every failure is an outcome
            outcome = f"error: {e!r}"
        # The run's names differ between brokers: the outcomes say <run>.
        print(json.dumps({"name": name, "outcome": outcome}, sort_keys=True).replace(RUN, "<run>"), flush=True)


if __name__ == "__main__":
    main()
