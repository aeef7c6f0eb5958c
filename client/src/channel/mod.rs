//! [`Channel`]: the AMQP methods a client calls. Synchronous methods send
//! and wait for their `-ok` reply; once the broker closes the channel
//! every call fails with [`Error::ChannelClosed`] carrying its reply code
//! and text. The state shared with the connection's reader lives in
//! `state`.

mod state;

pub use self::state::OutboxSlot;
pub(crate) use self::state::{ChannelCore, ChannelShared, ChannelState, PendingKind, Reply};

use crate::confirm::{Confirms, PublishConfirm};
use crate::connection::ConnectionInner;
use crate::consumer::{
    Consumer, ConsumerEnd, ConsumerSlot, DeliverySink, Returns, DEFAULT_CONSUMER_BUFFER,
    RETURNS_BUFFER,
};
use crate::error::{Error, Result};
use crate::message::{Delivery, GetMessage, IntoShortStr};
use crate::options::*;
use bytes::Bytes;
use leveret_protocol::Outgoing;
use leveret_protocol::{
    BasicCancel, BasicConsume, BasicGet, BasicProperties, BasicQos, BasicRecover, ChannelClose,
    ChannelOpen, ConfirmSelect, ExchangeBind, ExchangeDeclare, ExchangeDelete, ExchangeUnbind,
    FieldTable, Method, QueueBind, QueueDeclare, QueueDelete, QueuePurge, QueueUnbind, ShortStr,
    TxCommit, TxRollback, TxSelect,
};
use std::sync::Arc;
use tokio::sync::mpsc;

/// What `queue.declare-ok` says.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct QueueInfo {
    /// The queue's name (the broker's choice if none was given).
    pub name: ShortStr,
    /// Messages ready for delivery.
    pub message_count: u32,
    /// Active consumers.
    pub consumer_count: u32,
}

/// What a channel handle holds; closes the channel when the last handle
/// (including its consumers') is dropped.
#[derive(Debug)]
struct ChannelInner {
    core: ChannelCore,
    /// Keeps the connection open while the channel is in use.
    _connection: Arc<ConnectionInner>,
}

impl Drop for ChannelInner {
    fn drop(&mut self) {
        let chan = &self.core.chan;
        let mut state = chan.lock();
        if chan.begin_close(&mut state) {
            self.core.conn.send_from_drop(Outgoing::Method {
                channel: chan.id,
                method: goodbye().into(),
            });
        }
    }
}

fn goodbye() -> ChannelClose {
    ChannelClose {
        reply_code: 200,
        reply_text: ShortStr::from_static("Goodbye"),
        class_id: 0,
        method_id: 0,
    }
}

/// An AMQP channel. Cloning gives another handle on the same channel, and
/// calls from several tasks may overlap (replies are matched in order).
#[derive(Debug, Clone)]
pub struct Channel {
    inner: Arc<ChannelInner>,
}

/// The expected reply, as a function pointer for the pending table.
macro_rules! expect {
    ($($variant:ident)|+) => {
        (|m: &Method| matches!(m, $(Method::$variant(_))|+)) as fn(&Method) -> bool
    };
}

fn unexpected(method: &Method) -> Error {
    Error::Protocol(format!("unexpected reply {}", method.name()))
}

impl Channel {
    pub(crate) async fn open(
        connection: Arc<ConnectionInner>,
        chan: Arc<ChannelShared>,
    ) -> Result<Channel> {
        let core = ChannelCore::new(Arc::clone(&connection.shared), chan);
        let channel = Channel {
            inner: Arc::new(ChannelInner {
                core,
                _connection: connection,
            }),
        };
        let open = ChannelOpen {
            out_of_band: ShortStr::default(),
        };
        if let Err(error) = channel.core().call(open, expect!(ChannelOpenOk)).await {
            let chan = &channel.core().chan;
            channel.core().conn.remove_channel(chan);
            chan.finish(error.clone());
            return Err(error);
        }
        Ok(channel)
    }

    fn core(&self) -> &ChannelCore {
        &self.inner.core
    }

    /// The channel number.
    pub fn id(&self) -> u16 {
        self.core().chan.id
    }

    /// Whether the channel is open (not closing or closed).
    pub fn is_open(&self) -> bool {
        self.core().chan.lock().status.check().is_ok()
    }

    /// Closes the channel (reply code 200) and waits for `channel.close-ok`.
    /// If the broker had already closed it, that error is returned.
    pub async fn close(&self) -> Result<()> {
        let core = self.core();
        if let Ok(permit) = core.conn.reserve().await {
            let mut state = core.chan.lock();
            if core.chan.begin_close(&mut state) {
                permit.send(Outgoing::Method {
                    channel: core.chan.id,
                    method: goodbye().into(),
                });
            }
        }
        match self.closed().await {
            Error::Closed => Ok(()),
            error => Err(error),
        }
    }

    /// Resolves once the channel has ended, with why: [`Error::Closed`]
    /// after [`Channel::close`], [`Error::ChannelClosed`] when the broker
    /// closed it, or the connection's error.
    pub async fn closed(&self) -> Error {
        let mut ended = self.core().chan.ended.subscribe();
        let result = match ended.wait_for(Option::is_some).await {
            Ok(error) => error.clone().unwrap_or(Error::Closed),
            Err(_) => Error::Closed,
        };
        result
    }

    /// Declares an exchange of type `kind` (`direct`, `fanout`, `topic`,
    /// `headers`, or a plugin's).
    pub async fn exchange_declare(
        &self,
        exchange: impl IntoShortStr,
        kind: impl IntoShortStr,
        options: ExchangeDeclareOptions,
        arguments: FieldTable,
    ) -> Result<()> {
        let method = ExchangeDeclare {
            ticket: 0,
            exchange: exchange.into_short_str()?,
            kind: kind.into_short_str()?,
            passive: options.passive,
            durable: options.durable,
            auto_delete: options.auto_delete,
            internal: options.internal,
            no_wait: options.no_wait,
            arguments,
        };
        self.core()
            .call_unless_no_wait(method, options.no_wait, expect!(ExchangeDeclareOk))
            .await
    }

    /// Deletes an exchange.
    pub async fn exchange_delete(
        &self,
        exchange: impl IntoShortStr,
        options: ExchangeDeleteOptions,
    ) -> Result<()> {
        let method = ExchangeDelete {
            ticket: 0,
            exchange: exchange.into_short_str()?,
            if_unused: options.if_unused,
            no_wait: options.no_wait,
        };
        self.core()
            .call_unless_no_wait(method, options.no_wait, expect!(ExchangeDeleteOk))
            .await
    }

    /// Binds exchange `destination` to exchange `source` (RabbitMQ's
    /// exchange-to-exchange bindings).
    pub async fn exchange_bind(
        &self,
        destination: impl IntoShortStr,
        source: impl IntoShortStr,
        routing_key: impl IntoShortStr,
        options: ExchangeBindOptions,
        arguments: FieldTable,
    ) -> Result<()> {
        let method = ExchangeBind {
            ticket: 0,
            destination: destination.into_short_str()?,
            source: source.into_short_str()?,
            routing_key: routing_key.into_short_str()?,
            no_wait: options.no_wait,
            arguments,
        };
        self.core()
            .call_unless_no_wait(method, options.no_wait, expect!(ExchangeBindOk))
            .await
    }

    /// Removes an exchange-to-exchange binding.
    pub async fn exchange_unbind(
        &self,
        destination: impl IntoShortStr,
        source: impl IntoShortStr,
        routing_key: impl IntoShortStr,
        options: ExchangeBindOptions,
        arguments: FieldTable,
    ) -> Result<()> {
        let method = ExchangeUnbind {
            ticket: 0,
            destination: destination.into_short_str()?,
            source: source.into_short_str()?,
            routing_key: routing_key.into_short_str()?,
            no_wait: options.no_wait,
            arguments,
        };
        self.core()
            .call_unless_no_wait(method, options.no_wait, expect!(ExchangeUnbindOk))
            .await
    }

    /// Declares a queue (an empty name asks the broker to pick one).
    pub async fn queue_declare(
        &self,
        queue: impl IntoShortStr,
        options: QueueDeclareOptions,
        arguments: FieldTable,
    ) -> Result<QueueInfo> {
        let queue = queue.into_short_str()?;
        let method = QueueDeclare {
            ticket: 0,
            queue: queue.clone(),
            passive: options.passive,
            durable: options.durable,
            exclusive: options.exclusive,
            auto_delete: options.auto_delete,
            no_wait: options.no_wait,
            arguments,
        };
        if options.no_wait {
            if queue.is_empty() {
                return Err(Error::InvalidArgument(
                    "queue.declare with no_wait needs a queue name".to_owned(),
                ));
            }
            self.core().send(method).await?;
            return Ok(QueueInfo {
                name: queue,
                message_count: 0,
                consumer_count: 0,
            });
        }
        match self
            .core()
            .call(method, expect!(QueueDeclareOk))
            .await?
            .method
        {
            Method::QueueDeclareOk(ok) => Ok(QueueInfo {
                name: ok.queue,
                message_count: ok.message_count,
                consumer_count: ok.consumer_count,
            }),
            other => Err(unexpected(&other)),
        }
    }

    /// Binds a queue to an exchange.
    pub async fn queue_bind(
        &self,
        queue: impl IntoShortStr,
        exchange: impl IntoShortStr,
        routing_key: impl IntoShortStr,
        options: QueueBindOptions,
        arguments: FieldTable,
    ) -> Result<()> {
        let method = QueueBind {
            ticket: 0,
            queue: queue.into_short_str()?,
            exchange: exchange.into_short_str()?,
            routing_key: routing_key.into_short_str()?,
            no_wait: options.no_wait,
            arguments,
        };
        self.core()
            .call_unless_no_wait(method, options.no_wait, expect!(QueueBindOk))
            .await
    }

    /// Removes a queue binding.
    pub async fn queue_unbind(
        &self,
        queue: impl IntoShortStr,
        exchange: impl IntoShortStr,
        routing_key: impl IntoShortStr,
        arguments: FieldTable,
    ) -> Result<()> {
        let method = QueueUnbind {
            ticket: 0,
            queue: queue.into_short_str()?,
            exchange: exchange.into_short_str()?,
            routing_key: routing_key.into_short_str()?,
            arguments,
        };
        self.core()
            .call(method, expect!(QueueUnbindOk))
            .await
            .map(drop)
    }

    /// Removes every ready message from a queue; returns how many.
    pub async fn queue_purge(
        &self,
        queue: impl IntoShortStr,
        options: QueuePurgeOptions,
    ) -> Result<u32> {
        let method = QueuePurge {
            ticket: 0,
            queue: queue.into_short_str()?,
            no_wait: options.no_wait,
        };
        if options.no_wait {
            return self.core().send(method).await.map(|()| 0);
        }
        match self
            .core()
            .call(method, expect!(QueuePurgeOk))
            .await?
            .method
        {
            Method::QueuePurgeOk(ok) => Ok(ok.message_count),
            other => Err(unexpected(&other)),
        }
    }

    /// Deletes a queue; returns how many messages it held.
    pub async fn queue_delete(
        &self,
        queue: impl IntoShortStr,
        options: QueueDeleteOptions,
    ) -> Result<u32> {
        let method = QueueDelete {
            ticket: 0,
            queue: queue.into_short_str()?,
            if_unused: options.if_unused,
            if_empty: options.if_empty,
            no_wait: options.no_wait,
        };
        if options.no_wait {
            return self.core().send(method).await.map(|()| 0);
        }
        match self
            .core()
            .call(method, expect!(QueueDeleteOk))
            .await?
            .method
        {
            Method::QueueDeleteOk(ok) => Ok(ok.message_count),
            other => Err(unexpected(&other)),
        }
    }

    /// Limits unacknowledged deliveries. Consumers started afterwards
    /// buffer at most `prefetch_count` deliveries.
    pub async fn basic_qos(&self, prefetch_count: u16, options: BasicQosOptions) -> Result<()> {
        let method = BasicQos {
            prefetch_size: options.prefetch_size,
            prefetch_count,
            global: options.global,
        };
        self.core().call(method, expect!(BasicQosOk)).await?;
        self.core().chan.lock().prefetch_count = prefetch_count;
        Ok(())
    }

    /// Publishes a message. Waits only for room in the connection's
    /// outbox; the returned [`PublishConfirm`] resolves to the broker's
    /// ack or nack in confirm mode (at once to
    /// [`crate::Confirmation::NotRequested`] otherwise). Unroutable
    /// mandatory messages come back on [`Channel::returns`].
    pub async fn basic_publish(
        &self,
        exchange: impl IntoShortStr,
        routing_key: impl IntoShortStr,
        options: BasicPublishOptions,
        properties: BasicProperties,
        body: Bytes,
    ) -> Result<PublishConfirm> {
        self.reserve()
            .await?
            .basic_publish(exchange, routing_key, options, properties, body)
    }

    /// Room for one publish in the connection's outbox, waiting for it:
    /// [`OutboxSlot::basic_publish`] then never waits, for a caller that
    /// must not hold what it publishes while waiting (a port's window
    /// under its lock).
    pub async fn reserve(&self) -> Result<OutboxSlot<'_>> {
        self.core().reserve().await
    }

    /// Room for one publish in the connection's outbox if there is some
    /// now (`None` if it is full).
    pub fn try_reserve(&self) -> Result<Option<OutboxSlot<'_>>> {
        self.core().try_reserve()
    }

    /// The stream of messages the broker returns on this channel
    /// (`basic.return`). Without one, returned messages are dropped; a
    /// second call replaces (and ends) the first stream. Its buffer holds
    /// [`RETURNS_BUFFER`] messages; when full, reading the connection
    /// pauses until it is drained.
    pub fn returns(&self) -> Returns {
        let (tx, rx) = mpsc::channel(RETURNS_BUFFER);
        let mut state = self.core().chan.lock();
        if state.status.check().is_ok() {
            state.returns = Some(tx);
        }
        Returns::new(rx)
    }

    /// Starts a consumer on `queue` (an empty `consumer_tag` lets the
    /// broker pick one). Its buffer holds the channel's prefetch count
    /// (set [`Channel::basic_qos`] first), or [`DEFAULT_CONSUMER_BUFFER`]
    /// deliveries without one.
    pub async fn basic_consume(
        &self,
        queue: impl IntoShortStr,
        consumer_tag: impl IntoShortStr,
        options: BasicConsumeOptions,
        arguments: FieldTable,
    ) -> Result<Consumer> {
        self.consume(queue, consumer_tag, options, arguments, None)
            .await
    }

    /// [`Channel::basic_consume`] (with a tag the broker picks) whose
    /// deliveries `sink` takes on the connection's reader, as they are
    /// read; those it gives back go through the consumer's buffer.
    pub async fn basic_consume_into(
        &self,
        queue: impl IntoShortStr,
        options: BasicConsumeOptions,
        arguments: FieldTable,
        sink: Arc<dyn DeliverySink>,
    ) -> Result<Consumer> {
        self.consume(queue, "", options, arguments, Some(sink))
            .await
    }

    async fn consume(
        &self,
        queue: impl IntoShortStr,
        consumer_tag: impl IntoShortStr,
        options: BasicConsumeOptions,
        arguments: FieldTable,
        sink: Option<Arc<dyn DeliverySink>>,
    ) -> Result<Consumer> {
        let method = BasicConsume {
            ticket: 0,
            queue: queue.into_short_str()?,
            consumer_tag: consumer_tag.into_short_str()?,
            no_local: options.no_local,
            no_ack: options.no_ack,
            exclusive: options.exclusive,
            no_wait: false,
            arguments,
        };
        let capacity = match self.core().chan.lock().prefetch_count {
            0 => DEFAULT_CONSUMER_BUFFER,
            n => usize::from(n),
        };
        let (slot, rx, shared) = ConsumerSlot::new(capacity, sink);
        let reply = self
            .core()
            .call_with(
                method,
                expect!(BasicConsumeOk),
                PendingKind::Consume(slot),
                |_| {},
            )
            .await?;
        match reply.method {
            Method::BasicConsumeOk(ok) => {
                Ok(Consumer::new(ok.consumer_tag, rx, shared, self.clone()))
            }
            other => Err(unexpected(&other)),
        }
    }

    /// Cancels a consumer and waits for `basic.cancel-ok`; its stream ends
    /// with [`ConsumerEnd::Cancelled`] after the deliveries already
    /// buffered. A delivery that arrives for it while its buffer is full is
    /// dropped rather than waited for (waiting could never end if nobody
    /// drains the stream): unacknowledged, it is requeued when the channel
    /// closes; with `no_ack` it is lost.
    pub async fn basic_cancel(&self, consumer_tag: impl IntoShortStr) -> Result<()> {
        let consumer_tag = consumer_tag.into_short_str()?;
        if let Some(slot) = self.core().chan.lock().consumers.get(&consumer_tag) {
            slot.shared.cancelling.send_replace(true);
        }
        let method = BasicCancel {
            consumer_tag,
            no_wait: false,
        };
        self.core()
            .call_with(method, expect!(BasicCancelOk), PendingKind::Cancel, |_| {})
            .await
            .map(drop)
    }

    /// From a dropped [`Consumer`]: forget it and cancel it without waiting.
    pub(crate) fn cancel_on_drop(&self, consumer_tag: &ShortStr) {
        let core = self.core();
        let mut state = core.chan.lock();
        if let Some(slot) = state.consumers.remove(consumer_tag) {
            slot.end(ConsumerEnd::Cancelled);
        }
        if state.status.check().is_ok() {
            core.conn.send_from_drop(Outgoing::Method {
                channel: core.chan.id,
                method: BasicCancel {
                    consumer_tag: consumer_tag.clone(),
                    no_wait: true,
                }
                .into(),
            });
        }
    }

    /// Fetches one message, or `None` if the queue is empty.
    pub async fn basic_get(
        &self,
        queue: impl IntoShortStr,
        options: BasicGetOptions,
    ) -> Result<Option<GetMessage>> {
        let method = BasicGet {
            ticket: 0,
            queue: queue.into_short_str()?,
            no_ack: options.no_ack,
        };
        let reply = self
            .core()
            .call(method, expect!(BasicGetOk | BasicGetEmpty))
            .await?;
        match reply.method {
            Method::BasicGetOk(ok) => Ok(Some(GetMessage {
                delivery: Delivery::from_get(
                    ok.delivery_tag,
                    ok.redelivered,
                    ok.exchange,
                    ok.routing_key,
                    reply.content.unwrap_or_default(),
                    self.core().clone(),
                ),
                message_count: ok.message_count,
            })),
            Method::BasicGetEmpty(_) => Ok(None),
            other => Err(unexpected(&other)),
        }
    }

    /// Acknowledges a delivery (or, with `multiple`, every one up to it).
    /// An unknown tag makes the broker close the channel with 406
    /// PRECONDITION_FAILED, which later calls report.
    pub async fn basic_ack(&self, delivery_tag: u64, options: BasicAckOptions) -> Result<()> {
        self.core().basic_ack(delivery_tag, options).await
    }

    /// Rejects a delivery, or with `multiple` every one up to it.
    pub async fn basic_nack(&self, delivery_tag: u64, options: BasicNackOptions) -> Result<()> {
        self.core().basic_nack(delivery_tag, options).await
    }

    /// Rejects one delivery.
    pub async fn basic_reject(&self, delivery_tag: u64, options: BasicRejectOptions) -> Result<()> {
        self.core().basic_reject(delivery_tag, options).await
    }

    /// Redelivers every unacknowledged delivery of the channel
    /// (`basic.recover`; RabbitMQ supports only `requeue: true`).
    pub async fn basic_recover(&self, options: BasicRecoverOptions) -> Result<()> {
        let BasicRecoverOptions { requeue } = options;
        self.core()
            .call(BasicRecover { requeue }, expect!(BasicRecoverOk))
            .await
            .map(drop)
    }

    /// Puts the channel in confirm mode: from now on every publish is
    /// numbered and its [`PublishConfirm`] resolves to the broker's answer.
    pub async fn confirm_select(&self) -> Result<()> {
        // Numbering starts with the next publish after confirm.select, so
        // the table is created as the method is queued.
        self.core()
            .call_with(
                ConfirmSelect { no_wait: false },
                expect!(ConfirmSelectOk),
                PendingKind::Plain,
                |state: &mut ChannelState| {
                    if state.confirms.is_none() {
                        state.confirms = Some(Confirms::new());
                    }
                },
            )
            .await
            .map(drop)
    }

    /// Waits until every publish so far is confirmed; true if all were
    /// acked (none nacked) since the previous call.
    pub async fn wait_for_confirms(&self) -> Result<bool> {
        let chan = &self.core().chan;
        loop {
            let notified = chan.confirms_settled.notified();
            tokio::pin!(notified);
            notified.as_mut().enable();
            {
                let mut state = chan.lock();
                if let self::state::ChanStatus::Closed(error) = &state.status {
                    return Err(error.clone());
                }
                let Some(confirms) = state.confirms.as_mut() else {
                    return Err(Error::InvalidArgument(
                        "the channel is not in confirm mode".to_owned(),
                    ));
                };
                if let Some(all_acked) = confirms.take_if_settled() {
                    return Ok(all_acked);
                }
            }
            notified.await;
        }
    }

    /// Makes the channel transactional.
    pub async fn tx_select(&self) -> Result<()> {
        self.core()
            .call(TxSelect {}, expect!(TxSelectOk))
            .await
            .map(drop)
    }

    /// Commits the publishes and acks since the last commit or rollback.
    pub async fn tx_commit(&self) -> Result<()> {
        self.core()
            .call(TxCommit {}, expect!(TxCommitOk))
            .await
            .map(drop)
    }

    /// Discards the publishes and acks since the last commit or rollback.
    pub async fn tx_rollback(&self) -> Result<()> {
        self.core()
            .call(TxRollback {}, expect!(TxRollbackOk))
            .await
            .map(drop)
    }
}
