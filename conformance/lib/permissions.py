"""The differential permissions suite (issue 14): one definitions file
(permissions/definitions.json: users, vhosts, permissions, topic
permissions) loaded into a RabbitMQ 3.10 node of the suite's own (Debian's
rabbitmq-server, unprivileged, with its own ports and directories, the
file imported with `rabbitmqctl import_definitions`) and into a Leveret
(`--definitions`); then pika and amqplib each run the table of
permissions/table.json (RabbitMQ's mapping of operations to permissions,
allowed and refused) against both. A step passes when both brokers give
the same outcome: ok, or the same reply code and text.

The runner takes a Ctx with `leveret` (the binary; None when the runner was
given --url, and the suite is then skipped) and returns
[(test_id, status, detail)] like the upstream runners.
"""

import json
import os
import re
import shutil
import socket
import subprocess
import tempfile
import time

RABBIT_BIN = "/usr/lib/rabbitmq/bin"


class SetupError(Exception):
    pass


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_port(port, timeout):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            return True
        except OSError:
            time.sleep(0.2)
    return False


class RabbitNode:
    """A RabbitMQ node with its own directories, ports and Erlang cookie."""

    def __init__(self):
        self.dir = tempfile.mkdtemp(prefix="leveret-perm-rabbitmq-")
        self.port = free_port()
        self.node = f"leveret-perm-{os.getpid()}@localhost"
        self.env = dict(os.environ, HOME=self.dir, RABBITMQ_NODENAME=self.node,
                        RABBITMQ_MNESIA_BASE=os.path.join(self.dir, "mnesia"),
                        RABBITMQ_LOG_BASE=os.path.join(self.dir, "log"),
                        RABBITMQ_ENABLED_PLUGINS_FILE=os.path.join(self.dir, "enabled_plugins"),
                        RABBITMQ_CONFIG_FILE=os.path.join(self.dir, "rabbitmq"),
                        RABBITMQ_PID_FILE=os.path.join(self.dir, "pid"),
                        RABBITMQ_DIST_PORT=str(free_port()))
        with open(os.path.join(self.dir, "enabled_plugins"), "w") as f:
            f.write("[].\n")
        with open(os.path.join(self.dir, "rabbitmq.conf"), "w") as f:
            f.write(f"listeners.tcp.1 = 127.0.0.1:{self.port}\nloopback_users = none\n")
        self.proc = subprocess.Popen([os.path.join(RABBIT_BIN, "rabbitmq-server")], env=self.env,
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                     start_new_session=True)

    def ctl(self, *args, timeout=120):
        return subprocess.run([os.path.join(RABBIT_BIN, "rabbitmqctl"), "-n", self.node, *args],
                              env=self.env, text=True, capture_output=True, timeout=timeout)

    def await_startup(self):
        deadline = time.monotonic() + 120
        while True:
            r = self.ctl("await_startup", "--timeout", "30")
            if r.returncode == 0:
                return
            if time.monotonic() > deadline or self.proc.poll() is not None:
                raise SetupError(f"the RabbitMQ node did not start: {r.stdout}{r.stderr}")
            time.sleep(0.5)

    def load(self, definitions):
        r = self.ctl("import_definitions", definitions)
        if r.returncode != 0:
            raise SetupError(f"rabbitmqctl import_definitions: {r.stdout}{r.stderr}")
        # The import runs asynchronously: wait for its last item.
        deadline = time.monotonic() + 60
        while "amq.topic" not in self.ctl("list_topic_permissions", "-p", "/").stdout:
            if time.monotonic() > deadline:
                raise SetupError("RabbitMQ never finished importing the definitions")
            time.sleep(0.2)

    def stop(self):
        self.ctl("stop", timeout=60)
        try:
            self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, 9)
        shutil.rmtree(self.dir, ignore_errors=True)


class LeveretNode:
    def __init__(self, binary, definitions):
        self.dir = tempfile.mkdtemp(prefix="leveret-perm-")
        self.port = free_port()
        self.log = open(os.path.join(self.dir, "leveret.log"), "w")
        self.proc = subprocess.Popen(
            [binary, "--listen", f"127.0.0.1:{self.port}", "--data-dir", os.path.join(self.dir, "data"),
             "--metrics-listen", "127.0.0.1:0", "--http-listen", "127.0.0.1:0", "--definitions", definitions],
            stdout=self.log, stderr=subprocess.STDOUT, start_new_session=True)
        if not wait_port(self.port, 30):
            self.stop()
            raise SetupError("leveret did not start with the permissions definitions")

    def stop(self):
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        shutil.rmtree(self.dir, ignore_errors=True)


def outcomes(cmd, url, table):
    r = subprocess.run([*cmd, "--table", table, "--url", url], text=True, capture_output=True, timeout=600)
    if r.returncode != 0:
        raise SetupError(f"{' '.join(cmd)} against {url} failed: {r.stderr[-2000:]}")
    found = {}
    for line in r.stdout.splitlines():
        step = json.loads(line)
        # Server-generated names differ by design.
        found[step["name"]] = re.sub(r"amq\.gen-[A-Za-z0-9_-]+", "amq.gen-*", step["outcome"])
    return found


def run(ctx):
    if not ctx.leveret:
        return [("permissions", "skip", "needs a leveret of its own with the suite's definitions (not --url)")]
    if not os.path.exists(os.path.join(RABBIT_BIN, "rabbitmq-server")):
        raise SetupError("Debian's rabbitmq-server is not installed (apt-get install rabbitmq-server; .ci/run does)")
    ctx.ensure_python()
    ctx.ensure_node()
    here = os.path.join(ctx.here, "permissions")
    definitions = os.path.join(here, "definitions.json")
    table = os.path.join(here, "table.json")
    drivers = {
        "pika": [ctx.vpy, os.path.join(ctx.here, "python", "permissions.py")],
        "amqplib": ["node", os.path.join(ctx.here, "js", "permissions.js")],
    }
    rabbit = RabbitNode()
    leveret = None
    try:
        rabbit.await_startup()
        rabbit.load(definitions)
        leveret = LeveretNode(ctx.leveret, definitions)
        results = []
        for lib, cmd in drivers.items():
            reference = outcomes(cmd, f"amqp://127.0.0.1:{rabbit.port}", table)
            ours = outcomes(cmd, f"amqp://127.0.0.1:{leveret.port}", table)
            for name, expected in reference.items():
                got = ours.get(name, "(no outcome)")
                if got == expected:
                    results.append((f"{lib}: {name}", "pass", expected))
                else:
                    results.append((f"{lib}: {name}", "fail", f"RabbitMQ: {expected} / Leveret: {got}"))
        return results
    finally:
        if leveret:
            leveret.stop()
        rabbit.stop()


# name -> (description, runner)
SUITES = {
    "permissions": ("permissions table, pika + amqplib, RabbitMQ 3.10 beside Leveret", run),
}
