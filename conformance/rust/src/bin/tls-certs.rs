//! Writes the TLS suite's certificates into a directory (rcgen):
//! `ca.pem`; `server.pem` + `server.key` for localhost, signed by it;
//! `client.pem` + `client.key` + `client.p12` (password `pw`) for the user
//! `robot-7`, signed by it; `rogue-ca.pem`, and `rogue.pem` + `rogue.key` +
//! `rogue.p12`, a client certificate for `robot-7` signed by the rogue CA.
//!
//!     tls-certs DIR

use rcgen::{
    BasicConstraints, Certificate, CertificateParams, DnType, IsCa, KeyPair, KeyUsagePurpose,
};
use std::path::Path;

struct Authority {
    cert: Certificate,
    key: KeyPair,
}

fn authority(name: &str) -> Authority {
    let key = KeyPair::generate().expect("key");
    let mut params = CertificateParams::new(Vec::new()).expect("params");
    params.distinguished_name.push(DnType::CommonName, name);
    params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    params.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
    let cert = params.self_signed(&key).expect("CA");
    Authority { cert, key }
}

fn leaf(ca: &Authority, common_name: &str, dns: &[&str]) -> (Certificate, KeyPair) {
    let key = KeyPair::generate().expect("key");
    let mut params = CertificateParams::new(dns.iter().map(|d| d.to_string()).collect::<Vec<_>>())
        .expect("params");
    params
        .distinguished_name
        .push(DnType::CommonName, common_name);
    let cert = params.signed_by(&key, &ca.cert, &ca.key).expect("sign");
    (cert, key)
}

fn write(dir: &Path, name: &str, bytes: impl AsRef<[u8]>) {
    std::fs::write(dir.join(name), bytes).expect("write");
}

fn client(dir: &Path, ca: &Authority, stem: &str) {
    let (cert, key) = leaf(ca, "robot-7", &[]);
    write(dir, &format!("{stem}.pem"), cert.pem());
    write(dir, &format!("{stem}.key"), key.serialize_pem());
    let chain = [
        p12_keystore::Certificate::from_der(cert.der()).expect("cert"),
        p12_keystore::Certificate::from_der(ca.cert.der()).expect("CA"),
    ];
    let entry = p12_keystore::PrivateKeyChain::new(key.serialize_der(), [1u8; 20], chain);
    let mut store = p12_keystore::KeyStore::new();
    store.add_entry(
        "robot-7",
        p12_keystore::KeyStoreEntry::PrivateKeyChain(entry),
    );
    write(
        dir,
        &format!("{stem}.p12"),
        store.writer("pw").write().expect("PKCS#12"),
    );
}

fn main() {
    let dir = std::env::args().nth(1).expect("usage: tls-certs DIR");
    let dir = Path::new(&dir);
    std::fs::create_dir_all(dir).expect("dir");
    let ca = authority("leveret-conformance-ca");
    write(dir, "ca.pem", ca.cert.pem());
    let (server, key) = leaf(&ca, "localhost", &["localhost"]);
    write(dir, "server.pem", server.pem());
    write(dir, "server.key", key.serialize_pem());
    client(dir, &ca, "client");
    let rogue = authority("rogue-ca");
    write(dir, "rogue-ca.pem", rogue.cert.pem());
    client(dir, &rogue, "rogue");
}
