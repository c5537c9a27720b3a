//! Reading permutation names back: exact lookup, and the nearest existing names when a name
//! names nothing.

use super::{Config, Near, NotFound, Permutation};
pub(super) use crate::archive::edit_distance;

/// A permutation name split into its parts, values as written.
#[derive(Debug, PartialEq, Eq)]
pub(super) struct ParsedName {
    pub shader: String,
    pub level: String,
    pub dims: Vec<(String, String)>,
}

/// Splits `Shader@level{A=1,B=X}`; `Err` says what is malformed.
pub(super) fn parse_name(name: &str) -> Result<ParsedName, String> {
    const FORM: &str = "a permutation name has the form `Shader@level{DIM=value,...}`";
    let name = name.trim();
    let Some((shader, rest)) = name.split_once('@') else {
        return Err(format!("no `@level`: {FORM}"));
    };
    let (level, dims) = match rest.find('{') {
        Some(i) => {
            let body = &rest[i + 1..];
            let Some(body) = body.trim_end().strip_suffix('}') else {
                return Err(format!("missing `}}` at the end: {FORM}"));
            };
            (&rest[..i], body)
        }
        None => (rest, ""),
    };
    let mut parsed = Vec::new();
    for part in dims.split(',').map(str::trim).filter(|p| !p.is_empty()) {
        let Some((k, v)) = part.split_once('=') else {
            return Err(format!("`{part}` has no `=value`: {FORM}"));
        };
        parsed.push((k.trim().to_string(), v.trim().to_string()));
    }
    Ok(ParsedName { shader: shader.trim().to_string(), level: level.trim().to_string(), dims: parsed })
}

/// The most kept permutations [`nearest`] compares with the name asked for.
const NEAREST_BUDGET: usize = 1 << 18;

pub(super) fn find<'c>(config: &'c Config, name: &str) -> Result<Permutation<'c>, NotFound> {
    let not_found = |reason: String, wanted: Option<&ParsedName>| NotFound {
        name: name.to_string(),
        reason,
        nearest: wanted.map(|w| nearest(config, w, 5)).unwrap_or_default(),
    };
    let wanted = parse_name(name).map_err(|r| not_found(r, None))?;
    let Some(shader) = config.shader(&wanted.shader) else {
        return Err(not_found(format!("no shader named `{}`", wanted.shader), Some(&wanted)));
    };
    let level = match config.level(&wanted.level) {
        Some(l) if shader.levels.contains(&l.name) => l,
        _ => {
            return Err(not_found(
                format!(
                    "shader `{}` has no level `{}` (its levels: {})",
                    shader.name,
                    wanted.level,
                    shader.levels.join(", ")
                ),
                Some(&wanted),
            ))
        }
    };
    let mut values = Vec::with_capacity(shader.dimensions.len());
    for (k, _) in &wanted.dims {
        if !shader.dimensions.iter().any(|d| &d.name == k) {
            let names: Vec<&str> = shader.dimensions.iter().map(|d| d.name.as_str()).collect();
            let have = if names.is_empty() { "none".to_string() } else { names.join(", ") };
            return Err(not_found(
                format!("shader `{}` has no dimension `{k}` (its dimensions: {have})", shader.name),
                Some(&wanted),
            ));
        }
        if wanted.dims.iter().filter(|(o, _)| o == k).count() > 1 {
            return Err(not_found(format!("dimension `{k}` is given twice"), Some(&wanted)));
        }
    }
    for d in &shader.dimensions {
        let Some((_, raw)) = wanted.dims.iter().find(|(k, _)| *k == d.name) else {
            return Err(not_found(format!("no value for dimension `{}`", d.name), Some(&wanted)));
        };
        let Some(i) = d.parse(raw) else {
            return Err(not_found(
                format!("`{raw}` is not a value of dimension `{}` ({})", d.name, d.describe()),
                Some(&wanted),
            ));
        };
        values.push(d.values[i]);
    }
    Ok(Permutation::new(shader, level, values))
}

/// The characters of a shader name that near-miss search compares (a longer name asked
/// for is compared on these: the search costs at most this times each shader name, once).
const NEAR_NAME_CHARS: usize = 256;
/// The dimensions of a name asked for that near-miss search compares.
const NEAR_DIMENSIONS: usize = 64;

/// `text` cut to at most `chars` characters.
fn capped(text: &str, chars: usize) -> &str {
    text.char_indices().nth(chars).map_or(text, |(i, _)| &text[..i])
}

/// The `limit` kept permutations closest to `wanted`: same shader first (then by edit
/// distance of the shader name), same level, fewest differing dimensions; ties in
/// enumeration order. Shader names are compared first, once each (on their first
/// [`NEAR_NAME_CHARS`] characters): the permutations of a shader whose name alone scores
/// worse than the best found are never looked at. Looks at the first [`NEAREST_BUDGET`]
/// kept permutations only, and at [`NEAR_DIMENSIONS`] dimensions of `wanted`.
pub(super) fn nearest(config: &Config, wanted: &ParsedName, limit: usize) -> Vec<Near> {
    let wanted_shader = capped(&wanted.shader, NEAR_NAME_CHARS);
    let wanted_dims = &wanted.dims[..wanted.dims.len().min(NEAR_DIMENSIONS)];
    let wanted = ParsedName { shader: wanted.shader.clone(), level: wanted.level.clone(), dims: wanted_dims.to_vec() };
    let wanted = &wanted;
    let base: std::collections::HashMap<&str, usize> = config
        .shaders
        .iter()
        .map(|s| {
            let d = if s.name == wanted.shader {
                0
            } else {
                1000 + 10 * edit_distance(capped(&s.name, NEAR_NAME_CHARS), wanted_shader)
            };
            (s.name.as_str(), d)
        })
        .collect();
    let mut best: Vec<(usize, usize, Near)> = Vec::new();
    let mut worst = usize::MAX;
    let skip = |s: &super::Shader, worst: usize| base.get(s.name.as_str()).is_some_and(|&b| b > worst);
    let worst_now = std::cell::Cell::new(usize::MAX);
    let kept = config.kept_where(|s, _| !skip(s, worst_now.get())).take(NEAREST_BUDGET);
    for (order, p) in kept.enumerate() {
        let mut score = base.get(p.shader.name.as_str()).copied().unwrap_or(0);
        if p.level.name != wanted.level {
            score += 100;
        }
        for (d, v) in p.shader.dimensions.iter().zip(&p.values) {
            match wanted.dims.iter().find(|(k, _)| *k == d.name) {
                Some((_, raw)) if d.parse(raw).map(|i| d.values[i]) == Some(*v) => {}
                _ => score += 1,
            }
        }
        score += wanted.dims.iter().filter(|(k, _)| !p.shader.dimensions.iter().any(|d| &d.name == k)).count();
        if best.len() >= limit && score >= worst {
            continue;
        }
        let mut differences = Vec::new();
        if p.shader.name != wanted.shader {
            differences.push(format!("shader: {} -> {}", wanted.shader, p.shader.name));
        }
        if p.level.name != wanted.level {
            differences.push(format!("level: {} -> {}", wanted.level, p.level.name));
        }
        for (d, v) in p.shader.dimensions.iter().zip(&p.values) {
            let have = d.display(*v);
            match wanted.dims.iter().find(|(k, _)| *k == d.name) {
                Some((_, raw)) if d.parse(raw).map(|i| d.values[i]) == Some(*v) => {}
                Some((_, raw)) => differences.push(format!("{}: {raw} -> {have}", d.name)),
                None => differences.push(format!("{}: (missing) -> {have}", d.name)),
            }
        }
        for (k, raw) in &wanted.dims {
            if !p.shader.dimensions.iter().any(|d| &d.name == k) {
                differences.push(format!("{k}: {raw} -> (no such dimension)"));
            }
        }
        best.push((score, order, Near { name: p.name(), differences }));
        best.sort_by_key(|(s, o, _)| (*s, *o));
        best.truncate(limit);
        if best.len() >= limit {
            worst = best[best.len() - 1].0;
            worst_now.set(worst);
        }
    }
    best.into_iter().map(|(_, _, n)| n).collect()
}
