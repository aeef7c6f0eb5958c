//! Heap allocations on the MQTT hot path, counted by a global allocator
//! that counts only on the thread that asked it to.
//!
//! Measured (bytes 1.x): decoding a PUBLISH from a fresh read buffer
//! allocates once (the first `BytesMut::split_to` turns the buffer's Vec
//! into a shared allocation) and a second one from the same buffer nothing:
//! topic and payload are slices of the buffer. A 5.0 PUBLISH with
//! properties costs one more, the properties' box (and a Vec per list of
//! user properties). Encoding into a warm buffer allocates nothing.

use bytes::{Bytes, BytesMut};
use leveret_mqtt::{
    decode_packet, Delivery, MqttString, Packet, Properties, PropertyValues, ProtocolVersion,
    PubResponse, Publish, TopicName,
};
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::num::NonZeroU16;

struct Counting;

thread_local! {
    static COUNTING: Cell<bool> = const { Cell::new(false) };
    static ALLOCATIONS: Cell<usize> = const { Cell::new(0) };
}

fn note_allocation() {
    // try_with: the allocator may run while thread locals are torn down.
    let _ = COUNTING.try_with(|counting| {
        if counting.get() {
            let _ = ALLOCATIONS.try_with(|n| n.set(n.get() + 1));
        }
    });
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        note_allocation();
        System.alloc(layout)
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        note_allocation();
        System.alloc_zeroed(layout)
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        note_allocation();
        System.realloc(ptr, layout, new_size)
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        System.dealloc(ptr, layout)
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// Runs `f` and returns its result with the allocations it made on this thread.
fn count<T>(f: impl FnOnce() -> T) -> (T, usize) {
    ALLOCATIONS.with(|n| n.set(0));
    COUNTING.with(|c| c.set(true));
    let out = f();
    COUNTING.with(|c| c.set(false));
    (out, ALLOCATIONS.with(|n| n.get()))
}

fn publish(properties: Properties) -> Packet {
    Packet::Publish(Publish {
        dup: false,
        delivery: Delivery::AtLeastOnce(NonZeroU16::new(7).unwrap()),
        retain: false,
        topic: TopicName::from_static("sensors/r1/lidar"),
        properties,
        payload: Bytes::from_static(b"0123456789abcdef"),
    })
}

fn decode(buf: &mut BytesMut, version: ProtocolVersion) -> Packet {
    decode_packet(buf, version, 1 << 20).unwrap().unwrap()
}

#[test]
fn decoding_a_publish_allocates_once_then_never() {
    for version in [ProtocolVersion::V3_1_1, ProtocolVersion::V5] {
        let packet = publish(Properties::default());
        let mut wire = BytesMut::new();
        packet.encode(version, &mut wire).unwrap();
        packet.encode(version, &mut wire).unwrap();
        let mut buf = BytesMut::from(&wire[..]);
        let (first, n) = count(|| decode(&mut buf, version));
        assert_eq!(first, packet);
        assert_eq!(n, 1, "the read buffer's promotion to shared");
        let (second, n) = count(|| decode(&mut buf, version));
        assert_eq!(second, packet);
        assert_eq!(n, 0, "{version:?}: a second publish from the same buffer");
    }
}

#[test]
fn properties_cost_their_box() {
    let version = ProtocolVersion::V5;
    let with_expiry = publish(Properties::from(PropertyValues {
        message_expiry_interval: Some(60),
        content_type: Some(MqttString::from_static("application/json")),
        ..Default::default()
    }));
    let with_user = publish(Properties::from(PropertyValues {
        user_properties: vec![(
            MqttString::from_static("robot"),
            MqttString::from_static("r1"),
        )],
        ..Default::default()
    }));
    let mut wire = BytesMut::new();
    Packet::PingReq.encode(version, &mut wire).unwrap();
    with_expiry.encode(version, &mut wire).unwrap();
    with_user.encode(version, &mut wire).unwrap();
    let mut buf = BytesMut::from(&wire[..]);
    count(|| decode(&mut buf, version));
    let (decoded, n) = count(|| decode(&mut buf, version));
    assert_eq!(decoded, with_expiry);
    assert_eq!(n, 1, "the box");
    let (decoded, n) = count(|| decode(&mut buf, version));
    assert_eq!(decoded, with_user);
    assert_eq!(n, 2, "the box and the user properties' Vec");
}

#[test]
fn encoding_into_a_warm_buffer_does_not_allocate() {
    let packets = [
        publish(Properties::default()),
        Packet::PubAck(PubResponse::new(NonZeroU16::new(7).unwrap())),
        Packet::PingResp,
    ];
    let mut buf = BytesMut::with_capacity(4096);
    for version in [ProtocolVersion::V3_1_1, ProtocolVersion::V5] {
        let (_, n) = count(|| {
            for _ in 0..10 {
                buf.clear();
                for packet in &packets {
                    packet.encode(version, &mut buf).unwrap();
                }
            }
        });
        assert_eq!(n, 0, "{version:?}");
    }
}
