//! Leveret's uplink: the robot's end of the link to the fleet's broker
//! (a RabbitMQ cluster). Shovels ([`Shovel`]) forward messages from a
//! queue or exchange of one broker to a queue or exchange of another,
//! with RabbitMQ's dynamic-shovel parameters ([`ShovelConfig`]): store on
//! the robot while the link is down, forward with confirms when it is up,
//! fail over between the cluster's nodes, and never let a refusing
//! destination drain the source.
//!
//! Federation ([`FederationLink`]) brings an upstream exchange's messages
//! down to a local exchange, with RabbitMQ's upstream parameters
//! ([`UpstreamConfig`]), binding propagation and hop counting.
//!
//! Layout: `config.rs` the shovel parameters, `shovel.rs` the running
//! shovel, `pace.rs` its rate limits, `federation.rs` the federation
//! links.
//! Uses the broker's embedding API (for in-process local connections) and
//! the client crate.
#![deny(missing_docs)]

mod config;
mod federation;
mod pace;
mod shovel;

pub use config::{AckMode, DeleteAfter, Destination, ShovelConfig, Source};
pub use federation::{
    FederationLink, LinkState, LinkStatus, LocalExchange, UpstreamConfig, RECEIVED_FROM,
};
pub use shovel::{
    Shovel, ShovelState, ShovelStatus, MAX_SHOVEL_HOPS, SEQ_HEADER, SHOVELLED_HEADER,
};
