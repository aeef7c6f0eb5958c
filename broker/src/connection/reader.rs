//! Reading whole frames off a connection's socket into a buffer that costs
//! what the traffic needs, and no more:
//! - frames are limited to the protocol's 4096-byte minimum until the
//!   client's connection.tune-ok, then to the negotiated frame_max (the
//!   size is checked from the 7-byte header, before any payload is
//!   buffered);
//! - the buffer starts at [`READ_IDLE`] bytes and doubles while reads fill
//!   it (up to one minimum-size frame before tune-ok, [`READ_MAX`] after,
//!   or one whole frame when a frame is larger); the connection gives back
//!   whatever exceeds the frame in progress once no read but heartbeats
//!   has come for [`IDLE_RELEASE`], so an idle connection holds 1 KiB
//!   whatever it received before;
//! - nothing kept beyond the frame's handling points into the buffer, so
//!   the buffer is reused in place rather than reallocated: method frames
//!   whose values may be kept (names, arguments and tags of declare, bind,
//!   consume...) are copied out before decoding, and the channel copies
//!   message content below [`copy_below`] (larger bodies stay slices, each
//!   pinning at most four times its size).
//!
//! Uses the codec and the busy-poll state; the connection module drives it.

use super::source::{FrameSource, ReadError};
use crate::busy_poll::BusyPoll;
use crate::stats::ConnectionTraffic;
use bytes::{Buf, Bytes, BytesMut};
use leveret_protocol::{
    check_frame, check_protocol_header, decode_frame, parse_frame, DecodeError, Frame, FrameCheck,
    ProtocolHeaderCheck, FRAME_MIN_SIZE, FRAME_OVERHEAD, PROTOCOL_HEADER,
};
use std::future::Future;
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncReadExt, DuplexStream, Interest};
use tokio::net::tcp::OwnedReadHalf;

/// The buffer an idle connection keeps, enough for a typical small
/// publish in one read.
pub(super) const READ_IDLE: usize = 1024;
/// The largest buffer reads grow to (a single larger frame gets a buffer
/// of its own size).
pub(super) const READ_MAX: usize = 64 * 1024;
/// How long a connection (reader or writer) keeps a buffer larger than it
/// needs after its last read or write. Releasing at once, whenever the
/// socket had nothing more, cost a reallocation per wake-up (glibc
/// trimming and faulting the pages back in, seen in the broker's CPU per
/// message).
pub(super) const IDLE_RELEASE: std::time::Duration = std::time::Duration::from_secs(1);
/// The frame type of method frames.
const METHOD_FRAME: u8 = 1;
/// Methods whose decoded values are not kept beyond their handling, or
/// whose kept parts the channel copies itself (basic.publish's exchange
/// and routing key): these stay slices of the read buffer, the hot path.
const TRANSIENT_METHODS: [(u16, u16); 4] = [(60, 40), (60, 80), (60, 90), (60, 120)];

/// How often a connection that is not being read checks whether its peer
/// has hung up, while the peer's unread bytes keep the socket readable.
const HANGUP_CHECK: Duration = Duration::from_millis(250);

/// The read half of a connection's transport.
pub trait Incoming: AsyncRead + Unpin + Send + 'static {
    /// Resolves once the peer has hung up (or the socket failed), without
    /// reading what it sent before: a connection that is not being read
    /// (a blocked publisher) still ends when its client goes away. Never
    /// resolves where the transport cannot tell.
    fn hung_up(&self) -> impl Future<Output = ()> + Send + '_;
}

impl Incoming for OwnedReadHalf {
    async fn hung_up(&self) {
        loop {
            match self.ready(Interest::READABLE).await {
                Ok(ready) if !ready.is_read_closed() => tokio::time::sleep(HANGUP_CHECK).await,
                _ => return,
            }
        }
    }
}

/// TLS connections. The read half of a split TLS stream cannot reach its
/// socket to look for a hang-up without reading, so a TLS client that
/// goes away while its connection is not being read (a blocked publisher)
/// is found by the heartbeat instead.
#[cfg(feature = "tls")]
impl Incoming for tokio::io::ReadHalf<tokio_rustls::server::TlsStream<tokio::net::TcpStream>> {
    fn hung_up(&self) -> impl Future<Output = ()> + Send + '_ {
        std::future::pending()
    }
}

/// In-process connections: the embedding application's own code.
impl Incoming for tokio::io::ReadHalf<DuplexStream> {
    fn hung_up(&self) -> impl Future<Output = ()> + Send + '_ {
        std::future::pending()
    }
}

#[cfg(test)]
impl Incoming for DuplexStream {
    fn hung_up(&self) -> impl Future<Output = ()> + Send + '_ {
        std::future::pending()
    }
}

/// Bodies (and property lists) smaller than this are copied out of the
/// read buffer rather than kept as slices of it: a quarter of the largest
/// buffer a connection with `frame_max` can have (32 KiB by default), so a
/// slice pins at most four times its own size, where a 16-byte body kept
/// as a slice could pin a 64 KiB buffer. Copying that little costs little
/// in the broker's CPU per message (most at a few KiB).
pub(crate) fn copy_below(frame_max: u32) -> usize {
    READ_MAX.max(frame_max as usize + FRAME_OVERHEAD) / 4
}

/// Reads whole frames off the socket's read half.
pub(super) struct FrameReader<R> {
    socket: R,
    buf: BytesMut,
    /// The size of the buffer's allocation (its visible capacity shrinks as
    /// frames are taken off the front).
    allocated: usize,
    /// Largest frame payload accepted.
    frame_max: u32,
    /// The buffer size reads get, adapted to the traffic.
    want: usize,
    /// The most `want` may grow to: one minimum-size frame until tune-ok
    /// (a client sends a few small frames before it), [`READ_MAX`] after.
    want_max: usize,
    busy_poll: Option<Arc<BusyPoll>>,
    traffic: Option<Arc<ConnectionTraffic>>,
}

impl<R: Incoming> FrameReader<R> {
    /// A reader accepting frames up to the protocol's minimum frame size,
    /// counting each read into `traffic`.
    pub fn new(
        socket: R,
        busy_poll: Option<Arc<BusyPoll>>,
        traffic: Option<Arc<ConnectionTraffic>>,
    ) -> Self {
        FrameReader {
            socket,
            buf: BytesMut::with_capacity(READ_IDLE),
            allocated: READ_IDLE,
            frame_max: FRAME_MIN_SIZE,
            want: READ_IDLE,
            want_max: FRAME_MIN_SIZE as usize + FRAME_OVERHEAD,
            busy_poll,
            traffic,
        }
    }
}

impl<R: Incoming> FrameSource for FrameReader<R> {
    /// Resolves once the peer has hung up (see [`Incoming::hung_up`]).
    fn hung_up(&self) -> impl Future<Output = ()> + Send + '_ {
        self.socket.hung_up()
    }

    /// Accepts frames up to the negotiated `frame_max` from now on.
    fn set_frame_max(&mut self, frame_max: u32) {
        self.frame_max = frame_max;
        self.want_max = READ_MAX;
    }

    /// Whether the protocol header has arrived and is ours; it is taken off
    /// the buffer if so.
    async fn protocol_header(&mut self) -> Result<bool, ReadError> {
        loop {
            match check_protocol_header(&self.buf) {
                ProtocolHeaderCheck::Valid => {
                    self.buf.advance(PROTOCOL_HEADER.len());
                    return Ok(true);
                }
                ProtocolHeaderCheck::Invalid => return Ok(false),
                ProtocolHeaderCheck::Incomplete => self.fill().await?,
            }
        }
    }

    /// The next whole frame already buffered, if any. A frame that fails
    /// to decode has been taken off the buffer.
    fn buffered_frame(&mut self) -> Result<Option<Frame>, DecodeError> {
        let len = match check_frame(&self.buf, self.frame_max)? {
            FrameCheck::Incomplete { .. } => return Ok(None),
            FrameCheck::Complete { len } => len,
        };
        if may_be_kept(&self.buf[..len]) {
            let frame = Bytes::copy_from_slice(&self.buf[..len]);
            self.buf.advance(len);
            return parse_frame(frame).map(Some);
        }
        decode_frame(&mut self.buf, self.frame_max)
    }

    /// Reads more bytes.
    async fn fill(&mut self) -> Result<(), ReadError> {
        self.make_room(self.pending_frame_needs());
        let offered = self.buf.capacity() - self.buf.len();
        match self.socket.read_buf(&mut self.buf).await {
            Ok(0) => Err(ReadError::Closed),
            Ok(n) => {
                self.adapt(n, offered);
                if let Some(traffic) = &self.traffic {
                    traffic.read(n);
                }
                if let Some(busy_poll) = &self.busy_poll {
                    busy_poll.note_read();
                }
                Ok(())
            }
            Err(e) => Err(ReadError::Io(e)),
        }
    }

    /// Reads and drops whatever the peer still sends until it hangs up.
    /// After a framing error the stream can no longer be parsed, but
    /// closing the socket with input unread would reset the connection,
    /// and the peer could lose the `connection.close` that explains why.
    /// The buffer is reused, so discarding holds no more memory.
    async fn discard_input(&mut self) {
        loop {
            self.buf.clear();
            match self.socket.read_buf(&mut self.buf).await {
                Ok(0) | Err(_) => return,
                Ok(_) => {}
            }
        }
    }

    /// Whether the buffer is larger than the frame in progress needs (and
    /// than [`READ_IDLE`]).
    fn holds_spare(&self) -> bool {
        self.allocated > self.keep()
    }

    /// Gives back buffer space beyond what the frame in progress needs
    /// (the idle size when none is): the connection has been idle.
    fn release_spare(&mut self) {
        if self.holds_spare() {
            self.want = READ_IDLE;
            self.reallocate(self.keep());
        }
    }
}

impl<R: Incoming> FrameReader<R> {
    fn keep(&self) -> usize {
        (self.buf.len() + self.pending_frame_needs()).max(READ_IDLE)
    }

    /// Bytes still missing from the frame at the front of the buffer (0
    /// when the buffer is empty or holds something that is not a frame).
    fn pending_frame_needs(&self) -> usize {
        match check_frame(&self.buf, self.frame_max) {
            Ok(FrameCheck::Incomplete { needed }) if !self.buf.is_empty() => needed,
            _ => 0,
        }
    }

    /// Makes room for the frame in progress and for a read of the wanted
    /// size, in place when the buffer is not shared, else in a buffer of
    /// exactly that size.
    fn make_room(&mut self, needed: usize) {
        let spare = self.buf.capacity() - self.buf.len();
        if spare >= needed.max(self.want / 4).max(1) {
            return;
        }
        let room = needed.max(self.want.saturating_sub(self.buf.len()));
        if self.buf.try_reclaim(room) {
            return;
        }
        self.reallocate(self.buf.len() + room);
    }

    fn reallocate(&mut self, capacity: usize) {
        let mut fresh = BytesMut::with_capacity(capacity);
        fresh.extend_from_slice(&self.buf);
        self.buf = fresh;
        self.allocated = self.buf.capacity();
    }

    /// Grows the wanted size while reads fill what they are offered (it
    /// goes back to [`READ_IDLE`] when the connection has been idle).
    fn adapt(&mut self, read: usize, offered: usize) {
        if read >= offered {
            self.want = (self.want * 2).min(self.want_max);
        }
    }
}

/// Method frames other than the [`TRANSIENT_METHODS`].
fn may_be_kept(frame: &[u8]) -> bool {
    if frame.first() != Some(&METHOD_FRAME) {
        return false;
    }
    match frame.get(7..11) {
        Some(ids) => {
            let class = u16::from_be_bytes([ids[0], ids[1]]);
            let method = u16::from_be_bytes([ids[2], ids[3]]);
            !TRANSIENT_METHODS.contains(&(class, method))
        }
        None => true,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use leveret_protocol::{encode_method, BasicAck, Method, QueueDeclare, ShortStr};
    use tokio::io::AsyncWriteExt;

    fn frame_bytes(method: impl Into<Method>) -> BytesMut {
        let mut buf = BytesMut::new();
        encode_method(1, &method.into(), &mut buf);
        buf
    }

    #[test]
    fn declares_are_copied_out_and_acks_are_not() {
        let declare = frame_bytes(QueueDeclare {
            queue: ShortStr::from_static("a-queue-name-longer-than-23-bytes"),
            ..Default::default()
        });
        assert!(may_be_kept(&declare));
        let ack = frame_bytes(BasicAck {
            delivery_tag: 1,
            multiple: false,
        });
        assert!(!may_be_kept(&ack));
        assert!(
            !may_be_kept(&[3, 0, 1, 0, 0, 0, 1, 7, 0xce]),
            "a body frame"
        );
    }

    #[test]
    fn copies_below_a_quarter_of_the_largest_buffer() {
        assert_eq!(copy_below(131_072), (131_072 + 8) / 4);
        assert_eq!(copy_below(4096), READ_MAX / 4);
    }

    #[tokio::test]
    async fn frames_over_the_minimum_size_are_refused_before_tune() {
        let (mut client, server) = tokio::io::duplex(256 * 1024);
        let mut reader = FrameReader::new(server, None, None);
        let mut big = BytesMut::new();
        Frame::Body {
            channel: 1,
            payload: Bytes::from(vec![0u8; 5000]),
        }
        .encode(&mut big);
        client.write_all(&big).await.expect("write");
        match reader.next().await {
            Err(ReadError::Decode(DecodeError::FrameTooLarge { size, frame_max })) => {
                assert_eq!((size, frame_max), (5000, FRAME_MIN_SIZE));
            }
            other => panic!("expected a frame-size error, got {other:?}"),
        }
        assert!(
            reader.buf.capacity() < 8 * 1024,
            "the buffer never grew for the oversize frame: {}",
            reader.buf.capacity()
        );
    }

    #[tokio::test]
    async fn the_buffer_grows_for_a_large_frame_and_is_released_when_idle() {
        let (mut client, server) = tokio::io::duplex(256 * 1024);
        let mut reader = FrameReader::new(server, None, None);
        reader.set_frame_max(131_072);
        let mut big = BytesMut::new();
        Frame::Body {
            channel: 1,
            payload: Bytes::from(vec![7u8; 120_000]),
        }
        .encode(&mut big);
        let rest = big.split_off(100_000);
        client.write_all(&big).await.expect("write");
        while reader.buf.len() < 100_000 {
            reader.fill().await.expect("read");
        }
        assert!(
            reader.buf.capacity() >= 120_008,
            "room for the whole frame: {}",
            reader.buf.capacity()
        );
        client.write_all(&rest).await.expect("write");
        match reader.next().await.expect("a frame") {
            Frame::Body { payload, .. } => assert_eq!(payload.len(), 120_000),
            other => panic!("expected a body frame, got {other:?}"),
        }
        assert!(reader.holds_spare());
        reader.release_spare();
        assert!(!reader.holds_spare());
        assert!(
            reader.buf.capacity() <= READ_IDLE,
            "idle buffer of {} bytes",
            reader.buf.capacity()
        );
        let mut heartbeat = BytesMut::new();
        Frame::Heartbeat.encode(&mut heartbeat);
        client.write_all(&heartbeat).await.expect("write");
        assert!(matches!(reader.next().await, Ok(Frame::Heartbeat)));
    }

    #[tokio::test]
    async fn before_tune_ok_reads_stay_within_one_minimum_frame() {
        let (mut client, server) = tokio::io::duplex(1 << 20);
        let mut reader = FrameReader::new(server, None, None);
        let mut stream = BytesMut::new();
        for _ in 0..4000 {
            Frame::Heartbeat.encode(&mut stream);
        }
        client.write_all(&stream).await.expect("write");
        for _ in 0..4000 {
            reader.next().await.expect("a heartbeat");
            assert!(reader.allocated <= FRAME_MIN_SIZE as usize + FRAME_OVERHEAD);
        }
    }

    #[tokio::test]
    async fn reads_grow_while_they_fill_the_buffer() {
        let (mut client, server) = tokio::io::duplex(1 << 20);
        let mut reader = FrameReader::new(server, None, None);
        reader.set_frame_max(131_072);
        let mut stream = BytesMut::new();
        for _ in 0..2000 {
            Frame::Heartbeat.encode(&mut stream);
        }
        client.write_all(&stream).await.expect("write");
        let mut frames = 0;
        while frames < 2000 {
            reader.next().await.expect("a heartbeat");
            frames += 1;
        }
        assert!(reader.want > READ_IDLE, "want stayed at {}", reader.want);
        assert!(reader.want <= READ_MAX);
    }
}
