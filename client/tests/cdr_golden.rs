//! CDR byte for byte against omniORB: `golden/cdr_vectors.txt` holds
//! values marshalled by omniORB's `cdrMarshal` in both byte orders
//! (written by `golden/generate_cdr_vectors.py`); each must decode to the
//! value it was made from, and encoding that value must give the same
//! bytes, padding aside (omniORB leaves alignment padding uninitialised:
//! there a golden byte may differ from the zero this crate writes).

use bytes::{Bytes, BytesMut};
use leveret_client::ports::{
    CdrOptions, Charset, Endian, Point2D, PortData, Pose2D, Time, TimedBoolean, TimedBooleanSeq,
    TimedChar, TimedCharSeq, TimedDouble, TimedDoubleSeq, TimedFloat, TimedFloatSeq, TimedLong,
    TimedLongSeq, TimedOctet, TimedOctetSeq, TimedPose2D, TimedShort, TimedShortSeq, TimedState,
    TimedString, TimedStringSeq, TimedULong, TimedULongSeq, TimedUShort, TimedUShortSeq,
    TimedVelocity2D, Velocity2D,
};
use std::fmt::Debug;

const VECTORS: &str = include_str!("golden/cdr_vectors.txt");

const TM: Time = Time {
    sec: 0x0102_0304,
    nsec: 0x0a0b_0c0d,
};

fn golden(case: &str, endian: Endian) -> Vec<u8> {
    let order = match endian {
        Endian::Big => "0",
        Endian::Little => "1",
    };
    let line = VECTORS
        .lines()
        .find(|line| {
            let mut fields = line.split(' ');
            fields.next() == Some(case) && fields.next() == Some(order)
        })
        .unwrap_or_else(|| panic!("no vector for {case} {order}"));
    let hex = line.rsplit(' ').next().unwrap();
    (0..hex.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&hex[i..i + 2], 16).unwrap())
        .collect()
}

fn check<T: PortData + PartialEq + Debug>(case: &str, value: T, charset: Charset) {
    for endian in [Endian::Big, Endian::Little] {
        let options = CdrOptions { endian, charset };
        let expected = golden(case, endian);
        let decoded = T::decode_with(Bytes::from(expected.clone()), options)
            .unwrap_or_else(|e| panic!("{case} {endian:?}: {e}"));
        assert_eq!(decoded, value, "{case} {endian:?} decodes");
        let mut ours = BytesMut::new();
        value.encode_with(&mut ours, options).unwrap();
        assert_eq!(ours.len(), expected.len(), "{case} {endian:?} length");
        for (i, (a, b)) in ours.iter().zip(&expected).enumerate() {
            // A difference may only be padding: a zero of ours that the
            // decode above skipped (a data byte there would have changed
            // the decoded value).
            assert!(
                a == b || *a == 0,
                "{case} {endian:?} byte {i}: ours {a:#04x}, omniORB {b:#04x}"
            );
        }
    }
}

#[test]
fn timed_scalars() {
    check(
        "timed_double",
        TimedDouble { tm: TM, data: 3.25 },
        Charset::Utf8,
    );
    check(
        "timed_double_negative",
        TimedDouble {
            tm: Time { sec: 1, nsec: 2 },
            data: -1.0e-300,
        },
        Charset::Utf8,
    );
    check("timed_long", TimedLong { tm: TM, data: -2 }, Charset::Utf8);
}

#[test]
fn timed_strings() {
    let text = |data: &str| TimedString {
        tm: TM,
        data: data.into(),
    };
    check("timed_string", text("go"), Charset::Utf8);
    check("timed_string_empty", text(""), Charset::Utf8);
    check("timed_string_latin1", text("café Å"), Charset::Latin1);
}

#[test]
fn timed_sequences() {
    let seq = |data: Vec<f64>| TimedDoubleSeq { tm: TM, data };
    check(
        "timed_double_seq",
        seq(vec![1.5, -2.0, 1.0e300]),
        Charset::Utf8,
    );
    check("timed_double_seq_empty", seq(vec![]), Charset::Utf8);
}

#[test]
fn timed_2d_geometry() {
    check(
        "timed_pose2d",
        TimedPose2D {
            tm: TM,
            data: Pose2D {
                position: Point2D { x: 1.0, y: 2.0 },
                heading: 0.5,
            },
        },
        Charset::Utf8,
    );
    check(
        "timed_velocity2d",
        TimedVelocity2D {
            tm: TM,
            data: Velocity2D {
                vx: 0.1,
                vy: 0.2,
                va: 0.3,
            },
        },
        Charset::Utf8,
    );
}

#[test]
fn basic_timed_scalars() {
    check(
        "timed_state",
        TimedState { tm: TM, data: -3 },
        Charset::Utf8,
    );
    check(
        "timed_short",
        TimedShort { tm: TM, data: -300 },
        Charset::Utf8,
    );
    check(
        "timed_ushort",
        TimedUShort {
            tm: TM,
            data: 65000,
        },
        Charset::Utf8,
    );
    check(
        "timed_ulong",
        TimedULong {
            tm: TM,
            data: 4_000_000_000,
        },
        Charset::Utf8,
    );
    check(
        "timed_float",
        TimedFloat { tm: TM, data: 1.5 },
        Charset::Utf8,
    );
    check(
        "timed_char",
        TimedChar { tm: TM, data: b'A' },
        Charset::Utf8,
    );
    check(
        "timed_boolean",
        TimedBoolean { tm: TM, data: true },
        Charset::Utf8,
    );
    check(
        "timed_octet",
        TimedOctet { tm: TM, data: 0xfe },
        Charset::Utf8,
    );
}

#[test]
fn basic_timed_sequences() {
    check(
        "timed_short_seq",
        TimedShortSeq {
            tm: TM,
            data: vec![1, -2, 3],
        },
        Charset::Utf8,
    );
    check(
        "timed_long_seq",
        TimedLongSeq {
            tm: TM,
            data: vec![7, -8],
        },
        Charset::Utf8,
    );
    check(
        "timed_ushort_seq",
        TimedUShortSeq {
            tm: TM,
            data: vec![1, 65535],
        },
        Charset::Utf8,
    );
    check(
        "timed_ulong_seq",
        TimedULongSeq {
            tm: TM,
            data: vec![1, u32::MAX],
        },
        Charset::Utf8,
    );
    check(
        "timed_float_seq",
        TimedFloatSeq {
            tm: TM,
            data: vec![0.5, -0.25],
        },
        Charset::Utf8,
    );
    check(
        "timed_char_seq",
        TimedCharSeq {
            tm: TM,
            data: b"hi".to_vec(),
        },
        Charset::Utf8,
    );
    check(
        "timed_boolean_seq",
        TimedBooleanSeq {
            tm: TM,
            data: vec![true, false, true],
        },
        Charset::Utf8,
    );
    check(
        "timed_octet_seq",
        TimedOctetSeq {
            tm: TM,
            data: vec![0, 1, 0xff],
        },
        Charset::Utf8,
    );
    check(
        "timed_string_seq",
        TimedStringSeq {
            tm: TM,
            data: vec!["a".into(), String::new(), "bcd".into()],
        },
        Charset::Utf8,
    );
}
