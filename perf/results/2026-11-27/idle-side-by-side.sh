#!/usr/bin/env bash
# Idle RSS of Leveret (T: a release build; this run, CI's build of a8d8b7a), LavinMQ 2.9.1 and RabbitMQ 3.10, started side
# by side with their defaults here, read 15 s after each is serving; three rounds.
set -euo pipefail
here=$(cd "$(dirname "$0")/../.." && pwd)
T=${T:-$here/../target/release}
. "$here/lib/brokers.sh"
d=$(mktemp -d /tmp/leveret-idle3.XXXXXX)
trap cleanup EXIT
for round in 1 2 3; do
  lp=$(free_port) vp=$(free_port) rp=$(free_port)
  start_leveret "$lp" "leveret-$round"
  start_lavinmq "$vp"
  start_rabbitmq "$rp"
  sleep 15
  l=$(rss_kb "$leveret_pid") v=$(rss_kb "$lavinmq_pid") r=$(rss_kb "$rabbitmq_pid")
  awk -v l="$l" -v v="$v" -v r="$r" -v n="$round" 'BEGIN { printf "round %d: leveret %.1f MB, lavinmq %.1f MB, rabbitmq %.1f MB; leveret/lavinmq %.2f, leveret/rabbitmq %.3f\n", n, l/1024, v/1024, r/1024, l/v, l/r }'
  cleanup; pids=()
  d=$(mktemp -d /tmp/leveret-idle3.XXXXXX)
done
