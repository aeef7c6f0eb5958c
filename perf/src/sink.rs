//! The `sink` subcommand: a null AMQP 0.9.1 broker, to measure a load
//! generator's own ceiling. It answers the handshake and every declare,
//! bind, qos, consume and select with its `-ok`, confirms each publish at
//! once (one `basic.ack` with `multiple` per read), and drops the content:
//! nothing is routed, stored or delivered. A generator's publish rate into
//! it is the most that generator can measure of any broker on this
//! machine.
//!
//! Uses the protocol codec only; `compare` can list it as one more broker.

use crate::Result;
use bytes::{Bytes, BytesMut};
use leveret_protocol::{
    decode_frame, encode_method, BasicAck, BasicCancelOk, BasicConsumeOk, BasicQosOk,
    ChannelCloseOk, ChannelOpenOk, ConfirmSelectOk, ConnectionCloseOk, ConnectionOpenOk,
    ConnectionStart, ConnectionTune, ExchangeBindOk, ExchangeDeclareOk, ExchangeDeleteOk,
    ExchangeUnbindOk, FieldTable, FieldValue, Frame, Method, QueueBindOk, QueueDeclareOk,
    QueueDeleteOk, QueuePurgeOk, QueueUnbindOk, ShortStr, TxCommitOk, TxRollbackOk, TxSelectOk,
    PROTOCOL_HEADER,
};
use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

/// The largest frame the sink accepts.
const FRAME_MAX: u32 = 131_072;

/// Options of the `sink` subcommand.
#[derive(Debug, Clone, clap::Args)]
pub struct SinkArgs {
    /// Where to listen.
    #[arg(long, default_value = "127.0.0.1:5690")]
    pub listen: SocketAddr,
    /// Print the publish rate every second.
    #[arg(long)]
    pub verbose: bool,
}

/// Listens until killed.
pub async fn run(args: &SinkArgs) -> Result<()> {
    let listener = TcpListener::bind(args.listen).await?;
    eprintln!("sink: a null AMQP broker on {}", listener.local_addr()?);
    let published = Arc::new(AtomicU64::new(0));
    if args.verbose {
        let published = Arc::clone(&published);
        tokio::spawn(async move {
            let mut last = 0;
            loop {
                tokio::time::sleep(Duration::from_secs(1)).await;
                let now = published.load(Ordering::Relaxed);
                eprintln!("sink: {} msgs/s", now - last);
                last = now;
            }
        });
    }
    loop {
        let (socket, _) = listener.accept().await?;
        let published = Arc::clone(&published);
        tokio::spawn(async move {
            if let Err(error) = serve(socket, &published).await {
                eprintln!("sink: connection ended: {error}");
            }
        });
    }
}

/// One connection's channels: the next confirm tag of those in confirm
/// mode.
#[derive(Default)]
struct Channels {
    confirm_tags: HashMap<u16, u64>,
    names: u64,
}

async fn serve(mut socket: TcpStream, published: &AtomicU64) -> std::io::Result<()> {
    socket.set_nodelay(true)?;
    let mut header = [0u8; 8];
    socket.read_exact(&mut header).await?;
    if &header != PROTOCOL_HEADER {
        socket.write_all(PROTOCOL_HEADER).await?;
        return Ok(());
    }
    let mut out = BytesMut::with_capacity(64 * 1024);
    let start = ConnectionStart {
        version_major: 0,
        version_minor: 9,
        server_properties: [(
            ShortStr::from_static("product"),
            FieldValue::string("leveret-perf sink"),
        )]
        .into_iter()
        .collect::<FieldTable>(),
        mechanisms: Bytes::from_static(b"PLAIN AMQPLAIN"),
        locales: Bytes::from_static(b"en_US"),
    };
    encode_method(0, &start.into(), &mut out);
    socket.write_all(&out).await?;
    out.clear();
    let mut buf = BytesMut::with_capacity(64 * 1024);
    let mut channels = Channels::default();
    loop {
        if socket.read_buf(&mut buf).await? == 0 {
            return Ok(());
        }
        let mut confirmed: HashMap<u16, u64> = HashMap::new();
        loop {
            let frame = match decode_frame(&mut buf, FRAME_MAX) {
                Ok(Some(frame)) => frame,
                Ok(None) => break,
                Err(error) => {
                    return Err(std::io::Error::new(
                        std::io::ErrorKind::InvalidData,
                        error.to_string(),
                    ))
                }
            };
            let Frame::Method { channel, method } = frame else {
                continue;
            };
            if let Method::BasicPublish(_) = method {
                published.fetch_add(1, Ordering::Relaxed);
                if let Some(tag) = channels.confirm_tags.get_mut(&channel) {
                    *tag += 1;
                    confirmed.insert(channel, *tag);
                }
                continue;
            }
            match reply(&mut channels, channel, method) {
                Reply::Send(method) => encode_method(channel, &method, &mut out),
                Reply::None => {}
                Reply::Close => {
                    encode_method(0, &ConnectionCloseOk {}.into(), &mut out);
                    socket.write_all(&out).await?;
                    return Ok(());
                }
            }
        }
        for (channel, tag) in confirmed {
            let ack = BasicAck {
                delivery_tag: tag,
                multiple: true,
            };
            encode_method(channel, &ack.into(), &mut out);
        }
        if buf.capacity() - buf.len() < 4096 {
            buf.reserve(64 * 1024);
        }
        if !out.is_empty() {
            socket.write_all(&out).await?;
            out.clear();
        }
    }
}

enum Reply {
    Send(Method),
    None,
    Close,
}

/// The answer to a method other than basic.publish.
fn reply(channels: &mut Channels, channel: u16, method: Method) -> Reply {
    let mut name = |given: ShortStr, prefix: &str| {
        if given.is_empty() {
            channels.names += 1;
            ShortStr::try_from(format!("{prefix}{}", channels.names)).unwrap_or_default()
        } else {
            given
        }
    };
    let answer: Method = match method {
        Method::ConnectionStartOk(_) => ConnectionTune {
            channel_max: 2047,
            frame_max: FRAME_MAX,
            heartbeat: 0,
        }
        .into(),
        Method::ConnectionOpen(_) => ConnectionOpenOk::default().into(),
        Method::ConnectionClose(_) => return Reply::Close,
        Method::ChannelOpen(_) => ChannelOpenOk::default().into(),
        Method::ChannelClose(_) => {
            channels.confirm_tags.remove(&channel);
            ChannelCloseOk {}.into()
        }
        Method::ExchangeDeclare(m) if !m.no_wait => ExchangeDeclareOk {}.into(),
        Method::ExchangeDelete(m) if !m.no_wait => ExchangeDeleteOk {}.into(),
        Method::ExchangeBind(m) if !m.no_wait => ExchangeBindOk {}.into(),
        Method::ExchangeUnbind(m) if !m.no_wait => ExchangeUnbindOk {}.into(),
        Method::QueueDeclare(m) if !m.no_wait => QueueDeclareOk {
            queue: name(m.queue, "amq.gen-sink-"),
            message_count: 0,
            consumer_count: 0,
        }
        .into(),
        Method::QueueBind(m) if !m.no_wait => QueueBindOk {}.into(),
        Method::QueueUnbind(_) => QueueUnbindOk {}.into(),
        Method::QueuePurge(m) if !m.no_wait => QueuePurgeOk { message_count: 0 }.into(),
        Method::QueueDelete(m) if !m.no_wait => QueueDeleteOk { message_count: 0 }.into(),
        Method::BasicQos(_) => BasicQosOk {}.into(),
        Method::BasicConsume(m) if !m.no_wait => BasicConsumeOk {
            consumer_tag: name(m.consumer_tag, "amq.ctag-sink-"),
        }
        .into(),
        Method::BasicCancel(m) if !m.no_wait => BasicCancelOk {
            consumer_tag: m.consumer_tag,
        }
        .into(),
        Method::ConfirmSelect(m) => {
            channels.confirm_tags.insert(channel, 0);
            if m.no_wait {
                return Reply::None;
            }
            ConfirmSelectOk {}.into()
        }
        Method::TxSelect(_) => TxSelectOk {}.into(),
        Method::TxCommit(_) => TxCommitOk {}.into(),
        Method::TxRollback(_) => TxRollbackOk {}.into(),
        _ => return Reply::None,
    };
    Reply::Send(answer)
}

#[cfg(test)]
mod tests {
    use super::*;
    use leveret_client::{
        BasicProperties, BasicPublishOptions, Connection, FieldTable, QueueDeclareOptions,
    };

    /// A real client declares, confirms and publishes against the sink.
    #[tokio::test]
    async fn a_client_publishes_into_the_sink_with_confirms() {
        let listener = TcpListener::bind("127.0.0.1:0").await.expect("bind");
        let addr = listener.local_addr().expect("addr");
        let published = Arc::new(AtomicU64::new(0));
        let counter = Arc::clone(&published);
        tokio::spawn(async move {
            loop {
                let (socket, _) = listener.accept().await.expect("accept");
                let counter = Arc::clone(&counter);
                tokio::spawn(async move { serve(socket, &counter).await });
            }
        });
        let connection = Connection::connect(&format!("amqp://guest:guest@{addr}/%2f"))
            .await
            .expect("connect");
        let channel = connection.open_channel().await.expect("channel");
        let queue = channel
            .queue_declare("", QueueDeclareOptions::default(), FieldTable::new())
            .await
            .expect("declare");
        assert!(queue
            .name
            .as_str()
            .is_some_and(|n| n.starts_with("amq.gen-sink-")));
        channel.confirm_select().await.expect("confirms");
        for _ in 0..100 {
            let confirm = channel
                .basic_publish(
                    "",
                    &queue.name,
                    BasicPublishOptions::default(),
                    BasicProperties::default(),
                    Bytes::from_static(b"0123456789abcdef"),
                )
                .await
                .expect("publish");
            assert!(confirm.await.expect("confirmed").is_ack());
        }
        assert_eq!(published.load(Ordering::Relaxed), 100);
        connection.close().await.expect("close");
    }
}
