//! [`AsUser`]: [`Admin`]'s operations on exchanges, queues, bindings and
//! messages done on behalf of one user, checked against that user's
//! permissions in the vhost with the same rules AMQP applies to a
//! channel of theirs (`permissions`' `VhostAccess`), as RabbitMQ's
//! management API does (it runs each operation on a channel of the
//! caller's). A user without a permission on the vhost is refused
//! everything in it, whatever their tags.
//!
//! Where RabbitMQ's management API looks for the object before it checks
//! (deleting an exchange or a queue, purging, removing a binding), a
//! missing one is a 404 here too; elsewhere the check comes first, as on
//! AMQP.
//!
//! Uses [`Admin`] (whose operations it checks, and the aliveness test's
//! queue name), `permissions`, `inspect`'s destination kinds and the
//! vhost it checks in.

use crate::access::permissions::{Resource, Right, VhostAccess};
use crate::admin::{
    Admin, BindingSpec, ExchangeSettings, GetMode, GotMessage, QueueSettings, ALIVENESS_QUEUE,
};
use crate::error::{AmqpError, AmqpResult};
use crate::exchange::ExchangeKind;
use crate::inspect::DestinationKind;
use crate::vhost::Vhost;
use bytes::Bytes;
use leveret_protocol::{BasicProperties, ShortStr};
use std::sync::Arc;

/// [`Admin`] acting as one user (see the module docs); from
/// [`Admin::as_user`].
#[derive(Debug, Clone)]
pub struct AsUser<'a> {
    admin: &'a Admin,
    user: &'a str,
}

fn short(name: &str) -> AmqpResult<ShortStr> {
    ShortStr::try_from(name)
        .map_err(|_| AmqpError::precondition_failed("a name longer than 255 bytes"))
}

impl Admin {
    /// This broker's operations on behalf of `user`, checked against
    /// their permissions.
    pub fn as_user<'a>(&'a self, user: &'a str) -> AsUser<'a> {
        AsUser { admin: self, user }
    }
}

impl AsUser<'_> {
    /// The vhost (404 if there is none) and the user's rights in it
    /// (refused if they have no permission there).
    fn access(&self, vhost: &str) -> AmqpResult<(Arc<Vhost>, Arc<VhostAccess>)> {
        let found = self.admin.vhost(vhost)?;
        let access = self
            .admin
            .core
            .permissions
            .of(self.user, vhost)
            .ok_or_else(|| {
                AmqpError::access_refused(format_args!(
                    "access to vhost '{vhost}' refused for user '{}'",
                    self.user
                ))
            })?;
        Ok((found, access))
    }

    /// The routing key against the user's topic permission when
    /// `exchange` is a topic exchange (`Write` to publish, `Read` to bind);
    /// a missing exchange is the operation's own 404.
    fn check_topic(
        access: &VhostAccess,
        vhost: &Vhost,
        right: Right,
        exchange: &str,
        routing_key: &str,
    ) -> AmqpResult<()> {
        if !access.has_topic_permissions() {
            return Ok(());
        }
        match vhost.exchange(&short(exchange)?) {
            Some(found) if found.kind == ExchangeKind::Topic => {
                access.check_topic(right, exchange, routing_key)
            }
            _ => Ok(()),
        }
    }

    /// exchange.declare: configure on the exchange (and, creating it with
    /// an alternate exchange, read on it and write on the alternate).
    pub async fn declare_exchange(
        &self,
        vhost: &str,
        name: &str,
        settings: ExchangeSettings,
    ) -> AmqpResult<()> {
        let (found, access) = self.access(vhost)?;
        if !name.is_empty() {
            let exchange_name = short(name)?;
            let alternate = settings
                .arguments
                .get("alternate-exchange")
                .and_then(|v| v.as_bytes())
                .filter(|_| found.exchange(&exchange_name).is_none())
                .map(String::from_utf8_lossy);
            access.check_exchange_declare(name, alternate.as_deref())?;
        }
        self.admin.declare_exchange(vhost, name, settings).await
    }

    /// exchange.delete (404 if it does not exist): configure on it.
    pub async fn delete_exchange(
        &self,
        vhost: &str,
        name: &str,
        if_unused: bool,
    ) -> AmqpResult<()> {
        let (found, access) = self.access(vhost)?;
        found.exchange_or_404(&short(name)?)?;
        access.check(Right::Configure, Resource::Exchange(name))?;
        self.admin.delete_exchange(vhost, name, if_unused).await
    }

    /// queue.declare: configure on the queue (and, creating it with a
    /// dead-letter exchange, read on it and write on that exchange).
    pub async fn declare_queue(
        &self,
        vhost: &str,
        name: &str,
        settings: QueueSettings,
    ) -> AmqpResult<bool> {
        let (found, access) = self.access(vhost)?;
        let queue_name = short(name)?;
        let dead_letter_exchange = settings
            .arguments
            .get("x-dead-letter-exchange")
            .and_then(|v| v.as_bytes())
            .filter(|_| found.queue(&queue_name).is_none())
            .map(String::from_utf8_lossy);
        access.check_queue_declare(name, dead_letter_exchange.as_deref())?;
        self.admin.declare_queue(vhost, name, settings).await
    }

    /// queue.delete (404 if it does not exist): configure on it.
    pub async fn delete_queue(
        &self,
        vhost: &str,
        name: &str,
        if_unused: bool,
        if_empty: bool,
    ) -> AmqpResult<u32> {
        let (found, access) = self.access(vhost)?;
        found.queue_or_404(&short(name)?)?;
        access.check(Right::Configure, Resource::Queue(name))?;
        self.admin
            .delete_queue(vhost, name, if_unused, if_empty)
            .await
    }

    /// queue.purge (404 if it does not exist): read on it.
    pub fn purge_queue(&self, vhost: &str, name: &str) -> AmqpResult<u32> {
        let (found, access) = self.access(vhost)?;
        found.queue_or_404(&short(name)?)?;
        access.check(Right::Read, Resource::Queue(name))?;
        self.admin.purge_queue(vhost, name)
    }

    /// The checks of a binding change: write on the destination, read on
    /// the source, the routing key against a topic source's topic
    /// permission.
    fn check_binding(&self, vhost: &str, binding: &BindingSpec) -> AmqpResult<()> {
        let (found, access) = self.access(vhost)?;
        let destination = match binding.destination_kind {
            DestinationKind::Queue => Resource::Queue(&binding.destination),
            DestinationKind::Exchange => Resource::Exchange(&binding.destination),
        };
        access.check_binding(destination, &binding.source)?;
        Self::check_topic(
            &access,
            &found,
            Right::Read,
            &binding.source,
            &binding.routing_key,
        )
    }

    /// queue.bind or exchange.bind: write on the destination, read on the
    /// source, the routing key against a topic source's topic permission.
    pub async fn bind(&self, vhost: &str, binding: BindingSpec) -> AmqpResult<()> {
        self.check_binding(vhost, &binding)?;
        self.admin.bind(vhost, binding).await
    }

    /// Removes the binding whose properties key is `key` (404 if there
    /// is none), with a binding's checks.
    pub async fn unbind(
        &self,
        vhost: &str,
        source: &str,
        destination: &str,
        destination_kind: DestinationKind,
        key: &str,
    ) -> AmqpResult<()> {
        let binding = self
            .admin
            .binding(vhost, source, destination, destination_kind, key)?;
        self.check_binding(vhost, &binding)?;
        self.admin
            .unbind(vhost, source, destination, destination_kind, key)
            .await
    }

    /// basic.publish: write on the exchange, the routing key against a
    /// topic exchange's topic permission; refused during a resource alarm
    /// (see [`Admin::publish`]).
    pub async fn publish(
        &self,
        vhost: &str,
        exchange: &str,
        routing_key: &str,
        properties: BasicProperties,
        body: Bytes,
    ) -> AmqpResult<bool> {
        let (found, access) = self.access(vhost)?;
        access.check(Right::Write, Resource::Exchange(exchange))?;
        Self::check_topic(&access, &found, Right::Write, exchange, routing_key)?;
        self.admin
            .publish(vhost, exchange, routing_key, properties, body)
            .await
    }

    /// basic.get: read on the queue.
    pub fn get(
        &self,
        vhost: &str,
        queue: &str,
        count: usize,
        mode: GetMode,
    ) -> AmqpResult<Vec<GotMessage>> {
        let (_, access) = self.access(vhost)?;
        access.check(Right::Read, Resource::Queue(queue))?;
        self.admin.get(vhost, queue, count, mode)
    }

    /// RabbitMQ's aliveness test, which declares, publishes to and gets
    /// from its queue on a channel of the caller's: configure and read on
    /// the queue, write on the default exchange.
    pub async fn aliveness_test(&self, vhost: &str) -> AmqpResult<()> {
        let (_, access) = self.access(vhost)?;
        access.check_queue_declare(ALIVENESS_QUEUE, None)?;
        access.check(Right::Write, Resource::Exchange(""))?;
        access.check(Right::Read, Resource::Queue(ALIVENESS_QUEUE))?;
        self.admin.aliveness_test(vhost).await
    }
}
