//! # leveret-protocol
//!
//! The AMQP 0.9.1 codec shared by the Leveret broker and client: pure data
//! and encoding, no I/O and no async runtime.
//!
//! Decoding is streaming: [`decode_frame`] takes a whole frame off a read
//! buffer or says more bytes are needed, checks the declared size against
//! `frame_max` before buffering a payload, and hands out payloads as
//! `Bytes` slices of the read buffer, so message bodies are never copied.
//! Encoding appends to a `BytesMut`.
//!
//! ```
//! use bytes::BytesMut;
//! use leveret_protocol::{decode_frame, encode_method, Frame, Method, QueueDeclare, ShortStr};
//!
//! let mut buf = BytesMut::new();
//! let declare = QueueDeclare { queue: ShortStr::from_static("tasks"), durable: true, ..Default::default() };
//! encode_method(1, &declare.clone().into(), &mut buf);
//! let frame = decode_frame(&mut buf, 4096).unwrap().unwrap();
//! assert_eq!(frame, Frame::Method { channel: 1, method: Method::QueueDeclare(declare) });
//! ```
//!
//! # Layout
//! - [`frame`]: protocol header, frame envelope, streaming decode, encode and body splitting.
//! - [`method`]: the one table of every class and method, generating [`Method`] and a struct per method.
//! - [`properties`]: content headers and the fourteen basic properties.
//! - `outgoing`: [`Outgoing`], a client's items in sending order (methods, publishes with their content).
//! - [`handoff`]: the bounded queue those items cross to a writer or an in-process broker, holding no room while empty.
//! - [`types`]: short strings, field values, tables and arrays.
//! - [`reply`]: reply codes and whether they close a channel or the connection.
//! - [`error`]: [`DecodeError`], with the reply code each error calls for.
//! - `wire`: nom parsers and encoders for the argument types.
#![deny(missing_docs)]
#![forbid(unsafe_code)]

pub mod error;
pub mod frame;
pub mod handoff;
#[cfg(feature = "json")]
pub mod json;
pub mod method;
mod outgoing;
pub mod properties;
pub mod reply;
pub mod types;
mod wire;

pub use error::{DecodeError, SyntaxProblem};
pub use frame::{
    check_frame, check_protocol_header, decode_frame, encode_content, encode_header, encode_method,
    parse_frame, Frame, FrameCheck, ProtocolHeaderCheck, FRAME_END, FRAME_MIN_SIZE, FRAME_OVERHEAD,
    LEGACY_0_9_HEADER, PROTOCOL_HEADER,
};
pub use method::*;
pub use outgoing::Outgoing;
pub use properties::{BasicProperties, ContentHeader};
pub use reply::{ErrorScope, ReplyCode};
pub use types::{Decimal, FieldArray, FieldTable, FieldValue, LongStr, ShortStr, ShortStrTooLong};
