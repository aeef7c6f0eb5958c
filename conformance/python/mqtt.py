"""The MQTT suite's checks with Eclipse Paho's Python client:
python mqtt.py --port PORT

One JSON line per check: {"name", "outcome"}. A subscriber at QoS 1 on
`conf/<version>/#` and a publisher sending QoS 0, 1 and 2 to
`conf/<version>/<qos>`; the outcome lists what arrived (topic, payload,
QoS: min(publish, granted)) and whether every publish was acknowledged.
Then a login with a wrong password, whose outcome is the CONNACK reason.
"""

import argparse
import json
import threading
import time

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

VERSIONS = {"3.1.1": mqtt.MQTTv311, "5.0": mqtt.MQTTv5}


def client(version, name, password="guest"):
    c = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=f"conf-{name}", protocol=VERSIONS[version])
    c.username_pw_set("guest", password)
    return c


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
        ]
        for name, check in checks:
            try:
                outcome = check(args.port, version)
            except Exception as e:  # noqa: BLE001 - every failure is an outcome
                outcome = f"error: {e!r}"
            print(json.dumps({"name": name, "outcome": outcome}), flush=True)


if __name__ == "__main__":
    main()
