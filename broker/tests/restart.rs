//! An embedded broker restarted in the same process: `shutdown` releases
//! the data directory, so a new broker opens it at once and finds the
//! durable state.

use lapin::options::{
    BasicGetOptions, BasicPublishOptions, ConfirmSelectOptions, QueueDeclareOptions,
};
use lapin::types::FieldTable;
use lapin::{BasicProperties, Connection, ConnectionProperties};
use leveret_test_macros::both_runtimes;

async fn start(dir: &std::path::Path) -> leveret_broker::BrokerHandle {
    leveret_broker::Broker::builder()
        .listen("127.0.0.1:0".parse().expect("addr"))
        .data_dir(dir)
        .start()
        .await
        .expect("start on the data directory")
}

#[both_runtimes]
async fn shutdown_releases_the_data_directory_for_an_immediate_restart() {
    // One directory per runtime flavour: both variants run at once.
    let flavor = tokio::runtime::Handle::current().runtime_flavor();
    let dir =
        std::env::temp_dir().join(format!("leveret-restart-{}-{flavor:?}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let durable = QueueDeclareOptions {
        durable: true,
        ..Default::default()
    };
    for round in 0..3u8 {
        let handle = start(&dir).await;
        let url = format!("amqp://guest:guest@{}/%2f", handle.local_addrs()[0]);
        let conn = Connection::connect(&url, ConnectionProperties::default())
            .await
            .expect("connect");
        let channel = conn.create_channel().await.expect("channel");
        channel
            .queue_declare("kept", durable, FieldTable::default())
            .await
            .expect("declare");
        if round > 0 {
            let got = channel
                .basic_get("kept", BasicGetOptions { no_ack: true })
                .await
                .expect("get")
                .expect("the message from the previous round");
            assert_eq!(got.delivery.data, [round - 1]);
        }
        channel
            .confirm_select(ConfirmSelectOptions::default())
            .await
            .expect("confirms");
        let confirm = channel
            .basic_publish(
                "",
                "kept",
                BasicPublishOptions::default(),
                &[round],
                BasicProperties::default().with_delivery_mode(2),
            )
            .await
            .expect("publish")
            .await
            .expect("confirm");
        assert!(confirm.is_ack());
        // No waiting: the next round opens the directory right away.
        handle.shutdown().await;
    }
    let _ = std::fs::remove_dir_all(&dir);
}
