//! # leveret-broker
//!
//! An embeddable AMQP 0.9.1 broker. Start one inside a process with
//! [`Broker::builder`], or run the `leveret` binary.
//!
//! ```no_run
//! # async fn demo() -> Result<(), leveret_broker::StartError> {
//! let handle = leveret_broker::Broker::builder()
//!     .listen("127.0.0.1:0".parse().unwrap())
//!     .start()
//!     .await?;
//! println!("serving on {:?}", handle.local_addrs());
//! handle.shutdown().await;
//! # Ok(()) }
//! ```
#![forbid(unsafe_code)]

mod embed;

pub use embed::{Broker, BrokerBuilder, BrokerHandle, StartError};
