//! The effective configuration as `leveretctl environment` shows it (from
//! `GET /api/environment`), as `rabbitmqctl environment` shows the
//! application environment: every setting the binary runs with, from the
//! command line, the config file or the default, under the config file's
//! key names. Secrets stay out: users appear with their tags only,
//! `mqtt-default-pass` and the shovels' and federation upstreams' URIs
//! (which carry passwords) are not shown, only their names.

use crate::config::Settings;
use leveret_broker::{PeerVerification, ResidentMemoryWatermark};
use serde_json::{json, Map, Value};

impl Settings {
    /// The settings as a JSON object keyed by the config file's names.
    pub fn environment(&self) -> Value {
        let limits = &self.limits;
        let (watermark_key, watermark) = match limits.resident_memory_high_watermark {
            ResidentMemoryWatermark::Relative(fraction) => {
                ("vm-memory-high-watermark-relative", json!(fraction))
            }
            ResidentMemoryWatermark::Absolute(bytes) => {
                ("vm-memory-high-watermark-absolute", json!(bytes))
            }
            ResidentMemoryWatermark::Unwatched => {
                ("vm-memory-high-watermark-absolute", Value::Null)
            }
        };
        let names = |named: &[(String, Value)]| -> Vec<String> {
            named.iter().map(|(name, _)| name.clone()).collect()
        };
        let users: Vec<Value> = self
            .users
            .iter()
            .map(|(name, _)| {
                let user_limits = limits.user_limits.get(name);
                json!({
                    "name": name,
                    "tags": self.tags.get(name).cloned().unwrap_or_default(),
                    "max-connections": user_limits.and_then(|l| l.max_connections),
                    "max-channels": user_limits.and_then(|l| l.max_channels),
                })
            })
            .collect();
        let vhost_limits: Map<String, Value> = limits
            .vhost_limits
            .iter()
            .map(|(vhost, l)| {
                (
                    vhost.clone(),
                    json!({"max-connections": l.max_connections, "max-queues": l.max_queues}),
                )
            })
            .collect();
        let policies: Map<String, Value> = self.policies.iter().cloned().collect();
        let tls = self.tls.as_ref();
        let mut environment = json!({
            "config-file": self.config_file,
            "listen": self.listen,
            "tls-listen": self.tls_listen,
            "mqtt-listen": self.mqtt_listen,
            "mqtts-listen": self.mqtts_listen,
            "web-mqtt-listen": self.web_mqtt_listen,
            "mqtt-ssl-cert-login": self.mqtt_ssl_cert_login,
            "mqtt-max-session-expiry-interval-seconds": match self.mqtt_max_session_expiry_interval {
                Some(seconds) => json!(seconds),
                None => json!("infinity"),
            },
            "mqtt-default-user": self.mqtt_anonymous.as_ref().map(|(user, _)| user),
            "tls-certfile": tls.map(|t| &t.certfile),
            "tls-keyfile": tls.map(|t| &t.keyfile),
            "tls-cacertfile": tls.and_then(|t| t.cacertfile.as_ref()),
            "tls-verify": tls.map(|t| match t.verify {
                PeerVerification::None => "verify_none",
                PeerVerification::Optional | PeerVerification::Required => "verify_peer",
            }),
            "tls-fail-if-no-peer-cert": tls.map(|t| t.verify == PeerVerification::Required),
            "data-dir": self.data_dir,
            "log": self.log,
            "log-format": self.log_format,
            "log-file": self.log_file,
            "users": users,
            "vhosts": self.vhosts,
            "loopback-users": self.loopback_users,
            "heartbeat": limits.heartbeat,
            "frame-max": limits.frame_max,
            "channel-max": limits.channel_max,
            "max-message-size": limits.max_message_size,
            "memory-high-watermark": limits.memory_high_watermark,
            "disk-free-limit": limits.disk_free_limit,
            "max-connections": limits.max_connections,
            "handshake-timeout": limits.handshake_timeout.as_millis() as u64,
            "vhost-limits": vhost_limits,
            "product": self.product,
            "busy-poll": self.busy_poll.as_micros() as u64,
            "worker-threads": self.worker_threads,
            "metrics-listen": self.metrics_listen,
            "http-listen": self.http_listen,
            "definitions": self.definitions,
            "recover": self.recover,
            "shovels": names(&self.shovels),
            "federation-upstreams": names(&self.federation_upstreams),
            "policies": policies,
        });
        environment[watermark_key] = watermark;
        environment
    }
}
