//! The HTTP/1.1 front of `precimap serve`: an accept loop that caps open connections, closes a
//! connection whose request headers arrive too slowly or that sits idle between requests, and
//! fails a request body that arrives too slowly. The router behind it decides about each request
//! (authentication, load shedding, rate limits); this layer bounds what a client can hold open
//! without ever completing a request.

use axum::body::Body;
use axum::extract::ConnectInfo;
use axum::http::{header, HeaderValue, Request, StatusCode};
use axum::Router;
use bytes::Bytes;
use http_body::{Body as HttpBody, Frame, SizeHint};
use hyper::body::Incoming;
use hyper_util::rt::{TokioIo, TokioTimer};
use std::future::Future;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{Notify, Semaphore};
use tokio::task::JoinSet;
use tokio::time::{Instant, Sleep};
use tokio_util::sync::CancellationToken;
use tower::ServiceExt;

/// What one connection may hold open.
#[derive(Clone, Debug)]
pub struct ConnectionLimits {
    /// Open connections at most; further clients wait in the listen backlog until one closes.
    pub max_connections: usize,
    /// From a request's first byte until its header is complete.
    pub header_timeout: Duration,
    /// Between requests on a kept-alive connection (and before a new connection's first byte).
    pub idle_timeout: Duration,
    /// Longest wait for the next part of a request body, and the grace period before
    /// `body_min_rate` applies.
    pub body_timeout: Duration,
    /// Bytes per second a body must average over the time the server waits for it (beyond the
    /// `body_timeout` grace); 0 turns the rate check off.
    pub body_min_rate: u64,
}

impl Default for ConnectionLimits {
    fn default() -> Self {
        Self {
            max_connections: 1024,
            header_timeout: Duration::from_secs(20),
            idle_timeout: Duration::from_secs(60),
            body_timeout: Duration::from_secs(30),
            body_min_rate: 1024,
        }
    }
}

/// Serves `router` on `listener` until `shutdown` completes; then stops accepting, lets the open
/// requests finish (idle connections close at once) and returns.
pub async fn serve(
    listener: TcpListener,
    router: Router,
    limits: ConnectionLimits,
    shutdown: impl Future<Output = ()>,
) -> std::io::Result<()> {
    let limits = Arc::new(limits);
    let stop = CancellationToken::new();
    let permits = Arc::new(Semaphore::new(limits.max_connections.max(1)));
    let mut connections = JoinSet::new();
    tokio::pin!(shutdown);
    loop {
        while connections.try_join_next().is_some() {}
        let permit = tokio::select! {
            permit = permits.clone().acquire_owned() => match permit {
                Ok(permit) => permit,
                Err(_) => break,
            },
            () = &mut shutdown => break,
        };
        let (stream, peer) = tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok(accepted) => accepted,
                Err(e) => {
                    // Out of descriptors or a connection reset before it was accepted: keep
                    // serving the connections already open and try again shortly.
                    tracing::warn!(error = %e, "accepting a connection failed");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                    continue;
                }
            },
            () = &mut shutdown => break,
        };
        let _ = stream.set_nodelay(true);
        let (router, limits, stop) = (router.clone(), limits.clone(), stop.clone());
        connections.spawn(async move {
            serve_connection(stream, peer, router, &limits, stop).await;
            drop(permit);
        });
    }
    drop(listener);
    stop.cancel();
    while connections.join_next().await.is_some() {}
    Ok(())
}

async fn serve_connection(
    stream: TcpStream,
    peer: SocketAddr,
    router: Router,
    limits: &ConnectionLimits,
    stop: CancellationToken,
) {
    let clock = Arc::new(ConnectionClock::new());
    let io = TokioIo::new(WatchedStream { inner: stream, clock: clock.clone() });
    let body_limits = BodyLimits { timeout: limits.body_timeout, min_rate: limits.body_min_rate };
    let service_clock = clock.clone();
    let service = hyper::service::service_fn(move |request: Request<Incoming>| {
        let (router, clock) = (router.clone(), service_clock.clone());
        async move { Ok::<_, std::convert::Infallible>(handle(router, clock, peer, body_limits, request).await) }
    });
    let mut builder = hyper::server::conn::http1::Builder::new();
    // The connection clock below times headers and idle periods separately (hyper's own header
    // timeout also runs while a kept-alive connection is idle).
    builder.timer(TokioTimer::new()).header_read_timeout(None).keep_alive(true).max_buf_size(64 << 10);
    let connection = builder.serve_connection(io, service);
    tokio::pin!(connection);
    let watchdog = clock.watchdog(limits.header_timeout, limits.idle_timeout);
    tokio::pin!(watchdog);
    let mut stopping = false;
    loop {
        tokio::select! {
            result = connection.as_mut() => {
                if let Err(e) = result {
                    tracing::debug!(%peer, error = %e, "connection ended with an error");
                }
                return;
            }
            reason = &mut watchdog => {
                tracing::debug!(%peer, reason, "closing connection");
                return;
            }
            () = stop.cancelled(), if !stopping => {
                stopping = true;
                connection.as_mut().graceful_shutdown();
            }
        }
    }
}

/// One request through the router: the body wrapped in its rate check, the client's address
/// attached, and the response body tracked so that the connection counts as busy until the
/// response has been sent.
async fn handle(
    router: Router,
    clock: Arc<ConnectionClock>,
    peer: SocketAddr,
    body_limits: BodyLimits,
    request: Request<Incoming>,
) -> axum::response::Response {
    let busy = clock.request_started();
    let too_slow = Arc::new(AtomicBool::new(false));
    let mut request = if request.body().is_end_stream() {
        request.map(|_| Body::empty())
    } else {
        let flag = too_slow.clone();
        request.map(|body| Body::new(RateCheckedBody::new(body, body_limits, flag)))
    };
    request.extensions_mut().insert(ConnectInfo(peer));
    let mut response = match router.oneshot(request).await {
        Ok(response) => response,
        Err(never) => match never {},
    };
    if too_slow.load(Ordering::Relaxed) {
        *response.status_mut() = StatusCode::REQUEST_TIMEOUT;
        response.headers_mut().insert(header::CONNECTION, HeaderValue::from_static("close"));
    }
    response.map(|body| Body::new(TrackedBody { inner: body, _busy: busy }))
}

/// What a connection is doing, for its header and idle timeouts.
#[derive(Clone, Copy, Debug)]
enum Phase {
    /// No request in progress since this instant.
    Idle(Instant),
    /// A request's first bytes arrived at this instant; its header is not complete.
    Header(Instant),
    /// This many requests are being handled or having their responses sent.
    Busy(usize),
}

#[derive(Debug)]
struct ConnectionClock {
    phase: Mutex<Phase>,
    changed: Notify,
}

impl ConnectionClock {
    fn new() -> Self {
        Self { phase: Mutex::new(Phase::Idle(Instant::now())), changed: Notify::new() }
    }

    fn update(&self, f: impl FnOnce(Phase) -> Phase) {
        let mut phase = self.phase.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
        *phase = f(*phase);
        drop(phase);
        self.changed.notify_one();
    }

    fn bytes_arrived(&self) {
        let idle = matches!(*self.phase.lock().unwrap_or_else(|p| p.into_inner()), Phase::Idle(_));
        if idle {
            self.update(|phase| match phase {
                Phase::Idle(_) => Phase::Header(Instant::now()),
                other => other,
            });
        }
    }

    fn request_started(self: &Arc<Self>) -> BusyGuard {
        self.update(|phase| match phase {
            Phase::Busy(n) => Phase::Busy(n + 1),
            _ => Phase::Busy(1),
        });
        BusyGuard { clock: self.clone() }
    }

    /// Completes when the connection has waited too long for a header or sat idle too long;
    /// returns which.
    async fn watchdog(&self, header_timeout: Duration, idle_timeout: Duration) -> &'static str {
        loop {
            let changed = self.changed.notified();
            let phase = *self.phase.lock().unwrap_or_else(|p| p.into_inner());
            let (deadline, reason) = match phase {
                Phase::Idle(since) => (later(since, idle_timeout), "idle timeout"),
                Phase::Header(since) => (later(since, header_timeout), "header timeout"),
                Phase::Busy(_) => {
                    changed.await;
                    continue;
                }
            };
            if Instant::now() >= deadline {
                return reason;
            }
            tokio::select! {
                () = tokio::time::sleep_until(deadline) => {}
                () = changed => {}
            }
        }
    }
}

/// `since + wait`, or a year from now for a wait too long to represent.
fn later(since: Instant, wait: Duration) -> Instant {
    since.checked_add(wait).unwrap_or_else(|| Instant::now() + Duration::from_secs(365 * 86_400))
}

/// Marks its request finished (the connection idle when it was the last) when dropped.
#[derive(Debug)]
struct BusyGuard {
    clock: Arc<ConnectionClock>,
}

impl Drop for BusyGuard {
    fn drop(&mut self) {
        self.clock.update(|phase| match phase {
            Phase::Busy(n) if n > 1 => Phase::Busy(n - 1),
            _ => Phase::Idle(Instant::now()),
        });
    }
}

/// The socket, reporting each read to the connection's clock.
#[derive(Debug)]
struct WatchedStream {
    inner: TcpStream,
    clock: Arc<ConnectionClock>,
}

impl AsyncRead for WatchedStream {
    fn poll_read(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<std::io::Result<()>> {
        let before = buf.filled().len();
        let result = Pin::new(&mut self.inner).poll_read(cx, buf);
        if matches!(result, Poll::Ready(Ok(()))) && buf.filled().len() > before {
            self.clock.bytes_arrived();
        }
        result
    }
}

impl AsyncWrite for WatchedStream {
    fn poll_write(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write(cx, buf)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }
}

/// A response body that keeps its connection marked busy until it is sent (or dropped).
struct TrackedBody {
    inner: Body,
    _busy: BusyGuard,
}

impl HttpBody for TrackedBody {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Result<Frame<Bytes>, axum::Error>>> {
        Pin::new(&mut self.inner).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

#[derive(Clone, Copy, Debug)]
struct BodyLimits {
    timeout: Duration,
    min_rate: u64,
}

/// The error a too-slow body ends with.
#[derive(Debug, thiserror::Error)]
#[error(
    "the request body arrived too slowly (at least {min_rate} bytes/s after a {grace_s} s grace period, and no \
     pause longer than {grace_s} s); send it faster or in one go"
)]
pub struct BodyTooSlow {
    min_rate: u64,
    grace_s: u64,
}

/// A request body that fails when the client makes the server wait too long: for any one part
/// longer than the timeout, or in total longer than the timeout plus the time its bytes would
/// take at the minimum rate. Only time spent waiting on the client counts, not time the handler
/// takes between reads (a slow store upstream is not the client's fault).
struct RateCheckedBody {
    inner: Incoming,
    limits: BodyLimits,
    received: u64,
    waited: Duration,
    waiting_since: Option<Instant>,
    deadline: Pin<Box<Sleep>>,
    too_slow: Arc<AtomicBool>,
}

impl RateCheckedBody {
    fn new(inner: Incoming, limits: BodyLimits, too_slow: Arc<AtomicBool>) -> Self {
        Self {
            inner,
            limits,
            received: 0,
            waited: Duration::ZERO,
            waiting_since: None,
            deadline: Box::pin(tokio::time::sleep(limits.timeout)),
            too_slow,
        }
    }

    /// How much longer than already waited the client may keep the server waiting from now.
    fn allowance(&self) -> Duration {
        let earned = if self.limits.min_rate == 0 {
            Duration::MAX
        } else {
            let at_min_rate = Duration::try_from_secs_f64(self.received as f64 / self.limits.min_rate as f64);
            self.limits.timeout.saturating_add(at_min_rate.unwrap_or(Duration::MAX))
        };
        self.limits.timeout.min(earned.saturating_sub(self.waited))
    }
}

impl HttpBody for RateCheckedBody {
    type Data = Bytes;
    type Error = Box<dyn std::error::Error + Send + Sync>;

    fn poll_frame(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Result<Frame<Bytes>, Self::Error>>> {
        let this = &mut *self;
        match Pin::new(&mut this.inner).poll_frame(cx) {
            Poll::Ready(frame) => {
                if let Some(since) = this.waiting_since.take() {
                    this.waited += since.elapsed();
                }
                if let Some(Ok(data)) = frame.as_ref().map(|f| f.as_ref().map(Frame::data_ref)) {
                    this.received += data.map_or(0, |d| d.len() as u64);
                }
                Poll::Ready(frame.map(|f| f.map_err(Into::into)))
            }
            Poll::Pending => {
                if this.waiting_since.is_none() {
                    let now = Instant::now();
                    this.waiting_since = Some(now);
                    let allowance = this.allowance();
                    this.deadline.as_mut().reset(later(now, allowance));
                }
                if this.deadline.as_mut().poll(cx).is_ready() {
                    this.too_slow.store(true, Ordering::Relaxed);
                    let grace_s = this.limits.timeout.as_secs();
                    return Poll::Ready(Some(Err(Box::new(BodyTooSlow { min_rate: this.limits.min_rate, grace_s }))));
                }
                Poll::Pending
            }
        }
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}
