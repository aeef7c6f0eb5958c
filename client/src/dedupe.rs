//! Dropping the duplicates at-least-once forwarding can produce: a
//! message a shovel forwarded whose acknowledgement a failure cut comes
//! again. [`Dedupe`] remembers the identities of the last messages it saw
//! (a bounded number) and says whether a message is new.
//!
//! A message's identity, in order of preference: its `message-id`
//! property (set by the publisher, stable across any number of
//! forwards); a data port's `x-port` and `x-seq` headers (stamped once by
//! the out-port, kept by resends and shovels); a shovel's `x-leveret-seq`
//! (from a Leveret source, the shovel's name and the message's position in
//! the source queue: the same however often and on whatever link the
//! message is forwarded, across restarts of either end; from another
//! broker, unique per forward only). A message with none of these is
//! always new. Uses only the protocol's property types.

use crate::{BasicProperties, FieldValue};
use std::collections::{HashSet, VecDeque};

/// The data ports' header naming the out-port (`leveret_ports::PORT_HEADER`;
/// `ports/tests/layering.rs` checks the two agree).
const PORT_HEADER: &str = "x-port";
/// The data ports' header with the out-port's sequence number
/// (`leveret_ports::SEQ_HEADER`).
const SEQ_HEADER: &str = "x-seq";

/// Remembers the last `capacity` identities seen.
#[derive(Debug)]
pub struct Dedupe {
    capacity: usize,
    seen: HashSet<String>,
    order: VecDeque<String>,
}

fn header_text(properties: &BasicProperties, name: &str) -> Option<String> {
    match properties.headers.as_ref()?.get(name)? {
        FieldValue::LongStr(bytes) => Some(String::from_utf8_lossy(bytes).into_owned()),
        other => other.as_i64().map(|n| n.to_string()),
    }
}

/// The identity of a message, if it has one (see the module's docs).
pub fn identity(properties: &BasicProperties) -> Option<String> {
    if let Some(id) = &properties.message_id {
        return Some(format!("id:{}", id.to_string_lossy()));
    }
    if let (Some(port), Some(seq)) = (
        header_text(properties, PORT_HEADER),
        header_text(properties, SEQ_HEADER),
    ) {
        return Some(format!("port:{port}:{seq}"));
    }
    header_text(properties, "x-leveret-seq").map(|seq| format!("shovel:{seq}"))
}

impl Dedupe {
    /// Remembers up to `capacity` identities (at least one).
    pub fn new(capacity: usize) -> Dedupe {
        let capacity = capacity.max(1);
        Dedupe {
            capacity,
            seen: HashSet::with_capacity(capacity.min(1 << 16)),
            order: VecDeque::with_capacity(capacity.min(1 << 16)),
        }
    }

    /// Whether a message with these properties is seen for the first
    /// time (within the last `capacity` identities); it is remembered.
    pub fn first_time(&mut self, properties: &BasicProperties) -> bool {
        let Some(id) = identity(properties) else {
            return true;
        };
        if self.seen.contains(&id) {
            return false;
        }
        if self.order.len() == self.capacity {
            if let Some(oldest) = self.order.pop_front() {
                self.seen.remove(&oldest);
            }
        }
        self.seen.insert(id.clone());
        self.order.push_back(id);
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{FieldTable, ShortStr};

    fn with_headers(pairs: &[(&'static str, FieldValue)]) -> BasicProperties {
        let mut headers = FieldTable::new();
        for (key, value) in pairs {
            headers.insert(ShortStr::from_static(key), value.clone());
        }
        BasicProperties {
            headers: Some(headers),
            ..Default::default()
        }
    }

    #[test]
    fn drops_what_it_saw_by_the_best_identity_and_forgets_the_oldest() {
        let mut dedupe = Dedupe::new(2);
        let by_id = BasicProperties {
            message_id: Some(ShortStr::from_static("m-1")),
            ..with_headers(&[("x-leveret-seq", FieldValue::string("up:1:1"))])
        };
        assert!(dedupe.first_time(&by_id));
        assert!(!dedupe.first_time(&by_id));
        let port = with_headers(&[
            ("x-port", FieldValue::string("pose")),
            ("x-seq", FieldValue::I64(7)),
            ("x-leveret-seq", FieldValue::string("up:2:9")),
        ]);
        assert!(dedupe.first_time(&port));
        // Forwarded again on another link: a new x-leveret-seq, the same port seq.
        let again = with_headers(&[
            ("x-port", FieldValue::string("pose")),
            ("x-seq", FieldValue::I64(7)),
            ("x-leveret-seq", FieldValue::string("up:3:1")),
        ]);
        assert!(!dedupe.first_time(&again));
        let anonymous = BasicProperties::default();
        assert!(dedupe.first_time(&anonymous) && dedupe.first_time(&anonymous));
        // A third identity pushes out the first.
        assert!(dedupe.first_time(&with_headers(&[(
            "x-leveret-seq",
            FieldValue::string("up:3:2")
        )])));
        assert!(dedupe.first_time(&by_id), "forgotten after capacity");
    }
}
