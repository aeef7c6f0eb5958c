"""Eclipse Paho's MQTT interoperability suite (eclipse/paho.mqtt.testing,
issue 32): `interoperability/client_test.py` (MQTT 3.1.1) and
`client_test5.py` (5.0), unchanged, against Debian's Mosquitto 2.0 and a
Leveret, each with anonymous logins (the suite sends no user name).

The suite is not on any package registry, and its code is not copied into
this repository, so it comes from a checkout `PAHO_TESTING_DIR` names (the
repository's root; the last run used commit 9d7bb80); without one the suite
is reported skipped (so in CI, which reaches package registries only).
`python/paho_interop.py` runs one file with a JSON line per test; a test
with no result within TEST_TIMEOUT seconds (the longest takes about 20) (one of the suite's tests waits
forever for a broker that never disconnects it) is counted as hung and the
file runs again past it.

A test passes when it passes on Leveret; a test that fails on Leveret and
on Mosquitto is reported as skipped ("fails on Mosquitto too"): Leveret
must pass what Mosquitto passes. Every outcome goes to
`conformance/results/paho-interop.txt`.
"""

import json
import os
from concurrent.futures import ThreadPoolExecutor
import signal
import subprocess
import sys
import tempfile
import threading

from nodes import LeveretNode, SetupError, free_port

TEST_TIMEOUT = 60
FILES = (("3.1.1", "client_test.py"), ("5.0", "client_test5.py"))


def suite_dir(ctx):
    """The suite's interoperability/ directory in the checkout PAHO_TESTING_DIR names, or None: it is
    on no package registry (CI cannot fetch it) and its code is not copied into this repository."""
    root = os.environ.get("PAHO_TESTING_DIR")
    if not root:
        return None
    inter = os.path.join(root, "interoperability")
    if not os.path.exists(os.path.join(inter, "client_test5.py")):
        raise SetupError(f"no Paho interoperability suite at {inter} (PAHO_TESTING_DIR must name a checkout of "
                         "eclipse/paho.mqtt.testing)")
    return inter


def run_file(ctx, inter, name, port):
    """{test: (status, detail)} for one file of the suite against `port`."""
    results = {}
    skip = []
    while True:
        cmd = [ctx.vpy, os.path.join(ctx.here, "python", "paho_interop.py"), "--dir", inter, "--file", name,
               "--port", str(port), "--exclude", ",".join(skip)]
        errors = tempfile.TemporaryFile(mode="w+")
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=errors, text=True, start_new_session=True)
        lines = []
        cond = threading.Condition()

        def reader():
            for line in proc.stdout:
                with cond:
                    lines.append(line)
                    cond.notify()
            with cond:
                lines.append(None)
                cond.notify()

        threading.Thread(target=reader, daemon=True).start()
        current = None
        hung = False
        while True:
            with cond:
                if not lines:
                    cond.wait(timeout=TEST_TIMEOUT)
                if not lines:
                    hung = True
                    break
                line = lines.pop(0)
            if line is None:
                break
            try:
                rec = json.loads(line)
            except ValueError:
                continue
            if "start" in rec:
                current = rec["start"]
            elif "test" in rec:
                results[rec["test"]] = (rec["status"], rec.get("detail", ""))
                current = None
        if hung:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        errors.seek(0)
        tail = errors.read()[-1500:]
        if current is None:
            if not results:
                raise SetupError(f"{name} on port {port} gave no result (exit {proc.returncode}): {tail}")
            return results
        results[current] = ("fail", f"no result within {TEST_TIMEOUT}s (hung)" if hung
                            else f"the suite's process exited ({proc.returncode}) during the test: {tail}")
        skip = sorted(results)


def anonymous_leveret(binary):
    """A Leveret whose MQTT clients without a user name log in as guest."""
    conf_dir = tempfile.mkdtemp(prefix="leveret-conformance-conf-")
    conf = os.path.join(conf_dir, "leveret.toml")
    with open(conf, "w") as f:
        f.write('mqtt-default-user = "guest"\nmqtt-default-pass = "guest"\n')
    port = free_port()
    node = LeveretNode(binary, ["--config", conf, "--mqtt-listen", f"127.0.0.1:{port}"], wait_for=port)
    return node, port


def write_results(ctx, rows):
    out = os.path.join(ctx.here, "results", "paho-interop.txt")
    os.makedirs(os.path.dirname(out), exist_ok=True)
    with open(out, "w") as f:
        f.write("# conformance/run --suite mqtt-interop: Eclipse Paho's interoperability suite\n"
                "# test                               Mosquitto 2.0   Leveret\n")
        for tid, ref, ours in rows:
            f.write(f"{tid:42} {ref:15} {ours}\n")


def run(ctx):
    if not ctx.leveret:
        return [("paho-interop", "skip", "needs a leveret of its own with an MQTT listener (not --url)")]
    inter = suite_dir(ctx)
    if inter is None:
        return [("paho-interop", "skip", "set PAHO_TESTING_DIR to a checkout of eclipse/paho.mqtt.testing "
                 "(on no package registry, not copied here; the last run: conformance/results/paho-interop.txt)")]
    ctx.ensure_python()
    from mqtt import MosquittoNode
    reference = MosquittoNode(anonymous=True)
    leveret = None
    try:
        leveret, port = anonymous_leveret(ctx.leveret)
        results, rows = [], []
        for version, name in FILES:
            # Both brokers at once (each file takes minutes, mostly sleeps).
            with ThreadPoolExecutor(2) as pool:
                theirs_f = pool.submit(run_file, ctx, inter, name, reference.port)
                ours_f = pool.submit(run_file, ctx, inter, name, port)
                theirs, ours = theirs_f.result(), ours_f.result()
            for test in sorted(set(theirs) | set(ours)):
                ref_status, ref_detail = theirs.get(test, ("fail", "no result"))
                status, detail = ours.get(test, ("fail", "no result"))
                tid = f"{version}.{test}"
                rows.append((tid, ref_status, status))
                if status != "pass" and ref_status != "pass":
                    results.append((tid, "skip", f"fails on Mosquitto too: {ref_detail[-300:]}"))
                else:
                    results.append((tid, status, detail[-600:]))
        write_results(ctx, rows)
        return results
    finally:
        if leveret:
            leveret.stop()
        reference.stop()


SUITES = {
    "mqtt-interop": ("Eclipse Paho's MQTT interoperability suite (3.1.1, 5.0), Mosquitto 2.0 beside Leveret", run),
}
