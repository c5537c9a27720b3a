//! The shared remote cache, against real servers started here on free loopback ports:
//! `redis-server` and `nginx` with WebDAV (`dav_methods PUT`). Each scenario runs on both;
//! https runs against nginx with TLS and a certificate authority made with `openssl`.
//!
//! Builds are of `tests/in/lit.toml` (24 distinct keys), each "machine" with its own local
//! cache folder. Servers are stopped by a drop guard. A missing server binary fails the
//! test, naming its Debian package.

#[path = "it/build_support/mod.rs"]
mod build_support;
#[path = "../../compiler/tests/support/scale_set.rs"]
mod scale_set;

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, RwLock};
use std::time::{Duration, Instant};

use build_support::*;
use kiln::build::{self, RemoteCache, RemoteMode, Report};

const DISTINCT: usize = 24;
const TOKEN: &str = "s3cret-t0ken";

/// Tests that set `KILN_REMOTE_CACHE_*` variables hold this for writing; every other
/// build holds it for reading (the variables are read by every build of the process).
static ENV: RwLock<()> = RwLock::new(());

/// The environment to oneself: every `KILN_REMOTE_CACHE_*` variable set through it is
/// removed on drop, a failing test included.
struct Env(#[allow(dead_code)] std::sync::RwLockWriteGuard<'static, ()>);

const VARIABLES: [&str; 7] = [
    "KILN_RECORD_PIECE",
    "KILN_REMOTE_CACHE",
    "KILN_REMOTE_CACHE_KEY",
    "KILN_REMOTE_CACHE_MODE",
    "KILN_REMOTE_CACHE_TOKEN",
    "KILN_REMOTE_CACHE_TIMEOUT_MS",
    "KILN_REMOTE_CACHE_CA",
];

impl Env {
    fn lock() -> Env {
        Env(ENV.write().unwrap_or_else(|e| e.into_inner()))
    }
    fn set(&self, name: &str, value: &str) {
        assert!(VARIABLES.contains(&name));
        std::env::set_var(name, value);
    }
    fn remove(&self, name: &str) {
        std::env::remove_var(name);
    }
}

impl Drop for Env {
    fn drop(&mut self) {
        for v in VARIABLES {
            std::env::remove_var(v);
        }
    }
}

/// nginx is in /usr/sbin, which a user's PATH may lack.
fn nginx() -> &'static str {
    if Path::new("/usr/sbin/nginx").exists() {
        "/usr/sbin/nginx"
    } else {
        "nginx"
    }
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

fn wait_for_port(port: u16, server: &mut Child, log: &Path) {
    let start = Instant::now();
    while TcpStream::connect(("127.0.0.1", port)).is_err() {
        if let Ok(Some(status)) = server.try_wait() {
            panic!("the server exited ({status}): {}", std::fs::read_to_string(log).unwrap_or_default());
        }
        assert!(start.elapsed() < Duration::from_secs(20), "the server did not listen on {port}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Kind {
    Redis,
    Http,
    /// nginx over TLS, with a certificate authority made by the test (`ca.pem` in the
    /// server's folder).
    Https,
}

/// A server process, killed and reaped on drop.
struct Server {
    kind: Kind,
    child: Child,
    port: u16,
    /// The server's folder (nginx's prefix and data, redis's working folder).
    dir: tempfile::TempDir,
    password: Option<String>,
}

impl Drop for Server {
    fn drop(&mut self) {
        stop(&mut self.child);
    }
}

/// Stops a server: SIGTERM, so that nginx's master stops its workers too (a SIGKILL would
/// leave them running, holding the port); SIGKILL after 5 s.
fn stop(child: &mut Child) {
    // SAFETY: kill takes no pointer; the pid is our child's, not yet reaped (no reuse).
    unsafe { libc::kill(child.id() as libc::pid_t, libc::SIGTERM) };
    let start = Instant::now();
    while matches!(child.try_wait(), Ok(None)) && start.elapsed() < Duration::from_secs(5) {
        std::thread::sleep(Duration::from_millis(10));
    }
    let _ = child.kill();
    let _ = child.wait();
}

impl Server {
    fn start(kind: Kind) -> Server {
        Self::start_with(kind, None)
    }

    /// A server that requires `password` (redis `requirepass`; nginx: `Bearer <password>`
    /// or basic auth `ci:<password>`).
    fn start_with(kind: Kind, password: Option<&str>) -> Server {
        let dir = tempfile::tempdir().unwrap();
        let port = free_port();
        let log = dir.path().join("server.log");
        let mut child = match kind {
            Kind::Redis => {
                require_server("redis-server", &["--version"], "redis-server");
                let mut c = Command::new("redis-server");
                c.args(["--port", &port.to_string(), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no"])
                    .arg("--dir")
                    .arg(dir.path())
                    .arg("--logfile")
                    .arg(&log);
                if let Some(p) = password {
                    c.args(["--requirepass", p]);
                }
                c.stdout(Stdio::null()).stderr(Stdio::null()).spawn().unwrap()
            }
            Kind::Http | Kind::Https => {
                require_server(nginx(), &["-v"], "nginx-light");
                let prefix = dir.path();
                let tls = if kind == Kind::Https {
                    certificates(prefix);
                    format!(
                        "ssl; ssl_certificate {p}/server.pem; ssl_certificate_key {p}/server.key;",
                        p = prefix.display()
                    )
                } else {
                    ";".into()
                };
                std::fs::create_dir_all(prefix.join("data/kiln")).unwrap();
                std::fs::create_dir_all(prefix.join("logs")).unwrap();
                let auth = match password {
                    None => String::new(),
                    Some(p) => {
                        use base64::Engine;
                        let basic = base64::engine::general_purpose::STANDARD.encode(format!("ci:{p}"));
                        format!(
                            "map $http_authorization $kiln_ok {{ default 0; \"Bearer {p}\" 1; \"Basic {basic}\" 1; }}"
                        )
                    }
                };
                let check = if password.is_some() { "if ($kiln_ok = 0) { return 401; }" } else { "" };
                // As root, nginx's workers would run as nobody, unable to write our folders.
                // SAFETY: geteuid cannot fail and takes no argument.
                let user = if unsafe { libc::geteuid() } == 0 { "user root;" } else { "" };
                let config = format!(
                    "{user}
daemon off;
worker_processes 1;
pid {prefix}/nginx.pid;
error_log {log} warn;
events {{ worker_connections 128; }}
http {{
    access_log off;
    client_body_temp_path {prefix}/body;
    client_max_body_size 0;
    {auth}
    server {{
        listen 127.0.0.1:{port} {tls}
        root {prefix}/data;
        location /kiln/ {{
            {check}
            dav_methods PUT DELETE;
            create_full_put_path on;
            dav_access user:rw group:r all:r;
        }}
    }}
}}
",
                    prefix = prefix.display(),
                    log = log.display(),
                );
                std::fs::write(prefix.join("nginx.conf"), config).unwrap();
                Command::new(nginx())
                    .arg("-p")
                    .arg(prefix)
                    .arg("-c")
                    .arg(prefix.join("nginx.conf"))
                    .arg("-e")
                    .arg(&log)
                    .stdout(Stdio::null())
                    .stderr(Stdio::null())
                    .spawn()
                    .unwrap()
            }
        };
        wait_for_port(port, &mut child, &log);
        Server { kind, child, port, dir, password: password.map(String::from) }
    }

    fn url(&self) -> String {
        self.url_at(self.port)
    }

    /// This server's URL with another port (a proxy in front of it).
    fn url_at(&self, port: u16) -> String {
        match self.kind {
            Kind::Redis => format!("redis://127.0.0.1:{port}/0"),
            Kind::Http => format!("http://127.0.0.1:{port}/kiln"),
            Kind::Https => format!("https://127.0.0.1:{port}/kiln"),
        }
    }

    fn redis(&self) -> redis::Connection {
        let mut url = format!("redis://127.0.0.1:{}/0", self.port);
        if let Some(p) = &self.password {
            url = format!("redis://:{p}@127.0.0.1:{}/0", self.port);
        }
        redis::Client::open(url).unwrap().get_connection().unwrap()
    }

    /// Every key the server holds, sorted.
    fn keys(&self) -> Vec<String> {
        let mut keys: Vec<String> = match self.kind {
            Kind::Redis => {
                let keys: Vec<String> = redis::cmd("KEYS").arg("kiln:*").query(&mut self.redis()).unwrap();
                keys.into_iter().map(|k| k.trim_start_matches("kiln:").to_string()).collect()
            }
            Kind::Http | Kind::Https => std::fs::read_dir(self.dir.path().join("data/kiln"))
                .unwrap()
                .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .collect(),
        };
        keys.sort();
        keys
    }

    /// The keys holding compiled entries (the others hold preprocessing records).
    fn entries(&self) -> Vec<String> {
        self.keys().into_iter().filter(|k| self.get(k).starts_with(b"KILNCE")).collect()
    }

    fn get(&self, key: &str) -> Vec<u8> {
        match self.kind {
            Kind::Redis => redis::cmd("GET").arg(format!("kiln:{key}")).query(&mut self.redis()).unwrap(),
            Kind::Http | Kind::Https => std::fs::read(self.dir.path().join("data/kiln").join(key)).unwrap(),
        }
    }

    /// Overwrites a value through the server's own protocol (SET, HTTP PUT).
    fn set(&self, key: &str, value: &[u8]) {
        match self.kind {
            Kind::Redis => {
                let () = redis::cmd("SET").arg(format!("kiln:{key}")).arg(value).query(&mut self.redis()).unwrap();
            }
            Kind::Http | Kind::Https => {
                let status = ureq::put(format!("{}/{key}", self.url())).send(value).unwrap().status();
                assert!(status.is_success(), "PUT answered {status}");
            }
        }
    }

    fn is_running(&mut self) -> bool {
        self.child.try_wait().unwrap().is_none()
    }
}

/// In `dir`: a certificate authority (`ca.pem`) and the certificate it signs for
/// 127.0.0.1 (`server.pem`, `server.key`), P-256 keys, made with `openssl`.
fn certificates(dir: &Path) {
    require_server("openssl", &["version"], "openssl");
    let openssl = |args: &[&str]| {
        let o = Command::new("openssl").args(args).current_dir(dir).output().unwrap();
        assert!(o.status.success(), "openssl {args:?}: {}", String::from_utf8_lossy(&o.stderr));
    };
    let ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"];
    openssl(
        &[
            &["req", "-x509"],
            &ec[..],
            &["-keyout", "ca.key", "-out", "ca.pem", "-days", "2", "-subj", "/CN=kiln test CA"],
        ]
        .concat(),
    );
    openssl(&[&["req"], &ec[..], &["-keyout", "server.key", "-out", "server.csr", "-subj", "/CN=127.0.0.1"]].concat());
    std::fs::write(
        dir.join("server.ext"),
        "basicConstraints=CA:FALSE\nsubjectAltName=IP:127.0.0.1\nextendedKeyUsage=serverAuth\n",
    )
    .unwrap();
    openssl(&[
        "x509",
        "-req",
        "-in",
        "server.csr",
        "-CA",
        "ca.pem",
        "-CAkey",
        "ca.key",
        "-CAcreateserial",
        "-out",
        "server.pem",
        "-days",
        "2",
        "-extfile",
        "server.ext",
    ]);
}

/// Fails (never skips) when a server binary is missing, naming the Debian package.
fn require_server(binary: &str, version_arg: &[&str], package: &str) {
    let ok = Command::new(binary).args(version_arg).output().map(|o| o.status.success()).unwrap_or(false);
    assert!(
        ok,
        "`{binary}` is required by this test: install the Debian package `{package}` (apt-get install {package})"
    );
}

/// A "machine": its own copy of the inputs and its own local cache.
struct Machine {
    dir: tempfile::TempDir,
    config: PathBuf,
}

impl Machine {
    fn new() -> Machine {
        let dir = fixture();
        let config = dir.path().join("lit.toml");
        Machine { dir, config }
    }

    /// A machine building a generated set of 80 permutations (76 distinct keys: enough for
    /// a bundle).
    fn scale() -> Machine {
        let dir = tempfile::tempdir().unwrap();
        let (config, _) = scale_set::write(&dir.path().join("set"), 5 * scale_set::PER_MATERIAL);
        Machine { dir, config }
    }

    /// A machine building a generated set of about `permutations` permutations.
    fn scale_of(permutations: usize) -> Machine {
        let dir = tempfile::tempdir().unwrap();
        let (config, _) = scale_set::write(&dir.path().join("set"), permutations);
        Machine { dir, config }
    }

    fn archive(&self) -> PathBuf {
        self.dir.path().join("shaders.kpak")
    }

    fn options(&self, remote: RemoteCache, mode: Option<RemoteMode>) -> build::Options {
        let mut o = options(&self.config, &self.archive(), Some(&self.dir.path().join("cache")));
        o.remote_cache = remote;
        o.remote_cache_mode = mode;
        o
    }

    fn build(&self, url: &str) -> Report {
        self.build_with(RemoteCache::Url(url.into()), None)
    }

    fn build_with(&self, remote: RemoteCache, mode: Option<RemoteMode>) -> Report {
        let _env = ENV.read().unwrap_or_else(|e| e.into_inner());
        build_ok(&self.options(remote, mode))
    }

    /// [`Machine::build_with`] for a test that holds [`Env`] already.
    fn build_ok_locked(&self, remote: RemoteCache) -> Report {
        build_ok(&self.options(remote, None))
    }

    fn bytes(&self) -> Vec<u8> {
        std::fs::read(self.archive()).unwrap()
    }
}

/// The archive of a build without any remote cache.
fn reference() -> Vec<u8> {
    let m = Machine::new();
    m.build_with(RemoteCache::Disabled, None);
    m.bytes()
}

fn remote_warnings(report: &Report) -> Vec<&String> {
    report.warnings.iter().filter(|w| w.contains("remote cache")).collect()
}

fn hits_from_a_second_machine(kind: Kind) {
    let server = Server::start(kind);
    let url = server.url();

    // A developer's machine in read mode finds nothing and stores nothing.
    let dev = Machine::new();
    let r = dev.build_with(RemoteCache::Url(url.clone()), Some(RemoteMode::Read));
    assert_eq!((r.stats.compiled, r.stats.remote_hits, r.stats.remote_writes), (DISTINCT, 0, 0));
    assert!(server.keys().is_empty(), "read mode wrote {:?}", server.keys());

    // CI compiles everything and fills the remote.
    let ci = Machine::new();
    let r = ci.build(&url);
    assert_eq!((r.stats.compiled, r.stats.remote_hits, r.stats.remote_writes), (DISTINCT, 0, DISTINCT as u64));
    assert_eq!(r.stats.remote_errors, 0);
    assert_eq!(server.entries().len(), DISTINCT);
    assert_eq!(server.keys().len(), DISTINCT + 2, "and one set of preprocessing records, and the archive");
    assert_eq!(server.keys().iter().filter(|k| server.get(k).starts_with(b"KILNAR")).count(), 1, "one archive");

    // Another machine (its checkout at another path), fresh local cache: preprocesses
    // nothing (the records hold paths relative to the configuration's folder), compiles
    // nothing (the entries and the archive come from the remote), same bytes.
    let other = Machine::new();
    assert_ne!(other.dir.path(), ci.dir.path());
    let r = other.build_with(RemoteCache::Url(url.clone()), Some(RemoteMode::Read));
    assert_eq!((r.stats.compiled, r.stats.cache_hits, r.stats.remote_hits), (0, DISTINCT, DISTINCT as u64));
    assert_eq!(r.stats.preprocessed, 0);
    assert!(remote_warnings(&r).is_empty(), "{:?}", r.warnings);
    assert_eq!(other.bytes(), ci.bytes());
    assert_eq!(other.bytes(), reference(), "the remote changes no byte of the archive");

    // The same at the same path (CI runners, the pods of one job).
    std::fs::remove_dir_all(ci.dir.path().join("cache")).unwrap();
    std::fs::remove_file(ci.archive()).unwrap();
    let r = ci.build(&url);
    assert_eq!((r.stats.compiled, r.stats.preprocessed, r.stats.remote_hits), (0, 0, DISTINCT as u64));
    assert_eq!(ci.bytes(), other.bytes());

    // The remote hits were filled into that machine's local cache: without the remote,
    // it still compiles nothing.
    std::fs::remove_file(other.archive()).unwrap();
    let r = other.build_with(RemoteCache::Disabled, None);
    assert_eq!((r.stats.compiled, r.stats.cache_hits, r.stats.remote_hits), (0, DISTINCT, 0));
    assert_eq!(other.bytes(), ci.bytes());
}

#[test]
fn redis_serves_a_second_machine() {
    hits_from_a_second_machine(Kind::Redis);
}

#[test]
fn http_serves_a_second_machine() {
    hits_from_a_second_machine(Kind::Http);
}

/// A fresh local cache whose checkout differs from the build that filled the remote (a
/// header edited): it fills the last build's keys from the remote while it matches its
/// permutations to that build's records, so some of what it fetched is of no use to it.
/// The keys whose tokens changed are compiled, the rest are remote hits, and the remote
/// hits count only the keys the build uses; same bytes as a build without the remote.
fn a_fresh_cache_of_edited_sources(kind: Kind) {
    const WITH_FOG: usize = 12;
    let server = Server::start(kind);
    let url = server.url();
    Machine::new().build(&url);
    let edit = |m: &Machine| {
        let fog = m.dir.path().join("include/fog.ush");
        let text = std::fs::read_to_string(&fog).unwrap();
        let edited = text.replace("FOG_DENSITY: f32 = 0.02", "FOG_DENSITY: f32 = 0.03");
        assert_ne!(edited, text);
        std::fs::write(&fog, edited).unwrap();
    };
    let alone = Machine::new();
    edit(&alone);
    let r = alone.build_with(RemoteCache::Disabled, None);
    assert_eq!(r.stats.compiled, DISTINCT);

    let m = Machine::new();
    edit(&m);
    let r = m.build_with(RemoteCache::Url(url.clone()), Some(RemoteMode::Read));
    assert_eq!(
        (r.stats.compiled, r.stats.cache_hits, r.stats.remote_hits),
        (WITH_FOG, DISTINCT - WITH_FOG, (DISTINCT - WITH_FOG) as u64),
        "{:?}",
        r.stats
    );
    assert!(remote_warnings(&r).is_empty(), "{:?}", r.warnings);
    assert_eq!(m.bytes(), alone.bytes());
}

#[test]
fn redis_fills_a_fresh_cache_of_edited_sources() {
    a_fresh_cache_of_edited_sources(Kind::Redis);
}

#[test]
fn http_fills_a_fresh_cache_of_edited_sources() {
    a_fresh_cache_of_edited_sources(Kind::Http);
}

/// A TCP proxy in front of `server` that, when a client sends `trigger` (the first
/// remote write), kills the server and drops every connection: a server dying mid-build,
/// at a deterministic point.
fn killing_proxy(server: Arc<Mutex<Server>>, trigger: &'static [u8]) -> (u16, Arc<AtomicBool>) {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = listener.local_addr().unwrap().port();
    let upstream = server.lock().unwrap().port;
    let killed = Arc::new(AtomicBool::new(false));
    let flag = killed.clone();
    std::thread::spawn(move || {
        for client in listener.incoming() {
            let Ok(client) = client else { continue };
            if flag.load(Ordering::SeqCst) {
                continue; // dropped: the server is gone
            }
            let Ok(up) = TcpStream::connect(("127.0.0.1", upstream)) else { continue };
            let (server, flag) = (server.clone(), flag.clone());
            let (mut c_read, mut u_write) = (client.try_clone().unwrap(), up.try_clone().unwrap());
            let (mut u_read, mut c_write) = (up, client);
            std::thread::spawn(move || {
                let mut buf = vec![0u8; 64 << 10];
                let mut tail: Vec<u8> = Vec::new();
                loop {
                    let n = match c_read.read(&mut buf) {
                        Ok(0) | Err(_) => break,
                        Ok(n) => n,
                    };
                    tail.extend_from_slice(&buf[..n]);
                    if tail.windows(trigger.len()).any(|w| w == trigger) || flag.load(Ordering::SeqCst) {
                        if !flag.swap(true, Ordering::SeqCst) {
                            stop(&mut server.lock().unwrap().child);
                        }
                        break;
                    }
                    let keep = tail.len().saturating_sub(trigger.len());
                    tail.drain(..keep);
                    if u_write.write_all(&buf[..n]).is_err() {
                        break;
                    }
                }
                let _ = c_read.shutdown(std::net::Shutdown::Both);
                let _ = u_write.shutdown(std::net::Shutdown::Both);
            });
            std::thread::spawn(move || {
                let _ = std::io::copy(&mut u_read, &mut c_write);
                let _ = c_write.shutdown(std::net::Shutdown::Both);
            });
        }
    });
    (port, killed)
}

fn server_killed_mid_build(kind: Kind) {
    let server = Arc::new(Mutex::new(Server::start(kind)));
    let trigger: &'static [u8] = match kind {
        Kind::Redis => b"\r\nSET\r\n",
        Kind::Http | Kind::Https => b"PUT /kiln/",
    };
    let (port, killed) = killing_proxy(server.clone(), trigger);
    let url = server.lock().unwrap().url_at(port);
    let m = Machine::new();
    let r = m.build(&url);
    assert!(killed.load(Ordering::SeqCst), "the build wrote to the remote");
    assert!(!server.lock().unwrap().is_running());
    assert_eq!(r.stats.compiled, DISTINCT);
    assert!(r.stats.remote_errors >= 1);
    let warnings = remote_warnings(&r);
    assert_eq!(warnings.len(), 1, "one warning: {:?}", r.warnings);
    assert!(warnings[0].contains(&url) && warnings[0].contains("local cache only"), "{}", warnings[0]);
    assert_eq!(m.bytes(), reference());
}

#[test]
fn redis_killed_mid_build() {
    server_killed_mid_build(Kind::Redis);
}

#[test]
fn http_killed_mid_build() {
    server_killed_mid_build(Kind::Http);
}

/// A warm remote whose server dies while a fresh local cache copies its entries (at the
/// first `MGET`, or the first pipelined `GET`s: only those write `Host:` capitalized,
/// ureq's single requests write `host:`): one warning, every key compiled here, the same
/// bytes.
fn killed_while_a_fresh_cache_fills(kind: Kind, trigger: &'static [u8]) {
    let server = Arc::new(Mutex::new(Server::start(kind)));
    let direct = server.lock().unwrap().url();
    Machine::new().build(&direct);
    let (port, killed) = killing_proxy(server.clone(), trigger);
    let url = server.lock().unwrap().url_at(port);
    let m = Machine::new();
    let r = m.build(&url);
    assert!(killed.load(Ordering::SeqCst), "the fill asked for the entries");
    assert_eq!((r.stats.compiled, r.stats.remote_hits), (DISTINCT, 0));
    let warnings = remote_warnings(&r);
    assert_eq!(warnings.len(), 1, "one warning: {:?}", r.warnings);
    assert!(warnings[0].contains(&url) && warnings[0].contains("local cache only"), "{}", warnings[0]);
    assert_eq!(m.bytes(), reference());
}

#[test]
fn redis_killed_while_a_fresh_cache_fills() {
    killed_while_a_fresh_cache_fills(Kind::Redis, b"\r\nMGET\r\n");
}

#[test]
fn http_killed_while_a_fresh_cache_fills() {
    killed_while_a_fresh_cache_fills(Kind::Http, b"\r\nHost: ");
}

/// A port that accepts connections and never answers: the timeout bounds the wait, one
/// warning, the build goes on.
#[test]
fn a_server_that_never_answers_times_out_once() {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = listener.local_addr().unwrap().port();
    let held = Arc::new(Mutex::new(Vec::new()));
    let keep = held.clone();
    std::thread::spawn(move || {
        for c in listener.incoming().flatten() {
            keep.lock().unwrap().push(c);
        }
    });
    let env = Env::lock();
    env.set("KILN_REMOTE_CACHE_TIMEOUT_MS", "300");
    for url in [format!("redis://127.0.0.1:{port}"), format!("http://127.0.0.1:{port}/kiln")] {
        let m = Machine::new();
        let r = build_ok(&m.options(RemoteCache::Url(url.clone()), None));
        assert_eq!(r.stats.compiled, DISTINCT);
        let warnings = remote_warnings(&r);
        assert_eq!(warnings.len(), 1, "{:?}", r.warnings);
        assert!(warnings[0].contains(&url), "{}", warnings[0]);
        // The store is off after the first timeout: only the two workers' first waits fail.
        assert!((1..=2).contains(&r.stats.remote_errors), "{:?}", r.stats);
    }
    drop(env);
    assert!(!held.lock().unwrap().is_empty(), "kiln connected");
}

/// A loopback server that answers every connection's requests with `reply`, each byte
/// after `drip` (at once when zero), until the test ends.
fn hostile_http(reply: &'static [u8], drip: Duration) -> u16 {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = listener.local_addr().unwrap().port();
    std::thread::spawn(move || {
        for mut c in listener.incoming().flatten() {
            std::thread::spawn(move || {
                let mut buffer = [0; 1 << 16];
                while let Ok(n) = c.read(&mut buffer) {
                    if n == 0 {
                        return;
                    }
                    let requests = buffer[..n].windows(4).filter(|w| w == b"\r\n\r\n").count().max(1);
                    for _ in 0..requests {
                        if drip.is_zero() {
                            if c.write_all(reply).is_err() {
                                return;
                            }
                            continue;
                        }
                        for b in reply {
                            std::thread::sleep(drip);
                            if c.write_all(&[*b]).is_err() {
                                return;
                            }
                        }
                    }
                }
            });
        }
    });
    port
}

/// Issue 28, cases 1 and 8 in a whole build: a server that answers every request with a
/// body that is not a Kiln value, and one that drips a byte a little faster than the
/// timeout: one warning each, the build finishes within a few timeouts, same bytes.
#[test]
fn hostile_servers_are_one_warning_and_change_no_byte() {
    let env = Env::lock();
    env.set("KILN_REMOTE_CACHE_TIMEOUT_MS", "300");
    let reference = {
        let m = Machine::new();
        build_ok(&m.options(RemoteCache::Disabled, None));
        m.bytes()
    };
    for (reply, drip, why) in [
        (&b"HTTP/1.1 200 OK\r\nContent-Length: 11\r\n\r\nhello world"[..], Duration::ZERO, "not a Kiln value"),
        (b"HTTP/1.1 200 OK\r\nContent-Length: 1000\r\n\r\nKILN", Duration::from_millis(250), "timeout of 300 ms"),
    ] {
        let port = hostile_http(reply, drip);
        let url = format!("http://127.0.0.1:{port}/kiln");
        let m = Machine::new();
        let start = Instant::now();
        let r = build_ok(&m.options(RemoteCache::Url(url.clone()), None));
        assert!(start.elapsed() < Duration::from_secs(15), "{why}: {:?}", start.elapsed());
        let warnings = remote_warnings(&r);
        assert_eq!(warnings.len(), 1, "{why}: {:?}", r.warnings);
        assert!(warnings[0].contains(why) && warnings[0].contains(&format!("127.0.0.1:{port}")), "{}", warnings[0]);
        assert_eq!(r.stats.compiled, DISTINCT);
        assert_eq!(m.bytes(), reference, "{why}");
    }
}

/// One RESP command's arguments from `c` (`None` once the client has gone).
fn resp_command(c: &mut std::io::BufReader<TcpStream>) -> Option<Vec<Vec<u8>>> {
    use std::io::BufRead;
    let mut line = String::new();
    let mut number = |c: &mut std::io::BufReader<TcpStream>, kind: char| -> Option<usize> {
        line.clear();
        c.read_line(&mut line).ok().filter(|n| *n > 0)?;
        line.trim_end().strip_prefix(kind)?.parse().ok()
    };
    let count = number(c, '*')?;
    let mut args = Vec::with_capacity(count);
    for _ in 0..count {
        let mut arg = vec![0; number(c, '$')? + 2];
        c.read_exact(&mut arg).ok()?;
        arg.truncate(arg.len() - 2);
        args.push(arg);
    }
    Some(args)
}

/// A loopback redis that holds nothing: every `MGET` and `GET` a miss at once, every other
/// command `+OK`, except `dripped` (`SET`, `AUTH`, ...), whose answer is an endless line
/// sent a byte every `drip`.
fn dripping_redis(dripped: &'static str, drip: Duration) -> u16 {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = listener.local_addr().unwrap().port();
    std::thread::spawn(move || {
        for c in listener.incoming().flatten() {
            std::thread::spawn(move || {
                let mut writer = c.try_clone().unwrap();
                let mut reader = std::io::BufReader::new(c);
                while let Some(args) = resp_command(&mut reader) {
                    let name = String::from_utf8_lossy(&args[0]).to_ascii_uppercase();
                    let reply = match name.as_str() {
                        _ if name == dripped => loop {
                            std::thread::sleep(drip);
                            if writer.write_all(b"+").is_err() {
                                return;
                            }
                        },
                        "MGET" => format!("*{}\r\n{}", args.len() - 1, "$-1\r\n".repeat(args.len() - 1)),
                        "GET" => "$-1\r\n".to_string(),
                        _ => "+OK\r\n".to_string(),
                    };
                    if writer.write_all(reply.as_bytes()).is_err() {
                        return;
                    }
                }
            });
        }
    });
    port
}

/// Issue 28, case 1 for the redis client's own requests in a whole build: a redis that
/// drips its answer to `SET` (each entry written), or to `AUTH` (each connection's setup),
/// a byte a little faster than the timeout: the build finishes within a few timeouts with
/// one warning naming the server, what timed out and how long it waited, and writes the
/// same bytes as a local build.
#[test]
fn a_redis_that_drips_on_set_or_auth_is_one_warning_and_changes_no_byte() {
    let env = Env::lock();
    env.set("KILN_REMOTE_CACHE_TIMEOUT_MS", "300");
    env.set("KILN_REMOTE_CACHE_TOKEN", TOKEN);
    let reference = {
        let m = Machine::new();
        build_ok(&m.options(RemoteCache::Disabled, None));
        m.bytes()
    };
    for (dripped, what) in
        [("SET", "writing to it failed (SET: timed out after"), ("AUTH", "connecting: timed out after")]
    {
        let port = dripping_redis(dripped, Duration::from_millis(250));
        let url = format!("redis://127.0.0.1:{port}");
        let m = Machine::new();
        let start = Instant::now();
        let r = build_ok(&m.options(RemoteCache::Url(url.clone()), None));
        assert!(start.elapsed() < Duration::from_secs(15), "{dripped}: {:?}", start.elapsed());
        let warnings = remote_warnings(&r);
        assert_eq!(warnings.len(), 1, "{dripped}: {:?}", r.warnings);
        let w = warnings[0];
        assert!(w.contains(what) && w.contains(&url) && w.contains("timeout of 300 ms"), "{dripped}: {w}");
        assert!(!w.contains(TOKEN), "{w}");
        assert_eq!(r.stats.compiled, DISTINCT);
        assert_eq!(m.bytes(), reference, "{dripped}");
    }
}

/// `MAC` of a 32-byte key given as hex: what a team sets as `KILN_REMOTE_CACHE_KEY`.
const SIGNING_KEY: &str = "4b494c4e2074657374206b6579202d206e6f7420666f72207265616c20757365";

/// Signed entries (issue 28): with `KILN_REMOTE_CACHE_KEY`, every value stored carries a
/// MAC; someone without the key who rewrites values on the server (an entry without its
/// MAC, one with a forged MAC, the archive) has them refused: one warning naming the key,
/// the entries compiled again, the archive byte-identical to a local build's.
fn signed_entries(kind: Kind) {
    let server = Server::start(kind);
    let url = server.url();
    let env = Env::lock();
    env.set("KILN_REMOTE_CACHE_KEY", SIGNING_KEY);
    let reference = {
        let m = Machine::new();
        build_ok(&m.options(RemoteCache::Disabled, None));
        m.bytes()
    };
    let build = |m: &Machine| build_ok(&m.options(RemoteCache::Url(url.clone()), None));
    let r = build(&Machine::new());
    assert_eq!(r.stats.remote_writes, DISTINCT as u64);
    let keys = server.keys();
    assert!(keys.iter().all(|k| server.get(k).starts_with(b"KILNSG\0\x01")), "every value signed");

    // Another machine with the key: every entry and the archive from the remote.
    let m = Machine::new();
    let r = build(&m);
    assert_eq!((r.stats.compiled, r.stats.remote_hits), (0, DISTINCT as u64));
    assert!(remote_warnings(&r).is_empty(), "{:?}", r.warnings);
    assert_eq!(m.bytes(), reference);

    // Without the key: values are read as they are (not checked).
    env.remove("KILN_REMOTE_CACHE_KEY");
    let m = Machine::new();
    let r = build(&m);
    assert_eq!((r.stats.compiled, r.stats.remote_hits), (0, DISTINCT as u64));
    assert_eq!(m.bytes(), reference);
    env.set("KILN_REMOTE_CACHE_KEY", SIGNING_KEY);

    // Someone without the key rewrites values: every entry and the archive, each with
    // its MAC left out or forged (a value of another key behind it, or its own).
    let entries: Vec<String> = keys.iter().filter(|k| server.get(k)[40..].starts_with(b"KILNCER")).cloned().collect();
    assert_eq!(entries.len(), DISTINCT);
    let archive = keys.iter().find(|k| server.get(k)[40..].starts_with(b"KILNAR")).unwrap().clone();
    for (i, key) in entries.iter().chain([&archive]).enumerate() {
        let value = server.get(key);
        let forged = match i % 2 {
            0 => value[40..].to_vec(),
            _ => [&value[..8], &[0x5a; 32][..], &server.get(&entries[0])[40..]].concat(),
        };
        server.set(key, &forged);
    }
    let m = Machine::new();
    let r = build(&m);
    let warnings = remote_warnings(&r);
    assert_eq!(warnings.len(), 1, "{:?}", r.warnings);
    assert!(warnings[0].contains("MAC") && warnings[0].contains("refused"), "{}", warnings[0]);
    assert!(keys.iter().any(|k| warnings[0].contains(k.as_str())), "names the key: {}", warnings[0]);
    assert_eq!((r.stats.compiled, r.stats.remote_hits), (DISTINCT, 0));
    assert_eq!(m.bytes(), reference, "no forged value is used");
}

#[test]
fn redis_refuses_values_without_a_valid_mac() {
    signed_entries(Kind::Redis);
}

#[test]
fn http_refuses_values_without_a_valid_mac() {
    signed_entries(Kind::Http);
}

fn corrupted_entry(kind: Kind) {
    let server = Server::start(kind);
    let url = server.url();
    Machine::new().build(&url);
    let keys = server.entries();
    assert_eq!(keys.len(), DISTINCT);
    // One entry truncated, one with a flipped byte in the middle.
    let (truncated, flipped) = (&keys[3], &keys[11]);
    let value = server.get(truncated);
    server.set(truncated, &value[..value.len() / 2]);
    let mut value = server.get(flipped);
    let middle = value.len() / 2;
    value[middle] ^= 0x40;
    server.set(flipped, &value);

    let m = Machine::new();
    let r = m.build(&url);
    assert_eq!((r.stats.compiled, r.stats.remote_hits), (2, DISTINCT as u64 - 2));
    assert_eq!(r.stats.remote_writes, 2, "the two recompiled entries overwrite the bad ones");
    let corrupt: Vec<&String> = r.warnings.iter().filter(|w| w.contains("corrupted")).collect();
    assert_eq!(corrupt.len(), 2, "{:?}", r.warnings);
    assert!(
        corrupt.iter().any(|w| w.contains(truncated.as_str())) && corrupt.iter().any(|w| w.contains(flipped.as_str()))
    );
    assert_eq!(m.bytes(), reference());

    // Overwritten: a third machine gets every entry from the remote.
    let third = Machine::new();
    let r = third.build(&url);
    assert_eq!((r.stats.compiled, r.stats.remote_hits), (0, DISTINCT as u64));
    assert_eq!(third.bytes(), m.bytes());
}

#[test]
fn redis_corrupted_entry_is_recompiled_and_overwritten() {
    corrupted_entry(Kind::Redis);
}

#[test]
fn http_corrupted_entry_is_recompiled_and_overwritten() {
    corrupted_entry(Kind::Http);
}

/// The archive a build stored in the remote, damaged: a warning, the archive assembled
/// again from the entries (the remote's, checked) and stored over the damaged one.
fn corrupted_archive(kind: Kind) {
    let server = Server::start(kind);
    let url = server.url();
    Machine::new().build(&url);
    let archives: Vec<String> = server.keys().into_iter().filter(|k| server.get(k).starts_with(b"KILNAR")).collect();
    assert_eq!(archives.len(), 1, "{:?}", server.keys());
    let good = server.get(&archives[0]);
    let mut bad = good.clone();
    let middle = bad.len() / 2;
    bad[middle] ^= 0x01;
    server.set(&archives[0], &bad);

    let m = Machine::new();
    let r = m.build(&url);
    assert_eq!((r.stats.compiled, r.stats.remote_hits), (0, DISTINCT as u64));
    let corrupt: Vec<&String> = r.warnings.iter().filter(|w| w.contains("corrupted")).collect();
    assert_eq!(corrupt.len(), 1, "{:?}", r.warnings);
    assert!(corrupt[0].contains(&archives[0]) && corrupt[0].contains(&url), "{}", corrupt[0]);
    assert_eq!(m.bytes(), reference());
    assert_eq!(server.get(&archives[0]), good, "stored again, whole");
}

#[test]
fn redis_corrupted_archive_is_assembled_again() {
    corrupted_archive(Kind::Redis);
}

#[test]
fn http_corrupted_archive_is_assembled_again() {
    corrupted_archive(Kind::Http);
}

fn two_writers(kind: Kind) {
    let server = Server::start(kind);
    let url = server.url();
    let (a, b) = (Machine::new(), Machine::new());
    let (ra, rb) = std::thread::scope(|s| {
        let ta = s.spawn(|| a.build(&url));
        let tb = s.spawn(|| b.build(&url));
        (ta.join().unwrap(), tb.join().unwrap())
    });
    for r in [&ra, &rb] {
        assert!(remote_warnings(r).is_empty(), "{:?}", r.warnings);
        assert_eq!(r.stats.compiled as u64 + r.stats.remote_hits, DISTINCT as u64);
    }
    assert_eq!(a.bytes(), b.bytes());
    // Consistent: one value per key, each one whole (a fresh machine uses them all).
    assert_eq!(server.entries().len(), DISTINCT);
    let c = Machine::new();
    let r = c.build(&url);
    assert_eq!((r.stats.compiled, r.stats.remote_hits), (0, DISTINCT as u64));
    assert!(r.warnings.iter().all(|w| !w.contains("corrupted")), "{:?}", r.warnings);
    assert_eq!(c.bytes(), a.bytes());
}

/// A shard on a fresh machine against a warm remote takes its share in `MGET` batches, not
/// one `GET` per key, and compiles nothing.
#[test]
fn a_shard_fetches_its_share_in_batches() {
    let server = Server::start(Kind::Redis);
    let url = server.url();
    Machine::new().build(&url);
    let mut redis = server.redis();
    let () = redis::cmd("CONFIG").arg("RESETSTAT").query(&mut redis).unwrap();
    let m = Machine::new();
    let mut o = m.options(RemoteCache::Url(url), None);
    o.output = None;
    o.shard = Some(build::Shard { index: 0, count: 2 });
    let r = {
        let _env = ENV.read().unwrap_or_else(|e| e.into_inner());
        build_ok(&o)
    };
    let share = DISTINCT - r.stats.other_shards;
    assert!(share > 0 && r.stats.other_shards > 0, "{:?}", r.stats);
    assert_eq!((r.stats.compiled, r.stats.cache_hits, r.stats.remote_hits), (0, share, share as u64));
    let info: String = redis::cmd("INFO").arg("commandstats").query(&mut redis).unwrap();
    let calls = |command: &str| {
        info.lines()
            .find_map(|l| l.strip_prefix(&format!("cmdstat_{command}:calls=")))
            .and_then(|rest| rest.split(',').next()?.parse::<u64>().ok())
            .unwrap_or(0)
    };
    assert!(calls("mget") >= 1, "{info}");
    // One GET: the preprocessing records.
    assert!(calls("get") <= 1, "{info}");
}

/// Shards that find no preprocessing records share preprocessing by pieces: a shard stores
/// each piece's records as it finishes it, and a shard on a fresh machine (the whole set
/// gone from the remote) preprocesses nothing the pieces hold, takes the same share, and the
/// assembly's archive is the one-process archive. A damaged piece is preprocessed again.
#[test]
fn shards_share_preprocessing_by_pieces() {
    const PERMUTATIONS: usize = 8 * scale_set::PER_MATERIAL;
    let env = Env::lock();
    env.set("KILN_RECORD_PIECE", "16");
    let server = Server::start(Kind::Redis);
    let url = server.url();
    let reference = Machine::scale_of(PERMUTATIONS);
    reference.build_ok_locked(RemoteCache::Disabled);
    let shard = |index: usize| {
        let m = Machine::scale_of(PERMUTATIONS);
        let mut o = m.options(RemoteCache::Url(url.clone()), None);
        o.output = None;
        o.shard = Some(build::Shard { index, count: 2 });
        let r = build_ok(&o);
        assert!(remote_warnings(&r).is_empty(), "{:?}", r.warnings);
        r
    };
    let records =
        || -> Vec<String> { server.keys().into_iter().filter(|k| server.get(k).starts_with(b"KILNPP")).collect() };
    // The whole set is the largest records value; forgetting it leaves the pieces alone.
    let forget_whole = || {
        let whole = records().into_iter().max_by_key(|k| server.get(k).len()).unwrap();
        let () = redis::cmd("DEL").arg(format!("kiln:{whole}")).query(&mut server.redis()).unwrap();
    };
    let first = shard(1);
    assert!(first.stats.preprocessed > 0);
    assert!(records().len() > 2, "pieces besides the whole set: {:?}", records());
    forget_whole();
    let second = shard(0);
    assert_eq!(second.stats.preprocessed, 0, "every piece was found");
    forget_whole();
    let pieces = records();
    let mut damaged = server.get(&pieces[0]);
    *damaged.last_mut().unwrap() ^= 1;
    server.set(&pieces[0], &damaged);
    let again = shard(0);
    assert!(
        again.stats.preprocessed > 0 && again.stats.preprocessed <= 16,
        "only the damaged piece: {:?}",
        again.stats
    );
    assert_eq!(again.stats.other_shards, second.stats.other_shards, "the same share");
    let assembly = Machine::scale_of(PERMUTATIONS);
    let r = build_ok(&assembly.options(RemoteCache::Url(url.clone()), None));
    assert_eq!(r.stats.compiled, 0, "{:?}", r.stats);
    assert_eq!(assembly.bytes(), reference.bytes());
}

/// Entries go to the remote as the local cache holds them, compressed with the cache's
/// dictionary, which the remote then holds too: after two shards, an assembly on a fresh
/// machine fetches their dictionaries, compiles nothing and writes the one-process archive.
/// A damaged dictionary is refused (its content no longer hashes to its id): the entries
/// that name it are compiled again (with HTTP, those of the assembly's bundle parts too),
/// the archive's bytes unchanged.
fn entries_keep_their_cache_dictionaries(kind: Kind) {
    const PERMUTATIONS: usize = 40 * scale_set::PER_MATERIAL;
    let server = Server::start(kind);
    let url = server.url();
    let reference = Machine::scale_of(PERMUTATIONS);
    let distinct = reference.build_with(RemoteCache::Disabled, None).stats.compiled;
    for index in 0..2 {
        let m = Machine::scale_of(PERMUTATIONS);
        let mut o = m.options(RemoteCache::Url(url.clone()), None);
        o.output = None;
        o.shard = Some(build::Shard { index, count: 2 });
        let _env = ENV.read().unwrap_or_else(|e| e.into_inner());
        let r = build_ok(&o);
        assert!(remote_warnings(&r).is_empty(), "{:?}", r.warnings);
    }
    let dicts: Vec<String> = server.keys().into_iter().filter(|k| server.get(k).starts_with(b"KILNCD\0\x01")).collect();
    assert!(!dicts.is_empty(), "the shards trained dictionaries and stored them");
    // Remote header 24, then the entry's magic and check sum: its dictionary id.
    let named = server.entries().iter().filter(|k| server.get(k)[24 + 24..24 + 40] != [0; 16]).count();
    assert!(named > 0, "entries name a dictionary");

    let m = Machine::scale_of(PERMUTATIONS);
    let r = m.build(&url);
    assert_eq!((r.stats.compiled, r.stats.remote_hits), (0, distinct as u64), "{:?}", r.warnings);
    assert!(r.warnings.is_empty(), "{:?}", r.warnings);
    assert_eq!(m.bytes(), reference.bytes());
    let kept = std::fs::read_dir(m.dir.path().join("cache")).unwrap();
    assert!(kept.filter(|e| e.as_ref().unwrap().path().extension().is_some_and(|x| x == "kcd")).count() >= 1);

    for d in &dicts {
        let mut value = server.get(d);
        *value.last_mut().unwrap() ^= 1;
        server.set(d, &value);
    }
    let m = Machine::scale_of(PERMUTATIONS);
    let r = m.build_with(RemoteCache::Url(url), Some(RemoteMode::Read));
    assert_eq!(r.stats.compiled, named, "{:?}", r.stats);
    assert_eq!(r.stats.compiled as u64 + r.stats.remote_hits, distinct as u64);
    assert_eq!(m.bytes(), reference.bytes());
}

#[test]
fn redis_entries_keep_their_cache_dictionaries() {
    entries_keep_their_cache_dictionaries(Kind::Redis);
}

#[test]
fn http_entries_keep_their_cache_dictionaries() {
    entries_keep_their_cache_dictionaries(Kind::Http);
}

/// The values of `server` that are bundle parts.
fn bundle_parts(server: &Server) -> Vec<String> {
    server.keys().into_iter().filter(|k| server.get(k).starts_with(b"KILNBD")).collect()
}

/// Removes every entry stored under its own key (a bundle then serves alone).
fn remove_entries(server: &Server) {
    for k in server.entries() {
        std::fs::remove_file(server.dir.path().join("data/kiln").join(k)).unwrap();
    }
}

/// With HTTP, a build of more than a few keys stores them as a bundle too: a fresh local
/// cache fills from it alone (the entries under their own keys removed); a part damaged or
/// cut short gives the entries that pass their checks, the rest is fetched per key or
/// compiled, and the build (read-write) stores the part whole again; in read mode it stays.
#[test]
fn http_bundle_fills_a_fresh_cache_and_damage_is_repaired() {
    let server = Server::start(Kind::Http);
    let url = server.url();
    let ci = Machine::scale();
    let r = ci.build(&url);
    let distinct = r.stats.compiled;
    assert!(distinct >= 64, "{:?}", r.stats);
    assert_eq!(r.stats.remote_writes, distinct as u64, "bundle parts are not counted as entries");
    let parts = bundle_parts(&server);
    assert!(!parts.is_empty(), "{:?}", server.keys());
    let part = server.get(&parts[0]);

    remove_entries(&server);
    let m = Machine::scale();
    let r = m.build(&url);
    assert_eq!((r.stats.compiled, r.stats.remote_hits), (0, distinct as u64));
    assert!(r.warnings.is_empty(), "{:?}", r.warnings);
    assert_eq!(m.bytes(), ci.bytes());

    // The first entry of a part damaged (magic 8, key 32, length 8, value header 24, then
    // the entry): that key alone is compiled.
    let mut bad = part.clone();
    bad[8 + 40 + 24 + 44] ^= 0x10;
    server.set(&parts[0], &bad);
    let m = Machine::scale();
    let r = m.build(&url);
    assert_eq!((r.stats.compiled, r.stats.remote_hits), (1, distinct as u64 - 1));
    assert_eq!(m.bytes(), ci.bytes());
    assert_eq!(server.get(&parts[0]), part, "stored whole again");

    // Cut in half: the first half from the part, the rest of its keys compiled.
    server.set(&parts[0], &part[..part.len() / 2]);
    remove_entries(&server);
    let m = Machine::scale();
    let r = m.build(&url);
    assert!(r.stats.compiled > 0 && r.stats.remote_hits > 0, "{:?}", r.stats);
    assert_eq!(r.stats.compiled as u64 + r.stats.remote_hits, distinct as u64);
    assert_eq!(m.bytes(), ci.bytes());
    assert_eq!(server.get(&parts[0]), part, "stored whole again");

    // Read mode stores nothing, a damaged part included.
    server.set(&parts[0], &bad);
    let m = Machine::scale();
    let r = m.build_with(RemoteCache::Url(url.clone()), Some(RemoteMode::Read));
    assert_eq!(r.stats.compiled as u64 + r.stats.remote_hits, distinct as u64);
    assert_eq!(m.bytes(), ci.bytes());
    assert_eq!(server.get(&parts[0]), bad);
}

/// A warm remote whose server dies when a fresh local cache asks for its bundle: one
/// warning, every key compiled here, the same bytes.
#[test]
fn http_killed_while_a_fresh_cache_fills_from_a_bundle() {
    let server = Arc::new(Mutex::new(Server::start(Kind::Http)));
    let direct = server.lock().unwrap().url();
    let ci = Machine::scale();
    let distinct = ci.build(&direct).stats.compiled;
    assert!(!bundle_parts(&server.lock().unwrap()).is_empty());
    // The streamed GETs write `Host:` capitalized (ureq's single requests `host:`).
    let (port, killed) = killing_proxy(server.clone(), b"\r\nHost: ");
    let url = server.lock().unwrap().url_at(port);
    let m = Machine::scale();
    let r = m.build(&url);
    assert!(killed.load(Ordering::SeqCst), "the fill asked for the bundle");
    assert_eq!((r.stats.compiled, r.stats.remote_hits), (distinct, 0));
    let warnings = remote_warnings(&r);
    assert_eq!(warnings.len(), 1, "one warning: {:?}", r.warnings);
    assert!(warnings[0].contains(&url) && warnings[0].contains("local cache only"), "{}", warnings[0]);
    assert_eq!(m.bytes(), ci.bytes());
}

#[test]
fn redis_two_writers_at_once() {
    two_writers(Kind::Redis);
}

#[test]
fn http_two_writers_at_once() {
    two_writers(Kind::Http);
}

/// Everything a build shows: what `kiln build` prints (warnings, summary, failures) and
/// the report's and options' debug forms.
fn shown(options: &build::Options, result: &Result<Report, build::Error>) -> String {
    let mut text = format!("{options:?}\n{result:?}\n");
    if let Ok(r) = result {
        text.push_str(&r.warnings.join("\n"));
        text.push_str(&r.summary());
    }
    text
}

fn token_never_shown(kind: Kind) {
    let server = Server::start_with(kind, Some(TOKEN));
    let env = Env::lock();

    // The right token (bearer / redis AUTH): the remote works.
    env.set("KILN_REMOTE_CACHE_TOKEN", TOKEN);
    let m = Machine::new();
    let o = m.options(RemoteCache::Url(server.url()), None);
    let result = build::run(&o);
    let text = shown(&o, &result);
    let r = result.unwrap();
    assert_eq!((r.stats.remote_writes, r.stats.remote_errors), (DISTINCT as u64, 0), "{text}");
    assert!(!text.contains(TOKEN), "{text}");

    // `user:password` (HTTP basic auth; redis ACL user and password).
    if kind == Kind::Http {
        env.set("KILN_REMOTE_CACHE_TOKEN", &format!("ci:{TOKEN}"));
        let m = Machine::new();
        let o = m.options(RemoteCache::Url(server.url()), None);
        let result = build::run(&o);
        let text = shown(&o, &result);
        assert_eq!(result.unwrap().stats.remote_hits, DISTINCT as u64, "{text}");
        assert!(!text.contains(TOKEN), "{text}");
    }

    // A wrong token, and a wrong password in the URL: one warning each, naming the server
    // without the secret; the build succeeds.
    let wrong = "wr0ng-pa55word";
    let cases =
        [(Some(wrong.to_string()), server.url()), (None, server.url().replacen("://", &format!("://ci:{wrong}@"), 1))];
    for (token, url) in cases {
        match &token {
            Some(t) => env.set("KILN_REMOTE_CACHE_TOKEN", t),
            None => env.remove("KILN_REMOTE_CACHE_TOKEN"),
        }
        let m = Machine::new();
        let o = m.options(RemoteCache::Url(url), None);
        let result = build::run(&o);
        let text = shown(&o, &result);
        let r = result.unwrap();
        assert_eq!(r.stats.compiled, DISTINCT);
        let warnings = remote_warnings(&r);
        assert_eq!(warnings.len(), 1, "{text}");
        assert!(warnings[0].contains(&server.url()), "{}", warnings[0]);
        assert!(!text.contains(wrong) && !text.contains(TOKEN), "{text}");
    }
    env.remove("KILN_REMOTE_CACHE_TOKEN");
}

#[test]
fn redis_token_is_never_shown() {
    token_never_shown(Kind::Redis);
}

#[test]
fn http_token_is_never_shown() {
    token_never_shown(Kind::Http);
}

/// `KILN_REMOTE_CACHE` and `KILN_REMOTE_CACHE_MODE` choose the remote when the options
/// leave it to the environment; a bad URL is a configuration error that hides credentials.
#[test]
fn the_environment_chooses_the_remote() {
    let server = Server::start(Kind::Redis);
    let env = Env::lock();
    env.set("KILN_REMOTE_CACHE", &server.url());
    env.set("KILN_REMOTE_CACHE_MODE", "read");
    let m = Machine::new();
    let r = build_ok(&m.options(RemoteCache::Auto, None));
    assert_eq!((r.stats.compiled, r.stats.remote_writes), (DISTINCT, 0));
    env.remove("KILN_REMOTE_CACHE_MODE");
    let r = build_ok(&Machine::new().options(RemoteCache::Auto, None));
    assert_eq!(r.stats.remote_writes, DISTINCT as u64);
    env.set("KILN_REMOTE_CACHE", "memcached://user:hunter2@host");
    let e = build::run(&Machine::new().options(RemoteCache::Auto, None)).unwrap_err();
    drop(env);
    assert_eq!(e.exit_code(), 2);
    let text = e.to_string();
    assert!(text.contains("memcached://host") && !text.contains("hunter2"), "{text}");
}

/// https against nginx with TLS: a server certificate that the Mozilla roots do not trust is
/// one warning and the build goes on; trusted through `KILN_REMOTE_CACHE_CA`, the remote
/// serves a second machine; a CA file without a certificate is a configuration error.
#[test]
fn https_with_a_certificate_authority_of_ones_own() {
    let server = Server::start(Kind::Https);
    let url = server.url();
    let env = Env::lock();
    let run = |m: &Machine| build::run(&m.options(RemoteCache::Url(url.clone()), None));

    let m = Machine::new();
    let r = run(&m).unwrap();
    assert_eq!(r.stats.compiled, DISTINCT);
    let warnings = remote_warnings(&r);
    assert_eq!(warnings.len(), 1, "{:?}", r.warnings);
    assert!(warnings[0].contains(&url), "{}", warnings[0]);
    assert!(server.keys().is_empty(), "nothing went through an untrusted connection");

    env.set("KILN_REMOTE_CACHE_CA", server.dir.path().join("ca.pem").to_str().unwrap());
    let ci = Machine::new();
    let r = run(&ci).unwrap();
    assert_eq!((r.stats.remote_writes, r.stats.remote_errors), (DISTINCT as u64, 0), "{:?}", r.warnings);
    let other = Machine::new();
    let r = run(&other).unwrap();
    assert_eq!((r.stats.compiled, r.stats.remote_hits), (0, DISTINCT as u64), "{:?}", r.warnings);
    assert_eq!(other.bytes(), ci.bytes());

    // A bundle through https (ureq's streamed bodies): it alone fills a fresh cache.
    let ci = Machine::scale();
    let distinct = run(&ci).unwrap().stats.compiled;
    assert!(!bundle_parts(&server).is_empty(), "{:?}", server.keys());
    remove_entries(&server);
    let other = Machine::scale();
    let r = run(&other).unwrap();
    assert_eq!((r.stats.compiled, r.stats.remote_hits), (0, distinct as u64), "{:?}", r.warnings);
    assert_eq!(other.bytes(), ci.bytes());

    env.set("KILN_REMOTE_CACHE_CA", server.dir.path().join("server.ext").to_str().unwrap());
    let e = run(&Machine::new()).unwrap_err();
    assert_eq!(e.exit_code(), 2);
    assert!(e.to_string().contains("KILN_REMOTE_CACHE_CA") && e.to_string().contains("no PEM certificate"), "{e}");
}
