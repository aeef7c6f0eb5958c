"""The MQTT <-> AMQP suite (issue 32): real MQTT clients (Eclipse Paho's
Python client, mqtt.js, mosquitto_pub/mosquitto_sub) and real AMQP clients
(pika, amqplib) through one broker, Leveret beside a RabbitMQ 3.10 node of
its own with the `rabbitmq_mqtt` plugin enabled (Debian's package ships
it): the mapping rules (topic `/` <-> routing key `.`, wildcards, QoS <->
delivery mode, which headers an MQTT publish carries, what an MQTT
subscriber gets from an AMQP publish) are compared with RabbitMQ's.

`python/mqtt_amqp.py` and `js/mqtt-amqp.js` print one JSON line per
check. The MQTT 3.1.1 checks run against both brokers and pass when the
outcomes are the same, except where Leveret follows a later RabbitMQ on
purpose (DELIBERATE: the check then passes when Leveret's outcome is the
later RabbitMQ's, given here). The MQTT 5.0 checks (--v5) run against
Leveret only, RabbitMQ 3.10 having no MQTT 5.0, and pass when the outcome
is RabbitMQ 3.13's mapping, given here (EXPECTED_V5).
"""

import json
import os
import subprocess

from nodes import LeveretNode, RabbitNode, SetupError, free_port, wait_port

# Leveret maps `.` in a topic to `/` in the routing key and back, as RabbitMQ
# 3.12+ (docs/mqtt.md); RabbitMQ 3.10 passes the dot through, so `d/v1.2/x`
# reaches an AMQP queue as `d.v1.2.x` there.
DELIBERATE = {
    "paho 3.1.1 -> pika: a topic with a dot": ["d<run>.v1/2.x"],
    # RabbitMQ 3.10 delivers at the subscription's QoS whatever the message;
    # Leveret, as MQTT's min(publish, granted) and RabbitMQ 3.13 (a persistent
    # AMQP message counts as QoS 1, a transient one as QoS 0), sends a
    # transient message to a QoS 1 subscriber at QoS 0.
    "pika -> paho 3.1.1: delivery modes to QoS 0 and 1 subscribers": {
        "subscriber qos 0": [["s/<run>/m1", "delivery mode 1", 0, False], ["s/<run>/m2", "delivery mode 2", 0, False]],
        "subscriber qos 1": [["s/<run>/m1", "delivery mode 1", 0, False], ["s/<run>/m2", "delivery mode 2", 1, False]]},
    "amqplib -> mqtt.js 3.1.1: delivery modes to QoS 0 and 1 subscribers": {
        "subscriber qos 0": [["k/<run>/m1", "delivery mode 1", 0, False], ["k/<run>/m2", "delivery mode 2", 0, False]],
        "subscriber qos 1": [["k/<run>/m1", "delivery mode 1", 0, False], ["k/<run>/m2", "delivery mode 2", 1, False]]},
}

EXPECTED_V5 = {
    # RabbitMQ 3.13's rabbitmq_mqtt: Content Type -> content_type, Correlation
    # Data -> correlation_id, Response Topic -> reply_to (as a routing key),
    # User Properties -> headers, Message Expiry Interval -> expiration (ms);
    # and back for a 5.0 subscriber.
    "paho 5.0 <-> pika: content type, correlation, response topic, user properties": {
        "amqp to mqtt": [{"content_type": "text/plain", "correlation_data": "corr-7", "payload": "out", "qos": 1, "response_topic": "p5/<run>/back", "topic": "p5/<run>/out",
                          "user_properties": [["a", "b"]]}],
        "mqtt to amqp": [{"body": "{}", "content_type": "application/json", "correlation_id": "corr-42",
                          "delivery_mode": 2, "exchange": "amq.topic", "expiration": None,
                          "headers": {"k1": "v1", "k2": "v2"}, "reply_to": "p5.<run>.reply",
                          "routing_key": "p5.<run>.in"}],
    },
    "paho 5.0 <-> pika: message expiry": {"mqtt to amqp expiration": ["60000"],
                                           "amqp to mqtt interval in (0, 60]": [True]},
    "mqtt.js 5.0 <-> amqplib: content type and user properties": {
        "amqp to mqtt": [{"content_type": "application/cbor", "payload": "out", "topic": "j5/<run>/out",
                          "user_properties": {"robot": "r7"}}],
        "mqtt to amqp": [{"body": "v5", "content_type": "text/csv", "delivery_mode": 2, "exchange": "amq.topic",
                          "headers": {"sensor": "lidar", "unit": "m"}, "routing_key": "j5.<run>.in"}],
    },
}


def checks(cmd):
    r = subprocess.run(cmd, text=True, capture_output=True, timeout=600)
    lines = [line for line in r.stdout.splitlines() if line.startswith("{")]
    if not lines:
        raise SetupError(f"{' '.join(cmd[:2])} gave no result (exit {r.returncode}): {(r.stdout + r.stderr)[-2000:]}")
    return {c["name"]: c["outcome"] for c in map(json.loads, lines)}


def drivers(ctx, amqp_port, mqtt_port, v5):
    extra = ["--v5"] if v5 else []
    ports = ["--amqp-port", str(amqp_port), "--mqtt-port", str(mqtt_port), *extra]
    return {**checks([ctx.vpy, os.path.join(ctx.here, "python", "mqtt_amqp.py"), *ports]),
            **checks(["node", os.path.join(ctx.here, "js", "mqtt-amqp.js"), *ports])}


def show(outcome):
    return json.dumps(outcome, sort_keys=True)


def run(ctx):
    if not ctx.leveret:
        return [("mqtt-amqp", "skip", "needs a leveret of its own with an MQTT listener (not --url)")]
    ctx.ensure_python()
    ctx.ensure_node()
    rabbit_mqtt = free_port()
    reference = RabbitNode(conf=[f"mqtt.listeners.tcp.default = 127.0.0.1:{rabbit_mqtt}"], plugins=["rabbitmq_mqtt"])
    leveret = None
    try:
        if not wait_port(rabbit_mqtt, 60):
            raise SetupError("RabbitMQ's MQTT listener did not open")
        mqtt_port = free_port()
        leveret = LeveretNode(ctx.leveret, ["--mqtt-listen", f"127.0.0.1:{mqtt_port}"], wait_for=mqtt_port)
        theirs = drivers(ctx, reference.port, rabbit_mqtt, v5=False)
        ours = drivers(ctx, leveret.port, mqtt_port, v5=True)
        results = []
        for name, got in ours.items():
            if name in EXPECTED_V5:
                want, whose = EXPECTED_V5[name], "RabbitMQ 3.13's mapping"
            elif name in DELIBERATE:
                want, whose = DELIBERATE[name], f"RabbitMQ 3.12+ (3.10 differs: {show(theirs.get(name))})"
            else:
                want, whose = theirs.get(name, "(no outcome)"), "RabbitMQ 3.10"
            same = show(got) == show(want)
            results.append((name, "pass" if same else "fail", f"Leveret: {show(got)} / {whose}: {show(want)}"))
        return results
    finally:
        if leveret:
            leveret.stop()
        reference.stop()


SUITES = {
    "mqtt-amqp": ("MQTT <-> AMQP: paho, mqtt.js, mosquitto_pub/sub with pika, amqplib; Leveret beside RabbitMQ 3.10's "
                  "rabbitmq_mqtt", run),
}
