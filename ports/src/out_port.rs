//! [`OutPort`]: publishes typed values without ever making the caller wait
//! on the network.
//!
//! `put` encodes the value, numbers it and appends it to the port's window
//! (a bounded queue shared with the port's task) and returns: it never
//! waits for the broker, whatever the broker does. When the window is
//! full the profile's [`Backpressure`] decides: drop the oldest value
//! (one not yet written if there is one; else the oldest written one's
//! wait for its confirm is abandoned), refuse the new one, or wait for
//! room up to the put timeout (the only `put` that waits, and only by the
//! caller's choice).
//!
//! The window also bounds what is written: at most `max_unconfirmed`
//! messages (and `max_unconfirmed_bytes`) are in the connection and the
//! broker unconfirmed at any time, counting those whose wait was
//! abandoned, so a frozen broker never collects more than that in its
//! socket. When the broker confirms nothing for the profile's stall
//! timeout the link is reported degraded ([`LinkStatus::degraded`],
//! [`PortStatus::Degraded`], [`OutPortStats::stalls`]) until it confirms
//! again.
//!
//! The window's messages are published in order (mandatory, so an
//! unroutable message comes back and is counted apart from confirmed
//! ones), always under the window's lock and only into room the
//! connection's outbox has (a publish never waits there). When the link
//! is up and everything before it is published, `put` publishes its value
//! itself: no task stands between the caller and the connection, which
//! for an embedded broker means the broker's connection has the message
//! at once (and, when its loop is free, routes and queues it on the
//! caller's thread, handing it to an in-process in-port there, see
//! `leveret_broker::DirectLoop`; its confirm then comes with it, and `put`
//! settles it too, with no task woken). Everything else is the port's task's: publishing what `put`
//! left (link down, outbox full, a replay), keeping each message until the
//! broker confirms it (with publisher confirms), and, when the link drops,
//! reconnecting with backoff, declaring the topology again and replaying
//! the window as the profile's [`Replay`] policy says. A message older
//! than the profile's lifespan is never published: it is reported
//! expired, and what is published carries the rest of its lifespan as its
//! AMQP `expiration`, so the broker drops it too once it is stale.
//!
//! What became of each message, its [`Fate`], counted once, is reported
//! in three ways: the counters ([`OutPort::stats`],
//! [`OutPort::watch_stats`]), a stream of [`Outcome`]s
//! ([`OutPort::outcomes`]) and callbacks ([`OutPort::on_outcome`]).
//!
//! Uses the client's channels (publishing through room reserved in the
//! connection's outbox, `leveret_client::OutboxSlot`), the link and
//! announcement helpers of this module's siblings, and the profile.

use super::announce::{self, Announcer};
use super::cdr::CdrOptions;
use super::data::PortData;
use super::link::{self, Link, LinkStatus};
use super::openrtm::PortRole;
use super::profile::{Backpressure, Connector, PortProfile, Replay};
use bytes::{Bytes, BytesMut};
use futures_core::Stream;
use leveret_client::ConfirmFuture;
use leveret_client::OutboxSlot;
use leveret_client::{
    BasicProperties, BasicPublishOptions, Channel, Confirmation, Connection, PublishConfirm,
    ReturnedMessage, Returns, ShortStr,
};
use leveret_client::{Error, Result};
use std::collections::{HashSet, VecDeque};
use std::future::{Future, IntoFuture};
use std::marker::PhantomData;
use std::pin::Pin;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::task::Poll;
use std::time::Duration;
use tokio::sync::{broadcast, watch, Notify};
use tokio::task::JoinHandle;
use tokio::time::Instant;

/// How long closing a port waits for the broker's close-ok.
const CLOSE_TIMEOUT: Duration = Duration::from_secs(5);

/// Outcomes the [`OutPort::outcomes`] stream buffers for a slow reader
/// (a reader further behind skips ahead: see `broadcast::Receiver`).
const OUTCOME_BUFFER: usize = 1024;

/// What `put` did with a value, after RT-Middleware's data port return
/// codes. It says nothing of the broker: what becomes of an accepted value
/// later is an [`Outcome`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum PortStatus {
    /// Accepted; the link is up, so it is on its way.
    Ok,
    /// Accepted while the link is down: it is sent once the port has
    /// (re)connected, if still within its lifespan.
    ConnectionLost,
    /// Accepted while the link is degraded (the broker has stopped
    /// confirming or taking messages for longer than the profile's stall
    /// timeout, see [`LinkStatus::degraded`]): it waits in the window.
    Degraded,
    /// Not accepted: the window was full ([`Backpressure::DropNewest`], or
    /// [`Backpressure::Block`] past its deadline).
    SendFull,
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

    /// Whether the value was accepted (now, or for when the link is back).
    pub fn is_accepted(self) -> bool {
        matches!(
            self,
            PortStatus::Ok | PortStatus::ConnectionLost | PortStatus::Degraded
        )
    }
}

/// What finally became of an accepted message: each accepted message has
/// exactly one, once it leaves the window.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum Fate {
    /// The broker confirmed it (`basic.ack`).
    Confirmed,
    /// Written to the connection, and no confirm will be counted: the port
    /// has no confirms, or a full window ([`Backpressure::DropOldest`])
    /// abandoned the wait for its confirm.
    SentUnconfirmed,
    /// The broker refused it (`basic.nack`, e.g. a full queue with
    /// `x-overflow: reject-publish`).
    Rejected,
    /// No queue was bound to receive it (`basic.return`, NO_ROUTE).
    Unroutable,
    /// Never written: a full window ([`Backpressure::DropOldest`]) or the
    /// [`Replay`] policy after a reconnection dropped it.
    DroppedUnsent,
    /// Never written: its lifespan ran out first.
    Expired,
    /// Written on a link that dropped before its confirm came, and not
    /// written again (the [`Replay`] policy, or its lifespan, ruled it
    /// out, or a full window dropped it): the broker may or may not have
    /// it.
    Lost,
}

/// One message's [`Fate`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Outcome {
    /// The message's sequence number (its `x-seq` header).
    pub seq: u64,
    /// What became of it.
    pub fate: Fate,
}

/// An out-port's counters. Every accepted message is counted once by its
/// [`Fate`] when it leaves the window, so at every moment
/// `accepted == settled() + pending` (an invariant the tests check).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct OutPortStats {
    /// Values accepted (numbered `1..=accepted`).
    pub accepted: u64,
    /// Fate [`Fate::Confirmed`].
    pub confirmed: u64,
    /// Fate [`Fate::SentUnconfirmed`].
    pub sent_unconfirmed: u64,
    /// Fate [`Fate::Rejected`].
    pub rejected: u64,
    /// Fate [`Fate::Unroutable`].
    pub unroutable: u64,
    /// Fate [`Fate::DroppedUnsent`].
    pub dropped_unsent: u64,
    /// Fate [`Fate::Expired`].
    pub expired: u64,
    /// Fate [`Fate::Lost`].
    pub lost: u64,
    /// Accepted and not settled yet: in the window now (waiting to be
    /// written, or written and waiting for the confirm).
    pub pending: u64,
    /// Of those, written on the current link and waiting for the confirm.
    pub in_flight: u64,
    /// Publishes repeated after a reconnection (not a fate).
    pub resent: u64,
    /// Puts refused with [`PortStatus::SendFull`] (never accepted).
    pub send_full: u64,
    /// Times the link was found stalled ([`LinkStatus::degraded`]).
    pub stalls: u64,
    /// Without confirms: messages the broker returned as unroutable after
    /// they were counted [`Fate::SentUnconfirmed`] (not a fate: each is
    /// counted there already).
    pub returned_after_send: u64,
}

impl OutPortStats {
    /// The messages that have a fate: `accepted - pending`.
    pub fn settled(&self) -> u64 {
        self.confirmed
            + self.sent_unconfirmed
            + self.rejected
            + self.unroutable
            + self.dropped_unsent
            + self.expired
            + self.lost
    }
}

/// A message in the window.
#[derive(Debug)]
struct Entry {
    seq: u64,
    sent_ns: i64,
    /// When it was put, for its lifespan.
    put_at: Instant,
    body: Bytes,
    /// Publishes so far.
    attempts: u32,
}

impl Entry {
    /// The fate of this entry leaving the window unsettled: written on the
    /// current link (before `publish_from`), written on a link since lost,
    /// or never written (`unsent`: dropped or expired).
    fn unsettled_fate(&self, publish_from: u64, unsent: Fate) -> Fate {
        if self.seq < publish_from {
            Fate::SentUnconfirmed
        } else if self.attempts > 0 {
            Fate::Lost
        } else {
            unsent
        }
    }
}

/// A message written on the current link, waiting for its confirm. It
/// stays here until the confirm comes even if its entry has left the
/// window (abandoned by [`Backpressure::DropOldest`]): it is still in the
/// socket or the broker, and counts against the window's bounds.
#[derive(Debug)]
struct InFlight {
    seq: u64,
    confirm: ConfirmFuture,
    bytes: usize,
    written_at: Instant,
}

/// The window: accepted messages not yet settled, in sequence order.
#[derive(Debug)]
struct Window {
    entries: VecDeque<Entry>,
    next_seq: u64,
    /// The first sequence number not yet published on the current link.
    publish_from: u64,
    /// The current link's channel, while the link is up.
    channel: Option<Channel>,
    /// Confirms of the messages published on this link, in order.
    inflight: VecDeque<InFlight>,
    /// The current link's returned messages (with confirms: each before
    /// its message's confirm).
    returns: Option<Returns>,
    /// Sequence numbers the broker returned as unroutable, until their
    /// confirm arrives.
    returned: HashSet<u64>,
    /// The bodies' bytes of `inflight`.
    inflight_bytes: usize,
    /// The broker has confirmed nothing (or, without confirms, taken
    /// nothing) for longer than the stall timeout.
    degraded: bool,
    /// Threads waiting in `put_blocking` for room: the condition variable
    /// is signalled only for them (a signal costs a system call even when
    /// nobody waits).
    blocked_putters: usize,
    closed: bool,
    stats: OutPortStats,
}

impl Window {
    /// Refreshes the gauges after entries came or went.
    fn measure(&mut self) {
        self.stats.pending = self.entries.len() as u64;
        let publish_from = self.publish_from;
        self.stats.in_flight =
            self.entries
                .partition_point(|entry| entry.seq < publish_from) as u64;
    }

    /// Whether the socket and broker have room for `bytes` more: the
    /// window bounds what is written and unconfirmed, in messages and in
    /// bytes (one message always fits when nothing is in flight).
    fn has_room_in_flight(&self, bytes: usize, limits: &Limits) -> bool {
        self.inflight.is_empty()
            || (self.inflight.len() < limits.messages
                && self.inflight_bytes + bytes <= limits.bytes)
    }
}

/// The window's bounds.
#[derive(Debug, Clone, Copy)]
struct Limits {
    /// Messages in the window, and written but unconfirmed.
    messages: usize,
    /// Bytes written but unconfirmed.
    bytes: usize,
}

/// What publishing the window's next message did.
enum Next {
    /// Published one.
    Published,
    /// Nothing to publish, or no link to publish on.
    Idle,
    /// No room in flight (the window's bounds): a confirm makes room.
    Windowed,
    /// The connection's outbox is full: wait for room.
    Full,
    /// The link failed.
    Failed(Error),
}

/// How the port's messages are published, fixed when it starts.
#[derive(Debug)]
struct Publishing {
    exchange: ShortStr,
    routing_key: ShortStr,
    content_type: ShortStr,
    type_name: Option<ShortStr>,
    port: Arc<str>,
    persistent: bool,
    mandatory: bool,
    confirms: bool,
    lifespan: Option<Duration>,
    limits: Limits,
}

impl Publishing {
    /// Publishes a message through room reserved for it, with what is left
    /// of its lifespan as its expiration.
    fn publish(
        &self,
        slot: OutboxSlot<'_>,
        entry: &Entry,
        remaining: Option<Duration>,
    ) -> Result<PublishConfirm> {
        let properties = BasicProperties {
            content_type: Some(self.content_type.clone()),
            kind: self.type_name.clone(),
            delivery_mode: Some(if self.persistent { 2 } else { 1 }),
            timestamp: u64::try_from(entry.sent_ns / 1_000_000_000).ok(),
            // At least 1 ms: an expiration of 0 would mean "deliver now or
            // never", stricter than what is left.
            expiration: remaining
                .and_then(|left| ShortStr::try_from(left.as_millis().max(1).to_string()).ok()),
            headers: Some(link::headers(&self.port, entry.seq, entry.sent_ns)),
            ..Default::default()
        };
        let options = BasicPublishOptions {
            mandatory: self.mandatory,
        };
        slot.basic_publish(
            self.exchange.clone(),
            self.routing_key.clone(),
            options,
            properties,
            entry.body.clone(),
        )
    }
}

type OutcomeCallback = Box<dyn FnMut(&Outcome) + Send>;

/// Who hears of outcomes, and how many have been told.
struct Reporting {
    callbacks: Vec<OutcomeCallback>,
    /// Outcomes sent to the stream and the callbacks so far.
    delivered: u64,
}

/// What the port and its task share.
struct Shared {
    window: Mutex<Window>,
    /// Signals the task: a new message, or the port closed.
    work: Notify,
    /// Signals async `put`s waiting for room.
    room: Notify,
    /// Signals blocking `put`s waiting for room.
    room_blocking: Condvar,
    stats: watch::Sender<OutPortStats>,
    outcomes: broadcast::Sender<Outcome>,
    reporting: Mutex<Reporting>,
    link: Link,
    publishing: Publishing,
}

fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(|e| e.into_inner())
}

impl Shared {
    fn window(&self) -> MutexGuard<'_, Window> {
        lock(&self.window)
    }

    /// Sends the current counters to their watchers (see
    /// [`Shared::send_stats`]); whether a thread waits for room.
    fn publish_stats(&self) -> bool {
        self.send_stats(&lock(&self.reporting))
    }

    /// Sends the current counters to their watchers, read under the
    /// window's lock, so a `put` on another thread can never overwrite
    /// newer counters with the ones it saw (which left `flush` waiting for
    /// a `pending` of 0 already reached); but only once every outcome they
    /// count has been delivered, so a watcher of the counters (`flush`)
    /// finds those outcomes in the stream and the callbacks. Counters not
    /// sent now go out with the report of the outcomes still on their way.
    /// Whether a thread waits for room.
    fn send_stats(&self, reporting: &Reporting) -> bool {
        let window = self.window();
        if window.stats.settled() == reporting.delivered {
            self.stats.send_replace(window.stats);
        }
        window.blocked_putters > 0
    }

    /// Delivers the outcomes and publishes the counters (call it after
    /// releasing the window's lock, with the outcomes settled under it);
    /// wakes whoever waits for room if messages left it.
    fn report(&self, outcomes: &[Outcome], room: bool) {
        let blocked = {
            let mut reporting = lock(&self.reporting);
            for outcome in outcomes {
                let _ = self.outcomes.send(*outcome);
                for callback in reporting.callbacks.iter_mut() {
                    callback(outcome);
                }
            }
            reporting.delivered += outcomes.len() as u64;
            self.send_stats(&reporting)
        };
        if room {
            self.room.notify_waiters();
            if blocked {
                self.room_blocking.notify_all();
            }
        }
    }

    /// Publishes the window's oldest message not yet published on the
    /// current link, through `reserved` or else room the outbox has now,
    /// expiring on the way what is past its lifespan. Runs under the
    /// window's lock, so messages go out in order whoever publishes them.
    /// Without confirms a published message is settled at once.
    fn publish_next(
        &self,
        window: &mut Window,
        reserved: Option<OutboxSlot<'_>>,
        outcomes: &mut Vec<Outcome>,
    ) -> Next {
        let next = self.publish_one(window, reserved, outcomes);
        window.measure();
        next
    }

    fn publish_one(
        &self,
        window: &mut Window,
        reserved: Option<OutboxSlot<'_>>,
        outcomes: &mut Vec<Outcome>,
    ) -> Next {
        let lifespan = self.publishing.lifespan;
        if window.channel.is_none() {
            return Next::Idle;
        }
        let index = window
            .entries
            .partition_point(|entry| entry.seq < window.publish_from);
        let remaining = loop {
            let Some(entry) = window.entries.get(index) else {
                return Next::Idle;
            };
            let age = entry.put_at.elapsed();
            match lifespan {
                Some(lifespan) if age >= lifespan => {
                    let fate = entry.unsettled_fate(window.publish_from, Fate::Expired);
                    let seq = entry.seq;
                    window.entries.remove(index);
                    settle(&mut window.stats, outcomes, seq, fate);
                }
                Some(lifespan) => break Some(lifespan - age),
                None => break None,
            }
        };
        let bytes = window.entries[index].body.len();
        if self.publishing.confirms && !window.has_room_in_flight(bytes, &self.publishing.limits) {
            return Next::Windowed;
        }
        let Window {
            entries,
            publish_from,
            channel: Some(channel),
            inflight,
            inflight_bytes,
            stats,
            ..
        } = window
        else {
            return Next::Idle;
        };
        let slot = match reserved {
            Some(slot) => slot,
            None => match channel.try_reserve() {
                Ok(Some(slot)) => slot,
                Ok(None) => return Next::Full,
                Err(error) => return Next::Failed(error),
            },
        };
        let entry = &mut entries[index];
        let confirm = match self.publishing.publish(slot, entry, remaining) {
            Ok(confirm) => confirm,
            Err(error) => return Next::Failed(error),
        };
        if entry.attempts > 0 {
            stats.resent += 1;
        }
        entry.attempts += 1;
        let seq = entry.seq;
        *publish_from = seq + 1;
        if self.publishing.confirms {
            inflight.push_back(InFlight {
                seq,
                confirm: confirm.into_future(),
                bytes,
                written_at: Instant::now(),
            });
            *inflight_bytes += bytes;
        } else {
            entries.remove(index);
            settle(stats, outcomes, seq, Fate::SentUnconfirmed);
        }
        Next::Published
    }
}

impl Shared {
    /// Settles the messages at the front of what is in flight whose
    /// confirm has come, in order, without waiting: `put` does it right
    /// after it published, for an in-process publish the broker handled on
    /// the putting thread has its confirm by then, and nobody need wake
    /// the task for it. Stops at the first whose confirm has not come or
    /// is a failed link's (the task's to handle). How many it settled.
    fn settle_confirmed(&self, window: &mut Window, outcomes: &mut Vec<Outcome>) -> usize {
        let mut settled = 0;
        while let Some(oldest) = window.inflight.front_mut() {
            let Some(Ok(confirmation)) = oldest.confirm.try_answer() else {
                break;
            };
            let seq = oldest.seq;
            settle_in_flight(window, seq, confirmation, outcomes);
            settled += 1;
        }
        settled
    }
}

impl std::fmt::Debug for Shared {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Shared")
            .field("window", &self.window().stats)
            .finish_non_exhaustive()
    }
}

/// The fate of one message, counted.
fn settle(stats: &mut OutPortStats, outcomes: &mut Vec<Outcome>, seq: u64, fate: Fate) {
    match fate {
        Fate::Confirmed => stats.confirmed += 1,
        Fate::SentUnconfirmed => stats.sent_unconfirmed += 1,
        Fate::Rejected => stats.rejected += 1,
        Fate::Unroutable => stats.unroutable += 1,
        Fate::DroppedUnsent => stats.dropped_unsent += 1,
        Fate::Expired => stats.expired += 1,
        Fate::Lost => stats.lost += 1,
    }
    outcomes.push(Outcome { seq, fate });
}

/// Settles message `seq`, the oldest in flight, by its confirm (unless
/// that is settled already): it leaves what is in flight, and its entry
/// (if still in the window: a full window may have abandoned it since,
/// counted as sent-unconfirmed) gets its fate, unroutable if the broker
/// returned it.
fn settle_in_flight(
    window: &mut Window,
    seq: u64,
    confirmation: Confirmation,
    outcomes: &mut Vec<Outcome>,
) {
    if window
        .inflight
        .front()
        .is_none_or(|oldest| oldest.seq != seq)
    {
        return;
    }
    if let Some(settled) = window.inflight.pop_front() {
        window.inflight_bytes -= settled.bytes;
    }
    note_returns(window);
    let fate = match confirmation {
        _ if window.returned.remove(&seq) => Fate::Unroutable,
        Confirmation::Ack | Confirmation::NotRequested => Fate::Confirmed,
        Confirmation::Nack => Fate::Rejected,
    };
    if let Ok(index) = window.entries.binary_search_by_key(&seq, |entry| entry.seq) {
        window.entries.remove(index);
        settle(&mut window.stats, outcomes, seq, fate);
    }
    window.measure();
}

/// Notes every message the broker has returned so far (with confirms).
/// The broker sends a message's `basic.return` before its confirm, and
/// the client hands them over in that order, so its return is here by
/// the time its confirm is.
fn note_returns(window: &mut Window) {
    while let Some(message) = window.returns.as_mut().and_then(Returns::try_next) {
        if let Some(seq) = link::Stamp::read(message.properties.headers.as_ref()).seq {
            window.returned.insert(seq);
        }
    }
}

/// Takes the messages past their lifespan off the front of the window
/// (the oldest first, so they are all there), unless published on the
/// current link: the broker has those, with their expiration.
fn expire_oldest(window: &mut Window, lifespan: Option<Duration>, outcomes: &mut Vec<Outcome>) {
    let Some(lifespan) = lifespan else {
        return;
    };
    let unpublished = window.publish_from;
    while window
        .entries
        .front()
        .is_some_and(|entry| entry.seq >= unpublished && entry.put_at.elapsed() >= lifespan)
    {
        if let Some(entry) = window.entries.pop_front() {
            let fate = entry.unsettled_fate(unpublished, Fate::Expired);
            settle(&mut window.stats, outcomes, entry.seq, fate);
        }
    }
    window.measure();
}

/// Drops all but the newest `keep` messages of the window (a replay
/// policy, between links: nothing is in flight).
fn keep_newest(window: &mut Window, keep: usize, outcomes: &mut Vec<Outcome>) {
    let superseded = window.entries.len().saturating_sub(keep);
    for _ in 0..superseded {
        if let Some(entry) = window.entries.pop_front() {
            let fate = entry.unsettled_fate(window.publish_from, Fate::DroppedUnsent);
            settle(&mut window.stats, outcomes, entry.seq, fate);
        }
    }
    window.measure();
}

/// Makes room in a full window for [`Backpressure::DropOldest`]: drops the
/// oldest message not written on the current link, or, when every one is
/// written and waits for its confirm, abandons the oldest's wait. Either
/// way what is written stays bounded: an abandoned message still counts
/// in flight until its confirm comes.
fn drop_oldest(window: &mut Window, outcomes: &mut Vec<Outcome>) {
    let index = window
        .entries
        .partition_point(|entry| entry.seq < window.publish_from);
    let index = if index < window.entries.len() {
        index
    } else {
        0
    };
    if let Some(entry) = window.entries.remove(index) {
        let fate = entry.unsettled_fate(window.publish_from, Fate::DroppedUnsent);
        settle(&mut window.stats, outcomes, entry.seq, fate);
    }
    window.measure();
}

/// A typed publisher with reconnection and a bounded window. Dropping it
/// closes its connection; messages not yet confirmed are then abandoned
/// (see [`OutPort::flush`]).
#[derive(Debug)]
pub struct OutPort<T> {
    shared: Arc<Shared>,
    capacity: usize,
    backpressure: Backpressure,
    lifespan: Option<Duration>,
    cdr: CdrOptions,
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
        check_routes(&profile)?;
        let connector = connector.naming(announce::connection_name(PortRole::OutPort, &profile));
        let profile = Arc::new(profile);
        let first = open(connector.clone(), Arc::clone(&profile)).await?;
        OutPort::spawn(connector, profile, Some(first))
    }

    /// Starts the port at once, whether or not the broker is reachable:
    /// it connects in the background (retrying with backoff), and values
    /// put meanwhile wait in the window ([`PortStatus::ConnectionLost`]).
    /// Fails only on a profile that cannot work (one that routes nowhere).
    /// Must be called within a tokio runtime.
    pub fn start(profile: PortProfile) -> Result<Self> {
        OutPort::start_with(Connector::from(&profile), profile)
    }

    /// [`OutPort::start`] through `connector`.
    pub fn start_with(connector: Connector, profile: PortProfile) -> Result<Self> {
        check_routes(&profile)?;
        let connector = connector.naming(announce::connection_name(PortRole::OutPort, &profile));
        OutPort::spawn(connector, Arc::new(profile), None)
    }

    fn spawn(
        connector: Connector,
        profile: Arc<PortProfile>,
        first: Option<OutLink>,
    ) -> Result<Self> {
        let id: Arc<str> = link::port_id().into();
        let publishing = Publishing {
            exchange: ShortStr::try_from(profile.exchange.as_str())?,
            routing_key: ShortStr::try_from(profile.routing_key.as_str())?,
            content_type: ShortStr::try_from(super::cdr::content_type(
                T::CONTENT_TYPE,
                &profile.cdr,
            ))?,
            type_name: T::TYPE_NAME.map(ShortStr::try_from).transpose()?,
            port: Arc::clone(&id),
            persistent: profile.persistent,
            mandatory: profile.mandatory,
            confirms: profile.confirms,
            lifespan: profile.lifespan,
            limits: Limits {
                messages: profile.max_unconfirmed.max(1),
                bytes: profile.max_unconfirmed_bytes.max(1),
            },
        };
        let shared = Arc::new(Shared {
            window: Mutex::new(Window {
                entries: VecDeque::new(),
                next_seq: 1,
                publish_from: 1,
                channel: first.as_ref().map(|link| link.channel.clone()),
                inflight: VecDeque::new(),
                returns: first.as_ref().map(|link| link.channel.returns()),
                returned: HashSet::new(),
                inflight_bytes: 0,
                degraded: false,
                blocked_putters: 0,
                closed: false,
                stats: OutPortStats::default(),
            }),
            work: Notify::new(),
            room: Notify::new(),
            room_blocking: Condvar::new(),
            stats: watch::Sender::new(OutPortStats::default()),
            outcomes: broadcast::Sender::new(OUTCOME_BUFFER),
            reporting: Mutex::new(Reporting {
                callbacks: Vec::new(),
                delivered: 0,
            }),
            link: Link::new(),
            publishing,
        });
        if first.is_some() {
            shared.link.connected();
        }
        let announcer = Announcer::start::<T, _>(
            PortRole::OutPort,
            &profile,
            &id,
            None,
            shared.stats.subscribe(),
            shared.link.subscribe(),
        );
        if let Some(first) = &first {
            announcer.link_up(&first.connection);
        }
        let task = Task {
            shared: Arc::clone(&shared),
            connector,
            connecting: None,
            failures: 0,
            retry_at: Instant::now(),
            stall_timeout: profile.stall_timeout(),
            link: first,
            profile: Arc::clone(&profile),
            announcer,
        };
        let task = tokio::spawn(task.run());
        Ok(OutPort {
            shared,
            capacity: profile.max_unconfirmed.max(1),
            backpressure: profile.backpressure,
            lifespan: profile.lifespan,
            cdr: profile.cdr,
            timeout: profile.put_timeout,
            id,
            task: Some(task),
            _data: PhantomData,
        })
    }

    /// Puts `value` in the window and returns. It never waits on the
    /// network; with [`Backpressure::Block`] and a full window it waits for
    /// room, at most the profile's put timeout.
    pub async fn put(&self, value: &T) -> PortStatus {
        let body = match encode(value, self.cdr) {
            Ok(body) => body,
            Err(status) => return status,
        };
        let deadline = Instant::now() + self.timeout;
        let mut body = Some(body);
        loop {
            let room = self.shared.room.notified();
            match self.enqueue(&mut body) {
                Some(status) => return status,
                None if Instant::now() >= deadline => return self.refuse(),
                None => {
                    if tokio::time::timeout_at(deadline, room).await.is_err() {
                        // One more look: room made just at the deadline.
                        return self.enqueue(&mut body).unwrap_or_else(|| self.refuse());
                    }
                }
            }
        }
    }

    /// [`OutPort::put`] without ever waiting: with a full window,
    /// [`Backpressure::Block`] refuses the value ([`PortStatus::SendFull`]).
    /// Callable from any thread.
    pub fn try_put(&self, value: &T) -> PortStatus {
        let body = match encode(value, self.cdr) {
            Ok(body) => body,
            Err(status) => return status,
        };
        self.enqueue(&mut Some(body))
            .unwrap_or_else(|| self.refuse())
    }

    /// [`OutPort::put`] for a thread outside the async runtime (a control
    /// loop of its own): it blocks the thread, not a task, when
    /// [`Backpressure::Block`] waits for room. Never call it on a runtime
    /// thread.
    ///
    /// ```no_run
    /// use leveret_ports::{InPort, OutPort, PortProfile, Qos, Time, TimedVelocity2D};
    /// use std::time::Duration;
    ///
    /// # fn main() -> leveret_client::Result<()> {
    /// // The ports' tasks run on a runtime; the control loop on its own thread.
    /// let runtime = tokio::runtime::Runtime::new().expect("runtime");
    /// let profile = PortProfile::new("amqp://guest:guest@localhost:5672/%2f")?
    ///     .queue("cmd_vel")
    ///     .routing_key("cmd_vel")
    ///     .qos(Qos::Command);
    /// let output = runtime.block_on(OutPort::<TimedVelocity2D>::connect(profile.clone()))?;
    /// let input = runtime.block_on(InPort::<TimedVelocity2D>::connect(profile))?;
    /// std::thread::spawn(move || loop {
    ///     let command = TimedVelocity2D { tm: Time::now(), ..Default::default() };
    ///     output.put_blocking(&command);
    ///     if let Some(sample) = input.recv_blocking(Duration::from_millis(10)) {
    ///         println!("{:?}", sample.value);
    ///     }
    /// });
    /// # Ok(())
    /// # }
    /// ```
    pub fn put_blocking(&self, value: &T) -> PortStatus {
        let body = match encode(value, self.cdr) {
            Ok(body) => body,
            Err(status) => return status,
        };
        let deadline = std::time::Instant::now() + self.timeout;
        let mut body = Some(body);
        let mut window = self.shared.window();
        loop {
            if let Some(status) = self.enqueue_locked(window, &mut body) {
                return status;
            }
            window = self.shared.window();
            let now = std::time::Instant::now();
            if now >= deadline || window.closed {
                drop(window);
                return self.refuse();
            }
            if window.entries.len() < self.capacity {
                continue;
            }
            window.blocked_putters += 1;
            window = self
                .shared
                .room_blocking
                .wait_timeout(window, deadline - now)
                .unwrap_or_else(|e| e.into_inner())
                .0;
            window.blocked_putters -= 1;
        }
    }

    /// Appends the body if the policy lets it in now: `Some(status)` once
    /// decided, `None` if it must wait for room.
    fn enqueue(&self, body: &mut Option<Bytes>) -> Option<PortStatus> {
        self.enqueue_locked(self.shared.window(), body)
    }

    fn enqueue_locked(
        &self,
        mut window: MutexGuard<'_, Window>,
        body: &mut Option<Bytes>,
    ) -> Option<PortStatus> {
        if window.closed {
            return Some(PortStatus::Closed);
        }
        let mut outcomes = Vec::new();
        if window.entries.len() >= self.capacity {
            expire_oldest(&mut window, self.lifespan, &mut outcomes);
        }
        if window.entries.len() >= self.capacity {
            match self.backpressure {
                Backpressure::DropOldest => drop_oldest(&mut window, &mut outcomes),
                Backpressure::DropNewest => {
                    drop(window);
                    return Some(self.refuse());
                }
                Backpressure::Block => return None,
            }
        }
        let seq = window.next_seq;
        window.next_seq += 1;
        window.entries.push_back(Entry {
            seq,
            sent_ns: link::now_ns(),
            put_at: Instant::now(),
            body: body.take()?,
            attempts: 0,
        });
        window.stats.accepted += 1;
        window.measure();
        if window.channel.is_none() {
            drop(window);
            self.shared.work.notify_one();
            self.shared.report(&outcomes, false);
            return Some(PortStatus::ConnectionLost);
        }
        // Everything before it published: publish it here rather than
        // wake the task for it. The task takes over whatever this leaves
        // (no room in the outbox, a link that just failed) and polls the
        // confirm of a first message in flight.
        let before = outcomes.len();
        let publish_from = window.publish_from;
        let first_unsent = window
            .entries
            .partition_point(|entry| entry.seq < publish_from);
        let mut recovered = false;
        let wake = if first_unsent + 1 == window.entries.len() {
            let idle = window.inflight.is_empty();
            match self.shared.publish_next(&mut window, None, &mut outcomes) {
                Next::Published => {
                    // Its confirm, if it has come with it (in process).
                    if self.shared.settle_confirmed(&mut window, &mut outcomes) > 0 {
                        recovered = std::mem::take(&mut window.degraded);
                    }
                    // The task polls the confirm of a first message left
                    // in flight.
                    idle && !window.inflight.is_empty()
                }
                // The task publishes it when a confirm makes room.
                Next::Windowed => false,
                Next::Idle | Next::Full | Next::Failed(_) => true,
            }
        } else {
            true
        };
        let status = if window.degraded {
            PortStatus::Degraded
        } else {
            PortStatus::Ok
        };
        drop(window);
        if recovered {
            self.shared.link.degraded(false);
        }
        if wake {
            self.shared.work.notify_one();
        }
        self.shared.report(&outcomes, outcomes.len() > before);
        Some(status)
    }

    /// Counts a value refused for want of room.
    fn refuse(&self) -> PortStatus {
        let mut window = self.shared.window();
        if window.closed {
            return PortStatus::Closed;
        }
        window.stats.send_full += 1;
        drop(window);
        self.shared.publish_stats();
        PortStatus::SendFull
    }

    /// Waits until every accepted message has its [`Fate`] (nothing is
    /// pending); wrap it in a timeout.
    pub async fn flush(&self) {
        // The counters' watchers get them only once every outcome counted
        // is delivered (see `Shared::send_stats`). When the port's task
        // has settled a confirm under the window's lock and not yet
        // reported it, a `put` on this thread skips sending its counters,
        // so the watchers still hold the ones from before it, `pending` 0
        // among them, until the task reports; a task preempted there let
        // many puts in a row each flush at once (CI: 79 of 200 left
        // unconfirmed). So a flush waits for counters that count every
        // message accepted before it, then for nothing pending.
        let accepted = self.stats().accepted;
        let mut stats = self.shared.stats.subscribe();
        let _ = stats
            .wait_for(|s| s.accepted >= accepted && s.pending == 0)
            .await;
    }

    /// The counters so far.
    pub fn stats(&self) -> OutPortStats {
        self.shared.window().stats
    }

    /// The counters as they change, to wait for a condition on them.
    pub fn watch_stats(&self) -> watch::Receiver<OutPortStats> {
        self.shared.stats.subscribe()
    }

    /// The stream of [`Outcome`]s from now on. It buffers
    /// 1024 outcomes for a slow reader; one further behind is told how
    /// many it missed (`RecvError::Lagged`) and the counters stay exact.
    pub fn outcomes(&self) -> broadcast::Receiver<Outcome> {
        self.shared.outcomes.subscribe()
    }

    /// Calls `callback` with every [`Outcome`] from now on (keep it short:
    /// it runs on the port's task, or in `put` for a value it publishes
    /// without confirms or drops). The counters' watchers
    /// ([`OutPort::watch_stats`], [`OutPort::flush`]) see an outcome
    /// counted only once it has been delivered; [`OutPort::stats`] may
    /// count it a moment before.
    pub fn on_outcome(&self, callback: impl FnMut(&Outcome) + Send + 'static) {
        lock(&self.shared.reporting)
            .callbacks
            .push(Box::new(callback));
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

impl<T> Drop for OutPort<T> {
    fn drop(&mut self) {
        lock(&self.shared.window).closed = true;
        self.shared.work.notify_one();
        self.shared.room.notify_waiters();
        self.shared.room_blocking.notify_all();
    }
}

fn encode<T: PortData>(value: &T, options: CdrOptions) -> std::result::Result<Bytes, PortStatus> {
    let mut body = BytesMut::new();
    match value.encode_with(&mut body, options) {
        Ok(()) => Ok(body.freeze()),
        Err(error) => {
            tracing::warn!(%error, "out-port value could not be encoded");
            Err(PortStatus::InvalidArgs)
        }
    }
}

/// Refuses a profile whose messages could reach no queue (the default
/// exchange with no routing key), or that records on the default exchange
/// (no stream can be bound to it).
fn check_routes(profile: &PortProfile) -> Result<()> {
    if profile.exchange.is_empty() && profile.routing_key.is_empty() {
        return Err(Error::InvalidArgument(
            "the out-port's profile routes nowhere: no exchange and no routing key".to_owned(),
        ));
    }
    if profile.record.is_some() && profile.exchange.is_empty() {
        return Err(Error::InvalidArgument(
            "recording needs a named exchange: the default exchange routes to one queue only, \
             and no stream can be bound to it"
                .to_owned(),
        ));
    }
    Ok(())
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
            link::declare_queue(&channel, &profile, &profile.queue, false, true).await?;
        }
        link::declare_recording(&channel, &profile).await?;
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
    /// The confirm of message `seq`, the oldest in flight.
    Confirm(u64, Result<Confirmation>),
    Returned(Box<ReturnedMessage>),
    Work,
    Opened(Result<OutLink>),
    Lost(Error),
    Retry,
    /// The oldest message in flight has waited for its confirm longer
    /// than the stall timeout.
    Stalled,
}

struct Task {
    shared: Arc<Shared>,
    connector: Connector,
    profile: Arc<PortProfile>,
    link: Option<OutLink>,
    connecting: Option<Opening>,
    failures: u32,
    retry_at: Instant,
    /// How long the broker may confirm (or take) nothing before the link
    /// counts as degraded.
    stall_timeout: Duration,
    announcer: Announcer,
}

impl Task {
    async fn run(mut self) {
        loop {
            if self.shared.window().closed {
                break;
            }
            if self.link.is_some() && self.publish_next().await {
                continue;
            }
            if self.link.is_none() && self.connecting.is_none() && Instant::now() >= self.retry_at {
                let opening = open(self.connector.clone(), Arc::clone(&self.profile));
                self.connecting = Some(Box::pin(opening));
            }
            match self.next_event().await {
                Event::Returned(message) => self.returned(&message),
                Event::Confirm(seq, result) => self.confirmed(seq, result),
                Event::Work => {}
                Event::Retry => self.expire_while_down(),
                Event::Opened(result) => self.opened(result),
                Event::Lost(error) => self.lost(error),
                Event::Stalled => self.stalled(),
            }
        }
        self.shared.window().channel = None;
        if let Some(link) = self.link.take() {
            self.announcer.close().await;
            let _ = tokio::time::timeout(CLOSE_TIMEOUT, link.connection.close()).await;
        }
    }

    async fn next_event(&mut self) -> Event {
        let shared = &self.shared;
        let connecting = &mut self.connecting;
        let channel = self.link.as_ref().map(|link| link.channel.clone());
        let idle = self.link.is_none() && connecting.is_none();
        let stall_at = {
            let window = shared.window();
            match window.inflight.front() {
                Some(oldest) if !window.degraded => Some(oldest.written_at + self.stall_timeout),
                _ => None,
            }
        };
        let confirm = std::future::poll_fn(|cx| match shared.window().inflight.front_mut() {
            Some(oldest) => {
                let seq = oldest.seq;
                Pin::new(&mut oldest.confirm)
                    .poll(cx)
                    .map(|result| (seq, result))
            }
            None => Poll::Pending,
        });
        let stalled = async move {
            match stall_at {
                Some(at) => tokio::time::sleep_until(at).await,
                None => std::future::pending().await,
            }
        };
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
        let returned = std::future::poll_fn(|cx| match shared.window().returns.as_mut() {
            Some(returns) => match Pin::new(returns).poll_next(cx) {
                Poll::Ready(Some(message)) => Poll::Ready(Box::new(message)),
                // The channel's end shows as `closed`.
                Poll::Ready(None) | Poll::Pending => Poll::Pending,
            },
            None => Poll::Pending,
        });
        tokio::select! {
            biased;
            // A message's return comes before its confirm.
            message = returned => Event::Returned(message),
            (seq, result) = confirm => Event::Confirm(seq, result),
            () = self.shared.work.notified() => Event::Work,
            result = opened => Event::Opened(result),
            error = closed => Event::Lost(error),
            _ = tokio::time::sleep_until(self.retry_at), if idle => Event::Retry,
            () = stalled => Event::Stalled,
        }
    }

    /// Publishes the next message of the window not yet published on this
    /// link (waiting for room in the outbox if need be), expiring what is
    /// past its lifespan; false if there is none.
    async fn publish_next(&mut self) -> bool {
        let mut outcomes = Vec::new();
        let mut next = {
            let mut window = self.shared.window();
            self.shared.publish_next(&mut window, None, &mut outcomes)
        };
        if let (Next::Full, Some(link)) = (&next, &self.link) {
            let channel = link.channel.clone();
            let reserve = channel.reserve();
            tokio::pin!(reserve);
            // An outbox that takes nothing for the stall timeout is a
            // stalled link too (the way a port without confirms sees it).
            let reserved = match tokio::time::timeout(self.stall_timeout, &mut reserve).await {
                Ok(reserved) => reserved,
                Err(_) => {
                    self.stalled();
                    reserve.await
                }
            };
            next = match reserved {
                Ok(slot) => {
                    let mut window = self.shared.window();
                    self.shared
                        .publish_next(&mut window, Some(slot), &mut outcomes)
                }
                Err(error) => Next::Failed(error),
            };
        }
        if !outcomes.is_empty() {
            self.shared.report(&outcomes, true);
        }
        if matches!(next, Next::Published) && !self.profile.confirms {
            self.recovered();
        }
        match next {
            Next::Published | Next::Full => true,
            Next::Idle | Next::Windowed => !outcomes.is_empty(),
            Next::Failed(error) => {
                self.lost(error);
                true
            }
        }
    }

    /// The confirm of message `seq`, the oldest published, arrived (or its
    /// link failed). `put` may have settled it meanwhile.
    fn confirmed(&mut self, seq: u64, result: Result<Confirmation>) {
        match result {
            Ok(confirmation) => {
                let mut outcomes = Vec::new();
                {
                    let mut window = self.shared.window();
                    settle_in_flight(&mut window, seq, confirmation, &mut outcomes);
                }
                self.recovered();
                self.shared.report(&outcomes, true);
            }
            Err(error) => self.lost(error),
        }
    }

    /// The broker has confirmed nothing (or taken nothing) for the stall
    /// timeout: the link is degraded until it does.
    fn stalled(&mut self) {
        let mut window = self.shared.window();
        if window.degraded || window.channel.is_none() {
            return;
        }
        window.degraded = true;
        window.stats.stalls += 1;
        drop(window);
        self.shared.publish_stats();
        self.shared.link.degraded(true);
    }

    /// The broker confirmed (or took) a message: a degraded link is well
    /// again.
    fn recovered(&mut self) {
        let mut window = self.shared.window();
        if !window.degraded {
            return;
        }
        window.degraded = false;
        drop(window);
        self.shared.link.degraded(false);
    }

    /// The broker returned a message no queue took. With confirms its
    /// fate waits for its confirm (which follows); without, its fate was
    /// already counted (sent-unconfirmed): the return is counted apart.
    fn returned(&mut self, message: &ReturnedMessage) {
        let Some(seq) = link::Stamp::read(message.properties.headers.as_ref()).seq else {
            return;
        };
        let mut window = self.shared.window();
        if self.profile.confirms {
            window.returned.insert(seq);
            return;
        }
        window.stats.returned_after_send += 1;
        drop(window);
        self.shared.publish_stats();
    }

    /// While the link is down, the values past their lifespan leave the
    /// window (and make room) without waiting for the next link.
    fn expire_while_down(&mut self) {
        let mut outcomes = Vec::new();
        let mut window = self.shared.window();
        expire_oldest(&mut window, self.profile.lifespan, &mut outcomes);
        drop(window);
        if !outcomes.is_empty() {
            self.shared.report(&outcomes, true);
        }
    }

    /// The link failed: replay the window on the next one, as the replay
    /// policy says.
    fn lost(&mut self, error: Error) {
        if let Some(link) = self.link.take() {
            drop(link.channel);
            drop(link.connection);
        }
        let mut outcomes = Vec::new();
        let mut window = self.shared.window();
        window.channel = None;
        window.returns = None;
        window.returned.clear();
        window.inflight.clear();
        window.inflight_bytes = 0;
        window.degraded = false;
        window.publish_from = 0;
        window.measure();
        if self.profile.replay == Replay::Nothing {
            keep_newest(&mut window, 0, &mut outcomes);
        }
        drop(window);
        self.shared.report(&outcomes, !outcomes.is_empty());
        self.shared.link.lost(&error);
        self.failures = 0;
        self.retry_at = Instant::now();
    }

    fn opened(&mut self, result: Result<OutLink>) {
        self.connecting = None;
        match result {
            Ok(link) => {
                self.failures = 0;
                let mut outcomes = Vec::new();
                let mut window = self.shared.window();
                window.channel = Some(link.channel.clone());
                window.returns = Some(link.channel.returns());
                self.link = Some(link);
                if self.profile.replay == Replay::Latest {
                    keep_newest(&mut window, 1, &mut outcomes);
                }
                drop(window);
                self.shared.report(&outcomes, !outcomes.is_empty());
                self.shared.link.connected();
                if let Some(link) = &self.link {
                    self.announcer.link_up(&link.connection);
                }
            }
            Err(error) => {
                self.shared.link.failed(&error);
                self.retry_at = Instant::now() + self.profile.backoff.delay(self.failures);
                self.failures = self.failures.saturating_add(1);
            }
        }
    }
}
