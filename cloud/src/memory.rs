//! Process memory: resident size, and handing freed heap pages back to the system.

/// Scans between two calls of [`release_free_memory`] in a long run.
pub const RELEASE_EVERY: usize = 10;

/// Allocations at least this large get pages of their own (glibc's `M_MMAP_THRESHOLD`), bytes.
pub const OWN_PAGES_FROM: i32 = 128 * 1024;

/// Sets the allocator up for a long run: every allocation of [`OWN_PAGES_FROM`] bytes or more
/// (scans, feature sets, the tree of recent map points) is mapped on its own and unmapped when
/// freed.
///
/// glibc's default raises that threshold to the largest block freed so far, after which these
/// per-scan buffers land in the heap between longer-lived ones and what they leave behind is not
/// returned: over 2000 warehouse scans the resident size rose 2.7 MB, against 1.5 MB with the
/// threshold fixed, for about 5 % more time per scan (page faults on fresh mappings).
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
/// keeps what a thread freed in that thread's arena. A trim takes 0.17 ms; every
/// [`RELEASE_EVERY`] scans it keeps the resident size within 1-3 MB of the live heap.
pub fn release_free_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only walks the allocator's own free lists; it has no preconditions.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// [`release_free_memory`] after every [`RELEASE_EVERY`]-th of `done` scans: what a long run calls
/// after each scan.
pub fn release_periodically(done: usize) {
    if done.is_multiple_of(RELEASE_EVERY) {
        release_free_memory();
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

/// Resident memory along a run, MB (`None` where the system does not say).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct MemoryTrace {
    /// After the first scan.
    pub after_first_scan: Option<f64>,
    /// After half the scans, when their number is known in advance.
    pub half_way: Option<f64>,
    /// After the last scan.
    pub end: Option<f64>,
}

/// Samples the resident memory of a long run and trims the heap every [`RELEASE_EVERY`] scans.
#[derive(Clone, Debug)]
pub struct MemoryWatch {
    expected: Option<usize>,
    trace: MemoryTrace,
}

impl MemoryWatch {
    /// A watch over a run of `expected` scans, when known.
    pub fn new(expected: Option<usize>) -> Self {
        MemoryWatch { expected, trace: MemoryTrace::default() }
    }

    /// Called after each scan with the number done.
    pub fn observe(&mut self, done: usize) {
        if done == 1 {
            self.trace.after_first_scan = rss_mb();
        }
        if Some(done) == self.expected.map(|n| n / 2) {
            self.trace.half_way = rss_mb();
        }
        if Some(done) == self.expected {
            self.trace.end = rss_mb();
        }
        // The resident size is read before the trim: between two trims it is at its highest.
        release_periodically(done);
    }

    /// The trace; the end is read now if the run ended before the expected count.
    pub fn finish(self) -> MemoryTrace {
        MemoryTrace { end: self.trace.end.or_else(rss_mb), ..self.trace }
    }
}

/// The heap memory a value holds, bytes: what a long-running service reports per robot.
///
/// Counted from the containers' capacities and element sizes: what is reserved, not a measurement.
/// What an allocator adds per block is left out, and a reserved page that was never written (the
/// spare half of a hash table that just grew) is not resident, so the process's resident size can
/// be below or above the sum.
pub trait HeapSize {
    /// Bytes on the heap owned by this value.
    fn heap_bytes(&self) -> usize;
}

/// Bytes of a vector's buffer.
pub fn vec_bytes<T>(v: &Vec<T>) -> usize {
    v.capacity() * std::mem::size_of::<T>()
}

/// Bytes of a hash map's buffer for `capacity` entries: keys, values and one control byte each.
pub fn map_bytes<K, V>(capacity: usize) -> usize {
    capacity * (std::mem::size_of::<(K, V)>() + 1)
}

impl HeapSize for crate::PointCloud {
    fn heap_bytes(&self) -> usize {
        vec_bytes(&self.points)
            + self.intensity.as_ref().map_or(0, vec_bytes)
            + self.ring.as_ref().map_or(0, vec_bytes)
            + self.time.as_ref().map_or(0, vec_bytes)
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::Point3;

    use super::*;
    use crate::PointCloud;
    use crate::registration::GaussianCloud;
    use crate::voxel::VoxelMap;

    fn grid(n: usize) -> Vec<Point3<f32>> {
        (0..n).map(|i| Point3::new((i % 10) as f32, (i / 10 % 10) as f32, (i / 100) as f32)).collect()
    }

    #[test]
    fn sizes_follow_what_each_container_reserves() {
        let mut cloud = PointCloud::from_points(grid(1000));
        cloud.points.shrink_to_fit();
        assert_eq!(cloud.heap_bytes(), 1000 * 12);
        cloud.intensity = Some(vec![0.0; 1000]);
        assert_eq!(cloud.heap_bytes(), 1000 * 16);
        // Per point: f32 position, f32 plane normal, and the tree's f32 copy and index.
        let gaussians = GaussianCloud::new(&grid(1000), 10);
        assert!(gaussians.heap_bytes() >= 1000 * (12 + 12 + 16), "{}", gaussians.heap_bytes());
        // A voxel map grows with its cells, not with the points that fall in them.
        let mut map = VoxelMap::new(1.0).unwrap();
        map.insert(grid(1000));
        let cells = map.heap_bytes();
        map.insert(grid(1000).into_iter().map(|p| p + nalgebra::Vector3::new(0.1, 0.1, 0.1)));
        assert_eq!(map.heap_bytes(), cells);
    }
}
