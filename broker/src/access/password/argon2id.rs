//! The argon2id scheme (cargo feature `argon2`): new hashes with
//! RustCrypto's `argon2` and its default parameters, the PHC strings a
//! login may check (bounded costs), and the checks, in memory a hashing
//! thread keeps between them. Uses `argon2` and the parent's random source.

use argon2::password_hash::{PasswordHasher, PasswordVerifier, SaltString};
use argon2::{Argon2, Block};

/// The most memory an argon2id hash may ask each check for (64 MiB;
/// the default is 19 MiB): a hash from a file or an import cannot make a
/// login cost gigabytes.
const MAX_MEMORY_KIB: u32 = 64 * 1024;
/// The most passes it may ask for (the default is 2).
const MAX_PASSES: u32 = 8;
/// The most lanes it may ask for (the default is 1).
const MAX_LANES: u32 = 4;

/// The memory an argon2id check works in (19 MiB with the default
/// parameters), kept by a hashing thread from one check to the next while
/// checks keep coming. Allocated afresh per check, the C allocator keeps
/// many such blocks resident after a flood of checks; kept, a thread holds
/// one at a time.
#[derive(Default)]
pub struct HashMemory(Vec<Block>);

impl HashMemory {
    /// Gives the memory back (the thread has nothing more to check).
    pub fn release(&mut self) {
        self.0 = Vec::new();
    }

    /// `blocks` blocks of it, grown if needed.
    fn blocks(&mut self, blocks: usize) -> &mut [Block] {
        if self.0.len() < blocks {
            self.0.resize(blocks, Block::default());
        }
        &mut self.0[..blocks]
    }
}

/// A new PHC string for `password`, salted from the OS.
pub fn hash(password: &str) -> String {
    let mut salt = [0u8; 16];
    super::os_random(&mut salt);
    let salt = SaltString::encode_b64(&salt)
        .unwrap_or_else(|e| unreachable!("16 bytes are a valid salt: {e}"));
    Argon2::default()
        .hash_password(password.as_bytes(), &salt)
        .map(|hash| hash.to_string())
        // Only a parameter or output-size error can occur, and the
        // defaults have none.
        .unwrap_or_else(|e| unreachable!("argon2 with default parameters: {e}"))
}

/// Whether `stored` is an argon2id PHC string with a salt and a hash whose
/// costs a login may pay.
pub fn usable(stored: &str) -> bool {
    let Ok(parsed) = argon2::password_hash::PasswordHash::new(stored) else {
        return false;
    };
    let Ok(params) = argon2::Params::try_from(&parsed) else {
        return false;
    };
    let affordable = params.m_cost() <= MAX_MEMORY_KIB
        && params.t_cost() <= MAX_PASSES
        && params.p_cost() <= MAX_LANES;
    parsed.salt.is_some() && parsed.hash.is_some() && affordable
}

/// Whether `password` matches the PHC string `phc`.
pub fn verify(phc: &str, password: &[u8]) -> bool {
    argon2::password_hash::PasswordHash::new(phc)
        .is_ok_and(|parsed| Argon2::default().verify_password(password, &parsed).is_ok())
}

/// Whether `password` matches `phc`, the check working in `memory`.
pub fn verify_in(phc: &str, password: &[u8], memory: &mut HashMemory) -> bool {
    check_in(phc, password, memory).unwrap_or(false)
}

/// argon2id's check of `password` against the PHC string `phc`, in
/// `memory`; `None` if the string cannot be used.
fn check_in(phc: &str, password: &[u8], memory: &mut HashMemory) -> Option<bool> {
    let parsed = argon2::password_hash::PasswordHash::new(phc).ok()?;
    let expected = parsed.hash?;
    let params = argon2::Params::try_from(&parsed).ok()?;
    let version = match parsed.version {
        Some(version) => argon2::Version::try_from(version).ok()?,
        None => argon2::Version::default(),
    };
    let mut salt = [0u8; 64];
    let salt = parsed.salt?.decode_b64(&mut salt).ok()?;
    let blocks = params.block_count();
    let hasher = Argon2::new(argon2::Algorithm::Argon2id, version, params);
    let mut computed = vec![0u8; expected.len()];
    hasher
        .hash_password_into_with_memory(password, salt, &mut computed, memory.blocks(blocks))
        .ok()?;
    let differences = computed
        .iter()
        .zip(expected.as_bytes())
        .fold(0u8, |acc, (a, b)| acc | (a ^ b));
    Some(differences == 0)
}
