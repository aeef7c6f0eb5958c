#!/usr/bin/env bash
# The durable path, one run: Leveret (release), LavinMQ 2.9.1 and RabbitMQ 3.10 side by side,
# persistent messages to a durable queue with confirms and acks (issue 13 item 5): lavinmqperf's
# -p -c 256 -a 100 -P 1000 with one and with four publishers and consumers, the same with
# leveret-perf-go, and leveret-perf's confirm rows, which add publish-to-confirm latency.
# Output: durable.txt/.json beside this script. Needs: the release build
#   CARGO_TARGET_DIR=/work/target-perf cargo build --release -p leveret-perf -p leveret
# (or set T to another target dir), perf/generators/build-go, each external run on a queue of its own
# (compare's {queue}, deleted after the run, so no backlog carries over), rabbitmq-server, and LavinMQ in
# /work/shared/anchors/lavinmq.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
T=${T:-/work/target-perf/release}
LAVIN=${LAVIN:-/work/shared/anchors/lavinmq}
GO=$here/../../generators/bin/leveret-perf-go
P=$T/leveret-perf
Z=${Z:-10}
d=$(mktemp -d)
cleanup() {
  kill "$lev" 2>/dev/null || true
  pkill -f "$LAVIN/lavinmq" 2>/dev/null || true
  rabbitmqctl -q stop >/dev/null 2>&1 || true
  pkill -f beam.smp 2>/dev/null || true; pkill epmd 2>/dev/null || true
  rm -rf "$d"
}
trap cleanup EXIT
"$T/leveret" --listen 127.0.0.1:5811 --mqtt-listen none --data-dir "$d/lev" --metrics-listen 127.0.0.1:0 --http-listen 127.0.0.1:0 --log warn & lev=$!
"$LAVIN/start" 5812 "$d/lavin" >/dev/null 2>&1 &
rabbitmq-server -detached >/dev/null 2>&1
for i in $(seq 1 60); do rabbitmqctl -q await_startup >/dev/null 2>&1 && break; sleep 1; done
sleep 3
L=amqp://guest:guest@127.0.0.1:5811/%2f
V=amqp://guest:guest@127.0.0.1:5812/%2f
R=amqp://guest:guest@127.0.0.1:5672/%2f
ext=()
for gen in lavinmqperf go; do
  case $gen in
    lavinmqperf) cmd="$LAVIN/lavinmqperf throughput --uri={url} --queue={queue} -s 16 -z $Z -j -q" ;;
    go) cmd="$GO --uri={url} --queue={queue} -s 16 -z $Z -j -q" ;;
  esac
  ext+=(--external "$gen-persistent=$cmd -x 1 -y 1 -p -c 256 -a 100 -P 1000")
  ext+=(--external "$gen-persistent4x4=$cmd -x 4 -y 4 -p -c 256 -a 100 -P 1000")
done
echo "# $(date -u '+%F %H:%M') UTC, leveret $(git -C "$here" rev-parse --short HEAD); $0"
"$P" compare --url "$L" --name leveret --url "$V" --name lavinmq --url "$R" --name rabbitmq \
  --duration "$Z" --warmup 3 --settle 2 --only confirm,confirm4p,lavinmqperf-persistent,lavinmqperf-persistent4x4,go-persistent,go-persistent4x4 \
  "${ext[@]}" --json "$here/durable.json" | tee "$here/durable.txt"
