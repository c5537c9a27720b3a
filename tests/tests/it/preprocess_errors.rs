//! Every preprocessing error, compared as the whole rendered diagnostic (file, line, column,
//! snippet, include chain), plus the warnings that let preprocessing go on.

use std::path::Path;

use kiln::preprocess::{self, Options, SourceCache};

/// Writes `files` (path, text) under a temp dir and preprocesses the first one.
fn run(files: &[(&str, &str)], opts: Options) -> (Result<String, String>, String) {
    let dir = tempfile::tempdir().expect("temp dir");
    write_files(dir.path(), files);
    let cache = SourceCache::new(dir.path().to_path_buf());
    let main = dir.path().join(files[0].0);
    match preprocess::preprocess_file(&main, &opts, &cache) {
        Ok(out) => {
            let warnings = preprocess::render(&out.warnings, &cache, false);
            (Ok(out.text), warnings)
        }
        Err(e) => (Err(preprocess::render(&[e.diagnostic], &cache, false)), String::new()),
    }
}

fn write_files(root: &Path, files: &[(&str, &str)]) {
    for (path, text) in files {
        let p = root.join(path);
        std::fs::create_dir_all(p.parent().expect("has a parent")).expect("mkdir");
        std::fs::write(p, text).expect("write");
    }
}

fn error_of(files: &[(&str, &str)]) -> String {
    match run(files, Options::default()).0 {
        Ok(text) => panic!("expected an error, got output:\n{text}"),
        Err(e) => e,
    }
}

#[track_caller]
fn assert_error(files: &[(&str, &str)], expected: &str) {
    let got = error_of(files);
    assert_eq!(got.trim_end(), expected.trim_end(), "\n--- got:\n{got}\n--- expected:\n{expected}");
}

#[test]
fn error_directive() {
    assert_error(
        &[("main.usf", "fn f() {}\n#if 1\n#error this target is not supported\n#endif\n")],
        r#"
error: #error this target is not supported
  ┌─ main.usf:3:1
  │
3 │ #error this target is not supported
  │ ^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^
"#
        .trim_start(),
    );
}

#[test]
fn error_inside_include_shows_the_chain() {
    assert_error(
        &[
            ("main.usf", "// main\n#include \"a.ush\"\n"),
            ("a.ush", "#include \"sub/b.ush\"\n"),
            ("sub/b.ush", "\n#error deep\n"),
        ],
        r#"
error: #error deep
  ┌─ sub/b.ush:2:1
  │
2 │ #error deep
  │ ^^^^^^^^^^^
  │
  ┌─ a.ush:1:1
  │
1 │ #include "sub/b.ush"
  │ -------------------- included from here
  │
  ┌─ main.usf:2:1
  │
2 │ #include "a.ush"
  │ ---------------- included from here
"#
        .trim_start(),
    );
}

#[test]
fn unterminated_conditional() {
    assert_error(
        &[("main.usf", "a\n#ifdef X\nb\n#if 1\nc\n#endif\n")],
        r#"
error: unterminated #ifdef
  ┌─ main.usf:2:1
  │
2 │ #ifdef X
  │ ^^^^^^ this conditional is never closed
"#
        .trim_start(),
    );
}

#[test]
fn unbalanced_conditionals() {
    assert_error(
        &[("main.usf", "a\n  #endif\n")],
        r#"
error: #endif without #if
  ┌─ main.usf:2:3
  │
2 │   #endif
  │   ^^^^^^ no open conditional
"#
        .trim_start(),
    );
    assert_error(
        &[("main.usf", "#else\n")],
        r#"
error: #else without #if
  ┌─ main.usf:1:1
  │
1 │ #else
  │ ^^^^^ no open conditional
"#
        .trim_start(),
    );
}

#[test]
fn elif_after_else() {
    assert_error(
        &[("main.usf", "#if 0\n#else\nx\n#elif 1\n#endif\n")],
        r#"
error: #elif after #else
  ┌─ main.usf:4:1
  │
4 │ #elif 1
  │ ^^^^^ after the #else of this conditional
"#
        .trim_start(),
    );
    // The same when the #else group is skipped.
    assert_error(
        &[("main.usf", "#if 1\n#else\n#else\n#endif\n")],
        r#"
error: #else after #else
  ┌─ main.usf:3:1
  │
3 │ #else
  │ ^^^^^ after the #else of this conditional
"#
        .trim_start(),
    );
}

#[test]
fn missing_include() {
    assert_error(
        &[("main.usf", "#include \"nothere.ush\"\n")],
        r#"
error: cannot find include file `nothere.ush`
  ┌─ main.usf:1:10
  │
1 │ #include "nothere.ush"
  │          ^^^^^^^^^^^^^ not found
  │
  = searched: the including file's folder
"#
        .trim_start(),
    );
}

#[test]
fn escaping_include() {
    let dir = tempfile::tempdir().expect("temp dir");
    write_files(dir.path(), &[("outside.ush", "secret\n"), ("src/main.usf", "#include \"../outside.ush\"\n")]);
    let cache = SourceCache::new(dir.path().to_path_buf());
    let opts = Options { include_roots: vec![dir.path().join("src")], ..Options::default() };
    let err = preprocess::preprocess_file(&dir.path().join("src/main.usf"), &opts, &cache).expect_err("escapes");
    let got = preprocess::render(&[err.diagnostic], &cache, false);
    let expected = r#"
error: #include "../outside.ush" resolves to `outside.ush`, outside the include roots
  ┌─ src/main.usf:1:10
  │
1 │ #include "../outside.ush"
  │          ^^^^^^^^^^^^^^^^ this include escapes its root
"#
    .trim_start();
    assert_eq!(got.trim_end(), expected.trim_end(), "\n{got}");
}

#[cfg(unix)]
#[test]
fn symlink_escape_is_refused() {
    let dir = tempfile::tempdir().expect("temp dir");
    write_files(dir.path(), &[("outside/secret.ush", "secret\n"), ("src/main.usf", "#include <link.ush>\n")]);
    std::os::unix::fs::symlink(dir.path().join("outside/secret.ush"), dir.path().join("src/link.ush"))
        .expect("symlink");
    let cache = SourceCache::new(dir.path().to_path_buf());
    let opts = Options { include_roots: vec![dir.path().join("src")], ..Options::default() };
    let err = preprocess::preprocess_file(&dir.path().join("src/main.usf"), &opts, &cache).expect_err("escapes");
    let got = preprocess::render(&[err.diagnostic], &cache, false);
    let expected = r#"
error: #include "link.ush" resolves to `outside/secret.ush`, outside the include roots
  ┌─ src/main.usf:1:10
  │
1 │ #include <link.ush>
  │          ^^^^^^^^^^ this include escapes its root
"#
    .trim_start();
    assert_eq!(got.trim_end(), expected.trim_end(), "\n{got}");
}

#[test]
fn division_by_zero() {
    assert_error(
        &[("main.usf", "#define ZERO 0\n#if 4 / ZERO\n#endif\n")],
        r#"
error: division by zero in #if
  ┌─ main.usf:2:7
  │
2 │ #if 4 / ZERO
  │       ^ this divisor is zero
"#
        .trim_start(),
    );
}

#[test]
fn malformed_directives() {
    assert_error(
        &[("main.usf", "#frobnicate x\n")],
        r#"
error: invalid preprocessing directive #frobnicate
  ┌─ main.usf:1:2
  │
1 │ #frobnicate x
  │  ^^^^^^^^^^ unknown directive
"#
        .trim_start(),
    );
    assert_error(
        &[("main.usf", "#define 3 x\n")],
        r#"
error: macro names must be identifiers
  ┌─ main.usf:1:9
  │
1 │ #define 3 x
  │         ^ not an identifier
"#
        .trim_start(),
    );
    assert_error(
        &[("main.usf", "#define F(a, 1) a\n")],
        r#"
error: expected parameter name, found "1"
  ┌─ main.usf:1:14
  │
1 │ #define F(a, 1) a
  │              ^ expected a parameter name
"#
        .trim_start(),
    );
    assert_error(
        &[("main.usf", "#if\n#endif\n")],
        r#"
error: #if with no expression
  ┌─ main.usf:1:2
  │
1 │ #if
  │  ^^ expected an expression
"#
        .trim_start(),
    );
    assert_error(
        &[("main.usf", "#if 1 +\n#endif\n")],
        r#"
error: operator '+' has no right operand
  ┌─ main.usf:1:7
  │
1 │ #if 1 +
  │       ^ here
"#
        .trim_start(),
    );
    assert_error(
        &[("main.usf", "#define S(x) #y\n")],
        r#"
error: '#' is not followed by a macro parameter
  ┌─ main.usf:1:14
  │
1 │ #define S(x) #y
  │              ^ here
"#
        .trim_start(),
    );
    assert_error(
        &[("main.usf", "#define P ## x\n")],
        r#"
error: '##' cannot appear at either end of a macro expansion
  ┌─ main.usf:1:11
  │
1 │ #define P ## x
  │           ^^ here
"#
        .trim_start(),
    );
}

#[test]
fn wrong_argument_count() {
    assert_error(
        &[("main.usf", "#define F(a, b) a + b\nlet x = F(1);\n")],
        r#"
error: macro "F" requires 2 arguments, but only 1 given
  ┌─ main.usf:2:9
  │
2 │ let x = F(1);
  │         ^^^^ this invocation
"#
        .trim_start(),
    );
    assert_error(
        &[("main.usf", "#define F(a) a\n#define G F(1, 2)\nG\n")],
        r#"
error: macro "F" passed 2 arguments, but takes just 1
  ┌─ main.usf:3:1
  │
2 │ #define G F(1, 2)
  │           - in this macro's definition
3 │ G
  │ ^ this invocation
"#
        .trim_start(),
    );
}

#[test]
fn unterminated_invocation() {
    assert_error(
        &[("main.usf", "#define F(a) a\nF(1,\n  2\n")],
        r#"
error: unterminated argument list invoking macro "F"
  ┌─ main.usf:2:1
  │
2 │ F(1,
  │ ^ this invocation is never closed
"#
        .trim_start(),
    );
}

#[test]
fn unterminated_comment() {
    assert_error(
        &[("main.usf", "fn f() {}\n  /* never\n closed\n")],
        r#"
error: unterminated comment
  ┌─ main.usf:2:3
  │
2 │   /* never
  │   ^^ this comment is never closed
"#
        .trim_start(),
    );
}

#[test]
fn macro_bomb_is_bounded() {
    // Each level doubles: 2^40 tokens if nothing stopped it.
    let mut src = String::from("#define L0 x x\n");
    for i in 1..=40 {
        src.push_str(&format!("#define L{i} L{} L{}\n", i - 1, i - 1));
    }
    src.push_str("L40\n");
    let start = std::time::Instant::now();
    let opts = Options { max_output_bytes: 1 << 20, ..Options::default() };
    let (result, _) = run(&[("main.usf", &src)], opts);
    let err = result.expect_err("the bomb must fail");
    let expected = r#"
error: macro expansion makes more than 262144 tokens
   ┌─ main.usf:42:1
   │
 2 │ #define L1 L0 L0
   │               -- in this macro's definition
   ·
42 │ L40
   │ ^^^ while expanding this
"#
    .trim_start();
    assert_eq!(err.trim_end(), expected.trim_end(), "\n{err}");
    // Not a timing assertion on speed, a guard against a hang: generous on any machine.
    assert!(start.elapsed().as_secs() < 30);
}

#[test]
fn argument_bomb_is_bounded() {
    let mut src = String::from("#define D(x) x x\n");
    let mut call = String::from("1");
    for _ in 0..40 {
        call = format!("D({call})");
    }
    src.push_str(&call);
    src.push('\n');
    let opts = Options { max_output_bytes: 1 << 20, ..Options::default() };
    let (result, _) = run(&[("main.usf", &src)], opts);
    let err = result.expect_err("the bomb must fail");
    let expected = r#"
error: macro expansion makes more than 262144 tokens
  ┌─ main.usf:2:51
  │
2 │ D(D(D(D(D(D(D(D(D(D(D(D(D(D(D(D(D(D(D(D(D(D(D(D(D(D(D(D(D(D(D(D(D(D(D(D(D(D(D(D(1))))))))))))))))))))))))))))))))))))))))
  │                                                   ^ while expanding this
"#
    .trim_start();
    assert_eq!(err.trim_end(), expected.trim_end(), "\n{err}");
}

#[test]
fn deep_recursion_is_bounded() {
    let mut src = String::new();
    for i in 0..400 {
        src.push_str(&format!("#define M{i} M{}\n", i + 1));
    }
    src.push_str("M0\n");
    let (result, _) = run(&[("main.usf", &src)], Options::default());
    let err = result.expect_err("too deep");
    assert!(err.starts_with("error: macro expansion nested deeper than 256 levels"), "{err}");
}

#[test]
fn recursive_include_is_bounded() {
    let (result, _) = run(&[("main.usf", "#include \"main.usf\"\n")], Options::default());
    let err = result.expect_err("too deep");
    assert!(err.starts_with("error: #include nested depth 200 exceeds maximum of 200"), "{err}");
}

#[test]
fn warnings_do_not_stop() {
    let (result, warnings) =
        run(&[("main.usf", "#define A 1\n#define A 2\n#warning check this\nA\n")], Options::default());
    assert_eq!(preprocess::tokens(&result.expect("no error")), vec!["2"]);
    let expected = r#"
warning: "A" redefined
  ┌─ main.usf:2:9
  │
1 │ #define A 1
  │         - previous definition
2 │ #define A 2
  │         ^ redefined here

warning: #warning check this
  ┌─ main.usf:3:1
  │
3 │ #warning check this
  │ ^^^^^^^^^^^^^^^^^^^
"#
    .trim_start();
    assert_eq!(warnings.trim_end(), expected.trim_end(), "\n{warnings}");
}

#[test]
fn issue16_cpp_differences_are_located_errors() {
    // An unterminated comment in a skipped group is that, not only an unterminated #if.
    assert_error(
        &[("main.usf", "#if 0\nskipped\n  /* open\n#endif\n")],
        r#"
error: unterminated comment
  ┌─ main.usf:3:3
  │
3 │   /* open
  │   ^^ this comment is never closed
"#
        .trim_start(),
    );
    // Nested __VA_OPT__ is an error at its definition, as in cpp.
    assert_error(
        &[("main.usf", "#define F(...) a __VA_OPT__(b __VA_OPT__(c) d) e\n")],
        r#"
error: __VA_OPT__ may not appear in a __VA_OPT__
  ┌─ main.usf:1:31
  │
1 │ #define F(...) a __VA_OPT__(b __VA_OPT__(c) d) e
  │                               ^^^^^^^^^^ nested here
"#
        .trim_start(),
    );
    assert_error(
        &[("main.usf", "#define F(...) __VA_OPT__(a\n")],
        r#"
error: unterminated __VA_OPT__
  ┌─ main.usf:1:16
  │
1 │ #define F(...) __VA_OPT__(a
  │                ^^^^^^^^^^ this __VA_OPT__ is never closed
"#
        .trim_start(),
    );
    // Including a directory says so.
    assert_error(
        &[("main.usf", "#include \"sub\"\n"), ("sub/a.ush", "")],
        r#"
error: #include "sub" names `sub`, which is a directory, not a file
  ┌─ main.usf:1:10
  │
1 │ #include "sub"
  │          ^^^^^ not a file
"#
        .trim_start(),
    );
    // A lone CR ends a line: errors after CR-only lines name the right line.
    assert_error(
        &[("main.usf", "a\rb\r\n#error here\r")],
        r#"
error: #error here
  ┌─ main.usf:3:1
  │
3 │ #error here
  │ ^^^^^^^^^^^
"#
        .trim_start(),
    );
}

/// A source that is not UTF-8 is an error at its first bad byte (file, line, column), main
/// file or included, never replaced silently.
#[test]
fn invalid_utf8_is_located() {
    let dir = tempfile::tempdir().expect("temp dir");
    std::fs::write(dir.path().join("main.usf"), b"fn f() {}\n#include \"bad.ush\"\n").expect("write");
    std::fs::write(dir.path().join("bad.ush"), b"// ok\nlet x = 1; // caf\xe9 \xff\n").expect("write");
    let cache = SourceCache::new(dir.path().to_path_buf());
    let render = |path: &str| {
        let e = preprocess::preprocess_file(&dir.path().join(path), &Options::default(), &cache).expect_err(path);
        preprocess::render(&[e.diagnostic], &cache, false)
    };
    let expected_bad = r#"
error: `bad.ush` is not UTF-8 text
  ┌─ bad.ush:2:18
  │
2 │ let x = 1; // caf� �
  │                  ^ byte 0xe9
"#
    .trim_start();
    let got = render("main.usf");
    let expected_main = format!(
        "{}{}",
        expected_bad,
        r#"  │
  ┌─ main.usf:2:10
  │
2 │ #include "bad.ush"
  │          --------- included here
"#
    );
    assert_eq!(got.trim_end(), expected_main.trim_end(), "\n{got}");
    // Asked for again (from the cache), and as the main file.
    let got = render("bad.ush");
    assert_eq!(got.trim_end(), expected_bad.trim_end(), "\n{got}");
}

/// A source that is a FIFO (or a device) is refused at once, never read (it would block):
/// as the main file, and as an include.
#[test]
fn non_regular_files_are_refused() {
    let dir = tempfile::tempdir().expect("temp dir");
    let fifo = dir.path().join("pipe.ush");
    let made = std::process::Command::new("mkfifo").arg(&fifo).status().expect("mkfifo runs");
    assert!(made.success());
    std::fs::write(dir.path().join("main.usf"), "#include \"pipe.ush\"\n").expect("write");
    let cache = SourceCache::new(dir.path().to_path_buf());
    let e = preprocess::preprocess_file(&fifo, &Options::default(), &cache).expect_err("a FIFO");
    assert!(e.to_string().ends_with("is not a regular file (a device, FIFO or socket)"), "{e}");
    let e = preprocess::preprocess_file(&dir.path().join("main.usf"), &Options::default(), &cache).expect_err("a FIFO");
    let r = preprocess::render(&[e.diagnostic], &cache, false);
    assert!(r.starts_with("error: #include \"pipe.ush\" names `pipe.ush`, which is a device, FIFO or socket"), "{r}");
    let e = preprocess::preprocess_file(Path::new("/dev/zero"), &Options::default(), &cache).expect_err("a device");
    assert!(e.to_string().ends_with("is not a regular file (a device, FIFO or socket)"), "{e}");
}

/// An error on a very long line shows the line cut around its label, at its real column.
#[test]
fn long_lines_are_cut_in_diagnostics() {
    let text = format!("#define F(x) x\n{} F(1 {}\n", "a ".repeat(1000), "b ".repeat(1000));
    let got = error_of(&[("main.usf", &text)]);
    assert!(got.starts_with("error: unterminated argument list invoking macro \"F\"\n  ┌─ main.usf:2:2002\n"), "{got}");
    assert!(got.contains("2 │ … a a a a"), "{got}");
    assert!(got.contains("F(1 b b b"), "{got}");
    assert!(got.lines().all(|l| l.chars().count() < 200), "{got}");
}
