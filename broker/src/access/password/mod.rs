//! Password hashes. New ones are argon2id (RustCrypto's `argon2` with its
//! default parameters, a salt from the OS random source), in the PHC
//! string form (`$argon2id$v=19$m=…`): `argon2id` owns that scheme, behind
//! the `argon2` cargo feature (default). A build without it hashes new
//! passwords with RabbitMQ's salted SHA-256 (its default scheme) and
//! refuses argon2id hashes where it reads one (config, definitions, the
//! store), saying the build cannot check them. RabbitMQ's salted SHA-256
//! and SHA-512 hashes (`rabbit_password_hashing_sha256` / `_sha512`:
//! base64 of a 4-byte salt and the digest of salt + password) are accepted
//! as RabbitMQ exports them, so users moved from RabbitMQ log in
//! unchanged; Leveret's earlier form (72 hex digits: salt and SHA-256) is
//! still read. An empty `password_hash` is, as in RabbitMQ, a user who
//! cannot log in with a password at all.
//!
//! argon2id costs tens of milliseconds and megabytes per check by design:
//! `auth` runs it off the broker's threads (in `hash_pool`, whose threads
//! keep the check's memory in a [`HashMemory`] between checks) and
//! remembers successful logins. Uses `getrandom`, `sha2`, `base64` and,
//! with the feature, `argon2`; nothing else of the broker.

#[cfg(feature = "argon2")]
mod argon2id;

#[cfg(feature = "argon2")]
pub use argon2id::HashMemory;
use base64::Engine;
use sha2::{Digest, Sha256, Sha512};

/// Where a hashing thread keeps an argon2id check's memory; a build
/// without argon2id has no slow checks, so nothing to keep.
#[cfg(not(feature = "argon2"))]
#[derive(Default)]
pub struct HashMemory(());

#[cfg(not(feature = "argon2"))]
impl HashMemory {
    /// Gives the memory back (there is none).
    pub fn release(&mut self) {}
}

/// RabbitMQ's name for its salted SHA-256 scheme (its default).
pub const RABBIT_SHA256: &str = "rabbit_password_hashing_sha256";
/// RabbitMQ's name for its salted SHA-512 scheme.
pub const RABBIT_SHA512: &str = "rabbit_password_hashing_sha512";
/// The `hashing_algorithm` Leveret exports argon2id hashes under (RabbitMQ
/// has no such module: it cannot import these users).
pub const LEVERET_ARGON2ID: &str = "leveret_password_hashing_argon2id";

/// A stored password.
#[derive(Clone, PartialEq, Eq)]
pub struct PasswordHash(Scheme);

#[derive(Clone, PartialEq, Eq)]
enum Scheme {
    /// The PHC string.
    #[cfg(feature = "argon2")]
    Argon2id(String),
    /// RabbitMQ's scheme: a 4-byte salt and SHA-256 or SHA-512 of salt +
    /// password.
    Salted {
        algorithm: Salted,
        salt: [u8; 4],
        digest: Vec<u8>,
    },
    /// No password: RabbitMQ's empty `password_hash` (a user who
    /// authenticates some other way, or not at all). No password matches.
    None,
}

#[derive(Clone, Copy, PartialEq, Eq)]
enum Salted {
    Sha256,
    Sha512,
}

impl Salted {
    fn digest(self, salt: &[u8], password: &[u8]) -> Vec<u8> {
        match self {
            Salted::Sha256 => Sha256::new()
                .chain_update(salt)
                .chain_update(password)
                .finalize()
                .to_vec(),
            Salted::Sha512 => Sha512::new()
                .chain_update(salt)
                .chain_update(password)
                .finalize()
                .to_vec(),
        }
    }

    fn len(self) -> usize {
        match self {
            Salted::Sha256 => 32,
            Salted::Sha512 => 64,
        }
    }

    fn name(self) -> &'static str {
        match self {
            Salted::Sha256 => RABBIT_SHA256,
            Salted::Sha512 => RABBIT_SHA512,
        }
    }
}

impl std::fmt::Debug for PasswordHash {
    // Never prints the hash itself.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let scheme = match &self.0 {
            #[cfg(feature = "argon2")]
            Scheme::Argon2id(_) => "argon2id",
            Scheme::Salted { algorithm, .. } => algorithm.name(),
            Scheme::None => "none",
        };
        write!(f, "PasswordHash({scheme})")
    }
}

impl PasswordHash {
    /// Hashes `password` with argon2id and a fresh salt from the OS.
    #[cfg(feature = "argon2")]
    pub fn new(password: &str) -> Self {
        PasswordHash(Scheme::Argon2id(argon2id::hash(password)))
    }

    /// Hashes `password` with RabbitMQ's default scheme (salted SHA-256)
    /// and a fresh salt from the OS: this build has no argon2id.
    #[cfg(not(feature = "argon2"))]
    pub fn new(password: &str) -> Self {
        let mut salt = [0u8; 4];
        os_random(&mut salt);
        let digest = Salted::Sha256.digest(&salt, password.as_bytes());
        PasswordHash(Scheme::Salted {
            algorithm: Salted::Sha256,
            salt,
            digest,
        })
    }

    /// Reads a stored hash: an argon2id PHC string, or Leveret's earlier
    /// 72-hex-digit SHA-256 form. An argon2id hash costlier than a login
    /// may be, or in a build without argon2id, is `None`.
    pub fn parse(stored: &str) -> Option<Self> {
        let stored = stored.trim();
        if stored.starts_with("$argon2id$") {
            #[cfg(feature = "argon2")]
            return argon2id::usable(stored)
                .then(|| PasswordHash(Scheme::Argon2id(stored.to_owned())));
            #[cfg(not(feature = "argon2"))]
            return None;
        }
        if stored.len() != 72 || !stored.is_ascii() {
            return None;
        }
        let bytes = (0..36)
            .map(|i| u8::from_str_radix(&stored[2 * i..2 * i + 2], 16).ok())
            .collect::<Option<Vec<u8>>>()?;
        Self::salted(Salted::Sha256, &bytes)
    }

    /// Reads RabbitMQ's exported form: `password_hash` (base64) and its
    /// `hashing_algorithm`; argon2id hashes Leveret exported come back too.
    /// An empty `password_hash` is no password (RabbitMQ reads it so with
    /// any of its algorithms).
    pub fn from_rabbitmq(password_hash: &str, hashing_algorithm: &str) -> Option<Self> {
        if password_hash.trim().is_empty()
            && [RABBIT_SHA256, RABBIT_SHA512, LEVERET_ARGON2ID].contains(&hashing_algorithm)
        {
            return Some(PasswordHash(Scheme::None));
        }
        let algorithm = match hashing_algorithm {
            RABBIT_SHA256 => Salted::Sha256,
            RABBIT_SHA512 => Salted::Sha512,
            LEVERET_ARGON2ID => return Self::parse(password_hash).filter(Self::is_slow),
            _ => return None,
        };
        let bytes = base64::engine::general_purpose::STANDARD
            .decode(password_hash.trim())
            .ok()?;
        Self::salted(algorithm, &bytes)
    }

    fn salted(algorithm: Salted, bytes: &[u8]) -> Option<Self> {
        if bytes.len() != 4 + algorithm.len() {
            return None;
        }
        let (salt, digest) = bytes.split_at(4);
        Some(PasswordHash(Scheme::Salted {
            algorithm,
            salt: salt.try_into().ok()?,
            digest: digest.to_vec(),
        }))
    }

    /// The form RabbitMQ's definitions use: `(password_hash,
    /// hashing_algorithm)`.
    pub fn to_rabbitmq(&self) -> (String, &'static str) {
        match &self.0 {
            #[cfg(feature = "argon2")]
            Scheme::Argon2id(phc) => (phc.clone(), LEVERET_ARGON2ID),
            Scheme::Salted {
                algorithm,
                salt,
                digest,
            } => {
                let mut bytes = salt.to_vec();
                bytes.extend_from_slice(digest);
                (
                    base64::engine::general_purpose::STANDARD.encode(bytes),
                    algorithm.name(),
                )
            }
            Scheme::None => (String::new(), RABBIT_SHA256),
        }
    }

    /// The form the config file's `password-hash` takes for an argon2id
    /// hash (its PHC string); `None` for RabbitMQ's schemes, which go there
    /// as `to_rabbitmq` gives them, with `hashing-algorithm`.
    pub fn to_phc(&self) -> Option<&str> {
        match &self.0 {
            #[cfg(feature = "argon2")]
            Scheme::Argon2id(phc) => Some(phc),
            Scheme::Salted { .. } | Scheme::None => None,
        }
    }

    /// Whether checking a password costs argon2id's time and memory.
    pub fn is_slow(&self) -> bool {
        match self.0 {
            #[cfg(feature = "argon2")]
            Scheme::Argon2id(_) => true,
            Scheme::Salted { .. } | Scheme::None => false,
        }
    }

    /// Whether `password` matches (in constant time), an argon2id check
    /// working in `memory`.
    pub fn verify_in(&self, password: &[u8], memory: &mut HashMemory) -> bool {
        match &self.0 {
            #[cfg(feature = "argon2")]
            Scheme::Argon2id(phc) => argon2id::verify_in(phc, password, memory),
            Scheme::Salted { .. } | Scheme::None => {
                let _ = memory;
                self.verify(password)
            }
        }
    }

    /// Whether `password` matches (in constant time).
    pub fn verify(&self, password: &[u8]) -> bool {
        match &self.0 {
            #[cfg(feature = "argon2")]
            Scheme::Argon2id(phc) => argon2id::verify(phc, password),
            Scheme::Salted {
                algorithm,
                salt,
                digest,
            } => {
                let actual = algorithm.digest(salt, password);
                actual.len() == digest.len()
                    && actual
                        .iter()
                        .zip(digest)
                        .fold(0u8, |acc, (a, b)| acc | (a ^ b))
                        == 0
            }
            Scheme::None => false,
        }
    }
}

/// Fills `bytes` from the OS random source (`getrandom(2)`).
pub fn os_random(bytes: &mut [u8]) {
    // Fails only where the OS has no random source at all, which no
    // supported system lacks; a broker there cannot make salts or keys.
    getrandom::getrandom(bytes).expect("the OS random source");
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    #[cfg(feature = "argon2")]
    fn new_hashes_are_argon2id_salted_from_the_os_and_round_trip() {
        let a = PasswordHash::new("secret");
        let b = PasswordHash::new("secret");
        assert_ne!(a, b, "fresh salts");
        let phc = a.to_phc().expect("argon2id");
        assert!(phc.starts_with("$argon2id$v=19$"), "{phc}");
        assert!(a.verify(b"secret"));
        assert!(!a.verify(b"Secret"));
        let back = PasswordHash::parse(phc).expect("parses");
        assert!(back.verify(b"secret"));
        // The same answers in memory kept from one check to the next.
        let mut memory = HashMemory::default();
        for _ in 0..2 {
            assert!(a.verify_in(b"secret", &mut memory));
            assert!(!a.verify_in(b"Secret", &mut memory));
        }
        memory.release();
        assert!(b.verify_in(b"secret", &mut memory));
        let (exported, algorithm) = a.to_rabbitmq();
        assert_eq!(algorithm, LEVERET_ARGON2ID);
        assert!(PasswordHash::from_rabbitmq(&exported, algorithm)
            .expect("imports")
            .verify(b"secret"));
        assert_eq!(format!("{a:?}"), "PasswordHash(argon2id)");
    }

    /// Hashes made by RabbitMQ 3.10 itself (`rabbitmqctl add_user robot256
    /// robot-pw`, the same for robot512 with `password_hashing_module` set
    /// to `rabbit_password_hashing_sha512`, then `export_definitions`).
    #[test]
    fn rabbitmq_exported_hashes_log_in_unchanged() {
        for (exported, algorithm) in [
            ("XrbDVjlDKoAec+dZ1vISo+jt5TVEqQvMa8euInsOyfsIm1Ys", RABBIT_SHA256),
            (
                "QAJWCkh0XzlKuSwlxX7hzyjZmn6as792tFARsbbDNmV8vzgtI31i5J24yPZQLbAvHYllEK9xcKzusoOUeakD4AfG74E=",
                RABBIT_SHA512,
            ),
        ] {
            let hash = PasswordHash::from_rabbitmq(exported, algorithm).expect("imports");
            assert!(hash.verify(b"robot-pw"), "{algorithm}");
            assert!(!hash.verify(b"robot-pW"), "{algorithm}");
            assert!(!hash.is_slow());
            assert_eq!(hash.to_rabbitmq(), (exported.to_owned(), algorithm));
        }
        // RabbitMQ's guest/guest.
        let guest = "ryEPfAes34E9ktgNmN0qbYVWyPeURRbjxMcQf9tVwj2qap6R";
        assert!(PasswordHash::from_rabbitmq(guest, RABBIT_SHA256)
            .expect("imports")
            .verify(b"guest"));
        assert!(PasswordHash::from_rabbitmq("c2hvcnQ=", RABBIT_SHA256).is_none());
        assert!(PasswordHash::from_rabbitmq("x", "rabbit_password_hashing_md5").is_none());
    }

    /// RabbitMQ's empty `password_hash`: a user no password logs in as,
    /// exported back empty.
    #[test]
    fn an_empty_hash_is_no_password() {
        for algorithm in [RABBIT_SHA256, RABBIT_SHA512, LEVERET_ARGON2ID] {
            let none = PasswordHash::from_rabbitmq("", algorithm).expect("no password");
            assert!(!none.verify(b"") && !none.verify(b"guest"));
            assert_eq!(none.to_rabbitmq(), (String::new(), RABBIT_SHA256));
            assert_eq!(none.to_phc(), None);
            assert!(!none.is_slow());
        }
        assert!(PasswordHash::from_rabbitmq("", "rabbit_password_hashing_md5").is_none());
    }

    #[test]
    fn the_earlier_hex_form_is_still_read() {
        let salt = [1, 2, 3, 4];
        let digest = Salted::Sha256.digest(&salt, b"old");
        let hex: String = salt
            .iter()
            .chain(digest.iter())
            .map(|b| format!("{b:02x}"))
            .collect();
        assert!(PasswordHash::parse(&hex).expect("hex").verify(b"old"));
        assert!(PasswordHash::parse("zz").is_none());
        assert!(PasswordHash::parse("$argon2id$garbage").is_none());
    }

    #[test]
    #[cfg(not(feature = "argon2"))]
    fn without_argon2id_new_hashes_are_rabbitmqs_salted_sha256_and_argon2id_is_refused() {
        let a = PasswordHash::new("secret");
        assert_ne!(a, PasswordHash::new("secret"), "fresh salts");
        assert!(a.verify(b"secret") && !a.verify(b"Secret") && !a.is_slow());
        assert_eq!(a.to_rabbitmq().1, RABBIT_SHA256);
        let phc = "$argon2id$v=19$m=19456,t=2,p=1$c2FsdHNhbHQ$aGFzaGhhc2hoYXNoaGFzaGhhc2hoYXNoaGFzaGhhc2g";
        assert!(PasswordHash::parse(phc).is_none());
        assert!(PasswordHash::from_rabbitmq(phc, LEVERET_ARGON2ID).is_none());
    }

    #[test]
    #[cfg(feature = "argon2")]
    fn argon2id_hashes_costlier_than_a_login_may_be_are_refused() {
        let phc = PasswordHash::new("x").to_phc().unwrap().to_owned();
        let greedy = phc.replace("m=19456", "m=4194304");
        assert_ne!(greedy, phc);
        assert!(PasswordHash::parse(&greedy).is_none());
        let slow = phc.replace("t=2", "t=1000");
        assert!(PasswordHash::parse(&slow).is_none());
    }
}
