"""The MQTT suite (issue 32): Eclipse Paho's Python client
(python/mqtt.py) and Mosquitto's command-line clients (mosquitto_sub,
mosquitto_pub), in MQTT 3.1.1 and 5.0, against a Leveret started with
`--mqtt-listen` and against Debian's Mosquitto 2.0 as the reference (its
own listener and password file, user guest/guest). A check passes when
Leveret gives the expected outcome and Mosquitto the same one. A wrong
password is compared as "refused" only: Leveret answers 0x04 / 0x86 (bad
user name or password, as RabbitMQ), Mosquitto 2.0 0x05 / 0x87 (not
authorized).
"""

import json
import os
import shutil
import subprocess
import tempfile
import time

from nodes import LeveretNode, SetupError, free_port, wait_port

MOSQUITTO = "/usr/sbin/mosquitto"


class MosquittoNode:
    """Debian's mosquitto on a free loopback port: guest/guest only, or
    with `anonymous` any client without a user name."""

    def __init__(self, anonymous=False):
        tools = (MOSQUITTO,) if anonymous else (MOSQUITTO, "/usr/bin/mosquitto_passwd")
        for tool in tools:
            if not os.path.exists(tool):
                raise SetupError(f"{tool} is missing (apt-get install mosquitto mosquitto-clients)")
        self.dir = tempfile.mkdtemp(prefix="leveret-conformance-mosquitto-")
        os.chmod(self.dir, 0o755)  # mosquitto drops root for its own user
        self.port = free_port()
        if anonymous:
            access = "allow_anonymous true\n"
        else:
            passwd = os.path.join(self.dir, "passwd")
            open(passwd, "w").close()
            subprocess.run(["mosquitto_passwd", "-b", passwd, "guest", "guest"], check=True, capture_output=True)
            os.chmod(passwd, 0o644)
            access = f"allow_anonymous false\npassword_file {passwd}\n"
        conf = os.path.join(self.dir, "mosquitto.conf")
        with open(conf, "w") as f:
            f.write(f"listener {self.port} 127.0.0.1\n{access}")
        self.proc = subprocess.Popen([MOSQUITTO, "-c", conf], stdout=subprocess.DEVNULL,
                                     stderr=subprocess.DEVNULL, start_new_session=True)
        if not wait_port(self.port, 30):
            self.stop()
            raise SetupError("mosquitto did not start")

    def stop(self):
        if self.proc.poll() is None:
            self.proc.terminate()
            self.proc.wait(timeout=10)
        shutil.rmtree(self.dir, ignore_errors=True)


def paho(ctx, port):
    r = subprocess.run([ctx.vpy, os.path.join(ctx.here, "python", "mqtt.py"), "--port", str(port)],
                       text=True, capture_output=True, timeout=300)
    if r.returncode != 0:
        raise SetupError(f"python/mqtt.py on port {port} failed: {(r.stdout + r.stderr)[-2000:]}")
    return {c["name"]: c["outcome"] for c in map(json.loads, r.stdout.splitlines())}


def mosquitto_clients(port):
    """mosquitto_sub at QoS 1 on a wildcard, mosquitto_pub at QoS 1 and 2,
    in both versions; then mosquitto_pub with a wrong password."""
    outcomes = {}
    for version, flag in (("3.1.1", "mqttv311"), ("5.0", "mqttv5")):
        auth = ["-h", "127.0.0.1", "-p", str(port), "-V", flag, "-u", "guest"]
        sub = subprocess.Popen(["mosquitto_sub", *auth, "-P", "guest", "-t", f"cli/{version}/+", "-q", "1",
                                "-C", "2", "-v", "-W", "20"], text=True, stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT)
        time.sleep(1)
        codes = [subprocess.run(["mosquitto_pub", *auth, "-P", "guest", "-t", f"cli/{version}/{q}", "-m", f"m{q}",
                                 "-q", str(q)], capture_output=True, timeout=30).returncode for q in (1, 2)]
        out, _ = sub.communicate(timeout=30)
        outcomes[f"mosquitto_pub/sub {version}: QoS 1 and 2 to a wildcard subscriber"] = \
            f"pub exit codes {codes}, received {sorted(out.splitlines())}"
        bad = subprocess.run(["mosquitto_pub", *auth, "-P", "wrong", "-t", "cli/x", "-m", "x", "-q", "1"],
                             capture_output=True, timeout=30)
        outcomes[f"mosquitto_pub {version}: wrong password"] = \
            "refused: exit code nonzero" if bad.returncode != 0 else "accepted"
    return outcomes


def run(ctx):
    if not ctx.leveret:
        return [("mqtt", "skip", "needs a leveret of its own with an MQTT listener (not --url)")]
    ctx.ensure_python()
    reference = MosquittoNode()
    leveret = None
    try:
        mqtt_port = free_port()
        leveret = LeveretNode(ctx.leveret, ["--mqtt-listen", f"127.0.0.1:{mqtt_port}"], wait_for=mqtt_port)
        theirs = {**paho(ctx, reference.port), **mosquitto_clients(reference.port)}
        ours = {**paho(ctx, mqtt_port), **mosquitto_clients(mqtt_port)}
        results = []
        for name, expected in theirs.items():
            got = ours.get(name, "(no outcome)")
            same = got == expected or (got.startswith("refused") and expected.startswith("refused"))
            results.append((name, "pass" if same else "fail", f"Leveret: {got} / Mosquitto: {expected}"))
        return results
    finally:
        if leveret:
            leveret.stop()
        reference.stop()


SUITES = {
    "mqtt": ("MQTT 3.1.1 and 5.0, paho-mqtt + mosquitto_pub/sub, Mosquitto 2.0 beside Leveret", run),
}
