//! URI parsing, as RabbitMQ's URI specification describes (with empty
//! vhost paths meaning `/`).

use leveret_client::uri::{AuthMechanism, TlsSettings};
use leveret_client::{ConnectionOptions, Error};
use std::time::Duration;

fn parse(uri: &str) -> ConnectionOptions {
    ConnectionOptions::from_uri(uri).unwrap_or_else(|e| panic!("{uri}: {e}"))
}

fn rejects(uri: &str) {
    match ConnectionOptions::from_uri(uri) {
        Err(Error::InvalidUri(_)) => {}
        other => panic!("{uri} should be rejected, got {other:?}"),
    }
}

#[test]
fn full_uri() {
    let o = parse("amqp://user:pass@host.example:10000/vhost");
    assert_eq!(o.username, "user");
    assert_eq!(o.password, "pass");
    assert_eq!(o.host, "host.example");
    assert_eq!(o.port, 10000);
    assert_eq!(o.vhost, "vhost");
}

#[test]
fn defaults() {
    let o = parse("amqp://");
    assert_eq!(
        (o.username.as_str(), o.password.as_str()),
        ("guest", "guest")
    );
    assert_eq!(o.host, "localhost");
    assert_eq!(o.port, 5672);
    assert_eq!(o.vhost, "/");
    assert_eq!(o, ConnectionOptions::default());
}

#[test]
fn empty_path_is_the_default_vhost() {
    assert_eq!(parse("amqp://host").vhost, "/");
    assert_eq!(parse("amqp://host/").vhost, "/");
    assert_eq!(parse("amqp://host:5673").port, 5673);
}

#[test]
fn percent_encoded_vhost_and_credentials() {
    assert_eq!(parse("amqp://host/%2f").vhost, "/");
    assert_eq!(parse("amqp://host/%2Fprod").vhost, "/prod");
    assert_eq!(parse("amqp://host/a%20b").vhost, "a b");
    let o = parse("amqp://us%40er:p%3Aa%2Fss@host");
    assert_eq!(o.username, "us@er");
    assert_eq!(o.password, "p:a/ss");
}

#[test]
fn user_without_password_and_empty_credentials() {
    let o = parse("amqp://alice@host");
    assert_eq!(o.username, "alice");
    assert_eq!(o.password, "guest");
    let o = parse("amqp://:@host");
    assert_eq!(o.username, "");
    assert_eq!(o.password, "");
}

#[test]
fn empty_host_and_port_take_defaults() {
    let o = parse("amqp://user:pass@:/v");
    assert_eq!(o.host, "localhost");
    assert_eq!(o.port, 5672);
    assert_eq!(o.vhost, "v");
    assert_eq!(parse("amqp://:7000").port, 7000);
}

#[test]
fn ipv6_literal() {
    let o = parse("amqp://[::1]:5673/%2f");
    assert_eq!(o.host, "::1");
    assert_eq!(o.port, 5673);
    assert_eq!(parse("amqp://[fe80::1]").port, 5672);
}

#[test]
fn query_parameters() {
    let o =
        parse("amqp://host/v?heartbeat=10&frame_max=8192&channel_max=100&connection_timeout=2500");
    assert_eq!(o.heartbeat, 10);
    assert_eq!(o.frame_max, 8192);
    assert_eq!(o.channel_max, 100);
    assert_eq!(o.connection_timeout, Duration::from_millis(2500));
    assert_eq!(o.vhost, "v");
    let o = parse("amqp://host?heartbeat=0&auth_mechanism=external&connection_name=my%20app");
    assert_eq!(o.heartbeat, 0);
    assert_eq!(o.vhost, "/");
    assert_eq!(o.connection_name.as_deref(), Some("my app"));
}

/// The examples table of RabbitMQ's URI specification, with this client's
/// one deliberate difference: an empty vhost means `/`.
#[test]
fn the_specifications_examples() {
    let o = parse("amqp://user%61:%61pass@ho%61st:10000/v%2fhost");
    assert_eq!(
        (o.username.as_str(), o.password.as_str(), o.host.as_str()),
        ("usera", "apass", "hoast")
    );
    assert_eq!((o.port, o.vhost.as_str()), (10000, "v/host"));
    let o = parse("amqp://:@/");
    assert_eq!((o.username.as_str(), o.password.as_str()), ("", ""));
    assert_eq!(
        (o.host.as_str(), o.port, o.vhost.as_str()),
        ("localhost", 5672, "/")
    );
    let o = parse("amqp://user@");
    assert_eq!(
        (o.username.as_str(), o.password.as_str()),
        ("user", "guest")
    );
    let o = parse("amqp://user:pass@");
    assert_eq!((o.username.as_str(), o.password.as_str()), ("user", "pass"));
    assert_eq!(parse("amqp://:10000").port, 10000);
    assert_eq!(parse("amqp:///vhost").vhost, "vhost");
    assert_eq!(parse("amqp:///vhost").host, "localhost");
    assert_eq!(parse("amqp://[::1]").host, "::1");
}

#[test]
fn query_values_are_percent_decoded() {
    let o = parse("amqp://host?connection_name=a%26b%3Dc&heartbeat=%35");
    assert_eq!(o.connection_name.as_deref(), Some("a&b=c"));
    assert_eq!(o.heartbeat, 5);
}

#[test]
fn amqps_takes_rabbitmqs_tls_parameters() {
    let o = parse("amqps://robot@cell-3.local/%2f?cacertfile=%2Fetc%2Fca.pem&certfile=/c.pem&keyfile=/k.pem&server_name_indication=broker&auth_mechanism=external&verify=verify_peer");
    assert_eq!(o.port, 5671);
    assert_eq!(o.auth_mechanism, AuthMechanism::External);
    assert_eq!(
        o.tls,
        Some(TlsSettings {
            cacertfile: Some("/etc/ca.pem".into()),
            certfile: Some("/c.pem".into()),
            keyfile: Some("/k.pem".into()),
            server_name: Some("broker".into()),
        })
    );
    let system = parse("AMQPS://host:7000");
    assert_eq!(
        (system.port, system.tls),
        (7000, Some(TlsSettings::default()))
    );
    assert_eq!(parse("amqp://host").tls, None);
}

#[test]
fn scheme_is_case_insensitive() {
    assert_eq!(parse("AMQP://host").host, "host");
}

#[test]
fn invalid_uris() {
    rejects("http://host");
    rejects("host:5672");
    rejects("amqp://host?cacertfile=/ca.pem");
    rejects("amqps://host?verify=verify_none");
    rejects("amqps://host?auth_mechanism=kerberos");
    rejects("amqp://host:notaport");
    rejects("amqp://host:70000");
    rejects("amqp://host/a/b");
    rejects("amqp://host/%zz");
    rejects("amqp://[::1");
    rejects("amqp://host?heartbeat=x");
    rejects("amqp://host?heartbeat=65536");
    rejects("amqp://host?channel_max=-1");
    rejects("amqp://host?frame_max=4294967296");
    // Outside RFC 3986's syntax, which the AMQP URI specification uses.
    rejects("amqp:host");
    rejects("amqp://host#fragment");
    rejects("amqp://a@b@host");
    rejects("amqp://host/a b");
    rejects("amqp://host/%C3%28");
    rejects("amqp://[v1.future]");
    rejects("amqp://host//vhost");
}

#[test]
fn from_str_works() {
    let o: ConnectionOptions = "amqp://h:1/x".parse().expect("parse");
    assert_eq!((o.host.as_str(), o.port, o.vhost.as_str()), ("h", 1, "x"));
}
