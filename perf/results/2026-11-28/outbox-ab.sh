#!/usr/bin/env bash
# The outbox's queue, A/B: Leveret builds against each other, alternating, each started afresh per
# scenario on an empty data directory; lavinmqperf (LAVIN, default /work/shared/anchors/lavinmq)
# drives it for Z seconds. Per run: consumed msgs/s (lavinmqperf's average) and the broker's CPU
# (user + system, /proc/PID/stat) per consumed message.
#
# usage: outbox-ab.sh LEVERET-BINARY...   ROUNDS (default 3), Z (default 8)
set -euo pipefail
[ $# -ge 1 ] || { echo "usage: $0 LEVERET-BINARY..." >&2; exit 2; }
LAVIN=${LAVIN:-/work/shared/anchors/lavinmq}; ROUNDS=${ROUNDS:-3}; Z=${Z:-8}
hz=$(getconf CLK_TCK); d=$(mktemp -d /tmp/leveret-outbox-ab.XXXXXX); port=5697
pid=
trap '[ -n "$pid" ] && kill $pid 2>/dev/null; rm -rf "$d"' EXIT
scenarios=(
  "no-ack|-x1 -y1 -s16"
  "acks|-x1 -y1 -s16 -a 100 -P 1000"
  "4x4 no-ack|-x4 -y4 -s16"
  "persistent confirms acks|-x1 -y1 -s16 -p -c 256 -a 100 -P 1000"
)
echo "# $(date -u '+%F %H:%M') UTC; $(nproc) cores, load $(cut -d' ' -f1-3 /proc/loadavg); $Z s a run"
for b in "$@"; do echo "# $b: sha256 $(sha256sum "$b" | cut -c1-12)"; done
for r in $(seq "$ROUNDS"); do
  for s in "${scenarios[@]}"; do
    name=${s%%|*}; flags=${s#*|}
    for b in "$@"; do
      rm -rf "$d/data"
      "$b" --listen 127.0.0.1:$port --data-dir "$d/data" --metrics-listen 127.0.0.1:0 \
        --http-listen 127.0.0.1:0 --mqtt-listen none --log error >>"$d/leveret.log" 2>&1 &
      pid=$!
      until (echo >/dev/tcp/127.0.0.1/$port) 2>/dev/null; do sleep 0.1; done
      read -r u0 s0 < <(awk '{print $14" "$15}' /proc/$pid/stat)
      # shellcheck disable=SC2086
      json=$("$LAVIN/lavinmqperf" throughput --uri="amqp://guest:guest@127.0.0.1:$port/%2f" -j -q \
        $flags -z "$Z" 2>/dev/null | grep -o '{.*}' | tail -1)
      read -r u1 s1 < <(awk '{print $14" "$15}' /proc/$pid/stat)
      kill $pid; wait $pid 2>/dev/null || true; pid=
      python3 -c "import json; j=json.loads('$json'); c=j['avg_consume_rate']; n=c*j['elapsed_seconds']
print('round $r %-26s %-28s consumed %8d msg/s  cpu %.2f us/msg' % ('$name', '$b', c, (($u1-$u0)+($s1-$s0))/$hz/max(n,1)*1e6))"
    done
  done
done
