//! The source map: output bytes back to files, lines and columns through includes and macro
//! expansions; the file cache; the token hash.

use std::path::Path;

use kiln::preprocess::{self, CodespanDiagnostic as Diagnostic, Options, Origin, SourceCache};

fn write_files(root: &Path, files: &[(&str, &str)]) {
    for (path, text) in files {
        let p = root.join(path);
        std::fs::create_dir_all(p.parent().expect("has a parent")).expect("mkdir");
        std::fs::write(p, text).expect("write");
    }
}

const FILES: [(&str, &str); 4] = [
    ("main.usf", "// main\n#include \"a.ush\"\nfn main_fn() {}\n"),
    ("a.ush", "#include \"inc/b.ush\"\n"),
    ("inc/b.ush", "\n\n#include \"deeper/c.ush\"\n"),
    (
        "inc/deeper/c.ush",
        "#define INNER(x) (x * 2.0)\n#define OUTER(y) INNER(y) + bad_ident\nfn f() -> f32 { return OUTER(1.0); }\n",
    ),
];

/// (file name, line, column) of an origin, and of its macro definition.
fn place(cache: &SourceCache, o: &Origin) -> (String, usize, usize) {
    (cache.name(o.file), o.line, o.column)
}

#[test]
fn three_includes_and_two_macro_levels() {
    let dir = tempfile::tempdir().expect("temp dir");
    write_files(dir.path(), &FILES);
    let cache = SourceCache::new(dir.path().to_path_buf());
    let out =
        preprocess::preprocess_file(&dir.path().join("main.usf"), &Options::default(), &cache).expect("preprocesses");
    assert_eq!(
        preprocess::tokens(&out.text),
        preprocess::tokens("fn f() -> f32 { return (1.0 * 2.0) + bad_ident; }\nfn main_fn() {}")
    );

    // A token written in c.ush: its own place.
    let at = out.text.find("return").expect("in output");
    let o = out.map.origin(at).expect("mapped");
    assert_eq!(place(&cache, &o), ("inc/deeper/c.ush".into(), 3, 17));
    assert_eq!(o.macro_definition, None);
    let chain: Vec<(String, usize)> =
        o.include_chain.iter().map(|(f, r)| (cache.name(*f), cache.location(*f, r.start).0)).collect();
    assert_eq!(chain, vec![("inc/b.ush".into(), 3), ("a.ush".into(), 1), ("main.usf".into(), 2)]);

    // Made by OUTER: the invocation, with OUTER's definition as the note.
    let at = out.text.find("bad_ident").expect("in output");
    let o = out.map.origin(at).expect("mapped");
    assert_eq!(place(&cache, &o), ("inc/deeper/c.ush".into(), 3, 24));
    assert_eq!(&FILES[3].1[o.span.clone()], "OUTER(1.0)");
    let (def_file, def_span) = o.macro_definition.clone().expect("macro-made");
    assert_eq!(cache.name(def_file), "inc/deeper/c.ush");
    assert_eq!(&FILES[3].1[def_span.clone()], "bad_ident");
    assert_eq!(cache.location(def_file, def_span.start).0, 2);
    assert_eq!(o.include_chain.len(), 3);

    // Made by INNER inside OUTER (two levels): still the outer invocation, INNER's `*`.
    let at = out.text.find('*').expect("in output");
    let o = out.map.origin(at).expect("mapped");
    assert_eq!(place(&cache, &o), ("inc/deeper/c.ush".into(), 3, 24));
    let (_, def_span) = o.macro_definition.clone().expect("macro-made");
    assert_eq!(def_span.start, FILES[3].1.find('*').expect("star"));

    // The argument `1.0` was written at the invocation: it maps to itself.
    let at = out.text.find("1.0").expect("in output");
    let o = out.map.origin(at).expect("mapped");
    assert_eq!(place(&cache, &o), ("inc/deeper/c.ush".into(), 3, 30));
    assert_eq!(o.macro_definition, None);

    // Text after the include, back in main.usf.
    let at = out.text.find("main_fn").expect("in output");
    let o = out.map.origin(at).expect("mapped");
    assert_eq!(place(&cache, &o), ("main.usf".into(), 3, 4));
    assert!(o.include_chain.is_empty());

    // The labels the compile stage puts on a naga error, rendered.
    let at = out.text.find("bad_ident").expect("in output");
    let labels = out.map.labels(at..at + "bad_ident".len(), "no definition in scope for identifier: `bad_ident`");
    let d = Diagnostic::error().with_message("invalid expression").with_labels(labels);
    let rendered = preprocess::render(&[d], &cache, false);
    let expected = r#"
error: invalid expression
  ┌─ inc/deeper/c.ush:3:24
  │
2 │ #define OUTER(y) INNER(y) + bad_ident
  │                             --------- in this macro's definition
3 │ fn f() -> f32 { return OUTER(1.0); }
  │                        ^^^^^^^^^^ no definition in scope for identifier: `bad_ident`
  │
  ┌─ inc/b.ush:3:1
  │
3 │ #include "deeper/c.ush"
  │ ----------------------- included from here
  │
  ┌─ a.ush:1:1
  │
1 │ #include "inc/b.ush"
  │ -------------------- included from here
  │
  ┌─ main.usf:2:1
  │
2 │ #include "a.ush"
  │ ---------------- included from here
"#
    .trim_start();
    assert_eq!(rendered.trim_end(), expected.trim_end(), "\n{rendered}");
}

#[test]
fn columns_through_line_splices_and_every_byte_is_mapped() {
    let cache = SourceCache::new(std::env::temp_dir());
    let text = "#define A \\\n  one\nlet x = A;\nlet y = 1 + \\\n  22;\n";
    let id = cache.add_virtual("splice.usf", text);
    let out = preprocess::preprocess_file_id(id, &Options::default(), &cache).expect("preprocesses");
    let at = out.text.find("22").expect("in output");
    let o = out.map.origin(at).expect("mapped");
    assert_eq!((o.line, o.column), (5, 3));
    assert_eq!(&text[o.span.clone()], "2");
    for i in 0..out.text.len() {
        assert!(out.map.origin(i).is_some(), "byte {i} of {:?} has no origin", out.text);
    }
    // The source map is runs, not bytes.
    assert!(out.map.len() < 8, "{} entries", out.map.len());
}

#[test]
fn files_are_read_once_per_cache_across_threads() {
    let dir = tempfile::tempdir().expect("temp dir");
    write_files(dir.path(), &FILES);
    let cache = SourceCache::new(dir.path().to_path_buf());
    let main = dir.path().join("main.usf");
    std::thread::scope(|s| {
        for i in 0..4 {
            let (cache, main) = (&cache, &main);
            s.spawn(move || {
                let opts = Options { defines: vec![("PERM".into(), i.to_string())], ..Options::default() };
                let out = preprocess::preprocess_file(main, &opts, cache).expect("preprocesses");
                assert_eq!(out.files.len(), 4);
                assert_eq!(cache.name(out.files[0]), "main.usf");
            });
        }
    });
    assert_eq!(cache.len(), 4, "each of the 4 files read once");
    // Changing a file on disk does not matter any more: its text comes from the cache.
    std::fs::write(dir.path().join("inc/deeper/c.ush"), "changed\n").expect("write");
    let out = preprocess::preprocess_file(&main, &Options::default(), &cache).expect("from the cache");
    assert!(out.text.contains("bad_ident") && !out.text.contains("changed"));
    assert_eq!(cache.len(), 4);
}

#[test]
fn token_hash_ignores_spacing_and_comments() {
    let cache = SourceCache::new(std::env::temp_dir());
    let a = cache.add_virtual("a.usf", "#define N 4\nfn f() -> u32 { return N; }\n");
    let b = cache.add_virtual("b.usf", "fn  f ( ) ->u32{\n  // four\n  return /* n */ 4 ;\n}");
    let c = cache.add_virtual("c.usf", "fn f() -> u32 { return 5; }\n");
    let opts = Options::default();
    let h = |id| preprocess::preprocess_file_id(id, &opts, &cache).expect("ok").token_hash();
    assert_eq!(h(a), h(b));
    assert_ne!(h(a), h(c));
}
