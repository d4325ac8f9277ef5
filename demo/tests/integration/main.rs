//! `demo`'s integration tests, one test binary (one link instead of one per file): each module
//! is a topic.

mod cli;
mod demo;
mod figures;
