//! Feeds arbitrary bytes to leveret-mqtt's stream decoder as MQTT 3.1.1 and
//! as 5.0 (a CONNECT names its own level, 3.1 included), with no size
//! limit, a 4096-byte one, and a tiny one taken from the first byte.
//! Nothing may panic; each decode takes exactly the packet the fixed header
//! declared, or nothing; and whatever decodes must re-encode to bytes that
//! decode to the same packet and re-encode to the same bytes.
#![no_main]

use bytes::BytesMut;
use leveret_mqtt::{check_packet, decode_packet, DecodeError, PacketCheck, ProtocolVersion};
use libfuzzer_sys::fuzz_target;

fn check_stream(data: &[u8], version: ProtocolVersion, max_packet_size: u32) {
    let mut buf = BytesMut::from(data);
    loop {
        let declared = check_packet(&buf, max_packet_size);
        let before = buf.len();
        let result = decode_packet(&mut buf, version, max_packet_size);
        let consumed = before - buf.len();
        match (&declared, &result) {
            (Ok(PacketCheck::Complete { len }), Ok(Some(_)) | Err(DecodeError::Invalid { .. })) => {
                assert_eq!(consumed, *len, "decode took other than the declared packet")
            }
            _ => assert_eq!(consumed, 0, "decode took bytes without a packet"),
        }
        match result {
            Ok(Some(packet)) => {
                let mut first = BytesMut::new();
                packet
                    .encode(version, &mut first)
                    .expect("a decoded packet re-encodes");
                let mut again = first.clone();
                let decoded = decode_packet(&mut again, version, u32::MAX)
                    .expect("a re-encoded packet decodes")
                    .expect("a re-encoded packet is whole");
                assert!(again.is_empty(), "re-encoded packet left bytes");
                assert_eq!(decoded, packet, "re-decoded packet differs");
                let mut second = BytesMut::new();
                decoded.encode(version, &mut second).expect("re-encodes");
                assert_eq!(first, second, "re-encoding is not stable");
            }
            // The packet was taken off; the next one is still decodable.
            Err(DecodeError::Invalid { .. }) => {}
            Ok(None) | Err(_) => return,
        }
    }
}

fuzz_target!(|data: &[u8]| {
    let tiny = u32::from(data.first().copied().unwrap_or(0));
    for version in [ProtocolVersion::V3_1_1, ProtocolVersion::V5] {
        for max_packet_size in [u32::MAX, 4096, tiny] {
            check_stream(data, version, max_packet_size);
        }
    }
});
