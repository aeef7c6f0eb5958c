//! The message layout and the clock.
//!
//! A body starts with a little-endian `u64` sequence number (the
//! publisher's id in the top 16 bits, its counter in the low 48) and, if
//! it has room (16 bytes or more), a little-endian `u64` send time in
//! nanoseconds since a process-wide epoch; the rest is zeros. Bodies of 8
//! to 15 bytes carry the sequence number only; shorter ones are truncated
//! sequence numbers (only the round trip uses them, matching by order).
//!
//! [`BodyWriter`] writes bodies into one reused `BytesMut`: each body is
//! split off and frozen, so a publisher allocates once per chunk of
//! messages rather than once per message, and the chunk's memory is
//! reclaimed once the client's writer has sent the bodies in it.

use bytes::{BufMut, Bytes, BytesMut};
use std::sync::OnceLock;
use std::time::Instant;

/// Bytes needed for the sequence number and the timestamp.
pub const HEADER: usize = 16;

/// Bits of the sequence number that hold the publisher's counter.
pub const COUNTER_BITS: u32 = 48;

/// Mask of the counter bits.
pub const COUNTER_MASK: u64 = (1 << COUNTER_BITS) - 1;

/// How much a [`BodyWriter`] allocates at a time.
const CHUNK: usize = 64 * 1024;

static EPOCH: OnceLock<Instant> = OnceLock::new();

/// The process-wide epoch timestamps count from.
pub fn epoch() -> Instant {
    *EPOCH.get_or_init(Instant::now)
}

/// Nanoseconds since [`epoch`] (monotonic).
pub fn now_ns() -> u64 {
    u64::try_from(epoch().elapsed().as_nanos()).unwrap_or(u64::MAX)
}

/// The sequence number of message `n` of publisher `publisher`.
pub fn make_seq(publisher: u16, n: u64) -> u64 {
    (u64::from(publisher) << COUNTER_BITS) | (n & COUNTER_MASK)
}

/// Splits a sequence number into (publisher, counter).
pub fn split_seq(seq: u64) -> (u16, u64) {
    ((seq >> COUNTER_BITS) as u16, seq & COUNTER_MASK)
}

/// The sequence number at the start of a body, if it has 8 bytes.
pub fn read_seq(body: &[u8]) -> Option<u64> {
    let bytes: [u8; 8] = body.get(..8)?.try_into().ok()?;
    Some(u64::from_le_bytes(bytes))
}

/// The send time in a body, if it has 16 bytes.
pub fn read_timestamp(body: &[u8]) -> Option<u64> {
    let bytes: [u8; 8] = body.get(8..16)?.try_into().ok()?;
    Some(u64::from_le_bytes(bytes))
}

/// Writes bodies of a fixed size into a reused buffer.
#[derive(Debug)]
pub struct BodyWriter {
    buf: BytesMut,
    size: usize,
}

impl BodyWriter {
    /// A writer of `size`-byte bodies.
    pub fn new(size: usize) -> Self {
        BodyWriter {
            buf: BytesMut::with_capacity(CHUNK.max(size)),
            size,
        }
    }

    /// The body size.
    pub fn size(&self) -> usize {
        self.size
    }

    /// A body carrying `seq` and, if it has room, the current time.
    pub fn body(&mut self, seq: u64) -> Bytes {
        self.body_at(seq, now_ns())
    }

    /// A body carrying `seq` and, if it has room, `timestamp_ns`.
    pub fn body_at(&mut self, seq: u64, timestamp_ns: u64) -> Bytes {
        let size = self.size;
        if self.buf.capacity() < size {
            // Reclaims the chunk if every body split from it is gone,
            // otherwise allocates a new one.
            self.buf.reserve(CHUNK.max(size));
        }
        let seq_bytes = seq.to_le_bytes();
        if size >= 8 {
            self.buf.put_slice(&seq_bytes);
            if size >= HEADER {
                self.buf.put_u64_le(timestamp_ns);
                self.buf.put_bytes(0, size - HEADER);
            } else {
                self.buf.put_bytes(0, size - 8);
            }
        } else {
            self.buf.put_slice(&seq_bytes[..size]);
        }
        self.buf.split().freeze()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bodies_carry_sequence_and_time() {
        let mut writer = BodyWriter::new(64);
        let seq = make_seq(3, 41);
        let body = writer.body_at(seq, 12345);
        assert_eq!(body.len(), 64);
        assert_eq!(read_seq(&body), Some(seq));
        assert_eq!(read_timestamp(&body), Some(12345));
        assert_eq!(split_seq(seq), (3, 41));
    }

    #[test]
    fn short_bodies() {
        let mut writer = BodyWriter::new(8);
        let body = writer.body(7);
        assert_eq!(body.len(), 8);
        assert_eq!(read_seq(&body), Some(7));
        assert_eq!(read_timestamp(&body), None);
        let mut writer = BodyWriter::new(4);
        assert_eq!(writer.body(7).len(), 4);
    }

    #[test]
    fn the_chunk_is_reused_once_bodies_are_dropped() {
        let mut writer = BodyWriter::new(1024);
        for n in 0..1000 {
            let body = writer.body(n);
            assert_eq!(read_seq(&body), Some(n));
        }
    }
}
