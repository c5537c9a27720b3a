//! Reading a file by a path Kiln did not create (a cache file, a set of records, a
//! pipeline cache, a configuration, a source, an archive): only a regular file, and only up
//! to a bound, checked before anything is read or allocated. A FIFO (which would block the
//! reader), a device (`/dev/zero` never ends), a directory or a socket is an error that
//! says what the path is; the file is opened non-blocking and checked again once open, so
//! that a path swapped between the two looks cannot block either.

use std::fs::{File, Metadata};
use std::io::{self, Read};
use std::path::Path;

/// What a path that is not a regular file is, as an error's text.
pub fn describe(meta: &Metadata) -> &'static str {
    let t = meta.file_type();
    if t.is_dir() {
        return "it is a directory, not a regular file";
    }
    special(&t)
}

#[cfg(unix)]
fn special(t: &std::fs::FileType) -> &'static str {
    use std::os::unix::fs::FileTypeExt;
    if t.is_fifo() {
        "it is a FIFO, not a regular file"
    } else if t.is_socket() {
        "it is a socket, not a regular file"
    } else if t.is_char_device() || t.is_block_device() {
        "it is a device, not a regular file"
    } else {
        "it is not a regular file"
    }
}

#[cfg(not(unix))]
fn special(_: &std::fs::FileType) -> &'static str {
    "it is not a regular file"
}

/// The regular file at `path` (symbolic links followed), open for reading, with its
/// metadata; anything else is an error ([`describe`]), without blocking.
pub fn open_regular(path: &Path) -> io::Result<(File, Metadata)> {
    let meta = std::fs::metadata(path)?;
    if !meta.is_file() {
        return Err(io::Error::other(describe(&meta)));
    }
    let file = open_nonblocking(path)?;
    let meta = file.metadata()?;
    if !meta.is_file() {
        return Err(io::Error::other(describe(&meta)));
    }
    Ok((file, meta))
}

#[cfg(unix)]
fn open_nonblocking(path: &Path) -> io::Result<File> {
    use std::os::unix::fs::OpenOptionsExt;
    File::options().read(true).custom_flags(libc::O_NONBLOCK).open(path)
}

#[cfg(not(unix))]
fn open_nonblocking(path: &Path) -> io::Result<File> {
    File::open(path)
}

/// The whole content of the regular file at `path`, at most `max` bytes: a longer file is
/// an error (its size is checked before it is read, and the read stops at `max + 1` bytes
/// should it grow meanwhile).
pub fn read_regular(path: &Path, max: u64) -> io::Result<Vec<u8>> {
    let (file, meta) = open_regular(path)?;
    if meta.len() > max {
        return Err(too_large(meta.len(), max));
    }
    let mut bytes = Vec::with_capacity(meta.len() as usize);
    file.take(max + 1).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > max {
        return Err(too_large(bytes.len() as u64, max));
    }
    Ok(bytes)
}

/// [`read_regular`] as UTF-8 text.
pub fn read_regular_to_string(path: &Path, max: u64) -> io::Result<String> {
    String::from_utf8(read_regular(path, max)?).map_err(|_| io::Error::new(io::ErrorKind::InvalidData, "not UTF-8"))
}

fn too_large(len: u64, max: u64) -> io::Error {
    io::Error::other(format!("{len} bytes is over the limit of {max} bytes"))
}

#[cfg(all(test, unix))]
mod tests {
    use super::*;

    #[test]
    fn only_regular_files_up_to_the_bound_are_read() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("f");
        std::fs::write(&file, b"hello").unwrap();
        assert_eq!(read_regular(&file, 5).unwrap(), b"hello");
        assert!(read_regular(&file, 4).unwrap_err().to_string().contains("over the limit of 4 bytes"));
        let fifo = dir.path().join("fifo");
        let c = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
        // SAFETY: a path we own.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o644) }, 0);
        assert!(read_regular(&fifo, 1 << 20).unwrap_err().to_string().contains("FIFO"));
        let zero = dir.path().join("zero");
        std::os::unix::fs::symlink("/dev/zero", &zero).unwrap();
        assert!(read_regular(&zero, 1 << 20).unwrap_err().to_string().contains("device"));
        assert!(read_regular(dir.path(), 1 << 20).unwrap_err().to_string().contains("directory"));
    }
}
