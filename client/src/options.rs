//! Option structs for the channel methods, one per method family, each
//! `Default` (every flag off), so calls read
//! `QueueDeclareOptions { durable: true, ..Default::default() }` instead of
//! runs of bools. `no_wait` asks the broker not to reply; errors then only
//! show up as a channel close on a later call.

/// Flags of `exchange.declare`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ExchangeDeclareOptions {
    /// Only check that the exchange exists (404 if not).
    pub passive: bool,
    /// Survive a broker restart.
    pub durable: bool,
    /// Delete when the last binding from it is removed.
    pub auto_delete: bool,
    /// Not publishable by clients, only via exchange-to-exchange bindings.
    pub internal: bool,
    /// Do not wait for `exchange.declare-ok`.
    pub no_wait: bool,
}

/// Flags of `exchange.delete`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ExchangeDeleteOptions {
    /// Only delete if it has no bindings (406 otherwise).
    pub if_unused: bool,
    /// Do not wait for `exchange.delete-ok`.
    pub no_wait: bool,
}

/// Flags of `exchange.bind` and `exchange.unbind`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ExchangeBindOptions {
    /// Do not wait for the `-ok` reply.
    pub no_wait: bool,
}

/// Flags of `queue.declare`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct QueueDeclareOptions {
    /// Only check that the queue exists (404 if not).
    pub passive: bool,
    /// Survive a broker restart.
    pub durable: bool,
    /// Used by this connection only, deleted when it closes.
    pub exclusive: bool,
    /// Deleted when its last consumer is cancelled.
    pub auto_delete: bool,
    /// Do not wait for `queue.declare-ok` (the name must then be given).
    pub no_wait: bool,
}

/// Flags of `queue.bind`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct QueueBindOptions {
    /// Do not wait for `queue.bind-ok`.
    pub no_wait: bool,
}

/// Flags of `queue.purge`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct QueuePurgeOptions {
    /// Do not wait for `queue.purge-ok` (the count is then 0).
    pub no_wait: bool,
}

/// Flags of `queue.delete`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct QueueDeleteOptions {
    /// Only delete if it has no consumers (406 otherwise).
    pub if_unused: bool,
    /// Only delete if it holds no messages (406 otherwise).
    pub if_empty: bool,
    /// Do not wait for `queue.delete-ok` (the count is then 0).
    pub no_wait: bool,
}

/// Flags of `basic.qos`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct BasicQosOptions {
    /// Prefetch window in bytes (0 = none; RabbitMQ rejects anything else).
    pub prefetch_size: u32,
    /// Apply to the whole channel rather than to each new consumer
    /// (RabbitMQ's reading of the flag).
    pub global: bool,
}

/// Flags of `basic.consume`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct BasicConsumeOptions {
    /// Do not deliver messages published on this connection.
    pub no_local: bool,
    /// Deliveries count as acknowledged when sent.
    pub no_ack: bool,
    /// Be the queue's only consumer (403 if it has others).
    pub exclusive: bool,
}

/// Flags of `basic.publish`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct BasicPublishOptions {
    /// Return the message (see `Channel::returns`) if no queue takes it.
    pub mandatory: bool,
}

/// Flags of `basic.get`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct BasicGetOptions {
    /// The message counts as acknowledged when sent.
    pub no_ack: bool,
}

/// Flags of `basic.ack`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct BasicAckOptions {
    /// Acknowledge every delivery up to and including the tag.
    pub multiple: bool,
}

/// Flags of `basic.nack`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct BasicNackOptions {
    /// Reject every delivery up to and including the tag.
    pub multiple: bool,
    /// Put the messages back in their queue (otherwise drop or dead-letter).
    pub requeue: bool,
}

/// Flags of `basic.reject`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct BasicRejectOptions {
    /// Put the message back in its queue (otherwise drop or dead-letter).
    pub requeue: bool,
}

/// Flags of `basic.recover`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct BasicRecoverOptions {
    /// Requeue the unacknowledged deliveries, possibly to other consumers
    /// (otherwise redeliver them to the same consumers). RabbitMQ
    /// implements only `true`, and closes the channel with 540
    /// NOT_IMPLEMENTED for `false`.
    pub requeue: bool,
}
