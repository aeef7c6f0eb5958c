"""The TLS suite's checks with pika: python tls.py --certs DIR --port PORT

One JSON line per check: {"name", "outcome"}, outcome "ok" or "refused: ...".
"""

import argparse
import json
import os
import ssl

import pika


def check(port, cafile, client=None, external=False):
    context = ssl.create_default_context(cafile=cafile)
    if client:
        context.load_cert_chain(client + ".pem", client + ".key")
    credentials = pika.credentials.ExternalCredentials() if external else pika.PlainCredentials("guest", "guest")
    params = pika.ConnectionParameters("localhost", port, "/", credentials, ssl_options=pika.SSLOptions(context, "localhost"),
                                       connection_attempts=1, socket_timeout=20)
    try:
        connection = pika.BlockingConnection(params)
        ch = connection.channel()
        queue = ch.queue_declare("", exclusive=True).method.queue
        ch.basic_publish("", queue, b"tls")
        _, _, body = ch.basic_get(queue, auto_ack=True)
        connection.close()
        return "ok" if body == b"tls" else "refused: the message did not come back"
    except Exception as e:  # noqa: BLE001 - every refusal is an outcome
        return f"refused: {e!r}"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--certs", required=True)
    ap.add_argument("--port", type=int, required=True)
    args = ap.parse_args()
    d = lambda name: os.path.join(args.certs, name)  # noqa: E731
    checks = [
        ("handshake, PLAIN, round trip", dict(cafile=d("ca.pem"))),
        ("mutual TLS, EXTERNAL as robot-7", dict(cafile=d("ca.pem"), client=d("client"), external=True)),
        ("server not trusted (rogue CA)", dict(cafile=d("rogue-ca.pem"))),
        ("client certificate from a rogue CA", dict(cafile=d("ca.pem"), client=d("rogue"), external=True)),
    ]
    for name, kw in checks:
        print(json.dumps({"name": name, "outcome": check(args.port, **kw)}), flush=True)


if __name__ == "__main__":
    main()
