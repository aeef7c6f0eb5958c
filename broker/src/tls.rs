//! TLS for AMQP listeners, as RabbitMQ's `listeners.ssl` with its
//! `ssl_options`: a certificate chain and key from PEM files, and
//! optionally client certificates verified against a CA bundle
//! (`verify_peer`, with or without `fail_if_no_peer_cert`). A verified
//! client certificate's common name is the identity SASL EXTERNAL logs in
//! as (RabbitMQ's `rabbitmq_auth_mechanism_ssl` with
//! `ssl_cert_login_from = common_name`).
//!
//! [`TlsContext::reload`] re-reads the files: connections accepted after it
//! use the new certificates, open ones keep theirs, and files that do not
//! load leave the old configuration in place. rustls on the ring provider;
//! the handshake runs on the connection's own task under the handshake
//! timeout. Uses nothing else of the broker.

use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use rustls::server::WebPkiClientVerifier;
use rustls::{RootCertStore, ServerConfig};
use std::path::{Path, PathBuf};
use std::sync::{Arc, RwLock};

/// Whether and how client certificates are checked.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum PeerVerification {
    /// No client certificate is asked for (RabbitMQ's `verify_none`).
    #[default]
    None,
    /// A client certificate is asked for and, when given, must be signed
    /// by the CA bundle; clients without one are let in (`verify_peer`).
    Optional,
    /// Every client must give a certificate signed by the CA bundle
    /// (`verify_peer` with `fail_if_no_peer_cert = true`).
    Required,
}

/// What a TLS listener serves with (RabbitMQ's `ssl_options`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TlsOptions {
    /// The certificate chain, PEM, leaf first (`certfile`).
    pub certfile: PathBuf,
    /// Its private key, PEM: PKCS#8, PKCS#1 or SEC1 (`keyfile`).
    pub keyfile: PathBuf,
    /// CA certificates client certificates are checked against, PEM
    /// (`cacertfile`); needed unless `verify` is [`PeerVerification::None`].
    pub cacertfile: Option<PathBuf>,
    /// Client certificate checking.
    pub verify: PeerVerification,
}

/// Why a TLS configuration cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    /// A file cannot be read or holds no usable PEM item.
    #[error("{path}: {reason}")]
    File {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// TLS listeners without TLS options, or a reload without TLS.
    #[error("no TLS certificate and key are configured")]
    NoOptions,
    /// Client verification was asked for without a CA bundle.
    #[error("verifying client certificates needs a cacertfile")]
    NoCaBundle,
    /// rustls refused the certificates, the key or the CA bundle.
    #[error("{0}")]
    Rustls(String),
}

fn file_error(path: &Path, reason: impl ToString) -> TlsError {
    TlsError::File {
        path: path.to_owned(),
        reason: reason.to_string(),
    }
}

fn certificates(path: &Path) -> Result<Vec<CertificateDer<'static>>, TlsError> {
    let certs = CertificateDer::pem_file_iter(path)
        .map_err(|e| file_error(path, e))?
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| file_error(path, e))?;
    if certs.is_empty() {
        return Err(file_error(path, "no PEM certificate"));
    }
    Ok(certs)
}

fn server_config(options: &TlsOptions) -> Result<ServerConfig, TlsError> {
    let chain = certificates(&options.certfile)?;
    let key = PrivateKeyDer::from_pem_file(&options.keyfile)
        .map_err(|e| file_error(&options.keyfile, e))?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let builder = ServerConfig::builder_with_provider(Arc::clone(&provider))
        .with_safe_default_protocol_versions()
        .map_err(|e| TlsError::Rustls(e.to_string()))?;
    let builder = match options.verify {
        PeerVerification::None => builder.with_no_client_auth(),
        verify => {
            let ca = options.cacertfile.as_ref().ok_or(TlsError::NoCaBundle)?;
            let mut roots = RootCertStore::empty();
            for cert in certificates(ca)? {
                roots.add(cert).map_err(|e| file_error(ca, e))?;
            }
            let verifier = WebPkiClientVerifier::builder_with_provider(Arc::new(roots), provider);
            let verifier = if verify == PeerVerification::Optional {
                verifier.allow_unauthenticated()
            } else {
                verifier
            };
            let verifier = verifier
                .build()
                .map_err(|e| TlsError::Rustls(e.to_string()))?;
            builder.with_client_cert_verifier(verifier)
        }
    };
    builder
        .with_single_cert(chain, key)
        .map_err(|e| TlsError::Rustls(e.to_string()))
}

/// A TLS listener's configuration, reloadable while the broker runs.
#[derive(Debug)]
pub struct TlsContext {
    options: TlsOptions,
    current: RwLock<Arc<ServerConfig>>,
}

impl TlsContext {
    /// Loads the files `options` names.
    pub fn load(options: TlsOptions) -> Result<Self, TlsError> {
        let config = server_config(&options)?;
        Ok(TlsContext {
            options,
            current: RwLock::new(Arc::new(config)),
        })
    }

    /// Re-reads the files; on an error the configuration in use stays.
    pub fn reload(&self) -> Result<(), TlsError> {
        let config = Arc::new(server_config(&self.options)?);
        *self.current.write().unwrap_or_else(|e| e.into_inner()) = config;
        Ok(())
    }

    /// An acceptor with the current configuration.
    pub fn acceptor(&self) -> tokio_rustls::TlsAcceptor {
        let config = Arc::clone(&self.current.read().unwrap_or_else(|e| e.into_inner()));
        tokio_rustls::TlsAcceptor::from(config)
    }
}

/// The common name of a (verified) client certificate, the identity SASL
/// EXTERNAL logs in as.
/// When each certificate in the PEM file at `path` expires (its
/// `notAfter`), in seconds since the Unix epoch, in the file's order: what
/// RabbitMQ's `certificate-expiration` health check looks at.
pub fn certificate_expiry(path: &Path) -> Result<Vec<i64>, TlsError> {
    certificates(path)?
        .iter()
        .map(|certificate| {
            let (_, parsed) = x509_parser::parse_x509_certificate(certificate.as_ref())
                .map_err(|e| file_error(path, e))?;
            Ok(parsed.validity().not_after.timestamp())
        })
        .collect()
}

pub fn common_name(certificate: &CertificateDer<'_>) -> Option<String> {
    let (_, parsed) = x509_parser::parse_x509_certificate(certificate.as_ref()).ok()?;
    let name = parsed
        .subject()
        .iter_common_name()
        .next()?
        .as_str()
        .ok()?
        .to_owned();
    Some(name)
}

#[cfg(feature = "mqtt")]
/// A certificate's subject DN as RabbitMQ writes it (`rabbit_cert_info`,
/// RFC 4514): the RDNs last first, joined by `,` (a multi-valued RDN's
/// values by `+`), short attribute names (`CN`, `O`, `OU`, ...) or the
/// dotted OID, values escaped as RabbitMQ escapes them. What its
/// `ssl_cert_login_from = distinguished_name` login name and the
/// `mqtt_default_vhosts` mapping's keys are. `None` for a value that is
/// not a string.
pub fn subject(certificate: &CertificateDer<'_>) -> Option<String> {
    let (_, parsed) = x509_parser::parse_x509_certificate(certificate.as_ref()).ok()?;
    let mut rdns = Vec::new();
    for rdn in parsed.subject().iter() {
        let mut values = Vec::new();
        for attribute in rdn.iter() {
            let oid = attribute.attr_type().to_id_string();
            let mut text = match short_name(&oid) {
                Some(name) => format!("{name}="),
                None => format!("{oid}="),
            };
            escape_rdn_value(attribute.as_str().ok()?, &mut text);
            values.push(text);
        }
        rdns.push(values.join("+"));
    }
    rdns.reverse();
    Some(rdns.join(","))
}

#[cfg(feature = "mqtt")]
/// RabbitMQ's short names of subject attributes, by OID.
fn short_name(oid: &str) -> Option<&'static str> {
    Some(match oid {
        "2.5.4.4" => "SN",
        "2.5.4.42" => "GIVENNAME",
        "2.5.4.43" => "INITIALS",
        "2.5.4.44" => "GENERATIONQUALIFIER",
        "2.5.4.3" => "CN",
        "2.5.4.7" => "L",
        "2.5.4.8" => "ST",
        "2.5.4.10" => "O",
        "2.5.4.11" => "OU",
        "2.5.4.12" => "TITLE",
        "2.5.4.6" => "C",
        "2.5.4.5" => "SERIALNUMBER",
        "2.5.4.65" => "PSEUDONYM",
        "0.9.2342.19200300.100.1.25" => "DC",
        "1.2.840.113549.1.9.1" => "EMAILADDRESS",
        "2.5.4.9" => "STREET",
        "0.9.2342.19200300.100.1.1" => "UID",
        _ => return None,
    })
}

#[cfg(feature = "mqtt")]
/// RFC 4514 escaping as RabbitMQ does it: a leading space or `#`, a
/// trailing space and `"+,;<>\\` get a backslash; bytes below 32 or from
/// 126 up (UTF-8 sequences included) become `\\XX`.
fn escape_rdn_value(value: &str, out: &mut String) {
    let bytes = value.as_bytes();
    for (at, &byte) in bytes.iter().enumerate() {
        match byte {
            b' ' | b'#' if at == 0 => out.extend(['\\', byte as char]),
            b' ' if at + 1 == bytes.len() => out.push_str("\\ "),
            b'"' | b'+' | b',' | b';' | b'<' | b'>' | b'\\' => out.extend(['\\', byte as char]),
            byte if !(32..126).contains(&byte) => out.push_str(&format!("\\{byte:02X}")),
            byte => out.push(byte as char),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg(feature = "mqtt")]
    #[test]
    fn subjects_read_as_rabbitmq_writes_them() {
        let key = rcgen::KeyPair::generate().unwrap();
        let mut params = rcgen::CertificateParams::new(Vec::new()).unwrap();
        // The subject lists CN, then O (as `openssl req -subj /CN=../O=..`);
        // RabbitMQ writes the last first.
        params.distinguished_name = rcgen::DistinguishedName::new();
        params
            .distinguished_name
            .push(rcgen::DnType::CommonName, " #arm+1 ");
        params
            .distinguished_name
            .push(rcgen::DnType::OrganizationName, "Robots, Inc");
        let certificate = params.self_signed(&key).unwrap();
        assert_eq!(
            subject(certificate.der()).as_deref(),
            Some("O=Robots\\, Inc,CN=\\ #arm\\+1\\ ")
        );
        let mut escaped = String::new();
        escape_rdn_value("#é~\n", &mut escaped);
        assert_eq!(escaped, "\\#\\C3\\A9\\7E\\0A");
    }

    struct Files {
        dir: PathBuf,
    }

    impl Files {
        fn new(name: &str) -> Files {
            let dir =
                std::env::temp_dir().join(format!("leveret-tls-{name}-{}", std::process::id()));
            std::fs::create_dir_all(&dir).unwrap();
            Files { dir }
        }

        fn write(&self, name: &str, text: &str) -> PathBuf {
            let path = self.dir.join(name);
            std::fs::write(&path, text).unwrap();
            path
        }
    }

    impl Drop for Files {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.dir);
        }
    }

    fn self_signed(name: &str) -> (String, String, CertificateDer<'static>) {
        let key = rcgen::KeyPair::generate().unwrap();
        let mut params = rcgen::CertificateParams::new(vec!["localhost".to_owned()]).unwrap();
        params
            .distinguished_name
            .push(rcgen::DnType::CommonName, name);
        let cert = params.self_signed(&key).unwrap();
        (cert.pem(), key.serialize_pem(), cert.der().clone())
    }

    #[test]
    fn loads_pem_files_reads_the_common_name_and_keeps_the_old_config_on_a_bad_reload() {
        let files = Files::new("load");
        let (cert, key, der) = self_signed("robot-7");
        assert_eq!(common_name(&der).as_deref(), Some("robot-7"));
        let options = TlsOptions {
            certfile: files.write("cert.pem", &cert),
            keyfile: files.write("key.pem", &key),
            cacertfile: None,
            verify: PeerVerification::None,
        };
        let verifying = TlsOptions {
            verify: PeerVerification::Required,
            ..options.clone()
        };
        assert!(matches!(
            TlsContext::load(verifying),
            Err(TlsError::NoCaBundle)
        ));
        let context = TlsContext::load(options).expect("loads");
        context.reload().expect("reloads");
        files.write("cert.pem", "not a certificate");
        assert!(matches!(context.reload(), Err(TlsError::File { .. })));
        let _still = context.acceptor();
    }

    #[test]
    fn a_key_that_is_not_the_certificates_is_refused() {
        let files = Files::new("mismatch");
        let (cert, _, _) = self_signed("a");
        let (_, other_key, _) = self_signed("b");
        let options = TlsOptions {
            certfile: files.write("cert.pem", &cert),
            keyfile: files.write("key.pem", &other_key),
            cacertfile: None,
            verify: PeerVerification::None,
        };
        assert!(TlsContext::load(options).is_err());
    }
}
