"""The semantics suite (issue 30): one definitions file
(semantics/definitions.json: queues with arguments, a single active
consumer queue, policies matching name suffixes, an exchange policy, an
operator policy) loaded into a RabbitMQ 3.10 node of the suite's own
(with its management plugin, `rabbitmqctl import_definitions`) and into a
Leveret (`--definitions`); then pika (python/s_semantics.py, `main.py
--lib semantics`), amqplib (js/semantics.js, `main.js --semantics`) and
amqp091-go (go/.../semantics.go, `conformance-go --semantics`: argument
equivalence of queues the definitions and the API made) run the same
steps against both, with the broker's management API
(`--http`) for what an operator does meanwhile (policies set and cleared,
listings read). A scenario passes when it passes on both brokers and the
client observed the same things on both (run prefixes and
server-generated names aside).

The runner takes a Ctx with `leveret` (the binary; None when the runner
was given --url, and the suite is then skipped), `run_driver`,
`normalize` and `list_scenarios` from conformance/run, and returns [(test_id, status, detail)] like the
upstream runners.
"""

import os
import secrets

from nodes import LeveretNode, RabbitNode, SetupError, free_port, wait_port
from streams import compare


def run(ctx):
    if not ctx.leveret:
        return [("semantics", "skip", "needs a leveret of its own with the suite's definitions (not --url)")]
    ctx.ensure_python()
    ctx.ensure_node()
    definitions = os.path.join(ctx.here, "semantics", "definitions.json")
    drivers = [
        [ctx.vpy, os.path.join(ctx.here, "python", "main.py"), "--lib", "semantics"],
        ["node", os.path.join(ctx.here, "js", "main.js"), "--semantics"],
        ctx.go_driver() + ["--semantics"],
    ]
    rabbit_http = free_port()
    # Statistics every 100 ms (RabbitMQ's default is 5 s): its listings
    # show a queue's policy from them.
    rabbit = RabbitNode(conf=[f"management.tcp.port = {rabbit_http}", "management.tcp.ip = 127.0.0.1",
                              "collect_statistics_interval = 100"],
                        plugins=["rabbitmq_management"])
    leveret = None
    try:
        if not wait_port(rabbit_http, 60):
            raise SetupError("RabbitMQ's management listener did not open")
        # The import is asynchronous: its last item is the operator policy.
        rabbit.load(definitions, lambda node: "sem-op" in node.ctl("list_operator_policies", "-p", "/").stdout)
        leveret_http = free_port()
        leveret = LeveretNode(ctx.leveret, ["--definitions", definitions, "--http-listen", f"127.0.0.1:{leveret_http}"],
                              wait_for=leveret_http)
        brokers = (("rabbitmq", rabbit.port, rabbit_http), ("leveret", leveret.port, leveret_http))
        results = []
        for argv in drivers:
            names = ctx.list_scenarios(argv)
            records = {}
            for broker, port, http in brokers:
                prefix = f"se{secrets.token_hex(3)}-"
                found = ctx.run_driver(argv + ["--http", f"http://127.0.0.1:{http}"],
                                       f"amqp://guest:guest@127.0.0.1:{port}/%2f", prefix, names)
                records[broker] = {n: {**r, "obs": ctx.normalize(r.get("obs", []), prefix)} for n, r in found.items()}
            for name in names:
                missing = {"ok": False, "error": "no result", "obs": []}
                theirs = records["rabbitmq"].get(name, missing)
                status, detail = compare(records["leveret"].get(name, missing), theirs)
                # A scenario that fails on the reference is the suite's
                # fault: reported under its own name, never matched by
                # known-failures.txt.
                tid = name.removeprefix("semantics.") + ("" if theirs["ok"] else " (on RabbitMQ)")
                results.append((tid, status, detail))
        return results
    finally:
        if leveret:
            leveret.stop()
        rabbit.stop()


SUITES = {
    "semantics": ("policies, SAC, priorities, equivalence, refusals: pika + amqplib + amqp091-go, RabbitMQ 3.10 beside Leveret", run),
}
