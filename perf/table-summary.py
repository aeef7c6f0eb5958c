"""The summary table of perf/table: for each scenario and figure, each broker's median over the
rounds with the spread (min-max), and Leveret's ratio to LavinMQ per round (median, min-max).

usage: python3 table-summary.py BASE ROUNDS   (reads BASE-roundN.json and, if there is one,
BASE-ceilings.json: the `leveret-perf compare --json` files perf/table and perf/worker-threads write)
"""

import json
import statistics
import sys

FIGURES = {
    "publish rate": ("msgs/s", lambda v: f"{v / 1000:,.0f}k"),
    "consume rate": ("msgs/s", lambda v: f"{v / 1000:,.0f}k"),
    "broker CPU per message": ("µs", lambda v: f"{v / 1000:.2f}"),
    "latency p50": ("ms", lambda v: f"{v / 1000:.3f}"),
    "latency p99": ("ms", lambda v: f"{v / 1000:.3f}"),
    "p99": ("µs", lambda v: f"{v:.0f}"),
    "resident memory": ("MB", lambda v: f"{v / 1e6:.1f}"),
}


def load(path):
    with open(path) as f:
        return json.load(f)


def spread(values, show):
    values = [v for v in values if v is not None]
    if not values:
        return "-"
    text = show(statistics.median(values))
    if len(values) > 1:
        text += f" ({show(min(values))}-{show(max(values))})"
    return text


def table(runs, title, figures):
    names = [b["name"] for b in runs[0]["brokers"]]
    base = names.index("lavinmq") if "lavinmq" in names else None
    rows = {}
    for run in runs:
        for fig in run["figures"]:
            if fig["figure"] in figures:
                rows.setdefault((fig["scenario"], fig["figure"]), []).append(fig["values"])
    ratioed = [i for i, n in enumerate(names) if n.startswith("leveret")] if base is not None else []
    head = ["scenario", "figure"] + names + [f"{names[i]}/{names[base]}" for i in ratioed]
    lines = [head]
    for (scenario, figure), per_round in rows.items():
        unit, show = FIGURES[figure]
        line = [scenario, f"{figure} ({unit})"]
        for i in range(len(names)):
            line.append(spread([values[i] for values in per_round], show))
        for i in ratioed:
            ratios = [v[i] / v[base] for v in per_round if v[i] is not None and v[base]]
            line.append(spread(ratios, lambda r: f"{r:.2f}") if ratios else "-")
        lines.append(line)
    widths = [max(len(row[c]) for row in lines) for c in range(len(head))]
    print(f"\n{title}")
    for n, row in enumerate(lines):
        print("  ".join(cell.ljust(widths[c]) for c, cell in enumerate(row)).rstrip())
        if n == 0:
            print("  ".join("-" * w for w in widths))


def main():
    base, rounds = sys.argv[1], int(sys.argv[2])
    runs = [load(f"{base}-round{r}.json") for r in range(1, rounds + 1)]
    table(runs, f"median over {rounds} round(s), (min-max) when more than one; ratio per round", FIGURES)
    try:
        ceilings = load(f"{base}-ceilings.json")
    except FileNotFoundError:  # scripts that compare Leveret with itself measure no ceilings
        return
    table([ceilings], "generators' ceilings: publish rate into the sink, beside Leveret",
          ["publish rate", "consume rate"])


if __name__ == "__main__":
    main()
