//! Users and authentication: salted SHA-256 password hashes (RabbitMQ's
//! default scheme: a 4-byte salt prepended to the password before
//! hashing), and the SASL mechanisms PLAIN and AMQPLAIN.

use bytes::{Bytes, BytesMut};
use leveret_protocol::{FieldTable, FieldValue};
use sha2::{Digest, Sha256};
use std::collections::HashMap;

/// A stored password: salt and SHA-256 of salt + password.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PasswordHash {
    salt: [u8; 4],
    digest: [u8; 32],
}

impl PasswordHash {
    /// Hashes `password` with a fresh salt.
    pub fn new(password: &str) -> Self {
        use std::hash::{BuildHasher, Hasher};
        let mut hasher = std::collections::hash_map::RandomState::new().build_hasher();
        hasher.write(password.as_bytes());
        let salt = (hasher.finish() as u32).to_be_bytes();
        Self::with_salt(salt, password)
    }

    fn with_salt(salt: [u8; 4], password: &str) -> Self {
        let mut sha = Sha256::new();
        sha.update(salt);
        sha.update(password.as_bytes());
        PasswordHash {
            salt,
            digest: sha.finalize().into(),
        }
    }

    /// The stored form: 8 hex digits of salt, then 64 of SHA-256.
    pub fn to_hex(&self) -> String {
        self.salt
            .iter()
            .chain(self.digest.iter())
            .map(|b| format!("{b:02x}"))
            .collect()
    }

    /// Parses the stored form made by [`PasswordHash::to_hex`].
    pub fn from_hex(text: &str) -> Option<Self> {
        let text = text.trim();
        if text.len() != 72 || !text.is_ascii() {
            return None;
        }
        let mut bytes = [0u8; 36];
        for (i, byte) in bytes.iter_mut().enumerate() {
            *byte = u8::from_str_radix(&text[2 * i..2 * i + 2], 16).ok()?;
        }
        let mut salt = [0u8; 4];
        let mut digest = [0u8; 32];
        salt.copy_from_slice(&bytes[..4]);
        digest.copy_from_slice(&bytes[4..]);
        Some(PasswordHash { salt, digest })
    }

    /// Whether `password` matches.
    pub fn verify(&self, password: &[u8]) -> bool {
        let mut sha = Sha256::new();
        sha.update(self.salt);
        sha.update(password);
        let digest: [u8; 32] = sha.finalize().into();
        // Constant-time comparison.
        digest
            .iter()
            .zip(self.digest.iter())
            .fold(0u8, |acc, (a, b)| acc | (a ^ b))
            == 0
    }
}

/// The users the broker accepts.
#[derive(Debug, Clone)]
pub struct Users {
    users: HashMap<String, PasswordHash>,
    /// RabbitMQ's `loopback_users`: users who may connect only from the
    /// host itself (`guest` by default, as in RabbitMQ).
    loopback_only: Vec<String>,
}

impl Default for Users {
    fn default() -> Self {
        Users {
            users: HashMap::new(),
            loopback_only: vec![GUEST.to_owned()],
        }
    }
}

/// RabbitMQ's default user.
pub const GUEST: &str = "guest";

impl Users {
    /// Replaces the users who may connect only from the host itself.
    pub fn set_loopback_only(&mut self, names: Vec<String>) {
        self.loopback_only = names;
    }

    /// Whether `user` may connect from `peer` (an `ip:port`, or
    /// `in-process` for a connection inside the broker's own process).
    pub fn may_connect_from(&self, user: &str, peer: &str) -> bool {
        if !self.is_loopback_only(user) {
            return true;
        }
        match peer.parse::<std::net::SocketAddr>() {
            Ok(addr) => addr.ip().to_canonical().is_loopback(),
            // Not a socket address: an in-process connection.
            Err(_) => true,
        }
    }

    /// Whether `user` may connect only from the host itself.
    pub fn is_loopback_only(&self, user: &str) -> bool {
        self.loopback_only.iter().any(|name| name == user)
    }

    /// Whether `guest` is the only user (for the warning when a listener
    /// beyond this host is open).
    pub fn only_guest(&self) -> bool {
        self.users.len() == 1 && self.users.contains_key(GUEST)
    }

    /// Adds or replaces a user.
    pub fn insert(&mut self, name: impl Into<String>, password: &str) {
        self.users.insert(name.into(), PasswordHash::new(password));
    }

    /// Adds or replaces a user whose password is given already hashed.
    pub fn insert_hashed(&mut self, name: impl Into<String>, hash: PasswordHash) {
        self.users.insert(name.into(), hash);
    }

    /// Every user and their stored hash (for listings).
    pub fn iter(&self) -> impl Iterator<Item = (&str, &PasswordHash)> {
        self.users.iter().map(|(name, hash)| (name.as_str(), hash))
    }

    /// Checks a SASL response for `mechanism`; the user name if it passes.
    pub fn authenticate(&self, mechanism: &[u8], response: &Bytes) -> Option<String> {
        let (user, password) = match mechanism {
            b"PLAIN" => parse_plain(response)?,
            b"AMQPLAIN" => parse_amqplain(response)?,
            _ => return None,
        };
        let name = std::str::from_utf8(&user).ok()?;
        self.users
            .get(name)
            .filter(|hash| hash.verify(&password))
            .map(|_| name.to_owned())
    }
}

/// PLAIN: `authzid \0 user \0 password`.
fn parse_plain(response: &[u8]) -> Option<(Vec<u8>, Vec<u8>)> {
    let mut parts = response.splitn(3, |&b| b == 0);
    let _authzid = parts.next()?;
    let user = parts.next()?;
    let password = parts.next()?;
    Some((user.to_vec(), password.to_vec()))
}

/// AMQPLAIN: a field table without its length prefix, with LOGIN and PASSWORD.
fn parse_amqplain(response: &Bytes) -> Option<(Vec<u8>, Vec<u8>)> {
    let mut framed = BytesMut::with_capacity(response.len() + 4);
    framed.extend_from_slice(&(response.len() as u32).to_be_bytes());
    framed.extend_from_slice(response);
    let table = FieldTable::decode(&framed.freeze()).ok()?;
    let text = |v: &FieldValue| v.as_bytes().map(<[u8]>::to_vec);
    Some((text(table.get("LOGIN")?)?, text(table.get("PASSWORD")?)?))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plain_and_amqplain() {
        let mut users = Users::default();
        users.insert("guest", "guest");
        assert_eq!(
            users.authenticate(b"PLAIN", &Bytes::from_static(b"\0guest\0guest")),
            Some("guest".into())
        );
        assert_eq!(
            users.authenticate(b"PLAIN", &Bytes::from_static(b"\0guest\0nope")),
            None
        );
        let amqplain = Bytes::from_static(
            b"\x05LOGINS\x00\x00\x00\x05guest\x08PASSWORDS\x00\x00\x00\x05guest",
        );
        assert_eq!(
            users.authenticate(b"AMQPLAIN", &amqplain),
            Some("guest".into())
        );
        assert_eq!(users.authenticate(b"EXTERNAL", &amqplain), None);
    }

    #[test]
    fn loopback_users_connect_only_from_the_host() {
        let mut users = Users::default();
        users.insert("guest", "guest");
        users.insert("robot", "pw");
        assert!(users.may_connect_from("guest", "127.0.0.1:5000"));
        assert!(users.may_connect_from("guest", "[::1]:5000"));
        assert!(users.may_connect_from("guest", "[::ffff:127.0.0.1]:5000"));
        assert!(users.may_connect_from("guest", "in-process"));
        assert!(!users.may_connect_from("guest", "192.168.1.20:5000"));
        assert!(!users.may_connect_from("guest", "[2001:db8::1]:5000"));
        assert!(users.may_connect_from("robot", "192.168.1.20:5000"));
        users.set_loopback_only(Vec::new());
        assert!(users.may_connect_from("guest", "192.168.1.20:5000"));
    }

    #[test]
    fn stored_form_round_trips() {
        let hash = PasswordHash::new("robot");
        let text = hash.to_hex();
        assert_eq!(text.len(), 72);
        let back = PasswordHash::from_hex(&text).unwrap();
        assert!(back.verify(b"robot"));
        assert!(PasswordHash::from_hex("zz").is_none());
        assert!(PasswordHash::from_hex(&text.replace(&text[..2], "xy")).is_none());
    }

    #[test]
    fn hashes_are_salted() {
        let a = PasswordHash::new("secret");
        assert!(a.verify(b"secret"));
        assert!(!a.verify(b"Secret"));
        assert_ne!(
            PasswordHash::with_salt([1; 4], "x"),
            PasswordHash::with_salt([2; 4], "x")
        );
    }
}
