//! Typed permutation keys (`kiln::Build::rust_bindings`): the generated file compiles on its
//! own with rustc, and a program built from it names every permutation exactly as
//! `kiln list --all --json` does, skipped ones included.

use std::path::{Path, PathBuf};
use std::process::Command;

/// Every dimension kind, keyword and odd names, and skip rules that exercise the `#if`
/// language: unsigned arithmetic, shifts, `defined`, unknown identifiers, the comma operator,
/// short-circuits, signed division, shader defines overriding the level's.
const CONFIG: &str = r#"
[compiler]
include = ["src"]

[levels.sm5]
defines = { FEATURE_LEVEL = 5, SM5_PROFILE = 1, BIG = 9223372036854775807 }
targets = ["wgsl"]

[levels.es3_1]
defines = { FEATURE_LEVEL = 3, ES3_1_PROFILE = 1 }
targets = ["wgsl"]

[[shader]]
name = "ForwardPS"
source = "a.usf"
entry = "main"
stage = "fragment"
defines = { FEATURE_LEVEL = 4 }
dimensions = { HQ_SHADOWS = "bool", LIGHTS = [0, 1, 2, 4], QUALITY = { range = [-2, 3] }, BLEND_MODE = { enum = ["OPAQUE", "DEFAULT_LIT", "TRANSLUCENT"] }, TYPE = "bool" }
skip = [
  { when = "BLEND_MODE == BLEND_MODE_TRANSLUCENT && LIGHTS > 2", why = "translucency takes \"at most\" 2 lights" },
  { when = "QUALITY * 2 / (LIGHTS + 1) == 1 && -7 % 2 == -1", why = "quality twice the lights" },
  { when = "(-1 < 0u) ? 1 : (QUALITY < 0 && ES3_1_PROFILE)", why = "negative quality on mobile" },
  { when = "((-HQ_SHADOWS << 63) >> 63) == -1 && !defined(SM5_PROFILE) && TYPE", why = "sign-extended shift" },
  { when = "(QUALITY, TYPE) && UNKNOWN == 0 && FEATURE_LEVEL == 4 && LIGHTS % 4 == 1 && ((BIG + 1u) >> 63) == 1 && (BIG + HQ_SHADOWS > 0)", why = "wrapping" },
  { when = "0 && QUALITY / (LIGHTS + 1)", why = "never reached" },
]

[[shader]]
name = "MobileBasePassPS"
source = "a.usf"
stage = "fragment"
levels = ["es3_1"]

[[shader]]
name = "Type"
source = "a.usf"
stage = "compute"
levels = ["sm5"]
dimensions = { MATCH = [7, -3, 100], FN = { enum = ["A", "LOOP_B"] } }
skip = [ { when = "MATCH == -3 && FN == FN_LOOP_B", why = "no" } ]
"#;

/// The program that prints, for every shader, level and key of the domain: the canonical
/// name (or `-`) and the skip reason (or `-`).
const MAIN: &str = r#"
fn print<K: Copy>(name: &str, levels: &[Level], all: impl Fn() -> Vec<K>, f: impl Fn(K, Level) -> (Option<String>, Option<&'static str>)) {
    for &l in levels {
        for k in all() {
            let (n, r) = f(k, l);
            println!("{name}\t{}\t{}\t{}", l.name(), n.unwrap_or("-".into()), r.unwrap_or("-"));
        }
    }
}

fn main() {
    print(forward_ps::NAME, forward_ps::LEVELS, || forward_ps::Key::all().collect(), |k, l| (k.canonical_name(l), k.skip_reason(l)));
    print(mobile_base_pass_ps::NAME, mobile_base_pass_ps::LEVELS, || mobile_base_pass_ps::Key::all().collect(), |k, l| (k.canonical_name(l), k.skip_reason(l)));
    print(r#type::NAME, r#type::LEVELS, || r#type::Key::all().collect(), |k, l| (k.canonical_name(l), k.skip_reason(l)));

    // The names of the rules, constructed by hand.
    let k = forward_ps::Key { hq_shadows: true, lights: 4, quality: 0, blend_mode: forward_ps::BlendMode::Translucent, r#type: false };
    assert_eq!(k.canonical_name(Level::Sm5), None);
    assert_eq!(k.skip_reason(Level::Sm5), Some("translucency takes \"at most\" 2 lights"));
    let k = forward_ps::Key { blend_mode: forward_ps::BlendMode::DefaultLit, ..k };
    assert_eq!(k.canonical_name(Level::Sm5).as_deref(), Some("ForwardPS@sm5{HQ_SHADOWS=1,LIGHTS=4,QUALITY=0,BLEND_MODE=DEFAULT_LIT,TYPE=0}"));
    assert!(k.permutation_id(Level::Sm5).is_some());
    assert_ne!(k.permutation_id(Level::Sm5), k.permutation_id(Level::Es31));
    // Outside the domain: no name, no reason.
    let out = forward_ps::Key { lights: 3, ..k };
    assert_eq!((out.canonical_name(Level::Sm5), out.skip_reason(Level::Sm5), out.ordinal()), (None, None, None));
    let out = forward_ps::Key { quality: 4, ..k };
    assert_eq!(out.canonical_name(Level::Sm5), None);
    // Not at that level.
    assert_eq!(mobile_base_pass_ps::Key::default().canonical_name(Level::Sm5), None);
    assert_eq!(mobile_base_pass_ps::Key::default().canonical_name(Level::Es31).as_deref(), Some("MobileBasePassPS@es3_1{}"));
    // Default: every dimension's first value.
    let d = r#type::Key::default();
    assert_eq!((d.r#match, d.r#fn), (7, r#type::Fn::A));
    assert_eq!(r#type::Fn::LoopB.name(), "LOOP_B");
    assert_eq!(forward_ps::Key::default().quality, -2);
    // Generic code over keys.
    fn name_of<K: PermutationKey>(k: K) -> Option<String> { k.canonical_name(Level::from_name("sm5").unwrap()) }
    assert_eq!(name_of(k), k.canonical_name(Level::Sm5));
    assert_eq!(<r#type::Key as PermutationKey>::SHADER, "Type");
    assert_eq!(Level::from_name("es3_1"), Some(Level::Es31));
    for (i, k) in forward_ps::Key::all().enumerate() {
        assert_eq!(k.ordinal(), Some(i as u64));
    }
}
"#;

fn rustc() -> String {
    std::env::var("RUSTC").unwrap_or_else(|_| "rustc".into())
}

fn kiln_list(config: &Path) -> serde_json::Value {
    let out = crate::kiln_command()
        .args(["list", "--all", "--json", "--no-analysis", "--config"])
        .arg(config)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout).unwrap()
}

/// Compiles `source` with rustc as a library (warnings are errors), then with `main`
/// as a program; runs it and returns its output.
fn compile_and_run(dir: &Path, source: &str, main: &str) -> String {
    let lib = dir.join("kiln_shaders_lib.rs");
    std::fs::write(&lib, source).unwrap();
    let out = Command::new(rustc())
        .args(["--edition", "2021", "--crate-type", "lib", "-D", "warnings", "--out-dir"])
        .arg(dir)
        .arg(&lib)
        .output()
        .unwrap();
    assert!(out.status.success(), "the generated file does not compile:\n{}", String::from_utf8_lossy(&out.stderr));
    let bin_src = dir.join("kiln_shaders_main.rs");
    std::fs::write(&bin_src, format!("{source}\n{main}")).unwrap();
    let bin = dir.join("kiln_shaders_main");
    let out = Command::new(rustc()).args(["--edition", "2021", "-o"]).arg(&bin).arg(&bin_src).output().unwrap();
    assert!(out.status.success(), "the test program does not compile:\n{}", String::from_utf8_lossy(&out.stderr));
    let out = Command::new(&bin).output().unwrap();
    assert!(out.status.success(), "the test program failed:\n{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout).unwrap()
}

/// The lines the program prints, as `kiln list --all --json` says they should be.
fn expected(list: &serde_json::Value) -> String {
    let mut s = String::new();
    for p in list["permutations"].as_array().unwrap() {
        let kept = p["kept"].as_bool().unwrap();
        let name = if kept { p["name"].as_str().unwrap() } else { "-" };
        let why = if kept { "-" } else { p["skip"]["why"].as_str().unwrap() };
        s.push_str(&format!("{}\t{}\t{name}\t{why}\n", p["shader"].as_str().unwrap(), p["level"].as_str().unwrap()));
    }
    s
}

#[test]
fn generated_keys_name_every_permutation_as_kiln_list_does() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir_all(dir.path().join("src")).unwrap();
    std::fs::write(dir.path().join("src/a.usf"), "@fragment fn main() {}\n").unwrap();
    let config = dir.path().join("permutations.toml");
    std::fs::write(&config, CONFIG).unwrap();
    let loaded = kiln::permute::load(&config).unwrap();
    let source = kiln::keys::generate(&loaded).unwrap();
    let printed = compile_and_run(dir.path(), &source, MAIN);
    let list = kiln_list(&config);
    let want = expected(&list);
    assert_eq!(printed, want);
    // The rules did something: each reason but the unreachable one appears.
    for why in ["translucency takes", "quality twice", "negative quality", "sign-extended", "wrapping", "\tno\n"] {
        assert!(want.contains(why), "no permutation skipped by `{why}`");
    }
    assert!(!want.contains("never reached"));
}

#[test]
fn build_script_writes_bindings_that_find_archive_permutations_by_id() {
    let dir = tempfile::tempdir().unwrap();
    let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/in");
    let out_dir: PathBuf = dir.path().join("out");
    std::fs::create_dir_all(&out_dir).unwrap();
    let archive = kiln::Build::new(fixture.join("lit.toml"))
        .out_dir(&out_dir)
        .cache_dir(dir.path().join("cache"))
        .cargo_output(false)
        .rust_bindings("kiln_shaders.rs")
        .run()
        .unwrap();
    let path = out_dir.join("kiln_shaders.rs");
    let source = std::fs::read_to_string(&path).unwrap();
    assert!(source.contains("pub enum Level {") && source.contains("pub mod lit_ps {"), "{source}");
    // A program that prints each kept key's name and id: every id finds that name in the archive.
    let main = r#"
fn main() {
    for l in Level::ALL {
        for k in lit_ps::Key::all() {
            if let (Some(n), Some(id)) = (k.canonical_name(l), k.permutation_id(l)) { println!("{n}\t{id}"); }
        }
        for k in lit_vs::Key::all() {
            if let (Some(n), Some(id)) = (k.canonical_name(l), k.permutation_id(l)) { println!("{n}\t{id}"); }
        }
    }
}
"#;
    let printed = compile_and_run(dir.path(), &source, main);
    let archive = kiln::archive::Archive::open(&archive).unwrap();
    let mut seen = 0;
    for line in printed.lines() {
        let (name, id) = line.split_once('\t').unwrap();
        let p = archive.get_by_id(id.parse().unwrap()).unwrap().unwrap_or_else(|| panic!("{name} not found by id"));
        assert_eq!(p.name(), name);
        seen += 1;
    }
    assert_eq!(seen, archive.permutations().unwrap().count());
    // Rewritten only when its text changes.
    let before = std::fs::metadata(&path).unwrap().modified().unwrap();
    std::thread::sleep(std::time::Duration::from_millis(20));
    kiln::Build::new(fixture.join("lit.toml"))
        .out_dir(&out_dir)
        .cache_dir(dir.path().join("cache"))
        .cargo_output(false)
        .rust_bindings("kiln_shaders.rs")
        .run()
        .unwrap();
    assert_eq!(std::fs::metadata(&path).unwrap().modified().unwrap(), before);
}

#[test]
fn names_rust_cannot_spell_are_errors() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("a.usf"), "").unwrap();
    let config = dir.path().join("permutations.toml");
    let bad = |shaders: &str| {
        let text = format!("[compiler]\ninclude = [\".\"]\n[levels.sm5]\n{shaders}");
        std::fs::write(&config, text).unwrap();
        kiln::keys::generate(&kiln::permute::load(&config).unwrap()).unwrap_err().message
    };
    let e = bad("[[shader]]\nname = \"FooBar\"\nsource = \"a.usf\"\nstage = \"compute\"\n[[shader]]\nname = \"foo_bar\"\nsource = \"a.usf\"\nstage = \"compute\"\n");
    assert_eq!(e, "shaders `FooBar` and `foo_bar` are both named `foo_bar` in Rust");
    let e = bad("[[shader]]\nname = \"S\"\nsource = \"a.usf\"\nstage = \"compute\"\ndimensions = { KEY = { enum = [\"A\"] } }\n");
    assert_eq!(e, "shader `S`: enum dimension `KEY` would be named `Key`, the name of the key itself");
    let e =
        bad("[[shader]]\nname = \"S\"\nsource = \"a.usf\"\nstage = \"compute\"\ndimensions = { SELF = \"bool\" }\n");
    assert_eq!(e, "shader `S`: dimension `SELF` gives no Rust field name in lowercase");
}
