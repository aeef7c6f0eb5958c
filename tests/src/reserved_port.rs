//! Loopback addresses a test must know before anything listens on them,
//! or must bind again after an outage: a restarted broker or proxy, a
//! RabbitMQ node that cannot report the port it took, an address nothing
//! listens on.
//!
//! Binding port 0 and releasing it is not enough for these: every port-0
//! bind of every process on the machine draws from the kernel's ephemeral
//! range, so a concurrently starting listener may take the released port
//! before the test binds it again. [`reserved_addr`] draws instead from
//! outside that range, where no port-0 bind ever lands; only another
//! explicit pick could collide, and picks are random over thousands of
//! ports and checked free.

use std::collections::hash_map::RandomState;
use std::hash::{BuildHasher, Hasher};
use std::net::{Ipv4Addr, SocketAddr, TcpListener};

/// The lowest port drawn from below the ephemeral range.
const FLOOR: u16 = 10_000;

/// The fewest ports a range drawn from may have.
const ENOUGH: u16 = 1000;

/// A free loopback address outside the kernel's ephemeral port range
/// (Linux reads it from `ip_local_port_range`; elsewhere the IANA range,
/// 49152-65535, is assumed): below it, or above it where it starts too
/// low to leave room; checked free when picked, and released.
pub fn reserved_addr() -> SocketAddr {
    let (from, to) = drawn_from();
    for _ in 0..1000 {
        let port = from + (random() % u64::from(to - from)) as u16;
        let addr = SocketAddr::from((Ipv4Addr::LOCALHOST, port));
        if TcpListener::bind(addr).is_ok() {
            return addr;
        }
    }
    panic!("no free port between {from} and {to}");
}

/// The ports drawn from: `from..to`.
fn drawn_from() -> (u16, u16) {
    let (low, high) = ephemeral_range();
    if low >= FLOOR.saturating_add(ENOUGH) {
        (FLOOR, low)
    } else if high <= u16::MAX - ENOUGH {
        (high + 1, u16::MAX)
    } else {
        panic!("the ephemeral port range {low}-{high} leaves no room for reserved ports")
    }
}

/// The kernel's ephemeral port range, both ends included.
fn ephemeral_range() -> (u16, u16) {
    std::fs::read_to_string("/proc/sys/net/ipv4/ip_local_port_range")
        .ok()
        .and_then(|range| {
            let mut bounds = range.split_whitespace().map(str::parse);
            Some((bounds.next()?.ok()?, bounds.next()?.ok()?))
        })
        .unwrap_or((49152, u16::MAX))
}

/// A fresh random number: std's hasher keys are random per `RandomState`.
fn random() -> u64 {
    let mut hasher = RandomState::new().build_hasher();
    hasher.write_u32(std::process::id());
    hasher.finish()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reserved_addresses_are_free_loopback_ports_outside_the_ephemeral_range() {
        for _ in 0..50 {
            let addr = reserved_addr();
            assert!(addr.ip().is_loopback());
            let (low, high) = ephemeral_range();
            assert!(!(low..=high).contains(&addr.port()), "{addr}");
            TcpListener::bind(addr).expect("still free");
        }
    }
}
