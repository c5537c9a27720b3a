//! What the remote cache's transports share (redis, HTTP through `ureq`, and the plain-HTTP
//! batches of `http_batch`): a failed operation, the bound on what a value may be, the
//! deadline of a whole request and a host lookup bounded in time.

use std::io::{self, Read, Write};
use std::net::{SocketAddr, TcpStream, ToSocketAddrs};
use std::time::{Duration, Instant};

/// The largest value any build reads back, whatever its own figures say (see
/// [`super::remote::Remote::limit_values`]).
pub(super) const MAX_VALUE: u64 = 1 << 30;

/// The bound of a value when the build has not set one from its own figures: far above
/// any entry, archive or set of records of the bundled renderer and the generated sets,
/// far below what a hostile server could send.
pub(super) const DEFAULT_LIMIT: u64 = 64 << 20;

/// How long a whole request may take, beyond its transfer (see [`deadline`]): so many
/// timeouts (a server that drips a byte per timeout fails after about this many).
const REQUEST_TIMEOUTS: u32 = 4;

/// The slowest transfer rate a request is given time for, past its [`REQUEST_TIMEOUTS`]:
/// a value of `n` bytes announced adds `n / RATE` seconds.
const RATE: u64 = 16 << 20;

/// When a request started now must be done: [`REQUEST_TIMEOUTS`] timeouts.
pub(super) fn deadline(timeout: Duration) -> Instant {
    Instant::now() + timeout * REQUEST_TIMEOUTS
}

/// The time a value of `bytes` announced adds to its request's deadline.
pub(super) fn transfer_time(bytes: u64) -> Duration {
    Duration::from_millis(bytes.saturating_mul(1000) / RATE)
}

/// The most a whole request may take for a value of at most `limit` bytes (for `ureq`,
/// whose bound is per call, not per byte announced).
pub(super) fn request_bound(timeout: Duration, limit: u64) -> Duration {
    timeout * REQUEST_TIMEOUTS + transfer_time(limit)
}

/// One failed operation.
#[derive(Clone, Debug)]
pub(super) struct Fault {
    pub message: String,
    /// A timeout is not retried (it would double the wait).
    pub timed_out: bool,
}

impl Fault {
    /// A request that ran out of time.
    pub fn timeout(doing: &str) -> Fault {
        Fault { message: format!("{doing}: timed out"), timed_out: true }
    }

    /// A request that ran out of time after `waited`.
    pub fn timeout_after(doing: &str, waited: Duration) -> Fault {
        Fault { message: format!("{doing}: timed out after {} ms", waited.as_millis()), timed_out: true }
    }
}

/// The addresses of `host`, looked up on a thread of its own so that a stuck lookup is
/// bounded by `timeout` too (the lookup itself has no timeout).
pub(super) fn resolve(host: &str, port: u16, timeout: Duration) -> Result<Vec<SocketAddr>, Fault> {
    let (send, receive) = std::sync::mpsc::channel();
    let target = (host.to_string(), port);
    std::thread::spawn(move || {
        let _ = send.send(target.to_socket_addrs().map(Iterator::collect::<Vec<_>>));
    });
    match receive.recv_timeout(timeout) {
        Ok(Ok(addresses)) => Ok(addresses),
        Ok(Err(e)) => Err(Fault { message: format!("cannot resolve {host}: {e}"), timed_out: false }),
        Err(_) => Err(Fault::timeout_after(&format!("resolving {host}"), timeout)),
    }
}

/// A socket whose reads and writes end at a deadline for the whole request (each waits at
/// most the per-read or per-write timeout, and never past the deadline), not only per read:
/// a server that drips one byte per timeout, or takes in what it is sent as slowly, cannot
/// hold a request open for long.
#[derive(Debug)]
pub(super) struct Timed {
    stream: TcpStream,
    timeout: Duration,
    deadline: Option<Instant>,
}

impl Timed {
    pub fn new(stream: TcpStream, timeout: Duration) -> Timed {
        Timed { stream, timeout, deadline: None }
    }

    pub fn timeout(&self) -> Duration {
        self.timeout
    }

    /// Reads and writes from now on end at `deadline` (`None`: only the per-read and
    /// per-write timeouts).
    pub fn set_deadline(&mut self, deadline: Option<Instant>) {
        self.deadline = deadline;
        if deadline.is_none() {
            // The plain bounds again (a read or write under the deadline may have left them
            // shorter).
            let _ = self.stream.set_read_timeout(Some(self.timeout));
            let _ = self.stream.set_write_timeout(Some(self.timeout));
        }
    }

    /// What is left of the deadline, at most a timeout; an error once it has passed.
    fn left(&self) -> io::Result<Option<Duration>> {
        let Some(deadline) = self.deadline else { return Ok(None) };
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return Err(io::Error::new(io::ErrorKind::TimedOut, "the request took too long"));
        }
        Ok(Some(left.min(self.timeout)))
    }

    /// Moves the deadline `by` later (a value's length, once announced).
    pub fn extend_deadline(&mut self, by: Duration) {
        self.deadline = self.deadline.map(|d| d + by);
    }
}

impl Read for Timed {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        if let Some(left) = self.left()? {
            self.stream.set_read_timeout(Some(left))?;
        }
        self.stream.read(buf)
    }
}

impl Write for Timed {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        if let Some(left) = self.left()? {
            self.stream.set_write_timeout(Some(left))?;
        }
        self.stream.write(buf)
    }

    fn flush(&mut self) -> io::Result<()> {
        self.stream.flush()
    }
}
