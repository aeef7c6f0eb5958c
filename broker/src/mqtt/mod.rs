//! MQTT 3.1.1 and 5.0 on the same broker, as a front end over the one
//! core: each MQTT session drives the core through an in-process AMQP
//! connection of its own (`link`), as RabbitMQ's MQTT plugin did through
//! its direct connection, so routing, queues, permissions, limits,
//! confirms and acks are the AMQP side's. Publishes go to `amq.topic`;
//! each subscribing session owns a queue per QoS bound there
//! (`mapping`). `docs/mqtt.md` says what is supported.
//!
//! Layout: this file is the listener's accept loop; `session` one
//! connection (CONNECT, keepalive, the packet loop); `link` the AMQP side
//! of a session (login, channel, the methods it sends); `mapping` names
//! (topics ↔ routing keys, queue names, `vhost:user`); `takeover` the
//! client identifiers in use; `retained` the retained messages;
//! `releases` persistent sessions' QoS 2 publishes awaiting PUBREL;
//! `properties` 5.0 PUBLISH properties ↔ AMQP properties;
//! `subscriptions` a session's subscriptions, their 5.0 options and
//! shared subscriptions; `aliases` inbound topic aliases; `wills` last
//! wills and their delay.

mod aliases;
mod link;
mod mapping;
mod properties;
mod releases;
mod retained;
mod session;
mod subscriptions;
mod takeover;
mod wills;

pub(crate) use retained::Retained;
pub use retained::RetainedLimits;
use takeover::ClientIds;

use crate::core::Core;
use std::sync::Arc;
use tokio::net::TcpListener;

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
    /// Wills waiting for their delay.
    wills: wills::Wills,
}

impl Shared {
    pub(crate) fn new(anonymous: Option<(String, String)>, retained: Retained) -> Self {
        Shared {
            ids: Arc::default(),
            anonymous,
            retained,
            releases: Default::default(),
            wills: Default::default(),
        }
    }
}

/// Accepts MQTT connections until the broker shuts down; each session
/// holds a clone of `alive`, as AMQP connections do.
pub(crate) async fn accept_loop(
    core: Arc<Core>,
    listener: TcpListener,
    shared: Arc<Shared>,
    alive: tokio::sync::mpsc::Sender<()>,
) {
    let mut shutdown = core.shutdown_signal();
    // Counted with the AMQP connections against max_connections.
    while let Some((socket, peer, slot)) =
        crate::server::next_admitted(&core, &listener, &mut shutdown).await
    {
        let core = Arc::clone(&core);
        let shared = Arc::clone(&shared);
        let alive = alive.clone();
        tokio::spawn(async move {
            session::serve(core, socket, peer, slot, shared).await;
            drop(alive);
        });
    }
}
