//! The TCP side: listeners, the accept loop (TCP_NODELAY on every socket,
//! as RabbitMQ does and as the paper's latency figures call for; sockets
//! over `max_connections` closed at once; on a TLS listener the TLS
//! handshake, under the handshake timeout, on the connection's own task),
//! and the vhost sweeper that expires messages and queues.

use crate::admission::Slot;
use crate::connection::Identity;
use crate::core::Core;
#[cfg(feature = "tls")]
use crate::tls::TlsContext;
use std::sync::Arc;
use std::time::Duration;
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::watch;

/// Built without the `tls` feature there are no TLS listeners: the
/// context of one cannot exist.
#[cfg(not(feature = "tls"))]
pub(crate) enum TlsContext {}

/// The next connection to serve from `listener`: accepted, admitted
/// against `max_connections` (a socket over it is closed at once, before
/// anything is read), with TCP_NODELAY set. `None` once the broker shuts
/// down. The AMQP and MQTT accept loops both take their sockets here.
pub(crate) async fn next_admitted(
    core: &Arc<Core>,
    listener: &TcpListener,
    shutdown: &mut watch::Receiver<bool>,
) -> Option<(TcpStream, String, Slot)> {
    loop {
        let accepted = tokio::select! {
            accepted = listener.accept() => accepted,
            _ = shutdown.wait_for(|down| *down) => return None,
        };
        let (socket, peer) = match accepted {
            Ok(pair) => pair,
            Err(e) => {
                // Out of file descriptors and the like: back off briefly.
                tracing::warn!(error = %e, "accept failed");
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        let peer = peer.to_string();
        let Ok(slot) = core.connections.admit_network(&peer) else {
            continue;
        };
        if let Err(e) = socket.set_nodelay(true) {
            tracing::debug!(error = %e, "could not set TCP_NODELAY");
        }
        return Some((socket, peer, slot));
    }
}

/// Accepts AMQP connections until the broker shuts down.
///
/// Each connection task holds a clone of `alive`, so whoever holds the
/// receiver learns when the last connection has ended.
pub async fn accept_loop(
    core: Arc<Core>,
    listener: TcpListener,
    tls: Option<Arc<TlsContext>>,
    alive: tokio::sync::mpsc::Sender<()>,
) {
    let mut shutdown = core.shutdown_signal();
    while let Some((socket, peer, slot)) = next_admitted(&core, &listener, &mut shutdown).await {
        let local = socket.local_addr().ok();
        let core = Arc::clone(&core);
        let alive = alive.clone();
        match &tls {
            None => {
                let (read, write) = socket.into_split();
                // Spawned as it is: a block around it would keep room for
                // its arguments, and a second copy of it, through the
                // connection's life.
                let ends = (peer, local);
                let connection =
                    crate::connection::serve(core, read, write, ends, slot, Identity::None, alive);
                tokio::spawn(connection);
            }
            #[cfg(not(feature = "tls"))]
            Some(tls) => match **tls {},
            #[cfg(feature = "tls")]
            Some(tls) => {
                let acceptor = tls.acceptor();
                tokio::spawn(async move {
                    let handshake = acceptor.accept(socket);
                    let stream = match tokio::time::timeout(
                        core.limits.handshake_timeout,
                        handshake,
                    )
                    .await
                    {
                        Ok(Ok(stream)) => stream,
                        Ok(Err(e)) => {
                            tracing::info!(%peer, error = %e, "TLS handshake failed");
                            return;
                        }
                        Err(_) => {
                            tracing::warn!(%peer, "TLS handshake not completed within the handshake timeout");
                            return;
                        }
                    };
                    let identity = stream
                        .get_ref()
                        .1
                        .peer_certificates()
                        .and_then(|chain| chain.first())
                        .map_or(Identity::Tls(None), |cert| {
                            Identity::Tls(crate::tls::common_name(cert))
                        });
                    let (read, write) = tokio::io::split(stream);
                    let ends = (peer, local);
                    crate::connection::serve(core, read, write, ends, slot, identity, alive).await;
                });
            }
        }
    }
}

/// Expires messages and unused queues every `period`.
pub async fn sweeper(core: Arc<Core>, period: Duration) {
    let mut shutdown = core.shutdown_signal();
    let mut ticker = tokio::time::interval(period);
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = ticker.tick() => {}
            _ = shutdown.wait_for(|down| *down) => return,
        }
        for vhost in core.vhosts() {
            vhost.sweep().await;
        }
    }
}
