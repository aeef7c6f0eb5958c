//! The basic class on a channel: publishing (routing, mandatory returns,
//! confirms), consumers (consume, cancel, qos), basic.get, and settling
//! deliveries (ack, nack, reject, recover).

use super::names::unique_name;
use super::{Channel, Publish};
use crate::access::permissions::Right;
use crate::error::{AmqpError, AmqpResult};
use crate::exchange::Exchange;
use crate::message::Message;
use crate::outbox::Outbound;
use crate::queue::{Consumer, ConsumerArgs, DeadLetters, Queue, QueuedMessage, Unacked};
use crate::slice::{finish_in_background, Progress, Slice};
use crate::vhost::publish::Publishing;
use leveret_protocol::{
    BasicCancel, BasicCancelOk, BasicConsume, BasicConsumeOk, BasicGet, BasicGetEmpty,
    BasicPublish, BasicQos, BasicQosOk, FieldTable, ReplyCode, ShortStr,
};
use std::collections::{HashMap, VecDeque};
use std::sync::atomic::Ordering;
use std::sync::Arc;

/// A publish routed but not yet offered to all its queues, or owed a
/// basic.return: what [`Channel::finish_publish`] has left to do.
#[derive(Debug)]
pub(crate) struct Unfinished {
    publishing: Publishing,
    /// Its confirm tag, in confirm mode.
    confirm: Option<u64>,
    returned: Option<Outbound>,
}

/// What a client did with a delivery.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Settle {
    /// basic.ack.
    Ack,
    /// basic.reject or basic.nack.
    Reject {
        /// Put it back in the queue.
        requeue: bool,
    },
}

/// basic.recover, answered with recover-ok, or the deprecated
/// basic.recover-async, not answered.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Recover {
    /// basic.recover.
    Answered,
    /// basic.recover-async.
    Unanswered,
}

impl Channel {
    pub(super) fn basic_publish(&mut self, publish: BasicPublish) -> AmqpResult<()> {
        if publish.immediate {
            return Err(AmqpError::not_implemented("immediate=true"));
        }
        self.published = true;
        self.registration.publishing();
        self.assembly = super::Assembly::Header(publish);
        Ok(())
    }

    /// A whole message has arrived: route it now, or hold it for tx.commit.
    /// Errors name basic.publish, the method they answer.
    ///
    /// All but the waiting is done here, at once; what has to wait (room
    /// for its basic.return, a yield between the slices of a large fanout)
    /// is returned, for [`Channel::finish_publish`] in a future of its own
    /// on the heap. A future is copied each time it is created and awaited,
    /// once per level of calls, for every frame: so the content frames'
    /// path is synchronous and the common publish copies no large future.
    pub(super) fn publish(&mut self, publish: Publish) -> AmqpResult<Option<Box<Unfinished>>> {
        self.publish_checked(publish)
            .map_err(|e| e.during_ids(60, 40))
    }

    /// Checks a publish, then holds it for tx.commit, or routes it and
    /// hands it to the vhost's publish step (which stores it and offers it
    /// to its queues); what is left when it has to wait is returned.
    fn publish_checked(&mut self, mut publish: Publish) -> AmqpResult<Option<Box<Unfinished>>> {
        self.allow_exchange(Right::Write, publish.method.exchange.as_bytes())?;
        let exchange = self.publish_exchange(&publish.method.exchange)?;
        if exchange.options.internal {
            return Err(AmqpError::access_refused(format_args!(
                "cannot publish to internal exchange '{}' in vhost '{}'",
                exchange.name, self.vhost.name
            )));
        }
        self.allow_topic(Right::Write, &exchange, &publish.method.routing_key)?;
        if let Some(expiration) = &publish.properties.expiration {
            if expiration
                .as_str()
                .and_then(|e| e.parse::<u64>().ok())
                .is_none()
            {
                return Err(AmqpError::precondition_failed(format_args!(
                    "invalid expiration '{expiration}': not a non-negative integer"
                )));
            }
        }
        if let Some(user_id) = &publish.properties.user_id {
            if user_id.as_bytes() != self.user.as_bytes() {
                return Err(AmqpError::precondition_failed(format_args!(
                    "user_id property set to '{}' but authenticated user was '{}'",
                    user_id, self.user
                )));
            }
        }
        self.core.stats.received(self.confirms.is_some());
        self.rewrite_reply_to(&mut publish)?;
        if let Some(tx) = &mut self.tx {
            tx.hold(publish, self.core.limits.memory_high_watermark / 4)?;
            self.note_pending();
            return Ok(None);
        }
        let confirm = self.confirms.as_mut().map(|c| c.next_tag());
        let mut queues = std::mem::take(&mut self.route_buffer);
        let (message, returned) = self.route(&exchange, publish, &mut queues);
        let mut rest = Unfinished {
            publishing: Publishing::new(message, queues),
            confirm,
            returned,
        };
        // A basic.return goes out before anything else of its publish.
        if rest.returned.is_some() || self.publish_slice(&mut rest) == Progress::More {
            return Ok(Some(Box::new(rest)));
        }
        self.settle_publish(rest);
        Ok(None)
    }

    /// The exchange a publish names: the last publish's while it is the
    /// same name and not deleted (an exchange declared again after a
    /// delete is another one, and the deleted one says so), else the
    /// vhost's.
    fn publish_exchange(&mut self, name: &ShortStr) -> AmqpResult<Arc<Exchange>> {
        if let Some(last) = &self.last_exchange {
            if last.name == *name && !last.is_deleted() {
                return Ok(Arc::clone(last));
            }
        }
        let exchange = self.vhost.exchange_or_404(name)?;
        self.last_exchange = Some(Arc::clone(&exchange));
        Ok(exchange)
    }

    /// The part of a publish that waits: its basic.return, then the rest
    /// of its queues a slice at a time (a fanout to thousands of queues
    /// yields between slices: the channel's next frame waits, other
    /// connections do not).
    pub(super) async fn finish_publish(&mut self, mut rest: Box<Unfinished>) {
        if let Some(returned) = rest.returned.take() {
            self.send_return(returned).await;
        }
        while self.publish_slice(&mut rest) == Progress::More {
            tokio::task::yield_now().await;
        }
        self.settle_publish(*rest);
    }

    /// One slice of the vhost's publish step; notes a crowded queue it
    /// reached for the connection's flow control.
    fn publish_slice(&mut self, rest: &mut Unfinished) -> Progress {
        let progress = self
            .vhost
            .publish_step(&mut rest.publishing, &mut Slice::start());
        if let (None, Some(queue)) = (&self.crowded, rest.publishing.take_crowded()) {
            self.crowded = Some(queue);
        }
        progress
    }

    /// A publish offered to all its queues: the vhost routes its dead
    /// letters, its outcome waits for its confirm.
    fn settle_publish(&mut self, rest: Unfinished) {
        let (published, queues) = self.vhost.published(rest.publishing);
        self.route_buffer = queues;
        if let Some(tag) = rest.confirm {
            self.confirm(tag, published);
        }
    }

    /// Routes a publish through `exchange` into `queues` and builds the
    /// message, marked for storage when it is persistent and reaches
    /// durable queues; with it, the basic.return an unroutable mandatory
    /// message is owed, for the caller to send ([`Channel::send_return`])
    /// before anything else of this publish.
    pub(super) fn route(
        &mut self,
        exchange: &Arc<Exchange>,
        publish: Publish,
        queues: &mut Vec<Arc<Queue>>,
    ) -> (Arc<Message>, Option<Outbound>) {
        self.vhost.route(
            exchange,
            &publish.method.routing_key,
            publish.properties.headers.as_ref(),
            queues,
            &mut self.last_routed_queue,
        );
        let persistent = publish.properties.is_persistent();
        let stored = self.vhost.storage(persistent, queues);
        let ttl_ms = publish
            .properties
            .expiration
            .as_ref()
            .and_then(|e| e.as_str())
            .and_then(|e| e.parse::<u64>().ok());
        let message = Arc::new(Message {
            exchange: publish.method.exchange,
            routing_key: publish.method.routing_key,
            properties: publish.property_bytes,
            body: publish.body,
            persistent,
            priority: publish.properties.priority.unwrap_or(0),
            ttl_ms,
            stored,
        });
        let replied = queues.is_empty()
            && super::reply_to::is_reply_address(&message.exchange, &message.routing_key)
            && self.deliver_reply(&message);
        let reached = !queues.is_empty() || replied;
        self.core.stats.routed(reached, publish.method.mandatory);
        let returned = (!reached && publish.method.mandatory).then(|| Outbound::Return {
            channel: self.id,
            reply_code: ReplyCode::NoRoute.code(),
            reply_text: ShortStr::from_static("NO_ROUTE"),
            message: Arc::clone(&message),
        });
        (message, returned)
    }

    /// Sends a basic.return, waiting for room in the outbox.
    pub(super) async fn send_return(&self, returned: Outbound) {
        self.outbox().send(returned).await;
    }

    pub(super) async fn basic_qos(&mut self, qos: BasicQos) -> AmqpResult<()> {
        if qos.prefetch_size != 0 {
            return Err(AmqpError::not_implemented(format_args!(
                "prefetch_size!=0 ({})",
                qos.prefetch_size
            )));
        }
        let count = u32::from(qos.prefetch_count);
        if qos.global {
            self.link.global_prefetch.store(count, Ordering::Relaxed);
        } else {
            self.prefetch_count = count;
            self.registration.set_prefetch(count);
        }
        self.reply(BasicQosOk {}).await;
        // More credit may let waiting messages go.
        self.dispatch_consumed_queues();
        Ok(())
    }

    pub(super) async fn basic_consume(&mut self, consume: BasicConsume) -> AmqpResult<()> {
        if consume.queue == super::reply_to::PSEUDO_QUEUE {
            return self.consume_direct_reply(consume).await;
        }
        let queue_name = self.queue_name_or_last(consume.queue)?;
        self.allow_queue(Right::Read, queue_name.as_bytes())?;
        let queue = self.vhost.queue_or_404(&queue_name)?;
        crate::vhost::check_exclusive(&queue, self.outbox().connection_id, &self.vhost.name)?;
        let tag = if consume.consumer_tag.is_empty() {
            unique_name("amq.ctag-")
        } else {
            consume.consumer_tag
        };
        // A consumer whose queue was deleted (the server cancelled it) no
        // longer holds its tag, as in RabbitMQ.
        if self
            .consumers
            .get(&tag)
            .is_some_and(|(_, queue)| queue.is_deleted())
        {
            self.consumers.remove(&tag);
        }
        if self.consumers.contains_key(&tag) {
            return Err(AmqpError::not_allowed(format_args!(
                "attempt to reuse consumer tag '{}'",
                tag
            )));
        }
        if queue.is_stream() {
            return self
                .consume_stream(
                    &consume.arguments,
                    consume.no_ack,
                    consume.exclusive,
                    consume.no_wait,
                    queue,
                    tag,
                )
                .await;
        }
        let args = ConsumerArgs::parse(&consume.arguments, &queue.name, &self.vhost.name)?;
        let consumer = Arc::new(Consumer {
            tag: tag.clone(),
            channel: Arc::clone(&self.link),
            no_ack: consume.no_ack,
            exclusive: consume.exclusive,
            prefetch: self.prefetch_count,
            priority: args.priority,
            wants_position: args.wants_position,
            in_flight: Default::default(),
            active: Default::default(),
        });
        self.vhost
            .dead_letter(queue.add_consumer(Arc::clone(&consumer))?);
        self.consumers
            .insert(tag.clone(), (Arc::clone(&consumer), Arc::clone(&queue)));
        if !consume.no_wait {
            self.reply(BasicConsumeOk { consumer_tag: tag }).await;
        }
        // consume-ok is in the outbox ahead of any delivery: only now may
        // the queue deliver to this consumer.
        consumer.activate();
        self.vhost.dead_letter(queue.dispatch());
        Ok(())
    }

    /// basic.consume on a stream, with RabbitMQ 3.10's rules: a prefetch
    /// (basic.qos, per consumer) and manual acks are required; the consumer
    /// starts at its `x-stream-offset`.
    async fn consume_stream(
        &mut self,
        arguments: &FieldTable,
        no_ack: bool,
        exclusive: bool,
        no_wait: bool,
        queue: Arc<Queue>,
        tag: ShortStr,
    ) -> AmqpResult<()> {
        let resource = format!("queue '{}' in vhost '{}'", queue.name, self.vhost.name);
        if self.prefetch_count == 0 {
            return Err(AmqpError::precondition_failed(format_args!(
                "consumer prefetch count is not set for '{resource}'"
            )));
        }
        if no_ack {
            queue.refuse_on_stream("automatic acknowledgement")?;
        }
        let start = crate::queue::start_at(arguments, &queue.name, &self.vhost.name, now_ms())?;
        let consumer = Arc::new(Consumer {
            tag: tag.clone(),
            channel: Arc::clone(&self.link),
            no_ack: false,
            exclusive,
            prefetch: self.prefetch_count,
            priority: 0,
            wants_position: false,
            in_flight: Default::default(),
            active: Default::default(),
        });
        queue.add_stream_consumer(Arc::clone(&consumer), start)?;
        self.consumers
            .insert(tag.clone(), (Arc::clone(&consumer), Arc::clone(&queue)));
        if !no_wait {
            self.reply(BasicConsumeOk { consumer_tag: tag }).await;
        }
        consumer.activate();
        self.vhost.dead_letter(queue.dispatch());
        Ok(())
    }

    pub(super) async fn basic_cancel(&mut self, cancel: BasicCancel) -> AmqpResult<()> {
        if !self.cancel_direct_reply(&cancel.consumer_tag) {
            if let Some((consumer, queue)) = self.consumers.remove(&cancel.consumer_tag) {
                if queue.remove_consumer(&consumer) {
                    self.vhost.delete_queue(&queue).notify();
                } else {
                    // A single active consumer's successor takes over (once
                    // what the cancelled one holds unacked, which stays with
                    // this channel as in RabbitMQ, is settled).
                    self.vhost.dead_letter(queue.dispatch());
                }
            }
        }
        if !cancel.no_wait {
            self.reply(BasicCancelOk {
                consumer_tag: cancel.consumer_tag,
            })
            .await;
        }
        Ok(())
    }

    pub(super) async fn basic_get(&mut self, get: BasicGet) -> AmqpResult<()> {
        let queue_name = self.queue_name_or_last(get.queue)?;
        self.allow_queue(Right::Read, queue_name.as_bytes())?;
        let queue = self.vhost.queue_or_404(&queue_name)?;
        crate::vhost::check_exclusive(&queue, self.outbox().connection_id, &self.vhost.name)?;
        queue.refuse_on_stream("basic.get")?;
        let Some(permit) = self.outbox().reserve().await else {
            // The writer is gone: the connection is closing.
            return Ok(());
        };
        let (delivered, dead) = queue.get(&self.link, get.no_ack, permit);
        self.vhost.dead_letter(dead);
        if !delivered {
            self.reply(BasicGetEmpty {
                cluster_id: ShortStr::default(),
            })
            .await;
        }
        Ok(())
    }

    /// basic.ack, basic.nack and basic.reject.
    pub(super) fn settle(&mut self, tag: u64, multiple: bool, how: Settle) -> AmqpResult<()> {
        let Some(settled) = self.link.deliveries().take(tag, multiple) else {
            return Err(AmqpError::precondition_failed(format_args!(
                "unknown delivery tag {tag}"
            )));
        };
        if let (Settle::Reject { .. }, Some(stream)) =
            (how, settled.iter().find(|u| u.origin.queue.is_stream()))
        {
            let refused = stream
                .origin
                .queue
                .refuse_on_stream("basic.nack and basic.reject");
            // RabbitMQ 3.10 closes the connection; what was taken stays
            // unacked until then, as the client left it.
            self.link.deliveries().restore(settled);
            return refused;
        }
        if let Some(tx) = &mut self.tx {
            tx.settles.extend(settled.into_iter().map(|u| (u, how)));
            self.note_pending();
            return Ok(());
        }
        self.vhost
            .dead_letter(apply_settles(settled.into_iter().map(move |u| (u, how))));
        self.after_settles();
        Ok(())
    }

    /// With a channel-wide prefetch (basic.qos global), settling frees
    /// credit for every consumer of the channel, not only for the queues
    /// whose messages were settled: let them all dispatch again.
    pub(super) fn after_settles(&self) {
        if self.link.global_prefetch.load(Ordering::Relaxed) > 0 {
            self.dispatch_consumed_queues();
        }
    }

    /// Lets every queue this channel consumes from dispatch again.
    fn dispatch_consumed_queues(&self) {
        for (_, queue) in self.consumers.values() {
            self.vhost.dead_letter(queue.dispatch());
        }
    }

    /// basic.recover(-async). As in RabbitMQ, recover-ok goes out before
    /// the redeliveries (clients such as lapin discard deliveries that
    /// arrive before it).
    pub(super) async fn basic_recover(&mut self, requeue: bool, how: Recover) -> AmqpResult<()> {
        if !requeue {
            return Err(AmqpError::not_implemented("requeue=false"));
        }
        let unacked = self.link.deliveries().take_all();
        if how == Recover::Answered {
            self.reply(leveret_protocol::BasicRecoverOk {}).await;
        }
        self.vhost.dead_letter(requeue_all(unacked));
        Ok(())
    }

    /// An empty queue name means the channel's last declared queue.
    pub(super) fn queue_name_or_last(&self, name: ShortStr) -> AmqpResult<ShortStr> {
        if !name.is_empty() {
            return Ok(name);
        }
        self.last_queue
            .clone()
            .ok_or_else(|| AmqpError::not_found("no previously declared queue"))
    }
}

/// Most deliveries settled in one step of [`apply_settles`].
const SETTLE_BATCH: usize = 1024;

/// Applies settled deliveries: acks release, rejects requeue or
/// dead-letter, and the queues involved dispatch again (credit was freed).
/// The first [`SETTLE_BATCH`] now, their dead letters returned for the
/// caller to route; the rest a batch per slice in the background (their
/// dead letters wait in their queue for the next sweep), so a multiple ack
/// or a close that settles a million deliveries does not hold the thread.
pub(crate) fn apply_settles<I>(settles: I) -> DeadLetters
where
    I: IntoIterator<Item = (Unacked, Settle)>,
    I::IntoIter: ExactSizeIterator + Send + 'static,
{
    let mut settles = settles.into_iter();
    let mut dead = DeadLetters::default();
    for (_, dead_here) in settle_batch(&mut settles) {
        dead.append(dead_here);
    }
    if settles.len() > 0 {
        finish_in_background(move |_| {
            for (queue, dead_here) in settle_batch(&mut settles) {
                queue.defer(dead_here);
            }
            match settles.len() {
                0 => Progress::Done,
                _ => Progress::More,
            }
        });
    }
    dead
}

/// Requeues deliveries settled by a close, a recover or an abandoned
/// transaction, in tag order per queue.
pub(crate) fn requeue_all(unacked: VecDeque<Unacked>) -> DeadLetters {
    apply_settles(
        unacked
            .into_iter()
            .map(|u| (u, Settle::Reject { requeue: true })),
    )
}

/// Settles the next [`SETTLE_BATCH`] deliveries, grouped by queue (a hash
/// map: a batch spread over many queues costs one lookup per delivery; a
/// queue's acks leave its store in one submission); returns each queue's
/// dead letters.
fn settle_batch(
    settles: &mut impl Iterator<Item = (Unacked, Settle)>,
) -> Vec<(Arc<Queue>, DeadLetters)> {
    #[derive(Default)]
    struct QueueSettles {
        acked: Vec<QueuedMessage>,
        requeue: Vec<QueuedMessage>,
        dead: DeadLetters,
    }
    let mut by_queue: HashMap<*const Queue, (Arc<Queue>, QueueSettles)> = HashMap::new();
    for (u, how) in settles.take(SETTLE_BATCH) {
        if let Some(consumer) = &u.consumer {
            consumer.settled_one();
        }
        let (queue, settled) = by_queue
            .entry(Arc::as_ptr(&u.origin.queue))
            .or_insert_with(|| (Arc::clone(&u.origin.queue), QueueSettles::default()));
        match how {
            Settle::Ack => settled.acked.push(u.origin.message),
            Settle::Reject { requeue: false } => {
                settled.dead.append(queue.reject(u.origin.message))
            }
            Settle::Reject { requeue: true } => settled.requeue.push(u.origin.message),
        }
    }
    by_queue
        .into_values()
        .map(|(queue, mut settled)| {
            queue.settle(&settled.acked);
            // A requeue dispatches too.
            match settled.requeue.is_empty() {
                true => settled.dead.append(queue.dispatch()),
                false => settled.dead.append(queue.requeue(settled.requeue)),
            }
            (queue, settled.dead)
        })
        .collect()
}

/// Now in milliseconds since the epoch (a stream consumer's interval
/// offset counts back from it).
fn now_ms() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as i64)
}
