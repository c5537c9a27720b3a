//! What the remote cache's transports share (redis, HTTP through `ureq`, and the plain-HTTP
//! batches of `http_batch`): a failed operation and the bound on what a value may be.

/// The largest value read back (a guard against a server answering with something else).
pub(super) const MAX_VALUE: u64 = 1 << 30;

/// One failed operation.
#[derive(Debug)]
pub(super) struct Fault {
    pub message: String,
    /// A timeout is not retried (it would double the wait).
    pub timed_out: bool,
}
