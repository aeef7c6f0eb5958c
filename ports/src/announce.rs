//! Port announcements: every port says, on the broker, what it is and how
//! it is doing, so tools can list the ports connected to a broker and
//! follow one (`leveretctl port list`, `port stats`, `port echo`).
//!
//! This module owns the wire contract below, the [`Announcer`] a port
//! runs, and the reader, [`PortDirectory`]. It uses the client's channel
//! API and the ports' profile, link and statistics types; the ports call
//! it through three hooks only (start, link up, close), so announcing
//! never touches their windows, buffers or counters.
//!
//! # Who announces, when
//! Each port with an [`announce_interval`](PortProfile::announce_interval)
//! (1 s by default) runs an announcer task of its own that publishes on a
//! channel of its own on the port's connection: once when the port's link
//! comes up, then every interval while it is up, and, when the port is
//! closed or dropped, a last announcement with `state` `closed` (best
//! effort: within a second, and only if the link is up). A port's
//! `put` never waits for it, and nothing it sends is counted in the
//! port's statistics. Only standard AMQP is used, so it works the same on
//! RabbitMQ.
//!
//! # Wire contract (version 1)
//! The topic exchange [`PORTS_EXCHANGE`] (`leveret.ports`; declared
//! non-durable and not auto-delete by ports and readers alike), routing
//! key `out.NAME` or `in.NAME` (cut to 255 bytes). A transient message,
//! empty body, `type` property `leveret.port.announcement`, `timestamp`
//! the send time in seconds, `expiration` three intervals (a reader that
//! was away gets no stale announcements). Everything is in its headers:
//!
//! | key | type | meaning |
//! |---|---|---|
//! | `version` | long-long | 1; fields are only ever added under it |
//! | `port` | long string | the instance's id: an out-port's `x-port` header |
//! | `name` | long string | see [`PortProfile::port_name`] |
//! | `direction` | long string | `out` or `in` |
//! | `state` | long string | `up`, or `closed` for the last one |
//! | `interval_ms` | long-long | the announce interval |
//! | `sent_ns` | long-long | when sent, ns since the Unix epoch |
//! | `data_type` | long string | `PortData::TYPE_NAME`, else the Rust type's name |
//! | `content_type` | long string | the content type of its messages |
//! | `cdr_endian`, `cdr_charset` | long string | `little`/`big`, `utf-8`/`latin-1`; only for CDR content |
//! | `exchange` | long string | empty for the default exchange |
//! | `exchange_type` | long string | `direct`, `fanout`, `topic`, `headers`, or a plugin's |
//! | `routing_key` | long string | an out-port's |
//! | `binding_key` | long string | an in-port's |
//! | `queue` | long string | an in-port's queue; an out-port's if it binds one |
//! | `confirms`, `durable` | boolean | publisher confirms; durable topology |
//! | `lifespan_ms` | long-long | absent: values never go stale |
//! | `backpressure` | long string | out: `drop_oldest`, `drop_newest`, `block` |
//! | `replay` | long string | out: `all`, `latest`, `nothing` |
//! | `window` | long-long | out: the most values kept unconfirmed |
//! | `full_policy` | long string | in: `drop_oldest`, `drop_newest`, `block_broker` |
//! | `buffer`, `prefetch` | long-long | in: buffer size, prefetch count |
//! | `link` | table | `up`, `degraded` (booleans), `connects`, `losses` (long-long), `last_error` (long string, absent if none) |
//! | `stats` | table | every counter of [`OutPortStats`] or [`InPortStats`], long-long, by field name, in the struct's order |
//! | `latency` | table | in: `count`, `min_ns`, `mean_ns`, `p50_ns`, `p99_ns`, `max_ns` (long-long) |
//!
//! A reader ignores keys it does not know, and skips (with a debug log) a
//! message whose `version`, `port`, `name`, `direction`, `state`,
//! `interval_ms` or `sent_ns` is missing or of the wrong type.

use super::cdr::{CdrOptions, Charset, Endian};
use super::data::{DataError, PortData};
use super::in_port::InPortStats;
use super::latency::LatencyStats;
use super::link::{self, LinkStatus};
use super::openrtm::PortRole;
use super::out_port::OutPortStats;
use super::profile::{Backpressure, ExchangeKind, FullPolicy, PortProfile, Replay};
use bytes::Bytes;
use leveret_client::{
    BasicConsumeOptions, BasicProperties, BasicPublishOptions, Channel, Connection, Consumer,
    ExchangeDeclareOptions, FieldTable, FieldValue, QueueBindOptions, QueueDeclareOptions,
    ShortStr,
};
use leveret_client::{Error, Result};
use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::{watch, Notify};
use tokio::task::JoinHandle;
use tokio::time::{Instant, MissedTickBehavior};

/// The topic exchange ports announce themselves on.
pub const PORTS_EXCHANGE: &str = "leveret.ports";

/// The wire contract's version (the `version` header).
pub const ANNOUNCEMENT_VERSION: i64 = 1;

/// The `type` property of announcements.
const ANNOUNCEMENT_TYPE: &str = "leveret.port.announcement";

/// How long a closing port waits for its `closed` announcement.
pub(crate) const CLOSE_TIMEOUT: Duration = Duration::from_secs(1);

/// Counters a reader keeps from one announcement, at most.
const MAX_COUNTERS: usize = 64;

/// How often a reader's table drops the ports no longer live (and
/// whenever it is full); between times they are only filtered out.
const PRUNE_INTERVAL: Duration = Duration::from_secs(1);

/// Whether a port is running or has just closed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PortState {
    /// Running, its link up.
    Up,
    /// Closed (its last announcement).
    Closed,
}

impl PortState {
    /// The wire word: `up` or `closed`.
    pub fn as_str(self) -> &'static str {
        match self {
            PortState::Up => "up",
            PortState::Closed => "closed",
        }
    }
}

impl PortRole {
    /// The wire word of a port's direction: `out` or `in`.
    pub fn direction(self) -> &'static str {
        match self {
            PortRole::OutPort => "out",
            PortRole::InPort => "in",
        }
    }
}

/// An in-port's latencies as announced.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct LatencySummary {
    /// Samples measured.
    pub count: u64,
    /// Smallest.
    pub min: Duration,
    /// Mean.
    pub mean: Duration,
    /// Median.
    pub p50: Duration,
    /// 99th percentile.
    pub p99: Duration,
    /// Largest.
    pub max: Duration,
}

impl LatencySummary {
    /// The summary of `stats`.
    pub fn of(stats: &LatencyStats) -> Self {
        LatencySummary {
            count: stats.count,
            min: stats.min,
            mean: stats.mean(),
            p50: stats.percentile(0.5),
            p99: stats.percentile(0.99),
            max: stats.max,
        }
    }
}

/// One port's announcement, decoded (see the module's wire contract).
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct PortAnnouncement {
    /// The instance's id (an out-port's `x-port` header).
    pub id: String,
    /// The port's name.
    pub name: String,
    /// Out-port or in-port.
    pub role: PortRole,
    /// Up, or closed.
    pub state: PortState,
    /// How often it announces itself.
    pub interval: Duration,
    /// When this was sent, ns since the Unix epoch (the sender's clock).
    pub sent_ns: i64,
    /// Its data type's name.
    pub data_type: String,
    /// The content type of its messages.
    pub content_type: String,
    /// Byte order and charset of its CDR bodies (CDR content only).
    pub cdr: Option<CdrOptions>,
    /// Its exchange (empty: the default exchange).
    pub exchange: String,
    /// The exchange's type.
    pub exchange_kind: ExchangeKind,
    /// An out-port's routing key, an in-port's binding key.
    pub key: String,
    /// An in-port's queue; an out-port's if it binds one.
    pub queue: String,
    /// Publisher confirms.
    pub confirms: bool,
    /// Durable topology.
    pub durable: bool,
    /// How long its values stay useful.
    pub lifespan: Option<Duration>,
    /// An out-port's backpressure policy.
    pub backpressure: Option<Backpressure>,
    /// An out-port's replay policy.
    pub replay: Option<Replay>,
    /// An out-port's window.
    pub window: Option<u64>,
    /// An in-port's full policy.
    pub full_policy: Option<FullPolicy>,
    /// An in-port's buffer size.
    pub buffer: Option<u64>,
    /// An in-port's prefetch count.
    pub prefetch: Option<u64>,
    /// Its link.
    pub link: LinkStatus,
    /// Its counters by name, in the port's order.
    pub stats: Vec<(String, u64)>,
    /// An in-port's latencies.
    pub latency: Option<LatencySummary>,
}

/// Text values of the wire contract.
fn text(value: &str) -> FieldValue {
    FieldValue::string(value)
}

fn number(value: u64) -> FieldValue {
    FieldValue::I64(i64::try_from(value).unwrap_or(i64::MAX))
}

fn nanos(value: Duration) -> FieldValue {
    number(u64::try_from(value.as_nanos()).unwrap_or(u64::MAX))
}

fn millis(value: Duration) -> FieldValue {
    number(u64::try_from(value.as_millis()).unwrap_or(u64::MAX))
}

fn table<'a>(entries: impl IntoIterator<Item = (&'a str, FieldValue)>) -> FieldTable {
    let mut table = FieldTable::new();
    for (key, value) in entries {
        // The keys are this module's own, all short.
        if let Ok(key) = ShortStr::try_from(key) {
            table.insert(key, value);
        }
    }
    table
}

fn backpressure_word(policy: Backpressure) -> &'static str {
    match policy {
        Backpressure::DropOldest => "drop_oldest",
        Backpressure::DropNewest => "drop_newest",
        Backpressure::Block => "block",
    }
}

fn backpressure_of(word: &str) -> Option<Backpressure> {
    [
        Backpressure::DropOldest,
        Backpressure::DropNewest,
        Backpressure::Block,
    ]
    .into_iter()
    .find(|policy| backpressure_word(*policy) == word)
}

fn replay_word(policy: Replay) -> &'static str {
    match policy {
        Replay::All => "all",
        Replay::Latest => "latest",
        Replay::Nothing => "nothing",
    }
}

fn replay_of(word: &str) -> Option<Replay> {
    [Replay::All, Replay::Latest, Replay::Nothing]
        .into_iter()
        .find(|policy| replay_word(*policy) == word)
}

fn full_policy_word(policy: FullPolicy) -> &'static str {
    match policy {
        FullPolicy::DropOldest => "drop_oldest",
        FullPolicy::DropNewest => "drop_newest",
        FullPolicy::BlockBroker => "block_broker",
    }
}

fn full_policy_of(word: &str) -> Option<FullPolicy> {
    [
        FullPolicy::DropOldest,
        FullPolicy::DropNewest,
        FullPolicy::BlockBroker,
    ]
    .into_iter()
    .find(|policy| full_policy_word(*policy) == word)
}

fn endian_word(endian: Endian) -> &'static str {
    match endian {
        Endian::Little => "little",
        Endian::Big => "big",
    }
}

fn charset_word(charset: Charset) -> &'static str {
    match charset {
        Charset::Utf8 => "utf-8",
        Charset::Latin1 => "latin-1",
    }
}

/// An exchange type as written: the four standard ones by name, anything
/// else as given.
fn exchange_kind_of(word: &str) -> ExchangeKind {
    match word {
        "direct" => ExchangeKind::Direct,
        "fanout" => ExchangeKind::Fanout,
        "topic" => ExchangeKind::Topic,
        "headers" => ExchangeKind::Headers,
        other => ExchangeKind::Other(other.to_owned()),
    }
}

/// Whether messages of `content_type` are CDR.
fn is_cdr(content_type: &str) -> bool {
    content_type.starts_with("application/x-omg-cdr")
}

/// Reads the wire contract's fields out of a header table.
struct Fields<'a>(&'a FieldTable);

impl Fields<'_> {
    fn text(&self, key: &str) -> Option<String> {
        let bytes = self.0.get(key)?.as_bytes()?;
        std::str::from_utf8(bytes).ok().map(str::to_owned)
    }

    fn text_or_empty(&self, key: &str) -> String {
        self.text(key).unwrap_or_default()
    }

    fn number(&self, key: &str) -> Option<u64> {
        u64::try_from(self.0.get(key)?.as_i64()?).ok()
    }

    fn flag(&self, key: &str) -> bool {
        matches!(self.0.get(key), Some(FieldValue::Bool(true)))
    }

    fn table(&self, key: &str) -> Option<Fields<'_>> {
        match self.0.get(key)? {
            FieldValue::Table(table) => Some(Fields(table)),
            _ => None,
        }
    }

    fn required<T>(value: Option<T>, key: &str) -> std::result::Result<T, DataError> {
        value.ok_or_else(|| DataError::Invalid(format!("announcement without a valid {key}")))
    }
}

impl PortAnnouncement {
    /// What a port `id` with `profile` and data type `T` says of itself
    /// before any traffic: its identity and profile, state up, no counters
    /// yet. `queue` is an in-port's; an out-port's is the profile's if it
    /// binds one.
    fn describe<T: PortData>(
        role: PortRole,
        profile: &PortProfile,
        id: &str,
        queue: Option<&str>,
    ) -> Self {
        let out = role == PortRole::OutPort;
        let content_type = super::cdr::content_type(T::CONTENT_TYPE, &profile.cdr);
        let queue = match queue {
            Some(queue) => queue,
            None if profile.declare_queue => profile.queue.as_str(),
            None => "",
        };
        PortAnnouncement {
            id: id.to_owned(),
            name: profile.port_name(role),
            role,
            state: PortState::Up,
            interval: profile.announce_interval.unwrap_or_default(),
            sent_ns: 0,
            data_type: T::TYPE_NAME
                .unwrap_or(std::any::type_name::<T>())
                .to_owned(),
            content_type: content_type.to_owned(),
            cdr: is_cdr(content_type).then_some(profile.cdr),
            exchange: profile.exchange.clone(),
            exchange_kind: profile.exchange_kind.clone(),
            key: if out {
                profile.routing_key.clone()
            } else {
                profile.binding_key.clone()
            },
            queue: queue.to_owned(),
            confirms: profile.confirms,
            durable: profile.durable,
            lifespan: profile.lifespan,
            backpressure: out.then_some(profile.backpressure),
            replay: out.then_some(profile.replay),
            window: out.then_some(profile.max_unconfirmed as u64),
            full_policy: (!out).then_some(profile.full_policy),
            buffer: (!out).then_some(profile.buffer_size as u64),
            prefetch: (!out).then_some(u64::from(profile.prefetch)),
            link: LinkStatus::default(),
            stats: Vec::new(),
            latency: None,
        }
    }

    /// The routing key it is published with: `out.NAME` or `in.NAME`, cut
    /// to 255 bytes (at a character boundary).
    pub fn routing_key(&self) -> String {
        let mut key = format!("{}.{}", self.role.direction(), self.name);
        let mut end = key.len().min(ShortStr::MAX_LEN);
        while !key.is_char_boundary(end) {
            end -= 1;
        }
        key.truncate(end);
        key
    }

    /// The counter `name`, if the port has it.
    pub fn counter(&self, name: &str) -> Option<u64> {
        self.stats
            .iter()
            .find(|(counter, _)| counter == name)
            .map(|(_, value)| *value)
    }

    /// The headers that carry it (the wire contract).
    pub fn to_headers(&self) -> FieldTable {
        let mut headers = table([
            ("version", FieldValue::I64(ANNOUNCEMENT_VERSION)),
            ("port", text(&self.id)),
            ("name", text(&self.name)),
            ("direction", text(self.role.direction())),
            ("state", text(self.state.as_str())),
            ("interval_ms", millis(self.interval)),
            ("sent_ns", FieldValue::I64(self.sent_ns)),
            ("data_type", text(&self.data_type)),
            ("content_type", text(&self.content_type)),
            ("exchange", text(&self.exchange)),
            ("exchange_type", text(self.exchange_kind.as_str())),
            (
                match self.role {
                    PortRole::OutPort => "routing_key",
                    PortRole::InPort => "binding_key",
                },
                text(&self.key),
            ),
            ("queue", text(&self.queue)),
            ("confirms", FieldValue::Bool(self.confirms)),
            ("durable", FieldValue::Bool(self.durable)),
        ]);
        let optional = [
            self.cdr
                .map(|cdr| ("cdr_endian", text(endian_word(cdr.endian)))),
            self.cdr
                .map(|cdr| ("cdr_charset", text(charset_word(cdr.charset)))),
            self.lifespan
                .map(|lifespan| ("lifespan_ms", millis(lifespan))),
            self.backpressure
                .map(|policy| ("backpressure", text(backpressure_word(policy)))),
            self.replay
                .map(|policy| ("replay", text(replay_word(policy)))),
            self.window.map(|window| ("window", number(window))),
            self.full_policy
                .map(|policy| ("full_policy", text(full_policy_word(policy)))),
            self.buffer.map(|buffer| ("buffer", number(buffer))),
            self.prefetch.map(|prefetch| ("prefetch", number(prefetch))),
        ];
        for (key, value) in optional.into_iter().flatten() {
            headers.insert(ShortStr::from_static(key), value);
        }
        let mut link = table([
            ("up", FieldValue::Bool(self.link.up)),
            ("degraded", FieldValue::Bool(self.link.degraded)),
            ("connects", number(self.link.connects)),
            ("losses", number(self.link.losses)),
        ]);
        if let Some(error) = &self.link.last_error {
            link.insert(ShortStr::from_static("last_error"), text(error));
        }
        headers.insert(ShortStr::from_static("link"), FieldValue::Table(link));
        let stats = table(
            self.stats
                .iter()
                .map(|(name, value)| (name.as_str(), number(*value))),
        );
        headers.insert(ShortStr::from_static("stats"), FieldValue::Table(stats));
        if let Some(latency) = &self.latency {
            let latency = table([
                ("count", number(latency.count)),
                ("min_ns", nanos(latency.min)),
                ("mean_ns", nanos(latency.mean)),
                ("p50_ns", nanos(latency.p50)),
                ("p99_ns", nanos(latency.p99)),
                ("max_ns", nanos(latency.max)),
            ]);
            headers.insert(ShortStr::from_static("latency"), FieldValue::Table(latency));
        }
        headers
    }

    /// Reads an announcement from its headers; an error says what is
    /// missing or malformed (a foreign or damaged message).
    pub fn from_headers(headers: &FieldTable) -> std::result::Result<Self, DataError> {
        let fields = Fields(headers);
        let version = Fields::required(
            headers.get("version").and_then(FieldValue::as_i64),
            "version",
        )?;
        if version < 1 {
            return Err(DataError::Invalid(format!(
                "announcement version {version}"
            )));
        }
        let role = match Fields::required(fields.text("direction"), "direction")?.as_str() {
            "out" => PortRole::OutPort,
            "in" => PortRole::InPort,
            other => {
                return Err(DataError::Invalid(format!(
                    "announcement of a port neither out nor in: {other:?}"
                )))
            }
        };
        let state = match Fields::required(fields.text("state"), "state")?.as_str() {
            "up" => PortState::Up,
            "closed" => PortState::Closed,
            other => {
                return Err(DataError::Invalid(format!(
                    "announcement of a port in state {other:?}"
                )))
            }
        };
        let interval = Fields::required(
            fields.number("interval_ms").filter(|ms| *ms > 0),
            "interval_ms",
        )?;
        let content_type = fields.text_or_empty("content_type");
        let cdr = match (fields.text("cdr_endian"), fields.text("cdr_charset")) {
            (None, None) => None,
            (endian, charset) => Some(CdrOptions {
                endian: match endian.as_deref() {
                    Some("big") => Endian::Big,
                    _ => Endian::Little,
                },
                charset: match charset.as_deref() {
                    Some("latin-1") => Charset::Latin1,
                    _ => Charset::Utf8,
                },
            }),
        };
        let link = fields
            .table("link")
            .map_or_else(LinkStatus::default, |link| LinkStatus {
                up: link.flag("up"),
                degraded: link.flag("degraded"),
                connects: link.number("connects").unwrap_or(0),
                losses: link.number("losses").unwrap_or(0),
                last_error: link.text("last_error"),
            });
        let stats = match headers.get("stats") {
            Some(FieldValue::Table(stats)) => stats
                .iter()
                .filter_map(|(name, value)| {
                    let value = u64::try_from(value.as_i64()?).ok()?;
                    Some((name.as_str()?.to_owned(), value))
                })
                .take(MAX_COUNTERS)
                .collect(),
            _ => Vec::new(),
        };
        let latency = fields.table("latency").and_then(|latency| {
            let ns = |key| latency.number(key).map(Duration::from_nanos);
            Some(LatencySummary {
                count: latency.number("count")?,
                min: ns("min_ns")?,
                mean: ns("mean_ns")?,
                p50: ns("p50_ns")?,
                p99: ns("p99_ns")?,
                max: ns("max_ns")?,
            })
        });
        Ok(PortAnnouncement {
            id: Fields::required(fields.text("port").filter(|id| !id.is_empty()), "port")?,
            name: Fields::required(fields.text("name"), "name")?,
            role,
            state,
            interval: Duration::from_millis(interval),
            sent_ns: Fields::required(
                headers.get("sent_ns").and_then(FieldValue::as_i64),
                "sent_ns",
            )?,
            data_type: fields.text_or_empty("data_type"),
            content_type,
            cdr,
            exchange: fields.text_or_empty("exchange"),
            exchange_kind: exchange_kind_of(&fields.text_or_empty("exchange_type")),
            key: fields.text_or_empty(match role {
                PortRole::OutPort => "routing_key",
                PortRole::InPort => "binding_key",
            }),
            queue: fields.text_or_empty("queue"),
            confirms: fields.flag("confirms"),
            durable: fields.flag("durable"),
            lifespan: fields.number("lifespan_ms").map(Duration::from_millis),
            backpressure: fields
                .text("backpressure")
                .as_deref()
                .and_then(backpressure_of),
            replay: fields.text("replay").as_deref().and_then(replay_of),
            window: fields.number("window"),
            full_policy: fields
                .text("full_policy")
                .as_deref()
                .and_then(full_policy_of),
            buffer: fields.number("buffer"),
            prefetch: fields.number("prefetch"),
            link,
            stats,
            latency,
        })
    }
}

/// A port's counters as they go into its announcements.
pub(crate) trait AnnouncedStats: Clone + Send + Sync + 'static {
    /// Every counter, by its field name, in the struct's order.
    fn counters(&self) -> Vec<(&'static str, u64)>;

    /// The latencies, for a port that measures them.
    fn latency(&self) -> Option<LatencySummary>;
}

impl AnnouncedStats for OutPortStats {
    fn counters(&self) -> Vec<(&'static str, u64)> {
        vec![
            ("accepted", self.accepted),
            ("confirmed", self.confirmed),
            ("sent_unconfirmed", self.sent_unconfirmed),
            ("rejected", self.rejected),
            ("unroutable", self.unroutable),
            ("dropped_unsent", self.dropped_unsent),
            ("expired", self.expired),
            ("lost", self.lost),
            ("pending", self.pending),
            ("in_flight", self.in_flight),
            ("resent", self.resent),
            ("send_full", self.send_full),
            ("stalls", self.stalls),
            ("returned_after_send", self.returned_after_send),
        ]
    }

    fn latency(&self) -> Option<LatencySummary> {
        None
    }
}

impl AnnouncedStats for InPortStats {
    fn counters(&self) -> Vec<(&'static str, u64)> {
        vec![
            ("arrived", self.arrived),
            ("received", self.received),
            ("buffered", self.buffered),
            ("stale", self.stale),
            ("decode_errors", self.decode_errors),
            ("dropped", self.dropped),
            ("skipped", self.skipped),
            ("duplicates", self.duplicates),
            ("out_of_order", self.out_of_order),
            ("lost", self.lost),
        ]
    }

    fn latency(&self) -> Option<LatencySummary> {
        Some(LatencySummary::of(&self.latency))
    }
}

/// The name of every counter a port of this version announces (out-ports'
/// then in-ports', each once), for tools that list them as columns before
/// any port is heard.
pub fn announced_counters() -> Vec<&'static str> {
    let mut names: Vec<&'static str> = Vec::new();
    let all = OutPortStats::default()
        .counters()
        .into_iter()
        .chain(InPortStats::default().counters());
    for (name, _) in all {
        if !names.contains(&name) {
            names.push(name);
        }
    }
    names
}

/// The `connection_name` of a port's connection: `leveret port out NAME`.
pub(crate) fn connection_name(role: PortRole, profile: &PortProfile) -> String {
    format!(
        "leveret port {} {}",
        role.direction(),
        profile.port_name(role)
    )
}

/// Opens a channel on which [`PORTS_EXCHANGE`] exists: declared as ports
/// declare it, or, if it exists with other properties (the declaration
/// then fails and closes the channel), found passively on a new channel.
async fn ports_channel(connection: &Connection) -> Result<Channel> {
    let channel = connection.open_channel().await?;
    let declared = channel
        .exchange_declare(
            PORTS_EXCHANGE,
            ExchangeKind::Topic.as_str(),
            ExchangeDeclareOptions::default(),
            FieldTable::new(),
        )
        .await;
    match declared {
        Ok(()) => Ok(channel),
        Err(Error::ChannelClosed(reason)) => {
            tracing::debug!(%reason, "{PORTS_EXCHANGE} exists with other properties; using it as it is");
            let channel = connection.open_channel().await?;
            let passive = ExchangeDeclareOptions {
                passive: true,
                ..Default::default()
            };
            channel
                .exchange_declare(
                    PORTS_EXCHANGE,
                    ExchangeKind::Topic.as_str(),
                    passive,
                    FieldTable::new(),
                )
                .await?;
            Ok(channel)
        }
        Err(error) => Err(error),
    }
}

/// What a port and its announcer share.
#[derive(Debug)]
struct Handoff {
    /// The port's connection, each time its link comes up; the announcer
    /// takes it, so nothing here keeps a connection open.
    connection: Mutex<Option<Connection>>,
    /// Signals a new connection in `connection`.
    arrived: Notify,
}

impl Handoff {
    fn slot(&self) -> std::sync::MutexGuard<'_, Option<Connection>> {
        self.connection.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn give(&self, connection: &Connection) {
        *self.slot() = Some(connection.clone());
        self.arrived.notify_one();
    }

    fn take(&self) -> Option<Connection> {
        self.slot().take()
    }

    fn is_waiting(&self) -> bool {
        self.slot().is_some()
    }
}

/// A port's announcer: its task, and the port's side of the hooks. A
/// disabled one (no interval) does nothing.
#[derive(Debug)]
pub(crate) struct Announcer {
    running: Option<Running>,
}

#[derive(Debug)]
struct Running {
    handoff: Arc<Handoff>,
    stop: watch::Sender<bool>,
    task: JoinHandle<()>,
}

impl Announcer {
    /// Starts announcing the port `id` of data type `T` (see
    /// `PortAnnouncement::describe` for `queue`) with the counters `stats`
    /// and `link` carry, if its profile has an interval.
    pub(crate) fn start<T: PortData, S: AnnouncedStats>(
        role: PortRole,
        profile: &PortProfile,
        id: &str,
        queue: Option<&str>,
        stats: watch::Receiver<S>,
        link: watch::Receiver<LinkStatus>,
    ) -> Self {
        let port = PortAnnouncement::describe::<T>(role, profile, id, queue);
        if port.interval.is_zero() {
            return Announcer { running: None };
        }
        let handoff = Arc::new(Handoff {
            connection: Mutex::new(None),
            arrived: Notify::new(),
        });
        let (stop, stopped) = watch::channel(false);
        let task = Task {
            port,
            stats,
            link,
            handoff: Arc::clone(&handoff),
            stop: stopped,
        };
        Announcer {
            running: Some(Running {
                handoff,
                stop,
                task: tokio::spawn(task.run()),
            }),
        }
    }

    /// The port's link is up on `connection` (call it after marking the
    /// link up): announce there now, then every interval while it is up.
    pub(crate) fn link_up(&self, connection: &Connection) {
        if let Some(running) = &self.running {
            running.handoff.give(connection);
        }
    }

    /// The port is closing: announce `closed` if the link is up, within
    /// [`CLOSE_TIMEOUT`], and stop. Call it before closing the connection.
    pub(crate) async fn close(&mut self) {
        if let Some(mut running) = self.running.take() {
            running.stop.send_replace(true);
            if tokio::time::timeout(CLOSE_TIMEOUT, &mut running.task)
                .await
                .is_err()
            {
                running.task.abort();
            }
        }
    }
}

impl Drop for Announcer {
    fn drop(&mut self) {
        if let Some(running) = &self.running {
            running.task.abort();
        }
    }
}

/// Why the announcer left a link.
enum Left {
    /// The port is closing.
    Stopped,
    /// The link went down, or announcing on it failed.
    LinkDown,
    /// The port came up on a new connection (waiting in the handoff).
    NewLink,
}

struct Task<S> {
    /// The port's identity and profile; its state, counters and link are
    /// filled in for each announcement.
    port: PortAnnouncement,
    stats: watch::Receiver<S>,
    link: watch::Receiver<LinkStatus>,
    handoff: Arc<Handoff>,
    stop: watch::Receiver<bool>,
}

impl<S: AnnouncedStats> Task<S> {
    async fn run(mut self) {
        let mut waiting = false;
        loop {
            if !waiting {
                tokio::select! {
                    () = until(&mut self.stop, |stop| *stop) => return,
                    () = self.handoff.arrived.notified() => {}
                }
            }
            waiting = false;
            let Some(connection) = self.handoff.take() else {
                continue;
            };
            if !self.link.borrow_and_update().up {
                // Gone down again before it came to us.
                continue;
            }
            match self.announce_on(&connection).await {
                Left::Stopped => return,
                Left::LinkDown => {}
                Left::NewLink => waiting = true,
            }
        }
    }

    /// Announces on `connection` until the link goes down or the port
    /// closes.
    async fn announce_on(&mut self, connection: &Connection) -> Left {
        let opened = tokio::select! {
            () = until(&mut self.stop, |stop| *stop) => return Left::Stopped,
            opened = ports_channel(connection) => opened,
        };
        let channel = match opened {
            Ok(channel) => channel,
            Err(error) => {
                tracing::warn!(%error, port = %self.port.name, "port announcements off until the next link");
                return Left::LinkDown;
            }
        };
        let mut ticks = tokio::time::interval(self.port.interval);
        ticks.set_missed_tick_behavior(MissedTickBehavior::Delay);
        loop {
            tokio::select! {
                () = until(&mut self.stop, |stop| *stop) => {
                    let (key, properties) = self.announcement(PortState::Closed);
                    let farewell = async {
                        let _ = publish(&channel, &key, properties).await;
                        // Its close-ok says the broker has routed the farewell.
                        let _ = channel.close().await;
                    };
                    let _ = tokio::time::timeout(CLOSE_TIMEOUT, farewell).await;
                    return Left::Stopped;
                }
                changed = self.link.changed() => {
                    if changed.is_err() || !self.link.borrow_and_update().up {
                        return Left::LinkDown;
                    }
                }
                () = self.handoff.arrived.notified() => {
                    if self.handoff.is_waiting() {
                        return Left::NewLink;
                    }
                }
                _ = ticks.tick() => {
                    let (key, properties) = self.announcement(PortState::Up);
                    let published = tokio::select! {
                        published = publish(&channel, &key, properties) => published,
                        // The link went down while the outbox was full.
                        () = until(&mut self.link, |link| !link.up) => return Left::LinkDown,
                        () = until(&mut self.stop, |stop| *stop) => continue,
                    };
                    if let Err(error) = published {
                        tracing::debug!(%error, port = %self.port.name, "port announcement failed");
                        return Left::LinkDown;
                    }
                }
            }
        }
    }

    /// The routing key and properties of an announcement of the port as
    /// it is now.
    fn announcement(&mut self, state: PortState) -> (String, BasicProperties) {
        let stats = self.stats.borrow().clone();
        let port = &mut self.port;
        port.state = state;
        port.sent_ns = link::now_ns();
        port.link = self.link.borrow().clone();
        port.stats = stats
            .counters()
            .into_iter()
            .map(|(name, value)| (name.to_owned(), value))
            .collect();
        port.latency = stats.latency();
        let expiration = port.interval.saturating_mul(3).as_millis().max(1);
        let properties = BasicProperties {
            kind: Some(ShortStr::from_static(ANNOUNCEMENT_TYPE)),
            delivery_mode: Some(1),
            timestamp: u64::try_from(port.sent_ns / 1_000_000_000).ok(),
            expiration: ShortStr::try_from(expiration.to_string()).ok(),
            headers: Some(port.to_headers()),
            ..Default::default()
        };
        (port.routing_key(), properties)
    }
}

/// Waits until `value` satisfies `condition`, or its sender is gone.
async fn until<T>(value: &mut watch::Receiver<T>, condition: impl FnMut(&T) -> bool) {
    let _ = value.wait_for(condition).await;
}

/// Publishes one announcement (not mandatory: nobody listening is fine).
async fn publish(channel: &Channel, key: &str, properties: BasicProperties) -> Result<()> {
    channel
        .basic_publish(
            PORTS_EXCHANGE,
            key,
            BasicPublishOptions::default(),
            properties,
            Bytes::new(),
        )
        .await
        .map(drop)
}

/// A port as last heard from.
#[derive(Debug)]
struct Heard {
    announcement: PortAnnouncement,
    at: Instant,
}

impl Heard {
    /// Whether it still counts as connected: not closed, heard from within
    /// three of its intervals.
    fn live(&self, now: Instant) -> bool {
        self.announcement.state == PortState::Up
            && now.duration_since(self.at) <= self.announcement.interval.saturating_mul(3)
    }
}

/// The ports connected to a broker, from their announcements: an
/// exclusive, server-named queue bound to [`PORTS_EXCHANGE`] with `#`,
/// and a table of the live ports (closed ones and ones not heard from for
/// three of their intervals are dropped), by instance id. The table holds
/// at most [`PortDirectory::CAPACITY`] ports; a new one beyond that
/// replaces the one heard from longest ago.
///
/// Call [`PortDirectory::next`] steadily, or [`PortDirectory::close`] it:
/// like any consumer of this client, once its buffer is full the client
/// stops reading its connection, which stalls everything else on it.
///
/// ```no_run
/// use leveret_ports::PortDirectory;
/// use leveret_client::Connection;
///
/// # async fn demo() -> leveret_client::Result<()> {
/// let connection = Connection::connect("amqp://guest:guest@localhost:5672/%2f").await?;
/// let mut directory = PortDirectory::watch(&connection).await?;
/// while let Some(port) = directory.next().await {
///     println!("{} {:?}: {:?}", port.name, port.role, port.stats);
/// }
/// # Ok(())
/// # }
/// ```
#[derive(Debug)]
pub struct PortDirectory {
    consumer: Consumer,
    ports: HashMap<String, Heard>,
    /// When ports no longer live last left the table.
    pruned: Instant,
}

impl PortDirectory {
    /// The most ports the table holds.
    pub const CAPACITY: usize = 4096;

    /// Starts listening on a channel of its own on `connection`,
    /// declaring [`PORTS_EXCHANGE`] if no port has yet.
    pub async fn watch(connection: &Connection) -> Result<PortDirectory> {
        let channel = ports_channel(connection).await?;
        let options = QueueDeclareOptions {
            exclusive: true,
            auto_delete: true,
            ..Default::default()
        };
        let queue = channel
            .queue_declare("", options, FieldTable::new())
            .await?;
        channel
            .queue_bind(
                &queue.name,
                PORTS_EXCHANGE,
                "#",
                QueueBindOptions::default(),
                FieldTable::new(),
            )
            .await?;
        let options = BasicConsumeOptions {
            no_ack: true,
            exclusive: true,
            ..Default::default()
        };
        let consumer = channel
            .basic_consume(&queue.name, "", options, FieldTable::new())
            .await?;
        Ok(PortDirectory {
            consumer,
            ports: HashMap::new(),
            pruned: Instant::now(),
        })
    }

    /// The next announcement (the table updated with it), skipping
    /// messages that are not announcements; `None` once the channel has
    /// ended.
    pub async fn next(&mut self) -> Option<PortAnnouncement> {
        loop {
            let delivery = self.consumer.next().await?;
            let Some(headers) = delivery.properties.headers.as_ref() else {
                tracing::debug!(routing_key = %delivery.routing_key.to_string_lossy(), "skipped a message without headers on {PORTS_EXCHANGE}");
                continue;
            };
            match PortAnnouncement::from_headers(headers) {
                Ok(announcement) => {
                    self.record(&announcement);
                    return Some(announcement);
                }
                Err(error) => {
                    tracing::debug!(%error, routing_key = %delivery.routing_key.to_string_lossy(), "skipped a message on {PORTS_EXCHANGE}");
                }
            }
        }
    }

    fn record(&mut self, announcement: &PortAnnouncement) {
        let now = Instant::now();
        if self.ports.len() >= Self::CAPACITY || now.duration_since(self.pruned) >= PRUNE_INTERVAL {
            self.ports.retain(|_, heard| heard.live(now));
            self.pruned = now;
        }
        if let Some(heard) = self.ports.get(&announcement.id) {
            if heard.announcement.sent_ns > announcement.sent_ns {
                return;
            }
        }
        if announcement.state == PortState::Closed {
            self.ports.remove(&announcement.id);
            return;
        }
        if self.ports.len() >= Self::CAPACITY && !self.ports.contains_key(&announcement.id) {
            let oldest = self
                .ports
                .iter()
                .min_by_key(|(_, heard)| heard.at)
                .map(|(id, _)| id.clone());
            if let Some(oldest) = oldest {
                self.ports.remove(&oldest);
            }
        }
        self.ports.insert(
            announcement.id.clone(),
            Heard {
                announcement: announcement.clone(),
                at: now,
            },
        );
    }

    /// The live ports, by name, then out-ports first, then id.
    pub fn ports(&self) -> Vec<&PortAnnouncement> {
        let now = Instant::now();
        let mut ports: Vec<&PortAnnouncement> = self
            .ports
            .values()
            .filter(|heard| heard.live(now))
            .map(|heard| &heard.announcement)
            .collect();
        ports.sort_by(|a, b| {
            (&a.name, a.role == PortRole::InPort, &a.id).cmp(&(
                &b.name,
                b.role == PortRole::InPort,
                &b.id,
            ))
        });
        ports
    }

    /// The live ports named `name`, out-ports first.
    pub fn named(&self, name: &str) -> Vec<&PortAnnouncement> {
        let mut ports = self.ports();
        ports.retain(|port| port.name == name);
        ports
    }

    /// Stops listening: closes its channel, which deletes its queue.
    pub async fn close(self) {
        let _ = self.consumer.channel().close().await;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_counter_of_either_kind_of_port_is_listed_once() {
        let names = announced_counters();
        for (name, _) in OutPortStats::default()
            .counters()
            .into_iter()
            .chain(InPortStats::default().counters())
        {
            assert_eq!(names.iter().filter(|n| **n == name).count(), 1, "{name}");
        }
    }
    use crate::TimedPose2D;

    fn sample(role: PortRole) -> PortAnnouncement {
        let profile = PortProfile::default()
            .exchange("poses", ExchangeKind::Fanout)
            .routing_key("robot1")
            .binding_key("#")
            .lifespan(Duration::from_millis(250));
        let queue = (role == PortRole::InPort).then_some("q");
        let mut port = PortAnnouncement::describe::<TimedPose2D>(role, &profile, "1.2.3", queue);
        port.sent_ns = 42;
        port.link = LinkStatus {
            up: true,
            connects: 2,
            losses: 1,
            last_error: Some("cut".into()),
            ..LinkStatus::default()
        };
        port.stats = vec![("accepted".into(), 7), ("confirmed".into(), 6)];
        if role == PortRole::InPort {
            port.latency = Some(LatencySummary {
                count: 3,
                min: Duration::from_nanos(1),
                mean: Duration::from_nanos(2),
                p50: Duration::from_nanos(2),
                p99: Duration::from_nanos(3),
                max: Duration::from_nanos(3),
            });
        }
        port
    }

    #[test]
    fn announcements_round_trip_through_their_headers() {
        for role in [PortRole::OutPort, PortRole::InPort] {
            let port = sample(role);
            assert_eq!(
                PortAnnouncement::from_headers(&port.to_headers()),
                Ok(port.clone())
            );
        }
        let out = sample(PortRole::OutPort);
        assert_eq!(out.name, "poses/robot1");
        assert_eq!(out.routing_key(), "out.poses/robot1");
        assert_eq!(out.cdr, Some(CdrOptions::default()));
        let headers = out.to_headers();
        assert_eq!(
            headers.get("backpressure").and_then(FieldValue::as_bytes),
            Some(&b"drop_oldest"[..])
        );
        assert!(headers.get("binding_key").is_none());
        let input = sample(PortRole::InPort);
        assert_eq!((input.name.as_str(), input.key.as_str()), ("poses/#", "#"));
        assert_eq!(input.window, None);
        assert_eq!(input.buffer, Some(128));
    }

    #[test]
    fn a_long_name_makes_a_short_routing_key() {
        let mut port = sample(PortRole::OutPort);
        port.name = "é".repeat(200);
        let key = port.routing_key();
        assert!(key.len() <= ShortStr::MAX_LEN && key.starts_with("out.é"));
        assert!(ShortStr::try_from(key.as_str()).is_ok());
    }

    #[test]
    fn damaged_announcements_are_refused_not_misread() {
        let good = sample(PortRole::InPort).to_headers();
        for key in [
            "version",
            "port",
            "name",
            "direction",
            "state",
            "interval_ms",
            "sent_ns",
        ] {
            let mut damaged = good.clone();
            damaged.remove(key);
            assert!(
                PortAnnouncement::from_headers(&damaged).is_err(),
                "without {key}"
            );
            damaged.insert(
                ShortStr::try_from(key).unwrap(),
                FieldValue::Table(FieldTable::new()),
            );
            assert!(
                PortAnnouncement::from_headers(&damaged).is_err(),
                "{key} a table"
            );
        }
        for (key, value) in [
            ("direction", text("sideways")),
            ("state", text("asleep")),
            ("interval_ms", FieldValue::I64(0)),
            ("interval_ms", FieldValue::I64(-5)),
            ("version", FieldValue::I64(0)),
            ("name", FieldValue::LongStr(Bytes::from_static(b"\xff\xfe"))),
        ] {
            let mut damaged = good.clone();
            damaged.insert(ShortStr::from_static(key), value.clone());
            assert!(
                PortAnnouncement::from_headers(&damaged).is_err(),
                "{key} = {value:?}"
            );
        }
        // Damaged optional fields are dropped, the rest kept.
        let mut odd = good.clone();
        odd.insert(
            ShortStr::from_static("stats"),
            FieldValue::Table(table([
                ("received", FieldValue::I64(-1)),
                ("lost", text("many")),
                ("stale", FieldValue::I64(4)),
            ])),
        );
        odd.insert(ShortStr::from_static("latency"), FieldValue::I64(3));
        odd.insert(ShortStr::from_static("link"), text("up"));
        let read = PortAnnouncement::from_headers(&odd).expect("the required fields are there");
        assert_eq!(read.stats, [("stale".to_owned(), 4)]);
        assert_eq!((read.latency, read.link), (None, LinkStatus::default()));
    }
}
