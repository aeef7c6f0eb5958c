//! A loopback TCP proxy that injects a link's faults between a client and
//! a broker, for the tests of what survives them (the robot data ports,
//! the uplink's shovels): freeze (nothing forwarded, every socket kept
//! open, as a stopped process), cut every connection, stop listening (the
//! address refuses connections until a proxy listens there again), a
//! one-way latency, a bandwidth cap, and a cut in the middle of a frame
//! (after a given number of further bytes).

use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::watch;
use tokio::task::AbortHandle;

/// The faults in force; every relayed connection follows changes at once.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Faults {
    /// Nothing is forwarded; sockets stay open.
    pub frozen: bool,
    /// Added to every chunk, each way.
    pub latency: Duration,
    /// Bytes per second each way, at most.
    pub bandwidth: Option<u64>,
    /// Cut every connection after this many more bytes (either way): a
    /// cut in the middle of a frame.
    pub cut_after: Option<u64>,
}

/// The proxy; dropping it cuts everything.
#[derive(Debug)]
pub struct FaultProxy {
    /// Where clients connect.
    pub addr: SocketAddr,
    faults: watch::Sender<Faults>,
    connections: Arc<Mutex<Vec<AbortHandle>>>,
    accept: tokio::task::JoinHandle<()>,
}

impl FaultProxy {
    /// A proxy to `upstream` on a free loopback port that no other
    /// listener takes while the proxy is stopped, so [`Self::start_at`] can
    /// bring it back on the same address.
    pub async fn start(upstream: SocketAddr) -> FaultProxy {
        FaultProxy::start_at(crate::reserved_port::reserved_addr(), upstream).await
    }

    /// A proxy to `upstream` listening on `addr` (port 0 picks one).
    pub async fn start_at(addr: SocketAddr, upstream: SocketAddr) -> FaultProxy {
        let listener = TcpListener::bind(addr).await.expect("bind the proxy");
        let addr = listener.local_addr().expect("bound address");
        let (faults, _) = watch::channel(Faults::default());
        let connections = Arc::new(Mutex::new(Vec::new()));
        let tracked = Arc::clone(&connections);
        let gate = faults.clone();
        let accept = tokio::spawn(async move {
            while let Ok((inbound, _)) = listener.accept().await {
                let (up, down) = (gate.subscribe(), gate.subscribe());
                let cutter = gate.clone();
                let relay = tokio::spawn(async move {
                    let Ok(outbound) = TcpStream::connect(upstream).await else {
                        return;
                    };
                    let _ = inbound.set_nodelay(true);
                    let _ = outbound.set_nodelay(true);
                    let (in_read, in_write) = inbound.into_split();
                    let (out_read, out_write) = outbound.into_split();
                    let to_broker = forward(in_read, out_write, up, &cutter);
                    let to_client = forward(out_read, in_write, down, &cutter);
                    tokio::pin!(to_broker, to_client);
                    // A side that closes its half is passed on as a
                    // half-close; a failure or a cut ends both.
                    tokio::select! {
                        end = &mut to_broker => if end == End::Closed { to_client.await; },
                        end = &mut to_client => if end == End::Closed { to_broker.await; },
                    }
                });
                tracked
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .push(relay.abort_handle());
            }
        });
        FaultProxy {
            addr,
            faults,
            connections,
            accept,
        }
    }

    /// Changes the faults in force.
    pub fn set(&self, change: impl FnOnce(&mut Faults)) {
        self.faults.send_modify(change);
    }

    /// The faults in force (a spent `cut_after` reads `Some(0)`).
    pub fn faults(&self) -> Faults {
        self.faults.borrow().clone()
    }

    /// Freezes or thaws the link.
    pub fn freeze(&self, frozen: bool) {
        self.set(|f| f.frozen = frozen);
    }

    /// Drops every relayed connection (both sockets close); how many.
    pub fn cut(&self) -> usize {
        let all = std::mem::take(&mut *self.connections.lock().unwrap_or_else(|e| e.into_inner()));
        for connection in &all {
            connection.abort();
        }
        all.len()
    }

    /// Stops listening (the port is free again on return) and cuts every
    /// connection: unreachable until a proxy listens on the address again.
    pub async fn stop(&mut self) {
        self.accept.abort();
        let _ = (&mut self.accept).await;
        self.cut();
    }
}

impl Drop for FaultProxy {
    fn drop(&mut self) {
        self.accept.abort();
        self.cut();
    }
}

/// How one direction of a relayed connection ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum End {
    /// The sender closed its half; passed on.
    Closed,
    /// A socket failed, or a `cut_after` budget ran out.
    Broken,
}

/// Copies `from` to `to` under the faults in force.
async fn forward(
    mut from: tokio::net::tcp::OwnedReadHalf,
    mut to: tokio::net::tcp::OwnedWriteHalf,
    mut faults: watch::Receiver<Faults>,
    cutter: &watch::Sender<Faults>,
) -> End {
    let mut buf = vec![0u8; 16 * 1024];
    loop {
        if faults.wait_for(|f| !f.frozen).await.is_err() {
            return End::Broken;
        }
        let read = tokio::select! {
            read = from.read(&mut buf) => Some(read),
            _ = faults.wait_for(|f| f.frozen) => None,
        };
        let n = match read {
            None => continue,
            Some(Ok(0)) => {
                let _ = to.shutdown().await;
                return End::Closed;
            }
            Some(Err(_)) => return End::Broken,
            Some(Ok(n)) => n,
        };
        let now = faults.borrow().clone();
        // Bytes read before a freeze are still delivered (as the kernel
        // would have them in a stopped process's socket buffer).
        let mut chunk = &buf[..n];
        if let Some(budget) = now.cut_after {
            let allowed = usize::try_from(budget)
                .unwrap_or(usize::MAX)
                .min(chunk.len());
            cutter.send_modify(|f| f.cut_after = Some(budget - allowed as u64));
            if allowed < chunk.len() {
                let _ = to.write_all(&chunk[..allowed]).await;
                return End::Broken;
            }
            chunk = &chunk[..allowed];
        }
        if !now.latency.is_zero() {
            tokio::time::sleep(now.latency).await;
        }
        if let Some(rate) = now.bandwidth.filter(|r| *r > 0) {
            tokio::time::sleep(Duration::from_secs_f64(chunk.len() as f64 / rate as f64)).await;
        }
        if to.write_all(chunk).await.is_err() {
            return End::Broken;
        }
    }
}
