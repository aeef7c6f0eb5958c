//! Federation downstream: an exchange of an upstream broker (the fleet's
//! RabbitMQ) federated to a local exchange, as RabbitMQ's federation
//! plugin does it from the downstream side, so that commands and maps the
//! fleet publishes reach the robot's own bindings.
//!
//! A link declares on the upstream a durable queue of its own
//! (`federation: EXCHANGE -> NODE:VHOST:LOCAL`, with `expires` and
//! `message-ttl` as its `x-expires` and `x-message-ttl`), binds it to the
//! upstream exchange with the binding keys (and arguments) of the local
//! exchange's bindings, kept in step once a second (binding propagation:
//! only what some local binding wants crosses the link), consumes it
//! with `prefetch-count` and republishes each message to the local
//! exchange with an entry appended to its `x-received-from` header
//! (`uri`, `exchange`, `redelivered`, `cluster-name`), as RabbitMQ does.
//! A message that already went through `max-hops` links, or through this
//! node, is dropped (acknowledged and counted): loops end. Under
//! `on-confirm` (the default) the upstream message is acknowledged only
//! after the local broker confirmed it; while the link is down, what the
//! fleet publishes waits in the upstream queue.
//!
//! After a failure the link waits `reconnect-delay` (with the shovel's
//! backoff and jitter) and tries the upstream URIs in turn. Uses the
//! client crate for both ends (the local broker in process) and the
//! broker's `Admin` for the local bindings.

use crate::config::{ack_mode, prefetch, reconnect_delay, uris, AckMode};
use crate::shovel::{backoff, shown};
use leveret_broker::BrokerHandle;
use leveret_client::{
    BasicAckOptions, BasicConsumeOptions, BasicProperties, BasicPublishOptions, BasicQosOptions,
    Channel, ConfirmFuture, Connection, ExchangeDeclareOptions, FieldTable, FieldValue,
    QueueBindOptions, QueueDeclareOptions, ShortStr,
};
use serde_json::{Map, Value};
use std::collections::{BTreeMap, VecDeque};
use std::future::IntoFuture;
use std::sync::{Arc, Weak};
use std::time::Duration;
use tokio::sync::watch;

/// The header listing the links a message came through.
pub const RECEIVED_FROM: &str = "x-received-from";

/// How often the local bindings are compared with the upstream's.
const BINDING_SYNC: Duration = Duration::from_secs(1);

/// An upstream's parameters, with RabbitMQ's `federation-upstream` names
/// and defaults.
#[derive(Debug, Clone, PartialEq)]
pub struct UpstreamConfig {
    /// The upstream brokers (`uri`, one or a list: a cluster's nodes,
    /// tried in turn).
    pub uris: Vec<String>,
    /// The upstream exchange (`exchange`; by default the local exchange's
    /// name).
    pub exchange: Option<String>,
    /// Links a message may come through before it is dropped
    /// (`max-hops`, default 1).
    pub max_hops: u32,
    /// Unacknowledged messages the link holds (`prefetch-count`, default
    /// 1000).
    pub prefetch: u16,
    /// Wait before reconnecting (`reconnect-delay`, default 5 s).
    pub reconnect_delay: Duration,
    /// When the upstream message is acknowledged (`ack-mode`).
    pub ack_mode: AckMode,
    /// The upstream queue's `x-expires`, ms (`expires`; none by default:
    /// it waits for the robot forever).
    pub expires: Option<u64>,
    /// The upstream queue's `x-message-ttl`, ms (`message-ttl`).
    pub message_ttl: Option<u64>,
    /// Keep the messages' `user-id` (`trust-user-id`, default false: it
    /// is removed, since the local broker checks it against the link's
    /// user).
    pub trust_user_id: bool,
}

fn millis(object: &Map<String, Value>, key: &str) -> Result<Option<u64>, String> {
    match object.get(key) {
        None | Some(Value::Null) => Ok(None),
        Some(n) => n
            .as_u64()
            .filter(|n| *n > 0)
            .map(Some)
            .ok_or_else(|| format!("{key} must be a positive number of milliseconds")),
    }
}

impl UpstreamConfig {
    /// Reads RabbitMQ's JSON form of a `federation-upstream` parameter
    /// (`rabbitmqctl set_parameter federation-upstream NAME '{...}'`).
    /// Keys Leveret does not implement are refused with a reason.
    pub fn from_json(value: &Value) -> Result<UpstreamConfig, String> {
        let object = value
            .as_object()
            .ok_or("an upstream's parameters must be a JSON object")?;
        for key in object.keys() {
            match key.as_str() {
                "uri" | "exchange" | "max-hops" | "prefetch-count" | "reconnect-delay"
                | "ack-mode" | "expires" | "message-ttl" | "trust-user-id" => {}
                "queue" | "consumer-tag" => {
                    return Err(format!(
                        "{key}: queue federation is not supported (exchange federation only)"
                    ))
                }
                other => return Err(format!("{other} is not supported")),
            }
        }
        let uris = uris(object, "uri")?;
        let exchange = match object.get("exchange") {
            None | Some(Value::Null) => None,
            Some(Value::String(s)) => Some(s.clone()),
            Some(other) => return Err(format!("exchange must be a string, not {other}")),
        };
        let max_hops = match object.get("max-hops") {
            None => 1,
            Some(n) => n
                .as_u64()
                .and_then(|n| u32::try_from(n).ok())
                .filter(|n| *n > 0)
                .ok_or("max-hops must be a positive integer")?,
        };
        let prefetch = prefetch(object, "prefetch-count")?;
        let reconnect_delay = reconnect_delay(object)?;
        let ack_mode = ack_mode(object)?;
        let trust_user_id = match object.get("trust-user-id") {
            None => false,
            Some(Value::Bool(b)) => *b,
            Some(_) => return Err("trust-user-id must be true or false".into()),
        };
        Ok(UpstreamConfig {
            uris,
            exchange,
            max_hops,
            prefetch,
            reconnect_delay,
            ack_mode,
            expires: millis(object, "expires")?,
            message_ttl: millis(object, "message-ttl")?,
            trust_user_id,
        })
    }
}

/// The local end of a link.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LocalExchange {
    /// Its vhost.
    pub vhost: String,
    /// Its name.
    pub exchange: String,
    /// This node's name (`leveret@HOST`): names the upstream queue and
    /// marks messages that come back.
    pub node: String,
}

/// RabbitMQ's federation link states.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum LinkState {
    /// Connecting.
    #[default]
    Starting,
    /// Consuming from the upstream.
    Running,
    /// Waiting to reconnect after a failure.
    Error,
    /// Stopped.
    Terminated,
}

impl LinkState {
    /// RabbitMQ's name for it (`/api/federation-links`' `status`).
    pub fn as_str(self) -> &'static str {
        match self {
            LinkState::Starting => "starting",
            LinkState::Running => "running",
            LinkState::Error => "error",
            LinkState::Terminated => "terminated",
        }
    }
}

/// What a link is doing and has done.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct LinkStatus {
    /// Its state.
    pub state: LinkState,
    /// The upstream URI it is connected to (without credentials).
    pub upstream: Option<String>,
    /// The last failure, if any.
    pub last_error: Option<String>,
    /// Messages republished locally.
    pub forwarded: u64,
    /// Messages dropped for having come through `max-hops` links or this
    /// node already.
    pub dropped_hops: u64,
    /// Binding keys bound upstream now.
    pub bindings: usize,
}

/// A federation link running on the current tokio runtime.
#[derive(Debug)]
pub struct FederationLink {
    status: watch::Receiver<LinkStatus>,
    stop: watch::Sender<bool>,
    task: tokio::task::JoinHandle<()>,
}

impl FederationLink {
    /// Starts federating `config`'s upstream exchange to `local` of
    /// `broker`.
    pub fn start(
        upstream_name: &str,
        config: UpstreamConfig,
        local: LocalExchange,
        broker: &Arc<BrokerHandle>,
    ) -> FederationLink {
        let (status_tx, status) = watch::channel(LinkStatus::default());
        let (stop, stopped) = watch::channel(false);
        let link = Link {
            upstream_name: upstream_name.to_owned(),
            config,
            local,
            broker: Arc::downgrade(broker),
            status: status_tx,
            next_uri: 0,
        };
        FederationLink {
            status,
            stop,
            task: tokio::spawn(link.run(stopped)),
        }
    }

    /// What it is doing now.
    pub fn status(&self) -> LinkStatus {
        self.status.borrow().clone()
    }

    /// Its status as it changes.
    pub fn watch(&self) -> watch::Receiver<LinkStatus> {
        self.status.clone()
    }

    /// Stops it: unacknowledged messages go back to the upstream queue,
    /// which stays (with its bindings) so nothing published meanwhile is
    /// lost.
    pub async fn stop(self) {
        let _ = self.stop.send(true);
        let _ = self.task.await;
    }
}

struct Link {
    upstream_name: String,
    config: UpstreamConfig,
    local: LocalExchange,
    broker: Weak<BrokerHandle>,
    status: watch::Sender<LinkStatus>,
    next_uri: usize,
}

/// A binding as compared between the two ends: its key and its encoded
/// arguments.
type BindingKey = (String, Vec<u8>);

fn binding_key(routing_key: &str, arguments: &FieldTable) -> BindingKey {
    let mut encoded = bytes::BytesMut::new();
    arguments.encode(&mut encoded);
    (routing_key.to_owned(), encoded.to_vec())
}

impl Link {
    fn update(&self, change: impl FnOnce(&mut LinkStatus)) {
        self.status.send_modify(change);
    }

    fn upstream_exchange(&self) -> &str {
        self.config
            .exchange
            .as_deref()
            .unwrap_or(&self.local.exchange)
    }

    async fn run(mut self, mut stop: watch::Receiver<bool>) {
        let mut failures = 0u32;
        loop {
            self.update(|s| s.state = LinkState::Starting);
            let forwarded_before = self.status.borrow().forwarded;
            let failure = tokio::select! {
                failure = self.link() => failure,
                _ = stop.wait_for(|stopped| *stopped) => break,
            };
            if self.status.borrow().forwarded > forwarded_before {
                failures = 0;
            }
            failures = failures.saturating_add(1);
            let delay = backoff(self.config.reconnect_delay, failures);
            tracing::warn!(upstream = %self.upstream_name, exchange = %self.local.exchange, error = %failure, retry_in = ?delay, "federation link down");
            self.update(|s| {
                s.state = LinkState::Error;
                s.last_error = Some(failure);
                s.upstream = None;
                s.bindings = 0;
            });
            tokio::select! {
                _ = tokio::time::sleep(delay) => {}
                _ = stop.wait_for(|stopped| *stopped) => break,
            }
        }
        self.update(|s| s.state = LinkState::Terminated);
    }

    /// The first upstream that answers, starting after the last that
    /// failed.
    async fn connect_upstream(&mut self) -> Result<(Connection, String), String> {
        let uris = self.config.uris.clone();
        let mut last = String::new();
        for attempt in 0..uris.len() {
            let index = (self.next_uri + attempt) % uris.len();
            match Connection::connect(&uris[index]).await {
                Ok(connection) => {
                    self.next_uri = index;
                    return Ok((connection, shown(&uris[index])));
                }
                Err(e) => last = format!("{}: {e}", shown(&uris[index])),
            }
        }
        self.next_uri = (self.next_uri + 1) % uris.len();
        Err(last)
    }

    /// Runs one link until it fails; the failure.
    async fn link(&mut self) -> String {
        match self.forward().await {
            Ok(never) => match never {},
            Err(failure) => failure,
        }
    }

    async fn forward(&mut self) -> Result<std::convert::Infallible, String> {
        let e = |e: leveret_client::Error| e.to_string();
        let broker = self.broker.upgrade().ok_or("no local broker")?;
        let admin = broker.admin();
        let local_options = leveret_client::ConnectionOptions {
            vhost: self.local.vhost.clone(),
            ..Default::default()
        };
        let local_connection = Connection::in_process_with(&broker, local_options)
            .await
            .map_err(e)?;
        drop(broker);
        let (upstream_connection, upstream_uri) = self.connect_upstream().await?;
        let cluster_name = upstream_connection
            .server_properties()
            .get("cluster_name")
            .and_then(FieldValue::as_bytes)
            .map(|b| String::from_utf8_lossy(b).into_owned())
            .unwrap_or_else(|| upstream_uri.clone());
        let upstream = upstream_connection.open_channel().await.map_err(e)?;
        let exchange = self.upstream_exchange().to_owned();
        upstream
            .exchange_declare(
                exchange.as_str(),
                "direct",
                ExchangeDeclareOptions {
                    passive: true,
                    ..Default::default()
                },
                FieldTable::new(),
            )
            .await
            .map_err(|err| format!("upstream exchange '{exchange}': {err}"))?;
        let upstream = upstream_connection.open_channel().await.map_err(e)?;
        let queue = format!(
            "federation: {exchange} -> {}:{}:{}",
            self.local.node, self.local.vhost, self.local.exchange
        );
        let mut arguments = FieldTable::new();
        if let Some(ms) = self.config.expires {
            arguments.insert(
                ShortStr::from_static("x-expires"),
                FieldValue::I64(ms as i64),
            );
        }
        if let Some(ms) = self.config.message_ttl {
            arguments.insert(
                ShortStr::from_static("x-message-ttl"),
                FieldValue::I64(ms as i64),
            );
        }
        upstream
            .queue_declare(
                queue.as_str(),
                QueueDeclareOptions {
                    durable: true,
                    ..Default::default()
                },
                arguments,
            )
            .await
            .map_err(e)?;
        let mut bound: BTreeMap<BindingKey, (String, FieldTable)> = BTreeMap::new();
        self.sync_bindings(&admin, &upstream, &queue, &exchange, &mut bound)
            .await?;
        upstream
            .basic_qos(self.config.prefetch, BasicQosOptions::default())
            .await
            .map_err(e)?;
        let no_ack = self.config.ack_mode == AckMode::NoAck;
        let mut deliveries = upstream
            .basic_consume(
                queue.as_str(),
                "",
                BasicConsumeOptions {
                    no_ack,
                    ..Default::default()
                },
                FieldTable::new(),
            )
            .await
            .map_err(e)?;
        let local = local_connection.open_channel().await.map_err(e)?;
        let confirms = self.config.ack_mode == AckMode::OnConfirm;
        if confirms {
            local.confirm_select().await.map_err(e)?;
        }
        tracing::info!(upstream = %self.upstream_name, %upstream_uri, %exchange, local = %self.local.exchange, "federation link running");
        self.update(|s| {
            s.state = LinkState::Running;
            s.upstream = Some(upstream_uri.clone());
        });
        let mut inflight: VecDeque<(u64, ConfirmFuture)> = VecDeque::new();
        let window = usize::from(self.config.prefetch);
        let mut sync = tokio::time::interval(BINDING_SYNC);
        sync.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tokio::select! {
                biased;
                confirmation = async { (&mut inflight.front_mut().expect("guarded").1).await },
                    if !inflight.is_empty() =>
                {
                    let (tag, _) = inflight.pop_front().expect("guarded");
                    if !confirmation.map_err(e)?.is_ack() {
                        return Err("the local broker refused a message (left upstream)".into());
                    }
                    upstream.basic_ack(tag, BasicAckOptions::default()).await.map_err(e)?;
                    self.update(|s| s.forwarded += 1);
                }
                delivery = deliveries.next(), if inflight.len() < window => {
                    let Some(delivery) = delivery else {
                        return Err(format!("the upstream stopped delivering from '{queue}'"));
                    };
                    let hops = received_from(&delivery.properties);
                    let looped = hops.iter().any(|hop| hop.cluster_name.as_deref() == Some(self.local.node.as_str()));
                    if hops.len() as u64 >= u64::from(self.config.max_hops) || looped {
                        if !no_ack {
                            upstream.basic_ack(delivery.delivery_tag, BasicAckOptions::default()).await.map_err(e)?;
                        }
                        self.update(|s| s.dropped_hops += 1);
                        continue;
                    }
                    let properties = self.received(delivery.properties, &upstream_uri, &exchange, delivery.redelivered, &cluster_name);
                    let confirm = local
                        .basic_publish(
                            self.local.exchange.as_str(),
                            delivery.routing_key.clone(),
                            BasicPublishOptions::default(),
                            properties,
                            delivery.body,
                        )
                        .await
                        .map_err(e)?;
                    match self.config.ack_mode {
                        AckMode::OnConfirm => inflight.push_back((delivery.delivery_tag, confirm.into_future())),
                        AckMode::OnPublish => {
                            upstream.basic_ack(delivery.delivery_tag, BasicAckOptions::default()).await.map_err(e)?;
                            self.update(|s| s.forwarded += 1);
                        }
                        AckMode::NoAck => self.update(|s| s.forwarded += 1),
                    }
                }
                _ = sync.tick() => {
                    self.sync_bindings(&admin, &upstream, &queue, &exchange, &mut bound).await?;
                }
                error = upstream.closed() => return Err(format!("upstream: {error}")),
                error = local.closed() => return Err(format!("local: {error}")),
            }
        }
    }

    /// Binds the upstream queue with every (key, arguments) the local
    /// exchange's bindings have and `bound` lacks, and unbinds what no
    /// local binding wants any more.
    async fn sync_bindings(
        &self,
        admin: &leveret_broker::Admin,
        upstream: &Channel,
        queue: &str,
        exchange: &str,
        bound: &mut BTreeMap<BindingKey, (String, FieldTable)>,
    ) -> Result<(), String> {
        // Reading the local bindings and comparing them grows with their
        // number: on the blocking pool, not the broker's thread.
        let admin = admin.clone();
        let (vhost, name) = (self.local.vhost.clone(), self.local.exchange.clone());
        let mut kept = std::mem::take(bound);
        let (kept, gone, wanted) = tokio::task::spawn_blocking(move || {
            let local = admin
                .binding_keys_from(&vhost, &name)
                .ok_or_else(|| format!("no local exchange '{name}' in vhost '{vhost}'"))?;
            let mut wanted: BTreeMap<BindingKey, (String, FieldTable)> = local
                .into_iter()
                .map(|(key, arguments)| (binding_key(&key, &arguments), (key, arguments)))
                .collect();
            let gone_keys: Vec<BindingKey> = kept
                .keys()
                .filter(|k| !wanted.contains_key(*k))
                .cloned()
                .collect();
            let gone: Vec<(String, FieldTable)> = gone_keys
                .iter()
                .filter_map(|key| kept.remove(key))
                .collect();
            wanted.retain(|key, _| !kept.contains_key(key));
            Ok::<_, String>((kept, gone, wanted))
        })
        .await
        .map_err(|e| e.to_string())??;
        *bound = kept;
        for (routing_key, arguments) in gone {
            upstream
                .queue_unbind(queue, exchange, routing_key.as_str(), arguments)
                .await
                .map_err(|e| e.to_string())?;
        }
        for (key, (routing_key, arguments)) in wanted {
            upstream
                .queue_bind(
                    queue,
                    exchange,
                    routing_key.as_str(),
                    QueueBindOptions::default(),
                    arguments.clone(),
                )
                .await
                .map_err(|e| e.to_string())?;
            bound.insert(key, (routing_key, arguments));
        }
        let count = bound.len();
        self.update(|s| s.bindings = count);
        Ok(())
    }

    /// The message's properties with this link's `x-received-from` entry
    /// appended (and `user-id` removed unless trusted).
    fn received(
        &self,
        mut properties: BasicProperties,
        uri: &str,
        exchange: &str,
        redelivered: bool,
        cluster_name: &str,
    ) -> BasicProperties {
        if !self.config.trust_user_id {
            properties.user_id = None;
        }
        let mut headers = properties.headers.take().unwrap_or_default();
        let mut entry = FieldTable::new();
        entry.insert(ShortStr::from_static("uri"), FieldValue::string(uri));
        entry.insert(
            ShortStr::from_static("exchange"),
            FieldValue::string(exchange),
        );
        entry.insert(
            ShortStr::from_static("redelivered"),
            FieldValue::Bool(redelivered),
        );
        entry.insert(
            ShortStr::from_static("cluster-name"),
            FieldValue::string(cluster_name),
        );
        let mut list = match headers.remove(RECEIVED_FROM) {
            Some(FieldValue::Array(list)) => list,
            _ => Vec::new(),
        };
        list.push(FieldValue::Table(entry));
        headers.insert(
            ShortStr::from_static(RECEIVED_FROM),
            FieldValue::Array(list),
        );
        properties.headers = Some(headers);
        properties
    }
}

/// One entry of `x-received-from`.
struct Hop {
    cluster_name: Option<String>,
}

/// The links a message came through, from its `x-received-from`.
fn received_from(properties: &BasicProperties) -> Vec<Hop> {
    let Some(FieldValue::Array(list)) = properties
        .headers
        .as_ref()
        .and_then(|h| h.get(RECEIVED_FROM))
    else {
        return Vec::new();
    };
    list.iter()
        .map(|entry| Hop {
            cluster_name: match entry {
                FieldValue::Table(table) => table
                    .get("cluster-name")
                    .and_then(FieldValue::as_bytes)
                    .map(|b| String::from_utf8_lossy(b).into_owned()),
                _ => None,
            },
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn rabbitmqs_upstream_parameters_and_defaults() {
        let config = UpstreamConfig::from_json(&json!({
            "uri": ["amqp://fleet-1", "amqp://fleet-2"], "exchange": "fleet.commands",
            "max-hops": 2, "expires": 3_600_000, "message-ttl": 60_000,
        }))
        .unwrap();
        assert_eq!(config.uris.len(), 2);
        assert_eq!(config.exchange.as_deref(), Some("fleet.commands"));
        assert_eq!(config.max_hops, 2);
        assert_eq!(config.prefetch, 1000);
        assert_eq!(config.reconnect_delay, Duration::from_secs(5));
        assert_eq!(config.ack_mode, AckMode::OnConfirm);
        assert_eq!(
            (config.expires, config.message_ttl),
            (Some(3_600_000), Some(60_000))
        );
        assert!(!config.trust_user_id);
        let minimal = UpstreamConfig::from_json(&json!({"uri": "amqp://fleet"})).unwrap();
        assert_eq!((minimal.exchange, minimal.max_hops), (None, 1));
        for (value, reason) in [
            (json!({}), "uri is required"),
            (json!({"uri": "amqp://x", "queue": "q"}), "queue federation"),
            (json!({"uri": "amqp://x", "max-hops": 0}), "max-hops"),
            (json!({"uri": "amqp://x", "expires": -1}), "expires"),
            (json!({"uri": "amqp://x", "colour": 1}), "not supported"),
        ] {
            let error = UpstreamConfig::from_json(&value).unwrap_err();
            assert!(error.contains(reason), "{error}");
        }
    }

    #[test]
    fn hops_are_read_from_received_from() {
        let mut entry = FieldTable::new();
        entry.insert(
            ShortStr::from_static("cluster-name"),
            FieldValue::string("leveret@robot-7"),
        );
        let mut headers = FieldTable::new();
        headers.insert(
            ShortStr::from_static(RECEIVED_FROM),
            FieldValue::Array(vec![FieldValue::Table(entry), FieldValue::Bool(true)]),
        );
        let properties = BasicProperties {
            headers: Some(headers),
            ..Default::default()
        };
        let hops = received_from(&properties);
        assert_eq!(hops.len(), 2);
        assert_eq!(hops[0].cluster_name.as_deref(), Some("leveret@robot-7"));
        assert!(hops[1].cluster_name.is_none());
        assert!(received_from(&BasicProperties::default()).is_empty());
    }
}
