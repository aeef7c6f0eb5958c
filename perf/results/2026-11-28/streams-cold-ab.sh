#!/usr/bin/env bash
# Issue 33's cold read, A/B: Leveret builds against each other and LavinMQ 2.9.1, alternating.
# One stream of N 1 KiB messages is written once for Leveret (by the first build) and once for
# LavinMQ; then, ROUNDS times, each broker in turn is started on its data, the page cache dropped
# and one lavinmqperf consumer reads the stream from `first` (prefetch 1000, acks by 100). LavinMQ
# is restarted each round too: it reads through mappings, whose pages a page-cache drop cannot
# evict while mapped, so only a fresh process reads cold. Per round: wall time, messages/s (N over
# the wall time; lavinmqperf ends on one-second ticks, so a run of S seconds is known to ~1/S),
# broker user and system CPU a message (/proc/PID/stat), and how busy the disk was (io_ticks).
#
# usage: streams-cold-ab.sh LEVERET-BINARY... (root, to drop the page cache)
#   N (default 4194304, 4 GiB), ROUNDS (default 3), LAVIN (default /work/shared/anchors/lavinmq)
set -euo pipefail
[ $# -ge 1 ] || { echo "usage: $0 LEVERET-BINARY..." >&2; exit 2; }
LAVIN=${LAVIN:-/work/shared/anchors/lavinmq}; N=${N:-4194304}; ROUNDS=${ROUNDS:-3}
hz=$(getconf CLK_TCK); d=$(mktemp -d /tmp/leveret-cold-ab.XXXXXX); port=5699
disk=$(lsblk -no pkname "$(findmnt -no source -T "$d")" 2>/dev/null || true)
disk=${disk:-$(basename "$(findmnt -no source -T "$d")")}
pid=
trap '[ -n "$pid" ] && kill $pid 2>/dev/null; rm -rf "$d"' EXIT
perf() { "$LAVIN/lavinmqperf" throughput --uri="amqp://guest:guest@127.0.0.1:$port/%2f" -j -q "$@"; }
start() { # start BINARY|lavinmq: sets pid
  if [ "$1" = lavinmq ]; then
    GC_UNMAP_THRESHOLD=1 "$LAVIN/lavinmq" --data-dir "$d/lavin" --bind 127.0.0.1 --amqp-port $port \
      --http-port -1 --mqtt-port -1 --mqtts-port -1 --metrics-http-port -1 --clustering-port 0 \
      --control-unix-path "$d/lavin.ctl.sock" >>"$d/lavin.log" 2>&1 &
  else
    "$1" --listen 127.0.0.1:$port --data-dir "$d/leveret" --metrics-listen 127.0.0.1:0 \
      --http-listen 127.0.0.1:0 --mqtt-listen none --log warn >>"$d/leveret.log" 2>&1 &
  fi
  pid=$!
  until (echo >/dev/tcp/127.0.0.1/$port) 2>/dev/null; do sleep 0.1; done
}
stop() { kill $pid; wait $pid 2>/dev/null || true; pid=; }
for broker in "$1" lavinmq; do
  start "$broker"
  perf --queue=stream-cold -x 0 -y 1 -D 1 -P 10 -a 1 -z 2 '--queue-args={"x-queue-type":"stream"}' \
    '--consumer-args={"x-stream-offset":"next"}' >/dev/null
  perf --queue=stream-cold -x 1 -y 0 -s 1024 -c 256 -C "$N" -z 600 >/dev/null
  stop
done
echo "# $(date -u '+%F %H:%M') UTC; $N messages of 1 KiB, cold; $(nproc) cores, load $(cut -d' ' -f1-3 /proc/loadavg); disk $disk"
for b in "$@"; do echo "# $b: $("$b" --version 2>/dev/null | head -1) sha256 $(sha256sum "$b" | cut -c1-12)"; done
for r in $(seq "$ROUNDS"); do
  for broker in "$@" lavinmq; do
    start "$broker"
    sync; echo 3 >/proc/sys/vm/drop_caches
    read -r u0 s0 < <(awk '{print $14" "$15}' /proc/$pid/stat)
    io0=$(awk -v disk="$disk" '$3==disk {print $13}' /proc/diskstats); st=$(date +%s.%N)
    perf --queue=stream-cold -x 0 -y 1 -P 1000 -a 100 -D "$N" -z 600 \
      '--queue-args={"x-queue-type":"stream"}' '--consumer-args={"x-stream-offset":"first"}' >/dev/null
    en=$(date +%s.%N); io1=$(awk -v disk="$disk" '$3==disk {print $13}' /proc/diskstats)
    read -r u1 s1 < <(awk '{print $14" "$15}' /proc/$pid/stat)
    stop
    python3 -c "w=$en-$st; u=($u1-$u0)/$hz/$N*1e6; s=($s1-$s0)/$hz/$N*1e6
print('round $r %-40s wall %6.2f s %8.0f msg/s cpu %.2f us/msg (user %.2f sys %.2f) disk busy %3.0f%%' % ('$broker', w, $N/w, u+s, u, s, ($io1-$io0)/10/w))"
  done
done
