//! The broker-wide resource alarms (RabbitMQ's memory and disk alarms) and
//! their sources: `memory` holds the alarm itself (the [`MemoryGauge`]
//! that counts the broker's bytes and blocks publishers), `resident` and
//! `disk` are the watchers that feed it the process's resident memory and
//! the data directory's free space. Uses nothing else of the broker.
//!
//! [`MemoryGauge`]: memory::MemoryGauge

pub(crate) mod disk;
pub(crate) mod memory;
pub(crate) mod resident;
