//! Differential tests: Kiln's preprocessor against GNU `cpp -x c -P -undef -nostdinc -std=c11`
//! on the same files, comparing token streams (whitespace ignored).
//!
//! The corpus is `tests/in/preprocess/*.usf`; a first line `// args: -DNAME=V -Idir` gives
//! extra options to both. Then a few hundred random macro programs from a fixed seed.

use std::path::{Path, PathBuf};
use std::process::Command;

use kiln::preprocess::{self, Options, SourceCache};

const CPP_ARGS: [&str; 6] = ["-x", "c", "-P", "-undef", "-nostdinc", "-std=c11"];

fn package_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Fails with a clear message when `cpp` is missing: these tests need it.
fn require_cpp() {
    match Command::new("cpp").arg("--version").output() {
        Ok(o) if o.status.success() => {}
        _ => panic!(
            "the differential preprocessor tests need GNU `cpp` on PATH (Debian/Ubuntu: `apt-get install cpp`); \
             `.ci/run` installs it"
        ),
    }
}

/// Runs cpp from `cwd` on `file` (relative to `cwd`). Ok(stdout) or Err(stderr); a signed
/// overflow in `#if`, which cpp warns about, counts as a failure.
fn run_cpp(cwd: &Path, file: &Path, args: &[String]) -> Result<String, String> {
    let out = Command::new("cpp").args(CPP_ARGS).args(args).arg(file).current_dir(cwd).output().expect("cpp runs");
    // Kiln makes cpp's pedantic warning on signed overflow an error (as `-pedantic-errors`).
    let overflow = String::from_utf8_lossy(&out.stderr).contains("integer overflow in preprocessor expression");
    if out.status.success() && !overflow {
        Ok(String::from_utf8_lossy(&out.stdout).into_owned())
    } else {
        Err(String::from_utf8_lossy(&out.stderr).into_owned())
    }
}

/// Runs Kiln on `file` the way `kiln preprocess` does from `cwd`.
fn run_kiln(cwd: &Path, file: &Path, args: &[String]) -> Result<String, String> {
    let mut opts = Options::default();
    for a in args {
        if let Some(d) = a.strip_prefix("-D") {
            let (n, v) = d.split_once('=').unwrap_or((d, "1"));
            opts.defines.push((n.to_string(), v.to_string()));
        } else if let Some(i) = a.strip_prefix("-I") {
            opts.include_roots.push(cwd.join(i));
        }
    }
    let cache = SourceCache::new(cwd.to_path_buf());
    // The file name relative to `cwd`, as cpp sees it (for `__FILE__`).
    let prev = std::env::current_dir().ok();
    let abs = cwd.join(file);
    let result = if prev.as_deref() == Some(cwd) {
        preprocess::preprocess_file(file, &opts, &cache)
    } else {
        preprocess::preprocess_file(&abs, &opts, &cache)
    };
    result.map(|o| o.text).map_err(|e| preprocess::render(&[e.diagnostic], &cache, false))
}

fn args_of(text: &str) -> Vec<String> {
    match text.lines().next().and_then(|l| l.strip_prefix("// args:")) {
        Some(rest) => rest.split_whitespace().map(str::to_string).collect(),
        None => Vec::new(),
    }
}

/// Compares one file; `None` if the token streams agree (or both fail).
fn compare(cwd: &Path, file: &Path, args: &[String]) -> Option<String> {
    let cpp = run_cpp(cwd, file, args);
    let kiln = run_kiln(cwd, file, args);
    match (&cpp, &kiln) {
        (Ok(a), Ok(b)) => {
            let (ta, tb) = (preprocess::tokens(a), preprocess::tokens(b));
            if ta == tb {
                return None;
            }
            let i = ta.iter().zip(&tb).position(|(x, y)| x != y).unwrap_or(ta.len().min(tb.len()));
            let ctx = |t: &[&str]| t[i.saturating_sub(6)..(i + 6).min(t.len())].join(" ");
            Some(format!(
                "{}: token {i} differs\n   cpp: {}\n  kiln: {}\n--- cpp output\n{a}\n--- kiln output\n{b}",
                file.display(),
                ctx(&ta),
                ctx(&tb)
            ))
        }
        (Err(_), Err(_)) => None,
        (Ok(_), Err(e)) => Some(format!("{}: cpp succeeds, kiln fails:\n{e}", file.display())),
        (Err(e), Ok(_)) => Some(format!("{}: cpp fails, kiln succeeds; cpp says:\n{e}", file.display())),
    }
}

#[test]
fn corpus_matches_cpp() {
    require_cpp();
    let cwd = package_dir();
    let dir = cwd.join("in/preprocess");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .expect("tests/in/preprocess exists")
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "usf"))
        .collect();
    files.sort();
    assert!(files.len() >= 20, "the corpus has {} cases", files.len());
    let mut failures = Vec::new();
    for f in &files {
        let rel = f.strip_prefix(&cwd).expect("inside the package");
        let text = std::fs::read_to_string(f).expect("readable");
        let args = args_of(&text);
        // Every corpus case is valid C preprocessor input.
        if let Err(e) = run_cpp(&cwd, rel, &args) {
            failures.push(format!("{}: cpp rejects a corpus case:\n{e}", rel.display()));
            continue;
        }
        if let Some(f) = compare(&cwd, rel, &args) {
            failures.push(f);
        }
    }
    assert!(
        failures.is_empty(),
        "{} of {} cases differ from cpp:\n\n{}",
        failures.len(),
        files.len(),
        failures.join("\n\n")
    );
}

/// A small deterministic generator (xorshift64*).
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }
    fn pick<'a>(&mut self, items: &[&'a str]) -> &'a str {
        items[self.below(items.len())]
    }
    fn chance(&mut self, percent: usize) -> bool {
        self.below(100) < percent
    }
}

const OBJ: [&str; 5] = ["A", "B", "C", "D", "E"];
const FUN: [&str; 5] = ["F", "G", "H", "J", "K"];
const PLAIN: [&str; 8] = ["x", "y", "1", "2", "+", "*", "-", "."];

/// Parameter counts of the function-like macros defined so far (so most calls are valid).
type Sigs = std::collections::HashMap<&'static str, (usize, bool)>;

/// One random macro definition.
fn gen_define(r: &mut Rng, out: &mut String, sigs: &mut Sigs) {
    let func = r.chance(60);
    let name = if func { r.pick(&FUN) } else { r.pick(&OBJ) };
    let mut params: Vec<&str> = Vec::new();
    let mut variadic = false;
    if func {
        let n = r.below(4);
        params.extend(["p", "q", "s"].iter().take(n));
        variadic = r.chance(25);
        let mut list: Vec<&str> = params.clone();
        if variadic {
            list.push("...");
        }
        out.push_str(&format!("#define {name}({})", list.join(", ")));
        sigs.insert(name, (params.len(), variadic));
    } else {
        out.push_str(&format!("#define {name}"));
    }
    let len = r.below(7);
    let mut prev_operand = false;
    for i in 0..len {
        out.push(' ');
        let roll = r.below(100);
        let item: String = if roll < 25 && (!params.is_empty() || variadic) {
            let mut all = params.clone();
            if variadic {
                all.push("__VA_ARGS__");
            }
            let p = r.pick(&all);
            if r.chance(20) {
                format!("#{p}")
            } else {
                p.to_string()
            }
        } else if roll < 45 {
            r.pick(&OBJ).to_string()
        } else if roll < 65 {
            r.pick(&FUN).to_string()
        } else if roll < 75 {
            r.pick(&["(", ")", ","]).to_string()
        } else if roll < 85 && prev_operand && i + 1 < len {
            // Paste onto something that makes a valid token most of the time.
            format!("## {}", r.pick(&["x", "y", "1", "A", "F"]))
        } else if roll < 88 && variadic && prev_operand {
            ", ## __VA_ARGS__".to_string()
        } else {
            r.pick(&PLAIN).to_string()
        };
        prev_operand = item != "##";
        out.push_str(&item);
    }
    out.push('\n');
}

/// A random piece of text using the macros: names, calls with balanced arguments, noise.
fn gen_use(r: &mut Rng, out: &mut String, depth: usize, sigs: &Sigs) {
    let n = 1 + r.below(6);
    for _ in 0..n {
        let roll = r.below(100);
        if roll < 30 {
            out.push_str(r.pick(&OBJ));
        } else if roll < 70 && depth < 3 {
            let f = r.pick(&FUN);
            out.push_str(f);
            if r.chance(85) {
                out.push('(');
                let args = match sigs.get(f) {
                    Some(&(n, variadic)) if r.chance(90) => n + if variadic { r.below(3) } else { 0 },
                    _ => r.below(4),
                };
                for a in 0..args {
                    if a > 0 {
                        out.push(',');
                    }
                    if r.chance(70) {
                        gen_use(r, out, depth + 1, sigs);
                    }
                }
                out.push(')');
            }
        } else if roll < 75 {
            out.push('\n');
        } else if roll < 77 && depth == 0 {
            out.push_str("XSTR(");
            gen_use(r, out, depth + 1, sigs);
            out.push(')');
        } else {
            out.push_str(r.pick(&PLAIN));
        }
        out.push(' ');
    }
}

/// A random `#if` expression over constants, macros and operators.
fn gen_expr(r: &mut Rng, out: &mut String, depth: usize) {
    let roll = r.below(100);
    if depth > 3 || roll < 35 {
        let term =
            r.pick(&["0", "1", "2", "7", "0x10", "10u", "3000000000", "9223372036854775807", "'a'", "A", "B", "Z"]);
        out.push_str(term);
    } else if roll < 45 {
        out.push_str(&format!("defined({})", r.pick(&["A", "F", "Z"])));
    } else if roll < 55 {
        out.push_str(r.pick(&["!", "~", "-", "+"]));
        out.push(' ');
        gen_expr(r, out, depth + 1);
    } else if roll < 65 {
        out.push('(');
        gen_expr(r, out, depth + 1);
        out.push_str(" ? ");
        gen_expr(r, out, depth + 1);
        out.push_str(" : ");
        gen_expr(r, out, depth + 1);
        out.push(')');
    } else {
        out.push('(');
        gen_expr(r, out, depth + 1);
        let ops = ["+", "-", "*", "/", "%", "<<", ">>", "<", ">", "<=", ">=", "==", "!=", "&", "|", "^", "&&", "||"];
        out.push_str(&format!(" {} ", r.pick(&ops)));
        gen_expr(r, out, depth + 1);
        out.push(')');
    }
}

fn gen_program(r: &mut Rng) -> String {
    // Stringizing after expansion shows spacing, which the token comparison then checks.
    let mut out = String::from("#define STR(x) #x\n#define XSTR(x) STR(x)\n");
    let mut sigs = Sigs::new();
    for _ in 0..(4 + r.below(6)) {
        if r.chance(70) {
            gen_define(r, &mut out, &mut sigs);
        } else {
            gen_use(r, &mut out, 0, &sigs);
            out.push('\n');
            if r.chance(30) {
                let mut e = String::new();
                gen_expr(r, &mut e, 0);
                out.push_str(&format!("#if {e}\nyes\n#else\nno\n#endif\n"));
            }
            if r.chance(20) {
                let f = r.pick(&FUN);
                sigs.remove(f);
                out.push_str(&format!("#undef {f}\n"));
            }
        }
    }
    for _ in 0..4 {
        gen_use(r, &mut out, 0, &sigs);
        out.push('\n');
    }
    out
}

#[test]
fn random_macro_programs_match_cpp() {
    require_cpp();
    let dir = tempfile::tempdir().expect("temp dir");
    // `KILN_RANDOM_PROGRAMS=N` and `KILN_RANDOM_SEED=S` run a longer or different search.
    let count: usize = std::env::var("KILN_RANDOM_PROGRAMS").ok().and_then(|v| v.parse().ok()).unwrap_or(400);
    let seed: u64 =
        std::env::var("KILN_RANDOM_SEED").ok().and_then(|v| v.parse().ok()).unwrap_or(0x5eed_1234_abcd_0001);
    let mut r = Rng(seed | 1);
    let mut failures = Vec::new();
    let (mut ok, mut both_fail) = (0, 0);
    for i in 0..count {
        let program = gen_program(&mut r);
        let name = PathBuf::from(format!("gen{i}.usf"));
        std::fs::write(dir.path().join(&name), &program).expect("write");
        let cpp_ok = run_cpp(dir.path(), &name, &[]).is_ok();
        match compare(dir.path(), &name, &[]) {
            None if cpp_ok => ok += 1,
            None => both_fail += 1,
            Some(f) => failures.push(format!("program {i}:\n{program}\n{f}")),
        }
    }
    assert!(
        failures.is_empty(),
        "{} random programs differ from cpp:\n\n{}",
        failures.len(),
        failures.iter().take(5).cloned().collect::<Vec<_>>().join("\n\n")
    );
    // The generator must mostly make valid programs, or the test proves little.
    assert!(ok * 2 >= count, "only {ok} of {count} programs valid ({both_fail} rejected by both)");
}

/// A random valid `#if` expression: constants, `defined`, every operator (divisors are
/// never zero), signed and unsigned operands.
fn gen_const_expr(r: &mut Rng, out: &mut String, depth: usize) {
    let roll = r.below(100);
    if depth > 4 || roll < 30 {
        let consts = [
            "0",
            "1",
            "2",
            "7",
            "63",
            "64",
            "0x10",
            "10u",
            "0u",
            "3000000000",
            "9223372036854775807",
            "0xffffffffffffffff",
            "'a'",
            "'\\377'",
            "N",
            "UNDEFINED",
        ];
        out.push_str(r.pick(&consts));
    } else if roll < 38 {
        out.push_str(&format!("defined({})", r.pick(&["N", "UNDEFINED"])));
    } else if roll < 50 {
        out.push_str(r.pick(&["!", "~", "-", "+"]));
        out.push(' ');
        gen_const_expr(r, out, depth + 1);
    } else if roll < 60 {
        out.push('(');
        gen_const_expr(r, out, depth + 1);
        out.push_str(" ? ");
        gen_const_expr(r, out, depth + 1);
        out.push_str(" : ");
        gen_const_expr(r, out, depth + 1);
        out.push(')');
    } else if roll < 66 {
        out.push('(');
        gen_const_expr(r, out, depth + 1);
        out.push_str(&format!(" {} ", r.pick(&["/", "%"])));
        out.push_str(r.pick(&["1", "2", "7", "3u", "-3", "N"]));
        out.push(')');
    } else {
        let ops = ["+", "-", "*", "<<", ">>", "<", ">", "<=", ">=", "==", "!=", "&", "|", "^", "&&", "||"];
        out.push('(');
        gen_const_expr(r, out, depth + 1);
        out.push_str(&format!(" {} ", r.pick(&ops)));
        gen_const_expr(r, out, depth + 1);
        out.push(')');
    }
}

#[test]
fn random_if_expressions_match_cpp() {
    require_cpp();
    let dir = tempfile::tempdir().expect("temp dir");
    let seed: u64 =
        std::env::var("KILN_RANDOM_SEED").ok().and_then(|v| v.parse().ok()).unwrap_or(0x1f1f_2e2e_3d3d_4c4b);
    let files: usize =
        std::env::var("KILN_RANDOM_PROGRAMS").ok().and_then(|v| v.parse().ok()).map_or(4, |n: usize| n / 100);
    let mut r = Rng(seed | 1);
    let mut failures = Vec::new();
    for file in 0..files {
        let mut program = String::from("#define N 5\n");
        for i in 0..250 {
            let mut e = String::new();
            gen_const_expr(&mut r, &mut e, 0);
            program.push_str(&format!("#if {e}\nt{i}\n#else\nf{i}\n#endif\n"));
        }
        let name = PathBuf::from(format!("expr{file}.usf"));
        std::fs::write(dir.path().join(&name), &program).expect("write");
        // Expressions whose signed arithmetic overflows (cpp warns, Kiln refuses) are
        // checked by the unit tests; the rest of the file is compared here.
        if let Err(e) = run_cpp(dir.path(), &name, &[]) {
            let prefix = format!("{}:", name.display());
            let warned: Vec<usize> = e
                .lines()
                .filter(|l| l.contains("integer overflow in preprocessor expression") && l.starts_with(&prefix))
                .filter_map(|l| l[prefix.len()..].split(':').next()?.parse().ok())
                .collect();
            assert!(!warned.is_empty(), "cpp must accept every generated expression:\n{e}");
            // Expression i's `#if` is line 2 + 5i (after `#define N 5`), five lines each.
            let lines: Vec<&str> = program.lines().collect();
            let mut kept = String::new();
            for (i, block) in lines[1..].chunks(5).enumerate() {
                if !warned.contains(&(2 + 5 * i)) {
                    kept.push_str(&block.join("\n"));
                    kept.push('\n');
                }
            }
            program = format!("{}\n{kept}", lines[0]);
            std::fs::write(dir.path().join(&name), &program).expect("write");
            if let Err(e) = run_cpp(dir.path(), &name, &[]) {
                panic!("cpp must accept every generated expression:\n{e}");
            }
        }
        if let Some(f) = compare(dir.path(), &name, &[]) {
            failures.push(f);
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n\n"));
}

/// Replacement lists longer than Kiln keeps as tokens at their `#define` (4096) are read
/// again from the source on first use: parameters, `#`, `##`, `__VA_OPT__`, a comment and a
/// line splice inside, an identical redefinition, and `#undef` of one never used.
#[test]
fn long_definitions_match_cpp() {
    require_cpp();
    let dir = tempfile::tempdir().expect("temp dir");
    let mut program = String::from("#define STR(x) #x\n#define XSTR(x) STR(x)\n");
    let func: String = (0..800).map(|i| format!(" a{i} + b ## {i} #a __VA_OPT__(, __VA_ARGS__) /* c */")).collect();
    program.push_str(&format!("#define L1(a, b, ...){func}\n"));
    program.push_str(&format!("#define L1(a, b, ...){func}\n"));
    program.push_str("L1(p, q) L1(p, q, r, s)\nXSTR((L1(x, y, z)))\n");
    let obj: String = (0..3000).map(|i| format!(" y{i} z ## {i}")).collect();
    program.push_str(&format!("#define L2{obj} \\\n tail\nL2 L2\n"));
    let unused: String = (0..5000).map(|i| format!(" u{i}")).collect();
    program.push_str(&format!("#define L3{unused}\n#undef L3\nL3\n"));
    let name = PathBuf::from("long.usf");
    std::fs::write(dir.path().join(&name), &program).expect("write");
    if let Err(e) = run_cpp(dir.path(), &name, &[]) {
        panic!("cpp must accept the program:\n{e}");
    }
    if let Some(f) = compare(dir.path(), &name, &[]) {
        panic!("{}", &f[..f.len().min(4000)]);
    }
}

/// Small programs where Kiln once differed from cpp (issue 16): `##` at a line start is text,
/// not a directive (also in a skipped group, and `%:%:`); a lone CR ends a line as `\n` does
/// (and CRLF), in text, directives, splices, comments and `__LINE__`.
#[test]
fn line_starts_and_line_endings_match_cpp() {
    require_cpp();
    let dir = tempfile::tempdir().expect("temp dir");
    let cases: [(&str, &str); 10] = [
        ("hash_hash", "a\n## b\n  ## c\n%:%: d\n#define X 1\nX ## X\n"),
        ("hash_hash_skipped", "#if 0\n##if 1\n#endif\nok\n#if 0\n## else\nno\n#endif\n"),
        ("hash_hash_args", "#define F(x) [x]\nF(\n## y\n)\n"),
        ("cr", "a\r##b\rc\r#define X 1\rX __LINE__\r"),
        ("crlf", "a\r\n#define X 2\r\nX __LINE__\r\n#if X == 2\r\nyes\r\n#endif\r\n"),
        ("mixed", "a\r\n\rb\n\r\n#define Y __LINE__\rY\r\n__LINE__\n"),
        ("cr_splice", "#define Z 1 + \\\r 2\rZ __LINE__\r"),
        ("cr_comment", "a // comment\rb /* multi\r line */ c\r__LINE__\r"),
        ("cr_skipped", "#if 0\rno\r#else\ryes __LINE__\r#endif\r"),
        ("cr_args", "#define F(x, y) x y\rF(1,\r2)\r__LINE__\r"),
    ];
    let mut failures = Vec::new();
    for (name, text) in cases {
        let file = PathBuf::from(format!("{name}.usf"));
        std::fs::write(dir.path().join(&file), text).expect("write");
        if let Err(e) = run_cpp(dir.path(), &file, &[]) {
            panic!("cpp must accept {name}:\n{e}");
        }
        if let Some(f) = compare(dir.path(), &file, &[]) {
            failures.push(f);
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n\n"));
}

/// Every punctuator the lexer knows (with digraphs), a few other tokens, and WGSL's `@`.
const SPACING_TOKENS: [&str; 62] = [
    "%:%:", "...", "<<=", ">>=", "->", "--", "-=", "++", "+=", "<<", "<=", "<:", "<%", ">>", ">=", "==", "!=", "*=",
    "/=", "^=", "&&", "&=", "||", "|=", "##", "%=", "%>", "%:", ":>", "[", "]", "(", ")", "{", "}", ".", "&", "*", "+",
    "-", "~", "!", "/", "%", "<", ">", "^", "|", "?", ":", ";", "=", ",", "#", "@", "x", "L", "u8", "1", ".5", "\"s\"",
    "'c'",
];

/// Token spacing (issue 14): `kiln preprocess` keeps apart every pair of tokens that cpp
/// keeps apart where they meet at a macro expansion's edge (`#define DOT() .` then
/// `DOT()DOT()DOT()` is `. . .`, Wave's t_9_003). Every pair of tokens above, each made by a
/// macro (`I(a)I(b)`), a macro then text (`I(a)b`), text then a macro (`a I(b)` where `a`
/// cannot merge with the name), and three in a row; the token streams must agree.
#[test]
fn token_spacing_matches_cpp_for_every_pair() {
    require_cpp();
    let dir = tempfile::tempdir().expect("temp dir");
    // `,` `(` `)` cannot be a macro argument alone: they come from object-like macros.
    let made = |t: &str| match t {
        "," => "COMMA".to_string(),
        "(" => "LP".to_string(),
        ")" => "RP".to_string(),
        _ => format!("I({t})"),
    };
    let mut program = String::from("#define I(x) x\n#define COMMA ,\n#define LP (\n#define RP )\n#define DOT() .\n");
    program.push_str("DOT()DOT()DOT()\n");
    for a in SPACING_TOKENS {
        for b in SPACING_TOKENS {
            program.push_str(&format!("{}{}\n", made(a), made(b)));
            program.push_str(&format!("{}{}{}\n", made(a), made(b), made(a)));
            // After a macro, text: `b` itself (a `#` at a line start is no longer at one).
            program.push_str(&format!("{}{b}\n", made(a)));
            let word_like = a.as_bytes()[a.len() - 1].is_ascii_alphanumeric() || a.ends_with(['"', '\'']);
            if !word_like && !matches!(a, "#" | "%:" | "##" | "%:%:") {
                program.push_str(&format!("{a}{}\n", made(b)));
            }
        }
    }
    let name = PathBuf::from("spacing.usf");
    std::fs::write(dir.path().join(&name), &program).expect("write");
    if let Err(e) = run_cpp(dir.path(), &name, &[]) {
        panic!("cpp must accept the program:\n{}", &e[..e.len().min(3000)]);
    }
    let cpp = run_cpp(dir.path(), &name, &[]).expect("cpp");
    let kiln = run_kiln(dir.path(), &name, &[]).expect("kiln preprocesses it");
    // Line by line (`-P` may join or drop blank lines, so compare the lines with tokens).
    let lines = |s: &str| -> Vec<Vec<String>> {
        s.lines()
            .map(|l| preprocess::tokens(l).into_iter().map(str::to_string).collect::<Vec<_>>())
            .filter(|t| !t.is_empty())
            .collect()
    };
    let (a, b) = (lines(&cpp), lines(&kiln));
    let source: Vec<&str> = program.lines().skip(5).collect();
    let mut failures = Vec::new();
    for (i, (x, y)) in a.iter().zip(&b).enumerate() {
        if x != y {
            failures.push(format!(
                "{}\n   cpp: {}\n  kiln: {}",
                source.get(i).unwrap_or(&"?"),
                x.join(" "),
                y.join(" ")
            ));
        }
    }
    assert_eq!(a.len(), b.len(), "line counts differ");
    assert!(
        failures.is_empty(),
        "{} of {} lines differ:\n{}",
        failures.len(),
        a.len(),
        failures[..failures.len().min(30)].join("\n")
    );
}
