//! Reading a port's recording back: a [`Playback`] reads the stream a
//! [`super::Recording`] fills, from a [`Position`] (the first record, an
//! offset, or a time by the publisher's clock) to an optional end, at the
//! recorded pace times a rate factor or as fast as it can; a [`Player`]
//! decodes what it reads into [`Sample`]s with the original sequence
//! numbers and send times.
//!
//! A playback is a stream consumer (a prefetch, manual acks, which only
//! give the broker credit back: nothing is removed) started at
//! `x-stream-offset`; each record's offset is its delivery's
//! `x-stream-offset` header. Pacing follows the records' `x-sent-ns`
//! headers: the record sent `d` after the first one played is handed out
//! `d / rate` after it. A playback opened through a [`Connector`]
//! reconnects after a lost link (with backoff, as the ports do) and goes
//! on from the record after the last one it handed out, so nothing is
//! played twice or skipped; one on a connection of the caller's ends with
//! the error, and its last offset says where to start again.
//!
//! Uses the client's consumers and this crate's headers (`link`), data
//! decoding (`data`) and [`Connector`].

use super::data::PortData;
use super::in_port::Sample;
use super::link::Stamp;
use super::profile::{Backoff, Connector, PortProfile};
use leveret_client::{
    BasicConsumeOptions, BasicQosOptions, Connection, Consumer, ConsumerEnd, Delivery, Error,
    FieldTable, FieldValue, Result, ShortStr,
};
use std::marker::PhantomData;
use std::time::{Duration, SystemTime, UNIX_EPOCH};
use tokio::time::Instant;

/// The header with a stream delivery's offset (a long).
pub const OFFSET_HEADER: &str = "x-stream-offset";

/// How many records the broker sends a playback ahead of what it has read.
const PREFETCH: u16 = 256;

/// A place in a recording.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Position {
    /// The oldest record kept.
    First,
    /// The record at this offset (the stream's numbering, from 0).
    Offset(u64),
    /// The first record put at or after this time, by the publisher's
    /// clock (its `x-sent-ns`). The broker starts reading at the whole
    /// second before, by its own clock, and records put earlier are
    /// skipped.
    Time(SystemTime),
}

/// How a playback reads: from where, to where, how fast.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlayOptions {
    /// The first record played.
    pub start: Position,
    /// The last record played: the record at an offset, or the last put
    /// at or before a time (the playback ends when it reads a later one).
    /// `None`: the playback follows the recording as it grows.
    pub end: Option<Position>,
    /// The pace: `Some(1.0)` as recorded, `Some(10.0)` ten times as fast,
    /// `None` as fast as the records come.
    pub rate: Option<f64>,
    /// Ends the playback when no record arrives for this long (the end of
    /// what is recorded so far); `None`: wait for ever.
    pub idle: Option<Duration>,
}

impl Default for PlayOptions {
    /// Everything recorded, as fast as possible, following the recording.
    fn default() -> Self {
        PlayOptions {
            start: Position::First,
            end: None,
            rate: None,
            idle: None,
        }
    }
}

/// One record of a recording.
#[derive(Debug)]
pub struct Recorded {
    /// Its offset in the stream.
    pub offset: u64,
    /// The out-port that put it (`x-port`), if it said.
    pub port: Option<String>,
    /// The out-port's sequence number (`x-seq`), if it said.
    pub seq: Option<u64>,
    /// When it was put (`x-sent-ns`), if the out-port said.
    pub sent_at: Option<SystemTime>,
    /// The message as the stream delivered it (properties, body).
    pub delivery: Delivery,
}

/// Where pacing stands: the first record's send time and when it was
/// handed out.
#[derive(Debug, Clone, Copy)]
struct Anchor {
    sent_ns: i64,
    at: Instant,
}

/// A recording read back (see the module's docs).
pub struct Playback {
    connection: Connection,
    consumer: Consumer,
    stream: String,
    /// How to reconnect after a lost link (a playback opened through a
    /// connector), with the delays between attempts.
    reconnect: Option<(Connector, Backoff)>,
    options: PlayOptions,
    anchor: Option<Anchor>,
    /// The offset of the last record handed out.
    last_offset: Option<u64>,
    ended: bool,
}

impl std::fmt::Debug for Playback {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Playback")
            .field("options", &self.options)
            .field("last_offset", &self.last_offset)
            .finish_non_exhaustive()
    }
}

impl Playback {
    /// Opens the stream `stream` through `connector` and starts reading
    /// at `options.start`. Refuses a rate that is not a positive number.
    pub async fn open(connector: &Connector, stream: &str, options: PlayOptions) -> Result<Self> {
        let mut playback = Playback::over(connector.connect().await?, stream, options).await?;
        playback.reconnect = Some((connector.clone(), Backoff::default()));
        Ok(playback)
    }

    /// [`Playback::open`] on a connection of the caller's (the playback
    /// owns it from now on, and ends when it is lost).
    pub async fn over(connection: Connection, stream: &str, options: PlayOptions) -> Result<Self> {
        check_rate(options.rate)?;
        let consumer = consume(&connection, stream, options.start).await?;
        Ok(Playback {
            connection,
            consumer,
            stream: stream.to_owned(),
            reconnect: None,
            options,
            anchor: None,
            last_offset: None,
            ended: false,
        })
    }

    /// After a lost link: connects again (with backoff, for as long as
    /// connecting fails) and consumes from the record after the last one
    /// handed out. An error if the broker refuses the consumer (the
    /// stream is gone) or there is no connector to reconnect with.
    async fn resume(&mut self, lost: Error) -> Result<()> {
        let Some((connector, backoff)) = &self.reconnect else {
            return Err(lost);
        };
        let start = match self.last_offset {
            Some(last) => Position::Offset(last + 1),
            None => self.options.start,
        };
        tracing::debug!(error = %lost, ?start, "playback link lost; reconnecting");
        let mut failures = 0u32;
        loop {
            tokio::time::sleep(backoff.delay(failures)).await;
            let connection = match connector.connect().await {
                Ok(connection) => connection,
                Err(_) => {
                    failures = failures.saturating_add(1);
                    continue;
                }
            };
            match consume(&connection, &self.stream, start).await {
                Ok(consumer) => {
                    self.connection = connection;
                    self.consumer = consumer;
                    return Ok(());
                }
                Err(refused @ Error::ChannelClosed(_)) => return Err(refused),
                Err(_) => failures = failures.saturating_add(1),
            }
        }
    }

    /// [`Playback::open`] on the broker of `profile`, reading the stream
    /// it records to; refuses a profile that records nothing.
    pub async fn of(profile: &PortProfile, options: PlayOptions) -> Result<Self> {
        let Some(recording) = &profile.record else {
            return Err(Error::InvalidArgument(
                "the profile records nothing: no stream to play".to_owned(),
            ));
        };
        Playback::open(&Connector::from(profile), &recording.stream, options).await
    }

    /// The next record, when its time comes; `None` once past the end
    /// (or idle for `options.idle`); an error if the broker refuses or
    /// cancels the consumer (the stream is gone), or if the link fails on
    /// a caller's connection ([`Playback::over`]). Waits through a lost
    /// link's reconnection otherwise.
    pub async fn next(&mut self) -> Result<Option<Recorded>> {
        loop {
            if self.ended || self.past_end_offset() {
                self.ended = true;
                return Ok(None);
            }
            let delivery = match self.options.idle {
                Some(idle) => match tokio::time::timeout(idle, self.consumer.next()).await {
                    Ok(delivery) => delivery,
                    Err(_) => {
                        self.ended = true;
                        return Ok(None);
                    }
                },
                None => self.consumer.next().await,
            };
            let Some(delivery) = delivery else {
                let lost = match self.consumer.end_reason() {
                    Some(ConsumerEnd::ChannelClosed(error)) => error,
                    Some(ConsumerEnd::CancelledByBroker) => {
                        self.ended = true;
                        return Err(Error::Protocol(
                            "the broker cancelled the playback's consumer".to_owned(),
                        ));
                    }
                    _ => Error::Closed,
                };
                if let Err(error) = self.resume(lost).await {
                    self.ended = true;
                    return Err(error);
                }
                continue;
            };
            let headers = delivery.properties.headers.as_ref();
            let Some(offset) = headers
                .and_then(|h| h.get(OFFSET_HEADER))
                .and_then(FieldValue::as_i64)
                .and_then(|o| u64::try_from(o).ok())
            else {
                // Not acknowledged: a queue that is not a stream gets its
                // messages back when the playback closes.
                self.ended = true;
                return Err(Error::Protocol(
                    "a delivery without x-stream-offset: the queue is not a stream".to_owned(),
                ));
            };
            // Credit back at once: a stream keeps the record whatever the
            // ack. One that fails means a closing channel: the consumer
            // ends, and the playback resumes after this record.
            let _ = delivery.ack().await;
            let stamp = Stamp::read(headers);
            if let (Position::Time(start), Some(sent_ns)) = (self.options.start, stamp.sent_ns) {
                if time_of(sent_ns) < start {
                    continue;
                }
            }
            let beyond_end = match (self.options.end, stamp.sent_ns) {
                (Some(Position::Offset(end)), _) => offset > end,
                (Some(Position::Time(end)), Some(sent_ns)) => time_of(sent_ns) > end,
                _ => false,
            };
            if beyond_end {
                self.ended = true;
                return Ok(None);
            }
            if let Some(sent_ns) = stamp.sent_ns {
                self.pace(sent_ns).await;
            }
            self.last_offset = Some(offset);
            return Ok(Some(Recorded {
                offset,
                port: stamp.port,
                seq: stamp.seq,
                sent_at: stamp.sent_ns.map(time_of),
                delivery,
            }));
        }
    }

    /// Whether the record at the end offset has been handed out.
    fn past_end_offset(&self) -> bool {
        matches!(
            (self.options.end, self.last_offset),
            (Some(Position::Offset(end)), Some(last)) if last >= end
        )
    }

    /// Waits until the record sent at `sent_ns` is due.
    async fn pace(&mut self, sent_ns: i64) {
        let Some(rate) = self.options.rate else {
            return;
        };
        let Some(anchor) = self.anchor else {
            self.anchor = Some(Anchor {
                sent_ns,
                at: Instant::now(),
            });
            return;
        };
        let Ok(since) = u64::try_from(sent_ns.saturating_sub(anchor.sent_ns)) else {
            return;
        };
        let due = anchor.at + Duration::from_nanos(since).div_f64(rate);
        tokio::time::sleep_until(due).await;
    }

    /// The offset of the last record handed out.
    pub fn last_offset(&self) -> Option<u64> {
        self.last_offset
    }

    /// Closes the connection.
    pub async fn close(self) {
        let _ = self.connection.close().await;
    }
}

/// Starts a consumer of `stream` at `start` on a new channel of
/// `connection`, with the playback's prefetch.
async fn consume(connection: &Connection, stream: &str, start: Position) -> Result<Consumer> {
    let channel = connection.open_channel().await?;
    channel
        .basic_qos(PREFETCH, BasicQosOptions::default())
        .await?;
    let mut arguments = FieldTable::new();
    arguments.insert(
        ShortStr::from_static(OFFSET_HEADER),
        match start {
            Position::First => FieldValue::string("first"),
            Position::Offset(offset) => FieldValue::I64(i64::try_from(offset).unwrap_or(i64::MAX)),
            Position::Time(time) => {
                FieldValue::Timestamp(time.duration_since(UNIX_EPOCH).map_or(0, |d| d.as_secs()))
            }
        },
    );
    channel
        .basic_consume(stream, "", BasicConsumeOptions::default(), arguments)
        .await
}

/// Refuses a rate that is not a positive factor.
fn check_rate(rate: Option<f64>) -> Result<()> {
    match rate {
        Some(rate) if !(rate.is_finite() && rate > 0.0) => Err(Error::InvalidArgument(format!(
            "rate {rate}: not a positive factor"
        ))),
        _ => Ok(()),
    }
}

/// `sent_ns` (nanoseconds since the Unix epoch, as `x-sent-ns` says) as a
/// time; before the epoch counts as the epoch.
fn time_of(sent_ns: i64) -> SystemTime {
    UNIX_EPOCH + Duration::from_nanos(u64::try_from(sent_ns).unwrap_or(0))
}

/// A played record's value, with its offset.
#[derive(Debug, Clone, PartialEq)]
pub struct Replayed<T> {
    /// Its offset in the stream.
    pub offset: u64,
    /// The value, with the original sequence number and send time
    /// (`latency` is `None`: the value was recorded, not just sent).
    pub sample: Sample<T>,
}

/// A recording of `T` values played back (a typed [`Playback`]): records
/// that do not decode as `T` are skipped and counted.
#[derive(Debug)]
pub struct Player<T> {
    playback: Playback,
    options: super::CdrOptions,
    decode_errors: u64,
    _data: PhantomData<fn() -> T>,
}

impl<T: PortData> Player<T> {
    /// Plays the recording of `profile` (its stream, broker and CDR
    /// options).
    pub async fn open(profile: &PortProfile, options: PlayOptions) -> Result<Self> {
        Ok(Player::over(Playback::of(profile, options).await?, profile))
    }

    /// Plays the recording of `profile` through `connector`.
    pub async fn open_with(
        connector: &Connector,
        profile: &PortProfile,
        options: PlayOptions,
    ) -> Result<Self> {
        let Some(recording) = &profile.record else {
            return Err(Error::InvalidArgument(
                "the profile records nothing: no stream to play".to_owned(),
            ));
        };
        let playback = Playback::open(connector, &recording.stream, options).await?;
        Ok(Player::over(playback, profile))
    }

    fn over(playback: Playback, profile: &PortProfile) -> Self {
        Player {
            playback,
            options: profile.cdr,
            decode_errors: 0,
            _data: PhantomData,
        }
    }

    /// The next value, when its time comes (see [`Playback::next`]).
    pub async fn next(&mut self) -> Result<Option<Replayed<T>>> {
        loop {
            let Some(record) = self.playback.next().await? else {
                return Ok(None);
            };
            match super::in_port::decode::<T>(&record.delivery, self.options) {
                Ok(value) => {
                    return Ok(Some(Replayed {
                        offset: record.offset,
                        sample: Sample {
                            value,
                            seq: record.seq,
                            sent_at: record.sent_at,
                            latency: None,
                            redelivered: false,
                        },
                    }))
                }
                Err(error) => {
                    tracing::warn!(%error, offset = record.offset, "playback skipped a record that does not decode");
                    self.decode_errors += 1;
                }
            }
        }
    }

    /// Records skipped because they did not decode.
    pub fn decode_errors(&self) -> u64 {
        self.decode_errors
    }

    /// The offset of the last value handed out.
    pub fn last_offset(&self) -> Option<u64> {
        self.playback.last_offset()
    }

    /// Closes the connection.
    pub async fn close(self) {
        self.playback.close().await;
    }
}
