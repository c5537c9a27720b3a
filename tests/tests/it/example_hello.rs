//! The example app of `runtime/examples/hello-kiln`: its own permutations.toml and shaders,
//! built by its build.rs, rendered through the runtime's public API. The pixels must be what
//! its shaders compute, with the Khronos validation layer on (GL debug output on GL).

use kiln_example_hello::shaders::{hello_ps, hello_vs};
use kiln_example_hello::{archive, permutations, render, Frame, Image, Palette, Shape};
use kiln_runtime::pipelines::PipelineCache;
use kiln_runtime::validation::CheckedGpu;
use kiln_runtime::{Backend, GpuOptions};

/// A device with validation on, or a failing test that says what to install: a render test
/// never passes by skipping.
fn gpu(backend: Backend) -> CheckedGpu {
    CheckedGpu::new(&GpuOptions { backend, ..GpuOptions::default() })
        .unwrap_or_else(|e| panic!("the example renders on a {backend} adapter (Debian: mesa-vulkan-drivers): {e}"))
}

/// Pixel (column, row) of a 64x64 image at clip-space point (x, y).
fn at(x: f32, y: f32) -> (u32, u32) {
    (((x + 1.0) * 32.0) as u32, ((1.0 - y) * 32.0) as u32)
}

#[track_caller]
fn assert_pixel(image: &Image, (x, y): (u32, u32), want: [u8; 4], what: &str) {
    let got = image.pixel(x, y);
    let close = got.iter().zip(want).all(|(g, w)| g.abs_diff(w) <= 1);
    assert!(close, "{what}: pixel ({x}, {y}) is {got:?}, the shaders compute {want:?}");
}

/// Pixels that are not the clear color.
fn covered(image: &Image, clear: [u8; 4]) -> usize {
    image.rgba.chunks_exact(4).filter(|p| **p != clear).count()
}

const CLEAR: [u8; 4] = [0, 0, 51, 255];

#[test]
fn quad_tinted_warm_and_triangle_cool_on_vulkan_through_spirv_passthrough() {
    let gpu = gpu(Backend::Vulkan);
    let cache = PipelineCache::new(&gpu, archive().unwrap());
    assert!(cache.uses_spirv_passthrough(), "lavapipe allows passthrough and the example trusts its own archive");

    // WARM (1.0, 0.6, 0.2) times the tint (0.6, 1.0, 0.2) = (0.6, 0.6, 0.04).
    let quad = Frame::default();
    let image = render(&gpu, &cache, &quad).unwrap();
    assert_eq!((image.width, image.height), (64, 64));
    assert_pixel(&image, at(0.0, 0.0), [153, 153, 10, 255], "centre of the tinted warm quad");
    assert_pixel(&image, at(-0.4, 0.4), [153, 153, 10, 255], "upper left inside the quad");
    assert_pixel(&image, (0, 0), CLEAR, "top-left corner");
    assert_pixel(&image, (63, 63), CLEAR, "bottom-right corner");
    assert_eq!(covered(&image, CLEAR), 32 * 32, "the quad covers [-0.5, 0.5]^2: 32x32 pixels of 64x64");

    // The other permutation of each shader: no tint, so no binding at all.
    let triangle = Frame { shape: Shape::Triangle, palette: Palette::Cool, tint: None, ..Frame::default() };
    let image = render(&gpu, &cache, &triangle).unwrap();
    assert_pixel(&image, at(0.0, 0.0), [51, 153, 255, 255], "centre of the cool triangle");
    assert_pixel(&image, at(-0.4, 0.4), CLEAR, "upper left, outside the triangle");
    assert_pixel(&image, at(0.0, 0.45), [51, 153, 255, 255], "just under the apex");
    let n = covered(&image, CLEAR);
    assert!((480..=544).contains(&n), "the triangle covers half the quad's 1024 pixels, not {n}");

    // Both pipelines came from the runtime's cache, with layouts from reflection; a second
    // frame finds them.
    let stats = cache.stats();
    assert_eq!((stats.render_pipelines, stats.modules), (2, 4), "{stats:?}");
    render(&gpu, &cache, &quad).unwrap();
    assert_eq!(cache.stats(), stats, "the second frame of a pipeline creates nothing");
    assert_eq!(
        cache.permutations_used(),
        [
            "HelloPS@portable{PALETTE=COOL,TINT=0}",
            "HelloPS@portable{PALETTE=WARM,TINT=1}",
            "HelloVS@portable{SHAPE=QUAD}",
            "HelloVS@portable{SHAPE=TRIANGLE}",
        ]
    );
    gpu.check();
}

#[test]
fn bind_group_layouts_come_from_each_permutations_reflection() {
    let gpu = gpu(Backend::Vulkan);
    let archive = archive().unwrap();
    let cache = PipelineCache::new(&gpu, archive.clone());
    let state = kiln_runtime::pipelines::RenderState::fullscreen(kiln_runtime::pipelines::ColorTarget::new(
        kiln_example_hello::FORMAT,
        kiln_runtime::pipelines::Blend::Replace,
    ));
    let groups = |tint: Option<[f32; 4]>| {
        let (vs, ps) = permutations(&archive, &Frame { tint, ..Frame::default() }).unwrap();
        let pipeline = cache.render(&vs, Some(&ps), &state).unwrap();
        pipeline.layout.groups.iter().map(|g| g.iter().map(|b| (b.binding, b.name.clone())).collect()).collect()
    };
    let none: Vec<Vec<(u32, Option<String>)>> = groups(None);
    assert!(none.iter().all(Vec::is_empty), "TINT=0 binds nothing: {none:?}");
    assert_eq!(groups(Some([1.0; 4])), vec![vec![(0, Some("Tint".to_string()))]]);
    gpu.check();
}

#[test]
fn the_same_frames_on_gl_from_wgsl() {
    let gpu = gpu(Backend::Gl);
    let cache = PipelineCache::new(&gpu, archive().unwrap());
    assert!(!cache.uses_spirv_passthrough(), "GL takes WGSL");
    let image = render(&gpu, &cache, &Frame { palette: Palette::Cool, ..Frame::default() }).unwrap();
    // COOL (0.2, 0.6, 1.0) times the tint (0.6, 1.0, 0.2) = (0.12, 0.6, 0.2).
    assert_pixel(&image, at(0.0, 0.0), [31, 153, 51, 255], "centre of the tinted cool quad");
    assert_pixel(&image, (0, 63), CLEAR, "bottom-left corner");
    assert_eq!(covered(&image, CLEAR), 32 * 32);
    gpu.check();
}

#[test]
fn bad_sizes_are_errors_not_panics() {
    let gpu = gpu(Backend::Vulkan);
    let cache = PipelineCache::new(&gpu, archive().unwrap());
    let err = render(&gpu, &cache, &Frame { width: 0, ..Frame::default() }).unwrap_err().to_string();
    assert!(err.contains("0x64") && err.contains("1 to"), "{err}");
    gpu.check();
}

/// The example's typed keys (generated by its build.rs) find, by id, the very permutation a
/// lookup by dimension values finds, for every permutation of both shaders.
#[test]
fn typed_keys_find_what_names_find() {
    let archive = archive().unwrap();
    let mut seen = 0;
    for vs in hello_vs::Key::all() {
        for ps in hello_ps::Key::all() {
            let tint = ps.tint.then_some([1.0; 4]);
            let frame = Frame { shape: vs.shape, palette: ps.palette, tint, ..Frame::default() };
            let (vs_name, ps_name) = permutations(&archive, &frame).unwrap();
            let by_values = archive.shader("HelloVS").with("SHAPE", vs.shape.name()).find().unwrap();
            assert_eq!(vs_name, by_values.name());
            let by_values = archive
                .shader("HelloPS")
                .with("PALETTE", ps.palette.name())
                .with("TINT", u8::from(ps.tint))
                .find()
                .unwrap();
            assert_eq!(ps_name, by_values.name());
            seen += 1;
        }
    }
    assert_eq!(seen, 2 * 4);
    assert_eq!(archive.permutations().unwrap().count(), 2 + 4, "the archive holds the 6 permutations of the toml");
}

/// An application's own wgpu device, not the runtime's `Gpu`: the cache takes its adapter and
/// device, passes SPIR-V through because the device asked for `PASSTHROUGH_SHADERS`, and
/// creates every pipeline of the example with no validation message.
#[test]
fn a_cache_on_the_applications_own_device_creates_every_pipeline() {
    use kiln_runtime::pipelines::{Blend, ColorTarget, RenderState};
    use kiln_runtime::validation;
    assert!(validation::install(), "another logger is installed: validation messages cannot be recorded");
    assert!(
        validation::khronos_layer_manifest().is_some(),
        "no Khronos validation layer (Debian: vulkan-validationlayers)"
    );
    validation::enable_layer_for_process();
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = wgpu::Backends::VULKAN;
    desc.flags |= wgpu::InstanceFlags::DEBUG;
    let instance = wgpu::Instance::new(desc);
    let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions::default()))
        .expect("a Vulkan adapter (Debian: mesa-vulkan-drivers)");
    let (device, _queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
        label: Some("the application's device"),
        required_features: adapter.features() & wgpu::Features::PASSTHROUGH_SHADERS,
        ..Default::default()
    }))
    .unwrap();
    let cache = PipelineCache::for_device(&adapter, &device, archive().unwrap());
    assert_eq!(
        cache.uses_spirv_passthrough(),
        device.features().contains(wgpu::Features::PASSTHROUGH_SHADERS),
        "SPIR-V passthrough exactly where the device has it"
    );
    assert!(cache.uses_spirv_passthrough(), "lavapipe offers PASSTHROUGH_SHADERS");
    let state = RenderState::fullscreen(ColorTarget::new(kiln_example_hello::FORMAT, Blend::Replace));
    for shape in [Shape::Triangle, Shape::Quad] {
        for palette in [Palette::Warm, Palette::Cool] {
            for tint in [None, Some([0.5; 4])] {
                let (vs, ps) =
                    permutations(cache.archive(), &Frame { shape, palette, tint, ..Frame::default() }).unwrap();
                cache.render(&vs, Some(&ps), &state).unwrap_or_else(|e| panic!("{vs} + {ps}: {e}"));
            }
        }
    }
    assert_eq!(cache.stats().render_pipelines, 8);
    let _ = device.poll(wgpu::PollType::wait_indefinitely());
    let messages = validation::take();
    assert!(messages.is_empty(), "validation messages:\n{}", messages.join("\n"));
}
