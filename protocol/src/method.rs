//! Every class and method of AMQP 0.9.1, with RabbitMQ's extensions
//! (confirm.*, basic.nack, exchange.bind/unbind, connection.blocked,
//! connection.update-secret), declared once in the table at the bottom of
//! this file. The table generates one struct per method, the [`Method`]
//! enum, and their decoders and encoders, so ids, names and argument lists
//! cannot drift apart.

use crate::error::{DecodeError, SyntaxProblem};
use crate::types::{FieldTable, LongStr, ShortStr};
use crate::wire::{in_field, Arg, BitReader, BitWriter, WireError};
use bytes::{BufMut, Bytes, BytesMut};

fn syntax(location: &'static str, error: nom::Err<WireError>) -> DecodeError {
    let wire = match error {
        nom::Err::Error(e) | nom::Err::Failure(e) => e,
        nom::Err::Incomplete(_) => WireError::new(SyntaxProblem::Truncated),
    };
    DecodeError::Syntax {
        location,
        field: wire.field,
        problem: wire.problem,
    }
}

macro_rules! methods {
    ($(
        $(#[$doc:meta])*
        $name:ident = ($class_id:literal, $method_id:literal) $wire_name:literal $(content=$content:literal)? {
            $($field:ident : $ty:ty),* $(,)?
        }
    )*) => {
        $(
            $(#[$doc])*
            #[derive(Debug, Clone, PartialEq, Default)]
            pub struct $name {
                $(
                    #[doc = concat!("The `", stringify!($field), "` argument.")]
                    pub $field: $ty,
                )*
            }

            impl $name {
                /// Class id on the wire.
                pub const CLASS_ID: u16 = $class_id;
                /// Method id on the wire.
                pub const METHOD_ID: u16 = $method_id;
                /// The spec's name, `class.method`.
                pub const NAME: &'static str = $wire_name;

                #[allow(unused_variables, unused_mut)]
                fn decode_args(src: &Bytes, input: &[u8]) -> Result<Self, DecodeError> {
                    let mut bits = BitReader::default();
                    let mut input = input;
                    $(
                        let $field = match in_field(<$ty as Arg>::read(src, input, &mut bits), stringify!($field)) {
                            Ok((rest, value)) => {
                                input = rest;
                                value
                            }
                            Err(e) => return Err(syntax($wire_name, e)),
                        };
                    )*
                    if !input.is_empty() {
                        return Err(DecodeError::Syntax {
                            location: $wire_name,
                            field: "",
                            problem: SyntaxProblem::TrailingBytes(input.len()),
                        });
                    }
                    Ok($name { $($field),* })
                }

                #[allow(unused_variables, unused_mut)]
                fn encode_args(&self, buf: &mut BytesMut) {
                    let mut bits = BitWriter::default();
                    $(Arg::write(&self.$field, buf, &mut bits);)*
                }
            }

            impl From<$name> for Method {
                fn from(m: $name) -> Method {
                    Method::$name(m)
                }
            }
        )*

        /// One decoded AMQP method.
        #[derive(Debug, Clone, PartialEq)]
        #[allow(clippy::large_enum_variant)]
        pub enum Method {
            $(
                $(#[$doc])*
                $name($name),
            )*
        }

        impl Method {
            /// Class id on the wire.
            pub fn class_id(&self) -> u16 {
                match self { $(Method::$name(_) => $class_id,)* }
            }

            /// Method id on the wire.
            pub fn method_id(&self) -> u16 {
                match self { $(Method::$name(_) => $method_id,)* }
            }

            /// The spec's name, `class.method`.
            pub fn name(&self) -> &'static str {
                match self { $(Method::$name(_) => $wire_name,)* }
            }

            /// Whether a content header and body follow this method.
            pub fn has_content(&self) -> bool {
                match self { $(Method::$name(_) => false $(|| $content)?,)* }
            }

            /// The name of the method with these ids, if it exists.
            pub fn name_of(class_id: u16, method_id: u16) -> Option<&'static str> {
                match (class_id, method_id) {
                    $(($class_id, $method_id) => Some($wire_name),)*
                    _ => None,
                }
            }

            /// The (class, method) ids of the method with this spec name.
            pub fn ids_of(name: &str) -> Option<(u16, u16)> {
                match name {
                    $($wire_name => Some(($class_id, $method_id)),)*
                    _ => None,
                }
            }

            /// Decodes a method frame's payload (class id, method id,
            /// arguments). `payload` must hold exactly one method: bytes
            /// left after the last argument are a syntax error.
            pub fn decode(payload: &Bytes) -> Result<Method, DecodeError> {
                if payload.len() < 4 {
                    return Err(DecodeError::Syntax {
                        location: "method frame",
                        field: "class_id",
                        problem: SyntaxProblem::Truncated,
                    });
                }
                let class_id = u16::from_be_bytes([payload[0], payload[1]]);
                let method_id = u16::from_be_bytes([payload[2], payload[3]]);
                let args = &payload[4..];
                match (class_id, method_id) {
                    $(($class_id, $method_id) => $name::decode_args(payload, args).map(Method::$name),)*
                    _ => Err(DecodeError::UnknownMethod { class_id, method_id }),
                }
            }

            /// Encodes class id, method id and arguments (a method frame's payload).
            pub fn encode(&self, buf: &mut BytesMut) {
                buf.put_u16(self.class_id());
                buf.put_u16(self.method_id());
                match self { $(Method::$name(m) => m.encode_args(buf),)* }
            }
        }
    };
}

methods! {
    /// connection.start: the server's greeting, properties and mechanisms.
    ConnectionStart = (10, 10) "connection.start" {
        version_major: u8, version_minor: u8, server_properties: FieldTable,
        mechanisms: LongStr, locales: LongStr,
    }
    /// connection.start-ok: the client's properties and chosen mechanism.
    ConnectionStartOk = (10, 11) "connection.start-ok" {
        client_properties: FieldTable, mechanism: ShortStr, response: LongStr, locale: ShortStr,
    }
    /// connection.secure: a SASL challenge.
    ConnectionSecure = (10, 20) "connection.secure" { challenge: LongStr }
    /// connection.secure-ok: a SASL response.
    ConnectionSecureOk = (10, 21) "connection.secure-ok" { response: LongStr }
    /// connection.tune: the server's limits.
    ConnectionTune = (10, 30) "connection.tune" { channel_max: u16, frame_max: u32, heartbeat: u16 }
    /// connection.tune-ok: the limits the client chose.
    ConnectionTuneOk = (10, 31) "connection.tune-ok" { channel_max: u16, frame_max: u32, heartbeat: u16 }
    /// connection.open: selects the virtual host.
    ConnectionOpen = (10, 40) "connection.open" { virtual_host: ShortStr, capabilities: ShortStr, insist: bool }
    /// connection.open-ok.
    ConnectionOpenOk = (10, 41) "connection.open-ok" { known_hosts: ShortStr }
    /// connection.close: closes the connection, with the reason.
    ConnectionClose = (10, 50) "connection.close" {
        reply_code: u16, reply_text: ShortStr, class_id: u16, method_id: u16,
    }
    /// connection.close-ok.
    ConnectionCloseOk = (10, 51) "connection.close-ok" {}
    /// connection.blocked (RabbitMQ): the server stopped reading publishes.
    ConnectionBlocked = (10, 60) "connection.blocked" { reason: ShortStr }
    /// connection.unblocked (RabbitMQ).
    ConnectionUnblocked = (10, 61) "connection.unblocked" {}
    /// connection.update-secret (RabbitMQ): new credentials for a live connection.
    ConnectionUpdateSecret = (10, 70) "connection.update-secret" { new_secret: LongStr, reason: ShortStr }
    /// connection.update-secret-ok (RabbitMQ).
    ConnectionUpdateSecretOk = (10, 71) "connection.update-secret-ok" {}

    /// channel.open.
    ChannelOpen = (20, 10) "channel.open" { out_of_band: ShortStr }
    /// channel.open-ok.
    ChannelOpenOk = (20, 11) "channel.open-ok" { channel_id: LongStr }
    /// channel.flow: asks the peer to pause or resume sending content.
    ChannelFlow = (20, 20) "channel.flow" { active: bool }
    /// channel.flow-ok.
    ChannelFlowOk = (20, 21) "channel.flow-ok" { active: bool }
    /// channel.close: closes the channel, with the reason.
    ChannelClose = (20, 40) "channel.close" {
        reply_code: u16, reply_text: ShortStr, class_id: u16, method_id: u16,
    }
    /// channel.close-ok.
    ChannelCloseOk = (20, 41) "channel.close-ok" {}

    /// access.request: obsolete access tickets, still sent by old clients.
    AccessRequest = (30, 10) "access.request" {
        realm: ShortStr, exclusive: bool, passive: bool, active: bool, write: bool, read: bool,
    }
    /// access.request-ok.
    AccessRequestOk = (30, 11) "access.request-ok" { ticket: u16 }

    /// exchange.declare.
    ExchangeDeclare = (40, 10) "exchange.declare" {
        ticket: u16, exchange: ShortStr, kind: ShortStr, passive: bool, durable: bool,
        auto_delete: bool, internal: bool, no_wait: bool, arguments: FieldTable,
    }
    /// exchange.declare-ok.
    ExchangeDeclareOk = (40, 11) "exchange.declare-ok" {}
    /// exchange.delete.
    ExchangeDelete = (40, 20) "exchange.delete" { ticket: u16, exchange: ShortStr, if_unused: bool, no_wait: bool }
    /// exchange.delete-ok.
    ExchangeDeleteOk = (40, 21) "exchange.delete-ok" {}
    /// exchange.bind (RabbitMQ): binds an exchange to an exchange.
    ExchangeBind = (40, 30) "exchange.bind" {
        ticket: u16, destination: ShortStr, source: ShortStr, routing_key: ShortStr,
        no_wait: bool, arguments: FieldTable,
    }
    /// exchange.bind-ok (RabbitMQ).
    ExchangeBindOk = (40, 31) "exchange.bind-ok" {}
    /// exchange.unbind (RabbitMQ).
    ExchangeUnbind = (40, 40) "exchange.unbind" {
        ticket: u16, destination: ShortStr, source: ShortStr, routing_key: ShortStr,
        no_wait: bool, arguments: FieldTable,
    }
    /// exchange.unbind-ok (RabbitMQ); its id is 51, not 41.
    ExchangeUnbindOk = (40, 51) "exchange.unbind-ok" {}

    /// queue.declare.
    QueueDeclare = (50, 10) "queue.declare" {
        ticket: u16, queue: ShortStr, passive: bool, durable: bool, exclusive: bool,
        auto_delete: bool, no_wait: bool, arguments: FieldTable,
    }
    /// queue.declare-ok.
    QueueDeclareOk = (50, 11) "queue.declare-ok" { queue: ShortStr, message_count: u32, consumer_count: u32 }
    /// queue.bind.
    QueueBind = (50, 20) "queue.bind" {
        ticket: u16, queue: ShortStr, exchange: ShortStr, routing_key: ShortStr,
        no_wait: bool, arguments: FieldTable,
    }
    /// queue.bind-ok.
    QueueBindOk = (50, 21) "queue.bind-ok" {}
    /// queue.purge.
    QueuePurge = (50, 30) "queue.purge" { ticket: u16, queue: ShortStr, no_wait: bool }
    /// queue.purge-ok.
    QueuePurgeOk = (50, 31) "queue.purge-ok" { message_count: u32 }
    /// queue.delete.
    QueueDelete = (50, 40) "queue.delete" {
        ticket: u16, queue: ShortStr, if_unused: bool, if_empty: bool, no_wait: bool,
    }
    /// queue.delete-ok.
    QueueDeleteOk = (50, 41) "queue.delete-ok" { message_count: u32 }
    /// queue.unbind.
    QueueUnbind = (50, 50) "queue.unbind" {
        ticket: u16, queue: ShortStr, exchange: ShortStr, routing_key: ShortStr, arguments: FieldTable,
    }
    /// queue.unbind-ok.
    QueueUnbindOk = (50, 51) "queue.unbind-ok" {}

    /// basic.qos: prefetch limits.
    BasicQos = (60, 10) "basic.qos" { prefetch_size: u32, prefetch_count: u16, global: bool }
    /// basic.qos-ok.
    BasicQosOk = (60, 11) "basic.qos-ok" {}
    /// basic.consume: starts a consumer.
    BasicConsume = (60, 20) "basic.consume" {
        ticket: u16, queue: ShortStr, consumer_tag: ShortStr, no_local: bool, no_ack: bool,
        exclusive: bool, no_wait: bool, arguments: FieldTable,
    }
    /// basic.consume-ok.
    BasicConsumeOk = (60, 21) "basic.consume-ok" { consumer_tag: ShortStr }
    /// basic.cancel: ends a consumer (sent by the server too, RabbitMQ's consumer_cancel_notify).
    BasicCancel = (60, 30) "basic.cancel" { consumer_tag: ShortStr, no_wait: bool }
    /// basic.cancel-ok.
    BasicCancelOk = (60, 31) "basic.cancel-ok" { consumer_tag: ShortStr }
    /// basic.publish: a message follows.
    BasicPublish = (60, 40) "basic.publish" content=true {
        ticket: u16, exchange: ShortStr, routing_key: ShortStr, mandatory: bool, immediate: bool,
    }
    /// basic.return: an unroutable message comes back.
    BasicReturn = (60, 50) "basic.return" content=true {
        reply_code: u16, reply_text: ShortStr, exchange: ShortStr, routing_key: ShortStr,
    }
    /// basic.deliver: a message for a consumer.
    BasicDeliver = (60, 60) "basic.deliver" content=true {
        consumer_tag: ShortStr, delivery_tag: u64, redelivered: bool, exchange: ShortStr,
        routing_key: ShortStr,
    }
    /// basic.get: fetch one message.
    BasicGet = (60, 70) "basic.get" { ticket: u16, queue: ShortStr, no_ack: bool }
    /// basic.get-ok: the fetched message follows.
    BasicGetOk = (60, 71) "basic.get-ok" content=true {
        delivery_tag: u64, redelivered: bool, exchange: ShortStr, routing_key: ShortStr,
        message_count: u32,
    }
    /// basic.get-empty.
    BasicGetEmpty = (60, 72) "basic.get-empty" { cluster_id: ShortStr }
    /// basic.ack (also a publisher confirm, from the server).
    BasicAck = (60, 80) "basic.ack" { delivery_tag: u64, multiple: bool }
    /// basic.reject.
    BasicReject = (60, 90) "basic.reject" { delivery_tag: u64, requeue: bool }
    /// basic.recover-async (deprecated).
    BasicRecoverAsync = (60, 100) "basic.recover-async" { requeue: bool }
    /// basic.recover.
    BasicRecover = (60, 110) "basic.recover" { requeue: bool }
    /// basic.recover-ok.
    BasicRecoverOk = (60, 111) "basic.recover-ok" {}
    /// basic.nack (RabbitMQ).
    BasicNack = (60, 120) "basic.nack" { delivery_tag: u64, multiple: bool, requeue: bool }

    /// confirm.select (RabbitMQ): publisher confirms on this channel.
    ConfirmSelect = (85, 10) "confirm.select" { no_wait: bool }
    /// confirm.select-ok (RabbitMQ).
    ConfirmSelectOk = (85, 11) "confirm.select-ok" {}

    /// tx.select: makes the channel transactional.
    TxSelect = (90, 10) "tx.select" {}
    /// tx.select-ok.
    TxSelectOk = (90, 11) "tx.select-ok" {}
    /// tx.commit.
    TxCommit = (90, 20) "tx.commit" {}
    /// tx.commit-ok.
    TxCommitOk = (90, 21) "tx.commit-ok" {}
    /// tx.rollback.
    TxRollback = (90, 30) "tx.rollback" {}
    /// tx.rollback-ok.
    TxRollbackOk = (90, 31) "tx.rollback-ok" {}
}

#[cfg(test)]
#[path = "method_tests.rs"]
mod tests;
