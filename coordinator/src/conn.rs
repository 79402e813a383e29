//! The accept loop: one task per connection, with the limits a public server needs (issue 11,
//! finding 5: 300 half-sent requests exhausted the coordinator's file descriptors and `/healthz`
//! stopped answering).
//!
//! - A connection cap (`max_connections`): beyond it a new connection is closed at once, so
//!   descriptors stay available for the ones being served.
//! - HTTP/1 header-read timeout: a client that does not finish its request head in time is cut.
//! - HTTP/2 (gRPC) keep-alive pings: a dead peer's connection is closed.
//! - TLS handshakes run in the connection's own task with a timeout, never in the accept loop
//!   (one slow handshake used to hold every other client).
//!
//! REST bodies are bounded in time by a middleware (`rest::request_timeout`).

use std::sync::Arc;
use std::time::Duration;
use tokio::net::TcpListener;
use tokio::sync::Semaphore;

/// Connection limits (`TESSERA_MAX_CONNECTIONS`, `TESSERA_HEADER_TIMEOUT_SECONDS`).
#[derive(Clone, Copy, Debug)]
pub struct ConnLimits {
    pub max_connections: usize,
    pub header_read_timeout: Duration,
    pub tls_handshake_timeout: Duration,
}

impl Default for ConnLimits {
    fn default() -> Self {
        ConnLimits {
            max_connections: 512,
            header_read_timeout: Duration::from_secs(10),
            tls_handshake_timeout: Duration::from_secs(10),
        }
    }
}

/// Serves `app` on `listener` until the process ends.
pub async fn serve(
    listener: TcpListener,
    tls: Option<tokio_rustls::TlsAcceptor>,
    app: axum::Router,
    limits: ConnLimits,
) -> std::io::Result<()> {
    let permits = Arc::new(Semaphore::new(limits.max_connections.max(1)));
    let mut refused_logged = std::time::Instant::now() - Duration::from_secs(60);
    loop {
        let (tcp, addr) = match listener.accept().await {
            Ok(c) => c,
            Err(e) => {
                // Out of descriptors or similar: back off instead of spinning.
                tracing::warn!(error = %e, "accept failed");
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        let Ok(permit) = permits.clone().try_acquire_owned() else {
            if refused_logged.elapsed() > Duration::from_secs(10) {
                tracing::warn!(max = limits.max_connections, "connection limit reached: closing new connections");
                refused_logged = std::time::Instant::now();
            }
            drop(tcp);
            continue;
        };
        // TCP_NODELAY: a streamed result (header, then data) would otherwise stall ~40 ms per unit
        // on Nagle's algorithm meeting delayed ACKs.
        let _ = tcp.set_nodelay(true);
        let app = app.clone();
        let tls = tls.clone();
        tokio::spawn(async move {
            let _permit = permit;
            let service = hyper_util::service::TowerToHyperService::new(app);
            let mut builder = hyper_util::server::conn::auto::Builder::new(hyper_util::rt::TokioExecutor::new());
            builder.http1().timer(hyper_util::rt::TokioTimer::new()).header_read_timeout(limits.header_read_timeout);
            builder
                .http2()
                .timer(hyper_util::rt::TokioTimer::new())
                .keep_alive_interval(Some(Duration::from_secs(30)))
                .keep_alive_timeout(Duration::from_secs(20));
            let result = match tls {
                Some(acceptor) => {
                    match tokio::time::timeout(limits.tls_handshake_timeout, acceptor.accept(tcp)).await {
                        Ok(Ok(stream)) => {
                            builder.serve_connection_with_upgrades(hyper_util::rt::TokioIo::new(stream), service).await
                        }
                        Ok(Err(e)) => {
                            tracing::debug!(%addr, error = %e, "TLS handshake failed");
                            return;
                        }
                        Err(_) => {
                            tracing::debug!(%addr, "TLS handshake timed out");
                            return;
                        }
                    }
                }
                None => builder.serve_connection_with_upgrades(hyper_util::rt::TokioIo::new(tcp), service).await,
            };
            if let Err(e) = result {
                tracing::debug!(%addr, error = %e, "connection ended with an error");
            }
        });
    }
}
