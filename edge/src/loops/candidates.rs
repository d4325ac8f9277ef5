//! Loop candidates: the keyframes whose ring keys are nearest to a new one's (Scan Context's first
//! stage), in a kiddo k-d tree that grows as keyframes age out of the recent window.

use std::num::NonZero;

use kiddo::{MutableKdTree, SquaredEuclidean};

use super::scan_context::RINGS;

/// The ring keys of the keyframes that may close a loop, by keyframe index.
#[derive(Default)]
pub struct RingKeyIndex {
    tree: MutableKdTree<f32, RINGS>,
    len: usize,
}

impl RingKeyIndex {
    /// Adds keyframe `index`'s ring key.
    pub fn add(&mut self, key: &[f32; RINGS], index: usize) {
        // Only fails when the index overflows u32: four billion keyframes.
        if let Ok(item) = u32::try_from(index)
            && self.tree.add(key, item).is_ok()
        {
            self.len += 1;
        }
    }

    /// Keyframes in the index.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether no keyframe is indexed yet.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The `n` keyframes whose ring keys are nearest to `key`, nearest first.
    pub fn nearest(&self, key: &[f32; RINGS], n: usize) -> Vec<usize> {
        let Some(n) = NonZero::new(n.min(self.len)) else { return Vec::new() };
        let found = self.tree.query(key).nearest_n::<SquaredEuclidean<f32>>(n).execute();
        found.into_iter().map(|r| r.item as usize).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_the_nearest_keys_first_and_nothing_when_empty() {
        let mut index = RingKeyIndex::default();
        assert!(index.nearest(&[0.0; RINGS], 3).is_empty());
        for i in 0..100 {
            index.add(&[i as f32; RINGS], i);
        }
        assert_eq!(index.len(), 100);
        assert_eq!(index.nearest(&[41.2; RINGS], 3), vec![41, 42, 40]);
        assert_eq!(index.nearest(&[0.0; RINGS], 500).len(), 100);
    }
}
