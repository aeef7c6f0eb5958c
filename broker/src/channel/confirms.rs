//! Publisher confirms: confirm.select, the tag each publish gets, what
//! each waits for (the outcome the vhost's publish step returned), and the
//! acks and nacks that answer them. The channel watches the store itself:
//! [`Channel::confirms_due`] resolves once the store has reached what its
//! first waiting publish needs, and [`Channel::flush_confirms`] sends what
//! is due. Its connection only drives these futures ([`confirms_due`] for
//! all its channels at once) and knows nothing of the store.
//!
//! Confirms go out in tag order: consecutive acks are coalesced into one
//! basic.ack with `multiple` (sent once the connection has no more input
//! buffered), nacks one by one, and a publish waiting for the disk holds
//! back those after it, so a multiple ack never covers a message that is
//! not yet safe. A publish is acked only once its message and every
//! durable queue's entry are on disk; nacked when a queue refused it or a
//! write of it failed.

use super::Channel;
use crate::error::{AmqpError, AmqpResult};
use crate::registry::ChannelMode;
use crate::vhost::publish::Published;
use leveret_protocol::{BasicAck, BasicNack, ConfirmSelectOk};
use std::collections::VecDeque;

/// Publisher-confirm state of a channel.
#[derive(Debug, Default)]
pub(crate) struct Confirms {
    last_tag: u64,
    /// Publishes not yet confirmed, in tag order, with what they wait for.
    waiting: VecDeque<(u64, Published)>,
}

impl Confirms {
    pub(super) fn next_tag(&mut self) -> u64 {
        self.last_tag += 1;
        self.last_tag
    }

    /// Publishes awaiting their confirm.
    pub(super) fn len(&self) -> usize {
        self.waiting.len()
    }

    /// The store's progress the first waiting publish needs, if one waits
    /// on the store (a refused one is due at once).
    fn store_needs(&self) -> Option<u64> {
        let (_, first) = self.waiting.front()?;
        (!first.refused).then(|| first.written.last())
    }
}

/// Resolves once one of `channels` has confirms due, the one that waits
/// for the least store progress (never if none waits): its connection
/// then sends what is due on each ([`Channel::flush_confirms`]).
pub async fn confirms_due<'a>(channels: impl Iterator<Item = &'a Channel>) {
    let first = channels
        .filter_map(|channel| Some((channel.confirms.as_ref()?.store_needs()?, channel)))
        .min_by_key(|(needs, _)| *needs);
    match first {
        Some((_, channel)) => channel.confirms_due().await,
        None => std::future::pending().await,
    }
}

impl Channel {
    pub(super) async fn confirm_select(&mut self, no_wait: bool) -> AmqpResult<()> {
        if self.tx.is_some() {
            return Err(AmqpError::precondition_failed(
                "cannot switch from tx to confirm mode",
            ));
        }
        if self.confirms.is_none() {
            self.confirms = Some(Confirms::default());
            self.registration.set_mode(ChannelMode::Confirm);
        }
        if !no_wait {
            self.reply(ConfirmSelectOk {}).await;
        }
        Ok(())
    }

    /// Records the outcome of publish `tag`; it is confirmed by the next
    /// [`Channel::flush_confirms`] that finds it (and all before it) settled.
    pub(super) fn confirm(&mut self, tag: u64, published: Published) {
        if let Some(confirms) = &mut self.confirms {
            confirms.waiting.push_back((tag, published));
        }
        self.note_pending();
    }

    /// Resolves once the store has reached what this channel's first
    /// waiting publish needs (never if none waits on the store, or the
    /// channel has none).
    async fn confirms_due(&self) {
        let needs = self.confirms.as_ref().and_then(Confirms::store_needs);
        if let (Some(needs), Some(persistence)) = (needs, &self.core.persistence) {
            let mut durable = persistence.durable();
            if durable.wait_for(|d| d.flushed >= needs).await.is_ok() {
                return;
            }
        }
        std::future::pending().await
    }

    /// Sends the confirms that are due, in tag order: consecutive acks as
    /// one basic.ack with `multiple`, nacks one by one.
    pub async fn flush_confirms(&mut self) {
        let mut acks: Option<(u64, u64)> = None;
        let mut nacks = Vec::new();
        if let Some(confirms) = &mut self.confirms {
            while let Some(&(tag, published)) = confirms.waiting.front() {
                let ack = if published.refused {
                    false
                } else {
                    match &self.core.persistence {
                        Some(persistence) => match persistence.written(published.written) {
                            Some(written) => written,
                            None => break,
                        },
                        None => true,
                    }
                };
                confirms.waiting.pop_front();
                if ack {
                    self.core.stats.confirmed.inc();
                    acks = Some(acks.map_or((tag, tag), |(low, _)| (low, tag)));
                } else {
                    nacks.push((acks.take(), tag));
                }
            }
        }
        self.note_pending();
        for (before, tag) in nacks {
            if let Some((low, high)) = before {
                self.send_ack(low, high).await;
            }
            self.reply(BasicNack {
                delivery_tag: tag,
                multiple: false,
                requeue: false,
            })
            .await;
        }
        if let Some((low, high)) = acks {
            self.send_ack(low, high).await;
        }
    }

    async fn send_ack(&self, low: u64, high: u64) {
        self.reply(BasicAck {
            delivery_tag: high,
            multiple: high > low,
        })
        .await;
    }
}
