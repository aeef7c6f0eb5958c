//! [`Outgoing`]: what a client sends, in the order it is to go out. A
//! client's socket writer encodes these into frames; an in-process client
//! hands them to an embedded Leveret as they are (its frame-value link),
//! so both ends share this one type.

use crate::{BasicProperties, BasicPublish, Method};
use bytes::Bytes;

/// One item a client sends.
///
/// A publish's properties are boxed: decoded, they are ~450 bytes, and an
/// item is moved several times on its way (into and out of a channel's
/// slot, through the receiver's calls), each move a copy; an embedded
/// Leveret keeps the box for the message it routes, so on its value link
/// the allocation replaces one it would make anyway.
#[derive(Debug, Clone, PartialEq)]
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
        properties: Box<BasicProperties>,
        /// The body (a socket writer splits it by frame_max).
        body: Bytes,
    },
    /// Everything before this goes out; then the client's side ends.
    Shutdown,
}
