//! A JSON-RPC client that speaks to `kiln lsp` over the child's stdin and stdout, and the
//! test project (`tests/in/lsp/`, copied to a temporary folder). Shared by the LSP tests
//! (`compiler/tests/it/lsp.rs`) and the LSP bench (`compiler/benches/lsp.rs`) through
//! `#[path]` modules; each uses part of it.
#![allow(dead_code)]

use std::io::{BufRead, BufReader, Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc::{channel, Receiver};
use std::time::{Duration, Instant};

use serde_json::{json, Value};

pub const KILN: &str = env!("CARGO_BIN_EXE_kiln");
pub const WAIT: Duration = Duration::from_secs(30);

pub fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().expect("repository root").to_path_buf()
}

/// A copy of `tests/in/lsp/` in a temporary folder (canonical path).
pub fn project() -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().expect("temp dir");
    let root = dir.path().canonicalize().expect("canonical");
    copy_dir(&repo().join("tests/in/lsp"), &root);
    (dir, root)
}

pub fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).expect("mkdir");
    for e in std::fs::read_dir(from).expect("read_dir") {
        let e = e.expect("entry");
        let target = to.join(e.file_name());
        if e.file_type().expect("type").is_dir() {
            copy_dir(&e.path(), &target);
        } else {
            std::fs::copy(e.path(), &target).expect("copy");
        }
    }
}

pub fn uri(path: &Path) -> String {
    format!("file://{}", path.display())
}

/// A JSON-RPC client speaking to `kiln lsp` over its stdin and stdout.
pub struct Client {
    pub child: Child,
    stdin: Option<ChildStdin>,
    rx: Receiver<Value>,
    next_id: i64,
    /// Notifications received while waiting for something else.
    pending: Vec<Value>,
}

impl Client {
    pub fn start() -> Client {
        let mut command = Command::new(KILN);
        // None of the developer's Kiln settings (as the tests' `kiln_command`).
        for (name, _) in std::env::vars_os() {
            if name.to_string_lossy().starts_with("KILN_") || name == "CARGO_TARGET_DIR" {
                command.env_remove(&name);
            }
        }
        let mut child = command
            .arg("lsp")
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("start kiln lsp");
        let stdout = child.stdout.take().expect("stdout");
        let (tx, rx) = channel();
        std::thread::spawn(move || {
            let mut r = BufReader::new(stdout);
            loop {
                let mut len = None;
                loop {
                    let mut line = String::new();
                    if r.read_line(&mut line).unwrap_or(0) == 0 {
                        return;
                    }
                    let line = line.trim_end();
                    if line.is_empty() {
                        break;
                    }
                    if let Some(v) = line.strip_prefix("Content-Length: ") {
                        len = v.parse::<usize>().ok();
                    }
                }
                let mut body = vec![0; len.expect("Content-Length")];
                if r.read_exact(&mut body).is_err() {
                    return;
                }
                let v: Value = serde_json::from_slice(&body).expect("JSON from the server");
                if tx.send(v).is_err() {
                    return;
                }
            }
        });
        let stdin = child.stdin.take();
        Client { child, stdin, rx, next_id: 1, pending: Vec::new() }
    }

    /// Starts a server and initializes it with these options.
    pub fn initialized(options: Value) -> Client {
        let mut c = Client::start();
        let r = c.request(
            "initialize",
            json!({ "processId": null, "rootUri": null, "capabilities": {}, "initializationOptions": options }),
        );
        assert!(r["result"]["capabilities"]["hoverProvider"].as_bool().unwrap_or(false), "{r}");
        c.notify("initialized", json!({}));
        c
    }

    pub fn write_raw(&mut self, bytes: &[u8]) {
        let stdin = self.stdin.as_mut().expect("stdin open");
        stdin.write_all(bytes).expect("write to the server");
        stdin.flush().expect("flush");
    }

    pub fn send(&mut self, v: Value) {
        let body = v.to_string();
        self.write_raw(format!("Content-Length: {}\r\n\r\n{body}", body.len()).as_bytes());
    }

    pub fn notify(&mut self, method: &str, params: Value) {
        self.send(json!({ "jsonrpc": "2.0", "method": method, "params": params }));
    }

    /// Sends a request and waits for its response (keeping notifications for later).
    pub fn request(&mut self, method: &str, params: Value) -> Value {
        let id = self.next_id;
        self.next_id += 1;
        self.send(json!({ "jsonrpc": "2.0", "id": id, "method": method, "params": params }));
        self.response(json!(id))
    }

    pub fn response(&mut self, id: Value) -> Value {
        let deadline = Instant::now() + WAIT;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.rx.recv_timeout(left) {
                Ok(v) if v.get("method").is_none() && v["id"] == id => return v,
                Ok(v) => self.pending.push(v),
                Err(e) => panic!("no response to request {id}: {e:?}"),
            }
        }
    }

    /// The next `publishDiagnostics` for `uri` that `accept` takes (earlier ones are dropped).
    pub fn diagnostics(&mut self, uri: &str, accept: impl Fn(&Value) -> bool) -> Value {
        let deadline = Instant::now() + WAIT;
        let is_it = |v: &Value| v["method"] == "textDocument/publishDiagnostics" && v["params"]["uri"] == uri;
        let mut seen = Vec::new();
        let mut i = 0;
        while i < self.pending.len() {
            if is_it(&self.pending[i]) {
                let v = self.pending.remove(i);
                if accept(&v["params"]) {
                    return v["params"].clone();
                }
                seen.push(v);
            } else {
                i += 1;
            }
        }
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.rx.recv_timeout(left) {
                Ok(v) if is_it(&v) => {
                    if accept(&v["params"]) {
                        return v["params"].clone();
                    }
                    seen.push(v);
                }
                Ok(v) => self.pending.push(v),
                Err(_) => panic!("no accepted diagnostics for {uri}; got: {seen:#?}"),
            }
        }
    }

    pub fn open(&mut self, path: &Path, text: &str) {
        let params = json!({ "textDocument": { "uri": uri(path), "languageId": "wgsl", "version": 1, "text": text } });
        self.notify("textDocument/didOpen", params);
    }

    pub fn change(&mut self, path: &Path, version: i64, text: &str) {
        let params =
            json!({ "textDocument": { "uri": uri(path), "version": version }, "contentChanges": [{ "text": text }] });
        self.notify("textDocument/didChange", params);
    }

    /// Closes stdin and waits for the server to end; its exit status.
    pub fn finish(mut self) -> std::process::ExitStatus {
        drop(self.stdin.take());
        let deadline = Instant::now() + WAIT;
        loop {
            if let Some(s) = self.child.try_wait().expect("wait") {
                return s;
            }
            assert!(Instant::now() < deadline, "the server did not end after stdin closed");
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Client {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Diagnostics of a publish with severity 1 (errors).
pub fn errors(params: &Value) -> Vec<Value> {
    params["diagnostics"].as_array().map_or(Vec::new(), |d| d.iter().filter(|x| x["severity"] == 1).cloned().collect())
}

/// The 0-based number of the first line of `text` holding `needle`.
pub fn line_of(text: &str, needle: &str) -> u64 {
    text.lines().position(|l| l.contains(needle)).unwrap_or_else(|| panic!("no line with {needle:?}")) as u64
}

/// A position parameter: `path` at `line` and `character` (0-based).
pub fn at(path: &Path, line: u64, character: u64) -> Value {
    json!({ "textDocument": { "uri": uri(path) }, "position": { "line": line, "character": character } })
}

/// The 0-based column of `needle` in line `line` of `text`.
pub fn column(text: &str, line: u64, needle: &str) -> u64 {
    text.lines().nth(line as usize).and_then(|l| l.find(needle)).expect("column") as u64
}
