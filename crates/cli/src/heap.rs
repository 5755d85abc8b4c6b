//! The C heap's growth and trimming, tuned once at start-up.
//!
//! The guide's statistics and trees are decoded into many small allocations and dropped
//! again, megabytes at a time: a farm's coordinator decodes every tile's statistics, a
//! worker every tree version. With glibc's defaults the heap is grown a page range at a time
//! and given back to the kernel as soon as its free top passes 128 KiB, so each decode
//! faults its memory in again (zeroed pages, mprotect, page-table updates): half of a
//! statistics decode's time was in the kernel. Growing in 16 MiB steps and keeping up to
//! 256 MiB of free top makes the same decode 2.1x faster
//! (`docs/decisions/glibc-heap-settings.md`). The price is memory kept instead of returned:
//! at 256 spp the coordinator's peak rose from 1073 to 1331 MB and a worker's from 786 to
//! 839 MB (the one-process render's stayed at 660 MB).
//!
//! Setting these turns off glibc's adaptive mmap threshold, so it is set too: allocations
//! under 32 MiB (the most glibc allows) come from the heap, as the adaptive threshold would
//! have arranged after the first few large frees.

/// Extra bytes requested whenever the heap grows (`M_TOP_PAD`).
const TOP_PAD: libc::c_int = 16 << 20;
/// Free bytes at the heap's top before they are returned to the kernel (`M_TRIM_THRESHOLD`).
const TRIM_THRESHOLD: libc::c_int = 256 << 20;
/// Allocations at least this big are mapped on their own (`M_MMAP_THRESHOLD`).
const MMAP_THRESHOLD: libc::c_int = 32 << 20;

/// Applies the settings above (glibc only; elsewhere the allocator is left alone). Call
/// first thing in `main`, before any thread starts.
pub fn tune() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    for (param, value) in [
        (libc::M_TOP_PAD, TOP_PAD),
        (libc::M_TRIM_THRESHOLD, TRIM_THRESHOLD),
        (libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD),
    ] {
        // SAFETY: mallopt only changes allocator parameters; a refused value (it returns 0)
        // leaves the default, which is correct, only slower.
        unsafe { libc::mallopt(param, value) };
    }
}
