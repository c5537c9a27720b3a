//! Remote cache servers for benches: `redis-server` and nginx with WebDAV `PUT`, each
//! started on a free loopback port in its own temporary folder and stopped on drop. Shared
//! by the `remote` and `scale` benches (`#[path = "support/servers.rs"] mod servers;`).

use std::net::{TcpListener, TcpStream};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// The backends, in the order benches print them.
pub const KINDS: [&str; 2] = ["redis", "http"];

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

/// A server process, killed on drop.
pub struct Server {
    child: Child,
    /// What `--remote-cache` takes.
    pub url: String,
    _dir: tempfile::TempDir,
}

impl Server {
    /// The CPU time (user and system) the server's processes have spent so far: the child
    /// and its children (nginx's workers), from `/proc` (zero where there is none).
    #[allow(dead_code)] // the `remote` bench does not print it
    pub fn cpu(&self) -> Duration {
        let pid = self.child.id();
        let mut pids = vec![pid];
        if let Ok(children) = std::fs::read_to_string(format!("/proc/{pid}/task/{pid}/children")) {
            pids.extend(children.split_whitespace().filter_map(|p| p.parse::<u32>().ok()));
        }
        let ticks: u64 = pids
            .iter()
            .filter_map(|p| {
                let stat = std::fs::read_to_string(format!("/proc/{p}/stat")).ok()?;
                // After the command's name: state, ..., utime (the 12th), stime.
                let fields: Vec<&str> = stat.rsplit_once(')')?.1.split_whitespace().collect();
                Some(fields.get(11)?.parse::<u64>().ok()? + fields.get(12)?.parse::<u64>().ok()?)
            })
            .sum();
        // SAFETY: sysconf reads a constant of the system; it takes no pointer.
        let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) }.max(1) as u64;
        Duration::from_millis(ticks * 1000 / hz)
    }
}

impl Drop for Server {
    /// SIGTERM first: nginx's master then stops its workers (a SIGKILL would leave them
    /// running, holding the port and this process's output); SIGKILL after 5 s.
    fn drop(&mut self) {
        // SAFETY: kill takes no pointer; the pid is our child's, not yet reaped (no reuse).
        unsafe { libc::kill(self.child.id() as libc::pid_t, libc::SIGTERM) };
        let t = Instant::now();
        while matches!(self.child.try_wait(), Ok(None)) && t.elapsed() < Duration::from_secs(5) {
            std::thread::sleep(Duration::from_millis(10));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn installed(binary: &str, arg: &str) -> bool {
    Command::new(binary).arg(arg).output().map(|o| o.status.success()).unwrap_or(false)
}

/// Starts a `kind` server ("redis" or "http"); why not, when it is not installed or does not
/// start (a bench then skips its line).
pub fn start(kind: &str) -> Result<Server, String> {
    let dir = tempfile::tempdir().map_err(|e| format!("no temporary folder: {e}"))?;
    let port = free_port();
    let spawned = match kind {
        "redis" => {
            if !installed("redis-server", "--version") {
                return Err("redis-server is not installed (Debian package redis-server)".into());
            }
            Command::new("redis-server")
                .args(["--port", &port.to_string(), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no"])
                .arg("--dir")
                .arg(dir.path())
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .spawn()
                .map(|c| (c, format!("redis://127.0.0.1:{port}")))
        }
        _ => {
            if !installed(nginx(), "-v") {
                return Err("nginx is not installed (Debian package nginx-light)".into());
            }
            let p = dir.path();
            std::fs::create_dir_all(p.join("data/kiln")).unwrap();
            std::fs::create_dir_all(p.join("logs")).unwrap();
            // SAFETY: geteuid cannot fail and takes no argument.
            let user = if unsafe { libc::geteuid() } == 0 { "user root;" } else { "" };
            let conf = format!(
                "{user} daemon off; worker_processes 2; pid {p}/nginx.pid; error_log {p}/error.log;
                 events {{ worker_connections 256; }}
                 http {{ access_log off; client_body_temp_path {p}/body; client_max_body_size 0;
                   server {{ listen 127.0.0.1:{port}; root {p}/data;
                     location /kiln/ {{ dav_methods PUT; create_full_put_path on; }} }} }}",
                p = p.display()
            );
            std::fs::write(p.join("nginx.conf"), conf).unwrap();
            Command::new(nginx())
                .arg("-p")
                .arg(p)
                .arg("-c")
                .arg(p.join("nginx.conf"))
                .arg("-e")
                .arg(p.join("error.log"))
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .spawn()
                .map(|c| (c, format!("http://127.0.0.1:{port}/kiln")))
        }
    };
    let (child, url) = spawned.map_err(|e| format!("{kind} server does not start: {e}"))?;
    let server = Server { child, url, _dir: dir };
    let t = Instant::now();
    while TcpStream::connect(("127.0.0.1", port)).is_err() {
        if t.elapsed() > Duration::from_secs(20) {
            return Err(format!("{kind} server did not listen on port {port} within 20 s"));
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    Ok(server)
}
