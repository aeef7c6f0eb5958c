#!/usr/bin/env python3
"""Forwarding rate into a three-node RabbitMQ 3.10 cluster, Leveret's
shovel beside RabbitMQ's own (rabbitmq_shovel on a fourth RabbitMQ node as
the source), in one run (issue 16), for each destination queue type in
DEST_TYPES (default "quorum,classic,leveret": a quorum queue, which bounds
both shovels at what three replicating nodes take; a durable classic queue
on one node, which takes more; and, to see past the cluster, a durable
queue on a separate Leveret broker, which takes more still). Both shovels: on-confirm, prefetch 1000,
the same 100,000 persistent 64-byte messages waiting in a durable source
queue before the shovel starts; the rate is messages over the time from
the shovel's start to the last one in the destination queue. Usage:
python3 uplink.py > uplink.txt (needs the release leveret, pika in the
conformance venv, Debian's rabbitmq-server).
"""
import json
import os
import subprocess
import sys
import tempfile
import time

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", ".."))
sys.path.insert(0, os.path.join(REPO, "conformance", "lib"))
from nodes import LeveretNode, RabbitNode, free_port  # noqa: E402

VPY = os.path.join(REPO, "conformance", ".venv", "bin", "python")
COUNT = int(os.environ.get("COUNT", "100000"))
DEST_TYPES = os.environ.get("DEST_TYPES", "quorum,classic,leveret").split(",")

FILL = """
import pika, sys
url, queue, count = sys.argv[1], sys.argv[2], int(sys.argv[3])
c = pika.BlockingConnection(pika.URLParameters(url)); ch = c.channel(); ch.confirm_delivery()
ch.queue_declare(queue, durable=True)
body = b"x" * 64
props = pika.BasicProperties(delivery_mode=2)
for i in range(count):
    ch.basic_publish("", queue, body, props)
c.close()
"""

DEPTH = """
import pika, sys
c = pika.BlockingConnection(pika.URLParameters(sys.argv[1])); ch = c.channel()
print(ch.queue_declare(sys.argv[2], passive=True).method.message_count); c.close()
"""


def py(script, *args):
    return subprocess.run([VPY, "-c", script, *args], check=True, capture_output=True, text=True).stdout.strip()


def depth(url, queue):
    try:
        return int(py(DEPTH, url, queue))
    except subprocess.CalledProcessError:
        return -1


def cluster():
    home = tempfile.mkdtemp(prefix="uplink-perf-cookie-")
    cookie = os.path.join(home, ".erlang.cookie")
    with open(cookie, "w") as f:
        f.write("LEVERETUPLINKPERFCOOKIE")
    os.chmod(cookie, 0o400)
    nodes = [RabbitNode(home=home) for _ in range(3)]
    for node in nodes[1:]:
        for args in (["stop_app"], ["join_cluster", nodes[0].node], ["start_app"]):
            r = node.ctl(*args)
            assert r.returncode == 0, r
        node.await_startup()
    return nodes


def wait_drained(url, queue, start):
    while True:
        n = depth(url, queue)
        if n >= COUNT:
            return time.monotonic() - start
        time.sleep(0.2)


def leveret_shovel(dest_uris, queue):
    """Fills a Leveret's durable queue, then starts the binary with a shovel
    configured; the seconds until the destination has every message."""
    lev_dir = tempfile.mkdtemp(prefix="uplink-perf-")
    filler = LeveretNode(os.path.join(REPO, "target", "release", "leveret"), ["--log", "warn"])
    py(FILL, f"amqp://guest:guest@127.0.0.1:{filler.port}/%2f", "telemetry", str(COUNT))
    data = os.path.join(filler.dir, "data")
    filler.proc.terminate(); filler.proc.wait()
    config = os.path.join(lev_dir, "leveret.toml")
    with open(config, "w") as f:
        f.write('[shovels.up]\nsrc-uri = "amqp://"\nsrc-queue = "telemetry"\nsrc-prefetch-count = 1000\n'
                f'dest-uri = {json.dumps(dest_uris)}\ndest-queue = "{queue}"\n')
    start = time.monotonic()
    port = free_port()
    proc = subprocess.Popen([os.path.join(REPO, "target", "release", "leveret"), "--listen", f"127.0.0.1:{port}",
                             "--data-dir", data, "--metrics-listen", "127.0.0.1:0", "--http-listen", "127.0.0.1:0",
                             "--config", config, "--log", "warn"])
    elapsed = wait_drained(dest_uris[0], queue, start)
    proc.terminate(); proc.wait()
    return elapsed


def rabbitmq_shovel(dest_uris, queue, url):
    """The same with RabbitMQ's shovel on a node of its own."""
    source = RabbitNode(plugins=["rabbitmq_shovel"])
    try:
        py(FILL, url(source), "telemetry", str(COUNT))
        value = {"src-uri": url(source), "src-queue": "telemetry", "src-prefetch-count": 1000,
                 "dest-uri": dest_uris, "dest-queue": queue, "ack-mode": "on-confirm"}
        start = time.monotonic()
        r = source.ctl("set_parameter", "shovel", "up", json.dumps(value))
        assert r.returncode == 0, r
        return wait_drained(dest_uris[0], queue, start)
    finally:
        source.stop()


def main():
    print(f"# {COUNT} persistent 64 B messages, on-confirm, prefetch 1000, into a 3-node cluster", flush=True)
    nodes = cluster()
    url = lambda n: f"amqp://guest:guest@127.0.0.1:{n.port}/%2f"  # noqa: E731
    dest_uris = [url(n) for n in nodes]
    try:
        for kind in DEST_TYPES:
            queues = {who: f"{kind}-from-{who}" for who in ("leveret", "rabbitmq")}
            sink = None
            uris = dest_uris
            if kind == "leveret":
                sink = LeveretNode(os.path.join(REPO, "target", "release", "leveret"), ["--log", "warn"])
                uris = [f"amqp://guest:guest@127.0.0.1:{sink.port}/%2f"]
            queue_type = "classic" if kind == "leveret" else kind
            for queue in queues.values():
                subprocess.run([VPY, "-c", "import pika,sys; c=pika.BlockingConnection(pika.URLParameters(sys.argv[1])); "
                                "c.channel().queue_declare(sys.argv[2], durable=True, arguments={'x-queue-type':sys.argv[3]}); c.close()",
                                uris[0], queue, queue_type], check=True)
            elapsed = leveret_shovel(uris, queues["leveret"])
            print(f"{kind} queue, Leveret shovel:  {COUNT} in {elapsed:.1f} s = {COUNT / elapsed:,.0f} msgs/s (including the broker's start)", flush=True)
            elapsed_r = rabbitmq_shovel(uris, queues["rabbitmq"], url)
            print(f"{kind} queue, RabbitMQ shovel: {COUNT} in {elapsed_r:.1f} s = {COUNT / elapsed_r:,.0f} msgs/s", flush=True)
            print(f"{kind} queue, Leveret / RabbitMQ: {elapsed_r / elapsed:.2f}x", flush=True)
            if sink:
                sink.proc.terminate(); sink.proc.wait()
    finally:
        for node in nodes:
            node.stop()


if __name__ == "__main__":
    main()
