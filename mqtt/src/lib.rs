//! # leveret-mqtt
//!
//! The MQTT codec of Leveret: every control packet of MQTT 3.1.1 and 5.0
//! (and 3.1, which 3.1.1 kept on the wire), as pure data and encoding, no
//! I/O and no async runtime. The session layer (listeners, sessions, the
//! mapping onto AMQP queues) is built on it elsewhere.
//!
//! Decoding is streaming: [`decode_packet`] takes a whole packet off a
//! read buffer or says more bytes are needed, refuses a packet larger than
//! the caller's maximum from its fixed header before buffering the rest,
//! and hands out the PUBLISH payload, strings and binary data as `Bytes`
//! slices of the read buffer, so message bodies are never copied. The
//! rules a single packet can break are checked (`docs/mqtt.md` lists them
//! and the few left to the session), and each [`DecodeError`] carries the
//! reason code the session answers with ([`DecodeError::reason_code`],
//! [`DecodeError::connack_refusal`]).
//! Encoding appends to a `BytesMut` and checks the same rules, so whatever
//! encodes, decodes.
//!
//! ```
//! use bytes::{Bytes, BytesMut};
//! use leveret_mqtt::{decode_packet, Delivery, Packet, Properties, ProtocolVersion, Publish, TopicName};
//!
//! let publish = Packet::Publish(Publish {
//!     dup: false,
//!     delivery: Delivery::AtLeastOnce(7.try_into().unwrap()),
//!     retain: false,
//!     topic: TopicName::from_static("sensors/lidar"),
//!     properties: Properties::default(),
//!     payload: Bytes::from_static(b"42"),
//! });
//! let mut buf = BytesMut::new();
//! publish.encode(ProtocolVersion::V5, &mut buf).unwrap();
//! let decoded = decode_packet(&mut buf, ProtocolVersion::V5, 1 << 20).unwrap().unwrap();
//! assert_eq!(decoded, publish);
//! ```
//!
//! # Layout
//! - [`frame`]: the fixed header, streaming decode with the size limit, encoding.
//! - [`packet`]: the fifteen packets as types, and each one's body by version.
//! - [`properties`]: 5.0's properties, the packets each may appear on, their checks.
//! - [`reason`]: reason codes, which packets carry each, 3.1.1's return codes.
//! - [`topic`]: topic names and filters, wildcards, shared subscriptions.
//! - [`string`]: MQTT's UTF-8 string, checked.
//! - [`qos`]: QoS levels, packet identifiers, a PUBLISH's delivery.
//! - [`version`]: protocol versions and their names.
//! - [`error`]: [`DecodeError`], [`EncodeError`] and [`Problem`], with reason codes.
//! - `wire`: nom parsers and encoders for integers, strings and binary data.
#![deny(missing_docs)]
#![forbid(unsafe_code)]

pub mod error;
pub mod frame;
pub mod packet;
pub mod properties;
pub mod qos;
pub mod reason;
pub mod string;
pub mod topic;
pub mod version;
mod wire;

pub use error::{DecodeError, EncodeError, Problem};
pub use frame::{check_packet, decode_packet, PacketCheck, MAX_PACKET_SIZE};
pub use packet::{
    Auth, ConnAck, Connect, Disconnect, Packet, PacketType, PubResponse, Publish, RetainHandling,
    SubAck, Subscribe, Subscription, SubscriptionOptions, UnsubAck, Unsubscribe, Will,
};
pub use properties::{Properties, PropertyContext, PropertyId, PropertyValues};
pub use qos::{Delivery, PacketId, QoS};
pub use reason::ReasonCode;
pub use string::{MqttString, StringError};
pub use topic::{SharedFilter, TopicError, TopicFilter, TopicName};
pub use version::ProtocolVersion;
