"""The MQTT suite's checks with Eclipse Paho's Python client:
python mqtt.py --port PORT

One JSON line per check: {"name", "outcome"}. A subscriber at QoS 1 on
`conf/<version>/#` and a publisher sending QoS 0, 1 and 2 to
`conf/<version>/<qos>`; the outcome lists what arrived (topic, payload,
QoS: min(publish, granted)) and whether every publish was acknowledged.
Then a login with a wrong password, whose outcome is the CONNACK reason.
Retained messages: two retained publishes, one cleared by an empty
retained payload, then a new subscriber's view (topic, payload, QoS,
retain flag). A persistent session (3.1.1 clean session 0; 5.0 Clean
Start 0 with a Session Expiry Interval): subscribe, go away, a publish
while away, come back (session present, the message without
subscribing), then a clean session (no session present).
"""

import argparse
import json
import threading
import time

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

VERSIONS = {"3.1.1": mqtt.MQTTv311, "5.0": mqtt.MQTTv5}


def client(version, name, password="guest", clean_session=None):
    c = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=f"conf-{name}", protocol=VERSIONS[version],
                    clean_session=clean_session)
    c.username_pw_set("guest", password)
    return c


def publish_acked(port, version, topic, payload, retain):
    pub = client(version, f"pub-{version}")
    pub.connect("127.0.0.1", port)
    pub.loop_start()
    info = pub.publish(topic, payload, qos=1, retain=retain)
    info.wait_for_publish(timeout=10)
    pub.disconnect()
    pub.loop_stop()
    return info.is_published()


def retained(port, version):
    base = f"ret/{version}"
    acked = [publish_acked(port, version, f"{base}/{t}", p, True)
             for t, p in (("a", b"r1"), ("b", b"r2"), ("b", b""))]
    got = []
    sub = client(version, f"ret-sub-{version}")
    sub.on_message = lambda _c, _u, m: got.append([m.topic, m.payload.decode(), m.qos, bool(m.retain)])
    subscribed = threading.Event()
    sub.on_subscribe = lambda *_: subscribed.set()
    sub.connect("127.0.0.1", port)
    sub.loop_start()
    sub.subscribe(f"{base}/#", qos=1)
    subscribed.wait(10)
    time.sleep(1)
    sub.disconnect()
    sub.loop_stop()
    publish_acked(port, version, f"{base}/a", b"", True)
    return f"acknowledged={all(acked)} received={sorted(got)}"


def persistent_session(port, version):
    name = f"keep-{version}"
    topic = f"keep/{version}"
    got = []

    def connect(clean):
        if version == "5.0":
            c = client(version, name)
        else:
            c = client(version, name, clean_session=clean)
        present = []
        connected = threading.Event()

        def on_connect(_c, _u, flags, _reason, _props):
            present.append(flags.session_present)
            connected.set()

        c.on_connect = on_connect
        c.on_message = lambda _c, _u, m: got.append([m.topic, m.payload.decode(), m.qos])
        if version == "5.0":
            props = Properties(PacketTypes.CONNECT)
            props.SessionExpiryInterval = 0 if clean else 300
            c.connect("127.0.0.1", port, clean_start=clean, properties=props)
        else:
            c.connect("127.0.0.1", port)
        c.loop_start()
        connected.wait(10)
        return c, present[0] if present else None

    def leave(c):
        c.disconnect()
        c.loop_stop()

    c, first = connect(clean=False)
    subscribed = threading.Event()
    c.on_subscribe = lambda *_: subscribed.set()
    c.subscribe(f"{topic}/#", qos=1)
    subscribed.wait(10)
    leave(c)
    time.sleep(0.5)
    acked = publish_acked(port, version, f"{topic}/1", b"while away", False)
    c, second = connect(clean=False)
    time.sleep(1)
    leave(c)
    c, third = connect(clean=True)
    leave(c)
    return (f"acknowledged={acked} present: first={first} back={second} clean={third} "
            f"received={sorted(got)}")


def round_trip(port, version):
    got = []
    subscribed = threading.Event()
    all_in = threading.Event()
    sub = client(version, f"sub-{version}")

    def on_message(_c, _u, msg):
        got.append([msg.topic, msg.payload.decode(), msg.qos])
        if len(got) == 3:
            all_in.set()

    sub.on_message = on_message
    sub.on_subscribe = lambda *_: subscribed.set()
    sub.connect("127.0.0.1", port)
    sub.loop_start()
    sub.subscribe(f"conf/{version}/#", qos=1)
    if not subscribed.wait(10):
        return "no SUBACK"
    pub = client(version, f"pub-{version}")
    pub.connect("127.0.0.1", port)
    pub.loop_start()
    infos = [pub.publish(f"conf/{version}/{q}", f"m{q}".encode(), qos=q) for q in (0, 1, 2)]
    for info in infos:
        info.wait_for_publish(timeout=10)
    all_in.wait(10)
    time.sleep(0.2)
    for c in (pub, sub):
        c.disconnect()
        c.loop_stop()
    acknowledged = all(info.is_published() for info in infos)
    return f"acknowledged={acknowledged} received={sorted(got)}"


def wrong_password(port, version):
    c = client(version, f"bad-{version}", password="wrong")
    answered = threading.Event()
    outcome = ["no CONNACK"]

    def on_connect(_c, _u, _flags, reason, _props):
        outcome[0] = f"refused: {reason}" if reason.is_failure else "accepted"
        answered.set()

    c.on_connect = on_connect
    try:
        c.connect("127.0.0.1", port)
    except OSError as e:
        return f"refused: {e!r}"
    c.loop_start()
    answered.wait(10)
    c.loop_stop()
    return outcome[0]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, required=True)
    args = ap.parse_args()
    for version in VERSIONS:
        checks = [
            (f"paho {version}: QoS 0, 1, 2 publishes to a QoS 1 subscriber", round_trip),
            (f"paho {version}: wrong password", wrong_password),
            (f"paho {version}: retained messages, one cleared", retained),
            (f"paho {version}: a persistent session across a disconnect", persistent_session),
        ]
        for name, check in checks:
            try:
                outcome = check(args.port, version)
            except Exception as e:  # noqa: BLE001 - every failure is an outcome
                outcome = f"error: {e!r}"
            print(json.dumps({"name": name, "outcome": outcome}), flush=True)


if __name__ == "__main__":
    main()
