// Interim: embeds the archive named by KILN_DEV_ARCHIVE (or an empty archive) until
// kiln::Build lands on this branch.
fn main() {
    println!("cargo:rerun-if-env-changed=KILN_DEV_ARCHIVE");
    let out = std::path::PathBuf::from(std::env::var("OUT_DIR").unwrap()).join("shaders.kpak");
    let bytes = match std::env::var("KILN_DEV_ARCHIVE") {
        Ok(p) => {
            println!("cargo:rerun-if-changed={p}");
            std::fs::read(p).unwrap()
        }
        Err(_) => kiln::archive::ArchiveWriter::new().to_bytes(),
    };
    std::fs::write(out, bytes).unwrap();
}
