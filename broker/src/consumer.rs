//! Consumers and the per-channel delivery bookkeeping shared between a
//! channel (which handles acks) and the queues (which deliver): delivery
//! tags, the unacked list, prefetch credit and channel.flow.

use crate::outbox::Outbox;
use crate::queue::{Queue, QueuedMessage};
use leveret_protocol::ShortStr;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};

/// A delivery waiting for ack, nack or reject.
#[derive(Debug)]
pub struct Unacked {
    /// Its delivery tag.
    pub tag: u64,
    /// The queue it came from.
    pub queue: Arc<Queue>,
    /// The message and its place in the queue.
    pub message: QueuedMessage,
    /// The consumer it went to (None for basic.get).
    pub consumer: Option<Arc<Consumer>>,
}

/// Delivery tags and unacked deliveries of one channel, in tag order.
#[derive(Debug, Default)]
pub struct Deliveries {
    last_tag: u64,
    unacked: VecDeque<Unacked>,
}

impl Deliveries {
    /// Hands out the next delivery tag.
    pub fn next_tag(&mut self) -> u64 {
        self.last_tag += 1;
        self.last_tag
    }

    /// Records an unacked delivery (its tag must be the newest).
    pub fn push(&mut self, unacked: Unacked) {
        self.unacked.push_back(unacked);
    }

    /// Takes the deliveries `tag` settles: that one, or with `multiple`
    /// every one up to it (tag 0 with multiple means all). As in RabbitMQ,
    /// the tag itself must be outstanding, even with `multiple`; `None`
    /// means it is unknown or already settled.
    pub fn take(&mut self, tag: u64, multiple: bool) -> Option<Vec<Unacked>> {
        if multiple && tag == 0 {
            return Some(self.take_all());
        }
        let index = self.unacked.binary_search_by_key(&tag, |u| u.tag).ok()?;
        if multiple {
            Some(self.unacked.drain(..=index).collect())
        } else {
            self.unacked.remove(index).map(|u| vec![u])
        }
    }

    /// Puts taken deliveries back (a rolled-back transaction's acks).
    pub fn restore(&mut self, deliveries: impl IntoIterator<Item = Unacked>) {
        for unacked in deliveries {
            let at = self.unacked.partition_point(|u| u.tag < unacked.tag);
            self.unacked.insert(at, unacked);
        }
    }

    /// How many deliveries are unacked.
    pub fn unacked_count(&self) -> usize {
        self.unacked.len()
    }

    /// Takes every unacked delivery (channel close, recover).
    pub fn take_all(&mut self) -> Vec<Unacked> {
        self.unacked.drain(..).collect()
    }
}

/// What queues need of a channel to deliver to its consumers.
#[derive(Debug)]
pub struct ChannelLink {
    /// Channel number.
    pub id: u16,
    /// The connection's writer.
    pub outbox: Arc<Outbox>,
    deliveries: Mutex<Deliveries>,
    /// basic.qos global prefetch count (0 = none), RabbitMQ's meaning:
    /// shared by all consumers on the channel.
    pub global_prefetch: AtomicU32,
    /// Unacked deliveries to consumers of this channel.
    pub global_in_flight: AtomicU32,
    /// channel.flow state: false stops deliveries.
    pub flow_active: AtomicBool,
}

impl ChannelLink {
    /// A link for channel `id` of the connection writing to `outbox`.
    pub fn new(id: u16, outbox: Arc<Outbox>) -> Self {
        ChannelLink {
            id,
            outbox,
            deliveries: Mutex::new(Deliveries::default()),
            global_prefetch: AtomicU32::new(0),
            global_in_flight: AtomicU32::new(0),
            flow_active: AtomicBool::new(true),
        }
    }

    /// Locks the delivery bookkeeping. The lock is held for a few
    /// instructions (tag, push, or take) and never across an await.
    pub fn deliveries(&self) -> MutexGuard<'_, Deliveries> {
        self.deliveries.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// One basic.consume subscription.
#[derive(Debug)]
pub struct Consumer {
    /// Consumer tag.
    pub tag: ShortStr,
    /// Its channel.
    pub channel: Arc<ChannelLink>,
    /// Deliveries need no ack.
    pub no_ack: bool,
    /// Exclusive consumer of its queue.
    pub exclusive: bool,
    /// Per-consumer prefetch count (0 = unlimited).
    pub prefetch: u32,
    /// `x-priority` (RabbitMQ): higher-priority consumers are served first.
    pub priority: i64,
    /// Unacked deliveries to this consumer.
    pub in_flight: AtomicU32,
    /// Set once basic.consume-ok is on its way, so no delivery overtakes it.
    pub active: AtomicBool,
}

impl Consumer {
    /// Whether prefetch and flow allow one more delivery now.
    pub fn has_credit(&self) -> bool {
        if !self.active.load(Ordering::Acquire) || !self.channel.flow_active.load(Ordering::Relaxed)
        {
            return false;
        }
        if self.no_ack {
            return true;
        }
        let own = self.prefetch == 0 || self.in_flight.load(Ordering::Relaxed) < self.prefetch;
        let global = self.channel.global_prefetch.load(Ordering::Relaxed);
        own && (global == 0 || self.channel.global_in_flight.load(Ordering::Relaxed) < global)
    }

    /// Lets the queue deliver to this consumer.
    pub fn activate(&self) {
        self.active.store(true, Ordering::Release);
    }

    /// Counts one more unacked delivery.
    pub fn took_one(&self) {
        self.in_flight.fetch_add(1, Ordering::Relaxed);
        self.channel
            .global_in_flight
            .fetch_add(1, Ordering::Relaxed);
    }

    /// Counts one settled delivery.
    pub fn settled_one(&self) {
        self.in_flight.fetch_sub(1, Ordering::Relaxed);
        self.channel
            .global_in_flight
            .fetch_sub(1, Ordering::Relaxed);
    }
}
