//! The real LiDAR data lives beside the checkout, not in it (it is large and not ours to publish).

use std::path::{Path, PathBuf};

/// `relative` inside the shared data folder, `../shared/data` from the workspace root. Panics
/// naming the expected folder when it is missing, rather than letting a test fail later on an
/// unexplained "file not found".
pub fn shared_data(relative: &str) -> PathBuf {
    let root = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../../shared/data"));
    assert!(
        root.is_dir(),
        "the real test data is expected in {} (../shared/data beside the workspace)",
        root.display()
    );
    root.join(relative)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn joins_below_the_shared_folder() {
        let path = shared_data("kitti00/velodyne");
        assert!(path.ends_with("shared/data/kitti00/velodyne"), "{}", path.display());
    }
}
