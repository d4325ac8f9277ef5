//! `eval`'s integration tests, one test binary (one link instead of one per file): each module
//! is a topic.

mod cli;
mod load;
mod merge;
mod odometry_robustness;
mod report;
mod robustness;
