use super::*;
use proptest::prelude::*;

fn spec(
    pattern: &str,
    apply_to: ApplyTo,
    priority: i64,
    keys: &[(&str, PolicyValue)],
) -> PolicySpec {
    PolicySpec {
        pattern: pattern.into(),
        apply_to,
        priority,
        definition: keys
            .iter()
            .map(|(k, v)| (k.to_string(), v.clone()))
            .collect(),
    }
}

fn int(n: i64) -> PolicyValue {
    PolicyValue::Integer(n)
}

fn text(s: &str) -> PolicyValue {
    PolicyValue::Text(s.into())
}

fn user(name: &str, pattern: &str, priority: i64, keys: &[(&str, PolicyValue)]) -> Policy {
    Policy::new(
        PolicyKind::User,
        name,
        spec(pattern, ApplyTo::All, priority, keys),
    )
    .unwrap()
}

fn operator(name: &str, pattern: &str, keys: &[(&str, PolicyValue)]) -> Policy {
    Policy::new(
        PolicyKind::Operator,
        name,
        spec(pattern, ApplyTo::Queues, 0, keys),
    )
    .unwrap()
}

#[test]
fn the_highest_priority_match_applies_and_ties_go_by_name() {
    let set = VhostPolicies::default()
        .with(user("low", ".*", 0, &[("max-length", int(1))]))
        .with(user("high", "^orders", 5, &[("max-length", int(2))]))
        .with(user("b-tie", "^tie", 3, &[("max-length", int(3))]))
        .with(user("a-tie", "^tie", 3, &[("max-length", int(4))]));
    let name = |n: &str| {
        set.applied(ObjectKind::Queue, n.as_bytes())
            .policy_name()
            .map(str::to_owned)
    };
    assert_eq!(name("orders.eu").as_deref(), Some("high"));
    assert_eq!(name("other").as_deref(), Some("low"));
    assert_eq!(name("tie").as_deref(), Some("a-tie"));
    let without = set.without(PolicyKind::User, "low");
    assert_eq!(
        without.applied(ObjectKind::Queue, b"other").policy_name(),
        None
    );
}

#[test]
fn apply_to_limits_the_objects() {
    let set = VhostPolicies::default().with(
        Policy::new(
            PolicyKind::User,
            "ae",
            spec(
                ".*",
                ApplyTo::Exchanges,
                0,
                &[("alternate-exchange", text("ae"))],
            ),
        )
        .unwrap(),
    );
    assert!(set.applied(ObjectKind::Queue, b"x").policy.is_none());
    let alternate = set.applied(ObjectKind::Exchange, b"x").alternate_exchange();
    assert_eq!(alternate.as_ref().map(|a| a.as_bytes()), Some(&b"ae"[..]));
}

#[test]
fn keys_leveret_does_not_act_on_are_refused() {
    for (key, value, says) in [
        ("max-priority", int(10), "not recognised policy settings"),
        ("ha-mode", text("all"), "mirrored"),
        ("delivery-limit", int(3), "quorum"),
        ("message-ttl", int(-1), "not a valid message TTL"),
        ("expires", int(0), "not a valid queue expiry"),
        ("overflow", text("drop-tail"), "not a valid overflow"),
        ("max-length", text("5"), "not a valid maximum length"),
        ("queue-mode", text("fast"), "queue-mode"),
    ] {
        let error = Policy::new(
            PolicyKind::User,
            "p",
            spec(".*", ApplyTo::All, 0, &[(key, value)]),
        )
        .unwrap_err();
        assert!(error.contains(says), "{key}: {error}");
    }
    let error = Policy::new(
        PolicyKind::Operator,
        "p",
        spec(
            ".*",
            ApplyTo::Queues,
            0,
            &[("dead-letter-exchange", text("dlx"))],
        ),
    )
    .unwrap_err();
    assert!(
        error.contains("not recognised operator policy settings"),
        "{error}"
    );
    assert!(Policy::new(
        PolicyKind::User,
        "p",
        spec("(", ApplyTo::All, 0, &[("max-length", int(1))])
    )
    .is_err());
    assert!(Policy::new(PolicyKind::User, "p", spec(".*", ApplyTo::All, 0, &[])).is_err());
    for accepted in [("queue-mode", text("lazy")), ("queue-version", int(2))] {
        assert!(Policy::new(
            PolicyKind::User,
            "p",
            spec(".*", ApplyTo::All, 0, &[accepted])
        )
        .is_ok());
    }
}

#[test]
fn stream_keys_are_read_with_rabbitmqs_checks() {
    let policy = user(
        "s",
        ".*",
        0,
        &[
            ("max-age", text("2h")),
            ("stream-max-segment-size-bytes", int(1000)),
            ("max-length-bytes", int(3000)),
        ],
    );
    assert_eq!(policy.definition.max_age_ms, Some(7_200_000));
    assert_eq!(policy.definition.stream_max_segment_size_bytes, Some(1000));
    for (key, value, says) in [
        ("max-age", text("0s"), "<<\"0s\">> is not a valid max age"),
        ("max-age", text("1x"), "<<\"1x\">> is not a valid max age"),
        ("max-age", text("abc"), "is not a valid max age"),
        ("max-age", int(5), "5 is not a valid max age"),
        (
            "stream-max-segment-size-bytes",
            int(-1),
            "-1 is not a valid segment size",
        ),
        (
            "stream-max-segment-size-bytes",
            int(3_000_000_001),
            "3000000001 is not a valid segment size",
        ),
        (
            "stream-max-segment-size-bytes",
            text("5"),
            "<<\"5\">> is not a valid segment size",
        ),
    ] {
        let error = Policy::new(
            PolicyKind::User,
            "p",
            spec(".*", ApplyTo::All, 0, &[(key, value)]),
        )
        .unwrap_err();
        assert!(error.contains(says), "{key}: {error}");
    }
}

/// RabbitMQ 3.10 (checked on the shared node): a policy applies to a
/// stream only if all its keys are stream keys, to a classic queue only if
/// none is a stream-only key; otherwise the next match applies. Operator
/// policies likewise.
#[test]
fn a_policy_applies_only_to_the_queue_types_its_keys_fit() {
    let set = VhostPolicies::default()
        .with(user(
            "mixed",
            ".*",
            10,
            &[("max-length", int(5)), ("max-age", text("1h"))],
        ))
        .with(user("age", ".*", 5, &[("max-age", text("2h"))]))
        .with(user("bytes", ".*", 0, &[("max-length-bytes", int(100))]))
        .with(operator("op-expires", ".*", &[("expires", int(1000))]));
    let classic = set.applied(ObjectKind::Queue, b"q");
    let stream = set.applied(ObjectKind::Stream, b"q");
    assert_eq!(classic.policy_name(), Some("bytes"));
    assert_eq!(classic.operator_policy_name(), Some("op-expires"));
    assert_eq!(stream.policy_name(), Some("age"));
    assert_eq!(stream.max_age_ms(), Some(7_200_000));
    assert_eq!(stream.operator_policy_name(), None);
    let set = set.with(operator("op-bytes", ".*", &[("max-length-bytes", int(50))]));
    let set = set.without(PolicyKind::Operator, "op-expires");
    let stream = set
        .without(PolicyKind::User, "age")
        .applied(ObjectKind::Stream, b"q");
    assert_eq!(stream.policy_name(), Some("bytes"));
    assert_eq!(stream.max_length_bytes(), Some(50));
    // Exchanges are not judged by queue keys.
    assert_eq!(
        set.applied(ObjectKind::Exchange, b"q").policy_name(),
        Some("mixed")
    );
}

#[test]
fn operator_policies_merge_by_the_smaller_value() {
    let set = VhostPolicies::default()
        .with(user(
            "u",
            ".*",
            0,
            &[
                ("max-length", int(100)),
                ("message-ttl", int(50)),
                ("dead-letter-exchange", text("dlx")),
            ],
        ))
        .with(operator(
            "o",
            ".*",
            &[
                ("max-length", int(10)),
                ("message-ttl", int(500)),
                ("expires", int(60000)),
            ],
        ));
    let applied = set.applied(ObjectKind::Queue, b"q");
    assert_eq!(applied.max_length(), Some(10));
    assert_eq!(applied.message_ttl(), Some(50));
    assert_eq!(applied.expires(), Some(60000));
    let effective = applied.effective_definition();
    assert_eq!(effective["max-length"], int(10));
    assert_eq!(effective["message-ttl"], int(50));
    assert_eq!(effective["expires"], int(60000));
    assert_eq!(effective["dead-letter-exchange"], text("dlx"));
}

// Regular expressions beyond literal names and prefixes.
#[cfg(feature = "regex")]
#[test]
fn a_change_costs_one_match_and_agrees_with_a_full_look_up() {
    let before = VhostPolicies::default()
        .with(user("a", "^q", 1, &[("max-length", int(1))]))
        .with(user("b", "^q1", 2, &[("max-length", int(2))]));
    let names: Vec<&[u8]> = vec![b"q1", b"q2", b"x", b"q10"];
    type Change = Box<dyn Fn(&VhostPolicies) -> (VhostPolicies, PolicyKind, &'static str)>;
    let changes: Vec<Change> = vec![
        Box::new(|s| {
            (
                s.with(user("c", "^q2", 9, &[("max-length", int(3))])),
                PolicyKind::User,
                "c",
            )
        }),
        Box::new(|s| (s.without(PolicyKind::User, "b"), PolicyKind::User, "b")),
        Box::new(|s| {
            (
                s.with(user("b", "^x", 0, &[("max-length", int(4))])),
                PolicyKind::User,
                "b",
            )
        }),
        Box::new(|s| {
            (
                s.with(user("a", "^q", 0, &[("max-length", int(5))])),
                PolicyKind::User,
                "a",
            )
        }),
        Box::new(|s| {
            (
                s.with(operator("o", "1$", &[("max-length", int(6))])),
                PolicyKind::Operator,
                "o",
            )
        }),
        Box::new(|s| {
            (
                s.with(user("s", "^q", 5, &[("max-age", text("1h"))])),
                PolicyKind::User,
                "s",
            )
        }),
        Box::new(|s| {
            (
                s.with(user("a", "^q", 1, &[("max-length-bytes", int(7))])),
                PolicyKind::User,
                "a",
            )
        }),
    ];
    for change in &changes {
        let (after, kind, name) = change(&before);
        for object in &names {
            for of in [ObjectKind::Queue, ObjectKind::Stream] {
                let current = before.applied(of, object);
                let updated = after.after_change(&current, kind, name, of, object);
                assert_eq!(updated, after.applied(of, object), "{name} on {object:?}");
            }
        }
    }
}

// Regular expressions beyond literal names and prefixes.
#[cfg(feature = "regex")]
#[test]
fn a_pathological_pattern_is_refused_or_linear() {
    // Catastrophic backtracking shapes are linear in the regex crate.
    let policy = user("evil", "^(a+)+$", 0, &[("max-length", int(1))]);
    let name = "a".repeat(200) + "!";
    let set = VhostPolicies::default().with(policy);
    assert!(set
        .applied(ObjectKind::Queue, name.as_bytes())
        .policy
        .is_none());
    // A pattern whose program passes the size cap is refused.
    let huge = "(a{1000}){1000}";
    assert!(Policy::new(
        PolicyKind::User,
        "huge",
        spec(huge, ApplyTo::All, 0, &[("max-length", int(1))])
    )
    .is_err());
    let backref = "(a)\\1";
    assert!(Policy::new(
        PolicyKind::User,
        "br",
        spec(backref, ApplyTo::All, 0, &[("max-length", int(1))])
    )
    .is_err());
}

proptest! {
    #[test]
    fn the_stricter_value_wins(policy in proptest::option::of(0u64..1000), op in proptest::option::of(0u64..1000), arg in proptest::option::of(0u64..1000)) {
        let merged = stricter(stricter(policy, op), arg);
        let given: Vec<u64> = [policy, op, arg].into_iter().flatten().collect();
        prop_assert_eq!(merged, given.iter().copied().min());
        prop_assert_eq!(stricter(policy, op), stricter(op, policy));
        prop_assert_eq!(argument_wins(policy, arg), if arg.is_some() { arg } else { policy });
    }
}

#[test]
fn required_prefixes_are_read_only_where_the_pattern_plainly_has_one() {
    use super::ranked::required_prefix;
    for (pattern, prefix) in [
        ("^orders\\.eu", Some(&b"orders.eu"[..])),
        ("^ab+c", Some(b"a")),
        ("^ab?c", Some(b"a")),
        ("^ab*", Some(b"a")),
        ("^ab{0,2}", Some(b"a")),
        ("^a\\d", Some(b"a")),
        ("^(?i)abc", Some(b"")),
        ("^a|^b", None),
        ("(?i)^abc", None),
        ("abc", None),
    ] {
        assert_eq!(required_prefix(pattern).as_deref(), prefix, "{pattern}");
    }
}

proptest! {
    /// The prefix index finds what trying every policy in rank order finds.
    #[test]
    fn the_index_agrees_with_trying_every_policy(
        patterns in proptest::collection::vec("\\^?[ab.\\\\|?*+(){}1,]{0,6}", 1..12),
        priorities in proptest::collection::vec(0i64..3, 12),
        names in proptest::collection::vec("[ab.]{0,5}", 1..8),
    ) {
        let mut set = VhostPolicies::default();
        for (i, pattern) in patterns.iter().enumerate() {
            let spec = spec(pattern, ApplyTo::All, priorities[i], &[("max-length", int(1))]);
            if let Ok(policy) = Policy::new(PolicyKind::User, &format!("p{i}"), spec) {
                set = set.with(policy);
            }
        }
        for name in &names {
            let scanned = set
                .list(PolicyKind::User)
                .iter()
                .find(|p| p.matches(ObjectKind::Queue, name.as_bytes()))
                .map(|p| p.name.clone());
            let indexed = set.applied(ObjectKind::Queue, name.as_bytes()).policy_name().map(str::to_owned);
            prop_assert_eq!(indexed, scanned, "{:?} on {}", patterns, name);
        }
    }
}

/// A value each key listed in [`POLICY_KEYS`] takes.
fn sample(key: &str) -> PolicyValue {
    match key {
        "overflow" => text("drop-head"),
        "max-age" => text("1D"),
        "queue-mode" => text("lazy"),
        "queue-version" => int(2),
        "federation-upstream-set" => text("all"),
        "dead-letter-exchange"
        | "dead-letter-routing-key"
        | "alternate-exchange"
        | "federation-upstream"
        | "federation-upstream-pattern"
        | "ha-mode"
        | "ha-sync-mode"
        | "queue-master-locator"
        | "queue-leader-locator"
        | "dead-letter-strategy" => text("x"),
        _ => int(1000),
    }
}

/// Every key listed reads as listed: taken (by operator policies only
/// where listed so) or refused with its reason; a key not listed is
/// refused as RabbitMQ refuses one it does not know.
#[test]
fn every_policy_key_listed_reads_as_listed() {
    use definition::{KeySupport, POLICY_KEYS};
    for listed in POLICY_KEYS {
        let given = [(listed.name.to_owned(), sample(listed.name))];
        let as_user = Definition::read(PolicyKind::User, &given);
        let as_operator = Definition::read(PolicyKind::Operator, &given);
        match listed.support {
            KeySupport::Implemented | KeySupport::NoEffect(_) => {
                assert!(as_user.is_ok(), "{}: {as_user:?}", listed.name);
                assert_eq!(as_operator.is_ok(), listed.operator, "{}", listed.name);
            }
            KeySupport::Refused(why) => {
                for refused in [as_user, as_operator] {
                    let error = refused.unwrap_err();
                    assert!(error.contains(why), "{}: {error}", listed.name);
                }
            }
        }
    }
    let unknown = Definition::read(PolicyKind::User, &[("colour".to_owned(), text("red"))]);
    assert_eq!(
        unknown.unwrap_err(),
        "[colour] are not recognised policy settings"
    );
}

/// The table in `docs/policy-keys.md`, from [`POLICY_KEYS`].
fn policy_keys_markdown() -> String {
    use definition::{KeySupport, POLICY_KEYS};
    let mut out = String::from(
        "# Policy keys\n\n\
         Generated from `POLICY_KEYS` in `broker/src/policy/definition.rs` by its\n\
         test `the_policy_keys_table_is_the_code_list`; `LEVERET_WRITE_DOCS=1 cargo\n\
         test -p leveret-broker --lib policy::` rewrites it. Every key RabbitMQ 3.10\n\
         knows in a policy or operator policy definition, and what Leveret does with\n\
         it: **implemented** (checked as RabbitMQ checks it and acted on), **accepted,\n\
         no effect** (checked, listed, nothing else, for the reason given) or\n\
         **refused** (the policy is not set; the API answers 400 with the reason). A\n\
         key RabbitMQ does not know is refused as RabbitMQ refuses it (`[key] are not\n\
         recognised policy settings`). **operator** says whether an operator policy\n\
         may hold it; there the stricter of it and the policy's value applies.\n\
         Queue arguments against policies are in [`arguments.md`](arguments.md).\n\n\
         | key | status | operator | meaning |\n\
         |---|---|---|---|\n",
    );
    for listed in POLICY_KEYS {
        let status = match listed.support {
            KeySupport::Implemented => "implemented".to_owned(),
            KeySupport::NoEffect(why) => format!("accepted, no effect: {why}"),
            KeySupport::Refused(why) => format!("refused: {why}"),
        };
        let operator = if listed.operator { "yes" } else { "no" };
        out.push_str(&format!(
            "| `{}` | {status} | {operator} | {} |\n",
            listed.name, listed.meaning
        ));
    }
    out
}

#[test]
fn the_policy_keys_table_is_the_code_list() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../docs/policy-keys.md");
    let generated = policy_keys_markdown();
    if std::env::var_os("LEVERET_WRITE_DOCS").is_some() {
        std::fs::write(path, &generated).expect("write docs/policy-keys.md");
    }
    let written = std::fs::read_to_string(path).unwrap_or_default();
    assert!(
        written == generated,
        "docs/policy-keys.md differs from the code's list: run LEVERET_WRITE_DOCS=1 cargo test -p leveret-broker --lib policy::"
    );
}
