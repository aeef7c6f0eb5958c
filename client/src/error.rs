//! The client's error type. [`Error`] is `Clone` because one failure (a
//! closed channel, a lost connection) is handed to every call, consumer and
//! confirm waiting on it; closes sent by the broker carry its
//! [`CloseReason`] with the reply code and text.

use leveret_protocol::{ReplyCode, ShortStrTooLong};
use std::fmt;
use std::sync::Arc;

/// The result type of this crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// Why the broker closed a channel or the connection: the arguments of its
/// `channel.close` or `connection.close`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CloseReason {
    /// The reply code as sent (see [`CloseReason::reply_code`]).
    pub code: u16,
    /// The broker's reply text, e.g. `NOT_FOUND - no queue 'x' in vhost '/'`.
    pub text: String,
    /// Class of the method that caused the close (0 if none).
    pub class_id: u16,
    /// Method that caused the close (0 if none).
    pub method_id: u16,
}

impl CloseReason {
    /// The reply code, if it is one the spec defines.
    pub fn reply_code(&self) -> Option<ReplyCode> {
        ReplyCode::from_code(self.code)
    }
}

impl fmt::Display for CloseReason {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} {}", self.code, self.text)?;
        if self.class_id != 0 {
            match leveret_protocol::Method::name_of(self.class_id, self.method_id) {
                Some(name) => write!(f, " (in reply to {name})")?,
                None => write!(f, " (in reply to {}.{})", self.class_id, self.method_id)?,
            }
        }
        Ok(())
    }
}

/// Everything that can go wrong.
#[derive(Debug, Clone, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// The connection URI could not be parsed.
    #[error("invalid AMQP URI: {0}")]
    InvalidUri(String),
    /// An argument the client can check locally is invalid (a name longer
    /// than 255 bytes, a confirm wait on a channel not in confirm mode…).
    #[error("invalid argument: {0}")]
    InvalidArgument(String),
    /// Socket error, including the broker closing the socket without
    /// `connection.close`.
    #[error("I/O error: {0}")]
    Io(Arc<std::io::Error>),
    /// Connecting and the handshake took longer than `connection_timeout`.
    #[error("connection attempt timed out")]
    ConnectTimeout,
    /// The broker broke the protocol (a malformed or unexpected frame), or
    /// offered nothing this client can use (no PLAIN mechanism).
    #[error("protocol error: {0}")]
    Protocol(String),
    /// Nothing was heard from the broker for two heartbeat intervals.
    #[error("missed heartbeats from the broker")]
    MissedHeartbeats,
    /// The broker closed the channel (`channel.close`): every later call on
    /// the channel fails with this error.
    #[error("channel closed by the broker: {0}")]
    ChannelClosed(CloseReason),
    /// The broker closed the connection (`connection.close`).
    #[error("connection closed by the broker: {0}")]
    ConnectionClosed(CloseReason),
    /// This client closed the channel or connection.
    #[error("closed by the client")]
    Closed,
    /// TLS could not be set up: a certificate or key file that cannot be
    /// read, or a server name that is not one.
    #[error("TLS: {0}")]
    Tls(String),
    /// Every channel number up to `channel_max` is in use.
    #[error("no free channel number (channel_max {0})")]
    ChannelsExhausted(u16),
}

impl Error {
    /// The broker's reply code, for closes sent by the broker.
    pub fn reply_code(&self) -> Option<ReplyCode> {
        self.close_reason().and_then(CloseReason::reply_code)
    }

    /// The broker's close arguments, for closes sent by the broker.
    pub fn close_reason(&self) -> Option<&CloseReason> {
        match self {
            Error::ChannelClosed(reason) | Error::ConnectionClosed(reason) => Some(reason),
            _ => None,
        }
    }

    pub(crate) fn io(error: std::io::Error) -> Self {
        Error::Io(Arc::new(error))
    }
}

impl From<std::io::Error> for Error {
    fn from(error: std::io::Error) -> Self {
        Error::io(error)
    }
}

impl From<ShortStrTooLong> for Error {
    fn from(error: ShortStrTooLong) -> Self {
        Error::InvalidArgument(error.to_string())
    }
}
