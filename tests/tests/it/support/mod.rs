//! What every area's tests share: comparing images and blessing expected files.

use std::path::{Path, PathBuf};

use kiln_renderer::frame::Image;

/// Whether this run rewrites expected files (snapshots, golden images) instead of comparing
/// with them: `KILN_BLESS=1`. Review the diff afterwards.
pub fn bless() -> bool {
    std::env::var_os("KILN_BLESS").is_some()
}

/// The committed golden images, `tests/golden/`.
pub fn golden_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("golden")
}

/// Peak signal-to-noise ratio over RGB, in dB (infinite for identical images).
pub fn psnr(a: &Image, b: &Image) -> f64 {
    assert_eq!((a.width, a.height), (b.width, b.height));
    let mut se = 0.0f64;
    let mut n = 0.0f64;
    for (pa, pb) in a.rgba.chunks_exact(4).zip(b.rgba.chunks_exact(4)) {
        for c in 0..3 {
            let d = f64::from(pa[c]) - f64::from(pb[c]);
            se += d * d;
            n += 1.0;
        }
    }
    let mse = se / n;
    if mse == 0.0 {
        f64::INFINITY
    } else {
        10.0 * (255.0f64 * 255.0 / mse).log10()
    }
}

/// An RGBA PNG, read whole.
pub fn read_png(path: &Path) -> Image {
    let decoder = png::Decoder::new(std::io::BufReader::new(
        std::fs::File::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display())),
    ));
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    assert_eq!(info.color_type, png::ColorType::Rgba, "{}", path.display());
    buf.truncate(info.buffer_size());
    Image { width: info.width, height: info.height, rgba: buf }
}
