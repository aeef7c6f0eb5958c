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
import subprocess

from nodes import LeveretNode, RabbitNode, SetupError


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
        # The import is asynchronous: its last item is the topic permission.
        rabbit.load(definitions, lambda node: "amq.topic" in node.ctl("list_topic_permissions", "-p", "/").stdout)
        leveret = LeveretNode(ctx.leveret, ["--definitions", definitions])
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
