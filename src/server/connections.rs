//! Accepting connections on both listeners, and bounding what a slow or silent client can hold.
//!
//! A connection costs a file descriptor, a task and buffers whatever the client sends, so a client that
//! connects and then sends nothing, half a request head or a body one byte at a time must lose it within
//! set times, whatever the transport. The request deadline (`server.request_timeout_ms`) only starts once a
//! request is handed to a handler, so it cannot do this. The rules, all in `[server]`:
//!
//! - **`max_connections`** per listener: [`Listener::accept`] takes a slot (a semaphore permit) *before*
//!   accepting, so at the cap new clients wait in the kernel's backlog instead of costing descriptors; a
//!   slot is freed when its connection closes.
//! - **`header_read_timeout_ms`**: a new connection must deliver its first request head within this long
//!   (HTTP/2 and gRPC: its connection preface, after which it may wait for its first call like any idle
//!   connection); on HTTP/1.1 keep-alive, a request head must be complete within this long of its first
//!   byte.
//! - **`idle_timeout_ms`**: a connection with no request in flight is closed after this long without a new
//!   one, and so is one whose writes (responses) made no progress for this long (a client that stopped
//!   reading).
//! - **`body_read_timeout_ms`**: an HTTP request body must be complete within this long of its head
//!   ([`DeadlineBody`]); gRPC calls are bounded by tonic's call timeout and by the gap allowed between the
//!   messages of a client stream (set in `src/server/grpc/mod.rs` and `src/server/grpc/api.rs`).
//! - **`tcp_keepalive_ms`**: TCP keepalive on accepted sockets, so vanished peers are noticed.
//!
//! A connection the server closes lingers ([`LINGER`], as nginx's `lingering_close`): after its FIN it reads
//! and discards until the client closes too, so the last response reaches a client that was still sending.
//!
//! They are written here, on the socket, because hyper's server has no idle-connection timeout and no timeout
//! on a write that makes no progress, and its header-read timeout is HTTP/1.1's only (tonic's server has none).
//!
//! How: the accepted socket is wrapped in a [`Conn`] that enforces the times on its own reads and writes;
//! the transport tells it when requests begin and end ([`Activity::begin`], a guard that lives until the
//! response body is done), which is what "in flight" means here. The rules are evaluated only while a
//! read or a write is pending, with one timer each, so a healthy connection pays a few clock reads.

use std::future::Future;
use std::io;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use axum::body::Bytes;
use futures_util::task::AtomicWaker;
use parking_lot::Mutex;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tokio::time::{Instant, Sleep};

use crate::settings::ServerSettings;

/// The per-connection limits, from [`ServerSettings`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ConnectionLimits {
    pub max_connections: usize,
    pub header_read: Duration,
    pub idle: Duration,
    pub tcp_keepalive: Option<Duration>,
}

impl ConnectionLimits {
    pub fn from_settings(s: &ServerSettings) -> Self {
        Self {
            max_connections: s.max_connections,
            header_read: Duration::from_millis(s.header_read_timeout_ms),
            idle: Duration::from_millis(s.idle_timeout_ms),
            tcp_keepalive: (s.tcp_keepalive_ms > 0).then(|| Duration::from_millis(s.tcp_keepalive_ms)),
        }
    }
}

/// What a listener speaks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Protocol {
    /// HTTP/2 only (gRPC).
    Http2,
    /// HTTP/1.1, or HTTP/2 when a connection starts with its preface.
    Http1OrHttp2,
}

/// A TCP listener that holds at most `max_connections` open connections.
pub struct Listener {
    inner: TcpListener,
    slots: Arc<Semaphore>,
    limits: ConnectionLimits,
    protocol: Protocol,
    transport: &'static str,
}

impl Listener {
    pub fn new(inner: TcpListener, limits: ConnectionLimits, protocol: Protocol, transport: &'static str) -> Self {
        Self { inner, slots: Arc::new(Semaphore::new(limits.max_connections)), limits, protocol, transport }
    }

    pub fn local_addr(&self) -> io::Result<SocketAddr> {
        self.inner.local_addr()
    }

    /// Waits for a free slot, then for a connection (TCP_NODELAY and keepalive set). Accept errors are
    /// logged and retried: a failed accept (e.g. out of descriptors) must not stop the server.
    pub async fn accept(&self) -> (Conn, SocketAddr) {
        let slot = Arc::clone(&self.slots).acquire_owned().await.expect("the slot semaphore is never closed");
        loop {
            match self.inner.accept().await {
                Ok((stream, peer)) => {
                    // Without TCP_NODELAY a response written in pieces (HTTP/2 headers, data, trailers) waits
                    // for the client's delayed ACK (~40 ms on Linux).
                    if let Err(e) = stream.set_nodelay(true) {
                        tracing::warn!(transport = self.transport, "TCP_NODELAY on an accepted connection: {e}");
                    }
                    if let Some(idle) = self.limits.tcp_keepalive {
                        let keepalive = socket2::TcpKeepalive::new().with_time(idle);
                        if let Err(e) = socket2::SockRef::from(&stream).set_tcp_keepalive(&keepalive) {
                            tracing::warn!(transport = self.transport, "TCP keepalive on an accepted connection: {e}");
                        }
                    }
                    return (Conn::new(stream, slot, self.limits, self.protocol), peer);
                }
                Err(e) if is_per_connection(&e) => continue,
                Err(e) => {
                    tracing::error!(transport = self.transport, "accept failed: {e}; retrying in 100 ms");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                }
            }
        }
    }
}

/// Accept errors that concern only the connection being accepted.
fn is_per_connection(e: &io::Error) -> bool {
    matches!(
        e.kind(),
        io::ErrorKind::ConnectionRefused | io::ErrorKind::ConnectionAborted | io::ErrorKind::ConnectionReset
    )
}

/// What a connection is doing, shared between its socket wrapper and the transport's request hook.
pub struct Activity {
    header_read: Duration,
    idle: Duration,
    accepted: Instant,
    state: Mutex<ActivityState>,
    /// The task reading the connection, woken when the last request in flight ends (its read deadline
    /// changes from none to the idle one).
    reader: AtomicWaker,
}

struct ActivityState {
    in_flight: usize,
    requests: u64,
    /// When the connection last became idle (accept, or the end of its last request).
    idle_since: Instant,
    /// First byte of the next HTTP/1.1 request head, while idle.
    head_started: Option<Instant>,
    received: u64,
    /// HTTP/2 (gRPC, h2c): idle bytes are control frames (pings, window updates), not a request head, and
    /// once the preface is in, a connection may wait for its first call like any idle one.
    multiplexed: bool,
}

/// Length of the HTTP/2 connection preface (`PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n`).
const H2_PREFACE_LEN: u64 = 24;

impl Activity {
    fn new(limits: ConnectionLimits, protocol: Protocol) -> Self {
        let now = Instant::now();
        Self {
            header_read: limits.header_read,
            idle: limits.idle,
            accepted: now,
            state: Mutex::new(ActivityState {
                in_flight: 0,
                requests: 0,
                idle_since: now,
                head_started: None,
                received: 0,
                multiplexed: protocol == Protocol::Http2,
            }),
            reader: AtomicWaker::new(),
        }
    }

    /// A request began; it is in flight until the guard drops (keep it with the response body).
    pub fn begin(self: &Arc<Self>) -> RequestGuard {
        let mut s = self.state.lock();
        s.in_flight += 1;
        s.requests += 1;
        s.head_started = None;
        RequestGuard(Arc::clone(self))
    }

    fn received(&self, bytes: &[u8]) {
        let mut s = self.state.lock();
        if s.received == 0 && bytes.starts_with(b"PRI ") {
            s.multiplexed = true;
        }
        s.received += bytes.len() as u64;
        if s.in_flight == 0 && s.requests > 0 && !s.multiplexed && s.head_started.is_none() {
            s.head_started = Some(Instant::now());
        }
    }

    /// When a pending read gives up: none while a request is in flight (its own deadlines apply).
    fn read_deadline(&self) -> Option<Instant> {
        let s = self.state.lock();
        if s.in_flight > 0 {
            return None;
        }
        let handshaken = s.multiplexed && s.received >= H2_PREFACE_LEN;
        if s.requests == 0 && !handshaken {
            return Some(self.accepted + self.header_read);
        }
        let idle = s.idle_since + self.idle;
        Some(s.head_started.map_or(idle, |h| idle.min(h + self.header_read)))
    }
}

/// Keeps a request counted as in flight; see [`Activity::begin`].
pub struct RequestGuard(Arc<Activity>);

impl Drop for RequestGuard {
    fn drop(&mut self) {
        let mut s = self.0.state.lock();
        s.in_flight -= 1;
        if s.in_flight == 0 {
            s.idle_since = Instant::now();
            s.head_started = None;
            drop(s);
            self.0.reader.wake();
        }
    }
}

/// An accepted socket that closes itself (its reads or writes fail with `TimedOut`) when a rule of the
/// module docs says so, and frees its listener slot when dropped.
pub struct Conn {
    io: TcpStream,
    activity: Arc<Activity>,
    idle: Duration,
    read_timer: Pin<Box<Sleep>>,
    write_timer: Pin<Box<Sleep>>,
    write_stalled_since: Option<Instant>,
    /// Set once the write half is shut down: the end of the lingering close.
    linger: Option<Pin<Box<Sleep>>>,
    _slot: OwnedSemaphorePermit,
}

/// The longest a closing connection waits for its client to close its side (nginx's `lingering_timeout`
/// default), and never longer than the idle time.
pub const LINGER: Duration = Duration::from_secs(5);

/// Reads of a lingering close per poll, before it yields the thread.
const LINGER_READS_PER_POLL: usize = 64;

fn timed_out(what: &str) -> io::Error {
    io::Error::new(io::ErrorKind::TimedOut, what.to_string())
}

impl Conn {
    fn new(io: TcpStream, slot: OwnedSemaphorePermit, limits: ConnectionLimits, protocol: Protocol) -> Self {
        let far = Instant::now() + Duration::from_secs(86_400);
        Self {
            io,
            activity: Arc::new(Activity::new(limits, protocol)),
            idle: limits.idle,
            read_timer: Box::pin(tokio::time::sleep_until(far)),
            write_timer: Box::pin(tokio::time::sleep_until(far)),
            write_stalled_since: None,
            linger: None,
            _slot: slot,
        }
    }

    pub fn activity(&self) -> Arc<Activity> {
        Arc::clone(&self.activity)
    }

    /// Called when a write is pending: fails once writes made no progress for the idle time.
    fn poll_write_stall(&mut self, cx: &mut Context<'_>) -> Poll<io::Result<usize>> {
        let since = *self.write_stalled_since.get_or_insert_with(Instant::now);
        self.write_timer.as_mut().reset(since + self.idle);
        match self.write_timer.as_mut().poll(cx) {
            Poll::Ready(()) => {
                tracing::debug!("closing a connection whose client stopped reading");
                Poll::Ready(Err(timed_out("the client stopped reading")))
            }
            Poll::Pending => Poll::Pending,
        }
    }
}

impl AsyncRead for Conn {
    fn poll_read(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<io::Result<()>> {
        let this = &mut *self;
        let before = buf.filled().len();
        match Pin::new(&mut this.io).poll_read(cx, buf) {
            Poll::Ready(Ok(())) => {
                if buf.filled().len() > before {
                    this.activity.received(&buf.filled()[before..]);
                }
                Poll::Ready(Ok(()))
            }
            Poll::Ready(Err(e)) => Poll::Ready(Err(e)),
            Poll::Pending => {
                this.activity.reader.register(cx.waker());
                let Some(deadline) = this.activity.read_deadline() else { return Poll::Pending };
                this.read_timer.as_mut().reset(deadline);
                match this.read_timer.as_mut().poll(cx) {
                    Poll::Ready(()) => {
                        tracing::debug!("closing a connection that sent no complete request in time");
                        Poll::Ready(Err(timed_out("no request within the header-read or idle timeout")))
                    }
                    Poll::Pending => Poll::Pending,
                }
            }
        }
    }
}

impl AsyncWrite for Conn {
    fn poll_write(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<io::Result<usize>> {
        let this = &mut *self;
        match Pin::new(&mut this.io).poll_write(cx, buf) {
            Poll::Pending => this.poll_write_stall(cx),
            ready => {
                this.write_stalled_since = None;
                ready
            }
        }
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        let this = &mut *self;
        match Pin::new(&mut this.io).poll_write_vectored(cx, bufs) {
            Poll::Pending => this.poll_write_stall(cx),
            ready => {
                this.write_stalled_since = None;
                ready
            }
        }
    }

    fn is_write_vectored(&self) -> bool {
        self.io.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.io).poll_flush(cx)
    }

    /// A lingering close: the write half's FIN first, then whatever the client still sends is read and
    /// discarded until it closes its side (or [`LINGER`] passes, or it resets). Closing a socket with unread
    /// bytes makes the kernel answer with a reset, which throws away the part of the last response not yet
    /// delivered; an HTTP/2 client keeps sending window updates while it reads that response.
    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = &mut *self;
        if this.linger.is_none() {
            std::task::ready!(Pin::new(&mut this.io).poll_shutdown(cx))?;
            this.linger = Some(Box::pin(tokio::time::sleep(LINGER.min(this.idle))));
        }
        let mut scrap = [0u8; 2048];
        for _ in 0..LINGER_READS_PER_POLL {
            let mut buf = ReadBuf::new(&mut scrap);
            match Pin::new(&mut this.io).poll_read(cx, &mut buf) {
                Poll::Ready(Ok(())) if buf.filled().is_empty() => return Poll::Ready(Ok(())),
                Poll::Ready(Ok(())) => continue,
                // A reset from the client: nothing of ours is left to protect.
                Poll::Ready(Err(_)) => return Poll::Ready(Ok(())),
                Poll::Pending => {
                    let timer = this.linger.as_mut().expect("set above");
                    return timer.as_mut().poll(cx).map(Ok);
                }
            }
        }
        // A client that keeps sending gets no more than the linger time, and the task's thread is not held.
        if this.linger.as_mut().expect("set above").as_mut().poll(cx).is_ready() {
            return Poll::Ready(Ok(()));
        }
        cx.waker().wake_by_ref();
        Poll::Pending
    }
}

/// The connection's activity, as tonic's connect info: tonic puts it into every request's extensions,
/// where [`CountRequestsLayer`] finds it.
#[derive(Clone)]
pub struct ConnActivity(pub Arc<Activity>);

impl tonic::transport::server::Connected for Conn {
    type ConnectInfo = ConnActivity;

    fn connect_info(&self) -> ConnActivity {
        ConnActivity(self.activity())
    }
}

/// A response body that keeps its request counted as in flight until it is done or dropped.
pub struct GuardedBody<B> {
    inner: B,
    _guard: Option<RequestGuard>,
}

impl<B> GuardedBody<B> {
    pub fn new(inner: B, guard: Option<RequestGuard>) -> Self {
        Self { inner, _guard: guard }
    }
}

impl<B: http_body::Body + Unpin> http_body::Body for GuardedBody<B> {
    type Data = B::Data;
    type Error = B::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<Self::Data>, Self::Error>>> {
        Pin::new(&mut self.inner).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}

/// The tower layer (for tonic) that counts each call as in flight on its connection.
#[derive(Clone, Copy, Default)]
pub struct CountRequestsLayer;

impl<S> tower::Layer<S> for CountRequestsLayer {
    type Service = CountRequests<S>;

    fn layer(&self, inner: S) -> CountRequests<S> {
        CountRequests(inner)
    }
}

/// See [`CountRequestsLayer`].
#[derive(Clone)]
pub struct CountRequests<S>(S);

type BoxFuture<T> = Pin<Box<dyn Future<Output = T> + Send + 'static>>;

impl<S, ReqBody> tower::Service<axum::http::Request<ReqBody>> for CountRequests<S>
where
    S: tower::Service<axum::http::Request<ReqBody>, Response = axum::http::Response<tonic::body::Body>>,
    S::Future: Send + 'static,
{
    type Response = axum::http::Response<tonic::body::Body>;
    type Error = S::Error;
    type Future = BoxFuture<Result<Self::Response, S::Error>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), S::Error>> {
        self.0.poll_ready(cx)
    }

    fn call(&mut self, req: axum::http::Request<ReqBody>) -> Self::Future {
        let guard = req.extensions().get::<ConnActivity>().map(|c| c.0.begin());
        let response = self.0.call(req);
        Box::pin(async move {
            let r = response.await?;
            Ok(r.map(|body| tonic::body::Body::new(GuardedBody::new(body, guard))))
        })
    }
}

/// The request body did not arrive within `server.body_read_timeout_ms`.
#[derive(Debug, thiserror::Error)]
#[error("the request body did not arrive within {ms} ms")]
pub struct BodyTimedOut {
    pub ms: u64,
}

/// An HTTP request body that fails with [`BodyTimedOut`] unless it is complete by its deadline.
pub struct DeadlineBody {
    inner: axum::body::Body,
    deadline: Pin<Box<Sleep>>,
    ms: u64,
}

impl DeadlineBody {
    pub fn new(inner: axum::body::Body, timeout: Duration) -> Self {
        Self { inner, deadline: Box::pin(tokio::time::sleep(timeout)), ms: timeout.as_millis() as u64 }
    }
}

impl http_body::Body for DeadlineBody {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<Bytes>, axum::Error>>> {
        let this = &mut *self;
        match Pin::new(&mut this.inner).poll_frame(cx) {
            Poll::Pending => match this.deadline.as_mut().poll(cx) {
                Poll::Ready(()) => Poll::Ready(Some(Err(axum::Error::new(BodyTimedOut { ms: this.ms })))),
                Poll::Pending => Poll::Pending,
            },
            ready => ready,
        }
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}

/// Whether `e` (or what caused it) is a [`BodyTimedOut`].
pub fn body_timed_out(e: &(dyn std::error::Error + 'static)) -> Option<u64> {
    let mut cur = Some(e);
    while let Some(err) = cur {
        if let Some(t) = err.downcast_ref::<BodyTimedOut>() {
            return Some(t.ms);
        }
        cur = err.source();
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits() -> ConnectionLimits {
        ConnectionLimits {
            max_connections: 4,
            header_read: Duration::from_secs(10),
            idle: Duration::from_secs(60),
            tcp_keepalive: None,
        }
    }

    /// The flaky shutdown test's failure, made certain: the server writes a response larger than the socket
    /// buffers hold, shuts down and closes while bytes the client sent later lie unread. A plain close then
    /// makes the kernel reset the connection and drop what it had not yet sent; the lingering close lets the
    /// client read the whole response and its end.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_closing_connection_delivers_its_last_response_though_the_client_sent_more() {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let listener =
            Listener::new(TcpListener::bind("127.0.0.1:0").await.unwrap(), limits(), Protocol::Http2, "test");
        let addr = listener.local_addr().unwrap();
        const RESPONSE: usize = 16 << 20;
        let server = tokio::spawn(async move {
            let (mut conn, _) = listener.accept().await;
            let mut first = [0u8; 4];
            conn.read_exact(&mut first).await.unwrap();
            conn.write_all(&vec![7u8; RESPONSE]).await.unwrap();
            conn.shutdown().await.unwrap();
        });
        let mut client = TcpStream::connect(addr).await.unwrap();
        client.write_all(b"ask!").await.unwrap();
        let mut got = vec![0u8; 64 << 10];
        let mut total = client.read(&mut got).await.unwrap();
        // Control bytes the server never reads (as an HTTP/2 client's window updates), then the rest.
        client.write_all(&[0u8; 512]).await.unwrap();
        let end = loop {
            match client.read(&mut got).await {
                Ok(0) => break Ok(()),
                Ok(n) => total += n,
                Err(e) => break Err(e),
            }
        };
        assert_eq!((end.map_err(|e| e.kind()), total), (Ok(()), RESPONSE), "the whole response, then its end");
        drop(client);
        server.await.unwrap();
    }

    #[test]
    fn http1_deadlines_follow_the_request_cycle() {
        let a = Arc::new(Activity::new(limits(), Protocol::Http1OrHttp2));
        assert_eq!(a.read_deadline(), Some(a.accepted + Duration::from_secs(10)), "first head from accept");
        a.received(b"GET / HTTP/1.1\r\n");
        let guard = a.begin();
        assert_eq!(a.read_deadline(), None, "nothing while a request is in flight");
        drop(guard);
        let idle = a.read_deadline().unwrap();
        assert!(idle >= a.accepted + Duration::from_secs(60), "then the idle time");
        a.received(b"GET /hea");
        let head = a.read_deadline().unwrap();
        assert!(head < idle && head >= a.accepted + Duration::from_secs(10), "a started head has 10 s");
    }

    #[test]
    fn http2_connections_wait_for_calls_like_idle_ones_once_the_preface_is_in() {
        let a = Arc::new(Activity::new(limits(), Protocol::Http1OrHttp2));
        a.received(b"PRI * HTTP/2.0\r\n\r\n");
        assert_eq!(a.read_deadline(), Some(a.accepted + Duration::from_secs(10)), "preface not complete");
        a.received(b"SM\r\n\r\n");
        assert_eq!(a.read_deadline(), Some(a.accepted + Duration::from_secs(60)));
        drop(a.begin());
        a.received(b"\x00\x00\x08\x06\x00");
        let d = a.read_deadline().unwrap();
        assert!(d >= a.accepted + Duration::from_secs(60), "control frames are not a request head");
        let g = Arc::new(Activity::new(limits(), Protocol::Http2));
        assert_eq!(g.read_deadline(), Some(g.accepted + Duration::from_secs(10)));
    }
}
