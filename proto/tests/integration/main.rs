//! `proto`'s integration tests, one test binary (one link instead of one per file): each module
//! is a topic.

mod codec;
mod messages;
