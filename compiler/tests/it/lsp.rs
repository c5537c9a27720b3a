//! `kiln lsp` through a real client: a plain JSON-RPC client over the child's stdio
//! (protocol tests), and Neovim's built-in LSP client run headless with a Lua script
//! (`compiler/tests/lsp/nvim.lua`). The project is `tests/in/lsp/`, copied to a temporary
//! folder per test. The client is `compiler/tests/support/lsp_client.rs`; the diagnostics
//! latency and the server's memory are measured by `cargo bench -p kiln --bench lsp`.

#[path = "../support/lsp_client.rs"]
mod lsp_client;

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Duration;

use lsp_client::*;
use serde_json::{json, Value};

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
    let out = crate::kiln_command()
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
    let mut cmd = crate::kiln_command();
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
