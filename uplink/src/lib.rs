//! Leveret's uplink: the robot's end of the link to the fleet's broker
//! (a RabbitMQ cluster). Shovels ([`Shovel`]) forward messages from a
//! queue or exchange of one broker to a queue or exchange of another,
//! with RabbitMQ's dynamic-shovel parameters ([`ShovelConfig`]): store on
//! the robot while the link is down, forward with confirms when it is up,
//! fail over between the cluster's nodes, and never let a refusing
//! destination drain the source.
//!
//! Layout: `config.rs` the parameters, `shovel.rs` the running shovel,
//! `pace.rs` its rate limits.
//! Uses the broker's embedding API (for in-process local connections) and
//! the client crate.
#![deny(missing_docs)]

mod config;
mod pace;
mod shovel;

pub use config::{AckMode, Destination, ShovelConfig, Source};
pub use shovel::{Shovel, ShovelState, ShovelStatus, SEQ_HEADER};
