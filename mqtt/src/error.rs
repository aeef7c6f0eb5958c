//! The codec's errors: [`DecodeError`] for what a peer sent, with the
//! reason code (or MQTT 3.1.1 reply) the session answers it with, and
//! [`EncodeError`] for a packet that cannot be written in the version asked
//! for. [`Problem`] says what was wrong with a field, on both sides.

use crate::packet::PacketType;
use crate::properties::PropertyId;
use crate::reason::ReasonCode;
use crate::topic::TopicError;
use crate::version::ProtocolVersion;

/// What was wrong with a field of a packet.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Problem {
    /// The packet ended before the field did.
    Truncated,
    /// Bytes were left over after the last field.
    TrailingBytes(usize),
    /// A string was not well-formed UTF-8 (surrogates and overlong forms
    /// included) (MQTT-1.5.3-1).
    InvalidUtf8,
    /// A string contained U+0000 (MQTT-1.5.3-2).
    NullCharacter,
    /// A string or binary value longer than 65,535 bytes, or a property
    /// list longer than a variable byte integer can say (encoding only).
    TooLong(usize),
    /// A variable byte integer used more bytes than its value needs (MQTT-1.5.5-1).
    NonMinimalInteger,
    /// A variable byte integer continued past its fourth byte.
    IntegerTooLong,
    /// Reserved bits in a flags or options byte were not zero.
    ReservedBitsSet,
    /// A QoS of 3.
    InvalidQos,
    /// Will QoS or Will Retain set without the Will Flag (MQTT-3.1.2-11, -13, -15).
    WillFieldsWithoutWill,
    /// MQTT 3.1.1's CONNECT had the password flag without the user name flag (MQTT-3.1.2-22).
    PasswordWithoutUsername,
    /// The protocol name and level are not MQTT 3.1, 3.1.1 or 5.0.
    UnsupportedProtocol(u8),
    /// A packet identifier of 0 where one is required (MQTT-2.2.1-3).
    ZeroPacketId,
    /// A property identifier the specification does not define.
    UnknownProperty(u32),
    /// A property that is not allowed on this packet.
    PropertyNotAllowed(PropertyId),
    /// A property given more than once where only one is allowed.
    DuplicateProperty(PropertyId),
    /// A property value out of its range (a Receive Maximum of 0, a byte
    /// flag other than 0 or 1, a Maximum QoS of 2…).
    InvalidPropertyValue(PropertyId),
    /// Authentication Data without an Authentication Method.
    AuthDataWithoutMethod,
    /// A reason code this packet may not carry.
    InvalidReasonCode(u8),
    /// A topic name that is not valid.
    InvalidTopicName(TopicError),
    /// A topic filter that is not valid.
    InvalidTopicFilter(TopicError),
    /// A PUBLISH with an empty topic and no Topic Alias (MQTT 5.0, 3.3.2.1).
    EmptyTopicWithoutAlias,
    /// A SUBSCRIBE or UNSUBSCRIBE without topic filters (MQTT-3.8.3-2, MQTT-3.10.3-2).
    NoTopicFilters,
    /// Subscription options with a QoS or Retain Handling of 3.
    InvalidSubscriptionOptions,
    /// No Local on a shared subscription (MQTT-3.8.3-4).
    NoLocalOnSharedSubscription,
    /// The DUP flag on a QoS 0 PUBLISH (MQTT-3.3.1-2; encoding only, a
    /// decoder reports it as [`DecodeError::BadFlags`]).
    DupOnQos0,
    /// Something this protocol version cannot carry (properties, reason
    /// codes or subscription options before 5.0, AUTH before 5.0).
    NotInVersion,
}

impl Problem {
    /// The MQTT 5.0 reason code a receiver disconnects with: 0x81 for bytes
    /// that cannot be parsed, 0x82 for well-formed values the protocol
    /// forbids, 0x8F and 0x90 for bad topic filters and names, 0x84 for a
    /// protocol it does not speak.
    pub fn reason_code(self) -> ReasonCode {
        match self {
            Problem::Truncated
            | Problem::TrailingBytes(_)
            | Problem::InvalidUtf8
            | Problem::NullCharacter
            | Problem::TooLong(_)
            | Problem::NonMinimalInteger
            | Problem::IntegerTooLong
            | Problem::ReservedBitsSet
            | Problem::InvalidQos
            | Problem::WillFieldsWithoutWill
            | Problem::PasswordWithoutUsername
            | Problem::UnknownProperty(_)
            | Problem::DupOnQos0 => ReasonCode::MalformedPacket,
            // Topic alias 0 (MQTT-3.3.2-8): 0x94, as Mosquitto answers it.
            Problem::InvalidPropertyValue(PropertyId::TopicAlias) => ReasonCode::TopicAliasInvalid,
            Problem::ZeroPacketId
            | Problem::PropertyNotAllowed(_)
            | Problem::DuplicateProperty(_)
            | Problem::InvalidPropertyValue(_)
            | Problem::AuthDataWithoutMethod
            | Problem::InvalidReasonCode(_)
            | Problem::EmptyTopicWithoutAlias
            | Problem::NoTopicFilters
            | Problem::InvalidSubscriptionOptions
            | Problem::NoLocalOnSharedSubscription
            | Problem::NotInVersion => ReasonCode::ProtocolError,
            Problem::InvalidTopicName(_) => ReasonCode::TopicNameInvalid,
            Problem::InvalidTopicFilter(_) => ReasonCode::TopicFilterInvalid,
            Problem::UnsupportedProtocol(_) => ReasonCode::UnsupportedProtocolVersion,
        }
    }
}

impl std::fmt::Display for Problem {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Problem::Truncated => f.write_str("truncated"),
            Problem::TrailingBytes(n) => write!(f, "{n} trailing bytes"),
            Problem::InvalidUtf8 => f.write_str("invalid UTF-8"),
            Problem::NullCharacter => f.write_str("U+0000 in a string"),
            Problem::TooLong(n) => write!(f, "too long ({n} bytes)"),
            Problem::NonMinimalInteger => {
                f.write_str("variable byte integer not in its shortest form")
            }
            Problem::IntegerTooLong => f.write_str("variable byte integer longer than 4 bytes"),
            Problem::ReservedBitsSet => f.write_str("reserved bits set"),
            Problem::InvalidQos => f.write_str("QoS 3"),
            Problem::WillFieldsWithoutWill => {
                f.write_str("will QoS or retain without the will flag")
            }
            Problem::PasswordWithoutUsername => f.write_str("password flag without user name flag"),
            Problem::UnsupportedProtocol(level) => {
                write!(f, "unsupported protocol (level {level})")
            }
            Problem::ZeroPacketId => f.write_str("packet identifier 0"),
            Problem::UnknownProperty(id) => write!(f, "unknown property {id:#04x}"),
            Problem::PropertyNotAllowed(id) => write!(f, "property {id:?} not allowed here"),
            Problem::DuplicateProperty(id) => write!(f, "property {id:?} given twice"),
            Problem::InvalidPropertyValue(id) => write!(f, "invalid value for property {id:?}"),
            Problem::AuthDataWithoutMethod => f.write_str("authentication data without a method"),
            Problem::InvalidReasonCode(code) => {
                write!(f, "reason code {code:#04x} not allowed here")
            }
            Problem::InvalidTopicName(e) => write!(f, "invalid topic name: {e}"),
            Problem::InvalidTopicFilter(e) => write!(f, "invalid topic filter: {e}"),
            Problem::EmptyTopicWithoutAlias => f.write_str("empty topic without a topic alias"),
            Problem::NoTopicFilters => f.write_str("no topic filters"),
            Problem::InvalidSubscriptionOptions => f.write_str("QoS or retain handling of 3"),
            Problem::NoLocalOnSharedSubscription => {
                f.write_str("no local on a shared subscription")
            }
            Problem::DupOnQos0 => f.write_str("DUP on a QoS 0 publish"),
            Problem::NotInVersion => f.write_str("not expressible in this protocol version"),
        }
    }
}

/// Everything that can go wrong decoding MQTT bytes. Never a panic: every
/// malformed input ends up here.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DecodeError {
    /// The packet's declared size (fixed header included) exceeds the
    /// receiver's maximum. Reported from the fixed header alone, before any
    /// of the packet is buffered.
    #[error("packet of {size} bytes exceeds the maximum packet size of {max} bytes")]
    PacketTooLarge {
        /// The whole packet's size as declared by its remaining length.
        size: u64,
        /// The limit in force.
        max: u32,
    },
    /// The remaining length was longer than 4 bytes or not in its shortest form.
    #[error("malformed remaining length: {0}")]
    MalformedRemainingLength(Problem),
    /// Packet type 0, or 15 (AUTH) before MQTT 5.0.
    #[error("unknown packet type {0}")]
    UnknownPacketType(u8),
    /// The fixed header's flags are not the ones this packet type requires
    /// (MQTT-2.2.2-1), or a PUBLISH has QoS 3 or DUP on QoS 0.
    #[error("{packet:?} with fixed header flags {flags:#06b}")]
    BadFlags {
        /// The packet type.
        packet: PacketType,
        /// The low four bits of the first byte.
        flags: u8,
    },
    /// A field of the packet was invalid.
    #[error("{packet:?}{}{field}: {problem}", if field.is_empty() { "" } else { " " })]
    Invalid {
        /// The packet type.
        packet: PacketType,
        /// The field that failed.
        field: &'static str,
        /// What was wrong.
        problem: Problem,
    },
}

impl DecodeError {
    /// The MQTT 5.0 reason code to refuse the packet with: in a DISCONNECT
    /// once connected, in the CONNACK if the error is in the CONNECT. A 3.1.1
    /// session closes the connection instead (see [`DecodeError::connack_refusal`]
    /// for the one case where it answers first).
    pub fn reason_code(&self) -> ReasonCode {
        match self {
            DecodeError::PacketTooLarge { .. } => ReasonCode::PacketTooLarge,
            DecodeError::MalformedRemainingLength(_)
            | DecodeError::UnknownPacketType(_)
            | DecodeError::BadFlags { .. } => ReasonCode::MalformedPacket,
            DecodeError::Invalid { problem, .. } => problem.reason_code(),
        }
    }

    /// For a CONNECT naming a protocol this codec does not speak: the
    /// version whose CONNACK to answer with, before closing. A client that
    /// asked for level 5 gets a 5.0 CONNACK with 0x84 (Unsupported Protocol
    /// Version); any other gets a 3.1.1 CONNACK with return code 0x01
    /// (unacceptable protocol version), which is what
    /// [`ReasonCode::UnsupportedProtocolVersion`] encodes to in 3.1.1.
    pub fn connack_refusal(&self) -> Option<ProtocolVersion> {
        match self {
            DecodeError::Invalid {
                problem: Problem::UnsupportedProtocol(level),
                ..
            } => Some(if *level == 5 {
                ProtocolVersion::V5
            } else {
                ProtocolVersion::V3_1_1
            }),
            _ => None,
        }
    }
}

/// A packet that cannot be encoded as asked.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum EncodeError {
    /// The packet's remaining length would exceed 268,435,455 bytes.
    #[error("remaining length of {remaining_length} bytes exceeds MQTT's 268435455")]
    PacketTooLarge {
        /// The remaining length the packet would have.
        remaining_length: usize,
    },
    /// A field breaks a rule of the protocol version asked for.
    #[error("{packet:?}{}{field}: {problem}", if field.is_empty() { "" } else { " " })]
    Invalid {
        /// The packet type.
        packet: PacketType,
        /// The field that failed.
        field: &'static str,
        /// What was wrong.
        problem: Problem,
    },
}
