//! Generated permutation sets of chosen shapes, for the compile bench and the tests of
//! module sharing: how many shaders, how many dimensions change the entry point's code,
//! how many only change helpers no entry point calls (as Unreal's shared headers do), and
//! how large each source is.
//!
//! Each shader includes one shared header of `helpers` functions (about 550 bytes each).
//! A `USE_k` dimension makes the entry point call helper `k` (so each of its values is
//! another module); an `UNUSED_k` dimension changes the body of a function nothing calls
//! (another token stream, the same compacted module). Shaders alternate between fragment
//! and compute entry points; every level is desktop (`spirv`, `msl`, `hlsl`, `wgsl`), and
//! with `mobile` a second, downlevel level writes `glsl`, `spirv`, `msl` and `wgsl`.

#![allow(dead_code)]

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

#[derive(Clone, Debug)]
pub struct Shape {
    pub name: &'static str,
    pub shaders: usize,
    /// Bool dimensions the entry point's code depends on.
    pub used: usize,
    /// Bool dimensions that only change a function nothing calls.
    pub unused: usize,
    /// Functions in the shared header (the source's size: about 550 bytes each).
    pub helpers: usize,
    /// How many of them every entry point calls (besides one per `USE_k`).
    pub calls: usize,
    /// A second, downlevel level (GLSL ES among its targets).
    pub mobile: bool,
}

impl Shape {
    /// Kept permutations.
    pub fn permutations(&self) -> usize {
        self.shaders * (1 << (self.used + self.unused)) * if self.mobile { 2 } else { 1 }
    }
}

/// Writes the set into `dir` (`permutations.toml`, `Common.ush`, one `.usf` per shader) and
/// returns the config's path.
pub fn write(dir: &Path, shape: &Shape) -> PathBuf {
    std::fs::create_dir_all(dir).unwrap();
    std::fs::write(dir.join("Common.ush"), header(shape)).unwrap();
    let mut toml = String::from("[compiler]\ninclude = [\".\"]\n\n");
    toml.push_str(
        "[levels.sm5]\ndefines = { SM5_PROFILE = 1 }\ntargets = [\"spirv\", \"msl\", \"hlsl\", \"wgsl\"]\n\n",
    );
    if shape.mobile {
        toml.push_str(
            "[levels.es3_1]\ndefines = { ES3_1_PROFILE = 1 }\ntargets = [\"glsl\", \"spirv\", \"msl\", \"wgsl\"]\nlimits = \"downlevel\"\n\n",
        );
    }
    let levels = if shape.mobile { "[\"sm5\", \"es3_1\"]" } else { "[\"sm5\"]" };
    for s in 0..shape.shaders {
        let compute = s % 2 == 1;
        std::fs::write(dir.join(format!("Shader{s}.usf")), shader(shape, s, compute)).unwrap();
        let dims: Vec<String> = (0..shape.used)
            .map(|k| format!("USE_{k} = \"bool\""))
            .chain((0..shape.unused).map(|k| format!("UNUSED_{k} = \"bool\"")))
            .collect();
        let _ = write!(
            toml,
            "[[shader]]\nname = \"Shader{s}\"\nsource = \"Shader{s}.usf\"\nentry = \"{}\"\nstage = \"{}\"\nlevels = {levels}\n",
            if compute { "main_cs" } else { "main_ps" },
            if compute { "compute" } else { "fragment" },
        );
        if !dims.is_empty() {
            let _ = writeln!(toml, "dimensions = {{ {} }}", dims.join(", "));
        }
        toml.push('\n');
    }
    let path = dir.join("permutations.toml");
    std::fs::write(&path, toml).unwrap();
    path
}

/// The shared header: uniforms, resources, and `helpers` functions of some arithmetic each.
fn header(shape: &Shape) -> String {
    let mut t = String::from(
        "// Generated: a shared header most of which any one shader never calls.\n\
         struct View {\n    tint: vec4<f32>,\n    scale: vec4<f32>,\n    params: vec4<f32>,\n}\n\
         @group(0) @binding(0) var<uniform> view: View;\n\
         @group(0) @binding(1) var color_tex: texture_2d<f32>;\n\n",
    );
    for i in 0..shape.helpers {
        let (a, b, c) = (1.0 + i as f32 * 0.125, 0.5 + (i % 7) as f32 * 0.25, (i % 5) as f32 + 0.75);
        let _ = write!(
            t,
            "fn helper_{i}(x: vec4<f32>, p: vec2<f32>) -> vec4<f32> {{\n\
             \x20   var a = x * {a:.3} + view.tint * {b:.3};\n\
             \x20   let s = sin(p.x * {c:.3}) * cos(p.y * {b:.3});\n\
             \x20   a = a + vec4<f32>(s, s * 0.5, -s, 1.0) * view.scale;\n\
             \x20   if (a.x > {c:.3}) {{\n\
             \x20       a = a.yzwx * {b:.3};\n\
             \x20   }} else {{\n\
             \x20       a = mix(a, a.wzyx, vec4<f32>(clamp(s, 0.0, 1.0)));\n\
             \x20   }}\n\
             \x20   for (var k = 0; k < 3; k = k + 1) {{\n\
             \x20       a = a * 0.9 + vec4<f32>(f32(k) * {a:.3});\n\
             \x20   }}\n\
             \x20   return normalize(a + vec4<f32>(0.001)) * length(x) + view.params * dot(a.xy, p);\n\
             }}\n\n",
        );
    }
    for k in 0..shape.unused {
        // Changes with its dimension; no entry point calls it.
        let _ = write!(
            t,
            "fn unused_{k}(x: vec4<f32>) -> vec4<f32> {{\n\
             #if UNUSED_{k}\n    return x * {}.5 + view.params;\n#else\n    return x.wzyx - view.tint;\n#endif\n}}\n\n",
            k + 2,
        );
    }
    t
}

/// One shader: it calls a few of the header's helpers always, and helper `k` under `USE_k`.
fn shader(shape: &Shape, s: usize, compute: bool) -> String {
    let mut body = String::new();
    for j in 0..shape.calls {
        let h = (s * 7 + j * 3) % shape.helpers;
        let _ = writeln!(body, "    c = helper_{h}(c, uv);");
    }
    for k in 0..shape.used {
        let h = (s * 5 + k * 11 + 1) % shape.helpers;
        let _ = writeln!(body, "#if USE_{k}\n    c = helper_{h}(c, uv * {}.0);\n#endif", k + 2);
    }
    if compute {
        format!(
            "#include \"Common.ush\"\n\n\
             @group(0) @binding(2) var<storage, read_write> out_buf: array<vec4<f32>>;\n\n\
             @compute @workgroup_size(64)\n\
             fn main_cs(@builtin(global_invocation_id) id: vec3<u32>) {{\n\
             \x20   let uv = vec2<f32>(f32(id.x & 63u), f32(id.x >> 6u)) / 64.0;\n\
             \x20   var c = textureLoad(color_tex, vec2<i32>(id.xy), 0) * {s}.0;\n\
             {body}\
             \x20   out_buf[id.x] = c;\n}}\n"
        )
    } else {
        format!(
            "#include \"Common.ush\"\n\n\
             @fragment\n\
             fn main_ps(@builtin(position) frag: vec4<f32>, @location(0) uv: vec2<f32>) -> @location(0) vec4<f32> {{\n\
             \x20   var c = textureLoad(color_tex, vec2<i32>(frag.xy), 0) + vec4<f32>(f32({s}));\n\
             {body}\
             \x20   return c;\n}}\n"
        )
    }
}
