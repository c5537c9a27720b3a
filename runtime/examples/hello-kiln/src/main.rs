//! `hello-kiln [--out hello.png] [--shape triangle|quad] [--palette warm|cool] [--no-tint]
//! [--backend vulkan|gl] [--size WxH] [--validation]`: renders one frame headless with the
//! example's own shaders and writes it as a PNG. `--validation` renders with the Khronos
//! validation layer (GL: debug output) and fails on any message. Exit status: 0 done,
//! 1 rendering failed, 2 bad usage.

use std::path::PathBuf;
use std::process::ExitCode;

use kiln_example_hello::{archive, render, Frame, Image, Palette, Shape};
use kiln_runtime::pipelines::PipelineCache;
use kiln_runtime::{Backend, Gpu, GpuOptions};

const USAGE: &str = "usage: hello-kiln [--out hello.png] [--shape triangle|quad] [--palette warm|cool] [--no-tint] \
                     [--backend vulkan|gl] [--size WxH] [--validation]";

struct Args {
    out: PathBuf,
    backend: Backend,
    validation: bool,
    frame: Frame,
}

fn parse(mut args: impl Iterator<Item = String>) -> Result<Args, String> {
    let mut parsed =
        Args { out: PathBuf::from("hello.png"), backend: Backend::Vulkan, validation: false, frame: Frame::default() };
    while let Some(arg) = args.next() {
        let mut value = |name: &str| args.next().ok_or_else(|| format!("{name} needs a value"));
        match arg.as_str() {
            "--out" => parsed.out = PathBuf::from(value("--out")?),
            "--shape" => {
                let v = value("--shape")?;
                parsed.frame.shape = *Shape::ALL
                    .iter()
                    .find(|s| s.name().eq_ignore_ascii_case(&v))
                    .ok_or_else(|| format!("--shape: `{v}` is not triangle or quad"))?;
            }
            "--palette" => {
                let v = value("--palette")?;
                parsed.frame.palette = *Palette::ALL
                    .iter()
                    .find(|p| p.name().eq_ignore_ascii_case(&v))
                    .ok_or_else(|| format!("--palette: `{v}` is not warm or cool"))?;
            }
            "--no-tint" => parsed.frame.tint = None,
            "--validation" => parsed.validation = true,
            "--backend" => {
                let name = value("--backend")?;
                parsed.backend =
                    Backend::from_name(&name).ok_or_else(|| format!("--backend: `{name}` is not vulkan or gl"))?;
            }
            "--size" => {
                let size = value("--size")?;
                let wh = size.split_once('x').and_then(|(w, h)| Some((w.parse().ok()?, h.parse().ok()?)));
                let Some((width, height)) = wh else { return Err(format!("--size: `{size}` is not WxH")) };
                (parsed.frame.width, parsed.frame.height) = (width, height);
            }
            "-h" | "--help" => return Err(String::new()),
            other => return Err(format!("unknown argument `{other}`")),
        }
    }
    Ok(parsed)
}

fn write_png(path: &std::path::Path, image: &Image) -> Result<(), String> {
    let what = |e: &dyn std::fmt::Display| format!("cannot write {}: {e}", path.display());
    let dir = path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(std::path::Path::new("."));
    // A temporary file renamed into place: never a half-written PNG.
    let temp = path.with_file_name(format!(".{}.tmp", path.file_name().and_then(|n| n.to_str()).unwrap_or("out")));
    let file = std::fs::File::create(&temp).map_err(|e| what(&format_args!("{e} (in {})", dir.display())))?;
    let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), image.width, image.height);
    encoder.set_color(png::ColorType::Rgba);
    encoder.set_depth(png::BitDepth::Eight);
    let written = encoder
        .write_header()
        .and_then(|mut w| w.write_image_data(&image.rgba).and_then(|()| w.finish()))
        .map_err(|e| what(&e))
        .and_then(|()| std::fs::rename(&temp, path).map_err(|e| what(&e)));
    if written.is_err() {
        let _ = std::fs::remove_file(&temp);
    }
    written
}

fn main() -> ExitCode {
    let args = match parse(std::env::args().skip(1)) {
        Ok(a) => a,
        Err(e) if e.is_empty() => {
            println!("{USAGE}");
            return ExitCode::SUCCESS;
        }
        Err(e) => {
            eprintln!("hello-kiln: {e}\n{USAGE}");
            return ExitCode::from(2);
        }
    };
    let run = || -> Result<String, String> {
        // 1. The archive build.rs embedded, and a device.
        let archive = archive().map_err(|e| e.to_string())?;
        let gpu =
            Gpu::new(&GpuOptions { backend: args.backend, ..GpuOptions::default() }).map_err(|e| e.to_string())?;
        // 2. The runtime's pipeline cache over that archive (one per device and archive).
        let cache = PipelineCache::new(&gpu, archive);
        // 3. Render: the cache finds or creates the pipeline of the frame's permutations.
        let image = render(&gpu, &cache, &args.frame).map_err(|e| e.to_string())?;
        if args.validation {
            gpu.wait();
            let messages = kiln_runtime::validation::take();
            if !messages.is_empty() {
                return Err(format!("{} validation message(s):\n{}", messages.len(), messages.join("\n")));
            }
        }
        write_png(&args.out, &image)?;
        let modules = if cache.uses_spirv_passthrough() { "SPIR-V passthrough" } else { "WGSL" };
        Ok(format!(
            "wrote {} ({}x{}, {} on {}, modules from {modules}: {})",
            args.out.display(),
            image.width,
            image.height,
            gpu.backend,
            gpu.info.name,
            cache.permutations_used().join(" + ")
        ))
    };
    match run() {
        Ok(line) => {
            println!("{line}");
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("hello-kiln: {e}");
            ExitCode::from(1)
        }
    }
}
