//! Certificates for the TLS tests, made with rcgen: a CA that signs
//! server certificates for localhost and client certificates (PEM, or
//! PKCS#12 for lapin, which takes client certificates only in that form),
//! and a directory for the PEM files that tools like Mosquitto's read.

use rcgen::{
    BasicConstraints, Certificate, CertificateParams, DnType, IsCa, KeyPair, KeyUsagePurpose,
};
use std::path::{Path, PathBuf};

/// A directory of PEM files of a test's own, removed at the end.
#[derive(Debug)]
pub struct PemFiles {
    dir: PathBuf,
}

impl PemFiles {
    /// A new, empty directory named after `name`.
    pub fn new(name: &str) -> PemFiles {
        let dir = std::env::temp_dir().join(crate::unique(&format!("leveret-pem-{name}")));
        std::fs::create_dir_all(&dir).expect("PEM directory");
        PemFiles { dir }
    }

    /// The directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Writes `text` to file `name` in it; its path.
    pub fn write(&self, name: &str, text: &str) -> PathBuf {
        let path = self.dir.join(name);
        std::fs::write(&path, text).expect("write a PEM file");
        path
    }

    /// A certificate signed by `ca` with `subject` (in that order) and its
    /// key, written as `STEM.pem` and `STEM.key`; their paths.
    pub fn signed_subject(
        &self,
        ca: &Authority,
        subject: &[(DnType, &str)],
        stem: &str,
    ) -> (PathBuf, PathBuf) {
        let (cert, key) = ca.sign_subject(subject, false);
        (
            self.write(&format!("{stem}.pem"), &cert.pem()),
            self.write(&format!("{stem}.key"), &key.serialize_pem()),
        )
    }

    /// A certificate for `common_name` signed by `ca` and its key (see
    /// [`PemFiles::signed_subject`]).
    pub fn signed(&self, ca: &Authority, common_name: &str) -> (PathBuf, PathBuf) {
        self.signed_subject(ca, &[(DnType::CommonName, common_name)], common_name)
    }
}

impl Drop for PemFiles {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// A certificate authority.
pub struct Authority {
    cert: Certificate,
    key: KeyPair,
}

impl std::fmt::Debug for Authority {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Authority").finish_non_exhaustive()
    }
}

impl Authority {
    /// A new CA named `name`.
    pub fn new(name: &str) -> Authority {
        let key = KeyPair::generate().expect("key");
        let mut params = CertificateParams::new(Vec::new()).expect("params");
        params.distinguished_name.push(DnType::CommonName, name);
        params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
        params.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
        let cert = params.self_signed(&key).expect("CA");
        Authority { cert, key }
    }

    /// Its certificate, PEM.
    pub fn pem(&self) -> String {
        self.cert.pem()
    }

    /// A certificate for `common_name` (with `localhost` as its DNS name),
    /// valid now or expired since 2021, and its key.
    pub fn sign(&self, common_name: &str, expired: bool) -> (Certificate, KeyPair) {
        self.sign_subject(&[(DnType::CommonName, common_name)], expired)
    }

    /// A certificate whose subject is `subject`, in that order (with
    /// `localhost` as its DNS name), valid now or expired since 2021, and
    /// its key.
    pub fn sign_subject(
        &self,
        subject: &[(DnType, &str)],
        expired: bool,
    ) -> (Certificate, KeyPair) {
        let key = KeyPair::generate().expect("key");
        let mut params = CertificateParams::new(vec!["localhost".to_owned()]).expect("params");
        params.distinguished_name = rcgen::DistinguishedName::new();
        for (kind, value) in subject {
            params.distinguished_name.push(kind.clone(), *value);
        }
        if expired {
            params.not_before = rcgen::date_time_ymd(2020, 1, 1);
            params.not_after = rcgen::date_time_ymd(2021, 1, 1);
        }
        let cert = params.signed_by(&key, &self.cert, &self.key).expect("sign");
        (cert, key)
    }

    /// A certificate for `common_name` with its key and this CA, as
    /// PKCS#12 protected by `password`.
    pub fn pkcs12(&self, common_name: &str, expired: bool, password: &str) -> Vec<u8> {
        let (cert, key) = self.sign(common_name, expired);
        let chain = [
            p12_keystore::Certificate::from_der(cert.der()).expect("cert"),
            p12_keystore::Certificate::from_der(self.cert.der()).expect("CA cert"),
        ];
        let entry = p12_keystore::PrivateKeyChain::new(key.serialize_der(), [1u8; 20], chain);
        let mut store = p12_keystore::KeyStore::new();
        store.add_entry(
            common_name,
            p12_keystore::KeyStoreEntry::PrivateKeyChain(entry),
        );
        store.writer(password).write().expect("PKCS#12")
    }
}
