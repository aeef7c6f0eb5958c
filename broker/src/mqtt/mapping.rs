//! RabbitMQ's mapping between MQTT and AMQP names: topics and routing
//! keys (`/` ↔ `.`), filters and binding keys (`+` ↔ `*`, `#` ↔ `#`), the
//! per-session queue names, and the vhost a `vhost:user` user name picks.
//! As RabbitMQ 3.12 and later, `.` and `/` swap in both directions, so a
//! topic with a dot in it round-trips (`a.b/c` → `a/b.c` → `a.b/c`).

use leveret_mqtt::QoS;
use leveret_protocol::ShortStr;

/// The exchange MQTT publishes go to and subscriptions bind to.
pub(super) const EXCHANGE: &str = "amq.topic";

/// The vhost a session gets when nothing else picks one.
pub(super) const DEFAULT_VHOST: &str = "/";

/// Swaps `/` and `.`, keeping every other character.
fn swap_separators(name: &str) -> String {
    name.chars()
        .map(|c| match c {
            '/' => '.',
            '.' => '/',
            other => other,
        })
        .collect()
}

/// The routing key of an MQTT topic name; `None` if it is longer than a
/// routing key may be (255 bytes).
pub(super) fn routing_key(topic: &str) -> Option<ShortStr> {
    ShortStr::try_from(swap_separators(topic)).ok()
}

/// The binding key of an MQTT topic filter (`+` → `*`); `None` if it is
/// too long for a binding key.
pub(super) fn binding_key(filter: &str) -> Option<ShortStr> {
    let key: String = swap_separators(filter)
        .chars()
        .map(|c| if c == '+' { '*' } else { c })
        .collect();
    ShortStr::try_from(key).ok()
}

/// The MQTT topic filter of a binding key (`*` → `+`); `None` if it is
/// not UTF-8.
pub(super) fn filter(binding_key: &ShortStr) -> Option<String> {
    let key = binding_key.as_str()?;
    Some(swap_separators(key).replace('*', "+"))
}

/// The MQTT topic of an AMQP routing key; `None` when it cannot be a
/// topic name (not UTF-8, or a wildcard character in it).
pub(super) fn topic(routing_key: &ShortStr) -> Option<String> {
    let key = routing_key.as_str()?;
    if key.contains(['+', '#']) {
        return None;
    }
    Some(swap_separators(key))
}

/// The queue of a session's subscriptions at one QoS:
/// `mqtt-subscription-<client id>qos<N>`, as RabbitMQ names it.
pub(super) fn queue_name(client_id: &str, qos: QoS) -> Option<ShortStr> {
    ShortStr::try_from(format!("mqtt-subscription-{client_id}qos{}", qos.level())).ok()
}

/// The client identifier whose session's queue `name` is named
/// ([`queue_name`]), if it is named so.
pub(super) fn session_of_queue(name: &str) -> Option<&str> {
    let rest = name.strip_prefix("mqtt-subscription-")?;
    ["qos0", "qos1", "qos2"]
        .iter()
        .find_map(|qos| rest.strip_suffix(qos))
}

/// The queue of shared subscription `$share/GROUP/FILTER` in a vhost:
/// `mqtt-shared-GROUP/FILTER` (a group has no `/`, so two subscriptions
/// never share a name); `None` if that is longer than a queue name.
pub(super) fn shared_queue_name(group: &str, filter: &str) -> Option<ShortStr> {
    ShortStr::try_from(format!("{SHARED_QUEUE_PREFIX}{group}/{filter}")).ok()
}

/// How the queue of a shared subscription's group is named first.
pub(super) const SHARED_QUEUE_PREFIX: &str = "mqtt-shared-";

/// The longest client identifier whose queue names fit in a queue name.
pub(super) const MAX_CLIENT_ID: usize = 255 - "mqtt-subscription-qos0".len();

/// The vhost an MQTT user name names, if any, and its user: `vhost:user`
/// split at the last `:` as RabbitMQ splits it (a user name has no `:`, a
/// vhost may), else no vhost (`vhosts` picks one).
pub(super) fn vhost_in_user_name(username: &str) -> (Option<&str>, &str) {
    match username.rsplit_once(':') {
        Some((vhost, user)) if !vhost.is_empty() => (Some(vhost), user),
        _ => (None, username),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn session_queues_are_known_by_their_names() {
        for qos in [QoS::AtMostOnce, QoS::AtLeastOnce, QoS::ExactlyOnce] {
            let name = queue_name("robot-7", qos).unwrap();
            assert_eq!(session_of_queue(name.as_str().unwrap()), Some("robot-7"));
        }
        assert_eq!(session_of_queue("mqtt-subscription-robot-7"), None);
        assert_eq!(session_of_queue("mqtt-shared-g/qos1"), None);
        assert_eq!(session_of_queue("orders-qos1"), None);
    }

    #[test]
    fn topics_and_routing_keys_swap_separators() {
        assert_eq!(routing_key("a/b").unwrap(), "a.b");
        assert_eq!(routing_key("a.b/c").unwrap(), "a/b.c");
        assert_eq!(topic(&ShortStr::from_static("a.b")).unwrap(), "a/b");
        let round = topic(&routing_key("x.y/z/").unwrap()).unwrap();
        assert_eq!(round, "x.y/z/");
        assert!(routing_key(&"a".repeat(256)).is_none());
    }

    #[test]
    fn filters_map_wildcards() {
        assert_eq!(binding_key("a/+/c").unwrap(), "a.*.c");
        assert_eq!(binding_key("a/#").unwrap(), "a.#");
        assert_eq!(binding_key("#").unwrap(), "#");
        for f in ["a/+/c", "a/#", "#", "x.y/+"] {
            assert_eq!(filter(&binding_key(f).unwrap()).unwrap(), f);
        }
    }

    #[test]
    fn routing_keys_with_mqtt_wildcards_are_not_topics() {
        // `*` is no wildcard in a topic name: it stays.
        assert_eq!(topic(&ShortStr::from_static("a.*")).unwrap(), "a/*");
        assert!(topic(&ShortStr::from_static("a.#")).is_none());
        assert!(topic(&ShortStr::from_static("a.+")).is_none());
    }

    #[test]
    fn queue_names_follow_rabbitmq() {
        let name = queue_name("sensor-1", QoS::AtLeastOnce).unwrap();
        assert_eq!(name, "mqtt-subscription-sensor-1qos1");
        assert!(queue_name(&"c".repeat(MAX_CLIENT_ID), QoS::AtMostOnce).is_some());
        assert!(queue_name(&"c".repeat(MAX_CLIENT_ID + 1), QoS::AtMostOnce).is_none());
    }

    #[test]
    fn shared_queues_are_named_by_group_and_filter() {
        assert_eq!(
            shared_queue_name("workers", "jobs/+").unwrap(),
            "mqtt-shared-workers/jobs/+"
        );
        assert_ne!(
            shared_queue_name("a-b", "c").unwrap(),
            shared_queue_name("a", "b-c").unwrap()
        );
        assert!(shared_queue_name("g", &"f".repeat(242)).is_none());
        assert!(shared_queue_name("g", &"f".repeat(241)).is_some());
    }

    #[test]
    fn user_names_pick_a_vhost() {
        assert_eq!(vhost_in_user_name("guest"), (None, "guest"));
        assert_eq!(vhost_in_user_name("robots:arm"), (Some("robots"), "arm"));
        assert_eq!(vhost_in_user_name("a:b:arm"), (Some("a:b"), "arm"));
        assert_eq!(vhost_in_user_name(":guest"), (None, ":guest"));
    }
}
