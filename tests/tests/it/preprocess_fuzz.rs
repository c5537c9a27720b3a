//! Garbage in, diagnostics out: random and mutated inputs must give an output or an error,
//! never a panic or a hang.
//!
//! The hostile classes of issue 16 have their own loop (`hostile_classes_never_panic_or_hang`):
//! CR and CRLF line endings, bytes that are not UTF-8, `##` at a line start, nested
//! `__VA_OPT__`, huge lines, calls with many arguments, long definitions. Each case runs on
//! its own thread under a time guard, and every error must point at the source.

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::Duration;

use kiln::preprocess::{self, Options, SourceCache};

struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

/// Pieces that make preprocessor-shaped garbage.
const PIECES: [&str; 58] = [
    "\r",
    "\r\n",
    "\n##",
    "\n%:%:",
    "__VA_OPT__(",
    "#define V(...) ",
    "V(",
    "\\\r",
    "#if 0\n",
    "#include \"sub\"\n",
    "#",
    "#define ",
    "#undef ",
    "#if ",
    "#ifdef ",
    "#ifndef ",
    "#elif ",
    "#else",
    "#endif",
    "#include ",
    "#error ",
    "#warning ",
    "#pragma ",
    "#line ",
    "defined",
    "(",
    ")",
    ",",
    "##",
    "#",
    "\"",
    "'",
    "/*",
    "*/",
    "//",
    "\\\n",
    "\n",
    " ",
    "A",
    "B",
    "F",
    "x",
    "__VA_ARGS__",
    "...",
    "0",
    "1",
    "/",
    "%",
    "<",
    ">",
    "?",
    ":",
    "??=",
    "%:",
    "__LINE__",
    "__FILE__",
    "_Pragma",
    "\u{e9}",
];

fn check(text: &str, what: &str) {
    let cache = SourceCache::new(std::env::temp_dir());
    let id = cache.add_virtual("fuzz.usf", text);
    let opts = Options { max_output_bytes: 1 << 18, max_expansion_depth: 64, ..Options::default() };
    let result = catch_unwind(AssertUnwindSafe(|| {
        match preprocess::preprocess_file_id(id, &opts, &cache) {
            Ok(out) => {
                // Every output byte has an origin or sits in generated spacing; rendering works.
                let _ = out.map.origin(out.text.len() / 2);
                let _ = preprocess::render(&out.warnings, &cache, false);
            }
            Err(e) => {
                let r = preprocess::render(&[e.diagnostic], &cache, false);
                assert!(r.starts_with("error"), "{r}");
                // A panic inside the preprocessor's worker thread comes back as this error.
                assert!(!r.contains("internal error"), "{r}");
                // Every error points at the source.
                assert!(r.contains("┌─ fuzz.usf:"), "an error without a location:\n{r}\non {text:?}");
            }
        }
    }));
    if result.is_err() {
        panic!("the preprocessor panicked on {what}:\n{text:?}");
    }
}

#[test]
fn random_pieces_never_panic() {
    // `KILN_FUZZ_ITERS=N` runs a longer search.
    let iters: usize = std::env::var("KILN_FUZZ_ITERS").ok().and_then(|v| v.parse().ok()).unwrap_or(3000);
    let seed: u64 = std::env::var("KILN_FUZZ_SEED").ok().and_then(|v| v.parse().ok()).unwrap_or(0xfeed_beef_1234_5679);
    let mut r = Rng(seed | 1);
    for i in 0..iters {
        let n = 1 + r.below(60);
        let mut s = String::new();
        for _ in 0..n {
            s.push_str(PIECES[r.below(PIECES.len())]);
        }
        check(&s, &format!("random input {i}"));
    }
}

#[test]
fn random_bytes_never_panic() {
    let mut r = Rng(0x0123_4567_89ab_cdef);
    for i in 0..1000 {
        let n = r.below(200);
        let bytes: Vec<u8> = (0..n).map(|_| r.below(128) as u8).collect();
        let s = String::from_utf8_lossy(&bytes).into_owned();
        check(&s, &format!("random bytes {i}"));
    }
}

#[test]
fn mutated_corpus_never_panics() {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("in/preprocess");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .expect("corpus")
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "usf"))
        .collect();
    files.sort();
    let mut r = Rng(0xabad_cafe_0000_0001);
    for f in &files {
        let text = std::fs::read_to_string(f).expect("readable");
        for m in 0..40 {
            let mut b: Vec<char> = text.chars().collect();
            for _ in 0..1 + r.below(4) {
                if b.is_empty() {
                    break;
                }
                let at = r.below(b.len());
                match r.below(3) {
                    0 => {
                        let len = r.below(12).min(b.len() - at);
                        b.drain(at..at + len);
                    }
                    1 => {
                        for c in PIECES[r.below(PIECES.len())].chars().rev() {
                            b.insert(at, c);
                        }
                    }
                    _ => {
                        let len = r.below(30).min(b.len() - at);
                        let dup: Vec<char> = b[at..at + len].to_vec();
                        let to = r.below(b.len());
                        for (k, c) in dup.into_iter().enumerate() {
                            b.insert(to + k, c);
                        }
                    }
                }
            }
            let s: String = b.into_iter().collect();
            check(&s, &format!("mutation {m} of {}", f.display()));
        }
    }
}

#[test]
fn deep_nesting_is_an_error_not_a_stack_overflow() {
    // Test threads have small stacks: these must fail cleanly well before that matters.
    let args = format!("#define f(x) x\n{}1{}\n", "f(".repeat(5000), ")".repeat(5000));
    let parens = format!("#if {}1{}\n#endif\n", "(".repeat(50_000), ")".repeat(50_000));
    let includes_text = "#include \"fuzz.usf\"\n";
    for (what, text) in
        [("nested arguments", args.as_str()), ("nested parentheses", parens.as_str()), ("self include", includes_text)]
    {
        let cache = SourceCache::new(std::env::temp_dir());
        let id = cache.add_virtual("fuzz.usf", text);
        let r = preprocess::preprocess_file_id(id, &Options::default(), &cache);
        let e = r.expect_err(what);
        assert!(!e.to_string().contains("internal error"), "{what}: {e}");
    }
}

/// A case that takes longer than this hangs (linear work on these inputs takes well under a
/// second in a debug build).
const GUARD: Duration = Duration::from_secs(30);

/// Preprocesses `bytes` as a file on disk (so bytes that are not UTF-8 reach the reader) on
/// its own thread: it must answer within [`GUARD`], without a panic, and an error must be
/// located (a `┌─ file:line:column` in its rendering).
fn check_file(dir: &Path, bytes: Vec<u8>, what: &str) {
    let path = dir.join("fuzz.usf");
    std::fs::write(&path, &bytes).expect("write");
    let (tx, rx) = mpsc::channel();
    let root = dir.to_path_buf();
    std::thread::spawn(move || {
        let cache = SourceCache::new(root.clone());
        let opts = Options { max_output_bytes: 1 << 20, include_roots: vec![root], ..Options::default() };
        let r = catch_unwind(AssertUnwindSafe(|| match preprocess::preprocess_file(&path, &opts, &cache) {
            Ok(out) => {
                let _ = out.map.origin(out.text.len() / 2);
                Ok(preprocess::render(&out.warnings, &cache, false))
            }
            Err(e) => Err(preprocess::render(&[e.diagnostic], &cache, false)),
        }));
        let _ = tx.send(r);
    });
    let shown = || {
        let s = String::from_utf8_lossy(&bytes);
        if s.len() > 400 {
            format!("{:?}... ({} bytes)", &s[..s.floor_char_boundary(400)], bytes.len())
        } else {
            format!("{s:?}")
        }
    };
    match rx.recv_timeout(GUARD) {
        Err(_) => panic!("{what}: no answer within {GUARD:?} (a hang) on\n{}", shown()),
        Ok(Err(_)) => panic!("{what}: the preprocessor panicked on\n{}", shown()),
        Ok(Ok(Ok(_))) => {}
        Ok(Ok(Err(r))) => {
            assert!(r.starts_with("error"), "{what}: {r}");
            assert!(!r.contains("internal error"), "{what}: {r}\non\n{}", shown());
            assert!(
                r.contains("┌─ fuzz.usf:") || r.contains("┌─ sub"),
                "{what}: an error without a location:\n{r}\non\n{}",
                shown()
            );
        }
    }
}

/// Pieces of the hostile classes, as bytes.
const HOSTILE: [&[u8]; 30] = [
    b"\r",
    b"\r\n",
    b"\n",
    b"\n##",
    b"##",
    b"%:%:",
    b"\xff",
    b"\xe9",
    b"\xc3",
    b"\xf0\x9f",
    b"\xc3\xa9",
    b"#define F(...) ",
    b"#define G(x, y) ",
    b"__VA_OPT__(",
    b"__VA_OPT__",
    b"__VA_ARGS__",
    b"F(",
    b"G(",
    b")",
    b",",
    b"#",
    b" ## ",
    b"/*",
    b"*/",
    b"\\",
    b"#if 0\n",
    b"#endif\n",
    b"__LINE__",
    b"x",
    b"\"",
];

#[test]
fn hostile_classes_never_panic_or_hang() {
    let dir = tempfile::tempdir().expect("temp dir");
    std::fs::create_dir_all(dir.path().join("sub")).expect("mkdir");
    let iters: usize = std::env::var("KILN_FUZZ_ITERS").ok().and_then(|v| v.parse().ok()).unwrap_or(600);
    let mut r = Rng(0x0bad_5eed_1616_0001);
    for i in 0..iters {
        let mut b = Vec::new();
        for _ in 0..1 + r.below(40) {
            b.extend_from_slice(HOSTILE[r.below(HOSTILE.len())]);
        }
        check_file(dir.path(), b, &format!("hostile pieces {i}"));
    }
    // Big instances of each class, a few sizes each: huge lines, many arguments, long
    // definitions (used and not), long ## chains, CR-only files, bad bytes deep in a file.
    let big = |n: usize| -> Vec<(String, Vec<u8>)> {
        vec![
            ("__LINE__ on one line".into(), "__LINE__ ".repeat(n).into_bytes()),
            ("many arguments".into(), format!("#define G(x, y) x\nG({})\n", "a,".repeat(n)).into_bytes()),
            ("many arguments, unterminated".into(), format!("#define G(x, y) x\nG({}", "(a),".repeat(n)).into_bytes()),
            (
                "variadic, many arguments".into(),
                format!("#define F(...) __VA_OPT__(<__VA_ARGS__>)\nF({})\n", "a,".repeat(n)).into_bytes(),
            ),
            ("a long definition".into(), format!("#define L {}\nL L\n", "t + ".repeat(n)).into_bytes()),
            ("a long unused definition".into(), format!("#define L(x) {} x\n", "#x ## y".repeat(n)).into_bytes()),
            ("a long ## chain".into(), format!("#define P {}\nP\n", "a ## ".repeat(n) + "b").into_bytes()),
            ("CR-only lines".into(), "#define X 1\rX __LINE__\r##\r".repeat(n / 8 + 1).into_bytes()),
            (
                "nested __VA_OPT__".into(),
                format!("#define F(...) {}\n", "__VA_OPT__(".repeat(n / 100 + 2)).into_bytes(),
            ),
            ("a huge line of punctuation".into(), "+-*/%<>=!&|^~?:;.,#".repeat(n / 4).into_bytes()),
            ("bad bytes at the end".into(), {
                let mut v = "x\n".repeat(n).into_bytes();
                v.extend_from_slice(b"caf\xe9\n");
                v
            }),
            (
                "unterminated comment skipped".into(),
                format!("#if 0\n{}/* open\n#endif\n", "x\r".repeat(n)).into_bytes(),
            ),
        ]
    };
    for n in [1_000, 40_000] {
        for (what, bytes) in big(n) {
            check_file(dir.path(), bytes, &format!("{what} ({n})"));
        }
    }
}
