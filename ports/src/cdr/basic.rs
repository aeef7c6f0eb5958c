//! The types of OpenRTM-aist's `BasicDataType.idl` (module `RTC`): [`Time`]
//! and the `Timed*` values and sequences, the wide-character ones
//! included (a `wchar` is a `char` up to U+FFFF, a `wstring` a
//! [`WString`]; both UTF-16 in CDR, see the `cdr` module).

use super::WString;

use std::time::{Duration, SystemTime, UNIX_EPOCH};

idl_structs!(
    /// `RTC::Time`: seconds and nanoseconds (since the Unix epoch, as
    /// OpenRTM-aist stamps data).
    Time [Copy, Eq, PartialOrd, Ord, Hash] {
        /// Seconds.
        sec: u32,
        /// Nanoseconds, below 1e9.
        nsec: u32,
    }
);

impl Time {
    /// The current time.
    pub fn now() -> Self {
        Time::from(SystemTime::now())
    }
}

impl From<SystemTime> for Time {
    /// Saturates outside 1970..2106, as a `u32` of seconds must.
    fn from(time: SystemTime) -> Self {
        let since = time.duration_since(UNIX_EPOCH).unwrap_or_default();
        match u32::try_from(since.as_secs()) {
            Ok(sec) => Time {
                sec,
                nsec: since.subsec_nanos(),
            },
            Err(_) => Time {
                sec: u32::MAX,
                nsec: 999_999_999,
            },
        }
    }
}

impl From<Time> for SystemTime {
    fn from(time: Time) -> Self {
        UNIX_EPOCH + Duration::new(time.sec.into(), time.nsec.min(999_999_999))
    }
}

timed_structs!(
    /// `RTC::TimedState` (a `short`).
    TimedState(i16) [Copy, Eq];
    /// `RTC::TimedShort`.
    TimedShort(i16) [Copy, Eq];
    /// `RTC::TimedLong` (an IDL `long` is 32 bits).
    TimedLong(i32) [Copy, Eq];
    /// `RTC::TimedUShort`.
    TimedUShort(u16) [Copy, Eq];
    /// `RTC::TimedULong`.
    TimedULong(u32) [Copy, Eq];
    /// `RTC::TimedFloat`.
    TimedFloat(f32) [Copy];
    /// `RTC::TimedDouble`.
    TimedDouble(f64) [Copy];
    /// `RTC::TimedChar` (an IDL `char`: one byte, Latin-1).
    TimedChar(u8) [Copy, Eq];
    /// `RTC::TimedWChar` (an IDL `wchar`: one UTF-16 code unit, so a
    /// character up to U+FFFF).
    TimedWChar(char) [Copy, Eq];
    /// `RTC::TimedBoolean`.
    TimedBoolean(bool) [Copy, Eq];
    /// `RTC::TimedOctet`.
    TimedOctet(u8) [Copy, Eq];
    /// `RTC::TimedString` (in the port's charset; no NUL inside).
    TimedString(String) [Eq];
    /// `RTC::TimedWString` (UTF-16 in CDR whatever the port's charset; no
    /// NUL inside).
    TimedWString(WString) [Eq];
    /// `RTC::TimedShortSeq`.
    TimedShortSeq(Vec<i16>) [Eq];
    /// `RTC::TimedLongSeq`.
    TimedLongSeq(Vec<i32>) [Eq];
    /// `RTC::TimedUShortSeq`.
    TimedUShortSeq(Vec<u16>) [Eq];
    /// `RTC::TimedULongSeq`.
    TimedULongSeq(Vec<u32>) [Eq];
    /// `RTC::TimedFloatSeq`.
    TimedFloatSeq(Vec<f32>);
    /// `RTC::TimedDoubleSeq`.
    TimedDoubleSeq(Vec<f64>);
    /// `RTC::TimedCharSeq`.
    TimedCharSeq(Vec<u8>) [Eq];
    /// `RTC::TimedWCharSeq` (each a character up to U+FFFF).
    TimedWCharSeq(Vec<char>) [Eq];
    /// `RTC::TimedBooleanSeq`.
    TimedBooleanSeq(Vec<bool>) [Eq];
    /// `RTC::TimedOctetSeq`.
    TimedOctetSeq(Vec<u8>) [Eq];
    /// `RTC::TimedStringSeq` (each string in the port's charset).
    TimedStringSeq(Vec<String>) [Eq];
    /// `RTC::TimedWStringSeq`.
    TimedWStringSeq(Vec<WString>) [Eq];
);

#[cfg(test)]
mod tests {
    use super::super::testing::{bytes, check, TM, TM_CDR};
    use super::*;
    use crate::{CdrOptions, Endian, PortData};
    use bytes::{Bytes, BytesMut};

    #[test]
    fn timed_double() {
        let value = TimedDouble { tm: TM, data: 1.0 };
        // The double is aligned to 8: right after the 8-byte Time.
        check(value, &bytes(&[&TM_CDR, &[0, 0, 0, 0, 0, 0, 0xf0, 0x3f]]));
        assert_eq!(TimedDouble::TYPE_NAME, Some("IDL:RTC/TimedDouble:1.0"));
    }

    #[test]
    fn timed_long() {
        check(
            TimedLong { tm: TM, data: -2 },
            &bytes(&[&TM_CDR, &[0xfe, 0xff, 0xff, 0xff]]),
        );
    }

    #[test]
    fn timed_string() {
        check(
            TimedString {
                tm: TM,
                data: "go".into(),
            },
            // Length 3 counts the NUL.
            &bytes(&[&TM_CDR, &[3, 0, 0, 0], b"go\0"]),
        );
        check(
            TimedString {
                tm: TM,
                data: String::new(),
            },
            &bytes(&[&TM_CDR, &[1, 0, 0, 0, 0]]),
        );
        let mut buf = BytesMut::new();
        let nul = TimedString {
            tm: TM,
            data: "a\0b".into(),
        };
        assert!(nul.encode(&mut buf).is_err());
        let unterminated = bytes(&[&TM_CDR, &[2, 0, 0, 0], b"ab"]);
        assert!(TimedString::decode(Bytes::from(unterminated)).is_err());
    }

    #[test]
    fn timed_double_seq_pads_before_the_doubles() {
        check(
            TimedDoubleSeq {
                tm: TM,
                data: vec![1.0, -2.0],
            },
            &bytes(&[
                &TM_CDR,
                &[2, 0, 0, 0],
                // Count ends at 12: 4 bytes of padding to reach 16.
                &[0, 0, 0, 0],
                &[0, 0, 0, 0, 0, 0, 0xf0, 0x3f],
                &[0, 0, 0, 0, 0, 0, 0, 0xc0],
            ]),
        );
        // No element, no padding.
        check(
            TimedDoubleSeq {
                tm: TM,
                data: vec![],
            },
            &bytes(&[&TM_CDR, &[0, 0, 0, 0]]),
        );
        // A count larger than the body cannot allocate.
        let lying = bytes(&[&TM_CDR, &[0xff, 0xff, 0xff, 0x0f]]);
        assert!(matches!(
            TimedDoubleSeq::decode(Bytes::from(lying)),
            Err(crate::DataError::Truncated { .. })
        ));
    }

    #[test]
    fn timed_wchar_is_two_octets_big_endian_in_either_byte_order() {
        let omega = TimedWChar {
            tm: TM,
            data: '\u{3a9}',
        };
        // The octet count 2, then U+03A9 big-endian.
        let expected = bytes(&[&TM_CDR, &[2, 0x03, 0xa9]]);
        check(omega, &expected);
        let big = CdrOptions {
            endian: Endian::Big,
            ..CdrOptions::default()
        };
        let mut buf = BytesMut::new();
        omega.encode_with(&mut buf, big).unwrap();
        assert_eq!(&buf[8..], [2, 0x03, 0xa9]);
        // With a byte order mark, either way round.
        for unit in [[4, 0xfe, 0xff, 0x03, 0xa9], [4, 0xff, 0xfe, 0xa9, 0x03]] {
            let body = Bytes::from(bytes(&[&TM_CDR, &unit]));
            assert_eq!(TimedWChar::decode(body).unwrap(), omega);
        }
        // Beyond U+FFFF is two code units: not a wchar.
        let emoji = TimedWChar {
            tm: TM,
            data: '\u{1f600}',
        };
        assert!(emoji.encode(&mut BytesMut::new()).is_err());
    }

    #[test]
    fn timed_wstring_is_utf16_after_a_little_endian_byte_order_mark() {
        check(
            TimedWString {
                tm: TM,
                data: "A\u{e9}\u{20ac}".into(),
            },
            // 8 octets: the mark FF FE and three code units, no terminator.
            &bytes(&[
                &TM_CDR,
                &[8, 0, 0, 0],
                &[0xff, 0xfe, 0x41, 0, 0xe9, 0, 0xac, 0x20],
            ]),
        );
        // Beyond U+FFFF: a surrogate pair.
        check(
            TimedWString {
                tm: TM,
                data: "\u{1f600}".into(),
            },
            &bytes(&[&TM_CDR, &[6, 0, 0, 0], &[0xff, 0xfe, 0x3d, 0xd8, 0, 0xde]]),
        );
        // The empty string is its length alone.
        check(
            TimedWString {
                tm: TM,
                data: WString::default(),
            },
            &bytes(&[&TM_CDR, &[0, 0, 0, 0]]),
        );
        let nul = TimedWString {
            tm: TM,
            data: "a\0b".into(),
        };
        assert!(nul.encode(&mut BytesMut::new()).is_err());
    }

    #[test]
    fn a_wstring_is_big_endian_unless_its_mark_says_otherwise() {
        let value = |text: &str| TimedWString {
            tm: TM,
            data: text.into(),
        };
        let decode = |units: &[u8]| {
            let length = u32::try_from(units.len()).unwrap().to_le_bytes();
            TimedWString::decode(Bytes::from(bytes(&[&TM_CDR, &length, units])))
        };
        // No mark: big-endian, whatever the stream's byte order.
        assert_eq!(decode(&[0, 0x41, 0, 0xe9]).unwrap(), value("A\u{e9}"));
        assert_eq!(
            decode(&[0xfe, 0xff, 0, 0x41, 0, 0xe9]).unwrap(),
            value("A\u{e9}")
        );
        assert_eq!(
            decode(&[0xff, 0xfe, 0x41, 0, 0xe9, 0]).unwrap(),
            value("A\u{e9}")
        );
        // The mark alone is the empty string; only a leading mark is one.
        assert_eq!(decode(&[0xff, 0xfe]).unwrap(), value(""));
        assert_eq!(
            decode(&[0xfe, 0xff, 0, 0x41, 0xfe, 0xff]).unwrap(),
            value("A\u{feff}")
        );
    }

    #[test]
    fn timed_wchar_seq_and_wstring_seq() {
        check(
            TimedWCharSeq {
                tm: TM,
                data: vec!['a', '\u{3a9}'],
            },
            &bytes(&[&TM_CDR, &[2, 0, 0, 0], &[2, 0, 0x61], &[2, 0x03, 0xa9]]),
        );
        check(
            TimedWStringSeq {
                tm: TM,
                data: vec!["\u{3a9}\u{3bc}".into(), "a".into()],
            },
            &bytes(&[
                &TM_CDR,
                &[2, 0, 0, 0],
                &[6, 0, 0, 0, 0xff, 0xfe, 0xa9, 0x03, 0xbc, 0x03],
                // The first string ends at 22: padding to 24.
                &[0, 0],
                &[4, 0, 0, 0, 0xff, 0xfe, 0x61, 0],
            ]),
        );
    }

    #[test]
    fn time_converts_both_ways() {
        let time = UNIX_EPOCH + Duration::new(5, 7);
        let tm = Time::from(time);
        assert_eq!(tm, Time { sec: 5, nsec: 7 });
        assert_eq!(SystemTime::from(tm), time);
    }
}
