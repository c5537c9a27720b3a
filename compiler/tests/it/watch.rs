//! `kiln build --watch`: one line per rebuild, rebuilds on an edit, keeps going after a
//! broken one.

use std::io::{BufRead, BufReader};
use std::process::{Child, Stdio};
use std::sync::mpsc;
use std::time::Duration;

/// Kills the watch when the test ends, passed or not.
struct Watching(Child);

impl Drop for Watching {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// The next stderr line containing `what`, with every line read on the way.
fn wait_for(lines: &mpsc::Receiver<String>, what: &str) -> String {
    let mut seen = String::new();
    loop {
        match lines.recv_timeout(Duration::from_secs(120)) {
            Ok(line) => {
                seen.push_str(&line);
                seen.push('\n');
                if line.contains(what) {
                    return seen;
                }
            }
            Err(e) => panic!("no line with `{what}` ({e}); read:\n{seen}"),
        }
    }
}

#[test]
fn build_watch_rebuilds_on_an_edit() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(
        d.join("permutations.toml"),
        "[compiler]\ninclude = [\".\"]\n[levels.sm5]\ntargets = [\"wgsl\", \"spirv\"]\n\
         [[shader]]\nname = \"S\"\nsource = \"s.usf\"\nstage = \"compute\"\nentry = \"main\"\ndimensions = { A = [1, 2] }\n",
    )
    .unwrap();
    std::fs::write(
        d.join("s.usf"),
        "#include \"h.ush\"\n@group(0) @binding(0) var<storage, read_write> o: array<f32>;\n\
         @compute @workgroup_size(1) fn main() { o[0] = K * f32(A); }\n",
    )
    .unwrap();
    std::fs::write(d.join("h.ush"), "const K: f32 = 1.0;\n").unwrap();
    let mut child = crate::kiln_command()
        .args(["build", "--watch", "--cache-dir", "cache", "-o", "out.kpak"])
        .current_dir(d)
        .stderr(Stdio::piped())
        .stdout(Stdio::null())
        .spawn()
        .unwrap();
    let stderr = child.stderr.take().unwrap();
    let _child = Watching(child);
    let (tx, lines) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });

    let out = wait_for(&lines, "kiln: built");
    assert!(out.contains("2 permutations") && out.contains("watching 3 files"), "{out}");
    let first = std::fs::read(d.join("out.kpak")).unwrap();

    std::fs::write(d.join("h.ush"), "const K: f32 = 3.0;\n").unwrap();
    let out = wait_for(&lines, "kiln: rebuilt");
    assert!(out.contains("rebuilt after h.ush changed") && out.contains("2 compiled"), "{out}");
    let second = std::fs::read(d.join("out.kpak")).unwrap();
    assert_ne!(first, second);

    // A broken edit: the mapped diagnostic, the archive kept, and the watch goes on.
    std::fs::write(d.join("h.ush"), "const K: f32 = ;\n").unwrap();
    let out = wait_for(&lines, "kiln: rebuilt");
    assert!(out.contains("h.ush:1:") && out.contains("S@sm5{A=1}"), "{out}");
    assert!(out.contains("2 of 2 permutations failed, archive kept"), "{out}");
    assert_eq!(std::fs::read(d.join("out.kpak")).unwrap(), second);

    // Back to the first text: served from the cache.
    std::fs::write(d.join("h.ush"), "const K: f32 = 1.0;\n").unwrap();
    let out = wait_for(&lines, "kiln: rebuilt");
    assert!(out.contains("0 compiled, 2 cache hits"), "{out}");
    assert_eq!(std::fs::read(d.join("out.kpak")).unwrap(), first);
}
