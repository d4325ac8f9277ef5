//! Z-order (Morton) sorting, which puts spatial neighbours next to each other so that deltas
//! between consecutive points of an unordered cloud become small.

/// Bits per axis in a 63-bit Morton code.
const BITS: u32 = 21;

/// The permutation sorting quantised points by the Morton code of their coordinates (ties keep
/// input order); `q` is iterated twice.
///
/// Coordinates are taken relative to the minimum corner and, if the cloud spans more than
/// 2^21 steps, shifted right until it fits: coarser cells only affect the order, not the values.
pub(crate) fn order(q: impl Iterator<Item = [i32; 3]> + Clone) -> Vec<usize> {
    let Some(min) = q.clone().reduce(|m, p| std::array::from_fn(|k| m[k].min(p[k]))) else {
        return Vec::new();
    };
    let offsets = q.map(move |p| std::array::from_fn::<u64, 3, _>(|k| (i64::from(p[k]) - i64::from(min[k])) as u64));
    let span = offsets.clone().flatten().max().unwrap_or(0);
    let shift = (u64::BITS - span.leading_zeros()).saturating_sub(BITS);
    let keys = offsets.map(|o| (0..3).fold(0, |code, k| code | spread(o[k] >> shift) << k));
    let mut keyed: Vec<(u64, usize)> = keys.zip(0..).collect();
    // The index breaks ties, so the order is deterministic. (An LSD radix sort was slower: its
    // scatter passes over 2 MB miss the cache.)
    keyed.sort_unstable();
    keyed.into_iter().map(|(_, i)| i).collect()
}

/// Spreads the low 21 bits of `v` to every third bit.
fn spread(v: u64) -> u64 {
    let mut x = v & 0x1f_ffff;
    x = (x | x << 32) & 0x001f_0000_0000_ffff;
    x = (x | x << 16) & 0x001f_0000_ff00_00ff;
    x = (x | x << 8) & 0x100f_00f0_0f00_f00f;
    x = (x | x << 4) & 0x10c3_0c30_c30c_30c3;
    (x | x << 2) & 0x1249_2492_4924_9249
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spread_puts_bits_three_apart() {
        assert_eq!(spread(0b1), 0b1);
        assert_eq!(spread(0b11), 0b1001);
        assert_eq!(spread(0x1f_ffff), 0x1249_2492_4924_9249);
    }

    #[test]
    fn order_is_z_order_and_a_permutation() {
        let q = [[1, 1, 0], [0, 0, 0], [1, 0, 0], [0, 1, 0], [-5, 0, 0]];
        // Offsets from the corner (-5, 0, 0) and their codes, by hand: (6,1,0) -> 74, (5,0,0) -> 65,
        // (6,0,0) -> 72, (5,1,0) -> 67, (0,0,0) -> 0.
        let o = order(q.iter().copied());
        assert_eq!(o, vec![4, 1, 3, 2, 0]);
        assert!(order(std::iter::empty()).is_empty());
        // Wide spans (full i32 range) still sort without overflow.
        let o = order([[i32::MAX, 0, 0], [i32::MIN, 0, 0]].into_iter());
        assert_eq!(o, vec![1, 0]);
    }
}
