//! `cloud`'s integration tests, one test binary (one link instead of one per file): each module
//! is a topic.

mod formats;
mod global;
mod pose_graph;
mod registration;
mod visibility;
