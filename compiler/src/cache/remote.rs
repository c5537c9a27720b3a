//! The shared remote cache, layered under the local one (like Unreal's local and shared DDC).
//!
//! Takes a URL (`redis://host:port[/db]` or `http(s)://host[:port]/prefix`), a [`Mode`] and
//! credentials from the environment; gives byte values by [`Key`]. A value is the local
//! cache's entry encoding (magic, checksum, body) behind a header with one xxh3-128 of the key
//! and the entry, which the [`super::Cache`] that layers this store checks on every value it
//! reads (the entry's own checksum is checked when the entry is used, as in its packs): a
//! corrupted or truncated remote entry is a miss, recompiled and overwritten. Sets of preprocessing
//! records and archives (checksummed too) are shared the same way, under their own keys.
//! [`Remote::get_each`] fetches many values with few round trips: redis `MGET`, or with
//! plain HTTP pipelined `GET`s (`super::http_batch`), on several connections at once.
//!
//! HTTP follows the convention of bazel-remote and of ccache's and sccache's WebDAV
//! backends: `GET`, `PUT` and `HEAD` of `<prefix>/<key>` (nginx with `dav_methods PUT`
//! serves it); a 404 is a miss. Redis stores each value under `kiln:<key>`.
//!
//! Guarantees: every connect, read and write is bounded by a timeout ([`DEFAULT_TIMEOUT`],
//! or `KILN_REMOTE_CACHE_TIMEOUT_MS`), and every request as a whole by a few of them (redis
//! commands and a connection's setup included; redis is spoken over plain TCP only, by
//! [`RawRedis`], the `redis` crate only parsing the URL); the first failure (server down, slow, connection
//! dropped, refused credentials) turns the store off for the rest of the build and leaves
//! exactly one warning; credentials (`KILN_REMOTE_CACHE_TOKEN`, or those in the URL) never
//! appear in a message: URLs are shown through [`redact`].

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use super::fault::{deadline, request_bound, resolve, transfer_time, Fault, Timed, DEFAULT_LIMIT, MAX_VALUE};
use super::Key;

/// The default bound of each connect, read and write.
pub const DEFAULT_TIMEOUT: Duration = Duration::from_secs(3);
/// The most a value's announced length reserves before its bytes arrive (larger values grow
/// as they do).
const MAX_RESERVE: usize = 64 << 20;
/// Keys fetched per round trip by [`Remote::get_each`] (a few megabytes of entries of the
/// bundled renderer's set).
pub const BATCH: usize = 64;
/// Connections used at once by [`Remote::get_each`] (each keep-alive; with HTTP, a batch of
/// pipelined requests in flight with plain HTTP, one request with HTTPS): enough to hide a
/// round trip behind the others' transfers.
const STREAMS: usize = 4;

/// Whether a build writes what it compiles to the remote cache.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Mode {
    /// Look up only: a developer's machine, when CI fills the cache.
    Read,
    /// Look up, and store every entry this build compiled.
    #[default]
    ReadWrite,
}

impl Mode {
    pub fn parse(text: &str) -> Result<Mode, String> {
        match text {
            "read" => Ok(Mode::Read),
            "read-write" => Ok(Mode::ReadWrite),
            other => Err(format!("unknown remote cache mode `{other}` (expected read or read-write)")),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Mode::Read => "read",
            Mode::ReadWrite => "read-write",
        }
    }
}

/// Which remote cache a build uses.
#[derive(Clone, Default, PartialEq, Eq)]
pub enum RemoteCache {
    /// `KILN_REMOTE_CACHE` when it is set and not empty, else none.
    #[default]
    Auto,
    /// This URL.
    Url(String),
    /// None, whatever the environment says.
    Disabled,
}

impl std::fmt::Debug for RemoteCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            RemoteCache::Auto => f.write_str("Auto"),
            RemoteCache::Url(url) => f.debug_tuple("Url").field(&redact(url)).finish(),
            RemoteCache::Disabled => f.write_str("Disabled"),
        }
    }
}

/// A resolved remote cache: where, how, and with which credentials.
#[derive(Clone, PartialEq, Eq)]
pub struct Options {
    pub url: String,
    pub mode: Mode,
    /// `KILN_REMOTE_CACHE_TOKEN`: HTTP `Bearer <token>`, or basic auth when it is
    /// `user:password`; redis `AUTH` when the URL holds no password.
    pub token: Option<String>,
    /// Bound of each connect, read and write (`KILN_REMOTE_CACHE_TIMEOUT_MS`).
    pub timeout: Duration,
    /// `KILN_REMOTE_CACHE_KEY`: the 32-byte key of the values' MAC (see [`Remote`]).
    pub key: Option<SigningKey>,
}

/// The key of the remote values' MAC (blake3 in keyed mode). Never printed.
#[derive(Clone, PartialEq, Eq)]
pub struct SigningKey([u8; 32]);

impl SigningKey {
    /// A key of 64 hexadecimal digits.
    pub fn parse(hex: &str) -> Result<SigningKey, String> {
        let hex = hex.trim();
        if hex.len() != 64 || !hex.bytes().all(|b| b.is_ascii_hexdigit()) {
            return Err(format!("expected 64 hexadecimal digits (32 bytes), got {} characters", hex.len()));
        }
        let mut key = [0u8; 32];
        for (i, byte) in key.iter_mut().enumerate() {
            *byte = u8::from_str_radix(&hex[2 * i..2 * i + 2], 16).expect("hex digits");
        }
        Ok(SigningKey(key))
    }
}

impl std::fmt::Debug for SigningKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("SigningKey(***)")
    }
}

impl std::fmt::Debug for Options {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Options")
            .field("url", &redact(&self.url))
            .field("mode", &self.mode)
            .field("token", &self.token.as_ref().map(|_| "***"))
            .field("timeout", &self.timeout)
            .field("key", &self.key)
            .finish()
    }
}

impl Options {
    /// The remote cache `which` names, with `mode` (else `KILN_REMOTE_CACHE_MODE`, else
    /// read-write) and the token and timeout of the environment; `None` when there is none.
    pub fn resolve(which: &RemoteCache, mode: Option<Mode>) -> Result<Option<Options>, Error> {
        let url = match which {
            RemoteCache::Disabled => return Ok(None),
            RemoteCache::Url(u) => u.clone(),
            RemoteCache::Auto => match std::env::var("KILN_REMOTE_CACHE") {
                Ok(u) if !u.trim().is_empty() => u,
                _ => return Ok(None),
            },
        };
        let mode = match mode {
            Some(m) => m,
            None => match std::env::var("KILN_REMOTE_CACHE_MODE") {
                Ok(m) if !m.is_empty() => {
                    Mode::parse(&m).map_err(|why| Error::Env { name: "KILN_REMOTE_CACHE_MODE", why })?
                }
                _ => Mode::ReadWrite,
            },
        };
        let token = std::env::var("KILN_REMOTE_CACHE_TOKEN").ok().filter(|t| !t.is_empty());
        let timeout = match std::env::var("KILN_REMOTE_CACHE_TIMEOUT_MS") {
            Ok(ms) if !ms.is_empty() => match ms.trim().parse::<u64>() {
                Ok(ms) if ms > 0 => Duration::from_millis(ms),
                _ => {
                    return Err(Error::Env {
                        name: "KILN_REMOTE_CACHE_TIMEOUT_MS",
                        why: format!("`{ms}` is not a positive number of milliseconds"),
                    })
                }
            },
            _ => DEFAULT_TIMEOUT,
        };
        let key = match std::env::var("KILN_REMOTE_CACHE_KEY") {
            Ok(hex) if !hex.trim().is_empty() => {
                Some(SigningKey::parse(&hex).map_err(|why| Error::Env { name: "KILN_REMOTE_CACHE_KEY", why })?)
            }
            _ => None,
        };
        Ok(Some(Options { url: url.trim().to_string(), mode, token, timeout, key }))
    }
}

/// A remote cache that cannot be used as configured.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("invalid remote cache URL `{url}`: {why}")]
    Url { url: String, why: String },
    #[error("invalid {name}: {why}")]
    Env { name: &'static str, why: String },
}

/// The counts of `--stats-json`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Stats {
    /// Entries served by the remote cache (checked, then copied into the local cache).
    pub hits: u64,
    /// Entries stored to it.
    pub writes: u64,
    /// Failed operations (after the first one the store is off: usually 0 or 1), and values
    /// refused (not a Kiln value, or without a valid MAC).
    pub errors: u64,
}

/// A value stored with a MAC (`KILN_REMOTE_CACHE_KEY`): this magic, the MAC, the value.
const SIGNED_MAGIC: &[u8; 8] = b"KILNSG\0\x01";
const SIGNED_HEADER: usize = 8 + 32;

/// The MAC of the value `value` stored under `key`: blake3 in keyed mode over a context
/// string, the key and the value (a value moved to another key no longer verifies).
fn mac(signing: &SigningKey, key: &Key, value: &[u8]) -> [u8; 32] {
    let mut h = blake3::Hasher::new_keyed(&signing.0);
    h.update(b"kiln remote cache value v1\0");
    h.update(&key.0);
    h.update(value);
    *h.finalize().as_bytes()
}

/// [`mac`] of the value `source` reads.
fn mac_of(signing: &SigningKey, key: &Key, source: &dyn Source) -> std::io::Result<[u8; 32]> {
    let mut h = blake3::Hasher::new_keyed(&signing.0);
    h.update(b"kiln remote cache value v1\0");
    h.update(&key.0);
    let read = std::io::copy(&mut source.open()?, &mut h)?;
    if read != source.len() {
        return Err(std::io::Error::other("it changed while read"));
    }
    Ok(*h.finalize().as_bytes())
}

/// What a value read from the remote is ([`Remote::classify`]).
enum Kind {
    /// Behind [`SIGNED_MAGIC`] and a MAC, which is `checked` when this build has a key.
    Signed { checked: bool },
    /// A Kiln value as it is (no key, no MAC).
    Plain,
    /// Not taken, and why.
    Refused(&'static str),
}

/// [`Remote::get_to`]'s checks on a value arriving in pieces: its head held until it says
/// what the value is, then the rest passed on (and hashed, when signed); whether it is
/// accepted is known only at its end.
struct Incoming<'a> {
    remote: &'a Remote,
    key: &'a Key,
    head: Vec<u8>,
    state: Arriving,
    sink: &'a mut dyn FnMut(&[u8]) -> std::io::Result<()>,
    passed: u64,
}

/// Where an [`Incoming`] value is: its head still arriving; the rest passing on (with
/// the hasher and expected MAC of a signed value this build checks); or refused, and why.
enum Arriving {
    Head,
    Passing(Option<(blake3::Hasher, [u8; 32])>),
    Refused(&'static str),
}

impl Incoming<'_> {
    fn push(&mut self, mut data: &[u8]) -> std::io::Result<()> {
        if let Arriving::Head = self.state {
            let take = (SIGNED_HEADER - self.head.len()).min(data.len());
            self.head.extend_from_slice(&data[..take]);
            data = &data[take..];
            if self.head.len() < SIGNED_HEADER {
                return Ok(());
            }
            self.decide()?;
        }
        self.pass(data)
    }

    /// The head is whole (or the value ended): what follows is passed on, or dropped.
    fn decide(&mut self) -> std::io::Result<()> {
        self.state = match self.remote.classify(&self.head) {
            Kind::Signed { checked } => {
                let check = checked.then(|| {
                    let mut h = blake3::Hasher::new_keyed(&self.remote.key.as_ref().expect("checked with a key").0);
                    h.update(b"kiln remote cache value v1\0");
                    h.update(&self.key.0);
                    (h, self.head[8..SIGNED_HEADER].try_into().expect("32 bytes"))
                });
                Arriving::Passing(check)
            }
            Kind::Plain => {
                self.state = Arriving::Passing(None);
                let head = std::mem::take(&mut self.head);
                return self.pass(&head);
            }
            Kind::Refused(why) => Arriving::Refused(why),
        };
        Ok(())
    }

    fn pass(&mut self, data: &[u8]) -> std::io::Result<()> {
        match &mut self.state {
            Arriving::Passing(check) if !data.is_empty() => {
                if let Some((h, _)) = check {
                    h.update(data);
                }
                self.passed += data.len() as u64;
                (self.sink)(data)
            }
            _ => Ok(()),
        }
    }

    /// Whether the whole value passed its checks (else it is refused, with one warning).
    fn finish(mut self) -> std::io::Result<bool> {
        if let Arriving::Head = self.state {
            self.decide()?;
        }
        let why = match &self.state {
            Arriving::Passing(Some((h, expected))) if h.finalize().as_bytes() != expected => {
                "its MAC does not match KILN_REMOTE_CACHE_KEY"
            }
            Arriving::Passing(_) => return Ok(true),
            Arriving::Refused(why) => why,
            Arriving::Head => unreachable!("decided above"),
        };
        self.remote.refuse(self.key, why);
        Ok(false)
    }
}

/// Everything `from` reads, to `push` in pieces.
fn copy_pieces(
    from: &mut dyn std::io::Read,
    push: &mut dyn FnMut(&[u8]) -> std::io::Result<()>,
) -> std::io::Result<()> {
    let mut buf = vec![0u8; 256 << 10];
    loop {
        match from.read(&mut buf) {
            Ok(0) => return Ok(()),
            Ok(n) => push(&buf[..n])?,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
}

/// A value for [`Remote::store_from`]: its length, and its bytes from the start as often as
/// asked.
pub(crate) trait Source: Sync {
    fn len(&self) -> u64;
    fn open(&self) -> std::io::Result<Box<dyn std::io::Read + '_>>;
}

/// A value in memory, in pieces, for [`Remote::store_from`]: sent as it is, without
/// copying the pieces into one buffer (a large value, such as a set's preprocessing
/// records, would be held twice or three times).
pub(crate) struct Pieces<'a>(pub &'a [&'a [u8]]);

impl Source for Pieces<'_> {
    fn len(&self) -> u64 {
        self.0.iter().map(|p| p.len() as u64).sum()
    }

    fn open(&self) -> std::io::Result<Box<dyn std::io::Read + '_>> {
        let empty: Box<dyn std::io::Read + '_> = Box::new(std::io::empty());
        Ok(self.0.iter().fold(empty, |all, &p| Box::new(std::io::Read::chain(all, p))))
    }
}

/// Opens a [`Source`]'s bytes for one attempt.
type Body<'a> = dyn Fn() -> std::io::Result<Box<dyn std::io::Read + 'a>> + 'a;

/// `scheme://host[:port]/path` of `url`, without user, password, query or fragment: the
/// only form of a remote cache URL that Kiln prints.
pub fn redact(url: &str) -> String {
    let Some(at) = url.find("://") else { return "<remote cache URL>".into() };
    let (scheme, rest) = (&url[..at], &url[at + 3..]);
    let authority_end = rest.find(['/', '?', '#']).unwrap_or(rest.len());
    let host = rest[..authority_end].rsplit_once('@').map_or(&rest[..authority_end], |(_, h)| h);
    let path = rest[authority_end..].split(['?', '#']).next().unwrap_or("");
    format!("{scheme}://{host}{path}")
}

/// The remote cache of one build.
pub struct Remote {
    store: Store,
    /// The redacted URL, for messages.
    shown: String,
    mode: Mode,
    /// Strings never to print (token, password, the raw URL).
    secrets: Vec<String>,
    off: AtomicBool,
    warning: Mutex<Option<String>>,
    /// The largest value read ([`Remote::limit_values`]).
    limit: AtomicU64,
    timeout: Duration,
    key: Option<SigningKey>,
    hits: AtomicU64,
    writes: AtomicU64,
    errors: AtomicU64,
}

impl std::fmt::Debug for Remote {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Remote").field("url", &self.shown).field("mode", &self.mode).finish_non_exhaustive()
    }
}

enum Store {
    Redis(Box<RedisStore>),
    Http(Box<HttpStore>),
}

impl Remote {
    /// Parses the URL and prepares the client; connects on first use.
    pub fn open(options: &Options) -> Result<Remote, Error> {
        let shown = redact(&options.url);
        let bad = |why: String| Error::Url { url: shown.clone(), why };
        let scheme = options.url.split_once("://").map(|(s, _)| s.to_ascii_lowercase());
        let mut secrets: Vec<String> = options.token.iter().cloned().collect();
        if options.url != shown {
            secrets.push(options.url.clone());
        }
        let store = match scheme.as_deref() {
            Some("redis") => {
                let (store, password) = RedisStore::new(options).map_err(|e| bad(scrub(&e, &secrets)))?;
                secrets.extend(password);
                Store::Redis(Box::new(store))
            }
            Some("rediss") | Some("redis+unix") | Some("unix") => return Err(bad(NOT_PLAIN_REDIS.into())),
            Some("http") | Some("https") => {
                let (store, password) = HttpStore::new(options).map_err(bad)?;
                secrets.extend(password);
                Store::Http(Box::new(store))
            }
            _ => return Err(bad("expected redis://host:port[/db] or http(s)://host[:port]/prefix".into())),
        };
        secrets.retain(|s| !s.is_empty());
        Ok(Remote {
            store,
            shown,
            mode: options.mode,
            secrets,
            off: AtomicBool::new(false),
            warning: Mutex::new(None),
            limit: AtomicU64::new(DEFAULT_LIMIT),
            timeout: options.timeout,
            key: options.key.clone(),
            hits: AtomicU64::new(0),
            writes: AtomicU64::new(0),
            errors: AtomicU64::new(0),
        })
    }

    /// The URL as Kiln prints it (see [`redact`]).
    pub fn url(&self) -> &str {
        &self.shown
    }

    pub fn mode(&self) -> Mode {
        self.mode
    }

    /// Values larger than `bytes` (at most [`MAX_VALUE`]) are refused before anything is
    /// allocated for them: the build sets it from its own figures (what its largest entry,
    /// archive or set of records can be, with a wide margin).
    pub fn limit_values(&self, bytes: u64) {
        self.limit.store(bytes.clamp(1 << 20, MAX_VALUE), Ordering::Relaxed);
    }

    fn limit(&self) -> u64 {
        let raw = self.limit.load(Ordering::Relaxed);
        if self.key.is_some() {
            raw + SIGNED_HEADER as u64
        } else {
            raw
        }
    }

    /// Whether values carry a MAC (`KILN_REMOTE_CACHE_KEY` is set).
    pub(crate) fn signs(&self) -> bool {
        self.key.is_some()
    }

    /// The value a reader hands on from what the server sent for `key`: with a key, the
    /// value behind a valid MAC; without, the value (a signed one's MAC left unchecked).
    /// `None`, and the store off with one warning, for anything that is not a Kiln value
    /// or (with a key) has no valid MAC: a server that answers so is not trusted again
    /// this build.
    fn accept<'v>(&self, key: &Key, value: &'v [u8]) -> Option<&'v [u8]> {
        // Values still arriving from a batch asked before the store went off are dropped.
        if self.off.load(Ordering::Relaxed) {
            return None;
        }
        let why = match self.classify(value) {
            Kind::Signed { checked: true }
                if mac(self.key.as_ref()?, key, &value[SIGNED_HEADER..]) == value[8..SIGNED_HEADER] =>
            {
                return Some(&value[SIGNED_HEADER..])
            }
            Kind::Signed { checked: true } => "its MAC does not match KILN_REMOTE_CACHE_KEY",
            Kind::Signed { checked: false } => return Some(&value[SIGNED_HEADER..]),
            Kind::Plain => return Some(value),
            Kind::Refused(why) => why,
        };
        self.refuse(key, why);
        None
    }

    /// What a value that starts with `head` (its first [`SIGNED_HEADER`] bytes, or all of
    /// a shorter one) is to this build.
    fn classify(&self, head: &[u8]) -> Kind {
        let signed = head.len() >= SIGNED_HEADER && &head[..8] == SIGNED_MAGIC;
        match &self.key {
            Some(_) if signed => Kind::Signed { checked: true },
            Some(_) if head.starts_with(b"KILN") => Kind::Refused("it has no MAC (KILN_REMOTE_CACHE_KEY is set)"),
            None if signed => Kind::Signed { checked: false },
            None if head.starts_with(b"KILN") => Kind::Plain,
            _ => Kind::Refused("it is not a Kiln value"),
        }
    }

    /// Turns the store off for a value of `key` that is refused (one warning).
    fn refuse(&self, key: &Key, why: &str) {
        self.errors.fetch_add(1, Ordering::Relaxed);
        if !self.off.swap(true, Ordering::Relaxed) {
            let message = format!(
                "warning: remote cache {}: the value of {key} is refused ({why}); this build goes on with the local cache only",
                self.shown
            );
            *self.warning.lock().expect("no panics while locked") = Some(message);
        }
    }

    /// Whether entries compiled by this build go to the remote.
    pub fn writes(&self) -> bool {
        self.mode == Mode::ReadWrite && !self.off.load(Ordering::Relaxed)
    }

    /// The value stored under `key`; `None` for a miss, and once the store is off.
    pub fn get(&self, key: &Key) -> Option<Vec<u8>> {
        let mut value = Vec::new();
        self.get_into(key, &mut value).then_some(value)
    }

    /// [`Remote::get`] into `value` (cleared first, its capacity kept): whether it was there.
    fn get_into(&self, key: &Key, value: &mut Vec<u8>) -> bool {
        if self.off.load(Ordering::Relaxed) {
            return false;
        }
        let limit = self.limit();
        match self.retry(|| {
            value.clear();
            match &self.store {
                Store::Redis(r) => r.get_into(key, value, limit),
                Store::Http(h) => h.get_into(key, value, limit),
            }
        }) {
            Ok(true) => match self.accept(key, value).map(|v| v.len()) {
                Some(len) => {
                    value.drain(..value.len() - len);
                    true
                }
                None => false,
            },
            Ok(false) => false,
            Err(f) => {
                self.fail("reading from", f);
                false
            }
        }
    }

    /// The value stored under `key`, in pieces as it arrives, to `sink` (a value too large
    /// to hold whole: an archive). True once the whole value arrived and passed its checks;
    /// a signed value's MAC is known good only then, so whatever `sink` got is to be thrown
    /// away on false (a miss, a failure or a refusal: those two with one warning).
    pub(crate) fn get_to(&self, key: &Key, sink: &mut dyn FnMut(&[u8]) -> std::io::Result<()>) -> bool {
        if self.off.load(Ordering::Relaxed) {
            return false;
        }
        let limit = self.limit();
        let mut incoming = Incoming { remote: self, key, head: Vec::new(), state: Arriving::Head, sink, passed: 0 };
        let fetch = |incoming: &mut Incoming<'_>| match &self.store {
            Store::Redis(r) => r.get_to(key, limit, &mut |d| incoming.push(d)),
            Store::Http(h) => h.get_to(key, limit, &mut |d| incoming.push(d)),
        };
        let mut result = fetch(&mut incoming);
        // Once more on a new connection (an idle one the server closed) when nothing arrived.
        if result.as_ref().is_err_and(|f| !f.timed_out && incoming.passed == 0 && incoming.head.is_empty()) {
            result = fetch(&mut incoming);
        }
        match result {
            Ok(true) => match incoming.finish() {
                Ok(accepted) => accepted,
                Err(e) => {
                    self.fail("reading from", Fault { message: format!("keeping a value: {e}"), timed_out: false });
                    false
                }
            },
            Ok(false) => false,
            Err(f) => {
                self.fail("reading from", f);
                false
            }
        }
    }

    /// Calls `f` with each of `keys` and the value stored under it (`None` for a miss, and
    /// once the store is off), from several threads, in no particular order: one round trip
    /// per [`BATCH`] keys with redis (`MGET`), on [`STREAMS`] connections, so that the
    /// server answers one while the others' answers are checked and written (two, on the
    /// build's workers, left it idle about half the time); with HTTP, [`STREAMS`]
    /// connections, each with its own body buffer, asking for a batch of pipelined `GET`s at
    /// a time (plain HTTP) or one key (HTTPS).
    pub fn get_each(&self, keys: &[Key], f: impl Fn(&Key, Option<&[u8]>) + Sync) {
        // Each value accepted (else a miss, and the store off).
        let f_accepted = &f;
        let f = |key: &Key, v: Option<&[u8]>| f(key, v.and_then(|v| self.accept(key, v)));
        let limit = self.limit();
        match &self.store {
            Store::Redis(r) => in_batches(keys, BATCH, |batch, value| {
                // Each value handed on as it arrives; after a failure, the keys not answered
                // yet are asked again once (an idle connection the server closed), then are
                // misses.
                let done = std::cell::Cell::new(0);
                if !self.off.load(Ordering::Relaxed) {
                    let mut each = |key: &Key, v: Option<&[u8]>| {
                        f(key, v);
                        done.set(done.get() + 1);
                    };
                    if let Err(fault) = self.retry(|| r.get_many(&batch[done.get()..], value, limit, &mut each)) {
                        self.fail("reading from", fault);
                    }
                }
                batch[done.get()..].iter().for_each(|key| f(key, None));
            }),
            Store::Http(h) => {
                // Plain HTTP: batches of pipelined GETs; HTTPS: one request at a time.
                let batch = if h.batch.is_some() { super::http_batch::BATCH } else { 1 };
                in_batches(keys, batch, |chunk, value| match &h.batch {
                    Some(p) => self.get_pipelined(p, chunk, value, limit, &f),
                    None => chunk.iter().for_each(|key| {
                        // Accepted already.
                        let found = self.get_into(key, value);
                        f_accepted(key, found.then_some(value.as_slice()));
                    }),
                });
            }
        }
    }

    /// `f` with each of `keys` and its value, through pipelined GETs: a connection the server
    /// closed after some answers leaves the rest to a new one; a failure before any answer
    /// is tried again once (an idle connection the server closed), except a timeout.
    fn get_pipelined(
        &self,
        batch: &super::http_batch::HttpBatch,
        keys: &[Key],
        value: &mut Vec<u8>,
        limit: u64,
        f: &impl Fn(&Key, Option<&[u8]>),
    ) {
        let (mut done, mut retried) = (0, false);
        while done < keys.len() && !self.off.load(Ordering::Relaxed) {
            match batch.get(&keys[done..], value, limit, f) {
                Ok(n) => done += n,
                Err((n, fault)) => {
                    done += n;
                    if n == 0 && !retried && !fault.timed_out {
                        retried = true;
                        continue;
                    }
                    self.fail("reading from", fault);
                }
            }
        }
        keys[done..].iter().for_each(|key| f(key, None));
    }

    /// Whether values of many megabytes are read as they arrive ([`Remote::get_streamed`]):
    /// with HTTP. Redis hands a client each value whole.
    pub(crate) fn streams(&self) -> bool {
        matches!(self.store, Store::Http(_))
    }

    /// Calls `f` with the index of each of `keys` and a reader of the value stored under it
    /// as it arrives (`None` for a miss, once the store is off, and without
    /// [`Remote::streams`]), on [`STREAMS`] connections, one request at a time on each,
    /// in no particular order. A connection that fails while `f` reads makes `f`'s reads
    /// fail (a truncated value), then turns the store off.
    pub(crate) fn get_streamed(&self, keys: &[Key], f: impl Fn(usize, Option<&mut dyn std::io::Read>) + Sync) {
        let Store::Http(h) = &self.store else {
            (0..keys.len()).for_each(|i| f(i, None));
            return;
        };
        let next = std::sync::atomic::AtomicUsize::new(0);
        std::thread::scope(|s| {
            for _ in 0..STREAMS.min(keys.len()) {
                s.spawn(|| loop {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    let Some(key) = keys.get(i) else { break };
                    if self.off.load(Ordering::Relaxed) {
                        f(i, None);
                        continue;
                    }
                    let called = std::cell::Cell::new(false);
                    let mut g = |body: Option<&mut dyn std::io::Read>| {
                        called.set(true);
                        f(i, body);
                    };
                    let limit = self.limit();
                    let mut result = h.get_streamed(key, limit, &mut g);
                    // Once more on a new connection (an idle one the server closed), unless
                    // it timed out or `f` had its answer.
                    if result.as_ref().is_err_and(|(_, fault)| !called.get() && !fault.timed_out) {
                        result = h.get_streamed(key, limit, &mut g);
                    }
                    if let Err((_, fault)) = result {
                        self.fail("reading from", fault);
                        if !called.get() {
                            f(i, None);
                        }
                    }
                });
            }
        });
    }

    /// Whether the remote holds a value under `key` (HTTP `HEAD`, redis `EXISTS`); `None`
    /// once the store is off.
    pub(crate) fn contains(&self, key: &Key) -> Option<bool> {
        if self.off.load(Ordering::Relaxed) {
            return None;
        }
        self.retry(|| match &self.store {
            Store::Redis(r) => r.contains(key),
            Store::Http(h) => h.head(key),
        })
        .map_err(|fault| self.fail("reading from", fault))
        .ok()
    }

    /// Stores the entry `value` under `key` (in read-write mode, while the store is on).
    pub fn put(&self, key: &Key, value: &[u8]) {
        if self.store(key, value) {
            self.writes.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// [`Remote::put`] of each of `entries` (key, value): with redis, [`BATCH`] `SET`s sent
    /// at once, then their replies read (one round trip rather than one per entry, which a
    /// shard compiling on one thread waited for one by one); with HTTP, one `PUT` each.
    pub fn put_each(&self, entries: &[(Key, Vec<u8>)]) {
        let Store::Redis(r) = &self.store else {
            entries.iter().for_each(|(key, value)| self.put(key, value));
            return;
        };
        for batch in entries.chunks(BATCH) {
            if !self.writes() {
                return;
            }
            let signed: Vec<std::borrow::Cow<'_, [u8]>> =
                batch.iter().map(|(key, value)| self.signed(key, value)).collect();
            let values: Vec<(&Key, &[u8])> = batch.iter().map(|(k, _)| k).zip(signed.iter().map(|v| &v[..])).collect();
            match self.retry(|| r.put_many(&values)) {
                Ok(()) => {
                    self.writes.fetch_add(batch.len() as u64, Ordering::Relaxed);
                }
                Err(f) => self.fail("writing to", f),
            }
        }
    }

    /// `value` as stored under `key`: behind a MAC with `KILN_REMOTE_CACHE_KEY`.
    fn signed<'v>(&self, key: &Key, value: &'v [u8]) -> std::borrow::Cow<'v, [u8]> {
        match &self.key {
            Some(k) => [&SIGNED_MAGIC[..], &mac(k, key, value), value].concat().into(),
            None => value.into(),
        }
    }

    /// [`Remote::put`] of a value that is not a compiled entry (not counted in the stats).
    pub(crate) fn store(&self, key: &Key, value: &[u8]) -> bool {
        if !self.writes() {
            return false;
        }
        let signed = self.signed(key, value);
        let value = &signed[..];
        match self.retry(|| match &self.store {
            Store::Redis(r) => r.put(key, value),
            Store::Http(h) => h.put(key, value),
        }) {
            Ok(()) => true,
            Err(f) => {
                self.fail("writing to", f);
                false
            }
        }
    }

    /// [`Remote::store`] of a value read from `source` rather than held in memory (an
    /// archive: the largest value a build stores). It is read once more to sign it (with
    /// `KILN_REMOTE_CACHE_KEY`) and once per attempt; a source whose length changes while it
    /// is sent fails the request, which the server then never sees whole.
    pub(crate) fn store_from(&self, key: &Key, source: &dyn Source) -> bool {
        if !self.writes() {
            return false;
        }
        let prefix = match &self.key {
            Some(k) => match mac_of(k, key, source) {
                Ok(m) => [&SIGNED_MAGIC[..], &m].concat(),
                Err(e) => {
                    self.fail("writing to", Fault { message: format!("reading the value: {e}"), timed_out: false });
                    return false;
                }
            },
            None => Vec::new(),
        };
        let len = prefix.len() as u64 + source.len();
        let body = || -> std::io::Result<Box<dyn std::io::Read + '_>> {
            Ok(Box::new(std::io::Read::chain(&prefix[..], source.open()?)))
        };
        match self.retry(|| match &self.store {
            Store::Redis(r) => r.put_from(key, len, &body),
            Store::Http(h) => h.put_from(key, len, &body),
        }) {
            Ok(()) => true,
            Err(f) => {
                self.fail("writing to", f);
                false
            }
        }
    }

    /// Counts a value that passed its checks.
    pub(crate) fn count_hit(&self) {
        self.hits.fetch_add(1, Ordering::Relaxed);
    }

    /// Counts `n` values that passed their checks (see [`super::Cache::prefill_from_remote`]).
    pub fn count_hits(&self, n: u64) {
        self.hits.fetch_add(n, Ordering::Relaxed);
    }

    pub fn stats(&self) -> Stats {
        Stats {
            hits: self.hits.load(Ordering::Relaxed),
            writes: self.writes.load(Ordering::Relaxed),
            errors: self.errors.load(Ordering::Relaxed),
        }
    }

    /// The one warning about the store failing, the first time it is asked for.
    pub fn take_warning(&self) -> Option<String> {
        self.warning.lock().expect("no panics while locked").take()
    }

    /// `op` again once when it failed on something other than a timeout: a pooled
    /// connection the server closed while idle fails once, then a new one works.
    fn retry<T>(&self, mut op: impl FnMut() -> Result<T, Fault>) -> Result<T, Fault> {
        match op() {
            Err(f) if !f.timed_out && !self.off.load(Ordering::Relaxed) => op(),
            r => r,
        }
    }

    fn fail(&self, doing: &str, fault: Fault) {
        self.errors.fetch_add(1, Ordering::Relaxed);
        if !self.off.swap(true, Ordering::Relaxed) {
            let why = if fault.timed_out {
                // Named as a timeout, with what was waited for (never the OS's words).
                format!(
                    "{}: {} sent nothing within the timeout of {} ms, or a request took longer than {} ms",
                    fault.message,
                    self.shown,
                    self.timeout.as_millis(),
                    super::fault::request_bound(self.timeout, 0).as_millis()
                )
            } else {
                fault.message
            };
            let message = format!(
                "warning: remote cache {}: {doing} it failed ({}); this build goes on with the local cache only",
                self.shown,
                scrub(&why, &self.secrets)
            );
            *self.warning.lock().expect("no panics while locked") = Some(message);
        }
    }
}

/// `text` with every secret replaced by `***`.
fn scrub(text: &str, secrets: &[String]) -> String {
    let mut out = text.to_string();
    for s in secrets.iter().filter(|s| !s.is_empty()) {
        out = out.replace(s.as_str(), "***");
    }
    out
}

/// Redis over [`RawRedis`] connections, a few kept open for the workers. The `redis` crate
/// parses the URL; every request (`MGET`, `GET` as an `MGET` of one key, `SET`, `EXISTS`)
/// and every connection's setup (lookup, connect, `AUTH`, `SELECT`) runs under a deadline
/// for the whole of it.
struct RedisStore {
    /// Where requests go, and how connections log in.
    target: RawTarget,
    idle: Mutex<Vec<RawRedis>>,
    timeout: Duration,
}

impl RedisStore {
    /// The store and the password it uses (a secret).
    fn new(options: &Options) -> Result<(RedisStore, Option<String>), String> {
        use redis::IntoConnectionInfo;
        let mut info = options.url.as_str().into_connection_info().map_err(|e| e.to_string())?;
        if info.redis_settings().password().is_none() {
            if let Some(token) = &options.token {
                let settings = info.redis_settings().clone();
                let settings = match token.split_once(':') {
                    Some((user, password)) => settings.set_username(user).set_password(password),
                    None => settings.set_password(token),
                };
                info = info.set_redis_settings(settings);
            }
        }
        let password = info.redis_settings().password().map(str::to_string);
        let settings = info.redis_settings();
        let target = RawTarget {
            address: match info.addr() {
                redis::ConnectionAddr::Tcp(host, port) => (host.clone(), *port),
                _ => return Err(NOT_PLAIN_REDIS.into()),
            },
            username: settings.username().map(str::to_string),
            password: password.clone(),
            db: settings.db(),
        };
        let store = RedisStore { target, idle: Mutex::default(), timeout: options.timeout };
        Ok((store, password))
    }

    /// `f` on an idle connection, else a new one; a connection that failed is dropped (its
    /// reply may be half read).
    fn with_connection<T>(&self, f: impl FnOnce(&mut RawRedis) -> Result<T, Fault>) -> Result<T, Fault> {
        let idle = self.idle.lock().expect("no panics while locked").pop();
        let mut connection = match idle {
            Some(c) => c,
            None => RawRedis::connect(&self.target, self.timeout)?,
        };
        let result = f(&mut connection)?;
        self.idle.lock().expect("no panics while locked").push(connection);
        Ok(result)
    }

    fn name(key: &Key) -> String {
        format!("kiln:{key}")
    }

    /// The value of `key` into `value`: whether it was there (an `MGET` of one key: its
    /// value is read straight into `value`, without a general reply parser).
    fn get_into(&self, key: &Key, value: &mut Vec<u8>, limit: u64) -> Result<bool, Fault> {
        let mut found = None;
        self.get_many(std::slice::from_ref(key), value, limit, &mut |_, v| found = v.map(<[u8]>::len))?;
        Ok(found.map(|len| value.truncate(len)).is_some())
    }

    fn contains(&self, key: &Key) -> Result<bool, Fault> {
        self.with_connection(|c| c.exists(&Self::name(key)))
    }

    fn put(&self, key: &Key, value: &[u8]) -> Result<(), Fault> {
        self.with_connection(|c| c.set(&Self::name(key), value))
    }

    /// `SET` of each of `values`, pipelined on one connection.
    fn put_many(&self, values: &[(&Key, &[u8])]) -> Result<(), Fault> {
        let named: Vec<(String, &[u8])> = values.iter().map(|(k, v)| (Self::name(k), *v)).collect();
        self.with_connection(|c| c.set_many(&named))
    }

    /// `GET` of `key`, its value to `push` in pieces: whether it was there.
    fn get_to(&self, key: &Key, limit: u64, push: &mut dyn FnMut(&[u8]) -> std::io::Result<()>) -> Result<bool, Fault> {
        self.with_connection(|c| c.get_to(&Self::name(key), limit, push))
    }

    fn put_from(&self, key: &Key, len: u64, body: &Body<'_>) -> Result<(), Fault> {
        let mut body =
            body().map_err(|e| Fault { message: format!("SET: reading the value: {e}"), timed_out: false })?;
        self.with_connection(|c| c.set_from(&Self::name(key), len, &mut body))
    }

    /// One `MGET` of every key: `f` with each key and its value (`value` is the buffer of
    /// [`RawRedis::mget`]); an error leaves the keys after those `f` had unanswered.
    fn get_many(
        &self,
        keys: &[Key],
        value: &mut Vec<u8>,
        limit: u64,
        f: &mut dyn FnMut(&Key, Option<&[u8]>),
    ) -> Result<(), Fault> {
        if keys.is_empty() {
            return Ok(());
        }
        self.with_connection(|c| c.mget(keys, value, limit, f))
    }
}

/// Why a redis URL other than `redis://host:port[/db]` is refused.
const NOT_PLAIN_REDIS: &str =
    "only redis://host:port[/db] is supported (no TLS, no unix socket: a TLS tunnel such as stunnel can sit in front)";

/// How [`RawRedis`] connections reach and log in to the server.
struct RawTarget {
    /// Host and port.
    address: (String, u16),
    username: Option<String>,
    password: Option<String>,
    db: i64,
}

/// A plain RESP2 connection that sends `MGET`, `SET` and `EXISTS` and reads their replies
/// straight from a buffered socket: each bulk string is read into a vector of its announced
/// length, without the `redis` crate's general reply parser and `Value` tree (most of the
/// CPU a warm-remote fill spent in the client). Each request, and the connection's setup,
/// has a deadline for the whole of it ([`RawRedis::within`]), besides the per-read and
/// per-write timeout.
struct RawRedis {
    reader: std::io::BufReader<Timed>,
}

impl RawRedis {
    fn io_fault(e: std::io::Error) -> Fault {
        if matches!(e.kind(), std::io::ErrorKind::TimedOut | std::io::ErrorKind::WouldBlock) {
            return Fault::timeout("reading a reply");
        }
        Fault { message: e.to_string(), timed_out: false }
    }

    fn protocol(what: &str) -> Fault {
        Fault { message: format!("unexpected reply from redis: {what}"), timed_out: false }
    }

    /// Looks the host up, connects, then logs in and selects the database as the URL and
    /// token say: all of it within one request's deadline.
    fn connect(target: &RawTarget, timeout: Duration) -> Result<RawRedis, Fault> {
        let start = Instant::now();
        let end = deadline(timeout);
        let (host, port) = &target.address;
        let timed_out = |f: Fault| match f.timed_out {
            true => Fault::timeout_after("connecting", start.elapsed()),
            false => f,
        };
        let addresses = resolve(host, *port, timeout).map_err(timed_out)?;
        let mut last = Fault { message: format!("no address for {host}"), timed_out: false };
        for address in addresses {
            let left = end.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(Fault::timeout_after("connecting", start.elapsed()));
            }
            match std::net::TcpStream::connect_timeout(&address, left.min(timeout)) {
                Ok(stream) => {
                    stream.set_read_timeout(Some(timeout)).map_err(Self::io_fault)?;
                    stream.set_write_timeout(Some(timeout)).map_err(Self::io_fault)?;
                    let _ = stream.set_nodelay(true);
                    let mut c =
                        RawRedis { reader: std::io::BufReader::with_capacity(1 << 16, Timed::new(stream, timeout)) };
                    c.reader.get_mut().set_deadline(Some(end));
                    let logged_in = c.log_in(target);
                    c.reader.get_mut().set_deadline(None);
                    logged_in.map_err(timed_out)?;
                    return Ok(c);
                }
                Err(e) => last = timed_out(Self::io_fault(e)),
            }
        }
        Err(last)
    }

    /// `AUTH` and `SELECT`, where the target needs them.
    fn log_in(&mut self, target: &RawTarget) -> Result<(), Fault> {
        if let Some(password) = &target.password {
            let mut args: Vec<&[u8]> = vec![b"AUTH"];
            args.extend(target.username.as_deref().map(str::as_bytes));
            args.push(password.as_bytes());
            self.send(&args)?;
            self.expect_ok("AUTH")?;
        }
        if target.db != 0 {
            let db = target.db.to_string();
            self.send(&[b"SELECT", db.as_bytes()])?;
            self.expect_ok("SELECT")?;
        }
        Ok(())
    }

    /// `request` (named `command` in a fault) under a deadline for the whole of it: a few
    /// timeouts, plus the transfer time of the `sending` bytes it sends (what it reads moves
    /// the deadline as lengths are announced). A timeout is named with the time waited.
    fn within<T>(
        &mut self,
        command: &str,
        sending: u64,
        request: impl FnOnce(&mut RawRedis) -> Result<T, Fault>,
    ) -> Result<T, Fault> {
        let start = Instant::now();
        let timeout = self.reader.get_ref().timeout();
        self.reader.get_mut().set_deadline(Some(deadline(timeout) + transfer_time(sending)));
        let result = request(self);
        self.reader.get_mut().set_deadline(None);
        result.map_err(|f| match f.timed_out {
            true => Fault::timeout_after(command, start.elapsed()),
            false => f,
        })
    }

    /// `SET name value`.
    fn set(&mut self, name: &str, value: &[u8]) -> Result<(), Fault> {
        self.within("SET", value.len() as u64, |c| {
            c.send(&[b"SET", name.as_bytes(), value])?;
            c.expect_ok("SET")
        })
    }

    /// `SET` of each (name, value), every command sent before the first reply is read.
    fn set_many(&mut self, values: &[(String, &[u8])]) -> Result<(), Fault> {
        let sending = values.iter().map(|(_, v)| v.len() as u64).sum();
        self.within("SET", sending, |c| {
            for (name, value) in values {
                c.send(&[b"SET", name.as_bytes(), value])?;
            }
            values.iter().try_for_each(|_| c.expect_ok("SET"))
        })
    }

    /// `SET name value` with the `len` bytes of `value` copied from it to the socket as
    /// they are read. A value shorter than announced fails before its end is sent (the
    /// connection is then dropped, so the server never stores it).
    fn set_from(&mut self, name: &str, len: u64, value: &mut dyn std::io::Read) -> Result<(), Fault> {
        use std::io::Write;
        self.within("SET", len, |c| {
            let head = format!("*3\r\n$3\r\nSET\r\n${}\r\n{name}\r\n${len}\r\n", name.len());
            let socket = c.reader.get_mut();
            socket.write_all(head.as_bytes()).map_err(Self::io_fault)?;
            let sent = std::io::copy(&mut std::io::Read::take(value, len), socket).map_err(Self::io_fault)?;
            if sent != len {
                return Err(Fault { message: "SET: the value changed while it was sent".into(), timed_out: false });
            }
            socket.write_all(b"\r\n").map_err(Self::io_fault)?;
            c.expect_ok("SET")
        })
    }

    /// `GET name`, its value to `push` in pieces as it is read: whether it was there. A
    /// failure of `push` (the disk it writes to) fails the request.
    fn get_to(
        &mut self,
        name: &str,
        limit: u64,
        push: &mut dyn FnMut(&[u8]) -> std::io::Result<()>,
    ) -> Result<bool, Fault> {
        use std::io::Read;
        self.within("GET", 0, |c| {
            c.send(&[b"GET", name.as_bytes()])?;
            let len = c.header(b'$')?;
            if len < 0 {
                return Ok(false);
            }
            if len as u64 > limit {
                let message = format!("a value of {len} bytes is larger than any this build stores (at most {limit})");
                return Err(Fault { message, timed_out: false });
            }
            c.reader.get_mut().extend_deadline(transfer_time(len as u64));
            let mut left = len as u64;
            let mut buf = vec![0u8; 256 << 10];
            while left > 0 {
                let want = buf.len().min(left as usize);
                let n = c.reader.read(&mut buf[..want]).map_err(Self::io_fault)?;
                if n == 0 {
                    return Err(Self::protocol("a truncated value"));
                }
                push(&buf[..n])
                    .map_err(|e| Fault { message: format!("GET: keeping the value: {e}"), timed_out: false })?;
                left -= n as u64;
            }
            let mut end = [0u8; 2];
            c.reader.read_exact(&mut end).map_err(Self::io_fault)?;
            if &end != b"\r\n" {
                return Err(Self::protocol("a bulk string without its CRLF"));
            }
            Ok(true)
        })
    }

    /// `EXISTS name`: whether the server holds it.
    fn exists(&mut self, name: &str) -> Result<bool, Fault> {
        self.within("EXISTS", 0, |c| {
            c.send(&[b"EXISTS", name.as_bytes()])?;
            Ok(c.header(b':')? > 0)
        })
    }

    fn send(&mut self, args: &[&[u8]]) -> Result<(), Fault> {
        use std::io::Write;
        let mut out = Vec::with_capacity(16 + args.iter().map(|a| a.len() + 16).sum::<usize>());
        out.extend_from_slice(format!("*{}\r\n", args.len()).as_bytes());
        for a in args {
            out.extend_from_slice(format!("${}\r\n", a.len()).as_bytes());
            out.extend_from_slice(a);
            out.extend_from_slice(b"\r\n");
        }
        self.reader.get_mut().write_all(&out).map_err(Self::io_fault)
    }

    /// One reply line without its CRLF.
    fn line(&mut self) -> Result<Vec<u8>, Fault> {
        use std::io::{BufRead, Read};
        let mut line = Vec::new();
        (&mut self.reader).take(64 * 1024).read_until(b'\n', &mut line).map_err(Self::io_fault)?;
        if !line.ends_with(b"\r\n") {
            return Err(Self::protocol("a truncated reply"));
        }
        line.truncate(line.len() - 2);
        Ok(line)
    }

    /// The number after the line's type byte `kind`; a server error (`-...`) is a fault
    /// (its text never holds the password: redis does not echo arguments).
    fn header(&mut self, kind: u8) -> Result<i64, Fault> {
        let line = self.line()?;
        match line.split_first() {
            Some((&k, number)) if k == kind => std::str::from_utf8(number)
                .ok()
                .and_then(|n| n.parse().ok())
                .ok_or_else(|| Self::protocol("a malformed length")),
            Some((b'-', text)) => Err(Fault { message: String::from_utf8_lossy(text).into_owned(), timed_out: false }),
            _ => Err(Self::protocol("an unexpected reply type")),
        }
    }

    fn expect_ok(&mut self, command: &str) -> Result<(), Fault> {
        let line = self.line()?;
        match line.split_first() {
            Some((b'+', _)) => Ok(()),
            Some((b'-', text)) => {
                Err(Fault { message: format!("{command}: {}", String::from_utf8_lossy(text)), timed_out: false })
            }
            _ => Err(Self::protocol("an unexpected reply type")),
        }
    }

    /// One `MGET` of `keys`: `f` with each key and its value as the reply arrives (read into
    /// `value` one at a time, not gathered); an error leaves the keys after those `f` had
    /// unanswered. The whole reply is bounded by a deadline (moved by the time each value's
    /// announced length takes), each value by `limit`, checked before it is allocated.
    fn mget(
        &mut self,
        keys: &[Key],
        value: &mut Vec<u8>,
        limit: u64,
        f: &mut dyn FnMut(&Key, Option<&[u8]>),
    ) -> Result<(), Fault> {
        self.within("MGET", 0, |c| c.mget_within(keys, value, limit, f))
    }

    fn mget_within(
        &mut self,
        keys: &[Key],
        value: &mut Vec<u8>,
        limit: u64,
        f: &mut dyn FnMut(&Key, Option<&[u8]>),
    ) -> Result<(), Fault> {
        use std::io::Read;
        let names: Vec<String> = keys.iter().map(RedisStore::name).collect();
        let mut args: Vec<&[u8]> = Vec::with_capacity(keys.len() + 1);
        args.push(b"MGET");
        args.extend(names.iter().map(|n| n.as_bytes()));
        self.send(&args)?;
        let count = self.header(b'*')?;
        if count != keys.len() as i64 {
            let message = format!("MGET of {} keys answered {count} values", keys.len());
            return Err(Fault { message, timed_out: false });
        }
        for key in keys {
            let len = self.header(b'$')?;
            if len < 0 {
                f(key, None);
                continue;
            }
            if len as u64 > limit {
                let message = format!("a value of {len} bytes is larger than any this build stores (at most {limit})");
                return Err(Fault { message, timed_out: false });
            }
            self.reader.get_mut().extend_deadline(transfer_time(len as u64));
            // Read into spare capacity (not zeroed first; the buffer's pages are reused from
            // value to value); an early end is a truncated value.
            value.clear();
            // Room for the whole value at once (a large one is not grown step by step), up
            // to a bound: a damaged length reserves no more.
            value.reserve((len as usize + 2).min(MAX_RESERVE));
            (&mut self.reader).take(len as u64 + 2).read_to_end(value).map_err(Self::io_fault)?;
            if value.len() != len as usize + 2 {
                return Err(Self::protocol("a truncated value"));
            }
            if !value.ends_with(b"\r\n") {
                return Err(Self::protocol("a bulk string without its CRLF"));
            }
            f(key, Some(&value[..len as usize]));
        }
        Ok(())
    }
}

/// GET and PUT of `<prefix>/<key>` through `ureq` (keep-alive connections, pooled).
struct HttpStore {
    agent: ureq::Agent,
    /// The URL without credentials, without a trailing slash.
    prefix: String,
    authorization: Option<String>,
    /// A fill's pipelined GETs, with plain HTTP.
    batch: Option<super::http_batch::HttpBatch>,
}

impl HttpStore {
    /// The store and the password it uses (a secret).
    fn new(options: &Options) -> Result<(HttpStore, Option<String>), String> {
        let url = options.url.as_str();
        let (scheme, rest) = url.split_once("://").expect("checked by the caller");
        if scheme.eq_ignore_ascii_case("https") && !cfg!(feature = "https") {
            return Err("this kiln was built without https support (cargo feature `https`)".into());
        }
        let authority_end = rest.find(['/', '?', '#']).unwrap_or(rest.len());
        let (userinfo, host) = match rest[..authority_end].rsplit_once('@') {
            Some((u, h)) => (Some(u), h),
            None => (None, &rest[..authority_end]),
        };
        if host.is_empty() {
            return Err("no host".into());
        }
        if rest[authority_end..].contains(['?', '#']) {
            return Err("a query or fragment has no meaning here".into());
        }
        let path = rest[authority_end..].trim_end_matches('/');
        let prefix = format!("{scheme}://{host}{path}");
        // Credentials in the URL win over the token; `user:password` is basic auth.
        let credentials = userinfo.map(str::to_string).or_else(|| options.token.clone());
        let (authorization, password) = match credentials {
            None => (None, None),
            Some(c) => match c.split_once(':') {
                Some((_, password)) => {
                    use base64::Engine;
                    let encoded = base64::engine::general_purpose::STANDARD.encode(c.as_bytes());
                    (Some(format!("Basic {encoded}")), Some(password.to_string()))
                }
                None => (Some(format!("Bearer {c}")), Some(c.clone())),
            },
        };
        let config = ureq::Agent::config_builder()
            .http_status_as_error(false)
            .timeout_connect(Some(options.timeout))
            .timeout_resolve(Some(options.timeout))
            .timeout_per_read(Some(options.timeout))
            .timeout_per_write(Some(options.timeout))
            .timeout_per_call(Some(request_bound(options.timeout, DEFAULT_LIMIT)))
            .max_idle_connections_per_host(STREAMS)
            .user_agent(concat!("kiln/", env!("CARGO_PKG_VERSION")));
        #[cfg(feature = "https")]
        let config = match std::env::var_os("KILN_REMOTE_CACHE_CA").filter(|p| !p.is_empty()) {
            Some(path) => config.tls_config(trusted(std::path::Path::new(&path))?),
            None => config,
        };
        let config = config.build();
        let agent = ureq::Agent::with_parts(
            config,
            ureq::unversioned::transport::DefaultConnector::default(),
            OnceResolver::default(),
        );
        let batch = if scheme.eq_ignore_ascii_case("http") {
            super::http_batch::HttpBatch::new(host, path, authorization.as_deref(), options.timeout)
        } else {
            None
        };
        Ok((HttpStore { agent, prefix, authorization, batch }, password))
    }

    fn url(&self, key: &Key) -> String {
        format!("{}/{key}", self.prefix)
    }

    fn fault(e: ureq::Error) -> Fault {
        let timed_out = match &e {
            ureq::Error::Timeout(_) => true,
            ureq::Error::Io(io) => matches!(io.kind(), std::io::ErrorKind::TimedOut | std::io::ErrorKind::WouldBlock),
            _ => false,
        };
        if timed_out {
            return Fault::timeout("waiting for an answer");
        }
        Fault { message: e.to_string(), timed_out }
    }

    fn status(doing: &str, status: ureq::http::StatusCode) -> Fault {
        Fault { message: format!("{doing} answered {status}"), timed_out: false }
    }

    /// The value of `key` appended to `value`; whether there was one.
    fn get_into(&self, key: &Key, value: &mut Vec<u8>, limit: u64) -> Result<bool, Fault> {
        if let Some(p) = &self.batch {
            // Plain HTTP: one request of the batches' kind (a deadline for the whole of it).
            let found = std::cell::Cell::new(None);
            let mut body = std::mem::take(value);
            let r = p.get(std::slice::from_ref(key), &mut body, limit, &|_, v| found.set(Some(v.is_some())));
            *value = body;
            return match r {
                Ok(_) => Ok(found.get() == Some(true)),
                Err((_, fault)) => Err(fault),
            };
        }
        let mut request = self.agent.get(self.url(key));
        if let Some(a) = &self.authorization {
            request = request.header("Authorization", a);
        }
        let mut response = request.call().map_err(Self::fault)?;
        match response.status().as_u16() {
            200 => {
                // Room for the announced length at once (not grown as it comes).
                use std::io::Read;
                let announced = response.body().content_length().unwrap_or(0);
                if announced > limit {
                    let message = format!("a value of {announced} bytes is larger than any this build stores");
                    return Err(Fault { message, timed_out: false });
                }
                value.reserve(announced as usize);
                let mut reader = response.body_mut().with_config().limit(limit).reader();
                reader.read_to_end(value).map_err(|e| Self::fault(ureq::Error::Io(e)))?;
                Ok(true)
            }
            404 => Ok(false),
            _ => Err(Self::status("GET", response.status())),
        }
    }

    /// `f` with a reader of the value of `key` as it arrives (`None` for a 404): pipelined
    /// plain HTTP's connections, else ureq's. `Err((called, fault))` as
    /// [`super::http_batch::HttpBatch::get_streamed`].
    fn get_streamed(
        &self,
        key: &Key,
        limit: u64,
        f: &mut dyn FnMut(Option<&mut dyn std::io::Read>),
    ) -> Result<(), (bool, Fault)> {
        if let Some(p) = &self.batch {
            return p.get_streamed(key, limit, f);
        }
        let mut request = self.agent.get(self.url(key));
        if let Some(a) = &self.authorization {
            request = request.header("Authorization", a);
        }
        let mut response = request.call().map_err(|e| (false, Self::fault(e)))?;
        match response.status().as_u16() {
            200 => {
                let mut reader = response.body_mut().with_config().limit(limit).reader();
                f(Some(&mut reader));
                std::io::copy(&mut reader, &mut std::io::sink())
                    .map_err(|e| (true, Self::fault(ureq::Error::Io(e))))?;
                Ok(())
            }
            404 => {
                f(None);
                Ok(())
            }
            _ => Err((false, Self::status("GET", response.status()))),
        }
    }

    /// `GET` of `key`, its body to `push` in pieces: whether it was there.
    fn get_to(&self, key: &Key, limit: u64, push: &mut dyn FnMut(&[u8]) -> std::io::Result<()>) -> Result<bool, Fault> {
        let mut outcome = Ok(false);
        let mut f = |body: Option<&mut dyn std::io::Read>| {
            if let Some(body) = body {
                outcome = copy_pieces(body, push).map(|()| true);
            }
        };
        self.get_streamed(key, limit, &mut f).map_err(|(_, fault)| fault)?;
        outcome.map_err(|e| Fault { message: format!("GET: {e}"), timed_out: false })
    }

    /// Whether `key` has a value (`HEAD`).
    fn head(&self, key: &Key) -> Result<bool, Fault> {
        let mut request = self.agent.head(self.url(key));
        if let Some(a) = &self.authorization {
            request = request.header("Authorization", a);
        }
        let response = request.call().map_err(Self::fault)?;
        match response.status().as_u16() {
            200 => Ok(true),
            404 => Ok(false),
            _ => Err(Self::status("HEAD", response.status())),
        }
    }

    fn put(&self, key: &Key, value: &[u8]) -> Result<(), Fault> {
        let mut request = self.agent.put(self.url(key));
        if let Some(a) = &self.authorization {
            request = request.header("Authorization", a);
        }
        let response = request.send(value).map_err(Self::fault)?;
        if response.status().is_success() {
            Ok(())
        } else {
            Err(Self::status("PUT", response.status()))
        }
    }

    /// [`HttpStore::put`] of `len` bytes read from `body` as they are sent (with their
    /// length announced, so a server need not take a chunked upload).
    fn put_from(&self, key: &Key, len: u64, body: &Body<'_>) -> Result<(), Fault> {
        let mut request = self.agent.put(self.url(key)).header("Content-Length", len.to_string());
        if let Some(a) = &self.authorization {
            request = request.header("Authorization", a);
        }
        let body = body().map_err(|e| Fault { message: format!("PUT: reading the value: {e}"), timed_out: false })?;
        let mut exact = std::io::Read::take(body, len);
        let response = request.send(ureq::SendBody::from_reader(&mut exact)).map_err(Self::fault)?;
        if response.status().is_success() {
            Ok(())
        } else {
            Err(Self::status("PUT", response.status()))
        }
    }
}

/// Resolves each host once per build, then gives its addresses again. ureq's own resolver
/// resolves before every request, on a thread of its own when the lookup has a timeout (a
/// thousand threads for a thousand GETs: a quarter of a fresh local cache's fill with HTTP).
/// (`ureq::unversioned`: outside ureq's semver promise, pinned by Cargo.lock.)
#[derive(Debug, Default)]
struct OnceResolver {
    resolved: Mutex<std::collections::HashMap<String, ureq::unversioned::resolver::ResolvedSocketAddrs>>,
}

impl ureq::unversioned::resolver::Resolver for OnceResolver {
    fn resolve(
        &self,
        uri: &ureq::http::Uri,
        config: &ureq::config::Config,
        timeout: ureq::unversioned::transport::NextTimeout,
    ) -> Result<ureq::unversioned::resolver::ResolvedSocketAddrs, ureq::Error> {
        let host = format!("{:?} {:?}", uri.scheme(), uri.authority());
        if let Some(addresses) = self.resolved.lock().expect("no panics while locked").get(&host) {
            return Ok(addresses.clone());
        }
        let addresses = ureq::unversioned::resolver::DefaultResolver::default().resolve(uri, config, timeout)?;
        self.resolved.lock().expect("no panics while locked").insert(host, addresses.clone());
        Ok(addresses)
    }
}

/// TLS that trusts only the certificates of the PEM file at `path` (`KILN_REMOTE_CACHE_CA`:
/// a company's own certificate authority, or a self-signed server's certificate) instead
/// of the Mozilla roots.
#[cfg(feature = "https")]
fn trusted(path: &std::path::Path) -> Result<ureq::tls::TlsConfig, String> {
    use ureq::tls::{parse_pem, PemItem, RootCerts, TlsConfig};
    let why = |e: String| format!("KILN_REMOTE_CACHE_CA: {}: {e}", path.display());
    let pem = crate::archive::input::read_regular(path, 16 << 20).map_err(|e| why(e.to_string()))?;
    let mut certificates = Vec::new();
    for item in parse_pem(&pem) {
        if let PemItem::Certificate(c) = item.map_err(|e| why(e.to_string()))? {
            certificates.push(c);
        }
    }
    if certificates.is_empty() {
        return Err(why("no PEM certificate in it".into()));
    }
    Ok(TlsConfig::builder().root_certs(RootCerts::new_with_certs(&certificates)).build())
}

/// Runs `work` on [`STREAMS`] threads (fewer for few keys), each taking the next `batch` of
/// `keys` until none are left, with a value buffer of its own.
fn in_batches(keys: &[Key], batch: usize, work: impl Fn(&[Key], &mut Vec<u8>) + Sync) {
    let next = std::sync::atomic::AtomicUsize::new(0);
    std::thread::scope(|s| {
        for _ in 0..STREAMS.min(keys.len().div_ceil(batch)) {
            s.spawn(|| {
                let mut value = Vec::new();
                loop {
                    let at = next.fetch_add(batch, Ordering::Relaxed).min(keys.len());
                    let chunk = &keys[at..(at + batch).min(keys.len())];
                    if chunk.is_empty() {
                        break;
                    }
                    work(chunk, &mut value);
                }
            });
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn redact_drops_credentials_query_and_fragment() {
        assert_eq!(redact("redis://:s3cret@127.0.0.1:6379/2"), "redis://127.0.0.1:6379/2");
        assert_eq!(redact("redis://user:s3cret@cache:6379"), "redis://cache:6379");
        assert_eq!(redact("https://ci:pa@ss@cache.example/kiln?sig=abc#x"), "https://cache.example/kiln");
        assert_eq!(redact("http://host:8080/prefix/"), "http://host:8080/prefix/");
        assert_eq!(redact("not a url with s3cret"), "<remote cache URL>");
    }

    #[test]
    fn mode_parses_its_two_names() {
        assert_eq!(Mode::parse("read"), Ok(Mode::Read));
        assert_eq!(Mode::parse("read-write"), Ok(Mode::ReadWrite));
        assert!(Mode::parse("write").unwrap_err().contains("read or read-write"));
    }

    fn options(url: &str, token: Option<&str>) -> Options {
        Options {
            url: url.into(),
            mode: Mode::ReadWrite,
            token: token.map(String::from),
            timeout: Duration::from_millis(200),
            key: None,
        }
    }

    #[test]
    fn bad_urls_are_errors_that_hide_credentials() {
        let e = Remote::open(&options("ftp://user:s3cret@host/x", None)).unwrap_err().to_string();
        assert!(e.contains("ftp://host/x") && !e.contains("s3cret"), "{e}");
        let e = Remote::open(&options("http://user:s3cret@", None)).unwrap_err().to_string();
        assert!(e.contains("no host") && !e.contains("s3cret"), "{e}");
        let e = Remote::open(&options("redis://:s3cret@host:notaport", None)).unwrap_err().to_string();
        assert!(!e.contains("s3cret"), "{e}");
    }

    #[test]
    fn http_credentials_come_from_the_url_or_the_token() {
        let bearer = HttpStore::new(&options("http://h/p/", Some("t0ken"))).unwrap();
        assert_eq!(bearer.0.authorization.as_deref(), Some("Bearer t0ken"));
        assert_eq!(bearer.0.prefix, "http://h/p");
        let basic = HttpStore::new(&options("http://h/p", Some("ci:pw"))).unwrap();
        assert_eq!(basic.0.authorization.as_deref(), Some("Basic Y2k6cHc="));
        let url = HttpStore::new(&options("http://ci:pw@h:81/p", Some("ignored"))).unwrap();
        assert_eq!((url.0.authorization.as_deref(), url.0.prefix.as_str()), (Some("Basic Y2k6cHc="), "http://h:81/p"));
        assert_eq!(url.1.as_deref(), Some("pw"));
    }

    #[test]
    fn a_server_that_is_down_is_one_warning_without_secrets() {
        // A port that was free a moment ago: connection refused.
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        for url in [format!("redis://:s3cret@127.0.0.1:{port}"), format!("http://u:s3cret@127.0.0.1:{port}/kiln")] {
            let remote = Remote::open(&options(&url, None)).unwrap();
            let key = Key([7; 32]);
            assert_eq!(remote.get(&key), None);
            assert_eq!(remote.get(&key), None);
            remote.put(&key, b"value");
            let warning = remote.take_warning().expect("one warning");
            assert!(warning.contains(&format!("127.0.0.1:{port}")) && !warning.contains("s3cret"), "{warning}");
            assert_eq!(remote.take_warning(), None, "only one");
            assert_eq!(remote.stats(), Stats { hits: 0, writes: 0, errors: 1 });
        }
    }

    /// A server on a free loopback port that answers each `(awaited, reply)` in turn: reads
    /// until what it got holds `awaited`, then writes `reply`; then closes.
    fn scripted_server(script: Vec<(&'static [u8], &'static [u8])>) -> u16 {
        use std::io::{Read, Write};
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let port = listener.local_addr().unwrap().port();
        std::thread::spawn(move || {
            let (mut socket, _) = listener.accept().unwrap();
            let mut got = Vec::new();
            for (awaited, reply) in script {
                while !got.windows(awaited.len()).any(|w| w == awaited) {
                    let mut buffer = [0; 4096];
                    match socket.read(&mut buffer) {
                        Ok(0) | Err(_) => return,
                        Ok(n) => got.extend_from_slice(&buffer[..n]),
                    }
                }
                got.clear();
                let _ = socket.write_all(reply);
            }
        });
        port
    }

    fn raw_target(port: u16, password: Option<&str>, db: i64) -> RawTarget {
        RawTarget { address: ("127.0.0.1".into(), port), username: None, password: password.map(String::from), db }
    }

    fn raw_mget(target: &RawTarget, keys: &[Key]) -> Result<Vec<Option<Vec<u8>>>, Fault> {
        let mut c = RawRedis::connect(target, Duration::from_secs(2))?;
        let mut values = Vec::new();
        c.mget(keys, &mut Vec::new(), 1 << 20, &mut |_, v| values.push(v.map(<[u8]>::to_vec)))?;
        Ok(values)
    }

    #[test]
    fn raw_mget_logs_in_selects_and_reads_values_and_misses() {
        let keys = [Key([1; 32]), Key([2; 32]), Key([3; 32])];
        let port = scripted_server(vec![
            (b"$4\r\nAUTH\r\n$2\r\npw\r\n", b"+OK\r\n"),
            (b"$6\r\nSELECT\r\n$1\r\n2\r\n", b"+OK\r\n"),
            (b"0303\r\n", b"*3\r\n$3\r\nab\n\r\n$-1\r\n$0\r\n\r\n"),
        ]);
        let values = raw_mget(&raw_target(port, Some("pw"), 2), &keys).unwrap();
        assert_eq!(values, vec![Some(b"ab\n".to_vec()), None, Some(Vec::new())]);
    }

    #[test]
    fn raw_mget_faults_on_truncated_or_unexpected_replies() {
        let keys = [Key([1; 32]), Key([2; 32])];
        for (reply, why) in [
            (&b"*2\r\n$5\r\nab"[..], "truncated value"),
            (b"*2\r\n$2\r\nabcd\r\n$-1\r\n", "CRLF"),
            (b"*1\r\n$-1\r\n", "answered 1 values"),
            (b"-ERR wrong\r\n", "ERR wrong"),
            (b":1\r\n", "reply type"),
        ] {
            let port = scripted_server(vec![(b"0202\r\n", reply)]);
            let fault = raw_mget(&raw_target(port, None, 0), &keys).unwrap_err();
            assert!(!fault.timed_out, "{why}: {}", fault.message);
            assert!(fault.message.contains(why), "{why}: {}", fault.message);
        }
        let port = scripted_server(vec![(b"AUTH", b"-WRONGPASS invalid password\r\n")]);
        let fault = raw_mget(&raw_target(port, Some("s3cret"), 0), &keys).unwrap_err();
        assert!(fault.message.contains("WRONGPASS") && !fault.message.contains("s3cret"), "{}", fault.message);
    }

    #[test]
    fn a_streamed_value_cut_short_is_one_warning_then_misses() {
        let port = scripted_server(vec![(b"\r\n\r\n", b"HTTP/1.1 200 OK\r\nContent-Length: 100\r\n\r\nKILN")]);
        let remote = Remote::open(&options(&format!("http://u:s3cret@127.0.0.1:{port}/kiln"), None)).unwrap();
        assert!(remote.streams());
        let got = Mutex::new(Vec::new());
        let each = |i: usize, body: Option<&mut dyn std::io::Read>| {
            let read = body.map(|b| {
                let mut v = Vec::new();
                let _ = b.read_to_end(&mut v);
                v
            });
            got.lock().unwrap().push((i, read));
        };
        remote.get_streamed(&[Key([1; 32])], each);
        // Its 4 bytes (then the value ends early), one warning; the store is off after it.
        assert_eq!(got.lock().unwrap().drain(..).collect::<Vec<_>>(), vec![(0, Some(b"KILN".to_vec()))]);
        let warning = remote.take_warning().expect("one warning");
        assert!(warning.contains("truncated") && !warning.contains("s3cret"), "{warning}");
        remote.get_streamed(&[Key([2; 32])], each);
        assert_eq!(got.into_inner().unwrap(), vec![(0, None)]);
        assert_eq!((remote.stats().errors, remote.take_warning()), (1, None));
    }

    /// A server on a free loopback port that answers every connection (on a thread each)
    /// with `reply` once the request's head is in, one byte every `drip` (all at once when
    /// zero); it stops after `stop`.
    fn hostile_server(reply: Vec<u8>, drip: Duration, stop: Duration) -> u16 {
        use std::io::{Read, Write};
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let port = listener.local_addr().unwrap().port();
        let end = std::time::Instant::now() + stop;
        std::thread::spawn(move || {
            for socket in listener.incoming().flatten() {
                let reply = reply.clone();
                std::thread::spawn(move || {
                    let mut socket = socket;
                    let mut got = Vec::new();
                    let mut buffer = [0; 4096];
                    // An HTTP request's head, or a redis command of those a store sends.
                    let asked =
                        |w: &[u8]| [&b"\r\n\r\n"[..], b"GET ", b"MGET", b"\nSET", b"ISTS", b"AUTH"].contains(&w);
                    while !got.windows(4).any(asked) {
                        match socket.read(&mut buffer) {
                            Ok(0) | Err(_) => return,
                            Ok(n) => got.extend_from_slice(&buffer[..n]),
                        }
                    }
                    if drip.is_zero() {
                        let _ = socket.write_all(&reply);
                        let _ = socket.read(&mut buffer);
                        return;
                    }
                    for byte in reply.iter().cycle() {
                        if std::time::Instant::now() > end || socket.write_all(&[*byte]).is_err() {
                            return;
                        }
                        std::thread::sleep(drip);
                    }
                });
                if std::time::Instant::now() > end {
                    return;
                }
            }
        });
        port
    }

    fn fetch_all(remote: &Remote, keys: &[Key]) -> Vec<Option<Vec<u8>>> {
        let got = Mutex::new(Vec::new());
        remote.get_each(keys, |_, v| got.lock().unwrap().push(v.map(<[u8]>::to_vec)));
        got.into_inner().unwrap()
    }

    fn many_keys(n: usize) -> Vec<Key> {
        (0..n).map(|i| Key([i as u8; 32])).collect()
    }

    /// Case 1 of issue 28: a server that drips one byte a little faster than the timeout
    /// (each read is in time) is cut off by the request's deadline: one warning naming the
    /// timeout, the server and the wait; every key a miss.
    #[test]
    fn a_server_that_drips_is_cut_off_by_the_request_deadline() {
        let timeout = Duration::from_millis(200);
        for reply in [&b"HTTP/1.1 200 OK\r\nContent-Length: 100000\r\n\r\n"[..], b"*64\r\n$100000\r\n"] {
            let port = hostile_server(reply.to_vec(), timeout * 3 / 4, Duration::from_secs(20));
            let url = if reply.starts_with(b"HTTP") {
                format!("http://127.0.0.1:{port}/kiln")
            } else {
                format!("redis://127.0.0.1:{port}")
            };
            let mut o = options(&url, None);
            o.timeout = timeout;
            let remote = Remote::open(&o).unwrap();
            let start = std::time::Instant::now();
            let got = fetch_all(&remote, &many_keys(300));
            let took = start.elapsed();
            assert!(got.iter().all(Option::is_none));
            assert!(took < timeout * 12, "{url}: {took:?}");
            let warning = remote.take_warning().expect("one warning");
            assert!(
                warning.contains("timeout of 200 ms") && warning.contains(&format!("127.0.0.1:{port}")),
                "{warning}"
            );
            assert!(!warning.contains("os error"), "{warning}");
            assert!(remote.take_warning().is_none());
        }
    }

    /// Case 1 for the redis client's other requests: a server that drips its answer to
    /// `SET`, to `EXISTS` or to `AUTH` (a connection's setup) a byte a little faster than
    /// the timeout is cut off by the request's deadline: one warning naming the server, what
    /// timed out and how long it waited.
    #[test]
    fn redis_requests_that_drip_are_cut_off_by_their_deadline() {
        let timeout = Duration::from_millis(200);
        let put = |r: &Remote| r.put(&Key([1; 32]), b"KILNCER\x02 a value");
        let contains = |r: &Remote| assert_eq!(r.contains(&Key([1; 32])), None);
        let get = |r: &Remote| assert_eq!(r.get(&Key([1; 32])), None);
        let cases: [(&str, &str, &dyn Fn(&Remote)); 3] =
            [("SET", "", &put), ("EXISTS", "", &contains), ("connecting", ":pw@", &get)];
        for (what, login, request) in cases {
            // An endless line: `+O+O+O...`, never its CRLF.
            let port = hostile_server(b"+O".to_vec(), timeout * 3 / 4, Duration::from_secs(20));
            let mut o = options(&format!("redis://{login}127.0.0.1:{port}"), None);
            o.timeout = timeout;
            let remote = Remote::open(&o).unwrap();
            let start = std::time::Instant::now();
            request(&remote);
            let took = start.elapsed();
            // Loose upper bounds: a loaded machine delays the client, while a request the
            // deadline failed to cut would wait out the server's 20 s.
            assert!(took < timeout * 16, "{what}: {took:?}");
            let warning = remote.take_warning().expect("one warning");
            let waited: u128 = warning
                .split(&format!("{what}: timed out after "))
                .nth(1)
                .and_then(|rest| rest.split(" ms").next())
                .and_then(|n| n.parse().ok())
                .unwrap_or_else(|| panic!("{what}: {warning}"));
            assert!((700..3000).contains(&waited), "{what}: {warning}");
            assert!(
                warning.contains("timeout of 200 ms") && warning.contains(&format!("127.0.0.1:{port}")),
                "{warning}"
            );
            assert!(!warning.contains("os error") && !warning.contains("pw"), "{warning}");
            assert_eq!((remote.take_warning(), remote.stats().errors), (None, 1));
            assert!(!remote.writes(), "off");
        }
    }

    /// TLS and unix-socket redis URLs are refused when the store opens (never a request
    /// without a deadline), saying what is supported.
    #[test]
    fn redis_urls_other_than_plain_tcp_are_refused() {
        for url in ["rediss://127.0.0.1:6380", "redis+unix:///tmp/redis.sock", "unix:///tmp/redis.sock"] {
            let e = Remote::open(&options(url, None)).unwrap_err().to_string();
            assert!(e.contains("only redis://host:port[/db] is supported"), "{url}: {e}");
        }
    }

    /// Case 2: a value far larger than any this build stores is refused from its announced
    /// length, before anything is allocated or read: the store is off after it.
    #[test]
    fn a_huge_value_is_refused_before_it_is_read() {
        for reply in [
            &b"HTTP/1.1 200 OK\r\nContent-Length: 1073741824\r\n\r\nKILN"[..],
            b"*64\r\n$1073741824\r\nKILN",
            b"HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\n40000000\r\nKILN",
        ] {
            let port = hostile_server(reply.to_vec(), Duration::ZERO, Duration::from_secs(20));
            let url = if reply.starts_with(b"HTTP") {
                format!("http://127.0.0.1:{port}/kiln")
            } else {
                format!("redis://127.0.0.1:{port}")
            };
            let remote = Remote::open(&options(&url, None)).unwrap();
            remote.limit_values(8 << 20);
            let start = std::time::Instant::now();
            assert!(fetch_all(&remote, &many_keys(64)).iter().all(Option::is_none));
            assert_eq!(remote.get(&Key([1; 32])), None);
            assert!(start.elapsed() < Duration::from_secs(2), "{:?}", start.elapsed());
            let warning = remote.take_warning().expect("one warning");
            assert!(warning.contains("larger than any this build stores"), "{warning}");
            assert!(remote.take_warning().is_none());
        }
    }

    /// Case 8: a server that answers every request with a body that is not a Kiln value is
    /// switched off after the first: one warning, no more requests.
    #[test]
    fn a_server_that_answers_anything_but_kiln_values_is_switched_off() {
        let port = hostile_server(
            b"HTTP/1.1 200 OK\r\nContent-Length: 5\r\n\r\nhello".repeat(64),
            Duration::ZERO,
            Duration::from_secs(20),
        );
        let remote = Remote::open(&options(&format!("http://127.0.0.1:{port}/kiln"), None)).unwrap();
        assert!(fetch_all(&remote, &many_keys(10)).iter().all(Option::is_none));
        assert_eq!(remote.get(&Key([1; 32])), None);
        let warning = remote.take_warning().expect("one warning");
        assert!(warning.contains("not a Kiln value") && warning.contains("refused"), "{warning}");
        assert!(remote.take_warning().is_none());
        assert!(!remote.writes(), "off");
        assert_eq!(remote.stats().errors, 1);
    }

    #[test]
    fn signed_values_verify_and_anything_else_is_refused() {
        let signing = SigningKey::parse(&"0f".repeat(32)).unwrap();
        assert!(SigningKey::parse("abc").is_err() && SigningKey::parse(&"zz".repeat(32)).is_err());
        assert_eq!(format!("{signing:?}"), "SigningKey(***)");
        let mut o = options("http://127.0.0.1:9/kiln", None);
        o.key = Some(signing.clone());
        let key = Key([5; 32]);
        let value = b"KILNCER\x02 a value".to_vec();
        let signed = [&SIGNED_MAGIC[..], &mac(&signing, &key, &value), &value].concat();
        let remote = Remote::open(&o).unwrap();
        assert_eq!(remote.accept(&key, &signed), Some(&value[..]));
        assert!(remote.take_warning().is_none());
        // Under another key; with a byte changed; unsigned: refused, the first with a warning.
        for (k, v) in
            [(Key([6; 32]), signed.clone()), (key, [&signed[..50], b"X", &signed[51..]].concat()), (key, value.clone())]
        {
            let remote = Remote::open(&o).unwrap();
            assert_eq!(remote.accept(&k, &v), None);
            let warning = remote.take_warning().unwrap();
            assert!(warning.contains(&k.to_string()) && warning.contains("MAC"), "{warning}");
        }
        // A reader without the key takes a signed value as it is.
        let remote = Remote::open(&options("http://127.0.0.1:9/kiln", None)).unwrap();
        assert_eq!(remote.accept(&key, &signed), Some(&value[..]));
    }

    #[test]
    fn debug_output_hides_the_token() {
        let text = format!("{:?}", options("redis://:pw@h:1", Some("t0ken")));
        assert!(!text.contains("t0ken") && !text.contains("pw"), "{text}");
    }
}
