"""Brokers the differential suites start for themselves: a RabbitMQ 3.10
node (Debian's rabbitmq-server run unprivileged from /usr/lib/rabbitmq/bin,
with its own directories, ports and Erlang cookie) and a leveret process,
each on free loopback ports and removed when stopped."""

import os
import random
import shutil
import socket
import subprocess
import tempfile
import time

RABBIT_BIN = "/usr/lib/rabbitmq/bin"


class SetupError(Exception):
    pass


def _ephemeral_range():
    try:
        with open("/proc/sys/net/ipv4/ip_local_port_range") as f:
            low, high = f.read().split()[:2]
            return int(low), int(high)
    except (OSError, ValueError):
        return 49152, 65535


def free_port():
    """A free loopback port outside the kernel's ephemeral range (below it,
    or above it where it starts too low): a port-0 bind (every broker's
    metrics and HTTP listeners, every client's connection) never lands
    there, so nothing takes it between this pick and the bind of the
    broker it is for."""
    low, high = _ephemeral_range()
    if low >= 11000:
        floor, ceiling = 10000, low
    elif high <= 64535:
        floor, ceiling = high + 1, 65536
    else:
        raise SetupError(f"the ephemeral port range {low}-{high} leaves no room")
    for _ in range(1000):
        port = random.randrange(floor, ceiling)
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise SetupError(f"no free port between {floor} and {ceiling}")


def wait_port(port, timeout):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            return True
        except OSError:
            time.sleep(0.2)
    return False


def require_rabbitmq():
    if not os.path.exists(os.path.join(RABBIT_BIN, "rabbitmq-server")):
        raise SetupError("Debian's rabbitmq-server is not installed (apt-get install rabbitmq-server; .ci/run does)")


class RabbitNode:
    """A RabbitMQ node; `conf` holds rabbitmq.conf lines besides its plain
    listener on `self.port`, `plugins` the plugins to enable; nodes given
    the same `home` share its Erlang cookie (to form a cluster)."""

    def __init__(self, conf=(), plugins=(), home=None):
        require_rabbitmq()
        self.dir = tempfile.mkdtemp(prefix="leveret-conformance-rabbitmq-")
        self.port = free_port()
        self.node = f"leveret-conf-{os.getpid()}-{self.port}@localhost"
        self.env = dict(os.environ, HOME=home or self.dir, RABBITMQ_NODENAME=self.node,
                        RABBITMQ_MNESIA_BASE=os.path.join(self.dir, "mnesia"),
                        RABBITMQ_LOG_BASE=os.path.join(self.dir, "log"),
                        RABBITMQ_ENABLED_PLUGINS_FILE=os.path.join(self.dir, "enabled_plugins"),
                        RABBITMQ_CONFIG_FILE=os.path.join(self.dir, "rabbitmq"),
                        RABBITMQ_PID_FILE=os.path.join(self.dir, "pid"),
                        RABBITMQ_DIST_PORT=str(free_port()))
        with open(os.path.join(self.dir, "enabled_plugins"), "w") as f:
            f.write("[" + ",".join(plugins) + "].\n")
        with open(os.path.join(self.dir, "rabbitmq.conf"), "w") as f:
            f.write(f"listeners.tcp.1 = 127.0.0.1:{self.port}\nloopback_users = none\n")
            f.write("".join(line + "\n" for line in conf))
        self.proc = subprocess.Popen([os.path.join(RABBIT_BIN, "rabbitmq-server")], env=self.env,
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                     start_new_session=True)
        self.await_startup()

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
                log = ""
                for name in os.listdir(os.path.join(self.dir, "log")) if os.path.isdir(os.path.join(self.dir, "log")) else []:
                    log += open(os.path.join(self.dir, "log", name), errors="replace").read()[-2000:]
                self.stop()
                raise SetupError(f"the RabbitMQ node did not start: {r.stdout}{r.stderr}{log}")
            time.sleep(0.5)

    def load(self, definitions, done):
        """Imports a definitions file and waits until `done()` says the
        asynchronous import has finished."""
        r = self.ctl("import_definitions", definitions)
        if r.returncode != 0:
            raise SetupError(f"rabbitmqctl import_definitions: {r.stdout}{r.stderr}")
        deadline = time.monotonic() + 60
        while not done(self):
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
    """A leveret with `args` besides its plain listener on `self.port`
    (its management API on a port of the kernel's choosing unless `args`
    say `--http-listen`); `wait_for` names another port to wait for (a
    TLS listener, the management API)."""

    def __init__(self, binary, args=(), wait_for=None):
        self.dir = tempfile.mkdtemp(prefix="leveret-conformance-")
        self.port = free_port()
        self.logpath = os.path.join(self.dir, "leveret.log")
        self.log = open(self.logpath, "w")
        http = [] if "--http-listen" in args else ["--http-listen", "127.0.0.1:0"]
        self.proc = subprocess.Popen(
            [binary, "--listen", f"127.0.0.1:{self.port}", "--data-dir", os.path.join(self.dir, "data"),
             "--metrics-listen", "127.0.0.1:0", *http,
             # MQTT is on 1883 by default; a suite that wants it passes its own port.
             "--mqtt-listen", "none", *args],
            stdout=self.log, stderr=subprocess.STDOUT, start_new_session=True)
        if not all(wait_port(p, 30) for p in [self.port, wait_for] if p):
            tail = open(self.logpath, errors="replace").read()[-2000:]
            self.stop()
            raise SetupError(f"leveret did not start: {tail}")

    def stop(self):
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        shutil.rmtree(self.dir, ignore_errors=True)
