#!/usr/bin/env python3
"""TLS against plaintext, Leveret beside RabbitMQ 3.10, in one run (issue 14).

Certificates from the conformance suite's rcgen generator; Leveret (release)
with a plaintext and a TLS listener; a RabbitMQ node of its own with the same
(conformance/lib/nodes.py). Each generator drives the four endpoints one
after the other: leveret-perf (ours; amqps with cacertfile) and lavinmqperf
(LavinMQ's, amqps with verify=none). Usage: python3 tls.py > tls.txt
"""
import os
import subprocess
import sys
import tempfile
import time

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", ".."))
sys.path.insert(0, os.path.join(REPO, "conformance", "lib"))
from nodes import LeveretNode, RabbitNode, free_port, wait_port  # noqa: E402

PERF = os.path.join(REPO, "target", "release", "leveret-perf")
LAVINMQPERF = os.path.join(REPO, "..", "shared", "anchors", "lavinmq", "lavinmqperf")
CERTS_BIN = os.path.join(REPO, "conformance", ".cache", "cargo-target", "debug", "tls-certs")


def run(cmd):
    print("$ " + " ".join(cmd), flush=True)
    r = subprocess.run(cmd, text=True, capture_output=True, timeout=300)
    print(r.stdout[-3000:] + r.stderr[-1500:], flush=True)


def main():
    certs = tempfile.mkdtemp(prefix="tls-perf-")
    subprocess.run([CERTS_BIN, certs], check=True)
    c = lambda n: os.path.join(certs, n)  # noqa: E731
    lev_tls = free_port()
    leveret = LeveretNode(os.path.join(REPO, "target", "release", "leveret"),
                          ["--tls-listen", f"127.0.0.1:{lev_tls}", "--tls-certfile", c("server.pem"),
                           "--tls-keyfile", c("server.key"), "--log", "warn"], wait_for=lev_tls)
    rab_tls = free_port()
    rabbit = RabbitNode(conf=[f"listeners.ssl.1 = 127.0.0.1:{rab_tls}", f"ssl_options.certfile = {c('server.pem')}",
                              f"ssl_options.keyfile = {c('server.key')}", "ssl_options.verify = verify_none",
                              "ssl_options.fail_if_no_peer_cert = false"])
    assert wait_port(rab_tls, 30)
    try:
        endpoints = [("Leveret plain", f"amqp://guest:guest@localhost:{leveret.port}/%2f"),
                     ("Leveret TLS", f"amqps://guest:guest@localhost:{lev_tls}/%2f"),
                     ("RabbitMQ plain", f"amqp://guest:guest@localhost:{rabbit.port}/%2f"),
                     ("RabbitMQ TLS", f"amqps://guest:guest@localhost:{rab_tls}/%2f")]
        ca = "cacertfile=" + c("ca.pem")
        for name, url in endpoints:
            ours = url + ("?" + ca if url.startswith("amqps") else "")
            print(f"\n## {name}", flush=True)
            run([PERF, "throughput", "--url", ours, "-x", "1", "-y", "1", "-s", "16", "--duration", "8", "--warmup", "2"])
            run([PERF, "rtt", "--url", ours, "--sizes", "16", "--count", "3000"])
            theirs = url + ("?verify=none" if url.startswith("amqps") else "")
            run([LAVINMQPERF, "throughput", f"--uri={theirs}", "-x", "1", "-y", "1", "-s", "16", "-z", "8", "-j", "-q"])
            run([LAVINMQPERF, "throughput", f"--uri={theirs}", "-x", "1", "-y", "1", "-s", "128", "-r", "1000", "-l", "-z", "8", "-j", "-q",
                 # A queue of its own: the throughput run's backlog is not its business.
                 "-u", "perf-latency"])
            time.sleep(1)
    finally:
        leveret.stop()
        rabbit.stop()


if __name__ == "__main__":
    main()
