//! The broker's protocol error: a reply code that knows its scope, the text
//! a person can act on, and the method that caused it.

use leveret_protocol::{ErrorScope, Method, ReplyCode};
use std::fmt;

/// An AMQP error to report with channel.close or connection.close.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub struct AmqpError {
    /// The reply code; its scope says whether the channel or the connection closes.
    pub code: ReplyCode,
    /// Reply text, prefixed with the code's name as RabbitMQ does.
    pub text: String,
    /// Class id of the method that failed (0 if none).
    pub class_id: u16,
    /// Method id of the method that failed (0 if none).
    pub method_id: u16,
}

impl fmt::Display for AmqpError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} {}", self.code.code(), self.text)
    }
}

impl AmqpError {
    /// An error with `detail`, formatted as `"NAME - detail"`.
    pub fn new(code: ReplyCode, detail: impl fmt::Display) -> Self {
        AmqpError {
            code,
            text: format!("{} - {}", code.name(), detail),
            class_id: 0,
            method_id: 0,
        }
    }

    /// Ties the error to the method that caused it.
    pub fn during(mut self, method: &Method) -> Self {
        if self.class_id == 0 {
            self.class_id = method.class_id();
            self.method_id = method.method_id();
        }
        self
    }

    /// Ties the error to explicit method ids.
    pub fn during_ids(mut self, class_id: u16, method_id: u16) -> Self {
        if self.class_id == 0 {
            self.class_id = class_id;
            self.method_id = method_id;
        }
        self
    }

    /// Whether the error closes the whole connection.
    pub fn is_connection_error(&self) -> bool {
        self.code.scope() == ErrorScope::Connection
    }

    /// The reply text, truncated to fit a short string.
    pub fn reply_text(&self) -> leveret_protocol::ShortStr {
        let mut end = self.text.len().min(255);
        while !self.text.is_char_boundary(end) {
            end -= 1;
        }
        leveret_protocol::ShortStr::try_from(&self.text[..end]).unwrap_or_default()
    }
}

macro_rules! constructors {
    ($($fn_name:ident => $code:ident),* $(,)?) => {
        impl AmqpError {$(
            #[doc = concat!("A ", stringify!($code), " error.")]
            pub fn $fn_name(detail: impl fmt::Display) -> Self {
                AmqpError::new(ReplyCode::$code, detail)
            }
        )*}
    };
}

constructors! {
    not_found => NotFound,
    precondition_failed => PreconditionFailed,
    access_refused => AccessRefused,
    resource_locked => ResourceLocked,
    command_invalid => CommandInvalid,
    channel_error => ChannelError,
    unexpected_frame => UnexpectedFrame,
    frame_error => FrameError,
    syntax_error => SyntaxError,
    not_implemented => NotImplemented,
    not_allowed => NotAllowed,
    resource_error => ResourceError,
    internal_error => InternalError,
}

impl AmqpError {
    /// 404 for a queue that is not there (or going), as RabbitMQ words it:
    /// `no queue 'NAME' in vhost 'VHOST'`.
    pub fn no_queue(name: impl fmt::Display, vhost: impl fmt::Display) -> Self {
        AmqpError::not_found(format_args!("no queue '{name}' in vhost '{vhost}'"))
    }
}

/// Result of a protocol operation.
pub type AmqpResult<T> = Result<T, AmqpError>;
