//! queue.declare, bind, unbind, purge and delete on a channel.

use super::Channel;
use crate::access::permissions::{Resource, Right};
use crate::error::{AmqpError, AmqpResult};
use crate::queue::{Deleted, QueueOptions};
use crate::vhost::{check_exclusive, BindingChange, QueueDeclaration};
use leveret_protocol::{
    QueueBind, QueueBindOk, QueueDeclare, QueueDeclareOk, QueueDelete, QueueDeleteOk, QueuePurge,
    QueuePurgeOk, QueueUnbind, QueueUnbindOk, ShortStr,
};

impl Channel {
    pub(super) async fn queue_declare(&mut self, declare: QueueDeclare) -> AmqpResult<()> {
        if declare.passive && declare.queue == super::reply_to::PSEUDO_QUEUE {
            // The direct reply-to pseudo-queue always "exists"; RabbitMQ
            // reports it with one consumer.
            if !declare.no_wait {
                self.reply(QueueDeclareOk {
                    queue: declare.queue,
                    message_count: 0,
                    consumer_count: 1,
                })
                .await;
            }
            return Ok(());
        }
        let connection_id = self.outbox().connection_id;
        let server_named = declare.queue.is_empty() && !declare.passive;
        let name = if server_named {
            super::names::unique_name("amq.gen-")
        } else {
            self.queue_name_or_last(declare.queue)?
        };
        if !declare.passive {
            let dead_letter_exchange = declare
                .arguments
                .get("x-dead-letter-exchange")
                .and_then(|v| v.as_bytes())
                .filter(|_| self.vhost.queue(&name).is_none())
                .map(String::from_utf8_lossy);
            self.access
                .current()?
                .check_queue_declare(&name.to_string_lossy(), dead_letter_exchange.as_deref())?;
        }
        let decl = QueueDeclaration {
            name,
            passive: declare.passive,
            server_named,
            options: QueueOptions {
                durable: declare.durable,
                exclusive_owner: declare.exclusive.then_some(connection_id),
                auto_delete: declare.auto_delete,
                arguments: declare.arguments,
            },
            max_queues: (self.core.limit_tables)
                .vhost(&self.vhost.name.to_string_lossy())
                .max_queues,
        };
        if !decl.passive {
            self.core.stats.queues_declared.inc();
        }
        let (queue, created) = self.vhost.declare_queue(decl, connection_id)?;
        if created {
            self.core.stats.queues_created.inc();
        }
        self.last_queue = Some(queue.name.clone());
        if queue.store_id().is_some() {
            self.definitions_on_disk().await?;
        }
        // The count leaves out messages that have expired.
        self.vhost.expire(&queue).await;
        if !declare.no_wait {
            self.reply(QueueDeclareOk {
                queue: queue.name.clone(),
                message_count: queue.message_count(),
                consumer_count: queue.consumer_count(),
            })
            .await;
        }
        Ok(())
    }

    /// An empty routing key with an empty queue name means the last queue's name.
    fn bind_names(
        &self,
        queue: ShortStr,
        routing_key: ShortStr,
    ) -> AmqpResult<(ShortStr, ShortStr)> {
        let shortcut = queue.is_empty();
        let queue = self.queue_name_or_last(queue)?;
        let routing_key = if shortcut && routing_key.is_empty() {
            queue.clone()
        } else {
            routing_key
        };
        Ok((queue, routing_key))
    }

    /// RabbitMQ's checks for a binding change: write on the queue, read
    /// on the exchange, and the routing key against a topic exchange's
    /// topic permission.
    fn allow_queue_binding(
        &mut self,
        queue: &ShortStr,
        exchange: &ShortStr,
        routing_key: &ShortStr,
    ) -> AmqpResult<()> {
        self.access.current()?.check_binding(
            Resource::Queue(&queue.to_string_lossy()),
            &exchange.to_string_lossy(),
        )?;
        self.allow_topic_binding(exchange, routing_key)
    }

    pub(super) async fn queue_bind(&mut self, bind: QueueBind) -> AmqpResult<()> {
        let (name, routing_key) = self.bind_names(bind.queue, bind.routing_key)?;
        self.allow_queue_binding(&name, &bind.exchange, &routing_key)?;
        let queue = self.vhost.queue_or_404(&name)?;
        check_exclusive(&queue, self.outbox().connection_id, &self.vhost.name)?;
        self.vhost.bind_queue(
            &queue,
            &bind.exchange,
            routing_key,
            bind.arguments,
            BindingChange::Bind,
        )?;
        if queue.store_id().is_some() && self.exchange_is_durable(&bind.exchange) {
            self.definitions_on_disk().await?;
        }
        if !bind.no_wait {
            self.reply(QueueBindOk {}).await;
        }
        Ok(())
    }

    /// queue.unbind; as in RabbitMQ, unbinding a missing queue or from a
    /// missing exchange succeeds.
    pub(super) async fn queue_unbind(&mut self, unbind: QueueUnbind) -> AmqpResult<()> {
        let (name, routing_key) = self.bind_names(unbind.queue, unbind.routing_key)?;
        self.allow_queue_binding(&name, &unbind.exchange, &routing_key)?;
        if let Some(queue) = self.vhost.queue(&name) {
            check_exclusive(&queue, self.outbox().connection_id, &self.vhost.name)?;
            if self.vhost.exchange(&unbind.exchange).is_some() {
                self.vhost.bind_queue(
                    &queue,
                    &unbind.exchange,
                    routing_key,
                    unbind.arguments,
                    BindingChange::Unbind,
                )?;
                if queue.store_id().is_some() && self.exchange_is_durable(&unbind.exchange) {
                    self.definitions_on_disk().await?;
                }
            }
        }
        self.reply(QueueUnbindOk {}).await;
        Ok(())
    }

    pub(super) async fn queue_purge(&mut self, purge: QueuePurge) -> AmqpResult<()> {
        let name = self.queue_name_or_last(purge.queue)?;
        self.allow_queue(Right::Read, name.as_bytes())?;
        let queue = self.vhost.queue_or_404(&name)?;
        check_exclusive(&queue, self.outbox().connection_id, &self.vhost.name)?;
        queue.refuse_on_stream("queue.purge")?;
        let message_count = queue.purge();
        if !purge.no_wait {
            self.reply(QueuePurgeOk { message_count }).await;
        }
        Ok(())
    }

    pub(super) async fn queue_delete(&mut self, delete: QueueDelete) -> AmqpResult<()> {
        let name = self.queue_name_or_last(delete.queue)?;
        self.allow_queue(Right::Configure, name.as_bytes())?;
        let deleted = match self.vhost.queue(&name) {
            // Deleting a queue that does not exist succeeds, as in RabbitMQ.
            None => Deleted::default(),
            Some(queue) => {
                check_exclusive(&queue, self.outbox().connection_id, &self.vhost.name)?;
                self.vhost.expire(&queue).await;
                // As RabbitMQ: not empty, then in use; in use decided
                // with no await before the delete (`Queue::take_unused`).
                if delete.if_empty && queue.message_count() > 0 {
                    return Err(AmqpError::precondition_failed(format_args!(
                        "queue '{}' in vhost '{}' not empty",
                        name, self.vhost.name
                    )));
                }
                if delete.if_unused && !queue.take_unused() {
                    return Err(AmqpError::precondition_failed(format_args!(
                        "queue '{}' in vhost '{}' in use",
                        name, self.vhost.name
                    )));
                }
                let deleted = self.vhost.delete_queue(&queue);
                if queue.store_id().is_some() {
                    if let Err(e) = self.definitions_on_disk().await {
                        deleted.notify();
                        return Err(e);
                    }
                }
                deleted
            }
        };
        if !delete.no_wait {
            let message_count = deleted.messages;
            self.reply(QueueDeleteOk { message_count }).await;
        }
        // As RabbitMQ: delete-ok first, then the consumers' basic.cancel.
        deleted.notify();
        Ok(())
    }
}
