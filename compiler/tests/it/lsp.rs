//! `kiln lsp` through a real client: a plain JSON-RPC client over the child's stdio
//! (protocol tests), and Neovim's built-in LSP client run headless with a Lua script
//! (`compiler/tests/lsp/nvim.lua`). The project is `tests/in/lsp/`, copied to a temporary
//! folder per test. `cargo test -p kiln --test lsp -- --ignored latency --nocapture` measures
//! the diagnostics latency of 50 edits on the bundled set.

use std::io::{BufRead, BufReader, Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc::{channel, Receiver};
use std::time::{Duration, Instant};

use serde_json::{json, Value};

const KILN: &str = env!("CARGO_BIN_EXE_kiln");
const WAIT: Duration = Duration::from_secs(30);

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().expect("repository root").to_path_buf()
}

/// A copy of `tests/in/lsp/` in a temporary folder (canonical path).
fn project() -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().expect("temp dir");
    let root = dir.path().canonicalize().expect("canonical");
    copy_dir(&repo().join("tests/in/lsp"), &root);
    (dir, root)
}

fn copy_dir(from: &Path, to: &Path) {
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

fn uri(path: &Path) -> String {
    format!("file://{}", path.display())
}

/// A JSON-RPC client speaking to `kiln lsp` over its stdin and stdout.
struct Client {
    child: Child,
    stdin: Option<ChildStdin>,
    rx: Receiver<Value>,
    next_id: i64,
    /// Notifications received while waiting for something else.
    pending: Vec<Value>,
}

impl Client {
    fn start() -> Client {
        let mut child = Command::new(KILN)
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
    fn initialized(options: Value) -> Client {
        let mut c = Client::start();
        let r = c.request(
            "initialize",
            json!({ "processId": null, "rootUri": null, "capabilities": {}, "initializationOptions": options }),
        );
        assert!(r["result"]["capabilities"]["hoverProvider"].as_bool().unwrap_or(false), "{r}");
        c.notify("initialized", json!({}));
        c
    }

    fn write_raw(&mut self, bytes: &[u8]) {
        let stdin = self.stdin.as_mut().expect("stdin open");
        stdin.write_all(bytes).expect("write to the server");
        stdin.flush().expect("flush");
    }

    fn send(&mut self, v: Value) {
        let body = v.to_string();
        self.write_raw(format!("Content-Length: {}\r\n\r\n{body}", body.len()).as_bytes());
    }

    fn notify(&mut self, method: &str, params: Value) {
        self.send(json!({ "jsonrpc": "2.0", "method": method, "params": params }));
    }

    /// Sends a request and waits for its response (keeping notifications for later).
    fn request(&mut self, method: &str, params: Value) -> Value {
        let id = self.next_id;
        self.next_id += 1;
        self.send(json!({ "jsonrpc": "2.0", "id": id, "method": method, "params": params }));
        self.response(json!(id))
    }

    fn response(&mut self, id: Value) -> Value {
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
    fn diagnostics(&mut self, uri: &str, accept: impl Fn(&Value) -> bool) -> Value {
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

    fn open(&mut self, path: &Path, text: &str) {
        let params = json!({ "textDocument": { "uri": uri(path), "languageId": "wgsl", "version": 1, "text": text } });
        self.notify("textDocument/didOpen", params);
    }

    fn change(&mut self, path: &Path, version: i64, text: &str) {
        let params =
            json!({ "textDocument": { "uri": uri(path), "version": version }, "contentChanges": [{ "text": text }] });
        self.notify("textDocument/didChange", params);
    }

    /// Closes stdin and waits for the server to end; its exit status.
    fn finish(mut self) -> std::process::ExitStatus {
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
fn errors(params: &Value) -> Vec<Value> {
    params["diagnostics"].as_array().map_or(Vec::new(), |d| d.iter().filter(|x| x["severity"] == 1).cloned().collect())
}

/// The 0-based lines reported inactive (`Unnecessary`-tagged hints).
fn inactive_lines(params: &Value) -> Vec<u64> {
    let mut out = Vec::new();
    for d in params["diagnostics"].as_array().into_iter().flatten() {
        if d["tags"].as_array().is_some_and(|t| t.contains(&json!(1))) {
            let (s, e) =
                (d["range"]["start"]["line"].as_u64().unwrap_or(0), d["range"]["end"]["line"].as_u64().unwrap_or(0));
            out.extend(s..e);
        }
    }
    out
}

fn line_of(text: &str, needle: &str) -> u64 {
    text.lines().position(|l| l.contains(needle)).unwrap_or_else(|| panic!("no line with {needle:?}")) as u64
}

#[test]
fn an_error_in_a_header_shows_on_the_header_line() {
    let (_dir, root) = project();
    let header = root.join("shaders/Common.ush");
    let text = std::fs::read_to_string(&header).expect("read").replace("return s.albedo;", "return s.albedo + oops;");
    std::fs::write(&header, &text).expect("write");
    let mut c = Client::initialized(json!({ "permutation": { "FULLY_ROUGH": 1 } }));
    let lit = root.join("shaders/Lit.usf");
    c.open(&lit, &std::fs::read_to_string(&lit).expect("read"));
    let want = line_of(&text, "oops");
    let d = c.diagnostics(&uri(&header), |p| !errors(p).is_empty());
    let e = &errors(&d)[0];
    assert_eq!(e["range"]["start"]["line"], want, "{d:#}");
    assert!(e["message"].as_str().unwrap_or("").contains("oops"), "{e}");
    assert_eq!(c.finish().code(), Some(0));
}

#[test]
fn an_error_some_permutations_hit_counts_them_as_the_build_does() {
    let (_dir, root) = project();
    let lit = root.join("shaders/Lit.usf");
    let text = std::fs::read_to_string(&lit).expect("read").replace(
        "    return vec4<f32>(lit, 1.0);",
        "#if NUM_LIGHTS == 2\n    let bad: i32 = 1.5;\n#endif\n    return vec4<f32>(lit, 1.0);",
    );
    // The build's own count, from the same text on disk.
    std::fs::write(&lit, &text).expect("write");
    let stats = root.join("stats.json");
    let out = Command::new(KILN)
        .args(["build", "--no-cache", "--config"])
        .arg(root.join("permutations.toml"))
        .arg("-o")
        .arg(root.join("out.kpak"))
        .arg("--stats-json")
        .arg(&stats)
        .output()
        .expect("kiln build");
    assert_eq!(out.status.code(), Some(1), "{}", String::from_utf8_lossy(&out.stderr));
    let stats: Value = serde_json::from_str(&std::fs::read_to_string(&stats).expect("stats")).expect("json");
    let failed = stats["failed"].as_u64().expect("failed");
    let kept = stats["permutations"].as_u64().expect("permutations");

    let mut c = Client::initialized(json!({}));
    c.open(&lit, &text);
    let want =
        format!("in {failed} of {kept} permutations of LitPS@sm5, e.g. `LitPS@sm5{{FULLY_ROUGH=0,NUM_LIGHTS=2}}`");
    let d = c.diagnostics(&uri(&lit), |p| {
        errors(p).iter().any(|e| e["message"].as_str().unwrap_or("").contains("permutations of"))
    });
    let e = errors(&d)
        .into_iter()
        .find(|e| e["message"].as_str().unwrap_or("").contains("permutations of"))
        .expect("counted");
    assert!(e["message"].as_str().unwrap_or("").ends_with(&want), "{e} / {want}");
    assert_eq!(e["range"]["start"]["line"], line_of(&text, "let bad"), "{e}");
}

/// The lines of `file` that `kiln preprocess` of this permutation keeps (by their text).
fn preprocessed(root: &Path, file: &Path, defines: &[&str]) -> String {
    let mut cmd = Command::new(KILN);
    cmd.arg("preprocess").arg(file).arg("--config").arg(root.join("permutations.toml")).args(["--level", "sm5"]);
    for d in defines {
        cmd.arg("-D").arg(d);
    }
    let out = cmd.output().expect("kiln preprocess");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout).expect("utf-8")
}

/// The 0-based code lines of `text` absent from `output` (directives, blank lines and lines
/// expanding a dimension aside).
fn absent_lines(text: &str, output: &str) -> Vec<u64> {
    let kept: Vec<&str> = output.lines().map(str::trim).collect();
    text.lines()
        .enumerate()
        // Lines naming a dimension come out with its value in place of its name.
        .filter(|(_, l)| !l.trim().is_empty() && !l.trim_start().starts_with('#') && !l.contains("NUM_LIGHTS"))
        .filter(|(_, l)| !kept.contains(&l.trim()))
        .map(|(i, _)| i as u64)
        .collect()
}

#[test]
fn inactive_lines_match_kiln_preprocess_and_follow_the_active_permutation() {
    let (_dir, root) = project();
    let lit = root.join("shaders/Lit.usf");
    let text = std::fs::read_to_string(&lit).expect("read");
    let mut c = Client::initialized(json!({}));
    c.open(&lit, &text);
    let d = c.diagnostics(&uri(&lit), |p| !inactive_lines(p).is_empty());
    let expected = absent_lines(&text, &preprocessed(&root, &lit, &["FULLY_ROUGH=0", "NUM_LIGHTS=0"]));
    assert_eq!(inactive_lines(&d), expected, "{d:#}");

    let r = c.request("kiln/permutations", json!({ "textDocument": { "uri": uri(&lit) } }));
    assert_eq!(r["result"]["permutations"].as_array().map(Vec::len), Some(7), "{r}");
    assert_eq!(r["result"]["active"], "LitPS@sm5{FULLY_ROUGH=0,NUM_LIGHTS=0}");

    let r = c
        .request("kiln/setPermutation", json!({ "textDocument": { "uri": uri(&lit) }, "values": { "NUM_LIGHTS": 2 } }));
    assert_eq!(r["result"]["active"], "LitPS@sm5{FULLY_ROUGH=0,NUM_LIGHTS=2}", "{r}");
    let expected = absent_lines(&text, &preprocessed(&root, &lit, &["FULLY_ROUGH=0", "NUM_LIGHTS=2"]));
    let d = c.diagnostics(&uri(&lit), |p| inactive_lines(p) == expected);
    assert_eq!(inactive_lines(&d), expected);

    let header = root.join("shaders/Common.ush");
    let name = "LitPS@sm5{FULLY_ROUGH=1,NUM_LIGHTS=1}";
    let r = c.request("kiln/setPermutation", json!({ "textDocument": { "uri": uri(&lit) }, "permutation": name }));
    assert_eq!(r["result"]["active"], name, "{r}");
    let htext = std::fs::read_to_string(&header).expect("read");
    // Inactive regions are published for open documents.
    c.open(&header, &htext);
    let want = vec![line_of(&htext, "return s.albedo *")];
    c.diagnostics(&uri(&header), |p| inactive_lines(p) == want);

    let r = c.request(
        "kiln/setPermutation",
        json!({ "textDocument": { "uri": uri(&lit) }, "permutation": "LitPS@sm5{NOPE=1}" }),
    );
    assert!(r["error"].is_object(), "{r}");
    let r = c.request(
        "kiln/setPermutation",
        json!({ "textDocument": { "uri": uri(&lit) }, "permutation": "LitPS@sm5{FULLY_ROUGH=1,NUM_LIGHTS=4}" }),
    );
    assert!(r["error"].is_object(), "a skipped permutation is no choice: {r}");
}

#[test]
fn an_edit_moves_diagnostics_and_every_change_is_answered_with_its_version() {
    let (_dir, root) = project();
    let lit = root.join("shaders/Lit.usf");
    let text = std::fs::read_to_string(&lit).expect("read");
    let mut c = Client::initialized(json!({}));
    c.open(&lit, &text);
    c.diagnostics(&uri(&lit), |p| p["version"] == 1);
    let broken = text.replace("var s: Surface;", "var s: Surfac;");
    c.change(&lit, 2, &broken);
    let d = c.diagnostics(&uri(&lit), |p| p["version"] == 2);
    let e = &errors(&d)[0];
    assert_eq!(e["range"]["start"]["line"], line_of(&broken, "Surfac;"), "{d:#}");
    c.change(&lit, 3, &broken);
    c.diagnostics(&uri(&lit), |p| p["version"] == 3 && !errors(p).is_empty());
    // A ranged edit (the server asks for whole texts; some clients send ranges anyway).
    let l = line_of(&broken, "Surfac;");
    let col = column(&broken, l, "Surfac;") + 6;
    let range = json!({ "start": { "line": l, "character": col }, "end": { "line": l, "character": col } });
    let params = json!({ "textDocument": { "uri": uri(&lit), "version": 4 }, "contentChanges": [{ "range": range, "text": "e" }] });
    c.notify("textDocument/didChange", params);
    c.diagnostics(&uri(&lit), |p| p["version"] == 4 && errors(p).is_empty());

    // An unsaved header buffer is what the shader reads.
    let header = root.join("shaders/Common.ush");
    let htext = std::fs::read_to_string(&header).expect("read");
    c.open(&header, &htext.replace("roughness: f32,", "roughness: f32,\n    bad: nope,"));
    let d = c.diagnostics(&uri(&header), |p| !errors(p).is_empty());
    assert_eq!(errors(&d)[0]["range"]["start"]["line"], line_of(&htext, "roughness: f32,") + 1, "{d:#}");
}

#[test]
fn a_header_only_other_permutations_read_is_checked_when_edited() {
    let (_dir, root) = project();
    let lit = root.join("shaders/Lit.usf");
    let extra = root.join("shaders/Extra.ush");
    std::fs::write(&extra, "fn extra() -> f32 { return 1.0; }\n").expect("write");
    let text = format!(
        "#if NUM_LIGHTS == 4\n#include \"Extra.ush\"\n#endif\n{}",
        std::fs::read_to_string(&lit).expect("read")
    );
    std::fs::write(&lit, &text).expect("write");
    let mut c = Client::initialized(json!({}));
    c.open(&lit, &text);
    // The domain check learns that a permutation reads Extra.ush.
    c.diagnostics(&uri(&lit), |p| p["version"] == 1);
    std::thread::sleep(Duration::from_millis(500));
    c.open(&extra, "fn extra() -> f32 { return nope; }\n");
    let want = "in 1 of 7 permutations of LitPS@sm5, e.g. `LitPS@sm5{FULLY_ROUGH=0,NUM_LIGHTS=4}`";
    let d =
        c.diagnostics(&uri(&extra), |p| errors(p).iter().any(|e| e["message"].as_str().unwrap_or("").ends_with(want)));
    assert_eq!(errors(&d)[0]["range"]["start"]["line"], 0, "{d:#}");
}

#[test]
fn a_header_included_twice_is_inactive_only_where_both_inclusions_skip_it() {
    let (_dir, root) = project();
    let lit = root.join("shaders/Lit.usf");
    let twice = root.join("shaders/Twice.ush");
    // A guard the preprocessor cannot take for an include guard: the second inclusion skips
    // the whole file, the first keeps it.
    std::fs::write(&twice, "#if !defined(TWICE)\n#define TWICE 1\nconst TWICE_VALUE: f32 = 1.0;\n#if FULLY_ROUGH\nconst ROUGH_ONLY: f32 = 2.0;\n#endif\n#endif\n").expect("write");
    let text =
        format!("#include \"Twice.ush\"\n#include \"Twice.ush\"\n{}", std::fs::read_to_string(&lit).expect("read"));
    let mut c = Client::initialized(json!({}));
    c.open(&lit, &text);
    c.open(&twice, &std::fs::read_to_string(&twice).expect("read"));
    let d = c.diagnostics(&uri(&twice), |p| !inactive_lines(p).is_empty());
    assert_eq!(inactive_lines(&d), vec![4], "{d:#}");
}

#[test]
fn the_set_and_the_permutation_come_from_the_client_settings() {
    let (_dir, root) = project();
    // The set named by initializationOptions.config, the file opened from another folder name.
    let moved = root.join("config/kiln.toml");
    std::fs::create_dir_all(moved.parent().expect("parent")).expect("mkdir");
    let t = std::fs::read_to_string(root.join("permutations.toml")).expect("read");
    std::fs::write(
        &moved,
        t.replace("include = [\"shaders\"]", "include = [\"../shaders\"]").replace("\"shaders\" }", "\"../shaders\" }"),
    )
    .expect("write");
    std::fs::remove_file(root.join("permutations.toml")).expect("rm");
    let lit = root.join("shaders/Lit.usf");
    let mut c = Client::initialized(json!({ "config": moved, "permutation": { "NUM_LIGHTS": 1 } }));
    c.open(&lit, &std::fs::read_to_string(&lit).expect("read"));
    c.diagnostics(&uri(&lit), |p| p["version"] == 1);
    let r = c.request("kiln/permutations", json!({ "textDocument": { "uri": uri(&lit) } }));
    assert_eq!(r["result"]["active"], "LitPS@sm5{FULLY_ROUGH=0,NUM_LIGHTS=1}", "{r}");
    c.notify(
        "workspace/didChangeConfiguration",
        json!({ "settings": { "kiln": { "permutation": { "FULLY_ROUGH": 1, "NUM_LIGHTS": 2 } } } }),
    );
    let r = c.request("kiln/permutations", json!({ "textDocument": { "uri": uri(&lit) } }));
    assert_eq!(r["result"]["active"], "LitPS@sm5{FULLY_ROUGH=1,NUM_LIGHTS=2}", "{r}");
    c.notify(
        "workspace/didChangeConfiguration",
        json!({ "settings": { "permutation": "LitPS@sm5{FULLY_ROUGH=0,NUM_LIGHTS=4}" } }),
    );
    let r = c.request("kiln/permutations", json!({ "textDocument": { "uri": uri(&lit) } }));
    assert_eq!(r["result"]["active"], "LitPS@sm5{FULLY_ROUGH=0,NUM_LIGHTS=4}", "{r}");
}

#[test]
fn exit_without_shutdown_ends_with_status_1() {
    let mut c = Client::initialized(json!({}));
    c.notify("exit", Value::Null);
    assert_eq!(c.finish().code(), Some(1));
}

#[test]
fn a_broken_permutation_set_is_reported_on_its_shaders() {
    let (_dir, root) = project();
    let lit = root.join("shaders/Lit.usf");
    let toml = root.join("permutations.toml");
    let ttext = std::fs::read_to_string(&toml).expect("read");
    let mut c = Client::initialized(json!({}));
    c.open(&lit, &std::fs::read_to_string(&lit).expect("read"));
    c.diagnostics(&uri(&lit), |p| p["version"] == 1);
    c.open(&toml, &ttext.replace("stage = \"fragment\"", "stage = \"pixel\""));
    let d = c.diagnostics(&uri(&toml), |p| !errors(p).is_empty());
    assert_eq!(errors(&d)[0]["range"]["start"]["line"], line_of(&ttext, "stage = "), "{d:#}");
    c.diagnostics(&uri(&lit), |p| {
        errors(p).iter().any(|e| e["message"].as_str().unwrap_or("").contains("does not load"))
    });
    c.change(&toml, 2, &ttext);
    c.diagnostics(&uri(&lit), |p| errors(p).is_empty());
}

fn at(path: &Path, line: u64, character: u64) -> Value {
    json!({ "textDocument": { "uri": uri(path) }, "position": { "line": line, "character": character } })
}

fn column(text: &str, line: u64, needle: &str) -> u64 {
    text.lines().nth(line as usize).and_then(|l| l.find(needle)).expect("column") as u64
}

#[test]
fn hover_definition_completion_and_symbols() {
    let (_dir, root) = project();
    let lit = root.join("shaders/Lit.usf");
    let header = root.join("shaders/Common.ush");
    let text = std::fs::read_to_string(&lit).expect("read");
    let htext = std::fs::read_to_string(&header).expect("read");
    let mut c = Client::initialized(json!({ "permutation": "LitPS@sm5{FULLY_ROUGH=0,NUM_LIGHTS=2}" }));
    c.open(&lit, &text);

    let l = line_of(&text, "f32(NUM_LIGHTS)");
    let h = c.request("textDocument/hover", at(&lit, l, column(&text, l, "NUM_LIGHTS") + 2));
    let v = h["result"]["contents"]["value"].as_str().unwrap_or("").to_string();
    assert!(v.contains("`NUM_LIGHTS` = `2`"), "{h}");
    assert!(v.contains("`4`: 1 kept") && v.contains("`0`: 2 kept"), "{v}");

    let h = c.request("textDocument/hover", at(&lit, 0, 12));
    assert!(h["result"]["contents"]["value"].as_str().unwrap_or("").contains("Common.ush"), "{h}");
    let d = c.request("textDocument/definition", at(&lit, 0, 12));
    assert_eq!(d["result"]["uri"], uri(&header), "{d}");

    let l = line_of(&text, "shade(s");
    let d = c.request("textDocument/definition", at(&lit, l, column(&text, l, "shade") + 1));
    assert_eq!(d["result"]["uri"], uri(&header), "{d}");
    let hl = line_of(&htext, "fn shade");
    assert_eq!(d["result"]["range"]["start"], json!({ "line": hl, "character": column(&htext, hl, "shade") }), "{d}");

    let l = line_of(&text, "var s: Surface");
    let d = c.request("textDocument/definition", at(&lit, l, column(&text, l, "Surface") + 1));
    assert_eq!(d["result"]["range"]["start"]["line"], line_of(&htext, "struct Surface"), "{d}");

    c.open(&header, &htext);
    let l = line_of(&htext, "* ROUGHNESS_SCALE");
    let h = c.request("textDocument/hover", at(&header, l, column(&htext, l, "ROUGHNESS_SCALE") + 1));
    assert!(h["result"]["contents"]["value"].as_str().unwrap_or("").contains("2.0"), "{h}");
    let d = c.request("textDocument/definition", at(&header, l, column(&htext, l, "ROUGHNESS_SCALE") + 1));
    assert_eq!(d["result"]["range"]["start"]["line"], line_of(&htext, "#define ROUGHNESS_SCALE"), "{d}");
    let d = c.request(
        "textDocument/definition",
        at(&lit, line_of(&text, "f32(NUM_LIGHTS)"), column(&text, line_of(&text, "f32(NUM_LIGHTS)"), "NUM_LIGHTS")),
    );
    assert_eq!(d["result"]["uri"], uri(&root.join("permutations.toml")), "{d}");

    let edited = text.replace("#if NUM_LIGHTS > 0", "#if ");
    c.change(&lit, 2, &edited);
    let l = line_of(&edited, "#if ");
    let r = c.request("textDocument/completion", at(&lit, l, 4));
    let labels: Vec<&str> = r["result"].as_array().into_iter().flatten().filter_map(|i| i["label"].as_str()).collect();
    assert!(
        labels.contains(&"NUM_LIGHTS") && labels.contains(&"ROUGHNESS_SCALE") && labels.contains(&"FEATURE_LEVEL"),
        "{labels:?}"
    );
    let edited = format!("#include \"\n{text}");
    c.change(&lit, 3, &edited);
    let r = c.request("textDocument/completion", at(&lit, 0, 10));
    let labels: Vec<&str> = r["result"].as_array().into_iter().flatten().filter_map(|i| i["label"].as_str()).collect();
    assert!(labels.contains(&"Common.ush") && labels.contains(&"/Engine/Common.ush"), "{labels:?}");

    let r = c.request("textDocument/documentSymbol", json!({ "textDocument": { "uri": uri(&header) } }));
    let names: Vec<&str> = r["result"].as_array().into_iter().flatten().filter_map(|i| i["name"].as_str()).collect();
    assert_eq!(names, ["Surface", "shade"], "{r}");
}

#[test]
fn hostile_input_gives_diagnostics_or_errors_and_never_ends_the_server() {
    let (_dir, root) = project();
    let mut c = Client::start();
    // Before initialize: an error response.
    let r = c.request("textDocument/hover", at(&root.join("shaders/Lit.usf"), 0, 0));
    assert!(r["error"].is_object(), "{r}");
    let r = c.request("initialize", json!({ "capabilities": {} }));
    assert!(r["result"].is_object(), "{r}");
    c.notify("initialized", json!({}));

    // Malformed JSON, then a message without a header: answered or skipped, not fatal.
    c.write_raw(b"Content-Length: 9\r\n\r\n{not json");
    c.write_raw(b"garbage line\r\n\r\n");
    c.write_raw(b"Content-Length: 4\r\n\r\n\xff\xfe\x00\x01");
    c.write_raw(b"Content-Length: 2\r\n\r\n[]");
    // A length no one could allocate: skipped (the input then ends inside it, in another test).
    c.write_raw(b"Content-Length: 300000000\r\n\r\n");
    c.write_raw(&vec![b' '; 300_000_000]);
    let r = c.request("no/suchRequest", json!({}));
    assert_eq!(r["error"]["code"], -32601, "{r}");
    let r = c.request("textDocument/hover", json!({ "textDocument": 7 }));
    assert!(r["result"].is_null() || r["error"].is_object(), "{r}");
    let r = c.request("kiln/setPermutation", json!({ "textDocument": { "uri": "http://x/y" }, "permutation": 3 }));
    assert!(r["error"].is_object(), "{r}");

    // A missing include.
    let lit = root.join("shaders/Lit.usf");
    c.open(&lit, "#include \"Missing.ush\"\n");
    let d = c.diagnostics(&uri(&lit), |p| !errors(p).is_empty());
    assert!(errors(&d)[0]["message"].as_str().unwrap_or("").contains("Missing.ush"), "{d}");

    // A file outside every root.
    let outside = root.join("outside.usf");
    c.open(&outside, "fn f() {}\n");
    let d = c.diagnostics(&uri(&outside), |p| p["diagnostics"].as_array().is_some_and(|d| !d.is_empty()));
    assert!(d["diagnostics"][0]["message"].as_str().unwrap_or("").contains("outside every include root"), "{d}");

    // A 10 MB file.
    let big = root.join("shaders/Big.ush");
    c.open(&big, &"// filler line\n".repeat(700_000));
    let d = c.diagnostics(&uri(&big), |p| p["diagnostics"].as_array().is_some_and(|d| !d.is_empty()));
    assert!(d["diagnostics"][0]["message"].as_str().unwrap_or("").contains("limit"), "{d}");

    // Garbage and deep nesting in a shader.
    c.change(&lit, 2, &"#if (".repeat(10_000));
    c.diagnostics(&uri(&lit), |p| p["version"] == 2 && !errors(p).is_empty());
    c.change(&lit, 3, &format!("{}\n", "(".repeat(100_000)));
    c.diagnostics(&uri(&lit), |p| p["version"] == 3);
    c.change(&lit, 4, "\u{0}\u{feff}#define A A A\nA\n#include \"/etc/passwd\"\n#include \"../../../x\"\n");
    c.diagnostics(&uri(&lit), |p| p["version"] == 4);

    // A broken toml, open and edited: a diagnostic on it and on the shader.
    let toml = root.join("permutations.toml");
    let ttext = std::fs::read_to_string(&toml).expect("read");
    c.open(&toml, &ttext);
    c.change(&toml, 2, "[compiler\ninclude = 3\n");
    c.diagnostics(&uri(&toml), |p| !errors(p).is_empty());
    c.change(&lit, 5, "fn f() {}\n");
    let d = c.diagnostics(&uri(&lit), |p| p["version"] == 5);
    assert!(!errors(&d).is_empty(), "a broken set is reported on the shader: {d}");
    c.change(&toml, 3, &ttext);
    c.change(&lit, 6, &std::fs::read_to_string(&lit).expect("read"));
    c.diagnostics(&uri(&lit), |p| p["version"] == 6 && errors(p).is_empty());

    // Positions past the end, a non-file URI, an unknown document.
    let r = c.request("textDocument/hover", at(&lit, 99_999, 99_999));
    assert!(r.get("result").is_some(), "{r}");
    let r = c.request(
        "textDocument/definition",
        json!({ "textDocument": { "uri": "untitled:1" }, "position": { "line": 0, "character": 0 } }),
    );
    assert!(r.get("result").is_some() || r.get("error").is_some(), "{r}");
    let r = c.request("kiln/permutations", json!({ "textDocument": { "uri": uri(&root.join("nowhere/x.usf")) } }));
    assert!(r.get("result").is_some() || r.get("error").is_some(), "{r}");

    let r = c.request("shutdown", Value::Null);
    assert!(r["result"].is_null() && r.get("error").is_none(), "{r}");
    c.notify("exit", Value::Null);
    assert_eq!(c.finish().code(), Some(0));
}

#[test]
fn the_end_of_stdin_ends_the_server() {
    let c = Client::start();
    assert_eq!(c.finish().code(), Some(0));
    let mut c = Client::initialized(json!({}));
    c.write_raw(b"Content-Length: 100\r\n\r\n{\"jsonrpc\"");
    assert_eq!(c.finish().code(), Some(0));
    // A length no one could allocate, then the end of input.
    let mut c = Client::initialized(json!({}));
    c.write_raw(b"Content-Length: 99999999999999\r\n\r\n{");
    assert_eq!(c.finish().code(), Some(0));
}

#[test]
fn neovim_shows_diagnostics_hover_and_definitions() {
    let found = Command::new("nvim").arg("--version").stdout(Stdio::null()).stderr(Stdio::null()).status();
    assert!(
        found.is_ok_and(|s| s.success()),
        "`nvim` is missing: install the Debian package `neovim` (apt-get install -y neovim) to run this test"
    );
    let (_dir, root) = project();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/lsp/nvim.lua");
    let out_file = root.join("nvim-results.json");
    let out = Command::new("nvim")
        .args(["--headless", "-u", "NONE", "-i", "NONE", "-n", "-c"])
        .arg(format!("luafile {}", script.display()))
        .env("KILN", KILN)
        .env("KILN_LSP_ROOT", &root)
        .env("KILN_LSP_OUT", &out_file)
        .env("HOME", &root)
        .stdin(Stdio::null())
        .output()
        .expect("run nvim");
    let results = std::fs::read_to_string(&out_file).unwrap_or_else(|_| {
        panic!(
            "nvim wrote no results (status {:?}):\n{}\n{}",
            out.status,
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        )
    });
    let r: Value = serde_json::from_str(&results).expect("results are JSON");
    assert_eq!(r["error"], Value::Null, "{r:#}");
    let htext = std::fs::read_to_string(root.join("shaders/Common.ush")).expect("read");
    assert_eq!(r["header_error_line"], line_of(&htext, "oops"), "{r:#}");
    assert!(r["hover"].as_str().unwrap_or("").contains("`NUM_LIGHTS` = `0`"), "{r:#}");
    assert!(r["include_definition"].as_str().unwrap_or("").ends_with("shaders/Common.ush"), "{r:#}");
    assert!(r["function_definition"].as_str().unwrap_or("").ends_with("shaders/Common.ush"), "{r:#}");
    assert_eq!(r["function_definition_line"], line_of(&htext, "fn shade"), "{r:#}");
    assert!(r["inactive"].as_u64().unwrap_or(0) > 0, "{r:#}");
}

/// `cargo test -p kiln --test lsp --release -- --ignored latency --nocapture`: 50 edits to
/// a 265-line shader of the bundled set (read by five shaders); prints the median and p95 time from each `didChange` to
/// its `publishDiagnostics`.
#[test]
#[ignore]
fn latency() {
    // `KILN_LSP_LATENCY_FILE=shader_src/Private/Common.ush` measures a header every shader reads.
    let file = std::env::var("KILN_LSP_LATENCY_FILE")
        .unwrap_or_else(|_| "shader_src/Private/Desktop/VolumetricFog.usf".into());
    let shader = repo().join(file).canonicalize().expect("shader");
    let text = std::fs::read_to_string(&shader).expect("read");
    let mut c = Client::initialized(json!({}));
    c.open(&shader, &text);
    c.diagnostics(&uri(&shader), |p| p["version"] == 1);
    let mut times = Vec::new();
    for i in 0..50 {
        let version = i + 2;
        // Alternately valid and broken, so errors come and go.
        let edited = if i % 2 == 0 {
            format!("{text}\nconst EDIT_{i}: f32 = 1.0;\n")
        } else {
            format!("{text}\nconst EDIT_{i}: f32 = nope;\n")
        };
        let t = Instant::now();
        c.change(&shader, version, &edited);
        c.diagnostics(&uri(&shader), |p| p["version"] == version);
        times.push(t.elapsed());
        std::thread::sleep(Duration::from_millis(30));
    }
    times.sort();
    let ms = |d: Duration| d.as_secs_f64() * 1000.0;
    println!(
        "kiln lsp: diagnostics after an edit to {} ({} lines), 50 edits: median {:.1} ms, p95 {:.1} ms, max {:.1} ms",
        shader.file_name().map(|f| f.to_string_lossy().into_owned()).unwrap_or_default(),
        text.lines().count(),
        ms(times[24]),
        ms(times[47]),
        ms(times[49])
    );
    let status = std::fs::read_to_string(format!("/proc/{}/status", c.child.id())).unwrap_or_default();
    let peak = status.lines().find(|l| l.starts_with("VmHWM")).unwrap_or("VmHWM: unknown");
    println!("kiln lsp: peak memory of the server on the bundled set: {}", peak.trim_start_matches("VmHWM:").trim());
}

/// `cargo test -p kiln --test lsp --release -- --ignored memory --nocapture`: the test
/// project with two more dimensions (100,100 kept permutations); opens the shader, lets the
/// background check run through the domain, lists the permutations and hovers a dimension
/// (each walks the whole domain), and prints the server's peak memory.
#[test]
#[ignore]
fn memory_100k() {
    let (_dir, root) = project();
    let toml = root.join("permutations.toml");
    let t = std::fs::read_to_string(&toml).expect("read").replace(
        "NUM_LIGHTS = [0, 1, 2, 4] }",
        "NUM_LIGHTS = [0, 1, 2, 4], A = { range = [0, 142] }, B = { range = [0, 99] } }",
    );
    std::fs::write(&toml, t).expect("write");
    let lit = root.join("shaders/Lit.usf");
    let text = std::fs::read_to_string(&lit).expect("read");
    let mut c = Client::initialized(json!({}));
    let start = Instant::now();
    c.open(
        &lit,
        &text.replace(
            "    return vec4<f32>(lit, 1.0);",
            "#if A == 7\n    let bad: i32 = 1.5;\n#endif\n    return vec4<f32>(lit, 1.0);",
        ),
    );
    let d = c.diagnostics(&uri(&lit), |p| {
        errors(p).iter().any(|e| e["message"].as_str().unwrap_or("").contains("permutations of"))
    });
    println!(
        "kiln lsp: 100,100 permutations checked in {:.1} s: {}",
        start.elapsed().as_secs_f64(),
        errors(&d)[0]["message"]
    );
    let r = c.request("kiln/permutations", json!({ "textDocument": { "uri": uri(&lit) } }));
    assert_eq!(r["result"]["permutations"].as_array().map(Vec::len), Some(100_100));
    let l = line_of(&text, "f32(NUM_LIGHTS)");
    let h = c.request("textDocument/hover", at(&lit, l, column(&text, l, "NUM_LIGHTS") + 1));
    assert!(h["result"]["contents"]["value"].as_str().unwrap_or("").contains("28600 kept"), "{h}");
    let status = std::fs::read_to_string(format!("/proc/{}/status", c.child.id())).unwrap_or_default();
    let peak = status.lines().find(|l| l.starts_with("VmHWM")).unwrap_or("VmHWM: unknown");
    println!("kiln lsp: peak memory on 100,100 permutations: {}", peak.trim_start_matches("VmHWM:").trim());
}
