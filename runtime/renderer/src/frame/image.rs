//! Read-back texels to 8-bit RGBA images, mapped so every target is visible.

use half_float::f16_to_f32;

/// How a captured target is mapped to 8 bits.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Visualize {
    /// Already display-ready (sRGB output) or data in [0, 1] (GBuffers): written as is.
    Direct,
    /// HDR color: Reinhard `x / (1 + x)`, then sRGB encoded.
    Hdr,
    /// Reverse-Z depth: the depths present are stretched to [0, 1], near bright, nothing
    /// drawn (0) black.
    Depth,
}

/// An 8-bit RGBA image.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    pub rgba: Vec<u8>,
}

impl Image {
    pub fn pixel(&self, x: u32, y: u32) -> [u8; 4] {
        let i = ((y * self.width + x) * 4) as usize;
        [self.rgba[i], self.rgba[i + 1], self.rgba[i + 2], self.rgba[i + 3]]
    }

    /// Mean luminance (0 to 255) of a rectangle.
    pub fn mean_luma(&self, x0: u32, y0: u32, x1: u32, y1: u32) -> f64 {
        let mut sum = 0.0;
        let mut n = 0.0;
        for y in y0..y1.min(self.height) {
            for x in x0..x1.min(self.width) {
                let [r, g, b, _] = self.pixel(x, y);
                sum += 0.299 * f64::from(r) + 0.587 * f64::from(g) + 0.114 * f64::from(b);
                n += 1.0;
            }
        }
        if n == 0.0 {
            0.0
        } else {
            sum / n
        }
    }

    /// Number of distinct colors (a constant image has 1).
    pub fn distinct_colors(&self) -> usize {
        let mut seen: Vec<[u8; 4]> = self.rgba.chunks_exact(4).map(|c| [c[0], c[1], c[2], c[3]]).collect();
        seen.sort_unstable();
        seen.dedup();
        seen.len()
    }

    /// PNG-encoded bytes.
    pub fn to_png(&self) -> Vec<u8> {
        let mut out = Vec::new();
        {
            let mut encoder = png::Encoder::new(&mut out, self.width, self.height);
            encoder.set_color(png::ColorType::Rgba);
            encoder.set_depth(png::BitDepth::Eight);
            let mut writer = encoder.write_header().expect("png header into a Vec");
            writer.write_image_data(&self.rgba).expect("png data into a Vec");
        }
        out
    }
}

fn srgb_encode(linear: f32) -> u8 {
    let c = linear.clamp(0.0, 1.0);
    let s = if c <= 0.003_130_8 { c * 12.92 } else { 1.055 * c.powf(1.0 / 2.4) - 0.055 };
    (s * 255.0 + 0.5) as u8
}

fn unorm(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8
}

/// Texels of one row as linear floats (rgba); `None` for formats the runtime never captures.
fn texel(format: wgpu::TextureFormat, b: &[u8]) -> Option<[f32; 4]> {
    use wgpu::TextureFormat as F;
    let f32_at = |i: usize| f32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]]);
    let f16_at = |i: usize| f16_to_f32(u16::from_le_bytes([b[i], b[i + 1]]));
    Some(match format {
        F::Rgba8Unorm | F::Rgba8UnormSrgb => [b[0], b[1], b[2], b[3]].map(|v| f32::from(v) / 255.0),
        F::Bgra8Unorm | F::Bgra8UnormSrgb => [b[2], b[1], b[0], b[3]].map(|v| f32::from(v) / 255.0),
        F::R8Unorm => [f32::from(b[0]) / 255.0, 0.0, 0.0, 1.0],
        F::Rgb10a2Unorm => {
            let v = u32::from_le_bytes([b[0], b[1], b[2], b[3]]);
            [
                (v & 1023) as f32 / 1023.0,
                ((v >> 10) & 1023) as f32 / 1023.0,
                ((v >> 20) & 1023) as f32 / 1023.0,
                (v >> 30) as f32 / 3.0,
            ]
        }
        F::Rgba16Float => [f16_at(0), f16_at(2), f16_at(4), f16_at(6)],
        F::Rg16Float => [f16_at(0), f16_at(2), 0.0, 1.0],
        F::R16Float => [f16_at(0), 0.0, 0.0, 1.0],
        F::R32Float | F::Depth32Float | F::Depth32FloatStencil8 => [f32_at(0), 0.0, 0.0, 1.0],
        F::Rg32Float => [f32_at(0), f32_at(4), 0.0, 1.0],
        F::Rgba32Float => [f32_at(0), f32_at(4), f32_at(8), f32_at(12)],
        F::R32Uint => [u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32, 0.0, 0.0, 1.0],
        _ => return None,
    })
}

/// Converts read-back bytes to an image (`None` for an unsupported format).
pub(super) fn decode(
    bytes: &[u8],
    width: u32,
    height: u32,
    padded_row: u32,
    format: wgpu::TextureFormat,
    visualize: Visualize,
) -> Option<Image> {
    let bpp = format
        .block_copy_size(Some(wgpu::TextureAspect::All))
        .or_else(|| format.block_copy_size(Some(wgpu::TextureAspect::DepthOnly)))? as usize;
    // Depth packed into rgba8unorm by `VisualizeDepthPS`: the bytes are the float's bits.
    let packed_depth = visualize == Visualize::Depth && format == wgpu::TextureFormat::Rgba8Unorm;
    let mut texels = Vec::with_capacity((width * height) as usize);
    for y in 0..height as usize {
        let row = &bytes[y * padded_row as usize..];
        for x in 0..width as usize {
            let b = &row[x * bpp..x * bpp + bpp];
            texels.push(if packed_depth {
                [f32::from_le_bytes([b[0], b[1], b[2], b[3]]), 0.0, 0.0, 1.0]
            } else {
                texel(format, b)?
            });
        }
    }
    let rgba = match visualize {
        Visualize::Direct => texels
            .iter()
            .flat_map(|t| {
                // sRGB formats hold encoded bytes already: written as they are.
                [unorm(t[0]), unorm(t[1]), unorm(t[2]), 255]
            })
            .collect(),
        Visualize::Hdr => texels
            .iter()
            .flat_map(|t| {
                let m = |v: f32| srgb_encode(v.max(0.0) / (1.0 + v.max(0.0)));
                [m(t[0]), m(t[1]), m(t[2]), 255]
            })
            .collect(),
        Visualize::Depth => {
            let drawn = texels.iter().map(|t| t[0]).filter(|d| *d > 0.0);
            let (lo, hi) = drawn.fold((f32::MAX, f32::MIN), |(lo, hi), d| (lo.min(d), hi.max(d)));
            let range = (hi - lo).max(1e-12);
            texels
                .iter()
                .flat_map(|t| {
                    let v = if t[0] > 0.0 { unorm(0.1 + 0.9 * (t[0] - lo) / range) } else { 0 };
                    [v, v, v, 255]
                })
                .collect()
        }
    };
    Some(Image { width, height, rgba })
}

/// IEEE half to single precision, without a dependency.
mod half_float {
    pub fn f16_to_f32(h: u16) -> f32 {
        let sign = if h & 0x8000 != 0 { -1.0 } else { 1.0 };
        let exp = i32::from((h >> 10) & 0x1f);
        let frac = f32::from(h & 0x3ff);
        match exp {
            0 => sign * frac * 2f32.powi(-24),
            31 => {
                if frac == 0.0 {
                    sign * f32::INFINITY
                } else {
                    f32::NAN
                }
            }
            _ => sign * (1.0 + frac / 1024.0) * 2f32.powi(exp - 15),
        }
    }

    #[cfg(test)]
    mod tests {
        #[test]
        fn known_halves() {
            for (h, f) in [
                (0x3c00u16, 1.0f32),
                (0xc000, -2.0),
                (0x3800, 0.5),
                (0x0000, 0.0),
                (0x7bff, 65504.0),
                (0x0001, 5.960_464_5e-8),
            ] {
                assert_eq!(super::f16_to_f32(h), f, "{h:#06x}");
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_is_stretched_and_background_black() {
        let bytes: Vec<u8> = [0.0f32, 0.5, 0.75, 1.0].iter().flat_map(|d| d.to_le_bytes()).collect();
        let img = decode(&bytes, 4, 1, 16, wgpu::TextureFormat::Depth32Float, Visualize::Depth).unwrap();
        let v: Vec<u8> = img.rgba.chunks(4).map(|c| c[0]).collect();
        assert_eq!(v, vec![0, 26, 140, 255]);
    }

    #[test]
    fn packed_depth_is_read_from_its_bits() {
        let bytes: Vec<u8> = [0.0f32, 0.25, 0.5].iter().flat_map(|d| d.to_le_bytes()).collect();
        let img = decode(&bytes, 3, 1, 12, wgpu::TextureFormat::Rgba8Unorm, Visualize::Depth).unwrap();
        let v: Vec<u8> = img.rgba.chunks(4).map(|c| c[0]).collect();
        assert_eq!(v, vec![0, 26, 255]);
    }

    #[test]
    fn hdr_is_tonemapped_into_range() {
        let one = 0x3c00u16.to_le_bytes();
        let big = 0x7bffu16.to_le_bytes();
        let bytes: Vec<u8> = [one, one, one, one, big, big, big, one].concat();
        let img = decode(&bytes, 2, 1, 16, wgpu::TextureFormat::Rgba16Float, Visualize::Hdr).unwrap();
        assert_eq!(img.pixel(0, 0), [188, 188, 188, 255], "1.0 -> 0.5 linear -> sRGB 188");
        assert_eq!(img.pixel(1, 0)[0], 255);
    }

    #[test]
    fn rgb10a2_decodes_each_channel() {
        let v: u32 = 1023 | (512 << 10) | (3 << 30); // blue 0
        let img = decode(&v.to_le_bytes(), 1, 1, 4, wgpu::TextureFormat::Rgb10a2Unorm, Visualize::Direct).unwrap();
        assert_eq!(img.pixel(0, 0), [255, 128, 0, 255]);
    }
}
