//! A configuration with several problems: every one is reported, in file order, each with its
//! line and column, and the whole rendered text is compared.

use std::path::Path;

#[test]
fn every_problem_of_a_bad_file_is_reported_at_once() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("in/permute/bad/permutations.toml");
    let err = kiln::permute::load(&path).unwrap_err();
    let rendered = err.render().replace(&path.display().to_string(), "permutations.toml");
    assert_eq!(
        rendered,
        r#"error: dimension `FEATURE_LEVEL` clashes with a define of level `sm5`
   ┌─ permutations.toml:12:16
   │
 6 │ defines = { FEATURE_LEVEL = 5 }
   │             ------------- `FEATURE_LEVEL` is defined by level `sm5` here
   ·
12 │ dimensions = { FEATURE_LEVEL = "bool", LIGHTS = { range = [1, 4] } }
   │                ^^^^^^^^^^^^^ dimension declared here

error: derived define `PACKED` depends on itself through `FAST`
   ┌─ permutations.toml:13:36
   │
13 │ derived = { PACKED = "LIGHTS > 2 ? FAST : 0", FAST = "PACKED == 0" }
   │                                    ^^^^ `FAST` depends on `PACKED`
   │
   = cycle: PACKED -> FAST -> PACKED

error: invalid expression: operator '&&' has no right operand
   ┌─ permutations.toml:14:31
   │
14 │ skip = [{ when = "LIGHTS == 3 &&", why = "three is odd" }]
   │                               ^^ operator '&&' has no right operand
   │
   = expressions use the `#if` language: integers, defined(X), ! ~ * / % + - << >> < <= > >= == != & ^ | && || ?:

error: duplicate shader name `A`
   ┌─ permutations.toml:17:8
   │
 9 │ name = "A"
   │        --- first declared here
   ·
17 │ name = "A"
   │        ^^^ declared again here

error: cannot resolve source `Missing.usf` of shader `A`
   ┌─ permutations.toml:18:10
   │
18 │ source = "Missing.usf"
   │          ^^^^^^^^^^^^^ not found
   │
   = cannot find `Missing.usf` in the include roots
   = a source resolves like `#include <...>`: through a virtual root or against the include roots

error: unknown level `es3_1`
   ┌─ permutations.toml:20:11
   │
20 │ levels = ["es3_1"]
   │           ^^^^^^^ no `[levels.*]` table has this name
   │
   = expected one of: sm5

"#
    );
}
