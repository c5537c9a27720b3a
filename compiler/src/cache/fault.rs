//! What the remote cache's transports share (redis, HTTP through `ureq`, and the plain-HTTP
//! batches of `http_batch`): a failed operation, the bound on what a value may be, and the
//! deadline of a whole request.

use std::io::{self, Read, Write};
use std::net::TcpStream;
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
#[derive(Debug)]
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
}

/// A socket whose reads end at a deadline for the whole request (each read waits at most
/// the per-read timeout, and never past the deadline), not only per read: a server that
/// drips one byte per timeout cannot hold a request open for long.
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

    /// Reads from now on end at `deadline` (`None`: only the per-read timeout).
    pub fn set_deadline(&mut self, deadline: Option<Instant>) {
        self.deadline = deadline;
        if deadline.is_none() {
            // The per-read bound again (a read under the deadline may have left it shorter).
            let _ = self.stream.set_read_timeout(Some(self.timeout));
        }
    }

    /// Moves the deadline `by` later (a value's length, once announced).
    pub fn extend_deadline(&mut self, by: Duration) {
        self.deadline = self.deadline.map(|d| d + by);
    }
}

impl Read for Timed {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        if let Some(deadline) = self.deadline {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(io::Error::new(io::ErrorKind::TimedOut, "the request took too long"));
            }
            self.stream.set_read_timeout(Some(left.min(self.timeout)))?;
        }
        self.stream.read(buf)
    }
}

impl Write for Timed {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        self.stream.write(buf)
    }

    fn flush(&mut self) -> io::Result<()> {
        self.stream.flush()
    }
}
