//! exchange.declare, delete, bind and unbind on a channel.

use super::Channel;
use crate::error::AmqpResult;
use crate::exchange::ExchangeOptions;
use crate::vhost::{BindingChange, ExchangeDeclaration};
use leveret_protocol::{
    ExchangeBind, ExchangeBindOk, ExchangeDeclare, ExchangeDeclareOk, ExchangeDelete,
    ExchangeDeleteOk, ExchangeUnbind, ExchangeUnbindOk,
};

impl Channel {
    pub(super) async fn exchange_declare(&mut self, declare: ExchangeDeclare) -> AmqpResult<()> {
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
        if !declare.no_wait {
            self.reply(ExchangeDeclareOk {}).await;
        }
        Ok(())
    }

    pub(super) async fn exchange_delete(&mut self, delete: ExchangeDelete) -> AmqpResult<()> {
        self.vhost
            .delete_exchange(&delete.exchange, delete.if_unused)?;
        if !delete.no_wait {
            self.reply(ExchangeDeleteOk {}).await;
        }
        Ok(())
    }

    pub(super) async fn exchange_bind(&mut self, bind: ExchangeBind) -> AmqpResult<()> {
        self.vhost.bind_exchange(
            &bind.destination,
            &bind.source,
            bind.routing_key,
            bind.arguments,
            BindingChange::Bind,
        )?;
        if !bind.no_wait {
            self.reply(ExchangeBindOk {}).await;
        }
        Ok(())
    }

    pub(super) async fn exchange_unbind(&mut self, unbind: ExchangeUnbind) -> AmqpResult<()> {
        self.vhost.bind_exchange(
            &unbind.destination,
            &unbind.source,
            unbind.routing_key,
            unbind.arguments,
            BindingChange::Unbind,
        )?;
        if !unbind.no_wait {
            self.reply(ExchangeUnbindOk {}).await;
        }
        Ok(())
    }
}
