//! # leveret-broker
#![forbid(unsafe_code)]
