//! # leveret-client
//!
//! A thin async AMQP 0.9.1 client on `leveret-protocol`, and typed robot
//! data ports over it. Work in progress: the client API lands with issue 5.
#![deny(missing_docs)]
#![forbid(unsafe_code)]

pub use leveret_protocol as protocol;
