//! `sim`'s integration tests, one test binary (one link instead of one per file): each module
//! is a topic.

mod motion;
mod packets;
mod sim;
