//! `kiln lsp` figures: `cargo bench -p kiln --bench lsp [-- latency | memory]` (both by
//! default) runs the server as an editor does, through the tests' JSON-RPC client
//! (`compiler/tests/support/lsp_client.rs`), and prints:
//!
//! - latency: the time from each of 50 edits (alternately valid and broken) to its
//!   diagnostics, on a shader of the bundled set (`KILN_LSP_LATENCY_FILE` names another,
//!   relative to the repository), and the server's peak memory;
//! - memory: the test project grown to 100,100 kept permutations: the time to check them
//!   all in the background, and the server's peak memory after listing them and hovering a
//!   dimension.
//!
//! Figures only: the behaviour is tested in `compiler/tests/it/lsp.rs`.

#[path = "../tests/support/lsp_client.rs"]
mod lsp_client;

use std::time::{Duration, Instant};

use lsp_client::*;
use serde_json::json;

fn main() {
    // `cargo bench` passes `--bench`; any other argument picks the measures.
    let picked: Vec<String> = std::env::args().skip(1).filter(|a| !a.starts_with("--")).collect();
    let run = |name: &str| picked.is_empty() || picked.iter().any(|p| p == name);
    if run("latency") {
        latency();
    }
    if run("memory") {
        memory_100k();
    }
}

/// 50 edits to a shader of the bundled set (`KILN_LSP_LATENCY_FILE`, else the volumetric
/// fog shader, read by several shaders); prints the median and p95 time from each
/// `didChange` to its `publishDiagnostics`, and the server's peak memory.
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

/// The test project with two more dimensions (100,100 kept permutations): opens the shader,
/// lets the background check run through the domain, lists the permutations and hovers a
/// dimension (each walks the whole domain); prints the time and the server's peak memory.
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
