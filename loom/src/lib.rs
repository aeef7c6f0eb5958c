//! Model checks, with [loom](https://docs.rs/loom), of the broker's
//! concurrency protocols: every interleaving of a few threads is explored,
//! where a stress test only samples some.
//!
//! The checks live in `tests/` and compile only with `--cfg loom`, which is
//! why they are a crate of their own: tokio and bytes change their own
//! code under that flag, so the broker crate cannot be built with it. Run
//! them with
//!
//! ```text
//! RUSTFLAGS="--cfg loom" CARGO_TARGET_DIR=target/loom cargo test -p leveret-loom
//! ```
//!
//! - `tests/prefetch_credit.rs` compiles the broker's own
//!   `broker/src/consumer/credit.rs` (atomics only) against loom's atomics:
//!   queues racing for a channel's shared prefetch never take more than the
//!   limit, and a refused take leaves no trace.
//! - `tests/tag_handover.rs` is an isolated model of how a delivery tag and
//!   the delivery's place in the connection's outbox are handed out: under
//!   one lock, tags reach the client in order; handed out under the lock and
//!   queued after it (the broker's former dispatch), they can overtake each
//!   other, and the model finds it.
//! - `tests/handoff.rs` compiles the protocol crate's own
//!   `protocol/src/handoff.rs` (a mutex and an atomic) against loom's:
//!   senders racing for one room deliver every item once and in order,
//!   waiting senders are served in the order they began to wait, a room
//!   given back or a cancelled reserve never strands a waiting sender (a
//!   wait given up passes the room it was given to the next in line), a
//!   receiver gone closes the queue and drops its items, and the last
//!   sender gone wakes the receiver after the items.
//!
//! The plain-thread counterparts run in the broker's unit tests and in
//! `tests/tests/multi_thread_stress.rs` on every `cargo test`.
#![forbid(unsafe_code)]
