//! A 5.0 connection's inbound topic aliases: the CONNACK tells the client
//! it may use [`TOPIC_ALIAS_MAXIMUM`]; a PUBLISH with a topic and an alias
//! sets the alias, one with an empty topic uses it. Per connection, at
//! most that many topics (each at most a routing key long, as longer
//! topics are refused). The broker sends no aliases (the client's Topic
//! Alias Maximum only allows them).

use bytes::Bytes;
use leveret_mqtt::{MqttString, ReasonCode, TopicName};
use std::num::NonZeroU16;

/// The highest topic alias a client may use.
pub(super) const TOPIC_ALIAS_MAXIMUM: u16 = 16;

/// The topics set by alias, index `alias - 1`.
#[derive(Debug, Default)]
pub(super) struct TopicAliases {
    topics: Vec<Option<TopicName>>,
}

impl TopicAliases {
    /// The topic a PUBLISH goes to: `topic` (set as `alias`'s if it has
    /// one), or `alias`'s if `topic` is empty. 0x94 for an alias above
    /// the maximum, 0x82 for an empty topic with an alias never set.
    pub(super) fn resolve(
        &mut self,
        topic: TopicName,
        alias: Option<NonZeroU16>,
    ) -> Result<TopicName, ReasonCode> {
        let Some(alias) = alias else {
            return Ok(topic);
        };
        if alias.get() > TOPIC_ALIAS_MAXIMUM {
            return Err(ReasonCode::TopicAliasInvalid);
        }
        let index = usize::from(alias.get() - 1);
        if topic.is_empty() {
            return self
                .topics
                .get(index)
                .cloned()
                .flatten()
                .ok_or(ReasonCode::ProtocolError);
        }
        if self.topics.len() <= index {
            self.topics.resize(index + 1, None);
        }
        // A copy: a slice of the read buffer would keep it alive.
        let owned = MqttString::from_utf8(Bytes::copy_from_slice(topic.as_str().as_bytes()))
            .ok()
            .and_then(|t| TopicName::new(t).ok());
        self.topics[index] = owned;
        Ok(topic)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn alias(n: u16) -> Option<NonZeroU16> {
        NonZeroU16::new(n)
    }

    #[test]
    fn an_alias_is_set_then_used_and_can_be_changed() {
        let mut aliases = TopicAliases::default();
        let empty = || TopicName::from_static("");
        assert_eq!(
            aliases.resolve(empty(), alias(1)),
            Err(ReasonCode::ProtocolError)
        );
        let a = TopicName::from_static("a/b");
        assert_eq!(aliases.resolve(a.clone(), alias(1)), Ok(a.clone()));
        assert_eq!(aliases.resolve(empty(), alias(1)), Ok(a));
        let c = TopicName::from_static("c");
        aliases.resolve(c.clone(), alias(1)).unwrap();
        assert_eq!(aliases.resolve(empty(), alias(1)), Ok(c.clone()));
        assert_eq!(
            aliases.resolve(empty(), alias(TOPIC_ALIAS_MAXIMUM)),
            Err(ReasonCode::ProtocolError)
        );
        assert_eq!(
            aliases.resolve(c, alias(TOPIC_ALIAS_MAXIMUM + 1)),
            Err(ReasonCode::TopicAliasInvalid)
        );
        assert!(aliases.topics.len() <= usize::from(TOPIC_ALIAS_MAXIMUM));
    }
}
