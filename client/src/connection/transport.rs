//! What a connection runs over: any byte stream that can be split into a
//! read half for the reader task and a write half for the writer task.
//! TCP splits without a lock; the in-process pipe of an embedded Leveret
//! (`tokio::io::DuplexStream`) through `tokio::io::split`. The handshake,
//! reader and writer are generic over [`Transport`], so both share them.

use crate::error::Result;
use crate::uri::ConnectionOptions;
use tokio::io::{AsyncRead, AsyncWrite, DuplexStream, ReadHalf, WriteHalf};
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

impl Transport for DuplexStream {
    type Read = ReadHalf<DuplexStream>;
    type Write = WriteHalf<DuplexStream>;

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
