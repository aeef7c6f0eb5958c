//! Heap allocations on the hot path, counted by a global allocator that
//! counts only on the thread that asked it to.
//!
//! Measured (bytes 1.x): decoding a basic.publish + header + body triple
//! from a fresh read buffer allocates exactly once — the first
//! `BytesMut::split_to` turns the buffer's Vec into a shared allocation —
//! and decoding a second triple from the same buffer allocates nothing.
//! Encoding into warm buffers allocates nothing.

use bytes::{Bytes, BytesMut};
use leveret_protocol::{
    decode_frame, encode_content, encode_method, BasicDeliver, BasicProperties, BasicPublish,
    FieldTable, FieldValue, Frame, Method, ShortStr,
};
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

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

const BODY: &[u8] = b"0123456789abcdef";

fn publish() -> Method {
    BasicPublish {
        ticket: 0,
        exchange: ShortStr::from_static("amq.direct"),
        routing_key: ShortStr::from_static("orders.created"),
        mandatory: false,
        immediate: false,
    }
    .into()
}

fn deliver() -> Method {
    BasicDeliver {
        consumer_tag: ShortStr::from_static("amq.ctag-1"),
        delivery_tag: 7,
        redelivered: false,
        exchange: ShortStr::from_static("amq.direct"),
        routing_key: ShortStr::from_static("orders.created"),
    }
    .into()
}

fn encode_triple(method: &Method, props: &BasicProperties, buf: &mut BytesMut) {
    let mut scratch = BytesMut::new();
    props.encode(&mut scratch);
    encode_method(1, method, buf);
    encode_content(1, 60, &scratch, BODY, 131_072, buf);
}

fn decode_triple(buf: &mut BytesMut) -> (Frame, BasicProperties, Frame) {
    let method = decode_frame(buf, 131_072).unwrap().unwrap();
    let props = match decode_frame(buf, 131_072).unwrap().unwrap() {
        Frame::Header { header, .. } => header.properties().unwrap(),
        other => panic!("expected a header, got {other:?}"),
    };
    let body = decode_frame(buf, 131_072).unwrap().unwrap();
    (method, props, body)
}

fn persistent() -> BasicProperties {
    BasicProperties {
        delivery_mode: Some(2),
        ..Default::default()
    }
}

#[test]
fn decoding_a_publish_triple_allocates_once_then_never() {
    let mut wire = BytesMut::new();
    encode_triple(&publish(), &persistent(), &mut wire);
    encode_triple(&publish(), &persistent(), &mut wire);
    let mut buf = BytesMut::from(&wire[..]);

    let ((method, props, body), first) = count(|| decode_triple(&mut buf));
    assert_eq!(
        method,
        Frame::Method {
            channel: 1,
            method: publish()
        }
    );
    assert_eq!(props, persistent());
    assert_eq!(
        body,
        Frame::Body {
            channel: 1,
            payload: Bytes::from_static(BODY)
        }
    );
    // The promotion of the read buffer to a shared allocation.
    assert_eq!(first, 1, "first triple from a fresh buffer");

    let (_, second) = count(|| decode_triple(&mut buf));
    assert_eq!(second, 0, "second triple from the same buffer");
    assert!(buf.is_empty());
}

#[test]
fn decoding_a_deliver_triple_with_properties_allocates_once() {
    let props = BasicProperties {
        content_type: Some(ShortStr::from_static("application/json")),
        delivery_mode: Some(2),
        timestamp: Some(1_767_225_600),
        ..Default::default()
    };
    let mut wire = BytesMut::new();
    encode_triple(&deliver(), &props, &mut wire);
    let mut buf = BytesMut::from(&wire[..]);
    let ((_, decoded, _), n) = count(|| decode_triple(&mut buf));
    assert_eq!(decoded, props);
    assert_eq!(n, 1);
}

#[test]
fn a_headers_table_costs_its_vector() {
    // Tables are a Vec of entries: one allocation, more if it grows
    // (here 3 entries: Vec growth 0 -> 4 is one allocation).
    let mut headers = FieldTable::new();
    headers.insert(ShortStr::from_static("a"), FieldValue::I32(1));
    headers.insert(ShortStr::from_static("b"), FieldValue::string("x"));
    headers.insert(ShortStr::from_static("c"), FieldValue::Bool(true));
    let props = BasicProperties {
        headers: Some(headers),
        ..persistent()
    };
    let mut wire = BytesMut::new();
    encode_triple(&publish(), &props, &mut wire);
    let mut buf = BytesMut::from(&wire[..]);
    let ((_, decoded, _), n) = count(|| decode_triple(&mut buf));
    assert_eq!(decoded, props);
    assert_eq!(n, 2, "shared promotion + the table's Vec");
}

#[test]
fn encoding_into_warm_buffers_does_not_allocate() {
    let mut scratch = BytesMut::with_capacity(256);
    let mut buf = BytesMut::with_capacity(4096);
    let props = persistent();
    let method = publish();
    let (_, n) = count(|| {
        for _ in 0..10 {
            buf.clear();
            scratch.clear();
            props.encode(&mut scratch);
            encode_method(1, &method, &mut buf);
            encode_content(1, 60, &scratch, BODY, 131_072, &mut buf);
        }
    });
    assert_eq!(n, 0);
}
