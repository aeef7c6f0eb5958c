//! Publisher confirms (per message and wait-for-all, acks and nacks,
//! concurrent publishers) and transactions (commit, rollback).

mod common;

use bytes::Bytes;
use common::{broker, temp_queue, unique, within};
use leveret_client::{
    BasicAckOptions, BasicGetOptions, BasicProperties, BasicPublishOptions, Channel, Confirmation,
    Error, FieldTable, FieldValue, QueueDeclareOptions, ShortStr,
};

async fn publish(
    channel: &Channel,
    queue: &ShortStr,
    body: &str,
) -> leveret_client::PublishConfirm {
    within(
        "publish",
        channel.basic_publish(
            "",
            queue,
            BasicPublishOptions::default(),
            BasicProperties::default(),
            Bytes::copy_from_slice(body.as_bytes()),
        ),
    )
    .await
    .expect("publish")
}

async fn ready(channel: &Channel, queue: &ShortStr) -> u32 {
    let passive = QueueDeclareOptions {
        passive: true,
        ..Default::default()
    };
    within(
        "passive declare",
        channel.queue_declare(queue, passive, FieldTable::new()),
    )
    .await
    .expect("passive declare")
    .message_count
}

/// `queue`'s ready count once `until` accepts it, waiting for at most the
/// hang limit: a channel's unacked messages go back to their queue after
/// its close-ok, as a RabbitMQ queue process hears of the close in its
/// own time.
async fn ready_once(channel: &Channel, queue: &ShortStr, until: impl Fn(u32) -> bool) -> u32 {
    within("the ready count", async {
        loop {
            let count = ready(channel, queue).await;
            if until(count) {
                return count;
            }
            tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        }
    })
    .await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_confirm_mode_nothing_is_requested() {
    let broker = broker().await;
    let (connection, channel) = broker.channel().await;
    let queue = temp_queue(&channel, "noconfirm").await;
    let confirm = publish(&channel, &queue.name, "x").await;
    assert_eq!(confirm.await.expect("confirm"), Confirmation::NotRequested);
    let err = channel
        .wait_for_confirms()
        .await
        .expect_err("not in confirm mode");
    assert!(matches!(err, Error::InvalidArgument(_)));
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn each_publish_is_acked() {
    let broker = broker().await;
    let (connection, channel) = broker.channel().await;
    let queue = temp_queue(&channel, "acked").await;
    within("confirm.select", channel.confirm_select())
        .await
        .expect("confirm.select");
    // Selecting again is allowed and changes nothing.
    channel.confirm_select().await.expect("again");
    let mut confirms = Vec::new();
    for i in 0..100 {
        confirms.push(publish(&channel, &queue.name, &i.to_string()).await);
    }
    // Await in reverse order: each resolves on its own.
    for confirm in confirms.into_iter().rev() {
        assert_eq!(
            within("confirm", confirm).await.expect("confirm"),
            Confirmation::Ack
        );
    }
    assert!(within("wait", channel.wait_for_confirms())
        .await
        .expect("wait"));
    assert_eq!(ready(&channel, &queue.name).await, 100);
    // Unroutable messages are acked too (after their return, if mandatory).
    let confirm = channel
        .basic_publish(
            "amq.direct",
            unique("nowhere").as_str(),
            BasicPublishOptions { mandatory: true },
            BasicProperties::default(),
            Bytes::from_static(b"lost"),
        )
        .await
        .expect("publish");
    assert!(within("confirm", confirm).await.expect("confirm").is_ack());
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn wait_for_confirms_covers_dropped_handles() {
    let broker = broker().await;
    let (connection, channel) = broker.channel().await;
    let queue = temp_queue(&channel, "waitall").await;
    channel.confirm_select().await.expect("confirm.select");
    // Nothing outstanding: returns at once.
    assert!(within("wait", channel.wait_for_confirms())
        .await
        .expect("wait"));
    for i in 0..500 {
        drop(publish(&channel, &queue.name, &i.to_string()).await);
    }
    assert!(within("wait", channel.wait_for_confirms())
        .await
        .expect("wait"));
    assert_eq!(ready(&channel, &queue.name).await, 500);
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn full_queue_with_reject_publish_nacks() {
    let broker = broker().await;
    let (connection, channel) = broker.channel().await;
    let mut arguments = FieldTable::new();
    arguments.insert(ShortStr::from_static("x-max-length"), FieldValue::I32(1));
    arguments.insert(
        ShortStr::from_static("x-overflow"),
        FieldValue::string("reject-publish"),
    );
    arguments.insert(ShortStr::from_static("x-expires"), FieldValue::I32(60_000));
    let queue = channel
        .queue_declare(
            unique("overflow").as_str(),
            QueueDeclareOptions::default(),
            arguments,
        )
        .await
        .expect("declare");
    channel.confirm_select().await.expect("confirm.select");
    let first = publish(&channel, &queue.name, "fits").await;
    let second = publish(&channel, &queue.name, "overflows").await;
    let third = publish(&channel, &queue.name, "overflows too").await;
    assert_eq!(within("1", first).await.expect("1"), Confirmation::Ack);
    assert_eq!(within("2", second).await.expect("2"), Confirmation::Nack);
    assert_eq!(within("3", third).await.expect("3"), Confirmation::Nack);
    // wait_for_confirms reports the nacks once.
    assert!(!within("wait", channel.wait_for_confirms())
        .await
        .expect("wait"));
    assert!(within("wait", channel.wait_for_confirms())
        .await
        .expect("wait"));
    assert_eq!(ready(&channel, &queue.name).await, 1);
    channel
        .queue_delete(&queue.name, Default::default())
        .await
        .expect("delete");
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_publishers_on_one_channel_get_their_own_confirms() {
    let broker = broker().await;
    let (connection, channel) = broker.channel().await;
    let queue = temp_queue(&channel, "concurrent").await;
    channel.confirm_select().await.expect("confirm.select");
    let mut tasks = Vec::new();
    for task in 0..4 {
        let channel = channel.clone();
        let queue = queue.name.clone();
        tasks.push(tokio::spawn(async move {
            for i in 0..100 {
                let confirm = channel
                    .basic_publish(
                        "",
                        &queue,
                        BasicPublishOptions::default(),
                        BasicProperties::default(),
                        Bytes::from(format!("{task}:{i}")),
                    )
                    .await
                    .expect("publish");
                assert!(confirm.await.expect("confirm").is_ack());
            }
        }));
    }
    for task in tasks {
        within("publisher", task).await.expect("publisher");
    }
    assert!(channel.wait_for_confirms().await.expect("wait"));
    assert_eq!(ready(&channel, &queue.name).await, 400);
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn channel_close_fails_outstanding_confirms() {
    let broker = broker().await;
    let (connection, channel) = broker.channel().await;
    channel.confirm_select().await.expect("confirm.select");
    // Publishing to a missing exchange closes the channel with 404, and the
    // broker never confirms that publish.
    let confirm = channel
        .basic_publish(
            unique("no-such-exchange").as_str(),
            "k",
            BasicPublishOptions::default(),
            BasicProperties::default(),
            Bytes::from_static(b"x"),
        )
        .await
        .expect("publish");
    let err = within("confirm", confirm)
        .await
        .expect_err("channel closed");
    assert_eq!(
        err.reply_code(),
        Some(leveret_client::ReplyCode::NotFound),
        "{err:?}"
    );
    let err = channel.wait_for_confirms().await.expect_err("closed");
    assert_eq!(err.reply_code(), Some(leveret_client::ReplyCode::NotFound));
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tx_commit_and_rollback_of_publishes() {
    let broker = broker().await;
    let (connection, channel) = broker.channel().await;
    let queue = temp_queue(&channel, "tx").await;
    within("tx.select", channel.tx_select())
        .await
        .expect("tx.select");
    drop(publish(&channel, &queue.name, "rolled back").await);
    within("rollback", channel.tx_rollback())
        .await
        .expect("rollback");
    assert_eq!(ready(&channel, &queue.name).await, 0);
    drop(publish(&channel, &queue.name, "committed 1").await);
    drop(publish(&channel, &queue.name, "committed 2").await);
    // Not visible before the commit.
    assert_eq!(ready(&channel, &queue.name).await, 0);
    within("commit", channel.tx_commit()).await.expect("commit");
    assert_eq!(ready(&channel, &queue.name).await, 2);
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tx_rollback_of_acks_keeps_messages_unacked() {
    let broker = broker().await;
    let (connection, channel) = broker.channel().await;
    let queue = temp_queue(&channel, "txack").await;
    channel.confirm_select().await.expect("confirm.select");
    for body in ["a", "b"] {
        assert!(publish(&channel, &queue.name, body)
            .await
            .await
            .expect("confirm")
            .is_ack());
    }
    let tx = connection.open_channel().await.expect("channel");
    tx.tx_select().await.expect("tx.select");
    let a = tx
        .basic_get(&queue.name, BasicGetOptions::default())
        .await
        .expect("get")
        .expect("a");
    let b = tx
        .basic_get(&queue.name, BasicGetOptions::default())
        .await
        .expect("get")
        .expect("b");
    tx.basic_ack(b.delivery_tag, BasicAckOptions { multiple: true })
        .await
        .expect("ack");
    tx.tx_rollback().await.expect("rollback");
    // The acks were discarded: both are still unacked, and come back
    // when the channel closes.
    assert_eq!(ready(&channel, &queue.name).await, 0);
    tx.close().await.expect("close");
    assert_eq!(ready_once(&channel, &queue.name, |n| n == 2).await, 2);
    let _ = a;
    // Ack inside a committed transaction sticks: of two messages taken,
    // the one acked stays gone when the channel's close returns the other.
    let tx = connection.open_channel().await.expect("channel");
    tx.tx_select().await.expect("tx.select");
    let mut taken = Vec::new();
    for _ in 0..2 {
        let m = tx
            .basic_get(&queue.name, BasicGetOptions::default())
            .await
            .expect("get")
            .expect("message");
        assert!(m.redelivered);
        taken.push(m);
    }
    taken.remove(0).ack().await.expect("ack");
    tx.tx_commit().await.expect("commit");
    assert_eq!(ready(&channel, &queue.name).await, 0);
    tx.close().await.expect("close");
    // The close returns what it held in one step: once anything is back,
    // everything is, and only the unacked one may be.
    assert_eq!(ready_once(&channel, &queue.name, |n| n > 0).await, 1);
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tx_commit_without_select_is_an_error() {
    let broker = broker().await;
    let (connection, channel) = broker.channel().await;
    let err = channel.tx_commit().await.expect_err("not transactional");
    assert_eq!(
        err.reply_code(),
        Some(leveret_client::ReplyCode::PreconditionFailed),
        "{err:?}"
    );
    connection.close().await.expect("close");
}
