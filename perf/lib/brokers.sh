# Sourced by perf scripts (bash): starts the brokers a side-by-side run
# compares, each on free ports with directories of its own under $d, and
# stops them on exit. Leveret from $T (release by default), LavinMQ 2.9.1
# from $LAVIN, and a RabbitMQ 3.10 node of its own (the shared one on 5672
# is never touched).
#
# The sourcing script sets `d` (a scratch directory it owns) and `T`, then
# calls the start_* functions; `pids` holds what `cleanup` kills, and
# *_pid variables the brokers' process ids for CPU and RSS readings.

LAVIN=${LAVIN:-/work/shared/anchors/lavinmq}
RB=/usr/lib/rabbitmq/bin # Debian's scripts run as root, without the su of /usr/sbin's wrappers
pids=()
rabbit_node=leveret-perf-$$@localhost

free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }

await_port() {
  for _ in $(seq 1 100); do (exec 3<>"/dev/tcp/127.0.0.1/$1") 2>/dev/null && return 0; sleep 0.1; done
  echo "nothing listens on port $1" >&2
  return 1
}

rabbit_env() {
  env HOME="$d/rabbit" RABBITMQ_NODENAME="$rabbit_node" RABBITMQ_DIST_PORT="$rdist" \
    RABBITMQ_MNESIA_BASE="$d/rabbit/mnesia" RABBITMQ_LOG_BASE="$d/rabbit/log" \
    RABBITMQ_ENABLED_PLUGINS_FILE="$d/rabbit/enabled_plugins" RABBITMQ_PID_FILE="$d/rabbit/pid" \
    RABBITMQ_CONFIG_FILE="$d/rabbit/rabbitmq" "$@"
}

cleanup() {
  for pid in "${pids[@]}"; do kill "$pid" 2>/dev/null || true; done
  # Only this script's own node: never the shared one on 5672.
  if [ -n "${rabbit:-}" ]; then
    rabbit_env "$RB/rabbitmqctl" -q -n "$rabbit_node" stop >/dev/null 2>&1 ||
      { [ -f "$d/rabbit/pid" ] && kill "$(cat "$d/rabbit/pid")" 2>/dev/null; }
  fi
  rm -rf "$d"
}

# start_leveret PORT NAME [ARGS...]: Leveret on PORT, data in $d/NAME; sets leveret_pid.
start_leveret() {
  "$T/leveret" --listen "127.0.0.1:$1" --data-dir "$d/$2" --metrics-listen 127.0.0.1:0 \
    --http-listen 127.0.0.1:0 --mqtt-listen none --log warn "${@:3}" >"$d/$2.log" 2>&1 &
  leveret_pid=$!
  pids+=("$leveret_pid")
  await_port "$1"
}

# start_lavinmq PORT [MQTT_PORT]: LavinMQ on PORT (and MQTT 3.1.1 on MQTT_PORT), data in
# $d/lavin; sets lavinmq_pid. As the anchor's own `start` script runs it, with MQTT optional.
start_lavinmq() {
  GC_UNMAP_THRESHOLD=1 "$LAVIN/lavinmq" --data-dir "$d/lavin" --bind 127.0.0.1 --amqp-port "$1" \
    --http-port -1 --mqtt-port "${2:--1}" --mqtts-port -1 --metrics-http-port -1 --clustering-port 0 \
    --control-unix-path "$d/lavin.ctl.sock" >"$d/lavin.log" 2>&1 &
  lavinmq_pid=$!
  pids+=("$lavinmq_pid")
  await_port "$1"
}

# start_rabbitmq PORT [MQTT_PORT]: a RabbitMQ node of this script's own on PORT (and with its
# MQTT plugin on MQTT_PORT, anonymous logins as guest); sets rabbitmq_pid.
start_rabbitmq() {
  rdist=$(($1 + 10000))
  [ $rdist -lt 65535 ] || rdist=$(($1 - 10000))
  mkdir -p "$d/rabbit"
  printf 'listeners.tcp.1 = 127.0.0.1:%s\nloopback_users = none\n' "$1" >"$d/rabbit/rabbitmq.conf"
  if [ -n "${2:-}" ]; then
    echo '[rabbitmq_mqtt].' >"$d/rabbit/enabled_plugins"
    printf 'mqtt.listeners.tcp.1 = 127.0.0.1:%s\n' "$2" >>"$d/rabbit/rabbitmq.conf"
  else
    echo '[].' >"$d/rabbit/enabled_plugins"
  fi
  # More open files than a shell's 1,024 (RabbitMQ's memory monitor crashes without, perf/README).
  (ulimit -n 65536 2>/dev/null || true; rabbit_env setsid "$RB/rabbitmq-server") >"$d/rabbit.out" 2>&1 &
  rabbit=$!
  # await_startup fails at once while the node is not yet known to epmd: retry while it boots.
  for try in $(seq 1 60); do
    rabbit_env "$RB/rabbitmqctl" -q -n "$rabbit_node" await_startup --timeout 30 >/dev/null 2>&1 && break
    if ! kill -0 "$rabbit" 2>/dev/null || [ "$try" = 60 ]; then
      echo "RabbitMQ did not start:" >&2
      tail -20 "$d/rabbit.out" >&2
      return 1
    fi
    sleep 2
  done
  rabbitmq_pid=$(cat "$d/rabbit/pid")
  await_port "$1"
}

# start_mosquitto PORT: Debian's Mosquitto 2.0 with its defaults and anonymous logins on PORT,
# its files in $d/mosquitto; sets mosquitto_pid.
start_mosquitto() {
  mkdir -p "$d/mosquitto"
  chmod 755 "$d" "$d/mosquitto" # it drops root for its own user
  printf 'listener %s 127.0.0.1\nallow_anonymous true\n' "$1" >"$d/mosquitto/mosquitto.conf"
  /usr/sbin/mosquitto -c "$d/mosquitto/mosquitto.conf" >"$d/mosquitto.log" 2>&1 &
  mosquitto_pid=$!
  pids+=("$mosquitto_pid")
  await_port "$1"
}

# cpu_ticks PID: user + system clock ticks the process has used.
cpu_ticks() { awk '{print $14 + $15}' "/proc/$1/stat"; }

# rss_kb PID: its resident set now, KiB.
rss_kb() { awk '/^VmRSS/ {print $2}' "/proc/$1/status"; }
