//! RabbitMQ's `loopback_users` (issue 14, safe defaults): `guest` may log
//! in only from this host. A client that connects to one of this host's
//! own non-loopback addresses arrives from that address, as a remote
//! client would, so the broker listens on every interface and the test
//! connects both ways.

#[macro_use]
mod common;

use common::*;
use leveret_broker::{Broker, Permission};
use std::net::{IpAddr, SocketAddr, UdpSocket};

/// An address of this host that is not loopback: the source address the
/// kernel picks towards a documentation-only address (a UDP "connect"
/// sends nothing).
fn non_loopback_address() -> Option<IpAddr> {
    let socket = UdpSocket::bind("0.0.0.0:0").ok()?;
    socket.connect("192.0.2.1:9").ok()?;
    let ip = socket.local_addr().ok()?.ip();
    (!ip.is_loopback() && !ip.is_unspecified()).then_some(ip)
}

/// A broker on every interface with `builder`'s users, and the URL of
/// `user` through `ip`.
async fn on_every_interface(
    builder: leveret_broker::BrokerBuilder,
) -> (leveret_broker::BrokerHandle, u16) {
    let any: SocketAddr = "0.0.0.0:0".parse().expect("static address");
    let handle = builder.listen(any).start().await.expect("broker starts");
    let port = handle.local_addrs()[0].port();
    (handle, port)
}

fn url(user: &str, password: &str, ip: IpAddr, port: u16) -> String {
    format!("amqp://{user}:{password}@{}/%2f", SocketAddr::new(ip, port))
}

#[both_runtimes]
async fn guest_is_refused_beyond_this_host_with_rabbitmqs_403() {
    let Some(remote) = non_loopback_address() else {
        panic!("this host has no non-loopback address to connect from");
    };
    let builder = Broker::builder()
        .user("guest", "guest")
        .user("robot", "pw")
        .permission("guest", "/", Permission::full())
        .permission("robot", "/", Permission::full());
    let (handle, port) = on_every_interface(builder).await;
    let local = IpAddr::from([127, 0, 0, 1]);
    let ok = tmo!(lp::Connection::connect(
        &url("guest", "guest", local, port),
        lp::ConnectionProperties::default()
    ));
    assert!(ok.is_ok(), "guest via localhost: {ok:?}");
    let refused = tmo!(lp::Connection::connect(
        &url("guest", "guest", remote, port),
        lp::ConnectionProperties::default()
    ));
    lp::assert_err(
        refused,
        403,
        "ACCESS_REFUSED - user 'guest' can only connect via localhost",
    );
    let robot = tmo!(lp::Connection::connect(
        &url("robot", "pw", remote, port),
        lp::ConnectionProperties::default()
    ));
    assert!(robot.is_ok(), "another user from anywhere: {robot:?}");
    handle.shutdown().await;
}

#[both_runtimes]
async fn an_empty_loopback_users_list_lets_guest_in_from_anywhere() {
    let Some(remote) = non_loopback_address() else {
        panic!("this host has no non-loopback address to connect from");
    };
    let builder = Broker::builder().loopback_users(Vec::<String>::new());
    let (handle, port) = on_every_interface(builder).await;
    let connected = tmo!(lp::Connection::connect(
        &url("guest", "guest", remote, port),
        lp::ConnectionProperties::default()
    ));
    assert!(connected.is_ok(), "guest from {remote}: {connected:?}");
    handle.shutdown().await;
}
