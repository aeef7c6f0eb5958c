//! The fifteen control packets (MQTT 5.0, chapter 3; 3.1.1, chapter 3) as
//! types, and each one's variable header and payload: decoded from a
//! buffered packet body by version, and written by version with the rules a
//! decoder checks, so that whatever encodes, decodes.
//!
//! One type serves every version: fields a version cannot carry
//! (properties, reason codes, subscription options before 5.0) must hold
//! their defaults to encode in it, and decode as defaults from it.

use crate::error::Problem;
use crate::properties::{Properties, PropertyContext};
use crate::qos::{Delivery, PacketId, QoS};
use crate::reason::ReasonCode;
use crate::string::MqttString;
use crate::topic::{TopicError, TopicFilter, TopicName};
use crate::version::ProtocolVersion;
use crate::wire::{
    binary, binary_slice, fail, in_field, put_binary, put_string, put_u16, put_u8, string, Fault,
    PResult, Sink,
};
use bytes::Bytes;
use nom::number::complete::{be_u16, be_u8};

/// A control packet type, the high nibble of the first byte.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum PacketType {
    /// 1: client asks to connect.
    Connect = 1,
    /// 2: connect acknowledgment.
    ConnAck = 2,
    /// 3: publish message.
    Publish = 3,
    /// 4: QoS 1 publish acknowledgment.
    PubAck = 4,
    /// 5: QoS 2 publish received (part 1).
    PubRec = 5,
    /// 6: QoS 2 publish release (part 2).
    PubRel = 6,
    /// 7: QoS 2 publish complete (part 3).
    PubComp = 7,
    /// 8: subscribe request.
    Subscribe = 8,
    /// 9: subscribe acknowledgment.
    SubAck = 9,
    /// 10: unsubscribe request.
    Unsubscribe = 10,
    /// 11: unsubscribe acknowledgment.
    UnsubAck = 11,
    /// 12: ping request.
    PingReq = 12,
    /// 13: ping response.
    PingResp = 13,
    /// 14: disconnect notification.
    Disconnect = 14,
    /// 15: authentication exchange (5.0 only).
    Auth = 15,
}

impl PacketType {
    /// The packet type of a first byte's high nibble, if it names one in
    /// `version` (0 is reserved; 15 is reserved before 5.0).
    pub fn from_nibble(nibble: u8, version: ProtocolVersion) -> Option<Self> {
        use PacketType::*;
        Some(match nibble {
            1 => Connect,
            2 => ConnAck,
            3 => Publish,
            4 => PubAck,
            5 => PubRec,
            6 => PubRel,
            7 => PubComp,
            8 => Subscribe,
            9 => SubAck,
            10 => Unsubscribe,
            11 => UnsubAck,
            12 => PingReq,
            13 => PingResp,
            14 => Disconnect,
            15 if version.is_v5() => Auth,
            _ => return None,
        })
    }

    /// The fixed header flags every packet but PUBLISH must carry (2.1.3):
    /// 0b0010 for PUBREL, SUBSCRIBE and UNSUBSCRIBE, 0 for the others.
    pub(crate) fn required_flags(self) -> u8 {
        match self {
            PacketType::PubRel | PacketType::Subscribe | PacketType::Unsubscribe => 0b0010,
            _ => 0,
        }
    }
}

/// CONNECT: the first packet a client sends.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Connect {
    /// The protocol the client speaks: CONNECT is written in its own
    /// version and decoded by the level it carries.
    pub version: ProtocolVersion,
    /// Clean Session (3.1.1) or Clean Start (5.0).
    pub clean_start: bool,
    /// Keep alive in seconds (0 = off).
    pub keep_alive: u16,
    /// CONNECT properties (5.0).
    pub properties: Properties,
    /// The client identifier (may be empty).
    pub client_id: MqttString,
    /// The will message.
    pub will: Option<Will>,
    /// The user name.
    pub username: Option<MqttString>,
    /// The password (binary data).
    pub password: Option<Bytes>,
}

/// The will message of a CONNECT.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Will {
    /// Will properties (5.0).
    pub properties: Properties,
    /// The topic it is published to (not empty).
    pub topic: TopicName,
    /// Its payload.
    pub payload: Bytes,
    /// Its QoS.
    pub qos: QoS,
    /// Whether it is retained.
    pub retain: bool,
}

/// CONNACK: the server's answer to CONNECT.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ConnAck {
    /// Whether the server resumed a session.
    pub session_present: bool,
    /// The outcome. In 3.1.1 only the six codes of
    /// [`ReasonCode::to_v3_connack`] exist.
    pub reason: ReasonCode,
    /// CONNACK properties (5.0).
    pub properties: Properties,
}

/// PUBLISH: an application message.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Publish {
    /// Whether this is a redelivery (never on QoS 0).
    pub dup: bool,
    /// QoS and packet identifier.
    pub delivery: Delivery,
    /// Whether the message is retained.
    pub retain: bool,
    /// The topic; empty only in 5.0 with a Topic Alias.
    pub topic: TopicName,
    /// PUBLISH properties (5.0).
    pub properties: Properties,
    /// The application message: a slice of the read buffer when decoded.
    pub payload: Bytes,
}

/// PUBACK, PUBREC, PUBREL and PUBCOMP: a packet identifier with, in 5.0, a
/// reason code and properties.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PubResponse {
    /// The PUBLISH (or PUBREL) this answers.
    pub packet_id: PacketId,
    /// The outcome (always Success in 3.1.1).
    pub reason: ReasonCode,
    /// Properties (5.0).
    pub properties: Properties,
}

impl PubResponse {
    /// A successful response without properties.
    pub fn new(packet_id: PacketId) -> Self {
        PubResponse {
            packet_id,
            reason: ReasonCode::Success,
            properties: Properties::default(),
        }
    }
}

/// What to do with retained messages when a subscription is made (5.0).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum RetainHandling {
    /// 0: send retained messages at subscribe.
    #[default]
    SendAtSubscribe,
    /// 1: send them only if the subscription did not exist.
    SendIfNewSubscription,
    /// 2: do not send them.
    DoNotSend,
}

/// The options byte of a subscription. Before 5.0 only the QoS exists.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct SubscriptionOptions {
    /// The maximum QoS the subscriber accepts.
    pub qos: QoS,
    /// Do not send the subscriber its own publishes (5.0).
    pub no_local: bool,
    /// Keep the RETAIN flag as published (5.0).
    pub retain_as_published: bool,
    /// Retained messages at subscribe (5.0).
    pub retain_handling: RetainHandling,
}

/// One topic filter of a SUBSCRIBE with its options.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Subscription {
    /// The filter (possibly a shared subscription).
    pub filter: TopicFilter,
    /// Its options.
    pub options: SubscriptionOptions,
}

/// SUBSCRIBE.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Subscribe {
    /// The packet identifier.
    pub packet_id: PacketId,
    /// SUBSCRIBE properties (5.0): at most one Subscription Identifier.
    pub properties: Properties,
    /// At least one subscription.
    pub subscriptions: Vec<Subscription>,
}

/// SUBACK.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SubAck {
    /// The SUBSCRIBE's packet identifier.
    pub packet_id: PacketId,
    /// SUBACK properties (5.0).
    pub properties: Properties,
    /// One code per subscription, in order (in 3.1.1: granted QoS 0 to 2 or 0x80).
    pub reasons: Vec<ReasonCode>,
}

/// UNSUBSCRIBE.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Unsubscribe {
    /// The packet identifier.
    pub packet_id: PacketId,
    /// UNSUBSCRIBE properties (5.0).
    pub properties: Properties,
    /// At least one filter.
    pub filters: Vec<TopicFilter>,
}

/// UNSUBACK.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UnsubAck {
    /// The UNSUBSCRIBE's packet identifier.
    pub packet_id: PacketId,
    /// UNSUBACK properties (5.0).
    pub properties: Properties,
    /// One code per filter (5.0; empty in 3.1.1, which has no payload).
    pub reasons: Vec<ReasonCode>,
}

/// DISCONNECT.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Disconnect {
    /// Why (5.0; Normal disconnection in 3.1.1).
    pub reason: ReasonCode,
    /// DISCONNECT properties (5.0).
    pub properties: Properties,
}

/// AUTH (5.0 only).
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Auth {
    /// Success, Continue authentication or Re-authenticate.
    pub reason: ReasonCode,
    /// AUTH properties.
    pub properties: Properties,
}

/// An MQTT control packet.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Packet {
    /// CONNECT (boxed: it is the largest packet and comes once).
    Connect(Box<Connect>),
    /// CONNACK.
    ConnAck(ConnAck),
    /// PUBLISH.
    Publish(Publish),
    /// PUBACK.
    PubAck(PubResponse),
    /// PUBREC.
    PubRec(PubResponse),
    /// PUBREL.
    PubRel(PubResponse),
    /// PUBCOMP.
    PubComp(PubResponse),
    /// SUBSCRIBE.
    Subscribe(Subscribe),
    /// SUBACK.
    SubAck(SubAck),
    /// UNSUBSCRIBE.
    Unsubscribe(Unsubscribe),
    /// UNSUBACK.
    UnsubAck(UnsubAck),
    /// PINGREQ.
    PingReq,
    /// PINGRESP.
    PingResp,
    /// DISCONNECT.
    Disconnect(Disconnect),
    /// AUTH.
    Auth(Auth),
}

impl Packet {
    /// The packet's type.
    pub fn packet_type(&self) -> PacketType {
        match self {
            Packet::Connect(_) => PacketType::Connect,
            Packet::ConnAck(_) => PacketType::ConnAck,
            Packet::Publish(_) => PacketType::Publish,
            Packet::PubAck(_) => PacketType::PubAck,
            Packet::PubRec(_) => PacketType::PubRec,
            Packet::PubRel(_) => PacketType::PubRel,
            Packet::PubComp(_) => PacketType::PubComp,
            Packet::Subscribe(_) => PacketType::Subscribe,
            Packet::SubAck(_) => PacketType::SubAck,
            Packet::Unsubscribe(_) => PacketType::Unsubscribe,
            Packet::UnsubAck(_) => PacketType::UnsubAck,
            Packet::PingReq => PacketType::PingReq,
            Packet::PingResp => PacketType::PingResp,
            Packet::Disconnect(_) => PacketType::Disconnect,
            Packet::Auth(_) => PacketType::Auth,
        }
    }

    /// The first byte of the fixed header: type and flags.
    pub(crate) fn first_byte(&self) -> u8 {
        let kind = self.packet_type();
        let flags = match self {
            Packet::Publish(p) => {
                (u8::from(p.dup) << 3) | (p.delivery.qos().level() << 1) | u8::from(p.retain)
            }
            _ => kind.required_flags(),
        };
        ((kind as u8) << 4) | flags
    }

    /// Decodes a packet body (everything after the fixed header) of the
    /// packet `kind`, whose fixed header flags are already checked.
    pub(crate) fn decode_body(
        kind: PacketType,
        flags: u8,
        src: &Bytes,
        version: ProtocolVersion,
    ) -> Result<Packet, Fault> {
        let input: &[u8] = src;
        let result = match kind {
            PacketType::Connect => {
                decode_connect(src, input).map(|(r, p)| (r, Packet::Connect(Box::new(p))))
            }
            PacketType::ConnAck => {
                decode_connack(src, input, version).map(|(r, p)| (r, Packet::ConnAck(p)))
            }
            PacketType::Publish => {
                decode_publish(src, flags, input, version).map(|(r, p)| (r, Packet::Publish(p)))
            }
            PacketType::PubAck => {
                pub_response(src, input, version, kind).map(|(r, p)| (r, Packet::PubAck(p)))
            }
            PacketType::PubRec => {
                pub_response(src, input, version, kind).map(|(r, p)| (r, Packet::PubRec(p)))
            }
            PacketType::PubRel => {
                pub_response(src, input, version, kind).map(|(r, p)| (r, Packet::PubRel(p)))
            }
            PacketType::PubComp => {
                pub_response(src, input, version, kind).map(|(r, p)| (r, Packet::PubComp(p)))
            }
            PacketType::Subscribe => {
                decode_subscribe(src, input, version).map(|(r, p)| (r, Packet::Subscribe(p)))
            }
            PacketType::SubAck => {
                decode_suback(src, input, version).map(|(r, p)| (r, Packet::SubAck(p)))
            }
            PacketType::Unsubscribe => {
                decode_unsubscribe(src, input, version).map(|(r, p)| (r, Packet::Unsubscribe(p)))
            }
            PacketType::UnsubAck => {
                decode_unsuback(src, input, version).map(|(r, p)| (r, Packet::UnsubAck(p)))
            }
            PacketType::PingReq => Ok((input, Packet::PingReq)),
            PacketType::PingResp => Ok((input, Packet::PingResp)),
            PacketType::Disconnect => {
                if version.is_v5() {
                    reason_and_properties(src, input, kind, PropertyContext::Disconnect).map(
                        |(r, (reason, properties))| {
                            (r, Packet::Disconnect(Disconnect { reason, properties }))
                        },
                    )
                } else {
                    Ok((input, Packet::Disconnect(Disconnect::default())))
                }
            }
            PacketType::Auth => reason_and_properties(src, input, kind, PropertyContext::Auth)
                .map(|(r, (reason, properties))| (r, Packet::Auth(Auth { reason, properties }))),
        };
        match result {
            Ok((rest, _)) if !rest.is_empty() => {
                Err(Fault::new(Problem::TrailingBytes(rest.len()), ""))
            }
            Ok((_, packet)) => Ok(packet),
            Err(nom::Err::Error(f) | nom::Err::Failure(f)) => Err(f),
            // Complete parsers never ask for more.
            Err(nom::Err::Incomplete(_)) => Err(Fault::new(Problem::Truncated, "")),
        }
    }

    /// Writes the packet body (everything after the fixed header) in
    /// `version`, checking what a decoder checks.
    pub(crate) fn write_body(
        &self,
        version: ProtocolVersion,
        s: &mut impl Sink,
    ) -> Result<(), Fault> {
        match self {
            Packet::Connect(p) => write_connect(p, s),
            Packet::ConnAck(p) => write_connack(p, version, s),
            Packet::Publish(p) => write_publish(p, version, s),
            Packet::PubAck(p) | Packet::PubRec(p) | Packet::PubRel(p) | Packet::PubComp(p) => {
                put_u16(s, p.packet_id.get());
                write_reason_and_properties(
                    p.reason,
                    &p.properties,
                    version,
                    self.packet_type(),
                    PropertyContext::PubResponse,
                    s,
                )
            }
            Packet::Subscribe(p) => write_subscribe(p, version, s),
            Packet::SubAck(p) => write_suback(p, version, s),
            Packet::Unsubscribe(p) => write_unsubscribe(p, version, s),
            Packet::UnsubAck(p) => write_unsuback(p, version, s),
            Packet::PingReq | Packet::PingResp => Ok(()),
            Packet::Disconnect(p) => write_reason_and_properties(
                p.reason,
                &p.properties,
                version,
                PacketType::Disconnect,
                PropertyContext::Disconnect,
                s,
            ),
            Packet::Auth(p) => {
                if !version.is_v5() {
                    return Err(Fault::new(Problem::NotInVersion, "packet type"));
                }
                write_reason_and_properties(
                    p.reason,
                    &p.properties,
                    version,
                    PacketType::Auth,
                    PropertyContext::Auth,
                    s,
                )
            }
        }
    }
}

// ---- decoding ----

fn packet_id(input: &[u8]) -> PResult<'_, PacketId> {
    let (rest, id) = in_field(be_u16(input), "packet id")?;
    match PacketId::new(id) {
        Some(id) => Ok((rest, id)),
        None => in_field(fail(Problem::ZeroPacketId), "packet id"),
    }
}

/// Properties in 5.0; none before.
fn properties<'a>(
    src: &Bytes,
    input: &'a [u8],
    version: ProtocolVersion,
    context: PropertyContext,
    field: &'static str,
) -> PResult<'a, Properties> {
    if version.is_v5() {
        in_field(Properties::decode(src, input, context), field)
    } else {
        Ok((input, Properties::default()))
    }
}

fn topic_name<'a>(src: &Bytes, input: &'a [u8], field: &'static str) -> PResult<'a, TopicName> {
    let (rest, s) = in_field(string(src, input), field)?;
    match TopicName::new(s) {
        Ok(topic) => Ok((rest, topic)),
        Err(e) => in_field(fail(Problem::InvalidTopicName(e)), field),
    }
}

fn topic_filter<'a>(src: &Bytes, input: &'a [u8]) -> PResult<'a, TopicFilter> {
    let (rest, s) = in_field(string(src, input), "topic filter")?;
    match TopicFilter::new(s) {
        Ok(filter) => Ok((rest, filter)),
        Err(e) => in_field(fail(Problem::InvalidTopicFilter(e)), "topic filter"),
    }
}

/// A reason code byte that `packet` may carry in `version`.
fn reason_code(
    input: &[u8],
    packet: PacketType,
    version: ProtocolVersion,
) -> PResult<'_, ReasonCode> {
    let (rest, code) = in_field(be_u8(input), "reason code")?;
    let reason = match (packet, version.is_v5()) {
        (PacketType::ConnAck, false) => ReasonCode::from_v3_connack(code),
        (PacketType::SubAck, false) => ReasonCode::from_u8(code).filter(|r| r.in_v3_suback()),
        _ => ReasonCode::from_u8(code).filter(|r| r.allowed_in(packet)),
    };
    match reason {
        Some(reason) => Ok((rest, reason)),
        None => in_field(fail(Problem::InvalidReasonCode(code)), "reason code"),
    }
}

/// 5.0's optional reason code and optional properties at the end of a
/// packet: absent means Success and none (3.4.2.1, 3.14.2.1, 3.15.2.1).
fn reason_and_properties<'a>(
    src: &Bytes,
    input: &'a [u8],
    packet: PacketType,
    context: PropertyContext,
) -> PResult<'a, (ReasonCode, Properties)> {
    if input.is_empty() {
        return Ok((input, (ReasonCode::Success, Properties::default())));
    }
    let (input, reason) = reason_code(input, packet, ProtocolVersion::V5)?;
    if input.is_empty() {
        return Ok((input, (reason, Properties::default())));
    }
    let (input, props) = in_field(Properties::decode(src, input, context), "properties")?;
    Ok((input, (reason, props)))
}

fn decode_connect<'a>(src: &Bytes, input: &'a [u8]) -> PResult<'a, Connect> {
    let (input, name) = in_field(binary_slice(input), "protocol name")?;
    let (input, level) = in_field(be_u8(input), "protocol level")?;
    let Some(version) = ProtocolVersion::from_connect(name, level) else {
        return in_field(fail(Problem::UnsupportedProtocol(level)), "protocol level");
    };
    let (input, flags) = in_field(be_u8(input), "connect flags")?;
    let will_flag = flags & 0x04 != 0;
    let will_qos = (flags >> 3) & 0x03;
    let will_retain = flags & 0x20 != 0;
    let has_password = flags & 0x40 != 0;
    let has_username = flags & 0x80 != 0;
    let flag_problem = if flags & 0x01 != 0 {
        Some(Problem::ReservedBitsSet)
    } else if !will_flag && (will_qos != 0 || will_retain) {
        Some(Problem::WillFieldsWithoutWill)
    } else if will_qos == 3 {
        Some(Problem::InvalidQos)
    } else if !version.is_v5() && has_password && !has_username {
        Some(Problem::PasswordWithoutUsername)
    } else {
        None
    };
    if let Some(problem) = flag_problem {
        return in_field(fail(problem), "connect flags");
    }
    let (input, keep_alive) = in_field(be_u16(input), "keep alive")?;
    let (input, props) = properties(src, input, version, PropertyContext::Connect, "properties")?;
    let (mut input, client_id) = in_field(string(src, input), "client id")?;
    let mut will = None;
    if will_flag {
        let (rest, will_props) = properties(
            src,
            input,
            version,
            PropertyContext::Will,
            "will properties",
        )?;
        let (rest, topic) = topic_name(src, rest, "will topic")?;
        if topic.is_empty() {
            return in_field(
                fail(Problem::InvalidTopicName(TopicError::Empty)),
                "will topic",
            );
        }
        let (rest, payload) = in_field(binary(src, rest), "will payload")?;
        input = rest;
        will = Some(Will {
            properties: will_props,
            topic,
            payload,
            qos: QoS::from_level(will_qos).unwrap_or_default(),
            retain: will_retain,
        });
    }
    let mut username = None;
    if has_username {
        let (rest, v) = in_field(string(src, input), "user name")?;
        input = rest;
        username = Some(v);
    }
    let mut password = None;
    if has_password {
        let (rest, v) = in_field(binary(src, input), "password")?;
        input = rest;
        password = Some(v);
    }
    Ok((
        input,
        Connect {
            version,
            clean_start: flags & 0x02 != 0,
            keep_alive,
            properties: props,
            client_id,
            will,
            username,
            password,
        },
    ))
}

fn decode_connack<'a>(
    src: &Bytes,
    input: &'a [u8],
    version: ProtocolVersion,
) -> PResult<'a, ConnAck> {
    let (input, flags) = in_field(be_u8(input), "acknowledge flags")?;
    if flags & 0xFE != 0 {
        return in_field(fail(Problem::ReservedBitsSet), "acknowledge flags");
    }
    let (input, reason) = reason_code(input, PacketType::ConnAck, version)?;
    let (input, props) = properties(src, input, version, PropertyContext::ConnAck, "properties")?;
    Ok((
        input,
        ConnAck {
            session_present: flags & 0x01 != 0,
            reason,
            properties: props,
        },
    ))
}

fn decode_publish<'a>(
    src: &Bytes,
    flags: u8,
    input: &'a [u8],
    version: ProtocolVersion,
) -> PResult<'a, Publish> {
    let (input, topic) = topic_name(src, input, "topic")?;
    let (input, delivery) = match (flags >> 1) & 0x03 {
        0 => (input, Delivery::AtMostOnce),
        1 => {
            let (rest, id) = packet_id(input)?;
            (rest, Delivery::AtLeastOnce(id))
        }
        // The caller refused QoS 3 with the fixed header.
        _ => {
            let (rest, id) = packet_id(input)?;
            (rest, Delivery::ExactlyOnce(id))
        }
    };
    let (input, props) = properties(src, input, version, PropertyContext::Publish, "properties")?;
    if topic.is_empty() && !version.is_v5() {
        return in_field(fail(Problem::InvalidTopicName(TopicError::Empty)), "topic");
    }
    if topic.is_empty() && props.topic_alias.is_none() {
        return in_field(fail(Problem::EmptyTopicWithoutAlias), "topic");
    }
    // The rest of the packet is the payload.
    let payload = src.slice_ref(input);
    Ok((
        &input[input.len()..],
        Publish {
            dup: flags & 0x08 != 0,
            delivery,
            retain: flags & 0x01 != 0,
            topic,
            properties: props,
            payload,
        },
    ))
}

fn pub_response<'a>(
    src: &Bytes,
    input: &'a [u8],
    version: ProtocolVersion,
    packet: PacketType,
) -> PResult<'a, PubResponse> {
    let (input, packet_id) = packet_id(input)?;
    let (input, (reason, properties)) = if version.is_v5() {
        reason_and_properties(src, input, packet, PropertyContext::PubResponse)?
    } else {
        (input, (ReasonCode::Success, Properties::default()))
    };
    Ok((
        input,
        PubResponse {
            packet_id,
            reason,
            properties,
        },
    ))
}

fn subscription_options(
    input: &[u8],
    version: ProtocolVersion,
) -> PResult<'_, SubscriptionOptions> {
    let (rest, byte) = in_field(be_u8(input), "subscription options")?;
    let reserved = if version.is_v5() { 0xC0 } else { 0xFC };
    let retain_handling = match (byte >> 4) & 0x03 {
        0 => Some(RetainHandling::SendAtSubscribe),
        1 => Some(RetainHandling::SendIfNewSubscription),
        2 => Some(RetainHandling::DoNotSend),
        _ => None,
    };
    let qos = QoS::from_level(byte & 0x03);
    let options = match (byte & reserved != 0, qos, retain_handling) {
        (true, _, _) => Err(Problem::ReservedBitsSet),
        (false, Some(qos), Some(retain_handling)) => Ok(SubscriptionOptions {
            qos,
            no_local: byte & 0x04 != 0,
            retain_as_published: byte & 0x08 != 0,
            retain_handling,
        }),
        // MQTT-3-8.3-4 makes a QoS of 3 malformed in 3.1.1; 5.0 calls it a
        // protocol error (3.8.3.1).
        (false, _, _) if version.is_v5() => Err(Problem::InvalidSubscriptionOptions),
        (false, _, _) => Err(Problem::InvalidQos),
    };
    match options {
        Ok(options) => Ok((rest, options)),
        Err(problem) => in_field(fail(problem), "subscription options"),
    }
}

fn decode_subscribe<'a>(
    src: &Bytes,
    input: &'a [u8],
    version: ProtocolVersion,
) -> PResult<'a, Subscribe> {
    let (input, packet_id) = packet_id(input)?;
    let (mut input, props) = properties(
        src,
        input,
        version,
        PropertyContext::Subscribe,
        "properties",
    )?;
    let mut subscriptions = Vec::new();
    while !input.is_empty() {
        let (rest, filter) = topic_filter(src, input)?;
        let (rest, options) = subscription_options(rest, version)?;
        if options.no_local && filter.shared().is_some() {
            return in_field(
                fail(Problem::NoLocalOnSharedSubscription),
                "subscription options",
            );
        }
        subscriptions.push(Subscription { filter, options });
        input = rest;
    }
    if subscriptions.is_empty() {
        return in_field(fail(Problem::NoTopicFilters), "payload");
    }
    Ok((
        input,
        Subscribe {
            packet_id,
            properties: props,
            subscriptions,
        },
    ))
}

fn decode_suback<'a>(
    src: &Bytes,
    input: &'a [u8],
    version: ProtocolVersion,
) -> PResult<'a, SubAck> {
    let (input, packet_id) = packet_id(input)?;
    let (mut input, props) =
        properties(src, input, version, PropertyContext::SubAck, "properties")?;
    let mut reasons = Vec::with_capacity(input.len());
    while !input.is_empty() {
        let (rest, reason) = reason_code(input, PacketType::SubAck, version)?;
        reasons.push(reason);
        input = rest;
    }
    Ok((
        input,
        SubAck {
            packet_id,
            properties: props,
            reasons,
        },
    ))
}

fn decode_unsubscribe<'a>(
    src: &Bytes,
    input: &'a [u8],
    version: ProtocolVersion,
) -> PResult<'a, Unsubscribe> {
    let (input, packet_id) = packet_id(input)?;
    let (mut input, props) = properties(
        src,
        input,
        version,
        PropertyContext::Unsubscribe,
        "properties",
    )?;
    let mut filters = Vec::new();
    while !input.is_empty() {
        let (rest, filter) = topic_filter(src, input)?;
        filters.push(filter);
        input = rest;
    }
    if filters.is_empty() {
        return in_field(fail(Problem::NoTopicFilters), "payload");
    }
    Ok((
        input,
        Unsubscribe {
            packet_id,
            properties: props,
            filters,
        },
    ))
}

fn decode_unsuback<'a>(
    src: &Bytes,
    input: &'a [u8],
    version: ProtocolVersion,
) -> PResult<'a, UnsubAck> {
    let (input, packet_id) = packet_id(input)?;
    let (mut input, props) =
        properties(src, input, version, PropertyContext::UnsubAck, "properties")?;
    let mut reasons = Vec::new();
    if version.is_v5() {
        reasons.reserve(input.len());
        while !input.is_empty() {
            let (rest, reason) = reason_code(input, PacketType::UnsubAck, version)?;
            reasons.push(reason);
            input = rest;
        }
    }
    Ok((
        input,
        UnsubAck {
            packet_id,
            properties: props,
            reasons,
        },
    ))
}

// ---- encoding ----

fn named<T>(result: Result<T, Fault>, field: &'static str) -> Result<T, Fault> {
    result.map_err(|mut f| {
        if f.field.is_empty() {
            f.field = field;
        }
        f
    })
}

/// Properties in 5.0; before, there must be none.
fn write_properties(
    props: &Properties,
    version: ProtocolVersion,
    context: PropertyContext,
    field: &'static str,
    s: &mut impl Sink,
) -> Result<(), Fault> {
    if version.is_v5() {
        named(props.write(context, s), field)
    } else if props.is_empty() {
        Ok(())
    } else {
        Err(Fault::new(Problem::NotInVersion, field))
    }
}

fn write_topic_name(topic: &TopicName, s: &mut impl Sink) {
    put_string(s, topic.as_mqtt_string());
}

/// 5.0's optional reason code and properties, in their shortest form;
/// before 5.0 the reason must be Success and there are no properties.
/// A decoder takes every form ([`reason_and_properties`]).
fn write_reason_and_properties(
    reason: ReasonCode,
    props: &Properties,
    version: ProtocolVersion,
    packet: PacketType,
    context: PropertyContext,
    s: &mut impl Sink,
) -> Result<(), Fault> {
    if !version.is_v5() {
        if reason != ReasonCode::Success {
            return Err(Fault::new(Problem::NotInVersion, "reason code"));
        }
        return write_properties(props, version, context, "properties", s);
    }
    if !reason.allowed_in(packet) {
        return Err(Fault::new(
            Problem::InvalidReasonCode(reason.code()),
            "reason code",
        ));
    }
    if reason == ReasonCode::Success && props.is_empty() {
        return Ok(());
    }
    put_u8(s, reason.code());
    // PUBACK to PUBCOMP and DISCONNECT may end after the reason code
    // (3.4.2.2, 3.14.2.2); AUTH says nothing of it, so it always carries
    // its property length.
    if props.is_empty() && packet != PacketType::Auth {
        return Ok(());
    }
    named(props.write(context, s), "properties")
}

fn write_connect(p: &Connect, s: &mut impl Sink) -> Result<(), Fault> {
    let version = p.version;
    if !version.is_v5() && p.password.is_some() && p.username.is_none() {
        return Err(Fault::new(Problem::PasswordWithoutUsername, "password"));
    }
    let name = version.protocol_name().as_bytes();
    put_u16(s, name.len() as u16);
    s.put(name);
    put_u8(s, version.level());
    let mut flags = u8::from(p.clean_start) << 1;
    if let Some(will) = &p.will {
        flags |= 0x04 | (will.qos.level() << 3) | (u8::from(will.retain) << 5);
    }
    flags |= u8::from(p.password.is_some()) << 6;
    flags |= u8::from(p.username.is_some()) << 7;
    put_u8(s, flags);
    put_u16(s, p.keep_alive);
    write_properties(
        &p.properties,
        version,
        PropertyContext::Connect,
        "properties",
        s,
    )?;
    put_string(s, &p.client_id);
    if let Some(will) = &p.will {
        write_properties(
            &will.properties,
            version,
            PropertyContext::Will,
            "will properties",
            s,
        )?;
        if will.topic.is_empty() {
            return Err(Fault::new(
                Problem::InvalidTopicName(TopicError::Empty),
                "will topic",
            ));
        }
        write_topic_name(&will.topic, s);
        put_binary(s, &will.payload, "will payload")?;
    }
    if let Some(username) = &p.username {
        put_string(s, username);
    }
    if let Some(password) = &p.password {
        put_binary(s, password, "password")?;
    }
    Ok(())
}

fn write_connack(p: &ConnAck, version: ProtocolVersion, s: &mut impl Sink) -> Result<(), Fault> {
    put_u8(s, u8::from(p.session_present));
    let code = if version.is_v5() {
        Some(p.reason.code()).filter(|_| p.reason.allowed_in(PacketType::ConnAck))
    } else {
        p.reason.to_v3_connack()
    };
    let Some(code) = code else {
        return Err(Fault::new(
            Problem::InvalidReasonCode(p.reason.code()),
            "reason code",
        ));
    };
    put_u8(s, code);
    write_properties(
        &p.properties,
        version,
        PropertyContext::ConnAck,
        "properties",
        s,
    )
}

fn write_publish(p: &Publish, version: ProtocolVersion, s: &mut impl Sink) -> Result<(), Fault> {
    if p.dup && p.delivery == Delivery::AtMostOnce {
        return Err(Fault::new(Problem::DupOnQos0, "dup"));
    }
    if p.topic.is_empty() {
        if !version.is_v5() {
            return Err(Fault::new(
                Problem::InvalidTopicName(TopicError::Empty),
                "topic",
            ));
        }
        if p.properties.topic_alias.is_none() {
            return Err(Fault::new(Problem::EmptyTopicWithoutAlias, "topic"));
        }
    }
    write_topic_name(&p.topic, s);
    if let Some(id) = p.delivery.packet_id() {
        put_u16(s, id.get());
    }
    write_properties(
        &p.properties,
        version,
        PropertyContext::Publish,
        "properties",
        s,
    )?;
    s.put(&p.payload);
    Ok(())
}

fn write_subscribe(
    p: &Subscribe,
    version: ProtocolVersion,
    s: &mut impl Sink,
) -> Result<(), Fault> {
    if p.subscriptions.is_empty() {
        return Err(Fault::new(Problem::NoTopicFilters, "payload"));
    }
    put_u16(s, p.packet_id.get());
    write_properties(
        &p.properties,
        version,
        PropertyContext::Subscribe,
        "properties",
        s,
    )?;
    for sub in &p.subscriptions {
        let o = sub.options;
        if o.no_local && sub.filter.shared().is_some() {
            return Err(Fault::new(
                Problem::NoLocalOnSharedSubscription,
                "subscription options",
            ));
        }
        let extended = SubscriptionOptions {
            qos: o.qos,
            ..Default::default()
        } != o;
        if !version.is_v5() && extended {
            return Err(Fault::new(Problem::NotInVersion, "subscription options"));
        }
        let retain_handling = match o.retain_handling {
            RetainHandling::SendAtSubscribe => 0,
            RetainHandling::SendIfNewSubscription => 1,
            RetainHandling::DoNotSend => 2,
        };
        put_string(s, sub.filter.as_mqtt_string());
        put_u8(
            s,
            o.qos.level()
                | (u8::from(o.no_local) << 2)
                | (u8::from(o.retain_as_published) << 3)
                | (retain_handling << 4),
        );
    }
    Ok(())
}

fn write_suback(p: &SubAck, version: ProtocolVersion, s: &mut impl Sink) -> Result<(), Fault> {
    put_u16(s, p.packet_id.get());
    write_properties(
        &p.properties,
        version,
        PropertyContext::SubAck,
        "properties",
        s,
    )?;
    for reason in &p.reasons {
        let problem = if version.is_v5() && !reason.allowed_in(PacketType::SubAck) {
            Some(Problem::InvalidReasonCode(reason.code()))
        } else if !version.is_v5() && !reason.in_v3_suback() {
            Some(Problem::NotInVersion)
        } else {
            None
        };
        if let Some(problem) = problem {
            return Err(Fault::new(problem, "reason code"));
        }
        put_u8(s, reason.code());
    }
    Ok(())
}

fn write_unsubscribe(
    p: &Unsubscribe,
    version: ProtocolVersion,
    s: &mut impl Sink,
) -> Result<(), Fault> {
    if p.filters.is_empty() {
        return Err(Fault::new(Problem::NoTopicFilters, "payload"));
    }
    put_u16(s, p.packet_id.get());
    write_properties(
        &p.properties,
        version,
        PropertyContext::Unsubscribe,
        "properties",
        s,
    )?;
    for filter in &p.filters {
        put_string(s, filter.as_mqtt_string());
    }
    Ok(())
}

fn write_unsuback(p: &UnsubAck, version: ProtocolVersion, s: &mut impl Sink) -> Result<(), Fault> {
    put_u16(s, p.packet_id.get());
    write_properties(
        &p.properties,
        version,
        PropertyContext::UnsubAck,
        "properties",
        s,
    )?;
    if !version.is_v5() && !p.reasons.is_empty() {
        return Err(Fault::new(Problem::NotInVersion, "reason code"));
    }
    for reason in &p.reasons {
        if !reason.allowed_in(PacketType::UnsubAck) {
            return Err(Fault::new(
                Problem::InvalidReasonCode(reason.code()),
                "reason code",
            ));
        }
        put_u8(s, reason.code());
    }
    Ok(())
}

#[cfg(test)]
#[path = "packet_tests.rs"]
mod tests;
