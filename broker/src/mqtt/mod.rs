//! MQTT 3.1.1 and 5.0 on the same broker, as a front end over the one
//! core: each MQTT session drives the core through an in-process AMQP
//! connection of its own (`link`), as RabbitMQ's MQTT plugin did through
//! its direct connection, so routing, queues, permissions, limits,
//! confirms and acks are the AMQP side's. Publishes go to `amq.topic`;
//! each subscribing session owns a queue per QoS bound there
//! (`mapping`). `docs/mqtt.md` says what is supported.
//!
//! Layout: this file is the listeners' accept loop (TCP, TLS, WebSocket:
//! the transport's handshake, then a session over its byte stream);
//! `websocket` the WebSocket handshake and byte-stream adapter;
//! `client_stream` what a session needs of its transport, and its bytes
//! counted; `session` one connection (CONNECT, keepalive, the packet
//! loop); `link` the AMQP side of a session (login, channel, the methods
//! it sends); `mapping` names (topics ↔ routing keys, queue names,
//! `vhost:user`); `vhosts` the vhost a session lives in (the port and
//! certificate mappings); `takeover` the client identifiers in use;
//! `retained` the retained messages; `releases` persistent sessions' QoS 2
//! publishes awaiting PUBREL; `shares` persistent sessions' shared
//! subscriptions and their groups' hold on their queues; [`sweeper`] the
//! expiry of what those two keep; `properties` 5.0 PUBLISH properties ↔ AMQP properties;
//! `subscriptions` a session's subscriptions, their 5.0 options and shared
//! subscriptions; `expiry` a persistent session's expiry on its queues;
//! `aliases` inbound topic aliases; `wills` last wills and their delay.

mod aliases;
mod client_stream;
mod expiry;
mod link;
mod mapping;
mod properties;
mod releases;
mod retained;
mod session;
mod shares;
mod subscriptions;
mod takeover;
mod vhosts;
mod websocket;
mod wills;

use retained::Retained;
pub use retained::RetainedLimits;
use takeover::ClientIds;

use crate::core::Core;
use crate::store::MetaRecord;
use std::sync::Arc;
use tokio::net::{TcpListener, TcpStream};

/// What a broker's MQTT listeners share.
#[derive(Debug)]
pub(crate) struct Shared {
    /// The client identifiers in use.
    ids: Arc<ClientIds>,
    /// The user and password a CONNECT without a user name logs in as
    /// (RabbitMQ's `mqtt.allow_anonymous` with `mqtt.default_user` and
    /// `default_pass`); without one such a CONNECT is refused.
    anonymous: Option<(String, String)>,
    /// Retained messages, per vhost.
    retained: Retained,
    /// Persistent sessions' QoS 2 publishes awaiting PUBREL.
    releases: releases::Releases,
    /// Persistent sessions' shared subscriptions.
    shares: shares::Shares,
    /// Whether a client on a TLS listener with a verified certificate and
    /// no user name logs in as the certificate's common name (RabbitMQ's
    /// `mqtt.ssl_cert_login`).
    certificate_login: bool,
    /// The longest Session Expiry Interval a session is given (s; `None`:
    /// no cap but the queues' own, RabbitMQ's `infinity`): a 5.0 session's
    /// is at most this, a 3.1.1 persistent session's is this (as RabbitMQ
    /// 3.13), and so is at most a session's restored from the store;
    /// RabbitMQ's `mqtt.max_session_expiry_interval_seconds`, a day by
    /// default ([`expiry::capped`]).
    max_session_expiry: Option<u32>,
    /// Wills waiting for their delay.
    wills: wills::Wills,
}

impl Shared {
    /// What the listeners share; `recovered` is the store's metadata
    /// (retained messages, unreleased QoS 2 publishes and persistent
    /// sessions' shared subscriptions come from it).
    pub(crate) fn new(
        core: &Core,
        recovered: &[MetaRecord],
        options: Options,
        retained_limits: RetainedLimits,
    ) -> Self {
        let (persistence, max) = (&core.persistence, options.max_session_expiry);
        Shared {
            ids: Arc::default(),
            anonymous: options.anonymous,
            retained: Retained::new(
                recovered,
                Arc::clone(&core.gauge),
                core.persistence.clone(),
                retained_limits,
            ),
            releases: releases::Releases::new(recovered, persistence.clone(), max),
            shares: shares::Shares::new(recovered, persistence.clone(), max),
            certificate_login: options.certificate_login,
            max_session_expiry: options.max_session_expiry,
            wills: Default::default(),
        }
    }

    /// Gives the persistent sessions recovered from the store the session
    /// expiry cap, every part of each written back
    /// ([`write_back_restored`]): once at start, after the queues are
    /// rebuilt and before anything sweeps them.
    pub(crate) async fn reconcile_queues(&self, core: &Core) {
        let max = self.max_session_expiry;
        write_back_restored(&self.releases, &self.shares, &core.vhosts(), max).await;
    }
}

/// Gives the persistent sessions recovered from the store (QoS 2 records
/// `releases`, shared subscriptions `shares`, queues in `vhosts`) the
/// session expiry cap `max`, every part of each written back: their QoS 2
/// records ([`releases::Releases::settle_yielding`]), their shared
/// subscriptions, with the groups' queues their groups' expiry
/// ([`shares::Shares::reconcile`]), then their own queues
/// ([`expiry::cap_restored_queues`]); yielding between bounded steps.
///
/// Records before queues: the store keeps submission order, so a crash
/// part way leaves some records capped beside queues that are not, never
/// queues capped beside records that are not. A later start under a
/// raised cap can then keep a queue longer than its records (the session
/// found, its QoS 2 and shared subscription state gone first, as when
/// they expire before it), but never records after their queue has gone
/// (a session found from its records alone, with no queue, and records
/// kept for ever under `infinity`).
async fn write_back_restored(
    releases: &releases::Releases,
    shares: &shares::Shares,
    vhosts: &[Arc<crate::vhost::Vhost>],
    max: Option<u32>,
) {
    // `holds` reads which sessions have records, not their expiry, so the
    // write-back before it changes nothing it sees.
    releases.settle_yielding().await;
    shares.reconcile(vhosts).await;
    let holds = |vhost: &str, client_id: &str| {
        releases.holds(vhost, client_id) || shares.holds(vhost, client_id)
    };
    let capped = expiry::cap_restored_queues(vhosts, max, holds).await;
    if capped > 0 {
        tracing::info!(
            queues = capped,
            max_seconds = max,
            "MQTT sessions' queues restored with a longer expiry (or none) given the session expiry cap"
        );
    }
}

/// How often [`sweeper`] looks for expired sessions' state.
const SESSION_SWEEP_PERIOD: std::time::Duration = std::time::Duration::from_secs(1);

/// At most this many expired sessions' state is deleted under one lock
/// (each holds at most 256 unreleased publishes or 4,096 shared
/// subscriptions); [`sweeper`] yields between batches.
const SWEEP_BATCH: usize = 16;

/// Deletes, until the broker shuts down, the state persistent sessions
/// kept beside their queues once their Session Expiry Interval has passed
/// (their unreleased QoS 2 publishes, their shared subscriptions and so
/// their groups' hold on their queues), from the store too, so that a
/// session that never comes back leaves nothing behind.
pub(crate) async fn sweeper(core: Arc<Core>, shared: Arc<Shared>) {
    let mut shutdown = core.shutdown_signal();
    let mut ticks = tokio::time::interval(SESSION_SWEEP_PERIOD);
    ticks.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = ticks.tick() => {}
            _ = shutdown.wait_for(|down| *down) => return,
        }
        // Sessions whose interval changed, moved on even if none connects.
        shared.shares.settle_yielding(&core).await;
        loop {
            let releases = shared.releases.sweep();
            let (shares, groups, more) = shared.shares.sweep();
            if releases > 0 || shares > 0 {
                tracing::debug!(
                    releases,
                    shares,
                    groups = groups.len(),
                    "expired MQTT sessions' state deleted"
                );
            }
            shared.shares.apply_yielding(&core, groups).await;
            if releases < SWEEP_BATCH && !more {
                break;
            }
            tokio::task::yield_now().await;
        }
    }
}

/// How a broker's MQTT clients log in beyond a user name and password,
/// and how long their sessions may outlive their connections.
#[derive(Debug, Clone)]
pub(crate) struct Options {
    /// See [`Shared::anonymous`].
    pub anonymous: Option<(String, String)>,
    /// See [`Shared::certificate_login`].
    pub certificate_login: bool,
    /// See [`Shared::max_session_expiry`].
    pub max_session_expiry: Option<u32>,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            anonymous: None,
            certificate_login: false,
            max_session_expiry: Some(expiry::DEFAULT_MAX_SECONDS),
        }
    }
}

/// What an MQTT listener's connections travel over.
#[derive(Debug, Clone)]
pub(crate) enum Transport {
    /// Plain TCP (RabbitMQ's `mqtt.listeners.tcp`, 1883).
    Tcp,
    /// TLS with the broker's TLS settings (`mqtt.listeners.ssl`, 8883).
    #[cfg(feature = "tls")]
    Tls(Arc<crate::tls::TlsContext>),
    /// WebSocket, path `/ws`, subprotocol `mqtt` (RabbitMQ's
    /// `web_mqtt.tcp.port`, 15675).
    WebSocket,
}

/// Accepts MQTT connections over `transport` until the broker shuts
/// down; each session holds a clone of `alive`, as AMQP connections do.
pub(crate) async fn accept_loop(
    core: Arc<Core>,
    listener: TcpListener,
    transport: Transport,
    shared: Arc<Shared>,
    alive: tokio::sync::mpsc::Sender<()>,
) {
    let mut shutdown = core.shutdown_signal();
    // Counted with the AMQP connections against max_connections.
    while let Some((socket, peer, slot)) =
        crate::server::next_admitted(&core, &listener, &mut shutdown).await
    {
        let port = socket.local_addr().map(|a| a.port()).unwrap_or_default();
        let origin = session::Origin {
            peer,
            port,
            certificate: None,
        };
        let arrival = Box::new(session::Arrival {
            socket,
            origin,
            slot,
            alive: alive.clone(),
        });
        let (core, shared) = (Arc::clone(&core), Arc::clone(&shared));
        // Each transport's future is spawned as it is: a layer around
        // them would keep room for its own arguments through the session.
        match &transport {
            Transport::Tcp => tokio::spawn(session::serve(core, shared, arrival)),
            #[cfg(feature = "tls")]
            Transport::Tls(tls) => tokio::spawn(serve_tls(core, shared, Arc::clone(tls), arrival)),
            Transport::WebSocket => tokio::spawn(serve_websocket(core, shared, arrival)),
        };
    }
}

/// The TLS handshake (a boxed future, freed once done), then the session
/// over the TLS stream, in the task's own future: each transport's task is
/// spawned as it is, so a TCP session's holds no room for a TLS stream.
#[cfg(feature = "tls")]
async fn serve_tls(
    core: Arc<Core>,
    shared: Arc<Shared>,
    tls: Arc<crate::tls::TlsContext>,
    arrival: Box<session::Arrival<TcpStream>>,
) {
    let (socket, mut rest) = arrival.take_socket();
    let handshake = tls.acceptor().accept(socket);
    let peer = &rest.origin.peer;
    let Some(stream) = Box::pin(handshaken(&core, peer, "TLS", handshake)).await else {
        return;
    };
    rest.origin.certificate = stream
        .get_ref()
        .1
        .peer_certificates()
        .and_then(|chain| chain.first())
        .map(|certificate| session::ClientCertificate {
            common_name: crate::tls::common_name(certificate),
            subject: crate::tls::subject(certificate),
        });
    session::serve(core, shared, rest.carrying(stream)).await;
}

/// The WebSocket handshake, then the session over the WebSocket stream
/// (as over TLS).
async fn serve_websocket(
    core: Arc<Core>,
    shared: Arc<Shared>,
    arrival: Box<session::Arrival<TcpStream>>,
) {
    let (socket, rest) = arrival.take_socket();
    let max_message = session::max_packet(&core.limits) as usize;
    let handshake = websocket::accept(socket, max_message);
    let peer = &rest.origin.peer;
    let Some(stream) = Box::pin(handshaken(&core, peer, "WebSocket", handshake)).await else {
        return;
    };
    session::serve(core, shared, rest.carrying(stream)).await;
}

/// A transport's `handshake` (TLS, WebSocket: `what`) within the
/// handshake timeout; `None`, logged, if it failed or took too long.
/// Callers box it, so that its state is freed once it is done instead of
/// staying in the session's task for the session's life.
async fn handshaken<S, E: std::fmt::Display>(
    core: &Core,
    peer: &str,
    what: &str,
    handshake: impl std::future::Future<Output = Result<S, E>>,
) -> Option<S> {
    match tokio::time::timeout(core.limits.handshake_timeout, handshake).await {
        Ok(Ok(stream)) => Some(stream),
        Ok(Err(e)) => {
            tracing::info!(%peer, error = %e, "MQTT {what} handshake failed");
            None
        }
        Err(_) => {
            tracing::warn!(%peer, "MQTT {what} handshake not completed within the handshake timeout");
            None
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::Store;
    use crate::testkit::RecordingStore;

    /// A crash part way through the start-up write-back leaves records
    /// capped beside queues that are not, never the other way round: the
    /// store is asked for every record (QoS 2: `aq`, shared subscription:
    /// `as`) before any queue (`q`).
    #[tokio::test]
    async fn at_start_a_sessions_records_are_written_back_before_its_queue() {
        let store = Arc::new(RecordingStore::default());
        let h = crate::testkit::Harness::durable_over(Arc::clone(&store) as Arc<dyn Store>);
        let persistence = h.persistence.clone().expect("a store");
        // An older Leveret's 3.1.1 session: unmarked queue, no expiry.
        h.declare_queue("mqtt-subscription-devqos1", true, &[]);
        assert!(persistence.sync().await);
        let before = store.written().len();
        let (vhost, client_id) = ("/".to_owned(), "dev".to_owned());
        let recovered = [
            MetaRecord::Unreleased {
                vhost: vhost.clone(),
                client_id: client_id.clone(),
                packet_id: 1,
                session_expiry: None,
            },
            MetaRecord::SharedSubscription {
                vhost,
                client_id,
                filter: "$share/g/t/#".to_owned(),
                qos: 1,
                retain_as_published: false,
                subscription_id: 0,
                session_expiry: u32::MAX,
            },
        ];
        let max = Some(60);
        let releases = releases::Releases::new(&recovered, Some(Arc::clone(&persistence)), max);
        let shares = shares::Shares::new(&recovered, Some(Arc::clone(&persistence)), max);
        write_back_restored(&releases, &shares, &[Arc::clone(&h.vhost)], max).await;
        assert!(persistence.sync().await);
        let written: Vec<Vec<u8>> = store.written()[before..]
            .iter()
            .map(|(key, _)| key.clone())
            .collect();
        let last_record = written
            .iter()
            .rposition(|key| key.starts_with(b"aq") || key.starts_with(b"as"));
        let first_queue = written.iter().position(|key| key.starts_with(b"q"));
        let kinds = |prefix: &[u8]| written.iter().filter(|k| k.starts_with(prefix)).count();
        assert_eq!((kinds(b"aq"), kinds(b"as"), kinds(b"q")), (1, 1, 1));
        assert!(last_record < first_queue, "{written:?}");
    }
}
