//! The `hello-kiln` binary: a PNG of what the shaders compute (with the validation layer on),
//! exit 2 for bad usage, exit 1 and no file when the PNG cannot be written.

use std::process::{Command, Output};

fn hello(args: &[&str], dir: &std::path::Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_hello-kiln")).args(args).current_dir(dir).output().unwrap()
}

fn text(o: &Output) -> String {
    format!("stdout: {}\nstderr: {}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

#[test]
fn writes_the_png_the_shaders_compute() {
    let dir = tempfile::tempdir().unwrap();
    let o =
        hello(&["--out", "cool.png", "--palette", "cool", "--no-tint", "--size", "32x16", "--validation"], dir.path());
    // A missing device or layer is a failure naming the Debian package, never a skip.
    assert_eq!(o.status.code(), Some(0), "{} (Debian: mesa-vulkan-drivers, vulkan-validationlayers)", text(&o));
    assert!(String::from_utf8_lossy(&o.stdout).contains("HelloPS@portable{PALETTE=COOL,TINT=0}"), "{}", text(&o));
    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(dir.path().join("cool.png")).unwrap()));
    let mut reader = decoder.read_info().unwrap();
    let mut rgba = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut rgba).unwrap();
    assert_eq!((info.width, info.height, info.color_type), (32, 16, png::ColorType::Rgba));
    let pixel = |x: usize, y: usize| &rgba[(y * 32 + x) * 4..][..4];
    // COOL (0.2, 0.6, 1.0) at the centre of the quad; the clear color in a corner.
    assert_eq!(pixel(16, 8), [51, 153, 255, 255]);
    assert_eq!(pixel(0, 0), [0, 0, 51, 255]);
    let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(names, ["cool.png"], "no temporary file is left");
}

#[test]
fn bad_usage_exits_2_with_the_usage() {
    let dir = tempfile::tempdir().unwrap();
    for args in [&["--shape", "hexagon"][..], &["--size", "64"], &["--bogus"], &["--out"]] {
        let o = hello(args, dir.path());
        assert_eq!(o.status.code(), Some(2), "{args:?}: {}", text(&o));
        assert!(String::from_utf8_lossy(&o.stderr).contains("usage: hello-kiln"), "{args:?}: {}", text(&o));
    }
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
}

#[test]
fn an_unwritable_output_exits_1_and_leaves_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let o = hello(&["--out", "missing/dir/x.png"], dir.path());
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert!(String::from_utf8_lossy(&o.stderr).contains("cannot write missing/dir/x.png"), "{}", text(&o));
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
}
