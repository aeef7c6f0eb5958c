//! Access control: who may connect and what they may do.
//!
//! - `auth`: users, their tags and password hashes, and the SASL
//!   mechanisms that check them; `password` the hash schemes, `hash_pool`
//!   the bounded threads that check slow hashes, `login_backoff` failed
//!   logins answered later.
//! - `permissions`: RabbitMQ's configure, write and read permissions and
//!   their patterns.
//!
//! These are shared pieces that every layer may use. `lasting` (users,
//! vhosts and permissions that last: restored at start, and their store
//! records) sits higher, in the operators' layer of the crate's Layout:
//! only the admin handle and the start-up use it.

pub(crate) mod auth;
pub(crate) mod hash_pool;
pub(crate) mod lasting;
mod login_backoff;
pub(crate) mod password;
pub(crate) mod permissions;
