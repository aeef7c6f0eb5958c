//! exchange.declare, delete, bind and unbind on a channel.

use super::Channel;
use crate::access::permissions::{Resource, Right};
use crate::error::AmqpResult;
use crate::exchange::ExchangeOptions;
use crate::vhost::{BindingChange, ExchangeDeclaration};
use leveret_protocol::{
    ExchangeBind, ExchangeBindOk, ExchangeDeclare, ExchangeDeclareOk, ExchangeDelete,
    ExchangeDeleteOk, ExchangeUnbind, ExchangeUnbindOk, ShortStr,
};

impl Channel {
    pub(super) async fn exchange_declare(&mut self, declare: ExchangeDeclare) -> AmqpResult<()> {
        let durable = declare.durable;
        // RabbitMQ's checks: configure on the exchange (the default
        // exchange is refused by the vhost with its own text), and when it
        // is created with an alternate exchange, read on it and write on
        // the alternate.
        if !declare.passive && !declare.exchange.is_empty() {
            let alternate = declare
                .arguments
                .get("alternate-exchange")
                .and_then(|v| v.as_bytes())
                .filter(|_| self.vhost.exchange(&declare.exchange).is_none())
                .map(String::from_utf8_lossy);
            self.access.current()?.check_exchange_declare(
                &declare.exchange.to_string_lossy(),
                alternate.as_deref(),
            )?;
        }
        self.vhost.declare_exchange(ExchangeDeclaration {
            name: declare.exchange,
            kind: declare.kind,
            passive: declare.passive,
            options: ExchangeOptions {
                durable: declare.durable,
                auto_delete: declare.auto_delete,
                internal: declare.internal,
                arguments: declare.arguments,
            },
        })?;
        if durable {
            self.definitions_on_disk().await?;
        }
        if !declare.no_wait {
            self.reply(ExchangeDeclareOk {}).await;
        }
        Ok(())
    }

    pub(super) async fn exchange_delete(&mut self, delete: ExchangeDelete) -> AmqpResult<()> {
        if !delete.exchange.is_empty() {
            self.allow_exchange(Right::Configure, delete.exchange.as_bytes())?;
        }
        let durable = self.exchange_is_durable(&delete.exchange);
        self.vhost
            .delete_exchange(&delete.exchange, delete.if_unused)?;
        if durable {
            self.definitions_on_disk().await?;
        }
        if !delete.no_wait {
            self.reply(ExchangeDeleteOk {}).await;
        }
        Ok(())
    }

    pub(super) async fn exchange_bind(&mut self, bind: ExchangeBind) -> AmqpResult<()> {
        self.allow_binding(&bind.destination, &bind.source, &bind.routing_key)?;
        self.vhost.bind_exchange(
            &bind.destination,
            &bind.source,
            bind.routing_key,
            bind.arguments,
            BindingChange::Bind,
        )?;
        if self.exchange_is_durable(&bind.source) && self.exchange_is_durable(&bind.destination) {
            self.definitions_on_disk().await?;
        }
        if !bind.no_wait {
            self.reply(ExchangeBindOk {}).await;
        }
        Ok(())
    }

    pub(super) async fn exchange_unbind(&mut self, unbind: ExchangeUnbind) -> AmqpResult<()> {
        self.allow_binding(&unbind.destination, &unbind.source, &unbind.routing_key)?;
        self.vhost.bind_exchange(
            &unbind.destination,
            &unbind.source,
            unbind.routing_key,
            unbind.arguments,
            BindingChange::Unbind,
        )?;
        if self.exchange_is_durable(&unbind.source) && self.exchange_is_durable(&unbind.destination)
        {
            self.definitions_on_disk().await?;
        }
        if !unbind.no_wait {
            self.reply(ExchangeUnbindOk {}).await;
        }
        Ok(())
    }

    /// RabbitMQ's checks for a binding change between exchanges: write on
    /// the destination, read on the source, and the routing key against
    /// a topic source's topic permission.
    fn allow_binding(
        &mut self,
        destination: &ShortStr,
        source: &ShortStr,
        routing_key: &ShortStr,
    ) -> AmqpResult<()> {
        self.access.current()?.check_binding(
            Resource::Exchange(&destination.to_string_lossy()),
            &source.to_string_lossy(),
        )?;
        self.allow_topic_binding(source, routing_key)
    }

    /// Whether `name` is a durable exchange: only changes to those (and
    /// to bindings between durable ends) are written to disk.
    pub(super) fn exchange_is_durable(&self, name: &ShortStr) -> bool {
        self.vhost
            .exchange(name)
            .is_some_and(|exchange| exchange.options.durable)
    }
}
