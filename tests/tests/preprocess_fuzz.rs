//! Garbage in, diagnostics out: random and mutated inputs must give an output or an error,
//! never a panic or a hang.

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::PathBuf;

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
const PIECES: [&str; 48] = [
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
