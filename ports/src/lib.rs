//! # leveret-ports
//!
//! Robot data ports over AMQP, after the AMQP data ports of OpenRTM-aist
//! (RT-Middleware): an [`OutPort`] publishes typed values, an [`InPort`]
//! receives them, wired through the exchange, queue and keys of a
//! [`PortProfile`] (OpenRTM's AMQP connector profile plus reliability
//! settings).
//!
//! Each port owns one connection (made by a [`Connector`]: TCP, or an
//! embedded Leveret in-process) and one task. Messages carry the out-port's
//! identity, a sequence number and the send time in headers, which the
//! in-port uses to drop duplicates and to count what the paper's
//! reliability experiment counts (received, lost, out of order), plus
//! latency. Both ports reconnect with backoff when the link drops and
//! declare their topology again; with publisher confirms the out-port
//! resends what the broker had not confirmed, so a control loop sees each
//! message once and in order across reconnections.
//!
//! A control loop's `put` never waits on the network: it enqueues into a
//! bounded window and returns; what becomes of each value, its [`Fate`],
//! is reported once ([`Outcome`], [`OutPortStats`]). The window also
//! bounds what is written and unconfirmed, and a broker that stops
//! confirming makes the link [`LinkState::Degraded`]. Freshness and reliability are set per
//! port: a lifespan, a [`Backpressure`] and a [`Replay`] policy, or a
//! [`Qos`] preset naming them together. An in-port without a queue name
//! gets a named queue of its own that outlives its reconnections. Every
//! port announces itself (name, type, profile, link, counters) on the
//! [`PORTS_EXCHANGE`], where a [`PortDirectory`] lists the ports of a
//! broker.
//!
//! ```no_run
//! use leveret_ports::{
//!     ExchangeKind, FullPolicy, InPort, OutPort, PortProfile, PortStatus, Time, TimedPose2D,
//! };
//!
//! # async fn demo() -> leveret_client::Result<()> {
//! let profile = PortProfile::new("amqp://guest:guest@localhost:5672/%2f")?
//!     .exchange("poses", ExchangeKind::Fanout)
//!     .buffer(100, FullPolicy::BlockBroker);
//! let input = InPort::<TimedPose2D>::connect(profile.clone()).await?;
//! let output = OutPort::<TimedPose2D>::connect(profile).await?;
//! let pose = TimedPose2D { tm: Time::now(), ..Default::default() };
//! assert_eq!(output.put(&pose).await, PortStatus::Ok);
//! let sample = input.recv().await.expect("port open");
//! println!("{:?} after {:?}; {:?}", sample.value, sample.latency, input.stats());
//! # Ok(())
//! # }
//! ```
//!
//! Built on `leveret-client`'s public API only: an out-port publishes
//! through room it reserves in its connection's outbox
//! ([`leveret_client::OutboxSlot`]), an in-port takes deliveries on the
//! connection's reader ([`leveret_client::DeliverySink`]).
//!
//! Features: `tls` (default) for `amqps://` profiles (the client's
//! `tls`); `embedded` for `Connector::in_process`, on `leveret-broker`
//! without its default features (the application names any it wants on
//! its own dependency); `serde` for `Postcard`. In-process ports alone
//! (`default-features = false, features = ["embedded"]`) build 44 crates
//! on Linux; with every default of this crate and the broker, 117
//! (`perf/crate-count`).
//!
//! Layout:
//! - `data`: [`PortData`] (value ⇄ body), its impls and [`DataError`].
//! - [`cdr`]: OMG CDR (either byte order) and the types of OpenRTM-aist's
//!   `BasicDataType.idl` and `ExtendedDataTypes.idl` (`RTC::Time`,
//!   `RTC::Timed*`, the 2D and 3D geometry), all re-exported here too;
//!   [`cdr::render`] shows a body by its type's name.
//! - `profile`: [`PortProfile`], [`ExchangeKind`], [`FullPolicy`],
//!   [`Backoff`], [`Connector`], [`Recording`].
//! - `openrtm`: [`PortProfile::from_properties`] (OpenRTM-aist connector
//!   properties), [`PortRole`], [`ConnectorProfile`].
//! - `link`: [`LinkStatus`], topology declaration, the headers.
//! - `out_port`: [`OutPort`], [`PortStatus`], [`OutPortStats`].
//! - `in_port`: [`InPort`], [`Sample`], [`InPortStats`].
//! - `spin`: how `InPort::recv_blocking` waits before it sleeps when the
//!   profile asks for it (a bounded adaptive spin, `PortProfile::spin`).
//! - `playback`: a port's [`Recording`] read back: [`Playback`] (records),
//!   [`Player`] (typed values), from a [`Position`] at a rate.
//! - `latency`: [`LatencyStats`] (min, max, mean and percentiles).
//! - `announce`: ports announcing themselves on [`PORTS_EXCHANGE`] (the
//!   wire contract), and [`PortDirectory`], which reads the
//!   announcements ([`PortAnnouncement`]).
#![deny(missing_docs)]
#![forbid(unsafe_code)]

mod announce;
pub mod cdr;
mod data;
mod in_port;
mod latency;
mod link;
mod openrtm;
mod out_port;
mod playback;
mod profile;
mod spin;

pub use announce::{
    announced_counters, LatencySummary, PortAnnouncement, PortDirectory, PortState,
    ANNOUNCEMENT_VERSION, PORTS_EXCHANGE,
};
// Every RTC data type is here as well as in `cdr` (a glob of the two
// type modules, one per OpenRTM-aist IDL file, so the list cannot go
// stale); the codec itself stays in `cdr`.
pub use cdr::basic::*;
pub use cdr::extended::*;
pub use cdr::interface::*;
pub use cdr::{CdrOptions, Charset, Endian, WString};
#[cfg(feature = "serde")]
pub use data::Postcard;
pub use data::{DataError, PortData};
pub use in_port::{InPort, InPortStats, Sample};
pub use latency::LatencyStats;
pub use link::{LinkState, LinkStatus, PORT_HEADER, SENT_HEADER, SEQ_HEADER};
pub use openrtm::{ConnectorProfile, PortRole};
pub use out_port::{Fate, OutPort, OutPortStats, Outcome, PortStatus};
pub use playback::{PlayOptions, Playback, Player, Position, Recorded, Replayed, OFFSET_HEADER};
pub use profile::{
    Backoff, Backpressure, Connector, ExchangeKind, FullPolicy, PortProfile, Qos, Recording, Replay,
};

/// The repository README's Rust examples, compiled as doc tests so they
/// stay as shown; the `docs/` pages' below, one struct per page. They are
/// compiled here, in the crate that sees the client, the ports and (with
/// `embedded`) the broker, which is what the examples use.
#[cfg(all(doctest, feature = "embedded"))]
#[doc = include_str!("../../README.md")]
pub struct ReadmeDoctests;
#[cfg(all(doctest, feature = "embedded"))]
#[doc = include_str!("../../docs/architecture.md")]
pub struct ArchitectureDoctests;
#[cfg(all(doctest, feature = "embedded"))]
#[doc = include_str!("../../docs/compatibility.md")]
pub struct CompatibilityDoctests;
#[cfg(all(doctest, feature = "embedded"))]
#[doc = include_str!("../../docs/configuration.md")]
pub struct ConfigurationDoctests;
#[cfg(all(doctest, feature = "embedded"))]
#[doc = include_str!("../../docs/mqtt.md")]
pub struct MqttDoctests;
#[cfg(all(doctest, feature = "embedded"))]
#[doc = include_str!("../../docs/operations.md")]
pub struct OperationsDoctests;
#[cfg(all(doctest, feature = "embedded"))]
#[doc = include_str!("../../docs/performance.md")]
pub struct PerformanceDoctests;
#[cfg(all(doctest, feature = "embedded"))]
#[doc = include_str!("../../docs/ports.md")]
pub struct PortsDoctests;
#[cfg(all(doctest, feature = "embedded"))]
#[doc = include_str!("../../docs/storage.md")]
pub struct StorageDoctests;
#[cfg(all(doctest, feature = "embedded"))]
#[doc = include_str!("../../docs/uplink.md")]
pub struct UplinkDoctests;
#[cfg(all(doctest, feature = "embedded"))]
#[doc = include_str!("../../docs/README.md")]
pub struct DocsIndexDoctests;
