//! The writer task of a connection over a byte stream: owns the socket's
//! write half and drains the bounded outbox. Everything waiting is encoded
//! into one reused buffer and written with one syscall (batching under
//! load, no added latency when idle); a heartbeat goes out whenever
//! nothing was written for an interval. (An in-process link has no writer:
//! the outbox's items go to the embedded broker as they are.)

use super::frames::ByteOutput;
use leveret_protocol::handoff;
use leveret_protocol::Outgoing;
use std::time::Duration;
use tokio::io::AsyncWrite;
use tokio::sync::oneshot;

/// How many items may wait for the writer. Senders wait for room, so a
/// slow socket slows publishers down instead of growing a buffer.
pub(crate) const OUTBOX_CAPACITY: usize = 256;

/// Stop adding to a batch once the buffer holds this much.
const BATCH_BYTES: usize = 128 * 1024;

/// Runs until [`Outgoing::Shutdown`], every sender dropping, or a write
/// error, which is reported through `failed`.
pub(crate) async fn run<W: AsyncWrite + Unpin + Send + 'static>(
    mut output: ByteOutput<W>,
    mut inbox: handoff::Receiver<Outgoing>,
    frame_max: u32,
    heartbeat: Duration,
    failed: oneshot::Sender<std::io::Error>,
) {
    let result: std::io::Result<()> = async {
        loop {
            let next = if heartbeat.is_zero() {
                inbox.recv().await
            } else {
                tokio::select! {
                    item = inbox.recv() => item,
                    _ = tokio::time::sleep(heartbeat) => {
                        output.heartbeat();
                        output.write().await?;
                        continue;
                    }
                }
            };
            let Some(item) = next else {
                output.write().await?;
                return output.shutdown().await;
            };
            let mut stop = output.push(item, frame_max);
            while !stop && output.batched() < BATCH_BYTES {
                match inbox.try_recv() {
                    Some(item) => stop = output.push(item, frame_max),
                    None => break,
                }
            }
            output.write().await?;
            if stop {
                return output.shutdown().await;
            }
        }
    }
    .await;
    if let Err(error) = result {
        tracing::debug!(%error, "AMQP writer stopped");
        let _ = failed.send(error);
    }
}
