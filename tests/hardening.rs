//! `precimap serve` against hostile and careless clients, over real sockets on loopback: each
//! test starts the real binary (its own port, job store and file store) and speaks raw HTTP/1.1
//! to it, so that what is measured is what a client meets — which bytes the server reads, when
//! it closes a connection, how much memory it takes, and what its error responses say.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

const TOKEN: &str = "hardening-token";
const FOUR_MIB: usize = 4 << 20;

/// A `precimap serve` child process, killed when dropped.
struct Server {
    child: Child,
    port: u16,
    dir: tempfile::TempDir,
}

impl Server {
    fn start(extra: &[&str]) -> Self {
        let dir = tempfile::tempdir().unwrap();
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let log = std::fs::File::create(dir.path().join("serve.log")).unwrap();
        let child = Command::new(env!("CARGO_BIN_EXE_precimap"))
            .args(["serve", "--listen", &format!("127.0.0.1:{port}")])
            .arg("--db")
            .arg(format!("sqlite://{}/jobs.db", dir.path().display()))
            .arg("--store")
            .arg(format!("file://{}", dir.path().join("store").display()))
            .args(extra)
            .env("PRECIMAP_TOKEN", TOKEN)
            .env("PRECIMAP_LOG", "info")
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .expect("spawn precimap serve");
        let mut server = Self { child, port, dir };
        let started = Instant::now();
        loop {
            if let Some(status) = server.child.try_wait().unwrap() {
                panic!("precimap serve exited ({status}): {}", server.log());
            }
            let answer = blocking_get(port, "/healthz");
            if answer.as_ref().is_some_and(|a| a.status == 200) {
                break;
            }
            assert!(started.elapsed() < Duration::from_secs(30), "precimap serve does not answer: {}", server.log());
            std::thread::sleep(Duration::from_millis(50));
        }
        server
    }

    fn log(&self) -> String {
        std::fs::read_to_string(self.dir.path().join("serve.log")).unwrap_or_default()
    }

    fn store(&self) -> PathBuf {
        self.dir.path().join("store")
    }

    /// The server's resident memory in KiB (`VmRSS` of /proc/PID/status).
    fn rss_kib(&self) -> u64 {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.child.id())).unwrap();
        let line = status.lines().find(|l| l.starts_with("VmRSS:")).expect("VmRSS");
        line.split_whitespace().nth(1).unwrap().parse().unwrap()
    }

    fn addr(&self) -> String {
        format!("127.0.0.1:{}", self.port)
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

#[derive(Debug)]
struct Answer {
    status: u16,
    head: String,
    body: String,
}

impl Answer {
    fn parse(raw: &[u8]) -> Option<Self> {
        let text = String::from_utf8_lossy(raw);
        let (head, body) = text.split_once("\r\n\r\n")?;
        let status = head.split_whitespace().nth(1)?.parse().ok()?;
        Some(Self { status, head: head.to_ascii_lowercase(), body: body.to_string() })
    }

    fn json(&self) -> serde_json::Value {
        serde_json::from_str(&self.body).unwrap_or_else(|e| panic!("not JSON ({e}): {self:?}"))
    }

    /// An error response in the API's shape, naming no path, URL or store of the server.
    fn assert_clean_error(&self, server: &Server) {
        assert!(self.status >= 400, "{self:?}");
        assert!(self.head.contains("content-type: application/json"), "{self:?}");
        let json = self.json();
        assert!(json["error"].as_str().is_some_and(|e| !e.is_empty()), "{self:?}");
        let root = server.dir.path().display().to_string();
        for leak in [root.as_str(), "file://", "s3://", "/tmp/", "sqlite:", "jobs.db"] {
            assert!(!self.body.contains(leak), "the answer shows {leak:?}: {self:?}");
        }
    }
}

/// One request on a fresh connection (closed after it), its whole answer read within `limit`.
async fn exchange(addr: &str, request: &[u8], limit: Duration) -> Option<Answer> {
    let work = async {
        let mut stream = TcpStream::connect(addr).await.ok()?;
        stream.write_all(request).await.ok()?;
        let mut raw = Vec::new();
        let _ = stream.read_to_end(&mut raw).await;
        Answer::parse(&raw)
    };
    tokio::time::timeout(limit, work).await.ok().flatten()
}

fn request(method: &str, path: &str, auth: Option<&str>, body: &str) -> Vec<u8> {
    let auth = auth.map(|a| format!("Authorization: {a}\r\n")).unwrap_or_default();
    format!(
        "{method} {path} HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n{auth}Content-Type: application/json\r\n\
         Content-Length: {}\r\n\r\n{body}",
        body.len()
    )
    .into_bytes()
}

fn bearer() -> String {
    format!("Bearer {TOKEN}")
}

fn blocking_get(port: u16, path: &str) -> Option<Answer> {
    use std::io::{Read as _, Write as _};
    let mut stream = std::net::TcpStream::connect(("127.0.0.1", port)).ok()?;
    stream.set_read_timeout(Some(Duration::from_secs(5))).ok()?;
    stream.write_all(&request("GET", path, None, "")).ok()?;
    let mut raw = Vec::new();
    let _ = stream.read_to_end(&mut raw);
    Answer::parse(&raw)
}

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap()
}

/// Waits until the server closes `stream` (EOF or reset); how long that took, or `None` after
/// `limit`.
async fn closed_within(stream: &mut TcpStream, limit: Duration) -> Option<Duration> {
    let started = Instant::now();
    let mut buf = [0u8; 4096];
    tokio::time::timeout(limit, async {
        loop {
            match stream.read(&mut buf).await {
                Ok(0) | Err(_) => return started.elapsed(),
                Ok(_) => {}
            }
        }
    })
    .await
    .ok()
}

/// A submission with a 4 MiB body and no token: the 401 must come back whether or not the
/// client ever sends the body, and the server must close the connection instead of draining it.
async fn unauthenticated_submission(mut stream: TcpStream, send_body: bool) -> Result<Answer, String> {
    let head = format!(
        "POST /v1/campaigns HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/json\r\n\
         Content-Length: {FOUR_MIB}\r\n\r\n"
    );
    stream.write_all(head.as_bytes()).await.map_err(|e| format!("header: {e}"))?;
    let (mut reader, mut writer) = stream.into_split();
    let body = tokio::spawn(async move {
        if send_body {
            let chunk = vec![b' '; 64 << 10];
            for _ in 0..FOUR_MIB / chunk.len() {
                if writer.write_all(&chunk).await.is_err() {
                    break;
                }
            }
        }
        // Keep the write side open: a server that waits for the body waits for ever.
        tokio::time::sleep(Duration::from_secs(60)).await;
        drop(writer);
    });
    let mut raw = Vec::new();
    let mut buf = vec![0u8; 16 << 10];
    let read = tokio::time::timeout(Duration::from_secs(20), async {
        loop {
            match reader.read(&mut buf).await {
                Ok(0) | Err(_) => break,
                Ok(n) => raw.extend_from_slice(&buf[..n]),
            }
        }
    })
    .await;
    body.abort();
    if read.is_err() {
        return Err(format!("the connection stayed open for 20 s; read so far: {:?}", String::from_utf8_lossy(&raw)));
    }
    Answer::parse(&raw).ok_or_else(|| format!("no answer: {:?}", String::from_utf8_lossy(&raw)))
}

#[test]
fn unauthenticated_submissions_are_refused_without_reading_their_bodies() {
    // A read budget the health probe stays inside; every other limit at its default.
    let server = Server::start(&["--reads-per-s", "1000", "--read-burst", "1000"]);
    let rt = runtime();
    // No body sent at all: the 401 still arrives, so nothing waited for the body.
    let answer = rt
        .block_on(async { unauthenticated_submission(TcpStream::connect(server.addr()).await.unwrap(), false).await })
        .unwrap();
    assert_eq!(answer.status, 401, "{answer:?}");
    answer.assert_clean_error(&server);

    let flood = 1000;
    let before = server.rss_kib();
    let (latencies, answers, peak_kib) = rt.block_on(async {
        let addr = server.addr();
        let done = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let probes = Arc::new(std::sync::atomic::AtomicUsize::new(0));
        // The probe runs on its own thread with blocking sockets, so that the flood's client
        // tasks do not delay it on this side.
        let probe = {
            let (port, done, probes) = (server.port, done.clone(), probes.clone());
            std::thread::spawn(move || {
                let mut latencies = Vec::new();
                while !done.load(std::sync::atomic::Ordering::Relaxed) {
                    let started = Instant::now();
                    let answer = blocking_get(port, "/healthz");
                    let latency = started.elapsed();
                    assert_eq!(answer.map(|a| a.status), Some(200), "healthz during the flood");
                    latencies.push(latency);
                    probes.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    std::thread::sleep(Duration::from_millis(10));
                }
                latencies
            })
        };
        let mut peak = 0;
        let watch = {
            let pid = server.child.id();
            let done = done.clone();
            tokio::spawn(async move {
                let mut peak = 0u64;
                while !done.load(std::sync::atomic::Ordering::Relaxed) {
                    if let Ok(status) = std::fs::read_to_string(format!("/proc/{pid}/status")) {
                        let rss = status
                            .lines()
                            .find(|l| l.starts_with("VmRSS:"))
                            .and_then(|l| l.split_whitespace().nth(1)?.parse().ok())
                            .unwrap_or(0);
                        peak = peak.max(rss);
                    }
                    tokio::time::sleep(Duration::from_millis(10)).await;
                }
                peak
            })
        };
        // Rounds of `flood` submissions, each round's connections all open first and then every
        // submission sent at once, until the probe has enough answers to give a p99.
        let mut answers = Vec::new();
        let mut rounds = 0;
        while rounds < 10 && (rounds == 0 || probes.load(std::sync::atomic::Ordering::Relaxed) < 100) {
            let mut streams = Vec::with_capacity(flood);
            for _ in 0..flood {
                streams.push(TcpStream::connect(&addr).await.expect("connect (is `ulimit -n` at least 2500?)"));
            }
            let submissions: Vec<_> =
                streams.into_iter().map(|stream| tokio::spawn(unauthenticated_submission(stream, true))).collect();
            for s in submissions {
                answers.push(s.await.unwrap());
            }
            rounds += 1;
        }
        done.store(true, std::sync::atomic::Ordering::Relaxed);
        peak = peak.max(watch.await.unwrap());
        (probe.join().unwrap(), answers, peak)
    });
    let after = server.rss_kib();
    let refused = answers.iter().filter(|a| matches!(a, Ok(a) if a.status == 401)).count();
    let failures: Vec<_> = answers.iter().filter(|a| !matches!(a, Ok(a) if a.status == 401)).take(3).collect();
    assert_eq!(refused, answers.len(), "not every submission got its 401: {failures:?}");
    assert!(latencies.len() >= 100, "only {} /healthz probes during the flood", latencies.len());
    let mut sorted = latencies.clone();
    sorted.sort();
    let slowest: Vec<_> = sorted.iter().rev().take(5).collect();
    eprintln!("slowest /healthz answers: {slowest:?}");
    let p99 = sorted[(sorted.len() * 99).div_ceil(100) - 1];
    let growth_mib = peak_kib.max(after).saturating_sub(before) as f64 / 1024.0;
    eprintln!(
        "{} rounds of {flood} concurrent unauthenticated 4 MiB submissions: server RSS {:.1} MiB before, peak {:.1} MiB \
         (growth {growth_mib:.1} MiB), /healthz p50 {:?} p99 {:?} max {:?} over {} probes during the flood",
        answers.len() / flood,
        before as f64 / 1024.0,
        peak_kib as f64 / 1024.0,
        sorted[sorted.len() / 2],
        p99,
        sorted[sorted.len() - 1],
        sorted.len()
    );
    assert!(growth_mib < 100.0, "server RSS grew {growth_mib:.1} MiB");
    assert!(p99 < Duration::from_millis(100), "/healthz p99 {p99:?} during the flood");
}

#[test]
fn slow_headers_and_idle_connections_are_closed_within_their_timeouts() {
    let server = Server::start(&["--header-timeout-s", "1", "--idle-timeout-s", "2.5"]);
    let rt = runtime();
    rt.block_on(async {
        let addr = server.addr();
        // Never a byte: closed by the idle timeout.
        let opened = Instant::now();
        let mut silent = Vec::new();
        for _ in 0..200 {
            silent.push(TcpStream::connect(&addr).await.unwrap());
        }
        // Headers dribbled a byte every 200 ms: closed by the header timeout, long before the
        // header would be complete.
        let mut slow = Vec::new();
        for _ in 0..50 {
            let mut stream = TcpStream::connect(&addr).await.unwrap();
            stream.write_all(b"GET /healthz HTTP/1.1\r\nHost: l").await.unwrap();
            slow.push(stream);
        }
        let dribble = tokio::spawn(async move {
            let started = Instant::now();
            let mut open: Vec<Option<TcpStream>> = slow.into_iter().map(Some).collect();
            let mut closed_after = Vec::new();
            while started.elapsed() < Duration::from_secs(6) && open.iter().any(Option::is_some) {
                for slot in open.iter_mut() {
                    if let Some(stream) = slot {
                        if stream.write_all(b"o").await.is_err() {
                            closed_after.push(started.elapsed());
                            *slot = None;
                        }
                    }
                }
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
            (closed_after, open.iter().filter(|s| s.is_some()).count())
        });
        // A kept-alive connection after one answered request: closed by the idle timeout.
        let mut kept = TcpStream::connect(&addr).await.unwrap();
        kept.write_all(b"GET /healthz HTTP/1.1\r\nHost: localhost\r\n\r\n").await.unwrap();
        let mut buf = vec![0u8; 4096];
        let n = kept.read(&mut buf).await.unwrap();
        assert!(String::from_utf8_lossy(&buf[..n]).starts_with("HTTP/1.1 200"));
        let kept_closed = closed_within(&mut kept, Duration::from_secs(10)).await;

        // When the last silent connection was seen closed, from when the first was opened.
        let mut idle_closed = Vec::new();
        for stream in silent.iter_mut() {
            idle_closed.push(closed_within(stream, Duration::from_secs(10)).await.map(|_| opened.elapsed()));
        }
        let (slow_closed, still_open) = dribble.await.unwrap();
        eprintln!(
            "header timeout 1 s: 50 dribbling connections closed within {:?}; idle timeout 2.5 s: 200 silent \
             connections closed within {:?}, a kept-alive one after {kept_closed:?}",
            slow_closed.iter().max(),
            idle_closed.iter().flatten().max()
        );
        assert_eq!(still_open, 0, "dribbling connections still open after 6 s");
        // A write fails only once the close has come back, so allow a few dribble periods.
        assert!(slow_closed.iter().all(|t| *t < Duration::from_secs(3)), "{slow_closed:?}");
        assert!(idle_closed.iter().all(|t| t.is_some_and(|t| t < Duration::from_secs(5))), "{idle_closed:?}");
        assert!(idle_closed[0].is_some_and(|t| t > Duration::from_secs(2)), "closed before the idle timeout");
        let kept_closed = kept_closed.expect("the kept-alive connection stayed open");
        assert!(kept_closed > Duration::from_millis(1500) && kept_closed < Duration::from_secs(5), "{kept_closed:?}");
    });
    // The server still serves.
    assert_eq!(blocking_get(server.port, "/healthz").map(|a| a.status), Some(200));
}

#[test]
fn a_slow_upload_is_dropped_and_leaves_no_temporary_file() {
    let server = Server::start(&["--body-timeout-s", "1", "--body-min-rate", "1000"]);
    let rt = runtime();
    rt.block_on(async {
        let mut stream = TcpStream::connect(server.addr()).await.unwrap();
        let head = format!(
            "PUT /v1/objects/inputs/slow/strip.las HTTP/1.1\r\nHost: localhost\r\nAuthorization: {}\r\n\
             Content-Length: 100000\r\n\r\n",
            bearer()
        );
        stream.write_all(head.as_bytes()).await.unwrap();
        let started = Instant::now();
        let (mut reader, mut writer) = stream.into_split();
        // Two bytes a second, each within the 1 s pause allowance: only the rate check stops it.
        let trickle = tokio::spawn(async move {
            for _ in 0..40 {
                if writer.write_all(b"x").await.is_err() {
                    break;
                }
                tokio::time::sleep(Duration::from_millis(500)).await;
            }
        });
        let mut raw = Vec::new();
        let read = tokio::time::timeout(Duration::from_secs(10), reader.read_to_end(&mut raw)).await;
        let elapsed = started.elapsed();
        trickle.abort();
        assert!(read.is_ok(), "the slow upload was not dropped within 10 s");
        eprintln!("a 2 byte/s upload was dropped after {elapsed:?}");
        assert!(elapsed < Duration::from_secs(4), "{elapsed:?}");
        if let Some(answer) = Answer::parse(&raw) {
            assert_eq!(answer.status, 408, "{answer:?}");
            answer.assert_clean_error(&server);
        }
    });
    let leftovers = files_under(&server.store());
    assert!(leftovers.is_empty(), "files left in the store: {leftovers:?}");
}

fn files_under(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    if let Ok(entries) = std::fs::read_dir(dir) {
        for entry in entries.flatten() {
            let path = entry.path();
            if path.is_dir() {
                out.extend(files_under(&path));
            } else {
                out.push(path);
            }
        }
    }
    out
}

fn manifest(name: &str, lever_arm: &str) -> String {
    format!(
        r#"{{"name": "{name}", "scanners": {{"left": {{"lever_arm_m": {lever_arm}}}}},
            "trajectories": [{{"id": "v01", "uri": "inputs/a/t.csv"}}],
            "strips": [{{"id": "v01-left", "trajectory": "v01", "scanner": "left", "uri": "inputs/a/s.las"}}]}}"#
    )
}

#[test]
fn every_error_is_json_and_names_no_server_path() {
    let server = Server::start(&["--max-manifest-bytes", "2000", "--reads-per-s", "1000", "--read-burst", "1000"]);
    let rt = runtime();
    let addr = server.addr();
    let auth = bearer();
    let call = |method: &str, path: &str, auth: Option<&str>, body: &str| {
        rt.block_on(exchange(&addr, &request(method, path, auth, body), Duration::from_secs(10)))
            .unwrap_or_else(|| panic!("no answer to {method} {path}"))
    };
    let health = call("GET", "/healthz", None, "");
    assert_eq!(health.status, 200);
    assert_eq!(health.json(), serde_json::json!({"status": "ok"}), "/healthz names nothing of the server");

    // The scheme of the credential in any case; a wrong token or none is 401.
    assert_eq!(call("GET", "/v1/token", Some(&format!("bearer {TOKEN}")), "").status, 204);
    assert_eq!(call("GET", "/v1/token", Some(&format!("BEARER {TOKEN}")), "").status, 204);
    let long_key = format!("/v1/objects/inputs/{}.las", "n".repeat(300));
    let huge = "x".repeat(3000);
    let cases: Vec<(&str, &str, Option<&str>, &str, u16)> = vec![
        ("GET", "/no/such/route", None, "", 404),
        ("GET", "/v1/campaigns/not-a-uuid", None, "", 404),
        ("PUT", "/healthz", Some(&auth), "", 405),
        ("GET", "/v1/campaigns?limit=many", None, "", 400),
        ("GET", "/v1/campaigns/00000000-0000-0000-0000-000000000000/events?tail=1&after=2", None, "", 400),
        ("POST", "/v1/campaigns", None, "{}", 401),
        ("POST", "/v1/campaigns", Some("Bearer wrong"), "{}", 401),
        ("POST", "/v1/campaigns", Some(&auth), &huge, 413),
        ("POST", "/v1/campaigns", Some(&auth), "{not json", 422),
        ("PUT", &long_key, Some(&auth), "x", 400),
        ("PUT", "/v1/objects/c/escape", Some(&auth), "x", 403),
        ("PUT", "/v1/objects/inputs/a/s.las", Some(&auth), "strip", 201),
        // A key that would need an existing object to be a folder, and one naming that folder.
        ("PUT", "/v1/objects/inputs/a/s.las/inner", Some(&auth), "x", 409),
        ("PUT", "/v1/objects/inputs/a", Some(&auth), "x", 409),
    ];
    for (method, path, token, body, expected) in &cases {
        let answer = call(method, path, *token, body);
        assert_eq!(answer.status, *expected, "{method} {path}: {answer:?}");
        if answer.status >= 400 {
            answer.assert_clean_error(&server);
        }
        if answer.status == 405 {
            assert!(answer.head.contains("allow:"), "{answer:?}");
        }
        if answer.status == 401 {
            assert!(answer.head.contains("www-authenticate: bearer"), "{answer:?}");
        }
    }
    // A missing input is named by its JSON path, not by where the store keeps it.
    let missing = call("POST", "/v1/campaigns", Some(&auth), &manifest("m", "[0, 0.5, 0.3]"));
    assert_eq!(missing.status, 422, "{missing:?}");
    missing.assert_clean_error(&server);
    assert_eq!(missing.json()["problems"][0]["path"], "$.trajectories[0].uri", "{missing:?}");
    // Absurd numbers and a NUL in the name: 422 naming each field.
    let absurd = call("POST", "/v1/campaigns", Some(&auth), &manifest("a\\u0000b", "[1e308, 0, 0]"));
    assert_eq!(absurd.status, 422, "{absurd:?}");
    absurd.assert_clean_error(&server);
    let paths: Vec<_> = absurd.json()["problems"].as_array().unwrap().iter().map(|p| p["path"].clone()).collect();
    assert!(paths.contains(&"$.name".into()) && paths.contains(&"$.scanners.left.lever_arm_m[0]".into()), "{absurd:?}");
    // Failed uploads leave no temporary file behind.
    let leftovers: Vec<_> =
        files_under(&server.store()).into_iter().filter(|p| p.to_string_lossy().contains(".upload-")).collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}

#[test]
fn overload_is_shed_and_greedy_readers_are_limited() {
    let server = Server::start(&["--max-in-flight", "1", "--reads-per-s", "2", "--read-burst", "3"]);
    let rt = runtime();
    rt.block_on(async {
        let addr = server.addr();
        // Reads beyond the burst: 429 with Retry-After.
        let mut statuses = Vec::new();
        for _ in 0..6 {
            let answer =
                exchange(&addr, &request("GET", "/v1/campaigns", None, ""), Duration::from_secs(5)).await.unwrap();
            if answer.status == 429 {
                assert!(answer.head.contains("retry-after:"), "{answer:?}");
                answer.assert_clean_error(&server);
            }
            statuses.push(answer.status);
        }
        assert_eq!(statuses[0], 200, "{statuses:?}");
        assert!(statuses.iter().filter(|s| **s == 429).count() >= 2, "{statuses:?}");
        tokio::time::sleep(Duration::from_millis(1600)).await;
        // An upload in progress holds the only request slot: a write meanwhile is shed with 503.
        let mut upload = TcpStream::connect(&addr).await.unwrap();
        let head = format!(
            "PUT /v1/objects/inputs/held.las HTTP/1.1\r\nHost: localhost\r\nAuthorization: {}\r\n\
             Content-Length: 10\r\n\r\nabc",
            bearer()
        );
        upload.write_all(head.as_bytes()).await.unwrap();
        tokio::time::sleep(Duration::from_millis(300)).await;
        let shed = exchange(&addr, &request("GET", "/v1/campaigns", None, ""), Duration::from_secs(5)).await.unwrap();
        assert_eq!(shed.status, 503, "{shed:?}");
        assert!(shed.head.contains("retry-after:"), "{shed:?}");
        shed.assert_clean_error(&server);
        // The held upload completes normally.
        upload.write_all(b"defghij").await.unwrap();
        let mut buf = vec![0u8; 4096];
        let n = tokio::time::timeout(Duration::from_secs(5), upload.read(&mut buf)).await.unwrap().unwrap();
        assert!(
            String::from_utf8_lossy(&buf[..n]).starts_with("HTTP/1.1 201"),
            "{}",
            String::from_utf8_lossy(&buf[..n])
        );
    });
}

#[test]
fn a_symlink_leaving_the_file_store_is_refused_and_its_target_never_shown() {
    let server = Server::start(&[]);
    let outside = tempfile::tempdir().unwrap();
    let secret = outside.path().join("secret.csv");
    std::fs::write(&secret, "TOP-SECRET first line\n").unwrap();
    let inputs = server.store().join("inputs").join("a");
    std::fs::create_dir_all(&inputs).unwrap();
    std::os::unix::fs::symlink(&secret, inputs.join("t.csv")).unwrap();
    std::fs::write(inputs.join("s.las"), b"not really a strip").unwrap();
    std::os::unix::fs::symlink(outside.path(), server.store().join("inputs").join("out")).unwrap();
    let rt = runtime();
    let addr = server.addr();
    let auth = bearer();
    let call = |method: &str, path: &str, body: &str| {
        rt.block_on(exchange(&addr, &request(method, path, Some(&auth), body), Duration::from_secs(10))).unwrap()
    };
    // A manifest naming the link is refused at submission.
    let refused = call("POST", "/v1/campaigns", &manifest("linked", "[0, 0.5, 0.3]"));
    assert!(matches!(refused.status, 400 | 422), "{refused:?}");
    refused.assert_clean_error(&server);
    assert!(refused.body.contains("symbolic link"), "{refused:?}");
    assert!(!refused.body.contains("TOP-SECRET"), "{refused:?}");
    // An upload through a linked folder writes nothing outside the store.
    let through = call("PUT", "/v1/objects/inputs/out/planted.csv", "planted");
    assert_eq!(through.status, 400, "{through:?}");
    through.assert_clean_error(&server);
    assert!(!outside.path().join("planted.csv").exists());
    assert_eq!(std::fs::read_to_string(&secret).unwrap(), "TOP-SECRET first line\n");
}
