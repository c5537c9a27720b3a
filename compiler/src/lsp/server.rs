//! The server loop: messages in on stdin (read on their own thread, malformed ones answered
//! and skipped), answers and notifications out on stdout, the background domain check on a
//! worker thread whose results come back through the same queue.

use std::collections::{HashMap, HashSet};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{channel, Receiver, Sender};
use std::sync::Arc;

use lsp_server::{ErrorCode, Message, Notification, Request, Response};
use lsp_types::notification::Notification as _;
use lsp_types::{Diagnostic, DiagnosticSeverity, DiagnosticTag, PublishDiagnosticsParams, Url};
use serde_json::{json, Value};

use super::check::{self, FileDiag};
use super::text::{line_start, path_uri, uri_path};
use super::workspace::Active;
use super::workspace::{cache_with, find_config, resolve_choice, Doc, Overlays, Workspace, MAX_DOC_BYTES};
use crate::permute::{Config, Permutation};
use crate::preprocess::{self, SourceCache};

/// What the loop waits for.
pub(super) enum Event {
    Msg(Message),
    /// A message that was not JSON-RPC: answered with a parse error.
    Malformed(String),
    /// stdin ended (the client exited or crashed).
    Eof,
    /// One shader's domain, checked for generation `gen`.
    Domain {
        gen: u64,
        config_path: PathBuf,
        shader: usize,
        domain: check::Domain,
    },
}

/// Work for the background thread: the shaders of each set still to check.
struct Job {
    gen: u64,
    overlays: Overlays,
    sets: Vec<(PathBuf, Arc<Config>, Vec<usize>)>,
}

/// Serves the Language Server Protocol on stdin and stdout until `exit` or the end of stdin.
pub fn run_stdio() -> Result<(), String> {
    // The preprocessor and naga recurse as deep as the input nests: a big stack, once.
    let worker = std::thread::Builder::new().name("kiln-lsp".into()).stack_size(preprocess::STACK_BYTES).spawn(|| {
        preprocess::big_stack_thread();
        serve()
    });
    match worker {
        Ok(h) => h.join().unwrap_or_else(|_| Err("the server panicked".into())),
        Err(e) => Err(format!("cannot start the server thread: {e}")),
    }
}

fn serve() -> Result<(), String> {
    let (tx, rx) = channel::<Event>();
    let reader_tx = tx.clone();
    std::thread::Builder::new()
        .name("kiln-lsp-stdin".into())
        .spawn(move || read_stdin(reader_tx))
        .map_err(|e| format!("cannot start the reader: {e}"))?;
    let gen = Arc::new(AtomicU64::new(0));
    let (job_tx, job_rx) = channel::<Job>();
    let worker_gen = gen.clone();
    std::thread::Builder::new()
        .name("kiln-lsp-check".into())
        .stack_size(preprocess::STACK_BYTES)
        .spawn(move || background(job_rx, tx, worker_gen))
        .map_err(|e| format!("cannot start the checker: {e}"))?;
    let mut server = Server::new(gen, job_tx);
    server.run(rx);
    if server.exit_early {
        return Err("the client sent `exit` before `shutdown`".into());
    }
    Ok(())
}

/// Largest message body read; a larger one is skipped unread (lsp-server's own reader
/// would allocate whatever a `Content-Length` claims).
const MAX_MESSAGE_BYTES: usize = 256 << 20;

fn read_stdin(tx: Sender<Event>) {
    let stdin = std::io::stdin();
    let mut input = stdin.lock();
    loop {
        let event = match read_message(&mut input) {
            Ok(Some(body)) => match serde_json::from_slice::<Message>(&body) {
                Ok(m) => Event::Msg(m),
                Err(e) => Event::Malformed(format!("not a JSON-RPC message: {e}")),
            },
            Ok(None) => Event::Eof,
            Err(e) if e.kind() == std::io::ErrorKind::InvalidData => Event::Malformed(e.to_string()),
            Err(_) => Event::Eof,
        };
        let end = matches!(event, Event::Eof);
        if tx.send(event).is_err() || end {
            return;
        }
    }
}

/// One message body of the base protocol (`Content-Length: N\r\n\r\n` then N bytes);
/// `None` at the end of input. A bad header or an oversized body is `InvalidData`, the
/// input then positioned after it.
fn read_message(input: &mut impl std::io::BufRead) -> std::io::Result<Option<Vec<u8>>> {
    use std::io::{BufRead, Error, ErrorKind, Read};
    let mut size: Option<usize> = None;
    let mut bad_header = None;
    loop {
        let mut line = Vec::new();
        if input.by_ref().take(64 << 10).read_until(b'\n', &mut line)? == 0 {
            return Ok(None);
        }
        let text = String::from_utf8_lossy(&line);
        let text = text.trim_end_matches(['\r', '\n']);
        if text.is_empty() {
            if size.is_some() || bad_header.is_some() {
                break;
            }
            continue;
        }
        match text.split_once(':') {
            Some((name, value)) if name.trim().eq_ignore_ascii_case("content-length") => {
                match value.trim().parse::<usize>() {
                    Ok(n) => size = Some(n),
                    Err(_) => bad_header = Some(format!("bad Content-Length: {value:?}")),
                }
            }
            Some(_) => {}
            None => bad_header = Some(format!("malformed header: {text:?}")),
        }
    }
    let Some(size) = size else {
        return Err(Error::new(ErrorKind::InvalidData, bad_header.unwrap_or_else(|| "no Content-Length".into())));
    };
    if size > MAX_MESSAGE_BYTES {
        let skipped = std::io::copy(&mut input.by_ref().take(size as u64), &mut std::io::sink())?;
        if skipped < size as u64 {
            return Ok(None);
        }
        return Err(Error::new(ErrorKind::InvalidData, format!("a message of {size} bytes is over the limit")));
    }
    let mut body = vec![0; size];
    match input.read_exact(&mut body) {
        Ok(()) => Ok(Some(body)),
        Err(e) if e.kind() == ErrorKind::UnexpectedEof => Ok(None),
        Err(e) => Err(e),
    }
}

/// The background checker: always the newest job; a newer generation cancels the one running.
fn background(jobs: Receiver<Job>, tx: Sender<Event>, current: Arc<AtomicU64>) {
    preprocess::big_stack_thread();
    while let Ok(mut job) = jobs.recv() {
        while let Ok(newer) = jobs.try_recv() {
            job = newer;
        }
        let cancelled = || current.load(Ordering::Relaxed) != job.gen;
        'sets: for (config_path, config, shaders) in &job.sets {
            for &i in shaders {
                let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                    check::check_domain(config, i, &job.overlays, &cancelled)
                }));
                match result {
                    Ok(Some(domain)) => {
                        let e = Event::Domain { gen: job.gen, config_path: config_path.clone(), shader: i, domain };
                        if tx.send(e).is_err() {
                            return;
                        }
                    }
                    Ok(None) => break 'sets,
                    Err(_) => continue,
                }
            }
        }
    }
}

pub(super) struct Server {
    pub docs: HashMap<PathBuf, Doc>,
    pub workspaces: Vec<Workspace>,
    /// `initializationOptions.config`.
    init_config: Option<PathBuf>,
    /// `initializationOptions.permutation` or the last `workspace/didChangeConfiguration`'s.
    default_choice: Option<Value>,
    /// The shader a file's features and inactive regions follow (set by `kiln/setPermutation`).
    pub focus: HashMap<PathBuf, usize>,
    /// Files whose last published diagnostics were not empty.
    published: HashSet<PathBuf>,
    /// What was last published for each file.
    last_sent: HashMap<PathBuf, blake3::Hash>,
    gen: Arc<AtomicU64>,
    jobs: Sender<Job>,
    initialized: bool,
    shutdown: bool,
    /// `exit` came before `shutdown` (the exit status is then 1, as LSP says).
    exit_early: bool,
}

impl Server {
    fn new(gen: Arc<AtomicU64>, jobs: Sender<Job>) -> Server {
        Server {
            docs: HashMap::new(),
            workspaces: Vec::new(),
            init_config: None,
            default_choice: None,
            focus: HashMap::new(),
            published: HashSet::new(),
            last_sent: HashMap::new(),
            gen,
            jobs,
            initialized: false,
            shutdown: false,
            exit_early: false,
        }
    }

    fn run(&mut self, rx: Receiver<Event>) {
        while let Ok(event) = rx.recv() {
            let keep_going = match event {
                Event::Eof => false,
                Event::Malformed(e) => {
                    let raw = json!({"jsonrpc": "2.0", "id": null, "error": {"code": -32700, "message": e}});
                    let body = raw.to_string();
                    write_raw(&format!("Content-Length: {}\r\n\r\n{body}", body.len()))
                }
                Event::Domain { gen, config_path, shader, domain } => {
                    if gen == self.gen.load(Ordering::Relaxed) {
                        self.domain_done(&config_path, shader, domain);
                    }
                    true
                }
                Event::Msg(m) => {
                    let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| self.message(m.clone())));
                    match outcome {
                        Ok(go) => go,
                        Err(_) => {
                            if let Message::Request(r) = m {
                                send(Response::new_err(r.id, ErrorCode::InternalError as i32, "internal error".into()));
                            }
                            true
                        }
                    }
                }
            };
            if !keep_going {
                break;
            }
        }
        // Stop the background check.
        self.gen.fetch_add(1, Ordering::Relaxed);
    }

    /// Handles one message; `false` ends the server (`exit`, or stdout gone).
    fn message(&mut self, m: Message) -> bool {
        match m {
            Message::Request(r) => {
                let id = r.id.clone();
                let resp = match self.request(r) {
                    Ok(v) => Response::new_ok(id, v),
                    Err((code, msg)) => Response::new_err(id, code, msg),
                };
                send(Message::Response(resp))
            }
            Message::Notification(n) => {
                if n.method == "exit" {
                    self.exit_early = !self.shutdown;
                    return false;
                }
                if self.initialized {
                    self.notification(n);
                }
                true
            }
            Message::Response(_) => true,
        }
    }

    fn request(&mut self, r: Request) -> Result<Value, (i32, String)> {
        if r.method == "initialize" {
            return Ok(self.initialize(&r.params));
        }
        if !self.initialized {
            return Err((ErrorCode::ServerNotInitialized as i32, "the server is not initialized".into()));
        }
        if self.shutdown {
            return Err((ErrorCode::InvalidRequest as i32, "the server is shut down".into()));
        }
        let p = &r.params;
        match r.method.as_str() {
            "shutdown" => {
                self.shutdown = true;
                self.gen.fetch_add(1, Ordering::Relaxed);
                Ok(Value::Null)
            }
            "kiln/permutations" => self.permutations(p),
            "kiln/setPermutation" => self.set_permutation(p),
            "textDocument/hover" => Ok(self.feature(p, super::features::hover)),
            "textDocument/definition" => Ok(self.feature(p, super::features::definition)),
            "textDocument/completion" => Ok(self.feature(p, super::features::completion)),
            "textDocument/documentSymbol" => Ok(self.feature(p, super::features::symbols)),
            "textDocument/semanticTokens/full" => Ok(self.feature(p, super::features::semantic_tokens)),
            m => Err((ErrorCode::MethodNotFound as i32, format!("unknown request `{m}`"))),
        }
    }

    fn initialize(&mut self, params: &Value) -> Value {
        let opts = &params["initializationOptions"];
        if let Some(c) = opts["config"].as_str() {
            let p = PathBuf::from(c);
            self.init_config = Some(p.canonicalize().unwrap_or(p));
        }
        if !opts["permutation"].is_null() {
            self.default_choice = Some(opts["permutation"].clone());
        }
        self.initialized = true;
        json!({
            "capabilities": {
                "textDocumentSync": { "openClose": true, "change": 1, "save": { "includeText": false } },
                "hoverProvider": true,
                "definitionProvider": true,
                "completionProvider": { "triggerCharacters": ["\"", "/", "(", " ", "<"] },
                "documentSymbolProvider": true,
                "semanticTokensProvider": {
                    "legend": { "tokenTypes": ["comment"], "tokenModifiers": [] },
                    "full": true
                }
            },
            "serverInfo": { "name": "kiln", "version": crate::VERSION }
        })
    }

    fn notification(&mut self, n: Notification) {
        let p = &n.params;
        let uri = p["textDocument"]["uri"].as_str().and_then(|u| Url::parse(u).ok());
        match n.method.as_str() {
            "textDocument/didOpen" | "textDocument/didChange" => {
                let Some(uri) = uri else { return };
                let Some(path) = uri_path(&uri) else { return };
                let version = p["textDocument"]["version"].as_i64().unwrap_or(0) as i32;
                let text = if n.method == "textDocument/didOpen" {
                    p["textDocument"]["text"].as_str().map(str::to_string)
                } else {
                    let old = self.docs.get(&path).map_or(String::new(), |d| d.text.to_string());
                    p["contentChanges"].as_array().map(|changes| apply_changes(old, changes))
                };
                let Some(text) = text else { return };
                if n.method == "textDocument/didOpen" {
                    // Always answered, even with what was published before it was opened.
                    self.last_sent.remove(&path);
                }
                self.docs.insert(path.clone(), Doc { uri, version, text: text.into() });
                self.changed(&path);
            }
            "textDocument/didClose" => {
                let Some(path) = uri.as_ref().and_then(uri_path) else { return };
                self.docs.remove(&path);
                self.changed(&path);
            }
            "textDocument/didSave" => {
                if let Some(path) = uri.as_ref().and_then(uri_path) {
                    self.changed(&path);
                }
            }
            "workspace/didChangeConfiguration" => {
                let s = &p["settings"];
                let choice = [&s["permutation"], &s["kiln"]["permutation"]].into_iter().find(|v| !v.is_null());
                if let Some(c) = choice {
                    self.default_choice = Some(c.clone());
                    for w in 0..self.workspaces.len() {
                        self.workspaces[w].chosen.clear();
                        self.apply_default(w);
                        self.refresh_all(w);
                    }
                }
            }
            _ => {}
        }
    }

    /// The set that serves `path`: `initializationOptions.config`, else the nearest
    /// `permutations.toml` above it (loaded on first use).
    fn workspace_for(&mut self, path: &Path) -> Option<usize> {
        let config = match &self.init_config {
            Some(c) => c.clone(),
            None => find_config(path)?,
        };
        if let Some(i) = self.workspaces.iter().position(|w| w.config_path == config) {
            return Some(i);
        }
        self.workspaces.push(Workspace::load(&config, &self.docs));
        let w = self.workspaces.len() - 1;
        self.apply_default(w);
        Some(w)
    }

    /// Chooses the default permutation (if any) for every shader it names.
    fn apply_default(&mut self, w: usize) {
        let Some(choice) = self.default_choice.clone() else { return };
        let ws = &mut self.workspaces[w];
        let Ok(config) = ws.config.clone() else { return };
        for i in 0..config.shaders.len() {
            if let Ok(Some(key)) = resolve_choice(&config, i, &choice) {
                ws.chosen.insert(i, key);
            }
        }
    }

    /// A source cache over the open buffers for set `w`'s file names.
    fn shared_cache(&self, w: usize, overlays: &Overlays) -> Arc<SourceCache> {
        let base = self.workspaces[w].config_path.parent().unwrap_or(Path::new("/")).to_path_buf();
        Arc::new(cache_with(overlays, &base))
    }

    /// The open buffers, for the preprocessor.
    fn overlays(&self) -> Overlays {
        Arc::new(self.docs.iter().map(|(p, d)| (p.clone(), d.text.clone())).collect())
    }

    /// Re-checks the active permutation of each of `shaders` and queues their domains.
    fn recheck(&mut self, w: usize, shaders: &[usize], cache: &Arc<SourceCache>) {
        let ws = &mut self.workspaces[w];
        let Ok(config) = ws.config.clone() else { return };
        let mut jobs = Vec::new();
        for &i in shaders {
            match ws.active_key(i) {
                Some((level, values)) => jobs.push((i, level, values)),
                None => {
                    ws.active.remove(&i);
                }
            }
        }
        for (i, active) in check_all(&config, &jobs, cache) {
            ws.active.insert(i, active);
            ws.domain.remove(&i);
            ws.pending.insert(i);
        }
    }

    /// After `path` changed (opened, edited, closed, saved): check the active permutation of
    /// every shader reading it, publish, and queue the domains in the background.
    fn changed(&mut self, path: &Path) {
        if let Some(w) = self.config_workspace(path) {
            let reloaded = Workspace::load(path, &self.docs);
            self.workspaces[w] = reloaded;
            self.apply_default(w);
            self.refresh_all(w);
            self.publish_one(path, config_problem(&self.workspaces[w]));
            return;
        }
        let problem = self.doc_problem(path);
        let Some(w) = problem.as_ref().map_or_else(|| self.workspace_for(path), |_| None) else {
            self.publish_one(path, problem.into_iter().collect());
            return;
        };
        self.gen.fetch_add(1, Ordering::Relaxed);
        let overlays = self.overlays();
        let cache = self.shared_cache(w, &overlays);
        if self.workspaces[w].active.is_empty() {
            self.refresh_all(w);
            return;
        }
        let before: Vec<usize> = self.workspaces[w].readers(path);
        let mut touched: HashSet<PathBuf> = HashSet::from([path.to_path_buf()]);
        let files_of = |ws: &Workspace, i: &usize| ws.active.get(i).map(|a| a.files.clone()).unwrap_or_default();
        touched.extend(before.iter().flat_map(|i| files_of(&self.workspaces[w], i)));
        self.recheck(w, &before, &cache);
        self.workspaces[w].recent = before.clone();
        touched.extend(before.iter().flat_map(|i| files_of(&self.workspaces[w], i)));
        self.publish(w, touched);
        self.schedule(overlays);
    }

    /// The set whose `permutations.toml` is `path` (loaded on first use), if it is one.
    fn config_workspace(&mut self, path: &Path) -> Option<usize> {
        if let Some(w) = self.workspaces.iter().position(|w| w.config_path == path) {
            return Some(w);
        }
        let is_config = match &self.init_config {
            Some(c) => c == path,
            None => path.file_name().is_some_and(|n| n == "permutations.toml"),
        };
        if !is_config {
            return None;
        }
        self.workspaces.push(Workspace::load(path, &self.docs));
        Some(self.workspaces.len() - 1)
    }

    /// Why `path` cannot be checked (too large, no set, a broken set, outside every root).
    fn doc_problem(&mut self, path: &Path) -> Option<FileDiag> {
        let warn = |severity, message: String| FileDiag {
            path: path.to_path_buf(),
            range: line_start(0),
            severity,
            message,
            context: String::new(),
        };
        if self.docs.get(path).is_some_and(|d| d.text.len() > MAX_DOC_BYTES) {
            let n = self.docs[path].text.len();
            return Some(warn(
                DiagnosticSeverity::WARNING,
                format!("not checked: {n} bytes is over the {MAX_DOC_BYTES}-byte limit of kiln lsp"),
            ));
        }
        let Some(w) = self.workspace_for(path) else {
            return Some(warn(
                DiagnosticSeverity::WARNING,
                "no permutations.toml in this folder or above: not checked".into(),
            ));
        };
        let ws = &self.workspaces[w];
        if let Err(e) = &ws.config {
            let first = e.lines().next().unwrap_or("").to_string();
            return Some(warn(
                DiagnosticSeverity::ERROR,
                format!("{} does not load: {first}", ws.config_path.display()),
            ));
        }
        if !ws.serves(path) {
            return Some(warn(
                DiagnosticSeverity::WARNING,
                format!("outside every include root of {}: not checked", ws.config_path.display()),
            ));
        }
        None
    }

    /// Checks every shader's active permutation of set `w` and publishes every file.
    fn refresh_all(&mut self, w: usize) {
        self.gen.fetch_add(1, Ordering::Relaxed);
        let overlays = self.overlays();
        let cache = self.shared_cache(w, &overlays);
        let n = self.workspaces[w].config.as_ref().map_or(0, |c| c.shaders.len());
        self.workspaces[w].active.clear();
        self.workspaces[w].domain.clear();
        let all: Vec<usize> = (0..n).collect();
        self.recheck(w, &all, &cache);
        let mut touched: HashSet<PathBuf> = self.workspaces[w].active.values().flat_map(|a| a.files.clone()).collect();
        touched.extend(self.docs.keys().cloned());
        touched.extend(self.published.iter().cloned());
        self.publish(w, touched);
        self.schedule(overlays);
    }

    /// Sends the background checker every pending shader.
    fn schedule(&mut self, overlays: Overlays) {
        let gen = self.gen.fetch_add(1, Ordering::Relaxed) + 1;
        let sets = self
            .workspaces
            .iter()
            .filter_map(|w| {
                let c = w.config.as_ref().ok()?.clone();
                let mut pending: Vec<usize> = w.pending.iter().copied().collect();
                // The shaders of the last edit first: their counts are the ones being looked at.
                pending.sort_unstable_by_key(|i| (!w.recent.contains(i), *i));
                (!pending.is_empty()).then(|| (w.config_path.clone(), c, pending))
            })
            .collect();
        let _ = self.jobs.send(Job { gen, overlays, sets });
    }

    fn domain_done(&mut self, config_path: &Path, shader: usize, domain: check::Domain) {
        let Some(w) = self.workspaces.iter().position(|w| w.config_path == config_path) else { return };
        let ws = &mut self.workspaces[w];
        ws.pending.remove(&shader);
        let mut touched: HashSet<PathBuf> = domain.diags.iter().map(|d| d.path.clone()).collect();
        if let Some(old) = ws.domain.insert(shader, domain.diags) {
            touched.extend(old.into_iter().map(|d| d.path));
        }
        ws.domain_files.insert(shader, domain.files);
        touched.extend(ws.active.get(&shader).map(|a| a.files.clone()).unwrap_or_default());
        self.publish(w, touched);
    }

    /// The shader a file's inactive regions and features follow.
    pub fn focus_of(&self, w: usize, path: &Path) -> Option<usize> {
        let readers = self.workspaces[w].readers(path);
        match self.focus.get(path) {
            Some(i) if readers.contains(i) => Some(*i),
            _ => readers.first().copied(),
        }
    }

    /// Everything known about `path` in set `w`, as it would be published.
    fn diagnostics_of(&self, w: usize, path: &Path) -> Vec<Diagnostic> {
        let ws = &self.workspaces[w];
        if let Err(e) = &ws.config {
            let first = e.lines().next().unwrap_or("").to_string();
            let d = FileDiag {
                path: path.to_path_buf(),
                range: line_start(0),
                severity: DiagnosticSeverity::ERROR,
                message: format!("{} does not load: {first}", ws.config_path.display()),
                context: String::new(),
            };
            return if path == ws.config_path { Vec::new() } else { vec![to_lsp(d)] };
        }
        let mut list: Vec<FileDiag> = Vec::new();
        let mut shaders: Vec<&usize> = ws.active.keys().collect();
        shaders.sort_unstable();
        for i in shaders {
            let a = &ws.active[i];
            if let Some(dom) = ws.domain.get(i) {
                list.extend(dom.iter().filter(|d| d.path == path).cloned());
            }
            for d in a.diags.iter().filter(|d| d.path == path) {
                if !list.iter().any(|x| x.same(d)) {
                    list.push(d.clone());
                }
            }
        }
        let mut out: Vec<Diagnostic> = list.into_iter().map(to_lsp).collect();
        // Inactive regions only for open documents: they are for reading, not a problem list.
        let open = self.docs.contains_key(path);
        if let Some(a) = self.focus_of(w, path).and_then(|i| ws.active.get(&i)).filter(|_| open) {
            for (_, lines) in a.skipped.iter().filter(|(p, _)| p == path) {
                out.push(Diagnostic {
                    range: lsp_types::Range {
                        start: lsp_types::Position { line: lines.start - 1, character: 0 },
                        end: lsp_types::Position { line: lines.end - 1, character: 0 },
                    },
                    severity: Some(DiagnosticSeverity::HINT),
                    source: Some("kiln".into()),
                    message: format!("inactive in `{}`", a.name),
                    tags: Some(vec![DiagnosticTag::UNNECESSARY]),
                    ..Diagnostic::default()
                });
            }
        }
        out
    }

    /// Publishes the diagnostics of each of `paths` that is open, has diagnostics, or had some.
    fn publish(&mut self, w: usize, paths: HashSet<PathBuf>) {
        let mut paths: Vec<PathBuf> = paths.into_iter().collect();
        paths.sort();
        for path in paths {
            let ws = &self.workspaces[w];
            let belongs = match &ws.config {
                Ok(_) => ws.serves(&path),
                Err(_) => {
                    path != ws.config_path
                        && (self.init_config.is_some() || find_config(&path).as_ref() == Some(&ws.config_path))
                }
            };
            // Files of other sets, and this set's files it cannot check, have their own words.
            if !belongs && self.docs.contains_key(&path) {
                continue;
            }
            let diags = self.diagnostics_of(w, &path);
            self.send_diagnostics(&path, diags);
        }
    }

    /// Publishes one problem (or nothing) for a file the sets do not serve.
    fn publish_one(&mut self, path: &Path, problems: Vec<FileDiag>) {
        let diags = problems.into_iter().map(to_lsp).collect();
        self.send_diagnostics(path, diags);
    }

    fn send_diagnostics(&mut self, path: &Path, diagnostics: Vec<Diagnostic>) {
        let doc = self.docs.get(path);
        if diagnostics.is_empty() && doc.is_none() && !self.published.contains(path) {
            return;
        }
        let Some(uri) = doc.map(|d| d.uri.clone()).or_else(|| path_uri(path)) else { return };
        if diagnostics.is_empty() {
            self.published.remove(path);
        } else {
            self.published.insert(path.to_path_buf());
        }
        let params = PublishDiagnosticsParams { uri, diagnostics, version: doc.map(|d| d.version) };
        // The same list for the same version again says nothing new (the background check
        // of each shader reading a common header would otherwise repeat it).
        let fingerprint = blake3::hash(serde_json::to_string(&params).unwrap_or_default().as_bytes());
        if self.last_sent.insert(path.to_path_buf(), fingerprint) == Some(fingerprint) {
            return;
        }
        send(Message::Notification(Notification::new(
            lsp_types::notification::PublishDiagnostics::METHOD.into(),
            params,
        )));
    }

    /// `kiln/permutations`.
    fn permutations(&mut self, p: &Value) -> Result<Value, (i32, String)> {
        let (w, path) = self.target(p)?;
        let ws = &self.workspaces[w];
        let Ok(config) = &ws.config else { return Err(invalid("the permutation set does not load")) };
        let focus = self.focus_of(w, &path);
        let overlays = self.overlays();
        let mut names = Vec::new();
        for i in ws.readers(&path) {
            super::features::reading_permutations(config, i, &path, &overlays, &mut names);
        }
        let active = focus.and_then(|i| ws.active.get(&i)).map(|a| a.name.clone());
        Ok(json!({ "permutations": names, "active": active }))
    }

    /// `kiln/setPermutation`.
    fn set_permutation(&mut self, p: &Value) -> Result<Value, (i32, String)> {
        let (w, path) = self.target(p)?;
        let Ok(config) = self.workspaces[w].config.clone() else {
            return Err(invalid("the permutation set does not load"));
        };
        let (choice, shaders): (Value, Vec<usize>) = if let Some(name) = p["permutation"].as_str() {
            let i = config.shaders.iter().position(|s| name.starts_with(&format!("{}@", s.name)));
            let i = i.ok_or_else(|| invalid(&format!("unknown permutation `{name}`")))?;
            (Value::String(name.into()), vec![i])
        } else if p["values"].is_object() {
            (p["values"].clone(), self.focus_of(w, &path).into_iter().collect())
        } else {
            return Err(invalid("expected `permutation` (a canonical name) or `values`"));
        };
        let i = *shaders.first().ok_or_else(|| invalid("no shader reads this file"))?;
        let key = match resolve_choice(&config, i, &choice) {
            Ok(Some(k)) => k,
            Ok(None) => return Err(invalid("these values name no dimension of the shader")),
            Err(e) => return Err(invalid(&e)),
        };
        self.workspaces[w].chosen.insert(i, key);
        self.focus.insert(path.clone(), i);
        self.gen.fetch_add(1, Ordering::Relaxed);
        let overlays = self.overlays();
        let cache = self.shared_cache(w, &overlays);
        let mut touched: HashSet<PathBuf> = HashSet::from([path]);
        touched.extend(self.workspaces[w].active.get(&i).map(|a| a.files.clone()).unwrap_or_default());
        self.recheck(w, &[i], &cache);
        self.workspaces[w].recent = vec![i];
        touched.extend(self.workspaces[w].active.get(&i).map(|a| a.files.clone()).unwrap_or_default());
        touched.extend(self.published.iter().cloned());
        self.publish(w, touched);
        self.schedule(overlays);
        let name = self.workspaces[w].active.get(&i).map(|a| a.name.clone());
        Ok(json!({ "active": name }))
    }

    /// The set and path of a request's `textDocument`, its active results computed.
    fn target(&mut self, p: &Value) -> Result<(usize, PathBuf), (i32, String)> {
        let uri = p["textDocument"]["uri"].as_str().and_then(|u| Url::parse(u).ok());
        let path = uri.as_ref().and_then(uri_path).ok_or_else(|| invalid("expected textDocument.uri, a file: URI"))?;
        let w = self.workspace_for(&path).ok_or_else(|| invalid("no permutations.toml serves this file"))?;
        if self.workspaces[w].active.is_empty() && self.workspaces[w].config.is_ok() {
            self.refresh_all(w);
        }
        Ok((w, path))
    }

    /// Runs a feature on the file of a request with its focus shader's active permutation.
    fn feature(&mut self, p: &Value, f: fn(&super::features::Ctx<'_>, &Value) -> Value) -> Value {
        let Ok((w, path)) = self.target(p) else { return Value::Null };
        let text: Arc<str> = match self.docs.get(&path) {
            Some(d) => d.text.clone(),
            None => match std::fs::read_to_string(&path) {
                Ok(t) => t.into(),
                Err(_) => return Value::Null,
            },
        };
        let ws = &self.workspaces[w];
        let Ok(config) = &ws.config else { return Value::Null };
        let shader = self.focus_of(w, &path);
        let active = shader.and_then(|i| ws.active.get(&i));
        let ctx = super::features::Ctx { config, shader, active, path: &path, text: &text };
        f(&ctx, p)
    }
}

/// A document's text after `contentChanges`: whole texts (the full sync the server asks
/// for) or, from a client that sends them anyway, ranged edits.
fn apply_changes(mut text: String, changes: &[Value]) -> String {
    for c in changes {
        let Some(new) = c["text"].as_str() else { continue };
        match serde_json::from_value::<lsp_types::Range>(c["range"].clone()) {
            Ok(r) => {
                let start = super::text::offset_of(&text, r.start);
                let end = super::text::offset_of(&text, r.end).max(start);
                text.replace_range(start..end, new);
            }
            Err(_) => text = new.to_string(),
        }
    }
    text
}

/// [`check::check_active`] of each (shader, level, values); a check that panics is left out.
/// One thread: measured on two busy cores, spreading a header's readers over two threads
/// was no faster, and the background check already has the other core.
fn check_all(config: &Config, jobs: &[(usize, usize, Vec<i64>)], cache: &Arc<SourceCache>) -> Vec<(usize, Active)> {
    let one = |(i, level, values): &(usize, usize, Vec<i64>)| {
        let p = Permutation::new(config.shaders.get(*i)?, config.levels.get(*level)?, values.clone());
        let checked =
            std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| check::check_active(config, &p, *level, cache)));
        Some((*i, checked.ok()?))
    };
    jobs.iter().filter_map(one).collect()
}

fn invalid(message: &str) -> (i32, String) {
    (ErrorCode::InvalidParams as i32, message.to_string())
}

/// A config that does not load, as diagnostics on its own file.
fn config_problem(ws: &Workspace) -> Vec<FileDiag> {
    let mut out: Vec<FileDiag> = ws
        .config_errors
        .iter()
        .map(|(range, message)| FileDiag {
            path: ws.config_path.clone(),
            range: *range,
            severity: DiagnosticSeverity::ERROR,
            message: message.clone(),
            context: String::new(),
        })
        .collect();
    if let (Err(e), true) = (&ws.config, out.is_empty()) {
        out.push(FileDiag {
            path: ws.config_path.clone(),
            range: line_start(0),
            severity: DiagnosticSeverity::ERROR,
            message: e.clone(),
            context: String::new(),
        });
    }
    out
}

fn to_lsp(d: FileDiag) -> Diagnostic {
    let message = if d.context.is_empty() { d.message } else { format!("{}\n{}", d.message, d.context) };
    Diagnostic {
        range: d.range,
        severity: Some(d.severity),
        source: Some("kiln".into()),
        message,
        ..Diagnostic::default()
    }
}

/// Writes one message to stdout; `false` when the client is gone.
fn send(m: impl Into<Message>) -> bool {
    let m: Message = m.into();
    let out = std::io::stdout();
    let mut lock = out.lock();
    m.write(&mut lock).is_ok() && lock.flush().is_ok()
}

fn write_raw(text: &str) -> bool {
    let out = std::io::stdout();
    let mut lock = out.lock();
    lock.write_all(text.as_bytes()).is_ok() && lock.flush().is_ok()
}
