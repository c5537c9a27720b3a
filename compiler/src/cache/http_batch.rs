//! Pipelined HTTP/1.1 `GET`s of a fill from a plain-HTTP remote cache: the requests of a
//! batch of keys go out in one write on a keep-alive connection, and the responses are read
//! back in order (RFC 9112 9.3.2: a server answers pipelined requests in the order it
//! received them). One request per entry cost a fill a send, a wake-up and a round trip
//! each: on a generated set, more of its CPU than reading the entries' bytes.
//!
//! Only the fill's batches come this way (`https` and single lookups stay with `ureq`).
//! Every connect, read and write is bounded by the store's timeout, each response by a
//! deadline ([`super::fault::deadline`], later by the time its announced length takes),
//! and each value by the build's limit, checked before anything is allocated for it
//! (chunk sizes included: one that overflows is malformed); a server that closes
//! the connection after some answers (nginx does after `keepalive_requests`) leaves the
//! rest of the batch to a new connection; anything unexpected is a [`Fault`].

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::sync::{Mutex, OnceLock};
use std::time::Duration;

use super::fault::{deadline, resolve, transfer_time, Fault, Timed};
use super::Key;

/// The most keys whose requests go out at once on one connection (few enough that the
/// requests fit the socket buffers, so writing them never waits for the server to
/// read, while it waits for this side to read its answers).
pub const BATCH: usize = 64;
/// The largest response head read (status line and headers).
const MAX_HEAD: usize = 64 << 10;

/// A plain-HTTP server and the prefix its values live under.
pub struct HttpBatch {
    /// `host[:port]`, as the `Host` header gives it.
    authority: String,
    host: String,
    port: u16,
    /// The prefix's path, without a trailing slash.
    path: String,
    /// `Authorization` header line, with its CRLF (a secret: never in a message).
    authorization: String,
    timeout: Duration,
    /// Resolved on first use, once per build.
    addresses: OnceLock<Result<Vec<SocketAddr>, Fault>>,
    idle: Mutex<Vec<BufReader<Timed>>>,
}

impl HttpBatch {
    /// For `http://authority/path` (no credentials in it), with the `Authorization` value.
    pub fn new(authority: &str, path: &str, authorization: Option<&str>, timeout: Duration) -> Option<HttpBatch> {
        let (host, port) = match authority.rsplit_once(':') {
            Some((h, p)) if !h.ends_with(':') && (h.starts_with('[') || !h.contains(':')) => (h, p.parse().ok()?),
            _ => (authority, 80),
        };
        let host = host.trim_start_matches('[').trim_end_matches(']');
        if host.is_empty() {
            return None;
        }
        Some(HttpBatch {
            authority: authority.to_string(),
            host: host.to_string(),
            port,
            path: path.trim_end_matches('/').to_string(),
            authorization: authorization.map(|a| format!("Authorization: {a}\r\n")).unwrap_or_default(),
            timeout,
            addresses: OnceLock::new(),
            idle: Mutex::default(),
        })
    }

    /// Asks for each of `keys` on one connection and calls `f` with each answer in order
    /// (`None` for a 404), `value` holding the body. `Ok(n)`: the first `n >= 1` keys were
    /// answered (fewer than all when the server closed the connection after them);
    /// `Err((n, fault))`: the first `n` were, then the connection failed.
    pub fn get(
        &self,
        keys: &[Key],
        value: &mut Vec<u8>,
        limit: u64,
        f: &impl Fn(&Key, Option<&[u8]>),
    ) -> Result<usize, (usize, Fault)> {
        let mut connection = self.connection().map_err(|fault| (0, fault))?;
        let mut requests = Vec::with_capacity(keys.len() * (120 + self.path.len() + self.authorization.len()));
        for key in keys {
            write!(
                requests,
                "GET {}/{key} HTTP/1.1\r\nHost: {}\r\nUser-Agent: kiln/{}\r\n{}\r\n",
                self.path,
                self.authority,
                env!("CARGO_PKG_VERSION"),
                self.authorization
            )
            .expect("writing to a Vec");
        }
        connection.get_mut().write_all(&requests).map_err(|e| (0, io_fault("sending requests", e)))?;
        for (n, key) in keys.iter().enumerate() {
            connection.get_mut().set_deadline(Some(deadline(self.timeout)));
            let (found, keep_alive) = read_response(&mut connection, value, limit).map_err(|fault| (n, fault))?;
            f(key, found.then_some(value.as_slice()));
            if !keep_alive {
                return Ok(n + 1);
            }
        }
        connection.get_mut().set_deadline(None);
        self.idle.lock().expect("no panics while locked").push(connection);
        Ok(keys.len())
    }

    /// Asks for `key` alone and gives `f` a reader of its body as it arrives (`None` for a
    /// 404): for values too large to hold whole. What `f` leaves unread is read and
    /// dropped, so that the connection serves the next request. `Err((called, fault))`:
    /// the connection failed, before `f` was called or after.
    pub fn get_streamed(
        &self,
        key: &Key,
        limit: u64,
        f: &mut dyn FnMut(Option<&mut dyn Read>),
    ) -> Result<(), (bool, Fault)> {
        let mut connection = self.connection().map_err(|fault| (false, fault))?;
        let request = format!(
            "GET {}/{key} HTTP/1.1\r\nHost: {}\r\nUser-Agent: kiln/{}\r\n{}\r\n",
            self.path,
            self.authority,
            env!("CARGO_PKG_VERSION"),
            self.authorization
        );
        connection.get_mut().write_all(request.as_bytes()).map_err(|e| (false, io_fault("sending a request", e)))?;
        connection.get_mut().set_deadline(Some(deadline(self.timeout)));
        let mut head = read_head(&mut connection, limit).map_err(|fault| (false, fault))?;
        match head.length.filter(|_| head.status == 200 && !head.chunked) {
            Some(length) => {
                let mut body = connection.by_ref().take(length);
                f(Some(&mut body));
                std::io::copy(&mut body, &mut std::io::sink()).map_err(|e| (true, io_fault("reading a value", e)))?;
                if body.limit() != 0 {
                    return Err((true, bad("a value is truncated (the connection closed)")));
                }
            }
            None => {
                // A miss, or a body without a length: read whole first.
                let mut value = Vec::new();
                read_body(&mut connection, &mut head, &mut value, limit).map_err(|fault| (false, fault))?;
                f((head.status == 200).then_some(&mut value.as_slice() as &mut dyn Read));
            }
        }
        if head.keep_alive {
            connection.get_mut().set_deadline(None);
            self.idle.lock().expect("no panics while locked").push(connection);
        }
        Ok(())
    }

    fn connection(&self) -> Result<BufReader<Timed>, Fault> {
        if let Some(c) = self.idle.lock().expect("no panics while locked").pop() {
            return Ok(c);
        }
        let addresses = self.addresses.get_or_init(|| resolve(&self.host, self.port, self.timeout));
        let addresses = addresses.as_ref().map_err(Fault::clone)?;
        let mut last = None;
        for address in addresses {
            match TcpStream::connect_timeout(address, self.timeout) {
                Ok(stream) => {
                    let setup = stream
                        .set_read_timeout(Some(self.timeout))
                        .and_then(|()| stream.set_write_timeout(Some(self.timeout)))
                        .and_then(|()| stream.set_nodelay(true));
                    setup.map_err(|e| io_fault("connecting", e))?;
                    return Ok(BufReader::with_capacity(64 << 10, Timed::new(stream, self.timeout)));
                }
                Err(e) => last = Some(e),
            }
        }
        Err(match last {
            Some(e) => io_fault("connecting", e),
            None => Fault { message: format!("{} has no address", self.host), timed_out: false },
        })
    }
}

fn io_fault(doing: &str, e: std::io::Error) -> Fault {
    if matches!(e.kind(), std::io::ErrorKind::TimedOut | std::io::ErrorKind::WouldBlock) {
        return Fault::timeout(doing);
    }
    Fault { message: format!("{doing}: {e}"), timed_out: false }
}

fn bad(why: impl Into<String>) -> Fault {
    Fault { message: why.into(), timed_out: false }
}

/// A response's status line and headers.
struct Head {
    status: u16,
    /// `Content-Length`.
    length: Option<u64>,
    chunked: bool,
    keep_alive: bool,
}

/// Reads a response's head; a status other than 200 or 404, or a length over `limit`, is a
/// fault. The reader's deadline is moved by the time the announced length takes.
fn read_head(reader: &mut BufReader<Timed>, limit: u64) -> Result<Head, Fault> {
    let mut head = Vec::with_capacity(256);
    loop {
        let before = head.len();
        let n = reader.by_ref().take((MAX_HEAD - before) as u64).read_until(b'\n', &mut head);
        match n.map_err(|e| io_fault("reading a response", e))? {
            0 if before == 0 => return Err(bad("the server closed the connection")),
            0 => return Err(bad("a response head is truncated or too long")),
            _ => {}
        }
        if head.ends_with(b"\r\n\r\n") || head.ends_with(b"\n\n") {
            break;
        }
    }
    let mut headers = [httparse::EMPTY_HEADER; 64];
    let mut response = httparse::Response::new(&mut headers);
    match response.parse(&head) {
        Ok(httparse::Status::Complete(_)) => {}
        _ => return Err(bad("malformed HTTP response")),
    }
    let status = response.code.unwrap_or(0);
    let mut keep_alive = response.version == Some(1);
    let (mut length, mut chunked) = (None, false);
    for h in response.headers.iter() {
        let text = std::str::from_utf8(h.value).unwrap_or("").trim();
        if h.name.eq_ignore_ascii_case("content-length") {
            length = Some(text.parse::<u64>().map_err(|_| bad("malformed Content-Length"))?);
        } else if h.name.eq_ignore_ascii_case("transfer-encoding") {
            chunked = text.to_ascii_lowercase().ends_with("chunked");
        } else if h.name.eq_ignore_ascii_case("connection") {
            let text = text.to_ascii_lowercase();
            keep_alive = text.contains("keep-alive") || (keep_alive && !text.contains("close"));
        }
    }
    if status != 200 && status != 404 {
        return Err(bad(format!("GET answered {status}")));
    }
    if let Some(l) = length.filter(|&l| l > limit) {
        return Err(too_large(l, limit));
    }
    reader.get_mut().extend_deadline(transfer_time(length.unwrap_or(0)));
    Ok(Head { status, length, chunked, keep_alive })
}

/// Reads one response: its body into `value` (cleared first; for a 200 the value, else
/// discarded); whether it was a 200 (a 404 is a miss, anything else a fault) and whether the
/// connection stays open after it.
fn read_response(reader: &mut BufReader<Timed>, value: &mut Vec<u8>, limit: u64) -> Result<(bool, bool), Fault> {
    let mut head = read_head(reader, limit)?;
    read_body(reader, &mut head, value, limit)?;
    Ok((head.status == 200, head.keep_alive))
}

/// The body of the response of `head` into `value` (cleared first); a body that runs to
/// the end of the connection leaves it closed.
fn read_body(reader: &mut BufReader<Timed>, head: &mut Head, value: &mut Vec<u8>, limit: u64) -> Result<(), Fault> {
    value.clear();
    if head.chunked {
        read_chunked(reader, value, limit)?;
    } else if let Some(length) = head.length {
        value.reserve(length as usize);
        let read = reader.by_ref().take(length).read_to_end(value).map_err(|e| io_fault("reading a value", e))?;
        if read as u64 != length {
            return Err(bad("a value is truncated (the connection closed)"));
        }
    } else {
        // The body runs to the end of the connection (one byte more than the limit: a
        // longer one is refused).
        reader.by_ref().take(limit + 1).read_to_end(value).map_err(|e| io_fault("reading a value", e))?;
        if value.len() as u64 > limit {
            return Err(too_large(value.len() as u64, limit));
        }
        head.keep_alive = false;
    }
    Ok(())
}

/// A value of `length` bytes, over `limit`.
fn too_large(length: u64, limit: u64) -> Fault {
    bad(format!("a value of {length} bytes or more is larger than any this build stores (at most {limit})"))
}

/// A `Transfer-Encoding: chunked` body into `value`: at most `limit` bytes, each chunk's
/// size checked before its bytes are read (a size that overflows is malformed).
fn read_chunked(reader: &mut BufReader<Timed>, value: &mut Vec<u8>, limit: u64) -> Result<(), Fault> {
    let mut line = Vec::new();
    let read_line = |reader: &mut BufReader<Timed>, line: &mut Vec<u8>| -> Result<(), Fault> {
        line.clear();
        let n = reader.by_ref().take(4096).read_until(b'\n', line).map_err(|e| io_fault("reading a value", e))?;
        if n == 0 || !line.ends_with(b"\n") {
            return Err(bad("a chunked value is truncated"));
        }
        Ok(())
    };
    loop {
        read_line(reader, &mut line)?;
        // At most 16 hex digits (RFC 9112 7.1: a recipient must guard against overflow).
        let size = std::str::from_utf8(&line)
            .ok()
            .map(|l| l.split(';').next().unwrap_or("").trim())
            .filter(|digits| !digits.is_empty() && digits.len() <= 16)
            .and_then(|digits| u64::from_str_radix(digits, 16).ok())
            .ok_or_else(|| bad("malformed chunk size"))?;
        if size == 0 {
            // Trailers, up to the empty line.
            loop {
                read_line(reader, &mut line)?;
                if line == b"\r\n" || line == b"\n" {
                    return Ok(());
                }
            }
        }
        match (value.len() as u64).checked_add(size) {
            Some(total) if total <= limit => reader.get_mut().extend_deadline(transfer_time(size)),
            total => return Err(too_large(total.unwrap_or(u64::MAX), limit)),
        }
        let read = reader.by_ref().take(size).read_to_end(value).map_err(|e| io_fault("reading a value", e))?;
        if read as u64 != size {
            return Err(bad("a chunked value is truncated"));
        }
        read_line(reader, &mut line)?;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::net::TcpListener;

    /// A server that reads everything sent to it (until the requests of `expect` keys) and
    /// answers with `reply`, then closes.
    fn serve(reply: Vec<u8>, expect: usize) -> (u16, std::thread::JoinHandle<String>) {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let port = listener.local_addr().unwrap().port();
        let handle = std::thread::spawn(move || {
            let (mut s, _) = listener.accept().unwrap();
            let mut got = Vec::new();
            let mut buf = [0u8; 4096];
            while got.windows(4).filter(|w| w == b"\r\n\r\n").count() < expect {
                let n = s.read(&mut buf).unwrap();
                if n == 0 {
                    break;
                }
                got.extend_from_slice(&buf[..n]);
            }
            s.write_all(&reply).unwrap();
            String::from_utf8(got).unwrap()
        });
        (port, handle)
    }

    fn keys(n: u8) -> Vec<Key> {
        (0..n).map(|i| Key([i; 32])).collect()
    }

    type Answers = Vec<(Key, Option<Vec<u8>>)>;

    fn answers(pipeline: &HttpBatch, keys: &[Key]) -> (Result<usize, (usize, Fault)>, Answers) {
        let got = Mutex::new(Vec::new());
        let mut value = Vec::new();
        let r = pipeline.get(keys, &mut value, 1 << 20, &|k, v| got.lock().unwrap().push((*k, v.map(<[u8]>::to_vec))));
        (r, got.into_inner().unwrap())
    }

    #[test]
    fn pipelined_answers_in_order_with_lengths_chunks_and_misses() {
        let reply = b"HTTP/1.1 200 OK\r\nContent-Length: 5\r\n\r\nhello\
HTTP/1.1 404 Not Found\r\nContent-Length: 9\r\nContent-Type: text/html\r\n\r\nnot found\
HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\n3;x=y\r\nabc\r\n2\r\nde\r\n0\r\nT: 1\r\n\r\n"
            .to_vec();
        let (port, server) = serve(reply, 3);
        let p =
            HttpBatch::new(&format!("127.0.0.1:{port}"), "/kiln/", Some("Bearer t"), Duration::from_secs(5)).unwrap();
        let k = keys(3);
        let (r, got) = answers(&p, &k);
        assert_eq!(r.unwrap(), 3);
        assert_eq!(got, vec![(k[0], Some(b"hello".to_vec())), (k[1], None), (k[2], Some(b"abcde".to_vec()))]);
        let requests = server.join().unwrap();
        assert!(requests.starts_with(&format!("GET /kiln/{} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n", k[0])));
        assert_eq!(requests.matches("Authorization: Bearer t\r\n").count(), 3, "{requests}");
        assert_eq!(p.idle.lock().unwrap().len(), 1, "the connection is kept");
    }

    #[test]
    fn a_close_after_some_answers_leaves_the_rest() {
        let reply = b"HTTP/1.1 200 OK\r\nContent-Length: 1\r\nConnection: close\r\n\r\nA".to_vec();
        let (port, server) = serve(reply, 3);
        let p = HttpBatch::new(&format!("127.0.0.1:{port}"), "", None, Duration::from_secs(5)).unwrap();
        let (r, got) = answers(&p, &keys(3));
        assert_eq!(r.unwrap(), 1);
        assert_eq!(got.len(), 1);
        assert!(p.idle.lock().unwrap().is_empty(), "a closed connection is not kept");
        server.join().unwrap();
    }

    #[test]
    fn truncated_malformed_and_failed_answers_are_faults_after_the_good_ones() {
        for (reply, answered, why) in [
            (&b"HTTP/1.1 200 OK\r\nContent-Length: 1\r\n\r\nAHTTP/1.1 200 OK\r\nContent-Length: 10\r\n\r\nshort"[..], 1, "truncated"),
            (b"HTTP/1.1 200 OK\r\nContent-Length: 1\r\n\r\nAHTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\n5\r\nab", 1, "truncated"),
            (b"HTTP/1.1 500 Oops\r\nContent-Length: 0\r\n\r\n", 0, "500"),
            (b"garbage\r\n\r\n", 0, "malformed"),
            (b"HTTP/1.1 200 OK\r\nContent-Length: x\r\n\r\n", 0, "Content-Length"),
            (b"", 0, "closed"),
        ] {
            let (port, server) = serve(reply.to_vec(), 2);
            let p = HttpBatch::new(&format!("127.0.0.1:{port}"), "/p", None, Duration::from_secs(5)).unwrap();
            let (r, got) = answers(&p, &keys(2));
            let (n, fault) = r.unwrap_err();
            assert_eq!((n, got.len()), (answered, answered), "{why}");
            assert!(fault.message.contains(why), "{why}: {}", fault.message);
            server.join().unwrap();
        }
    }

    /// `get_streamed` of one key against `reply`: what `f` read (`None` for a miss), the
    /// result, and the connections kept.
    type Streamed = (Option<Vec<u8>>, Result<(), (bool, Fault)>, usize);

    fn streamed(reply: &[u8], read: usize) -> Streamed {
        let (port, server) = serve(reply.to_vec(), 1);
        let p = HttpBatch::new(&format!("127.0.0.1:{port}"), "/kiln", None, Duration::from_secs(5)).unwrap();
        let mut got = None;
        let r = p.get_streamed(&Key([9; 32]), 1 << 20, &mut |body| {
            got = body.map(|b| {
                let mut v = Vec::new();
                b.take(read as u64).read_to_end(&mut v).unwrap();
                v
            })
        });
        let requests = server.join().unwrap();
        assert!(requests.starts_with(&format!("GET /kiln/{} HTTP/1.1\r\n", Key([9; 32]))), "{requests}");
        let kept = p.idle.lock().unwrap().len();
        (got, r, kept)
    }

    #[test]
    fn a_streamed_body_is_read_as_it_comes_and_its_rest_dropped() {
        let (got, r, kept) = streamed(b"HTTP/1.1 200 OK\r\nContent-Length: 10\r\n\r\n0123456789", 4);
        assert_eq!((got.as_deref(), r.is_ok(), kept), (Some(&b"0123"[..]), true, 1));
        let chunked = b"HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\n3\r\nabc\r\n0\r\n\r\n";
        let (got, r, kept) = streamed(chunked, 100);
        assert_eq!((got.as_deref(), r.is_ok(), kept), (Some(&b"abc"[..]), true, 1));
        let (got, r, kept) = streamed(b"HTTP/1.1 404 Not Found\r\nContent-Length: 3\r\n\r\nno!", 100);
        assert_eq!((got, r.is_ok(), kept), (None, true, 1));
    }

    #[test]
    fn a_streamed_body_cut_short_or_refused_is_a_fault() {
        let (got, r, kept) = streamed(b"HTTP/1.1 200 OK\r\nContent-Length: 10\r\n\r\n01234", 100);
        let (called, fault) = r.unwrap_err();
        assert_eq!((got.as_deref(), called, kept), (Some(&b"01234"[..]), true, 0));
        assert!(fault.message.contains("truncated"), "{}", fault.message);
        let (got, r, _) = streamed(b"HTTP/1.1 403 Forbidden\r\nContent-Length: 0\r\n\r\n", 100);
        let (called, fault) = r.unwrap_err();
        assert_eq!((got, called), (None, false));
        assert!(fault.message.contains("403"), "{}", fault.message);
    }

    /// Case 3 of issue 28: chunk sizes that overflow a u64 (or the sum) are refused, not
    /// wrapped.
    #[test]
    fn chunk_sizes_that_overflow_are_refused() {
        for (size, why) in [
            ("ffffffffffffffff", "larger than any"),
            ("10000000000000000", "malformed chunk size"),
            ("", "malformed chunk size"),
        ] {
            let reply = format!("HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\n3\r\nabc\r\n{size}\r\nxyz");
            let (port, server) = serve(reply.into_bytes(), 1);
            let p = HttpBatch::new(&format!("127.0.0.1:{port}"), "/p", None, Duration::from_secs(5)).unwrap();
            let (r, got) = answers(&p, &keys(1));
            let (n, fault) = r.unwrap_err();
            assert_eq!((n, got.len()), (0, 0), "{size}");
            assert!(fault.message.contains(why), "{size}: {}", fault.message);
            server.join().unwrap();
        }
    }

    #[test]
    fn authorities_give_host_and_port() {
        let p = |a: &str| HttpBatch::new(a, "/x", None, Duration::from_secs(1)).map(|p| (p.host, p.port));
        assert_eq!(p("cache.example"), Some(("cache.example".into(), 80)));
        assert_eq!(p("10.0.0.1:8080"), Some(("10.0.0.1".into(), 8080)));
        assert_eq!(p("[::1]:81"), Some(("::1".into(), 81)));
        assert_eq!(p("[::1]"), Some(("::1".into(), 80)));
        assert_eq!(p("h:notaport"), None);
    }

    #[test]
    fn a_server_that_is_not_there_is_a_fault() {
        let port = TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let p = HttpBatch::new(&format!("127.0.0.1:{port}"), "/p", None, Duration::from_millis(500)).unwrap();
        let (r, got) = answers(&p, &keys(2));
        assert!(r.unwrap_err().1.message.contains("connecting"));
        assert!(got.is_empty());
    }
}
