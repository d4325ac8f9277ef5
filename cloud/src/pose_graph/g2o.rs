//! The g2o text format of 3-D pose graphs, parsed from and written to strings (the caller reads
//! and writes the files).
//!
//! ```text
//! VERTEX_SE3:QUAT id x y z qx qy qz qw
//! EDGE_SE3:QUAT a b x y z qx qy qz qw  I11 I12 I13 I14 I15 I16  I22 ... I26  ...  I66
//! FIX id
//! ```
//!
//! An edge is the measured pose of `b` in the frame of `a`, with the 21 upper-triangular entries of
//! its information matrix, translation then rotation: the order of [`Edge::information`], so it
//! is used as it stands. Vertex ids may be any integers; they map to pose indices in the order the
//! vertices appear and are kept for writing. An edge between consecutive poses (index `b = a + 1`)
//! is [`EdgeKind::Odometry`], any other [`EdgeKind::Loop`] (the format does not say).
//!
//! An information matrix with a negative eigenvalue (published benchmarks carry a few, from
//! rounding a covariance's inverse to 6 digits) is accepted as GTSAM's reader accepts it, and
//! repaired to the nearest positive semi-definite matrix in the Frobenius norm (Higham 1988: its
//! negative eigenvalues set to zero); [`G2o::repaired`] lists each such edge, for the caller to warn.

use std::collections::HashMap;
use std::fmt::Write;

use nalgebra::{Isometry3, Matrix6, Quaternion, Translation3, UnitQuaternion};

use super::{Edge, EdgeKind, PoseGraph, PoseGraphError, nearest_psd};

const VERTEX: &str = "VERTEX_SE3:QUAT";
const EDGE: &str = "EDGE_SE3:QUAT";
const FIX: &str = "FIX";

/// Why a g2o text could not be read; every variant names its line (1-based).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum G2oError {
    /// A tag this reader does not know.
    #[error("line {line}: unknown tag {tag:?} (expected {VERTEX}, {EDGE} or {FIX})")]
    UnknownTag {
        /// Line number.
        line: usize,
        /// The first word of the line.
        tag: String,
    },
    /// A line with the wrong count of values, or a value that is not a number.
    #[error("line {line}: {message}")]
    Malformed {
        /// Line number.
        line: usize,
        /// What is wrong.
        message: String,
    },
    /// An edge or FIX line names a vertex not defined before it.
    #[error("line {line}: unknown vertex id {id}")]
    UnknownVertex {
        /// Line number.
        line: usize,
        /// The id.
        id: i64,
    },
    /// A vertex id defined twice.
    #[error("line {line}: vertex id {id} defined twice")]
    DuplicateVertex {
        /// Line number.
        line: usize,
        /// The id.
        id: i64,
    },
    /// An edge the graph refuses (self loop, non-finite values).
    #[error("line {line}: {source}")]
    Edge {
        /// Line number.
        line: usize,
        /// Why.
        source: PoseGraphError,
    },
}

/// A graph read from g2o text, and the edges whose information matrix had to be repaired.
#[derive(Clone, Debug)]
pub struct G2o {
    /// The graph.
    pub graph: PoseGraph,
    /// Edges whose information matrix was not positive semi-definite, in file order.
    pub repaired: Vec<Repaired>,
}

/// An edge whose information matrix had a negative eigenvalue, set to zero.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Repaired {
    /// Line number (1-based).
    pub line: usize,
    /// The edge's pose indices.
    pub from: usize,
    /// The edge's pose indices.
    pub to: usize,
    /// The most negative eigenvalue of the matrix as written.
    pub min_eigenvalue: f64,
}

/// Reads a graph from g2o text. Blank lines and lines starting with `#` are skipped.
pub fn parse(text: &str) -> Result<G2o, G2oError> {
    let mut reader = Reader { graph: PoseGraph::new(), index_of: HashMap::new(), repaired: Vec::new() };
    for (n, line) in text.lines().enumerate() {
        let mut words = line.split_whitespace();
        if let Some(tag) = words.next().filter(|t| !t.starts_with('#')) {
            reader.line(n + 1, tag, &words.collect::<Vec<_>>())?;
        }
    }
    Ok(G2o { graph: reader.graph, repaired: reader.repaired })
}

/// The graph read so far, the pose index of each vertex id, and the edges repaired.
struct Reader {
    graph: PoseGraph,
    index_of: HashMap<i64, usize>,
    repaired: Vec<Repaired>,
}

impl Reader {
    /// One line: its tag and the words after it.
    fn line(&mut self, line: usize, tag: &str, fields: &[&str]) -> Result<(), G2oError> {
        let malformed = |message: String| G2oError::Malformed { line, message };
        match (tag, fields) {
            (VERTEX, [id, pose @ ..]) => {
                let id = vertex_id(id).map_err(malformed)?;
                let pose = pose_from(numbers::<7>(pose).map_err(malformed)?).map_err(malformed)?;
                if self.index_of.insert(id, self.graph.poses().len()).is_some() {
                    return Err(G2oError::DuplicateVertex { line, id });
                }
                self.graph.add_pose_with_id(pose, id);
            }
            (EDGE, [a, b, values @ ..]) => {
                let (from, to) = (self.vertex(line, a)?, self.vertex(line, b)?);
                let values = numbers::<28>(values).map_err(malformed)?;
                let measurement = pose_from(values[..7].try_into().expect("7 of 28 values")).map_err(malformed)?;
                let kind = if to == from + 1 { EdgeKind::Odometry } else { EdgeKind::Loop };
                let written = upper_triangle(&values[7..]);
                let (information, min_eigenvalue) = nearest_psd(&written);
                if information != written {
                    self.repaired.push(Repaired { line, from, to, min_eigenvalue });
                }
                let edge = Edge { from, to, measurement, information, kind };
                self.graph.add_edge(edge).map_err(|source| G2oError::Edge { line, source })?;
            }
            (FIX, ids) => {
                for id in ids {
                    let index = self.vertex(line, id)?;
                    self.graph.fix(index).map_err(|source| G2oError::Edge { line, source })?;
                }
            }
            (VERTEX | EDGE, _) => return Err(malformed(format!("{tag} without its vertex ids"))),
            _ => return Err(G2oError::UnknownTag { line, tag: tag.to_owned() }),
        }
        Ok(())
    }

    /// The pose index of a vertex id defined on an earlier line.
    fn vertex(&self, line: usize, word: &str) -> Result<usize, G2oError> {
        let id = vertex_id(word).map_err(|message| G2oError::Malformed { line, message })?;
        self.index_of.get(&id).copied().ok_or(G2oError::UnknownVertex { line, id })
    }
}

fn vertex_id(word: &str) -> Result<i64, String> {
    word.parse().map_err(|_| format!("vertex id {word:?} is not an integer"))
}

/// Writes `graph` as g2o text: the vertices with their ids, the edges, and a FIX line for the
/// poses marked fixed. Numbers are written in Rust's shortest round-trip form, so parsing the text
/// gives back the same values.
pub fn write(graph: &PoseGraph) -> String {
    let mut out = String::new();
    let ids = graph.ids();
    for (pose, id) in graph.poses().iter().zip(ids) {
        let _ = writeln!(out, "{VERTEX} {id} {}", pose_text(pose));
    }
    for e in graph.edges() {
        let info: Vec<String> =
            (0..6).flat_map(|r| (r..6).map(move |c| (r, c))).map(|(r, c)| e.information[(r, c)].to_string()).collect();
        let _ = writeln!(out, "{EDGE} {} {} {} {}", ids[e.from], ids[e.to], pose_text(&e.measurement), info.join(" "));
    }
    let fixed: Vec<String> = (0..ids.len()).filter(|&i| graph.is_marked_fixed(i)).map(|i| ids[i].to_string()).collect();
    if !fixed.is_empty() {
        let _ = writeln!(out, "{FIX} {}", fixed.join(" "));
    }
    out
}

/// `x y z qx qy qz qw`.
fn pose_text(pose: &Isometry3<f64>) -> String {
    let (t, q) = (pose.translation.vector, pose.rotation.coords);
    format!("{} {} {} {} {} {} {}", t.x, t.y, t.z, q.x, q.y, q.z, q.w)
}

/// Exactly `N` numbers from `words` (after the ids: 7 of a pose, 28 of an edge's pose and
/// information).
fn numbers<const N: usize>(words: &[&str]) -> Result<[f64; N], String> {
    if words.len() != N {
        return Err(format!("expected {N} numbers after the vertex ids, found {}", words.len()));
    }
    let mut values = [0.0; N];
    for (v, w) in values.iter_mut().zip(words) {
        *v = w.parse().map_err(|_| format!("{w:?} is not a number"))?;
    }
    Ok(values)
}

/// The pose of `x y z qx qy qz qw`, the quaternion normalised (files carry 6-7 digits) unless it is
/// unit to rounding already, so that what [`write`] wrote reads back bit for bit; refused when a
/// value is not finite or the quaternion is zero.
fn pose_from(v: [f64; 7]) -> Result<Isometry3<f64>, String> {
    let q = Quaternion::new(v[6], v[3], v[4], v[5]);
    if !v.iter().all(|x| x.is_finite()) || q.norm() < 1e-9 {
        return Err("non-finite value or zero quaternion".into());
    }
    let rotation = if (q.norm_squared() - 1.0).abs() <= 4.0 * f64::EPSILON {
        UnitQuaternion::new_unchecked(q)
    } else {
        UnitQuaternion::from_quaternion(q)
    };
    Ok(Isometry3::from_parts(Translation3::new(v[0], v[1], v[2]), rotation))
}

/// The symmetric matrix of 21 upper-triangular entries, row by row.
fn upper_triangle(values: &[f64]) -> Matrix6<f64> {
    let mut m = Matrix6::zeros();
    let cells = (0..6).flat_map(|r| (r..6).map(move |c| (r, c)));
    for ((r, c), v) in cells.zip(values) {
        m[(r, c)] = *v;
        m[(c, r)] = *v;
    }
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    const INFO: &str = "1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 4 0 0 4 0 4";

    fn text(lines: &[&str]) -> String {
        lines.join("\n")
    }

    #[test]
    fn reads_arbitrary_ids_kinds_and_fixes_and_writes_them_back() {
        let input = text(&[
            "# comment",
            "VERTEX_SE3:QUAT 10 0 0 0 0 0 0 1",
            "VERTEX_SE3:QUAT -3 1 0 0 0 0 0 2",
            "",
            "VERTEX_SE3:QUAT 7 2 0 0 0 0 0.7071067811865476 0.7071067811865476",
            &format!("EDGE_SE3:QUAT 10 -3 1 0 0 0 0 0 1 {INFO}"),
            &format!("EDGE_SE3:QUAT 10 7 2 0 0 0 0 0 1 {INFO}"),
            "FIX -3",
        ]);
        let read = parse(&input).unwrap();
        assert!(read.repaired.is_empty());
        let graph = read.graph;
        assert_eq!(graph.ids(), &[10, -3, 7]);
        assert_eq!(graph.poses()[1].rotation.coords.w, 1.0, "the quaternion (0 0 0 2) is normalised");
        let kinds: Vec<_> = graph.edges().iter().map(|e| (e.from, e.to, e.kind)).collect();
        assert_eq!(kinds, [(0, 1, EdgeKind::Odometry), (0, 2, EdgeKind::Loop)]);
        assert_eq!(graph.edges()[0].information[(3, 3)], 4.0);
        assert!(graph.is_fixed(1) && !graph.is_fixed(0), "FIX moves the gauge");
        let again = parse(&write(&graph)).unwrap().graph;
        assert_eq!(again, graph);
    }

    #[test]
    fn errors_name_the_line() {
        let vertex = "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1";
        let cases = [
            (text(&[vertex, "VERTEX_SE2 1 0 0 0"]), "line 2: unknown tag \"VERTEX_SE2\""),
            (
                text(&[vertex, "VERTEX_SE3:QUAT 1 0 0 0 0 0 1"]),
                "line 2: expected 7 numbers after the vertex ids, found 6",
            ),
            (text(&["", vertex, "VERTEX_SE3:QUAT 1 0 0 x 0 0 0 1"]), "line 3: \"x\" is not a number"),
            (text(&[vertex, "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1"]), "line 2: vertex id 0 defined twice"),
            (text(&[vertex, "VERTEX_SE3:QUAT 1 0 0 0 0 0 0 0"]), "line 2: non-finite value or zero quaternion"),
            (text(&[vertex, &format!("EDGE_SE3:QUAT 0 5 1 0 0 0 0 0 1 {INFO}")]), "line 2: unknown vertex id 5"),
            (text(&[vertex, &format!("EDGE_SE3:QUAT 0 0 1 0 0 0 0 0 1 {INFO}")]), "line 2: edge from pose 0 to itself"),
            (text(&[vertex, "EDGE_SE3:QUAT 0"]), "line 2: EDGE_SE3:QUAT without its vertex ids"),
            (text(&[vertex, "FIX 4"]), "line 2: unknown vertex id 4"),
            (text(&[vertex, "VERTEX_SE3:QUAT 1.5 0 0 0 0 0 0 1"]), "line 2: vertex id \"1.5\" is not an integer"),
        ];
        for (input, expected) in cases {
            let error = parse(&input).unwrap_err().to_string();
            assert!(error.starts_with(expected), "{error:?} should start with {expected:?}");
        }
    }

    #[test]
    fn an_information_matrix_that_is_not_psd_is_repaired_and_reported() {
        // The translation block [[1, 2], [2, 1]] has eigenvalues 3 and -1.
        let bad = "1 2 0 0 0 0 1 0 0 0 0 1 0 0 0 4 0 0 4 0 4";
        let input = text(&[
            "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1",
            "VERTEX_SE3:QUAT 1 0 0 0 0 0 0 1",
            &format!("EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {bad}"),
            &format!("EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {INFO}"),
        ]);
        let read = parse(&input).unwrap();
        assert_eq!(read.repaired.len(), 1, "{:?}", read.repaired);
        let r = read.repaired[0];
        assert_eq!((r.line, r.from, r.to), (3, 0, 1));
        assert!((r.min_eigenvalue + 1.0).abs() < 1e-12, "{r:?}");
        // Nearest PSD: the -1 eigenvalue (direction (1, -1)/sqrt 2) dropped: [[1.5, 1.5], [1.5, 1.5]].
        let m = read.graph.edges()[0].information;
        for (rc, expected) in [((0, 0), 1.5), ((0, 1), 1.5), ((1, 1), 1.5), ((2, 2), 1.0), ((5, 5), 4.0)] {
            assert!((m[rc] - expected).abs() < 1e-12, "{rc:?}: {m}");
        }
        assert_eq!(
            read.graph.edges()[1].information,
            upper_triangle(&[1., 0., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1., 0., 0., 0., 4., 0., 0., 4., 0., 4.])
        );
        // Non-finite values are still refused.
        let nan = text(&[
            "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1",
            "VERTEX_SE3:QUAT 1 0 0 0 0 0 0 1",
            &format!("EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 NaN {}", &INFO[2..]),
        ]);
        assert!(parse(&nan).unwrap_err().to_string().starts_with("line 3: "));
    }
}
