#!/usr/bin/env bash
# (kept beside its results; run from any directory, as root to drop the page cache)
# streams-streamcpu-cold.sh T MIB MODE: fill a stream of MIB MiB (1 KiB msgs) on Leveret from T (LavinMQ 2.9.1
# with BROKER=lavinmq), drop the page cache (unless NODROP=1), read it from `first` with lavinmqperf -P 1000 -a 100
# as perf/streams' cold read does; prints the broker's CPU a message. MODE: plain | record (perf record -g into
# /tmp/streamcpu/perf.data) | stat (perf stat of its system calls into /tmp/streamcpu/stat.txt)
set -euo pipefail
T=$1; MIB=$2; MODE=${3:-plain}
. "$(cd "$(dirname "$0")/../.." && pwd)/lib/brokers.sh"
d=$(mktemp -d /tmp/leveret-cold.XXXXXX)
trap cleanup EXIT
port=$(free_port)
if [ "${BROKER:-leveret}" = lavinmq ]; then start_lavinmq "$port"; pid=$lavinmq_pid
else start_leveret "$port" leveret; pid=$leveret_pid; fi
mkdir -p /tmp/streamcpu
perf() { "$LAVIN/lavinmqperf" throughput --uri="amqp://guest:guest@127.0.0.1:$port/%2f" -j -q "$@"; }
n=$((MIB * 1024))
perf --queue=stream-cold -x 0 -y 1 -D 1 -P 10 -a 1 -z 2 '--queue-args={"x-queue-type":"stream"}' '--consumer-args={"x-stream-offset":"next"}' >/dev/null
perf --queue=stream-cold -x 1 -y 0 -s 1024 -c 256 -C "$n" -z 300 >/dev/null
sync; [ -n "${NODROP:-}" ] || echo 3 >/proc/sys/vm/drop_caches
t0=$(awk '{print $14 + $15}' /proc/$pid/stat)
case $MODE in
  record) /usr/bin/perf record -F 2000 -g -p "$pid" -o /tmp/streamcpu/perf.data 2>/dev/null & rec=$! ;;
  stat) /usr/bin/perf stat -e 'syscalls:sys_enter_sendto,syscalls:sys_enter_write,syscalls:sys_enter_writev,syscalls:sys_enter_pread64,syscalls:sys_enter_futex,syscalls:sys_enter_epoll_wait,context-switches,syscalls:sys_enter_recvfrom,syscalls:sys_enter_read' -p "$pid" -o /tmp/streamcpu/stat.txt & rec=$! ;;
esac
json=$(perf --queue=stream-cold -x 0 -y 1 -P 1000 -a 100 -D "$n" -z 300 '--queue-args={"x-queue-type":"stream"}' '--consumer-args={"x-stream-offset":"first"}' | tail -1)
t1=$(awk '{print $14 + $15}' /proc/$pid/stat)
[ "$MODE" != plain ] && { kill -INT $rec; wait $rec || true; }
python3 -c "
import json,sys; r=json.loads('''$json'''); n=$n
c=r['avg_consume_rate']*r['elapsed_seconds']
print(f\"cold {n} msgs: {r['elapsed_seconds']:.2f} s {r['avg_consume_rate']:,} msg/s cpu {($t1-$t0)/100/max(c,1)*1e6:.2f} us/msg load $(cut -d' ' -f1 /proc/loadavg)\")"
