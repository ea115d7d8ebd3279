//! Transparent huge pages for large fresh buffers.
//!
//! A build writes most of its memory once, into buffers it has just
//! allocated, and every 4 KiB page of them is a page fault the kernel
//! answers by zeroing the page: `perf` put those faults at 18.6% of the
//! library scene's build (session 25) and the zeroing at 28.6% of a whole
//! `rebraid bench library --scale 3` run (session 26). Where the kernel's
//! transparent huge pages are in `madvise` mode (Debian's default, and this
//! machine's), memory is backed by 2 MiB pages only where it was advised,
//! which Embree does for every allocation of its BVHs of 2 MiB or more
//! (`os_advise` in its `common/sys/alloc.cpp`); one fault then maps 512
//! pages. Advice only: contents and validity are unchanged, and where the
//! kernel has no huge pages (or another OS) nothing happens.
//!
//! Used where it was measured to pay: the top level's copied leaf blocks
//! (44 MB for the library scene at 3M triangles with the overlap budget;
//! the copy 64-140 ms -> 22-30 ms on one thread, 28-83 -> 12-28 ms on two,
//! session 26). The object builds' buffers are mostly below `MIN_BYTES`
//! (one per object); glibc's own `glibc.malloc.hugetlb=1`, which advises
//! every large allocation, removed only 23% of the library's page faults
//! and no measurable object-build time.

/// Buffers below this many bytes are left alone (a huge page covers only
/// the 2 MiB-aligned middle of a buffer).
const MIN_BYTES: usize = 4 << 20;

/// Huge page size on x86-64 and the usual arm64 configuration.
#[cfg(target_os = "linux")]
const HUGE_PAGE: usize = 2 << 20;

/// Advise huge pages for the 2 MiB-aligned part of `buf`'s capacity, before
/// it is written (pages already touched stay as they are).
pub(crate) fn advise<T>(buf: &mut Vec<T>) {
    let bytes = buf.capacity() * std::mem::size_of::<T>();
    if bytes < MIN_BYTES {
        return;
    }
    #[cfg(target_os = "linux")]
    {
        let start = buf.as_mut_ptr() as usize;
        let first = start.next_multiple_of(HUGE_PAGE);
        let end = (start + bytes) / HUGE_PAGE * HUGE_PAGE;
        if end > first {
            // SAFETY: `[first, end)` lies inside `buf`'s allocation (page
            // aligned, as madvise requires), and MADV_HUGEPAGE is advice
            // that changes neither the mapping's contents nor its validity;
            // its result is ignored (an unsupported kernel says EINVAL).
            unsafe {
                libc::madvise(first as *mut libc::c_void, end - first, libc::MADV_HUGEPAGE);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn advice_leaves_buffers_as_they_are() {
        let mut small: Vec<u64> = Vec::with_capacity(100);
        super::advise(&mut small);
        small.push(7);
        let mut big: Vec<u32> = Vec::with_capacity(3 << 20);
        super::advise(&mut big);
        big.extend(0..3u32 << 20);
        assert_eq!(small, [7]);
        assert!(big.iter().enumerate().all(|(i, &v)| v == i as u32));
    }
}
