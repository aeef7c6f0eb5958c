//! [`Admin`]: a cloneable handle on a running broker for tools beside the
//! AMQP listeners (the `leveret` binary's HTTP API, an embedder's own
//! dashboard). This module holds the handle and the operations that change
//! things, each doing what the AMQP method of the same meaning does, with
//! the same checks.
//!
//! Layout: `mod` the handle and the object operations; `access` users,
//! vhosts and permissions; `inspect` reading state into
//! `crate::inspect`'s structs; `limits` vhost and user limits;
//! `parameters` runtime parameters; `policies` policies and operator
//! policies; `vhost_deletion` deleting a vhost and all it holds;
//! `as_user` ([`AsUser`](as_user::AsUser)), the same operations checked
//! against a user's permissions, built on the handle.
//!
//! Uses the layers below (the channel's settling, the core, vhosts,
//! exchanges, queues, outboxes), `inspect`'s structs and `access::lasting`'s
//! records; nothing below calls it.

mod access;
pub(crate) mod as_user;
mod inspect;
mod limits;
mod parameters;
mod policies;
mod vhost_deletion;

use crate::channel::{apply_settles, Settle};
use crate::core::Core;
use crate::error::{AmqpError, AmqpResult};
use crate::exchange::ExchangeOptions;
use crate::inspect::DestinationKind;
use crate::message::Message;
use crate::outbox::{Outbound, Outbox};
use crate::queue::{ChannelLink, DeadLetters, Queue, QueueOptions};
use crate::vhost::{check_exclusive, BindingChange, ExchangeDeclaration, QueueDeclaration, Vhost};
use bytes::{Bytes, BytesMut};
use leveret_protocol::{BasicProperties, FieldTable, ShortStr};
use std::sync::Arc;

/// A cheap, cloneable handle for inspecting and administering a running
/// broker. It stays usable after the broker shuts down, showing what was
/// left.
#[derive(Debug, Clone)]
pub struct Admin {
    pub(crate) core: Arc<Core>,
}

impl Admin {
    /// Closes connection `id` with 320 CONNECTION_FORCED and `reason` as
    /// the text; false if no such connection is open.
    pub fn close_connection(&self, id: u64, reason: &str) -> bool {
        self.core.registry.close(id, reason)
    }
}

/// The connection id the management operations act as: connection ids
/// start at 1, so no client's exclusive queue belongs to it.
const ADMIN_CONNECTION: u64 = 0;

/// The queue RabbitMQ's aliveness test ([`Admin::aliveness_test`])
/// declares, publishes to and gets from.
pub(crate) const ALIVENESS_QUEUE: &str = "aliveness-test";

/// How `Admin::get` leaves the messages it fetched (RabbitMQ's `ackmode`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GetMode {
    /// Acknowledge: the messages leave the queue.
    Ack,
    /// Reject without requeue: the messages leave the queue, to its
    /// dead-letter exchange if it has one.
    RejectDrop,
    /// Put them back, flagged redelivered (`ack_requeue_true` and
    /// `reject_requeue_true` alike).
    Requeue,
}

/// A message fetched by [`Admin::get`].
#[derive(Debug, Clone, PartialEq)]
pub struct GotMessage {
    /// The exchange it was published to.
    pub exchange: String,
    /// Its routing key.
    pub routing_key: String,
    /// Delivered before.
    pub redelivered: bool,
    /// Ready messages left in the queue after this one was taken.
    pub remaining: u32,
    /// Its properties.
    pub properties: BasicProperties,
    /// Its body.
    pub body: Bytes,
}

/// What an exchange is declared as.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ExchangeSettings {
    /// `direct`, `fanout`, `topic` or `headers`.
    pub kind: String,
    /// Survives restarts.
    pub durable: bool,
    /// Deleted when its last binding goes.
    pub auto_delete: bool,
    /// Only reachable through exchange-to-exchange bindings.
    pub internal: bool,
    /// Arguments.
    pub arguments: FieldTable,
}

/// What a queue is declared as (queues declared through [`Admin`] are
/// never exclusive: no connection would own them).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct QueueSettings {
    /// Survives restarts.
    pub durable: bool,
    /// Deleted when its last consumer goes.
    pub auto_delete: bool,
    /// Arguments.
    pub arguments: FieldTable,
}

/// A binding to add or remove.
#[derive(Debug, Clone, PartialEq)]
pub struct BindingSpec {
    /// The source exchange.
    pub source: String,
    /// The destination's name.
    pub destination: String,
    /// Queue or exchange.
    pub destination_kind: DestinationKind,
    /// The binding key.
    pub routing_key: String,
    /// Binding arguments.
    pub arguments: FieldTable,
}

fn short(text: &str, what: &str) -> AmqpResult<ShortStr> {
    ShortStr::try_from(text)
        .map_err(|_| AmqpError::precondition_failed(format_args!("{what} longer than 255 bytes")))
}

impl Admin {
    pub(crate) fn vhost(&self, name: &str) -> AmqpResult<Arc<Vhost>> {
        let missing = || AmqpError::not_found(format_args!("no vhost '{name}'"));
        let name = ShortStr::try_from(name).map_err(|_| missing())?;
        self.core.vhost(&name).ok_or_else(missing)
    }

    fn queue_in(&self, vhost: &Vhost, name: &str) -> AmqpResult<Arc<Queue>> {
        vhost.queue_or_404(&short(name, "queue name")?)
    }

    /// Waits until every definition change submitted so far is on disk,
    /// when `durable` says the change touched the store: as over AMQP, the
    /// caller hears of success only once the disk has it.
    async fn on_disk(&self, durable: bool) -> AmqpResult<()> {
        match &self.core.persistence {
            Some(persistence) if durable && !persistence.sync().await => Err(
                AmqpError::resource_error("could not write the definition to disk"),
            ),
            _ => Ok(()),
        }
    }

    /// exchange.declare, as a client would (same checks, same errors).
    pub async fn declare_exchange(
        &self,
        vhost: &str,
        name: &str,
        settings: ExchangeSettings,
    ) -> AmqpResult<()> {
        let vhost = self.vhost(vhost)?;
        let durable = settings.durable;
        vhost.declare_exchange(ExchangeDeclaration {
            name: short(name, "exchange name")?,
            kind: short(&settings.kind, "exchange type")?,
            passive: false,
            options: ExchangeOptions {
                durable: settings.durable,
                auto_delete: settings.auto_delete,
                internal: settings.internal,
                arguments: settings.arguments,
            },
        })?;
        self.on_disk(durable).await
    }

    /// exchange.delete; deleting one that does not exist is a 404 here
    /// (the HTTP API's meaning), unlike over AMQP.
    pub async fn delete_exchange(
        &self,
        vhost: &str,
        name: &str,
        if_unused: bool,
    ) -> AmqpResult<()> {
        let vhost = self.vhost(vhost)?;
        let name = short(name, "exchange name")?;
        let durable = vhost.exchange_or_404(&name)?.options.durable;
        vhost.delete_exchange(&name, if_unused)?;
        self.on_disk(durable).await
    }

    /// queue.declare (not exclusive); true if the queue was created.
    pub async fn declare_queue(
        &self,
        vhost: &str,
        name: &str,
        settings: QueueSettings,
    ) -> AmqpResult<bool> {
        let vhost = self.vhost(vhost)?;
        let name = short(name, "queue name")?;
        if name.is_empty() {
            return Err(AmqpError::precondition_failed("a queue needs a name"));
        }
        self.core.stats.queues_declared.inc();
        let max_queues = (self.core.limit_tables)
            .vhost(&vhost.name.to_string_lossy())
            .max_queues;
        let (queue, created) = vhost.declare_queue(
            QueueDeclaration {
                name,
                passive: false,
                server_named: false,
                options: QueueOptions {
                    durable: settings.durable,
                    exclusive_owner: None,
                    auto_delete: settings.auto_delete,
                    arguments: settings.arguments,
                },
                max_queues,
            },
            ADMIN_CONNECTION,
        )?;
        if created {
            self.core.stats.queues_created.inc();
        }
        self.on_disk(queue.store_id().is_some()).await?;
        Ok(created)
    }

    /// queue.delete: 404 if it does not exist, 406 if `if_empty` and it
    /// has ready messages, or `if_unused` and it is in use (consumers, or
    /// an MQTT shared subscription's member about to consume it), decided
    /// and the queue taken in one step, so nothing comes to use it before
    /// it goes.
    pub async fn delete_queue(
        &self,
        vhost: &str,
        name: &str,
        if_unused: bool,
        if_empty: bool,
    ) -> AmqpResult<u32> {
        let vhost = self.vhost(vhost)?;
        let queue = self.queue_in(&vhost, name)?;
        if if_empty && queue.message_count() > 0 {
            return Err(AmqpError::precondition_failed(format_args!(
                "queue '{}' in vhost '{}' not empty",
                name, vhost.name
            )));
        }
        if if_unused && !queue.take_unused() {
            return Err(AmqpError::precondition_failed(format_args!(
                "queue '{}' in vhost '{}' in use",
                name, vhost.name
            )));
        }
        let count = vhost.delete_queue(&queue).notify();
        self.on_disk(queue.store_id().is_some()).await?;
        Ok(count)
    }

    /// queue.purge: drops the ready messages; returns how many.
    pub fn purge_queue(&self, vhost: &str, name: &str) -> AmqpResult<u32> {
        let vhost = self.vhost(vhost)?;
        let queue = self.queue_in(&vhost, name)?;
        queue.refuse_on_stream("queue.purge")?;
        Ok(queue.purge())
    }

    /// queue.bind or exchange.bind.
    pub async fn bind(&self, vhost: &str, binding: BindingSpec) -> AmqpResult<()> {
        self.change_binding(vhost, binding, BindingChange::Bind)
            .await
    }

    /// Removes the binding whose [`crate::inspect::BindingInfo::properties_key`] is `key`;
    /// 404 if there is none.
    pub async fn unbind(
        &self,
        vhost: &str,
        source: &str,
        destination: &str,
        destination_kind: DestinationKind,
        key: &str,
    ) -> AmqpResult<()> {
        let binding = self.binding(vhost, source, destination, destination_kind, key)?;
        self.change_binding(vhost, binding, BindingChange::Unbind)
            .await
    }

    /// The binding whose [`crate::inspect::BindingInfo::properties_key`]
    /// is `key` (not one of the default exchange's); 404 if there is none.
    pub(crate) fn binding(
        &self,
        vhost: &str,
        source: &str,
        destination: &str,
        destination_kind: DestinationKind,
        key: &str,
    ) -> AmqpResult<BindingSpec> {
        let found = self.bindings().into_iter().find(|b| {
            b.vhost == vhost
                && b.source == source
                && !b.source.is_empty()
                && b.destination == destination
                && b.destination_kind == destination_kind
                && b.properties_key() == key
        });
        let Some(found) = found else {
            return Err(AmqpError::not_found(format_args!(
                "no binding '{key}' from '{source}' to '{destination}' in vhost '{vhost}'"
            )));
        };
        Ok(BindingSpec {
            source: found.source,
            destination: found.destination,
            destination_kind,
            routing_key: found.routing_key,
            arguments: found.arguments,
        })
    }

    async fn change_binding(
        &self,
        vhost: &str,
        binding: BindingSpec,
        change: BindingChange,
    ) -> AmqpResult<()> {
        let vhost = self.vhost(vhost)?;
        let source = short(&binding.source, "exchange name")?;
        let routing_key = short(&binding.routing_key, "routing key")?;
        let source_durable = vhost.exchange(&source).is_some_and(|e| e.options.durable);
        let durable = match binding.destination_kind {
            DestinationKind::Queue => {
                let queue = self.queue_in(&vhost, &binding.destination)?;
                vhost.bind_queue(&queue, &source, routing_key, binding.arguments, change)?;
                queue.store_id().is_some()
            }
            DestinationKind::Exchange => {
                let destination = short(&binding.destination, "exchange name")?;
                vhost.bind_exchange(
                    &destination,
                    &source,
                    routing_key,
                    binding.arguments,
                    change,
                )?;
                vhost
                    .exchange(&destination)
                    .is_some_and(|e| e.options.durable)
            }
        };
        self.on_disk(durable && source_durable).await
    }

    /// basic.publish of one message, as a client in confirm mode would:
    /// returns once any durable queue's copy is on disk, with whether any
    /// queue took it. Exchange `""` is the default exchange. During a
    /// memory or disk alarm, when AMQP publishers are blocked, it is
    /// refused (506 RESOURCE_ERROR) rather than left waiting. A message a
    /// queue refused (overflow `reject-publish`), which such a client
    /// would have nacked, is an error (406, RabbitMQ's text).
    pub async fn publish(
        &self,
        vhost: &str,
        exchange: &str,
        routing_key: &str,
        properties: BasicProperties,
        body: Bytes,
    ) -> AmqpResult<bool> {
        let gauge = &self.core.gauge;
        if gauge.in_alarm() {
            return Err(AmqpError::resource_error(format_args!(
                "publishing is blocked by a resource alarm ({})",
                gauge.alarm_reason()
            )));
        }
        self.publish_now(vhost, exchange, routing_key, properties, body)
            .await
    }

    /// [`Admin::publish`] whatever the alarms (the aliveness test's: as in
    /// RabbitMQ, it passes during an alarm).
    async fn publish_now(
        &self,
        vhost: &str,
        exchange: &str,
        routing_key: &str,
        properties: BasicProperties,
        body: Bytes,
    ) -> AmqpResult<bool> {
        let vhost = self.vhost(vhost)?;
        let exchange = vhost.exchange_or_404(&short(exchange, "exchange name")?)?;
        if exchange.options.internal {
            return Err(AmqpError::access_refused(format_args!(
                "cannot publish to internal exchange '{}' in vhost '{}'",
                exchange.name, vhost.name
            )));
        }
        if body.len() as u64 > self.core.limits.max_message_size {
            return Err(AmqpError::precondition_failed(format_args!(
                "message size {} is larger than configured max size {}",
                body.len(),
                self.core.limits.max_message_size
            )));
        }
        let ttl_ms = match &properties.expiration {
            None => None,
            Some(text) => Some(
                text.as_str()
                    .and_then(|e| e.parse::<u64>().ok())
                    .ok_or_else(|| {
                        AmqpError::precondition_failed(format_args!(
                            "invalid expiration '{text}': not a non-negative integer"
                        ))
                    })?,
            ),
        };
        let routing_key = short(routing_key, "routing key")?;
        self.core.stats.received(false);
        let mut queues = Vec::new();
        vhost.route(
            &exchange,
            &routing_key,
            properties.headers.as_ref(),
            &mut queues,
            &mut None,
        );
        self.core.stats.routed(!queues.is_empty(), false);
        let persistent = properties.is_persistent();
        let stored = vhost.storage(persistent, &queues);
        let mut encoded = BytesMut::new();
        properties.encode(&mut encoded);
        let message = Arc::new(Message {
            exchange: exchange.name.clone(),
            routing_key,
            properties: encoded.freeze(),
            body,
            persistent,
            priority: properties.priority.unwrap_or(0),
            ttl_ms,
            stored,
        });
        let reached = !queues.is_empty();
        let published = vhost.publish(message, queues).await;
        if published.refused {
            return Err(AmqpError::precondition_failed(
                "Unable to publish message. Check queue limits.",
            ));
        }
        if let Some(persistence) = &self.core.persistence {
            if !persistence.wait_written(published.written).await {
                return Err(AmqpError::resource_error(
                    "could not write the message to disk",
                ));
            }
        }
        Ok(reached)
    }

    /// basic.get up to `count` times, then settles what it got as `mode`
    /// says.
    pub fn get(
        &self,
        vhost: &str,
        queue: &str,
        count: usize,
        mode: GetMode,
    ) -> AmqpResult<Vec<GotMessage>> {
        let vhost = self.vhost(vhost)?;
        let queue = self.queue_in(&vhost, queue)?;
        check_exclusive(&queue, ADMIN_CONNECTION, &vhost.name)?;
        queue.refuse_on_stream("basic.get")?;
        let (outbox, mut answers) = Outbox::new(ADMIN_CONNECTION);
        let link = ChannelLink::new(0, Arc::clone(&outbox));
        let mut got = Vec::new();
        let mut dead = DeadLetters::default();
        while got.len() < count {
            let Some(permit) = outbox.try_reserve() else {
                break;
            };
            let (found, dead_here) = queue.get(&link, false, permit);
            dead.append(dead_here);
            if !found {
                break;
            }
            // The answer basic.get would have sent is in our own outbox.
            let Some(Outbound::GetOk {
                redelivered,
                message_count,
                message,
                ..
            }) = answers.try_recv()
            else {
                break;
            };
            got.push(GotMessage {
                exchange: message.exchange.to_string_lossy().into_owned(),
                routing_key: message.routing_key.to_string_lossy().into_owned(),
                redelivered,
                remaining: message_count,
                properties: BasicProperties::decode(&message.properties).unwrap_or_default(),
                body: message.body.clone(),
            });
        }
        let how = match mode {
            GetMode::Ack => Settle::Ack,
            GetMode::RejectDrop => Settle::Reject { requeue: false },
            GetMode::Requeue => Settle::Reject { requeue: true },
        };
        let taken = link.deliveries().take_all();
        dead.append(apply_settles(taken.into_iter().map(move |u| (u, how))));
        vhost.dead_letter(dead);
        Ok(got)
    }

    /// RabbitMQ's aliveness test: declares `aliveness-test` in the vhost,
    /// publishes to it and gets the message back.
    pub async fn aliveness_test(&self, vhost: &str) -> AmqpResult<()> {
        self.declare_queue(vhost, ALIVENESS_QUEUE, QueueSettings::default())
            .await?;
        let body = Bytes::from_static(b"test_message");
        self.publish_now(
            vhost,
            "",
            ALIVENESS_QUEUE,
            BasicProperties::default(),
            body.clone(),
        )
        .await?;
        let got = self.get(vhost, ALIVENESS_QUEUE, 1, GetMode::Ack)?;
        if got.first().is_some_and(|m| m.body == body) {
            Ok(())
        } else {
            Err(AmqpError::internal_error(
                "the aliveness test message did not come back",
            ))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::QueueSettings;
    use crate::Broker;
    use bytes::Bytes;
    use leveret_protocol::{BasicProperties, FieldTable, FieldValue, ShortStr};

    /// A publish a queue refused is an error, not "routed": the message a
    /// confirm-mode client would have had nacked.
    async fn a_refused_publish_is_an_error() {
        let broker = Broker::builder().start().await.expect("broker starts");
        let admin = broker.admin();
        let mut arguments = FieldTable::default();
        arguments.insert(ShortStr::from_static("x-max-length"), FieldValue::I32(1));
        arguments.insert(
            ShortStr::from_static("x-overflow"),
            FieldValue::string("reject-publish"),
        );
        let settings = QueueSettings {
            durable: false,
            auto_delete: false,
            arguments,
        };
        assert_eq!(admin.declare_queue("/", "full", settings).await, Ok(true));
        let publish = || {
            admin.publish(
                "/",
                "",
                "full",
                BasicProperties::default(),
                Bytes::from_static(b"m"),
            )
        };
        assert_eq!(publish().await, Ok(true), "the first fits");
        let refused = publish().await.expect_err("the second is refused");
        assert_eq!(
            refused.code,
            leveret_protocol::ReplyCode::PreconditionFailed,
            "{refused:?}"
        );
        assert_eq!(
            admin
                .publish("/", "", "nowhere", BasicProperties::default(), Bytes::new())
                .await,
            Ok(false),
            "an unroutable message is not an error"
        );
        broker.shutdown().await;
    }

    #[tokio::test]
    async fn a_refused_publish_is_an_error_current_thread() {
        a_refused_publish_is_an_error().await;
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_refused_publish_is_an_error_multi_thread() {
        a_refused_publish_is_an_error().await;
    }
}
