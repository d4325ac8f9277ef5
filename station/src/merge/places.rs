//! Step 2a — candidate overlaps from place recognition: whether some keyframe of one map looks like
//! some keyframe of another (Scan Context, compared across robots as the edge compares a robot's
//! own keyframes for its loops). The merger uses it to leave unsearched the pairs of placed maps
//! that show none (see `Merger::set_places`), and, when a search of two whole maps finds no link,
//! to search again around the closest candidate ([`Candidate::around`]).
//!
//! Global registration of two whole maps is the costliest step of a merge, and many pairs of a
//! large fleet share nothing. Every robot sends each keyframe's descriptor with it; comparing two
//! maps of a few hundred keyframes each costs tens of milliseconds the first time (ring keys in a
//! k-d tree, then the full descriptor of the nearest ten) and only their new keyframes after that, against hundreds of milliseconds for a search.

use std::sync::Arc;

use cloud::global::Around;
use cloud::memory::vec_bytes;
use cloud::scan_context::{Comparable, RINGS, RingKeyIndex};
use nalgebra::Point3;
use rayon::prelude::*;

/// How maps' places are compared.
#[derive(Clone, Debug, PartialEq)]
pub struct PlaceConfig {
    /// Ring-key neighbours compared by the full descriptor (default 10, Scan Context's).
    pub candidates: usize,
    /// Two keyframes farther apart than this descriptor distance are different places (default
    /// 0.35, the edge's loop threshold: looser than Scan Context's 0.13, because the search and its
    /// checks, not the descriptor, decide).
    pub max_distance: f64,
    /// Columns searched either side of the sector-key alignment (default 3, the edge's).
    pub shift_window: usize,
}

impl Default for PlaceConfig {
    fn default() -> Self {
        Self { candidates: 10, max_distance: 0.35, shift_window: 3 }
    }
}

/// One keyframe as place recognition sees it.
#[derive(Clone)]
pub struct Place {
    /// Its descriptor.
    pub context: Arc<Comparable>,
    /// Where the keyframe's sensor stood, in the map's frame: where a search for an overlap that
    /// the descriptor suggests looks.
    pub position: Point3<f32>,
}

/// A map's places: every keyframe's descriptor and position, and their ring keys indexed.
pub struct Places {
    contexts: Vec<Arc<Comparable>>,
    positions: Vec<Point3<f32>>,
    index: RingKeyIndex,
    /// Grid and range shared by every descriptor; `None` when they differ or there are none.
    shape: Option<Shape>,
}

/// What two descriptors must share to be compared: rings, sectors and range (its bits).
type Shape = (usize, usize, u64);

/// A keyframe of one map that looks like a keyframe of another: where the two maps may overlap.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Candidate {
    /// Keyframe of the first map (its position among the places).
    pub a: usize,
    /// Keyframe of the second map.
    pub b: usize,
    /// Their descriptor distance (eq. 5 of Scan Context).
    pub distance: f64,
}

impl Places {
    /// The places of a map's keyframes.
    pub fn new(places: Vec<Place>) -> Self {
        let (contexts, positions): (Vec<Arc<Comparable>>, Vec<Point3<f32>>) =
            places.into_iter().map(|p| (p.context, p.position)).unzip();
        let mut index = RingKeyIndex::default();
        for (k, c) in contexts.iter().enumerate() {
            index.add(&c.ring_key, k);
        }
        let shape_of = |c: &Arc<Comparable>| (c.rings, c.sectors, c.max_range.to_bits());
        let shape = contexts.first().map(shape_of).filter(|s| contexts.iter().all(|c| shape_of(c) == *s));
        Self { contexts, positions, index, shape }
    }

    /// Bytes of the ring-key index (the descriptors are the caller's, shared).
    pub fn index_bytes(&self) -> usize {
        // kiddo does not report its size: a ring key, an item and a bucket's share per keyframe.
        self.index.len() * (std::mem::size_of::<[f32; RINGS]>() + 2 * std::mem::size_of::<u32>())
            + vec_bytes(&self.contexts)
            + vec_bytes(&self.positions)
    }

    /// Keyframes described.
    pub fn len(&self) -> usize {
        self.contexts.len()
    }

    /// Whether no keyframe is described.
    pub fn is_empty(&self) -> bool {
        self.contexts.is_empty()
    }

    /// Whether descriptors of the two maps mean the same (same grid and range): robots configured
    /// differently cannot be compared, and their pairs are searched without candidates.
    pub fn comparable(&self, other: &Places) -> bool {
        self.shape.is_some() && self.shape == other.shape
    }

    /// The closest candidate between the two maps among the keyframes added since `since`: each
    /// newer keyframe of either map against every keyframe of the other (descriptors do not depend
    /// on poses, so what was compared once need not be compared again).
    pub fn best_match(&self, other: &Places, since: Since, config: &PlaceConfig) -> Option<Candidate> {
        let ours = (since.a..self.len()).into_par_iter().filter_map(|a| {
            other.best_for(&self.contexts[a], config).map(|(b, distance)| Candidate { a, b, distance })
        });
        let theirs = (since.b..other.len()).into_par_iter().filter_map(|b| {
            self.best_for(&other.contexts[b], config).map(|(a, distance)| Candidate { a, b, distance })
        });
        ours.chain(theirs).min_by(|x, y| x.distance.total_cmp(&y.distance).then((x.a, x.b).cmp(&(y.a, y.b))))
    }

    /// What has been compared: every keyframe of both maps now.
    pub fn since(a: &Places, b: &Places) -> Since {
        Since { a: a.len(), b: b.len() }
    }

    /// This map's keyframe most like `query`, if close enough (Scan Context's two stages: the
    /// nearest ring keys, then the full descriptor).
    fn best_for(&self, query: &Comparable, config: &PlaceConfig) -> Option<(usize, f64)> {
        self.index
            .nearest(&query.ring_key, config.candidates)
            .into_iter()
            .map(|k| (k, self.contexts[k].distance(query, config.shift_window).distance))
            .min_by(|x, y| x.1.total_cmp(&y.1).then(x.0.cmp(&y.0)))
            .filter(|&(_, d)| d <= config.max_distance)
    }
}

impl Candidate {
    /// Where the search for the overlap it suggests looks, between map `a` (the target: the
    /// first map of the pair) and map `b` (the source): around the two keyframes, as far as
    /// their descriptors reach. `None` when the places are not the candidate's.
    pub fn around(&self, a: &Places, b: &Places) -> Option<Around> {
        let (_, _, range) = a.shape.filter(|_| a.comparable(b))?;
        Some(Around {
            source: *b.positions.get(self.b)?,
            target: *a.positions.get(self.a)?,
            radius: f64::from_bits(range) as f32,
        })
    }
}

/// How many keyframes of each map of a pair were compared already.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Since {
    /// Keyframes of the first map.
    pub a: usize,
    /// Keyframes of the second map.
    pub b: usize,
}

#[cfg(test)]
mod tests {
    use super::*;
    use cloud::PointCloud;
    use cloud::scan_context::{ScanContext, ScanContextConfig};
    use nalgebra::{Isometry3, Vector3};

    fn scene(seed: u64) -> PointCloud {
        PointCloud::from_points(testkit::boxes_around(seed))
    }

    /// Places of scans taken at the origin.
    fn places(scans: &[PointCloud]) -> Places {
        places_at(scans, &vec![Point3::origin(); scans.len()])
    }

    /// Places of scans taken at `positions`.
    fn places_at(scans: &[PointCloud], positions: &[Point3<f32>]) -> Places {
        let config = ScanContextConfig::default();
        let place =
            |(s, &position)| Place { context: Arc::new(Comparable::new(&ScanContext::new(s, &config))), position };
        Places::new(scans.iter().zip(positions).map(place).collect())
    }

    #[test]
    fn a_candidate_points_the_search_at_its_two_keyframes() {
        let (here, elsewhere) = (scene(5), scene(6));
        let turned = here.transformed(&Isometry3::rotation(Vector3::z() * -1.0).cast());
        let a = places_at(&[elsewhere, here], &[Point3::new(40.0, 0.0, 0.0), Point3::new(3.0, -7.0, 0.5)]);
        let b = places_at(&[turned], &[Point3::new(-12.0, 25.0, 0.0)]);
        let found = a.best_match(&b, Since::default(), &PlaceConfig::default()).expect("the same place");
        let around = found.around(&a, &b).expect("comparable places");
        // The second map is the source: its keyframe's position is where the search looks in it.
        assert_eq!((around.target, around.source), (Point3::new(3.0, -7.0, 0.5), Point3::new(-12.0, 25.0, 0.0)));
        assert_eq!(around.radius, ScanContextConfig::default().max_range as f32);
        // A candidate of other places points nowhere.
        assert_eq!(Candidate { a: 5, b: 0, distance: 0.1 }.around(&a, &b), None);
    }

    #[test]
    fn the_same_place_seen_turned_is_a_candidate_and_another_is_not() {
        let (here, elsewhere, third) = (scene(1), scene(2), scene(3));
        let turned = here.transformed(&Isometry3::rotation(Vector3::z() * 2.0).cast());
        let a = places(&[elsewhere.clone(), here]);
        let b = places(&[third.clone(), turned]);
        let config = PlaceConfig::default();
        let found = a.best_match(&b, Since::default(), &config).expect("the same place");
        assert_eq!((found.a, found.b), (1, 1));
        assert!(a.comparable(&b));
        // Compared before: nothing new to find.
        assert_eq!(a.best_match(&b, Places::since(&a, &b), &config), None);
        // Only the newer keyframes are compared.
        assert_eq!(a.best_match(&b, Since { a: 2, b: 1 }, &config).map(|c| (c.a, c.b)), Some((1, 1)));
        assert_eq!(places(&[elsewhere]).best_match(&places(&[third]), Since::default(), &config), None);
    }

    #[test]
    fn descriptors_of_different_ranges_are_not_comparable() {
        let scan = scene(4);
        let indoor = ScanContextConfig { max_range: 40.0, ..ScanContextConfig::default() };
        let a = places(std::slice::from_ref(&scan));
        let context = Arc::new(Comparable::new(&ScanContext::new(&scan, &indoor)));
        let b = Places::new(vec![Place { context, position: Point3::origin() }]);
        assert!(!a.comparable(&b));
        assert!(!a.comparable(&Places::new(Vec::new())));
    }
}
