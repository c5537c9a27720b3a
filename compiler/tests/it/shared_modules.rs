//! Second-level deduplication: permutations whose token streams differ only in helpers the
//! entry point never calls compact to one module, and the writers run once for them. The
//! artifacts are byte-identical to a build that shares nothing, `--stats-json` counts the
//! shared compiles, and `kiln explain` names the permutations that share a module.

#[path = "../../benches/shapes/mod.rs"]
mod shapes;

use std::path::Path;
use std::process::Output;

fn kiln(dir: &Path, args: &[&str], share: bool) -> Output {
    let mut c = crate::kiln_command();
    c.args(args).current_dir(dir);
    if share {
        c.env_remove("KILN_SHARED_MODULES");
    } else {
        c.env("KILN_SHARED_MODULES", "0");
    }
    c.output().unwrap()
}

fn stats(path: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
}

/// Two shaders (a fragment and a compute one), one dimension the entry point uses, two that
/// only change an uncalled helper, at a desktop and a downlevel level: 32 keys, 8 modules.
fn shape() -> shapes::Shape {
    shapes::Shape { name: "test", shaders: 2, used: 1, unused: 2, helpers: 6, calls: 2, mobile: true }
}

#[test]
fn shared_modules_give_the_same_archive_and_are_counted() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    shapes::write(d, &shape());
    let run = |out: &str, share: bool| {
        let stats_file = format!("{out}.json");
        let o = kiln(
            d,
            &[
                "build",
                "--no-cache",
                "-o",
                out,
                "--emit-dir",
                &format!("{out}.d"),
                "--stats-json",
                &stats_file,
                "-j",
                "2",
            ],
            share,
        );
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        stats(&d.join(stats_file))
    };
    let shared = run("shared.kpak", true);
    let alone = run("alone.kpak", false);
    assert_eq!(shared["permutations"], 32);
    assert_eq!(shared["unique_sources"], 32, "every permutation has its own token stream");
    assert_eq!(shared["compiled"], 32);
    // 8 distinct compacted modules of 4 keys each: the first two keys of each run the writers.
    assert_eq!(shared["shared_modules"], 32 - 2 * 8, "8 distinct compacted modules among 32 keys");
    assert_eq!(alone["compiled"], 32);
    assert_eq!(alone["shared_modules"], 0);
    assert_eq!(shared["artifacts"], alone["artifacts"]);
    let archive = |name: &str| std::fs::read(d.join(name)).unwrap();
    assert!(archive("shared.kpak") == archive("alone.kpak"), "the archives differ");
    let index = |name: &str| std::fs::read_to_string(d.join(name).join("index.json")).unwrap();
    assert_eq!(index("shared.kpak.d"), index("alone.kpak.d"));
    // Distinct modules give distinct artifacts: the permutations' WGSL files are those of the
    // 4 modules per level (the same WGSL text at both levels, stored once).
    let idx: serde_json::Value = serde_json::from_str(&index("shared.kpak.d")).unwrap();
    let wgsl: std::collections::BTreeSet<&str> =
        idx.as_object().unwrap().values().map(|t| t["wgsl"].as_str().unwrap()).collect();
    assert_eq!(wgsl.len(), 4);
}

#[test]
fn explain_names_the_permutations_sharing_a_module() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    shapes::write(d, &shape());
    let o = kiln(d, &["explain", "Shader0@sm5{USE_0=1,UNUSED_0=0,UNUSED_1=1}"], true);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = String::from_utf8_lossy(&o.stdout);
    let expected = "compacted module: 4 kept permutation(s) of Shader0@sm5 compact to this one's module";
    assert!(text.contains(expected), "{text}");
    for name in [
        "  Shader0@sm5{USE_0=1,UNUSED_0=0,UNUSED_1=0}\n",
        "  Shader0@sm5{USE_0=1,UNUSED_0=0,UNUSED_1=1}  (this one)\n",
        "  Shader0@sm5{USE_0=1,UNUSED_0=1,UNUSED_1=0}\n",
        "  Shader0@sm5{USE_0=1,UNUSED_0=1,UNUSED_1=1}\n",
    ] {
        assert!(text.contains(name), "{name:?} missing from:\n{text}");
    }
    assert!(!text.contains("USE_0=0"), "{text}");
}
