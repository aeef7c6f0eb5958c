//! The byte streams a connection runs over: any stream that can be split
//! into a read half for the reader task and a write half for the writer
//! task. TCP splits without a lock; TLS (rustls over TCP, feature `tls`)
//! through `tokio::io::split`. Their frames are decoded and encoded by
//! `frames`, which also carries an embedded Leveret's frame values.

use crate::error::Result;
use crate::uri::ConnectionOptions;
use tokio::io::{AsyncRead, AsyncWrite};
use tokio::net::tcp::{OwnedReadHalf, OwnedWriteHalf};
use tokio::net::TcpStream;

/// A byte stream a connection can run over.
pub(crate) trait Transport: AsyncRead + AsyncWrite + Send + Unpin + 'static {
    /// The reader task's half.
    type Read: AsyncRead + Send + Sync + Unpin + 'static;
    /// The writer task's half.
    type Write: AsyncWrite + Send + Unpin + 'static;

    /// Splits the stream for the reader and writer tasks.
    fn into_halves(self) -> (Self::Read, Self::Write);
}

impl Transport for TcpStream {
    type Read = OwnedReadHalf;
    type Write = OwnedWriteHalf;

    fn into_halves(self) -> (OwnedReadHalf, OwnedWriteHalf) {
        self.into_split()
    }
}

#[cfg(feature = "tls")]
impl Transport for tokio_rustls::client::TlsStream<TcpStream> {
    type Read = tokio::io::ReadHalf<Self>;
    type Write = tokio::io::WriteHalf<Self>;

    fn into_halves(self) -> (Self::Read, Self::Write) {
        tokio::io::split(self)
    }
}

/// Opens a TCP connection to the options' host and port, with Nagle off
/// (frames are batched by the writer already).
pub(crate) async fn tcp(options: &ConnectionOptions) -> Result<TcpStream> {
    let stream = TcpStream::connect((options.host.as_str(), options.port)).await?;
    stream.set_nodelay(true)?;
    Ok(stream)
}

/// TLS over `stream` as `settings` say: the broker's certificate checked
/// against the CA file or the operating system's CA certificates, and a
/// client certificate when one is given.
#[cfg(feature = "tls")]
pub(crate) async fn tls(
    stream: TcpStream,
    host: &str,
    settings: &crate::uri::TlsSettings,
) -> Result<tokio_rustls::client::TlsStream<TcpStream>> {
    use crate::error::Error;
    use rustls::pki_types::pem::PemObject;
    use rustls::pki_types::{CertificateDer, PrivateKeyDer, ServerName};
    use std::sync::Arc;

    let failed = |what: &str, e: &dyn std::fmt::Display| Error::Tls(format!("{what}: {e}"));
    let mut roots = rustls::RootCertStore::empty();
    match &settings.cacertfile {
        Some(path) => {
            for cert in CertificateDer::pem_file_iter(path).map_err(|e| failed("cacertfile", &e))? {
                let cert = cert.map_err(|e| failed("cacertfile", &e))?;
                roots.add(cert).map_err(|e| failed("cacertfile", &e))?;
            }
        }
        None => {
            let found = rustls_native_certs::load_native_certs();
            for cert in found.certs {
                // Certificates the system has but rustls cannot parse are
                // skipped, as browsers do.
                let _ = roots.add(cert);
            }
        }
    }
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let builder = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| failed("protocol versions", &e))?
        .with_root_certificates(roots);
    let config = match (&settings.certfile, &settings.keyfile) {
        (Some(certfile), Some(keyfile)) => {
            let chain = CertificateDer::pem_file_iter(certfile)
                .map_err(|e| failed("certfile", &e))?
                .collect::<std::result::Result<Vec<_>, _>>()
                .map_err(|e| failed("certfile", &e))?;
            let key = PrivateKeyDer::from_pem_file(keyfile).map_err(|e| failed("keyfile", &e))?;
            builder
                .with_client_auth_cert(chain, key)
                .map_err(|e| failed("client certificate", &e))?
        }
        (None, None) => builder.with_no_client_auth(),
        _ => return Err(Error::Tls("give both certfile and keyfile".into())),
    };
    let name = settings.server_name.as_deref().unwrap_or(host).to_owned();
    let name = ServerName::try_from(name).map_err(|e| failed("server name", &e))?;
    let connector = tokio_rustls::TlsConnector::from(Arc::new(config));
    Ok(connector.connect(name, stream).await?)
}
