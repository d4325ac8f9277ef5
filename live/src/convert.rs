//! Conversions from the project's types (nalgebra, `cloud::PointCloud`) to Foxglove's messages.

use foxglove::bytes::{BufMut, Bytes, BytesMut};
use foxglove::messages::packed_element_field::NumericType;
use foxglove::messages::{
    Color, FrameTransform, LinePrimitive, PackedElementField, PointCloud, Pose, PosesInFrame, Quaternion, SceneEntity,
    SceneUpdate, Timestamp, Vector3, line_primitive,
};
use nalgebra::{Isometry3, Point3};

/// Name of the per-point label field that [`point_cloud`] adds: which robot the point came from.
pub const ROBOT_FIELD: &str = "robot";

/// A rigid transform as a Foxglove pose.
pub fn pose(iso: &Isometry3<f64>) -> Pose {
    Pose { position: Some(translation(iso)), orientation: Some(rotation(iso)) }
}

fn translation(iso: &Isometry3<f64>) -> Vector3 {
    let t = &iso.translation.vector;
    Vector3 { x: t.x, y: t.y, z: t.z }
}

fn rotation(iso: &Isometry3<f64>) -> Quaternion {
    let q = iso.rotation.quaternion();
    Quaternion { x: q.i, y: q.j, z: q.k, w: q.w }
}

/// `child`'s placement in `parent`: maps child points into the parent frame.
pub fn frame_transform(parent: &str, child: &str, iso: &Isometry3<f64>, timestamp: Timestamp) -> FrameTransform {
    FrameTransform {
        timestamp: Some(timestamp),
        parent_frame_id: parent.to_owned(),
        child_frame_id: child.to_owned(),
        translation: Some(translation(iso)),
        rotation: Some(rotation(iso)),
    }
}

/// Points in `frame`, placed by `origin`: x, y, z as f32 and, with `robots` (one per point), a
/// u32 field [`ROBOT_FIELD`] that Foxglove can colour by.
pub fn point_cloud(
    frame: &str,
    origin: &Isometry3<f64>,
    points: &[Point3<f32>],
    robots: Option<&[u32]>,
    timestamp: Timestamp,
) -> PointCloud {
    let field = |name: &str, offset: u32, ty: NumericType| PackedElementField {
        name: name.to_owned(),
        offset,
        r#type: ty as i32,
    };
    let mut fields = vec![
        field("x", 0, NumericType::Float32),
        field("y", 4, NumericType::Float32),
        field("z", 8, NumericType::Float32),
    ];
    let robots = robots.filter(|r| r.len() == points.len());
    if robots.is_some() {
        fields.push(field(ROBOT_FIELD, 12, NumericType::Uint32));
    }
    let stride = 4 * fields.len();
    PointCloud {
        timestamp: Some(timestamp),
        frame_id: frame.to_owned(),
        pose: Some(pose(origin)),
        point_stride: stride as u32,
        fields,
        data: packed(points, robots, stride),
    }
}

/// The points' bytes, little endian, `stride` bytes each.
fn packed(points: &[Point3<f32>], robots: Option<&[u32]>, stride: usize) -> Bytes {
    let mut data = BytesMut::with_capacity(points.len() * stride);
    for (i, p) in points.iter().enumerate() {
        data.put_f32_le(p.x);
        data.put_f32_le(p.y);
        data.put_f32_le(p.z);
        if let Some(robots) = robots {
            data.put_u32_le(robots[i]);
        }
    }
    data.freeze()
}

/// A trajectory: poses in `frame`.
pub fn poses_in_frame(frame: &str, poses: &[Isometry3<f64>], timestamp: Timestamp) -> PosesInFrame {
    PosesInFrame { timestamp: Some(timestamp), frame_id: frame.to_owned(), poses: poses.iter().map(pose).collect() }
}

/// One scene entity `id` in `frame` drawing a line per segment (replacing the entity's earlier lines).
pub fn lines(frame: &str, id: &str, segments: &[[Point3<f64>; 2]], color: Color, timestamp: Timestamp) -> SceneUpdate {
    let points = segments.iter().flatten().map(|p| foxglove::messages::Point3 { x: p.x, y: p.y, z: p.z }).collect();
    let line = LinePrimitive {
        r#type: line_primitive::Type::LineList as i32,
        pose: Some(pose(&Isometry3::identity())),
        thickness: 3.0,
        scale_invariant: true,
        points,
        color: Some(color),
        ..LinePrimitive::default()
    };
    let entity = SceneEntity {
        timestamp: Some(timestamp),
        frame_id: frame.to_owned(),
        id: id.to_owned(),
        lines: vec![line],
        ..SceneEntity::default()
    };
    SceneUpdate { deletions: vec![], entities: vec![entity] }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3 as V3;

    #[test]
    fn cloud_bytes_hold_the_points_and_labels() {
        let points = [Point3::new(1.0f32, -2.0, 3.5), Point3::new(0.25, 0.5, -0.75)];
        let cloud = point_cloud("map", &Isometry3::identity(), &points, Some(&[1, 2]), Timestamp::new(1, 0));
        assert_eq!(cloud.point_stride, 16);
        assert_eq!(cloud.data.len(), 32);
        let f32_at = |o: usize| f32::from_le_bytes(cloud.data[o..o + 4].try_into().unwrap());
        let u32_at = |o: usize| u32::from_le_bytes(cloud.data[o..o + 4].try_into().unwrap());
        assert_eq!([f32_at(16), f32_at(20), f32_at(24), f32_at(0)], [0.25, 0.5, -0.75, 1.0]);
        assert_eq!([u32_at(12), u32_at(28)], [1, 2]);
        // Labels of the wrong length are left out rather than misread.
        let bare = point_cloud("map", &Isometry3::identity(), &points, Some(&[1]), Timestamp::new(1, 0));
        assert_eq!((bare.point_stride, bare.fields.len()), (12, 3));
    }

    #[test]
    fn pose_keeps_translation_and_rotation() {
        let iso = Isometry3::new(V3::new(1.0, 2.0, 3.0), V3::new(0.1, -0.2, 0.3));
        let p = pose(&iso);
        let (t, q) = (p.position.unwrap(), p.orientation.unwrap());
        let back = Isometry3::from_parts(
            nalgebra::Translation3::new(t.x, t.y, t.z),
            nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q.w, q.x, q.y, q.z)),
        );
        assert!((back.to_homogeneous() - iso.to_homogeneous()).norm() < 1e-12);
    }
}
