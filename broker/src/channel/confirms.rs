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
    /// (a refused one needs none: it is due at once).
    fn store_needs(&self) -> Option<u64> {
        let (_, first) = self.waiting.front()?;
        Some(if first.refused {
            0
        } else {
            first.written.last()
        })
    }
}

/// Resolves once one of `channels` has confirms due, the one that waits
/// for the least store progress (never if none waits; a closing channel
/// sends no more confirms, so it is never due): its connection
/// then sends what is due on each ([`Channel::flush_confirms`]).
pub async fn confirms_due<'a>(channels: impl Iterator<Item = &'a Channel>) {
    let first = channels
        .filter(|channel| !channel.closing)
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
    /// waiting publish needs, or the persister has stopped (what it never
    /// wrote is then nacked): never if none waits on the store, or the
    /// channel has none.
    async fn confirms_due(&self) {
        let Some(needs) = self.confirms.as_ref().and_then(Confirms::store_needs) else {
            return std::future::pending().await;
        };
        if let Some(persistence) = &self.core.persistence {
            let mut durable = persistence.durable();
            // An error is the persister gone: due too.
            let _ = durable.wait_for(|d| d.flushed >= needs).await;
        }
    }

    /// Forgets the publishes awaiting their confirm: a channel that closes
    /// sends no more confirms (RabbitMQ drops those of a channel closed on
    /// error), and a client that reopens its number must not take them
    /// for the new channel's.
    pub(super) fn drop_confirms(&mut self) {
        if let Some(confirms) = &mut self.confirms {
            confirms.waiting.clear();
        }
        self.note_pending();
    }

    /// Sends the confirms that are due, in tag order: consecutive acks as
    /// one basic.ack with `multiple`, nacks one by one (none once the
    /// channel is closing).
    pub async fn flush_confirms(&mut self) {
        if self.closing {
            return;
        }
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::access::auth::Users;
    use crate::access::permissions::{Permission, Permissions};
    use crate::channel::WholePublish;
    use crate::core::{Core, CoreOptions, Limits};
    use crate::outbox::{Framed, Outbound, Outbox};
    use crate::parameters::Parameters;
    use crate::queue::QueueOptions;
    use crate::store::{Persistence, Recovered, Store};
    use crate::testkit::Gated;
    use crate::vhost::QueueDeclaration;
    use bytes::Bytes;
    use leveret_protocol::handoff;
    use leveret_protocol::{BasicProperties, BasicPublish, Method, ShortStr};
    use std::sync::atomic::Ordering;
    use std::sync::Arc;

    /// A channel in confirm mode on a broker over `store`, with a durable
    /// queue `kept`, and what its outbox receives.
    async fn confirming(store: Arc<Gated>) -> (Channel, handoff::Receiver<Outbound>) {
        let (outbox, inbox) = Outbox::new(1);
        (confirming_on(store, outbox).await, inbox)
    }

    /// [`confirming`]'s channel, sending into `outbox`.
    async fn confirming_on(store: Arc<Gated>, outbox: Arc<Outbox>) -> Channel {
        let store: Arc<dyn Store> = store;
        let persistence = Persistence::start(store, &Recovered::default()).expect("persister");
        let permissions = Permissions::default();
        permissions
            .set("guest", "/", Permission::full())
            .expect("set");
        let core = Core::new(CoreOptions {
            vhosts: vec!["/".into()],
            users: Users::default(),
            permissions,
            parameters: Parameters::default(),
            limits: Limits::default(),
            persistence: Some(persistence),
            product: "test".into(),
            busy_poll: None,
        });
        let vhost = core.vhost(&ShortStr::from_static("/")).expect("vhost /");
        vhost
            .declare_queue(
                QueueDeclaration {
                    name: ShortStr::from_static("kept"),
                    passive: false,
                    server_named: false,
                    max_queues: None,
                    options: QueueOptions {
                        durable: true,
                        exclusive_owner: None,
                        auto_delete: false,
                        arguments: Default::default(),
                    },
                },
                0,
            )
            .expect("queue.declare");
        let mut channel = Channel::new(1, outbox, vhost, core, "guest".into(), 0);
        channel.confirm_select(true).await.expect("confirm.select");
        channel
    }

    fn publish_persistent(channel: &mut Channel) {
        let left = channel.publish_at_once(WholePublish {
            channel: 1,
            method: BasicPublish {
                routing_key: ShortStr::from_static("kept"),
                ..Default::default()
            },
            properties: Box::new(BasicProperties {
                delivery_mode: Some(2),
                ..Default::default()
            }),
            body: Bytes::from_static(b"safe"),
        });
        assert!(left.is_none(), "a publish to one queue finishes at once");
    }

    fn sent(inbox: &mut handoff::Receiver<Outbound>) -> Vec<Method> {
        std::iter::from_fn(|| inbox.try_recv())
            .filter_map(|item| match item.framed() {
                Framed::Method { method, .. } => Some(method),
                _ => None,
            })
            .collect()
    }

    /// The channel watches the store itself: no ack while the message's
    /// entry is not on disk, its confirm falls due once it is, and the
    /// acks of publishes written together go out as one.
    #[tokio::test]
    async fn a_confirm_waits_for_the_store_and_falls_due_with_it() {
        let store = Arc::new(Gated::default());
        store.hold(true);
        let (mut channel, mut inbox) = confirming(Arc::clone(&store)).await;
        publish_persistent(&mut channel);
        publish_persistent(&mut channel);
        channel.flush_confirms().await;
        assert!(sent(&mut inbox).is_empty(), "nothing is on disk yet");
        // A zero timeout polls the future once, then gives up.
        let due = confirms_due(std::iter::once(&channel));
        assert!(
            tokio::time::timeout(std::time::Duration::ZERO, due)
                .await
                .is_err(),
            "not due while the store holds the write"
        );
        store.hold(false);
        falls_due(&channel).await;
        // Both entries may not be in the group that made the first due.
        let persistence = channel.core.persistence.clone().expect("persister");
        assert!(persistence.sync().await);
        channel.flush_confirms().await;
        let methods = sent(&mut inbox);
        assert!(
            matches!(
                methods[..],
                [Method::BasicAck(BasicAck {
                    delivery_tag: 2,
                    multiple: true
                })]
            ),
            "{methods:?}"
        );
        assert_eq!(channel.confirms.as_ref().map(Confirms::len), Some(0));
        assert_eq!(channel.core.stats.confirmed.get(), 2);
    }

    /// A nack dropped because the connection was told to close while it
    /// waited for room is followed by no ack, even once the writer has
    /// made room: an ack `multiple` of later publishes would confirm the
    /// refused one to the publisher (review BUG 1).
    #[tokio::test]
    async fn a_nack_dropped_at_the_close_is_followed_by_no_ack() {
        let (close, closing) = tokio::sync::watch::channel(false);
        let (outbox, mut inbox) = Outbox::connection(1, false, closing);
        let mut channel = confirming_on(Arc::new(Gated::default()), Arc::clone(&outbox)).await;
        let fill = leveret_protocol::BasicCancel {
            consumer_tag: ShortStr::from_static("fill"),
            no_wait: true,
        };
        for _ in 0..crate::outbox::OUTBOX_CAPACITY {
            assert!(outbox.try_send(Outbound::method(1, fill.clone().into())));
        }
        let refused = Published {
            refused: true,
            ..Published::default()
        };
        channel.confirm(1, refused);
        let flushing = tokio::spawn(async move {
            channel.flush_confirms().await;
            channel
        });
        tokio::task::yield_now().await;
        assert!(!flushing.is_finished(), "the nack waits for room");
        close.send_replace(true);
        let mut channel = tokio::time::timeout(std::time::Duration::from_secs(30), flushing)
            .await
            .expect("the wait ends at the close")
            .expect("ran");
        let drained = sent(&mut inbox);
        assert_eq!(drained.len(), crate::outbox::OUTBOX_CAPACITY);
        assert!(drained.iter().all(|m| matches!(m, Method::BasicCancel(_))));
        channel.confirm(2, Published::default());
        channel.confirm(3, Published::default());
        channel.flush_confirms().await;
        let methods = sent(&mut inbox);
        assert!(
            methods.is_empty(),
            "no confirm after the dropped nack: {methods:?}"
        );
    }

    /// Awaits `confirms_due` on `channel`, failing (not hanging) if it
    /// never resolves.
    async fn falls_due(channel: &Channel) {
        tokio::time::timeout(
            std::time::Duration::from_secs(30),
            confirms_due(std::iter::once(channel)),
        )
        .await
        .expect("confirms fall due");
    }

    /// A channel closed on error sends no more confirms: not the ack of a
    /// publish whose write finishes after its channel.close.
    #[tokio::test]
    async fn a_channel_closed_on_error_sends_no_more_confirms() {
        let store = Arc::new(Gated::default());
        store.hold(true);
        let (mut channel, mut inbox) = confirming(Arc::clone(&store)).await;
        publish_persistent(&mut channel);
        channel
            .close_with(AmqpError::precondition_failed("test"))
            .await;
        store.hold(false);
        let persistence = channel.core.persistence.clone().expect("persister");
        assert!(persistence.sync().await);
        let due = confirms_due(std::iter::once(&channel));
        assert!(
            tokio::time::timeout(std::time::Duration::ZERO, due)
                .await
                .is_err(),
            "a closing channel has no confirms due"
        );
        tokio::time::timeout(std::time::Duration::from_secs(30), channel.flush_confirms())
            .await
            .expect("flush");
        let methods = sent(&mut inbox);
        assert!(
            matches!(methods[..], [Method::ChannelClose(_)]),
            "{methods:?}"
        );
        assert_eq!(channel.confirms.as_ref().map(Confirms::len), Some(0));
    }

    /// Once the persister has stopped, a publish it never wrote is nacked
    /// rather than left waiting for ever.
    #[tokio::test]
    async fn a_stopped_persister_nacks_what_it_never_wrote() {
        let store = Arc::new(Gated::default());
        let (mut channel, mut inbox) = confirming(Arc::clone(&store)).await;
        let persistence = channel.core.persistence.clone().expect("persister");
        assert!(persistence.close(Vec::new()).await);
        publish_persistent(&mut channel);
        falls_due(&channel).await;
        // The persister thread may still be ending: due again until it has.
        let methods = tokio::time::timeout(std::time::Duration::from_secs(30), async {
            loop {
                channel.flush_confirms().await;
                let methods = sent(&mut inbox);
                if !methods.is_empty() {
                    return methods;
                }
                tokio::task::yield_now().await;
            }
        })
        .await
        .expect("the publish is confirmed");
        assert!(
            matches!(
                methods[..],
                [Method::BasicNack(BasicNack {
                    delivery_tag: 1,
                    ..
                })]
            ),
            "{methods:?}"
        );
        assert_eq!(channel.core.stats.confirmed.get(), 0);
    }

    /// A refused publish waits for nothing: it is due at once.
    #[test]
    fn a_refused_head_is_due_at_once() {
        let mut confirms = Confirms::default();
        assert_eq!(confirms.store_needs(), None);
        confirms.waiting.push_back((
            1,
            Published {
                refused: true,
                ..Default::default()
            },
        ));
        assert_eq!(confirms.store_needs(), Some(0));
    }

    /// A publish whose write failed is nacked, never acked.
    #[tokio::test]
    async fn a_failed_write_is_nacked() {
        let store = Arc::new(Gated::default());
        store.failing.store(true, Ordering::SeqCst);
        let (mut channel, mut inbox) = confirming(Arc::clone(&store)).await;
        publish_persistent(&mut channel);
        falls_due(&channel).await;
        channel.flush_confirms().await;
        let methods = sent(&mut inbox);
        assert!(
            matches!(
                methods[..],
                [Method::BasicNack(BasicNack {
                    delivery_tag: 1,
                    multiple: false,
                    ..
                })]
            ),
            "{methods:?}"
        );
        assert_eq!(channel.core.stats.confirmed.get(), 0);
    }
}
