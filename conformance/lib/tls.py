"""The TLS suite (issue 14): certificates made with rcgen
(rust/src/bin/tls-certs.rs: a CA, a server certificate for localhost, a
client certificate for user robot-7, and the same signed by a rogue CA);
a RabbitMQ 3.10 node with a TLS listener (`listeners.ssl`, `ssl_options`
with verify_peer, the rabbitmq_auth_mechanism_ssl plugin with
`ssl_cert_login_from = common_name`) and a Leveret with the same files
(`--tls-listen`, `--tls-certfile`, `--tls-keyfile`, `--tls-cacertfile`).
pika, amqplib, amqp091-go and lapin each run four checks against both: a
handshake with PLAIN and a round trip, mutual TLS logging in with EXTERNAL
as robot-7, a server the client does not trust, and a client certificate
from the rogue CA. A check passes when it gives the expected outcome on
Leveret and the same outcome on RabbitMQ.
"""

import json
import os
import subprocess

from nodes import LeveretNode, RabbitNode, SetupError, free_port, wait_port

EXPECTED = {
    "handshake, PLAIN, round trip": "ok",
    "mutual TLS, EXTERNAL as robot-7": "ok",
    "server not trusted (rogue CA)": "refused",
    "client certificate from a rogue CA": "refused",
}

# guest/guest and robot-7 (password robot-pw), as RabbitMQ 3.10 hashes them.
USERS = {
    "users": [
        {"name": "guest", "password_hash": "ryEPfAes34E9ktgNmN0qbYVWyPeURRbjxMcQf9tVwj2qap6R",
         "hashing_algorithm": "rabbit_password_hashing_sha256", "tags": ["administrator"], "limits": {}},
        {"name": "robot-7", "password_hash": "XrbDVjlDKoAec+dZ1vISo+jt5TVEqQvMa8euInsOyfsIm1Ys",
         "hashing_algorithm": "rabbit_password_hashing_sha256", "tags": [], "limits": {}},
    ],
    "vhosts": [{"name": "/"}],
    "permissions": [
        {"user": user, "vhost": "/", "configure": ".*", "write": ".*", "read": ".*"} for user in ("guest", "robot-7")
    ],
}


def go_tls_driver(ctx):
    ctx.ensure_go()
    out = os.path.join(ctx.here, "go", "bin", "leveret-tls")
    src = os.path.join(ctx.here, "go", "src", "leveret-tls")
    newest = max(os.path.getmtime(os.path.join(src, f)) for f in os.listdir(src))
    if not os.path.exists(out) or os.path.getmtime(out) < newest:
        env = ctx.go_env("/usr/share/gocode:" + os.path.join(ctx.here, "go"))
        r = subprocess.run(["go", "build", "-o", out, "leveret-tls"], env=env, text=True, capture_output=True)
        if r.returncode != 0:
            raise SetupError("go build of go/src/leveret-tls failed:\n" + (r.stdout + r.stderr)[-3000:])
    return [out]


def outcomes(cmd, certs, port):
    r = subprocess.run([*cmd, "--certs", certs, "--port", str(port)], text=True, capture_output=True, timeout=600)
    if r.returncode != 0:
        raise SetupError(f"{' '.join(cmd)} on port {port} failed: {(r.stdout + r.stderr)[-2000:]}")
    return {c["name"]: c["outcome"] for c in map(json.loads, r.stdout.splitlines())}


def run(ctx):
    if not ctx.leveret:
        return [("tls", "skip", "needs a leveret of its own with the suite's certificates (not --url)")]
    ctx.ensure_python()
    ctx.ensure_node()
    rust = ctx.rust_driver()[0]
    bin_dir = os.path.dirname(rust)
    drivers = {
        "pika": [ctx.vpy, os.path.join(ctx.here, "python", "tls.py")],
        "amqplib": ["node", os.path.join(ctx.here, "js", "tls.js")],
        "amqp091-go": go_tls_driver(ctx),
        "lapin": [os.path.join(bin_dir, "tls-lapin")],
    }
    certs = os.path.join(ctx.cache, "tls-certs")
    r = subprocess.run([os.path.join(bin_dir, "tls-certs"), certs], text=True, capture_output=True)
    if r.returncode != 0:
        raise SetupError("tls-certs failed: " + r.stderr[-2000:])
    cert = lambda name: os.path.join(certs, name)  # noqa: E731
    definitions = os.path.join(certs, "users.json")
    with open(definitions, "w") as f:
        json.dump(USERS, f)
    rabbit_tls = free_port()
    rabbit = RabbitNode(conf=[
        f"listeners.ssl.1 = 127.0.0.1:{rabbit_tls}",
        f"ssl_options.cacertfile = {cert('ca.pem')}",
        f"ssl_options.certfile = {cert('server.pem')}",
        f"ssl_options.keyfile = {cert('server.key')}",
        "ssl_options.verify = verify_peer",
        "ssl_options.fail_if_no_peer_cert = false",
        "auth_mechanisms.1 = PLAIN",
        "auth_mechanisms.2 = AMQPLAIN",
        "auth_mechanisms.3 = EXTERNAL",
        "ssl_cert_login_from = common_name",
    ], plugins=["rabbitmq_auth_mechanism_ssl"])
    leveret = None
    try:
        rabbit.load(definitions, lambda node: "robot-7" in node.ctl("list_permissions", "-p", "/").stdout)
        if not wait_port(rabbit_tls, 30):
            raise SetupError("RabbitMQ's TLS listener did not open")
        leveret_tls = free_port()
        leveret = LeveretNode(ctx.leveret, [
            "--definitions", definitions, "--tls-listen", f"127.0.0.1:{leveret_tls}",
            "--tls-certfile", cert("server.pem"), "--tls-keyfile", cert("server.key"),
            "--tls-cacertfile", cert("ca.pem")], wait_for=leveret_tls)
        results = []
        for lib, cmd in drivers.items():
            reference = outcomes(cmd, certs, rabbit_tls)
            ours = outcomes(cmd, certs, leveret_tls)
            for name, expected in EXPECTED.items():
                got, ref = ours.get(name, "(no outcome)"), reference.get(name, "(no outcome)")
                ok = got.split(":")[0] == expected and ref.split(":")[0] == expected
                detail = f"Leveret: {got} / RabbitMQ: {ref}"
                results.append((f"{lib}: {name}", "pass" if ok else "fail", detail))
        return results
    finally:
        if leveret:
            leveret.stop()
        rabbit.stop()


SUITES = {
    "tls": ("TLS and mutual TLS, pika + amqplib + amqp091-go + lapin, RabbitMQ 3.10 beside Leveret", run),
}
