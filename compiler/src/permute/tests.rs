//! Unit tests: small `permutations.toml` texts in, configs, permutation streams and whole
//! rendered diagnostics out.

use super::*;

const LEVELS: &str = r#"[compiler]
include = ["shaders"]

[levels.sm5]
defines = { FEATURE_LEVEL = 5, SM5_PROFILE = 1 }
targets = ["spirv", "wgsl"]

[levels.es3_1]
defines = { FEATURE_LEVEL = 3, ES3_1_PROFILE = 1 }
targets = ["glsl"]
limits = "downlevel"
"#;

/// A folder with `shaders/A.usf` and `shaders/B.usf`, and `text` checked as its `permutations.toml`.
fn load_text(text: &str) -> Result<Config, ConfigError> {
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir(dir.path().join("shaders")).unwrap();
    std::fs::write(dir.path().join("shaders/A.usf"), "fn a() {}\n").unwrap();
    std::fs::write(dir.path().join("shaders/B.usf"), "fn b() {}\n").unwrap();
    schema::parse(text, &dir.path().join("permutations.toml"), "permutations.toml")
}

fn config(shaders: &str) -> Config {
    match load_text(&format!("{LEVELS}{shaders}")) {
        Ok(c) => c,
        Err(e) => panic!("{}", e.render()),
    }
}

/// The rendered error of `text` (LEVELS prepended when `with_levels`).
fn error(text: &str) -> String {
    match load_text(text) {
        Ok(_) => panic!("accepted:\n{text}"),
        Err(e) => e.render(),
    }
}

fn names(c: &Config) -> Vec<String> {
    c.permutations().filter(Permutation::is_kept).map(|p| p.name()).collect()
}

// --- the schema ------------------------------------------------------------------------

#[test]
fn full_example_reads_in_declared_order() {
    let c = config(
        r#"
[[shader]]
name = "MobileBasePassPS"
source = "A.usf"
entry = "main_ps"
stage = "fragment"
levels = ["es3_1"]
defines = { MATERIAL_TWOSIDED = 0 }
dimensions = { FULLY_ROUGH = "bool", MAX_DYNAMIC_POINT_LIGHTS = [0, 1, 2, 4], USE_VERTEX_FOG = "bool", DEFERRED_SHADING_PATH = "bool" }
derived = { PACK_INTERPOLANTS = "USE_VERTEX_FOG && ES3_1_PROFILE" }
skip = [ { when = "DEFERRED_SHADING_PATH && MAX_DYNAMIC_POINT_LIGHTS > 0", why = "deferred lights run in their own pass" } ]
"#,
    );
    assert_eq!(c.levels.len(), 2);
    assert_eq!(c.levels[0].name, "sm5");
    assert_eq!(c.levels[0].targets, vec![Target::Spirv, Target::Wgsl]);
    assert_eq!(c.levels[0].limits, Limits::Default);
    assert_eq!(c.levels[1].limits, Limits::Downlevel);
    assert_eq!(c.levels[1].defines, vec![("FEATURE_LEVEL".to_string(), 3), ("ES3_1_PROFILE".to_string(), 1)]);
    let s = &c.shaders[0];
    assert_eq!(s.entry, "main_ps");
    assert_eq!(s.stage, Stage::Fragment);
    assert_eq!(s.levels, vec!["es3_1"]);
    assert!(s.source_path.ends_with("shaders/A.usf"), "{}", s.source_path.display());
    let dims: Vec<&str> = s.dimensions.iter().map(|d| d.name.as_str()).collect();
    assert_eq!(dims, ["FULLY_ROUGH", "MAX_DYNAMIC_POINT_LIGHTS", "USE_VERTEX_FOG", "DEFERRED_SHADING_PATH"]);
    assert_eq!(s.dimensions[1].values, vec![0, 1, 2, 4]);
    assert_eq!(s.derived, vec![("PACK_INTERPOLANTS".to_string(), "USE_VERTEX_FOG && ES3_1_PROFILE".to_string())]);
    assert_eq!(s.skip[0].why, "deferred lights run in their own pass");
}

#[test]
fn defaults_when_left_out() {
    let c = config(
        r#"
[[shader]]
name = "Plain"
source = "A.usf"
stage = "compute"
"#,
    );
    let s = &c.shaders[0];
    assert_eq!(s.entry, "main");
    assert_eq!(s.levels, vec!["sm5", "es3_1"]);
    assert!(s.dimensions.is_empty() && s.defines.is_empty() && s.derived.is_empty() && s.skip.is_empty());
    assert_eq!(names(&c), ["Plain@sm5{}", "Plain@es3_1{}"]);
    let c = load_text("[levels.x]\n[[shader]]\nname = \"S\"\nsource = \"A.usf\"\nstage = \"vertex\"\n[compiler]\ninclude = [\"shaders\"]\n").unwrap();
    assert_eq!(c.levels[0].targets, Target::ALL.to_vec());
}

#[test]
fn virtual_roots_resolve_sources() {
    let c = load_text(
        r#"[compiler]
virtual = { "/Engine" = "shaders" }
[levels.sm5]
[[shader]]
name = "S"
source = "/Engine/B.usf"
stage = "vertex"
"#,
    )
    .unwrap();
    assert!(c.shaders[0].source_path.ends_with("shaders/B.usf"));
    assert!(c.virtual_roots[0].1.is_absolute());
}

#[test]
fn error_unknown_top_level_key() {
    assert_eq!(
        error("[compiler]\ninclude = [\"shaders\"]\n[level.sm5]\n"),
        r#"error: unknown field `level`, expected one of `compiler`, `levels`, `shader`, `budget`, `usage`
  ┌─ permutations.toml:3:2
  │
3 │ [level.sm5]
  │  ^^^^^ unknown key

"#
    );
}

#[test]
fn error_unknown_shader_key() {
    assert_eq!(
        error(&format!("{LEVELS}\n[[shader]]\nname = \"S\"\nsource = \"A.usf\"\nstage = \"vertex\"\nskips = []\n")),
        r#"error: unknown field `skips`, expected one of `name`, `source`, `entry`, `stage`, `levels`, `defines`, `dimensions`, `derived`, `skip`, `budget`, `always`
   ┌─ permutations.toml:17:1
   │
17 │ skips = []
   │ ^^^^^ unknown key

"#
    );
}

#[test]
fn error_unknown_level_key() {
    assert_eq!(
        error("[levels.sm5]\ntarget = [\"wgsl\"]\n"),
        r#"error: unknown field `target`, expected one of `defines`, `targets`, `limits`
  ┌─ permutations.toml:2:1
  │
2 │ target = ["wgsl"]
  │ ^^^^^^ unknown key

"#
    );
}

#[test]
fn error_wrong_type() {
    assert_eq!(
        error("[levels.sm5]\ndefines = { FEATURE_LEVEL = \"five\" }\n"),
        r#"error: invalid type: string "five", expected an integer or a boolean
  ┌─ permutations.toml:2:29
  │
2 │ defines = { FEATURE_LEVEL = "five" }
  │                             ^^^^^^ wrong type

"#
    );
}

#[test]
fn error_unknown_target() {
    assert_eq!(
        error("[levels.sm5]\ntargets = [\"spirv\", \"dxil\"]\n"),
        r#"error: unknown variant `dxil`, expected one of `wgsl`, `spirv`, `msl`, `glsl`, `hlsl`
  ┌─ permutations.toml:2:21
  │
2 │ targets = ["spirv", "dxil"]
  │                     ^^^^^^ unknown value

"#
    );
}

#[test]
fn error_unknown_stage_and_limits() {
    assert_eq!(
        error(&format!("{LEVELS}\n[[shader]]\nname = \"S\"\nsource = \"A.usf\"\nstage = \"pixel\"\n")),
        r#"error: unknown variant `pixel`, expected one of `vertex`, `fragment`, `compute`
   ┌─ permutations.toml:16:9
   │
16 │ stage = "pixel"
   │         ^^^^^^^ unknown value

"#
    );
    assert_eq!(
        error("[levels.es3_1]\nlimits = \"mobile\"\n"),
        r#"error: unknown variant `mobile`, expected `default` or `downlevel`
  ┌─ permutations.toml:2:10
  │
2 │ limits = "mobile"
  │          ^^^^^^^^ unknown value

"#
    );
}

#[test]
fn error_missing_field() {
    assert_eq!(
        error(&format!("{LEVELS}\n[[shader]]\nname = \"S\"\nsource = \"A.usf\"\n")),
        r#"error: missing field `stage`
   ┌─ permutations.toml:13:1
   │
13 │ [[shader]]
   │ ^^^^^^^^^^ in this table

"#
    );
}

#[test]
fn error_unknown_level() {
    assert_eq!(
        error(&format!("{LEVELS}\n[[shader]]\nname = \"S\"\nsource = \"A.usf\"\nstage = \"vertex\"\nlevels = [\"sm5\", \"es31\"]\n")),
        r#"error: unknown level `es31`
   ┌─ permutations.toml:17:18
   │
17 │ levels = ["sm5", "es31"]
   │                  ^^^^^^ no `[levels.*]` table has this name
   │
   = expected one of: sm5, es3_1

"#
    );
}

#[test]
fn error_duplicate_shader_name() {
    assert_eq!(
        error(&format!(
            "{LEVELS}\n[[shader]]\nname = \"S\"\nsource = \"A.usf\"\nstage = \"vertex\"\n\n[[shader]]\nname = \"S\"\nsource = \"B.usf\"\nstage = \"fragment\"\n"
        )),
        r#"error: duplicate shader name `S`
   ┌─ permutations.toml:19:8
   │
14 │ name = "S"
   │        --- first declared here
   ·
19 │ name = "S"
   │        ^^^ declared again here

"#
    );
}

#[test]
fn error_dimension_clashes_with_level_define() {
    assert_eq!(
        error(&format!(
            "{LEVELS}\n[[shader]]\nname = \"S\"\nsource = \"A.usf\"\nstage = \"vertex\"\ndimensions = {{ ES3_1_PROFILE = \"bool\" }}\n"
        )),
        r#"error: dimension `ES3_1_PROFILE` clashes with a define of level `es3_1`
   ┌─ permutations.toml:17:16
   │
 9 │ defines = { FEATURE_LEVEL = 3, ES3_1_PROFILE = 1 }
   │                                ------------- `ES3_1_PROFILE` is defined by level `es3_1` here
   ·
17 │ dimensions = { ES3_1_PROFILE = "bool" }
   │                ^^^^^^^^^^^^^ dimension declared here

"#
    );
}

#[test]
fn error_dimension_clashes_with_shader_define() {
    assert_eq!(
        error(&format!(
            "{LEVELS}\n[[shader]]\nname = \"S\"\nsource = \"A.usf\"\nstage = \"vertex\"\ndefines = {{ MODE = 1 }}\ndimensions = {{ MODE = [1, 2] }}\n"
        )),
        r#"error: dimension `MODE` clashes with a shader define
   ┌─ permutations.toml:18:16
   │
17 │ defines = { MODE = 1 }
   │             ---- `MODE` is already a shader define
18 │ dimensions = { MODE = [1, 2] }
   │                ^^^^ dimension declared here

"#
    );
}

#[test]
fn error_enum_value_clashes() {
    assert_eq!(
        error(&format!(
            "{LEVELS}\n[[shader]]\nname = \"S\"\nsource = \"A.usf\"\nstage = \"vertex\"\ndefines = {{ BLEND_OPAQUE = 7 }}\ndimensions = {{ BLEND = {{ enum = [\"OPAQUE\", \"MASKED\"] }} }}\n"
        )),
        r#"error: enum value `BLEND_OPAQUE` clashes with a shader define
   ┌─ permutations.toml:18:16
   │
17 │ defines = { BLEND_OPAQUE = 7 }
   │             ------------ `BLEND_OPAQUE` is already a shader define
18 │ dimensions = { BLEND = { enum = ["OPAQUE", "MASKED"] } }
   │                ^^^^^ enum value declared here

"#
    );
}

fn dimension_error(dims: &str) -> String {
    error(&format!("[compiler]\ninclude = [\"shaders\"]\n[levels.sm5]\n[[shader]]\nname = \"S\"\nsource = \"A.usf\"\nstage = \"vertex\"\ndimensions = {{ {dims} }}\n"))
}

#[test]
fn error_empty_domains() {
    assert_eq!(
        dimension_error("A = []"),
        r#"error: empty dimension: a dimension needs at least one value
  ┌─ permutations.toml:8:20
  │
8 │ dimensions = { A = [] }
  │                    ^^ here

"#
    );
    assert_eq!(
        dimension_error("A = { range = [3, 1] }"),
        r#"error: empty range: 3 is greater than 1 (both ends are included)
  ┌─ permutations.toml:8:20
  │
8 │ dimensions = { A = { range = [3, 1] } }
  │                    ^^^^^^^^^^^^^^^^^^ here

"#
    );
    assert_eq!(
        dimension_error("A = { enum = [] }"),
        r#"error: empty enum: a dimension needs at least one value
  ┌─ permutations.toml:8:29
  │
8 │ dimensions = { A = { enum = [] } }
  │                             ^^ here

"#
    );
}

#[test]
fn error_bad_dimension_kinds() {
    assert_eq!(
        dimension_error("A = \"boolean\""),
        r#"error: unknown dimension kind `boolean`, expected "bool", a list of integers, { range = [lo, hi] } or { enum = [...] }
  ┌─ permutations.toml:8:20
  │
8 │ dimensions = { A = "boolean" }
  │                    ^^^^^^^^^ here

"#
    );
    assert_eq!(
        dimension_error("A = [0, 1, 1]"),
        r#"error: the value 1 appears twice in this dimension
  ┌─ permutations.toml:8:20
  │
8 │ dimensions = { A = [0, 1, 1] }
  │                    ^^^^^^^^^ here

"#
    );
    assert_eq!(
        dimension_error("A = { range = [0, 1, 2] }"),
        r#"error: expected [lo, hi], two integers
  ┌─ permutations.toml:8:30
  │
8 │ dimensions = { A = { range = [0, 1, 2] } }
  │                              ^^^^^^^^^ here

"#
    );
    assert_eq!(
        dimension_error("A = 3"),
        r#"error: invalid type: integer `3`, expected a dimension: "bool", a list of integers, { range = [lo, hi] } or { enum = ["NAME", ...] }
  ┌─ permutations.toml:8:20
  │
8 │ dimensions = { A = 3 }
  │                    ^ wrong type

"#
    );
}

#[test]
fn error_expression_does_not_parse() {
    assert_eq!(
        error(&format!(
            "{LEVELS}\n[[shader]]\nname = \"S\"\nsource = \"A.usf\"\nstage = \"vertex\"\ndimensions = {{ A = \"bool\" }}\nskip = [{{ when = \"A && (FEATURE_LEVEL >\", why = \"x\" }}]\n"
        )),
        "error: invalid expression: operator '>' has no right operand\n   ┌─ permutations.toml:18:39\n   │\n18 │ skip = [{ when = \"A && (FEATURE_LEVEL >\", why = \"x\" }]\n   │                                       ^ operator '>' has no right operand\n   │\n   = expressions use the `#if` language: integers, defined(X), ! ~ * / % + - << >> < <= > >= == != & ^ | && || ?:\n\n"
    );
}

#[test]
fn error_derived_depends_on_itself() {
    assert_eq!(
        error(&format!(
            "{LEVELS}\n[[shader]]\nname = \"S\"\nsource = \"A.usf\"\nstage = \"vertex\"\nderived = {{ X = \"X + 1\" }}\n"
        )),
        r#"error: derived define `X` depends on itself
   ┌─ permutations.toml:17:18
   │
17 │ derived = { X = "X + 1" }
   │                  ^ `X` is used in its own definition

"#
    );
    assert_eq!(
        error(&format!(
            "{LEVELS}\n[[shader]]\nname = \"S\"\nsource = \"A.usf\"\nstage = \"vertex\"\nderived = {{ X = \"Y || FEATURE_LEVEL\", Y = \"!X\" }}\n"
        )),
        r#"error: derived define `X` depends on itself through `Y`
   ┌─ permutations.toml:17:18
   │
17 │ derived = { X = "Y || FEATURE_LEVEL", Y = "!X" }
   │                  ^ `Y` depends on `X`
   │
   = cycle: X -> Y -> X

"#
    );
}

#[test]
fn error_derived_uses_a_later_one() {
    assert_eq!(
        error(&format!(
            "{LEVELS}\n[[shader]]\nname = \"S\"\nsource = \"A.usf\"\nstage = \"vertex\"\nderived = {{ X = \"Y\", Y = \"1\" }}\n"
        )),
        r#"error: derived define `X` uses `Y`, which is derived after it
   ┌─ permutations.toml:17:18
   │
17 │ derived = { X = "Y", Y = "1" }
   │                  ^ declared later
   │
   = a derived define sees only the derived defines written before it: move it after the ones it uses

"#
    );
}

#[test]
fn error_skip_uses_derived() {
    assert_eq!(
        error(&format!(
            "{LEVELS}\n[[shader]]\nname = \"S\"\nsource = \"A.usf\"\nstage = \"vertex\"\nderived = {{ P = \"1\" }}\nskip = [{{ when = \"!P\", why = \"never\" }}]\n"
        )),
        r#"error: skip rule uses derived define `P`
   ┌─ permutations.toml:18:20
   │
17 │ derived = { P = "1" }
   │             - derived here
18 │ skip = [{ when = "!P", why = "never" }]
   │                    ^ skip rules do not see derived defines
   │
   = skip rules see the dimensions and the level's and shader's defines; write the condition in those terms

"#
    );
}

#[test]
fn error_source_not_resolved() {
    let e = error(&format!("{LEVELS}\n[[shader]]\nname = \"S\"\nsource = \"Missing.usf\"\nstage = \"vertex\"\n"));
    assert!(
        e.starts_with(
            r#"error: cannot resolve source `Missing.usf` of shader `S`
   ┌─ permutations.toml:15:10
   │
15 │ source = "Missing.usf"
   │          ^^^^^^^^^^^^^ not found
   │
   = "#
        ),
        "{e}"
    );
    assert!(
        e.ends_with(
            "   = a source resolves like `#include <...>`: through a virtual root or against the include roots\n\n"
        ),
        "{e}"
    );
}

#[test]
fn error_several_problems_reported_together() {
    let e = load_text(&format!(
        "{LEVELS}\n[[shader]]\nname = \"S\"\nsource = \"A.usf\"\nstage = \"vertex\"\nlevels = [\"nope\", \"sm5\"]\ndimensions = {{ FEATURE_LEVEL = \"bool\" }}\n"
    ))
    .unwrap_err();
    let messages: Vec<&str> = e.diagnostics.iter().map(|d| d.message.as_str()).collect();
    assert_eq!(messages, ["unknown level `nope`", "dimension `FEATURE_LEVEL` clashes with a define of level `sm5`"]);
    assert_eq!(e.to_string(), "permutations.toml: unknown level `nope` (and 1 more problems)");
}

#[test]
fn error_toml_syntax() {
    assert_eq!(
        error("[levels.sm5\n"),
        r#"error: unclosed table, expected `]`
  ┌─ permutations.toml:1:12
  │
1 │ [levels.sm5
  │            ^ here

"#
    );
}

#[test]
fn unreadable_file_is_a_config_error() {
    let e = load(Path::new("/nonexistent/permutations.toml")).unwrap_err();
    assert!(
        e.render().starts_with("error: cannot read permutation set `/nonexistent/permutations.toml`: "),
        "{}",
        e.render()
    );
}

// --- enumeration -----------------------------------------------------------------------

#[test]
fn product_in_declared_order_first_dimension_slowest() {
    let c = config(
        r#"
[[shader]]
name = "S"
source = "A.usf"
stage = "fragment"
levels = ["sm5"]
dimensions = { B = [4, 2], A = "bool" }
"#,
    );
    assert_eq!(names(&c), ["S@sm5{B=4,A=0}", "S@sm5{B=4,A=1}", "S@sm5{B=2,A=0}", "S@sm5{B=2,A=1}"]);
}

#[test]
fn shaders_then_levels_then_dimensions() {
    let c = config(
        r#"
[[shader]]
name = "Second"
source = "A.usf"
stage = "fragment"
levels = ["es3_1", "sm5"]
dimensions = { X = "bool" }

[[shader]]
name = "First"
source = "B.usf"
stage = "vertex"
levels = ["sm5"]
"#,
    );
    assert_eq!(
        names(&c),
        ["Second@es3_1{X=0}", "Second@es3_1{X=1}", "Second@sm5{X=0}", "Second@sm5{X=1}", "First@sm5{}"]
    );
    assert_eq!(
        c.counts(),
        vec![
            Count { shader: "Second".into(), level: "es3_1".into(), kept: 2, skipped: 0 },
            Count { shader: "Second".into(), level: "sm5".into(), kept: 2, skipped: 0 },
            Count { shader: "First".into(), level: "sm5".into(), kept: 1, skipped: 0 },
        ]
    );
}

#[test]
fn skip_rules_see_dimensions_and_level_and_shader_defines() {
    let c = config(
        r#"
[[shader]]
name = "MobileBasePassPS"
source = "A.usf"
stage = "fragment"
defines = { MATERIAL_TWOSIDED = 1 }
dimensions = { FULLY_ROUGH = "bool", MAX_DYNAMIC_POINT_LIGHTS = [0, 1, 2, 4], DEFERRED_SHADING_PATH = "bool" }
skip = [
  { when = "DEFERRED_SHADING_PATH && MAX_DYNAMIC_POINT_LIGHTS > 0", why = "deferred lights run in their own pass" },
  { when = "SM5_PROFILE && MAX_DYNAMIC_POINT_LIGHTS == 4", why = "desktop uses the light grid" },
  { when = "MATERIAL_TWOSIDED && FULLY_ROUGH && defined(ES3_1_PROFILE)", why = "two-sided rough is not on mobile" },
]
"#,
    );
    let counts = c.counts();
    // sm5: 16 total; rule 1 drops DEFERRED=1 with lights 1,2,4 (2*3=6); rule 2 drops lights=4
    // with DEFERRED=0 (2 more). es3_1: rule 1 drops 6 of 16; rule 3 drops FULLY_ROUGH=1 of the
    // remaining 10 (5).
    assert_eq!(counts[0], Count { shader: "MobileBasePassPS".into(), level: "sm5".into(), kept: 8, skipped: 8 });
    assert_eq!(counts[1], Count { shader: "MobileBasePassPS".into(), level: "es3_1".into(), kept: 5, skipped: 11 });
    let p = c.find("MobileBasePassPS@sm5{FULLY_ROUGH=0,MAX_DYNAMIC_POINT_LIGHTS=4,DEFERRED_SHADING_PATH=1}").unwrap();
    assert_eq!(p.skipped_by, Some(0), "the first rule that matches is the one reported");
    let matched: Vec<Result<bool, String>> = p.skip_results().into_iter().map(|r| r.matched).collect();
    assert_eq!(matched, [Ok(true), Ok(true), Ok(false)]);
}

#[test]
fn derived_see_earlier_derived_and_defines() {
    let c = config(
        r#"
[[shader]]
name = "S"
source = "A.usf"
stage = "fragment"
levels = ["es3_1", "sm5"]
defines = { BASE = 10 }
dimensions = { USE_VERTEX_FOG = "bool" }
derived = { PACK_INTERPOLANTS = "USE_VERTEX_FOG && ES3_1_PROFILE", SLOTS = "BASE + PACK_INTERPOLANTS * 2", HAS_SM5 = "defined(SM5_PROFILE)" }
"#,
    );
    let derived: Vec<(String, Vec<i64>)> = c.permutations().map(|p| (p.name(), p.derived.clone())).collect();
    assert_eq!(
        derived,
        vec![
            ("S@es3_1{USE_VERTEX_FOG=0}".to_string(), vec![0, 10, 0]),
            ("S@es3_1{USE_VERTEX_FOG=1}".to_string(), vec![1, 12, 0]),
            ("S@sm5{USE_VERTEX_FOG=0}".to_string(), vec![0, 10, 1]),
            ("S@sm5{USE_VERTEX_FOG=1}".to_string(), vec![0, 10, 1]),
        ]
    );
}

#[test]
fn defines_list_every_origin() {
    let c = config(
        r#"
[[shader]]
name = "S"
source = "A.usf"
stage = "fragment"
levels = ["es3_1"]
defines = { FEATURE_LEVEL = 31, TWO_SIDED = 0 }
dimensions = { BLEND = { enum = ["OPAQUE", "MASKED"] }, LIGHTS = { range = [1, 3] } }
derived = { MASKED = "BLEND == BLEND_MASKED" }
"#,
    );
    let p = c.find("S@es3_1{BLEND=MASKED,LIGHTS=2}").unwrap();
    let listed: Vec<String> = p.defines().iter().map(|d| format!("{}={} ({})", d.name, d.value, d.origin)).collect();
    assert_eq!(
        listed,
        [
            "ES3_1_PROFILE=1 (level es3_1)",
            "FEATURE_LEVEL=31 (shader (overrides the level's 3))",
            "TWO_SIDED=0 (shader)",
            "BLEND=1 (dimension)",
            "BLEND_OPAQUE=0 (enum value of BLEND)",
            "BLEND_MASKED=1 (enum value of BLEND)",
            "LIGHTS=2 (dimension)",
            "MASKED=1 (derived: BLEND == BLEND_MASKED)",
        ]
    );
    let opts = p.preprocess_options(&c);
    assert!(opts.defines.contains(&("BLEND_MASKED".to_string(), "1".to_string())));
    assert!(opts.defines.contains(&("FEATURE_LEVEL".to_string(), "31".to_string())));
    assert_eq!(opts.include_roots, c.include_roots);
}

#[test]
fn enum_and_range_dimensions() {
    let c = config(
        r#"
[[shader]]
name = "S"
source = "A.usf"
stage = "fragment"
levels = ["sm5"]
dimensions = { BLEND_MODE = { enum = ["OPAQUE", "MASKED", "TRANSLUCENT"] }, CASCADES = { range = [2, 4] } }
skip = [{ when = "BLEND_MODE == BLEND_MODE_TRANSLUCENT && CASCADES > 2", why = "translucency uses one cascade" }]
"#,
    );
    assert_eq!(c.shaders[0].dimensions[0].values, vec![0, 1, 2]);
    assert_eq!(c.shaders[0].dimensions[1].values, vec![2, 3, 4]);
    assert_eq!(
        names(&c),
        [
            "S@sm5{BLEND_MODE=OPAQUE,CASCADES=2}",
            "S@sm5{BLEND_MODE=OPAQUE,CASCADES=3}",
            "S@sm5{BLEND_MODE=OPAQUE,CASCADES=4}",
            "S@sm5{BLEND_MODE=MASKED,CASCADES=2}",
            "S@sm5{BLEND_MODE=MASKED,CASCADES=3}",
            "S@sm5{BLEND_MODE=MASKED,CASCADES=4}",
            "S@sm5{BLEND_MODE=TRANSLUCENT,CASCADES=2}",
        ]
    );
    // Names accept an enum's label or its index, dimensions in any order, spaces.
    for name in [
        "S@sm5{BLEND_MODE=MASKED,CASCADES=3}",
        "S@sm5{BLEND_MODE=1,CASCADES=3}",
        "S@sm5{ CASCADES = 3 , BLEND_MODE = MASKED }",
    ] {
        let p = c.find(name).unwrap();
        assert_eq!(p.values, vec![1, 3]);
        assert_eq!(p.name(), "S@sm5{BLEND_MODE=MASKED,CASCADES=3}");
    }
    let skipped = c.find("S@sm5{BLEND_MODE=TRANSLUCENT,CASCADES=4}").unwrap();
    assert_eq!(skipped.skipped_by, Some(0));
}

#[test]
fn single_value_dimension_and_negative_values() {
    let c = config(
        r#"
[[shader]]
name = "S"
source = "A.usf"
stage = "fragment"
levels = ["sm5"]
dimensions = { ONE = [7], BIAS = { range = [-1, 1] } }
"#,
    );
    assert_eq!(names(&c), ["S@sm5{ONE=7,BIAS=-1}", "S@sm5{ONE=7,BIAS=0}", "S@sm5{ONE=7,BIAS=1}"]);
    assert_eq!(c.find("S@sm5{ONE=7,BIAS=-1}").unwrap().values, vec![7, -1]);
}

#[test]
fn evaluation_errors_keep_the_permutation_and_say_why() {
    let c = config(
        r#"
[[shader]]
name = "S"
source = "A.usf"
stage = "fragment"
levels = ["sm5"]
dimensions = { D = [0, 2] }
skip = [{ when = "4 / D == 2", why = "the half" }]
"#,
    );
    let all: Vec<(String, bool, Option<String>)> =
        c.permutations().map(|p| (p.name(), p.is_kept(), p.error.clone())).collect();
    assert_eq!(all[1], ("S@sm5{D=2}".to_string(), false, None));
    assert_eq!(all[0].0, "S@sm5{D=0}");
    assert!(all[0].1);
    let e = all[0].2.clone().expect("division by zero reported");
    assert!(e.starts_with("skip rule 1 (`4 / D == 2`): "), "{e}");
}

#[test]
fn twenty_bool_dimensions_stream() {
    let dims: Vec<String> = (0..20).map(|i| format!("D{i} = \"bool\"")).collect();
    let c = config(&format!(
        "\n[[shader]]\nname = \"Big\"\nsource = \"A.usf\"\nstage = \"compute\"\nlevels = [\"sm5\"]\ndimensions = {{ {} }}\nskip = [{{ when = \"D0 && D19\", why = \"a quarter\" }}]\n",
        dims.join(", ")
    ));
    // Counted as they stream by: nothing is collected.
    let (mut kept, mut skipped) = (0usize, 0usize);
    let mut last = None;
    for p in c.permutations() {
        if p.is_kept() {
            kept += 1;
        } else {
            skipped += 1;
        }
        last = Some(p.values);
    }
    assert_eq!(kept + skipped, 1 << 20);
    assert_eq!(skipped, 1 << 18);
    assert_eq!(last, Some(vec![1; 20]));
}

// --- names -----------------------------------------------------------------------------

#[test]
fn unknown_names_get_the_nearest_with_differences() {
    let c = config(
        r#"
[[shader]]
name = "MobileBasePassPS"
source = "A.usf"
stage = "fragment"
levels = ["es3_1"]
dimensions = { FULLY_ROUGH = "bool", MAX_DYNAMIC_POINT_LIGHTS = [0, 1, 2, 4] }
"#,
    );
    let e = c.find("MobileBasePassPS@es3_1{FULLY_ROUGH=1,MAX_DYNAMIC_POINT_LIGHTS=3}").unwrap_err();
    assert_eq!(
        e.render(),
        "error: no permutation named `MobileBasePassPS@es3_1{FULLY_ROUGH=1,MAX_DYNAMIC_POINT_LIGHTS=3}`
  = `3` is not a value of dimension `MAX_DYNAMIC_POINT_LIGHTS` ([0, 1, 2, 4])
closest permutations:
  MobileBasePassPS@es3_1{FULLY_ROUGH=1,MAX_DYNAMIC_POINT_LIGHTS=0}  (MAX_DYNAMIC_POINT_LIGHTS: 3 -> 0)
  MobileBasePassPS@es3_1{FULLY_ROUGH=1,MAX_DYNAMIC_POINT_LIGHTS=1}  (MAX_DYNAMIC_POINT_LIGHTS: 3 -> 1)
  MobileBasePassPS@es3_1{FULLY_ROUGH=1,MAX_DYNAMIC_POINT_LIGHTS=2}  (MAX_DYNAMIC_POINT_LIGHTS: 3 -> 2)
  MobileBasePassPS@es3_1{FULLY_ROUGH=1,MAX_DYNAMIC_POINT_LIGHTS=4}  (MAX_DYNAMIC_POINT_LIGHTS: 3 -> 4)
  MobileBasePassPS@es3_1{FULLY_ROUGH=0,MAX_DYNAMIC_POINT_LIGHTS=0}  (FULLY_ROUGH: 1 -> 0, MAX_DYNAMIC_POINT_LIGHTS: 3 -> 0)
"
    );
    let e = c.find("MobileBasePasPS@es3_1{FULLY_ROUGH=1,MAX_DYNAMIC_POINT_LIGHTS=2}").unwrap_err();
    assert_eq!(e.reason, "no shader named `MobileBasePasPS`");
    assert_eq!(e.nearest[0].name, "MobileBasePassPS@es3_1{FULLY_ROUGH=1,MAX_DYNAMIC_POINT_LIGHTS=2}");
    assert_eq!(e.nearest[0].differences, ["shader: MobileBasePasPS -> MobileBasePassPS"]);
    let e = c.find("MobileBasePassPS@sm5{FULLY_ROUGH=0,MAX_DYNAMIC_POINT_LIGHTS=2}").unwrap_err();
    assert_eq!(e.reason, "shader `MobileBasePassPS` has no level `sm5` (its levels: es3_1)");
    assert_eq!(e.nearest[0].differences, ["level: sm5 -> es3_1"]);
    let e = c.find("MobileBasePassPS@es3_1{FULLY_ROUGH=0}").unwrap_err();
    assert_eq!(e.reason, "no value for dimension `MAX_DYNAMIC_POINT_LIGHTS`");
    assert_eq!(e.nearest[0].differences, ["MAX_DYNAMIC_POINT_LIGHTS: (missing) -> 0"]);
    let e = c.find("MobileBasePassPS@es3_1{FULLY_ROUGH=0,MAX_DYNAMIC_POINT_LIGHTS=0,FOG=1}").unwrap_err();
    assert_eq!(
        e.reason,
        "shader `MobileBasePassPS` has no dimension `FOG` (its dimensions: FULLY_ROUGH, MAX_DYNAMIC_POINT_LIGHTS)"
    );
    assert_eq!(e.nearest[0].differences, ["FOG: 1 -> (no such dimension)"]);
    let e = c.find("MobileBasePassPS").unwrap_err();
    assert_eq!(e.reason, "no `@level`: a permutation name has the form `Shader@level{DIM=value,...}`");
}

#[test]
fn parse_names() {
    assert_eq!(
        names::parse_name("S@l{A=1,B=X}").unwrap(),
        names::ParsedName {
            shader: "S".into(),
            level: "l".into(),
            dims: vec![("A".into(), "1".into()), ("B".into(), "X".into())]
        }
    );
    assert_eq!(names::parse_name("S@l").unwrap().dims, vec![]);
    assert_eq!(names::parse_name("S@l{}").unwrap().level, "l");
    assert!(names::parse_name("S@l{A=1").is_err());
    assert!(names::parse_name("S@l{A}").is_err());
}

// --- dead dimensions -------------------------------------------------------------------

fn pp(values: &[i64], hash: u8) -> Preprocessed {
    Preprocessed { values: values.to_vec(), hash: Some(blake3::hash(&[hash])) }
}

#[test]
fn dead_dimension_needs_every_group_to_agree() {
    let c = config(
        r#"
[[shader]]
name = "S"
source = "A.usf"
stage = "fragment"
levels = ["sm5"]
dimensions = { A = "bool", B = [0, 1, 2] }
"#,
    );
    let (s, l) = (&c.shaders[0], &c.levels[0]);
    // The hash depends on B only: A is dead, B is not.
    let all: Vec<Preprocessed> = (0..2).flat_map(|a| (0..3).map(move |b| pp(&[a, b], b as u8))).collect();
    let dead = dead_dimensions_in(s, l, &all);
    assert_eq!(
        dead,
        vec![DeadDimension { shader: "S".into(), level: "sm5".into(), dimension: "A".into(), multiplier: 2 }]
    );
    // One group where A matters (B=2): A is live.
    let mut some = all.clone();
    some[5] = pp(&[1, 2], 9);
    assert!(dead_dimensions_in(s, l, &some).is_empty());
    // A failure is never the same as anything.
    let mut failed = all.clone();
    failed[3].hash = None;
    assert!(dead_dimensions_in(s, l, &failed).is_empty());
    // Skip rules left one member per group for A: it costs nothing, so it is not reported.
    let lone: Vec<Preprocessed> = (0..3).map(|b| pp(&[0, b], b as u8)).collect();
    assert!(dead_dimensions_in(s, l, &lone).is_empty());
}

#[test]
fn unknown_identifiers_in_expressions_warn() {
    let c = config(
        r#"
[[shader]]
name = "S"
source = "A.usf"
stage = "vertex"
levels = ["sm5"]
dimensions = { DEFERRED = "bool" }
derived = { D = "DEFERED || defined(ES3_1_PROFILE)" }
skip = [{ when = "DEFERRED && SM5_PROFILE && !LATE", why = "x" }]
"#,
    );
    assert_eq!(
        c.warnings,
        [
            r#"warning: derived define `D` uses `DEFERED`, which no level, shader, dimension or derived define defines
   ┌─ permutations.toml:19:18
   │
19 │ derived = { D = "DEFERED || defined(ES3_1_PROFILE)" }
   │                  ^^^^^^^ reads as 0
   │
   = an unknown identifier is 0, as in `#if`; check the spelling

"#,
            r#"warning: skip rule uses `LATE`, which no level, shader, dimension or derived define defines
   ┌─ permutations.toml:20:47
   │
20 │ skip = [{ when = "DEFERRED && SM5_PROFILE && !LATE", why = "x" }]
   │                                               ^^^^ reads as 0
   │
   = an unknown identifier is 0, as in `#if`; check the spelling

"#,
        ]
    );
}

#[test]
fn error_roots_targets_names_and_reasons() {
    assert_eq!(
        error("[compiler]\ninclude = [\"nowhere\"]\nvirtual = { Engine = \"shaders\" }\n"),
        r#"error: include root `nowhere` is not a folder
  ┌─ permutations.toml:2:12
  │
2 │ include = ["nowhere"]
  │            ^^^^^^^^^ no such folder
  │
  = include roots are relative to the folder of permutations.toml

error: virtual root `Engine` must start with `/`
  ┌─ permutations.toml:3:13
  │
3 │ virtual = { Engine = "shaders" }
  │             ^^^^^^ expected a name like "/Engine"

"#
    );
    assert_eq!(
        error("[levels.sm5]\ntargets = [\"wgsl\", \"wgsl\"]\ndefines = { \"NOT AN IDENT\" = 1 }\n"),
        r#"error: target `wgsl` is listed twice
  ┌─ permutations.toml:2:20
  │
2 │ targets = ["wgsl", "wgsl"]
  │                    ^^^^^^ listed again here

error: `NOT AN IDENT` is not a valid define name
  ┌─ permutations.toml:3:13
  │
3 │ defines = { "NOT AN IDENT" = 1 }
  │             ^^^^^^^^^^^^^^ expected an identifier

"#
    );
    assert_eq!(
        error("[compiler]\ninclude = [\"shaders\"]\n[levels.sm5]\n[[shader]]\nname = \"A{B}\"\nsource = \"A.usf\"\nstage = \"vertex\"\nskip = [{ when = \"1\", why = \" \" }]\n"),
        r#"error: shader name `A{B}` cannot appear in a permutation name
  ┌─ permutations.toml:5:8
  │
5 │ name = "A{B}"
  │        ^^^^^^ use letters, digits, `_`, `.` and `-`

error: a skip rule needs a reason
  ┌─ permutations.toml:8:29
  │
8 │ skip = [{ when = "1", why = " " }]
  │                             ^^^ expected a sentence saying why these permutations are not needed

"#
    );
}

/// Damaged files (a byte deleted, or a troublesome one inserted, at many places) load or fail
/// with diagnostics; none panics, and every error renders.
#[test]
fn damaged_files_never_panic() {
    let good = format!(
        "{LEVELS}{}",
        r#"
[[shader]]
name = "S"
source = "A.usf"
stage = "fragment"
defines = { TWO_SIDED = 1 }
dimensions = { M = { enum = ["A", "B"] }, R = { range = [0, 3] }, L = [0, 2, 4], F = "bool" }
derived = { P = "F && ES3_1_PROFILE", Q = "P + R * 2" }
skip = [{ when = "M == M_B && L > 2", why = "é, unicode in a reason" }]
"#
    );
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir(dir.path().join("shaders")).unwrap();
    std::fs::write(dir.path().join("shaders/A.usf"), "fn a() {}\n").unwrap();
    let path = dir.path().join("permutations.toml");
    let boundaries: Vec<usize> = (0..=good.len()).filter(|i| good.is_char_boundary(*i)).collect();
    let (mut ok, mut failed) = (0, 0);
    for (n, &i) in boundaries.iter().enumerate().step_by(3) {
        let next = boundaries.get(n + 1).copied().unwrap_or(good.len());
        let insert = ["\"", "{", "]", "=", "\n", "1", "é"][n % 7];
        for text in [format!("{}{}", &good[..i], &good[next..]), format!("{}{insert}{}", &good[..i], &good[i..])] {
            match schema::parse(&text, &path, "permutations.toml") {
                Ok(c) => {
                    ok += 1;
                    c.permutations().take(64).for_each(|p| drop(p.name()));
                }
                Err(e) => {
                    failed += 1;
                    assert!(e.render().starts_with("error: "), "{}", e.render());
                }
            }
        }
    }
    assert!(ok > 0 && failed > 0, "{ok} loaded, {failed} failed");
}
