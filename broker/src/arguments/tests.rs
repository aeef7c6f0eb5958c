//! The equivalence check against RabbitMQ 3.10's answers, and the
//! generated table in `docs/arguments.md`.

use super::*;
use crate::testkit::table;
use leveret_protocol::ReplyCode;

fn compare(current: &[(&str, FieldValue)], requested: &[(&str, FieldValue)]) -> Option<String> {
    first_inequivalent(
        Scope::Queue,
        &table(current),
        &table(requested),
        "queue 'q' in vhost '/'",
    )
    .map(|error| {
        assert_eq!(error.code, ReplyCode::PreconditionFailed);
        error.text
    })
}

/// Every integer width and signedness is the same number (pika sends
/// 1000 as a signed 32-bit integer, the management API as 64-bit).
#[test]
fn integers_are_equal_by_value_whatever_their_width() {
    let widths = [
        FieldValue::I8(100),
        FieldValue::U8(100),
        FieldValue::I16(100),
        FieldValue::U16(100),
        FieldValue::I32(100),
        FieldValue::U32(100),
        FieldValue::I64(100),
    ];
    for a in &widths {
        for b in &widths {
            for key in [
                "x-message-ttl",
                "x-expires",
                "x-max-priority",
                "x-max-length",
            ] {
                assert_eq!(
                    compare(&[(key, a.clone())], &[(key, b.clone())]),
                    None,
                    "{a:?} {b:?}"
                );
            }
        }
    }
}

/// The texts RabbitMQ 3.10.8 answered for the same redeclarations.
#[test]
fn differences_are_named_with_rabbitmqs_texts() {
    assert_eq!(
        compare(
            &[("x-message-ttl", FieldValue::I32(1000))],
            &[("x-message-ttl", FieldValue::I64(2000))]
        )
        .unwrap(),
        "PRECONDITION_FAILED - inequivalent arg 'x-message-ttl' for queue 'q' in vhost '/': received '2000' but current is '1000'"
    );
    assert_eq!(
        compare(&[("x-message-ttl", FieldValue::I32(1000))], &[]).unwrap(),
        "PRECONDITION_FAILED - inequivalent arg 'x-message-ttl' for queue 'q' in vhost '/': received none but current is the value '1000' of type 'signedint'"
    );
    assert_eq!(
        compare(&[], &[("x-queue-type", FieldValue::string("quorum"))]).unwrap(),
        "PRECONDITION_FAILED - inequivalent arg 'x-queue-type' for queue 'q' in vhost '/': received the value 'quorum' of type 'longstr' but current is none"
    );
    // A number is not a string, nor a boolean.
    assert!(compare(
        &[("x-max-length", FieldValue::I32(1))],
        &[("x-max-length", FieldValue::string("1"))]
    )
    .is_some());
    assert!(compare(
        &[("x-single-active-consumer", FieldValue::Bool(true))],
        &[("x-single-active-consumer", FieldValue::I8(1))]
    )
    .is_some());
}

#[test]
fn classic_is_no_type_and_unknown_arguments_are_not_compared() {
    let classic = || FieldValue::string("classic");
    assert_eq!(compare(&[("x-queue-type", classic())], &[]), None);
    assert_eq!(compare(&[], &[("x-queue-type", classic())]), None);
    assert_eq!(
        compare(
            &[("x-foo", FieldValue::I32(1))],
            &[("x-foo", FieldValue::I32(2))]
        ),
        None
    );
    // Refused arguments are never stored, so never compared either.
    assert_eq!(
        compare(&[], &[("x-delivery-limit", FieldValue::I32(2))]),
        None
    );
}

#[test]
fn exchanges_compare_only_their_alternate_exchange() {
    let compare = |a: &[(&str, FieldValue)], b: &[(&str, FieldValue)]| {
        first_inequivalent(
            Scope::Exchange,
            &table(a),
            &table(b),
            "exchange 'x' in vhost '/'",
        )
        .map(|e| e.text)
    };
    let text = FieldValue::string;
    assert_eq!(
        compare(&[("x-foo", text("a"))], &[("x-foo", text("b"))]),
        None
    );
    assert_eq!(
        compare(
            &[("alternate-exchange", text("a"))],
            &[("alternate-exchange", text("b"))]
        )
        .unwrap(),
        "PRECONDITION_FAILED - inequivalent arg 'alternate-exchange' for exchange 'x' in vhost '/': received 'b' but current is 'a'"
    );
}

#[test]
fn each_argument_is_listed_once_and_refusals_name_it() {
    for (i, a) in ARGUMENTS.iter().enumerate() {
        assert!(
            ARGUMENTS[..i]
                .iter()
                .all(|b| (b.scope, b.name) != (a.scope, a.name)),
            "{} twice",
            a.name
        );
        if let Some(error) = refusal(a, "queue 'q' in vhost '/'") {
            assert_eq!(error.code, ReplyCode::PreconditionFailed);
            assert!(
                error.text.contains(&format!("'{}'", a.name)),
                "{}",
                error.text
            );
        }
    }
}

/// The table in `docs/arguments.md`, from [`ARGUMENTS`].
fn markdown() -> String {
    let mut out = String::from(
        "# Arguments\n\n\
         Generated from `ARGUMENTS` in `broker/src/arguments/mod.rs` by its test\n\
         `the_docs_table_is_the_code_list`; `LEVERET_WRITE_DOCS=1 cargo test -p\n\
         leveret-broker --lib arguments::` rewrites it. Every argument RabbitMQ 3.10\n\
         knows for `queue.declare`, `exchange.declare` and `basic.consume`, and what\n\
         Leveret does with it:\n\n\
         - **implemented**: validated with RabbitMQ's error texts and acted on;\n\
         - **accepted, no effect**: validated as RabbitMQ does and kept (shown in\n  \
         listings, compared on redeclaration) with no effect, for the reason given;\n\
         - **refused**: 406 PRECONDITION_FAILED with a text naming the argument;\n  \
         nothing is declared.\n\n\
         A **compared** argument must be the same when the queue or exchange is\n\
         declared again (406 `inequivalent arg` otherwise); numbers are compared by\n\
         value whatever their AMQP width or signedness, as RabbitMQ compares them, so\n\
         a queue declared through the management API or definitions (64-bit\n\
         integers) can be declared again by pika (32-bit) and the other way round.\n\n\
         Arguments not in this table are treated as RabbitMQ 3.10 treats arguments it\n\
         does not know: kept as declared, shown in listings, never compared, no\n\
         effect (an application's or a plugin's own keys pass through unchanged).\n\n\
         **status** is a classic queue's; **on a stream** what a stream\n\
         (`x-queue-type: stream`) or its consumers do with it. A stream compares\n\
         every argument it takes when it is declared again.\n\n\
         | argument | where | status | compared | on a stream | meaning |\n\
         |---|---|---|---|---|---|\n",
    );
    for a in ARGUMENTS {
        let scope = match a.scope {
            Scope::Queue => "queue.declare",
            Scope::Exchange => "exchange.declare",
            Scope::Consumer => "basic.consume",
        };
        let described = |support: Support| match support {
            Support::Implemented => "implemented".to_owned(),
            Support::NoEffect(why) => format!("accepted, no effect: {why}"),
            Support::Refused(why) => format!("refused: {why}"),
        };
        let status = described(a.support);
        let on_stream = a.on_stream.map_or("—".to_owned(), described);
        let compared = if a.compared { "yes" } else { "no" };
        out.push_str(&format!(
            "| `{}` | {scope} | {status} | {compared} | {on_stream} | {} |\n",
            a.name, a.meaning
        ));
    }
    out
}

#[test]
fn the_docs_table_is_the_code_list() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../docs/arguments.md");
    let generated = markdown();
    if std::env::var_os("LEVERET_WRITE_DOCS").is_some() {
        std::fs::write(path, &generated).expect("write docs/arguments.md");
    }
    let written = std::fs::read_to_string(path).unwrap_or_default();
    assert!(
        written == generated,
        "docs/arguments.md differs from the code's list: run LEVERET_WRITE_DOCS=1 cargo test -p leveret-broker --lib arguments::"
    );
}
