//! In-process connections that carry values instead of bytes (the fast
//! path of an embedding application's own client): the client hands the
//! broker each [`Outgoing`] item as it built it (a method, or a
//! basic.publish with its properties and body, which reaches its channel
//! whole), and takes the broker's frames as values ([`DirectReply`]: a
//! delivery, get-ok or return comes whole, with its message's content), so
//! no frame is encoded or parsed on either side (only a publish's
//! properties are encoded once, for the message, and decoded once by the
//! client) and no writer task stands between the client and the broker in
//! either direction. The handshake, channels, permissions, routing, queues, acks,
//! limits (`max_message_size` included) and statistics are the
//! connection's one code path, the same as for a socket.
//!
//! What a client can make the broker hold is bounded as on a socket: the
//! items waiting for the connection loop ([`DIRECT_CAPACITY`]; a client
//! with more waits for room), whose bodies the client allocated and the
//! channel counts as it does any content, and the outbox's items on the way
//! back.
//!
//! A client may also take deliveries inline ([`DirectReplies::deliver_inline`]):
//! the queue's dispatch hands each to it on the dispatching thread, with no
//! outbox item and no task in between, whenever the client has handled
//! everything the outbox sent it before (counted here, so the order of
//! deliveries and methods is the outbox's).
//!
//! A client may also run the connection's loop on its own thread for a
//! publish ([`DirectLoop`], in `direct_loop`): the item is handed over
//! beside the channel, read before it, and handled where it was sent.
//!
//! Uses the connection loop, which it feeds through [`FrameSource`], and
//! the outbox, which it drains in place of the socket writer.

use super::direct_loop::{self, DirectLoop, Handed};
use super::source::{FrameSource, ReadError};
use crate::channel::WholePublish;
use crate::outbox::{Framed, InlineDeliveries, Outbound, Outbox};
use bytes::Bytes;
use leveret_protocol::handoff;
use leveret_protocol::{ContentHeader, DecodeError, Frame, Method, Outgoing, FRAME_OVERHEAD};
use std::collections::VecDeque;
use std::future::Future;
use std::sync::Arc;
use tokio::sync::oneshot;

/// Items a client may have waiting for the connection loop.
pub const DIRECT_CAPACITY: usize = 256;

/// How many outbox items the client takes between wake-ups of the queues
/// that found the outbox full (the socket writer wakes them after each
/// write; here there is no write).
const WAKE_EVERY: u32 = 64;

/// Both ends of an in-process connection, for its client: items go to the
/// broker through `to_broker` (waiting for room when the broker is behind),
/// and frames come back from [`DirectReplies`]. Dropping both ends is the
/// client going away: the broker then cleans up as for a closed socket.
#[derive(Debug)]
pub struct DirectLink {
    /// The client's items, starting with `connection.start-ok` (no
    /// protocol header: the link speaks AMQP 0.9.1 by construction).
    pub to_broker: handoff::Sender<Outgoing>,
    /// The broker's frames, starting with `connection.start`.
    pub from_broker: DirectReplies,
    /// The connection's loop, for a publish handled on the client's thread.
    pub here: DirectLoop,
}

/// The connection loop's source of an in-process client's frames: a
/// publish on a channel is handed over whole ([`WholePublish`]: its
/// properties are neither encoded into a header frame nor decoded from
/// one); every other item becomes its frames here (a publish's body as one
/// body frame: it is not parsed from a buffer, so frame_max has nothing to
/// protect).
pub(super) struct DirectFrames {
    rx: handoff::Receiver<Outgoing>,
    /// An item a client thread handed the loop: before anything in `rx`.
    handed: Arc<Handed>,
    /// An item received and not yet taken, whole or as frames.
    held: Option<Outgoing>,
    /// The frames of a publish not taken whole (a method is one frame and
    /// never waits here): empty, and without room, on an idle link.
    frames: VecDeque<Frame>,
    ended: bool,
}

impl DirectFrames {
    pub(super) fn new(rx: handoff::Receiver<Outgoing>, handed: Arc<Handed>) -> Self {
        DirectFrames {
            rx,
            handed,
            held: None,
            frames: VecDeque::new(),
            ended: false,
        }
    }

    /// The next item, if one has been received.
    fn next_item(&mut self) -> Option<Outgoing> {
        if self.ended {
            return None;
        }
        self.held
            .take()
            .or_else(|| self.handed.take())
            .or_else(|| self.rx.try_recv())
    }

    /// The next item's first frame (the others, a publish's, wait in
    /// `frames`); none at the client's end.
    fn first_frame(&mut self, item: Outgoing) -> Option<Frame> {
        match item {
            Outgoing::Method { channel, method } => Some(Frame::Method { channel, method }),
            Outgoing::Publish {
                channel,
                method,
                properties,
                body,
            } => {
                self.frames.push_back(Frame::Header {
                    channel,
                    header: ContentHeader::new(body.len() as u64, &properties),
                });
                if !body.is_empty() {
                    self.frames.push_back(Frame::Body {
                        channel,
                        payload: body,
                    });
                }
                Some(Frame::Method {
                    channel,
                    method: Method::BasicPublish(method),
                })
            }
            Outgoing::Shutdown => {
                self.ended = true;
                None
            }
        }
    }
}

impl FrameSource for DirectFrames {
    fn buffered_publish(&mut self) -> Option<WholePublish> {
        if !self.frames.is_empty() {
            return None;
        }
        match self.next_item()? {
            Outgoing::Publish {
                channel,
                method,
                properties,
                body,
            } if channel != 0 => Some(WholePublish {
                channel,
                method,
                properties,
                body,
            }),
            other => {
                self.held = Some(other);
                None
            }
        }
    }

    fn buffered_frame(&mut self) -> Result<Option<Frame>, DecodeError> {
        if let Some(frame) = self.frames.pop_front() {
            return Ok(Some(frame));
        }
        Ok(self.next_item().and_then(|item| self.first_frame(item)))
    }

    async fn fill(&mut self) -> Result<(), ReadError> {
        if !self.frames.is_empty() || self.held.is_some() || self.handed.is_full() {
            return Ok(());
        }
        if self.ended {
            return Err(ReadError::Closed);
        }
        // A client thread that hands an item runs the loop itself, with
        // no wake: each poll looks at the handed item first.
        let (handed, rx) = (&self.handed, &mut self.rx);
        let received = std::future::poll_fn(|cx| {
            if handed.is_full() {
                return std::task::Poll::Ready(None);
            }
            rx.poll_recv(cx).map(Some)
        })
        .await;
        match received {
            None => Ok(()),
            Some(Some(item)) => {
                self.held = Some(item);
                Ok(())
            }
            Some(None) => {
                self.ended = true;
                Err(ReadError::Closed)
            }
        }
    }

    async fn protocol_header(&mut self) -> Result<bool, ReadError> {
        Ok(true)
    }

    fn hung_up(&self) -> impl Future<Output = ()> + Send + '_ {
        // A client that drops its sender ends the loop at its next read;
        // while blocked, the loop learns it from the replies' end instead.
        std::future::pending()
    }

    fn set_frame_max(&mut self, _frame_max: u32) {}

    fn holds_spare(&self) -> bool {
        self.rx.holds_room() || self.frames.capacity() > 0
    }

    fn release_spare(&mut self) {
        self.rx.release_room();
        if self.frames.is_empty() {
            self.frames = VecDeque::new();
        }
    }

    async fn discard_input(&mut self) {
        self.handed.take();
        while self.rx.recv().await.is_some() {}
    }
}

/// What the connection hands its in-process client in place of starting a
/// socket writer.
pub(super) struct WriterEnd {
    /// The outbox's receiver: once it is dropped, with the client's
    /// replies, the connection sees the client gone (as when a socket
    /// writer ends).
    pub inbox: handoff::Receiver<Outbound>,
    pub outbox: Arc<Outbox>,
}

/// What an in-process client receives from the broker.
#[derive(Debug)]
pub enum DirectReply {
    /// A frame.
    Frame(Frame),
    /// A content-carrying method (deliver, get-ok, return) with its
    /// message's content, whole: what its method, content header and body
    /// frames would carry.
    Content {
        /// Channel number (never 0).
        channel: u16,
        /// The method.
        method: Method,
        /// The message's encoded property flags and list.
        properties: Bytes,
        /// The message's body.
        body: Bytes,
    },
}

/// The broker's replies for an in-process client, taken straight from the
/// connection's outbox.
pub struct DirectReplies {
    state: Replies,
    /// The frames of content on channel 0 (never sent) still to return: a
    /// method is one frame, returned as it comes, so an idle connection's
    /// replies hold no room here.
    pending: VecDeque<Frame>,
    taken: u32,
    /// Whether the client holds an item taken from the outbox (returned
    /// whole or as the frames in `pending`) that it has not yet handled:
    /// it has once it asks for the next reply with `pending` empty.
    in_hand: bool,
    /// Inline deliveries set before the outbox was handed over.
    inline: Option<Arc<dyn InlineDeliveries>>,
}

enum Replies {
    Starting(oneshot::Receiver<WriterEnd>),
    Open(WriterEnd),
    Ended,
}

impl std::fmt::Debug for DirectReplies {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DirectReplies")
            .field("state", &self.state)
            .field("pending", &self.pending.len())
            .field("in_hand", &self.in_hand)
            .finish_non_exhaustive()
    }
}

impl std::fmt::Debug for Replies {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Replies::Starting(_) => "Starting",
            Replies::Open(_) => "Open",
            Replies::Ended => "Ended",
        })
    }
}

impl DirectReplies {
    pub(super) fn new(start: oneshot::Receiver<WriterEnd>) -> Self {
        DirectReplies {
            state: Replies::Starting(start),
            pending: VecDeque::new(),
            taken: 0,
            in_hand: false,
            inline: None,
        }
    }

    /// Takes the connection's deliveries inline from now on, whenever
    /// everything sent before has been handled (see [`InlineDeliveries`]);
    /// the others still come through [`DirectReplies::recv`].
    pub fn deliver_inline(&mut self, inline: Arc<dyn InlineDeliveries>) {
        match &self.state {
            Replies::Open(end) => end.outbox.set_inline(inline),
            Replies::Starting(_) => self.inline = Some(inline),
            Replies::Ended => {}
        }
    }

    /// The broker's next reply if one is ready now (`Pending` if not),
    /// without waiting: a client that has just taken one can take those
    /// that came with it before it writes to its own peer.
    pub fn try_recv(&mut self) -> std::task::Poll<Option<DirectReply>> {
        let mut next = std::pin::pin!(self.recv());
        next.as_mut()
            .poll(&mut std::task::Context::from_waker(std::task::Waker::noop()))
    }

    /// Whether the replies keep room an idle client does not need: the
    /// outbox's queue has grown since it was last given back, or frames
    /// of content are still buffered.
    pub fn holds_room(&self) -> bool {
        matches!(&self.state, Replies::Open(end) if end.inbox.holds_room())
            || self.pending.capacity() > 0
    }

    /// Gives back the room [`DirectReplies::holds_room`] finds, as far as
    /// nothing waits in it (the next reply grows it again): for a client
    /// gone idle.
    pub fn release_room(&mut self) {
        if let Replies::Open(end) = &mut self.state {
            end.inbox.release_room();
        }
        if self.pending.is_empty() {
            self.pending = VecDeque::new();
        }
    }

    /// The broker's next reply, waiting for it; `None` once the broker
    /// has ended the connection (after everything it sent before).
    pub async fn recv(&mut self) -> Option<DirectReply> {
        if self.in_hand && self.pending.is_empty() {
            self.in_hand = false;
            if let Replies::Open(end) = &self.state {
                end.outbox.handled();
            }
        }
        loop {
            if let Some(frame) = self.pending.pop_front() {
                return Some(DirectReply::Frame(frame));
            }
            let end = match &mut self.state {
                Replies::Open(end) => end,
                Replies::Ended => return None,
                Replies::Starting(start) => {
                    self.state = match start.await {
                        Ok(end) => {
                            if let Some(inline) = self.inline.take() {
                                end.outbox.set_inline(inline);
                            }
                            Replies::Open(end)
                        }
                        Err(_) => Replies::Ended,
                    };
                    continue;
                }
            };
            let item = match end.inbox.try_recv() {
                Some(item) => item,
                None => {
                    // Everything sent so far is taken: the queues that
                    // found the outbox full may deliver again.
                    end.outbox.wake_blocked();
                    match end.inbox.recv().await {
                        Some(item) => item,
                        None => {
                            self.state = Replies::Ended;
                            return None;
                        }
                    }
                }
            };
            self.in_hand = true;
            self.taken += 1;
            if self.taken % WAKE_EVERY == 0 {
                end.outbox.wake_blocked();
            }
            match item.framed() {
                Framed::Method { channel, method } => {
                    return Some(DirectReply::Frame(Frame::Method { channel, method }));
                }
                Framed::Content {
                    channel,
                    method,
                    message,
                } if channel != 0 => {
                    return Some(DirectReply::Content {
                        channel,
                        method,
                        properties: message.properties.clone(),
                        body: message.body.clone(),
                    });
                }
                Framed::Content {
                    channel,
                    method,
                    message,
                } => {
                    let frame_max = end.outbox.frame_max();
                    let content = (&message.properties, &message.body);
                    push_content_frames(channel, method, content, frame_max, &mut self.pending);
                }
                Framed::Shutdown => self.state = Replies::Ended,
            }
        }
    }
}

/// Appends a content-carrying method's frames, its body split by
/// `frame_max`; `content` is its message's encoded properties and body.
fn push_content_frames(
    channel: u16,
    method: Method,
    (properties, body): (&Bytes, &Bytes),
    frame_max: u32,
    out: &mut VecDeque<Frame>,
) {
    out.push_back(Frame::Method { channel, method });
    out.push_back(Frame::Header {
        channel,
        header: ContentHeader {
            class_id: ContentHeader::BASIC_CLASS,
            body_size: body.len() as u64,
            property_bytes: properties.clone(),
        },
    });
    let chunk = (frame_max as usize).saturating_sub(FRAME_OVERHEAD).max(1);
    let mut start = 0;
    while start < body.len() {
        let end = (start + chunk).min(body.len());
        out.push_back(Frame::Body {
            channel,
            payload: body.slice(start..end),
        });
        start = end;
    }
}

/// Starts the connection side of an in-process link: the frames the client
/// sends, and where the connection puts its writer's end.
/// Serves an in-process client: `serve` is the connection's loop over
/// the frames given, with the writer's end sent once it starts; spawned on
/// the current runtime, where the client may also run it (see
/// [`DirectLoop`]).
pub(super) fn link<F>(
    serve: impl FnOnce(DirectFrames, oneshot::Sender<WriterEnd>) -> F,
) -> DirectLink
where
    F: Future<Output = ()> + Send + 'static,
{
    let (to_broker, rx) = handoff::channel(DIRECT_CAPACITY);
    let (start_tx, start_rx) = oneshot::channel();
    let handed = Arc::new(Handed::default());
    let connection = serve(DirectFrames::new(rx, Arc::clone(&handed)), start_tx);
    let here = direct_loop::spawn(connection, handed, &to_broker);
    DirectLink {
        to_broker,
        from_broker: DirectReplies::new(start_rx),
        here,
    }
}
