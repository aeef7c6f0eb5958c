//! Logins tried as an adversary would (issue 29, finding 1): a flood of
//! `connection.start-ok` with a known user's name and wrong passwords,
//! from many raw sockets that wait for the refusal or hang up early,
//! while a known user and a user logging in for the first time connect
//! with lapin. The broker must keep its password checks bounded (at most
//! `HASH_THREADS` hashing threads and checks at once, checks of clients
//! that hung up dropped), let both legitimate users in, and give its
//! memory back after.
//!
//! These need an in-process Leveret (its hashing pool's figures, this
//! process's threads and memory), so they always start one; both take
//! [`SERIAL`] so that neither measures while the other floods.

#[macro_use]
mod common;

use bytes::{Bytes, BytesMut};
use common::*;
use leveret_broker::{Broker, Permission, HASH_THREADS};
use leveret_protocol::{
    decode_frame, encode_method, ConnectionStartOk, FieldTable, Frame, Method, ShortStr,
    PROTOCOL_HEADER,
};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// Held by every test of this file for its whole run.
static SERIAL: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

/// Sockets flooding at once.
const FLOODERS: usize = 60;
/// How long the flood lasts at least (it also lasts until both
/// legitimate logins are done).
const FLOOD: Duration = Duration::from_secs(4);
/// How long a legitimate login may take under the flood before the test
/// calls it locked out: a hang limit, not a latency target (those are
/// measured in `perf/`).
const LOGIN_HANG: Duration = Duration::from_secs(20);
/// Resident memory one flood may leave behind in this test process: the
/// hashing threads' argon2 blocks (19 MiB each) that glibc's per-thread
/// arenas may keep, twice over, and the flood's connections' buffers. The
/// unbounded pool this replaces reached gigabytes; the `leveret` binary
/// (jemalloc) returns to within a few MiB of idle (figures in `perf/`).
const RSS_CAP: usize = 2 * HASH_THREADS * 19 * 1024 * 1024 + 32 * 1024 * 1024;
/// Resident memory a second flood may add to the first's.
const RSS_REPEAT_SLACK: usize = 24 * 1024 * 1024;
/// Threads beyond the hashing pool's that may come and go meanwhile
/// (tokio's blocking pool for the odd file operation, lapin's).
const THREAD_SLACK: usize = 8;

/// This process's resident memory, bytes.
fn rss() -> Option<usize> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
    let kib: usize = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// This process's threads: all of them, and the hashing pool's.
fn threads() -> Option<(usize, usize)> {
    let mut all = 0;
    let mut hashing = 0;
    for task in std::fs::read_dir("/proc/self/task").ok()? {
        all += 1;
        let comm = std::fs::read_to_string(task.ok()?.path().join("comm")).unwrap_or_default();
        if comm.trim() == "leveret-hash" {
            hashing += 1;
        }
    }
    Some((all, hashing))
}

fn start_ok(user: &str, password: &str) -> BytesMut {
    let method = ConnectionStartOk {
        client_properties: FieldTable::new(),
        mechanism: ShortStr::from_static("PLAIN"),
        response: Bytes::from(format!("\0{user}\0{password}")),
        locale: ShortStr::from_static("en_US"),
    };
    let mut buf = BytesMut::new();
    encode_method(0, &method.into(), &mut buf);
    buf
}

/// One wrong login on a raw socket: the header, connection.start, a
/// start-ok with a wrong password; then either a hang-up after 30 ms or
/// a wait for the broker's answer. True if the broker let it in.
async fn wrong_login(addr: &str, attempt: usize) -> bool {
    let Ok(mut socket) = TcpStream::connect(addr).await else {
        return false;
    };
    if socket.write_all(PROTOCOL_HEADER).await.is_err() {
        return false;
    }
    let mut buf = BytesMut::new();
    let mut started = false;
    loop {
        match decode_frame(&mut buf, 0) {
            Ok(Some(Frame::Method {
                method: Method::ConnectionStart(_),
                ..
            })) if !started => {
                started = true;
                let refused = start_ok("guest", &format!("wrong-{attempt}"));
                if socket.write_all(&refused).await.is_err() {
                    return false;
                }
                if attempt % 2 == 0 {
                    tokio::time::sleep(Duration::from_millis(30)).await;
                    return false;
                }
            }
            Ok(Some(Frame::Method {
                method: Method::ConnectionTune(_),
                ..
            })) => return true,
            Ok(Some(_)) => {}
            Ok(None) => match socket.read_buf(&mut buf).await {
                Ok(0) | Err(_) => return false,
                Ok(_) => {}
            },
            Err(_) => return false,
        }
    }
}

/// A lapin login to "/" as `user`, within [`LOGIN_HANG`].
async fn login(b: &TestBroker, user: &str, password: &str) {
    let url = b.url_with(user, password, "%2f");
    let connecting = lp::Connection::connect(&url, lp::ConnectionProperties::default());
    let connection = tokio::time::timeout(LOGIN_HANG, connecting)
        .await
        .unwrap_or_else(|_| panic!("{user} locked out by the flood: no login in {LOGIN_HANG:?}"))
        .unwrap_or_else(|e| panic!("{user} refused under the flood: {e}"));
    let _ = connection.close(200, "bye").await;
}

#[both_runtimes]
async fn a_wrong_password_flood_stays_bounded_and_locks_nobody_out() {
    let _serial = SERIAL.lock().await;
    let b = TestBroker::leveret(
        Broker::builder()
            .user("guest", "guest")
            .user("robot", "robot-pw")
            .permission("guest", "/", Permission::full())
            .permission("robot", "/", Permission::full()),
    )
    .await;
    let admin = b.admin().expect("in-process broker");
    // guest is a known user: its password has been checked once.
    login(&b, "guest", "guest").await;
    let rss_before = rss();
    let threads_before = threads();
    eprintln!("before the flood: rss {rss_before:?}, threads (all, hashing) {threads_before:?}");

    // Two floods, one after the other: the first shows the bounds hold
    // under it; the second that nothing it leaves behind grows with each
    // flood (the allocator may keep what the first one freed, e.g. the
    // hashing threads' argon2 blocks in glibc's per-thread arenas, but a
    // second flood must reuse it).
    let mut rss_after = Vec::new();
    for round in 1..=2 {
        eprintln!("flood {round}");
        let stop = Arc::new(AtomicBool::new(false));
        let attempts = Arc::new(AtomicUsize::new(0));
        let let_in = Arc::new(AtomicUsize::new(0));
        let flooders: Vec<_> = (0..FLOODERS)
            .map(|i| {
                let (addr, stop) = (b.addr(), Arc::clone(&stop));
                let (attempts, let_in) = (Arc::clone(&attempts), Arc::clone(&let_in));
                tokio::spawn(async move {
                    let mut attempt = i;
                    while !stop.load(Ordering::Relaxed) {
                        if wrong_login(&addr, attempt).await {
                            let_in.fetch_add(1, Ordering::Relaxed);
                        }
                        attempts.fetch_add(1, Ordering::Relaxed);
                        attempt += FLOODERS;
                    }
                })
            })
            .collect();
        let watch = {
            let stop = Arc::clone(&stop);
            tokio::spawn(async move {
                let mut most = (0, 0);
                while !stop.load(Ordering::Relaxed) {
                    if let Some((all, hashing)) = threads() {
                        most = (most.0.max(all), most.1.max(hashing));
                    }
                    tokio::time::sleep(Duration::from_millis(50)).await;
                }
                most
            })
        };
        let flood_started = tokio::time::Instant::now();
        // Let the flood fill the queues first.
        tokio::time::sleep(Duration::from_millis(500)).await;
        let started = std::time::Instant::now();
        login(&b, "robot", "robot-pw").await;
        let first_time = started.elapsed();
        let started = std::time::Instant::now();
        login(&b, "guest", "guest").await;
        let known = started.elapsed();
        tokio::time::sleep_until(flood_started + FLOOD).await;
        let during = admin.hash_pool_stats();
        stop.store(true, Ordering::Relaxed);
        for flooder in flooders {
            within("a flooder to stop", flooder).await.expect("flooder");
        }
        let (most_threads, most_hashing) = watch.await.expect("watcher");
        eprintln!(
            "flood: {} attempts; first-time login {first_time:?}, known user's {known:?}; \
             most threads {most_threads} (hashing {most_hashing}); pool {during:?}",
            attempts.load(Ordering::Relaxed)
        );
        assert_eq!(
            let_in.load(Ordering::Relaxed),
            0,
            "no wrong password let in"
        );
        assert!(attempts.load(Ordering::Relaxed) > FLOODERS, "the flood ran");
        assert!(during.threads <= HASH_THREADS, "{during:?}");
        assert!(during.peak_running <= HASH_THREADS, "{during:?}");
        assert!(
            during.abandoned > 0,
            "checks of clients that hung up are dropped before they start: {during:?}"
        );
        if let Some((threads_before, _)) = threads_before {
            assert!(
                most_hashing <= HASH_THREADS,
                "hashing threads {most_hashing}"
            );
            assert!(
                most_threads <= threads_before + HASH_THREADS + THREAD_SLACK,
                "threads grew from {threads_before} to {most_threads}"
            );
        }

        // Afterwards: nothing left running or waiting, memory given back.
        let deadline = tokio::time::Instant::now() + LOGIN_HANG;
        loop {
            let stats = admin.hash_pool_stats();
            if stats.running == 0 && stats.waiting == 0 {
                break;
            }
            assert!(
                tokio::time::Instant::now() < deadline,
                "checks still going after the flood: {stats:?}"
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        rss_after.push(rss());
        eprintln!(
            "after flood {round}: rss {:?}, threads {:?}",
            rss_after[round - 1],
            threads()
        );
    }
    if let (Some(before), Some(first), Some(second)) = (rss_before, rss_after[0], rss_after[1]) {
        assert!(
            first <= before + RSS_CAP,
            "resident memory grew from {} to {} MiB in one flood",
            before >> 20,
            first >> 20
        );
        assert!(
            second <= first + RSS_REPEAT_SLACK,
            "resident memory grew from {} to {} MiB in a second flood",
            first >> 20,
            second >> 20
        );
    }
    b.stop().await;
}
