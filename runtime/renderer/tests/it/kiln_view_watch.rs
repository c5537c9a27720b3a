//! `kiln-view --watch CONFIG` (feature `hot-reload`): a header edit re-renders `--out`; a
//! broken edit prints the mapped diagnostic and keeps rendering with the last good
//! pipelines; the next good edit renders again.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

/// Kills kiln-view when the test ends, passed or not.
struct Running(Child);

impl Drop for Running {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn copy(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        if e.file_type().unwrap().is_dir() {
            copy(&e.path(), &to.join(e.file_name()));
        } else {
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
}

/// Saves as editors do: a new file renamed over the old one.
fn save(path: &Path, text: &str) {
    let tmp = path.with_extension("tmp~");
    std::fs::write(&tmp, text).unwrap();
    std::fs::rename(&tmp, path).unwrap();
}

/// Lines of a pipe, read on a thread.
fn lines(pipe: impl std::io::Read + Send + 'static) -> mpsc::Receiver<String> {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(pipe).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    rx
}

fn next_line(rx: &mpsc::Receiver<String>, errors: &mpsc::Receiver<String>) -> String {
    match rx.recv_timeout(Duration::from_secs(300)) {
        Ok(l) => l,
        Err(e) => {
            panic!("kiln-view printed no line ({e}); stderr:\n{}", errors.try_iter().collect::<Vec<_>>().join("\n"))
        }
    }
}

#[test]
fn watch_rerenders_after_a_header_edit_and_survives_a_broken_one() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    copy(&root.join("shader_src"), &d.join("shader_src"));
    std::fs::copy(root.join("permutations.toml"), d.join("permutations.toml")).unwrap();
    let header = d.join("shader_src/Private/Mobile/MobileLighting.ush");
    let original = std::fs::read_to_string(&header).unwrap();
    const SKY: &str = "return max(irradiance, vec3<f32>(0.0));";
    assert!(original.contains(SKY), "MobileLighting.ush no longer has the line this test edits");

    let mut child = Command::new(env!("CARGO_BIN_EXE_kiln-view"))
        .args(["--watch", "permutations.toml", "--pipeline", "mobile-forward", "--size", "96x54"])
        .args(["--out", "f.png", "--watch-reloads", "3"])
        .current_dir(d)
        .env("KILN_CACHE_DIR", d.join("cache"))
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let (out, err) = (lines(child.stdout.take().unwrap()), lines(child.stderr.take().unwrap()));
    let mut child = Running(child);

    let line = next_line(&out, &err);
    assert!(line.starts_with("kiln-view: watching ") && line.contains("mobile-forward"), "{line}");
    let first = std::fs::read(d.join("f.png")).unwrap();

    // A brighter sky light: the base pass permutations that read the header are rebuilt.
    save(&header, &original.replace(SKY, &SKY.replace("(0.0));", "(0.0)) * 3.0;")));
    let line = next_line(&out, &err);
    assert!(line.starts_with("kiln-view: reload after MobileLighting.ush: "), "{line}");
    assert!(line.contains("permutations rebuilt") && line.contains("edit to frame"), "{line}");
    let brighter = std::fs::read(d.join("f.png")).unwrap();
    assert_ne!(brighter, first, "the frame did not change after the edit");

    // A broken edit: Kiln's diagnostic at the header's line, and the last good pipelines.
    let broken_line = original.lines().position(|l| l.contains(SKY)).unwrap() + 1;
    save(&header, &original.replace(SKY, "return max(irradiance, ;"));
    let line = next_line(&out, &err);
    assert!(line.contains("failed: the shaders do not build; keeping the last good pipelines"), "{line}");
    // The diagnostic goes to stderr, which its reader thread may hand over after the stdout
    // line: read it until both parts are there or the pipe stays quiet for 30 s.
    let at = format!("shader_src/Private/Mobile/MobileLighting.ush:{broken_line}:");
    let mut stderr = String::new();
    while !(stderr.contains(&at) && stderr.contains("MobileBasePassPS@es3_1{")) {
        match err.recv_timeout(Duration::from_secs(30)) {
            Ok(line) => stderr.push_str(&(line + "\n")),
            Err(_) => panic!("no diagnostic at {at} naming MobileBasePassPS@es3_1 on stderr:\n{stderr}"),
        }
    }
    // Still rendering: the process is alive and `--out` holds the last good frame.
    std::thread::sleep(Duration::from_millis(300));
    assert!(child.0.try_wait().unwrap().is_none(), "kiln-view stopped after a broken edit");
    assert_eq!(std::fs::read(d.join("f.png")).unwrap(), brighter);

    // The next good edit renders again.
    save(&header, &original.replace(SKY, &SKY.replace("(0.0));", "(0.0)) * 0.25;")));
    let line = next_line(&out, &err);
    assert!(line.starts_with("kiln-view: reload after MobileLighting.ush: "), "{line}");
    let darker = std::fs::read(d.join("f.png")).unwrap();
    assert_ne!(darker, brighter);
    assert_ne!(darker, first);

    // `--watch-reloads 3`: done.
    let status = child.0.wait().unwrap();
    assert!(status.success(), "{status}");
}
