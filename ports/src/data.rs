//! [`PortData`]: how a port's value type becomes a message body and back.
//! Implemented here for raw bytes (`Bytes`, `Vec<u8>`), UTF-8 text
//! (`String`), the numeric primitives and `bool` (little-endian, exactly
//! their size), OpenRTM-aist's CDR data types (see `cdr`), and, with the
//! `serde` feature, any serde type wrapped in `Postcard`.

use super::cdr::CdrOptions;
use bytes::{BufMut, Bytes, BytesMut};

/// Why a value could not be encoded or a body decoded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum DataError {
    /// A fixed-size value of `expected` bytes came in a body of `actual`.
    #[error("expected a body of {expected} bytes, got {actual}")]
    Length {
        /// Bytes the type takes.
        expected: usize,
        /// Bytes in the body.
        actual: usize,
    },
    /// The body ended `needed` bytes short of a field at `offset`.
    #[error("body truncated: {needed} more bytes needed at offset {offset}")]
    Truncated {
        /// Where the field starts.
        offset: usize,
        /// How many bytes are missing.
        needed: usize,
    },
    /// The value ended before the body did (this many bytes were left).
    #[error("{0} bytes left over after the value")]
    Trailing(usize),
    /// Text that is not UTF-8.
    #[error("text is not UTF-8")]
    Utf8,
    /// The body's `type` property names another type than the port's.
    #[error("the message holds {found}, the port takes {expected}")]
    TypeMismatch {
        /// The port's type name.
        expected: &'static str,
        /// The message's `type` property.
        found: String,
    },
    /// Anything else wrong with the value or the body.
    #[error("{0}")]
    Invalid(String),
}

/// A value a port can carry: encoded into a message body by the out-port,
/// decoded from it by the in-port.
pub trait PortData: Sized + Send + 'static {
    /// The `content-type` property of published messages.
    const CONTENT_TYPE: &'static str = "application/octet-stream";
    /// The `type` property of published messages (a CORBA repository id
    /// for the CDR types). An in-port refuses a message whose `type` is set
    /// and differs, rather than misreading its bytes.
    const TYPE_NAME: Option<&'static str> = None;

    /// Appends the value's encoding to `buf`.
    fn encode(&self, buf: &mut BytesMut) -> Result<(), DataError>;

    /// Decodes a whole body.
    fn decode(body: Bytes) -> Result<Self, DataError>;

    /// [`PortData::encode`] for a port whose profile sets the CDR byte
    /// order and charset; only CDR types differ from `encode`.
    fn encode_with(&self, buf: &mut BytesMut, options: CdrOptions) -> Result<(), DataError> {
        let _ = options;
        self.encode(buf)
    }

    /// [`PortData::decode`] with the profile's CDR byte order and charset.
    fn decode_with(body: Bytes, options: CdrOptions) -> Result<Self, DataError> {
        let _ = options;
        Self::decode(body)
    }
}

impl PortData for Bytes {
    fn encode(&self, buf: &mut BytesMut) -> Result<(), DataError> {
        buf.extend_from_slice(self);
        Ok(())
    }

    fn decode(body: Bytes) -> Result<Self, DataError> {
        Ok(body)
    }
}

impl PortData for Vec<u8> {
    fn encode(&self, buf: &mut BytesMut) -> Result<(), DataError> {
        buf.extend_from_slice(self);
        Ok(())
    }

    fn decode(body: Bytes) -> Result<Self, DataError> {
        Ok(body.to_vec())
    }
}

impl PortData for String {
    const CONTENT_TYPE: &'static str = "text/plain; charset=utf-8";

    fn encode(&self, buf: &mut BytesMut) -> Result<(), DataError> {
        buf.extend_from_slice(self.as_bytes());
        Ok(())
    }

    fn decode(body: Bytes) -> Result<Self, DataError> {
        String::from_utf8(body.to_vec()).map_err(|_| DataError::Utf8)
    }
}

/// Fixed-size body check shared by the primitives.
fn exact<const N: usize>(body: &[u8]) -> Result<[u8; N], DataError> {
    body.try_into().map_err(|_| DataError::Length {
        expected: N,
        actual: body.len(),
    })
}

macro_rules! little_endian {
    ($($t:ty),*) => {$(
        impl PortData for $t {
            fn encode(&self, buf: &mut BytesMut) -> Result<(), DataError> {
                buf.put_slice(&self.to_le_bytes());
                Ok(())
            }

            fn decode(body: Bytes) -> Result<Self, DataError> {
                Ok(<$t>::from_le_bytes(exact(&body)?))
            }
        }
    )*};
}

little_endian!(u8, i8, u16, i16, u32, i32, u64, i64, u128, i128, f32, f64);

impl PortData for bool {
    fn encode(&self, buf: &mut BytesMut) -> Result<(), DataError> {
        buf.put_u8(u8::from(*self));
        Ok(())
    }

    fn decode(body: Bytes) -> Result<Self, DataError> {
        match exact::<1>(&body)? {
            [0] => Ok(false),
            [1] => Ok(true),
            [other] => Err(DataError::Invalid(format!("{other} is not a boolean"))),
        }
    }
}

/// Any serde type, encoded with postcard (`serde` feature).
///
/// postcard is compact (variable-length integers, no field names), has a
/// documented, stable wire format (1.0), and also runs without `std` on
/// microcontrollers, which makes it a fit for robot data; JSON would be
/// several times larger and slower for numeric data.
#[cfg(feature = "serde")]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Hash)]
pub struct Postcard<T>(pub T);

#[cfg(feature = "serde")]
impl<T> PortData for Postcard<T>
where
    T: serde::Serialize + serde::de::DeserializeOwned + Send + 'static,
{
    const CONTENT_TYPE: &'static str = "application/x-postcard";

    fn encode(&self, buf: &mut BytesMut) -> Result<(), DataError> {
        let bytes =
            postcard::to_allocvec(&self.0).map_err(|e| DataError::Invalid(e.to_string()))?;
        buf.extend_from_slice(&bytes);
        Ok(())
    }

    fn decode(body: Bytes) -> Result<Self, DataError> {
        let (value, rest) =
            postcard::take_from_bytes(&body).map_err(|e| DataError::Invalid(e.to_string()))?;
        if !rest.is_empty() {
            return Err(DataError::Trailing(rest.len()));
        }
        Ok(Postcard(value))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn round_trip<T: PortData + PartialEq + std::fmt::Debug>(value: T, bytes: &[u8]) {
        let mut buf = BytesMut::new();
        value.encode(&mut buf).unwrap();
        assert_eq!(&buf[..], bytes);
        assert_eq!(T::decode(buf.freeze()).unwrap(), value);
    }

    #[test]
    fn primitives_are_little_endian_and_exact() {
        round_trip(0x1234u16, &[0x34, 0x12]);
        round_trip(-2i32, &[0xfe, 0xff, 0xff, 0xff]);
        round_trip(1.0f64, &[0, 0, 0, 0, 0, 0, 0xf0, 0x3f]);
        round_trip(1.5f32, &[0, 0, 0xc0, 0x3f]);
        round_trip(true, &[1]);
        round_trip(String::from("é"), "é".as_bytes());
        round_trip(vec![1u8, 2], &[1, 2]);
        assert_eq!(
            u32::decode(Bytes::from_static(&[1, 2, 3])),
            Err(DataError::Length {
                expected: 4,
                actual: 3
            })
        );
        assert!(bool::decode(Bytes::from_static(&[2])).is_err());
        assert_eq!(
            String::decode(Bytes::from_static(&[0xff])),
            Err(DataError::Utf8)
        );
    }

    #[cfg(feature = "serde")]
    #[test]
    fn postcard_is_compact_and_strict() {
        #[derive(Debug, PartialEq, serde::Serialize, serde::Deserialize)]
        struct Cmd {
            id: u32,
            speed: f32,
            name: String,
        }
        let value = Postcard(Cmd {
            id: 300,
            speed: 0.5,
            name: "go".into(),
        });
        // varint 300 = ac 02; f32 LE; length-prefixed string.
        round_trip(value, &[0xac, 0x02, 0, 0, 0, 0x3f, 2, b'g', b'o']);
        let mut buf = BytesMut::new();
        Postcard(7u8).encode(&mut buf).unwrap();
        buf.put_u8(0);
        assert_eq!(
            Postcard::<u8>::decode(buf.freeze()),
            Err(DataError::Trailing(1))
        );
    }
}
