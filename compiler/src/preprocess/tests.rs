//! Directive by directive: small input → expected tokens (joined by one space), and error
//! messages. The differential tests against cpp live in `tests/tests/preprocess_cpp.rs`.

use super::*;

fn run_with(src: &str, opts: &Options) -> Result<Output, Error> {
    let cache = SourceCache::new(std::env::temp_dir());
    let id = cache.add_virtual("t.usf", src);
    preprocess_file_id(id, opts, &cache)
}

fn pp(src: &str) -> String {
    match run_with(src, &Options::default()) {
        Ok(out) => tokens(&out.text).join(" "),
        Err(e) => panic!("unexpected error {e} for:\n{src}"),
    }
}

fn err(src: &str) -> String {
    match run_with(src, &Options::default()) {
        Ok(out) => panic!("expected an error, got {:?} for:\n{src}", out.text),
        Err(e) => e.to_string(),
    }
}

#[track_caller]
fn cases(cases: &[(&str, &str)]) {
    for (src, want) in cases {
        assert_eq!(pp(src), *want, "input:\n{src}");
    }
}

#[test]
fn define_object_like() {
    cases(&[
        ("#define A 1\nA", "1"),
        ("#define A\n[A]", "[ ]"),
        ("#define A B\n#define B 2\nA", "2"),
        ("#define A A + 1\nA", "A + 1"),
        ("#define A (x)\nA", "( x )"),
        ("#define A /* c */ 1 /* d */\nA", "1"),
        ("#define A 1 \\\n + 2\nA", "1 + 2"),
        ("  #  define A 3\nA", "3"),
        ("%:define A 4\nA", "4"),
    ]);
}

#[test]
fn define_function_like() {
    cases(&[
        ("#define F(x) [x]\nF(1) F (2) F\n(3)", "[ 1 ] [ 2 ] [ 3 ]"),
        ("#define F(x) [x]\nF + 1", "F + 1"),
        ("#define F(x, y) x y\nF((a, b), c)", "( a , b ) c"),
        ("#define F() z\nF() F( )", "z z"),
        ("#define F(x) [x]\nF()", "[ ]"),
        ("#define F(x) #x\nF(a  \"b\\n\"  'c')", r#""a \"b\\n\" 'c'""#),
        ("#define F(a, b) a ## b\nF(x, y) F(, y) F(x, ) F(,)", "xy y x"),
        ("#define F(...) <__VA_ARGS__>\nF() F(1, 2)", "< > < 1 , 2 >"),
        ("#define F(a, ...) a __VA_OPT__(+) __VA_ARGS__\nF(1) F(1, 2)", "1 1 + 2"),
        ("#define F(x) x F(x)\nF(1)", "1 F ( 1 )"),
        ("#define F(x, y) x y\nF(\n1\n,\n)", "1"),
    ]);
}

#[test]
fn undef() {
    cases(&[
        ("#define A 1\n#undef A\nA", "A"),
        ("#undef NEVER_DEFINED\nok", "ok"),
        ("#define F(x) x\n#undef F\nF(1)", "F ( 1 )"),
    ]);
    assert_eq!(err("#undef\n"), "no macro name given in #undef directive");
    assert_eq!(err("#undef 1\n"), "macro names must be identifiers");
}

#[test]
fn conditionals() {
    cases(&[
        ("#if 1\na\n#else\nb\n#endif", "a"),
        ("#if 0\na\n#else\nb\n#endif", "b"),
        ("#if 0\na\n#elif 2 > 1\nb\n#elif 1\nc\n#endif", "b"),
        ("#define X\n#ifdef X\na\n#endif\n#ifndef X\nb\n#endif", "a"),
        ("#if defined X || defined(Y)\na\n#else\nb\n#endif", "b"),
        ("#define V 3\n#if V * 2 == 6 && V << 1 == 6\nok\n#endif", "ok"),
        ("#if 0\n#if 1\nnested\n#endif\n#bogus\n#else\nouter\n#endif", "outer"),
        ("#if 1\n#elif 1 / 0\n#endif\nok", "ok"),
        ("#if 0\n#elif 0\n#else\nlast\n#endif", "last"),
        ("#if 0\n'unterminated\n\"also\n#endif\nok", "ok"),
        ("#if 0\n/*\n#endif\n*/\n#endif\nok", "ok"),
        ("#define F(x) x\n#if F(2) == 2\nok\n#endif", "ok"),
        ("#define D defined(Z)\n#if !D\nok\n#endif", "ok"),
    ]);
    assert_eq!(err("#if 1\n"), "unterminated #if");
    assert_eq!(err("#endif\n"), "#endif without #if");
    assert_eq!(err("#elif 1\n"), "#elif without #if");
    assert_eq!(err("#if 1\n#else\n#elif 1\n#endif\n"), "#elif after #else");
    assert_eq!(err("#if 0\n#else\n#else\n#endif\n"), "#else after #else");
    assert_eq!(err("#if 1 / 0\n#endif\n"), "division by zero in #if");
    assert_eq!(err("#if\n#endif\n"), "#if with no expression");
    assert_eq!(err("#ifdef\n#endif\n"), "no macro name given in #ifdef directive");
    assert_eq!(err("#if defined\n#endif\n"), "operator \"defined\" requires an identifier");
}

#[test]
fn include_and_once() {
    let dir = tempfile::tempdir().expect("temp dir");
    let w = |p: &str, t: &str| {
        let p = dir.path().join(p);
        std::fs::create_dir_all(p.parent().expect("parent")).expect("mkdir");
        std::fs::write(p, t).expect("write");
    };
    w("main.usf", "#include \"a.ush\"\n#include \"a.ush\"\n#include <lib/b.ush>\n#include \"/Engine/c.ush\"\n#define H \"a.ush\"\n#include H\nend\n");
    w("a.ush", "#pragma once\nA\n");
    w("roots/lib/b.ush", "#ifndef B\n#define B\nB_BODY\n#endif\n");
    w("engine/c.ush", "#include <lib/b.ush>\nC\n");
    let cache = SourceCache::new(dir.path().to_path_buf());
    let opts = Options {
        include_roots: vec![dir.path().join("roots")],
        virtual_roots: vec![("/Engine".into(), dir.path().join("engine"))],
        ..Options::default()
    };
    let out = preprocess_file(&dir.path().join("main.usf"), &opts, &cache).expect("preprocesses");
    assert_eq!(tokens(&out.text).join(" "), "A B_BODY C end");
    let names: Vec<String> = out.files.iter().map(|&f| cache.name(f)).collect();
    assert_eq!(names, ["main.usf", "a.ush", "roots/lib/b.ush", "engine/c.ush"]);
    assert_eq!(
        resolve_source("/Engine/c.ush", &opts).expect("resolves"),
        dir.path().join("engine/c.ush").canonicalize().expect("exists")
    );
    assert_eq!(
        resolve_source("lib/b.ush", &opts).expect("resolves"),
        dir.path().join("roots/lib/b.ush").canonicalize().expect("exists")
    );
    assert!(resolve_source("missing.ush", &opts).is_err());
    assert!(resolve_source("../main.usf", &opts).is_err());
}

#[test]
fn error_and_warning() {
    assert_eq!(err("#error stop /* here */ now\n"), "#error stop   now");
    assert_eq!(err("#error\n"), "#error");
    let out = run_with("#warning careful\nx\n", &Options::default()).expect("warnings continue");
    assert_eq!(tokens(&out.text), ["x"]);
    assert_eq!(out.warnings.len(), 1);
    assert_eq!(out.warnings[0].message, "#warning careful");
}

#[test]
fn pragma_and_line() {
    cases(&[
        ("#pragma once\nx", "x"),
        ("#pragma unroll\nx", "# pragma unroll x"),
        ("_Pragma(\"omp parallel\") x", "# pragma omp parallel x"),
        ("#line 10\n__LINE__", "10"),
        ("#line 20 \"other.usf\"\n__LINE__ __FILE__", "20 \"other.usf\""),
        ("# 5 \"marker.usf\"\n__LINE__", "5"),
        ("#\nx", "x"),
        ("\u{feff}#define B 1\nB", "1"),
        ("a\r\n#define C 2\r\nC\r\n", "a 2"),
    ]);
    assert_eq!(err("#nonsense\n"), "invalid preprocessing directive #nonsense");
}

#[test]
fn builtins_and_predefined() {
    cases(&[
        ("__LINE__\n\n__LINE__", "1 3"),
        ("__FILE__", "\"t.usf\""),
        ("__STDC__ __STDC_VERSION__", "1 201112L"),
        ("__COUNTER__ __COUNTER__", "0 1"),
        ("#define L __LINE__\n\nL", "3"),
    ]);
    let opts = Options { defines: vec![("N".into(), "4".into()), ("F(x)".into(), "x*N".into())], ..Options::default() };
    let out = run_with("N F(2)", &opts).expect("ok");
    assert_eq!(tokens(&out.text).join(" "), "4 2 * 4");
}

#[test]
fn wgsl_passes_through() {
    let src = "@group(0) @binding(1) var<uniform> u: array<vec4<f32>, 4>;\nfn f(x: f32) -> f32 { return x; }\n";
    let out = run_with(src, &Options::default()).expect("ok");
    assert_eq!(out.text, src);
    assert_eq!(out.map.len(), 1);
}

#[test]
fn pastes_never_merge_by_accident() {
    cases(&[
        ("#define M -\n-M M- M-1", "- - - - - - 1"),
        ("#define E\na E b", "a b"),
        ("#define F(x) -x\nF(-1)", "- - 1"),
        ("#define S /\nS/ /S", "/ / / /"),
    ]);
}

#[test]
fn macro_errors() {
    assert_eq!(err("#define F(x) x\nF(1, 2)\n"), "macro \"F\" passed 2 arguments, but takes just 1");
    assert_eq!(err("#define F(x, y) x\nF(1)\n"), "macro \"F\" requires 2 arguments, but only 1 given");
    assert_eq!(err("#define F(x) x\nF(1\n"), "unterminated argument list invoking macro \"F\"");
    assert_eq!(err("#define F(x, x) x\n"), "duplicate macro parameter \"x\"");
    assert_eq!(err("#define F(x x\n"), "expected ',' or ')', found \"x\"");
    assert_eq!(err("#define F(x\n"), "missing ')' in macro parameter list");
    assert_eq!(err("#define defined 1\n"), "\"defined\" cannot be used as a macro name");
    assert_eq!(
        err("#define C(a, b) a ## b\nC(+, /)\n"),
        "pasting \"+\" and \"/\" does not give a valid preprocessing token"
    );
    assert_eq!(err("/* open\n"), "unterminated comment");
}

/// The token hash as first written: every token through the general lexer.
fn token_hash_reference(text: &str) -> blake3::Hash {
    let src = text.as_bytes();
    let mut buf = Vec::new();
    let mut pos = 0;
    loop {
        let (kind, len) = lexer::next(src, pos);
        match kind {
            lexer::Kind::Eof => break,
            lexer::Kind::Space | lexer::Kind::Newline | lexer::Kind::LineComment | lexer::Kind::BlockComment { .. } => {
            }
            _ => {
                buf.extend_from_slice(&(len as u32).to_le_bytes());
                buf.extend_from_slice(&src[pos..pos + len]);
            }
        }
        pos += len.max(1);
    }
    blake3::hash(&buf)
}

#[test]
fn token_hash_fast_paths_agree_with_the_lexer() {
    let fixed = [
        "",
        "fn main() -> @location(0) vec4<f32> { return vec4(1.0, 0.5e-3, .5, 0x1p4); }",
        "a+b a + b a/**/+/* x */b // c\n u8\"s\" L'c' U\"x\" u'y' uvw Lx Ux $id é",
        "x <<= y >>= z ... ## %:%: <: :> <% %> -> ++ -- && || \t\r\x0b\x0c end",
        "\"unterminated\n 'c\n /* open",
        "@ ` \\ \u{7f} \u{e9}t\u{e9} 1.e+5 1..2",
    ];
    for text in fixed {
        assert_eq!(token_hash(text), token_hash_reference(text), "{text:?}");
    }
    // Random texts over the bytes that matter to the lexer.
    let alphabet: Vec<char> = "aLuU8_$ 0.e+-\n\t\r/*\"'\\<>=#%:@`(){}[];,?~é".chars().collect();
    let mut state = 0x2545_f491_4f6c_dd1du64;
    for _ in 0..20_000 {
        let len = (state % 64) as usize;
        let mut text = String::new();
        for _ in 0..len {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            text.push(alphabet[(state % alphabet.len() as u64) as usize]);
        }
        assert_eq!(token_hash(&text), token_hash_reference(&text), "{text:?}");
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
    }
    // Texts longer than the hash's buffer, with tokens of every length across its chunks.
    for long in [1usize, 15, 16, 17, 40, 5000, 70_000] {
        let mut text = String::new();
        let mut i = 0;
        while text.len() < 100_000 {
            text.push_str(&"x".repeat(1 + i % long));
            text.push_str(if i % 3 == 0 { " + " } else { "(" });
            i += 1;
        }
        assert_eq!(token_hash(&text), token_hash_reference(&text), "tokens up to {long} bytes");
    }
}

#[test]
fn long_definitions_are_read_when_used() {
    // Past 4096 tokens a body is kept as its place in the source (read on first use).
    let body: String = (0..5000).map(|i| format!(" t{i}")).collect();
    let src = format!("#define L(x){body} x\nL(end)\n");
    let out = pp(&src);
    assert!(out.starts_with("t0 t1 t2 "), "{}", &out[..40]);
    assert!(out.ends_with("t4998 t4999 end"), "{}", &out[out.len() - 40..]);
    // An identical redefinition is quiet, a different one warns.
    let same = run_with(&format!("#define L{body}\n#define L{body}\n"), &Options::default()).expect("ok");
    assert!(same.warnings.is_empty());
    let other = run_with(&format!("#define L{body}\n#define L{body} more\n"), &Options::default()).expect("ok");
    assert_eq!(other.warnings.len(), 1);
    assert_eq!(other.warnings[0].message, "\"L\" redefined");
    // Errors of a long body are found at its definition, used or not.
    let e = err(&format!("#define L(...){body} __VA_OPT__(a __VA_OPT__(b))\n"));
    assert_eq!(e, "__VA_OPT__ may not appear in a __VA_OPT__");
    let e = err(&format!("#define L{body} ##\n"));
    assert_eq!(e, "'##' cannot appear at either end of a macro expansion");
    // A used body larger than the expansion budget is an error before it is read.
    let opts = Options { max_output_bytes: 4096, ..Options::default() };
    let e = run_with(&format!("#define L{body}\nL\n"), &opts).expect_err("over budget");
    assert!(e.to_string().starts_with("macro expansion makes more than"), "{e}");
}

#[test]
fn va_opt_is_checked_at_its_definition() {
    assert_eq!(err("#define F(...) a __VA_OPT__(b __VA_OPT__(c) d) e\n"), "__VA_OPT__ may not appear in a __VA_OPT__");
    assert_eq!(err("#define F(...) a __VA_OPT__(b\n"), "unterminated __VA_OPT__");
    assert_eq!(err("#define F(...) a __VA_OPT__ b\n"), "__VA_OPT__ must be followed by an open parenthesis");
    assert_eq!(err("#define F(...) #__VA_OPT__(#__VA_OPT__(x))\n"), "__VA_OPT__ may not appear in a __VA_OPT__");
    assert_eq!(pp("#define F(...) a __VA_OPT__((b)(c)) d\nF() F(1)"), "a d a ( b ) ( c ) d");
    // Outside a variadic macro it is a name, with cpp's warning.
    let out = run_with("#define A a __VA_OPT__(b)\nA\n", &Options::default()).expect("a warning only");
    assert_eq!(tokens(&out.text).join(" "), "a __VA_OPT__ ( b )");
    assert_eq!(out.warnings[0].message, "__VA_OPT__ can only appear in the expansion of a C++20 variadic macro");
}

#[test]
fn warnings_are_capped() {
    // One warning per line for 1,500 lines: the first thousand kept, the rest counted.
    let out = run_with(&"'\n".repeat(1500), &Options::default()).expect("warnings only");
    assert_eq!(out.warnings.len(), 1001);
    assert_eq!(out.warnings[0].message, "missing terminating ' character");
    assert_eq!(out.warnings[1000].message, "500 more warnings not shown");
}

#[test]
fn long_lines_are_shown_cut() {
    let cache = SourceCache::new(std::env::temp_dir());
    let long = "a ".repeat(5000);
    let src = format!("#define BIG {long}\n#define BIG {long}b\nx\n");
    let id = cache.add_virtual("t.usf", &src);
    let out = preprocess_file_id(id, &Options::default(), &cache).expect("a warning only");
    let r = render(&out.warnings, &cache, false);
    assert!(r.lines().all(|l| l.chars().count() < 3 * MAX_SHOWN_LINE), "{r}");
    assert!(r.contains("2 │ #define BIG a a a"), "{r}");
    assert!(r.contains("a a…\n"), "{r}");
    assert!(r.contains("^^^ redefined here"), "{r}");
}

/// The 1-based lines `src`'s false groups excluded.
fn skipped(src: &str) -> Vec<u32> {
    let out = run_with(src, &Options::default()).expect("preprocesses");
    out.skipped.iter().flat_map(|(_, r)| r.clone()).collect()
}

#[test]
fn skipped_lines() {
    assert_eq!(skipped("#if 0\na\nb\n#endif\nc\n"), [2, 3]);
    assert_eq!(skipped("#if 1\na\n#else\nb\n#endif\n"), [4]);
    assert_eq!(skipped("#if 0\na\n#elif 0\nb\n#elif 1\nc\n#else\nd\n#endif\n"), [2, 4, 8]);
    assert_eq!(skipped("#ifdef X\n#if 1\na\n#endif\n#endif\nb\n"), [2, 3, 4]);
    assert_eq!(skipped("#if 0\n#endif\n"), Vec::<u32>::new());
    assert_eq!(skipped("a\n#if 1 /* x\n y */\nb\n#endif\n"), Vec::<u32>::new());
}

#[test]
fn buffer_text_replaces_the_file_on_disk() {
    let dir = tempfile::tempdir().expect("temp dir");
    let root = dir.path().canonicalize().expect("canonical");
    std::fs::write(root.join("h.ush"), "on_disk").expect("write");
    std::fs::write(root.join("m.usf"), "#include \"h.ush\"\n").expect("write");
    let cache = SourceCache::new(root.clone());
    cache.set_text(&root.join("h.ush"), "in_buffer");
    let out = preprocess_file(&root.join("m.usf"), &Options::default(), &cache).expect("preprocesses");
    assert_eq!(tokens(&out.text), ["in_buffer"]);
    let inc = out.map.includes();
    assert_eq!(inc.len(), 1);
    assert_eq!(cache.path(inc[0].2), root.join("h.ush"));
    assert_eq!(inc[0].1, 0..16);
}
