//! rabbitmqctl's column names for each `list_*` command, mapped onto the
//! management API's JSON fields (most are the same name; a few are paths,
//! like consumers' `queue_name`), and how a value prints: text as is,
//! numbers and booleans as JSON writes them, tables and lists as JSON
//! (`[]` for an empty arguments table, as rabbitmqctl prints it).

use serde_json::Value;

/// One listing's columns: (rabbitmqctl name, path in the API object).
pub struct Table {
    columns: &'static [(&'static str, &'static [&'static str])],
    /// The columns shown when none are asked for.
    pub default: &'static [&'static str],
}

impl Table {
    fn path(&self, name: &str) -> Option<&'static [&'static str]> {
        self.columns
            .iter()
            .find(|(column, _)| *column == name)
            .map(|(_, path)| *path)
    }

    /// Whether `name` is a column of this listing.
    pub fn knows(&self, name: &str) -> bool {
        self.path(name).is_some()
    }

    /// Every column name.
    pub fn known(&self) -> Vec<&'static str> {
        self.columns.iter().map(|(name, _)| *name).collect()
    }

    /// The value of column `name` for `item` (null for a column the
    /// listing does not have), as `--formatter json` prints it.
    pub fn value(&self, name: &str, item: &Value) -> Value {
        let Some(path) = self.path(name) else {
            return Value::Null;
        };
        if name == "source_kind" {
            // A binding's source is always an exchange; the API has no field for it.
            return Value::String("exchange".to_owned());
        }
        path.iter().fold(item, |value, key| &value[*key]).clone()
    }

    /// The cell of column `name` for `item`, as the table prints it.
    pub fn cell(&self, name: &str, item: &Value) -> String {
        let value = self.value(name, item);
        if name == "arguments" && value.as_object().is_some_and(|o| o.is_empty()) {
            return "[]".to_owned();
        }
        render(&value)
    }
}

/// A value as rabbitmqctl would print it.
pub fn render(value: &Value) -> String {
    match value {
        Value::String(s) => s.clone(),
        Value::Null => String::new(),
        other => other.to_string(),
    }
}

pub const QUEUES: Table = Table {
    columns: &[
        ("name", &["name"]),
        ("durable", &["durable"]),
        ("auto_delete", &["auto_delete"]),
        ("arguments", &["arguments"]),
        ("policy", &["policy"]),
        ("operator_policy", &["operator_policy"]),
        (
            "effective_policy_definition",
            &["effective_policy_definition"],
        ),
        ("exclusive", &["exclusive"]),
        ("messages_ready", &["messages_ready"]),
        ("messages_unacknowledged", &["messages_unacknowledged"]),
        ("messages", &["messages"]),
        ("message_bytes_ready", &["message_bytes_ready"]),
        ("consumers", &["consumers"]),
        ("state", &["state"]),
        ("type", &["type"]),
        ("first_offset", &["stream", "first_offset"]),
        ("last_offset", &["stream", "last_offset"]),
        ("segments", &["stream", "segments"]),
        ("disk_bytes", &["stream", "bytes"]),
    ],
    default: &["name", "messages"],
};

pub const EXCHANGES: Table = Table {
    columns: &[
        ("name", &["name"]),
        ("type", &["type"]),
        ("durable", &["durable"]),
        ("auto_delete", &["auto_delete"]),
        ("internal", &["internal"]),
        ("arguments", &["arguments"]),
        ("policy", &["policy"]),
    ],
    default: &["name", "type"],
};

/// `list_policies` and `list_operator_policies`.
pub const POLICIES: Table = Table {
    columns: &[
        ("vhost", &["vhost"]),
        ("name", &["name"]),
        ("pattern", &["pattern"]),
        ("apply-to", &["apply-to"]),
        ("definition", &["definition"]),
        ("priority", &["priority"]),
    ],
    default: &[
        "vhost",
        "name",
        "pattern",
        "apply-to",
        "definition",
        "priority",
    ],
};

pub const GLOBAL_PARAMETERS: Table = Table {
    columns: &[("name", &["name"]), ("value", &["value"])],
    default: &["name", "value"],
};

pub const BINDINGS: Table = Table {
    columns: &[
        ("source_name", &["source"]),
        ("source_kind", &[]),
        ("destination_name", &["destination"]),
        ("destination_kind", &["destination_type"]),
        ("routing_key", &["routing_key"]),
        ("arguments", &["arguments"]),
    ],
    default: &[
        "source_name",
        "source_kind",
        "destination_name",
        "destination_kind",
        "routing_key",
        "arguments",
    ],
};

pub const CONNECTIONS: Table = Table {
    columns: &[
        ("name", &["name"]),
        ("user", &["user"]),
        ("vhost", &["vhost"]),
        ("peer_host", &["peer_host"]),
        ("peer_port", &["peer_port"]),
        ("state", &["state"]),
        ("channels", &["channels"]),
        ("protocol", &["protocol"]),
        ("frame_max", &["frame_max"]),
        ("channel_max", &["channel_max"]),
        ("timeout", &["timeout"]),
        ("connected_at", &["connected_at"]),
        ("client_properties", &["client_properties"]),
    ],
    default: &["user", "peer_host", "peer_port", "state"],
};

pub const VHOSTS: Table = Table {
    columns: &[
        ("name", &["name"]),
        ("description", &["description"]),
        ("tags", &["tags"]),
        ("tracing", &["tracing"]),
        ("default_queue_type", &["default_queue_type"]),
        ("cluster_state", &["cluster_state"]),
        ("metadata", &["metadata"]),
    ],
    default: &["name"],
};

pub const CHANNELS: Table = Table {
    columns: &[
        ("pid", &["name"]),
        ("connection", &["connection_details", "name"]),
        ("name", &["name"]),
        ("number", &["number"]),
        ("user", &["user"]),
        ("vhost", &["vhost"]),
        ("transactional", &["transactional"]),
        ("confirm", &["confirm"]),
        ("consumer_count", &["consumer_count"]),
        ("messages_unacknowledged", &["messages_unacknowledged"]),
        ("prefetch_count", &["prefetch_count"]),
        ("global_prefetch_count", &["global_prefetch_count"]),
        ("state", &["state"]),
    ],
    default: &["pid", "user", "consumer_count", "messages_unacknowledged"],
};

pub const USERS: Table = Table {
    columns: &[("user", &["name"]), ("tags", &["tags"])],
    default: &["user", "tags"],
};

pub const PERMISSIONS: Table = Table {
    columns: &[
        ("user", &["user"]),
        ("configure", &["configure"]),
        ("write", &["write"]),
        ("read", &["read"]),
    ],
    default: &["user", "configure", "write", "read"],
};

pub const TOPIC_PERMISSIONS: Table = Table {
    columns: &[
        ("user", &["user"]),
        ("exchange", &["exchange"]),
        ("write", &["write"]),
        ("read", &["read"]),
    ],
    default: &["user", "exchange", "write", "read"],
};

pub const CONSUMERS: Table = Table {
    columns: &[
        ("queue_name", &["queue", "name"]),
        ("channel_pid", &["channel_details", "name"]),
        ("consumer_tag", &["consumer_tag"]),
        ("ack_required", &["ack_required"]),
        ("prefetch_count", &["prefetch_count"]),
        ("active", &["active"]),
        ("activity_status", &["activity_status"]),
        ("exclusive", &["exclusive"]),
        ("arguments", &["arguments"]),
    ],
    default: &[
        "queue_name",
        "channel_pid",
        "consumer_tag",
        "ack_required",
        "prefetch_count",
        "active",
        "arguments",
    ],
};

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn cells_follow_paths_and_rabbitmqctl_rendering() {
        let consumer = json!({"queue": {"name": "q"}, "channel_details": {"name": "c (1)"},
                              "ack_required": true, "arguments": {}});
        assert_eq!(CONSUMERS.cell("queue_name", &consumer), "q");
        assert_eq!(CONSUMERS.cell("channel_pid", &consumer), "c (1)");
        assert_eq!(CONSUMERS.cell("ack_required", &consumer), "true");
        assert_eq!(CONSUMERS.cell("arguments", &consumer), "[]");
        assert!(!QUEUES.knows("pid"));
        let binding = json!({"source": "x", "destination_type": "queue"});
        assert_eq!(BINDINGS.cell("destination_kind", &binding), "queue");
        assert_eq!(BINDINGS.cell("source_kind", &binding), "exchange");
    }
}
