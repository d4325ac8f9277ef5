//! Topic and frame names, the same in every program (station, demo, edge) and recording.
//!
//! Frames: `map` is the station's global frame; `robot{N}` is robot N's odometry frame (its
//! sensor frame at its first scan), placed in `map` by the merge; `robot{N}/sensor` is robot N's
//! sensor at its newest scan (edge recordings only).

/// The global map (`foxglove.PointCloud` in `map`, a `robot` field per point).
pub const MAP: &str = "/map";
/// Frame placements (`foxglove.FrameTransforms`): `map` -> `robot{N}` for each merged robot
/// (station), `robot{N}` -> `robot{N}/sensor` per scan (edge).
pub const TF: &str = "/tf";
/// The station's status (JSON).
pub const STATION_STATUS: &str = "/station/status";
/// The global frame.
pub const MAP_FRAME: &str = "map";

/// Robot N's odometry frame.
pub fn robot_frame(robot: u32) -> String {
    format!("robot{robot}")
}

/// Robot N's sensor frame at its newest scan.
pub fn sensor_frame(robot: u32) -> String {
    format!("robot{robot}/sensor")
}

/// Robot N's keyframes as they arrive (`foxglove.PointCloud` in `robot{N}`, posed).
pub fn keyframe(robot: u32) -> String {
    format!("/robot{robot}/keyframe")
}

/// Robot N's keyframe trajectory (`foxglove.PosesInFrame` in `robot{N}`).
pub fn trajectory(robot: u32) -> String {
    format!("/robot{robot}/trajectory")
}

/// Robot N's loop edges (`foxglove.SceneUpdate`: a line per loop in `robot{N}`).
pub fn loops(robot: u32) -> String {
    format!("/robot{robot}/loops")
}

/// Robot N's status (JSON: merge status and confidence at the station; scan counts at the edge).
pub fn status(robot: u32) -> String {
    format!("/robot{robot}/status")
}
