#!/usr/bin/env bash
# Issue 33's cold read, A/B, timed by the delivery window: as streams-cold-ab.sh, plus the window.
# One stream of N 1 KiB messages is written once for Leveret (by the first build) and once for
# LavinMQ; then, ROUNDS times, each broker in turn is started on its data, the page cache dropped
# and one lavinmqperf consumer reads the stream from `first` (prefetch 1000, acks by 100). LavinMQ
# is restarted each round too: it reads through mappings, whose pages a page-cache drop cannot
# evict while mapped, so only a fresh process reads cold. Per round: wall time, messages/s (N over
# the wall time; lavinmqperf ends on one-second ticks, so a run of S seconds is known to ~1/S),
# broker user and system CPU a message (/proc/PID/stat), and how busy the disk was (io_ticks).
# lavinmqperf's own times fall on one-second ticks; so each round is also timed by its delivery
# window: `ss` samples the bytes the broker's sockets have had acknowledged every 0.1 s (two
# processes a sample), and the window runs from the first sample that grew by over 1 MiB to the
# last (the handshake and the close before and after it move a few hundred bytes). Rate over the
# window: N / window, which misses up to one sample's worth at its start: about 1% of a 10 s window.
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
# window FILE: samples the bytes acknowledged on the broker's side of connections on $port until
# FILE is gone, then prints the delivery window's start and end (seconds, as date +%s.%N).
window() {
  local prev=0 now t first=0 last=0
  while [ -e "$1" ]; do
    now=$(ss -tinH state established "( sport = :$port )" |
      awk '{for (i = 1; i <= NF; i++) if ($i ~ /^bytes_acked:/) { split($i, f, ":"); n += f[2] } }
           END { print n + 0 }')
    t=$(date +%s.%N)
    if [ $((now - prev)) -gt 1048576 ]; then
      [ "$first" = 0 ] && first=$t
      last=$t
    fi
    prev=$now
    sleep 0.1
  done
  echo "$first $last"
}
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
    touch "$d/sampling"
    window "$d/sampling" >"$d/window" &
    sampler=$!
    perf --queue=stream-cold -x 0 -y 1 -P 1000 -a 100 -D "$N" -z 600 \
      '--queue-args={"x-queue-type":"stream"}' '--consumer-args={"x-stream-offset":"first"}' >/dev/null
    en=$(date +%s.%N)
    rm "$d/sampling"
    wait $sampler
    read -r w0 w1 <"$d/window"
    io1=$(awk -v disk="$disk" '$3==disk {print $13}' /proc/diskstats)
    read -r u1 s1 < <(awk '{print $14" "$15}' /proc/$pid/stat)
    stop
    python3 -c "w=$en-$st; u=($u1-$u0)/$hz/$N*1e6; s=($s1-$s0)/$hz/$N*1e6; win=$w1-$w0
print('round $r %-40s window %6.2f s %8.0f msg/s (wall %6.2f s) cpu %.2f us/msg (user %.2f sys %.2f) disk busy %3.0f%%' % ('$broker', win, $N/win if win > 0 else 0, w, u+s, u, s, ($io1-$io0)/10/w))"
  done
done
