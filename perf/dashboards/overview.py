#!/usr/bin/env python3
"""Runs every panel query of RabbitMQ's "RabbitMQ-Overview" Grafana
dashboard against a real Prometheus scraping a running Leveret while
traffic runs, and reports panel by panel which show data.

    perf/dashboards/overview.py --amqp 127.0.0.1:5672 --metrics 127.0.0.1:15692 \
        --dashboard RabbitMQ-Overview.json [--seconds 75]

The dashboard JSON is rabbitmq-server's
deps/rabbitmq_prometheus/docker/grafana/dashboards/RabbitMQ-Overview.json
(not copied here). The script starts `prometheus` (Debian's package) with a
1 s scrape of `--metrics`, drives AMQP traffic with pika for `--seconds`
(confirmed publishes, unroutable mandatory and non-mandatory ones,
consumers with manual and automatic acks, requeued nacks, basic.get with
both ack modes and on an empty queue, queue, channel and connection
churn), then evaluates each target as an instant query with the
dashboard's variables set as Grafana would set them
(`$rabbitmq_cluster` from `rabbitmq_identity_info`, no `$namespace`).
A panel "shows data" when each of its targets answers with at least one
series. Prints one line per panel and the count.
"""

import argparse
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.parse
import urllib.request

import pika


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def query(prometheus, promql):
    url = f"http://{prometheus}/api/v1/query?" + urllib.parse.urlencode({"query": promql})
    with urllib.request.urlopen(url, timeout=10) as response:
        body = json.load(response)
    if body["status"] != "success":
        raise RuntimeError(f"{promql}: {body}")
    return body["data"]["result"]


def start_prometheus(metrics):
    directory = tempfile.mkdtemp(prefix="overview-prometheus-")
    config = os.path.join(directory, "prometheus.yml")
    with open(config, "w") as f:
        f.write(
            "global:\n  scrape_interval: 1s\n  evaluation_interval: 1s\n"
            "scrape_configs:\n  - job_name: leveret\n    static_configs:\n"
            f"      - targets: ['{metrics}']\n"
        )
    address = f"127.0.0.1:{free_port()}"
    child = subprocess.Popen(
        [
            "prometheus",
            f"--config.file={config}",
            f"--storage.tsdb.path={os.path.join(directory, 'data')}",
            f"--web.listen-address={address}",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    return child, directory, address


def traffic(amqp, stop):
    """Every kind of traffic the dashboard plots, in rounds, until `stop`."""
    host, port = amqp.rsplit(":", 1)
    parameters = pika.ConnectionParameters(host=host, port=int(port), heartbeat=0)
    connection = pika.BlockingConnection(parameters)
    publisher = connection.channel()
    publisher.confirm_delivery()
    publisher.queue_declare("overview-work")
    publisher.queue_declare("overview-auto")
    publisher.queue_declare("overview-poll")
    consumer = connection.channel()
    consumer.basic_qos(prefetch_count=50)
    round_number = 0

    def manual(ch, method, _properties, _body):
        # Every fifth delivery is nacked back once: redeliveries.
        if method.delivery_tag % 5 == 0 and not method.redelivered:
            ch.basic_nack(method.delivery_tag, requeue=True)
        else:
            ch.basic_ack(method.delivery_tag)

    consumer.basic_consume("overview-work", manual)
    consumer.basic_consume("overview-auto", lambda *_: None, auto_ack=True)
    while not stop.is_set():
        round_number += 1
        for _ in range(20):
            publisher.basic_publish("", "overview-work", b"work")
            publisher.basic_publish("", "overview-auto", b"auto")
            publisher.basic_publish("", "overview-poll", b"poll")
        try:
            publisher.basic_publish("", "overview-nowhere", b"returned", mandatory=True)
        except pika.exceptions.UnroutableError:
            pass
        publisher.basic_publish("amq.direct", "nowhere", b"dropped")
        for ack in (False, True):
            method, _, _ = publisher.basic_get("overview-poll", auto_ack=ack)
            if method and not ack:
                publisher.basic_ack(method.delivery_tag)
        publisher.queue_purge("overview-poll")
        publisher.basic_get("overview-poll", auto_ack=True)
        # Churn: a queue, a channel, a connection.
        churn = connection.channel()
        churn.queue_declare(f"overview-churn-{round_number}")
        churn.queue_delete(f"overview-churn-{round_number}")
        churn.close()
        pika.BlockingConnection(parameters).close()
        connection.process_data_events(time_limit=0.5)
    connection.close()


def variables(prometheus):
    identity = query(prometheus, "rabbitmq_identity_info")
    if not identity:
        raise RuntimeError("no rabbitmq_identity_info")
    return {
        "$rabbitmq_cluster": identity[0]["metric"]["rabbitmq_cluster"],
        "$namespace": identity[0]["metric"].get("namespace", ""),
    }


def panels(dashboard):
    for panel in dashboard["panels"]:
        for inner in panel.get("panels", []) + [panel]:
            if inner.get("targets"):
                yield inner


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--amqp", required=True)
    parser.add_argument("--metrics", required=True)
    parser.add_argument("--dashboard", required=True)
    parser.add_argument("--seconds", type=float, default=75)
    args = parser.parse_args()
    with open(args.dashboard) as f:
        dashboard = json.load(f)
    child, directory, prometheus = start_prometheus(args.metrics)
    stop = threading.Event()
    driver = threading.Thread(target=traffic, args=(args.amqp, stop))
    try:
        deadline = time.time() + 30
        while True:
            try:
                if query(prometheus, 'up{job="leveret"} == 1'):
                    break
            except OSError:
                pass
            if time.time() > deadline:
                raise RuntimeError("prometheus never scraped leveret")
            time.sleep(0.5)
        driver.start()
        time.sleep(args.seconds)
        values = variables(prometheus)
        shown = 0
        total = 0
        for panel in panels(dashboard):
            total += 1
            title = panel.get("title") or "(nodes table)"
            answers = []
            for target in panel["targets"]:
                expr = target["expr"]
                for name, value in values.items():
                    expr = expr.replace(name, value)
                if "$" in expr:
                    raise RuntimeError(f"unresolved variable in {expr}")
                result = query(prometheus, expr)
                answers.append([series["value"][1] for series in result])
            ok = all(answers)
            shown += ok
            figures = "; ".join(",".join(a[:3]) or "no data" for a in answers)
            print(f"{'data   ' if ok else 'NO DATA'}  {title}: {figures}")
        print(f"{shown} of {total} panels show data")
    finally:
        stop.set()
        if driver.is_alive():
            driver.join(timeout=30)
        child.terminate()
        child.wait()
        shutil.rmtree(directory, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
