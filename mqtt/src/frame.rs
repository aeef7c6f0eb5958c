//! The fixed header (2.1): packet type and flags, then the remaining length
//! as a variable byte integer. Streaming decode from a read buffer, with
//! the maximum packet size enforced from the fixed header alone, and
//! encoding of a whole packet into a write buffer.

use crate::error::{DecodeError, EncodeError};
use crate::packet::{Packet, PacketType};
use crate::version::ProtocolVersion;
use crate::wire::{put_u8, put_vbi, read_vbi, vbi_len, Counter, Fault, VBI_MAX};
use bytes::{Buf, BytesMut};

/// The largest packet MQTT can frame: a first byte, four bytes of
/// remaining length and 268,435,455 bytes after them.
pub const MAX_PACKET_SIZE: u32 = 1 + 4 + VBI_MAX;

/// How much of a packet a buffer holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PacketCheck {
    /// At least `needed` more bytes are required (a lower bound while the
    /// fixed header itself is incomplete).
    Incomplete {
        /// Bytes missing.
        needed: usize,
    },
    /// A whole packet of `len` bytes (fixed header included) is at the front.
    Complete {
        /// The whole packet's length.
        len: usize,
    },
}

/// A measured packet: its fixed header's length and its whole length.
enum Measure {
    Incomplete { needed: usize },
    Complete { header: usize, total: usize },
}

fn measure(buf: &[u8], max_packet_size: u32) -> Result<Measure, DecodeError> {
    let Some(length_bytes) = buf.get(1..) else {
        return Ok(Measure::Incomplete { needed: 2 });
    };
    match read_vbi(length_bytes) {
        Err(problem) => Err(DecodeError::MalformedRemainingLength(problem)),
        Ok(None) => Ok(Measure::Incomplete { needed: 1 }),
        Ok(Some((remaining, len))) => {
            let header = 1 + len;
            // At most 5 + 268,435,455: fits in usize on every target Rust supports.
            let total = header + remaining as usize;
            if total as u64 > u64::from(max_packet_size) {
                return Err(DecodeError::PacketTooLarge {
                    size: total as u64,
                    max: max_packet_size,
                });
            }
            if buf.len() < total {
                Ok(Measure::Incomplete {
                    needed: total - buf.len(),
                })
            } else {
                Ok(Measure::Complete { header, total })
            }
        }
    }
}

/// Checks whether `buf` starts with a whole packet, without decoding it.
/// The packet's size (fixed header included, as MQTT 5.0's Maximum Packet
/// Size counts it) is checked against `max_packet_size` as soon as the
/// remaining length is in, before any of the rest is buffered.
pub fn check_packet(buf: &[u8], max_packet_size: u32) -> Result<PacketCheck, DecodeError> {
    Ok(match measure(buf, max_packet_size)? {
        Measure::Incomplete { needed } => PacketCheck::Incomplete { needed },
        Measure::Complete { total, .. } => PacketCheck::Complete { len: total },
    })
}

/// The packet type and flags of a first byte, checked against `version`.
fn packet_type(first: u8, version: ProtocolVersion) -> Result<(PacketType, u8), DecodeError> {
    let nibble = first >> 4;
    let flags = first & 0x0F;
    let kind =
        PacketType::from_nibble(nibble, version).ok_or(DecodeError::UnknownPacketType(nibble))?;
    let valid = match kind {
        // QoS 3 is malformed (MQTT-3.3.1-4), and so is DUP on QoS 0
        // (MQTT-3.3.1-2).
        PacketType::Publish => {
            let qos = (flags >> 1) & 0x03;
            qos != 3 && !(qos == 0 && flags & 0x08 != 0)
        }
        _ => flags == kind.required_flags(),
    };
    if valid {
        Ok((kind, flags))
    } else {
        Err(DecodeError::BadFlags {
            packet: kind,
            flags,
        })
    }
}

/// Takes one packet off the front of `buf` if it holds a whole one.
/// `Ok(None)` means more bytes are needed.
///
/// `version` is the connection's protocol version; CONNECT names its own
/// and is decoded by it, so a server decodes a connection's first packet
/// with any version and checks that it is a CONNECT. A packet larger than
/// `max_packet_size` (fixed header included) is refused from its fixed
/// header, as is an unknown type or wrong flags: those errors leave `buf`
/// as it was, and the connection must be closed. A packet whose body fails
/// to decode has been taken off the buffer. Strings, binary data and the
/// PUBLISH payload are `Bytes` slices of the buffer, never copies.
pub fn decode_packet(
    buf: &mut BytesMut,
    version: ProtocolVersion,
    max_packet_size: u32,
) -> Result<Option<Packet>, DecodeError> {
    let Some(&first) = buf.first() else {
        return Ok(None);
    };
    let (kind, flags) = packet_type(first, version)?;
    let (header, total) = match measure(buf, max_packet_size)? {
        Measure::Incomplete { .. } => return Ok(None),
        Measure::Complete { header, total } => (header, total),
    };
    let mut body = buf.split_to(total).freeze();
    body.advance(header);
    Packet::decode_body(kind, flags, &body, version)
        .map(Some)
        .map_err(|Fault { problem, field }| DecodeError::Invalid {
            packet: kind,
            field,
            problem,
        })
}

impl Packet {
    /// The packet's remaining length in `version`, after checking it can
    /// be written in it.
    fn remaining_length(&self, version: ProtocolVersion) -> Result<usize, EncodeError> {
        let mut counter = Counter::default();
        self.write_body(version, &mut counter)
            .map_err(|fault| self.encode_error(fault))?;
        if counter.0 > VBI_MAX as usize {
            return Err(EncodeError::PacketTooLarge {
                remaining_length: counter.0,
            });
        }
        Ok(counter.0)
    }

    fn encode_error(&self, Fault { problem, field }: Fault) -> EncodeError {
        EncodeError::Invalid {
            packet: self.packet_type(),
            field,
            problem,
        }
    }

    /// The size of the encoded packet, fixed header included: what a
    /// session compares with the peer's Maximum Packet Size.
    pub fn encoded_len(&self, version: ProtocolVersion) -> Result<usize, EncodeError> {
        let remaining = self.remaining_length(version)?;
        Ok(1 + vbi_len(remaining) + remaining)
    }

    /// Appends the packet, written in `version` (a CONNECT in its own), to
    /// `buf` and returns its size. A packet the version cannot carry, or
    /// that breaks a rule a decoder checks, is refused and `buf` is left as
    /// it was.
    pub fn encode(
        &self,
        version: ProtocolVersion,
        buf: &mut BytesMut,
    ) -> Result<usize, EncodeError> {
        let remaining = self.remaining_length(version)?;
        let total = 1 + vbi_len(remaining) + remaining;
        let before = buf.len();
        buf.reserve(total);
        put_u8(buf, self.first_byte());
        // remaining_length kept it within VBI_MAX.
        put_vbi(buf, remaining as u32);
        if let Err(fault) = self.write_body(version, buf) {
            buf.truncate(before);
            return Err(self.encode_error(fault));
        }
        debug_assert_eq!(buf.len() - before, total);
        Ok(total)
    }
}
