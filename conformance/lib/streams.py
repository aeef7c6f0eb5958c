"""The stream queue suite (issue 33): pika (python/s_streams.py) and
amqp091-go (go/src/leveret-conformance/streams.go, `--streams`) scenarios
run against a RabbitMQ 3.10 node of the suite's own (lib/nodes.py; stream
queues need no plugin over AMQP 0.9.1) and against a Leveret. A scenario
passes when it passes on both and the client observed the same things on
both (run names and server-generated names aside). Where RabbitMQ's
output depends on its storage layout the scenarios record invariants
instead (see python/s_streams.py).

The runner takes a Ctx with `leveret` (the binary; None when the runner was
given --url, and the suite is then skipped), `run_driver`, `normalize` and
`go_driver` from conformance/run, and returns [(test_id, status, detail)]
like the upstream runners.
"""

import json
import os
import secrets
import tempfile

from nodes import LeveretNode, RabbitNode


def compare(ours, theirs):
    """(status, detail) of one scenario from its two records, normalized."""
    if not theirs["ok"]:
        return "fail", f"fails on RabbitMQ: {theirs.get('error')}"
    if not ours["ok"]:
        return "fail", f"Leveret: {ours.get('error')} / RabbitMQ passed; observed: {json.dumps(ours['obs'])[:1500]}"
    a, b = ours["obs"], theirs["obs"]
    if a != b:
        diffs = [f"{(x or y)[0]}: Leveret {json.dumps(x)} / RabbitMQ {json.dumps(y)}"
                 for x, y in (((a[i] if i < len(a) else None), (b[i] if i < len(b) else None)) for i in range(max(len(a), len(b))))
                 if x != y]
        return "fail", "observed differently: " + "; ".join(diffs[:4])
    return "pass", ""


# A policy both brokers load (RabbitMQ with `rabbitmqctl import_definitions`,
# Leveret with `--definitions`), for the scenario `retention.by_policy`.
POLICY = {"vhost": "/", "name": "streams-retention", "pattern": "policy-retained$", "apply-to": "queues",
          "priority": 0, "definition": {"max-length-bytes": 3000, "stream-max-segment-size-bytes": 1000}}


def run(ctx):
    if not ctx.leveret:
        return [("streams", "skip", "needs a leveret of its own beside its RabbitMQ node (not --url)")]
    ctx.ensure_python()
    drivers = [
        [ctx.vpy, os.path.join(ctx.here, "python", "main.py"), "--lib", "streams"],
        ctx.go_driver() + ["--streams"],
    ]
    rabbit = RabbitNode()
    leveret = None
    definitions = tempfile.NamedTemporaryFile("w", suffix=".json", prefix="leveret-conformance-streams-")
    try:
        json.dump({"policies": [POLICY]}, definitions)
        definitions.flush()
        rabbit.load(definitions.name, lambda node: POLICY["name"] in node.ctl("list_policies", "-p", "/").stdout)
        leveret = LeveretNode(ctx.leveret, ["--definitions", definitions.name])
        results = []
        for argv in drivers:
            names = ctx.list_scenarios(argv)
            records = {}
            for broker, port in (("rabbitmq", rabbit.port), ("leveret", leveret.port)):
                prefix = f"st{secrets.token_hex(3)}-"
                found = ctx.run_driver(argv, f"amqp://guest:guest@127.0.0.1:{port}/%2f", prefix, names)
                records[broker] = {n: {**r, "obs": ctx.normalize(r.get("obs", []), prefix)} for n, r in found.items()}
            for name in names:
                missing = {"ok": False, "error": "no result", "obs": []}
                theirs = records["rabbitmq"].get(name, missing)
                status, detail = compare(records["leveret"].get(name, missing), theirs)
                # A scenario that fails on the reference is the suite's
                # fault: reported under its own name, never matched by
                # known-failures.txt.
                tid = name.removeprefix("streams.") + ("" if theirs["ok"] else " (on RabbitMQ)")
                results.append((tid, status, detail))
        return results
    finally:
        if leveret:
            leveret.stop()
        rabbit.stop()
        definitions.close()


SUITES = {
    "streams": ("stream queues, pika + amqp091-go, RabbitMQ 3.10 beside Leveret", run),
}
