//! A running shovel: consumes from its source and publishes to its
//! destination until stopped, reconnecting after any failure.
//!
//! Each link (a source and a destination connection) runs one loop:
//! deliveries are published in order with `mandatory` set and, under
//! `on-confirm`, acknowledged at the source only after the destination's
//! confirm. A destination `basic.nack` or a `basic.return` (no queue took
//! it) stops publishing: the messages in flight are settled (those the
//! destination took are acknowledged), the refused ones go back to the
//! source (`basic.nack` with requeue) and are counted, and the shovel is
//! `blocked` for `reconnect-delay` before it tries again: a destination
//! that refuses never drains the source. A retried message arrives after
//! later ones the destination took.
//!
//! A shovel reading a stream (`x-stream-offset` in `src-consumer-args`)
//! consumes it from that offset at the start of every link, as
//! RabbitMQ's shovel does: after a restart or a lost link it reads from
//! the configured offset again (from `first`: everything again). Its acks
//! only give the stream credit back, and a refusal nacks nothing (a stream
//! takes no `basic.nack`): the stream keeps the message, and the next
//! link offers it again if the configured offset reaches back to it. Every
//! forwarded message carries `x-leveret-seq`, which is how returns are
//! matched to publishes and how a consumer at the destination drops the
//! duplicates at-least-once forwarding makes after a crash: from a Leveret
//! source it is the shovel's name and the message's position in the source
//! queue (`x-leveret-position`, asked for at basic.consume), the same each
//! time that message is forwarded and never another's; from a stream read
//! with `x-stream-offset` (of any broker), the shovel's name, the stream's
//! name and the record's `x-stream-offset`, so the re-reads after a
//! restart carry the ids of the first reads; from another broker's queue,
//! the shovel's name, a number unique to this process and a count
//! (unique, but new at each forward).
//!
//! Every forwarded message also carries `x-leveret-shovelled`, the list
//! of the shovels it went through (each running shovel's own id: its
//! name, a number unique to this process and a count). A delivery that
//! already lists this shovel, or lists [`MAX_SHOVEL_HOPS`] shovels, came
//! round a loop (two shovels a → b and b → a, or a destination that routes
//! back into the source, which no check at declaration can see): it is
//! acknowledged at the source without being forwarded, counted in
//! `dropped_loops` and logged, as federation drops a message that came
//! back through its node. Without this, ten messages in a loop kept a core
//! busy for ever. The list is kept even when `dest-publish-properties`
//! replaces the headers. With `dest-add-forward-headers`, RabbitMQ's
//! `x-shovelled` entry of this shovel is put in front of the ones the
//! message already has, as RabbitMQ does.
//!
//! With `src-delete-after`, the shovel takes no more deliveries than it
//! has left to forward (counted across reconnects; under `no-ack` it
//! still acknowledges each one as it publishes it, so none beyond the count
//! leaves the source), and ends `completed` once that many were forwarded.
//!
//! After a failure the shovel waits `reconnect-delay`, doubling per failed
//! attempt up to 4 s (or `reconnect-delay` if longer), with up to 25% jitter,
//! and tries the destination URIs in turn starting after the last one that
//! failed. Uses the client crate for both ends (the local broker in
//! process), nothing else of the broker.

use crate::config::{AckMode, DeleteAfter, Destination, ShovelConfig, Source};
use crate::pace::Pace;
use leveret_broker::{process_nonce, BrokerHandle, POSITION_HEADER};
use leveret_client::{
    BasicAckOptions, BasicConsumeOptions, BasicNackOptions, BasicProperties, BasicPublishOptions,
    BasicQosOptions, Channel, ConfirmFuture, Confirmation, Connection, ConnectionOptions,
    FieldTable, FieldValue, QueueBindOptions, QueueDeclareOptions, ShortStr,
};
use std::collections::{HashSet, VecDeque};
use std::future::IntoFuture;
use std::sync::{Arc, Weak};
use std::time::Duration;
use tokio::sync::watch;

/// The header each forwarded message carries.
pub const SEQ_HEADER: &str = "x-leveret-seq";

/// The header listing the shovels a message went through.
pub const SHOVELLED_HEADER: &str = "x-leveret-shovelled";

/// Shovels a message may go through: one that lists this many is taken
/// for a loop too long to see this shovel in (and dropped).
pub const MAX_SHOVEL_HOPS: usize = 32;

/// How often a shovel that drops looping messages says so.
const LOOP_WARNING_EVERY: Duration = Duration::from_secs(10);

/// RabbitMQ's shovel states.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum ShovelState {
    /// Opening its connections.
    #[default]
    Connecting,
    /// Forwarding.
    Running,
    /// The destination refused a message: waiting before it tries again.
    Blocked,
    /// Stopped.
    Terminated,
}

/// What a shovel is doing and has done.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ShovelStatus {
    /// Its state.
    pub state: ShovelState,
    /// The destination URI it is connected to (without credentials).
    pub destination: Option<String>,
    /// The last failure, if any.
    pub last_error: Option<String>,
    /// Messages the destination took (confirmed, or published under
    /// `on-publish` and `no-ack`).
    pub forwarded: u64,
    /// Messages the destination refused (nacked or returned unroutable),
    /// left at the source.
    pub refused: u64,
    /// Links that ended (failures and refusals).
    pub restarts: u64,
    /// Messages dropped (acknowledged at the source, not forwarded)
    /// because they had already gone through this shovel, or through
    /// [`MAX_SHOVEL_HOPS`] shovels: they came round a loop.
    pub dropped_loops: u64,
    /// Whether it forwarded all `src-delete-after` asked for and stopped
    /// (its owner deletes it, as RabbitMQ deletes such a shovel).
    pub completed: bool,
}

/// A shovel running on the current tokio runtime.
#[derive(Debug)]
pub struct Shovel {
    name: String,
    status: watch::Receiver<ShovelStatus>,
    stop: watch::Sender<bool>,
    task: tokio::task::JoinHandle<()>,
}

impl Shovel {
    /// Starts the shovel `name`; `local` is the broker an `amqp://` URI
    /// without a host means.
    pub fn start(name: &str, config: ShovelConfig, local: Option<&Arc<BrokerHandle>>) -> Shovel {
        let (status_tx, status) = watch::channel(ShovelStatus::default());
        let config_delete_after = config.delete_after;
        let (stop, stopped) = watch::channel(false);
        static STARTED: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let started = STARTED.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let link = Link {
            name: name.to_owned(),
            id: format!("{name}@{:x}.{started}", process_nonce()),
            config,
            local: local.map(Arc::downgrade),
            status: status_tx,
            next_destination: 0,
            epoch: 0,
            remaining: match config_delete_after {
                DeleteAfter::Count(n) => Some(n),
                DeleteAfter::Never | DeleteAfter::QueueLength => None,
            },
        };
        let task = tokio::spawn(link.run(stopped));
        Shovel {
            name: name.to_owned(),
            status,
            stop,
            task,
        }
    }

    /// Its name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// What it is doing now.
    pub fn status(&self) -> ShovelStatus {
        self.status.borrow().clone()
    }

    /// Its status as it changes.
    pub fn watch(&self) -> watch::Receiver<ShovelStatus> {
        self.status.clone()
    }

    /// Stops it: unacknowledged messages go back to the source.
    pub async fn stop(self) {
        let _ = self.stop.send(true);
        let _ = self.task.await;
    }
}

/// A URI with its credentials removed, for logs and status.
pub(crate) fn shown(uri: &str) -> String {
    match (uri.split_once("://"), uri.rfind('@')) {
        (Some((scheme, rest)), Some(at)) => {
            let after = &uri[at + 1..];
            if rest.contains('@') {
                format!("{scheme}://{after}")
            } else {
                uri.to_owned()
            }
        }
        _ => uri.to_owned(),
    }
}

/// Whether `uri` names the local broker (`amqp://` with no host).
pub(crate) fn is_local(uri: &str) -> bool {
    let Some(rest) = uri.strip_prefix("amqp://") else {
        return false;
    };
    let authority = rest.split(['/', '?']).next().unwrap_or("");
    let host = authority.rsplit_once('@').map_or(authority, |(_, h)| h);
    host.is_empty()
}

/// Why a link ended.
enum Ended {
    /// A connection or channel failed.
    Failed(String),
    /// The destination refused a message (left at the source).
    Refused(String),
    /// The shovel was told to stop.
    Stopped,
    /// It forwarded everything `src-delete-after` asked for.
    Completed,
}

impl From<leveret_client::Error> for Ended {
    fn from(e: leveret_client::Error) -> Self {
        Ended::Failed(e.to_string())
    }
}

/// A published message waiting for its confirm.
struct InFlight {
    source_tag: u64,
    seq: String,
    confirm: ConfirmFuture,
}

struct Link {
    name: String,
    /// This running shovel's entry in [`SHOVELLED_HEADER`]: no other
    /// shovel, here or on another broker, has it.
    id: String,
    config: ShovelConfig,
    local: Option<Weak<BrokerHandle>>,
    status: watch::Sender<ShovelStatus>,
    next_destination: usize,
    epoch: u64,
    /// Messages left to forward under `src-delete-after` (`None`: no
    /// limit, or `queue-length` not yet measured).
    remaining: Option<u64>,
}

impl Link {
    fn update(&self, change: impl FnOnce(&mut ShovelStatus)) {
        self.status.send_modify(change);
    }

    async fn run(mut self, mut stop: watch::Receiver<bool>) {
        let mut failures: u32 = 0;
        loop {
            self.update(|s| s.state = ShovelState::Connecting);
            let forwarded_before = self.status.borrow().forwarded;
            let ended = tokio::select! {
                ended = self.link() => ended,
                _ = stop.wait_for(|stopped| *stopped) => Ended::Stopped,
            };
            let (delay, reason) = match ended {
                Ended::Stopped => break,
                Ended::Completed => {
                    tracing::info!(shovel = %self.name, "shovel forwarded all src-delete-after asked for");
                    self.update(|s| {
                        s.completed = true;
                        s.state = ShovelState::Terminated;
                    });
                    break;
                }
                Ended::Refused(reason) => {
                    self.update(|s| s.state = ShovelState::Blocked);
                    (self.config.reconnect_delay, reason)
                }
                Ended::Failed(reason) => {
                    if self.status.borrow().forwarded > forwarded_before {
                        failures = 0;
                    }
                    failures = failures.saturating_add(1);
                    (backoff(self.config.reconnect_delay, failures), reason)
                }
            };
            tracing::warn!(shovel = %self.name, error = %reason, retry_in = ?delay, "shovel link ended");
            self.update(|s| {
                s.last_error = Some(reason);
                s.restarts += 1;
                s.destination = None;
            });
            tokio::select! {
                _ = tokio::time::sleep(delay) => {}
                _ = stop.wait_for(|stopped| *stopped) => break,
            }
        }
        self.update(|s| s.state = ShovelState::Terminated);
    }

    async fn connect(&self, uri: &str) -> Result<Connection, Ended> {
        if is_local(uri) {
            let options = ConnectionOptions::from_uri(uri)?;
            let broker = self
                .local
                .as_ref()
                .and_then(Weak::upgrade)
                .ok_or_else(|| Ended::Failed("no local broker".into()))?;
            return Ok(Connection::in_process_with(&broker, options).await?);
        }
        Ok(Connection::connect(uri).await?)
    }

    /// The first destination that answers, starting after the last one
    /// that failed.
    async fn connect_destination(&mut self) -> Result<(Connection, String), Ended> {
        let uris = self.config.dest_uris.clone();
        let mut last = String::new();
        for attempt in 0..uris.len() {
            let index = (self.next_destination + attempt) % uris.len();
            match self.connect(&uris[index]).await {
                Ok(connection) => {
                    self.next_destination = index;
                    return Ok((connection, shown(&uris[index])));
                }
                Err(Ended::Failed(e)) => last = format!("{}: {e}", shown(&uris[index])),
                Err(other) => return Err(other),
            }
        }
        self.next_destination = (self.next_destination + 1) % uris.len();
        Err(Ended::Failed(last))
    }

    /// The source queue, declared and bound for an exchange source.
    async fn source_queue(&self, channel: &Channel) -> Result<String, Ended> {
        match &self.config.source {
            Source::Queue(queue) => Ok(queue.clone()),
            Source::Exchange { exchange, key } => {
                let queue = format!("shovel.{}", self.name);
                let durable = QueueDeclareOptions {
                    durable: true,
                    ..Default::default()
                };
                channel
                    .queue_declare(queue.as_str(), durable, FieldTable::new())
                    .await?;
                channel
                    .queue_bind(
                        queue.as_str(),
                        exchange.as_str(),
                        key.as_str(),
                        QueueBindOptions::default(),
                        FieldTable::new(),
                    )
                    .await?;
                Ok(queue)
            }
        }
    }

    /// Runs one link until it ends.
    async fn link(&mut self) -> Ended {
        match self.forward().await {
            Ok(never) => match never {},
            Err(ended) => ended,
        }
    }

    async fn forward(&mut self) -> Result<std::convert::Infallible, Ended> {
        let src_uri = self.config.src_uri.clone();
        let source_connection = self.connect(&src_uri).await?;
        let (destination_connection, destination) = self.connect_destination().await?;
        let source = source_connection.open_channel().await?;
        source
            .basic_qos(self.config.prefetch, BasicQosOptions::default())
            .await?;
        let queue = self.source_queue(&source).await?;
        if self.config.delete_after == DeleteAfter::QueueLength && self.remaining.is_none() {
            let passive = QueueDeclareOptions {
                passive: true,
                ..Default::default()
            };
            let info = source
                .queue_declare(queue.as_str(), passive, FieldTable::new())
                .await?;
            self.remaining = Some(u64::from(info.message_count));
        }
        if self.remaining == Some(0) {
            return Err(Ended::Completed);
        }
        let publisher = destination_connection.open_channel().await?;
        let confirms = self.config.ack_mode == AckMode::OnConfirm;
        if confirms {
            publisher.confirm_select().await?;
        }
        let mut returns = publisher.returns();
        // A limited shovel acknowledges even under no-ack, so that the
        // broker delivers no more than the prefetch window it can refuse.
        let no_ack = self.config.ack_mode == AckMode::NoAck && self.remaining.is_none();
        // `src-consumer-args`, and: a Leveret queue adds each message's
        // position (a stream has its offsets; other brokers ignore the
        // argument).
        let mut arguments = self.config.consumer_args.clone();
        arguments.insert(
            ShortStr::from_static(POSITION_HEADER),
            FieldValue::Bool(true),
        );
        let mut consumer = source
            .basic_consume(
                queue.as_str(),
                "",
                BasicConsumeOptions {
                    no_ack,
                    ..Default::default()
                },
                arguments,
            )
            .await?;
        self.epoch += 1;
        tracing::info!(shovel = %self.name, source = %queue, %destination, "shovel running");
        self.update(|s| {
            s.state = ShovelState::Running;
            s.destination = Some(destination);
        });
        let mut bandwidth = self.config.bandwidth_limit.map(Pace::new);
        let mut message_rate = self.config.message_rate_limit.map(Pace::new);
        let mut inflight: VecDeque<InFlight> = VecDeque::new();
        let mut returned: HashSet<String> = HashSet::new();
        let mut counter: u64 = 0;
        let mut loop_warning = LoopWarning::default();
        let window = usize::from(self.config.prefetch);
        loop {
            tokio::select! {
                biased;
                confirmation = async { (&mut inflight.front_mut().expect("guarded").confirm).await },
                    if !inflight.is_empty() =>
                {
                    // The confirms already in, taken together: the ones the
                    // destination took are acknowledged at the source with
                    // one `multiple` ack (everything before them is settled).
                    let first = inflight.pop_front().expect("guarded");
                    let mut settled = vec![(first.source_tag, first.seq, confirmation?)];
                    while let Some(confirmation) =
                        inflight.front_mut().and_then(|f| confirmed_now(&mut f.confirm))
                    {
                        let next = inflight.pop_front().expect("just seen");
                        settled.push((next.source_tag, next.seq, confirmation?));
                    }
                    let mut settled = settled.into_iter();
                    let (mut taken, mut last) = (0, None);
                    let mut refusal = None;
                    for (tag, seq, confirmation) in settled.by_ref() {
                        match settle(&mut returns, &mut returned, &seq, confirmation) {
                            None => (taken, last) = (taken + 1, Some(tag)),
                            Some(why) => {
                                refusal = Some((why, tag));
                                break;
                            }
                        }
                    }
                    if let Some(tag) = last {
                        source.basic_ack(tag, BasicAckOptions { multiple: taken > 1 }).await?;
                    }
                    let Some((why, tag)) = refusal else {
                        self.forwarded(taken)?;
                        continue;
                    };
                    self.forwarded(taken)?;
                    // Publish nothing more; settle what is in flight (the
                    // destination may take later ones), and put back what
                    // it refused.
                    let mut refused = vec![tag];
                    let mut rest: Vec<(u64, String, Confirmation)> = settled.collect();
                    for later in inflight.drain(..) {
                        rest.push((later.source_tag, later.seq, later.confirm.await?));
                    }
                    for (tag, seq, confirmation) in rest {
                        match settle(&mut returns, &mut returned, &seq, confirmation) {
                            None => {
                                source.basic_ack(tag, BasicAckOptions::default()).await?;
                                self.forwarded(1)?;
                            }
                            Some(_) => refused.push(tag),
                        }
                    }
                    // A stream keeps every message whatever its consumers
                    // do, and takes no basic.nack (RabbitMQ 3.10 closes
                    // the connection): the next link reads from the
                    // configured offset again.
                    let count = refused.len() as u64;
                    self.update(|s| s.refused += count);
                    if self.config.reads_stream() {
                        return Err(Ended::Refused(format!(
                            "the destination {why} {count} message(s), kept in the stream"
                        )));
                    }
                    let requeue = BasicNackOptions { multiple: false, requeue: true };
                    for tag in &refused {
                        source.basic_nack(*tag, requeue).await?;
                    }
                    return Err(Ended::Refused(format!(
                        "the destination {why} {count} message(s), left at the source"
                    )));
                }
                delivery = consumer.next(),
                    if inflight.len() < window
                        && self.remaining.is_none_or(|left| (inflight.len() as u64) < left) =>
                {
                    let Some(delivery) = delivery else {
                        return Err(Ended::Failed(format!("the source stopped delivering from {queue}")));
                    };
                    let trail = shovelled(&delivery.properties);
                    if trail.len() >= MAX_SHOVEL_HOPS || trail.contains(&self.id) {
                        if !no_ack {
                            source.basic_ack(delivery.delivery_tag, BasicAckOptions::default()).await?;
                        }
                        self.dropped_loop(&mut loop_warning, trail.len());
                        continue;
                    }
                    if let Some(pace) = &mut message_rate {
                        pace.take(1).await;
                    }
                    if let Some(pace) = &mut bandwidth {
                        pace.take(delivery.body.len() as u64).await;
                    }
                    counter += 1;
                    let stable = if self.config.reads_stream() {
                        stream_offset_of(&delivery.properties).map(|offset| format!("{queue}@{offset}"))
                    } else {
                        position_of(&delivery.properties)
                    };
                    let seq = match stable {
                        Some(position) => format!("{}:{position}", self.name),
                        None => format!("{}:{}:{}:{counter}", self.name, process_nonce(), self.epoch),
                    };
                    let (exchange, key) = match &self.config.destination {
                        Destination::Queue(queue) => (String::new(), queue.clone()),
                        Destination::Exchange { exchange, key } => (
                            exchange.clone(),
                            key.clone().unwrap_or_else(|| delivery.routing_key.to_string()),
                        ),
                    };
                    let properties = self.forwarded_properties(delivery.properties, trail, &seq);
                    let confirm = publisher
                        .basic_publish(
                            exchange.as_str(),
                            key.as_str(),
                            BasicPublishOptions { mandatory: true },
                            properties,
                            delivery.body,
                        )
                        .await?;
                    match self.config.ack_mode {
                        AckMode::OnConfirm => inflight.push_back(InFlight {
                            source_tag: delivery.delivery_tag,
                            seq,
                            confirm: confirm.into_future(),
                        }),
                        AckMode::OnPublish => {
                            source.basic_ack(delivery.delivery_tag, BasicAckOptions::default()).await?;
                            self.forwarded(1)?;
                        }
                        AckMode::NoAck => {
                            if !no_ack {
                                source.basic_ack(delivery.delivery_tag, BasicAckOptions::default()).await?;
                            }
                            self.forwarded(1)?;
                        }
                    }
                }
                error = publisher.closed() => return Err(Ended::Failed(format!("destination: {error}"))),
                error = source.closed() => return Err(Ended::Failed(format!("source: {error}"))),
            }
        }
    }

    /// Counts `count` messages the destination took; ends the link once
    /// `src-delete-after` is reached. Called with the messages settled at
    /// the source, and with nothing later in flight beyond the count.
    fn forwarded(&mut self, count: u64) -> Result<(), Ended> {
        if count == 0 {
            return Ok(());
        }
        self.update(|s| s.forwarded += count);
        match &mut self.remaining {
            Some(left) => {
                *left = left.saturating_sub(count);
                if *left == 0 {
                    Err(Ended::Completed)
                } else {
                    Ok(())
                }
            }
            None => Ok(()),
        }
    }

    /// Counts a message dropped for coming round a loop, and says so at
    /// most every [`LOOP_WARNING_EVERY`].
    fn dropped_loop(&mut self, warning: &mut LoopWarning, hops: usize) {
        self.update(|s| s.dropped_loops += 1);
        warning.unreported += 1;
        if warning
            .last
            .is_some_and(|last| last.elapsed() < LOOP_WARNING_EVERY)
        {
            return;
        }
        tracing::warn!(
            shovel = %self.name,
            dropped = warning.unreported,
            total = self.status.borrow().dropped_loops,
            hops,
            "shovel dropped messages that had already gone through it (or through {MAX_SHOVEL_HOPS} shovels): its source and destination form a loop"
        );
        *warning = LoopWarning {
            last: Some(tokio::time::Instant::now()),
            unreported: 0,
        };
    }

    /// The message's properties with `dest-publish-properties` set over
    /// them and the shovel's headers added: `trail` (the shovels it went
    /// through before, read before the headers may be replaced) with this
    /// one appended.
    fn forwarded_properties(
        &self,
        properties: BasicProperties,
        trail: Vec<String>,
        seq: &str,
    ) -> BasicProperties {
        let earlier_forwards = match properties
            .headers
            .as_ref()
            .and_then(|h| h.get("x-shovelled"))
        {
            Some(FieldValue::Array(entries)) => entries.clone(),
            _ => Vec::new(),
        };
        let mut properties = overlay(properties, &self.config.publish_properties);
        let mut headers = properties.headers.take().unwrap_or_default();
        headers.remove(POSITION_HEADER);
        headers.insert(ShortStr::from_static(SEQ_HEADER), FieldValue::string(seq));
        let trail = trail
            .into_iter()
            .chain([self.id.clone()])
            .map(|id| FieldValue::string(&id))
            .collect();
        headers.insert(
            ShortStr::from_static(SHOVELLED_HEADER),
            FieldValue::Array(trail),
        );
        if self.config.add_forward_headers {
            let mut shovelled = FieldTable::new();
            for (key, value) in [
                ("shovel-type", "dynamic"),
                ("shovel-name", self.name.as_str()),
                ("shovel-vhost", "/"),
            ] {
                shovelled.insert(ShortStr::from_static(key), FieldValue::string(value));
            }
            shovelled.insert(
                ShortStr::from_static("src-uri"),
                FieldValue::string(&shown(&self.config.src_uri)),
            );
            let destination = &self.config.dest_uris[self.next_destination];
            shovelled.insert(
                ShortStr::from_static("dest-uri"),
                FieldValue::string(&shown(destination)),
            );
            let entries = std::iter::once(FieldValue::Table(shovelled))
                .chain(earlier_forwards)
                .collect();
            headers.insert(
                ShortStr::from_static("x-shovelled"),
                FieldValue::Array(entries),
            );
        }
        properties.headers = Some(headers);
        properties
    }
}

/// `message` with every property `set` has replaced.
fn overlay(mut message: BasicProperties, set: &BasicProperties) -> BasicProperties {
    fn take<T: Clone>(field: &mut Option<T>, set: &Option<T>) {
        if set.is_some() {
            field.clone_from(set);
        }
    }
    take(&mut message.content_type, &set.content_type);
    take(&mut message.content_encoding, &set.content_encoding);
    take(&mut message.headers, &set.headers);
    take(&mut message.delivery_mode, &set.delivery_mode);
    take(&mut message.priority, &set.priority);
    take(&mut message.correlation_id, &set.correlation_id);
    take(&mut message.reply_to, &set.reply_to);
    take(&mut message.expiration, &set.expiration);
    take(&mut message.message_id, &set.message_id);
    take(&mut message.timestamp, &set.timestamp);
    take(&mut message.kind, &set.kind);
    take(&mut message.user_id, &set.user_id);
    take(&mut message.app_id, &set.app_id);
    take(&mut message.cluster_id, &set.cluster_id);
    message
}

/// Whether the destination took a message: `None` if it did, else why
/// not. The broker sends a message's `basic.return` before its confirm,
/// so every return for it has arrived by the time the confirm has.
fn settle(
    returns: &mut leveret_client::Returns,
    returned: &mut HashSet<String>,
    seq: &str,
    confirmation: Confirmation,
) -> Option<&'static str> {
    while let Some(message) = returns.try_next() {
        if let Some(seq) = seq_of(&message.properties) {
            returned.insert(seq);
        }
    }
    match confirmation {
        _ if returned.remove(seq) => Some("returned unroutable"),
        Confirmation::Nack => Some("nacked"),
        Confirmation::Ack | Confirmation::NotRequested => None,
    }
}

/// A confirm that has already arrived, without waiting for one that has
/// not.
fn confirmed_now(confirm: &mut ConfirmFuture) -> Option<leveret_client::Result<Confirmation>> {
    let mut context = std::task::Context::from_waker(std::task::Waker::noop());
    match std::future::Future::poll(std::pin::Pin::new(confirm), &mut context) {
        std::task::Poll::Ready(confirmation) => Some(confirmation),
        std::task::Poll::Pending => None,
    }
}

/// The source's `x-leveret-position` of a delivery, if it has one.
fn position_of(properties: &BasicProperties) -> Option<String> {
    let value = properties.headers.as_ref()?.get(POSITION_HEADER)?;
    std::str::from_utf8(value.as_bytes()?)
        .ok()
        .map(str::to_owned)
}

/// The `x-stream-offset` of a delivery from a stream.
fn stream_offset_of(properties: &BasicProperties) -> Option<i64> {
    properties
        .headers
        .as_ref()?
        .get("x-stream-offset")?
        .as_i64()
}

/// The shovels a message went through, from its [`SHOVELLED_HEADER`].
fn shovelled(properties: &BasicProperties) -> Vec<String> {
    let Some(FieldValue::Array(list)) = properties
        .headers
        .as_ref()
        .and_then(|h| h.get(SHOVELLED_HEADER))
    else {
        return Vec::new();
    };
    list.iter()
        .filter_map(|id| std::str::from_utf8(id.as_bytes()?).ok())
        .map(str::to_owned)
        .collect()
}

/// When a link last warned of looping messages, and how many it dropped
/// since.
#[derive(Default)]
struct LoopWarning {
    last: Option<tokio::time::Instant>,
    unreported: u64,
}

/// The `x-leveret-seq` of a message, if it has one.
fn seq_of(properties: &BasicProperties) -> Option<String> {
    let value = properties.headers.as_ref()?.get(SEQ_HEADER)?;
    std::str::from_utf8(value.as_bytes()?)
        .ok()
        .map(str::to_owned)
}

/// The longest wait between attempts when `reconnect-delay` is shorter:
/// a link that comes back is used within about this long.
const BACKOFF_CEILING: Duration = Duration::from_secs(4);

/// `base` doubled per failure up to [`BACKOFF_CEILING`] (or `base` when
/// longer), plus up to 25% jitter: a drain starts within 5 s of the link
/// coming back unless `reconnect-delay` asks for longer.
pub(crate) fn backoff(base: Duration, failures: u32) -> Duration {
    let doubled = base.saturating_mul(1 << failures.saturating_sub(1).min(16));
    let capped = doubled.min(base.max(BACKOFF_CEILING));
    let jitter = {
        use std::hash::{BuildHasher, Hasher};
        let mut hasher = std::collections::hash_map::RandomState::new().build_hasher();
        hasher.write_u32(failures);
        (hasher.finish() % 1000) as u32
    };
    capped + capped / 4 * jitter / 1000
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn local_uris_and_credentials() {
        assert!(is_local("amqp://"));
        assert!(is_local("amqp:///%2f"));
        assert!(is_local("amqp://robot:pw@/%2f"));
        assert!(!is_local("amqp://fleet"));
        assert!(!is_local("amqps://"));
        assert_eq!(shown("amqp://u:secret@fleet:5672/v"), "amqp://fleet:5672/v");
        assert_eq!(shown("amqp://fleet"), "amqp://fleet");
    }

    #[test]
    fn backoff_doubles_jitters_and_is_capped() {
        let base = Duration::from_millis(100);
        for failures in 1..40 {
            let delay = backoff(base, failures);
            let plain = base * (1u32 << (failures - 1).min(16));
            let plain = plain.min(BACKOFF_CEILING);
            assert!(
                delay >= plain && delay <= plain + plain / 4,
                "{failures}: {delay:?}"
            );
        }
        assert!(backoff(Duration::from_secs(1), 30) <= Duration::from_secs(5));
        let long = Duration::from_secs(10);
        assert!(backoff(long, 10) >= long && backoff(long, 10) <= long + long / 4);
    }
}
