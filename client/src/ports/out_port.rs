//! [`OutPort`]: publishes typed values, each with the port's sequence
//! number and the time of `put` in its headers.
//!
//! One task per port owns the port's connection. `put` encodes the value,
//! takes a slot in the window of unconfirmed messages and hands the message
//! to the task, which numbers it and publishes it in order. With publisher
//! confirms a message stays in the window until the broker confirms it;
//! when the link drops the task reconnects with backoff, declares the
//! topology again and republishes the whole window in order before
//! anything newer (the in-port drops the duplicates this can make). `put`
//! never takes longer than the profile's `put_timeout`, and says what
//! became of the value with a [`PortStatus`].

use super::data::PortData;
use super::link::{self, Link, LinkStatus};
use super::profile::{Connector, PortProfile};
use crate::confirm::ConfirmFuture;
use crate::error::{Error, Result};
use crate::{BasicProperties, BasicPublishOptions, Channel, Confirmation, Connection, ShortStr};
use bytes::{Bytes, BytesMut};
use std::collections::VecDeque;
use std::future::{Future, IntoFuture};
use std::marker::PhantomData;
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::Poll;
use std::time::Duration;
use tokio::sync::{mpsc, oneshot, watch, OwnedSemaphorePermit, Semaphore};
use tokio::task::JoinHandle;
use tokio::time::Instant;

/// How long closing a port waits for the broker's close-ok.
const CLOSE_TIMEOUT: Duration = Duration::from_secs(5);

/// What became of a `put`, after RT-Middleware's data port return codes.
/// "Accepted" values are in the port's window: they reach the broker
/// unless it rejects them or the port is dropped first.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum PortStatus {
    /// The broker has the message (with confirms), or it was handed to the
    /// connection (without).
    Ok,
    /// Not accepted: the window of unconfirmed messages stayed full for
    /// the whole timeout (a slow or unreachable broker).
    SendFull,
    /// Accepted, but not confirmed within the timeout; it stays in the
    /// window and is resent after a reconnection if need be.
    SendTimeout,
    /// Accepted while the link to the broker is down: it is sent once the
    /// port has reconnected.
    ConnectionLost,
    /// The broker refused the message (`basic.nack`, e.g. a full queue
    /// with `x-overflow: reject-publish`); it is not resent.
    Rejected,
    /// Not accepted: the value could not be encoded.
    InvalidArgs,
    /// Not accepted: the port is closed.
    Closed,
}

impl PortStatus {
    /// Whether this is [`PortStatus::Ok`].
    pub fn is_ok(self) -> bool {
        self == PortStatus::Ok
    }

    /// Whether the value is on its way (now or after a reconnection).
    pub fn is_accepted(self) -> bool {
        matches!(
            self,
            PortStatus::Ok | PortStatus::SendTimeout | PortStatus::ConnectionLost
        )
    }
}

/// An out-port's counters.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct OutPortStats {
    /// Values accepted (numbered `1..=accepted`).
    pub accepted: u64,
    /// Confirmed by the broker (or written, without confirms).
    pub confirmed: u64,
    /// Refused by the broker.
    pub rejected: u64,
    /// Publishes repeated after a reconnection.
    pub resent: u64,
    /// Puts refused with [`PortStatus::SendFull`].
    pub send_full: u64,
    /// Puts that returned [`PortStatus::SendTimeout`].
    pub send_timeouts: u64,
    /// Messages waiting for their confirm now.
    pub unconfirmed: u64,
}

/// A message on its way to the task.
struct Request {
    body: Bytes,
    sent_ns: i64,
    slot: OwnedSemaphorePermit,
    reply: oneshot::Sender<PortStatus>,
}

/// What the port and its task share.
#[derive(Debug)]
struct Shared {
    stats: Mutex<OutPortStats>,
    link: Link,
    /// Messages in the window (accepted, not yet confirmed).
    window: watch::Sender<usize>,
}

impl Shared {
    fn stats(&self) -> std::sync::MutexGuard<'_, OutPortStats> {
        self.stats.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// A typed publisher with reconnection and an unconfirmed window. Dropping
/// it closes its connection; unconfirmed messages are then abandoned (see
/// [`OutPort::flush`]).
#[derive(Debug)]
pub struct OutPort<T> {
    requests: mpsc::UnboundedSender<Request>,
    slots: Arc<Semaphore>,
    shared: Arc<Shared>,
    timeout: Duration,
    id: Arc<str>,
    task: Option<JoinHandle<()>>,
    _data: PhantomData<fn(&T)>,
}

impl<T: PortData> OutPort<T> {
    /// Connects over TCP to the profile's broker and declares its topology;
    /// fails if this first attempt does (later losses are reconnected).
    pub async fn connect(profile: PortProfile) -> Result<Self> {
        OutPort::connect_with(Connector::from(&profile), profile).await
    }

    /// [`OutPort::connect`] through `connector` (an embedded broker, or a
    /// setup of one's own).
    pub async fn connect_with(connector: Connector, profile: PortProfile) -> Result<Self> {
        let profile = Arc::new(profile);
        let first = open(connector.clone(), Arc::clone(&profile)).await?;
        let shared = Arc::new(Shared {
            stats: Mutex::new(OutPortStats::default()),
            link: Link::new(),
            window: watch::Sender::new(0),
        });
        shared.link.connected();
        let id: Arc<str> = link::port_id().into();
        let (requests, rx) = mpsc::unbounded_channel();
        let slots = Arc::new(Semaphore::new(profile.max_unconfirmed.max(1)));
        let task = Task {
            requests: rx,
            shared: Arc::clone(&shared),
            connector,
            exchange: ShortStr::try_from(profile.exchange.as_str())?,
            routing_key: ShortStr::try_from(profile.routing_key.as_str())?,
            content_type: ShortStr::try_from(T::CONTENT_TYPE)?,
            type_name: T::TYPE_NAME.map(ShortStr::try_from).transpose()?,
            port: Arc::clone(&id),
            timeout: profile.put_timeout,
            profile,
            next_seq: 1,
            window: VecDeque::new(),
            published: 0,
            inflight: VecDeque::new(),
            link: Some(first),
            connecting: None,
            failures: 0,
            retry_at: Instant::now(),
        };
        let timeout = task.timeout;
        let task = tokio::spawn(task.run());
        Ok(OutPort {
            requests,
            slots,
            shared,
            timeout,
            id,
            task: Some(task),
            _data: PhantomData,
        })
    }

    /// Publishes `value`, waiting at most the profile's `put_timeout`.
    pub async fn put(&self, value: &T) -> PortStatus {
        let deadline = Instant::now() + self.timeout;
        let mut body = BytesMut::new();
        if let Err(error) = value.encode(&mut body) {
            tracing::warn!(%error, "out-port value could not be encoded");
            return PortStatus::InvalidArgs;
        }
        let sent_ns = link::now_ns();
        let slot = match tokio::time::timeout_at(deadline, Arc::clone(&self.slots).acquire_owned())
            .await
        {
            Ok(Ok(slot)) => slot,
            Ok(Err(_)) => return PortStatus::Closed,
            Err(_) => {
                self.shared.stats().send_full += 1;
                return PortStatus::SendFull;
            }
        };
        let (reply, answer) = oneshot::channel();
        let request = Request {
            body: body.freeze(),
            sent_ns,
            slot,
            reply,
        };
        if self.requests.send(request).is_err() {
            return PortStatus::Closed;
        }
        match tokio::time::timeout_at(deadline, answer).await {
            Ok(Ok(status)) => status,
            Ok(Err(_)) => PortStatus::Closed,
            Err(_) => {
                self.shared.stats().send_timeouts += 1;
                PortStatus::SendTimeout
            }
        }
    }

    /// Waits until every accepted message has been confirmed (or
    /// rejected); wrap it in a timeout.
    pub async fn flush(&self) {
        let mut window = self.shared.window.subscribe();
        let _ = window.wait_for(|n| *n == 0).await;
    }

    /// The counters so far.
    pub fn stats(&self) -> OutPortStats {
        *self.shared.stats()
    }

    /// The link's state, to watch for losses and reconnections.
    pub fn link(&self) -> watch::Receiver<LinkStatus> {
        self.shared.link.subscribe()
    }

    /// This port's `x-port` header value.
    pub fn id(&self) -> &str {
        &self.id
    }

    /// Closes the connection (without waiting for unconfirmed messages:
    /// [`OutPort::flush`] first for that).
    pub async fn close(mut self) {
        let task = self.task.take();
        drop(self);
        if let Some(task) = task {
            let _ = task.await;
        }
    }
}

/// A message in the window.
struct Entry {
    properties: BasicProperties,
    body: Bytes,
    reply: Option<oneshot::Sender<PortStatus>>,
    attempts: u32,
    _slot: OwnedSemaphorePermit,
}

/// A connection with its channel, topology declared.
struct OutLink {
    connection: Connection,
    channel: Channel,
}

type Opening = Pin<Box<dyn Future<Output = Result<OutLink>> + Send>>;

/// Connects and declares the topology (and confirm mode).
async fn open(connector: Connector, profile: Arc<PortProfile>) -> Result<OutLink> {
    let setup = async {
        let connection = connector.connect().await?;
        let channel = connection.open_channel().await?;
        link::declare_exchange(&channel, &profile).await?;
        if profile.declare_queue && !profile.queue.is_empty() {
            link::declare_queue(&channel, &profile).await?;
        }
        if profile.confirms {
            channel.confirm_select().await?;
        }
        Ok(OutLink {
            connection,
            channel,
        })
    };
    match tokio::time::timeout(profile.broker.connection_timeout, setup).await {
        Ok(result) => result,
        Err(_) => Err(Error::ConnectTimeout),
    }
}

/// What woke the task.
enum Event {
    Confirm(Result<Confirmation>),
    Request(Request),
    Dropped,
    Opened(Result<OutLink>),
    Lost(Error),
    Retry,
}

struct Task {
    requests: mpsc::UnboundedReceiver<Request>,
    shared: Arc<Shared>,
    connector: Connector,
    profile: Arc<PortProfile>,
    exchange: ShortStr,
    routing_key: ShortStr,
    content_type: ShortStr,
    type_name: Option<ShortStr>,
    port: Arc<str>,
    timeout: Duration,
    next_seq: u64,
    /// Accepted, unconfirmed messages in sequence order; the first
    /// `published` of them were published on the current link.
    window: VecDeque<Entry>,
    published: usize,
    /// Confirms of the published messages, in the same order.
    inflight: VecDeque<ConfirmFuture>,
    link: Option<OutLink>,
    connecting: Option<Opening>,
    failures: u32,
    retry_at: Instant,
}

impl Task {
    async fn run(mut self) {
        loop {
            if self.link.is_some() && self.published < self.window.len() {
                self.publish_pending().await;
                continue;
            }
            if self.link.is_none() && self.connecting.is_none() && Instant::now() >= self.retry_at {
                let opening = open(self.connector.clone(), Arc::clone(&self.profile));
                self.connecting = Some(Box::pin(opening));
            }
            match self.next_event().await {
                Event::Confirm(result) => self.settle(result),
                Event::Request(request) => self.accept(request),
                Event::Dropped => break,
                Event::Opened(result) => self.opened(result),
                Event::Lost(error) => self.lost(error),
                Event::Retry => {}
            }
        }
        if let Some(link) = self.link.take() {
            let _ = tokio::time::timeout(CLOSE_TIMEOUT, link.connection.close()).await;
        }
    }

    async fn next_event(&mut self) -> Event {
        let inflight = &mut self.inflight;
        let connecting = &mut self.connecting;
        let channel = self.link.as_ref().map(|link| link.channel.clone());
        let idle = self.link.is_none() && connecting.is_none();
        let confirm = std::future::poll_fn(|cx| match inflight.front_mut() {
            Some(confirm) => Pin::new(confirm).poll(cx),
            None => Poll::Pending,
        });
        let opened = std::future::poll_fn(|cx| match connecting.as_mut() {
            Some(opening) => opening.as_mut().poll(cx),
            None => Poll::Pending,
        });
        let closed = async move {
            match channel {
                Some(channel) => channel.closed().await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            biased;
            result = confirm => Event::Confirm(result),
            request = self.requests.recv() => match request {
                Some(request) => Event::Request(request),
                None => Event::Dropped,
            },
            result = opened => Event::Opened(result),
            error = closed => Event::Lost(error),
            _ = tokio::time::sleep_until(self.retry_at), if idle => Event::Retry,
        }
    }

    fn accept(&mut self, request: Request) {
        let seq = self.next_seq;
        self.next_seq += 1;
        let properties = BasicProperties {
            content_type: Some(self.content_type.clone()),
            kind: self.type_name.clone(),
            delivery_mode: Some(if self.profile.persistent { 2 } else { 1 }),
            timestamp: u64::try_from(request.sent_ns / 1_000_000_000).ok(),
            headers: Some(link::headers(&self.port, seq, request.sent_ns)),
            ..Default::default()
        };
        let mut reply = Some(request.reply);
        if self.link.is_none() {
            if let Some(reply) = reply.take() {
                let _ = reply.send(PortStatus::ConnectionLost);
            }
        }
        self.window.push_back(Entry {
            properties,
            body: request.body,
            reply,
            attempts: 0,
            _slot: request.slot,
        });
        self.shared.stats().accepted += 1;
        self.window_changed();
    }

    /// Publishes, in order, every message of the window not yet published
    /// on the current link.
    async fn publish_pending(&mut self) {
        while self.published < self.window.len() {
            let Some(link) = &self.link else {
                return;
            };
            let entry = &mut self.window[self.published];
            let result = link
                .channel
                .basic_publish(
                    &self.exchange,
                    &self.routing_key,
                    BasicPublishOptions::default(),
                    entry.properties.clone(),
                    entry.body.clone(),
                )
                .await;
            let confirm = match result {
                Ok(confirm) => confirm,
                Err(error) => {
                    self.lost(error);
                    return;
                }
            };
            if entry.attempts > 0 {
                self.shared.stats().resent += 1;
            }
            entry.attempts += 1;
            if self.profile.confirms {
                self.inflight.push_back(confirm.into_future());
                self.published += 1;
            } else if let Some(mut entry) = self.window.pop_front() {
                if let Some(reply) = entry.reply.take() {
                    let _ = reply.send(PortStatus::Ok);
                }
                self.shared.stats().confirmed += 1;
                self.window_changed();
            }
        }
    }

    /// The oldest published message was confirmed (or its link failed).
    fn settle(&mut self, result: Result<Confirmation>) {
        let status = match result {
            Ok(Confirmation::Ack | Confirmation::NotRequested) => PortStatus::Ok,
            Ok(Confirmation::Nack) => PortStatus::Rejected,
            Err(error) => return self.lost(error),
        };
        self.inflight.pop_front();
        self.published -= 1;
        if let Some(mut entry) = self.window.pop_front() {
            if let Some(reply) = entry.reply.take() {
                let _ = reply.send(status);
            }
        }
        {
            let mut stats = self.shared.stats();
            if status.is_ok() {
                stats.confirmed += 1;
            } else {
                stats.rejected += 1;
            }
        }
        self.window_changed();
    }

    /// The link failed: keep the window for the next one.
    fn lost(&mut self, error: Error) {
        if let Some(link) = self.link.take() {
            drop(link.channel);
            drop(link.connection);
        }
        self.inflight.clear();
        self.published = 0;
        for entry in &mut self.window {
            if let Some(reply) = entry.reply.take() {
                let _ = reply.send(PortStatus::ConnectionLost);
            }
        }
        self.shared.link.lost(&error);
        self.failures = 0;
        self.retry_at = Instant::now();
    }

    fn opened(&mut self, result: Result<OutLink>) {
        self.connecting = None;
        match result {
            Ok(link) => {
                self.link = Some(link);
                self.failures = 0;
                self.shared.link.connected();
            }
            Err(error) => {
                self.shared.link.failed(&error);
                self.retry_at = Instant::now() + self.profile.backoff.delay(self.failures);
                self.failures = self.failures.saturating_add(1);
            }
        }
    }

    fn window_changed(&self) {
        let len = self.window.len();
        self.shared.stats().unconfirmed = len as u64;
        self.shared.window.send_replace(len);
    }
}
