#!/usr/bin/env bash
# Round trip with one core taken by a CPU hog, busy polling on and off,
# against LavinMQ 2.9.1 and RabbitMQ 3.10 in one run (issue 19, item 3).
# Two generators: leveret-perf rtt (one message in flight, 16 B, through two
# queues and an echo client) and lavinmqperf's latency mode (128 B at
# 1 kHz, its own client). Usage: busy-poll-contention.sh [hog]
# (with "hog": one `sha1sum /dev/zero` runs for the whole measurement).
# OLD_LEVERET=path adds that binary with --busy-poll 200 (a build from
# before busy polling yielded to CPU pressure); RABBIT_URL adds RabbitMQ.
set -euo pipefail
cd "$(dirname "$0")/../../.."
LAVIN=/work/shared/anchors/lavinmq
PERF=target/release/leveret-perf
work=$(mktemp -d)
pids=()
cleanup() { kill "${pids[@]}" 2>/dev/null || true; wait 2>/dev/null || true; rm -rf "$work"; }
trap cleanup EXIT

start_leveret() { # port busy-poll-µs [binary]
  "${3:-target/release/leveret}" --listen "127.0.0.1:$1" --mqtt-listen none --data-dir "$work/lv$1" --busy-poll "$2" \
    --metrics-listen 127.0.0.1:0 --http-listen 127.0.0.1:0 --log warn &
  pids+=($!)
}
start_leveret 5801 200
start_leveret 5802 0
"$LAVIN/start" 5803 "$work/lavin" >/dev/null 2>&1 &
pids+=($!)
sleep 3
brokers=("leveret busy-poll 200=amqp://guest:guest@127.0.0.1:5801/%2f"
         "leveret busy-poll 0=amqp://guest:guest@127.0.0.1:5802/%2f"
         "lavinmq 2.9.1=amqp://guest:guest@127.0.0.1:5803/%2f")
if [[ -n "${OLD_LEVERET:-}" ]]; then
  start_leveret 5804 200 "$OLD_LEVERET"
  sleep 1
  brokers+=("leveret busy-poll 200 not yielding=amqp://guest:guest@127.0.0.1:5804/%2f")
fi
if [[ -n "${RABBIT_URL:-}" ]]; then brokers+=("rabbitmq=$RABBIT_URL"); fi

if [[ "${1:-}" == hog ]]; then
  sha1sum /dev/zero & pids+=($!)
  echo "# one CPU hog running (sha1sum /dev/zero)"
fi
for round in 1 2; do
  for entry in "${brokers[@]}"; do
    name=${entry%%=*}; url=${entry#*=}
    rtt=$($PERF --threads 1 rtt --url "$url" --sizes 16 --count 3000 2>&1 | grep -E "^16 B" | tr '\n' ' ')
    lat=$("$LAVIN/lavinmqperf" throughput --uri="$url" -x1 -y1 -s128 -r1000 -z 8 -l -q 2>&1 | grep -E "median|99th" | tr '\n' ' ')
    echo "round $round | $name | leveret-perf rtt 16 B: $rtt | lavinmqperf -s128 -r1000 -l: $lat"
  done
done
