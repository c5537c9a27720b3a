//! `permutations.toml`: the serde shape of the file, and its check into a [`Config`].
//!
//! serde and toml report syntax, unknown keys and wrong types (with the span of the offending
//! value); everything that needs more than one value at a time (clashing defines, unknown
//! levels, derived dependencies, expressions) is checked here, after deserialization, and
//! reported together.

use std::collections::{HashMap, HashSet};
use std::fmt;
use std::ops::Range;
use std::path::{Path, PathBuf};

use codespan_reporting::diagnostic::{Diagnostic, Label, LabelStyle};
use indexmap::IndexMap;
use serde::de::{self, Deserializer, MapAccess, SeqAccess, Visitor};
use serde::Deserialize;
use toml::Spanned;

use super::error::ConfigError;
use super::{Budget, BudgetLimit, Config, Dimension, Level, Limits, Shader, ShaderBudget, SkipRule};
use crate::preprocess;
use crate::{Stage, Target};

/// Most values one dimension may take (a larger range is almost certainly a typo).
pub const MAX_DIMENSION_VALUES: usize = 65_536;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawConfig {
    #[serde(default)]
    compiler: RawCompiler,
    #[serde(default)]
    levels: IndexMap<Spanned<String>, RawLevel>,
    #[serde(default)]
    shader: Vec<Spanned<RawShader>>,
    #[serde(default)]
    budget: RawBudget,
    #[serde(default)]
    usage: RawUsage,
}

/// `[usage]`: what a `kiln build --usage-only` keeps beyond the recorded permutations.
#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct RawUsage {
    #[serde(default)]
    keep: Vec<Spanned<String>>,
}

/// `[budget]`: limits a CI build checks ([`super::Budget`]).
#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct RawBudget {
    max_permutations: Option<Spanned<i64>>,
    max_distinct: Option<Spanned<i64>>,
    max_archive_bytes: Option<Spanned<i64>>,
    max_compile_ms: Option<Spanned<i64>>,
}

/// A shader's `budget = { max_permutations = N }`.
#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct RawShaderBudget {
    max_permutations: Option<Spanned<i64>>,
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct RawCompiler {
    #[serde(default)]
    include: Vec<Spanned<String>>,
    #[serde(default, rename = "virtual")]
    virtual_roots: IndexMap<Spanned<String>, Spanned<String>>,
    max_permutations: Option<Spanned<i64>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawLevel {
    #[serde(default)]
    defines: IndexMap<Spanned<String>, Spanned<DefineValue>>,
    targets: Option<Vec<Spanned<Target>>>,
    limits: Option<RawLimits>,
}

/// `limits`: `"default"`, `"downlevel"`, or `{ base = ..., <wgpu Limits field> = value, ... }`.
enum RawLimits {
    Base(Limits),
    /// The table's entries as written; checked in [`parse`] so that errors point at each one.
    Table(Vec<(Spanned<String>, Spanned<toml::Value>)>),
}

impl<'de> Deserialize<'de> for RawLimits {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = RawLimits;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("\"default\", \"downlevel\" or a table { base = \"default\" | \"downlevel\", <wgpu Limits field> = value, ... }")
            }
            fn visit_str<E: de::Error>(self, v: &str) -> Result<RawLimits, E> {
                limits_base(v).map(RawLimits::Base).ok_or_else(|| E::unknown_variant(v, &["default", "downlevel"]))
            }
            fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<RawLimits, A::Error> {
                let mut entries = Vec::new();
                while let Some(k) = map.next_key::<Spanned<String>>()? {
                    entries.push((k, map.next_value::<Spanned<toml::Value>>()?));
                }
                Ok(RawLimits::Table(entries))
            }
        }
        d.deserialize_any(V)
    }
}

fn limits_base(name: &str) -> Option<Limits> {
    match name {
        "default" => Some(Limits::Default),
        "downlevel" => Some(Limits::Downlevel),
        _ => None,
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawShader {
    name: Spanned<String>,
    source: Spanned<String>,
    entry: Option<String>,
    stage: Stage,
    levels: Option<Spanned<Vec<Spanned<String>>>>,
    #[serde(default)]
    defines: IndexMap<Spanned<String>, Spanned<DefineValue>>,
    #[serde(default)]
    dimensions: IndexMap<Spanned<String>, Spanned<DimensionKind>>,
    #[serde(default)]
    derived: IndexMap<Spanned<String>, Spanned<String>>,
    #[serde(default)]
    skip: Vec<Spanned<RawSkip>>,
    budget: Option<RawShaderBudget>,
    #[serde(default)]
    always: bool,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSkip {
    when: Spanned<String>,
    why: Spanned<String>,
}

/// A constant define: an integer, or a boolean read as 0 / 1.
struct DefineValue(i64);

impl<'de> Deserialize<'de> for DefineValue {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = DefineValue;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("an integer or a boolean")
            }
            fn visit_i64<E: de::Error>(self, v: i64) -> Result<DefineValue, E> {
                Ok(DefineValue(v))
            }
            fn visit_u64<E: de::Error>(self, v: u64) -> Result<DefineValue, E> {
                i64::try_from(v)
                    .map(DefineValue)
                    .map_err(|_| E::custom("integer out of range: defines are 64-bit signed"))
            }
            fn visit_bool<E: de::Error>(self, v: bool) -> Result<DefineValue, E> {
                Ok(DefineValue(i64::from(v)))
            }
        }
        d.deserialize_any(V)
    }
}

/// The value of one entry of `dimensions`, checked as it is read so that an error points at
/// the value itself.
enum DimensionKind {
    /// The values, and whether they were written `"bool"`.
    Values(Vec<i64>, bool),
    Enum(Vec<String>),
}

const DIMENSION_EXPECTED: &str =
    "a dimension: \"bool\", a list of integers, { range = [lo, hi] } or { enum = [\"NAME\", ...] }";

impl<'de> Deserialize<'de> for DimensionKind {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = DimensionKind;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str(DIMENSION_EXPECTED)
            }
            fn visit_str<E: de::Error>(self, v: &str) -> Result<DimensionKind, E> {
                if v == "bool" {
                    Ok(DimensionKind::Values(vec![0, 1], true))
                } else {
                    Err(E::custom(format!("unknown dimension kind `{v}`, expected \"bool\", a list of integers, {{ range = [lo, hi] }} or {{ enum = [...] }}")))
                }
            }
            fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<DimensionKind, A::Error> {
                let mut values = Vec::new();
                while let Some(v) = seq.next_element::<i64>()? {
                    if values.contains(&v) {
                        return Err(de::Error::custom(format!("the value {v} appears twice in this dimension")));
                    }
                    values.push(v);
                }
                if values.is_empty() {
                    return Err(de::Error::custom("empty dimension: a dimension needs at least one value"));
                }
                Ok(DimensionKind::Values(values, false))
            }
            fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<DimensionKind, A::Error> {
                let Some(key) = map.next_key::<String>()? else {
                    return Err(de::Error::custom(
                        "empty table, expected { range = [lo, hi] } or { enum = [\"NAME\", ...] }",
                    ));
                };
                let kind = match key.as_str() {
                    "range" => {
                        let Range2(lo, hi) = map.next_value()?;
                        if lo > hi {
                            return Err(de::Error::custom(format!(
                                "empty range: {lo} is greater than {hi} (both ends are included)"
                            )));
                        }
                        let count = (hi as i128 - lo as i128 + 1) as u128;
                        if count > MAX_DIMENSION_VALUES as u128 {
                            return Err(de::Error::custom(format!(
                                "range of {count} values: a dimension may have at most {MAX_DIMENSION_VALUES}"
                            )));
                        }
                        DimensionKind::Values((lo..=hi).collect(), false)
                    }
                    "enum" => {
                        let EnumNames(names) = map.next_value()?;
                        DimensionKind::Enum(names)
                    }
                    other => {
                        return Err(de::Error::custom(format!("unknown key `{other}`, expected `range` or `enum`")));
                    }
                };
                if let Some(extra) = map.next_key::<String>()? {
                    return Err(de::Error::custom(format!(
                        "unexpected key `{extra}`: a dimension table has exactly one key, `range` or `enum`"
                    )));
                }
                Ok(kind)
            }
        }
        d.deserialize_any(V)
    }
}

/// `[lo, hi]`.
struct Range2(i64, i64);

impl<'de> Deserialize<'de> for Range2 {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = Range2;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("[lo, hi], two integers")
            }
            fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Range2, A::Error> {
                let lo = seq.next_element::<i64>()?;
                let hi = seq.next_element::<i64>()?;
                let more = seq.next_element::<de::IgnoredAny>()?;
                match (lo, hi, more) {
                    (Some(lo), Some(hi), None) => Ok(Range2(lo, hi)),
                    _ => Err(de::Error::custom("expected [lo, hi], two integers")),
                }
            }
        }
        d.deserialize_seq(V)
    }
}

/// `["A", "B"]`: non-empty, distinct, each usable in a define name.
struct EnumNames(Vec<String>);

impl<'de> Deserialize<'de> for EnumNames {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = EnumNames;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("a list of names")
            }
            fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<EnumNames, A::Error> {
                let mut names: Vec<String> = Vec::new();
                while let Some(n) = seq.next_element::<String>()? {
                    if n.is_empty() || !n.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_') {
                        return Err(de::Error::custom(format!(
                            "enum name `{n}` is not usable in a define: use letters, digits and `_`"
                        )));
                    }
                    if names.contains(&n) {
                        return Err(de::Error::custom(format!("enum name `{n}` appears twice")));
                    }
                    names.push(n);
                }
                if names.is_empty() {
                    return Err(de::Error::custom("empty enum: a dimension needs at least one value"));
                }
                Ok(EnumNames(names))
            }
        }
        d.deserialize_seq(V)
    }
}

/// Collects diagnostics against the toml file.
struct Checker {
    diagnostics: Vec<Diagnostic<()>>,
    warnings: Vec<Diagnostic<()>>,
}

impl Checker {
    fn error(
        &mut self,
        span: Range<usize>,
        message: impl Into<String>,
        label: impl Into<String>,
    ) -> &mut Diagnostic<()> {
        self.diagnostics.push(
            Diagnostic::error()
                .with_message(message.into())
                .with_labels(vec![Label::primary((), span).with_message(label.into())]),
        );
        self.diagnostics.last_mut().expect("just pushed")
    }

    /// Warns about identifiers of `expr` that nothing defines (they read as 0: likely a typo).
    fn unknown_identifiers(&mut self, text: &str, expr: &Spanned<String>, known: &dyn Fn(&str) -> bool, what: &str) {
        for id in preprocess::expr::identifiers(expr.get_ref()) {
            if known(&id) {
                continue;
            }
            let at = find_word(expr.get_ref(), &id).unwrap_or(0);
            let span = inner_span(text, &expr.span(), expr.get_ref(), at, id.len());
            self.warnings.push(
                Diagnostic::warning()
                    .with_message(format!(
                        "{what} uses `{id}`, which no level, shader, dimension or derived define defines"
                    ))
                    .with_labels(vec![Label::primary((), span).with_message("reads as 0")])
                    .with_notes(vec!["an unknown identifier is 0, as in `#if`; check the spelling".into()]),
            );
        }
    }
}

/// Names the preprocessor gives a meaning of its own: a define with one of them would not
/// reach the shader as written (`defined` is an operator, `__LINE__` is replaced, ...).
const RESERVED: &[&str] = &[
    "defined",
    "__VA_ARGS__",
    "__VA_OPT__",
    "__LINE__",
    "__FILE__",
    "__COUNTER__",
    "__INCLUDE_LEVEL__",
    "__BASE_FILE__",
    "__DATE__",
    "__TIME__",
    "__STDC__",
    "__STDC_VERSION__",
    "__STDC_HOSTED__",
    "__has_include",
    "__has_include_next",
    "_Pragma",
];

impl Checker {
    /// A located error when `name` (a define, dimension or derived define) is reserved.
    fn reserved(&mut self, name: &Spanned<String>, what: &str) {
        let n = name.get_ref();
        if RESERVED.contains(&n.as_str()) {
            self.error(name.span(), format!("{what} `{n}` is a name the preprocessor reserves"), "reserved name")
                .notes
                .push("`defined`, `__VA_ARGS__`, `__LINE__`, `__FILE__` and the like cannot be defines".into());
        }
    }
}

/// `value` in words for a message: `a string`, `-1`, `a table`.
fn describe_value(value: &toml::Value) -> String {
    match value {
        toml::Value::String(s) => format!("the string {s:?}"),
        toml::Value::Integer(n) => n.to_string(),
        toml::Value::Float(f) => format!("the float {f}"),
        toml::Value::Boolean(b) => format!("the boolean {b}"),
        toml::Value::Datetime(_) => "a date".into(),
        toml::Value::Array(_) => "an array".into(),
        toml::Value::Table(_) => "a table".into(),
    }
}

fn is_ident(s: &str) -> bool {
    let mut b = s.bytes();
    matches!(b.next(), Some(c) if c.is_ascii_alphabetic() || c == b'_')
        && b.all(|c| c.is_ascii_alphanumeric() || c == b'_')
}

/// Whether `s` can be a shader or level name inside a canonical name.
fn is_name(s: &str) -> bool {
    !s.is_empty() && s.bytes().all(|c| c.is_ascii_alphanumeric() || c == b'_' || c == b'.' || c == b'-')
}

/// The span, in the toml text, of bytes `offset..offset+len` of a string value spanning
/// `span`. Exact when the string is written without escapes; otherwise the whole string.
fn inner_span(text: &str, span: &Range<usize>, value: &str, offset: usize, len: usize) -> Range<usize> {
    let raw = text.get(span.clone()).unwrap_or("");
    for quote in ['"', '\''] {
        if raw.len() >= 2
            && raw.starts_with(quote)
            && raw.ends_with(quote)
            && !raw.starts_with(&format!("{quote}{quote}{quote}"))
            && &raw[1..raw.len() - 1] == value
        {
            let start = span.start + 1 + offset.min(value.len());
            let end = (start + len.max(1)).min(span.end).max(start + 1);
            return start..end;
        }
    }
    span.clone()
}

/// Byte offset of identifier `name` as a whole word in `expr`.
fn find_word(expr: &str, name: &str) -> Option<usize> {
    let bytes = expr.as_bytes();
    let word = |b: u8| b.is_ascii_alphanumeric() || b == b'_';
    let mut from = 0;
    while let Some(i) = expr[from..].find(name) {
        let at = from + i;
        let end = at + name.len();
        if (at == 0 || !word(bytes[at - 1])) && (end == bytes.len() || !word(bytes[end])) {
            return Some(at);
        }
        from = at + 1;
    }
    None
}

/// Parses and checks `text` (the contents of the file at `path`): the toml, then each
/// section in file order ([`parse_compiler`], [`parse_level`], [`parse_shader`]), every
/// problem reported together, in file order.
pub(super) fn parse(text: &str, path: &Path, display: &str) -> Result<Config, ConfigError> {
    let fail = |diagnostics: Vec<Diagnostic<()>>| ConfigError::new(display.to_string(), text.to_string(), diagnostics);
    let raw: RawConfig = match toml::from_str(text) {
        Ok(raw) => raw,
        Err(e) => {
            let message = e.message().trim_end().to_string();
            let mut d = Diagnostic::error().with_message(message.clone());
            if let Some(span) = e.span().or_else(|| deepest_line(text)) {
                d = d.with_labels(vec![Label::primary((), span).with_message(label_for(&message))]);
            }
            return Err(fail(vec![d]));
        }
    };
    let path = path.canonicalize().or_else(|_| std::path::absolute(path)).unwrap_or_else(|_| path.to_path_buf());
    let dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
    let mut c = Checker { diagnostics: Vec::new(), warnings: Vec::new() };

    let compiler = parse_compiler(&mut c, &raw.compiler, &dir, display);
    let budget = parse_budget(&mut c, &raw.budget);
    let usage_keep = parse_usage(&mut c, &raw.usage);
    // Sources resolve through the roots: with a bad root, their errors would only be noise.
    let roots_ok = c.diagnostics.is_empty();
    let levels = raw.levels.iter().map(|(name, l)| parse_level(&mut c, text, name, l)).collect();
    let scope = LevelScope {
        text,
        raw_levels: &raw.levels,
        all_defines: raw.levels.values().flat_map(|l| l.defines.keys().map(|k| k.get_ref().as_str())).collect(),
        defines: raw.levels.iter().map(|(k, v)| (k.get_ref().as_str(), &v.defines)).collect(),
        pp_options: preprocess::Options {
            include_roots: compiler.include_roots.clone(),
            virtual_roots: compiler.virtual_roots.clone(),
            ..preprocess::Options::default()
        },
        roots_ok,
    };
    let mut shaders = Vec::new();
    let mut seen_names: HashMap<String, Range<usize>> = HashMap::new();
    for raw_shader in &raw.shader {
        shaders.push(parse_shader(&mut c, &scope, &mut seen_names, raw_shader.get_ref()));
    }

    if !c.diagnostics.is_empty() {
        // In file order, by where each problem is (stable: one place keeps the order found).
        let at =
            |d: &Diagnostic<()>| d.labels.iter().find(|l| l.style == LabelStyle::Primary).map_or(0, |l| l.range.start);
        c.diagnostics.sort_by_key(at);
        return Err(fail(c.diagnostics));
    }
    let warnings = c
        .warnings
        .into_iter()
        .map(|w| ConfigError::new(display.to_string(), text.to_string(), vec![w]).render())
        .collect();
    Ok(Config {
        path,
        dir,
        include_roots: compiler.include_roots,
        virtual_roots: compiler.virtual_roots,
        levels,
        shaders,
        warnings,
        max_permutations: compiler.max_permutations,
        budget,
        usage_keep,
        source: std::sync::Arc::new((display.to_string(), text.to_string())),
    })
}

/// `[compiler]`, checked.
struct CompilerSection {
    include_roots: Vec<PathBuf>,
    virtual_roots: Vec<(String, PathBuf)>,
    max_permutations: Option<u64>,
}

/// `[compiler]`: include roots and virtual roots (folders that exist, relative to `dir`),
/// `max_permutations`.
fn parse_compiler(c: &mut Checker, raw: &RawCompiler, dir: &Path, display: &str) -> CompilerSection {
    let mut include_roots = Vec::new();
    for inc in &raw.include {
        let p = dir.join(inc.get_ref());
        if !p.is_dir() {
            c.error(inc.span(), format!("include root `{}` is not a folder", inc.get_ref()), "no such folder")
                .notes
                .push(format!("include roots are relative to the folder of {display}"));
        }
        include_roots.push(p.canonicalize().unwrap_or(p));
    }
    let mut virtual_roots = Vec::new();
    for (name, target) in &raw.virtual_roots {
        if !name.get_ref().starts_with('/') {
            c.error(
                name.span(),
                format!("virtual root `{}` must start with `/`", name.get_ref()),
                "expected a name like \"/Engine\"",
            );
        }
        let p = dir.join(target.get_ref());
        if !p.is_dir() {
            c.error(
                target.span(),
                format!("virtual root `{}` maps to `{}`, which is not a folder", name.get_ref(), target.get_ref()),
                "no such folder",
            );
        }
        virtual_roots.push((name.get_ref().clone(), p.canonicalize().unwrap_or(p)));
    }
    let max_permutations = raw.max_permutations.as_ref().and_then(|m| positive(c, m, "max_permutations"));
    CompilerSection { include_roots, virtual_roots, max_permutations }
}

/// `[budget]`: each limit a positive number.
fn parse_budget(c: &mut Checker, raw: &RawBudget) -> Budget {
    let mut limit = |m: &Option<Spanned<i64>>, what: &str| {
        let m = m.as_ref()?;
        positive(c, m, what).map(|value| BudgetLimit { value, span: m.span() })
    };
    Budget {
        max_permutations: limit(&raw.max_permutations, "max_permutations"),
        max_distinct: limit(&raw.max_distinct, "max_distinct"),
        max_archive_bytes: limit(&raw.max_archive_bytes, "max_archive_bytes"),
        max_compile_ms: limit(&raw.max_compile_ms, "max_compile_ms"),
    }
}

/// `[usage] keep`: patterns over canonical names (`*` any run of characters, `?` one).
fn parse_usage(c: &mut Checker, raw: &RawUsage) -> Vec<String> {
    let mut keep = Vec::new();
    for p in &raw.keep {
        if p.get_ref().trim().is_empty() || p.get_ref().contains(char::is_whitespace) {
            c.error(
                p.span(),
                "a `[usage] keep` pattern is a canonical name with `*` and `?`",
                "expected a pattern such as \"ScreenVS@*\"",
            );
        }
        keep.push(p.get_ref().clone());
    }
    keep
}

/// A positive count, or an error at its value.
fn positive(c: &mut Checker, m: &Spanned<i64>, what: &str) -> Option<u64> {
    match u64::try_from(*m.get_ref()) {
        Ok(v) if v > 0 => Some(v),
        _ => {
            c.error(m.span(), format!("`{what}` must be a positive number"), "expected a number above 0");
            None
        }
    }
}

/// One `[levels.NAME]` table.
fn parse_level(c: &mut Checker, text: &str, name: &Spanned<String>, raw: &RawLevel) -> Level {
    if !is_name(name.get_ref()) {
        c.error(
            name.span(),
            format!("level name `{}` cannot appear in a permutation name", name.get_ref()),
            "use letters, digits, `_`, `.` and `-`",
        );
    }
    let mut defines = Vec::new();
    for (k, v) in &raw.defines {
        if !is_ident(k.get_ref()) {
            c.error(k.span(), format!("`{}` is not a valid define name", k.get_ref()), "expected an identifier");
        }
        c.reserved(k, "define");
        defines.push((k.get_ref().clone(), v.get_ref().0));
    }
    let targets = match &raw.targets {
        Some(ts) if ts.is_empty() => {
            c.error(
                level_targets_span(text, name.span()),
                format!("level `{}` has no targets", name.get_ref()),
                "an empty list",
            )
            .notes
            .push("list at least one of wgsl, spirv, msl, glsl, hlsl, or leave `targets` out for all of them".into());
            Vec::new()
        }
        Some(ts) => {
            let mut out: Vec<Target> = Vec::new();
            for t in ts {
                if out.contains(t.get_ref()) {
                    c.error(t.span(), format!("target `{}` is listed twice", t.get_ref()), "listed again here");
                } else {
                    out.push(*t.get_ref());
                }
            }
            out
        }
        None => Target::ALL.to_vec(),
    };
    let mut limit_overrides: Vec<(String, u64)> = Vec::new();
    let limits = match &raw.limits {
        Some(RawLimits::Base(b)) => *b,
        None => Limits::Default,
        Some(RawLimits::Table(entries)) => parse_limits_table(c, entries, &mut limit_overrides),
    };
    Level { name: name.get_ref().clone(), defines, targets, limits, limit_overrides }
}

/// A `limits = { base = ..., field = value, ... }` table: its base, and each override in
/// `overrides`.
fn parse_limits_table(
    c: &mut Checker,
    entries: &[(Spanned<String>, Spanned<toml::Value>)],
    overrides: &mut Vec<(String, u64)>,
) -> Limits {
    let mut base = Limits::Default;
    for (k, v) in entries {
        let field = k.get_ref();
        if field == "base" {
            match v.get_ref().as_str().and_then(limits_base) {
                Some(b) => base = b,
                None => {
                    c.error(
                        v.span(),
                        "`base` is \"default\" or \"downlevel\"",
                        "expected \"default\" or \"downlevel\"",
                    );
                }
            }
            continue;
        }
        let Some(&(_, wide)) = crate::archive::limits::WGPU_LIMITS.iter().find(|(f, _)| f == field) else {
            let near = crate::archive::limits::WGPU_LIMITS
                .iter()
                .map(|(f, _)| *f)
                .min_by_key(|f| super::names::edit_distance(f, field))
                .unwrap_or("max_bind_groups");
            c.error(k.span(), format!("unknown limit `{field}`"), "not a field of wgpu's `Limits`")
                .notes
                .push(format!("the table takes `base` and the fields of wgpu's `Limits`, such as `{near}`"));
            continue;
        };
        let max = if wide { u64::MAX } else { u64::from(u32::MAX) };
        match v.get_ref().as_integer().and_then(|n| u64::try_from(n).ok()).filter(|n| *n <= max) {
            Some(n) => {
                if overrides.iter().any(|(f, _)| f == field) {
                    c.error(k.span(), format!("limit `{field}` is set twice"), "set again here");
                }
                overrides.push((field.clone(), n));
            }
            None => {
                let ty = if wide { "u64" } else { "u32" };
                c.error(
                    v.span(),
                    format!("limit `{field}` takes a non-negative integer ({ty}), not {}", describe_value(v.get_ref())),
                    format!("expected an integer from 0 to {max}"),
                );
            }
        }
    }
    base
}

/// What every `[[shader]]` sees of the rest of the file.
struct LevelScope<'a> {
    text: &'a str,
    raw_levels: &'a IndexMap<Spanned<String>, RawLevel>,
    /// Every define of every level (an expression may use any of them).
    all_defines: HashSet<&'a str>,
    /// Each level's defines, by level name.
    defines: HashMap<&'a str, &'a IndexMap<Spanned<String>, Spanned<DefineValue>>>,
    pp_options: preprocess::Options,
    /// Whether the roots are good, so that sources can be resolved through them.
    roots_ok: bool,
}

/// Every name a define or expression of one shader can see, with where it was written, for
/// clashes. Level defines may differ per level: each one of the shader's levels is checked.
struct ShaderScope<'a> {
    names: HashMap<String, (Range<usize>, &'static str)>,
    levels: &'a [String],
    level_defines: &'a HashMap<&'a str, &'a IndexMap<Spanned<String>, Spanned<DefineValue>>>,
}

impl ShaderScope<'_> {
    /// Whether `defined` (declared at `key`) clashes with a name in scope: an error if so.
    fn clash(&self, c: &mut Checker, what: &str, key: &Spanned<String>, defined: &str) -> bool {
        if let Some((span, kind)) = self.names.get(defined) {
            let d = c.error(
                key.span(),
                format!("{what} `{defined}` clashes with a {kind}"),
                format!("{what} declared here"),
            );
            d.labels.push(Label::secondary((), span.clone()).with_message(format!("`{defined}` is already a {kind}")));
            return true;
        }
        for l in self.levels {
            if let Some((lk, _)) = self.level_defines[l.as_str()].get_key_value(defined) {
                let d = c.error(
                    key.span(),
                    format!("{what} `{defined}` clashes with a define of level `{l}`"),
                    format!("{what} declared here"),
                );
                d.labels.push(
                    Label::secondary((), lk.span()).with_message(format!("`{defined}` is defined by level `{l}` here")),
                );
                return true;
            }
        }
        false
    }
}

/// One `[[shader]]` table: its name (unique), levels, defines, dimensions, derived defines,
/// skip rules and source.
fn parse_shader(
    c: &mut Checker,
    scope: &LevelScope<'_>,
    seen_names: &mut HashMap<String, Range<usize>>,
    s: &RawShader,
) -> Shader {
    let name = s.name.get_ref();
    if !is_name(name) {
        c.error(
            s.name.span(),
            format!("shader name `{name}` cannot appear in a permutation name"),
            "use letters, digits, `_`, `.` and `-`",
        );
    }
    if let Some(first) = seen_names.get(name) {
        let d = c.error(s.name.span(), format!("duplicate shader name `{name}`"), "declared again here");
        d.labels.push(Label::secondary((), first.clone()).with_message("first declared here"));
    } else {
        seen_names.insert(name.clone(), s.name.span());
    }
    let levels = shader_levels(c, scope, s);
    let mut names = ShaderScope { names: HashMap::new(), levels: &levels, level_defines: &scope.defines };
    let mut defines = Vec::new();
    for (k, v) in &s.defines {
        if !is_ident(k.get_ref()) {
            c.error(k.span(), format!("`{}` is not a valid define name", k.get_ref()), "expected an identifier");
        }
        c.reserved(k, "define");
        defines.push((k.get_ref().clone(), v.get_ref().0));
        names.names.insert(k.get_ref().clone(), (k.span(), "shader define"));
    }
    let dimensions = s.dimensions.iter().map(|(k, v)| shader_dimension(c, &mut names, k, v.get_ref())).collect();
    let (derived, derived_spans) = shader_derived(c, scope, &mut names, s);
    let skip = shader_skip(c, scope, &names, s);
    let source_path = shader_source(c, scope, s);
    let max_permutations = s
        .budget
        .as_ref()
        .and_then(|b| b.max_permutations.as_ref())
        .and_then(|m| positive(c, m, "max_permutations").map(|value| BudgetLimit { value, span: m.span() }));
    Shader {
        name: name.clone(),
        source: s.source.get_ref().clone(),
        source_path,
        entry: s.entry.clone().unwrap_or_else(|| "main".to_string()),
        stage: s.stage,
        levels,
        defines,
        dimensions,
        derived,
        skip,
        budget: ShaderBudget { max_permutations },
        always: s.always,
        spans: super::ShaderSpans {
            name: s.name.span(),
            each_dimension: s.dimensions.keys().map(|k| k.span()).collect(),
            dimensions: match (s.dimensions.first(), s.dimensions.last()) {
                (Some((first, _)), Some((_, last))) => first.span().start..last.span().end,
                _ => s.name.span(),
            },
            derived: derived_spans,
        },
    }
}

/// A shader's `levels` (all of the file's when left out), each one declared, none twice.
fn shader_levels(c: &mut Checker, scope: &LevelScope<'_>, s: &RawShader) -> Vec<String> {
    let name = s.name.get_ref();
    let level_names: Vec<Spanned<String>> = match &s.levels {
        Some(ls) => {
            if ls.get_ref().is_empty() {
                c.error(ls.span(), format!("shader `{name}` has no levels"), "expected at least one level name");
            }
            ls.get_ref().clone()
        }
        None => scope.raw_levels.keys().cloned().collect(),
    };
    let mut shader_levels: Vec<String> = Vec::new();
    for l in &level_names {
        if !scope.defines.contains_key(l.get_ref().as_str()) {
            let known: Vec<&str> = scope.raw_levels.keys().map(|k| k.get_ref().as_str()).collect();
            let d =
                c.error(l.span(), format!("unknown level `{}`", l.get_ref()), "no `[levels.*]` table has this name");
            d.notes.push(if known.is_empty() {
                "no levels are declared: add a `[levels.NAME]` table".to_string()
            } else {
                format!("expected one of: {}", known.join(", "))
            });
        } else if shader_levels.contains(l.get_ref()) {
            c.error(l.span(), format!("level `{}` is listed twice", l.get_ref()), "listed again here");
        } else {
            shader_levels.push(l.get_ref().clone());
        }
    }
    if s.levels.is_none() && scope.raw_levels.is_empty() {
        c.error(s.name.span(), format!("shader `{name}` has no levels"), "no `[levels.*]` table is declared");
    }
    shader_levels
}

/// One dimension of a shader, its name (and an enum's `DIM_VALUE` defines) added to `names`.
fn shader_dimension(
    c: &mut Checker,
    names: &mut ShaderScope<'_>,
    k: &Spanned<String>,
    kind: &DimensionKind,
) -> Dimension {
    let dname = k.get_ref();
    if !is_ident(dname) {
        c.error(k.span(), format!("`{dname}` is not a valid dimension name"), "expected an identifier");
    }
    c.reserved(k, "dimension");
    names.clash(c, "dimension", k, dname);
    names.names.insert(dname.clone(), (k.span(), "dimension"));
    match kind {
        DimensionKind::Values(values, is_bool) => {
            Dimension { name: dname.clone(), values: values.clone(), labels: Vec::new(), is_bool: *is_bool }
        }
        DimensionKind::Enum(labels) => {
            for label in labels {
                let define = format!("{dname}_{label}");
                if !names.clash(c, "enum value", k, &define) {
                    names.names.insert(define, (k.span(), "dimension's enum value"));
                }
            }
            Dimension {
                name: dname.clone(),
                values: (0..labels.len() as i64).collect(),
                labels: labels.clone(),
                is_bool: false,
            }
        }
    }
}

/// A shader's derived defines (name, expression) and the span of each expression.
fn shader_derived(
    c: &mut Checker,
    scope: &LevelScope<'_>,
    names: &mut ShaderScope<'_>,
    s: &RawShader,
) -> (Vec<(String, String)>, Vec<Range<usize>>) {
    let derived_names: Vec<&str> = s.derived.keys().map(|k| k.get_ref().as_str()).collect();
    let mut derived = Vec::new();
    let mut derived_spans = Vec::new();
    for (i, (k, expr)) in s.derived.iter().enumerate() {
        let dname = k.get_ref();
        if !is_ident(dname) {
            c.error(k.span(), format!("`{dname}` is not a valid define name"), "expected an identifier");
        }
        c.reserved(k, "derived define");
        names.clash(c, "derived define", k, dname);
        names.names.insert(dname.clone(), (k.span(), "derived define"));
        if check_expression(c, scope.text, expr) {
            check_derived_dependencies(c, scope.text, &s.derived, &derived_names, i);
            let known = |id: &str| {
                scope.all_defines.contains(id) || names.names.contains_key(id) || derived_names.contains(&id)
            };
            c.unknown_identifiers(scope.text, expr, &known, &format!("derived define `{dname}`"));
        }
        derived.push((dname.clone(), expr.get_ref().clone()));
        derived_spans.push(expr.span());
    }
    (derived, derived_spans)
}

/// A shader's skip rules: expressions over what they may see, each with a reason.
fn shader_skip(c: &mut Checker, scope: &LevelScope<'_>, names: &ShaderScope<'_>, s: &RawShader) -> Vec<SkipRule> {
    let text = scope.text;
    let derived_names: Vec<&str> = s.derived.keys().map(|k| k.get_ref().as_str()).collect();
    let mut skip = Vec::new();
    for rule in &s.skip {
        let r = rule.get_ref();
        if check_expression(c, text, &r.when) {
            for id in preprocess::expr::identifiers(r.when.get_ref()) {
                if let Some((dk, _)) = s.derived.get_key_value(id.as_str()) {
                    let at = find_word(r.when.get_ref(), &id).unwrap_or(0);
                    let span = inner_span(text, &r.when.span(), r.when.get_ref(), at, id.len());
                    let d = c.error(
                        span,
                        format!("skip rule uses derived define `{id}`"),
                        "skip rules do not see derived defines",
                    );
                    d.labels.push(Label::secondary((), dk.span()).with_message("derived here"));
                    d.notes.push("skip rules see the dimensions and the level's and shader's defines; write the condition in those terms".into());
                }
            }
            let known = |id: &str| {
                scope.all_defines.contains(id) || names.names.contains_key(id) || derived_names.contains(&id)
            };
            c.unknown_identifiers(text, &r.when, &known, "skip rule");
        }
        if r.why.get_ref().trim().is_empty() {
            c.error(
                r.why.span(),
                "a skip rule needs a reason",
                "expected a sentence saying why these permutations are not needed",
            );
        }
        skip.push(SkipRule { when: r.when.get_ref().clone(), why: r.why.get_ref().clone(), span: r.when.span() });
    }
    skip
}

/// A shader's source, resolved like `#include <...>` (empty while the roots are bad).
fn shader_source(c: &mut Checker, scope: &LevelScope<'_>, s: &RawShader) -> PathBuf {
    if !scope.roots_ok {
        return PathBuf::new();
    }
    match preprocess::resolve_source(s.source.get_ref(), &scope.pp_options) {
        Ok(p) => p,
        Err(e) => {
            let d = c.error(
                s.source.span(),
                format!("cannot resolve source `{}` of shader `{}`", s.source.get_ref(), s.name.get_ref()),
                "not found",
            );
            d.notes.push(e.to_string());
            d.notes.push(
                "a source resolves like `#include <...>`: through a virtual root or against the include roots".into(),
            );
            PathBuf::new()
        }
    }
}

/// The span of the first line that nests deepest (dotted key parts, brackets, braces): where
/// a "recursion limit" error, which toml gives without a span, comes from. Clipped to 80 bytes.
fn deepest_line(text: &str) -> Option<Range<usize>> {
    let mut best: Option<(usize, Range<usize>)> = None;
    let mut start = 0;
    for line in text.split_inclusive('\n') {
        let depth = line.bytes().filter(|b| matches!(b, b'.' | b'[' | b'{')).count();
        if depth > 0 && best.as_ref().is_none_or(|(d, _)| depth > *d) {
            let trimmed = line.trim_end().len();
            best = Some((depth, start..start + trimmed.clamp(1, 80)));
        }
        start += line.len();
    }
    best.map(|(_, span)| span)
}

/// The span of `targets = ...` in the level table whose name is at `name` (the name itself
/// when it is not found).
fn level_targets_span(text: &str, name: Range<usize>) -> Range<usize> {
    let from = name.end.min(text.len());
    let rest = text.get(from..).unwrap_or("");
    let end = rest.find("\n[").map_or(rest.len(), |i| i + 1);
    match find_word(&rest[..end], "targets") {
        Some(at) => {
            let line_end = rest[at..end].find('\n').map_or(end, |i| at + i);
            from + at..from + line_end
        }
        None => name,
    }
}

/// The label under a serde/toml error, from its message.
fn label_for(message: &str) -> String {
    if message.starts_with("unknown field") {
        "unknown key".into()
    } else if message.starts_with("missing field") {
        "in this table".into()
    } else if message.starts_with("invalid type") {
        "wrong type".into()
    } else if message.starts_with("unknown variant") {
        "unknown value".into()
    } else {
        "here".into()
    }
}

/// Checks that `expr` parses; reports the column of the problem. Returns whether it parsed.
fn check_expression(c: &mut Checker, text: &str, expr: &Spanned<String>) -> bool {
    // Every identifier reads as 1, so a division by an identifier cannot fail here: what
    // fails is the syntax.
    match preprocess::expr::eval(expr.get_ref(), &|_| Some(1)) {
        Ok(_) => true,
        Err(e) => {
            let span = inner_span(text, &expr.span(), expr.get_ref(), e.offset, e.len);
            c.error(span, format!("invalid expression: {}", e.message), e.message.clone())
                .notes
                .push("expressions use the `#if` language: integers, defined(X), ! ~ * / % + - << >> < <= > >= == != & ^ | && || ?:".into());
            false
        }
    }
}

/// Derived define `index` may use only derived defines written before it.
fn check_derived_dependencies(
    c: &mut Checker,
    text: &str,
    derived: &IndexMap<Spanned<String>, Spanned<String>>,
    names: &[&str],
    index: usize,
) {
    let (key, expr) = derived.get_index(index).expect("index in range");
    let name = key.get_ref().as_str();
    let uses = |i: usize| -> Vec<usize> {
        let (_, e) = derived.get_index(i).expect("index in range");
        let ids = preprocess::expr::identifiers(e.get_ref());
        (0..names.len()).filter(|j| ids.iter().any(|id| id == names[*j])).collect()
    };
    let point_at = |id: &str| {
        let at = find_word(expr.get_ref(), id).unwrap_or(0);
        inner_span(text, &expr.span(), expr.get_ref(), at, id.len())
    };
    for j in uses(index) {
        if j == index {
            c.error(
                point_at(name),
                format!("derived define `{name}` depends on itself"),
                format!("`{name}` is used in its own definition"),
            );
            return;
        }
        if j < index {
            continue;
        }
        // A later derived define: is there a path back to `index`?
        let mut seen = HashSet::new();
        let mut stack = vec![(j, vec![j])];
        let mut cycle = None;
        while let Some((k, path)) = stack.pop() {
            if !seen.insert(k) {
                continue;
            }
            for n in uses(k) {
                if n == index {
                    cycle = Some(path.clone());
                    break;
                }
                let mut p = path.clone();
                p.push(n);
                stack.push((n, p));
            }
            if cycle.is_some() {
                break;
            }
        }
        let later = names[j];
        match cycle {
            Some(path) => {
                let chain: Vec<&str> =
                    std::iter::once(name).chain(path.iter().map(|k| names[*k])).chain(std::iter::once(name)).collect();
                let d = c.error(
                    point_at(later),
                    format!("derived define `{name}` depends on itself through `{later}`"),
                    format!("`{later}` depends on `{name}`"),
                );
                d.notes.push(format!("cycle: {}", chain.join(" -> ")));
            }
            None => {
                let d = c.error(
                    point_at(later),
                    format!("derived define `{name}` uses `{later}`, which is derived after it"),
                    "declared later",
                );
                d.notes.push(
                    "a derived define sees only the derived defines written before it: move it after the ones it uses"
                        .into(),
                );
            }
        }
        return;
    }
}
