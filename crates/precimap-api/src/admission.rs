//! Who may make the server do work, decided from a request's headers before its body is read:
//! writes need the bearer token and a free write slot, reads are rate-limited per client, and
//! requests beyond the in-flight limit are shed with 503 rather than queued.

use crate::errors::ApiError;
use crate::server::ApiState;
use axum::extract::{ConnectInfo, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, Method, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::sync::Semaphore;

/// How writers prove who they are.
#[derive(Clone, Debug)]
pub enum Auth {
    /// Writes need `Authorization: Bearer <token>` (the scheme in any letter case).
    Token(String),
    /// No authentication (only for a server bound to loopback in tests and the embedded mode).
    Disabled,
}

/// Limits on the requests the router works on at once and on each client's reads.
#[derive(Clone, Debug)]
pub struct AdmissionLimits {
    /// Requests handled at once; more are answered 503 at once.
    pub max_in_flight: usize,
    /// Authorised writes (manifests, uploads, cancels, deletes) handled at once; more get 503.
    /// Each buffers at most one manifest, so this bounds the memory writes can take.
    pub max_in_flight_writes: usize,
    /// Sustained reads per second per client address (0: unlimited).
    pub reads_per_s: f64,
    /// Reads a client may make in a burst above the sustained rate.
    pub read_burst: f64,
}

impl Default for AdmissionLimits {
    fn default() -> Self {
        Self { max_in_flight: 256, max_in_flight_writes: 16, reads_per_s: 20.0, read_burst: 100.0 }
    }
}

/// The shared state of the admission checks.
#[derive(Debug)]
pub struct Admission {
    pub limits: AdmissionLimits,
    writes: Arc<Semaphore>,
    readers: Mutex<HashMap<IpAddr, Bucket>>,
}

/// Clients whose buckets are tracked at most; full buckets are forgotten first.
const MAX_TRACKED_CLIENTS: usize = 10_000;

impl Admission {
    pub fn new(limits: AdmissionLimits) -> Self {
        Self {
            writes: Arc::new(Semaphore::new(limits.max_in_flight_writes.max(1))),
            limits,
            readers: Mutex::new(HashMap::new()),
        }
    }

    /// Takes one read from `client`'s bucket; `Err(wait)` when it is empty.
    fn take_read(&self, client: IpAddr, now: Instant) -> Result<(), Duration> {
        let (rate, burst) = (self.limits.reads_per_s, self.limits.read_burst.max(1.0));
        if rate <= 0.0 {
            return Ok(());
        }
        let mut readers = self.readers.lock().unwrap_or_else(|p| p.into_inner());
        if readers.len() >= MAX_TRACKED_CLIENTS && !readers.contains_key(&client) {
            readers.retain(|_, b| b.level(now, rate, burst) < burst);
            if readers.len() >= MAX_TRACKED_CLIENTS {
                // Every tracked client is mid-burst: forget them all rather than grow.
                readers.clear();
            }
        }
        let bucket = readers.entry(client).or_insert(Bucket { tokens: burst, at: now });
        let level = bucket.level(now, rate, burst);
        if level >= 1.0 {
            *bucket = Bucket { tokens: level - 1.0, at: now };
            Ok(())
        } else {
            Err(Duration::from_secs_f64((1.0 - level) / rate))
        }
    }
}

#[derive(Clone, Copy, Debug)]
struct Bucket {
    tokens: f64,
    at: Instant,
}

impl Bucket {
    fn level(&self, now: Instant, rate: f64, burst: f64) -> f64 {
        (self.tokens + now.saturating_duration_since(self.at).as_secs_f64() * rate).min(burst)
    }
}

fn is_read(method: &Method) -> bool {
    matches!(*method, Method::GET | Method::HEAD | Method::OPTIONS)
}

/// Writes: the token, then a write slot, both before anything reads the body. A refused write
/// also closes its connection, so that its unread body is never drained.
pub async fn admit(State(state): State<Arc<ApiState>>, request: Request, next: Next) -> Response {
    if is_read(request.method()) {
        let client = request.extensions().get::<ConnectInfo<SocketAddr>>().map(|c| c.0.ip());
        if let Some(client) = client {
            if let Err(wait) = state.admission.take_read(client, Instant::now()) {
                let mut response = ApiError::new(
                    StatusCode::TOO_MANY_REQUESTS,
                    format!(
                        "more than {} reads per second from this client; slow down",
                        state.admission.limits.reads_per_s
                    ),
                )
                .into_response();
                let seconds = wait.as_secs().max(1).to_string();
                if let Ok(value) = HeaderValue::from_str(&seconds) {
                    response.headers_mut().insert(header::RETRY_AFTER, value);
                }
                return response;
            }
        }
        return next.run(request).await;
    }
    if let Err(e) = authorize(&state, request.headers()) {
        return closing(e.into_response());
    }
    let Ok(_slot) = state.admission.writes.clone().try_acquire_owned() else {
        let mut response = closing(
            ApiError::new(
                StatusCode::SERVICE_UNAVAILABLE,
                format!(
                    "{} writes are in progress, the most this server takes at once; retry shortly",
                    state.admission.limits.max_in_flight_writes
                ),
            )
            .into_response(),
        );
        response.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from_static("1"));
        return response;
    };
    next.run(request).await
}

fn closing(mut response: Response) -> Response {
    response.headers_mut().insert(header::CONNECTION, HeaderValue::from_static("close"));
    response
}

/// The answer to a request shed because `max_in_flight` requests are in progress.
pub async fn overloaded(_: tower::BoxError) -> Response {
    let mut response = ApiError::new(
        StatusCode::SERVICE_UNAVAILABLE,
        "the server is at its limit of requests in progress; retry shortly",
    )
    .into_response();
    response.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from_static("1"));
    response
}

/// Checks `Authorization: Bearer <token>`; the scheme is case-insensitive (RFC 9110 §11.1).
pub fn authorize(state: &ApiState, headers: &HeaderMap) -> Result<(), ApiError> {
    let Auth::Token(expected) = &state.auth else { return Ok(()) };
    let given = headers.get(header::AUTHORIZATION).and_then(|v| v.to_str().ok()).and_then(bearer_token);
    match given {
        Some(token) if constant_time_eq(token.as_bytes(), expected.as_bytes()) => Ok(()),
        Some(_) => Err(ApiError::new(StatusCode::UNAUTHORIZED, "wrong bearer token")),
        None => Err(ApiError::new(
            StatusCode::UNAUTHORIZED,
            "writes need `Authorization: Bearer <token>` (the server's PRECIMAP_TOKEN)",
        )),
    }
}

/// The token of a `Bearer` credential, the scheme matched in any case.
fn bearer_token(value: &str) -> Option<&str> {
    let (scheme, token) = value.trim_start().split_once(' ')?;
    scheme.eq_ignore_ascii_case("bearer").then(|| token.trim()).filter(|t| !t.is_empty())
}

/// Compares without an early exit, so response time does not reveal how much of a guess was
/// right (the length may leak; the token's entropy does not depend on it).
fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_bearer_scheme_is_case_insensitive() {
        assert_eq!(bearer_token("Bearer abc"), Some("abc"));
        assert_eq!(bearer_token("bearer abc"), Some("abc"));
        assert_eq!(bearer_token("BEARER  abc "), Some("abc"));
        assert_eq!(bearer_token("Basic abc"), None);
        assert_eq!(bearer_token("Bearer "), None);
        assert_eq!(bearer_token("Bearerabc"), None);
    }

    #[test]
    fn reads_are_limited_per_client_and_refill() {
        let admission =
            Admission::new(AdmissionLimits { reads_per_s: 10.0, read_burst: 3.0, ..AdmissionLimits::default() });
        let (a, b): (IpAddr, IpAddr) = ("10.0.0.1".parse().unwrap(), "10.0.0.2".parse().unwrap());
        let t0 = Instant::now();
        for _ in 0..3 {
            assert!(admission.take_read(a, t0).is_ok());
        }
        let wait = admission.take_read(a, t0).unwrap_err();
        assert!(wait <= Duration::from_millis(100), "{wait:?}");
        // Another client has its own bucket; the first refills at the sustained rate.
        assert!(admission.take_read(b, t0).is_ok());
        assert!(admission.take_read(a, t0 + Duration::from_millis(110)).is_ok());
        assert!(admission.take_read(a, t0 + Duration::from_millis(110)).is_err());
    }
}
