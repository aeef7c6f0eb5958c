//! What many cores would contend on (issue 36 goal 4; the analysis is in
//! `docs/performance.md`, "Scaling beyond two cores"): each structure that
//! every message touches, driven from 1, 2, 4 threads at once through the
//! broker's own code where the structure is the broker's:
//!
//! - `counter`: one `AtomicU64` that every thread adds to (how the
//!   broker-wide counters and the memory gauge count) against one
//!   cache-line-padded slot per thread, summed by readers (the design that
//!   removes the shared line);
//! - `queue`: publish then basic.get (no-ack) through `Queue::publish` and
//!   the channel-side `get`, every thread on one queue (one
//!   `Mutex<QueueState>` for all) against each thread on its own queue;
//! - `persister`: `Persistence::submit` of one op from every thread into
//!   the one persister's inbox (over an in-memory store, so the figure is
//!   the inbox and the persister thread, not a disk), until all are flushed;
//! - `registry`: `Vhost::queue`, the registry's `RwLock` read that a
//!   lookup by name takes.
//!
//! Each sample runs every thread for the same number of operations and
//! reports the total rate (`thrpt`, operations a second across threads):
//! a structure that scales shows the rate growing with threads; a
//! contended one shows it flat or falling. On this 2-core machine only 1
//! and 2 threads run in parallel (4 shows oversubscription); run it on a
//! larger machine with `CONTENTION_THREADS=1,2,4,8,16`.
//!
//! Run: `cargo bench -p leveret-broker --features bench-internals --bench contention`

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use leveret_broker::bench::{Getter, Queues};
use leveret_broker::store::{MemoryStore, Persistence, Recovered, Store, StoreOp};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Barrier, Mutex};
use std::time::{Duration, Instant};

/// Thread counts to run: `CONTENTION_THREADS` (comma-separated) or 1, 2, 4.
fn thread_counts() -> Vec<usize> {
    match std::env::var("CONTENTION_THREADS") {
        Ok(list) => list
            .split(',')
            .map(|n| n.trim().parse().expect("CONTENTION_THREADS: numbers"))
            .collect(),
        Err(_) => vec![1, 2, 4],
    }
}

/// Runs `work(thread, operations)` on `threads` threads released together;
/// the time from the release until the last one finishes.
fn on_threads(threads: usize, operations: u64, work: impl Fn(usize, u64) + Sync) -> Duration {
    let start_line = Barrier::new(threads + 1);
    std::thread::scope(|scope| {
        let running: Vec<_> = (0..threads)
            .map(|thread| {
                let (start_line, work) = (&start_line, &work);
                scope.spawn(move || {
                    start_line.wait();
                    work(thread, operations);
                })
            })
            .collect();
        start_line.wait();
        let started = Instant::now();
        for thread in running {
            thread.join().expect("a bench thread");
        }
        started.elapsed()
    })
}

/// A counter slot alone on its cache line (128 bytes: two lines, as the
/// adjacent-line prefetcher of x86 pulls pairs).
#[repr(align(128))]
#[derive(Default)]
struct PaddedSlot(AtomicU64);

fn counter(c: &mut Criterion) {
    let mut group = c.benchmark_group("counter");
    for threads in thread_counts() {
        group.throughput(Throughput::Elements(threads as u64));
        let shared = AtomicU64::new(0);
        group.bench_with_input(BenchmarkId::new("shared", threads), &threads, |b, &n| {
            b.iter_custom(|iters| {
                on_threads(n, iters, |_, ops| {
                    for _ in 0..ops {
                        shared.fetch_add(1, Ordering::Relaxed);
                    }
                })
            })
        });
        let slots: Vec<PaddedSlot> = (0..threads).map(|_| PaddedSlot::default()).collect();
        group.bench_with_input(
            BenchmarkId::new("per_thread", threads),
            &threads,
            |b, &n| {
                b.iter_custom(|iters| {
                    on_threads(n, iters, |thread, ops| {
                        let slot = &slots[thread].0;
                        for _ in 0..ops {
                            slot.fetch_add(1, Ordering::Relaxed);
                        }
                    })
                })
            },
        );
        // Readers sum the slots: the total is every add, as with one counter.
        let summed: u64 = slots
            .iter()
            .map(|slot| slot.0.load(Ordering::Relaxed))
            .sum();
        assert!(summed > 0 && shared.load(Ordering::Relaxed) > 0);
    }
    group.finish();
}

fn queue(c: &mut Criterion) {
    let mut group = c.benchmark_group("queue");
    let queues = Queues::default();
    let counts = thread_counts();
    let most = counts.iter().copied().max().unwrap_or(1);
    queues.declare("shared");
    for thread in 0..most {
        queues.declare(&format!("own-{thread}"));
    }
    for threads in counts {
        group.throughput(Throughput::Elements(threads as u64));
        for (bench, shared) in [("one_queue", true), ("queue_each", false)] {
            let getters: Vec<Mutex<Getter>> =
                (0..threads).map(|_| Mutex::new(queues.channel())).collect();
            group.bench_with_input(BenchmarkId::new(bench, threads), &threads, |b, &n| {
                b.iter_custom(|iters| {
                    let elapsed = on_threads(n, iters, |thread, times| {
                        let name = if shared {
                            "shared".to_owned()
                        } else {
                            format!("own-{thread}")
                        };
                        let mut getter = getters[thread].lock().expect("one thread each");
                        queues.publish_and_get(&name, &mut getter, times);
                    });
                    queues.purge();
                    elapsed
                })
            });
        }
    }
    group.finish();
}

fn persister(c: &mut Criterion) {
    let mut group = c.benchmark_group("persister");
    let store: Arc<dyn Store> = Arc::new(MemoryStore::default());
    let persistence = Persistence::start(store, &Recovered::default()).expect("it starts");
    for threads in thread_counts() {
        group.throughput(Throughput::Elements(threads as u64));
        group.bench_with_input(BenchmarkId::new("submit", threads), &threads, |b, &n| {
            b.iter_custom(|iters| {
                let elapsed = on_threads(n, iters, |thread, times| {
                    for op in 0..times {
                        let id = (thread as u64) << 48 | op;
                        persistence.submit(vec![StoreOp::DeleteMessage { id }]);
                    }
                });
                // Until the persister has taken everything submitted: the
                // inbox's cost is both sides of it.
                let started = Instant::now();
                let last = persistence.submit(Vec::new());
                while persistence.flushed() < last {
                    std::thread::yield_now();
                }
                elapsed + started.elapsed()
            })
        });
    }
    group.finish();
}

fn registry(c: &mut Criterion) {
    let mut group = c.benchmark_group("registry");
    let queues = Queues::default();
    for index in 0..100 {
        queues.declare(&format!("queue-{index}"));
    }
    for threads in thread_counts() {
        group.throughput(Throughput::Elements(threads as u64));
        group.bench_with_input(BenchmarkId::new("lookup", threads), &threads, |b, &n| {
            b.iter_custom(|iters| {
                on_threads(n, iters, |_, times| {
                    for _ in 0..times {
                        assert!(queues.lookup("queue-42"));
                    }
                })
            })
        });
    }
    group.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default()
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(2));
    targets = counter, queue, persister, registry
}
criterion_main!(benches);
