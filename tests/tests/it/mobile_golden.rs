//! Golden images of the mobile frames: the bundled scene at 320x180 on lavapipe, compared
//! with the references committed under `tests/golden/`. Tolerance: 40 dB PSNR (lavapipe is
//! deterministic, so a rerun matches exactly; the margin absorbs Mesa versions that round
//! differently, while a lost light, shadow or pass costs far more). `KILN_BLESS=1` rewrites
//! the references.

use crate::mobile_support::*;
use kiln_renderer::mobile::MobileOptions;
use kiln_renderer::scene::Scene;
use kiln_runtime::Backend;

const TOLERANCE_PSNR: f64 = 40.0;

fn check(name: &str, options: MobileOptions) {
    let rig = rig(Backend::Vulkan);
    let image = rig.render(&Scene::bundled(), options);
    let path = golden_dir().join(format!("{name}.png"));
    if crate::support::bless() {
        std::fs::create_dir_all(golden_dir()).unwrap();
        kiln::archive::write_atomic(&path, &image.to_png()).unwrap();
        return;
    }
    assert!(path.exists(), "{} is missing: run with KILN_BLESS=1 to create it", path.display());
    let reference = read_png(&path);
    let p = psnr(&reference, &image);
    eprintln!("{name}: {p:.1} dB against {}", path.display());
    if p <= TOLERANCE_PSNR {
        let out = std::env::temp_dir().join(format!("{name}.actual.png"));
        let _ = std::fs::write(&out, image.to_png());
        panic!(
            "{name}: PSNR {p:.1} dB against the reference (tolerance {TOLERANCE_PSNR} dB); this frame is in {}",
            out.display()
        );
    }
}

#[test]
fn mobile_forward_matches_its_reference() {
    check("mobile_forward", MobileOptions::forward());
}

#[test]
fn mobile_deferred_matches_its_reference() {
    check("mobile_deferred", MobileOptions::deferred());
}

#[test]
fn mobile_forward_ldr_matches_its_reference() {
    // Mobile HDR off: gamma-space color straight from the base pass, no post processing.
    check("mobile_forward_ldr", MobileOptions { hdr: false, ..MobileOptions::forward() });
}
