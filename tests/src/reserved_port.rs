//! Loopback addresses a test must know before anything listens on them,
//! or must bind again after an outage: a restarted broker or proxy, a
//! RabbitMQ node that cannot report the port it took, an address nothing
//! listens on.
//!
//! Binding port 0 and releasing it is not enough for these: every port-0
//! bind of every process on the machine draws from the kernel's ephemeral
//! range, so a concurrently starting listener may take the released port
//! before the test binds it again. [`reserved_addr`] draws instead from
//! below that range, where no port-0 bind ever lands; only another
//! explicit pick could collide, and picks are random over thousands of
//! ports and checked free.

use std::collections::hash_map::RandomState;
use std::hash::{BuildHasher, Hasher};
use std::net::{Ipv4Addr, SocketAddr, TcpListener};

/// The lowest port drawn from.
const FLOOR: u16 = 10_000;

/// A free loopback address below the kernel's ephemeral port range (Linux
/// reads it from `ip_local_port_range`; elsewhere the IANA range, from
/// 49152, is assumed), checked free when picked and released.
pub fn reserved_addr() -> SocketAddr {
    let ceiling = ephemeral_floor();
    assert!(
        ceiling > FLOOR + 1000,
        "the ephemeral range starts at {ceiling}"
    );
    for _ in 0..1000 {
        let port = FLOOR + (random() % u64::from(ceiling - FLOOR)) as u16;
        let addr = SocketAddr::from((Ipv4Addr::LOCALHOST, port));
        if TcpListener::bind(addr).is_ok() {
            return addr;
        }
    }
    panic!("no free port between {FLOOR} and {ceiling}");
}

fn ephemeral_floor() -> u16 {
    std::fs::read_to_string("/proc/sys/net/ipv4/ip_local_port_range")
        .ok()
        .and_then(|range| range.split_whitespace().next()?.parse().ok())
        .unwrap_or(49152)
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
    fn reserved_addresses_are_free_loopback_ports_below_the_ephemeral_range() {
        for _ in 0..50 {
            let addr = reserved_addr();
            assert!(addr.ip().is_loopback());
            assert!((FLOOR..ephemeral_floor()).contains(&addr.port()), "{addr}");
            TcpListener::bind(addr).expect("still free");
        }
    }
}
