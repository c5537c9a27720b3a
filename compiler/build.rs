//! Fingerprints Kiln's own sources into `KILN_SOURCE_HASH`, part of every cache key, so a
//! cache never serves outputs of a different Kiln (a released version or a work tree).
//!
//! `KILN_PIN_SOURCE_HASH=<hex>` set while Kiln itself is built takes that value instead: for
//! measuring a change to the build's memory or time against a large warm cache made by
//! another binary (`KILN_SOURCE_HASH` of `target/*/build/kiln-*/output`), never for a
//! binary that is shipped, whose cache could then serve another Kiln's outputs.

use std::hash::{Hash, Hasher};
use std::path::{Path, PathBuf};

fn files(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else { return };
    for e in entries.flatten() {
        let p = e.path();
        if p.is_dir() {
            files(&p, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}

fn main() {
    if let Ok(v) = std::env::var("KILN_PIN_SOURCE_HASH") {
        println!("cargo:rustc-env=KILN_SOURCE_HASH={v}");
        println!("cargo:rerun-if-env-changed=KILN_PIN_SOURCE_HASH");
        return;
    }
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut list = Vec::new();
    files(&src, &mut list);
    list.sort();
    let mut h = std::hash::DefaultHasher::new();
    for f in &list {
        f.strip_prefix(&src).unwrap_or(f).hash(&mut h);
        std::fs::read(f).unwrap_or_default().hash(&mut h);
    }
    println!("cargo:rustc-env=KILN_SOURCE_HASH={:016x}", h.finish());
    println!("cargo:rerun-if-changed=src");
    // Else a pin set after an unpinned build would not run this again, and be ignored.
    println!("cargo:rerun-if-env-changed=KILN_PIN_SOURCE_HASH");
}
