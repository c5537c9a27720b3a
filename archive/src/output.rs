//! Writing an output file without destroying what its path names.
//!
//! Every file Kiln writes (the archive, `--stats-json`, `--emit-dir` files, cache packs,
//! records and stamps, the runtime's dumps) goes through [`write_with`]. What it takes: a path
//! and a function that fills a file. What it guarantees:
//!
//! - a missing path or a regular file is replaced atomically: a temporary file beside it
//!   (`.<name>.<pid>.<nanos>.<n>.tmp`, locked while it is written) renamed over it, so a
//!   reader sees the old file or the new one, never half of one;
//! - a symbolic link to a regular file stays a link: its target is replaced;
//! - a character device or a FIFO is written through, never renamed over (`-o /dev/null`
//!   means "discard"); a FIFO with no reader is an error, not a hang;
//! - a directory, a socket or a block device is refused with a clear error;
//! - temporary files left beside the target by a process that died (`kill -9`, a power
//!   loss) are removed by the next write of that target ([`remove_stale_temporaries`]).
//!
//! [`same_file`] tells whether two paths name one file, for refusing an output that would
//! overwrite an input.

use std::collections::HashSet;
use std::fs::{self, File};
use std::io;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

/// How [`write_with`] hands the file to the function that fills it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Sink {
    /// A fresh regular file (positioned writes and seeks work).
    Temporary,
    /// A character device or a FIFO written through: write sequentially, never seek.
    Stream,
}

/// Writes `bytes` to `path` (see the module's guarantees); `sync` makes the new contents
/// durable before the rename.
pub fn write(path: &Path, bytes: &[u8], sync: bool) -> io::Result<()> {
    write_with(path, sync, |f, _| io::Write::write_all(f, bytes))
}

/// Writes `path` with `fill` (see the module's guarantees). `fill` is told whether the file
/// is a fresh regular file or a stream it must write in order.
pub fn write_with(path: &Path, sync: bool, fill: impl FnOnce(&mut File, Sink) -> io::Result<()>) -> io::Result<()> {
    match fs::metadata(path) {
        Ok(meta) => {
            let t = meta.file_type();
            if t.is_file() {
                // Through a link, replace the file it points at and keep the link.
                let real = match fs::symlink_metadata(path) {
                    Ok(m) if m.file_type().is_symlink() => fs::canonicalize(path)?,
                    _ => path.to_path_buf(),
                };
                write_atomic(&real, sync, fill)
            } else if sys::is_stream(&t) {
                let mut f = sys::open_stream(path)?;
                fill(&mut f, Sink::Stream)
            } else {
                Err(refusal(describe(&t)))
            }
        }
        Err(e) if e.kind() == io::ErrorKind::NotFound => {
            // Not there, or a dangling link: a new regular file (the link is replaced).
            write_atomic(path, sync, fill)
        }
        Err(e) => Err(e),
    }
}

/// Why `path` cannot be an output, if it names something other than a regular file, a
/// character device or a FIFO (checked before a long build rather than after it).
pub fn check_target(path: &Path) -> io::Result<()> {
    match fs::metadata(path) {
        Ok(meta) => {
            let t = meta.file_type();
            if t.is_file() || sys::is_stream(&t) {
                Ok(())
            } else {
                Err(refusal(describe(&t)))
            }
        }
        Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(e),
    }
}

/// Whether `a` and `b` name the same existing file (same device and inode, through links;
/// where there are no inodes, the same canonical path).
pub fn same_file(a: &Path, b: &Path) -> bool {
    sys::same_file(a, b)
}

fn describe(t: &fs::FileType) -> &'static str {
    if t.is_dir() {
        "it is a directory"
    } else {
        sys::describe_special(t)
    }
}

fn refusal(why: &str) -> io::Error {
    io::Error::other(format!("{why}; give the path of a file"))
}

/// Creates a temporary file beside `path`, fills it, syncs it when asked, renames it over
/// `path`; on any error the temporary file is removed.
fn write_atomic(path: &Path, sync: bool, fill: impl FnOnce(&mut File, Sink) -> io::Result<()>) -> io::Result<()> {
    static COUNTER: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    fs::create_dir_all(dir)?;
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    remove_stale_temporaries_once(dir, &name);
    let nanos =
        std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.subsec_nanos()).unwrap_or(0);
    let n = COUNTER.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let tmp = dir.join(format!(".{name}.{}.{nanos}.{n}.tmp", std::process::id()));
    let result = (|| {
        let mut f = sys::create_temporary(&tmp)?;
        fill(&mut f, Sink::Temporary)?;
        if sync {
            f.sync_all()?;
        }
        fs::rename(&tmp, path)
    })();
    if result.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    result
}

/// The pid in a temporary file name of [`write_with`] (`.<name>.<pid>.<nanos>.<n>.tmp`).
pub fn temporary_owner(file_name: &str) -> Option<u32> {
    temporary_parts(file_name).map(|(_, pid)| pid)
}

/// (`<name>`, `<pid>`) of a temporary file name of [`write_with`].
pub fn temporary_parts(file_name: &str) -> Option<(&str, u32)> {
    let rest = file_name.strip_prefix('.')?.strip_suffix(".tmp")?;
    let mut fields = rest.rsplitn(4, '.');
    let (n, nanos, pid, name) = (fields.next()?, fields.next()?, fields.next()?, fields.next()?);
    let digits = |s: &str| !s.is_empty() && s.bytes().all(|b| b.is_ascii_digit());
    if name.is_empty() || !digits(n) || !digits(nanos) || !digits(pid) {
        return None;
    }
    Some((name, pid.parse().ok()?))
}

/// Whether the temporary file at `path` (named as [`temporary_owner`] reads) was left by a
/// process that no longer runs: its pid is gone and nobody holds its lock.
pub fn is_stale_temporary(path: &Path) -> bool {
    let Some(pid) = path.file_name().and_then(|n| n.to_str()).and_then(temporary_owner) else {
        return false;
    };
    if pid == std::process::id() || !sys::process_gone(pid) {
        return false;
    }
    match fs::symlink_metadata(path) {
        Ok(m) if m.file_type().is_file() => {}
        _ => return false,
    }
    sys::unlocked(path)
}

/// Removes the temporary files of [`write_with`] in `dir` whose writer died, for the files
/// `of` accepts (by name: `out.kpak` for `.out.kpak.<pid>.<nanos>.<n>.tmp`); returns how many.
/// Nothing else in the folder is touched.
pub fn remove_stale_temporaries(dir: &Path, of: &dyn Fn(&str) -> bool) -> usize {
    let Ok(entries) = fs::read_dir(dir) else { return 0 };
    let mut removed = 0;
    for e in entries.flatten() {
        let path = e.path();
        let ours = path.file_name().and_then(|n| n.to_str()).and_then(temporary_parts).is_some_and(|(n, _)| of(n));
        if ours && is_stale_temporary(&path) && fs::remove_file(&path).is_ok() {
            removed += 1;
        }
    }
    removed
}

/// [`remove_stale_temporaries`] of the file `name` the first time this process writes it
/// into `dir`.
fn remove_stale_temporaries_once(dir: &Path, name: &str) {
    static DONE: Mutex<Option<HashSet<(PathBuf, String)>>> = Mutex::new(None);
    let key = (fs::canonicalize(dir).unwrap_or_else(|_| dir.to_path_buf()), name.to_string());
    let first = match DONE.lock() {
        Ok(mut done) => done.get_or_insert_with(HashSet::new).insert(key),
        Err(_) => false,
    };
    if first {
        remove_stale_temporaries(dir, &|n| n == name);
    }
}

/// What differs between systems: devices and FIFOs, inodes, process ids and file locks.
#[cfg(unix)]
mod sys {
    use std::fs::{self, File};
    use std::io;
    use std::os::unix::fs::{FileTypeExt, MetadataExt, OpenOptionsExt};
    use std::os::unix::io::AsRawFd;
    use std::path::Path;

    /// A character device or a FIFO: written through, never renamed over.
    pub fn is_stream(t: &fs::FileType) -> bool {
        t.is_char_device() || t.is_fifo()
    }

    pub fn describe_special(t: &fs::FileType) -> &'static str {
        if t.is_socket() {
            "it is a socket"
        } else if t.is_block_device() {
            "it is a block device (Kiln writes through character devices and FIFOs only)"
        } else {
            "it is not a regular file"
        }
    }

    pub fn same_file(a: &Path, b: &Path) -> bool {
        match (fs::metadata(a), fs::metadata(b)) {
            (Ok(x), Ok(y)) => x.dev() == y.dev() && x.ino() == y.ino(),
            _ => false,
        }
    }

    /// Opens an existing device or FIFO for writing without creating, truncating or blocking.
    pub fn open_stream(path: &Path) -> io::Result<File> {
        let f = fs::OpenOptions::new().write(true).custom_flags(libc::O_NONBLOCK).open(path).map_err(|e| {
            if e.raw_os_error() == Some(libc::ENXIO) {
                io::Error::other("it is a FIFO with no reader")
            } else {
                e
            }
        })?;
        // Writes block as usual from here on (a FIFO's reader sets the pace).
        // SAFETY: fcntl on a descriptor we own, with integer arguments only.
        unsafe {
            let fd = f.as_raw_fd();
            let flags = libc::fcntl(fd, libc::F_GETFL);
            if flags >= 0 {
                libc::fcntl(fd, libc::F_SETFL, flags & !libc::O_NONBLOCK);
            }
        }
        Ok(f)
    }

    /// A new temporary file, locked until it is closed: a cleaner in another pid namespace
    /// sees that its writer is alive.
    pub fn create_temporary(tmp: &Path) -> io::Result<File> {
        let f = fs::OpenOptions::new().write(true).read(true).create_new(true).mode(0o644).open(tmp)?;
        // SAFETY: flock on a descriptor we own.
        unsafe { libc::flock(f.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
        Ok(f)
    }

    /// Whether no process `pid` runs (signal 0 only checks that it exists).
    pub fn process_gone(pid: u32) -> bool {
        if pid > i32::MAX as u32 {
            return false;
        }
        // SAFETY: signal 0 sends nothing.
        let gone = unsafe { libc::kill(pid as i32, 0) } == -1;
        gone && io::Error::last_os_error().raw_os_error() == Some(libc::ESRCH)
    }

    /// Whether nobody holds the lock of the temporary file at `path`.
    pub fn unlocked(path: &Path) -> bool {
        let Ok(f) = fs::OpenOptions::new().read(true).custom_flags(libc::O_NONBLOCK).open(path) else { return false };
        // SAFETY: flock on a descriptor we own; the lock is released when `f` closes.
        unsafe { libc::flock(f.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) == 0 }
    }
}

/// The portable fallback: no FIFOs or devices to write through, no inodes, and a temporary
/// file of another process is never taken for stale (Windows refuses to delete a file that
/// is open anyway).
#[cfg(not(unix))]
mod sys {
    use std::fs::{self, File};
    use std::io;
    use std::path::Path;

    pub fn is_stream(_: &fs::FileType) -> bool {
        false
    }

    pub fn describe_special(_: &fs::FileType) -> &'static str {
        "it is not a regular file"
    }

    pub fn same_file(a: &Path, b: &Path) -> bool {
        match (fs::canonicalize(a), fs::canonicalize(b)) {
            (Ok(x), Ok(y)) => x == y,
            _ => false,
        }
    }

    pub fn open_stream(_: &Path) -> io::Result<File> {
        Err(io::Error::other("it is not a regular file"))
    }

    pub fn create_temporary(tmp: &Path) -> io::Result<File> {
        fs::OpenOptions::new().write(true).read(true).create_new(true).open(tmp)
    }

    pub fn process_gone(_: u32) -> bool {
        false
    }

    pub fn unlocked(_: &Path) -> bool {
        false
    }
}

#[cfg(all(test, unix))]
mod tests {
    use super::*;
    use std::os::unix::fs::FileTypeExt;

    #[test]
    fn temporary_names_are_recognised_exactly() {
        assert_eq!(temporary_owner(".shaders.kpak.123.456.0.tmp"), Some(123));
        assert_eq!(temporary_owner(".a.b.c.7.8.9.tmp"), Some(7));
        for other in [".tmp-abc", "shaders.kpak.1.2.3.tmp", "..1.2.3.tmp", ".x.1.2.tmp", ".x.a.2.3.tmp", ".x.1.2.3"] {
            assert_eq!(temporary_owner(other), None, "{other}");
        }
    }

    #[test]
    fn regular_files_are_replaced_and_links_kept() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("real.bin");
        fs::write(&target, b"old").unwrap();
        let link = dir.path().join("link.bin");
        std::os::unix::fs::symlink(&target, &link).unwrap();
        write(&link, b"new", false).unwrap();
        assert!(fs::symlink_metadata(&link).unwrap().file_type().is_symlink());
        assert_eq!(fs::read(&target).unwrap(), b"new");
        let names: Vec<_> = fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(names.len(), 2, "no temporary file is left: {names:?}");
    }

    #[test]
    fn directories_and_sockets_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let e = write(dir.path(), b"x", false).unwrap_err();
        assert!(e.to_string().contains("is a directory"), "{e}");
        let sock = dir.path().join("s.sock");
        let _listener = std::os::unix::net::UnixListener::bind(&sock).unwrap();
        let e = write(&sock, b"x", false).unwrap_err();
        assert!(e.to_string().contains("is a socket"), "{e}");
        assert!(fs::symlink_metadata(&sock).unwrap().file_type().is_socket());
    }

    #[test]
    fn a_fifo_without_reader_is_an_error_and_stays_a_fifo() {
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("f");
        let c = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
        // SAFETY: `c` is a NUL-terminated path that outlives the call.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o644) }, 0);
        let e = write(&fifo, b"x", false).unwrap_err();
        assert!(e.to_string().contains("no reader"), "{e}");
        assert!(fs::symlink_metadata(&fifo).unwrap().file_type().is_fifo());
    }

    #[test]
    fn stale_temporaries_of_dead_processes_are_removed() {
        let dir = tempfile::tempdir().unwrap();
        // A pid that cannot be running (above pid_max's ceiling of 2^22).
        let dead = dir.path().join(".out.kpak.4194304999.1.0.tmp");
        let alive = dir.path().join(format!(".out.kpak.{}.1.0.tmp", std::process::id()));
        let user = dir.path().join(".notes.tmp");
        for p in [&dead, &alive, &user] {
            fs::write(p, b"x").unwrap();
        }
        // 4194304999 > i32::MAX is never treated as dead: use a real dead pid instead.
        let mut child = std::process::Command::new("true").spawn().unwrap();
        let pid = child.id();
        child.wait().unwrap();
        let dead_real = dir.path().join(format!(".out.kpak.{pid}.1.0.tmp"));
        fs::write(&dead_real, b"x").unwrap();
        let other = dir.path().join(format!(".other.bin.{pid}.1.0.tmp"));
        fs::write(&other, b"x").unwrap();
        assert_eq!(remove_stale_temporaries(dir.path(), &|n| n == "out.kpak"), 1);
        assert!(!dead_real.exists() && other.exists(), "only the temporaries of out.kpak");
        assert!(dead.exists() && alive.exists() && user.exists());
    }
}
