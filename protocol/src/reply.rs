//! Reply codes: the spec's constants, their names, and whether an error
//! closes a channel (soft) or the whole connection (hard).

/// What an error closes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ErrorScope {
    /// Not an error (200 reply-success).
    None,
    /// A soft error: the channel is closed with channel.close.
    Channel,
    /// A hard error: the connection is closed with connection.close.
    Connection,
}

macro_rules! reply_codes {
    ($($(#[$doc:meta])* $variant:ident = $code:literal, $name:literal, $scope:ident;)*) => {
        /// An AMQP 0.9.1 reply code.
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
        #[repr(u16)]
        pub enum ReplyCode {
            $($(#[$doc])* $variant = $code,)*
        }

        impl ReplyCode {
            /// The numeric code sent on the wire.
            pub fn code(self) -> u16 {
                self as u16
            }

            /// The spec's name, as RabbitMQ prefixes reply texts with it (`NOT_FOUND`).
            pub fn name(self) -> &'static str {
                match self {
                    $(ReplyCode::$variant => $name,)*
                }
            }

            /// Whether the error closes a channel or the connection.
            pub fn scope(self) -> ErrorScope {
                match self {
                    $(ReplyCode::$variant => ErrorScope::$scope,)*
                }
            }

            /// The reply code for a number, if the spec defines it.
            pub fn from_code(code: u16) -> Option<Self> {
                match code {
                    $($code => Some(ReplyCode::$variant),)*
                    _ => None,
                }
            }
        }
    };
}

reply_codes! {
    /// 200: success.
    Success = 200, "REPLY_SUCCESS", None;
    /// 311: content too large for the server to accept.
    ContentTooLarge = 311, "CONTENT_TOO_LARGE", Channel;
    /// 312: a mandatory message could not be routed (RabbitMQ's extension to the spec's codes).
    NoRoute = 312, "NO_ROUTE", Channel;
    /// 313: an immediate message had no consumer.
    NoConsumers = 313, "NO_CONSUMERS", Channel;
    /// 320: an operator closed the connection.
    ConnectionForced = 320, "CONNECTION_FORCED", Connection;
    /// 402: unknown virtual host path.
    InvalidPath = 402, "INVALID_PATH", Connection;
    /// 403: access refused.
    AccessRefused = 403, "ACCESS_REFUSED", Channel;
    /// 404: entity not found.
    NotFound = 404, "NOT_FOUND", Channel;
    /// 405: entity locked by another connection (exclusive queue).
    ResourceLocked = 405, "RESOURCE_LOCKED", Channel;
    /// 406: a precondition failed (redeclare mismatch, unknown delivery tag…).
    PreconditionFailed = 406, "PRECONDITION_FAILED", Channel;
    /// 501: malformed frame.
    FrameError = 501, "FRAME_ERROR", Connection;
    /// 502: malformed method arguments.
    SyntaxError = 502, "SYNTAX_ERROR", Connection;
    /// 503: a method not allowed in this state.
    CommandInvalid = 503, "COMMAND_INVALID", Connection;
    /// 504: a channel that is not open, or wrongly used.
    ChannelError = 504, "CHANNEL_ERROR", Connection;
    /// 505: a frame that was not expected here.
    UnexpectedFrame = 505, "UNEXPECTED_FRAME", Connection;
    /// 506: the server ran out of a resource.
    ResourceError = 506, "RESOURCE_ERROR", Connection;
    /// 530: not allowed (for example a vhost the user may not use).
    NotAllowed = 530, "NOT_ALLOWED", Connection;
    /// 540: a method or feature the server does not implement.
    NotImplemented = 540, "NOT_IMPLEMENTED", Connection;
    /// 541: internal error.
    InternalError = 541, "INTERNAL_ERROR", Connection;
}

impl std::fmt::Display for ReplyCode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} {}", self.code(), self.name())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scopes_follow_the_spec() {
        assert_eq!(ReplyCode::NotFound.scope(), ErrorScope::Channel);
        assert_eq!(ReplyCode::PreconditionFailed.scope(), ErrorScope::Channel);
        assert_eq!(ReplyCode::FrameError.scope(), ErrorScope::Connection);
        assert_eq!(ReplyCode::NotImplemented.scope(), ErrorScope::Connection);
        assert_eq!(ReplyCode::Success.scope(), ErrorScope::None);
    }

    #[test]
    fn codes_round_trip() {
        for code in 0..1000u16 {
            if let Some(reply) = ReplyCode::from_code(code) {
                assert_eq!(reply.code(), code);
            }
        }
        assert_eq!(ReplyCode::from_code(404), Some(ReplyCode::NotFound));
        assert_eq!(ReplyCode::NotFound.name(), "NOT_FOUND");
        assert_eq!(ReplyCode::from_code(999), None);
    }
}
