//! Users and authentication: the users, their password hashes
//! (`password`) and tags, RabbitMQ's `loopback_users`, and the SASL mechanisms
//! PLAIN and AMQPLAIN. An argon2id check runs in the hashing pool
//! (`hash_pool`: a few threads of its own, keys served in turn), keyed by
//! source address and user, so neither the broker's threads nor a flood
//! of logins is held by it and a flood for one user from one source
//! cannot starve another; a login that passed is remembered (a keyed
//! SHA-256 of user, hash and password under a per-process secret), so
//! reconnecting with the same password costs microseconds and waits for
//! no pool. Failed logins are never remembered, and are answered late
//! when their source failed before (`login_backoff`). Uses `password`,
//! `hash_pool` and `login_backoff`, nothing else of the broker.

use crate::access::hash_pool::{HashPool, HashPoolStats};
use crate::access::login_backoff::{source_of, LoginBackoff};
use crate::access::password::{HashMemory, PasswordHash};
use bytes::{Bytes, BytesMut};
use leveret_protocol::{FieldTable, FieldValue};
use sha2::{Digest, Sha256};
use std::collections::HashMap;
use std::sync::{Arc, Mutex, RwLock};

/// Logins that passed an argon2id check, one per user; the pool that
/// checks the others, and the failures per source.
struct VerifiedLogins {
    secret: [u8; 32],
    // Held for one lookup or insert, never across an await. Shared with
    // the checks waiting in the pool.
    passed: Arc<Mutex<HashMap<String, [u8; 32]>>>,
    pool: HashPool,
    backoff: LoginBackoff,
}

impl std::fmt::Debug for VerifiedLogins {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("VerifiedLogins")
    }
}

impl VerifiedLogins {
    fn new() -> Self {
        let mut secret = [0u8; 32];
        crate::access::password::os_random(&mut secret);
        VerifiedLogins {
            secret,
            passed: Arc::new(Mutex::new(HashMap::new())),
            pool: HashPool::default(),
            backoff: LoginBackoff::default(),
        }
    }

    fn key(&self, user: &str, hash: &PasswordHash, password: &[u8]) -> [u8; 32] {
        let (stored, _) = hash.to_rabbitmq();
        Sha256::new()
            .chain_update(self.secret)
            .chain_update((user.len() as u64).to_be_bytes())
            .chain_update(user)
            .chain_update((stored.len() as u64).to_be_bytes())
            .chain_update(stored)
            .chain_update(password)
            .finalize()
            .into()
    }

    fn passed(&self, user: &str, key: &[u8; 32]) -> bool {
        passed(&self.passed, user, key)
    }

    fn remember(&self, user: &str, key: [u8; 32]) {
        let mut passed = self.passed.lock().unwrap_or_else(|e| e.into_inner());
        passed.insert(user.to_owned(), key);
    }
}

/// Whether `key` is the login remembered for `user` (compared in
/// constant time).
fn passed(passed: &Mutex<HashMap<String, [u8; 32]>>, user: &str, key: &[u8; 32]) -> bool {
    let passed = passed.lock().unwrap_or_else(|e| e.into_inner());
    passed
        .get(user)
        .is_some_and(|known| known.iter().zip(key).fold(0u8, |acc, (a, b)| acc | (a ^ b)) == 0)
}

/// One user: how their password is checked, and their tags.
#[derive(Debug, Clone, PartialEq)]
pub struct User {
    /// The stored password hash.
    pub password_hash: PasswordHash,
    /// RabbitMQ's user tags (`administrator`, `monitoring`, `management`,
    /// `policymaker`…): the broker keeps them; the management API decides
    /// from them what the user may see and do there.
    pub tags: Vec<String>,
}

impl User {
    /// A user with `password_hash` and no tags.
    pub fn new(password_hash: PasswordHash) -> Self {
        User {
            password_hash,
            tags: Vec::new(),
        }
    }
}

/// The users the broker accepts. Clones share the users: a change through
/// one is seen by all (the lock is held for one lookup or change, never
/// across an await).
#[derive(Debug, Clone)]
pub struct Users {
    users: Arc<RwLock<HashMap<String, User>>>,
    verified: Arc<VerifiedLogins>,
    /// RabbitMQ's `loopback_users`: users who may connect only from the
    /// host itself (`guest` by default, as in RabbitMQ).
    loopback_only: Vec<String>,
}

impl Default for Users {
    fn default() -> Self {
        Users {
            users: Arc::new(RwLock::new(HashMap::new())),
            verified: Arc::new(VerifiedLogins::new()),
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

    fn read(&self) -> std::sync::RwLockReadGuard<'_, HashMap<String, User>> {
        self.users.read().unwrap_or_else(|e| e.into_inner())
    }

    fn write(&self) -> std::sync::RwLockWriteGuard<'_, HashMap<String, User>> {
        self.users.write().unwrap_or_else(|e| e.into_inner())
    }

    /// Whether `guest` is the only user (for the warning when a listener
    /// beyond this host is open).
    pub fn only_guest(&self) -> bool {
        let users = self.read();
        users.len() == 1 && users.contains_key(GUEST)
    }

    /// Whether `name` is a user.
    pub fn contains(&self, name: &str) -> bool {
        self.read().contains_key(name)
    }

    /// A user, if there is one by that name.
    pub fn get(&self, name: &str) -> Option<User> {
        self.read().get(name).cloned()
    }

    /// Adds or replaces a user; true if they are new.
    pub fn put(&self, name: impl Into<String>, user: User) -> bool {
        self.write().insert(name.into(), user).is_none()
    }

    /// Removes a user; true if there was one.
    pub fn remove(&self, name: &str) -> bool {
        self.write().remove(name).is_some()
    }

    /// Every user, sorted by name.
    pub fn list(&self) -> Vec<(String, User)> {
        let mut users: Vec<(String, User)> = self
            .read()
            .iter()
            .map(|(name, user)| (name.clone(), user.clone()))
            .collect();
        users.sort_by(|a, b| a.0.cmp(&b.0));
        users
    }

    /// Checks a SASL response for `mechanism` from `peer` (an `ip:port`,
    /// or `in-process`); the user name if it passes.
    pub async fn authenticate(
        &self,
        mechanism: &[u8],
        response: &Bytes,
        peer: &str,
    ) -> Option<String> {
        let credentials = match mechanism {
            b"PLAIN" => parse_plain(response),
            b"AMQPLAIN" => parse_amqplain(response),
            _ => None,
        };
        let named = credentials
            .and_then(|(user, password)| String::from_utf8(user).ok().map(|name| (name, password)));
        let Some((name, password)) = named else {
            self.failed(&source_of(peer)).await;
            return None;
        };
        self.check_password(&name, &password, peer)
            .await
            .then_some(name)
    }

    /// Whether `password` is `user`'s; `peer` is where the attempt comes
    /// from (an `ip:port`, or any other text naming the way in). A
    /// failure is answered late when that source failed before.
    pub async fn check_password(&self, user: &str, password: &[u8], peer: &str) -> bool {
        let source = source_of(peer);
        let passed = self.verify(user, password, &source).await;
        if !passed {
            self.failed(&source).await;
        }
        passed
    }

    /// Waits before a failure from `source` is answered, as long as its
    /// recent failures ask.
    async fn failed(&self, source: &str) {
        let delay = self.verified.backoff.failed(source);
        tokio::time::sleep(delay).await;
    }

    async fn verify(&self, user: &str, password: &[u8], source: &str) -> bool {
        let Some(User {
            password_hash: hash,
            ..
        }) = self.get(user)
        else {
            return false;
        };
        if !hash.is_slow() {
            return hash.verify(password);
        }
        let key = self.verified.key(user, &hash, password);
        if self.verified.passed(user, &key) {
            return true;
        }
        // Many connections of one user arriving together wait in one
        // queue; the first one's check serves the rest.
        let remembered = Arc::clone(&self.verified.passed);
        let name = user.to_owned();
        let candidate = password.to_vec();
        let check = move |memory: &mut HashMemory| {
            passed(&remembered, &name, &key) || hash.verify_in(&candidate, memory)
        };
        // Keyed by source and user: NUL cannot be in an address.
        let queue = format!("{source}\0{user}");
        let answer = match self.verified.pool.submit(&queue, check) {
            Ok(answer) => answer,
            Err(refused) => {
                tracing::warn!(%source, %user, reason = %refused, "password check refused");
                return false;
            }
        };
        // Dropping `answer` (the connection went away) withdraws a check
        // that has not started.
        let Ok(verified) = answer.await else {
            tracing::warn!(%source, %user, "password check refused: pushed out by checks of other users or sources");
            return false;
        };
        if verified {
            self.verified.remember(user, key);
        }
        verified
    }

    /// What the hashing pool has done (threads, checks running at most).
    pub fn hash_pool_stats(&self) -> HashPoolStats {
        self.verified.pool.stats()
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

/// The user name a PLAIN or AMQPLAIN response gives, whether or not its
/// password is right: for the log line of a refused login.
pub(crate) fn claimed_user(mechanism: &[u8], response: &Bytes) -> Option<Vec<u8>> {
    let (user, _password) = match mechanism {
        b"PLAIN" => parse_plain(response)?,
        b"AMQPLAIN" => parse_amqplain(response)?,
        _ => return None,
    };
    Some(user)
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

    const PEER: &str = "127.0.0.1:5000";

    #[tokio::test]
    async fn plain_and_amqplain() {
        let users = Users::default();
        users.put("guest", User::new(PasswordHash::new("guest")));
        assert_eq!(
            users
                .authenticate(b"PLAIN", &Bytes::from_static(b"\0guest\0guest"), PEER)
                .await,
            Some("guest".into())
        );
        assert_eq!(
            users
                .authenticate(b"PLAIN", &Bytes::from_static(b"\0guest\0nope"), PEER)
                .await,
            None
        );
        let amqplain = Bytes::from_static(
            b"\x05LOGINS\x00\x00\x00\x05guest\x08PASSWORDS\x00\x00\x00\x05guest",
        );
        assert_eq!(
            users.authenticate(b"AMQPLAIN", &amqplain, PEER).await,
            Some("guest".into())
        );
        assert_eq!(users.authenticate(b"EXTERNAL", &amqplain, PEER).await, None);
    }

    /// A login that passed argon2id is remembered (keyed by the password:
    /// another password is checked in full); failures never are, and the
    /// blocking checks give their slots back.
    #[cfg(feature = "argon2")]
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn argon2id_logins_are_checked_off_thread_and_remembered_only_when_right() {
        let users = Users::default();
        users.put("robot", User::new(PasswordHash::new("pw")));
        let wrong: Vec<_> = (0..8)
            .map(|i| {
                let users = users.clone();
                tokio::spawn(async move {
                    users
                        .check_password("robot", format!("no{i}").as_bytes(), PEER)
                        .await
                })
            })
            .collect();
        for attempt in wrong {
            assert!(!attempt.await.unwrap());
        }
        assert!(
            users.verified.passed.lock().unwrap().is_empty(),
            "failures are not remembered"
        );
        let stats = users.hash_pool_stats();
        assert_eq!((stats.running, stats.waiting, stats.finished), (0, 0, 8));
        assert!(stats.peak_running <= crate::access::hash_pool::HASH_THREADS);
        assert!(users.check_password("robot", b"pw", PEER).await);
        let hash = users.get("robot").unwrap().password_hash;
        let key = users.verified.key("robot", &hash, b"pw");
        assert!(users.verified.passed("robot", &key));
        assert!(!users
            .verified
            .passed("robot", &users.verified.key("robot", &hash, b"pw2")));
        assert!(users.check_password("robot", b"pw", PEER).await);
        assert!(!users.check_password("robot", b"pw2", PEER).await);
        assert!(!users.check_password("nobody", b"pw", PEER).await);
    }

    /// A flood of wrong passwords for one user from 127.0.0.1 holds
    /// neither a known login (remembered: no hashing) nor another user's
    /// first login from the same address (its own queue, served in
    /// turn).
    #[cfg(feature = "argon2")]
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_flood_for_one_user_holds_up_no_other_login() {
        let users = Users::default();
        users.put("guest", User::new(PasswordHash::new("guest")));
        users.put("robot", User::new(PasswordHash::new("pw")));
        assert!(users.check_password("guest", b"guest", PEER).await);
        let flood: Vec<_> = (0..200)
            .map(|i| {
                let users = users.clone();
                tokio::spawn(async move {
                    let wrong = format!("no{i}");
                    users
                        .check_password("guest", wrong.as_bytes(), "127.0.0.1:6000")
                        .await
                })
            })
            .collect();
        let hang = tokio::time::Instant::now() + std::time::Duration::from_secs(20);
        while users.hash_pool_stats().waiting < 100 {
            assert!(tokio::time::Instant::now() < hang, "the flood queued");
            tokio::task::yield_now().await;
        }
        let before = users.hash_pool_stats();
        assert!(
            users
                .check_password("guest", b"guest", "127.0.0.1:6001")
                .await
        );
        assert!(users.check_password("robot", b"pw", "127.0.0.1:6002").await);
        let after = users.hash_pool_stats();
        assert!(
            after.finished - before.finished <= 4 * crate::access::hash_pool::HASH_THREADS,
            "served in turn, not behind the flood: {before:?} then {after:?}"
        );
        assert!(after.peak_running <= crate::access::hash_pool::HASH_THREADS);
        for attempt in &flood {
            attempt.abort();
        }
    }

    #[test]
    fn loopback_users_connect_only_from_the_host() {
        let mut users = Users::default();
        users.put("guest", User::new(PasswordHash::new("guest")));
        users.put("robot", User::new(PasswordHash::new("pw")));
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
}
