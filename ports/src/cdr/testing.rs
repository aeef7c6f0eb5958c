//! Helpers for the CDR unit tests: a time stamp with distinct bytes, and
//! the checks every type's test makes of an encoding.

use crate::{DataError, PortData, Time};
use bytes::{Bytes, BytesMut};
use std::fmt::Debug;

pub const TM: Time = Time {
    sec: 0x0102_0304,
    nsec: 0x0a0b_0c0d,
};
/// `TM` in little-endian CDR.
pub const TM_CDR: [u8; 8] = [0x04, 0x03, 0x02, 0x01, 0x0d, 0x0c, 0x0b, 0x0a];

pub fn bytes(parts: &[&[u8]]) -> Vec<u8> {
    parts.concat()
}

/// `value` encodes to `expected` and back; every shorter prefix and one
/// byte more are refused.
pub fn check<T: PortData + PartialEq + Debug>(value: T, expected: &[u8]) {
    let mut buf = BytesMut::new();
    value.encode(&mut buf).unwrap();
    assert_eq!(&buf[..], expected, "encoding of {value:?}");
    assert_eq!(T::decode(Bytes::copy_from_slice(expected)).unwrap(), value);
    for len in 0..expected.len() {
        assert!(
            T::decode(Bytes::copy_from_slice(&expected[..len])).is_err(),
            "{len} of {} bytes decoded",
            expected.len()
        );
    }
    let mut long = expected.to_vec();
    long.push(0);
    assert_eq!(
        T::decode(Bytes::from(long)).unwrap_err(),
        DataError::Trailing(1)
    );
}
