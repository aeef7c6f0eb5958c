//! Feeds arbitrary bytes to every decoder of leveret-protocol: the frame
//! stream decoder with several frame_max values, Method::decode,
//! BasicProperties::decode, ContentHeader::decode and FieldTable::decode.
//! Nothing may panic, and whatever decodes must re-encode to bytes that
//! decode to the same value (compared by encoding, and by Debug text where
//! NaN floats make `==` false).
#![no_main]

use bytes::{Bytes, BytesMut};
use leveret_protocol::{decode_frame, BasicProperties, ContentHeader, FieldTable, Frame, Method};
use libfuzzer_sys::fuzz_target;

fn same<T: PartialEq + std::fmt::Debug>(a: &T, b: &T) {
    if a != b {
        assert_eq!(
            format!("{a:?}"),
            format!("{b:?}"),
            "re-decoded value differs"
        );
    }
}

fn check_frames(data: &[u8], frame_max: u32) {
    let mut buf = BytesMut::from(data);
    while let Ok(Some(frame)) = decode_frame(&mut buf, frame_max) {
        let mut first = BytesMut::new();
        frame.encode(&mut first);
        let mut again = first.clone();
        let decoded = decode_frame(&mut again, 0)
            .expect("a re-encoded frame decodes")
            .expect("a re-encoded frame is whole");
        assert!(again.is_empty(), "re-encoded frame left bytes");
        same(&decoded, &frame);
        let mut second = BytesMut::new();
        decoded.encode(&mut second);
        assert_eq!(first, second, "re-encoding is not stable");
        if let Frame::Header { header, .. } = &frame {
            check_properties(&header.property_bytes);
        }
    }
}

fn check_method(payload: &Bytes) {
    if let Ok(method) = Method::decode(payload) {
        let mut first = BytesMut::new();
        method.encode(&mut first);
        let decoded = Method::decode(&first.clone().freeze()).expect("a re-encoded method decodes");
        same(&decoded, &method);
        let mut second = BytesMut::new();
        decoded.encode(&mut second);
        assert_eq!(first, second, "re-encoding is not stable");
    }
}

fn check_properties(bytes: &Bytes) {
    if let Ok(props) = BasicProperties::decode(bytes) {
        let mut first = BytesMut::new();
        props.encode(&mut first);
        let decoded =
            BasicProperties::decode(&first.clone().freeze()).expect("re-encoded properties decode");
        same(&decoded, &props);
        let mut second = BytesMut::new();
        decoded.encode(&mut second);
        assert_eq!(first, second, "re-encoding is not stable");
    }
}

fn check_table(bytes: &Bytes) {
    if let Ok(table) = FieldTable::decode(bytes) {
        let mut first = BytesMut::new();
        table.encode(&mut first);
        let decoded =
            FieldTable::decode(&first.clone().freeze()).expect("a re-encoded table decodes");
        same(&decoded, &table);
    }
}

fuzz_target!(|data: &[u8]| {
    // The stream decoder, unlimited, at the spec minimum, at RabbitMQ's
    // default, and at a tiny limit taken from the input.
    let tiny = u32::from(data.first().copied().unwrap_or(0));
    for frame_max in [0, 4096, 131_072, tiny] {
        check_frames(data, frame_max);
    }

    // The payload decoders on the raw bytes.
    let bytes = Bytes::copy_from_slice(data);
    check_method(&bytes);
    check_properties(&bytes);
    check_table(&bytes);
    if let Ok(header) = ContentHeader::decode(&bytes) {
        let _ = header.properties();
    }

    // The same decoders past a 7-byte frame header, so that seeds written
    // as whole frames reach them with a payload at the front.
    if data.len() > 7 {
        let payload = bytes.slice(7..);
        check_method(&payload);
        check_properties(&payload.slice(payload.len().min(12)..));
    }
});
