//! Stream queues (`x-queue-type: stream`), as RabbitMQ 3.10 serves them
//! over AMQP 0.9.1: an append-only log that consumers read from an offset
//! of their choosing, each at its own pace, without removing anything.
//! This module owns a stream's state (its log and its readers) and the
//! queue operations that differ for a stream: appending a publish,
//! starting a consumer at its `x-stream-offset`, delivering records with
//! their `x-stream-offset` header, acks that only give credit back, and
//! retention. `log` owns the files; `args` validates declarations and
//! consumer arguments.
//!
//! A publish is appended under the stream's lock (a write to the page
//! cache) and made durable by the persister's next group commit
//! ([`Persistence::submit_sync`]), whose number the publish's confirm
//! waits for, as a durable queue's does. Readers hold no records beyond a
//! small batch: a reader behind the tail gets its next batch from a
//! blocking task (`spawn_blocking`) that reads without any lock, so old
//! segments are never read on a broker thread, and the next read starts
//! while half a read's worth is still to deliver (in the same blocking
//! task after a whole read, while the reader is well behind the tail, for
//! up to [`READS_A_RUN`] reads a task);
//! a reader at the tail is handed each publish as it is appended.
//! Deliveries leave in bursts, each sent to the connection's writer at
//! once. A record's properties are stored with its offset header already
//! in them, so a delivery slices the message out of the record without
//! decoding or copying it.

mod args;
mod log;

pub use args::{is_stream, start_at, StartAt, StreamArgs};

use super::{Consumer, Deleted, Enqueued, Origin, Queue, QueuedMessage, Unacked};
use crate::error::AmqpResult;
use crate::message::Message;
use crate::outbox::Outbound;
use crate::policy::{stricter, Applied};
use crate::store::Persistence;
use bytes::{Bytes, BytesMut};
use leveret_protocol::{BasicProperties, FieldTable, FieldValue, ShortStr};
use log::{Cursor, Record, StreamLog};
use std::collections::VecDeque;
use std::sync::{Arc, Mutex, MutexGuard};

/// The header each delivery from a stream carries: its offset (a long).
pub const OFFSET_HEADER: &str = "x-stream-offset";

/// Most records one read brings into a reader's batch.
const READ_RECORDS: usize = 256;
/// About the most bytes one read brings (at least one record).
const READ_BYTES: usize = 128 * 1024;
/// Most reads one blocking task makes for its reader before it hands the
/// next read on as a new task: at most this many × [`READ_BYTES`] (1 MiB)
/// a run, so a reader catching up on a long stream gives its blocking
/// thread back to the pool between runs rather than holding it for the
/// whole catch-up (other `spawn_blocking` work queues behind it).
const READS_A_RUN: usize = 8;

/// One stream's state (see the module docs).
#[derive(Debug)]
pub struct Stream {
    /// As declared (with the segment size the policies gave it then).
    declared: StreamArgs,
    persistence: Arc<Persistence>,
    state: Mutex<StreamState>,
}

#[derive(Debug)]
struct StreamState {
    log: StreamLog,
    /// In force: the declared retention with the policies' (the smaller
    /// of each, as RabbitMQ 3.10's `args_policy_lookup` takes it).
    args: StreamArgs,
    readers: Vec<Reader>,
    /// The submission number of the last append's sync: an append after it
    /// is durable starts a new chunk.
    last_sync: u64,
    /// Taken by an if-unused delete, which deletes it next: no consumer
    /// may come first ([`Stream::take_unused`]).
    going: bool,
    deleted: bool,
}

/// One consumer's place in the stream.
#[derive(Debug)]
struct Reader {
    consumer: Arc<Consumer>,
    /// The next record it is owed (after what is batched).
    cursor: Cursor,
    /// Records read for it, not yet delivered: under half a read's worth
    /// when its next read starts ([`wants_more`]), so at most about one
    /// and a half reads' worth.
    batch: VecDeque<Record>,
    /// A read task is out for it.
    reading: bool,
    /// Its last read found nothing where records were due (damage since
    /// start-up): no further read until the stream grows.
    stalled: bool,
}

/// Whether a reader whose batch is `batch` reads on (if it is owed
/// records and has credit): when the batch is under half a read's worth,
/// so the next read (from the disk, off the broker's threads) is under way
/// while the rest is delivered.
fn wants_more(batch: &VecDeque<Record>) -> bool {
    batch.len() < READ_RECORDS / 2
        && batch.iter().map(|r| r.payload.len()).sum::<usize>() < READ_BYTES / 2
}

/// A read to start once the stream's lock is let go.
struct ReadTask {
    consumer: Arc<Consumer>,
    cursor: Cursor,
    plan: log::ReadPlan,
    records: usize,
}

/// Deletes segment files retention let go on a blocking thread (inline
/// where there is no runtime, as in unit tests).
fn remove_in_background(paths: Vec<std::path::PathBuf>) {
    if paths.is_empty() {
        return;
    }
    match tokio::runtime::Handle::try_current() {
        Ok(runtime) => {
            runtime.spawn_blocking(move || log::remove_files(paths));
        }
        Err(_) => log::remove_files(paths),
    }
}

fn now_ms() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as i64)
}

/// Record flag (the stream's own, beside the log's `CHUNK_START`): the
/// stored properties already carry the record's [`OFFSET_HEADER`], so a
/// delivery sends them as they are.
const STAMPED: u8 = 1 << 1;
/// Record flag: the message is persistent (delivery-mode 2); set with
/// [`STAMPED`], whose records are delivered without decoding their
/// properties.
const PERSISTENT: u8 = 1 << 2;

/// A message as the record at `offset`: its payload (exchange and routing
/// key, a length byte each, properties (`u32` LE length), then the body)
/// and its flags. The properties are stored with the offset header
/// (replacing any the publisher set) and the record marked [`STAMPED`],
/// so no delivery decodes them again; properties that do not decode are
/// stored as they came, unmarked (their delivery then fails to decode them
/// and skips the record, with an error log).
fn encode(message: &Message, offset: u64) -> (Vec<u8>, u8) {
    let (properties, flags) = match BasicProperties::decode(&message.properties) {
        Ok(properties) => {
            let persistent = properties.delivery_mode == Some(2);
            let mut stamped = BytesMut::with_capacity(message.properties.len() + 32);
            with_offset(properties, offset).encode(&mut stamped);
            let flags = if persistent {
                STAMPED | PERSISTENT
            } else {
                STAMPED
            };
            (stamped.freeze(), flags)
        }
        Err(_) => (message.properties.clone(), 0),
    };
    let mut out = Vec::with_capacity(
        2 + message.exchange.len()
            + message.routing_key.len()
            + 4
            + properties.len()
            + message.body.len(),
    );
    for short in [&message.exchange, &message.routing_key] {
        out.push(short.len() as u8);
        out.extend_from_slice(short.as_bytes());
    }
    out.extend_from_slice(&(properties.len() as u32).to_le_bytes());
    out.extend_from_slice(&properties);
    out.extend_from_slice(&message.body);
    (out, flags)
}

/// `properties` with [`OFFSET_HEADER`] set to `offset`.
fn with_offset(mut properties: BasicProperties, offset: u64) -> BasicProperties {
    properties
        .headers
        .get_or_insert_with(FieldTable::new)
        .insert(
            ShortStr::from_static(OFFSET_HEADER),
            FieldValue::I64(offset as i64),
        );
    properties
}

/// The message a record holds, with its offset in [`OFFSET_HEADER`]:
/// sliced out of the payload without a copy, the properties as stored
/// when [`STAMPED`], else decoded and stamped (records an older Leveret
/// wrote). `None` if the payload does not decode (it passed its checksum,
/// so only a bug could make it so; it is skipped with an error log).
fn decode(record: &Record) -> Option<Message> {
    let payload = &record.payload;
    let mut at = 0;
    let mut short = || -> Option<ShortStr> {
        let len = usize::from(*payload.get(at)?);
        if payload.len() < at + 1 + len {
            return None;
        }
        let bytes = payload.slice(at + 1..at + 1 + len);
        at += 1 + len;
        ShortStr::try_from(bytes).ok()
    };
    let exchange = short()?;
    let routing_key = short()?;
    let len = u32::from_le_bytes(payload.get(at..at + 4)?.try_into().ok()?) as usize;
    at += 4;
    if payload.len() < at + len {
        return None;
    }
    let stored_properties = payload.slice(at..at + len);
    let body = payload.slice(at + len..);
    let (properties, persistent) = if record.flags & STAMPED != 0 {
        (stored_properties, record.flags & PERSISTENT != 0)
    } else {
        let properties = BasicProperties::decode(&stored_properties).ok()?;
        let persistent = properties.delivery_mode == Some(2);
        let mut encoded = BytesMut::with_capacity(len + 32);
        with_offset(properties, record.offset).encode(&mut encoded);
        (encoded.freeze(), persistent)
    };
    Some(Message {
        exchange,
        routing_key,
        persistent,
        priority: 0,
        properties,
        body,
        ttl_ms: None,
        stored: None,
    })
}

/// A stream's offsets and files, as listings and metrics show them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StreamFigures {
    /// The oldest offset held (the next one's when empty).
    pub first_offset: u64,
    /// The newest offset held; `None` when empty.
    pub last_offset: Option<u64>,
    /// Segment files.
    pub segments: u64,
    /// Bytes of its segment files.
    pub bytes: u64,
}

impl Stream {
    /// Stream `id`'s log under the store's data directory: a new, empty
    /// one when `new`, else the one stored (checked as it is opened).
    /// `None` if the broker keeps nothing on disk.
    pub fn open(
        args: StreamArgs,
        persistence: Arc<Persistence>,
        id: u64,
        new: bool,
    ) -> Option<std::io::Result<Stream>> {
        let dir = persistence.stream_dir(id)?;
        let log = if new {
            StreamLog::create(&dir, args.segment_bytes)
        } else {
            StreamLog::open(&dir, args.segment_bytes, persistence.recover_streams())
        };
        Some(log.map(|log| Stream {
            declared: args.clone(),
            persistence,
            state: Mutex::new(StreamState {
                log,
                args,
                readers: Vec::new(),
                last_sync: 0,
                going: false,
                deleted: false,
            }),
        }))
    }

    fn lock(&self) -> MutexGuard<'_, StreamState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Records held.
    pub fn len(&self) -> u64 {
        self.lock().log.len()
    }

    /// Bytes on disk.
    pub fn bytes(&self) -> u64 {
        self.lock().log.bytes()
    }

    /// Its offsets and files, for listings and metrics.
    pub fn figures(&self) -> StreamFigures {
        let st = self.lock();
        let (first, next) = (st.log.first_offset(), st.log.next_offset());
        StreamFigures {
            first_offset: first,
            last_offset: (next > first).then(|| next - 1),
            segments: st.log.segment_count() as u64,
            bytes: st.log.bytes(),
        }
    }

    /// Consumers reading it.
    pub fn reader_count(&self) -> usize {
        self.lock().readers.len()
    }

    /// queue.delete's if-unused ([`Queue::take_unused`]): whether no
    /// consumer reads the stream; if so it is marked going in the same
    /// lock hold, so that no consumer (404) comes before the delete that
    /// follows.
    pub(super) fn take_unused(&self) -> bool {
        let mut st = self.lock();
        if !st.readers.is_empty() {
            return false;
        }
        st.going = true;
        true
    }

    /// Its consumers, in registration order.
    pub fn consumers(&self) -> Vec<Arc<Consumer>> {
        self.lock()
            .readers
            .iter()
            .map(|r| Arc::clone(&r.consumer))
            .collect()
    }

    /// Applies retention now (the sweeper calls this, so a short
    /// `x-max-age` takes effect without new publishes).
    pub fn retain(&self) {
        let gone = {
            let mut st = self.lock();
            let (bytes, age) = (st.args.max_bytes, st.args.max_age_ms);
            st.log.retain(bytes, age, now_ms())
        };
        remove_in_background(gone);
    }

    /// Takes the retention `applied` gives (`max-length-bytes`,
    /// `max-age`: the smaller of each with the declared argument) and
    /// applies it at once, as RabbitMQ 3.10 does on a policy change. The
    /// segment size stays what the stream was declared with: RabbitMQ 3.10
    /// takes a policy's `stream-max-segment-size-bytes` only at declare.
    pub(super) fn apply_policies(&self, applied: &Applied) {
        {
            let mut st = self.lock();
            st.args.max_bytes = stricter(self.declared.max_bytes, applied.max_length_bytes());
            st.args.max_age_ms = stricter(self.declared.max_age_ms, applied.max_age_ms());
        }
        self.retain();
    }
}

impl Queue {
    fn stream_ref(&self) -> &Stream {
        self.stream.as_ref().expect("called on a stream only")
    }

    /// Appends a publish to the stream; hands it to readers at the tail.
    pub(super) fn stream_publish(self: &Arc<Self>, message: &Message) -> Enqueued {
        let stream = self.stream_ref();
        let mut tasks = Vec::new();
        let sync = {
            let mut st = stream.lock();
            if st.deleted {
                return Enqueued::Accepted { sync: 0 };
            }
            let stamped_at = st.log.next_offset();
            let (payload, flags) = encode(message, stamped_at);
            let payload = Bytes::from(payload);
            let chunk_start = stream.persistence.flushed() >= st.last_sync;
            let flags = if chunk_start {
                flags | log::CHUNK_START
            } else {
                flags
            };
            let timestamp = now_ms();
            let (offset, rolled) = match st.log.append(&payload, timestamp, flags) {
                Ok(appended) => appended,
                Err(e) => {
                    tracing::error!(queue = %self.name, vhost = %self.vhost, error = %e, "cannot append to a stream: the publish is refused");
                    return Enqueued::Refused { sync: 0 };
                }
            };
            debug_assert_eq!(offset, stamped_at, "appended where it was stamped");
            let sync = stream
                .persistence
                .submit_sync(st.log.sync_handles(rolled), st.log.synced_mark());
            st.last_sync = sync;
            if rolled {
                let (bytes, age) = (st.args.max_bytes, st.args.max_age_ms);
                remove_in_background(st.log.retain(bytes, age, timestamp));
            }
            self.stats.published();
            for reader in st.readers.iter_mut() {
                reader.stalled = false;
                if reader.cursor.offset == offset && reader.batch.is_empty() && !reader.reading {
                    reader.batch.push_back(Record {
                        offset,
                        timestamp_ms: timestamp,
                        flags,
                        payload: payload.clone(),
                    });
                    reader.cursor = Cursor::at(offset + 1);
                }
            }
            self.stream_deliver(&mut st, &mut tasks);
            sync
        };
        self.start_reads(tasks);
        Enqueued::Accepted { sync }
    }

    /// Adds a stream consumer starting at `start`. Its exclusive flag
    /// keeps no other reader out: RabbitMQ 3.10 accepts any number of
    /// consumers on a stream, exclusive or not (each reads every record;
    /// none takes one from another). 404 if the stream is deleted or
    /// going (taken by an if-unused delete): a reader added after the
    /// delete drained them would never hear of it.
    pub fn add_stream_consumer(&self, consumer: Arc<Consumer>, start: StartAt) -> AmqpResult<()> {
        let stream = self.stream_ref();
        let mut st = stream.lock();
        if st.deleted || st.going {
            return Err(self.gone());
        }
        let log = &st.log;
        let (first, next) = (log.first_offset(), log.next_offset());
        let cursor = match start {
            StartAt::First => Cursor::at(first),
            StartAt::Last => Cursor::at(log.last_chunk()),
            StartAt::Next => Cursor::at(next),
            // Past the end: it waits for that offset (RabbitMQ 3.10 too).
            StartAt::Offset(n) => Cursor::at(n.max(first)),
            StartAt::Timestamp(ms) => Cursor::at_time(log.offset_for_timestamp(ms).max(first), ms),
        };
        st.readers.push(Reader {
            consumer,
            cursor,
            batch: VecDeque::new(),
            reading: false,
            stalled: false,
        });
        self.stats.consumer_added();
        Ok(())
    }

    /// Removes a stream consumer; a stream is never auto-deleted.
    pub(super) fn remove_stream_consumer(&self, consumer: &Arc<Consumer>) -> bool {
        let mut st = self.stream_ref().lock();
        let before = st.readers.len();
        st.readers.retain(|r| !Arc::ptr_eq(&r.consumer, consumer));
        if st.readers.len() < before {
            self.stats.consumers_removed(1);
        }
        false
    }

    /// Delivers what readers have batched while they have credit and
    /// room, and starts reads for those that need more.
    pub(super) fn stream_dispatch(self: &Arc<Self>) {
        let mut tasks = Vec::new();
        {
            let mut st = self.stream_ref().lock();
            self.stream_deliver(&mut st, &mut tasks);
        }
        self.start_reads(tasks);
    }

    fn stream_deliver(self: &Arc<Self>, st: &mut StreamState, tasks: &mut Vec<ReadTask>) {
        if st.deleted {
            return;
        }
        let next = st.log.next_offset();
        for reader in st.readers.iter_mut() {
            let consumer = Arc::clone(&reader.consumer);
            if !reader.batch.is_empty() {
                self.deliver_burst(reader, &consumer);
            }
            if !reader.reading
                && wants_more(&reader.batch)
                && !reader.stalled
                && reader.cursor.offset < next
                && consumer.has_credit()
            {
                reader.reading = true;
                tasks.push(ReadTask {
                    records: (consumer.prefetch as usize).clamp(1, READ_RECORDS),
                    consumer,
                    cursor: reader.cursor,
                    plan: st.log.plan(&reader.cursor),
                });
            }
        }
    }

    /// Delivers what `reader` has batched while its consumer has credit
    /// and its connection room. The burst takes its tags and enters the
    /// outbox under one hold of the channel's delivery lock (so tags reach
    /// the client in the order they were handed out, whichever queue's
    /// thread delivers), and is sent once it is whole: the writer is woken
    /// once for it, not once a delivery.
    fn deliver_burst(self: &Arc<Self>, reader: &mut Reader, consumer: &Arc<Consumer>) {
        let mut burst = Vec::with_capacity(reader.batch.len());
        let mut deliveries = consumer.channel.deliveries();
        while !reader.batch.is_empty() {
            let Some(permit) = consumer.channel.outbox.try_reserve() else {
                consumer.channel.outbox.wait_for_room(self);
                break;
            };
            let Some(credit) = consumer.try_take_credit() else {
                break;
            };
            let Some(record) = reader.batch.pop_front() else {
                break;
            };
            let Some(message) = decode(&record) else {
                tracing::error!(queue = %self.name, offset = record.offset, "a stream record that passed its checksum does not decode; skipped");
                continue;
            };
            credit.keep();
            self.stats.delivered(false, false, &message);
            let message = Arc::new(message);
            let delivery_tag = deliveries.next_tag();
            deliveries.push(Unacked {
                tag: delivery_tag,
                origin: Origin {
                    queue: Arc::clone(self),
                    message: QueuedMessage {
                        seq: record.offset,
                        priority: 0,
                        message: Arc::clone(&message),
                        redelivered: false,
                        expires_at: None,
                    },
                },
                consumer: Some(Arc::clone(consumer)),
            });
            burst.push((
                permit,
                Outbound::Deliver {
                    channel: consumer.channel.id,
                    consumer_tag: consumer.tag.clone(),
                    delivery_tag,
                    redelivered: false,
                    message,
                },
            ));
        }
        for (permit, item) in burst {
            permit.send(item);
        }
        drop(deliveries);
    }

    /// Runs reads off the broker's threads (inline where there is no
    /// runtime, as in unit tests).
    fn start_reads(self: &Arc<Self>, tasks: Vec<ReadTask>) {
        for task in tasks {
            let queue = Arc::clone(self);
            let work = move || queue.run_reads(task);
            match tokio::runtime::Handle::try_current() {
                Ok(runtime) => {
                    runtime.spawn_blocking(work);
                }
                Err(_) => work(),
            }
        }
    }

    /// Reads `task`'s batch, hands it back and dispatches; while that
    /// leaves its reader wanting more and the read was a whole one (the
    /// reader is well behind the tail), reads on here rather than handing
    /// the next read to another blocking thread (a wake-up and a task
    /// switch each). A short read (the reader has caught up) hands its next
    /// read on as before, so a reader near the tail does not chase each
    /// append with a read of its own. Reads for other readers start as
    /// usual. After [`READS_A_RUN`] reads the next one is handed on too, so
    /// one run holds its blocking thread for at most that many reads.
    fn run_reads(self: &Arc<Self>, mut task: ReadTask) {
        for run in 1.. {
            let mut cursor = task.cursor;
            let records = task.plan.read(&mut cursor, task.records, READ_BYTES);
            let whole = records.len() >= task.records
                || records.iter().map(|r| r.payload.len()).sum::<usize>() >= READ_BYTES;
            let mut tasks = self.read_done(&task.consumer, cursor, records);
            let own = tasks
                .iter()
                .position(|t| Arc::ptr_eq(&t.consumer, &task.consumer))
                .filter(|_| whole && run < READS_A_RUN);
            let next = own.map(|i| tasks.swap_remove(i));
            self.start_reads(tasks);
            match next {
                Some(next) => task = next,
                None => return,
            }
        }
    }

    /// Takes a read's records into its reader's batch and delivers; the
    /// reads to start next.
    fn read_done(
        self: &Arc<Self>,
        consumer: &Arc<Consumer>,
        cursor: Cursor,
        records: Vec<Record>,
    ) -> Vec<ReadTask> {
        let mut tasks = Vec::new();
        let mut st = self.stream_ref().lock();
        let next = st.log.next_offset();
        let Some(reader) = st
            .readers
            .iter_mut()
            .find(|r| Arc::ptr_eq(&r.consumer, consumer))
        else {
            return tasks; // cancelled meanwhile
        };
        reader.reading = false;
        reader.stalled = records.is_empty() && cursor.offset < next;
        reader.cursor = cursor;
        reader.batch.extend(records);
        self.stream_deliver(&mut st, &mut tasks);
        tasks
    }

    /// Deletes the stream: its files go, its consumers come back to be
    /// told. The count is 0, as RabbitMQ 3.10's queue.delete-ok for a
    /// stream says: no message was ready to be taken, only kept.
    pub(super) fn stream_delete(&self) -> Deleted {
        let stream = self.stream_ref();
        let consumers: Vec<Arc<Consumer>> = {
            let mut st = stream.lock();
            st.deleted = true;
            st.log.destroy();
            st.readers.drain(..).map(|r| r.consumer).collect()
        };
        self.stats.queue_deleted(consumers.len());
        Deleted {
            messages: 0,
            consumers,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn message(properties: &BasicProperties) -> Message {
        let mut encoded = BytesMut::new();
        properties.encode(&mut encoded);
        Message {
            exchange: ShortStr::from_static("x"),
            routing_key: ShortStr::from_static("rk"),
            properties: encoded.freeze(),
            body: Bytes::from_static(b"body"),
            persistent: properties.delivery_mode == Some(2),
            priority: 0,
            ttl_ms: None,
            stored: None,
        }
    }

    fn record(offset: u64, (payload, flags): (Vec<u8>, u8)) -> Record {
        Record {
            offset,
            timestamp_ms: 0,
            flags,
            payload: payload.into(),
        }
    }

    fn offset_header(message: &Message) -> Option<FieldValue> {
        let read = BasicProperties::decode(&message.properties).unwrap();
        read.headers.unwrap().get(OFFSET_HEADER).cloned()
    }

    #[test]
    fn a_record_decodes_to_its_message_with_its_offset_header() {
        for delivery_mode in [Some(2), Some(1), None] {
            let mut headers = FieldTable::new();
            headers.insert(ShortStr::from_static("kept"), FieldValue::I32(7));
            // A publisher's own offset header is replaced, as RabbitMQ does.
            headers.insert(ShortStr::from_static(OFFSET_HEADER), FieldValue::I64(-1));
            let properties = BasicProperties {
                delivery_mode,
                headers: Some(headers),
                content_type: Some(ShortStr::from_static("text/plain")),
                ..Default::default()
            };
            let message = message(&properties);
            let stamped = record(42, encode(&message, 42));
            assert_ne!(stamped.flags & STAMPED, 0, "stamped when appended");
            let decoded = decode(&stamped).expect("decodes");
            assert_eq!(decoded.exchange, message.exchange);
            assert_eq!(decoded.routing_key, message.routing_key);
            assert_eq!(decoded.body, message.body);
            assert_eq!(decoded.persistent, delivery_mode == Some(2));
            assert_eq!(offset_header(&decoded), Some(FieldValue::I64(42)));
            let read = BasicProperties::decode(&decoded.properties).unwrap();
            assert_eq!(read.delivery_mode, delivery_mode);
            assert_eq!(read.content_type, properties.content_type);
            assert_eq!(read.headers.unwrap().get("kept"), Some(&FieldValue::I32(7)));
        }
    }

    #[test]
    fn a_record_stored_unstamped_is_stamped_as_it_is_delivered() {
        // As an older Leveret stored records: the properties as published.
        let message = message(&BasicProperties {
            delivery_mode: Some(2),
            ..Default::default()
        });
        let mut payload = vec![1, b'x', 2, b'r', b'k'];
        payload.extend_from_slice(&(message.properties.len() as u32).to_le_bytes());
        payload.extend_from_slice(&message.properties);
        payload.extend_from_slice(b"body");
        let decoded = decode(&record(9, (payload, 0))).expect("decodes");
        assert!(decoded.persistent);
        assert_eq!(decoded.body, message.body);
        assert_eq!(offset_header(&decoded), Some(FieldValue::I64(9)));
    }

    #[test]
    fn properties_that_do_not_decode_are_stored_unstamped_and_skipped() {
        let mut message = message(&BasicProperties::default());
        message.properties = Bytes::from_static(&[0xff, 0xff, 1]);
        let stored = record(3, encode(&message, 3));
        assert_eq!(stored.flags & STAMPED, 0);
        assert!(decode(&stored).is_none());
    }

    #[test]
    fn a_reader_reads_on_only_while_under_half_a_read_is_batched() {
        let batch = |records: usize, size: usize| -> VecDeque<Record> {
            (0..records)
                .map(|i| record(i as u64, (vec![0; size], 0)))
                .collect()
        };
        assert!(wants_more(&batch(0, 0)));
        assert!(wants_more(&batch(READ_RECORDS / 2 - 1, 1)));
        assert!(!wants_more(&batch(READ_RECORDS / 2, 1)), "records");
        assert!(wants_more(&batch(1, READ_BYTES / 2 - 1)));
        assert!(!wants_more(&batch(1, READ_BYTES / 2)), "bytes");
    }

    #[test]
    fn a_payload_cut_short_does_not_decode() {
        for flags in [0, STAMPED] {
            for payload in [&[5, b'a'][..], &[1, b'a', 0, 9, 0, 0, 0, 1]] {
                assert!(decode(&record(0, (payload.to_vec(), flags))).is_none());
            }
        }
    }
}
