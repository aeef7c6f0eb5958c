//! [`Admin`]'s reading of the broker's state: the listings and figures of
//! the embedding API ([`crate::BrokerHandle::overview`],
//! [`crate::BrokerHandle::queues`]) and of the `leveret` binary's HTTP
//! listeners, built as `inspect`'s plain structs.
//!
//! Cost: every call takes each registry lock it reads (a vhost's queue or
//! exchange map, the connection registry) once, for as long as copying out
//! `Arc`s takes, then reads each object under its own lock, briefly. A
//! listing is O(objects); callers that must not stall (the HTTP listeners)
//! take [`Admin::queue_refs`] and read the queues in chunks.
//!
//! Uses the core and what it holds (vhosts, exchanges, queues, the
//! registry, the counters) and `inspect`'s structs.

use super::Admin;
use crate::exchange::{Binding, Destination, Exchange};
use crate::inspect::{
    AuthAttemptFigures, BindingInfo, BusyPollFigures, ChannelInfo, ChurnTotals, ConnectionInfo,
    ConsumerInfo, DeadLetteredFigures, DestinationKind, ExchangeInfo, GlobalMessageStats,
    ObjectTotals, Overview, QueueInfo, QueueRef, QueueTotals, SocketTrafficFigures,
};
use crate::queue::Queue;
use crate::registry::{ChannelMode, ConnectionEntry};
use crate::stats::{AuthProtocol, DeadLetterStrategy};
use crate::vhost::Vhost;
use leveret_protocol::{FieldTable, ShortStr};
use std::sync::Arc;

/// Queues copied out of a vhost's registry per hold of its lock: copying
/// a large vhost's queues at once holds it for milliseconds; a chunk of
/// this size holds it briefly, and a declare waiting for the registry
/// gets in between chunks.
const REGISTRY_CHUNK: usize = 1024;

/// Every queue of `vhost`, read a chunk at a time. Queues added or removed
/// meanwhile may be missed (as a listing taken a moment earlier or later
/// would); none is listed twice.
fn all_queues(vhost: &Vhost) -> Vec<Arc<Queue>> {
    let mut all = Vec::new();
    loop {
        let chunk = vhost.queues_chunk(all.len(), REGISTRY_CHUNK);
        let last = chunk.len() < REGISTRY_CHUNK;
        all.extend(chunk);
        if last {
            break;
        }
    }
    all.sort_unstable_by_key(|q| Arc::as_ptr(q) as usize);
    all.dedup_by(|a, b| Arc::ptr_eq(a, b));
    all
}

/// Every binding of `exchange`, copied out a chunk at a time.
fn all_bindings(exchange: &Exchange) -> Vec<Binding> {
    let mut all = Vec::new();
    let mut after = None;
    loop {
        let (chunk, next) = exchange.bindings_chunk(after.as_ref(), REGISTRY_CHUNK);
        all.extend(chunk);
        match next {
            Some(cursor) => after = Some(cursor),
            None => return all,
        }
    }
}

fn text(s: &ShortStr) -> String {
    s.to_string_lossy().into_owned()
}

impl Admin {
    /// Broker-wide figures. Reads every queue once (for `queue_totals`).
    pub fn overview(&self) -> Overview {
        let core = &self.core;
        let c = &core.stats;
        // The closes are read before the listing: a connection or channel
        // is unlisted before its close is counted, so a close that lands
        // between the two reads is missed by both instead of shown by both
        // (read the other way round, an overview counted a connection's
        // close and still listed it: `stats` failed so on a loaded
        // machine). The counters are relaxed: this orders the reads, it
        // is no fence.
        let churn = ChurnTotals {
            connections_opened: c.connections_opened.get(),
            connections_closed: c.connections_closed.get(),
            channels_opened: c.channels_opened.get(),
            channels_closed: c.channels_closed.get(),
            queues_declared: c.queues_declared.get(),
            queues_created: c.queues_created.get(),
            queues_deleted: c.queues_deleted.get(),
        };
        let (connections, channels) = core.registry.counts();
        let mut queues = 0;
        let mut exchanges = 0;
        let mut totals = QueueTotals::default();
        for vhost in core.vhosts() {
            exchanges += vhost.exchanges().len() as u64;
            for queue in all_queues(&vhost) {
                queues += 1;
                let depth = queue.depth();
                totals.messages_ready += depth.ready;
                totals.messages_unacknowledged += depth.unacked;
            }
        }
        Overview {
            product: core.product.clone(),
            version: env!("CARGO_PKG_VERSION"),
            uptime: core.started.elapsed(),
            object_totals: ObjectTotals {
                connections: connections as u64,
                channels: channels as u64,
                exchanges,
                queues,
                consumers: c.consumers.get(),
            },
            queue_totals: totals,
            message_stats: GlobalMessageStats {
                received: c.received.get(),
                received_confirm: c.received_confirm.get(),
                routed: c.routed.get(),
                unroutable_dropped: c.unroutable_dropped.get(),
                unroutable_returned: c.unroutable_returned.get(),
                confirmed: c.confirmed.get(),
                delivered_consume_manual_ack: c.delivered_consume_manual_ack.get(),
                delivered_consume_auto_ack: c.delivered_consume_auto_ack.get(),
                delivered_get_manual_ack: c.delivered_get_manual_ack.get(),
                delivered_get_auto_ack: c.delivered_get_auto_ack.get(),
                get_empty: c.get_empty.get(),
                redelivered: c.redelivered.get(),
                acknowledged: c.acknowledged.get(),
            },
            churn,
            publishers: c.publishers.get(),
            memory_high_watermark: core.limits.memory_high_watermark,
            memory_used: core.gauge.used(),
            resident_memory_limit: core.gauge.resident_limit(),
            memory_alarm: core.gauge.memory_alarm(),
            disk_free_limit: core.limits.disk_free_limit,
            disk_alarm: core.gauge.disk_alarm(),
            busy_poll: core.busy_poll.as_ref().map(|busy_poll| {
                let (socket_reads, windows, polling, yielded_to_cpu_pressure) = busy_poll.figures();
                BusyPollFigures {
                    socket_reads,
                    windows,
                    polling,
                    yielded_to_cpu_pressure,
                }
            }),
            socket_traffic: SocketTrafficFigures::read(&c.socket_traffic),
            tcp_connections: core.connections.network_count() as u64,
            tcp_connections_limit: core.limits.max_connections.map(|max| max as u64),
            auth_attempts: [
                ("amqp091", AuthProtocol::Amqp091),
                ("mqtt", AuthProtocol::Mqtt),
            ]
            .map(|(protocol, which)| {
                let attempts = &c.auth_attempts[which as usize];
                AuthAttemptFigures {
                    protocol,
                    succeeded: attempts.succeeded.get(),
                    failed: attempts.failed.get(),
                }
            })
            .to_vec(),
            dead_lettered: [
                ("disabled", DeadLetterStrategy::Disabled),
                ("at_most_once", DeadLetterStrategy::AtMostOnce),
            ]
            .map(|(strategy, which)| {
                let [expired, rejected, maxlen] = &c.dead_lettered[which as usize];
                DeadLetteredFigures {
                    strategy,
                    expired: expired.get(),
                    rejected: rejected.get(),
                    maxlen: maxlen.get(),
                }
            })
            .to_vec(),
        }
    }

    /// The vhosts' names, sorted.
    pub fn vhosts(&self) -> Vec<String> {
        let mut names: Vec<String> = self.core.vhosts().iter().map(|v| text(&v.name)).collect();
        names.sort();
        names
    }

    /// A handle on every queue, sorted by vhost and name: taking them
    /// holds each vhost's queue map for as long as copying its `Arc`s
    /// takes; reading their figures ([`QueueRef::info`]) is left to the
    /// caller, one queue at a time.
    pub fn queue_refs(&self) -> Vec<QueueRef> {
        let mut refs: Vec<QueueRef> = self
            .core
            .vhosts()
            .into_iter()
            .flat_map(|vhost| {
                all_queues(&vhost).into_iter().map(move |queue| QueueRef {
                    vhost: vhost.name.clone(),
                    queue,
                })
            })
            .collect();
        refs.sort_by(|a, b| {
            (a.vhost.as_bytes(), a.queue.name.as_bytes())
                .cmp(&(b.vhost.as_bytes(), b.queue.name.as_bytes()))
        });
        refs
    }

    /// Every queue's figures, sorted by vhost and name.
    pub fn queues(&self) -> Vec<QueueInfo> {
        self.queue_refs().iter().map(QueueRef::info).collect()
    }

    /// One queue.
    pub fn queue(&self, vhost: &str, name: &str) -> Option<QueueRef> {
        let vhost = self.core.vhost(&ShortStr::try_from(vhost).ok()?)?;
        let queue = vhost.queue(&ShortStr::try_from(name).ok()?)?;
        Some(QueueRef {
            vhost: vhost.name.clone(),
            queue,
        })
    }

    /// Every exchange, sorted by vhost and name.
    pub fn exchanges(&self) -> Vec<ExchangeInfo> {
        let mut list: Vec<ExchangeInfo> = self
            .core
            .vhosts()
            .iter()
            .flat_map(|vhost| {
                vhost
                    .exchanges()
                    .into_iter()
                    .map(|e| exchange_info(&vhost.name, &e))
            })
            .collect();
        list.sort_by(|a, b| (&a.vhost, &a.name).cmp(&(&b.vhost, &b.name)));
        list
    }

    /// One exchange.
    pub fn exchange(&self, vhost: &str, name: &str) -> Option<ExchangeInfo> {
        let vhost = self.core.vhost(&ShortStr::try_from(vhost).ok()?)?;
        let exchange = vhost.exchange(&ShortStr::try_from(name).ok()?)?;
        Some(exchange_info(&vhost.name, &exchange))
    }

    /// The group commits' batch sizes and write-and-flush times, if the
    /// broker has a store.
    pub fn persister(&self) -> Option<crate::store::PersisterFigures> {
        self.core.persistence.as_ref().map(|p| p.figures())
    }

    /// The names of `vhost`'s exchanges (empty if there is no such vhost).
    pub fn exchange_names(&self, vhost: &str) -> Vec<String> {
        let Some(vhost) = ShortStr::try_from(vhost)
            .ok()
            .and_then(|name| self.core.vhost(&name))
        else {
            return Vec::new();
        };
        vhost.exchanges().iter().map(|e| text(&e.name)).collect()
    }

    /// The (binding key, arguments) of every binding from exchange `name`
    /// of `vhost`, whatever their destinations; `None` if there is no such
    /// exchange. (A federation link replays them on its upstream.)
    pub fn binding_keys_from(&self, vhost: &str, name: &str) -> Option<Vec<(String, FieldTable)>> {
        let vhost = self.core.vhost(&ShortStr::try_from(vhost).ok()?)?;
        let exchange = vhost.exchange(&ShortStr::try_from(name).ok()?)?;
        Some(
            all_bindings(&exchange)
                .into_iter()
                .map(|b| (text(&b.routing_key), b.arguments))
                .collect(),
        )
    }

    /// Every binding, sorted by vhost, source, destination and key; the
    /// default exchange's implicit ones first in each vhost.
    pub fn bindings(&self) -> Vec<BindingInfo> {
        let mut list = Vec::new();
        let mut vhosts = self.core.vhosts();
        vhosts.sort_by(|a, b| a.name.as_bytes().cmp(b.name.as_bytes()));
        for vhost in vhosts {
            let vhost_name = text(&vhost.name);
            let mut implicit: Vec<BindingInfo> = all_queues(&vhost)
                .iter()
                .map(|queue| BindingInfo {
                    vhost: vhost_name.clone(),
                    source: String::new(),
                    destination: text(&queue.name),
                    destination_kind: DestinationKind::Queue,
                    routing_key: text(&queue.name),
                    arguments: FieldTable::new(),
                })
                .collect();
            implicit.sort_by(|a, b| a.destination.cmp(&b.destination));
            list.extend(implicit);
            let mut explicit: Vec<BindingInfo> = vhost
                .exchanges()
                .iter()
                .flat_map(|exchange| {
                    let source = text(&exchange.name);
                    let vhost_name = vhost_name.clone();
                    all_bindings(exchange).into_iter().map(move |b| {
                        let (destination, destination_kind) = match &b.destination {
                            Destination::Queue(q) => (text(&q.name), DestinationKind::Queue),
                            Destination::Exchange(e) => (text(&e.name), DestinationKind::Exchange),
                        };
                        BindingInfo {
                            vhost: vhost_name.clone(),
                            source: source.clone(),
                            destination,
                            destination_kind,
                            routing_key: text(&b.routing_key),
                            arguments: b.arguments,
                        }
                    })
                })
                .collect();
            explicit.sort_by(|a, b| {
                (&a.source, &a.destination, &a.routing_key).cmp(&(
                    &b.source,
                    &b.destination,
                    &b.routing_key,
                ))
            });
            list.extend(explicit);
        }
        list
    }

    /// Every open connection, by id.
    pub fn connections(&self) -> Vec<ConnectionInfo> {
        self.core
            .registry
            .connections()
            .iter()
            .filter_map(|entry| connection_info(entry))
            .collect()
    }

    /// One open connection.
    pub fn connection(&self, id: u64) -> Option<ConnectionInfo> {
        connection_info(self.core.registry.connection_entry(id)?.as_ref())
    }

    /// Every consumer, sorted by vhost, queue and tag.
    pub fn consumers(&self) -> Vec<ConsumerInfo> {
        self.queue_refs()
            .iter()
            .flat_map(|queue| {
                let mut consumers = queue.consumers();
                consumers.sort_by(|a, b| a.tag.cmp(&b.tag));
                consumers
            })
            .collect()
    }

    /// Every open channel, by connection and number.
    pub fn channels(&self) -> Vec<ChannelInfo> {
        let consumers = self.consumers();
        let mut list = Vec::new();
        for entry in self.core.registry.connections() {
            let Some(opened) = entry.opened.get() else {
                continue;
            };
            for channel in entry.channels() {
                let link = &channel.link;
                let mode = channel.mode();
                let (unconfirmed, uncommitted, acks_uncommitted) = channel.pending();
                list.push(ChannelInfo {
                    connection_id: entry.id,
                    connection_peer: entry.peer.clone(),
                    number: channel.number,
                    user: opened.user.clone(),
                    vhost: opened.vhost.clone(),
                    consumers: consumers
                        .iter()
                        .filter(|c| c.connection_id == entry.id && c.channel == channel.number)
                        .count() as u64,
                    messages_unacknowledged: link.deliveries().unacked_count() as u64,
                    prefetch_count: channel.prefetch(),
                    global_prefetch_count: link
                        .global_prefetch
                        .load(std::sync::atomic::Ordering::Relaxed),
                    confirm: mode == ChannelMode::Confirm,
                    transactional: mode == ChannelMode::Transactional,
                    messages_unconfirmed: unconfirmed,
                    messages_uncommitted: uncommitted,
                    acks_uncommitted,
                });
            }
        }
        list
    }
}

fn exchange_info(vhost: &ShortStr, exchange: &crate::exchange::Exchange) -> ExchangeInfo {
    ExchangeInfo {
        vhost: text(vhost),
        name: text(&exchange.name),
        kind: exchange.kind.name(),
        durable: exchange.options.durable,
        auto_delete: exchange.options.auto_delete,
        internal: exchange.options.internal,
        arguments: exchange.options.arguments.clone(),
        policies: exchange.policies(),
    }
}

fn connection_info(entry: &ConnectionEntry) -> Option<ConnectionInfo> {
    let opened = entry.opened.get()?;
    Some(ConnectionInfo {
        id: entry.id,
        peer: entry.peer.clone(),
        protocol: entry.protocol,
        connected_at: entry.connected_at,
        user: opened.user.clone(),
        vhost: opened.vhost.clone(),
        client_properties: opened.client_properties.clone(),
        frame_max: opened.frame_max,
        channel_max: opened.channel_max,
        heartbeat_secs: opened.heartbeat_secs,
        channels: entry.channel_count() as u64,
        traffic: entry
            .traffic
            .as_ref()
            .map(|traffic| SocketTrafficFigures::read(&traffic.own)),
    })
}
