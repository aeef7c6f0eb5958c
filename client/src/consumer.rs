//! Consumers and returned messages as streams. A [`Consumer`] receives its
//! deliveries through a bounded buffer sized to the channel's prefetch
//! count (or [`DEFAULT_CONSUMER_BUFFER`] without one). When it is full the
//! reader stops reading the socket until there is room: backpressure on
//! the broker, never unbounded growth. That pauses the whole connection,
//! replies and confirms of its other channels included, so either set a
//! prefetch count before consuming with acks (the buffer then never fills)
//! or keep slow no-ack consumers and publishers waiting for confirms on
//! separate connections, as RabbitMQ advises anyway.
//!
//! Within the crate a consumer may also have a sink (`DeliverySink`, the
//! data ports' in-port intake) that takes its deliveries on the reader as
//! they are read; only those it gives back go through the buffer.
//!
//! The stream ends when the consumer is cancelled, by this client or by
//! the broker, or its channel closes; [`Consumer::end_reason`] then says
//! which. [`Returns`] is the same for `basic.return`.

use crate::channel::Channel;
use crate::error::{Error, Result};
use crate::message::{Delivery, ReturnedMessage};
use leveret_protocol::ShortStr;
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use tokio::sync::{mpsc, watch};

/// Buffer for a consumer's deliveries when the channel has no prefetch limit.
pub const DEFAULT_CONSUMER_BUFFER: usize = 1024;

/// Buffer for a channel's returned messages.
pub const RETURNS_BUFFER: usize = 256;

/// Why a consumer's stream ended.
#[derive(Debug, Clone)]
pub enum ConsumerEnd {
    /// Cancelled by this client (`basic.cancel` answered with cancel-ok).
    Cancelled,
    /// Cancelled by the broker with `basic.cancel`: its queue was deleted,
    /// or it failed over (RabbitMQ's consumer cancel notification).
    CancelledByBroker,
    /// Its channel or connection closed; the error says how.
    ChannelClosed(Error),
}

/// What the consumer and the reader share.
#[derive(Debug)]
pub(crate) struct ConsumerShared {
    end: Mutex<Option<ConsumerEnd>>,
    /// True once a cancel was asked for: a reader waiting for room in the
    /// buffer gives up.
    pub(crate) cancelling: watch::Sender<bool>,
}

impl ConsumerShared {
    fn new() -> Self {
        ConsumerShared {
            end: Mutex::new(None),
            cancelling: watch::Sender::new(false),
        }
    }

    fn end_reason(&self) -> Option<ConsumerEnd> {
        self.end.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }
}

/// Takes a consumer's deliveries on the connection's reader, as they are
/// read, ahead of the consumer's buffer: one task fewer between the broker
/// and the application (the data ports' in-process fast path).
pub trait DeliverySink: Send + Sync {
    /// Whether it took `delivery` (handled it, or dropped it); if not, it
    /// goes through the consumer's buffer. Deliveries come in order; a
    /// sink that leaves one must leave every later one until the
    /// consumer's side has handled it, so that none overtakes another.
    fn take(&self, delivery: &Delivery) -> bool;

    /// Whether `take` may run on an embedded broker's dispatching thread,
    /// under the queue's lock (the in-process fast path): only a sink
    /// whose work is short and never calls into the broker may say yes.
    /// A sink that says no has its deliveries go through the reader.
    fn runs_inline(&self) -> bool {
        false
    }
}

/// The reader's side of a consumer, kept in the channel's table.
pub(crate) struct ConsumerSlot {
    pub(crate) tx: mpsc::Sender<Delivery>,
    pub(crate) shared: Arc<ConsumerShared>,
    pub(crate) sink: Option<Arc<dyn DeliverySink>>,
}

impl std::fmt::Debug for ConsumerSlot {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ConsumerSlot")
            .field("shared", &self.shared)
            .field("sink", &self.sink.is_some())
            .finish_non_exhaustive()
    }
}

impl ConsumerSlot {
    /// A slot and the receiving end for a consumer, with the sink that
    /// takes its deliveries first, if any.
    pub(crate) fn new(
        capacity: usize,
        sink: Option<Arc<dyn DeliverySink>>,
    ) -> (Self, mpsc::Receiver<Delivery>, Arc<ConsumerShared>) {
        let (tx, rx) = mpsc::channel(capacity.max(1));
        let shared = Arc::new(ConsumerShared::new());
        let slot = ConsumerSlot {
            tx,
            shared: Arc::clone(&shared),
            sink,
        };
        (slot, rx, shared)
    }

    /// Ends the stream: records why, then drops the sender.
    pub(crate) fn end(self, reason: ConsumerEnd) {
        let mut end = self.shared.end.lock().unwrap_or_else(|e| e.into_inner());
        if end.is_none() {
            *end = Some(reason);
        }
        drop(end);
        self.shared.cancelling.send_replace(true);
    }
}

/// A consumer's stream of deliveries; implements
/// [`futures_core::Stream`] and has an async [`Consumer::next`].
/// Dropping it cancels the consumer (`basic.cancel` with no-wait).
#[derive(Debug)]
pub struct Consumer {
    tag: ShortStr,
    rx: mpsc::Receiver<Delivery>,
    shared: Arc<ConsumerShared>,
    channel: Channel,
}

impl Consumer {
    pub(crate) fn new(
        tag: ShortStr,
        rx: mpsc::Receiver<Delivery>,
        shared: Arc<ConsumerShared>,
        channel: Channel,
    ) -> Self {
        Consumer {
            tag,
            rx,
            shared,
            channel,
        }
    }

    /// The consumer tag (the broker's, if none was given).
    pub fn tag(&self) -> &ShortStr {
        &self.tag
    }

    /// The channel it consumes on.
    pub fn channel(&self) -> &Channel {
        &self.channel
    }

    /// The next delivery; `None` once the consumer has ended (see
    /// [`Consumer::end_reason`]).
    pub async fn next(&mut self) -> Option<Delivery> {
        self.rx.recv().await
    }

    /// Why the stream ended, once it has.
    pub fn end_reason(&self) -> Option<ConsumerEnd> {
        self.shared.end_reason()
    }

    /// Cancels the consumer and waits for `basic.cancel-ok`. Deliveries
    /// already buffered can still be taken with [`Consumer::next`].
    pub async fn cancel(&self) -> Result<()> {
        self.channel.basic_cancel(&self.tag).await
    }
}

impl futures_core::Stream for Consumer {
    type Item = Delivery;

    fn poll_next(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Delivery>> {
        self.get_mut().rx.poll_recv(cx)
    }
}

impl Drop for Consumer {
    fn drop(&mut self) {
        if self.shared.end_reason().is_none() {
            self.channel.cancel_on_drop(&self.tag);
        }
    }
}

/// The stream of a channel's returned messages (see `Channel::returns`);
/// implements [`futures_core::Stream`] and has an async [`Returns::next`].
#[derive(Debug)]
pub struct Returns {
    rx: mpsc::Receiver<ReturnedMessage>,
}

impl Returns {
    pub(crate) fn new(rx: mpsc::Receiver<ReturnedMessage>) -> Self {
        Returns { rx }
    }

    /// The next returned message; `None` once the channel has closed (or a
    /// newer `returns()` took over).
    pub async fn next(&mut self) -> Option<ReturnedMessage> {
        self.rx.recv().await
    }

    /// The next returned message if one is waiting, without waiting.
    pub fn try_next(&mut self) -> Option<ReturnedMessage> {
        self.rx.try_recv().ok()
    }
}

impl futures_core::Stream for Returns {
    type Item = ReturnedMessage;

    fn poll_next(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<ReturnedMessage>> {
        self.get_mut().rx.poll_recv(cx)
    }
}
