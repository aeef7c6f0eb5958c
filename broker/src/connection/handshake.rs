//! The connection.* handshake, a function a step, all of it within the
//! handshake timeout (RabbitMQ's `handshake_timeout`, from the
//! connection's start to connection.open-ok): the protocol header
//! ([`protocol_header`]); connection.start with the mechanisms offered and
//! the client's start-ok with its capabilities ([`Connection::start`]);
//! the login by the mechanism it chose, PLAIN, AMQPLAIN or EXTERNAL on
//! TLS ([`Connection::log_in`]); tune and tune-ok, bounded as RabbitMQ
//! bounds them ([`Connection::tune`]); and open: the vhost, the user's
//! permission on it, the vhost's and the user's connection limits
//! ([`Connection::open`]). A step that fails says how the connection
//! ended; `mod` closes it. Uses the core (users, permissions, limits,
//! statistics, the registry) and the connection's reader and outbox.

use super::source::{FrameSource, ReadError};
use super::{copy_below, loggable, Connection, Ended, Identity, Sink};
use crate::admission;
use crate::core::Core;
use crate::error::AmqpError;
use crate::stats::AuthProtocol;
use crate::vhost::Vhost;
use bytes::Bytes;
use leveret_protocol::{
    ConnectionOpen, ConnectionOpenOk, ConnectionStart, ConnectionStartOk, ConnectionTune,
    ConnectionTuneOk, FieldTable, FieldValue, Frame, Method, ReplyCode, ShortStr, FRAME_MIN_SIZE,
};
use std::sync::Arc;
use std::time::Duration;
use tokio::time::Instant;

/// Why a handshake step did not finish.
#[derive(Debug, Clone, Copy)]
enum Interrupted {
    TimedOut,
    ShuttingDown,
}

/// Runs a step of the handshake until the handshake deadline; a client
/// still in the handshake then is logged and dropped, as RabbitMQ does.
async fn handshake_step<T>(
    core: &Core,
    deadline: Instant,
    peer: &str,
    step: impl std::future::Future<Output = T>,
) -> Result<T, Interrupted> {
    let mut shutdown = core.shutdown_signal();
    let stopping = async move {
        let _ = shutdown.wait_for(|down| *down).await;
    };
    tokio::select! {
        done = tokio::time::timeout_at(deadline, step) => done.map_err(|_| {
            tracing::warn!(
                %peer,
                timeout = ?core.limits.handshake_timeout,
                "closing connection: handshake not completed within the handshake timeout"
            );
            Interrupted::TimedOut
        }),
        _ = stopping => Err(Interrupted::ShuttingDown),
    }
}

/// Reads the protocol header by the handshake deadline: gives the sink
/// back when it is AMQP 0-9-1's; answers a wrong one with ours, and gives
/// nothing back then, nor when the client went away or was too slow.
pub(super) async fn protocol_header<S: FrameSource, K: Sink>(
    core: &Core,
    deadline: Instant,
    peer: &str,
    reader: &mut S,
    sink: K,
) -> Option<K> {
    match handshake_step(core, deadline, peer, reader.protocol_header()).await {
        Ok(Ok(true)) => Some(sink),
        Ok(Ok(false)) => {
            tracing::info!(%peer, "wrong protocol header; answering with ours and closing");
            sink.refuse().await;
            None
        }
        Ok(Err(_)) | Err(_) => None,
    }
}

/// Whether the client's start-ok claims the capability `name`.
fn capability(start_ok: &ConnectionStartOk, name: &str) -> bool {
    match start_ok.client_properties.get("capabilities") {
        Some(FieldValue::Table(capabilities)) => {
            matches!(capabilities.get(name), Some(FieldValue::Bool(true)))
        }
        _ => false,
    }
}

impl Connection {
    /// The handshake after the protocol header, from connection.start to
    /// open-ok, by the handshake deadline: a client still in it then is
    /// dropped; one in it when the broker shuts down is closed forced.
    pub(super) async fn handshake<R: FrameSource>(
        &mut self,
        reader: &mut R,
        deadline: Instant,
    ) -> Result<(), Ended> {
        let core = Arc::clone(&self.core);
        let peer = self.peer.clone();
        let steps = self.handshake_steps(reader);
        match handshake_step(&core, deadline, &peer, steps).await {
            Ok(done) => done,
            Err(Interrupted::TimedOut) => Err(Ended::Read(ReadError::TimedOut)),
            Err(Interrupted::ShuttingDown) => Err(Ended::Forced(
                self.core.registry.close_reason(self.connection_id),
            )),
        }
    }

    /// The steps in their order.
    async fn handshake_steps<R: FrameSource>(&mut self, reader: &mut R) -> Result<(), Ended> {
        let start_ok = self.start(reader).await?;
        self.log_in(reader, &start_ok).await?;
        let tune_ok = self.tune(reader).await?;
        self.open(reader, start_ok.client_properties, &tune_ok)
            .await
    }

    /// The next connection method, heartbeats passed over; any other
    /// frame is UNEXPECTED_FRAME.
    async fn expect_method<R: FrameSource>(&self, reader: &mut R) -> Result<Method, Ended> {
        loop {
            match reader.next().await {
                Ok(Frame::Method { channel: 0, method }) => return Ok(method),
                Ok(Frame::Heartbeat) => continue,
                Ok(other) => {
                    return Err(Ended::Protocol(AmqpError::new(
                        ReplyCode::UnexpectedFrame,
                        format_args!(
                            "expected a connection method during the handshake, got {other:?}"
                        ),
                    )))
                }
                Err(ReadError::Decode(e)) => {
                    return Err(Ended::Protocol(AmqpError::new(e.reply_code(), &e)))
                }
                Err(e) => return Err(e.into()),
            }
        }
    }

    /// Sends connection.start with the mechanisms this transport offers
    /// and takes the client's start-ok; the capabilities it claims for
    /// consumer cancel and blocked notifications apply from here on.
    async fn start<R: FrameSource>(&mut self, reader: &mut R) -> Result<ConnectionStartOk, Ended> {
        self.outbox
            .method(
                0,
                ConnectionStart {
                    version_major: 0,
                    version_minor: 9,
                    server_properties: self.core.server_properties.clone(),
                    // EXTERNAL on every TLS connection, as RabbitMQ with
                    // rabbitmq_auth_mechanism_ssl: without a certificate
                    // the login is refused, not the mechanism.
                    mechanisms: Bytes::from_static(match self.identity {
                        Identity::Tls(_) => b"PLAIN AMQPLAIN EXTERNAL",
                        Identity::None => b"PLAIN AMQPLAIN",
                    }),
                    locales: Bytes::from_static(b"en_US"),
                },
            )
            .await;
        let Method::ConnectionStartOk(start_ok) = self.expect_method(reader).await? else {
            return Err(Ended::Protocol(AmqpError::command_invalid(
                "expected connection.start-ok",
            )));
        };
        self.outbox
            .set_cancel_notify(capability(&start_ok, "consumer_cancel_notify"));
        self.blocked_notify = capability(&start_ok, "connection.blocked");
        Ok(start_ok)
    }

    /// Logs the client in by the mechanism its start-ok chose; the user
    /// it proves, if they may connect from this peer, becomes the
    /// connection's. A refused login is closed with ACCESS_REFUSED when
    /// the client asked for that (`authentication_failure_close`); other
    /// clients just see the socket closed.
    async fn log_in<R: FrameSource>(
        &mut self,
        reader: &mut R,
        start_ok: &ConnectionStartOk,
    ) -> Result<(), Ended> {
        let authenticated = match (&self.identity, start_ok.mechanism.as_bytes()) {
            // SASL EXTERNAL: the verified certificate's common name, which
            // must be a user (RabbitMQ's rabbitmq_auth_mechanism_ssl).
            (Identity::Tls(Some(name)), b"EXTERNAL") => {
                self.core.users.contains(name).then(|| name.clone())
            }
            (_, mechanism) => {
                let users = &self.core.users;
                let login = users.authenticate(mechanism, &start_ok.response, &self.peer);
                // A client that hangs up withdraws its check (see `hash_pool`).
                tokio::select! {
                    user = login => user,
                    _ = reader.hung_up() => return Err(Ended::PeerClosed),
                }
            }
        };
        let allowed = authenticated
            .as_ref()
            .is_some_and(|user| self.core.users.may_connect_from(user, &self.peer));
        // An MQTT session's login is counted by the front end, once the
        // vhost has let it in too (as RabbitMQ 3.10's plugin counts it).
        if self.kind != "MQTT" {
            self.core.stats.login(AuthProtocol::Amqp091, allowed);
        }
        let failure_close = capability(start_ok, "authentication_failure_close");
        match authenticated {
            Some(user) if !allowed => {
                let refusal = format!("user '{user}' can only connect via localhost");
                tracing::warn!(peer = %self.peer, %user, mechanism = %start_ok.mechanism, "{} login refused: {refusal}", start_ok.mechanism);
                if !failure_close {
                    return Err(Ended::Refused(refusal));
                }
                let error = AmqpError::access_refused(refusal);
                Err(Ended::Protocol(error))
            }
            Some(user) => {
                self.user = user;
                Ok(())
            }
            None => {
                let refusal = self.login_refused(&start_ok.mechanism, &start_ok.response);
                if !failure_close {
                    // Clients that did not ask for a close just see the
                    // socket closed, as with RabbitMQ.
                    return Err(Ended::Refused(refusal));
                }
                let error = AmqpError::access_refused(format_args!(
                    "Login was refused using authentication mechanism {}. For details see the broker logfile.",
                    start_ok.mechanism
                ));
                Err(Ended::Protocol(error))
            }
        }
    }

    /// Logs a refused login with the user name the client gave (the
    /// client is told to look in the broker's log) and returns why.
    fn login_refused(&self, mechanism: &ShortStr, response: &Bytes) -> String {
        let claimed = match (&self.identity, mechanism.as_bytes()) {
            (Identity::Tls(name), b"EXTERNAL") => name.as_deref().map(str::as_bytes).map(loggable),
            (_, mechanism) => {
                crate::access::auth::claimed_user(mechanism, response).map(|user| loggable(&user))
            }
        };
        let refusal = match (&claimed, mechanism.as_bytes()) {
            (Some(user), _) => format!("user '{user}' - invalid credentials"),
            (None, b"EXTERNAL") => "no client certificate".to_owned(),
            (None, b"PLAIN" | b"AMQPLAIN") => "malformed response".to_owned(),
            (None, _) => "unsupported mechanism".to_owned(),
        };
        let refusal = format!(
            "{} login refused: {refusal}",
            loggable(mechanism.as_bytes())
        );
        tracing::warn!(
            connection = self.connection_id,
            peer = %self.peer,
            mechanism = %loggable(mechanism.as_bytes()),
            user = claimed.as_deref(),
            "{refusal}"
        );
        refusal
    }

    /// Sends connection.tune with the broker's limits and takes the
    /// client's tune-ok, refused (NOT_ALLOWED) outside RabbitMQ's bounds;
    /// the negotiated frame_max, channel_max and heartbeat apply to the
    /// reader and the outbox from here on, and to the writer from its next
    /// batch (the open-ok, or the close).
    async fn tune<R: FrameSource>(&mut self, reader: &mut R) -> Result<ConnectionTuneOk, Ended> {
        let core = Arc::clone(&self.core);
        let limits = &core.limits;
        self.outbox
            .method(
                0,
                ConnectionTune {
                    channel_max: limits.channel_max,
                    frame_max: limits.frame_max,
                    heartbeat: limits.heartbeat,
                },
            )
            .await;
        let Method::ConnectionTuneOk(tune_ok) = self.expect_method(reader).await? else {
            return Err(Ended::Protocol(AmqpError::command_invalid(
                "expected connection.tune-ok",
            )));
        };
        // As RabbitMQ: frame_max must lie in [4096, ours] (0, "unlimited",
        // is refused when we have a limit), channel_max in [0, ours].
        let frame_max = tune_ok.frame_max;
        if frame_max < FRAME_MIN_SIZE || frame_max > limits.frame_max {
            return Err(Ended::Protocol(AmqpError::not_allowed(format_args!(
                "frame_max={} outside of allowed range [{}, {}]",
                frame_max, FRAME_MIN_SIZE, limits.frame_max
            ))));
        }
        if limits.channel_max != 0 && tune_ok.channel_max > limits.channel_max {
            return Err(Ended::Protocol(AmqpError::not_allowed(format_args!(
                "channel_max={} outside of allowed range [0, {}]",
                tune_ok.channel_max, limits.channel_max
            ))));
        }
        // 0 is "no limit" in connection.tune: the other side's value, or
        // every channel number when both say 0.
        self.channel_max = match (tune_ok.channel_max, limits.channel_max) {
            (0, 0) => u16::MAX,
            (0, ours) => ours,
            (theirs, _) => theirs,
        };
        reader.set_frame_max(frame_max);
        self.copy_below = copy_below(frame_max);
        self.outbox.set_frame_max(frame_max);
        self.heartbeat = Duration::from_secs(tune_ok.heartbeat.into());
        self.outbox.set_heartbeat(self.heartbeat);
        Ok(tune_ok)
    }

    /// Takes connection.open: the vhost it names is entered
    /// ([`Connection::enter_vhost`]), the connection registered as open
    /// with what the client told of itself, and answered with open-ok.
    async fn open<R: FrameSource>(
        &mut self,
        reader: &mut R,
        client_properties: FieldTable,
        tune_ok: &ConnectionTuneOk,
    ) -> Result<(), Ended> {
        let Method::ConnectionOpen(open) = self.expect_method(reader).await? else {
            return Err(Ended::Protocol(AmqpError::command_invalid(
                "expected connection.open",
            )));
        };
        let vhost = self.enter_vhost(&open)?;
        self.client_name = match client_properties.get("connection_name") {
            Some(name) => name.as_bytes().map(loggable),
            None => None,
        };
        self.core.registry.opened(
            self.connection_id,
            crate::registry::Opened {
                user: self.user.clone(),
                vhost: vhost.name.to_string_lossy().into_owned(),
                client_properties,
                frame_max: tune_ok.frame_max,
                channel_max: self.channel_max,
                heartbeat_secs: tune_ok.heartbeat,
            },
        );
        if vhost.is_deleted() {
            // Deleted after the lookup above: its deletion closes the
            // connections it found registered, and this one may have
            // registered too late to be found.
            return Err(Ended::Protocol(
                AmqpError::not_allowed(format_args!("vhost {} not found", open.virtual_host))
                    .during_ids(10, 40),
            ));
        }
        self.vhost = Some(vhost);
        self.outbox
            .method(
                0,
                ConnectionOpenOk {
                    known_hosts: ShortStr::default(),
                },
            )
            .await;
        Ok(())
    }

    /// The vhost connection.open names, if it exists, the user has a
    /// permission on it, and neither the vhost's nor the user's
    /// connection limit is reached (each refused with NOT_ALLOWED and
    /// RabbitMQ's text); the connection's slot then counts it in both.
    fn enter_vhost(&mut self, open: &ConnectionOpen) -> Result<Arc<Vhost>, Ended> {
        let Some(vhost) = self.core.vhost(&open.virtual_host) else {
            return Err(Ended::Protocol(
                AmqpError::not_allowed(format_args!("vhost {} not found", open.virtual_host))
                    .during_ids(10, 40),
            ));
        };
        let permitted = vhost
            .name
            .as_str()
            .is_some_and(|name| self.core.permissions.may_open(&self.user, name));
        if !permitted {
            tracing::warn!(peer = %self.peer, vhost = %vhost.name, user = %self.user, "no permission on the vhost");
            return Err(Ended::Protocol(
                AmqpError::not_allowed(format_args!(
                    "access to vhost '{}' refused for user '{}'",
                    vhost.name, self.user
                ))
                .during_ids(10, 40),
            ));
        }
        let vhost_limits = self.core.limit_tables.vhost(&vhost.name.to_string_lossy());
        if let Err(limit) = self
            .slot
            .enter_vhost(&vhost.name, vhost_limits.max_connections)
        {
            tracing::warn!(peer = %self.peer, vhost = %vhost.name, user = %self.user, limit, "vhost connection limit reached");
            return Err(Ended::Protocol(
                AmqpError::not_allowed(format_args!(
                    "access to vhost '{}' refused for user '{}': connection limit ({}) is reached",
                    vhost.name, self.user, limit
                ))
                .during_ids(10, 40),
            ));
        }
        let user_limits = self.core.limit_tables.user(&self.user).unwrap_or_default();
        if let Err(admission::OverLimit(limit)) = self
            .slot
            .enter_user(&self.user, user_limits.max_connections)
        {
            tracing::warn!(peer = %self.peer, user = %self.user, limit, "user connection limit reached");
            return Err(Ended::Protocol(
                AmqpError::not_allowed(format_args!(
                    "connection refused for user '{}': user connection limit ({}) is reached",
                    self.user, limit
                ))
                .during_ids(10, 40),
            ));
        }
        Ok(vhost)
    }
}
