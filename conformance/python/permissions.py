"""Permissions table driver, pika: python permissions.py --table FILE --url URL

Runs each step of the table (conformance/permissions/table.json) on a fresh
connection and channel and prints one JSON line per step:
{"name": ..., "outcome": "ok" | "<code> <reply text>"}.
`URL` is amqp://HOST:PORT; each step's user and vhost come from the table.
"""

import argparse
import json
import re
import urllib.parse

import pika

PASSWORDS = {"guest": "guest", "pu": "robot-pw"}


def reply(error):
    """The reply code and text of a broker's close, from pika's exceptions."""
    if isinstance(error, (pika.exceptions.ChannelClosedByBroker, pika.exceptions.ConnectionClosedByBroker)):
        return f"{error.reply_code} {error.reply_text}"
    found = re.search(r'\((\d{3})\) "?([^"]*)', str(error.args))
    return f"{found.group(1)} {found.group(2)}".replace("\\'", "'") if found else f"error {error!r}"


def run_step(host, port, step):
    user = step.get("as", "pu")
    params = pika.ConnectionParameters(host, port, step.get("vhost", "/"),
                                       pika.PlainCredentials(user, PASSWORDS[user]),
                                       connection_attempts=1, blocked_connection_timeout=10)
    try:
        connection = pika.BlockingConnection(params)
    except Exception as e:  # noqa: BLE001 - every refusal is an outcome
        return reply(e)
    try:
        ch = connection.channel()
        op = step["op"]
        args = step.get("arguments")
        if op == "connection.open":
            pass
        elif op == "queue.declare":
            ch.queue_declare(step["queue"], passive=step.get("passive", False), arguments=args)
        elif op == "queue.delete":
            ch.queue_delete(step["queue"])
        elif op == "queue.purge":
            ch.queue_purge(step["queue"])
        elif op == "queue.bind":
            ch.queue_bind(step["queue"], step["exchange"], step["routing_key"])
        elif op == "queue.unbind":
            ch.queue_unbind(step["queue"], step["exchange"], step["routing_key"])
        elif op == "exchange.declare":
            ch.exchange_declare(step["exchange"], step["type"], passive=step.get("passive", False), arguments=args)
        elif op == "exchange.delete":
            ch.exchange_delete(step["exchange"])
        elif op == "exchange.bind":
            ch.exchange_bind(step["destination"], step["source"], step["routing_key"])
        elif op == "exchange.unbind":
            ch.exchange_unbind(step["destination"], step["source"], step["routing_key"])
        elif op == "basic.publish":
            ch.basic_publish(step["exchange"], step["routing_key"], b"permissions")
        elif op == "basic.consume":
            ch.basic_consume(step["queue"], lambda *a: None)
        elif op == "basic.get":
            ch.basic_get(step["queue"], auto_ack=True)
        else:
            raise ValueError(f"unknown op {op}")
        # A round trip, so that a refused publish has closed the channel.
        ch.basic_qos(prefetch_count=1)
        return "ok"
    except (pika.exceptions.ChannelClosedByBroker, pika.exceptions.ConnectionClosedByBroker) as e:
        return reply(e)
    finally:
        try:
            connection.close()
        except Exception:  # noqa: BLE001 - already closed by the broker
            pass


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--table", required=True)
    ap.add_argument("--url", required=True)
    args = ap.parse_args()
    url = urllib.parse.urlparse(args.url)
    for step in json.load(open(args.table))["steps"]:
        print(json.dumps({"name": step["name"], "outcome": run_step(url.hostname, url.port, step)}), flush=True)


if __name__ == "__main__":
    main()
