//! Codec throughput for the hot path: a basic.publish (client to broker)
//! and a basic.deliver (broker to consumer), each as method frame +
//! content header + 16-byte body frame. Throughput is in frames, so
//! criterion's elements/s is frames/s; time per iteration is per triple.
//!
//! Run: `cargo bench -p leveret-protocol --bench codec -- --warm-up-time 1 --measurement-time 3`

use bytes::{Bytes, BytesMut};
use criterion::{black_box, criterion_group, criterion_main, BatchSize, Criterion, Throughput};
use leveret_protocol::{
    decode_frame, encode_content, encode_method, BasicDeliver, BasicProperties, BasicPublish,
    Frame, Method, ShortStr,
};

const BODY: &[u8; 16] = b"0123456789abcdef";
const FRAME_MAX: u32 = 131_072;
const STREAM_TRIPLES: usize = 64;

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

fn publish_properties() -> BasicProperties {
    BasicProperties {
        delivery_mode: Some(2),
        ..Default::default()
    }
}

fn deliver() -> Method {
    BasicDeliver {
        consumer_tag: ShortStr::from_static("amq.ctag-Xk3Lq9Vd2aPz7wRbT0sY1g"),
        delivery_tag: 42_017,
        redelivered: false,
        exchange: ShortStr::from_static("amq.direct"),
        routing_key: ShortStr::from_static("orders.created"),
    }
    .into()
}

fn deliver_properties() -> BasicProperties {
    BasicProperties {
        content_type: Some(ShortStr::from_static("application/json")),
        delivery_mode: Some(2),
        timestamp: Some(1_767_225_600),
        ..Default::default()
    }
}

/// Encodes method + header + body into `buf`, the properties through
/// `scratch` (both reused, so a warm encoder does not allocate).
fn encode_triple(
    method: &Method,
    props: &BasicProperties,
    scratch: &mut BytesMut,
    buf: &mut BytesMut,
) {
    encode_method(1, method, buf);
    scratch.clear();
    props.encode(scratch);
    encode_content(1, 60, scratch, BODY, FRAME_MAX, buf);
}

fn wire(method: &Method, props: &BasicProperties) -> Bytes {
    let mut buf = BytesMut::new();
    encode_triple(method, props, &mut BytesMut::new(), &mut buf);
    buf.freeze()
}

/// What a reader does with a triple: take three frames off the read
/// buffer and decode the properties.
fn decode_triple(buf: &mut BytesMut) -> (Method, BasicProperties, Bytes) {
    let method = match decode_frame(buf, FRAME_MAX) {
        Ok(Some(Frame::Method { method, .. })) => method,
        other => panic!("expected a method frame, got {other:?}"),
    };
    let props = match decode_frame(buf, FRAME_MAX) {
        Ok(Some(Frame::Header { header, .. })) => header.properties().expect("properties"),
        other => panic!("expected a header frame, got {other:?}"),
    };
    let body = match decode_frame(buf, FRAME_MAX) {
        Ok(Some(Frame::Body { payload, .. })) => payload,
        other => panic!("expected a body frame, got {other:?}"),
    };
    (method, props, body)
}

fn bench_decode(c: &mut Criterion, name: &str, method: Method, props: BasicProperties) {
    let bytes = wire(&method, &props);
    let mut check = BytesMut::from(&bytes[..]);
    assert_eq!(
        decode_triple(&mut check),
        (method, props, Bytes::from_static(BODY))
    );

    let mut group = c.benchmark_group(name);
    group.throughput(Throughput::Elements(3));
    // A fresh read buffer per triple (its setup is not timed); the frames
    // are dropped inside the timed part, the buffer itself outside it.
    group.bench_function("decode", |b| {
        b.iter_batched_ref(
            || BytesMut::from(&bytes[..]),
            |buf| {
                let triple = decode_triple(buf);
                black_box(&triple);
            },
            BatchSize::SmallInput,
        )
    });
    // Steady state of a connection's reader: 64 triples arrive in one read
    // buffer, so its promotion to a shared allocation is paid once for all.
    let mut stream = BytesMut::new();
    for _ in 0..STREAM_TRIPLES {
        stream.extend_from_slice(&bytes);
    }
    group.throughput(Throughput::Elements(3 * STREAM_TRIPLES as u64));
    group.bench_function("decode_stream_of_64", |b| {
        b.iter_batched_ref(
            || BytesMut::from(&stream[..]),
            |buf| {
                for _ in 0..STREAM_TRIPLES {
                    let triple = decode_triple(buf);
                    black_box(&triple);
                }
            },
            BatchSize::SmallInput,
        )
    });
    group.finish();
}

fn bench_encode(c: &mut Criterion, name: &str, method: Method, props: BasicProperties) {
    let expected = wire(&method, &props);
    let mut group = c.benchmark_group(name);
    group.throughput(Throughput::Elements(3));
    let mut scratch = BytesMut::with_capacity(256);
    let mut buf = BytesMut::with_capacity(4096);
    group.bench_function("encode", |b| {
        b.iter(|| {
            buf.clear();
            encode_triple(
                black_box(&method),
                black_box(&props),
                &mut scratch,
                &mut buf,
            );
            black_box(&buf);
        })
    });
    assert_eq!(&buf[..], &expected[..]);
    group.finish();
}

fn publish_triple(c: &mut Criterion) {
    bench_decode(c, "publish_triple", publish(), publish_properties());
    bench_encode(c, "publish_triple", publish(), publish_properties());
}

fn deliver_triple(c: &mut Criterion) {
    bench_encode(c, "deliver_triple", deliver(), deliver_properties());
    bench_decode(c, "deliver_triple", deliver(), deliver_properties());
}

criterion_group!(benches, publish_triple, deliver_triple);
criterion_main!(benches);
