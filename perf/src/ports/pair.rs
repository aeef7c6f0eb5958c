//! One round-trip loop of the `ports` scenario: the measuring side's two
//! ends and an echo task that sends back what it receives, carried either
//! by robot data ports or by plain `basic.publish` and a consumer on the
//! same topology (what the ports cost on top of the client).

use super::Carrier;
use crate::Result;
use bytes::Bytes;
use leveret_client::{
    BasicAckOptions, BasicConsumeOptions, BasicProperties, BasicPublishOptions, BasicQosOptions,
    Channel, Connection, Consumer, FieldTable, QueueDeclareOptions, ShortStr,
};
use leveret_ports::{Connector, FullPolicy, InPort, OutPort, PortProfile, PortStatus};
use std::time::Duration;
use tokio::sync::oneshot;
use tokio::task::JoinHandle;

/// An echo that takes longer than this counts as lost.
pub const ECHO_TIMEOUT: Duration = Duration::from_secs(5);
/// Unacknowledged deliveries a raw consumer may hold; with one message in
/// flight, only late echoes of failed round trips ever use it.
const RAW_PREFETCH: u16 = 16;

/// How to reach one broker.
#[derive(Clone)]
pub struct Endpoint {
    /// Opens connections (TCP or in-process).
    pub connector: Connector,
    /// The ports' profile for this broker.
    pub profile: PortProfile,
}

impl Endpoint {
    /// An endpoint whose ports are transient, with prefetch and buffer
    /// large enough never to matter with one message in flight, and
    /// nothing dropped.
    /// `busy_poll` is the in-ports' busy-poll window, if any.
    pub fn new(connector: Connector, base: PortProfile, busy_poll: Option<Duration>) -> Endpoint {
        let mut profile = base
            .buffer(16, FullPolicy::BlockBroker)
            .prefetch(16)
            .put_timeout(Duration::from_secs(2))
            .durable(false);
        profile.busy_poll = busy_poll;
        Endpoint { connector, profile }
    }
}

/// A round-trip loop: the measuring side's ends and the echo task.
pub enum Pair {
    /// Out-ports and in-ports.
    Ports {
        /// Puts towards the echo.
        output: OutPort<Bytes>,
        /// Receives the echo.
        input: InPort<Bytes>,
        /// Stops the echo task.
        stop: oneshot::Sender<()>,
        /// The echo task; its result is its failed puts.
        echo: JoinHandle<u64>,
    },
    /// A publishing channel and a consumer.
    Raw {
        /// Publishes towards the echo.
        publisher: Channel,
        /// Receives the echo.
        consumer: Consumer,
        /// The echo's queue.
        queue: ShortStr,
        /// The measuring side's connections, closed with the pair.
        connections: [Connection; 2],
        /// Stops the echo task.
        stop: oneshot::Sender<()>,
        /// The echo task; its result is its failed publishes and acks.
        echo: JoinHandle<u64>,
    },
}

impl Pair {
    /// Opens the loop for `carrier`: four connections either way.
    pub async fn open(endpoint: &Endpoint, carrier: Carrier) -> Result<Pair> {
        match carrier {
            Carrier::Ports => Pair::open_ports(endpoint, false).await,
            Carrier::ConfirmedPorts => Pair::open_ports(endpoint, true).await,
            Carrier::RawClient => Pair::open_raw(endpoint).await,
        }
    }

    /// Four ports, each with its own connection; the in-ports consume
    /// server-named exclusive queues and the out-ports publish to them
    /// through the default exchange.
    async fn open_ports(endpoint: &Endpoint, confirms: bool) -> Result<Pair> {
        let profile = endpoint.profile.clone().confirms(confirms);
        let connector = &endpoint.connector;
        let echo_in = InPort::<Bytes>::connect_with(connector.clone(), profile.clone()).await?;
        let input = InPort::<Bytes>::connect_with(connector.clone(), profile.clone()).await?;
        let to_echo = profile
            .clone()
            .routing_key(echo_in.queue().to_string_lossy());
        let output = OutPort::<Bytes>::connect_with(connector.clone(), to_echo).await?;
        let back = profile.routing_key(input.queue().to_string_lossy());
        let echo_out = OutPort::<Bytes>::connect_with(connector.clone(), back).await?;
        let (stop, stopped) = oneshot::channel();
        let echo = tokio::spawn(echo_ports(echo_in, echo_out, stopped));
        Ok(Pair::Ports {
            output,
            input,
            stop,
            echo,
        })
    }

    /// The same topology without ports: four connections, a consumer with
    /// manual acks on each side's server-named queue, and publishes of the
    /// bare body (no headers) through the default exchange.
    async fn open_raw(endpoint: &Endpoint) -> Result<Pair> {
        let (echo_in_conn, echo_in_channel) = raw_connect(&endpoint.connector).await?;
        let (echo_queue, echo_consumer) = raw_consume(echo_in_channel).await?;
        let (in_conn, in_channel) = raw_connect(&endpoint.connector).await?;
        let (queue, consumer) = raw_consume(in_channel).await?;
        let (out_conn, publisher) = raw_connect(&endpoint.connector).await?;
        let (echo_out_conn, echo_publisher) = raw_connect(&endpoint.connector).await?;
        let (stop, stopped) = oneshot::channel();
        let echo = tokio::spawn(echo_raw(
            echo_consumer,
            echo_publisher,
            queue,
            [echo_in_conn, echo_out_conn],
            stopped,
        ));
        Ok(Pair::Raw {
            publisher,
            consumer,
            queue: echo_queue,
            connections: [in_conn, out_conn],
            stop,
            echo,
        })
    }

    /// One round trip: sends `payload` and waits for its echo. Returns
    /// the echo's one-way latency where the carrier measures it (the
    /// ports: from the echo's put to the measuring in-port's arrival).
    pub async fn round_trip(&mut self, payload: &Bytes) -> Result<Option<Duration>> {
        match self {
            Pair::Ports { output, input, .. } => {
                let status = output.put(payload).await;
                if status != PortStatus::Ok {
                    return Err(format!("put: {status:?}").into());
                }
                match tokio::time::timeout(ECHO_TIMEOUT, input.recv()).await {
                    Ok(Some(sample)) => Ok(sample.latency),
                    Ok(None) => Err("the in-port closed".into()),
                    Err(_) => Err("no echo within the timeout".into()),
                }
            }
            Pair::Raw {
                publisher,
                consumer,
                queue,
                ..
            } => {
                publisher
                    .basic_publish(
                        "",
                        &*queue,
                        BasicPublishOptions::default(),
                        BasicProperties::default(),
                        payload.clone(),
                    )
                    .await?;
                match tokio::time::timeout(ECHO_TIMEOUT, consumer.next()).await {
                    Ok(Some(delivery)) => {
                        // Inside the timed section, but it only queues a
                        // frame on the connection's outbox.
                        delivery.ack().await?;
                        Ok(None)
                    }
                    Ok(None) => Err("the consumer ended".into()),
                    Err(_) => Err("no echo within the timeout".into()),
                }
            }
        }
    }

    /// Drops echoes already waiting (after a failed round trip).
    pub fn drain(&mut self) {
        match self {
            Pair::Ports { input, .. } => while input.try_recv().is_some() {},
            // Unacknowledged, they stay with the consumer until the pair
            // closes; the prefetch window is large enough for a few.
            Pair::Raw { .. } => {}
        }
    }

    /// Stops the echo task and closes everything; returns the echo's
    /// failures.
    pub async fn close(self) -> u64 {
        match self {
            Pair::Ports {
                output,
                input,
                stop,
                echo,
            } => {
                let _ = stop.send(());
                let failures = echo.await.unwrap_or(0);
                output.close().await;
                input.close().await;
                failures
            }
            Pair::Raw {
                connections,
                stop,
                echo,
                ..
            } => {
                let _ = stop.send(());
                let failures = echo.await.unwrap_or(0);
                for connection in connections {
                    let _ = connection.close().await;
                }
                failures
            }
        }
    }
}

/// A connection and a channel on it.
async fn raw_connect(connector: &Connector) -> Result<(Connection, Channel)> {
    let connection = connector.connect().await?;
    let channel = connection.open_channel().await?;
    Ok((connection, channel))
}

/// A server-named exclusive queue and a manual-ack consumer on it.
async fn raw_consume(channel: Channel) -> Result<(ShortStr, Consumer)> {
    channel
        .basic_qos(RAW_PREFETCH, BasicQosOptions::default())
        .await?;
    let declare = QueueDeclareOptions {
        exclusive: true,
        ..Default::default()
    };
    let queue = channel
        .queue_declare("", declare, FieldTable::new())
        .await?;
    let consumer = channel
        .basic_consume(
            &queue.name,
            "",
            BasicConsumeOptions::default(),
            FieldTable::new(),
        )
        .await?;
    Ok((queue.name, consumer))
}

/// Puts back every value the in-port receives, until told to stop.
async fn echo_ports(
    input: InPort<Bytes>,
    output: OutPort<Bytes>,
    mut stop: oneshot::Receiver<()>,
) -> u64 {
    let mut failures = 0;
    loop {
        tokio::select! {
            biased;
            _ = &mut stop => break,
            sample = input.recv() => match sample {
                Some(sample) => {
                    if output.put(&sample.value).await != PortStatus::Ok {
                        failures += 1;
                    }
                }
                None => break,
            },
        }
    }
    output.close().await;
    input.close().await;
    failures
}

/// Republishes every delivery's body to `queue`, then acknowledges it.
async fn echo_raw(
    mut consumer: Consumer,
    publisher: Channel,
    queue: ShortStr,
    connections: [Connection; 2],
    mut stop: oneshot::Receiver<()>,
) -> u64 {
    let mut failures = 0;
    loop {
        tokio::select! {
            biased;
            _ = &mut stop => break,
            delivery = consumer.next() => match delivery {
                Some(delivery) => {
                    let sent = publisher
                        .basic_publish(
                            "",
                            &queue,
                            BasicPublishOptions::default(),
                            BasicProperties::default(),
                            delivery.body.clone(),
                        )
                        .await;
                    let acked = consumer
                        .channel()
                        .basic_ack(delivery.delivery_tag, BasicAckOptions::default())
                        .await;
                    if sent.is_err() || acked.is_err() {
                        failures += 1;
                    }
                }
                None => break,
            },
        }
    }
    for connection in connections {
        let _ = connection.close().await;
    }
    failures
}
