//! The page's server guards itself (helpers in `http.rs`): other hosts refused, a
//! Content-Security-Policy on every answer, idle connections capped, and crowds of `/events`
//! streams neither shut out the control API nor one address the others.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::time::{Duration, Instant};

use crate::common::root;
use crate::http::{finished_status, post, Daemon};

/// Raw request on a fresh connection: the response's head (status line and headers).
fn raw_head(addr: SocketAddr, request: &str) -> String {
    let mut s = TcpStream::connect_timeout(&addr, Duration::from_secs(5)).expect("connect");
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    s.write_all(request.as_bytes()).unwrap();
    let mut raw = Vec::new();
    let _ = s.read_to_end(&mut raw);
    let text = String::from_utf8_lossy(&raw).to_string();
    text.split("\r\n\r\n").next().unwrap_or_default().to_string()
}

/// Open sockets of process `pid` (its entries in /proc/PID/fd that are sockets).
fn sockets_of(pid: u32) -> usize {
    std::fs::read_dir(format!("/proc/{pid}/fd"))
        .map(|d| d.filter_map(|e| std::fs::read_link(e.ok()?.path()).ok()).filter(|l| l.to_string_lossy().starts_with("socket:")).count())
        .unwrap_or(0)
}

/// The page's server guards itself: a `Host` naming another site is refused (DNS
/// rebinding), every answer carries a Content-Security-Policy, a half-sent header is closed
/// after the header timeout, and idle connections beyond the cap are closed at once — the
/// daemon's descriptors stay bounded and the page answers again once they time out.
#[test]
fn the_server_refuses_other_hosts_sends_a_csp_and_caps_idle_connections() {
    use tagdeflect_sinks::http::{HEADER_TIMEOUT, MAX_CONNECTIONS};
    let rec = root().join("replay/one-cam");
    let mut d = Daemon::start(&["replay", rec.to_str().unwrap(), "--http", "127.0.0.1:0"]);
    let addr = d.addr();
    finished_status(addr);

    let head = raw_head(addr, "GET /api/status HTTP/1.1\r\nHost: evil.example:8080\r\nConnection: close\r\n\r\n");
    assert!(head.starts_with("HTTP/1.1 421"), "{head}");
    let head = raw_head(addr, &format!("GET / HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"));
    assert!(head.starts_with("HTTP/1.1 200"), "{head}");
    let csp = head.lines().find(|l| l.to_ascii_lowercase().starts_with("content-security-policy:")).unwrap_or_else(|| panic!("{head}"));
    assert!(csp.contains("script-src 'self'") && csp.contains("object-src 'none'"), "{csp}");
    let head = raw_head(addr, "GET / HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n");
    assert!(head.starts_with("HTTP/1.1 200"), "localhost is this server: {head}");

    // Half a header: the server closes the connection once the header timeout has passed.
    let mut half = TcpStream::connect(addr).unwrap();
    half.write_all(b"GET / HTTP/1.1\r\nHost: 127").unwrap();
    half.set_read_timeout(Some(HEADER_TIMEOUT + Duration::from_secs(20))).unwrap();
    let t0 = Instant::now();
    let mut buf = [0u8; 512];
    let n = half.read(&mut buf);
    assert!(n.is_ok(), "closed by the server, not by our read timeout: {n:?}");
    assert!(t0.elapsed() >= HEADER_TIMEOUT - Duration::from_secs(1), "closed after {:?}", t0.elapsed());

    // Far more idle connections than the cap: the daemon holds at most the cap.
    let pid = d.child.id();
    let before = sockets_of(pid);
    let idle: Vec<TcpStream> = (0..MAX_CONNECTIONS + 100).map(|_| TcpStream::connect(addr).unwrap()).collect();
    let deadline = Instant::now() + Duration::from_secs(30);
    // Wait until the daemon has taken every connection from the backlog (accepted or closed).
    loop {
        let held = sockets_of(pid);
        let still_open = idle.iter().filter(|s| {
            s.set_nonblocking(true).unwrap();
            let r = s.peek(&mut [0u8; 1]);
            matches!(r, Err(ref e) if e.kind() == std::io::ErrorKind::WouldBlock)
        });
        if still_open.count() <= MAX_CONNECTIONS {
            assert!(held <= before + MAX_CONNECTIONS + 2, "{held} sockets held (cap {MAX_CONNECTIONS}, {before} before)");
            break;
        }
        assert!(Instant::now() < deadline, "the daemon did not close the connections beyond its cap");
        std::thread::sleep(Duration::from_millis(200));
    }
    // The idle ones time out; the page answers again.
    let deadline = Instant::now() + tagdeflect_sinks::http::IDLE_TIMEOUT + Duration::from_secs(30);
    loop {
        let head = raw_head(addr, &format!("GET /api/status HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"));
        if head.starts_with("HTTP/1.1 200") {
            break;
        }
        assert!(Instant::now() < deadline, "the page did not answer after the idle connections timed out: {head}");
        std::thread::sleep(Duration::from_millis(500));
    }
    drop(idle);
    assert_eq!(d.stop(), Some(0));
}

/// An `/events` stream opened from the loopback address `ip` (127.x.y.z: every one of them
/// is this machine's), its answer's status line read.
fn open_stream_from(addr: SocketAddr, ip: [u8; 4]) -> TcpStream {
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    let s = rt.block_on(async {
        let socket = tokio::net::TcpSocket::new_v4().unwrap();
        socket.bind(SocketAddr::from((ip, 0))).unwrap();
        socket.connect(addr).await.expect("connect").into_std().unwrap()
    });
    s.set_nonblocking(false).unwrap();
    let mut s = s;
    s.write_all(format!("GET /events HTTP/1.1\r\nHost: {addr}\r\n\r\n").as_bytes()).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
    let mut head = [0u8; 12];
    s.read_exact(&mut head).expect("the stream's answer");
    assert_eq!(&head, b"HTTP/1.1 200", "a stream is served");
    s
}

/// Whether the server closed the stream: read until its end (closed) or `open_for` of data
/// without one (open: lines keep coming).
fn stream_closed(s: &mut TcpStream, open_for: Duration) -> bool {
    s.set_read_timeout(Some(Duration::from_millis(500))).unwrap();
    let until = Instant::now() + open_for;
    let mut buf = [0u8; 65536];
    while Instant::now() < until {
        match s.read(&mut buf) {
            Ok(0) => return true,
            Ok(_) => {}
            Err(e) if matches!(e.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut) => {}
            Err(_) => return true,
        }
    }
    false
}

/// A crowd of `/events` streams — as many as the server has connection slots, from eight
/// addresses — never shuts out the control API: a new connection closes
/// the oldest stream of the address holding the most, so a `mark` and a `stop` are answered
/// (409: no test runs), `/api/status` too, and the oldest stream's connection is the one closed.
#[test]
fn a_crowd_of_event_streams_leaves_room_for_the_control_api() {
    use tagdeflect_sinks::http::{MAX_CONNECTIONS, MAX_STREAMS_PER_ADDRESS};
    let dir = tempfile::tempdir().unwrap();
    let tests_dir = dir.path().join("tests");
    let mut d = Daemon::start(&["demo", "--http", "127.0.0.1:0", "--tests", tests_dir.to_str().unwrap()]);
    let addr = d.addr();
    let token = std::fs::read_to_string(tests_dir.join(".token")).unwrap().trim().to_string();
    let per = MAX_STREAMS_PER_ADDRESS / 2;
    let streams: Vec<TcpStream> = (0..MAX_CONNECTIONS).map(|k| open_stream_from(addr, [127, 0, 1, 1 + (k / per) as u8])).collect();
    let bearer = format!("Bearer {token}");
    let auth = [("Content-Type", "application/json"), ("Authorization", bearer.as_str())];
    let (code, body) = post(addr, "/api/test/mark", &auth, br#"{"note": "crowded"}"#);
    assert_eq!(code, 409, "the mark is answered (no test runs): {code} {body}");
    let (code, body) = post(addr, "/api/test/stop", &auth, b"{}");
    assert_eq!(code, 409, "the stop is answered (no test runs): {code} {body}");
    let head = raw_head(addr, &format!("GET /api/status HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"));
    assert!(head.starts_with("HTTP/1.1 200"), "{head}");
    // The oldest streams were closed for them (read to their end: the server closed them).
    let mut oldest = streams.into_iter().next().unwrap();
    assert!(stream_closed(&mut oldest, Duration::from_secs(30)), "the oldest stream was closed by the server");
    d.wait_stderr("was closed to make room", Duration::from_secs(10), "the eviction logged");
    assert_eq!(d.stop(), Some(0));
}

/// One address cannot close everyone else's `/events` streams: it holds at
/// most [`MAX_STREAMS_PER_ADDRESS`](tagdeflect_sinks::http::MAX_STREAMS_PER_ADDRESS) of them,
/// and each new one beyond that closes its own oldest. Four viewers on other addresses keep
/// their streams while 127.0.0.1 opens as many streams as the server has connection slots;
/// of those, the newest share stays open and the rest were closed.
#[test]
fn one_address_cannot_close_the_event_streams_of_others() {
    use tagdeflect_sinks::http::{MAX_CONNECTIONS, MAX_STREAMS_PER_ADDRESS};
    let mut d = Daemon::start(&["demo", "--http", "127.0.0.1:0"]);
    let addr = d.addr();
    let mut others: Vec<TcpStream> = (2..6).map(|k| open_stream_from(addr, [127, 0, 0, k])).collect();
    let mut crowd: Vec<TcpStream> = (0..MAX_CONNECTIONS).map(|_| open_stream_from(addr, [127, 0, 0, 1])).collect();
    let head = raw_head(addr, &format!("GET /api/status HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"));
    assert!(head.starts_with("HTTP/1.1 200"), "{head}");
    for (k, s) in others.iter_mut().enumerate() {
        assert!(!stream_closed(s, Duration::from_secs(2)), "viewer {k} on another address kept its stream");
    }
    let kept = MAX_CONNECTIONS - MAX_STREAMS_PER_ADDRESS;
    assert!(stream_closed(&mut crowd[0], Duration::from_secs(30)), "the crowd's oldest stream was closed");
    assert!(stream_closed(&mut crowd[kept - 1], Duration::from_secs(30)), "the crowd's streams beyond its share were closed");
    assert!(!stream_closed(&mut crowd[kept], Duration::from_secs(2)), "the crowd's newest {MAX_STREAMS_PER_ADDRESS} stay open");
    assert!(!stream_closed(crowd.last_mut().unwrap(), Duration::from_secs(2)));
    d.wait_stderr("its oldest was closed for its new one", Duration::from_secs(10), "the share logged");
    assert_eq!(d.stop(), Some(0));
}
