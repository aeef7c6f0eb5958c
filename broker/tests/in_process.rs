//! The in-process transport: a broker with no listener serves a
//! connection over an in-memory pipe exactly as over TCP.

use bytes::BytesMut;
use leveret_protocol::{decode_frame, Frame, Method, PROTOCOL_HEADER};
use leveret_test_macros::both_runtimes;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

#[both_runtimes]
async fn a_broker_without_listeners_greets_an_in_process_client() {
    let handle = leveret_broker::Broker::builder()
        .start()
        .await
        .expect("start");
    assert!(handle.local_addrs().is_empty());
    let mut pipe = handle.connect_in_process();
    pipe.write_all(PROTOCOL_HEADER).await.expect("header");
    let mut buf = BytesMut::new();
    let frame = tokio::time::timeout(std::time::Duration::from_secs(5), async {
        loop {
            if let Some(frame) = decode_frame(&mut buf, 0).expect("valid frame") {
                return frame;
            }
            assert!(pipe.read_buf(&mut buf).await.expect("read") > 0, "eof");
        }
    })
    .await
    .expect("connection.start in time");
    match frame {
        Frame::Method {
            channel: 0,
            method: Method::ConnectionStart(start),
        } => assert_eq!((start.version_major, start.version_minor), (0, 9)),
        other => panic!("expected connection.start, got {other:?}"),
    }
    handle.shutdown().await;
}
