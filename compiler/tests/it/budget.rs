//! Budgets (`[budget]`, a shader's `budget`), `kiln diff` and builds from usage (`--usage-only`), as CI runs them.

use std::path::Path;

use super::cli_build::{fixture, kiln, stderr, stdout};

/// `lit.toml` with `extra` appended to the `[[shader]]` of `shader`, and `budget` as its
/// `[budget]` table (none when empty).
fn lit_with(dir: &Path, name: &str, shader: &str, extra: &str, budget: &str) {
    let text = std::fs::read_to_string(dir.join("lit.toml")).unwrap();
    let at = text.find(&format!("name = \"{shader}\"")).unwrap();
    let end = text[at..].find("\n\n").map_or(text.len(), |e| at + e);
    let mut out = format!("{}\n{extra}{}", &text[..end], &text[end..]);
    if !budget.is_empty() {
        out = out.replacen("[levels.sm5]", &format!("[budget]\n{budget}\n\n[levels.sm5]"), 1);
    }
    std::fs::write(dir.join(name), out).unwrap();
}

#[test]
fn a_shader_over_its_budget_by_one_fails_with_exit_3_and_is_named() {
    let fx = fixture();
    let d = fx.path();
    // LitPS keeps 2 levels x (2 x 3 x 2 - 2 skipped) = 20 permutations.
    lit_with(d, "over.toml", "LitPS", "budget = { max_permutations = 19 }", "");
    lit_with(d, "fits.toml", "LitPS", "budget = { max_permutations = 20 }", "");

    let o = kiln(d, &["list", "--config", "fits.toml", "--check-budget"]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    assert!(stdout(&o).contains("budget: shader LitPS keeps 20 of 20 permutations"), "{}", stdout(&o));

    for args in [&["list", "--config", "over.toml", "--check-budget"][..], &["build", "--config", "over.toml"][..]] {
        let o = kiln(d, args);
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(3), "{args:?}: {err}");
        assert!(err.contains("error: shader `LitPS` keeps 20 permutations, over its budget of 19 by 1"), "{err}");
        // Located at the budget, and the dimension that multiplied it most named with its factor.
        assert!(err.contains("┌─ over.toml:"), "{err}");
        assert!(err.contains("budget: 19"), "{err}");
        assert!(err.contains("`BLEND` multiplies `LitPS` by 2.50: 8 permutations without it"), "{err}");
        assert!(err.contains("`LitPS` keeps 20: USE_FOG ×2, BLEND ×2.50, NUM_LIGHTS ×1.67, levels ×2"), "{err}");
    }
    // A failed budget compiles nothing and writes no archive.
    assert!(!d.join("shaders.kpak").exists());
}

#[test]
fn set_budgets_count_permutations_and_distinct_sources() {
    let fx = fixture();
    let d = fx.path();
    // 28 kept in all; DEBUG_VIEW never reaches LitVS's text, so 24 distinct.
    lit_with(d, "total.toml", "LitVS", "", "max_permutations = 27");
    let o = kiln(d, &["build", "--config", "total.toml"]);
    assert_eq!(o.status.code(), Some(3), "{}", stderr(&o));
    assert!(stderr(&o).contains("the set has 28 permutations, over its `[budget] max_permutations` of 27 by 1"));

    lit_with(d, "distinct.toml", "LitVS", "", "max_permutations = 28\nmax_distinct = 23");
    let o = kiln(d, &["list", "--config", "distinct.toml", "--check-budget"]);
    assert_eq!(o.status.code(), Some(3), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("the set has 24 distinct sources (compiles), over its `[budget] max_distinct` of 23 by 1")
    );
    let o = kiln(d, &["build", "--config", "distinct.toml", "--stats-json", "stats.json"]);
    assert_eq!(o.status.code(), Some(3), "{}", stderr(&o));
    assert!(stderr(&o).contains("the set has 24 distinct sources"), "{}", stderr(&o));

    lit_with(d, "fits.toml", "LitVS", "", "max_distinct = 24\nmax_compile_ms = 100000");
    let o = kiln(d, &["build", "--config", "fits.toml", "--stats-json", "stats.json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(d.join("stats.json")).unwrap()).unwrap();
    let ms = v["estimated_compile_ms"].as_f64().unwrap();
    assert!(ms > 0.0, "{v}");

    // The archive's bytes: over by one byte fails after writing it (so that it can be diffed).
    let bytes = std::fs::metadata(d.join("shaders.kpak")).unwrap().len();
    lit_with(d, "bytes.toml", "LitVS", "", &format!("max_archive_bytes = {}", bytes - 1));
    let o = kiln(d, &["build", "--config", "bytes.toml", "-o", "b.kpak"]);
    assert_eq!(o.status.code(), Some(3), "{}", stderr(&o));
    let err = stderr(&o);
    assert!(
        err.contains(&format!(
            "the set has {bytes} archive bytes, over its `[budget] max_archive_bytes` of {} by 1",
            bytes - 1
        )),
        "{err}"
    );
    assert!(err.contains("artifact and dictionary bytes by target: glsl "), "{err}");
}

#[test]
fn diff_of_two_configs_counts_exactly() {
    let fx = fixture();
    let d = fx.path();
    // New: LitPS gains NUM_LIGHTS = 4 (2 levels x 3 blends x 2 fog = 12 added); LitVS loses
    // DEBUG_VIEW (all 8 names change: 8 removed, 4 added).
    let old = std::fs::read_to_string(d.join("lit.toml")).unwrap();
    let new = old
        .replace("NUM_LIGHTS = [0, 2]", "NUM_LIGHTS = [0, 2, 4]")
        .replace("dimensions = { USE_FOG = \"bool\", DEBUG_VIEW = \"bool\" }", "dimensions = { USE_FOG = \"bool\" }");
    assert_ne!(old, new);
    std::fs::write(d.join("new.toml"), new).unwrap();

    let o = kiln(d, &["diff", "lit.toml", "new.toml", "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!((v["added"].as_u64(), v["removed"].as_u64()), (Some(16), Some(8)), "{v}");
    assert_eq!(v["permutations"], serde_json::json!([28, 36]));
    let ps = &v["shaders"]["LitPS"];
    assert_eq!((ps["added"].as_u64(), ps["removed"].as_u64()), (Some(12), Some(0)));
    assert_eq!(ps["permutations"], serde_json::json!([20, 32]));
    assert!(ps["added_names"].as_array().unwrap().iter().all(|n| n.as_str().unwrap().contains("NUM_LIGHTS=4")));
    let vs = &v["shaders"]["LitVS"];
    assert_eq!((vs["added"].as_u64(), vs["removed"].as_u64()), (Some(4), Some(8)));
    // DEBUG_VIEW was dead: the distinct sources do not change.
    assert_eq!(vs["distinct"], serde_json::json!([4, 4]));

    let o = kiln(d, &["diff", "lit.toml", "new.toml", "--markdown"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let md = stdout(&o);
    assert!(md.starts_with("| Shader | Permutations | Added | Removed | Distinct |\n|---|"), "{md}");
    assert!(md.contains("| `LitPS` | 20 → 32 | +12 | −0 |"), "{md}");
    assert!(md.contains("| **total** | 28 → 36 | +16 | −8 |"), "{md}");
}

#[test]
fn diff_of_two_archives_has_bytes_per_target() {
    let fx = fixture();
    let d = fx.path();
    let o = kiln(d, &["build", "--config", "lit.toml", "-o", "old.kpak"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let old = std::fs::read_to_string(d.join("lit.toml")).unwrap();
    std::fs::write(d.join("new.toml"), old.replace("NUM_LIGHTS = [0, 2]", "NUM_LIGHTS = [0, 2, 4]")).unwrap();
    let o = kiln(d, &["build", "--config", "new.toml", "-o", "new.kpak"]);
    assert!(o.status.success(), "{}", stderr(&o));

    let o = kiln(d, &["diff", "old.kpak", "new.kpak", "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!((v["added"].as_u64(), v["removed"].as_u64()), (Some(12), Some(0)), "{v}");
    let spirv = &v["shaders"]["LitPS"]["bytes"]["spirv"];
    assert!(spirv[1].as_u64() > spirv[0].as_u64(), "{v}");
    // LitVS keeps its permutations; its stored bytes may move (each target's zstd
    // dictionary is trained on the whole set).
    assert_eq!(
        (v["shaders"]["LitVS"]["added"].as_u64(), v["shaders"]["LitVS"]["removed"].as_u64()),
        (Some(0), Some(0))
    );
    let text = stdout(&kiln(d, &["diff", "old.kpak", "new.kpak"]));
    assert!(text.contains("LitPS: permutations 20 -> 32 (+12 -0), distinct 20 -> 32, glsl "), "{text}");
    assert!(text.contains("total: permutations 28 -> 40 (+12 -0)"), "{text}");
    assert!(text.contains("archive: "), "{text}");
    // The same archive twice: nothing changed.
    let same = stdout(&kiln(d, &["diff", "old.kpak", "old.kpak"]));
    assert!(same.starts_with("(2 shaders unchanged)\ntotal: permutations 28 -> 28 (+0 -0)"), "{same}");
}

/// A usage file recording one sm5 pipeline of the lit set.
const LIT_USAGE: &str =
    "kiln-usage 1\narchive 0000000000000000000000000000000000000000000000000000000000000000\nruns 1\n\
render LitVS@sm5{USE_FOG=0,DEBUG_VIEW=0} LitPS@sm5{USE_FOG=0,BLEND=OPAQUE,NUM_LIGHTS=2} TriangleList 3 0\n";

#[test]
fn usage_only_builds_the_recorded_the_kept_and_the_always_permutations() {
    let fx = fixture();
    let d = fx.path();
    std::fs::write(d.join("frame.usage"), LIT_USAGE).unwrap();
    let lit = std::fs::read_to_string(d.join("lit.toml")).unwrap();
    let with_usage = lit.replacen("[levels.sm5]", "[usage]\nkeep = [\"LitPS@es3_1{USE_FOG=1*\"]\n\n[levels.sm5]", 1);
    std::fs::write(
        d.join("usage.toml"),
        with_usage.replace(
            "levels = [\"sm5\", \"es3_1\"]\ndimensions = { USE_FOG = \"bool\", DEBUG_VIEW",
            "levels = [\"sm5\", \"es3_1\"]\nalways = true\ndimensions = { USE_FOG = \"bool\", DEBUG_VIEW",
        ),
    )
    .unwrap();
    let args = |j: &str, out: &str| {
        kiln(
            d,
            &[
                "build",
                "--config",
                "usage.toml",
                "--usage",
                "frame.usage",
                "--usage-only",
                "-j",
                j,
                "-o",
                out,
                "--stats-json",
                "stats.json",
            ],
        )
    };
    let o = args("1", "one.kpak");
    assert!(o.status.success(), "{}", stderr(&o));
    // LitVS: always, 8. LitPS: 1 recorded + es3_1 with fog (3 blends x 2 lights - 1 skipped) = 6 of 20.
    assert!(
        stderr(&o).contains("note: --usage-only built 14 permutations and left out 14: LitPS 14 of 20"),
        "{}",
        stderr(&o)
    );
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(d.join("stats.json")).unwrap()).unwrap();
    assert_eq!(
        (v["permutations"].as_u64(), v["used"].as_u64(), v["left_out"].as_u64()),
        (Some(14), Some(14), Some(14))
    );
    assert_eq!(v["shaders"]["LitPS"], serde_json::json!({ "used": 6, "left_out": 14 }));
    assert_eq!(v["shaders"]["LitVS"], serde_json::json!({ "used": 8, "left_out": 0 }));
    // Deterministic across -j and the cache.
    let o = args("2", "two.kpak");
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(std::fs::read(d.join("one.kpak")).unwrap(), std::fs::read(d.join("two.kpak")).unwrap());
    // And across shards: two shard processes on one cache, then the assembly, which compiles
    // nothing and writes the same bytes.
    let usage_only = ["build", "--config", "usage.toml", "--usage", "frame.usage", "--usage-only", "--cache-dir", "sc"];
    for shard in ["0/2", "1/2"] {
        let o = kiln(d, &[&usage_only[..], &["--shard", shard]].concat());
        assert!(o.status.success(), "{}", stderr(&o));
    }
    let o = kiln(d, &[&usage_only[..], &["-o", "sharded.kpak", "--stats-json", "assembly.json"]].concat());
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(d.join("assembly.json")).unwrap()).unwrap();
    assert_eq!(v["compiled"].as_u64(), Some(0), "{v}");
    assert_eq!(std::fs::read(d.join("one.kpak")).unwrap(), std::fs::read(d.join("sharded.kpak")).unwrap());
    let o = kiln(d, &["inspect", "one.kpak", "LitPS@sm5{USE_FOG=1,BLEND=OPAQUE,NUM_LIGHTS=2}", "--reflection"]);
    assert_eq!(o.status.code(), Some(2));

    // Nothing left out: the archive is a whole one, the plain build's permutations plus the
    // pipeline manifest.
    let all = lit.replace("levels = [\"sm5\", \"es3_1\"]\n", "levels = [\"sm5\", \"es3_1\"]\nalways = true\n");
    std::fs::write(d.join("all.toml"), all).unwrap();
    let o = kiln(d, &["build", "--config", "all.toml", "--usage", "frame.usage", "--usage-only", "-o", "all.kpak"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let o = kiln(d, &["build", "--config", "lit.toml", "-o", "plain.kpak"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let same_permutations = |a: &str, b: &str| {
        let list = |f: &str| stdout(&kiln(d, &["inspect", f, "--list"]));
        assert!(!list(a).is_empty());
        assert_eq!(list(a), list(b));
    };
    same_permutations("all.kpak", "plain.kpak");
    assert!(stdout(&kiln(d, &["inspect", "all.kpak", "--pipelines"])).starts_with("1 pipelines"));

    // `--usage` alone builds everything (the recorded permutations first): the same
    // permutations, and the manifest.
    let o = kiln(
        d,
        &["build", "--config", "lit.toml", "--usage", "frame.usage", "-j", "2", "-o", "first.kpak", "--no-cache"],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("note: the usage files record 2 of the permutations built"), "{}", stderr(&o));
    same_permutations("first.kpak", "plain.kpak");

    // A usage file that is not one is a located error, exit 2.
    std::fs::write(d.join("bad.usage"), "kiln-usage 1\nrender x\n").unwrap();
    let o = kiln(d, &["build", "--config", "lit.toml", "--usage", "bad.usage", "--usage-only"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("bad.usage: line 2: expected"), "{}", stderr(&o));
}

#[test]
fn usage_builds_store_a_pipeline_manifest_that_inspect_lists() {
    let fx = fixture();
    let d = fx.path();
    // Three pipelines: one the archive holds (frame 0), a compute of a permutation it holds
    // (frame 1), one of a permutation the set does not keep (left out of the manifest), and
    // a crafted permutation name that must come out escaped.
    let usage = format!(
        "{LIT_USAGE}render LitVS@sm5{{USE_FOG=1,DEBUG_VIEW=0}} LitPS@sm5{{USE_FOG=9,BLEND=OPAQUE,NUM_LIGHTS=2}} \
         TriangleList 1 0\nrender LitVS@sm5{{USE_FOG=0,DEBUG_VIEW=0}} - PointList;\u{1b}[31m 2 1\n"
    );
    std::fs::write(d.join("frame.usage"), usage).unwrap();
    let o = kiln(
        d,
        &["build", "--config", "lit.toml", "--usage", "frame.usage", "-o", "with.kpak", "--stats-json", "stats.json"],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(d.join("stats.json")).unwrap()).unwrap();
    assert_eq!((v["pipelines"].as_u64(), v["pipelines_left_out"].as_u64()), (Some(2), Some(1)));
    assert!(
        stderr(&o).contains(
            "note: the archive's pipeline manifest holds 2 pipelines; 1 recorded pipelines are left out of it \
             (a permutation of theirs is not in the archive)"
        ),
        "{}",
        stderr(&o)
    );
    let text = stdout(&kiln(d, &["inspect", "with.kpak", "--pipelines"]));
    assert_eq!(
        text,
        "2 pipelines, in first-use order:\n\
         render LitVS@sm5{USE_FOG=0,DEBUG_VIEW=0} LitPS@sm5{USE_FOG=0,BLEND=OPAQUE,NUM_LIGHTS=2} TriangleList 0\n\
         render LitVS@sm5{USE_FOG=0,DEBUG_VIEW=0} - PointList;\\u{1b}[31m 1\n"
    );
    let json: serde_json::Value =
        serde_json::from_str(&stdout(&kiln(d, &["inspect", "with.kpak", "--pipelines", "--json"]))).unwrap();
    let list = json["pipelines"].as_array().unwrap();
    assert_eq!(list.len(), 2);
    assert_eq!(list[0]["kind"], "render");
    assert_eq!(list[0]["fragment"], "LitPS@sm5{USE_FOG=0,BLEND=OPAQUE,NUM_LIGHTS=2}");
    assert_eq!((list[0]["first_frame"].as_u64(), list[1]["first_frame"].as_u64()), (Some(0), Some(1)));
    assert_eq!(list[1]["fragment"], serde_json::Value::Null);

    // Without `--usage`: no manifest, and the archive is the plain one.
    let o = kiln(d, &["build", "--config", "lit.toml", "-o", "plain.kpak"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&kiln(d, &["inspect", "plain.kpak", "--pipelines"])).starts_with("no pipeline manifest"));
    let json = stdout(&kiln(d, &["inspect", "plain.kpak", "--pipelines", "--json"]));
    assert_eq!(json, "{\n  \"pipelines\": null\n}\n");
    // The manifest is part of the build's fingerprint: the same output path, rebuilt with
    // usage, is rewritten.
    let o = kiln(d, &["build", "--config", "lit.toml", "--usage", "frame.usage", "-o", "plain.kpak"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(std::fs::read(d.join("plain.kpak")).unwrap(), std::fs::read(d.join("with.kpak")).unwrap());
}
