//! The server's connections before any request: what anyone who reaches the port can hold,
//! bounded before auth.
//!
//! - At most `max_connections` are open; one more is accepted and closed at once.
//! - A connection must send its opening bytes (the HTTP/2 preface and the header of its
//!   SETTINGS frame, or a TLS hello, which is longer) within `handshake_timeout`, or it is
//!   closed.
//! - Once it speaks HTTP/2, the server pings it every `keepalive_interval` and closes it when a
//!   ping goes unanswered for `keepalive_timeout` (set on the transport, see
//!   [`ConnectionLimits::apply`]), and each connection may open at most `max_concurrent_streams`
//!   streams at once.
//! - Running out of file descriptors makes the accept loop pause (100 ms) instead of spinning
//!   on the error.

use std::future::Future;
use std::io;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use futures::Stream;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tokio::time::Sleep;
use tonic::transport::server::{Connected, TcpConnectInfo};

/// Bounds on connections (see the module documentation).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ConnectionLimits {
    /// Connections open at once.
    pub max_connections: usize,
    /// Time from accept to a connection's first bytes.
    pub handshake_timeout: Duration,
    /// HTTP/2 streams one connection may have open at once (its SETTINGS).
    pub max_concurrent_streams: u32,
    /// Interval of the server's HTTP/2 pings.
    pub keepalive_interval: Duration,
    /// How long a ping may go unanswered before the connection is closed.
    pub keepalive_timeout: Duration,
}

impl Default for ConnectionLimits {
    fn default() -> Self {
        Self {
            max_connections: 1024,
            handshake_timeout: Duration::from_secs(10),
            max_concurrent_streams: 256,
            keepalive_interval: Duration::from_secs(30),
            keepalive_timeout: Duration::from_secs(20),
        }
    }
}

impl ConnectionLimits {
    /// The HTTP/2 settings on the transport.
    pub fn apply<L>(&self, server: tonic::transport::Server<L>) -> tonic::transport::Server<L> {
        server
            .max_concurrent_streams(self.max_concurrent_streams)
            .http2_keepalive_interval(Some(self.keepalive_interval))
            .http2_keepalive_timeout(Some(self.keepalive_timeout))
            .tcp_nodelay(true)
    }

    /// Accepted connections of `listener`, within the limits.
    pub fn incoming(
        &self,
        listener: TcpListener,
    ) -> impl Stream<Item = io::Result<LimitedConnection>> + Send + 'static {
        let slots = Arc::new(Semaphore::new(self.max_connections.max(1)));
        let handshake = self.handshake_timeout;
        futures::stream::unfold((listener, slots), move |(listener, slots)| async move {
            loop {
                match listener.accept().await {
                    Ok((stream, peer)) => {
                        let Ok(permit) = slots.clone().try_acquire_owned() else {
                            tracing::warn!(%peer, "connection refused: at --max-connections");
                            drop(stream);
                            continue;
                        };
                        // Without TCP_NODELAY small responses wait on delayed ACKs (~15 ms
                        // a call).
                        let _ = stream.set_nodelay(true);
                        let conn = LimitedConnection {
                            stream,
                            first_bytes: Some(Box::pin(tokio::time::sleep(handshake))),
                            received: 0,
                            _slot: permit,
                        };
                        return Some((Ok(conn), (listener, slots)));
                    }
                    Err(e) if out_of_descriptors(&e) => {
                        // The error repeats until a descriptor frees: wait for one instead
                        // of spinning on accept.
                        tracing::warn!(error = %e, "accept: out of file descriptors");
                        tokio::time::sleep(Duration::from_millis(100)).await;
                    }
                    Err(e) => {
                        // A connection that failed before it was accepted (reset, aborted)
                        // concerns only itself.
                        tracing::debug!(error = %e, "accept failed");
                        tokio::time::sleep(Duration::from_millis(1)).await;
                    }
                }
            }
        })
    }
}

/// The bytes a connection must send within the handshake timeout: HTTP/2's 24-byte preface and
/// the 9-byte header of the SETTINGS frame that must follow it (RFC 9113 §3.4). A TLS
/// ClientHello is longer.
const OPENING_BYTES: usize = 24 + 9;

/// EMFILE (this process) or ENFILE (the system).
fn out_of_descriptors(e: &io::Error) -> bool {
    matches!(e.raw_os_error(), Some(23) | Some(24))
}

/// A connection holding one of the server's slots until it closes, and closed if its opening
/// bytes do not come in time.
pub struct LimitedConnection {
    stream: TcpStream,
    /// Until the opening bytes have arrived.
    first_bytes: Option<Pin<Box<Sleep>>>,
    received: usize,
    _slot: OwnedSemaphorePermit,
}

impl AsyncRead for LimitedConnection {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        let before = buf.filled().len();
        let polled = Pin::new(&mut this.stream).poll_read(cx, buf);
        if let Some(deadline) = this.first_bytes.as_mut() {
            match &polled {
                Poll::Ready(Ok(())) => {
                    this.received += buf.filled().len() - before;
                    if this.received >= OPENING_BYTES {
                        this.first_bytes = None;
                    }
                }
                Poll::Pending => {
                    if deadline.as_mut().poll(cx).is_ready() {
                        return Poll::Ready(Err(io::Error::new(
                            io::ErrorKind::TimedOut,
                            "no handshake within --handshake-timeout-secs",
                        )));
                    }
                }
                Poll::Ready(Err(_)) => {}
            }
        }
        polled
    }
}

impl AsyncWrite for LimitedConnection {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.stream).poll_write(cx, buf)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_shutdown(cx)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.stream).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.stream.is_write_vectored()
    }
}

impl Connected for LimitedConnection {
    type ConnectInfo = TcpConnectInfo;

    fn connect_info(&self) -> Self::ConnectInfo {
        self.stream.connect_info()
    }
}
