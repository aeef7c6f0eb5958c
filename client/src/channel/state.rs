//! A channel's state, shared by its handles and the connection's reader:
//! its status, the calls waiting for their `-ok` reply (in order, since a
//! channel answers synchronous methods in order), its consumers, the
//! receiver of returned messages and the outstanding publisher confirms.
//! [`ChannelCore`] sends on behalf of a channel, each item through a
//! [`OutboxSlot`] of room reserved in the connection's outbox (waited for, or
//! taken only if there is room now; in process, a publish is handed to the
//! broker's connection loop and handled on the sending thread when that
//! loop is free and nothing sent before waits, see
//! `leveret_broker::DirectLoop`); [`ChannelShared`] is what the reader
//! drives.

use crate::confirm::{Confirms, PublishConfirm};
use crate::connection::Shared;
use crate::consumer::{ConsumerEnd, ConsumerShared, ConsumerSlot, DeliverySink};
use crate::error::{Error, Result};
use crate::message::{Content, Delivery, IntoShortStr, ReturnedMessage};
use crate::options::{BasicAckOptions, BasicNackOptions, BasicPublishOptions, BasicRejectOptions};
use bytes::Bytes;
use leveret_protocol::handoff;
use leveret_protocol::Outgoing;
use leveret_protocol::{
    BasicAck, BasicNack, BasicProperties, BasicPublish, BasicReject, Method, ShortStr,
};
use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex, MutexGuard};
use tokio::sync::{mpsc, oneshot, watch, Notify};

/// A reply to a synchronous method, with content for `basic.get-ok`.
#[derive(Debug)]
pub(crate) struct Reply {
    pub(crate) method: Method,
    pub(crate) content: Option<Content>,
}

/// What the reader does besides answering the caller.
#[derive(Debug)]
pub(crate) enum PendingKind {
    Plain,
    /// On `basic.consume-ok`, register the consumer under the tag, before
    /// any delivery for it can be read.
    Consume(ConsumerSlot),
    /// On `basic.cancel-ok`, end the consumer.
    Cancel,
}

/// A call waiting for its reply.
#[derive(Debug)]
pub(crate) struct Pending {
    request: &'static str,
    expect: fn(&Method) -> bool,
    kind: PendingKind,
    tx: oneshot::Sender<Result<Reply>>,
}

/// Where the channel is in its life.
#[derive(Debug)]
pub(crate) enum ChanStatus {
    Open,
    /// channel.close sent by this client; waiting for close-ok.
    Closing,
    Closed(Error),
}

impl ChanStatus {
    pub(crate) fn check(&self) -> Result<()> {
        match self {
            ChanStatus::Open => Ok(()),
            ChanStatus::Closing => Err(Error::Closed),
            ChanStatus::Closed(error) => Err(error.clone()),
        }
    }
}

#[derive(Debug)]
pub(crate) struct ChannelState {
    pub(crate) status: ChanStatus,
    pending: VecDeque<Pending>,
    pub(crate) consumers: HashMap<ShortStr, ConsumerSlot>,
    pub(crate) returns: Option<mpsc::Sender<ReturnedMessage>>,
    pub(crate) confirms: Option<Confirms>,
    pub(crate) prefetch_count: u16,
}

/// Where the reader hands a consumer's delivery: its sink first, if it
/// has one, then its buffer.
pub(crate) struct ConsumerRoute {
    pub(crate) tx: mpsc::Sender<Delivery>,
    pub(crate) shared: Arc<ConsumerShared>,
    pub(crate) sink: Option<Arc<dyn DeliverySink>>,
}

/// The part of a channel the reader drives.
#[derive(Debug)]
pub(crate) struct ChannelShared {
    pub(crate) id: u16,
    state: Mutex<ChannelState>,
    /// True once closing has begun (by either side).
    pub(crate) closing: watch::Sender<bool>,
    /// Set once, to why the channel ended.
    pub(crate) ended: watch::Sender<Option<Error>>,
    /// Woken when no confirm is outstanding any more, or on close.
    pub(crate) confirms_settled: Notify,
}

impl ChannelShared {
    pub(crate) fn new(id: u16) -> Self {
        ChannelShared {
            id,
            state: Mutex::new(ChannelState {
                status: ChanStatus::Open,
                pending: VecDeque::new(),
                consumers: HashMap::new(),
                returns: None,
                confirms: None,
                prefetch_count: 0,
            }),
            closing: watch::Sender::new(false),
            ended: watch::Sender::new(None),
            confirms_settled: Notify::new(),
        }
    }

    pub(crate) fn lock(&self) -> MutexGuard<'_, ChannelState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    pub(crate) fn is_closing(&self) -> bool {
        matches!(self.lock().status, ChanStatus::Closing)
    }

    /// Marks the channel closing; true if it was open.
    pub(crate) fn begin_close(&self, state: &mut ChannelState) -> bool {
        if !matches!(state.status, ChanStatus::Open) {
            return false;
        }
        state.status = ChanStatus::Closing;
        self.closing.send_replace(true);
        true
    }

    /// Ends the channel: every waiting call, consumer and confirm gets
    /// `error`, and so does every later call.
    pub(crate) fn finish(&self, error: Error) {
        let (pending, consumers) = {
            let mut state = self.lock();
            if let ChanStatus::Closed(_) = state.status {
                return;
            }
            state.status = ChanStatus::Closed(error.clone());
            state.returns = None;
            if let Some(confirms) = state.confirms.as_mut() {
                confirms.fail(&error);
            }
            (
                std::mem::take(&mut state.pending),
                std::mem::take(&mut state.consumers),
            )
        };
        for pending in pending {
            let _ = pending.tx.send(Err(error.clone()));
        }
        for (_, slot) in consumers {
            slot.end(ConsumerEnd::ChannelClosed(error.clone()));
        }
        self.closing.send_replace(true);
        self.confirms_settled.notify_waiters();
        self.ended.send_replace(Some(error));
    }

    /// Hands a reply to the oldest waiting call; an error text if nothing
    /// was waiting for this method.
    pub(crate) fn complete(&self, reply: Reply) -> std::result::Result<(), String> {
        let mut state = self.lock();
        let Some(pending) = state.pending.pop_front() else {
            return Err(format!(
                "unexpected {} on channel {}",
                reply.method.name(),
                self.id
            ));
        };
        if !(pending.expect)(&reply.method) {
            let text = format!(
                "{} on channel {} in reply to {}",
                reply.method.name(),
                self.id,
                pending.request
            );
            // Left waiting: the connection's end fails it with the
            // protocol error this becomes.
            state.pending.push_front(pending);
            return Err(text);
        }
        match (pending.kind, &reply.method) {
            (PendingKind::Consume(slot), Method::BasicConsumeOk(ok)) => {
                state.consumers.insert(ok.consumer_tag.clone(), slot);
            }
            (PendingKind::Cancel, Method::BasicCancelOk(ok)) => {
                if let Some(slot) = state.consumers.remove(&ok.consumer_tag) {
                    slot.end(ConsumerEnd::Cancelled);
                }
            }
            _ => {}
        }
        drop(state);
        let _ = pending.tx.send(Ok(reply));
        Ok(())
    }

    /// A consumer's sender and sink, for a delivery.
    pub(crate) fn consumer(&self, tag: &ShortStr) -> Option<ConsumerRoute> {
        let state = self.lock();
        let slot = state.consumers.get(tag)?;
        Some(ConsumerRoute {
            tx: slot.tx.clone(),
            shared: Arc::clone(&slot.shared),
            sink: slot.sink.clone(),
        })
    }

    /// The broker cancelled a consumer.
    pub(crate) fn cancelled_by_broker(&self, tag: &ShortStr) {
        let slot = self.lock().consumers.remove(tag);
        if let Some(slot) = slot {
            slot.end(ConsumerEnd::CancelledByBroker);
        }
    }

    /// Applies a publisher confirm.
    pub(crate) fn confirmed(&self, tag: u64, multiple: bool, ack: bool) {
        let settled = match self.lock().confirms.as_mut() {
            Some(confirms) => confirms.settle(tag, multiple, ack),
            None => {
                tracing::debug!(
                    channel = self.id,
                    "confirm on a channel not in confirm mode"
                );
                false
            }
        };
        if settled {
            self.confirms_settled.notify_waiters();
        }
    }

    /// Hands a returned message to the channel's [`crate::Returns`].
    pub(crate) async fn returned(&self, message: ReturnedMessage, conn: &Shared) {
        let Some(tx) = self.lock().returns.clone() else {
            tracing::debug!(
                channel = self.id,
                code = message.reply_code,
                "returned message dropped: nobody asked for returns"
            );
            return;
        };
        let message = match tx.try_send(message) {
            Ok(()) | Err(mpsc::error::TrySendError::Closed(_)) => return,
            Err(mpsc::error::TrySendError::Full(message)) => message,
        };
        let mut chan_closing = self.closing.subscribe();
        let mut conn_closing = conn.closing.subscribe();
        tokio::select! {
            _ = tx.send(message) => {}
            _ = chan_closing.wait_for(|c| *c) => {}
            _ = conn_closing.wait_for(|c| *c) => {}
        }
    }
}

/// Sends on behalf of a channel; cheap to clone (two `Arc`s), and what a
/// [`Delivery`] holds to acknowledge itself.
#[derive(Debug, Clone)]
pub(crate) struct ChannelCore {
    pub(crate) conn: Arc<Shared>,
    pub(crate) chan: Arc<ChannelShared>,
}

impl ChannelCore {
    pub(crate) fn new(conn: Arc<Shared>, chan: Arc<ChannelShared>) -> Self {
        ChannelCore { conn, chan }
    }

    /// Fails once the connection is closing: a frame queued behind
    /// connection.close would be discarded by the broker, unanswered.
    fn check_connection(&self) -> Result<()> {
        if *self.conn.closing.borrow() {
            return Err(self.conn.error());
        }
        Ok(())
    }

    /// Sends a synchronous method and waits for its reply. `prepare` runs
    /// under the channel's lock just before the method is queued.
    pub(crate) async fn call_with(
        &self,
        method: impl Into<Method>,
        expect: fn(&Method) -> bool,
        kind: PendingKind,
        prepare: impl FnOnce(&mut ChannelState),
    ) -> Result<Reply> {
        let method = method.into();
        let permit = self.conn.reserve().await?;
        let rx = {
            let mut state = self.chan.lock();
            state.status.check()?;
            self.check_connection()?;
            prepare(&mut state);
            let (tx, rx) = oneshot::channel();
            state.pending.push_back(Pending {
                request: method.name(),
                expect,
                kind,
                tx,
            });
            permit.send(Outgoing::Method {
                channel: self.chan.id,
                method,
            });
            rx
        };
        match rx.await {
            Ok(result) => result,
            Err(_) => Err(self.conn.error()),
        }
    }

    /// [`ChannelCore::call_with`] with nothing to prepare.
    pub(crate) async fn call(
        &self,
        method: impl Into<Method>,
        expect: fn(&Method) -> bool,
    ) -> Result<Reply> {
        self.call_with(method, expect, PendingKind::Plain, |_| {})
            .await
    }

    /// Sends `method` and waits for its -ok reply, or with `no_wait` only
    /// sends it (the reply was waived).
    pub(crate) async fn call_unless_no_wait(
        &self,
        method: impl Into<Method>,
        no_wait: bool,
        expect: fn(&Method) -> bool,
    ) -> Result<()> {
        if no_wait {
            return self.send(method).await;
        }
        self.call(method, expect).await.map(drop)
    }

    /// Sends a method that has no reply (or whose reply was waived).
    pub(crate) async fn send(&self, method: impl Into<Method>) -> Result<()> {
        self.reserve().await?.send(method)
    }

    /// Waits for room for one item in the connection's outbox.
    pub(crate) async fn reserve(&self) -> Result<OutboxSlot<'_>> {
        let permit = self.conn.reserve().await?;
        Ok(OutboxSlot { core: self, permit })
    }

    /// Room for one item in the connection's outbox if there is some now
    /// (`None` if it is full), without waiting: for callers that must not
    /// wait and have somewhere else to turn when it is full.
    pub(crate) fn try_reserve(&self) -> Result<Option<OutboxSlot<'_>>> {
        match self.conn.tx.try_reserve() {
            Ok(permit) => Ok(Some(OutboxSlot { core: self, permit })),
            Err(handoff::TrySendError::Full(())) => Ok(None),
            Err(handoff::TrySendError::Closed(())) => Err(self.conn.error()),
        }
    }

    pub(crate) async fn basic_ack(
        &self,
        delivery_tag: u64,
        options: BasicAckOptions,
    ) -> Result<()> {
        self.send(BasicAck {
            delivery_tag,
            multiple: options.multiple,
        })
        .await
    }

    pub(crate) async fn basic_nack(
        &self,
        delivery_tag: u64,
        options: BasicNackOptions,
    ) -> Result<()> {
        self.send(BasicNack {
            delivery_tag,
            multiple: options.multiple,
            requeue: options.requeue,
        })
        .await
    }

    pub(crate) async fn basic_reject(
        &self,
        delivery_tag: u64,
        options: BasicRejectOptions,
    ) -> Result<()> {
        self.send(BasicReject {
            delivery_tag,
            requeue: options.requeue,
        })
        .await
    }
}

/// Room reserved for one item of a channel in its connection's outbox
/// ([`crate::Channel::reserve`], [`crate::Channel::try_reserve`],
/// [`crate::Delivery::try_reserve_ack`]): sending through it never waits.
/// Dropping it unused gives the room back.
pub struct OutboxSlot<'a> {
    core: &'a ChannelCore,
    permit: handoff::Permit<'a, Outgoing>,
}

impl std::fmt::Debug for OutboxSlot<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OutboxSlot")
            .field("channel", &self.core.chan.id)
            .finish_non_exhaustive()
    }
}

impl OutboxSlot<'_> {
    /// Sends a method that has no reply (or whose reply was waived).
    pub(crate) fn send(self, method: impl Into<Method>) -> Result<()> {
        let core = self.core;
        let state = core.chan.lock();
        state.status.check()?;
        core.check_connection()?;
        let item = Outgoing::Method {
            channel: core.chan.id,
            method: method.into(),
        };
        // In process, on a thread running a broker connection's loop for
        // its own publish, an inline delivery's single-tag ack is deferred
        // until that run lets go, then handled on this thread with no
        // broker thread woken; any other method goes through the link, in
        // order after what was deferred (`leveret_broker::DirectLoop::defer`,
        // which states the ordering limit against other threads).
        #[cfg(feature = "embedded")]
        let item = match core.conn.here.as_ref() {
            Some(here) if leveret_broker::DirectLoop::may_defer() => {
                match core.conn.tx.clone().try_reserve_owned() {
                    Ok(room) => match here.defer(item, room) {
                        Ok(()) => return Ok(()),
                        Err((item, _room)) => item,
                    },
                    Err(_) => item,
                }
            }
            _ => item,
        };
        self.permit.send(item);
        Ok(())
    }

    /// [`crate::Channel::basic_publish`] through this room, without
    /// waiting: the message is numbered for its confirm in confirm mode.
    pub fn basic_publish(
        self,
        exchange: impl IntoShortStr,
        routing_key: impl IntoShortStr,
        options: BasicPublishOptions,
        properties: BasicProperties,
        body: Bytes,
    ) -> Result<PublishConfirm> {
        let method = BasicPublish {
            ticket: 0,
            exchange: exchange.into_short_str()?,
            routing_key: routing_key.into_short_str()?,
            mandatory: options.mandatory,
            immediate: false,
        };
        let core = self.core;
        let mut state = core.chan.lock();
        state.status.check()?;
        core.check_connection()?;
        let confirm = match state.confirms.as_mut() {
            Some(confirms) => confirms.register(),
            None => PublishConfirm::not_requested(),
        };
        let item = Outgoing::Publish {
            channel: core.chan.id,
            method,
            properties: Box::new(properties),
            body,
        };
        // In process, the broker's connection handles the publish on this
        // thread when its loop is free (after the channel's lock is let
        // go: an inline delivery to this connection takes it).
        #[cfg(feature = "embedded")]
        if let Some(mut claim) = core.conn.here.as_ref().and_then(|here| here.claim()) {
            if claim.hand_or_send(item, self.permit) {
                drop(state);
                if claim.run() {
                    (core.conn.inline_publishes).fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                }
            }
            return Ok(confirm);
        }
        self.permit.send(item);
        Ok(confirm)
    }
}
