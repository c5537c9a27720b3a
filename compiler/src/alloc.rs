//! The `kiln` binary's allocator: mimalloc, but for blocks of [`MAPPED`] bytes or more, each
//! mapped on its own. A build's large blocks are its tables (the blob table, the reuse maps,
//! the row numbers, the manifest's parts), which grow and are replaced stage after stage:
//! through mimalloc a freed table stayed resident for its purge delay beside the one that
//! replaced it (a table that grows is both at once), and a build peaked there. A mapped
//! block goes back to the system when it is freed, and one that grows is moved by the
//! kernel (`mremap`), not copied. Few blocks are that large, so the system calls cost
//! nothing that shows; the pages are faulted in on first touch either way. Linux only
//! (`mremap`); elsewhere the binary runs on mimalloc alone.

use std::alloc::{GlobalAlloc, Layout};

use mimalloc::MiMalloc;

/// The global allocator of the `kiln` binary ([`MAPPED`]).
pub struct Allocator;

/// Blocks of at least this many bytes are mapped on their own.
const MAPPED: usize = 1 << 20;

/// The alignment every mapping has (a page is at least this large).
const MAP_ALIGN: usize = 4096;

/// Whether a block of `layout` is mapped on its own: the same answer for a block's
/// allocation and its release, which get the same layout.
fn mapped(layout: Layout) -> bool {
    layout.size() >= MAPPED && layout.align() <= MAP_ALIGN
}

// SAFETY: blocks are mapped with read and write access and at least MAP_ALIGN alignment
// (checked by `mapped`), unmapped or remapped only with the size they were allocated with;
// the others are mimalloc's, passed on with their layouts unchanged.
unsafe impl GlobalAlloc for Allocator {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        match mapped(layout) {
            true => map(layout.size()),
            // SAFETY: the caller's contract, passed on.
            false => unsafe { MiMalloc.alloc(layout) },
        }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        match mapped(layout) {
            // A new anonymous mapping reads as zeros.
            true => map(layout.size()),
            // SAFETY: the caller's contract, passed on.
            false => unsafe { MiMalloc.alloc_zeroed(layout) },
        }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        match mapped(layout) {
            // SAFETY: `ptr` was mapped by `map` with this size (its layout is the one it was
            // allocated with).
            true => unsafe { unmap(ptr, layout.size()) },
            // SAFETY: the caller's contract, passed on.
            false => unsafe { MiMalloc.dealloc(ptr, layout) },
        }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: the caller guarantees `new_size`, rounded up to the alignment, does not
        // overflow.
        let new = unsafe { Layout::from_size_align_unchecked(new_size, layout.align()) };
        match (mapped(layout), mapped(new)) {
            // SAFETY: the caller's contract, passed on.
            (false, false) => unsafe { MiMalloc.realloc(ptr, layout, new_size) },
            // SAFETY: `ptr` was mapped with `layout.size()` bytes.
            (true, true) => unsafe { remap(ptr, layout.size(), new_size) },
            _ => {
                // SAFETY: `new` has a non-zero size (the caller's contract).
                let moved = unsafe { self.alloc(new) };
                if !moved.is_null() {
                    // SAFETY: both blocks are valid for the smaller size and do not overlap;
                    // the old one is released with its own layout.
                    unsafe {
                        std::ptr::copy_nonoverlapping(ptr, moved, layout.size().min(new_size));
                        self.dealloc(ptr, layout);
                    }
                }
                moved
            }
        }
    }
}

/// A new private anonymous mapping of `size` bytes (null where the system refuses), without
/// transparent huge pages (which would make a table's first touch fault in 2 MiB).
fn map(size: usize) -> *mut u8 {
    // SAFETY: a new mapping at an address the kernel picks; nothing else is touched.
    let p = unsafe {
        libc::mmap(
            std::ptr::null_mut(),
            size,
            libc::PROT_READ | libc::PROT_WRITE,
            libc::MAP_PRIVATE | libc::MAP_ANONYMOUS,
            -1,
            0,
        )
    };
    if p == libc::MAP_FAILED {
        return std::ptr::null_mut();
    }
    // SAFETY: advice on the mapping just made; a refusal changes nothing.
    unsafe { libc::madvise(p, size, libc::MADV_NOHUGEPAGE) };
    p.cast()
}

/// # Safety
/// `ptr` is a mapping of `size` bytes made by [`map`] or [`remap`], not used afterwards.
unsafe fn unmap(ptr: *mut u8, size: usize) {
    // SAFETY: the caller's contract: the whole mapping, which nothing uses any more.
    unsafe { libc::munmap(ptr.cast(), size) };
}

/// The mapping `ptr` of `old` bytes grown or shrunk to `new`, moved if the kernel must (null
/// where it refuses: the old mapping is then unchanged).
///
/// # Safety
/// `ptr` is a mapping of `old` bytes made by [`map`] or [`remap`].
unsafe fn remap(ptr: *mut u8, old: usize, new: usize) -> *mut u8 {
    // SAFETY: the caller's contract; the kernel keeps the contents and moves the pages.
    let p = unsafe { libc::mremap(ptr.cast(), old, new, libc::MREMAP_MAYMOVE) };
    match p == libc::MAP_FAILED {
        true => std::ptr::null_mut(),
        false => p.cast(),
    }
}
