//! exchange.declare, delete, bind and unbind on a channel.

use super::Channel;
use crate::error::AmqpResult;
use crate::exchange::ExchangeOptions;
use crate::vhost::ExchangeDeclaration;
use leveret_protocol::{
    ExchangeBindOk, ExchangeDeclare, ExchangeDeclareOk, ExchangeDelete, ExchangeDeleteOk,
    ExchangeUnbindOk, FieldTable, ShortStr,
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

    pub(super) async fn exchange_bind(
        &mut self,
        destination: ShortStr,
        source: ShortStr,
        routing_key: ShortStr,
        arguments: FieldTable,
        no_wait: bool,
        bind: bool,
    ) -> AmqpResult<()> {
        self.vhost
            .bind_exchange(&destination, &source, routing_key, arguments, bind)?;
        if !no_wait {
            if bind {
                self.reply(ExchangeBindOk {}).await;
            } else {
                self.reply(ExchangeUnbindOk {}).await;
            }
        }
        Ok(())
    }
}
