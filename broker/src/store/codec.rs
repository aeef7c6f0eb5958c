//! The store's key and value encoding (the key layout is described in the
//! module above): each [`StoreOp`] as the key-value change it makes, and a
//! full scan decoded back into [`Recovered`] records. Decoding checks every
//! length and tag, so a damaged value is an error, never a panic.

use super::{
    BindingRecord, EntryBody, ExchangeRecord, KvOp, KvPair, MessageRecord, MetaKey, MetaRecord,
    QueueRecord, Recovered, RecoveredEntry, StoreError, StoreOp,
};
use bytes::{Buf, BufMut, Bytes, BytesMut};
use leveret_protocol::{FieldTable, ShortStr};

fn put_short(buf: &mut impl BufMut, s: &ShortStr) {
    buf.put_u8(s.len() as u8);
    buf.put_slice(s.as_bytes());
}

fn take_short(buf: &mut Bytes) -> Result<ShortStr, StoreError> {
    if buf.is_empty() {
        return Err(corrupt("short string"));
    }
    let len = usize::from(buf.get_u8());
    if buf.len() < len {
        return Err(corrupt("short string"));
    }
    ShortStr::try_from(buf.split_to(len)).map_err(|_| corrupt("short string"))
}

fn put_long(buf: &mut impl BufMut, b: &[u8]) {
    buf.put_u32(b.len() as u32);
    buf.put_slice(b);
}

fn take_long(buf: &mut Bytes) -> Result<Bytes, StoreError> {
    if buf.len() < 4 {
        return Err(corrupt("long string"));
    }
    let len = buf.get_u32() as usize;
    if buf.len() < len {
        return Err(corrupt("long string"));
    }
    Ok(buf.split_to(len))
}

fn take_table(buf: &mut Bytes) -> Result<FieldTable, StoreError> {
    if buf.len() < 4 {
        return Err(corrupt("table"));
    }
    let len = u32::from_be_bytes([buf[0], buf[1], buf[2], buf[3]]) as usize;
    if buf.len() < 4 + len {
        return Err(corrupt("table"));
    }
    Ok(FieldTable::decode(&buf.split_to(4 + len))?)
}

fn take_u8(buf: &mut Bytes) -> Result<u8, StoreError> {
    if buf.is_empty() {
        return Err(corrupt("octet"));
    }
    Ok(buf.get_u8())
}

fn take_u32(buf: &mut Bytes) -> Result<u32, StoreError> {
    if buf.len() < 4 {
        return Err(corrupt("u32"));
    }
    Ok(buf.get_u32())
}

fn take_u64(buf: &mut Bytes) -> Result<u64, StoreError> {
    if buf.len() < 8 {
        return Err(corrupt("u64"));
    }
    Ok(buf.get_u64())
}

fn corrupt(what: &'static str) -> StoreError {
    StoreError::Corrupt { what }
}

fn name_key(tag: u8, vhost: &ShortStr, name: &ShortStr) -> Vec<u8> {
    let mut key = Vec::with_capacity(2 + vhost.len() + name.len());
    key.push(tag);
    key.extend_from_slice(vhost.as_bytes());
    key.push(0);
    key.extend_from_slice(name.as_bytes());
    key
}

fn binding_key(b: &BindingRecord) -> Vec<u8> {
    let mut buf = BytesMut::new();
    buf.put_u8(b'b');
    put_short(&mut buf, &b.vhost);
    put_short(&mut buf, &b.source);
    buf.put_u8(u8::from(b.to_queue));
    put_short(&mut buf, &b.destination);
    put_short(&mut buf, &b.routing_key);
    b.arguments.encode(&mut buf);
    buf.to_vec()
}

fn mark_key(queue: u64) -> Vec<u8> {
    let mut key = Vec::with_capacity(9);
    key.push(b'd');
    key.extend_from_slice(&queue.to_be_bytes());
    key
}

fn put_record(v: &mut impl BufMut, record: &MessageRecord) {
    put_short(v, &record.exchange);
    put_short(v, &record.routing_key);
    put_long(v, &record.properties);
    put_long(v, &record.body);
}

/// The bytes [`put_record`] writes.
fn record_len(record: &MessageRecord) -> usize {
    2 + record.exchange.len()
        + record.routing_key.len()
        + 8
        + record.properties.len()
        + record.body.len()
}

fn take_record(value: &mut Bytes) -> Result<MessageRecord, StoreError> {
    Ok(MessageRecord {
        exchange: take_short(value)?,
        routing_key: take_short(value)?,
        properties: take_long(value)?,
        body: take_long(value)?,
    })
}

fn message_key(id: u64) -> Vec<u8> {
    let mut key = Vec::with_capacity(9);
    key.push(b'm');
    key.extend_from_slice(&id.to_be_bytes());
    key
}

/// The queue id and position an index key (`i`) names, if it is one.
#[cfg(feature = "persistence")]
pub fn queue_position(key: &[u8]) -> Option<(u64, u64)> {
    match key {
        [b'i', rest @ ..] if rest.len() == 16 => Some((
            u64::from_be_bytes(rest[..8].try_into().ok()?),
            u64::from_be_bytes(rest[8..].try_into().ok()?),
        )),
        _ => None,
    }
}

fn index_key(queue: u64, seq: u64) -> Vec<u8> {
    let mut key = Vec::with_capacity(17);
    key.push(b'i');
    key.extend_from_slice(&queue.to_be_bytes());
    key.extend_from_slice(&seq.to_be_bytes());
    key
}

/// A metadata record's key: `a`, its kind, then each name as a long
/// string (names may hold any byte, so none is a separator).
fn meta_key(key: &MetaKey) -> Vec<u8> {
    let mut buf = BytesMut::new();
    buf.put_u8(b'a');
    match key {
        MetaKey::User(name) => {
            buf.put_u8(b'u');
            put_long(&mut buf, name.as_bytes());
        }
        MetaKey::Vhost(name) => {
            buf.put_u8(b'v');
            put_long(&mut buf, name.as_bytes());
        }
        MetaKey::Permission { user, vhost } => {
            buf.put_u8(b'p');
            put_long(&mut buf, user.as_bytes());
            put_long(&mut buf, vhost.as_bytes());
        }
        MetaKey::TopicPermission {
            user,
            vhost,
            exchange,
        } => {
            buf.put_u8(b't');
            put_long(&mut buf, user.as_bytes());
            put_long(&mut buf, vhost.as_bytes());
            put_long(&mut buf, exchange.as_bytes());
        }
        MetaKey::Parameter {
            component,
            vhost,
            name,
        } => {
            buf.put_u8(b'r');
            put_long(&mut buf, component.as_bytes());
            put_long(&mut buf, vhost.as_bytes());
            put_long(&mut buf, name.as_bytes());
        }
        MetaKey::Retained { vhost, topic } => {
            buf.put_u8(b'm');
            put_long(&mut buf, vhost.as_bytes());
            put_long(&mut buf, topic.as_bytes());
        }
        MetaKey::Unreleased {
            vhost,
            client_id,
            packet_id,
        } => {
            buf.put_u8(b'q');
            put_long(&mut buf, vhost.as_bytes());
            put_long(&mut buf, client_id.as_bytes());
            buf.put_u16(*packet_id);
        }
        MetaKey::SharedSubscription {
            vhost,
            client_id,
            filter,
        } => {
            buf.put_u8(b's');
            put_long(&mut buf, vhost.as_bytes());
            put_long(&mut buf, client_id.as_bytes());
            put_long(&mut buf, filter.as_bytes());
        }
    }
    buf.to_vec()
}

/// A metadata record's value: the fields its key does not hold.
fn meta_value(record: &MetaRecord) -> Vec<u8> {
    let mut buf = BytesMut::new();
    match record {
        MetaRecord::User {
            password_hash,
            hashing_algorithm,
            tags,
            ..
        } => {
            put_long(&mut buf, password_hash.as_bytes());
            put_long(&mut buf, hashing_algorithm.as_bytes());
            buf.put_u32(tags.len() as u32);
            for tag in tags {
                put_long(&mut buf, tag.as_bytes());
            }
        }
        MetaRecord::Vhost { .. } => {}
        MetaRecord::Permission {
            configure,
            write,
            read,
            ..
        } => {
            put_long(&mut buf, configure.as_bytes());
            put_long(&mut buf, write.as_bytes());
            put_long(&mut buf, read.as_bytes());
        }
        MetaRecord::TopicPermission { write, read, .. } => {
            put_long(&mut buf, write.as_bytes());
            put_long(&mut buf, read.as_bytes());
        }
        MetaRecord::Parameter { value, .. } => put_long(&mut buf, value.as_bytes()),
        MetaRecord::Retained {
            qos,
            properties,
            payload,
            ..
        } => {
            buf.put_u8(*qos);
            put_long(&mut buf, payload);
            // After the payload: records written before retained messages
            // kept properties end there.
            if !properties.is_empty() {
                put_long(&mut buf, properties);
            }
        }
        MetaRecord::Unreleased { session_expiry, .. } => {
            // Records written before sessions' expiry was kept have none.
            if let Some(seconds) = session_expiry {
                buf.put_u32(*seconds);
            }
        }
        MetaRecord::SharedSubscription {
            qos,
            retain_as_published,
            subscription_id,
            session_expiry,
            ..
        } => {
            buf.put_u8(*qos);
            buf.put_u8(u8::from(*retain_as_published));
            buf.put_u32(*subscription_id);
            buf.put_u32(*session_expiry);
        }
    }
    buf.to_vec()
}

fn take_text(buf: &mut Bytes, what: &'static str) -> Result<String, StoreError> {
    String::from_utf8(take_long(buf)?.to_vec()).map_err(|_| corrupt(what))
}

/// Decodes a metadata record from its key (after the `a`) and value.
fn decode_meta(key: &[u8], value: &mut Bytes) -> Result<MetaRecord, StoreError> {
    let Some((&kind, names)) = key.split_first() else {
        return Err(corrupt("metadata key"));
    };
    let mut names = Bytes::copy_from_slice(names);
    let record = match kind {
        b'u' => {
            let name = take_text(&mut names, "user name")?;
            let password_hash = take_text(value, "password hash")?;
            let hashing_algorithm = take_text(value, "hashing algorithm")?;
            let count = take_u32(value)?;
            // Each tag takes at least its 4-byte length: a count the value
            // cannot hold is damage, not an allocation.
            if value.len() < count as usize * 4 {
                return Err(corrupt("user tags"));
            }
            let tags = (0..count)
                .map(|_| take_text(value, "user tag"))
                .collect::<Result<_, _>>()?;
            MetaRecord::User {
                name,
                password_hash,
                hashing_algorithm,
                tags,
            }
        }
        b'v' => MetaRecord::Vhost {
            name: take_text(&mut names, "vhost name")?,
        },
        b'p' => MetaRecord::Permission {
            user: take_text(&mut names, "user name")?,
            vhost: take_text(&mut names, "vhost name")?,
            configure: take_text(value, "configure pattern")?,
            write: take_text(value, "write pattern")?,
            read: take_text(value, "read pattern")?,
        },
        b't' => MetaRecord::TopicPermission {
            user: take_text(&mut names, "user name")?,
            vhost: take_text(&mut names, "vhost name")?,
            exchange: take_text(&mut names, "exchange name")?,
            write: take_text(value, "write pattern")?,
            read: take_text(value, "read pattern")?,
        },
        b'r' => MetaRecord::Parameter {
            component: take_text(&mut names, "parameter component")?,
            vhost: take_text(&mut names, "vhost name")?,
            name: take_text(&mut names, "parameter name")?,
            value: take_text(value, "parameter value")?,
        },
        b'm' => MetaRecord::Retained {
            vhost: take_text(&mut names, "vhost name")?,
            topic: take_text(&mut names, "retained topic")?,
            qos: match value.first() {
                Some(&qos) if qos <= 2 => {
                    value.advance(1);
                    qos
                }
                _ => return Err(corrupt("retained QoS")),
            },
            payload: take_long(value)?,
            properties: if value.is_empty() {
                Bytes::new()
            } else {
                take_long(value)?
            },
        },
        b'q' => MetaRecord::Unreleased {
            vhost: take_text(&mut names, "vhost name")?,
            client_id: take_text(&mut names, "MQTT client identifier")?,
            packet_id: match (names.len() >= 2).then(|| names.get_u16()) {
                Some(id) if id != 0 => id,
                _ => return Err(corrupt("MQTT packet identifier")),
            },
            session_expiry: match value.len() {
                0 => None,
                4.. => Some(value.get_u32()),
                _ => return Err(corrupt("MQTT session expiry")),
            },
        },
        b's' => MetaRecord::SharedSubscription {
            vhost: take_text(&mut names, "vhost name")?,
            client_id: take_text(&mut names, "MQTT client identifier")?,
            filter: take_text(&mut names, "shared subscription filter")?,
            qos: match value.first() {
                Some(&qos) if qos <= 2 => {
                    value.advance(1);
                    qos
                }
                _ => return Err(corrupt("shared subscription QoS")),
            },
            retain_as_published: match value.first() {
                Some(&flag) if flag <= 1 => {
                    value.advance(1);
                    flag == 1
                }
                _ => return Err(corrupt("shared subscription option")),
            },
            subscription_id: match (value.len() >= 4).then(|| value.get_u32()) {
                Some(id) => id,
                None => return Err(corrupt("shared subscription identifier")),
            },
            session_expiry: match (value.len() >= 4).then(|| value.get_u32()) {
                Some(seconds) => seconds,
                None => return Err(corrupt("shared subscription's session expiry")),
            },
        },
        _ => return Err(corrupt("metadata kind")),
    };
    if !names.is_empty() || !value.is_empty() {
        return Err(corrupt("metadata record length"));
    }
    Ok(record)
}

impl StoreOp {
    /// The key-value change this op makes.
    pub fn to_kv(&self) -> KvOp {
        match self {
            StoreOp::PutExchange(x) => {
                let mut v = BytesMut::new();
                put_short(&mut v, &x.kind);
                v.put_u8(u8::from(x.auto_delete) | (u8::from(x.internal) << 1));
                x.arguments.encode(&mut v);
                (name_key(b'e', &x.vhost, &x.name), Some(v.to_vec()))
            }
            StoreOp::DeleteExchange { vhost, name } => (name_key(b'e', vhost, name), None),
            StoreOp::PutQueue(q) => {
                let mut v = BytesMut::new();
                v.put_u64(q.id);
                v.put_u8(u8::from(q.auto_delete));
                q.arguments.encode(&mut v);
                (name_key(b'q', &q.vhost, &q.name), Some(v.to_vec()))
            }
            StoreOp::DeleteQueue { vhost, name } => (name_key(b'q', vhost, name), None),
            StoreOp::PutBinding(b) => (binding_key(b), Some(Vec::new())),
            StoreOp::DeleteBinding(b) => (binding_key(b), None),
            StoreOp::PutMessage { id, record } => {
                let mut v = Vec::with_capacity(record_len(record));
                put_record(&mut v, record);
                (message_key(*id), Some(v))
            }
            StoreOp::DeleteMessage { id } => (message_key(*id), None),
            StoreOp::Enqueue { queue, seq, body } => {
                let value = match body {
                    EntryBody::Inline(record) => {
                        let mut v = Vec::with_capacity(1 + record_len(record));
                        v.put_u8(0);
                        put_record(&mut v, record);
                        v
                    }
                    EntryBody::Shared(id) => {
                        let mut v = Vec::with_capacity(9);
                        v.push(1);
                        v.extend_from_slice(&id.to_be_bytes());
                        v
                    }
                };
                (index_key(*queue, *seq), Some(value))
            }
            StoreOp::Delivered { queue, seq } => {
                (mark_key(*queue), Some(seq.to_be_bytes().to_vec()))
            }
            StoreOp::Dequeue { queue, seq } => (index_key(*queue, *seq), None),
            StoreOp::PutMeta(record) => (meta_key(&record.key()), Some(meta_value(record))),
            StoreOp::DeleteMeta(key) => (meta_key(key), None),
            StoreOp::Seeded => (SEEDED_MARKER_KEY.to_vec(), Some(Vec::new())),
            StoreOp::Starts { count } => (STARTS_KEY.to_vec(), Some(count.to_be_bytes().to_vec())),
            StoreOp::CleanShutdown { generation } => (
                CLEAN_MARKER_KEY.to_vec(),
                Some(generation.to_be_bytes().to_vec()),
            ),
        }
    }
}

/// Which engine of the [`DiskStore`](super::DiskStore) keeps a key.
#[cfg(feature = "persistence")]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Home {
    /// The message log: the keys written per message (index entries,
    /// shared records, delivery marks).
    Log,
    /// sled: definitions, users, parameters, the start count.
    Definitions,
    /// Both: the clean-shutdown marker, so each engine's files are checked
    /// against the manifest.
    Both,
}

/// Where `key` is kept.
#[cfg(feature = "persistence")]
pub fn home(key: &[u8]) -> Home {
    if LOG_PREFIXES.iter().any(|prefix| key.starts_with(prefix)) {
        Home::Log
    } else if key == CLEAN_MARKER_KEY {
        Home::Both
    } else {
        Home::Definitions
    }
}

/// The first bytes of every key kept in the message log.
#[cfg(feature = "persistence")]
pub const LOG_PREFIXES: [&[u8]; 3] = [b"i", b"m", b"d"];

/// The clean-shutdown marker's key (`!` sorts before every other tag).
pub const CLEAN_MARKER_KEY: &[u8] = b"!clean";

/// The key marking that the default user has been considered.
const SEEDED_MARKER_KEY: &[u8] = b"!seeded";

/// The key counting the broker's starts on the store.
const STARTS_KEY: &[u8] = b"!starts";

/// A record that could not be decoded: its key (escaped) and why.
#[derive(Debug, Clone, PartialEq)]
pub struct BadRecord {
    /// The key, printable.
    pub key: String,
    /// What is wrong with it.
    pub error: String,
}

impl std::fmt::Display for BadRecord {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "record {}: {}", self.key, self.error)
    }
}

impl Recovered {
    /// Decodes a full scan of a store; the first record that cannot be
    /// decoded is the error.
    pub fn from_scan(pairs: Vec<KvPair>) -> Result<Recovered, BadRecord> {
        let mut out = Recovered::default();
        for (key, value) in pairs {
            if let Err(e) = out.decode(&key, value) {
                return Err(bad_record(&key, &e));
            }
        }
        Ok(out)
    }

    /// Decodes what can be decoded of a full scan, and lists the records
    /// that cannot (for `--recover`).
    pub fn salvage(pairs: Vec<KvPair>) -> (Recovered, Vec<BadRecord>) {
        let mut out = Recovered::default();
        let mut dropped = Vec::new();
        for (key, value) in pairs {
            if let Err(e) = out.decode(&key, value) {
                dropped.push(bad_record(&key, &e));
            }
        }
        (out, dropped)
    }

    /// Adds one stored record.
    fn decode(&mut self, key: &[u8], value: Vec<u8>) -> Result<(), StoreError> {
        let out = self;
        let Some((&tag, rest)) = key.split_first() else {
            return Err(corrupt("empty key"));
        };
        let mut value = Bytes::from(value);
        match tag {
            b'!' if key == CLEAN_MARKER_KEY => {
                let bytes: [u8; 8] = value[..]
                    .try_into()
                    .map_err(|_| corrupt("clean-shutdown marker"))?;
                out.clean_generation = Some(u64::from_be_bytes(bytes));
            }
            b'!' if key == SEEDED_MARKER_KEY => out.seeded = true,
            b'!' if key == STARTS_KEY => {
                let bytes: [u8; 8] = value[..].try_into().map_err(|_| corrupt("start count"))?;
                out.starts = u64::from_be_bytes(bytes);
            }
            b'a' => out.meta.push(decode_meta(rest, &mut value)?),
            b'e' | b'q' => {
                let split = rest
                    .iter()
                    .position(|&b| b == 0)
                    .ok_or_else(|| corrupt("name key"))?;
                let vhost = ShortStr::try_from(Bytes::copy_from_slice(&rest[..split]))
                    .map_err(|_| corrupt("vhost"))?;
                let name = ShortStr::try_from(Bytes::copy_from_slice(&rest[split + 1..]))
                    .map_err(|_| corrupt("name"))?;
                if tag == b'e' {
                    let kind = take_short(&mut value)?;
                    let flags = take_u8(&mut value)?;
                    let arguments = take_table(&mut value)?;
                    out.exchanges.push(ExchangeRecord {
                        vhost,
                        name,
                        kind,
                        auto_delete: flags & 1 != 0,
                        internal: flags & 2 != 0,
                        arguments,
                    });
                } else {
                    let id = take_u64(&mut value)?;
                    let auto_delete = take_u8(&mut value)? != 0;
                    let arguments = take_table(&mut value)?;
                    out.queues.push(QueueRecord {
                        vhost,
                        name,
                        id,
                        auto_delete,
                        arguments,
                    });
                }
            }
            b'b' => {
                let mut k = Bytes::copy_from_slice(rest);
                out.bindings.push(BindingRecord {
                    vhost: take_short(&mut k)?,
                    source: take_short(&mut k)?,
                    to_queue: take_u8(&mut k)? != 0,
                    destination: take_short(&mut k)?,
                    routing_key: take_short(&mut k)?,
                    arguments: take_table(&mut k)?,
                });
            }
            b'm' => {
                let id = u64::from_be_bytes(rest.try_into().map_err(|_| corrupt("message key"))?);
                out.messages.insert(id, take_record(&mut value)?);
            }
            b'd' => {
                let queue = u64::from_be_bytes(rest.try_into().map_err(|_| corrupt("mark key"))?);
                out.delivered.insert(queue, take_u64(&mut value)?);
            }
            b'i' => {
                if rest.len() != 16 {
                    return Err(corrupt("index key"));
                }
                let queue =
                    u64::from_be_bytes(rest[..8].try_into().map_err(|_| corrupt("index key"))?);
                let seq =
                    u64::from_be_bytes(rest[8..].try_into().map_err(|_| corrupt("index key"))?);
                let body = match take_u8(&mut value)? {
                    0 => EntryBody::Inline(take_record(&mut value)?),
                    1 => EntryBody::Shared(take_u64(&mut value)?),
                    _ => return Err(corrupt("index entry kind")),
                };
                out.entries
                    .entry(queue)
                    .or_default()
                    .push(RecoveredEntry { seq, body });
            }
            _ => return Err(corrupt("unknown key tag")),
        }
        Ok(())
    }
}

fn bad_record(key: &[u8], error: &StoreError) -> BadRecord {
    BadRecord {
        key: key.escape_ascii().to_string(),
        error: error.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::{MemoryStore, Store, WriteMode};
    use leveret_protocol::FieldValue;

    fn s(v: &'static str) -> ShortStr {
        ShortStr::from_static(v)
    }

    /// A record's value is allocated at its exact size: no copy to fit.
    #[test]
    fn a_record_value_is_sized_exactly() {
        let record = MessageRecord {
            exchange: s("ex"),
            routing_key: s("a.b"),
            properties: Bytes::from_static(b"\x10\x00\x02"),
            body: Bytes::from(vec![7u8; 1000]),
        };
        let (_, shared) = StoreOp::PutMessage {
            id: 1,
            record: record.clone(),
        }
        .to_kv();
        let shared = shared.unwrap();
        assert_eq!(shared.len(), record_len(&record));
        assert_eq!(shared.capacity(), shared.len());
        let (_, inline) = StoreOp::Enqueue {
            queue: 1,
            seq: 1,
            body: EntryBody::Inline(record.clone()),
        }
        .to_kv();
        assert_eq!(inline.unwrap().len(), 1 + record_len(&record));
    }

    #[test]
    fn every_record_round_trips_through_keys_and_values() {
        let store = MemoryStore::default();
        let mut args = FieldTable::new();
        args.insert(s("x-max-length"), FieldValue::I64(5));
        let ops = [
            StoreOp::PutExchange(ExchangeRecord {
                vhost: s("/"),
                name: s("ex"),
                kind: s("topic"),
                auto_delete: false,
                internal: true,
                arguments: args.clone(),
            }),
            StoreOp::PutQueue(QueueRecord {
                vhost: s("/"),
                name: s("q"),
                id: 7,
                auto_delete: true,
                arguments: args.clone(),
            }),
            StoreOp::PutBinding(BindingRecord {
                vhost: s("/"),
                source: s("ex"),
                to_queue: true,
                destination: s("q"),
                routing_key: s("a.#"),
                arguments: args,
            }),
            StoreOp::PutMessage {
                id: 3,
                record: MessageRecord {
                    exchange: s("ex"),
                    routing_key: s("a.b"),
                    properties: Bytes::from_static(b"\x10\x00\x02"),
                    body: Bytes::from_static(b"hello"),
                },
            },
            StoreOp::Enqueue {
                queue: 7,
                seq: 2,
                body: EntryBody::Shared(3),
            },
            StoreOp::Enqueue {
                queue: 7,
                seq: 1,
                body: EntryBody::Inline(MessageRecord {
                    exchange: s(""),
                    routing_key: s("q"),
                    properties: Bytes::from_static(b"\x00\x00"),
                    body: Bytes::from_static(b"inline"),
                }),
            },
            StoreOp::Delivered { queue: 7, seq: 1 },
        ];
        store
            .write(ops.iter().map(StoreOp::to_kv).collect(), WriteMode::Atomic)
            .unwrap();
        let recovered = Recovered::from_scan(store.scan().unwrap()).unwrap();
        assert_eq!(recovered.exchanges.len(), 1);
        assert!(recovered.exchanges[0].internal);
        assert_eq!(recovered.queues[0].id, 7);
        assert_eq!(recovered.bindings[0].routing_key, s("a.#"));
        assert_eq!(recovered.messages[&3].body, Bytes::from_static(b"hello"));
        let entries = &recovered.entries[&7];
        assert_eq!(
            entries.iter().map(|e| e.seq).collect::<Vec<_>>(),
            vec![1, 2]
        );
        assert!(
            matches!(&entries[0].body, EntryBody::Inline(r) if r.body == Bytes::from_static(b"inline"))
        );
        assert_eq!(entries[1].body, EntryBody::Shared(3));
        assert_eq!(recovered.delivered[&7], 1);
        assert_eq!(recovered.max_message_id(), 3);

        store
            .write(
                vec![
                    StoreOp::Dequeue { queue: 7, seq: 1 }.to_kv(),
                    StoreOp::Dequeue { queue: 7, seq: 2 }.to_kv(),
                    StoreOp::DeleteMessage { id: 3 }.to_kv(),
                ],
                WriteMode::Plain,
            )
            .unwrap();
        let recovered = Recovered::from_scan(store.scan().unwrap()).unwrap();
        assert!(recovered.messages.is_empty());
        assert!(recovered.entries.is_empty());
    }

    /// `--recover` keeps every readable record and names each bad one;
    /// the strict decoding names the first.
    #[test]
    fn salvage_keeps_readable_records_and_names_the_bad_ones() {
        let good = StoreOp::DeleteExchange {
            vhost: s("/"),
            name: s("x"),
        };
        let mut exchange = good.to_kv();
        exchange.1 = Some({
            let mut v = BytesMut::new();
            put_short(&mut v, &s("direct"));
            v.put_u8(0);
            FieldTable::new().encode(&mut v);
            v.to_vec()
        });
        let marker = StoreOp::CleanShutdown { generation: 9 }.to_kv();
        let pairs = vec![
            (marker.0, marker.1.unwrap()),
            (b"m\0\0\0\0\0\0\0\x01".to_vec(), vec![200, 1, 2]),
            (exchange.0, exchange.1.unwrap()),
            (b"zzz".to_vec(), vec![]),
        ];
        let strict = Recovered::from_scan(pairs.clone()).unwrap_err();
        assert!(strict.key.starts_with('m'), "{strict}");
        let (recovered, dropped) = Recovered::salvage(pairs);
        assert_eq!(recovered.exchanges.len(), 1);
        assert_eq!(recovered.clean_generation, Some(9));
        assert_eq!(dropped.len(), 2, "{dropped:?}");
        assert_eq!(dropped[1].key, "zzz");
    }

    #[test]
    fn corrupt_values_are_errors_not_panics() {
        let pairs = vec![(b"m\0\0\0\0\0\0\0\x01".to_vec(), vec![200, 1, 2])];
        assert!(Recovered::from_scan(pairs).is_err());
        let pairs = vec![(b"i\0\0".to_vec(), vec![])];
        assert!(Recovered::from_scan(pairs).is_err());
    }

    /// Users, vhosts and permissions round trip with names holding any
    /// byte (a NUL in a name cannot shift one into the next); a delete
    /// removes exactly its record; damaged values are errors.
    #[test]
    fn metadata_records_round_trip_and_delete_by_key() {
        let store = MemoryStore::default();
        let records = [
            MetaRecord::User {
                name: "ro\0bot".into(),
                password_hash: "$argon2id$v=19$...".into(),
                hashing_algorithm: "leveret_argon2id".into(),
                tags: vec!["monitoring".into(), "management".into()],
            },
            MetaRecord::Vhost {
                name: "cell-1".into(),
            },
            MetaRecord::Permission {
                user: "a\0".into(),
                vhost: "b".into(),
                configure: ".*".into(),
                write: "^x".into(),
                read: String::new(),
            },
            MetaRecord::Permission {
                user: "a".into(),
                vhost: "\0b".into(),
                configure: "c".into(),
                write: "w".into(),
                read: "r".into(),
            },
            MetaRecord::TopicPermission {
                user: "a".into(),
                vhost: "/".into(),
                exchange: "amq.topic".into(),
                write: "^a\\.".into(),
                read: ".*".into(),
            },
            MetaRecord::Parameter {
                component: "shovel".into(),
                vhost: "/".into(),
                name: "up".into(),
                value: r#"{"src-queue": "q"}"#.into(),
            },
            // Without properties: as records written before they were
            // kept (nothing after the payload).
            MetaRecord::Retained {
                vhost: "/".into(),
                topic: "cell/\0temp".into(),
                qos: 1,
                properties: Bytes::new(),
                payload: Bytes::from_static(b"21.5\0"),
            },
            MetaRecord::Retained {
                vhost: "/".into(),
                topic: "cell/humidity".into(),
                qos: 0,
                properties: Bytes::from_static(b"opaque to the store"),
                payload: Bytes::from_static(b"40"),
            },
            MetaRecord::Unreleased {
                vhost: "/".into(),
                client_id: "sensor\0-1".into(),
                packet_id: 65_535,
                session_expiry: Some(u32::MAX),
            },
            MetaRecord::Unreleased {
                vhost: "/".into(),
                client_id: "sensor-2".into(),
                packet_id: 1,
                session_expiry: Some(3600),
            },
            MetaRecord::Unreleased {
                vhost: "/".into(),
                client_id: "sensor-3".into(),
                packet_id: 2,
                session_expiry: None,
            },
            MetaRecord::SharedSubscription {
                vhost: "/".into(),
                client_id: "sensor-1".into(),
                filter: "$share/g/cell/+".into(),
                qos: 2,
                retain_as_published: true,
                subscription_id: 268_435_455,
                session_expiry: u32::MAX,
            },
        ];
        let mut ops: Vec<_> = records
            .iter()
            .map(|r| StoreOp::PutMeta(r.clone()).to_kv())
            .collect();
        ops.push(StoreOp::Seeded.to_kv());
        ops.push(StoreOp::Starts { count: 3 }.to_kv());
        store.write(ops, WriteMode::Plain).unwrap();
        let recovered = Recovered::from_scan(store.scan().unwrap()).unwrap();
        assert!(recovered.seeded);
        assert_eq!(recovered.starts, 3);
        assert_eq!(recovered.meta.len(), records.len());
        for record in &records {
            assert!(recovered.meta.contains(record), "{record:?}");
        }
        store
            .write(
                vec![StoreOp::DeleteMeta(records[2].key()).to_kv()],
                WriteMode::Plain,
            )
            .unwrap();
        let recovered = Recovered::from_scan(store.scan().unwrap()).unwrap();
        assert_eq!(recovered.meta.len(), records.len() - 1);
        assert!(!recovered.meta.contains(&records[2]));
        assert!(recovered.meta.contains(&records[3]));

        let (key, value) = StoreOp::PutMeta(records[0].clone()).to_kv();
        let mut value = value.unwrap();
        // A tag count the value cannot hold.
        let count_at = value.len() - (4 + 10) - (4 + 10) - 4;
        value[count_at..count_at + 4].copy_from_slice(&u32::MAX.to_be_bytes());
        assert!(Recovered::from_scan(vec![(key.clone(), value)]).is_err());
        assert!(Recovered::from_scan(vec![(key, vec![0, 0])]).is_err());
        assert!(Recovered::from_scan(vec![(b"az".to_vec(), vec![])]).is_err());
    }
}
