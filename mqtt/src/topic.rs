//! Topic names (what a PUBLISH is sent to) and topic filters (what a
//! SUBSCRIBE asks for), with MQTT's rules (4.7): names carry no wildcards;
//! in filters `#` stands alone as the last level and `+` alone in its level;
//! and a filter `$share/GROUP/FILTER` is a shared subscription (5.0, 4.8.2)
//! whose group holds no `/`, `+` or `#` and whose filter is itself valid.
//!
//! The shared form is checked in every version: `$share/` names a shared
//! subscription to Mosquitto and RabbitMQ whatever the client's version.

use crate::string::MqttString;
use std::fmt;

/// Why a string is not a valid topic name or filter.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum TopicError {
    /// An empty filter, or an empty name where the protocol needs one.
    #[error("empty")]
    Empty,
    /// `+` or `#` in a topic name (MQTT-3.3.2-2).
    #[error("wildcard in a topic name")]
    Wildcard,
    /// `#` that is not a whole level at the end (MQTT-4.7.1-1).
    #[error("'#' not alone as the last level")]
    MisplacedMultiLevelWildcard,
    /// `+` that is not a whole level (MQTT-4.7.1-2).
    #[error("'+' not alone in its level")]
    MisplacedSingleLevelWildcard,
    /// `$share/…` without a group, with `+` or `#` in the group, or
    /// without a filter after it (MQTT 5.0, 4.8.2).
    #[error("shared subscription not of the form $share/GROUP/FILTER")]
    MalformedSharedSubscription,
}

/// A topic name: no wildcards. It may be empty, which only a 5.0 PUBLISH
/// carrying a Topic Alias may send; the codec checks that where it applies.
#[derive(Clone, Default, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct TopicName(MqttString);

impl TopicName {
    /// Checks `name` for wildcards.
    pub fn new(name: MqttString) -> Result<Self, TopicError> {
        if name.as_bytes().iter().any(|&b| b == b'+' || b == b'#') {
            return Err(TopicError::Wildcard);
        }
        Ok(TopicName(name))
    }

    /// A topic name from a static string; panics if it is not one.
    pub fn from_static(name: &'static str) -> Self {
        TopicName::new(MqttString::from_static(name)).expect("a valid topic name")
    }

    /// The text.
    pub fn as_str(&self) -> &str {
        self.0.as_str()
    }

    /// The string.
    pub fn as_mqtt_string(&self) -> &MqttString {
        &self.0
    }

    /// Whether the name is empty.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
}

/// A valid, non-empty topic filter.
#[derive(Clone, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct TopicFilter(MqttString);

/// The parts of a shared subscription's filter `$share/GROUP/FILTER`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SharedFilter<'a> {
    /// The share name (group): non-empty, no `/`, `+` or `#`.
    pub group: &'a str,
    /// The filter the group subscribes to.
    pub filter: &'a str,
}

const SHARE_PREFIX: &str = "$share/";

impl TopicFilter {
    /// Checks `filter` against the wildcard and shared subscription rules.
    pub fn new(filter: MqttString) -> Result<Self, TopicError> {
        let text = filter.as_str();
        match text.strip_prefix(SHARE_PREFIX) {
            Some(rest) => {
                let (group, inner) = rest
                    .split_once('/')
                    .ok_or(TopicError::MalformedSharedSubscription)?;
                if group.is_empty() || group.contains(['+', '#']) || inner.is_empty() {
                    return Err(TopicError::MalformedSharedSubscription);
                }
                check_filter(inner)?;
            }
            None => check_filter(text)?,
        }
        Ok(TopicFilter(filter))
    }

    /// A topic filter from a static string; panics if it is not one.
    pub fn from_static(filter: &'static str) -> Self {
        TopicFilter::new(MqttString::from_static(filter)).expect("a valid topic filter")
    }

    /// The text, `$share/GROUP/` included for a shared subscription.
    pub fn as_str(&self) -> &str {
        self.0.as_str()
    }

    /// The string.
    pub fn as_mqtt_string(&self) -> &MqttString {
        &self.0
    }

    /// Whether a PUBLISH to `topic` matches the filter (for a shared
    /// subscription, its inner filter): `+` is one level, `#` the rest
    /// (its parent level included), and a topic starting with `$` matches
    /// no filter starting with a wildcard (MQTT-4.7.2-1).
    pub fn matches(&self, topic: &str) -> bool {
        let filter = self.shared().map_or(self.as_str(), |s| s.filter);
        if topic.starts_with('$') && filter.starts_with(['+', '#']) {
            return false;
        }
        let mut levels = topic.split('/');
        for part in filter.split('/') {
            match (part, levels.next()) {
                ("#", _) => return true,
                ("+", Some(_)) => {}
                (part, Some(level)) if part == level => {}
                _ => return false,
            }
        }
        levels.next().is_none()
    }

    /// The group and filter of a shared subscription.
    pub fn shared(&self) -> Option<SharedFilter<'_>> {
        let rest = self.as_str().strip_prefix(SHARE_PREFIX)?;
        // `new` checked there is a '/' after the group.
        let (group, filter) = rest.split_once('/')?;
        Some(SharedFilter { group, filter })
    }
}

fn check_filter(filter: &str) -> Result<(), TopicError> {
    if filter.is_empty() {
        return Err(TopicError::Empty);
    }
    let mut levels = filter.split('/').peekable();
    while let Some(level) = levels.next() {
        if level.contains('#') && (level != "#" || levels.peek().is_some()) {
            return Err(TopicError::MisplacedMultiLevelWildcard);
        }
        if level.contains('+') && level != "+" {
            return Err(TopicError::MisplacedSingleLevelWildcard);
        }
    }
    Ok(())
}

impl fmt::Debug for TopicName {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Debug::fmt(&self.0, f)
    }
}

impl fmt::Debug for TopicFilter {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Debug::fmt(&self.0, f)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn filter(s: &str) -> Result<TopicFilter, TopicError> {
        TopicFilter::new(MqttString::try_from(s).unwrap())
    }

    #[test]
    fn filters_match_topics_as_the_specification_says() {
        let matches = |f: &str, t: &str| filter(f).unwrap().matches(t);
        assert!(matches("a/b", "a/b"));
        assert!(!matches("a/b", "a/b/c"));
        assert!(!matches("a/b/c", "a/b"));
        assert!(matches("a/+/c", "a/x/c"));
        assert!(matches("a/+", "a/"));
        assert!(!matches("a/+", "a"));
        assert!(matches("a/#", "a"));
        assert!(matches("a/#", "a/b/c"));
        assert!(matches("#", "a/b"));
        assert!(matches("+/+", "/x"));
        assert!(!matches("#", "$SYS/x"));
        assert!(!matches("+/x", "$SYS/x"));
        assert!(matches("$SYS/#", "$SYS/x"));
        assert!(matches("$share/g/a/+", "a/b"));
    }

    fn name(s: &str) -> Result<TopicName, TopicError> {
        TopicName::new(MqttString::try_from(s).unwrap())
    }

    #[test]
    fn spec_filter_examples() {
        // MQTT 3.1.1 and 5.0, 4.7.1.2 and 4.7.1.3.
        for ok in [
            "sport/tennis/player1/#",
            "sport/#",
            "#",
            "+",
            "+/tennis/#",
            "sport/+/player1",
            "/+",
            "+/+",
            "sport/",
            "/",
            "$SYS/#",
        ] {
            assert!(filter(ok).is_ok(), "{ok}");
        }
        assert_eq!(
            filter("sport/tennis#"),
            Err(TopicError::MisplacedMultiLevelWildcard)
        );
        assert_eq!(
            filter("sport/tennis/#/ranking"),
            Err(TopicError::MisplacedMultiLevelWildcard)
        );
        assert_eq!(
            filter("sport+"),
            Err(TopicError::MisplacedSingleLevelWildcard)
        );
        assert_eq!(
            filter("a/b+/c"),
            Err(TopicError::MisplacedSingleLevelWildcard)
        );
        assert_eq!(filter(""), Err(TopicError::Empty));
    }

    #[test]
    fn names_refuse_wildcards() {
        assert!(name("sport/tennis/player1").is_ok());
        assert!(name("/").is_ok());
        assert!(name("").is_ok());
        assert_eq!(name("sport/+"), Err(TopicError::Wildcard));
        assert_eq!(name("sport/#"), Err(TopicError::Wildcard));
        assert_eq!(name("a#b"), Err(TopicError::Wildcard));
    }

    #[test]
    fn shared_subscriptions() {
        let f = filter("$share/consumer1/sport/tennis/+").unwrap();
        assert_eq!(
            f.shared(),
            Some(SharedFilter {
                group: "consumer1",
                filter: "sport/tennis/+"
            })
        );
        assert_eq!(filter("$share/g//").unwrap().shared().unwrap().filter, "/");
        assert_eq!(filter("$share/g/#").unwrap().shared().unwrap().filter, "#");
        for bad in [
            "$share/",
            "$share/g",
            "$share//a",
            "$share/g/",
            "$share/g+/a",
            "$share/#/a",
        ] {
            assert_eq!(
                filter(bad),
                Err(TopicError::MalformedSharedSubscription),
                "{bad}"
            );
        }
        assert_eq!(
            filter("$share/g/a#"),
            Err(TopicError::MisplacedMultiLevelWildcard)
        );
        // Not the shared prefix: ordinary filters.
        assert_eq!(filter("$share").unwrap().shared(), None);
        assert_eq!(filter("$shared/a").unwrap().shared(), None);
        assert_eq!(filter("sport/#").unwrap().shared(), None);
    }
}
