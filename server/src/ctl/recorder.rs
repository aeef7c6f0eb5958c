//! `leveretctl port record NAME` and `port replay STREAM`: the ports'
//! flight recorder, with rosbag's habits. `record` binds a stream (made
//! with the retention asked for) to an announced port's exchange and key,
//! as a port profile's `Recording` does; `replay` plays a stream back
//! (leveret-ports' `Playback`) from a start to an end, at a rate, printing
//! each record or republishing it, with its original headers, to its
//! topic or another. This module owns the two commands, their arguments
//! and output; it uses the `ports` module's connection, port lookup and
//! value rendering, and the ctl's `Failure`s.

use crate::ports::{broker_failure, connect, find, show};
use crate::{emit, info, Cli, Failure};
use leveret_client::{BasicProperties, BasicPublishOptions, Channel, Connection};
use leveret_ports::{
    CdrOptions, PlayOptions, Playback, PortDirectory, Position, Recorded, Recording, OFFSET_HEADER,
};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

/// The options of `port record`.
#[derive(Debug, clap::Args)]
pub struct RecordArgs {
    /// The port whose messages are recorded (by its announced name).
    name: String,
    /// The stream recorded to (created if it does not exist).
    #[arg(long, value_name = "STREAM")]
    stream: String,
    /// How long records are kept (x-max-age: `30s`, `10m`, `2h`, `7D`).
    #[arg(long, value_name = "AGE")]
    max_age: Option<String>,
    /// The most bytes kept (x-max-length-bytes).
    #[arg(long, value_name = "BYTES")]
    max_length_bytes: Option<u64>,
    /// Seconds to wait for the port to announce itself (exit status 1 if
    /// it does not).
    #[arg(long, default_value = "3", value_name = "SECONDS")]
    wait: f64,
}

/// The options of `port replay`.
#[derive(Debug, clap::Args)]
pub struct ReplayArgs {
    /// The stream played.
    stream: String,
    /// Where to start: `first`, an offset (`120`), a time as Unix seconds
    /// (`@1764200000.25`), or how long ago (`30s`, `10m`, `2h`, `1D`).
    #[arg(long, default_value = "first", value_name = "POSITION")]
    start: String,
    /// The last record played: an offset, a time (`@SECONDS`) or how long
    /// ago, as --start. Without it, the replay ends once nothing more
    /// arrives for --idle seconds.
    #[arg(long, value_name = "POSITION")]
    end: Option<String>,
    /// The pace, as a factor of the recorded one (2: twice as fast).
    #[arg(long, default_value = "1", value_name = "FACTOR")]
    rate: f64,
    /// As fast as possible, without pacing (overrides --rate).
    #[arg(long)]
    fast: bool,
    /// Only records published to this topic: `EXCHANGE` or
    /// `EXCHANGE/KEY` (repeatable; all of them without one).
    #[arg(long, value_name = "TOPIC")]
    topic: Vec<String>,
    /// Republishes each record (its body and properties, with the original
    /// sequence number and send time) to the topic it was recorded from,
    /// instead of printing it.
    #[arg(long)]
    publish: bool,
    /// With --publish: republishes to this topic instead, `EXCHANGE` or
    /// `EXCHANGE/KEY` (the exchange must exist).
    #[arg(long, value_name = "TOPIC", requires = "publish")]
    into: Option<String>,
    /// Stop after this many records.
    #[arg(long, value_name = "N")]
    count: Option<u64>,
    /// Seconds without a record after which the replay ends (the end of
    /// what is recorded).
    #[arg(long, default_value = "1", value_name = "SECONDS")]
    idle: f64,
}

/// `port record`: binds the stream to the port's exchange and key.
pub async fn record(cli: &Cli, args: &RecordArgs) -> Result<(), Failure> {
    let connection = connect(cli).await?;
    let mut directory = PortDirectory::watch(&connection)
        .await
        .map_err(broker_failure)?;
    let wait = Duration::try_from_secs_f64(args.wait)
        .map_err(|_| Failure::Usage(format!("--wait {}: not a number of seconds", args.wait)))?;
    let port = find(&mut directory, &args.name, wait).await?;
    directory.close().await;
    if port.exchange.is_empty() {
        return Err(Failure::Refused(format!(
            "port {} is on the default exchange: a queue cannot be bound to it, so nothing can \
             record its messages (give the port a named exchange)",
            port.name
        )));
    }
    let recording = Recording {
        stream: args.stream.clone(),
        max_age: args.max_age.clone(),
        max_length_bytes: args.max_length_bytes,
    };
    let channel = connection.open_channel().await.map_err(broker_failure)?;
    recording
        .declare(&channel, &port.exchange, &port.key)
        .await
        .map_err(broker_failure)?;
    let _ = connection.close().await;
    info(
        cli,
        &format!(
            "Recording port {} (exchange {:?}, key {:?}) to stream {:?}",
            port.name, port.exchange, port.key, args.stream
        ),
    )?;
    Ok(())
}

/// A topic: an exchange and, optionally, a routing key.
#[derive(Debug, Clone, PartialEq, Eq)]
struct Topic {
    exchange: String,
    key: Option<String>,
}

impl Topic {
    fn parse(text: &str) -> Topic {
        match text.split_once('/') {
            Some((exchange, key)) => Topic {
                exchange: exchange.to_owned(),
                key: Some(key.to_owned()),
            },
            None => Topic {
                exchange: text.to_owned(),
                key: None,
            },
        }
    }

    fn matches(&self, exchange: &str, key: &str) -> bool {
        self.exchange == exchange && self.key.as_deref().is_none_or(|k| k == key)
    }
}

/// Parses a --start or --end position.
fn position(text: &str, option: &str) -> Result<Position, Failure> {
    let text = text.trim();
    if text == "first" {
        return Ok(Position::First);
    }
    if let Ok(offset) = text.parse::<u64>() {
        return Ok(Position::Offset(offset));
    }
    let bad = || {
        Failure::Usage(format!(
            "{option} {text:?}: `first`, an offset, @UNIX_SECONDS, or an age such as 10m"
        ))
    };
    if let Some(seconds) = text.strip_prefix('@') {
        let seconds: f64 = seconds.parse().map_err(|_| bad())?;
        let since = Duration::try_from_secs_f64(seconds).map_err(|_| bad())?;
        return Ok(Position::Time(UNIX_EPOCH + since));
    }
    let split = text.find(|c: char| !c.is_ascii_digit()).ok_or_else(bad)?;
    let (number, unit) = text.split_at(split);
    let number: u64 = number.parse().map_err(|_| bad())?;
    let unit_seconds = match unit {
        "s" => 1,
        "m" => 60,
        "h" => 3600,
        "D" => 86_400,
        _ => return Err(bad()),
    };
    let ago = Duration::from_secs(number.saturating_mul(unit_seconds));
    Ok(Position::Time(
        SystemTime::now().checked_sub(ago).unwrap_or(UNIX_EPOCH),
    ))
}

/// Where replayed records go.
enum Output {
    Print,
    /// Republished on this connection's channel (in confirm mode), to
    /// `into` or each record's own topic.
    Publish {
        connection: Connection,
        channel: Channel,
        into: Option<Topic>,
    },
}

/// `port replay`: plays the stream, printing or republishing.
pub async fn replay(cli: &Cli, args: &ReplayArgs) -> Result<(), Failure> {
    let start = position(&args.start, "--start")?;
    let end = match &args.end {
        Some(end) => match position(end, "--end")? {
            Position::First => {
                return Err(Failure::Usage(
                    "--end first: an end is an offset or a time".to_owned(),
                ))
            }
            end => Some(end),
        },
        None => None,
    };
    let rate = (!args.fast).then_some(args.rate);
    if rate.is_some_and(|rate| !(rate.is_finite() && rate > 0.0)) {
        return Err(Failure::Usage(format!(
            "--rate {}: a positive factor (or --fast)",
            args.rate
        )));
    }
    let idle = Duration::try_from_secs_f64(args.idle)
        .ok()
        .filter(|idle| !idle.is_zero())
        .ok_or_else(|| Failure::Usage(format!("--idle {}: not a number of seconds", args.idle)))?;
    let topics: Vec<Topic> = args.topic.iter().map(|t| Topic::parse(t)).collect();
    let options = PlayOptions {
        start,
        end,
        rate,
        idle: Some(idle),
    };
    let mut output = if args.publish {
        let connection = connect(cli).await?;
        let channel = connection.open_channel().await.map_err(broker_failure)?;
        channel.confirm_select().await.map_err(broker_failure)?;
        Output::Publish {
            connection,
            channel,
            into: args.into.as_deref().map(Topic::parse),
        }
    } else {
        Output::Print
    };
    let mut playback = Playback::over(connect(cli).await?, &args.stream, options)
        .await
        .map_err(broker_failure)?;
    info(
        cli,
        &format!(
            "Replaying stream {:?} from {} at {} ...",
            args.stream,
            args.start,
            if args.fast {
                "full speed".to_owned()
            } else {
                format!("{}x", args.rate)
            }
        ),
    )?;
    // The first record republished (its sender and sequence number):
    // reading it again means the replay has reached its own output, as
    // when it republishes into a recorded topic.
    let mut first_republished: Option<(String, u64)> = None;
    let mut played = 0u64;
    while args.count.is_none_or(|count| played < count) {
        let Some(record) = playback.next().await.map_err(broker_failure)? else {
            break;
        };
        let delivery = &record.delivery;
        if !topics.is_empty()
            && !topics.iter().any(|t| {
                t.matches(
                    &delivery.exchange.to_string_lossy(),
                    &delivery.routing_key.to_string_lossy(),
                )
            })
        {
            continue;
        }
        let identity = record.port.clone().zip(record.seq);
        if identity.is_some() && identity == first_republished {
            break;
        }
        match &mut output {
            Output::Print => emit(&line(&record))?,
            Output::Publish { channel, into, .. } => {
                republish(channel, into.as_ref(), &record).await?;
                if first_republished.is_none() {
                    first_republished = identity;
                }
            }
        }
        played += 1;
    }
    playback.close().await;
    if let Output::Publish {
        connection,
        channel,
        ..
    } = output
    {
        let all_acked = channel.wait_for_confirms().await.map_err(broker_failure)?;
        let _ = connection.close().await;
        if !all_acked {
            return Err(Failure::Refused(
                "the broker refused some republished records".to_owned(),
            ));
        }
    }
    info(cli, &format!("Replayed {played} records"))?;
    Ok(())
}

/// One printed record: `offset=N seq=S sent_ns=T topic=EXCHANGE/KEY VALUE`.
fn line(record: &Recorded) -> String {
    let delivery = &record.delivery;
    let type_name = delivery
        .properties
        .kind
        .as_ref()
        .map(|kind| kind.to_string_lossy().into_owned())
        .unwrap_or_default();
    let seq = record
        .seq
        .map_or_else(|| "-".to_owned(), |seq| seq.to_string());
    let sent = record
        .sent_at
        .and_then(|at| at.duration_since(UNIX_EPOCH).ok())
        .map_or_else(|| "-".to_owned(), |since| since.as_nanos().to_string());
    format!(
        "offset={} seq={seq} sent_ns={sent} topic={}/{} {}\n",
        record.offset,
        delivery.exchange,
        delivery.routing_key,
        show(&type_name, delivery.body.clone(), CdrOptions::default())
    )
}

/// Publishes `record` again, with its properties (less the stream's
/// offset header), to `into` or to the topic it was recorded from.
async fn republish(
    channel: &Channel,
    into: Option<&Topic>,
    record: &Recorded,
) -> Result<(), Failure> {
    let delivery = &record.delivery;
    let mut properties: BasicProperties = delivery.properties.clone();
    if let Some(headers) = properties.headers.as_mut() {
        headers.remove(OFFSET_HEADER);
    }
    let (exchange, key) = match into {
        Some(topic) => (
            topic.exchange.clone(),
            topic
                .key
                .clone()
                .unwrap_or_else(|| delivery.routing_key.to_string()),
        ),
        None => (
            delivery.exchange.to_string(),
            delivery.routing_key.to_string(),
        ),
    };
    channel
        .basic_publish(
            exchange.as_str(),
            key.as_str(),
            BasicPublishOptions::default(),
            properties,
            delivery.body.clone(),
        )
        .await
        .map_err(broker_failure)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn positions_are_first_offsets_unix_times_and_ages() {
        assert_eq!(position("first", "--start").ok(), Some(Position::First));
        assert_eq!(
            position(" 120 ", "--start").ok(),
            Some(Position::Offset(120))
        );
        assert_eq!(
            position("@1764200000.25", "--start").ok(),
            Some(Position::Time(
                UNIX_EPOCH + Duration::from_millis(1_764_200_000_250)
            ))
        );
        let before = SystemTime::now();
        let Ok(Position::Time(ago)) = position("10m", "--start") else {
            panic!("10m is an age");
        };
        let age = before.duration_since(ago).expect("in the past");
        assert!(age >= Duration::from_secs(599), "{age:?}");
        for bad in ["", "soon", "-5", "10ms", "1d", "@", "@x", "@-1"] {
            assert!(
                matches!(position(bad, "--start"), Err(Failure::Usage(_))),
                "{bad:?}"
            );
        }
    }

    #[test]
    fn topics_match_an_exchange_or_an_exchange_and_key() {
        let exchange = Topic::parse("poses");
        assert!(exchange.matches("poses", "any"));
        assert!(!exchange.matches("other", "any"));
        let keyed = Topic::parse("poses/robot1");
        assert!(keyed.matches("poses", "robot1"));
        assert!(!keyed.matches("poses", "robot2"));
    }
}
