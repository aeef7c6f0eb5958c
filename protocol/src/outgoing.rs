//! [`Outgoing`]: what a client sends, in the order it is to go out. A
//! client's socket writer encodes these into frames; an in-process client
//! hands them to an embedded Leveret as they are (its frame-value link),
//! so both ends share this one type.

use crate::{BasicProperties, BasicPublish, Method};
use bytes::Bytes;

/// One item a client sends.
///
/// `Publish` is large (the properties are inline) but is also the common
/// item: boxing it would cost an allocation per message, while a bounded
/// channel's slots are allocated once and reused.
#[derive(Debug, Clone, PartialEq)]
#[allow(clippy::large_enum_variant)]
pub enum Outgoing {
    /// A method without content.
    Method {
        /// Channel number.
        channel: u16,
        /// The method.
        method: Method,
    },
    /// basic.publish with its content, kept together so no other frame on
    /// the channel can come between them.
    Publish {
        /// Channel number.
        channel: u16,
        /// The method.
        method: BasicPublish,
        /// The content's properties.
        properties: BasicProperties,
        /// The body (a socket writer splits it by frame_max).
        body: Bytes,
    },
    /// Everything before this goes out; then the client's side ends.
    Shutdown,
}
