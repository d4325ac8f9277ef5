//! Process memory: resident size, and handing freed heap pages back to the system.

/// Scans between two calls of [`release_free_memory`] in a long run.
pub const RELEASE_EVERY: usize = 10;

/// Allocations at least this large get pages of their own (glibc's `M_MMAP_THRESHOLD`), bytes.
pub const OWN_PAGES_FROM: i32 = 128 * 1024;

/// Sets the allocator up for a long run: every allocation of [`OWN_PAGES_FROM`] bytes or more
/// (the maps' search trees, scans, keyframes) is mapped on its own and unmapped when freed.
///
/// glibc's default raises that threshold to the largest block freed so far, after which the
/// 2 MB search tree rebuilt every ten scans lands in the heap between short-lived buffers, and
/// what it leaves behind cannot be returned: the resident size then depended on the order in
/// which threads freed (28-34 MB at the end of the same 2000-scan run), 27 MB with the threshold fixed.
pub fn configure_allocator() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes a tuning parameter of the allocator; it has no preconditions.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, OWN_PAGES_FROM);
    }
}

/// Returns free heap pages to the system (glibc's `malloc_trim`; nothing elsewhere).
///
/// Each scan allocates and frees a few megabytes of buffers on rayon's worker threads, and glibc
/// keeps what a thread freed in that thread's arena: over 2000 scans the resident size crept up
/// 8 MB while the live heap grew 2.4 MB (the search trees and the pose log). A trim takes
/// 0.17 ms; every [`RELEASE_EVERY`] scans it keeps the resident size within 1-3 MB of the live heap.
pub fn release_free_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only walks the allocator's own free lists; it has no preconditions.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// The process's peak resident memory (Linux `VmHWM`), MB; `None` elsewhere.
pub fn peak_rss_mb() -> Option<f64> {
    proc_status_mb("VmHWM:")
}

/// The process's current resident memory (Linux `VmRSS`), MB; `None` elsewhere.
pub fn rss_mb() -> Option<f64> {
    proc_status_mb("VmRSS:")
}

fn proc_status_mb(field: &str) -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with(field))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}
