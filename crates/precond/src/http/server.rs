//! The accept loop: HTTP/1.1 connections served by hyper with the timer that makes its header
//! read timeout work (`axum::serve` sets none, so a client that sends its headers a byte at a
//! time, or opens a connection and says nothing, held it forever).
//!
//! - A connection must deliver each request's headers within [`ConnLimits::header_read`]
//!   from the moment the server waits for them — for a kept-alive connection, from the end
//!   of the previous response — or it is closed. So idle keep-alive connections are closed
//!   after the same time.
//! - Bodies have their own deadline, enforced where they are read
//!   ([`ApiJson`](super::extract::ApiJson), `408 request_timeout`).
//! - On shutdown the listener closes, every connection finishes the request it is serving
//!   and closes, and [`run`] returns when the last one has.

use axum::Router;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use std::future::Future;
use std::pin::pin;
use std::time::Duration;
use tokio::net::TcpListener;
use tokio::sync::watch;

/// Per-connection limits.
#[derive(Debug, Clone, Copy)]
pub struct ConnLimits {
    /// Longest wait for a request's complete headers (and the idle time of a kept-alive
    /// connection).
    pub header_read: Duration,
}

/// Serves `router` on `listener` until `shutdown` resolves, then lets the connections finish
/// their requests (see the module docs).
pub async fn run(
    listener: TcpListener,
    router: Router,
    limits: ConnLimits,
    shutdown: impl Future<Output = ()> + Send,
) {
    let (stop_tx, stop_rx) = watch::channel(false);
    // Every connection task holds a clone of `open_rx`; `open_tx.closed()` resolves when the
    // last one has ended.
    let (open_tx, open_rx) = watch::channel(());
    let mut shutdown = pin!(shutdown);
    loop {
        let (stream, peer) = tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok(accepted) => accepted,
                Err(e) => {
                    accept_error(e).await;
                    continue;
                }
            },
            () = &mut shutdown => break,
        };
        let _ = stream.set_nodelay(true);
        let service = TowerToHyperService::new(router.clone());
        let mut stop = stop_rx.clone();
        let open = open_rx.clone();
        tokio::spawn(async move {
            let mut builder = hyper::server::conn::http1::Builder::new();
            builder
                .timer(TokioTimer::new())
                .header_read_timeout(limits.header_read)
                .keep_alive(true);
            let mut conn = pin!(builder.serve_connection(TokioIo::new(stream), service));
            let mut stopping = false;
            loop {
                tokio::select! {
                    served = conn.as_mut() => {
                        if let Err(e) = served {
                            tracing::debug!(%peer, error = %e, "connection ended");
                        }
                        break;
                    }
                    changed = stop.changed(), if !stopping => {
                        stopping = true;
                        if changed.is_ok() {
                            conn.as_mut().graceful_shutdown();
                        }
                    }
                }
            }
            drop(open);
        });
    }
    drop(listener);
    let _ = stop_tx.send(true);
    drop(open_rx);
    open_tx.closed().await;
}

/// A failed accept: the peer gave up (nothing to do), or the process is out of file
/// descriptors or memory (wait a second for some to free, as hyper 0.14 did).
async fn accept_error(e: std::io::Error) {
    use std::io::ErrorKind::{ConnectionAborted, ConnectionRefused, ConnectionReset};
    if matches!(
        e.kind(),
        ConnectionRefused | ConnectionAborted | ConnectionReset
    ) {
        return;
    }
    tracing::error!(error = %e, "accept failed; retrying in 1 s");
    tokio::time::sleep(Duration::from_secs(1)).await;
}
