//! Logins tried as an adversary would (issue 29, finding 1): a flood of
//! `connection.start-ok` with a known user's name and wrong passwords,
//! from many raw sockets that wait for the refusal or hang up early,
//! while a known user and a user logging in for the first time connect
//! with lapin. The broker must keep its password checks bounded (at most
//! `HASH_THREADS` hashing threads and checks at once, checks of clients
//! that hung up dropped), let both legitimate users in, and give its
//! memory back after: what it still holds is counted by this test's own
//! global allocator ([`LiveHeap`]), which no allocator's retention of
//! freed pages can blur; resident memory only has a generous cap.
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
use std::alloc::{GlobalAlloc, Layout, System};
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
/// Resident memory the floods may leave behind in this test process: a
/// generous cap, as glibc keeps freed pages in per-thread arenas (the
/// hashing threads' argon2 blocks, the workers' buffers) in amounts that
/// depend on which thread ran what; the heap's figures above are exact.
/// The unbounded pool this replaces reached gigabytes; the `leveret`
/// binary (jemalloc) returns to within a few MiB of idle (figures in
/// `perf/`).
const RSS_CAP: usize = 256 * 1024 * 1024;
/// Heap the whole process may hold at once during a flood: the hashing
/// threads' argon2 blocks (19 MiB each), and the flooders' and their
/// connections' buffers with room to spare.
const HEAP_FLOOD_CAP: usize = HASH_THREADS * 19 * 1024 * 1024 + 32 * 1024 * 1024;
/// Heap a second flood may leave held beyond what the first left: the
/// odd buffer of a connection still closing or of lapin's. Anything a
/// flood leaks per attempt (thousands of them) would exceed it.
const HEAP_REPEAT_SLACK: usize = 4 * 1024 * 1024;
/// Threads beyond the hashing pool's that may come and go meanwhile
/// (tokio's blocking pool for the odd file operation, lapin's).
const THREAD_SLACK: usize = 8;

/// The system allocator, counting the bytes it holds for this process
/// (live allocations, not pages kept after a free).
struct LiveHeap;

static LIVE_HEAP_BYTES: AtomicUsize = AtomicUsize::new(0);
/// The most [`LIVE_HEAP_BYTES`] reached since [`reset_peak_heap`].
static PEAK_HEAP_BYTES: AtomicUsize = AtomicUsize::new(0);

fn count_allocation(bytes: usize) {
    let live = LIVE_HEAP_BYTES.fetch_add(bytes, Ordering::Relaxed) + bytes;
    PEAK_HEAP_BYTES.fetch_max(live, Ordering::Relaxed);
}

// SAFETY: every call is forwarded unchanged to `System`; the counter is
// the only addition.
unsafe impl GlobalAlloc for LiveHeap {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let block = System.alloc(layout);
        if !block.is_null() {
            count_allocation(layout.size());
        }
        block
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        let block = System.alloc_zeroed(layout);
        if !block.is_null() {
            count_allocation(layout.size());
        }
        block
    }
    unsafe fn dealloc(&self, block: *mut u8, layout: Layout) {
        System.dealloc(block, layout);
        LIVE_HEAP_BYTES.fetch_sub(layout.size(), Ordering::Relaxed);
    }
    unsafe fn realloc(&self, block: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let moved = System.realloc(block, layout, new_size);
        if !moved.is_null() {
            LIVE_HEAP_BYTES.fetch_sub(layout.size(), Ordering::Relaxed);
            count_allocation(new_size);
        }
        moved
    }
}

#[global_allocator]
static ALLOCATOR: LiveHeap = LiveHeap;

/// Bytes this process's heap holds live.
fn live_heap() -> usize {
    LIVE_HEAP_BYTES.load(Ordering::Relaxed)
}

/// The most the heap held live since the last call, and starts again
/// from what it holds now.
fn reset_peak_heap() -> usize {
    PEAK_HEAP_BYTES.swap(live_heap(), Ordering::Relaxed)
}

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
    eprintln!(
        "before the flood: rss {rss_before:?}, live heap {}, threads (all, hashing) \
         {threads_before:?}",
        live_heap()
    );

    // Two floods, one after the other: the first shows the bounds hold
    // under it; the second that nothing it leaves behind grows with each
    // flood. Resident memory only gets a cap: glibc may keep what a flood
    // freed in per-thread arenas (the hashing threads' argon2 blocks, the
    // workers' buffers), and how much depends on which threads ran what;
    // the live heap is exact.
    let mut rss_after = Vec::new();
    let mut heap_after = Vec::new();
    for round in 1..=2 {
        eprintln!("flood {round}");
        reset_peak_heap();
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
        let peak_heap = reset_peak_heap();
        eprintln!(
            "flood: {} attempts; first-time login {first_time:?}, known user's {known:?}; \
             most threads {most_threads} (hashing {most_hashing}); peak live heap \
             {peak_heap}; pool {during:?}",
            attempts.load(Ordering::Relaxed)
        );
        assert!(
            peak_heap <= HEAP_FLOOD_CAP,
            "the heap held {} MiB at once during the flood",
            peak_heap >> 20
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
        heap_after.push(live_heap());
        eprintln!(
            "after flood {round}: rss {:?}, live heap {}, threads {:?}",
            rss_after[round - 1],
            heap_after[round - 1],
            threads()
        );
    }
    if let Some(before) = rss_before {
        for (round, after) in rss_after.iter().enumerate() {
            if let Some(after) = after {
                assert!(
                    *after <= before + RSS_CAP,
                    "resident memory grew from {} to {} MiB by flood {}",
                    before >> 20,
                    after >> 20,
                    round + 1
                );
            }
        }
    }
    assert!(
        heap_after[1] <= heap_after[0] + HEAP_REPEAT_SLACK,
        "the live heap grew from {} to {} KiB in a second flood",
        heap_after[0] >> 10,
        heap_after[1] >> 10
    );
    b.stop().await;
}
