//! Operators cannot be locked out of the management API and the
//! Prometheus endpoint by sockets that say nothing (issue 29, finding 3:
//! 70 silent sockets per listener used to leave 2 of 30 API calls and 1
//! of 30 scrapes served). A flood of silent sockets, reopened as the
//! broker closes them, from the operator's own address (the hardest
//! case: no per-address bound can tell them apart), while an operator
//! makes authenticated API calls and scrapes on fresh connections; and
//! the single bounds: the oldest waiting connection of a full address
//! gives way, a silent socket is closed after the header timeout, a body
//! that trickles is closed after the body timeout.
//!
//! The flood holds [`FLOOD`] sockets per listener (the figure)
//! when the open-file limit allows it (the test raises its soft limit to
//! the hard one), fewer otherwise, and says so; `LEVERET_FLOOD` changes
//! the count. Latencies are printed, never asserted (CI is a loaded
//! 2-core machine); only a hang limit per call is.

mod common;

use common::ops::{basic, OpsBroker};
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// Silent sockets per listener in the flood.
const FLOOD: usize = 1000;
/// API calls and scrapes made during the flood, each.
const CALLS: usize = 30;
/// The longest one call may take before it counts as failed.
const CALL_LIMIT: Duration = Duration::from_secs(5);
/// The broker's own bounds (`server/src/http.rs`).
const MAX_PER_SOURCE: usize = 256;

/// Raises this process's soft open-file limit to the hard one; returns
/// the soft limit now in force.
fn raise_fd_limit() -> u64 {
    use rustix::process::{getrlimit, setrlimit, Resource};
    let mut limit = getrlimit(Resource::Nofile);
    if limit.current != limit.maximum {
        limit.current = limit.maximum;
        let _ = setrlimit(Resource::Nofile, limit);
    }
    getrlimit(Resource::Nofile).current.unwrap_or(u64::MAX)
}

/// The flood's size: `LEVERET_FLOOD` or [`FLOOD`], cut to what this
/// process's open-file limit allows for two listeners (and the calls).
fn flood_size() -> usize {
    let wanted = std::env::var("LEVERET_FLOOD")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(FLOOD);
    let limit = raise_fd_limit();
    let fits = usize::try_from(limit.saturating_sub(256) / 2).unwrap_or(usize::MAX);
    if fits < wanted {
        eprintln!("*** the open-file limit ({limit}) allows {fits} silent sockets per listener, not {wanted}");
    }
    wanted.min(fits)
}

/// One silent socket, held open and reopened whenever the broker closes
/// it, until `stop`; counts the opens that succeeded.
async fn hold_silent(addr: SocketAddr, opened: Arc<AtomicU64>, stop: Arc<AtomicBool>) {
    let mut buf = [0u8; 64];
    while !stop.load(Ordering::Relaxed) {
        let Ok(Ok(mut socket)) =
            tokio::time::timeout(Duration::from_secs(5), TcpStream::connect(addr)).await
        else {
            tokio::time::sleep(Duration::from_millis(20)).await;
            continue;
        };
        opened.fetch_add(1, Ordering::Relaxed);
        // Says nothing; waits for the broker to close it (or the stop).
        loop {
            match tokio::time::timeout(Duration::from_millis(500), socket.read(&mut buf)).await {
                Ok(Ok(0) | Err(_)) => break,
                Ok(Ok(_)) => {}
                Err(_) if stop.load(Ordering::Relaxed) => return,
                Err(_) => {}
            }
        }
    }
}

/// One request on a fresh connection: the status, or `None` if the
/// broker closed without answering, refused, or took longer than
/// [`CALL_LIMIT`].
async fn call(addr: SocketAddr, path: &str, auth: Option<&str>) -> Option<u16> {
    let exchange = async {
        let mut stream = TcpStream::connect(addr).await.ok()?;
        let mut head = format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n");
        if let Some(auth) = auth {
            head.push_str(&format!("Authorization: {auth}\r\n"));
        }
        head.push_str("\r\n");
        stream.write_all(head.as_bytes()).await.ok()?;
        let mut raw = Vec::new();
        stream.read_to_end(&mut raw).await.ok()?;
        let line = raw.split(|b| *b == b'\r').next()?;
        std::str::from_utf8(line)
            .ok()?
            .split_whitespace()
            .nth(1)?
            .parse()
            .ok()
    };
    tokio::time::timeout(CALL_LIMIT, exchange).await.ok()?
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flood_of_silent_sockets_does_not_lock_operators_out() {
    let flood = flood_size();
    let broker = OpsBroker::start("lockout", &[]);
    let stop = Arc::new(AtomicBool::new(false));
    let opened = Arc::new(AtomicU64::new(0));
    let mut holders = Vec::new();
    for addr in [broker.http, broker.metrics] {
        for _ in 0..flood {
            holders.push(tokio::spawn(hold_silent(
                addr,
                Arc::clone(&opened),
                Arc::clone(&stop),
            )));
        }
    }
    // Every silent socket is open at least once before the operator starts.
    let deadline = Instant::now() + Duration::from_secs(60);
    while opened.load(Ordering::Relaxed) < 2 * flood as u64 {
        assert!(Instant::now() < deadline, "the flood never got going");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let at_start = opened.load(Ordering::Relaxed);

    let auth = basic("guest", "guest");
    let (mut api_ok, mut scrapes_ok) = (0, 0);
    let (mut api_slowest, mut scrape_slowest) = (Duration::ZERO, Duration::ZERO);
    for _ in 0..CALLS {
        let started = Instant::now();
        if call(broker.http, "/api/overview", Some(&auth)).await == Some(200) {
            api_ok += 1;
        }
        api_slowest = api_slowest.max(started.elapsed());
        let started = Instant::now();
        if call(broker.metrics, "/metrics", None).await == Some(200) {
            scrapes_ok += 1;
        }
        scrape_slowest = scrape_slowest.max(started.elapsed());
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let reopened = opened.load(Ordering::Relaxed) - at_start;
    stop.store(true, Ordering::Relaxed);
    for holder in holders {
        holder.abort();
    }
    eprintln!(
        "flood of {flood} silent sockets per listener (reopened {reopened} times while measured): \
         {api_ok}/{CALLS} API calls (slowest {api_slowest:?}), {scrapes_ok}/{CALLS} scrapes (slowest {scrape_slowest:?})"
    );
    assert!(
        reopened > 0,
        "the broker closed none of the silent sockets while they were held"
    );
    assert!(api_ok >= CALLS - 1, "{api_ok}/{CALLS} API calls answered");
    assert!(
        scrapes_ok >= CALLS - 1,
        "{scrapes_ok}/{CALLS} scrapes answered"
    );
}

/// Whether the broker closes `socket` within `limit` (`false` if it is
/// still open then).
async fn closed_within(socket: &mut TcpStream, limit: Duration) -> bool {
    let mut buf = [0u8; 256];
    let deadline = tokio::time::Instant::now() + limit;
    loop {
        match tokio::time::timeout_at(deadline, socket.read(&mut buf)).await {
            Err(_) => return false,
            Ok(Ok(0) | Err(_)) => return true,
            Ok(Ok(_)) => {}
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_address_gives_up_its_oldest_waiting_connection() {
    raise_fd_limit();
    let broker = OpsBroker::start("per-source", &[]);
    let mut silent = Vec::new();
    for _ in 0..MAX_PER_SOURCE {
        silent.push(TcpStream::connect(broker.metrics).await.expect("connect"));
    }
    // A scrape from the same address makes room: the oldest silent socket
    // is closed (at once: far sooner than the header timeout would).
    assert_eq!(call(broker.metrics, "/metrics", None).await, Some(200));
    assert!(
        closed_within(&mut silent[0], Duration::from_secs(30)).await,
        "the oldest silent socket was closed to make room"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn silent_and_slow_clients_are_closed_quickly() {
    let broker = OpsBroker::start("slow", &[]);
    // Nothing at all: closed at the header timeout (2 s; 30 s is the hang
    // limit here, not a timing claim).
    let mut silent = TcpStream::connect(broker.http).await.expect("connect");
    let started = Instant::now();
    assert!(closed_within(&mut silent, Duration::from_secs(30)).await);
    eprintln!("silent socket closed after {:?}", started.elapsed());

    // Half a head, then nothing.
    let mut half = TcpStream::connect(broker.http).await.expect("connect");
    half.write_all(b"GET /api/overview HTTP/1.1\r\nHost: x\r\n")
        .await
        .expect("write");
    assert!(closed_within(&mut half, Duration::from_secs(30)).await);

    // A whole head announcing a body that then trickles in a byte per
    // second: closed at the body timeout (10 s), not served for ever.
    let auth = basic("guest", "guest");
    let mut trickle = TcpStream::connect(broker.http).await.expect("connect");
    let head = format!(
        "PUT /api/queues/%2F/slow HTTP/1.1\r\nHost: x\r\nAuthorization: {auth}\r\n\
         Content-Type: application/json\r\nContent-Length: 100000\r\n\r\n"
    );
    trickle.write_all(head.as_bytes()).await.expect("write");
    let started = Instant::now();
    let mut closed = false;
    while started.elapsed() < Duration::from_secs(60) {
        if trickle.write_all(b" ").await.is_err()
            || closed_within(&mut trickle, Duration::from_secs(1)).await
        {
            closed = true;
            break;
        }
    }
    assert!(closed, "a trickling body was served for a minute");
    eprintln!("trickling body closed after {:?}", started.elapsed());
    // The operator is still served.
    assert_eq!(
        call(broker.http, "/api/overview", Some(&auth)).await,
        Some(200)
    );
}

/// Queues the stalled readers' answers list: enough that an answer is far
/// larger than what the sockets' buffers take (several MB on loopback).
const QUEUES: usize = 6000;

/// Declares `count` transient queues `PREFIX.NNNNN` on `/` through one
/// definitions import.
async fn import_queues(broker: &OpsBroker, prefix: &str, count: usize) {
    let queues: Vec<serde_json::Value> = (0..count)
        .map(|n| serde_json::json!({"name": format!("{prefix}.{n:05}"), "vhost": "/", "durable": false, "auto_delete": false, "arguments": {}}))
        .collect();
    let auth = basic("guest", "guest");
    let imported = common::ops::request(
        broker.http,
        "POST",
        "/api/definitions",
        &[
            ("Authorization", auth.as_str()),
            ("Content-Type", "application/json"),
        ],
        serde_json::json!({"queues": queues}).to_string().as_bytes(),
    )
    .await;
    assert!(
        imported.status / 100 == 2,
        "{}: {}",
        imported.status,
        imported.text()
    );
}

/// Bytes the broker sends for `path` to a client that reads them all.
async fn answer_length(addr: SocketAddr, path: &str, auth: &str) -> usize {
    let mut stream = TcpStream::connect(addr).await.expect("connect");
    let head = format!(
        "GET {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\nAuthorization: {auth}\r\n\r\n"
    );
    stream.write_all(head.as_bytes()).await.expect("write");
    let mut raw = Vec::new();
    tokio::time::timeout(Duration::from_secs(120), stream.read_to_end(&mut raw))
        .await
        .expect("the whole answer within 120 s")
        .expect("read");
    raw.len()
}

/// Whether `raw` is a whole HTTP answer: as long as its Content-Length
/// says, or chunked to its last chunk.
fn complete_answer(raw: &[u8]) -> bool {
    let Some(split) = raw.windows(4).position(|w| w == b"\r\n\r\n") else {
        return false;
    };
    let head = String::from_utf8_lossy(&raw[..split]).to_ascii_lowercase();
    let body = &raw[split + 4..];
    match head
        .lines()
        .find_map(|line| line.strip_prefix("content-length:"))
    {
        Some(length) => length.trim().parse() == Ok(body.len()),
        None => head.contains("transfer-encoding: chunked") && body.ends_with(b"\r\n0\r\n\r\n"),
    }
}

/// A client that asks for a large answer and never reads it, with a small
/// receive buffer (the broker's writes stall as soon as the kernel's
/// buffers are full).
async fn ask_and_stop_reading(addr: SocketAddr, path: &str, auth: &str) -> TcpStream {
    let socket = tokio::net::TcpSocket::new_v4().expect("socket");
    socket.set_recv_buffer_size(4096).expect("SO_RCVBUF");
    let mut stream = socket.connect(addr).await.expect("connect");
    let head = format!(
        "GET {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\nAuthorization: {auth}\r\n\r\n"
    );
    stream.write_all(head.as_bytes()).await.expect("write");
    stream
}

/// Log lines of `listener`'s bounds that count peers which stopped
/// reading (the message names no listener: the `listener` field does).
fn not_reading_reports(broker: &OpsBroker, listener: &str) -> usize {
    broker
        .log()
        .iter()
        .filter(|line| line.contains("stopped reading their answer") && line.contains(listener))
        .count()
}

/// Issue 29: a client that asks for a large answer (`/api/queues`,
/// `/metrics/per-object` with thousands of queues) and stops reading it
/// held its connection slot (a connection being served is never closed to
/// make room) and the answer's memory for ever. Now a connection whose
/// writes make no progress for the write timeout (5 s) is closed, counted
/// and logged: the stalled client gets a truncated answer and the end of
/// its connection. On the binary's current-thread runtime (1 worker, the
/// default) and its multi-thread one (2 workers).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_stops_reading_its_answer_is_closed() {
    for workers in ["1", "2"] {
        let broker = OpsBroker::start(
            &format!("stalled-reader-{workers}"),
            &["--worker-threads", workers],
        );
        let auth = basic("guest", "guest");
        import_queues(&broker, "stalled", QUEUES).await;
        for (addr, path, listener) in [
            (broker.http, "/api/queues", "management"),
            (broker.metrics, "/metrics/per-object", "metrics"),
        ] {
            let whole = answer_length(addr, path, &auth).await;
            let mut stalled = ask_and_stop_reading(addr, path, &auth).await;
            // The broker says it closed it (60 s is a hang limit, not a
            // timing claim).
            let deadline = Instant::now() + Duration::from_secs(60);
            while not_reading_reports(&broker, listener) == 0 {
                assert!(
                    Instant::now() < deadline,
                    "{workers} worker(s), {path}: no log line about a peer that stopped reading:\n{}",
                    broker.log().join("\n")
                );
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
            // What the stalled client can still read is a part of the
            // answer, then the end of the connection.
            let mut got = Vec::new();
            let read = tokio::time::timeout(Duration::from_secs(60), stalled.read_to_end(&mut got))
                .await
                .expect("the connection ended");
            eprintln!(
                "{workers} worker(s), {path}: answer {whole} bytes; the stalled reader got {} before the close ({read:?})",
                got.len()
            );
            assert!(
                got.len() < whole,
                "{workers} worker(s), {path}: the stalled reader still got the whole answer ({whole} bytes)"
            );
            if listener == "management" {
                // A slow reader that keeps reading (1 MiB, then a pause of
                // a second, shorter than the write timeout) gets it all.
                let mut slow = TcpStream::connect(addr).await.expect("connect");
                let head = format!(
                    "GET {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\nAuthorization: {auth}\r\n\r\n"
                );
                slow.write_all(head.as_bytes()).await.expect("write");
                let mut slowly = Vec::new();
                let mut chunk = vec![0u8; 1 << 20];
                'reading: loop {
                    let mut filled = 0;
                    while filled < chunk.len() {
                        let read = tokio::time::timeout(
                            Duration::from_secs(30),
                            slow.read(&mut chunk[filled..]),
                        )
                        .await
                        .expect("30 s hang limit")
                        .expect("the slow reader's connection is not cut");
                        if read == 0 {
                            slowly.extend_from_slice(&chunk[..filled]);
                            break 'reading;
                        }
                        filled += read;
                    }
                    slowly.extend_from_slice(&chunk[..filled]);
                    tokio::time::sleep(Duration::from_secs(1)).await;
                }
                assert!(
                    complete_answer(&slowly),
                    "{workers} worker(s), {path}: a slow reader got {} of {whole} bytes",
                    slowly.len()
                );
            }
            // The listener serves the operator.
            let probe = if listener == "metrics" {
                "/metrics"
            } else {
                "/api/overview"
            };
            assert_eq!(call(addr, probe, Some(&auth)).await, Some(200), "{path}");
        }
        broker.terminate();
    }
}

/// A body the handler never reads (a GET sent with one, as `curl -X GET
/// -d` does) stayed unread in the socket when the broker closed it after
/// its answer, and the kernel answered the close with a reset, which threw
/// away the answer's bytes still in the send buffer: `/api/queues` with a
/// few thousand queues reached such a client cut short every time it read
/// its answer after the body had gone. The broker now reads to the peer's
/// end before closing (a lingering close).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_answer_reaches_a_client_whose_body_nobody_reads() {
    let broker = OpsBroker::start("unread-body", &[]);
    let auth = basic("guest", "guest");
    import_queues(&broker, "unread", 2000).await;
    let whole = answer_length(broker.http, "/api/queues", &auth).await;
    for attempt in 0..3 {
        let mut stream = TcpStream::connect(broker.http).await.expect("connect");
        let head = format!(
            "GET /api/queues HTTP/1.1\r\nHost: x\r\nConnection: close\r\nAuthorization: {auth}\r\n\
             Content-Length: 4\r\n\r\n"
        );
        stream.write_all(head.as_bytes()).await.expect("write");
        // The body goes once the answer has begun (so the broker has read
        // the head and is not reading it), and the answer is read a little
        // later, once the broker has written what its buffers take.
        let mut got = vec![0u8; 1];
        tokio::time::timeout(Duration::from_secs(30), stream.read_exact(&mut got))
            .await
            .expect("30 s hang limit")
            .expect("the answer begins");
        stream.write_all(b"null").await.expect("write the body");
        tokio::time::sleep(Duration::from_millis(300)).await;
        let read = tokio::time::timeout(Duration::from_secs(60), stream.read_to_end(&mut got))
            .await
            .expect("60 s hang limit");
        assert!(
            read.is_ok() && complete_answer(&got),
            "attempt {attempt}: {} of {whole} bytes, then {read:?}",
            got.len()
        );
    }
}

/// The lingering close is bounded: a client that keeps its socket open
/// and keeps sending after its answer is closed all the same (at the
/// linger's end, 2 s; 30 s is the hang limit: this fails only if the
/// linger had no end), and the listener serves the operator meanwhile.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_keeps_sending_after_its_answer_is_closed() {
    let broker = OpsBroker::start("lingering", &[]);
    let auth = basic("guest", "guest");
    let mut stream = TcpStream::connect(broker.http).await.expect("connect");
    let head = format!(
        "GET /api/overview HTTP/1.1\r\nHost: x\r\nConnection: close\r\nAuthorization: {auth}\r\n\r\n"
    );
    stream.write_all(head.as_bytes()).await.expect("write");
    // Read the answer to its end (the broker's FIN).
    let mut answer = Vec::new();
    let mut buf = [0u8; 4096];
    loop {
        let read = tokio::time::timeout(Duration::from_secs(30), stream.read(&mut buf))
            .await
            .expect("30 s hang limit")
            .expect("read");
        if read == 0 {
            break;
        }
        answer.extend_from_slice(&buf[..read]);
    }
    assert!(complete_answer(&answer));
    let started = Instant::now();
    let junk = vec![b'x'; 64 * 1024];
    let mut closed = false;
    let mut served_meanwhile = None;
    while started.elapsed() < Duration::from_secs(30) {
        if stream.write_all(&junk).await.is_err() {
            closed = true;
            break;
        }
        if served_meanwhile.is_none() {
            served_meanwhile = Some(call(broker.http, "/api/overview", Some(&auth)).await);
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert!(
        closed,
        "a client sending after its answer was read for 30 s"
    );
    eprintln!("closed after {:?}", started.elapsed());
    if let Some(served) = served_meanwhile {
        assert_eq!(served, Some(200), "the operator while a client lingered");
    }
    assert_eq!(
        call(broker.http, "/api/overview", Some(&auth)).await,
        Some(200)
    );
}
