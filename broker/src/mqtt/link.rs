//! A session's way into the core: an in-process AMQP connection
//! (`connection::serve_direct`), so that login (the AMQP handshake's own
//! PLAIN check, the one place passwords are checked), vhost permissions,
//! connection limits, routing, queues, publisher confirms, consumer acks
//! and statistics are exactly the AMQP side's. This module logs the
//! session in and opens its one channel in confirm mode with the
//! session's receive window as prefetch; it also builds the AMQP methods
//! the session sends.

use super::mapping::EXCHANGE;
use crate::admission::Slot;
use crate::connection::{serve_direct, DirectLink, DirectReply, Identity};
use crate::core::Core;
use crate::registry::Registry;
use crate::stats::ConnectionTraffic;
use bytes::{BufMut, Bytes, BytesMut};
use leveret_mqtt::QoS;
use leveret_protocol::{
    BasicProperties, BasicPublish, ChannelOpen, ConfirmSelect, ConnectionClose, ConnectionOpen,
    ConnectionStartOk, ConnectionTuneOk, FieldTable, FieldValue, Frame, Method, Outgoing,
    ReplyCode, ShortStr,
};
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::oneshot;
use tokio::time::Instant;

/// The channel a session uses.
pub(super) const CHANNEL: u16 = 1;

/// An open link: the AMQP connection's two ends, and what tells that it
/// has ended and cleaned up (its exclusive queues deleted).
pub(super) struct Link {
    pub direct: DirectLink,
    /// The AMQP connection's id (a takeover closes it by it).
    pub id: u64,
    ended: oneshot::Receiver<()>,
}

/// Why the core refused a session's login.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Refusal {
    /// Unknown user or wrong password (AMQP 403 during the handshake).
    BadCredentials,
    /// No such vhost, no permission on it, or a connection limit (530).
    NotAuthorized,
    /// Anything else: the broker shutting down, the handshake timeout.
    Unavailable,
}

/// What the session logs in with.
pub(super) struct Login<'a> {
    pub vhost: &'a str,
    pub user: &'a str,
    /// The password (PLAIN), or `None` for a login as the verified TLS
    /// client certificate's common name `user` (SASL EXTERNAL).
    pub password: Option<&'a [u8]>,
    /// The MQTT client's identifier, shown as the AMQP connection's name.
    pub client_id: &'a str,
    /// The session's receive window: QoS 1 deliveries unacknowledged at once.
    pub window: u16,
    /// The MQTT version, as RabbitMQ lists the connection's protocol.
    pub protocol: &'static str,
    /// The session's byte stream's counters, listed as the connection's.
    pub traffic: Arc<ConnectionTraffic>,
}

impl Link {
    /// Opens an AMQP connection for a session from `peer`, logs in, and
    /// opens its channel in confirm mode with `window` as prefetch; all by
    /// `deadline` (the MQTT handshake's).
    pub(super) async fn open(
        core: Arc<Core>,
        slot: Slot,
        peer: String,
        login: Login<'_>,
        deadline: Instant,
    ) -> Result<Link, Refusal> {
        let (done, ended) = oneshot::channel::<()>();
        let identity = match login.password {
            Some(_) => Identity::None,
            None => Identity::Tls(Some(login.user.to_owned())),
        };
        let kind = (login.protocol, Some(Arc::clone(&login.traffic)));
        let id = core.next_connection_id();
        let direct = serve_direct(core, id, slot, (peer, identity), kind, done);
        let mut link = Link { direct, id, ended };
        match tokio::time::timeout_at(deadline, link.handshake(&login)).await {
            Ok(Ok(())) => Ok(link),
            Ok(Err(refusal)) => Err(refusal),
            Err(_) => Err(Refusal::Unavailable),
        }
    }

    async fn handshake(&mut self, login: &Login<'_>) -> Result<(), Refusal> {
        self.expect(|m| matches!(m, Method::ConnectionStart(_)))
            .await?;
        let mut response = BytesMut::new();
        let mechanism = match login.password {
            Some(password) => {
                response.put_u8(0);
                response.put_slice(login.user.as_bytes());
                response.put_u8(0);
                response.put_slice(password);
                "PLAIN"
            }
            None => "EXTERNAL",
        };
        let mut capabilities = FieldTable::new();
        capabilities.insert(
            ShortStr::from_static("authentication_failure_close"),
            FieldValue::Bool(true),
        );
        let mut client_properties = FieldTable::new();
        client_properties.insert(
            ShortStr::from_static("capabilities"),
            FieldValue::Table(capabilities),
        );
        client_properties.insert(ShortStr::from_static("product"), FieldValue::string("MQTT"));
        if let Ok(name) = ShortStr::try_from(login.client_id) {
            client_properties.insert(
                ShortStr::from_static("connection_name"),
                FieldValue::string(name.as_str().unwrap_or_default()),
            );
        }
        self.send(
            0,
            ConnectionStartOk {
                client_properties,
                mechanism: ShortStr::from_static(mechanism),
                response: response.freeze(),
                locale: ShortStr::from_static("en_US"),
            },
        )
        .await?;
        let Method::ConnectionTune(tune) = self
            .expect(|m| matches!(m, Method::ConnectionTune(_)))
            .await?
        else {
            return Err(Refusal::Unavailable);
        };
        self.send(
            0,
            ConnectionTuneOk {
                channel_max: 1,
                frame_max: tune.frame_max,
                heartbeat: 0,
            },
        )
        .await?;
        let virtual_host = ShortStr::try_from(login.vhost).map_err(|_| Refusal::NotAuthorized)?;
        self.send(
            0,
            ConnectionOpen {
                virtual_host,
                ..Default::default()
            },
        )
        .await?;
        self.expect(|m| matches!(m, Method::ConnectionOpenOk(_)))
            .await?;
        self.send(CHANNEL, ChannelOpen::default()).await?;
        self.expect(|m| matches!(m, Method::ChannelOpenOk(_)))
            .await?;
        self.send(CHANNEL, ConfirmSelect { no_wait: false }).await?;
        self.expect(|m| matches!(m, Method::ConfirmSelectOk(_)))
            .await?;
        let qos = leveret_protocol::BasicQos {
            prefetch_size: 0,
            prefetch_count: login.window,
            global: false,
        };
        self.send(CHANNEL, qos).await?;
        self.expect(|m| matches!(m, Method::BasicQosOk(_))).await?;
        Ok(())
    }

    async fn send(&self, channel: u16, method: impl Into<Method>) -> Result<(), Refusal> {
        let item = Outgoing::Method {
            channel,
            method: method.into(),
        };
        (self.direct.to_broker.send(item).await).map_err(|_| Refusal::Unavailable)
    }

    /// The next method, if `wanted`; a connection.close is the refusal it
    /// carries.
    async fn expect(&mut self, wanted: impl Fn(&Method) -> bool) -> Result<Method, Refusal> {
        match self.direct.from_broker.recv().await {
            Some(DirectReply::Frame(Frame::Method { method, .. })) if wanted(&method) => Ok(method),
            Some(DirectReply::Frame(Frame::Method {
                method: Method::ConnectionClose(close),
                ..
            })) => Err(match close.reply_code {
                code if code == ReplyCode::AccessRefused.code() => Refusal::BadCredentials,
                code if code == ReplyCode::NotAllowed.code() => Refusal::NotAuthorized,
                _ => Refusal::Unavailable,
            }),
            // The broker closed without a close: a refused login.
            None => Err(Refusal::BadCredentials),
            Some(_) => Err(Refusal::Unavailable),
        }
    }

    /// Ends the AMQP connection and waits until the broker has cleaned
    /// up. A session the client ended with DISCONNECT closes it with
    /// connection.close (logged as closed by the client); otherwise the
    /// broker sees its client gone, as for a lost socket (a warning).
    ///
    /// Each step takes at most `stall`, as the session's other end steps,
    /// so that a takeover waiting for this end never waits for ever: the
    /// close is handed over while the core's replies are read (a
    /// connection blocked handing over a reply would never take it), and
    /// a connection that has not cleaned up by then is told to close
    /// through the `registry`, as a takeover closes one, and left to end.
    pub(super) async fn close(self, disconnected: bool, registry: &Registry, stall: Duration) {
        let Link {
            mut direct,
            ended,
            id,
        } = self;
        if disconnected {
            let close = ConnectionClose {
                reply_code: ReplyCode::Success.code(),
                reply_text: ShortStr::from_static("MQTT DISCONNECT"),
                class_id: 0,
                method_id: 0,
            };
            let (to_broker, from_broker) = (&direct.to_broker, &mut direct.from_broker);
            let room = async move {
                loop {
                    tokio::select! {
                        permit = to_broker.reserve() => return permit.ok(),
                        reply = from_broker.recv() => {
                            reply?;
                        }
                    }
                }
            };
            if let Ok(Some(permit)) = tokio::time::timeout(stall, room).await {
                permit.send(method_on(0, close));
            }
        }
        drop(direct);
        if tokio::time::timeout(stall, ended).await.is_err() {
            tracing::warn!(link = id, "AMQP link of an MQTT session not ended in time");
            registry.close(id, "MQTT session ended");
        }
    }
}

// The marks below all start with `x-mqtt-`, which `properties` keeps out
// of 5.0 user properties (its test `the_brokers_headers_are_no_user_properties`
// holds them to it).

/// The header a QoS 2 publish carries (RabbitMQ 3.13's name), so that a
/// QoS 2 subscriber gets it at QoS 2; without it a persistent message is
/// QoS 1 and a transient one QoS 0.
pub(super) const PUBLISH_QOS_HEADER: &str = "x-mqtt-publish-qos";
/// The header a publish with RETAIN set carries (`true`), for the
/// subscriptions with Retain As Published.
pub(super) const RETAIN_HEADER: &str = "x-mqtt-retain";
/// The header naming the client identifier that published a message,
/// set while the publishing session has a No Local subscription.
pub(super) const PUBLISHER_HEADER: &str = "x-mqtt-publisher";

/// How an MQTT publish is marked for its subscribers.
pub(super) struct Marks<'a> {
    pub qos: QoS,
    /// RETAIN was set.
    pub retain: bool,
    /// The publishing client, when No Local needs it.
    pub publisher: Option<&'a str>,
}

/// The AMQP properties of an MQTT publish: persistent for QoS 1 and 2, as
/// RabbitMQ's MQTT plugin publishes them; QoS 2 says so in
/// [`PUBLISH_QOS_HEADER`], RETAIN in [`RETAIN_HEADER`], the publisher in
/// [`PUBLISHER_HEADER`]; a 5.0 publish's (or will's) properties mapped.
pub(super) fn properties(
    marks: Marks<'_>,
    v5_properties: Option<&leveret_mqtt::Properties>,
    now: std::time::SystemTime,
) -> BasicProperties {
    let mut headers = FieldTable::new();
    if marks.qos == QoS::ExactlyOnce {
        headers.insert(
            ShortStr::from_static(PUBLISH_QOS_HEADER),
            FieldValue::U8(marks.qos.level()),
        );
    }
    if marks.retain {
        headers.insert(ShortStr::from_static(RETAIN_HEADER), FieldValue::Bool(true));
    }
    if let Some(publisher) = marks.publisher {
        headers.insert(
            ShortStr::from_static(PUBLISHER_HEADER),
            FieldValue::string(publisher),
        );
    }
    let mut properties = BasicProperties {
        delivery_mode: Some(if marks.qos == QoS::AtMostOnce { 1 } else { 2 }),
        headers: (!headers.is_empty()).then_some(headers),
        ..Default::default()
    };
    if let Some(mqtt) = v5_properties {
        super::properties::to_amqp(mqtt, &mut properties, now);
    }
    properties
}

/// A publish to [`EXCHANGE`].
pub(super) fn publish(routing_key: ShortStr, properties: BasicProperties, body: Bytes) -> Outgoing {
    Outgoing::Publish {
        channel: CHANNEL,
        method: BasicPublish {
            exchange: ShortStr::from_static(EXCHANGE),
            routing_key,
            ..Default::default()
        },
        properties: Box::new(properties),
        body,
    }
}

/// A method on the session's channel.
pub(super) fn method(method: impl Into<Method>) -> Outgoing {
    method_on(CHANNEL, method)
}

fn method_on(channel: u16, method: impl Into<Method>) -> Outgoing {
    Outgoing::Method {
        channel,
        method: method.into(),
    }
}
