//! The codec's one error type, [`DecodeError`], and how each error maps to
//! the AMQP reply code a peer must be closed with.

use crate::reply::ReplyCode;

/// Why a value inside a frame could not be decoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SyntaxProblem {
    /// The frame ended before the value did.
    Truncated,
    /// Bytes were left over after the last argument.
    TrailingBytes(usize),
    /// A field table or array held an unknown type tag.
    BadFieldTag(u8),
    /// A content header named properties this class does not have.
    UnknownProperty,
    /// A value was out of its allowed range.
    InvalidValue,
}

impl std::fmt::Display for SyntaxProblem {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SyntaxProblem::Truncated => f.write_str("truncated"),
            SyntaxProblem::TrailingBytes(n) => write!(f, "{n} trailing bytes"),
            SyntaxProblem::BadFieldTag(t) => write!(f, "unknown field type tag {t:#04x}"),
            SyntaxProblem::UnknownProperty => f.write_str("unknown property flag"),
            SyntaxProblem::InvalidValue => f.write_str("invalid value"),
        }
    }
}

/// Everything that can go wrong decoding AMQP bytes. Never a panic: every
/// malformed input ends up here, with where it failed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DecodeError {
    /// A frame declared a payload larger than the negotiated `frame_max`.
    #[error("frame payload of {size} bytes exceeds frame_max of {frame_max} bytes")]
    FrameTooLarge {
        /// The payload size the frame declared.
        size: u64,
        /// The limit in force.
        frame_max: u32,
    },
    /// The octet after the payload was not 0xCE.
    #[error("frame end octet is {found:#04x}, expected 0xce")]
    BadFrameEnd {
        /// What was found.
        found: u8,
    },
    /// The frame type octet is not method, header, body or heartbeat.
    #[error("unknown frame type {0}")]
    UnknownFrameType(u8),
    /// A heartbeat frame on a channel other than 0, or with a payload.
    #[error("heartbeat frame on channel {channel} with {size} payload bytes")]
    BadHeartbeat {
        /// The channel it arrived on.
        channel: u16,
        /// Its payload size.
        size: u32,
    },
    /// A method frame named a class and method this codec does not know.
    #[error("unknown method {class_id}.{method_id}")]
    UnknownMethod {
        /// Class id.
        class_id: u16,
        /// Method id.
        method_id: u16,
    },
    /// A value inside a frame was malformed.
    #[error("malformed {location}{}{field}: {problem}", if field.is_empty() { "" } else { "." })]
    Syntax {
        /// The method name (`"basic.publish"`) or structure (`"content header"`).
        location: &'static str,
        /// The argument or property that failed, if known.
        field: &'static str,
        /// What was wrong.
        problem: SyntaxProblem,
    },
}

impl DecodeError {
    /// The reply code to close the connection with: every decode error is a
    /// connection-level error. The choices follow RabbitMQ 3.10, observed on
    /// the wire: anything that cannot be decoded (including malformed
    /// arguments) is 501 FRAME_ERROR, a heartbeat on a channel other than 0
    /// is 505 UNEXPECTED_FRAME, an unknown method is 503 COMMAND_INVALID.
    pub fn reply_code(&self) -> ReplyCode {
        match self {
            DecodeError::BadHeartbeat { channel, .. } if *channel != 0 => {
                ReplyCode::UnexpectedFrame
            }
            DecodeError::FrameTooLarge { .. }
            | DecodeError::BadFrameEnd { .. }
            | DecodeError::UnknownFrameType(_)
            | DecodeError::BadHeartbeat { .. }
            | DecodeError::Syntax { .. } => ReplyCode::FrameError,
            DecodeError::UnknownMethod { .. } => ReplyCode::CommandInvalid,
        }
    }

    /// The (class, method) ids to report in connection.close, if the error
    /// is tied to one method.
    pub fn method_ids(&self) -> (u16, u16) {
        match self {
            DecodeError::UnknownMethod {
                class_id,
                method_id,
            } => (*class_id, *method_id),
            DecodeError::Syntax { location, .. } => {
                crate::method::Method::ids_of(location).unwrap_or((0, 0))
            }
            _ => (0, 0),
        }
    }
}
