//! [`FrameSource`]: what the connection loop needs of where its frames
//! come from, and [`ReadError`], why reading from one stopped. Two kinds
//! implement it: [`FrameReader`](super::reader::FrameReader),
//! which parses a byte stream (TCP, TLS, the in-process byte pipe), and
//! [`DirectFrames`](super::direct::DirectFrames), which receives the frame
//! values of an in-process client as they are, with nothing to parse, and
//! its publishes whole ([`WholePublish`]).
//!
//! Uses the channel's whole publish; the connection module drives it.

use crate::channel::WholePublish;
use leveret_protocol::{DecodeError, Frame};
use std::future::Future;

/// Why reading stopped.
#[derive(Debug, thiserror::Error)]
pub(super) enum ReadError {
    #[error("closed by peer")]
    Closed,
    #[error("{0}")]
    Io(std::io::Error),
    #[error("{0}")]
    Decode(DecodeError),
    #[error("timed out")]
    TimedOut,
}

/// Where a connection's frames come from.
pub(super) trait FrameSource: Send {
    /// The next input if it is a whole publish already received as one
    /// value (nothing to parse or assemble); taken off the input. Only a
    /// source of values has them, and only on an open channel's number
    /// (never 0): otherwise the input comes as frames.
    fn buffered_publish(&mut self) -> Option<WholePublish> {
        None
    }

    /// The next whole frame already received, if any. A frame that is not
    /// acceptable (too large, undecodable) is an error and has been taken.
    fn buffered_frame(&mut self) -> Result<Option<Frame>, DecodeError>;

    /// Waits for more input; `Closed` once the peer has gone.
    fn fill(&mut self) -> impl Future<Output = Result<(), ReadError>> + Send;

    /// The next frame, waiting for it; `Closed` on a clean end of stream.
    fn next(&mut self) -> impl Future<Output = Result<Frame, ReadError>> + Send {
        async move {
            loop {
                if let Some(frame) = self.buffered_frame().map_err(ReadError::Decode)? {
                    return Ok(frame);
                }
                self.fill().await?;
            }
        }
    }

    /// Whether the protocol header has arrived and is ours.
    fn protocol_header(&mut self) -> impl Future<Output = Result<bool, ReadError>> + Send;

    /// Resolves once the peer has gone, without reading what it sent
    /// before (a blocked publisher that goes away still ends). Never
    /// resolves where the transport cannot tell.
    fn hung_up(&self) -> impl Future<Output = ()> + Send + '_;

    /// Accepts frames up to the negotiated `frame_max` from now on.
    fn set_frame_max(&mut self, frame_max: u32);

    /// Whether the source holds buffer space it could give back.
    fn holds_spare(&self) -> bool;

    /// Gives back spare buffer space: the connection has been idle.
    fn release_spare(&mut self);

    /// Reads and drops whatever the peer still sends until it goes away
    /// (after input that cannot be parsed, so that the peer still gets
    /// the `connection.close` that explains why).
    fn discard_input(&mut self) -> impl Future<Output = ()> + Send;
}
